//! iHEX benchmarks (issue 8): how fast, how lean, and how close to the bus's physical limit the
//! gateway is. Run through `cargo xtask bench`; see docs/benchmarks.md.
//!
//! * [`bus`] — frame bit lengths and the frame-rate limit of a 500 kbit/s bus;
//! * [`workload`] — the sans-IO bridge on a fixed workload, for instruction counts (callgrind);
//! * [`procedure`] — docking → a procedure step's `done`, timed in the sans-IO core;
//! * [`results`], [`stats`], [`report`] — what the live run measured, percentiles, the results
//!   file, the table and the SVG plots.
//!
//! The I/O-heavy parts live in the `ihex-bench` binary (`src/main.rs` and its modules `live`: the
//! real gateway process over SocketCAN and Mosquitto; `islands`: 16 gateways with simulated
//! islands on one Mosquitto; `callgrind`: the workload under valgrind),
//! which use `anyhow` like the other tools; this library has no I/O and no error type.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod audit;
pub mod bus;
pub mod procedure;
pub mod report;
pub mod results;
pub mod stats;
pub mod workload;
