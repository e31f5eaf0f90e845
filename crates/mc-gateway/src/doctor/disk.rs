//! Free space where the gateway writes: its log directory and its state directory. A full SD card
//! loses the log (and with it the record of what the island did).

use std::path::Path;

use super::Verdict;

/// Identifier of the log-directory check.
pub const LOG: &str = "disk.log";
/// Identifier of the state-directory check.
pub const STATE: &str = "disk.state";
/// Less free space than this fails: a busy island logs some MiB a day.
pub const MIN_FREE: u64 = 100 * 1024 * 1024;

/// What `statvfs` says about a directory.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Facts {
    /// The directory.
    pub dir: String,
    /// It exists (else the figures are its nearest existing ancestor's, where it will be made).
    pub exists: bool,
    /// Bytes free for an unprivileged user, and the file system's size; `Err` when unreadable.
    pub space: Result<(u64, u64), String>,
}

/// `statvfs` of `dir`, or of its nearest existing ancestor.
pub fn gather(dir: &Path) -> Facts {
    let exists = dir.is_dir();
    let probe = dir
        .ancestors()
        .find(|p| p.is_dir())
        .unwrap_or(Path::new("/"));
    Facts {
        dir: dir.display().to_string(),
        exists,
        space: crate::sys::statvfs(probe).map_err(|e| format!("{}: {e}", probe.display())),
    }
}

/// Judges one directory (`what` names it in the line: "log", "state").
pub fn check(check: &'static str, what: &str, f: &Facts) -> Verdict {
    let mib = |b: u64| b / (1024 * 1024);
    let not_yet = if f.exists {
        ""
    } else {
        " (not created yet; the gateway or its service creates it)"
    };
    match &f.space {
        Err(e) => Verdict::fail(
            check,
            format!("{what} directory {}: cannot read its file system ({e})", f.dir),
            "check the path and its permissions",
        ),
        Ok((free, _)) if *free < MIN_FREE => Verdict::fail(
            check,
            format!("{what} directory {}: only {} MiB free{not_yet}", f.dir, mib(*free)),
            format!(
                "free space on that file system (at least {} MiB): delete old logs \
                 (`sudo find {} -name '*.jsonl' -mtime +30 -delete`), `sudo journalctl --vacuum-size=100M`, \
                 or a larger SD card",
                mib(MIN_FREE),
                f.dir
            ),
        ),
        Ok((free, total)) => Verdict::pass(
            check,
            format!(
                "{what} directory {}: {} MiB free of {} MiB{not_yet}",
                f.dir,
                mib(*free),
                mib(*total)
            ),
        ),
    }
}

/// Gathers and judges the log directory and, when it is another one, the state directory.
pub fn check_dirs(log: Option<&Path>, state: Option<&Path>) -> Vec<Verdict> {
    let mut out = vec![match log {
        Some(dir) => check(LOG, "log", &gather(dir)),
        None => Verdict::skip(LOG, "no log file configured (--log-dir -)"),
    }];
    out.push(match state {
        Some(dir) if Some(dir) != log => check(STATE, "state", &gather(dir)),
        Some(_) => Verdict::skip(STATE, "the state directory is the log directory (above)"),
        None => Verdict::skip(
            STATE,
            "no state directory: neither XDG_STATE_HOME nor HOME is set",
        ),
    });
    out
}
