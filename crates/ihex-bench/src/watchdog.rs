//! A live run's stalled phase, explained: when a phase has run for longer than any phase should,
//! the state of every thread of the processes it measures and of the benchmark itself (from
//! `/proc`: state, CPU time, where it waits in the kernel) goes to stdout, so that a hang inside
//! the microVM can be read from the run's log instead of only timing out.

use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

/// What runs now.
struct Phase {
    name: String,
    since: Instant,
    pids: Vec<u32>,
    /// When its threads were last written out.
    reported: Option<Instant>,
}

/// Watches the phases announced with [`Watchdog::phase`] from a thread of its own.
pub(crate) struct Watchdog {
    now: Arc<Mutex<Phase>>,
}

impl Watchdog {
    /// Starts watching: a phase running longer than `after` is written out, and again every
    /// `after` while it lasts.
    pub(crate) fn start(after: Duration) -> Watchdog {
        let now = Arc::new(Mutex::new(Phase {
            name: "start".into(),
            since: Instant::now(),
            pids: Vec::new(),
            reported: None,
        }));
        let watched = Arc::downgrade(&now);
        thread::spawn(move || loop {
            thread::sleep(Duration::from_secs(5));
            // The run is over once the watchdog is dropped.
            let Some(now) = watched.upgrade() else { return };
            let Ok(mut p) = now.lock() else { return };
            let last = p.reported.unwrap_or(p.since);
            if last.elapsed() >= after {
                p.reported = Some(Instant::now());
                println!(
                    "bench: watchdog: phase {:?} has run for {:.0} s; its processes' threads:\n{}",
                    p.name,
                    p.since.elapsed().as_secs_f64(),
                    threads(&p.pids)
                );
            }
        });
        Watchdog { now }
    }

    /// `name` runs from now, measuring `pids` (the benchmark's own threads are always written).
    pub(crate) fn phase(&self, name: &str, pids: &[u32]) {
        if let Ok(mut p) = self.now.lock() {
            *p = Phase {
                name: name.into(),
                since: Instant::now(),
                pids: pids.to_vec(),
                reported: None,
            };
        }
    }
}

/// One line per thread of `pids` and of this process: pid/tid, name, state, CPU ms, the kernel
/// function it waits in and the top of its kernel stack (readable by root).
fn threads(pids: &[u32]) -> String {
    let mut out = String::new();
    for pid in pids.iter().copied().chain([std::process::id()]) {
        let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
            out.push_str(&format!("  {pid}: gone\n"));
            continue;
        };
        for task in tasks.flatten() {
            let dir = task.path();
            let read = |f: &str| std::fs::read_to_string(dir.join(f)).unwrap_or_default();
            let stat = read("stat");
            let (name, rest) = stat
                .split_once(" (")
                .and_then(|(_, r)| r.rsplit_once(") "))
                .unwrap_or(("?", ""));
            let f: Vec<&str> = rest.split_whitespace().collect();
            let ticks = |i: usize| f.get(i).and_then(|v| v.parse::<u64>().ok()).unwrap_or(0);
            let stack: Vec<String> = read("stack")
                .lines()
                .take(4)
                .filter_map(|l| l.split_whitespace().nth(1).map(str::to_owned))
                .collect();
            out.push_str(&format!(
                "  {pid}/{} {name}: state {}, cpu {:.0} ms, wchan {}, stack {}\n",
                task.file_name().to_string_lossy(),
                f.first().copied().unwrap_or("?"),
                (ticks(11) + ticks(12)) as f64 * 1000.0 / crate::live::USER_HZ,
                read("wchan"),
                stack.join(" < ")
            ));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn this_process_is_written_thread_by_thread() {
        let t = threads(&[]);
        let me = format!("  {}/{} ", std::process::id(), std::process::id());
        assert!(t.contains(&me), "{t}");
        assert!(t.contains("state "), "{t}");
        // A process that is gone says so.
        assert!(threads(&[u32::MAX]).contains(&format!("{}: gone", u32::MAX)));
    }
}
