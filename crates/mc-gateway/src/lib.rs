//! iHEX main controller: bridges MQTT JSON commands and events to the island's CAN bus.
//!
//! The logic is the sans-IO [`ihex_gateway_core::Bridge`]; this crate is the tokio shell around it:
//! [`can`] (SocketCAN, or any [`can::FrameLink`]), [`mqtt`] (rumqttc, one task owning the event
//! loop), [`mod@run`] building the resources and then running them around the core, [`config`]
//! (CLI > env > TOML > defaults), [`log`], [`shutdown`], [`metrics`], [`feed`] (the core's publications and
//! views for other adapters); with the default `demo` feature the embedded broker and the simulated
//! island (`demo`), and with the default `web` feature the island view (`web`, `docs/web.md`);
//! [`doctor`] is `mc-gateway doctor`, the bring-up checks.
//!
//! ```no_run
//! # async fn f() -> Result<(), Box<dyn std::error::Error>> {
//! let config = mc_gateway::Config::lab("127.0.0.1:1883", "vcan0")?;
//! let stop = tokio_util::sync::CancellationToken::new();
//! mc_gateway::run(config, stop).await?;
//! # Ok(()) }
//! ```
#![warn(missing_docs)]
// The one exception is `sys` (system calls std and tokio do not offer).
#![deny(unsafe_code)]

pub mod audit;
pub mod can;
pub mod config;
#[cfg(feature = "demo")]
pub mod demo;
pub mod doctor;
pub mod error;
pub mod feed;
pub mod fw;
mod handover;
pub mod log;
pub mod metrics;
pub mod mqtt;
pub mod run;
pub mod shutdown;
#[cfg(feature = "sila")]
pub mod sila;
#[allow(unsafe_code)]
mod sys;
mod timer;
#[cfg(feature = "web")]
pub mod web;

/// The sans-IO gateway core this shell runs (re-exported for the tests and tools built on the shell).
pub use ihex_gateway_core as core;
pub use ihex_gateway_core::topic;

pub use config::Config;
pub use error::GatewayError;
pub use run::{run, run_with_stats, Gateway};
/// The shutdown signal [`run()`] takes (re-exported so callers need no direct `tokio-util` dependency).
pub use tokio_util::sync::CancellationToken;

/// Locks `m`, also when poisoned: a poisoned lock only means a thread panicked while holding it;
/// the data is still usable.
pub(crate) fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}
