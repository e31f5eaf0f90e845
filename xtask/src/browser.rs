//! The host stage's browser test: the ignored test `crates/mc-gateway/tests/browser.rs` drives the
//! island view in Debian's headless Chromium through chromedriver, against the demo gateway built by
//! the same stage (same profile and features: nothing recompiles).
//!
//! Where Chromium or chromedriver is missing the test is skipped with a warning — except in CI
//! (`CI=true`), where that is a failure (`cargo xtask setup` installs both on Debian).

use anyhow::Result;

use crate::ignored_test::{program, IgnoredTest};

/// Debian's packages for the browser test.
pub const PACKAGES: [&str; 2] = ["chromium", "chromium-driver"];

/// The browser test's screenshot folder; its last screenshot proves the test ran to its end.
const LAST_SCREENSHOT: &str = "web-screenshots/recovered.png";

/// Whether this machine can run the test: both programs present (`IHEX_CHROMIUM` and
/// `IHEX_CHROMEDRIVER` name them elsewhere than on `PATH`).
pub fn present() -> bool {
    program(
        "IHEX_CHROMIUM",
        &["chromium", "chromium-browser", "google-chrome"],
    )
    .is_some()
        && program("IHEX_CHROMEDRIVER", &["chromedriver"]).is_some()
}

/// Runs the browser test.
pub fn run() -> Result<()> {
    IgnoredTest {
        label: "browser test",
        test: "web",
        missing: "chromium or chromedriver not found (`cargo xtask setup` installs Debian's \
                   chromium and chromium-driver; IHEX_CHROMIUM / IHEX_CHROMEDRIVER name them)",
        marker: LAST_SCREENSHOT,
    }
    .run(present())
}
