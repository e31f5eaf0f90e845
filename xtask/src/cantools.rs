//! The host stage's cantools round trip: a virtual environment in `target/venv` with the pinned
//! Python packages of the host stage ([`REQUIREMENTS`]: cantools, and the reference SiLA client the
//! SiLA test uses), then the ignored cantools test of `crates/ihex-proto/tests/dbc.rs` run with it
//! and with the golden vectors of the same stage.
//!
//! pip runs only when the requirements changed since the last install (a stamp file in the
//! environment), so a warm run costs the test alone. Where Python or PyPI is missing the round trip
//! is skipped with a warning — except in CI (`CI=true`), where that is a failure.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

use crate::cmd;

/// The pinned requirements, relative to the workspace root.
const REQUIREMENTS: [&str; 2] = [
    "crates/ihex-proto/tests/dbc/requirements.txt",
    "crates/mc-gateway/tests/sila/requirements.txt",
];

/// True under CI, where nothing may be skipped for want of a tool.
pub fn in_ci() -> bool {
    std::env::var("CI").is_ok_and(|v| v == "true")
}

/// Runs the round trip on the vectors `golden.rs` wrote to `vectors`.
pub fn round_trip(vectors: &Path) -> Result<()> {
    let python = match venv() {
        Ok(p) => p,
        Err(e) if !in_ci() => {
            println!(
                "xtask: WARNING: cantools round trip SKIPPED: {e:#}\n\
                 xtask: (with CI=true this fails the host stage)"
            );
            return Ok(());
        }
        Err(e) => return Err(e.context("CI=true: the cantools round trip must run")),
    };
    let report = vectors.with_file_name("cantools-report.txt");
    if report.exists() {
        std::fs::remove_file(&report)?;
    }
    cmd::run(
        cmd::cargo()
            .current_dir(cmd::root())
            .env("IHEX_CANTOOLS_PYTHON", &python)
            .env("IHEX_GOLDEN_VECTORS", vectors)
            .env("IHEX_CANTOOLS_REPORT", &report)
            // `--workspace`, not `-p ihex-proto`: the features resolve as in the host stage's
            // `cargo test --workspace`, so its build is reused instead of ihex-proto and its
            // dependencies compiling again (2 min of a cold run).
            .args(["test", "--workspace", "--features", cmd::HOST_FEATURES])
            .args(["--test", "dbc", "--", "--ignored"]),
    )?;
    // The test writes its report only when it ran to the end: no report, no round trip.
    let done = std::fs::read_to_string(&report).with_context(|| {
        format!(
            "the cantools test did not run (no {}): was it renamed or filtered out?",
            report.display()
        )
    })?;
    print!("xtask: {done}");
    Ok(())
}

/// The environment's Python, created and filled when needed.
pub fn venv() -> Result<PathBuf> {
    let root = cmd::root();
    let dir = cmd::target_dir().join("venv");
    let python = dir.join("bin/python");
    let mut wanted = String::new();
    for r in REQUIREMENTS {
        wanted += &std::fs::read_to_string(root.join(r)).with_context(|| format!("reading {r}"))?;
    }
    let stamp = dir.join("ihex-requirements.txt");
    if python.is_file() && std::fs::read_to_string(&stamp).is_ok_and(|s| s == wanted) {
        return Ok(python);
    }
    // A half-made environment (an interrupted or failed creation, a full disk) has no pip: made
    // again from scratch rather than failing every later run.
    let has_pip = python.is_file()
        && Command::new(&python)
            .args(["-m", "pip", "--version"])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
    if !has_pip {
        if dir.exists() {
            std::fs::remove_dir_all(&dir)
                .with_context(|| format!("removing the broken {}", dir.display()))?;
        }
        let Some(system) = cmd::find("python3") else {
            bail!("python3 not found (install Python 3 with pip and venv)");
        };
        cmd::run(Command::new(system).arg("-m").arg("venv").arg(&dir)).context(
            "creating the virtual environment (on Debian/Ubuntu: apt-get install python3-venv)",
        )?;
    }
    let mut pip = Command::new(&python);
    pip.args(["-m", "pip", "install", "--disable-pip-version-check", "-q"]);
    for r in REQUIREMENTS {
        pip.arg("-r").arg(root.join(r));
    }
    cmd::run(&mut pip).context("installing cantools and sila2 from PyPI")?;
    std::fs::write(&stamp, wanted).with_context(|| format!("writing {}", stamp.display()))?;
    Ok(python)
}
