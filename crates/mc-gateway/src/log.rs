//! Logging set-up for the binary: human-readable lines on stderr and JSON lines in a rotated file,
//! both written by threads of their own (`Batched`: every [`FLUSH_EVERY`] or [`FLUSH_AT`] bytes,
//! lossy beyond [`BUFFERED_BYTES`]), so logging never blocks the data path and never wakes a
//! thread per line.
//! Keep the returned [`LogGuard`] until shutdown: dropping it writes out what is still buffered.
//!
//! Every gateway of a machine started with the same log directory writes to the same file (one file
//! per rotation period, pruned by the appender): each JSON line carries the writing process's
//! `pid`, so `jq 'select(.pid == 1234)'` separates them. A file per process instead would escape the
//! appender's pruning and grow the directory with every run.

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use tracing_appender::rolling;

use tracing_subscriber::{
    filter::{LevelFilter, Targets},
    fmt::{
        self,
        format::{Format, Json, JsonFields, Writer},
        FmtContext, FormatEvent, FormatFields, FormattedFields,
    },
    layer::SubscriberExt,
    registry::LookupSpan,
    util::SubscriberInitExt,
    Layer,
};

use crate::config::{LogConfig, Rotation};
use crate::handover::Handover;

/// How long a logged line waits for its writer's thread at most. The thread writes what came in
/// that time in one write: at info every published event is a line, and a writer woken for each
/// (as `tracing-appender`'s non-blocking writer is) cost two thread wake-ups per command
/// (docs/benchmarks.md).
pub const FLUSH_EVERY: Duration = Duration::from_millis(100);

/// Bytes of waiting lines that wake the writer's thread before its period is over (about 130
/// lines): above about 1,300 lines a second the buffer stays this small.
pub const FLUSH_AT: usize = 32 * 1024;

/// Bytes of lines each writer holds for its thread before further lines are dropped (a thread
/// that cannot keep up: a slow disk, a busy core).
pub const BUFFERED_BYTES: usize = 256 * 1024;

/// A log writer that never blocks the thread that logs: lines are appended to a buffer, which a
/// thread of its own writes out every [`FLUSH_EVERY`], as soon as it holds [`FLUSH_AT`] bytes,
/// and once more when its [`Flusher`] is dropped; when the buffer holds [`BUFFERED_BYTES`] a line
/// is dropped. After a period without lines the thread sleeps until the next line, which it
/// writes a period later with those logged after it: an idle gateway's writers never wake.
#[derive(Clone)]
struct Batched(Arc<Lines>);

/// The lines waiting for a [`Batched`] writer's thread.
#[derive(Default)]
struct Lines(Handover<Vec<u8>>);

/// Writes out what is left and stops a [`Batched`] writer's thread when dropped.
struct Flusher {
    lines: Arc<Lines>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Batched {
    /// A writer around `out` and the guard of its thread, named `name`, which writes `every`
    /// ([`FLUSH_EVERY`]).
    fn new<W: std::io::Write + Send + 'static>(
        mut out: W,
        name: &str,
        every: Duration,
    ) -> std::io::Result<(Batched, Flusher)> {
        let lines = Arc::new(Lines::default());
        let theirs = Arc::clone(&lines);
        let thread = std::thread::Builder::new()
            .name(name.into())
            .spawn(move || {
                let mut taken = Vec::new();
                loop {
                    let open = theirs.0.take(&mut taken);
                    let wrote = write_out(&mut taken, &mut out);
                    if !open {
                        return;
                    }
                    if !wrote && !theirs.0.sleep(Vec::is_empty) {
                        continue;
                    }
                    std::thread::park_timeout(every);
                }
            })?;
        let flusher = Flusher {
            lines: Arc::clone(&lines),
            thread: Some(thread),
        };
        Ok((Batched(lines), flusher))
    }
}

/// Writes the lines `taken` from the hand-over to `out` and keeps at most [`FLUSH_AT`] of room: a
/// flood's larger buffer is given back once written. False when there were none.
fn write_out(taken: &mut Vec<u8>, out: &mut impl std::io::Write) -> bool {
    if taken.is_empty() {
        return false;
    }
    // Nowhere to report a failing log: the lines are lost, as when full.
    let _ = out.write_all(taken).and_then(|()| out.flush());
    taken.clear();
    taken.shrink_to(FLUSH_AT);
    true
}

impl std::io::Write for &Lines {
    fn write(&mut self, line: &[u8]) -> std::io::Result<usize> {
        // Refused only once the writer's thread is gone, which the guard's drop alone ends.
        let _ = self.0.put(|waiting| {
            let before = waiting.len();
            if before + line.len() <= BUFFERED_BYTES {
                waiting.extend_from_slice(line);
            }
            ((), before < FLUSH_AT && waiting.len() >= FLUSH_AT)
        });
        Ok(line.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for Batched {
    type Writer = &'a Lines;

    fn make_writer(&'a self) -> &'a Lines {
        &self.0
    }
}

impl Drop for Flusher {
    fn drop(&mut self) {
        self.lines.0.close();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// Name of the log files: `mc-gateway.<date>.jsonl` in the log directory.
pub const FILE_PREFIX: &str = "mc-gateway";

/// The target of the line that reports why the gateway stopped on an error ([`fatal`]): written to
/// the JSON file whatever the filter says, never to stderr (where `main` prints the error itself).
pub const FATAL_TARGET: &str = "mc_gateway::fatal";

/// Logs `error`, the reason the gateway stops, to the JSON file (see [`FATAL_TARGET`]).
pub fn fatal(error: &str) {
    tracing::error!(target: FATAL_TARGET, error, "the gateway stopped on an error");
}

/// The file the JSON lines go to now: `DIR/mc-gateway.<period>.jsonl`, the period in UTC as the
/// appender names it (`YYYY-MM-DD` daily, `-HH` hourly, `-HH-mm` minutely, none when never
/// rotated); `None` without a file.
pub fn current_file(cfg: &LogConfig, now: time::OffsetDateTime) -> Option<PathBuf> {
    let dir = cfg.dir.as_deref()?;
    Some(dir.join(file_name(cfg.rotation, now)))
}

fn file_name(rotation: Rotation, now: time::OffsetDateTime) -> String {
    let now = now.to_offset(time::UtcOffset::UTC);
    let day = format!(
        "{:04}-{:02}-{:02}",
        now.year(),
        u8::from(now.month()),
        now.day()
    );
    let period = match rotation {
        Rotation::Never => return format!("{FILE_PREFIX}.jsonl"),
        Rotation::Daily => day,
        Rotation::Hourly => format!("{day}-{:02}", now.hour()),
        Rotation::Minutely => format!("{day}-{:02}-{:02}", now.hour(), now.minute()),
    };
    format!("{FILE_PREFIX}.{period}.jsonl")
}

/// The JSON log line: tracing-subscriber's JSON format (the event's fields under `fields`, the
/// current span's under `span`, no span list) with the process ID as its first member. At info
/// every published event is a line, so the line is written here directly: the crate's formatter
/// takes each field through serde and escapes a `%` or `?` value piece by piece while it is
/// formatted, which cost more than the command the event answers (docs/benchmarks.md). Events of
/// the `log` crate, whose metadata the crate normalises, and a span whose fields are not a JSON
/// object go through the crate's formatter ([`JsonLine::crate_format`]); the tests hold the two
/// to the same bytes.
struct JsonLine {
    json: Format<Json>,
    /// `{"pid":N,`.
    head: String,
}

impl JsonLine {
    fn new(pid: u32) -> JsonLine {
        JsonLine {
            json: fmt::format()
                .json()
                .with_current_span(true)
                .with_span_list(false),
            head: format!("{{\"pid\":{pid},"),
        }
    }

    /// The crate's JSON formatter, with the process ID put in as the line's first member.
    fn crate_format<S, N>(
        &self,
        ctx: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &tracing::Event<'_>,
    ) -> std::fmt::Result
    where
        S: tracing::Subscriber + for<'a> LookupSpan<'a>,
        N: for<'a> FormatFields<'a> + 'static,
    {
        let mut line = String::new();
        self.json.format_event(ctx, Writer::new(&mut line), event)?;
        match line.strip_prefix('{') {
            Some(rest) => {
                writer.write_str(&self.head)?;
                writer.write_str(rest)
            }
            None => writer.write_str(&line),
        }
    }
}

thread_local! {
    /// The line being written and the text of one `%` or `?` field, reused from line to line.
    static LINE: std::cell::RefCell<(String, String)> = const {
        std::cell::RefCell::new((String::new(), String::new()))
    };
}

impl<S, N> FormatEvent<S, N> for JsonLine
where
    S: tracing::Subscriber + for<'a> LookupSpan<'a>,
    N: for<'a> FormatFields<'a> + 'static,
{
    fn format_event(
        &self,
        ctx: &FmtContext<'_, S, N>,
        mut writer: Writer<'_>,
        event: &tracing::Event<'_>,
    ) -> std::fmt::Result {
        let meta = event.metadata();
        let now = time::OffsetDateTime::now_utc();
        // Four digits of year, as the crate's timer writes them (a clock set far off: its format).
        if meta.fields().field("log.target").is_some() || !(0..=9999).contains(&now.year()) {
            return self.crate_format(ctx, writer, event);
        }
        let span = event
            .parent()
            .and_then(|id| ctx.span(id))
            .or_else(|| ctx.lookup_current());
        // The span's fields are read after the event's, as the crate's formatter reads them: a
        // field whose formatting records into that span finds its extensions unlocked.
        let write = |line: &mut String, value: &mut String| -> bool {
            line.clear();
            line.push_str(&self.head);
            line.push_str("\"timestamp\":\"");
            timestamp(line, now);
            line.push_str("\",\"level\":\"");
            line.push_str(meta.level().as_str());
            line.push_str("\",\"fields\":{");
            event.record(&mut Fields {
                line: &mut *line,
                value,
                first: true,
            });
            line.push_str("},\"target\":");
            json_str(line, meta.target());
            if let Some(span) = &span {
                let ext = span.extensions();
                let inner = ext
                    .get::<FormattedFields<N>>()
                    .and_then(|f| f.fields.strip_prefix('{'))
                    .and_then(|f| f.strip_suffix('}'));
                let Some(inner) = inner else {
                    return false;
                };
                line.push_str(",\"span\":{");
                line.push_str(inner);
                if !inner.is_empty() {
                    line.push(',');
                }
                line.push_str("\"name\":");
                json_str(line, span.name());
                line.push('}');
            }
            line.push_str("}\n");
            true
        };
        // A field's formatting may log in turn: that line gets buffers of its own.
        let written = LINE.with(|bufs| match bufs.try_borrow_mut() {
            Ok(mut bufs) => {
                let (line, value) = &mut *bufs;
                write(line, value).then(|| writer.write_str(line))
            }
            Err(_) => {
                let (mut line, mut value) = (String::new(), String::new());
                write(&mut line, &mut value).then(|| writer.write_str(&line))
            }
        });
        match written {
            Some(result) => result,
            // Span fields that are not a JSON object: the crate's formatter says so in its way.
            None => self.crate_format(ctx, writer, event),
        }
    }
}

/// `t` (year 0 to 9999) as tracing-subscriber's timer writes it: RFC 3339, UTC, microseconds.
fn timestamp(line: &mut String, t: time::OffsetDateTime) {
    let digits = |line: &mut String, v: u32, width: u32| {
        for p in (0..width).rev() {
            // A digit: below 10.
            line.push(char::from(b'0' + (v / 10u32.pow(p) % 10) as u8));
        }
    };
    digits(line, u32::try_from(t.year()).unwrap_or(0), 4);
    line.push('-');
    digits(line, u32::from(u8::from(t.month())), 2);
    line.push('-');
    digits(line, u32::from(t.day()), 2);
    line.push('T');
    digits(line, u32::from(t.hour()), 2);
    line.push(':');
    digits(line, u32::from(t.minute()), 2);
    line.push(':');
    digits(line, u32::from(t.second()), 2);
    line.push('.');
    digits(line, t.microsecond(), 6);
    line.push('Z');
}

fn json_str(line: &mut String, s: &str) {
    ihex_gateway_core::json_text::write_str(s, |t| line.push_str(t));
}

/// The event's fields as the members of a JSON object, as tracing-serde writes them: strings,
/// numbers and booleans as such, everything else (`%`, `?`, errors, 128-bit numbers) as the string
/// of its `Debug` form.
struct Fields<'a> {
    line: &'a mut String,
    /// The text of a `Debug` value, before it is escaped.
    value: &'a mut String,
    first: bool,
}

impl Fields<'_> {
    fn key(&mut self, field: &tracing::field::Field) {
        if !std::mem::take(&mut self.first) {
            self.line.push(',');
        }
        json_str(self.line, field.name());
        self.line.push(':');
    }
}

impl tracing::field::Visit for Fields<'_> {
    fn record_str(&mut self, field: &tracing::field::Field, value: &str) {
        self.key(field);
        json_str(self.line, value);
    }

    fn record_bool(&mut self, field: &tracing::field::Field, value: bool) {
        self.key(field);
        self.line.push_str(if value { "true" } else { "false" });
    }

    fn record_u64(&mut self, field: &tracing::field::Field, value: u64) {
        self.key(field);
        let _ = write!(self.line, "{value}");
    }

    fn record_i64(&mut self, field: &tracing::field::Field, value: i64) {
        self.key(field);
        let _ = write!(self.line, "{value}");
    }

    fn record_f64(&mut self, field: &tracing::field::Field, value: f64) {
        self.key(field);
        // serde_json's text for it (`null` when not finite).
        let text = serde_json::to_string(&value).unwrap_or_else(|_| "null".into());
        self.line.push_str(&text);
    }

    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        self.key(field);
        self.value.clear();
        let _ = write!(self.value, "{value:?}");
        json_str(self.line, self.value);
    }
}

/// Writes out what the log writers still hold, and stops them, when dropped.
#[must_use = "dropping the guard stops the log writers"]
pub struct LogGuard {
    _flushers: Vec<Flusher>,
}

/// Why logging could not be set up.
#[derive(Debug, thiserror::Error)]
pub enum LogError {
    /// The filter does not parse.
    #[error("invalid log filter {0:?}: {1}")]
    Filter(String, String),
    /// The log directory cannot be created or opened.
    #[error("cannot open a log file in {0}: {1}")]
    File(String, String),
    /// A log writer's thread cannot be started.
    #[error("cannot start a log writer thread: {0}")]
    Thread(String),
    /// A global subscriber is already installed.
    #[error("logging already initialised: {0}")]
    Init(String),
}

/// The filter directives: the configured ones, with the embedded broker silenced unless the
/// configuration mentions it (rumqttd logs every client disconnect, our readiness probe included,
/// as an error).
fn directives(cfg: &LogConfig) -> String {
    if cfg.filter.contains("rumqttd") {
        cfg.filter.clone()
    } else {
        format!("{},rumqttd=off", cfg.filter)
    }
}

/// `target=level` directives and a default level: tracing-subscriber's `Targets`, not `EnvFilter`,
/// whose span and field filters bring the regex engines (424 KB of code in the Pi build, resident all
/// the gateway's life: docs/benchmarks.md, memory).
fn filter(cfg: &LogConfig) -> Result<Targets, LogError> {
    let d = directives(cfg);
    // `Targets` would take `[span]` or `a{field}` for a target name and silently match nothing.
    let target_char = |c: char| c.is_ascii_alphanumeric() || matches!(c, '_' | ':' | '-' | '.');
    if let Some(bad) = d
        .split(',')
        .find(|dir| !dir.split('=').next().unwrap_or("").chars().all(target_char))
    {
        let why = format!(
            "{bad:?} is not `target=level`: span and field filters are not supported, targets are \
             module paths (e.g. `info,mc_gateway::mqtt=debug`)"
        );
        return Err(LogError::Filter(d, why));
    }
    d.parse()
        .map_err(|e: tracing_subscriber::filter::ParseError| LogError::Filter(d, e.to_string()))
}

/// Colour on stderr only for a person at a terminal, and never when `NO_COLOR` is set to anything
/// but the empty string (no-color.org).
pub fn use_colour(stderr_is_terminal: bool, no_color: Option<std::ffi::OsString>) -> bool {
    stderr_is_terminal && no_color.is_none_or(|v| v.is_empty())
}

/// Installs the global subscriber.
pub fn init(cfg: &LogConfig) -> Result<LogGuard, LogError> {
    let mut flushers = Vec::new();
    let ansi = use_colour(
        std::io::IsTerminal::is_terminal(&std::io::stderr()),
        std::env::var_os("NO_COLOR"),
    );
    let (term, f) = Batched::new(std::io::stderr(), "ihex-log-stderr", FLUSH_EVERY)
        .map_err(|e| LogError::Thread(e.to_string()))?;
    flushers.push(f);
    let term_layer = fmt::layer()
        .with_ansi(ansi)
        .with_writer(term)
        .with_filter(filter(cfg)?.with_target(FATAL_TARGET, LevelFilter::OFF));
    let file_layer = match &cfg.dir {
        Some(dir) => {
            let rotation = match cfg.rotation {
                Rotation::Minutely => rolling::Rotation::MINUTELY,
                Rotation::Hourly => rolling::Rotation::HOURLY,
                Rotation::Daily => rolling::Rotation::DAILY,
                Rotation::Never => rolling::Rotation::NEVER,
            };
            // Created here, before the appender: its pruning of old files reads the directory first
            // and would print a confusing "No such file or directory" for a fresh --log-dir.
            std::fs::create_dir_all(dir)
                .map_err(|e| LogError::File(dir.display().to_string(), e.to_string()))?;
            let appender = rolling::Builder::new()
                .rotation(rotation)
                .filename_prefix(FILE_PREFIX)
                .filename_suffix("jsonl")
                .max_log_files(30)
                .build(dir)
                .map_err(|e| LogError::File(dir.display().to_string(), e.to_string()))?;
            let (file, f) = Batched::new(appender, "ihex-log-file", FLUSH_EVERY)
                .map_err(|e| LogError::Thread(e.to_string()))?;
            flushers.push(f);
            Some(
                fmt::layer()
                    .fmt_fields(JsonFields::new())
                    .event_format(JsonLine::new(std::process::id()))
                    .with_writer(file)
                    .with_filter(filter(cfg)?.with_target(FATAL_TARGET, LevelFilter::ERROR)),
            )
        }
        None => None,
    };
    tracing_subscriber::registry()
        .with(term_layer)
        .with(file_layer)
        .try_init()
        .map_err(|e| LogError::Init(e.to_string()))?;
    match current_file(cfg, time::OffsetDateTime::now_utc()) {
        Some(file) => tracing::info!(
            file = %file.display(),
            pid = std::process::id(),
            "JSON log file"
        ),
        None => tracing::info!("no JSON log file (--log-dir -)"),
    }
    Ok(LogGuard {
        _flushers: flushers,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A writer that keeps what it is given and counts the writes.
    #[derive(Clone, Default)]
    struct Kept(Arc<std::sync::Mutex<(Vec<u8>, usize)>>);

    impl std::io::Write for Kept {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            let mut kept = self.0.lock().unwrap();
            kept.0.extend_from_slice(buf);
            kept.1 += 1;
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[test]
    fn lines_are_written_together_in_order_and_all_of_them_at_the_end() {
        use std::io::Write as _;
        use tracing_subscriber::fmt::MakeWriter as _;
        let kept = Kept::default();
        let (writer, flusher) = Batched::new(kept.clone(), "test-log", FLUSH_EVERY).unwrap();
        // The thread's first turn, at once, finds nothing; the next is a period away.
        std::thread::sleep(FLUSH_EVERY / 4);
        for i in 0..100 {
            writeln!(writer.make_writer(), "line {i}").unwrap();
        }
        let want: String = (0..100).map(|i| format!("line {i}\n")).collect();
        let deadline = std::time::Instant::now() + 20 * FLUSH_EVERY;
        while kept.0.lock().unwrap().0.len() < want.len() {
            assert!(std::time::Instant::now() < deadline, "not written in time");
            std::thread::sleep(FLUSH_EVERY / 10);
        }
        let (text, writes) = kept.0.lock().unwrap().clone();
        assert_eq!(String::from_utf8(text).unwrap(), want);
        // One write for lines logged together; two when a slow start of the thread put its first
        // turn among them.
        assert!(writes <= 2, "{writes} writes for 100 lines");
        writeln!(writer.make_writer(), "the last").unwrap();
        drop(flusher);
        let text = String::from_utf8(kept.0.lock().unwrap().0.clone()).unwrap();
        assert!(text.ends_with("line 99\nthe last\n"), "{text}");
    }

    #[test]
    fn an_idle_writer_sleeps_until_the_next_line() {
        use std::io::Write as _;
        use tracing_subscriber::fmt::MakeWriter as _;
        let kept = Kept::default();
        let every = Duration::from_millis(20);
        let (writer, _flusher) = Batched::new(kept.clone(), "test-log", every).unwrap();
        let written = |n: usize| {
            let deadline = std::time::Instant::now() + 100 * every;
            while kept.0.lock().unwrap().0.len() < n {
                assert!(std::time::Instant::now() < deadline, "not written in time");
                std::thread::sleep(every / 4);
            }
        };
        let asleep = || {
            let deadline = std::time::Instant::now() + 100 * every;
            while !writer.0 .0.asleep() {
                assert!(std::time::Instant::now() < deadline, "never went to sleep");
                std::thread::sleep(every / 4);
            }
        };
        asleep();
        writeln!(writer.make_writer(), "first").unwrap();
        written(6);
        asleep();
        let writes = kept.0.lock().unwrap().1;
        std::thread::sleep(5 * every);
        assert_eq!(
            kept.0.lock().unwrap().1,
            writes,
            "nothing written while asleep"
        );
        writeln!(writer.make_writer(), "second").unwrap();
        written(13);
        assert_eq!(
            String::from_utf8(kept.0.lock().unwrap().0.clone()).unwrap(),
            "first\nsecond\n"
        );
    }

    #[test]
    fn a_full_batch_is_written_before_the_period_is_over() {
        use std::io::Write as _;
        use tracing_subscriber::fmt::MakeWriter as _;
        let kept = Kept::default();
        // A period longer than the test may take: only the batch's size can wake the thread.
        let (writer, _flusher) =
            Batched::new(kept.clone(), "test-log", Duration::from_secs(3600)).unwrap();
        let line = [b'y'; 1023];
        for _ in 0..FLUSH_AT / 1024 {
            writer.make_writer().write_all(&line).unwrap();
            writer.make_writer().write_all(b"\n").unwrap();
        }
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        while kept.0.lock().unwrap().0.len() < FLUSH_AT {
            assert!(std::time::Instant::now() < deadline, "a full batch waited");
            std::thread::sleep(Duration::from_millis(1));
        }
    }

    #[test]
    fn a_line_that_does_not_fit_is_dropped_whole() {
        use std::io::Write as _;
        let lines = Lines::default();
        let line = [b'x'; 1000];
        for _ in 0..BUFFERED_BYTES / 1000 {
            assert_eq!((&lines).write(&line).unwrap(), 1000);
        }
        let full = lines.0.with(Vec::len);
        assert_eq!(full, BUFFERED_BYTES / 1000 * 1000);
        // Reported as written (the logger must not retry), kept out of the buffer.
        assert_eq!((&lines).write(&line).unwrap(), 1000);
        assert_eq!(lines.0.with(Vec::len), full);
        assert_eq!((&lines).write(b"short\n").unwrap(), 6);
        assert_eq!(lines.0.with(Vec::len), full + 6);
    }

    #[test]
    fn a_flood_s_buffer_is_given_back_once_written() {
        use std::io::Write as _;
        let lines = Lines::default();
        let line = [b'x'; 1000];
        for _ in 0..BUFFERED_BYTES / 1000 {
            (&lines).write_all(&line).unwrap();
        }
        let (mut taken, mut out) = (Vec::new(), Vec::new());
        lines.0.take(&mut taken);
        write_out(&mut taken, &mut out);
        assert_eq!(out.len(), BUFFERED_BYTES / 1000 * 1000);
        assert!(taken.capacity() <= FLUSH_AT, "{}", taken.capacity());
        // The next take hands the kept room to the logger's side.
        (&lines).write_all(b"one\n").unwrap();
        lines.0.take(&mut taken);
        write_out(&mut taken, &mut out);
        assert!(lines.0.with(Vec::capacity) <= FLUSH_AT);
        assert!(out.ends_with(b"xxone\n"));
    }

    impl Kept {
        /// The lines, each timestamp checked for the timer's shape and then replaced by `T`.
        fn take(&self) -> Vec<String> {
            let text = String::from_utf8(std::mem::take(&mut self.0.lock().unwrap().0)).unwrap();
            text.lines()
                .map(|l| {
                    let (head, rest) = l.split_once("\"timestamp\":\"").expect(l);
                    let (ts, tail) = rest.split_once('"').expect(l);
                    let shape: String = ts
                        .chars()
                        .map(|c| if c.is_ascii_digit() { '0' } else { c })
                        .collect();
                    assert_eq!(shape, "0000-00-00T00:00:00.000000Z", "{l}");
                    format!("{head}\"timestamp\":\"T\"{tail}")
                })
                .collect()
        }
    }

    #[test]
    fn json_lines_are_the_crates_json_lines() {
        let (ours, theirs) = (Kept::default(), Kept::default());
        let layer = |format, lines: &Kept| {
            let lines = lines.clone();
            fmt::layer()
                .fmt_fields(JsonFields::new())
                .event_format(format)
                .with_writer(move || lines.clone())
        };
        let subscriber = tracing_subscriber::registry()
            .with(layer(JsonLine::new(4321), &ours))
            .with(
                fmt::layer()
                    .fmt_fields(JsonFields::new())
                    .event_format(JsonLine::new(4321).json)
                    .with_writer({
                        let lines = theirs.clone();
                        move || lines.clone()
                    }),
            );
        tracing::subscriber::with_default(subscriber, || {
            tracing::info!("plain message");
            tracing::warn!(
                a = 1u64,
                b = -2i64,
                c = true,
                d = 1.5f64,
                e = f64::NAN,
                s = "q\"uote\\ \n\u{1}\u{e9}",
                big = 1u128 << 100,
                "message {} with \"quotes\"",
                3
            );
            let payload = r#"{"event":"command_result","payload":{"request_id":"r\"1"}}"#;
            tracing::info!(event = "command_result", payload = %payload, "event published");
            let io = std::io::Error::other("disk \"full\"");
            tracing::error!(
                thing = ?Some("x"),
                error = &io as &dyn std::error::Error,
                "with debug"
            );
            tracing::debug!(target: "custom::target", r#type = "t", "a target and a raw name");
            tracing::trace!("trace");
            let mqtt = tracing::info_span!("mqtt", client_id = "ihex-gateway", n = 2);
            mqtt.in_scope(|| {
                tracing::info!("inside a span");
                let inner = tracing::info_span!("inner");
                inner.in_scope(|| tracing::info!("inside a span without fields"));
            });
            tracing::info!(parent: &mqtt, "with an explicit parent");
            let later = tracing::info_span!("later", a = tracing::field::Empty, b = "x");
            later.record("a", 5);
            later.in_scope(|| tracing::info!("inside a span recorded later"));
        });
        let (ours, theirs) = (ours.take(), theirs.take());
        assert_eq!(ours.len(), 10);
        // The crate's line is ours without the process ID in front.
        for (o, t) in ours.iter().zip(&theirs) {
            assert_eq!(o.replacen("{\"pid\":4321,", "{", 1), *t);
        }
        assert_eq!(ours.len(), theirs.len());
        assert!(
            ours[0].starts_with("{\"pid\":4321,\"timestamp\""),
            "{}",
            ours[0]
        );
    }

    #[test]
    fn the_current_file_is_named_as_the_appender_names_it() {
        // 2026-11-25 21:07:09 UTC, given in another offset.
        let now = time::OffsetDateTime::from_unix_timestamp(1_795_640_829)
            .unwrap()
            .to_offset(time::UtcOffset::from_hms(2, 0, 0).unwrap());
        let mut cfg = LogConfig {
            dir: Some("/var/log/ihex".into()),
            rotation: Rotation::Daily,
            filter: "info".into(),
        };
        let name = |cfg: &LogConfig| current_file(cfg, now).unwrap().display().to_string();
        assert_eq!(name(&cfg), "/var/log/ihex/mc-gateway.2026-11-25.jsonl");
        cfg.rotation = Rotation::Hourly;
        assert_eq!(name(&cfg), "/var/log/ihex/mc-gateway.2026-11-25-21.jsonl");
        cfg.rotation = Rotation::Minutely;
        assert_eq!(
            name(&cfg),
            "/var/log/ihex/mc-gateway.2026-11-25-21-07.jsonl"
        );
        cfg.rotation = Rotation::Never;
        assert_eq!(name(&cfg), "/var/log/ihex/mc-gateway.jsonl");
        cfg.dir = None;
        assert_eq!(current_file(&cfg, now), None);
    }

    #[test]
    fn colour_only_on_a_terminal_without_no_color() {
        assert!(use_colour(true, None));
        assert!(use_colour(true, Some("".into())));
        assert!(!use_colour(true, Some("1".into())));
        assert!(!use_colour(false, None));
    }

    #[test]
    fn broker_chatter_is_turned_down_unless_asked_for() {
        let mut cfg = LogConfig {
            dir: None,
            rotation: Rotation::Never,
            filter: "info".into(),
        };
        assert_eq!(directives(&cfg), "info,rumqttd=off");
        cfg.filter = "debug,rumqttd=info".into();
        assert_eq!(directives(&cfg), "debug,rumqttd=info");
        cfg.filter = "info,[".into();
        assert!(matches!(filter(&cfg), Err(LogError::Filter(..))));
    }

    #[test]
    fn filters_are_levels_and_module_paths() {
        let cfg = |f: &str| LogConfig {
            dir: None,
            rotation: Rotation::Never,
            filter: f.into(),
        };
        let t = filter(&cfg("warn,mc_gateway::mqtt=debug")).unwrap();
        assert!(t.would_enable("mc_gateway::mqtt::conn", &tracing::Level::DEBUG));
        assert!(!t.would_enable("mc_gateway::run", &tracing::Level::INFO));
        assert!(t.would_enable("mc_gateway::run", &tracing::Level::WARN));
        assert!(!t.would_enable("rumqttd::router", &tracing::Level::ERROR));
        for bad in [
            "info,mc_gateway=loud",
            "info,[span]=debug",
            "info,a{b}=debug",
        ] {
            let Err(LogError::Filter(_, why)) = filter(&cfg(bad)) else {
                panic!("{bad:?} accepted");
            };
            assert!(!why.is_empty(), "{bad:?}");
        }
    }
}
