//! The host stage's Prometheus test: the ignored test `crates/mc-gateway/tests/prometheus.rs` has
//! Debian's Prometheus server scrape the demo gateway built by the same stage (same profile and
//! features: nothing recompiles), checks the `ihex_` series and every expression of the shipped
//! Grafana dashboard, and runs `promtool check metrics` on the exposition.
//!
//! Where `prometheus` or `promtool` is missing the test is skipped with a warning — except in CI
//! (`CI=true`), where that is a failure (`cargo xtask setup` installs Debian's `prometheus`).

use anyhow::Result;

use crate::ignored_test::{program, IgnoredTest};

/// Debian's package for the Prometheus test (the server and `promtool`).
pub const PACKAGES: [&str; 1] = ["prometheus"];

/// Written by the test when it ran to its end.
const PASSED: &str = "prometheus/passed";

/// Whether this machine can run the test: both programs present (`IHEX_PROMETHEUS` and
/// `IHEX_PROMTOOL` name them elsewhere than on `PATH`).
pub fn present() -> bool {
    program("IHEX_PROMETHEUS", &["prometheus"]).is_some()
        && program("IHEX_PROMTOOL", &["promtool"]).is_some()
}

/// Runs the Prometheus test.
pub fn run() -> Result<()> {
    IgnoredTest {
        label: "Prometheus test",
        test: "prometheus",
        missing: "prometheus or promtool not found (`cargo xtask setup` installs Debian's \
                   prometheus; IHEX_PROMETHEUS / IHEX_PROMTOOL name them)",
        marker: PASSED,
    }
    .run(present())
}
