//! Instruction counts of the sans-IO workload under `valgrind --tool=callgrind`: run `n` and `2n`
//! iterations of each path in child processes of this same binary and take the difference, so
//! start-up, set-up and exit cancel out.

use std::collections::HashMap;
use std::path::Path;
use std::process::{Command, Stdio};

use anyhow::{anyhow, bail, Context, Result};

use ihex_bench::report::{Callgrind, PathCost};

/// Total instructions (`Ir`) of a callgrind output file (its `summary:` or `totals:` line).
pub fn total_instructions(out: &str) -> Option<u64> {
    out.lines()
        .find_map(|l| {
            l.strip_prefix("summary:")
                .or_else(|| l.strip_prefix("totals:"))
        })
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
}

/// Inclusive instructions (`Ir`) of each function of `names` in a callgrind output file: the cost
/// of its own lines plus that of every call it makes to another function, over all the blocks
/// callgrind wrote for it (one per source file its code came from, inlined code included). `None`
/// for a name the file does not have: the function was inlined into its caller, or never ran.
/// A function that calls itself is counted once; one that reaches itself through another would
/// be counted again (none of the tasks' loop functions does).
pub fn inclusive(out: &str, names: &[&str]) -> Vec<Option<u64>> {
    // Callgrind names a function in full once, `(id) name`, and as `(id)` after that.
    fn name<'a>(full: &mut HashMap<&'a str, &'a str>, spec: &'a str) -> Option<&'a str> {
        let spec = spec.trim();
        let Some((id, rest)) = spec.strip_prefix('(').and_then(|r| r.split_once(')')) else {
            return Some(spec);
        };
        let rest = rest.trim();
        if rest.is_empty() {
            full.get(id).copied()
        } else {
            full.insert(id, rest);
            Some(rest)
        }
    }
    let mut full = HashMap::new();
    let mut sums: HashMap<&str, u64> = HashMap::new();
    let (mut current, mut callee, mut call) = (None, None, false);
    for line in out.lines() {
        if let Some(spec) = line.strip_prefix("fn=") {
            current = name(&mut full, spec);
            call = false;
        } else if let Some(spec) = line.strip_prefix("cfn=") {
            callee = name(&mut full, spec);
        } else if line.starts_with("calls=") {
            call = true;
        } else if line.starts_with(|c: char| c.is_ascii_digit() || "+-*".contains(c)) {
            // `position cost`: after `calls=`, the cost is the call's inclusive one.
            let counted = !(std::mem::take(&mut call) && callee == current);
            let cost = line
                .split_whitespace()
                .nth(1)
                .and_then(|c| c.parse::<u64>().ok());
            if let (true, Some(f), Some(cost)) = (counted, current, cost) {
                if names.contains(&f) {
                    *sums.entry(f).or_default() += cost;
                }
            }
        }
    }
    names.iter().map(|n| sums.get(n).copied()).collect()
}

/// The audit writer's inline entry point in the `audited` workload: counting only inside it
/// separates what the writer thread pays from what the command path pays.
const WRITER: &str = "*AuditWriter*write_waiting*";

/// The phases of an answered command (the `answered` workload), each as the functions it is
/// counted in, in the order a command meets them: what the gateway's core task does between
/// reading the command from the MQTT task and handing its `command_result` back to it.
const PHASES: [(&str, &[&str]); 6] = [
    (
        "parse + core (command)",
        &["*Bridge*handle_delivered_command*"],
    ),
    (
        "frame out (poll, encode)",
        &["*Bridge*poll_transmit*", "*Packet*encode*"],
    ),
    // `handle_transmitted` itself is inlined into the caller: its two steps are counted.
    (
        "echo (frame confirmed)",
        &["*Bridge*release*", "*Bridge*on_frame_fate*"],
    ),
    ("ack (node's answer)", &["*Bridge*handle_packet*"]),
    (
        "publish: take from the core",
        &["*Bridge*poll_publication*"],
    ),
    (
        "publish: topic + JSON",
        &["*Topics*resolve*", "*PayloadWriter*write*"],
    ),
];

/// Instructions of `n` iterations of `path`; only inside functions matching `only` when given
/// (callgrind's `--toggle-collect`: everything they call is counted, nothing else).
fn measure_in(exe: &Path, path: &str, n: u64, dir: &Path, only: Option<&str>) -> Result<u64> {
    measure_only(exe, path, n, dir, only.as_slice())
}

/// [`measure_in`] counting inside any of the functions matching `only` (all when empty).
fn measure_only(exe: &Path, path: &str, n: u64, dir: &Path, only: &[&str]) -> Result<u64> {
    let out = dir.join(format!("callgrind.{path}.{n}.{}", std::process::id()));
    let mut valgrind = Command::new("valgrind");
    valgrind.args(["--tool=callgrind", "--quiet"]);
    for f in only {
        valgrind.arg(format!("--toggle-collect={f}"));
    }
    let status = valgrind
        .arg(format!("--callgrind-out-file={}", out.display()))
        .arg(exe)
        .args(["workload", "--path", path, "--n", &n.to_string()])
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .status()
        .context("running valgrind (Debian: apt-get install valgrind)")?;
    if !status.success() {
        bail!("valgrind on the {path} workload (n = {n}) failed: {status}");
    }
    let text = std::fs::read_to_string(&out).with_context(|| format!("{}", out.display()))?;
    let _ = std::fs::remove_file(&out);
    total_instructions(&text).ok_or_else(|| anyhow!("no instruction total in {}", out.display()))
}

fn measure(exe: &Path, path: &str, n: u64, dir: &Path) -> Result<u64> {
    measure_in(exe, path, n, dir, None)
}

fn path_cost(exe: &Path, path: &str, n: u64, dir: &Path) -> Result<PathCost> {
    path_cost_in(exe, path, n, dir, None)
}

fn path_cost_in(
    exe: &Path,
    path: &str,
    n: u64,
    dir: &Path,
    only: Option<&str>,
) -> Result<PathCost> {
    let a = measure_in(exe, path, n, dir, only)?;
    let b = measure_in(exe, path, 2 * n, dir, only)?;
    Ok(PathCost {
        n,
        instructions_n: a,
        instructions_2n: b,
        per_frame: (b as f64 - a as f64) / n as f64,
    })
}

/// Measures both paths with this executable.
pub fn run(n: u64) -> Result<Callgrind> {
    let exe = std::env::current_exe()?;
    let dir = std::env::temp_dir();
    let can_to_event = path_cost(&exe, "can", n, &dir)?;
    let again = measure(&exe, "can", n, &dir)?;
    let command_to_frame = path_cost(&exe, "command", n, &dir)?;
    let command_leased = path_cost(&exe, "command-leased", n, &dir)?;
    let command_answered = Some(path_cost(&exe, "answered", n, &dir)?);
    let command_audited = Some(path_cost(&exe, "audited", n, &dir)?);
    let audit_writer = path_cost_in(&exe, "audited", n, &dir, Some(WRITER))?;
    let mut command_phases = Vec::new();
    for (phase, functions) in PHASES {
        let a = measure_only(&exe, "answered", n, &dir, functions)?;
        let b = measure_only(&exe, "answered", 2 * n, &dir, functions)?;
        let cost = PathCost {
            n,
            instructions_n: a,
            instructions_2n: b,
            per_frame: (b as f64 - a as f64) / n as f64,
        };
        command_phases.push((phase.to_owned(), cost));
    }
    if audit_writer.per_frame <= 0.0 {
        bail!("callgrind counted nothing inside {WRITER}: was the audit writer inlined?");
    }
    Ok(Callgrind {
        command_leased: Some(command_leased),
        repeatable: again == can_to_event.instructions_n,
        can_to_event,
        command_to_frame,
        command_answered,
        command_audited,
        audit_writer: Some(audit_writer),
        command_phases,
        binary: format!(
            "{} ({})",
            exe.file_name().unwrap_or_default().to_string_lossy(),
            if cfg!(debug_assertions) {
                "debug"
            } else {
                "release"
            }
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_summary_line() {
        let out = "version: 1\ncreator: callgrind-3.19.0\nevents: Ir\nsummary: 1234567\n";
        assert_eq!(total_instructions(out), Some(1234567));
        assert_eq!(total_instructions("totals: 42 7\n"), Some(42));
        assert_eq!(total_instructions("events: Ir\n"), None);
    }

    #[test]
    fn inclusive_counts_add_the_calls_to_other_functions_over_every_block() {
        // `task` runs 10 of its own in two blocks (its code and code inlined from another
        // file), calls `work` (inclusive 100) and itself (50, not counted again); `work` is named
        // by its compressed id on its second appearance.
        let out = "\
events: Ir
fl=(1) a.rs
fn=(1) task
3 4
cfn=(2) work
calls=2 10
3 100
cfn=(1)
calls=1 3
4 50
fi=(2) b.rs
+1 6
fn=(2)
10 100
fn=(3) idle
1 7
totals: 267
";
        assert_eq!(
            inclusive(out, &["task", "work", "idle", "inlined"]),
            [Some(110), Some(100), Some(7), None]
        );
    }
}
