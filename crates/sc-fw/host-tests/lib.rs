//! sc-fw's HAL-free modules, built for the host so their unit tests run with plain `cargo test`.
//! The sources are the firmware's own files: there is no copy to drift.

#[path = "../src/record.rs"]
pub mod record;

#[path = "../src/bank.rs"]
pub mod bank;
