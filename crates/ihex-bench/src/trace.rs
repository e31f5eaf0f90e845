//! The kernel's trace (ftrace, through tracefs) of the measured process: for a few idle commands,
//! when it was woken, when it ran, which system calls it made and when it wrote the command's
//! frame; for a trial at a steady rate, how many system calls of each kind it made (its census).
//! No profiler runs in the microVM; this says where a command's time in the kernel goes.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

const ROOT: &str = "/sys/kernel/tracing";
const SYS_ENTER: &str = "raw_syscalls/sys_enter";
const EVENTS: [&str; 5] = [
    SYS_ENTER,
    "raw_syscalls/sys_exit",
    "sched/sched_switch",
    "sched/sched_wakeup",
    // A packet or frame handed to a device in the process's context: which calls transmit.
    "net/net_dev_queue",
];

/// The reads of a socket, by x86_64 number: `read`, `recvfrom`, `recvmsg`, `recvmmsg`.
const READS: [u32; 4] = [0, 45, 47, 299];

/// A trace running for one process.
pub(crate) struct Trace {
    root: PathBuf,
}

impl Trace {
    /// Starts tracing the system calls and scheduling of process `pid` (mounting tracefs when it
    /// is not yet), on the monotonic clock.
    pub(crate) fn start(pid: u32) -> Result<Trace> {
        Trace::start_events(&pid.to_string(), &EVENTS)
    }

    /// Starts tracing the system calls alone of every thread of process `pid` (`set_event_pid`
    /// matches threads, and a forwarder on rumqttc's blocking client makes its calls on two).
    pub(crate) fn start_calls(pid: u32) -> Result<Trace> {
        let tids: Vec<String> = fs::read_dir(format!("/proc/{pid}/task"))
            .with_context(|| format!("listing the threads of process {pid}"))?
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .collect();
        Trace::start_events(&tids.join(" "), &[SYS_ENTER])
    }

    /// Starts tracing `events` of the threads `pids` (space-separated).
    fn start_events(pids: &str, events: &[&str]) -> Result<Trace> {
        let t = Trace::open()?;
        t.write("set_event_pid", pids)?;
        for e in events {
            t.write(&format!("events/{e}/enable"), "1")?;
        }
        t.write("tracing_on", "1")?;
        Ok(t)
    }

    /// Tracefs, mounted when it is not yet, emptied and stopped, on the monotonic clock.
    fn open() -> Result<Trace> {
        let root = PathBuf::from(ROOT);
        if !root.join("trace").exists() {
            let ok = Command::new("mount")
                .args(["-t", "tracefs", "nodev", ROOT])
                .status()
                .is_ok_and(|s| s.success());
            if !ok || !root.join("trace").exists() {
                bail!("no tracefs at {ROOT} (mount -t tracefs nodev {ROOT} failed)");
            }
        }
        let t = Trace { root };
        t.write("tracing_on", "0")?;
        t.write("trace", "")?;
        t.write("trace_clock", "mono")?;
        t.write("buffer_size_kb", "8192")?;
        Ok(t)
    }

    /// Writes `text` into the trace (`trace_marker`), between the traced process's events.
    pub(crate) fn mark(&self, text: &str) -> Result<()> {
        self.write("trace_marker", text)
    }

    /// Stops tracing, switches the events off and returns the trace.
    pub(crate) fn stop(self) -> Result<String> {
        self.write("tracing_on", "0")?;
        let text = fs::read_to_string(self.root.join("trace")).context("reading the trace")?;
        for e in EVENTS {
            self.write(&format!("events/{e}/enable"), "0")?;
        }
        self.write("set_event_pid", "")?;
        self.write("trace", "")?;
        Ok(text)
    }

    fn write(&self, file: &str, text: &str) -> Result<()> {
        let p: &Path = &self.root.join(file);
        fs::write(p, text).with_context(|| format!("writing {text:?} to {}", p.display()))
    }
}

/// One probe of the trace, between the markers `ihex-probe K sent` and `ihex-probe K frame`:
/// times in µs from the first marker.
#[derive(Debug, Default, PartialEq)]
pub(crate) struct Probe {
    /// The process was woken (`sched_wakeup`).
    pub woken_us: Option<f64>,
    /// It began to run (`sched_switch` to it).
    pub running_us: Option<f64>,
    /// It entered its last read of a socket before the frame (`recvfrom`, `read`, `recvmsg`,
    /// `recvmmsg`).
    pub read_entered_us: Option<f64>,
    /// That read returned: from here to the frame it ran in user space only.
    pub read_us: Option<f64>,
    /// It entered the `write` or `sendto` of a 16-byte frame.
    pub frame_us: Option<f64>,
    /// Its system calls up to the frame's write, by name; a `write` or `sendto` with its file
    /// descriptor and length (`write(5, 8)`: an eventfd wake-up, a log line is longer).
    pub calls: Vec<String>,
}

/// The probes of `trace` for process `pid`.
pub(crate) fn probes(trace: &str, pid: u32) -> Vec<Probe> {
    let me = format!("-{pid} ");
    let woken = format!(" pid={pid} ");
    let mut out = Vec::new();
    let mut open: Option<(f64, Probe)> = None;
    for line in trace.lines().filter(|l| !l.starts_with('#')) {
        let Some((ts, what)) = timestamp_and_event(line) else {
            continue;
        };
        if what.contains("ihex-probe ") && what.trim_end().ends_with(" sent") {
            open = Some((ts, Probe::default()));
            continue;
        }
        let Some((t0, p)) = open.as_mut() else {
            continue;
        };
        let at = (ts - *t0) * 1e6;
        if what.contains("ihex-probe ") && what.trim_end().ends_with(" frame") {
            out.push(std::mem::take(p));
            open = None;
        } else if p.frame_us.is_some() {
            // What the process did after the frame is not the probe's.
            continue;
        } else if what.starts_with("sched_wakeup:") && what.contains(&woken) {
            p.woken_us.get_or_insert(at);
        } else if what.starts_with("sched_switch:") && what.contains(&format!("next_pid={pid} ")) {
            p.running_us.get_or_insert(at);
        } else if line.contains(&me) {
            if let Some(queued) = what.strip_prefix("net_dev_queue: ") {
                let field = |name: &str| {
                    queued
                        .split(' ')
                        .find_map(|f| f.strip_prefix(name))
                        .unwrap_or("?")
                };
                p.calls
                    .push(format!("xmit({}, {})", field("dev="), field("len=")));
            } else if let Some(exit) = what.strip_prefix("sys_exit: NR ") {
                let nr = exit.split(' ').next().and_then(|n| n.parse().ok());
                if nr.is_some_and(|nr| READS.contains(&nr)) {
                    p.read_us = Some(at);
                }
            } else if let Some(call) = SysEnter::of(what) {
                let (nr, arg) = (call.nr, |i| call.arg(i));
                p.calls.push(match (nr, arg(0), arg(2)) {
                    (1 | 44, Some(fd), Some(len)) => format!("{}({fd}, {len})", name(nr)),
                    _ => name(nr).to_owned(),
                });
                if READS.contains(&nr) {
                    p.read_entered_us = Some(at);
                }
                // write or send of 0x10 bytes (one `can_frame`): the frame.
                if matches!((nr, arg(2)), (1 | 44, Some(16))) {
                    p.frame_us = Some(at);
                }
            }
        }
    }
    out
}

/// The system calls of a trace by kind, most frequent first, and the events the ring buffer lost
/// (a census that lost some is short by as many). A `write` or `sendto` is told apart by its
/// length: 16 bytes is a CAN frame, 8 an eventfd wake-up.
pub(crate) fn census(trace: &str) -> (Vec<(String, u64)>, u64) {
    let mut counts: std::collections::BTreeMap<String, u64> = Default::default();
    let mut lost = 0;
    for line in trace.lines() {
        // `CPU:1 [LOST 123 EVENTS]`: the reader fell behind the ring buffer.
        if let Some(n) = line.split("[LOST ").nth(1) {
            lost += n
                .split(' ')
                .next()
                .and_then(|n| n.parse().ok())
                .unwrap_or(0);
            continue;
        }
        let Some((_, what)) = timestamp_and_event(line) else {
            continue;
        };
        let Some(call) = SysEnter::of(what) else {
            continue;
        };
        let nr = call.nr;
        let kind = match (name(nr), nr, call.arg(2)) {
            (n, 1 | 44, Some(16)) => format!("{n} 16 B"),
            (n, 1 | 44, Some(8)) => format!("{n} 8 B"),
            ("other", ..) => format!("nr {nr}"),
            (n, ..) => n.to_owned(),
        };
        *counts.entry(kind).or_default() += 1;
    }
    let mut counts: Vec<(String, u64)> = counts.into_iter().collect();
    counts.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    (counts, lost)
}

/// A `sys_enter` event: `sys_enter: NR 44 (7, 55d0, 4, 40, 0, 0)`, the arguments in hex.
struct SysEnter<'a> {
    /// The call's x86_64 number (`u32::MAX` when unreadable).
    nr: u32,
    args: &'a str,
}

impl<'a> SysEnter<'a> {
    fn of(event: &'a str) -> Option<SysEnter<'a>> {
        let rest = event.strip_prefix("sys_enter: NR ")?;
        let (nr, args) = rest.split_once(' ').unwrap_or((rest, ""));
        Some(SysEnter {
            nr: nr.parse().unwrap_or(u32::MAX),
            args,
        })
    }

    /// Argument `i` (the file descriptor is 0, a write's length 2).
    fn arg(&self, i: usize) -> Option<u64> {
        self.args
            .trim_start_matches('(')
            .trim_end_matches(')')
            .split(", ")
            .nth(i)
            .and_then(|a| u64::from_str_radix(a, 16).ok())
    }
}

/// The timestamp (s) and the event text of a trace line: `task-pid [cpu] flags  ts: event`.
fn timestamp_and_event(line: &str) -> Option<(f64, &str)> {
    let (head, event) = line.split_once(": ")?;
    let ts = head.rsplit(' ').next()?.parse().ok()?;
    Some((ts, event.trim_start()))
}

/// The x86_64 name of system call `nr`, for the calls a gateway makes around a command.
fn name(nr: u32) -> &'static str {
    match nr {
        0 => "read",
        1 => "write",
        7 => "poll",
        20 => "writev",
        24 => "sched_yield",
        44 => "sendto",
        45 => "recvfrom",
        46 => "sendmsg",
        47 => "recvmsg",
        54 => "setsockopt",
        202 => "futex",
        228 => "clock_gettime",
        230 => "clock_nanosleep",
        232 => "epoll_wait",
        233 => "epoll_ctl",
        281 => "epoll_pwait",
        299 => "recvmmsg",
        307 => "sendmmsg",
        _ => "other",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TRACE: &str = "\
# tracer: nop
#
   ihex-bench-90  [000] .....  100.000000: tracing_mark_write: ihex-probe 3 sent
  <idle>-0       [001] d.s..  100.000400: sched_wakeup: comm=mc-gateway pid=77 prio=120 target_cpu=001
  <idle>-0       [001] d....  100.000500: sched_switch: prev_comm=swapper/1 prev_pid=0 prev_prio=120 prev_state=R ==> next_comm=mc-gateway next_pid=77 next_prio=120
  mc-gateway-77  [001] .....  100.000600: sys_exit: NR 232 = 1
  mc-gateway-77  [001] .....  100.000700: sys_enter: NR 45 (7, 55d0, 1000, 40, 0, 0)
  mc-gateway-77  [001] .....  100.000750: net_dev_queue: dev=eth0 skbaddr=00000000c0ffee00 len=66
  mc-gateway-77  [001] .....  100.000800: sys_exit: NR 45 = 60
  mc-gateway-77  [001] .....  100.001100: sys_enter: NR 1 (5, 7ffd, 10, 0, 0, 0)
  mc-gateway-77  [001] .....  100.001300: sys_enter: NR 44 (7, 55d0, 4, 40, 0, 0)
   ihex-bench-90  [000] .....  100.002000: tracing_mark_write: ihex-probe 3 frame
";

    #[test]
    fn a_probe_gives_the_wake_up_the_run_the_calls_and_the_frame() {
        let p = probes(TRACE, 77);
        assert_eq!(p.len(), 1);
        let close = |a: Option<f64>, b: f64| (a.unwrap() - b).abs() < 0.01;
        assert!(close(p[0].woken_us, 400.0), "{p:?}");
        assert!(close(p[0].running_us, 500.0), "{p:?}");
        assert!(close(p[0].read_entered_us, 700.0), "{p:?}");
        assert!(close(p[0].read_us, 800.0), "{p:?}");
        assert!(close(p[0].frame_us, 1100.0), "{p:?}");
        // The PUBACK's sendto after the frame is not counted.
        assert_eq!(p[0].calls, ["recvfrom", "xmit(eth0, 66)", "write(5, 16)"]);
    }

    #[test]
    fn a_census_counts_the_calls_by_kind_and_frames_apart() {
        let trace = format!("{TRACE}CPU:1 [LOST 12 EVENTS]\n  mc-gateway-77  [001] .....  100.003: sys_enter: NR 1 (5, 7ffd, 8, 0, 0, 0)\n  mc-gateway-77  [001] .....  100.004: sys_enter: NR 999 (0)\n");
        let (counts, lost) = census(&trace);
        let c = |k: &str| counts.iter().find(|(n, _)| n == k).map(|(_, c)| *c);
        assert_eq!(c("recvfrom"), Some(1));
        assert_eq!(c("write 16 B"), Some(1), "{counts:?}");
        assert_eq!(c("write 8 B"), Some(1));
        assert_eq!(c("sendto"), Some(1), "the 4-byte PUBACK");
        assert_eq!(c("nr 999"), Some(1));
        assert_eq!(lost, 12);
        assert_eq!(
            counts.iter().map(|(_, c)| c).sum::<u64>(),
            5,
            "sys_exit and the rest are not calls"
        );
    }

    #[test]
    fn another_process_and_an_unfinished_probe_give_nothing() {
        assert_eq!(probes(TRACE, 78)[0].calls.len(), 0);
        let cut = TRACE.lines().take(7).collect::<Vec<_>>().join("\n");
        assert!(probes(&cut, 77).is_empty());
    }
}
