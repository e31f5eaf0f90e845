//! The audit trail in the gateway (`docs/audit.md`): the core task notes what happens — each
//! command as received with its origin, each answer, lease changes, firmware outcomes, start and
//! stop — as [`Record`]s, and hands them to a writer thread through a bounded queue without ever
//! waiting: a slow or full disk never slows a command or keeps it from its answer. The writer
//! appends them to the hash chain ([`ihex_audit::Writer`]) every [`WRITE_EVERY`] and makes them
//! durable at least once a second after that (`fdatasync`): a power cut loses at most the records
//! of the last 1.1 s.
//!
//! When a record cannot be written (a full disk, `--audit-max-bytes` reached, a failing disk) or the
//! queue is full, the record is lost and counted: the health flag ([`AuditStatus`], on `/healthz`
//! and in the metrics) says why, the core publishes one `audit_error` event, and once the writer
//! records again its first record is a `gap` saying how many were lost.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};

use bytes::Bytes;
use ihex_audit::{Head, Kind, Record, Writer, WriterOptions};
use ihex_gateway_core::event::{self, AuditError, Event};
use ihex_gateway_core::{Interface, Origin, Publication};
use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;
use serde_json::{json, Value};
use tokio::task::JoinSet;
use tracing::{error, info, warn};

use crate::config::AuditConfig;
use crate::handover::Handover;
use crate::lock;

/// Records waiting for the writer; beyond this they are lost (and counted).
pub const QUEUE: usize = 4096;
/// Places for waiting records the writer keeps between two takes: a burst's larger queue is given
/// back once written, so the queue's memory follows the last 100 ms's records, not the largest
/// burst since start (a bounded channel allocates all [`QUEUE`] places for good: 768 KiB).
const KEPT: usize = 256;
/// Longest time a written record waits for `fdatasync`.
pub const SYNC_EVERY: Duration = Duration::from_secs(1);
/// How often the writer's thread takes the records waiting: they are written together, and the
/// core's hand-over never wakes it (a thread woken per record cost about two thread wake-ups per
/// command: docs/benchmarks.md).
pub const WRITE_EVERY: Duration = Duration::from_millis(100);
/// Lines the island view may show.
pub const RECENT: usize = 50;

/// How the trail is doing, shared with the island view and the metrics.
#[derive(Debug, Default)]
pub struct AuditStatus {
    /// Records written since start.
    pub written: AtomicU64,
    /// Records lost since start (not written: disk full, queue full).
    pub lost: AtomicU64,
    /// True while records cannot be written.
    pub failing: AtomicBool,
    /// Why, while failing.
    pub why: Mutex<Option<String>>,
    /// The chain's head.
    pub head: Mutex<Option<Head>>,
    /// The last lines written, oldest first (the island view shows them).
    pub recent: Mutex<VecDeque<Vec<u8>>>,
}

impl AuditStatus {
    /// Why records are not being written, `None` while they are.
    pub fn problem(&self) -> Option<String> {
        if !self.failing.load(Ordering::Relaxed) {
            return None;
        }
        lock(&self.why).clone()
    }

    fn fail(&self, why: String) {
        self.lost.fetch_add(1, Ordering::Relaxed);
        *lock(&self.why) = Some(why);
        self.failing.store(true, Ordering::Relaxed);
    }
}

/// What the core task hands the writer: a record, or the text of a command or of a publication
/// with what the core knows about it. The writer makes the record's line from the text, so that
/// the core task builds no JSON tree and copies no payload (`Bytes` are shared).
#[derive(Debug)]
enum Note {
    /// A record made by the core task (start, stop, a `list` answer, Home Assistant's commands).
    Record(Record),
    /// A command as received.
    Command {
        origin: Origin,
        payload: Bytes,
        retained: bool,
    },
    /// An answer, lease change or firmware outcome, as published.
    Published {
        kind: Kind,
        origin: Option<Origin>,
        request_id: Option<String>,
        /// Formatted by the writer, not on the core task.
        node: Option<ihex_proto::NodeId>,
        text: Bytes,
    },
}

/// A note for the writer: when it was made, and how many records were lost (the queue full)
/// right before it.
type Item = (SystemTime, Note, u64);

/// The notes waiting for the writer, which takes them all at once every [`WRITE_EVERY`].
type Queue = Arc<Handover<Vec<Item>>>;

/// The core task's end of the trail.
#[derive(Debug)]
pub struct Audit {
    queue: Queue,
    /// Records lost to a full queue since the last one handed over.
    unsent: std::cell::Cell<u64>,
    status: Arc<AuditStatus>,
    /// `audit_error` was published for the current failure.
    reported: bool,
    anchor: Option<(Duration, Instant, Option<Head>)>,
}

impl Audit {
    /// Opens the trail `config` names (`None` when it is off) and starts its writer on `tasks`. A
    /// directory that cannot be opened does not stop the gateway: the trail is failing from the
    /// start (health flag, `audit_error`).
    pub fn start(config: &AuditConfig, tasks: &mut JoinSet<()>) -> Option<Audit> {
        let (audit, writer) = Audit::open(config)?;
        tasks.spawn_blocking(move || writer.run());
        Some(audit)
    }

    /// The trail `config` names and its writer, not started (the benchmark runs it inline).
    pub fn open(config: &AuditConfig) -> Option<(Audit, AuditWriter)> {
        let dir = config.dir.clone()?;
        let status = Arc::new(AuditStatus::default());
        let queue = Queue::default();
        let options = WriterOptions {
            max_bytes: config.max_bytes,
            ..WriterOptions::default()
        };
        let writer = AuditWriter::open(dir, options, queue.clone(), status.clone());
        let anchor = config.anchor.map(|every| (every, Instant::now(), None));
        let audit = Audit {
            queue,
            unsent: std::cell::Cell::new(0),
            status,
            reported: false,
            anchor,
        };
        Some((audit, writer))
    }

    /// The status the island view and the metrics read.
    pub fn status(&self) -> Arc<AuditStatus> {
        self.status.clone()
    }

    /// Hands `record` to the writer; never waits.
    pub fn record(&self, record: Record) {
        self.note(Note::Record(record));
    }

    fn note(&self, note: Note) {
        let now = SystemTime::now();
        let unsent = self.unsent.get();
        let queued = self.queue.put(|items| {
            let room = items.len() < QUEUE;
            if room {
                items.push((now, note, unsent));
            }
            (room, false)
        });
        let why = match queued {
            Some(true) => return self.unsent.set(0),
            Some(false) => {
                self.unsent.set(unsent + 1);
                "the audit writer's queue is full (a slow disk)"
            }
            None => "the audit writer stopped",
        };
        self.status.fail(why.into());
    }

    /// A command as received, with its origin.
    pub fn command(&self, origin: &Origin, payload: &Bytes, retained: bool) {
        self.note(Note::Command {
            origin: origin.clone(),
            payload: payload.clone(),
            retained,
        });
    }

    /// A command from Home Assistant (its topic names the element and the entity).
    pub fn ha_command(&self, topic: &str, payload: &[u8]) {
        let mut r = with_origin(Kind::Command, &Origin::new(Interface::Ha, None));
        r.request_id = Some(ihex_gateway_core::ha::command::REQUEST_ID.to_owned());
        let payload = String::from_utf8_lossy(payload);
        r.data = json!({"topic": topic, "payload": payload});
        self.record(r);
    }

    /// A publication leaves the core as `text`: answers, lease changes and firmware outcomes are
    /// recorded.
    pub fn published(&self, publication: &Publication, text: &Bytes) {
        let Publication::Event(e) = publication else {
            return;
        };
        let (kind, origin, request_id, node) = match e {
            Event::CommandResult(r) => {
                let node = match r.node {
                    event::Target::Node(id) => Some(id),
                    event::Target::All => None,
                };
                (Kind::Answer, &r.origin, &r.request_id, node)
            }
            Event::CommandRejected(r) => (Kind::Answer, &r.origin, &r.request_id, None),
            Event::NodeList(l) => {
                // The answer to `list`: what it said, not the whole island again.
                let mut r = Record::new(
                    Kind::Answer,
                    json!({"event": "node_list", "payload":
                        {"request_id": l.request_id, "nodes": l.nodes.len()}}),
                );
                r.request_id.clone_from(&l.request_id);
                return self.record(r);
            }
            Event::FwReport(_) | Event::FwUpload(_) => (Kind::Firmware, &None, &None, None),
            Event::LeaseGranted(_) | Event::LeaseEnded(_) | Event::LeasesReset(_) => {
                (Kind::Lease, &None, &None, None)
            }
            _ => return,
        };
        self.note(Note::Published {
            kind,
            origin: origin.clone(),
            request_id: request_id.clone(),
            node,
            text: text.clone(),
        });
    }

    /// An `audit_error` event when the trail started failing since the last call (one per
    /// failure: the health flag says the rest).
    pub fn poll_error(&mut self) -> Option<Event> {
        let failing = self.status.failing.load(Ordering::Relaxed);
        if !failing {
            self.reported = false;
            return None;
        }
        if std::mem::replace(&mut self.reported, true) {
            return None;
        }
        let reason = self.status.problem().unwrap_or_default();
        let lost = self.status.lost.load(Ordering::Relaxed);
        Some(Event::AuditError(AuditError { reason, lost }))
    }

    /// The chain's head as the retained anchor's payload (`SEQ:SHA256`), when one is due and the
    /// head moved since the last.
    pub fn poll_anchor(&mut self, now: Instant) -> Option<String> {
        let (every, next, last) = self.anchor.as_mut()?;
        if now < *next {
            return None;
        }
        *next = now + *every;
        let head = (*lock(&self.status.head))?;
        if *last == Some(head) {
            return None;
        }
        *last = Some(head);
        Some(head.to_text())
    }
}

impl Drop for Audit {
    fn drop(&mut self) {
        self.queue.close();
    }
}

fn with_origin(kind: Kind, origin: &Origin) -> Record {
    let mut r = Record::new(kind, Value::Null);
    r.interface = Some(origin.interface.as_str().to_owned());
    r.user.clone_from(&origin.user);
    r.claimed.clone_from(&origin.claimed);
    r
}

/// The fields of a command the trail indexes, read without building a tree (each may be
/// anything; only strings count).
#[derive(Deserialize)]
struct Peek<'a> {
    #[serde(borrow)]
    request_id: Option<&'a RawValue>,
    #[serde(borrow)]
    user: Option<&'a RawValue>,
    #[serde(borrow)]
    node: Option<&'a RawValue>,
    #[serde(borrow)]
    nodes: Option<&'a RawValue>,
}

/// A raw JSON value as a string, if it is one.
fn text_of(v: Option<&RawValue>) -> Option<String> {
    serde_json::from_str::<String>(v?.get()).ok()
}

/// The elements a command names: `node` (one ID or `all`) and `nodes` (IDs separated by commas).
fn elements(fields: [Option<String>; 2]) -> Vec<String> {
    fields
        .iter()
        .flatten()
        .flat_map(|v| v.split(','))
        .map(str::trim)
        .filter(|s| !s.is_empty() && *s != "all")
        .map(str::to_ascii_lowercase)
        .collect()
}

/// A record's line made from text: the same fields as [`Record`], `data` written as it came.
#[derive(Serialize)]
struct Line<'a> {
    kind: Kind,
    #[serde(skip_serializing_if = "Option::is_none")]
    interface: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    user: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    claimed: Option<&'a str>,
    #[serde(skip_serializing_if = "Option::is_none")]
    request_id: Option<&'a str>,
    #[serde(skip_serializing_if = "<[String]>::is_empty")]
    elements: &'a [String],
    data: Data<'a>,
}

/// A line's `data`.
#[derive(Serialize)]
#[serde(untagged)]
enum Data<'a> {
    /// `{"command": <as received>}` (a string when it was no JSON), `"retained": true` for a
    /// retained message.
    Command {
        command: Raw<'a>,
        #[serde(skip_serializing_if = "std::ops::Not::not")]
        retained: bool,
    },
    /// The publication as published.
    Published(&'a RawValue),
}

/// A command as received: its JSON, or its text when it is no JSON.
#[derive(Serialize)]
#[serde(untagged)]
enum Raw<'a> {
    Json(&'a RawValue),
    Text(std::borrow::Cow<'a, str>),
}

/// The `start` record: version and the options set.
pub fn start_record(config: &crate::config::Config) -> Record {
    Record::new(
        Kind::Start,
        json!({
            "version": env!("CARGO_PKG_VERSION"),
            "island": config.island,
            "options": crate::config::check::set_values(config),
        }),
    )
}

/// The writer's end: appends what comes, syncs at least every [`SYNC_EVERY`], records a `gap`
/// after a failure.
#[derive(Debug)]
pub struct AuditWriter {
    queue: Queue,
    /// The notes taken from the queue, being written (its places go back to the queue).
    taken: Vec<Item>,
    writer: Option<Writer>,
    status: Arc<AuditStatus>,
    /// Written and not yet synced since then.
    unsynced: Option<Instant>,
    /// Records lost since the last one written (the next `gap` says how many).
    unwritten: u64,
}

impl AuditWriter {
    fn open(
        dir: PathBuf,
        options: WriterOptions,
        queue: Queue,
        status: Arc<AuditStatus>,
    ) -> AuditWriter {
        let writer = match Writer::open(&dir, options) {
            Ok((w, resumed)) => {
                if let Some(torn) = &resumed.torn {
                    warn!(%torn, "audit: the last line was torn (a crash mid-write); the chain goes on in a new file");
                }
                let head = resumed
                    .head
                    .map_or_else(|| "none".to_owned(), |h| h.seq.to_string());
                info!(dir = %dir.display(), %head, "audit trail open");
                *lock(&status.head) = resumed.head;
                Some(w)
            }
            Err(e) => {
                error!(error = %e, "audit trail cannot be opened: nothing is recorded");
                status.fail(format!("cannot open {}: {e}", dir.display()));
                None
            }
        };
        AuditWriter {
            queue,
            taken: Vec::new(),
            writer,
            status,
            unsynced: None,
            unwritten: 0,
        }
    }

    /// The writer thread: every [`WRITE_EVERY`] writes what came, syncs when [`SYNC_EVERY`] has
    /// passed since the first record not yet synced; once the core's end is dropped, writes the
    /// rest, syncs and returns. With nothing to write or sync it sleeps until the next note, and
    /// takes it [`WRITE_EVERY`] later with those that came after it: an idle gateway's writer
    /// never wakes.
    pub fn run(mut self) {
        loop {
            std::thread::sleep(WRITE_EVERY);
            let open = self.drain();
            if !open
                || self
                    .unsynced
                    .is_some_and(|since| since.elapsed() >= SYNC_EVERY)
            {
                self.sync();
            }
            if !open {
                return;
            }
            if self.unsynced.is_none() {
                // Closed meanwhile: the next turn writes the rest and returns.
                let _ = self.queue.sleep(Vec::is_empty);
            }
        }
    }

    /// Writes every record waiting, without waiting for more (the benchmark's inline writer).
    // Never inlined: the benchmark counts the writer's instructions as those inside this function.
    #[inline(never)]
    pub fn write_waiting(&mut self) {
        self.drain();
    }

    /// Writes every record waiting; false once the core's end is gone and nothing is left.
    fn drain(&mut self) -> bool {
        let mut taken = std::mem::take(&mut self.taken);
        let open = self.queue.take(&mut taken);
        for (ts, note, unsent) in taken.drain(..) {
            self.take(ts, &note, unsent);
        }
        taken.shrink_to(KEPT);
        self.taken = taken;
        open
    }

    /// Writes the record of `note`, after a `gap` when records were lost right before it
    /// (`unsent` of them to a full queue, and those this writer could not write).
    fn take(&mut self, ts: SystemTime, note: &Note, unsent: u64) {
        self.unwritten += unsent;
        let Some(w) = self.writer.as_mut() else {
            return;
        };
        let status = &*self.status;
        let lost = self.unwritten;
        let mut written = Ok(());
        if lost > 0 {
            written = append(
                w,
                ts,
                &Record::new(Kind::Gap, json!({"lost": lost})),
                status,
            );
            if written.is_ok() {
                self.unwritten = 0;
            }
        }
        if written.is_ok() {
            written = append_note(w, ts, note, status);
        }
        match written {
            Ok(()) => {
                self.unsynced.get_or_insert_with(Instant::now);
                if status.failing.swap(false, Ordering::Relaxed) {
                    info!(lost, "audit trail records again");
                }
            }
            Err(e) => {
                if !status.failing.load(Ordering::Relaxed) {
                    error!(error = %e, "audit trail cannot record: records are lost until it can");
                }
                self.unwritten += 1;
                status.fail(e.to_string());
            }
        }
    }

    fn sync(&mut self) {
        self.unsynced = None;
        if let Some(w) = self.writer.as_mut() {
            if let Err(e) = w.sync() {
                error!(error = %e, "audit trail: fdatasync failed");
                *lock(&self.status.why) = Some(e.to_string());
                self.status.failing.store(true, Ordering::Relaxed);
            }
        }
    }
}

impl Drop for AuditWriter {
    fn drop(&mut self) {
        self.queue.writer_gone();
    }
}

/// Appends the record of `note`.
fn append_note(
    w: &mut Writer,
    ts: SystemTime,
    note: &Note,
    status: &AuditStatus,
) -> Result<(), ihex_audit::AuditError> {
    match note {
        Note::Record(r) => append(w, ts, r, status),
        Note::Command {
            origin,
            payload,
            retained,
        } => {
            let (command, peek) = match serde_json::from_slice::<&RawValue>(payload) {
                Ok(raw) => (
                    Raw::Json(raw),
                    serde_json::from_str::<Peek<'_>>(raw.get()).ok(),
                ),
                Err(_) => (Raw::Text(String::from_utf8_lossy(payload)), None),
            };
            let (request_id, claimed, elements) = match peek {
                Some(p) => (
                    text_of(p.request_id),
                    text_of(p.user),
                    elements([text_of(p.node), text_of(p.nodes)]),
                ),
                None => (None, None, Vec::new()),
            };
            let line = Line {
                kind: Kind::Command,
                interface: Some(origin.interface.as_str()),
                user: origin.user.as_deref(),
                claimed: claimed.as_deref(),
                request_id: request_id.as_deref(),
                elements: &elements,
                data: Data::Command {
                    command,
                    retained: *retained,
                },
            };
            append(w, ts, &line, status)
        }
        Note::Published {
            kind,
            origin,
            request_id,
            node,
            text,
        } => {
            let raw = serde_json::from_slice::<&RawValue>(text)?;
            let node = node.map(|id| event::HexId(id).to_string());
            let line = Line {
                kind: *kind,
                interface: origin.as_ref().map(|o| o.interface.as_str()),
                user: origin.as_ref().and_then(|o| o.user.as_deref()),
                claimed: origin.as_ref().and_then(|o| o.claimed.as_deref()),
                request_id: request_id.as_deref(),
                elements: node.as_slice(),
                data: Data::Published(raw),
            };
            append(w, ts, &line, status)
        }
    }
}

fn append<B: Serialize>(
    w: &mut Writer,
    ts: SystemTime,
    body: &B,
    status: &AuditStatus,
) -> Result<(), ihex_audit::AuditError> {
    let head = w.append(ts, body)?;
    status.written.fetch_add(1, Ordering::Relaxed);
    *lock(&status.head) = Some(head);
    let mut recent = lock(&status.recent);
    // The oldest line's buffer holds the newest: no allocation once the list is full.
    let mut line = match recent.len() {
        RECENT => recent.pop_front().unwrap_or_default(),
        _ => Vec::new(),
    };
    line.clear();
    line.extend_from_slice(w.last_line());
    recent.push_back(line);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_audit::dir::{chain_files, file_lines, verify_dir};
    use ihex_audit::Entry;

    fn entries(dir: &std::path::Path) -> Vec<Entry> {
        chain_files(dir)
            .unwrap()
            .iter()
            .flat_map(|f| file_lines(f).unwrap())
            .map(|l| serde_json::from_slice(&l.bytes).unwrap())
            .collect()
    }

    /// A trail in `dir`, anchored as `anchor` says.
    fn open_in(dir: &std::path::Path, anchor: Option<Duration>) -> (Audit, AuditWriter) {
        let config = AuditConfig {
            dir: Some(dir.to_owned()),
            anchor,
            max_bytes: None,
        };
        Audit::open(&config).unwrap()
    }

    #[test]
    fn records_lost_to_a_full_queue_are_a_gap_and_an_error_once() {
        let tmp = tempfile::tempdir().unwrap();
        let (mut audit, mut writer) = open_in(tmp.path(), Some(Duration::ZERO));
        let alice = Origin::new(Interface::Web, Some("local".into()));
        // The writer takes nothing meanwhile: the queue fills and the rest is lost.
        for _ in 0..QUEUE + 3 {
            let cmd = Bytes::from_static(br#"{"cmd":"list","request_id":"q"}"#);
            audit.command(&alice, &cmd, false);
        }
        assert_eq!(audit.status().lost.load(Ordering::Relaxed), 3);
        let Some(Event::AuditError(e)) = audit.poll_error() else {
            panic!("no audit_error")
        };
        assert_eq!(e.lost, 3);
        assert!(e.reason.contains("queue is full"), "{}", e.reason);
        assert_eq!(audit.poll_error(), None, "one event per failure");

        writer.write_waiting();
        audit.command(&alice, &Bytes::from_static(b"not json"), false);
        writer.write_waiting();
        let all = entries(tmp.path());
        assert_eq!(all.len(), QUEUE + 2);
        assert_eq!(
            all[QUEUE].record.kind,
            Kind::Gap,
            "right after what was queued"
        );
        assert_eq!(all[QUEUE].record.data, json!({"lost": 3}));
        let last = &all[QUEUE + 1].record;
        assert_eq!(last.data, json!({"command": "not json"}));
        assert_eq!(
            (last.interface.as_deref(), last.user.as_deref()),
            (Some("web"), Some("local"))
        );
        assert_eq!(audit.status().problem(), None, "recording again");
        assert_eq!(audit.poll_error(), None);
        let head = audit.poll_anchor(Instant::now()).unwrap();
        assert!(head.starts_with(&format!("{}:", QUEUE + 1)), "{head}");
        assert_eq!(
            audit.poll_anchor(Instant::now()),
            None,
            "the head did not move"
        );
        drop(audit);
        writer.run();
        assert_eq!(verify_dir(tmp.path(), None).unwrap().broken, None);
    }

    #[test]
    fn a_burst_s_queue_is_given_back_once_written() {
        let tmp = tempfile::tempdir().unwrap();
        let (audit, mut writer) = open_in(tmp.path(), None);
        let cmd = Bytes::from_static(br#"{"cmd":"list","request_id":"b"}"#);
        for _ in 0..QUEUE {
            audit.command(&Origin::default(), &cmd, false);
        }
        assert!(audit.queue.with(Vec::capacity) >= QUEUE);
        // Two takes: the burst's places come back to the writer with the first, and the queue
        // gets the writer's kept ones with the second.
        writer.write_waiting();
        audit.command(&Origin::default(), &cmd, false);
        writer.write_waiting();
        assert!(
            writer.taken.capacity() <= KEPT,
            "{}",
            writer.taken.capacity()
        );
        assert!(audit.queue.with(Vec::capacity) <= KEPT);
        assert_eq!(entries(tmp.path()).len(), QUEUE + 1, "every record written");
        assert_eq!(audit.status().lost.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn an_idle_writer_sleeps_until_the_next_note() {
        let tmp = tempfile::tempdir().unwrap();
        let (audit, writer) = open_in(tmp.path(), None);
        let queue = audit.queue.clone();
        let status = audit.status();
        let thread = std::thread::spawn(move || writer.run());
        let until = |what: &str, done: &dyn Fn() -> bool| {
            let deadline = Instant::now() + Duration::from_secs(20);
            while !done() {
                assert!(Instant::now() < deadline, "{what}: not in time");
                std::thread::sleep(WRITE_EVERY / 4);
            }
        };
        let cmd = Bytes::from_static(br#"{"cmd":"list","request_id":"i"}"#);
        audit.command(&Origin::default(), &cmd, false);
        // Written, synced a second later, then asleep.
        until("asleep", &|| queue.asleep());
        assert_eq!(status.written.load(Ordering::Relaxed), 1);
        audit.command(&Origin::default(), &cmd, false);
        until("the next note written", &|| {
            status.written.load(Ordering::Relaxed) == 2
        });
        drop(audit);
        thread.join().unwrap();
        assert_eq!(verify_dir(tmp.path(), None).unwrap().broken, None);
        assert_eq!(entries(tmp.path()).len(), 2);
    }

    #[test]
    fn a_note_after_the_writer_stopped_is_lost_and_says_why() {
        let tmp = tempfile::tempdir().unwrap();
        let (mut audit, writer) = open_in(tmp.path(), None);
        drop(writer);
        audit.command(&Origin::default(), &Bytes::from_static(b"{}"), false);
        assert_eq!(audit.status().lost.load(Ordering::Relaxed), 1);
        let Some(Event::AuditError(e)) = audit.poll_error() else {
            panic!("no audit_error")
        };
        assert!(e.reason.contains("writer stopped"), "{}", e.reason);
    }

    #[test]
    fn a_command_record_names_its_elements_and_claim() {
        let tmp = tempfile::tempdir().unwrap();
        let (audit, mut writer) = open_in(tmp.path(), None);
        let cmd =
            br#"{"cmd":"fw_update","image":"x","nodes":"111, 2A","user":"bob","request_id":"f"}"#;
        audit.command(&Origin::default(), &Bytes::from_static(cmd), true);
        writer.write_waiting();
        let r = &entries(tmp.path())[0].record;
        assert_eq!(r.elements, ["111", "2a"]);
        assert_eq!(r.claimed.as_deref(), Some("bob"));
        assert_eq!(
            (r.user.as_deref(), r.interface.as_deref()),
            (None, Some("mqtt"))
        );
        assert_eq!(r.request_id.as_deref(), Some("f"));
        assert_eq!(r.data["retained"], true);
    }
}
