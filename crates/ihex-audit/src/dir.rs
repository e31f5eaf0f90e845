//! The chain on disk: a directory of files `audit-<first seq, 12 digits>-<YYYYMMDD>.jsonl`, read in
//! the order of their first record. The [`Writer`] appends lines with blocking writes (the
//! gateway runs it on a task of its own), starts a new file at a size limit or when the UTC day
//! changes — the chain goes on across files — and after a restart continues the chain from the last
//! complete line, in a new file when the last one ends with a torn line (which stays as it was).

use std::fs::{self, File, OpenOptions};
use std::io::{self, Write};
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use serde::Serialize;

use crate::chain::{Chain, Head, LineError};
use crate::verify::{Loc, RawLine, Report, Verifier};

/// Default size at which the writer starts a new file, bytes.
pub const DEFAULT_FILE_BYTES: u64 = 16 << 20;

/// What can go wrong with the chain's directory.
#[derive(Debug, thiserror::Error)]
pub enum AuditError {
    /// A file operation failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The error.
        #[source]
        source: io::Error,
    },
    /// The size limit of the directory (`max_bytes`) is reached: nothing more is written.
    #[error("the audit directory reached its limit of {0} bytes")]
    Full(u64),
    /// The last complete line of the chain cannot be continued.
    #[error("{loc}: cannot continue the chain after this line: {source}")]
    Resume {
        /// The line.
        loc: Loc,
        /// Why.
        #[source]
        source: LineError,
    },
    /// A record could not be written as JSON.
    #[error("record not serialisable: {0}")]
    Json(#[from] serde_json::Error),
}

impl AuditError {
    /// True for a full disk or a full directory: the writer may succeed later, when there is room.
    pub fn is_full(&self) -> bool {
        match self {
            AuditError::Full(_) => true,
            AuditError::Io { source, .. } => source.raw_os_error() == Some(28), // ENOSPC
            _ => false,
        }
    }
}

fn io_err(path: &Path) -> impl FnOnce(io::Error) -> AuditError + '_ {
    move |source| AuditError::Io {
        path: path.to_owned(),
        source,
    }
}

/// The chain's files in `dir`, in the order of their first record.
pub fn chain_files(dir: &Path) -> Result<Vec<PathBuf>, AuditError> {
    let mut files: Vec<((u64, u32), PathBuf)> = Vec::new();
    for entry in fs::read_dir(dir).map_err(io_err(dir))? {
        let path = entry.map_err(io_err(dir))?.path();
        let Some(name) = path.file_name().and_then(|n| n.to_str()) else {
            continue;
        };
        if let Some(key) = order(name) {
            files.push((key, path));
        }
    }
    files.sort();
    Ok(files.into_iter().map(|(_, p)| p).collect())
}

/// The parts of a chain file's name `audit-<seq>-<YYYYMMDD>[-<n>].jsonl`: the first record's number,
/// the day, and `n` (a file started with the same first number after a torn one).
fn name_parts(name: &str) -> Option<(u64, Day, u32)> {
    let rest = name.strip_prefix("audit-")?.strip_suffix(".jsonl")?;
    let mut parts = rest.split('-');
    let seq = parts.next().filter(|s| s.len() == 12)?.parse().ok()?;
    let day = parts.next().filter(|d| d.len() == 8)?;
    let day = (
        day.get(0..4)?.parse().ok()?,
        day.get(4..6)?.parse().ok()?,
        day.get(6..8)?.parse().ok()?,
    );
    let n = match parts.next() {
        Some(n) => n.parse().ok()?,
        None => 0,
    };
    parts.next().is_none().then_some((seq, day, n))
}

/// The order of chain files: by first record, then by `n`.
fn order(name: &str) -> Option<(u64, u32)> {
    name_parts(name).map(|(seq, _, n)| (seq, n))
}

fn file_name(seq: u64, day: Day, n: u32) -> String {
    let (y, m, d) = day;
    match n {
        0 => format!("audit-{seq:012}-{y:04}{m:02}{d:02}.jsonl"),
        n => format!("audit-{seq:012}-{y:04}{m:02}{d:02}-{n}.jsonl"),
    }
}

/// A UTC day.
type Day = (i32, u8, u8);

fn day_of(t: SystemTime) -> Day {
    let t = time::OffsetDateTime::from(t);
    (t.year(), u8::from(t.month()), t.day())
}

/// The lines of one file, with their places.
pub fn file_lines(path: &Path) -> Result<Vec<RawLine>, AuditError> {
    let bytes = fs::read(path).map_err(io_err(path))?;
    let file = path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    let mut lines = Vec::new();
    let mut rest = &bytes[..];
    let mut n = 0;
    while !rest.is_empty() {
        n += 1;
        let (line, terminated, tail) = match rest.iter().position(|&b| b == b'\n') {
            Some(i) => (&rest[..i], true, &rest[i + 1..]),
            None => (rest, false, &rest[rest.len()..]),
        };
        lines.push(RawLine {
            loc: Loc {
                file: file.clone(),
                line: n,
            },
            bytes: line.to_vec(),
            terminated,
        });
        rest = tail;
    }
    Ok(lines)
}

/// Verifies the chain in `dir` (against the head an anchor published, if given).
pub fn verify_dir(dir: &Path, anchor: Option<Head>) -> Result<Report, AuditError> {
    let mut v = anchor.map_or_else(Verifier::new, Verifier::with_anchor);
    for path in chain_files(dir)? {
        for line in file_lines(&path)? {
            v.push(&line);
        }
        if v.done() {
            break;
        }
    }
    Ok(v.finish())
}

/// How the writer keeps its files.
#[derive(Clone, Debug)]
pub struct WriterOptions {
    /// Start a new file before one would grow beyond this (a single larger line still goes in).
    pub file_bytes: u64,
    /// Write nothing more once the directory's chain files hold this many bytes (`None`: until the
    /// disk is full).
    pub max_bytes: Option<u64>,
}

impl Default for WriterOptions {
    fn default() -> Self {
        WriterOptions {
            file_bytes: DEFAULT_FILE_BYTES,
            max_bytes: None,
        }
    }
}

/// What the writer found when it opened the directory.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Resumed {
    /// The last record already there.
    pub head: Option<Head>,
    /// The torn line the last file ended with (a crash mid-write); the chain goes on in a new file
    /// from the line before it.
    pub torn: Option<Loc>,
}

/// Appends records to the chain in a directory.
#[derive(Debug)]
pub struct Writer {
    dir: PathBuf,
    options: WriterOptions,
    chain: Chain,
    /// The file being written, its path, its length, and its UTC day.
    file: Option<(File, PathBuf, u64, Day)>,
    /// Bytes in the directory's chain files.
    total: u64,
    line: Vec<u8>,
}

impl Writer {
    /// Opens (creating it if needed) the chain in `dir` and continues it.
    pub fn open(dir: &Path, options: WriterOptions) -> Result<(Writer, Resumed), AuditError> {
        fs::create_dir_all(dir).map_err(io_err(dir))?;
        let files = chain_files(dir)?;
        let mut total = 0;
        for f in &files {
            total += fs::metadata(f).map_err(io_err(f))?.len();
        }
        let mut resumed = Resumed::default();
        let mut chain = Chain::new();
        let mut file = None;
        // The last complete line: in the last file, or (when that holds nothing complete) before.
        for (i, path) in files.iter().enumerate().rev() {
            let lines = file_lines(path)?;
            let last_file = i + 1 == files.len();
            let mut complete = lines.iter().rev().filter(|l| l.terminated);
            if last_file {
                if let Some(torn) = lines.last().filter(|l| !l.terminated) {
                    resumed.torn = Some(torn.loc.clone());
                }
            }
            if let Some(last) = complete.next() {
                chain = Chain::after(&last.bytes).map_err(|source| AuditError::Resume {
                    loc: last.loc.clone(),
                    source,
                })?;
                if last_file && resumed.torn.is_none() {
                    let f = OpenOptions::new()
                        .append(true)
                        .open(path)
                        .map_err(io_err(path))?;
                    let len = f.metadata().map_err(io_err(path))?.len();
                    let day = path
                        .file_name()
                        .and_then(|n| n.to_str())
                        .and_then(name_parts)
                        .map_or((0, 0, 0), |p| p.1);
                    file = Some((f, path.clone(), len, day));
                }
                break;
            }
        }
        resumed.head = chain.head();
        let writer = Writer {
            dir: dir.to_owned(),
            options,
            chain,
            file,
            total,
            line: Vec::with_capacity(1024),
        };
        Ok((writer, resumed))
    }

    /// The last record written.
    pub fn head(&self) -> Option<Head> {
        self.chain.head()
    }

    /// The directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The line [`Writer::append`] last wrote (without its `\n`; empty before the first).
    pub fn last_line(&self) -> &[u8] {
        self.line.strip_suffix(b"\n").unwrap_or(&self.line)
    }

    /// Appends the record `body` made at `ts`. On an error nothing of it stays in the file and the
    /// chain does not move: the same record may be tried again.
    pub fn append<B: Serialize>(&mut self, ts: SystemTime, body: &B) -> Result<Head, AuditError> {
        self.line.clear();
        let built = self.chain.build(ts, body, &mut self.line)?;
        let len = self.line.len() as u64;
        if let Some(max) = self.options.max_bytes {
            if self.total + len > max {
                return Err(AuditError::Full(max));
            }
        }
        let day = day_of(ts);
        let rotate = match &self.file {
            None => true,
            Some((_, _, size, d)) => {
                *d != day || (*size > 0 && size + len > self.options.file_bytes)
            }
        };
        if rotate {
            self.start_file(built.head().seq, day)?;
        }
        let Some((f, path, size, _)) = &mut self.file else {
            let source = io::Error::other("no file open");
            return Err(io_err(&self.dir)(source));
        };
        if let Err(e) = f.write_all(&self.line) {
            // Nothing half-written stays behind: the next line must follow a complete one.
            let _ = f.set_len(*size);
            return Err(io_err(path)(e));
        }
        *size += len;
        self.total += len;
        let head = built.head();
        self.chain.advance(built);
        Ok(head)
    }

    /// Makes what was written durable (`fdatasync`).
    pub fn sync(&mut self) -> Result<(), AuditError> {
        if let Some((f, path, _, _)) = &mut self.file {
            f.sync_data().map_err(io_err(path))?;
        }
        Ok(())
    }

    fn start_file(&mut self, seq: u64, day: Day) -> Result<(), AuditError> {
        self.sync()?;
        // Never after someone else's bytes: a name taken (a torn file with this first number) gets
        // the next `n`.
        let mut n = 0;
        let (f, path) = loop {
            let path = self.dir.join(file_name(seq, day, n));
            match OpenOptions::new().append(true).create_new(true).open(&path) {
                Ok(f) => break (f, path),
                Err(e) if e.kind() == io::ErrorKind::AlreadyExists => n += 1,
                Err(e) => return Err(io_err(&path)(e)),
            }
        };
        let len = 0;
        if let Ok(d) = File::open(&self.dir) {
            // The new name survives a power cut with the lines written to it.
            let _ = d.sync_all();
        }
        self.file = Some((f, path, len, day));
        Ok(())
    }
}
