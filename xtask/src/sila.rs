//! The host stage's SiLA test: the ignored test `crates/mc-gateway/tests/sila.rs` has the reference
//! SiLA 2 client (PyPI `sila2`, pinned in `crates/mc-gateway/tests/sila/requirements.txt`, in the
//! `target/venv` the cantools round trip also uses) drive the demo gateway built by the same stage.
//!
//! Where Python or PyPI is missing the test is skipped with a warning — except in CI (`CI=true`),
//! where that is a failure.

use anyhow::Result;

use crate::{cantools, ignored_test::IgnoredTest};

/// Written by the test when it ran to its end.
const PASSED: &str = "sila/passed";

/// Runs the SiLA test.
pub fn run() -> Result<()> {
    let venv = cantools::venv();
    if let Err(e) = &venv {
        println!("xtask: the Python environment for the SiLA test: {e:#}");
    }
    IgnoredTest {
        label: "SiLA reference client test",
        test: "sila",
        missing: "the Python environment with sila2 could not be made (python3 with venv and pip, \
                  and PyPI, are needed)",
        marker: PASSED,
    }
    .run(venv.is_ok())
}
