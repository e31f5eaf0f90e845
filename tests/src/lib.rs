//! Support library for iHEX integration tests, written once for every crate's tests: SocketCAN
//! interface leases, the one Mosquitto launcher ([`broker`]), the one MQTT test client ([`mqtt`]),
//! node IDs and ports from literals ([`id`], [`port`]), free loopback ports ([`free_port`]), a
//! fault-injecting TCP proxy, and timeouts that turn a hang into a failure.
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
pub mod net;
pub mod proxy;
pub mod time;
#[cfg(feature = "tls")]
pub mod tls;

pub use ihex_proto::test_util::{id, port, sc_id};
pub use net::free_port;
pub use time::{within, within_or_panic};
