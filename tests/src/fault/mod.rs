//! The fault suite's parts: the [`trace`] a run records, the [`check`]er that holds it to the
//! gateway's delivery contract, the seeded [`plan`] of commands and faults, and the [`harness`]
//! that runs a real gateway, broker, proxy and simulated island over vcan and records the trace.

pub mod check;
pub mod harness;
pub mod plan;
pub mod trace;
