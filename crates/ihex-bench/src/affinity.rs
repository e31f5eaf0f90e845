//! Where the live run's processes run (`live --pin`): the measured processes (the gateway, the
//! plain forwarder) alone on the first CPU, the benchmark's own threads on the others.
//!
//! A process started by a thread inherits that thread's CPU set, so the benchmark moves its own
//! thread to CPU 0 only while it starts a measured process: no system call on another process's
//! threads, which may already be running.

use anyhow::{bail, Context, Result};
use nix::sched::{sched_setaffinity, CpuSet};
use nix::unistd::Pid;

/// The two CPU sets of a pinned run.
pub(crate) struct Pinning {
    measured: CpuSet,
    rest: CpuSet,
}

/// The calling thread.
fn this_thread() -> Pid {
    Pid::from_raw(0)
}

impl Pinning {
    /// Moves the calling thread to CPUs `1..cpus`; threads and processes it starts later inherit
    /// that. Fails with fewer than two CPUs: there is nothing to keep the measured ones apart on.
    pub(crate) fn start(cpus: usize) -> Result<Pinning> {
        if cpus < 2 {
            bail!("--pin needs at least two CPUs (this machine has {cpus})");
        }
        let mut measured = CpuSet::new();
        measured.set(0)?;
        let mut rest = CpuSet::new();
        for cpu in 1..cpus.min(CpuSet::count()) {
            rest.set(cpu)?;
        }
        sched_setaffinity(this_thread(), &rest).context("moving the benchmark off CPU 0")?;
        Ok(Pinning { measured, rest })
    }

    /// Runs `start` (which starts a measured process) with the calling thread on CPU 0 when
    /// `pinning`, then moves the thread back; without it, just runs `start`.
    pub(crate) fn measured<T>(
        pinning: Option<&Pinning>,
        start: impl FnOnce() -> Result<T>,
    ) -> Result<T> {
        let Some(p) = pinning else {
            return start();
        };
        sched_setaffinity(this_thread(), &p.measured).context("moving to CPU 0")?;
        let started = start();
        sched_setaffinity(this_thread(), &p.rest).context("moving off CPU 0")?;
        started
    }

    /// What the table's heading says about it.
    pub(crate) fn layout(cpus: usize) -> String {
        let rest = match cpus {
            ..=2 => "CPU 1".to_owned(),
            _ => format!("CPUs 1-{}", cpus - 1),
        };
        format!(
            "the gateway and the plain forwarder alone on CPU 0, the benchmark's threads on \
             {rest} (the bare SocketCAN pair before that, on every CPU)"
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_cpu_cannot_be_pinned() {
        let e = Pinning::start(1).err().expect("one CPU");
        assert!(e.to_string().contains("at least two CPUs"), "{e}");
    }

    #[test]
    fn the_layout_names_the_benchmark_cpus() {
        assert!(Pinning::layout(2).contains("threads on CPU 1 ("));
        assert!(Pinning::layout(4).contains("threads on CPUs 1-3 ("));
    }
}
