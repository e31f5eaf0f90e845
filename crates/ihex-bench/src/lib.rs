//! iHEX benchmarks (issue 8): how fast, how lean, and how close to the bus's physical limit the
//! gateway is. Run through `cargo xtask bench`; see docs/benchmarks.md.
//!
//! * [`bus`] — frame bit lengths and the frame-rate limit of a 500 kbit/s bus;
//! * [`live`] — the real gateway process over SocketCAN and Mosquitto (rates, latency, CPU, RSS);
//! * [`workload`] — the sans-IO bridge on a fixed workload, for instruction counts (callgrind);
//! * [`callgrind`] — runs that workload under valgrind and derives instructions per frame;
//! * [`stats`], [`report`] — percentiles, the results file, the table and the SVG plots.
#![warn(missing_docs)]

pub mod bus;
pub mod callgrind;
pub mod live;
pub mod report;
pub mod stats;
pub mod workload;
