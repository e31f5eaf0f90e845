//! Support library for iHEX integration tests: SocketCAN interface leases, a throwaway Mosquitto
//! broker, a test MQTT client that reports what the broker answered, a fault-injecting TCP proxy, and timeouts that turn a hang into a failure.
//!
//! The SocketCAN tests live behind the `vcan` feature and expect `IHEX_TEST_CAN` to name the
//! interfaces they may use. `cargo xtask test` sets it up: natively when the host has vcan,
//! otherwise inside a QEMU microVM (see `docs/testing.md`).
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod bin;
pub mod broker;
pub mod can;
pub mod fault;
pub mod mqtt;
pub mod proxy;
pub mod time;
#[cfg(feature = "tls")]
pub mod tls;

pub use time::{within, within_or_panic};
