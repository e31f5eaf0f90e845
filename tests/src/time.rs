//! Timeouts for tests: a broken test must fail with a message, never hang the run.
//!
//! Emulated kernels (the TCG microVM) are many times slower than a host, so deadlines go through
//! [`scaled`], which multiplies them by `IHEX_TEST_TIME_SCALE` (the harness sets it in the VM).

use std::future::Future;
use std::time::Duration;

/// Environment variable multiplying every deadline given to [`scaled`] (a positive number).
pub const SCALE_ENV: &str = "IHEX_TEST_TIME_SCALE";

/// A future did not finish within its deadline.
#[derive(Debug, thiserror::Error)]
#[error("{what} did not finish within {after:?}")]
pub struct Timeout {
    /// What was awaited.
    pub what: String,
    /// The deadline that passed (after scaling).
    pub after: Duration,
}

/// `dur` multiplied by `IHEX_TEST_TIME_SCALE` (1 when unset or not a positive number).
pub fn scaled(dur: Duration) -> Duration {
    let factor = std::env::var(SCALE_ENV)
        .ok()
        .and_then(|s| s.trim().parse::<f64>().ok())
        .filter(|f| f.is_finite() && *f > 0.0)
        .unwrap_or(1.0);
    dur.mul_f64(factor)
}

/// Awaits `fut` for at most `scaled(dur)`; `what` names it in the error.
pub async fn within<F: Future>(
    dur: Duration,
    what: impl Into<String>,
    fut: F,
) -> Result<F::Output, Timeout> {
    let after = scaled(dur);
    tokio::time::timeout(after, fut).await.map_err(|_| Timeout {
        what: what.into(),
        after,
    })
}

/// Like [`within`], but panics with the timeout message (for tests that do not return `Result`).
#[track_caller]
pub fn within_or_panic<F: Future>(
    dur: Duration,
    what: impl Into<String>,
    fut: F,
) -> impl Future<Output = F::Output> {
    let caller = std::panic::Location::caller();
    let what = what.into();
    async move {
        match within(dur, what, fut).await {
            Ok(v) => v,
            Err(e) => panic!("{e} (at {caller})"),
        }
    }
}
