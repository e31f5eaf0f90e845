//! Standard output that survives a closed pipe: `ihex-provision fw … | head` stops printing when
//! `head` has had enough, instead of panicking (exit 101) as `println!` does on `EPIPE`.

use std::fmt;
use std::io::{self, IsTerminal, Write};
use std::sync::atomic::{AtomicBool, Ordering};

/// Set once stdout's reader has gone: nothing more is written.
static CLOSED: AtomicBool = AtomicBool::new(false);

/// Writes one line to stdout; after a broken pipe, nothing (other write errors are ignored too:
/// the output is a report, the exit status tells the outcome).
pub fn line(args: fmt::Arguments<'_>) {
    if CLOSED.load(Ordering::Relaxed) {
        return;
    }
    let mut out = io::stdout().lock();
    let written = out
        .write_fmt(args)
        .and_then(|()| out.write_all(b"\n"))
        .and_then(|()| out.flush());
    if let Err(e) = written {
        if e.kind() == io::ErrorKind::BrokenPipe {
            CLOSED.store(true, Ordering::Relaxed);
        }
    }
}

/// True when stdout is a terminal someone watches (progress bars), false when piped or closed.
pub fn is_terminal() -> bool {
    !CLOSED.load(Ordering::Relaxed) && io::stdout().is_terminal()
}
