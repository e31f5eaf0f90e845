//! Logging set-up for the binary: human-readable lines on stderr and JSON lines in a rotated file,
//! both written by background threads (`tracing-appender` non-blocking writers, lossy when full:
//! [`BUFFERED_LINES`] lines each), so logging never blocks the data path. Keep the returned
//! [`LogGuard`] until shutdown: dropping it flushes what is still buffered.
//!
//! Every gateway of a machine started with the same log directory writes to the same file (one file
//! per rotation period, pruned by the appender): each JSON line carries the writing process's
//! `pid`, so `jq 'select(.pid == 1234)'` separates them. A file per process instead would escape the
//! appender's pruning and grow the directory with every run.

use std::path::PathBuf;
use tracing_appender::{
    non_blocking::{NonBlocking, NonBlockingBuilder, WorkerGuard},
    rolling,
};

use tracing_subscriber::{
    filter::{LevelFilter, Targets},
    fmt::{
        self,
        format::{Format, Json, JsonFields, Writer},
        FmtContext, FormatEvent, FormatFields,
    },
    layer::SubscriberExt,
    registry::LookupSpan,
    util::SubscriberInitExt,
    Layer,
};

use crate::config::{LogConfig, Rotation};

/// Lines each log writer buffers for its thread before further lines are dropped. The crate's
/// default, 128,000, allocates and touches a 4 MB channel per writer at start-up: half the
/// gateway's resident memory (docs/benchmarks.md). 1,024 lines (32 KB) are a third of a second of
/// events at 3,000 a second, time enough for the writer's thread even on one busy core.
pub const BUFFERED_LINES: usize = 1024;

/// A non-blocking writer of [`BUFFERED_LINES`] lines around `w`.
fn non_blocking<W: std::io::Write + Send + 'static>(w: W) -> (NonBlocking, WorkerGuard) {
    NonBlockingBuilder::default()
        .buffered_lines_limit(BUFFERED_LINES)
        .finish(w)
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

/// The JSON format with the process ID as every line's first field.
struct WithPid {
    json: Format<Json>,
    pid: u32,
}

impl<S, N> FormatEvent<S, N> for WithPid
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
        let mut line = String::new();
        self.json.format_event(ctx, Writer::new(&mut line), event)?;
        // The JSON formatter writes one object per line; the pid goes in as its first member.
        match line.strip_prefix('{') {
            Some(rest) => write!(writer, "{{\"pid\":{},{rest}", self.pid),
            None => writer.write_str(&line),
        }
    }
}

/// Flushes the log writers when dropped.
#[must_use = "dropping the guard stops the log writers"]
pub struct LogGuard {
    _guards: Vec<WorkerGuard>,
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
    let mut guards = Vec::new();
    let ansi = use_colour(
        std::io::IsTerminal::is_terminal(&std::io::stderr()),
        std::env::var_os("NO_COLOR"),
    );
    let (term, g) = non_blocking(std::io::stderr());
    guards.push(g);
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
            let (file, g) = non_blocking(appender);
            guards.push(g);
            let json = fmt::format()
                .json()
                .with_current_span(true)
                .with_span_list(false);
            Some(
                fmt::layer()
                    .fmt_fields(JsonFields::new())
                    .event_format(WithPid {
                        json,
                        pid: std::process::id(),
                    })
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
    Ok(LogGuard { _guards: guards })
}

#[cfg(test)]
mod tests {
    use super::*;

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
