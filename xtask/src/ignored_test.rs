//! The host stage's tests against real programs a user has (a browser, Prometheus): each an
//! ignored test of the workspace, run with the host stage's build (same profile and features:
//! nothing recompiles). Where its programs are missing it is skipped with a warning — except in CI
//! (`CI=true`), where that is a failure (`cargo xtask setup` installs them on Debian). A file the
//! test writes at its end proves it ran to its end, not filtered out or renamed.

use std::{path::PathBuf, time::SystemTime};

use anyhow::{bail, Result};

use crate::{cantools::in_ci, cmd};

/// A program named by the environment variable `var`, or the first of `names` found on `PATH`.
pub fn program(var: &str, names: &[&str]) -> Option<PathBuf> {
    if let Some(p) = std::env::var_os(var) {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    names.iter().find_map(|n| cmd::find(n))
}

/// One ignored test and what it needs.
pub struct IgnoredTest {
    /// How the output names it ("browser test").
    pub label: &'static str,
    /// The integration test's name (`--test NAME`).
    pub test: &'static str,
    /// Why it cannot run when its programs are missing, and how to get them.
    pub missing: &'static str,
    /// The file (below the target folder) the test writes when it ran to its end.
    pub marker: &'static str,
}

impl IgnoredTest {
    /// Runs the test when `present` (its programs are there), else skips or fails as above.
    pub fn run(&self, present: bool) -> Result<()> {
        let Self {
            label,
            test,
            missing,
            marker,
        } = self;
        if !present {
            if in_ci() {
                bail!("CI=true: the {label} must run, but {missing}");
            }
            println!(
                "xtask: WARNING: {label} SKIPPED: {missing}\n\
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
            test,
            "--",
            "--ignored",
        ]))?;
        let marker = cmd::target_dir().join(marker);
        let fresh = std::fs::metadata(&marker)
            .and_then(|m| m.modified())
            .is_ok_and(|t| t >= started);
        if !fresh {
            bail!(
                "the {label} did not run to its end (no new {}): was it renamed or filtered out?",
                marker.display()
            );
        }
        Ok(())
    }
}
