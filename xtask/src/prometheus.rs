//! The host stage's Prometheus test: the ignored test `crates/mc-gateway/tests/prometheus.rs` has
//! Debian's Prometheus server scrape the demo gateway built by the same stage (same profile and
//! features: nothing recompiles), checks the `ihex_` series and every expression of the shipped
//! Grafana dashboard, and runs `promtool check metrics` on the exposition.
//!
//! Where `prometheus` or `promtool` is missing the test is skipped with a warning — except in CI
//! (`CI=true`), where that is a failure (`cargo xtask setup` installs Debian's `prometheus`).

use std::{path::PathBuf, time::SystemTime};

use anyhow::{bail, Result};

use crate::{cantools::in_ci, cmd};

/// Debian's package for the Prometheus test (the server and `promtool`).
pub const PACKAGES: [&str; 1] = ["prometheus"];

/// Written by the test when it ran to its end.
const PASSED: &str = "prometheus/passed";

/// A program named by the environment variable `var`, or `name` on `PATH`.
fn program(var: &str, name: &str) -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(var) {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    cmd::find(name)
}

/// Whether this machine can run the test: both programs present (`IHEX_PROMETHEUS` and
/// `IHEX_PROMTOOL` name them elsewhere than on `PATH`).
pub fn present() -> bool {
    program("IHEX_PROMETHEUS", "prometheus").is_some()
        && program("IHEX_PROMTOOL", "promtool").is_some()
}

/// Runs the Prometheus test.
pub fn run() -> Result<()> {
    if !present() {
        let why = "prometheus or promtool not found (`cargo xtask setup` installs Debian's \
                   prometheus; IHEX_PROMETHEUS / IHEX_PROMTOOL name them)";
        if in_ci() {
            bail!("CI=true: the Prometheus test must run, but {why}");
        }
        println!(
            "xtask: WARNING: Prometheus test SKIPPED: {why}\n\
             xtask: (with CI=true this fails the host stage)"
        );
        return Ok(());
    }
    let started = SystemTime::now();
    cmd::run(cmd::cargo().current_dir(cmd::root()).args([
        "test",
        "--workspace",
        "--features",
        cmd::HOST_FEATURES,
        "--test",
        "prometheus",
        "--",
        "--ignored",
    ]))?;
    let passed = cmd::target_dir().join(PASSED);
    let fresh = std::fs::metadata(&passed)
        .and_then(|m| m.modified())
        .is_ok_and(|t| t >= started);
    if !fresh {
        bail!(
            "the Prometheus test did not run to its end (no new {}): was it renamed or filtered out?",
            passed.display()
        );
    }
    Ok(())
}
