//! iHEX sub-controller firmware for the NUCLEO-F303RE: the embassy adapter around `ihex_sc_core::Node`.
//!
//! `src/main.rs` only sets the chip up and spawns the tasks of [`tasks`]; every task owns its
//! peripheral and talks to the node task through the channels and signals of [`event`]. The pin
//! assignment comes from `hw/pinmap.toml` through the generated [`board`] module, so the firmware and
//! the hardware notes cannot disagree. [`record`] and [`bank`] are pure and also tested on the host
//! (`crates/sc-fw/host-tests`).
#![no_std]
#![warn(missing_docs)]

pub mod bank;
pub mod board;
pub mod can;
pub mod clock;
pub mod config;
pub mod event;
pub mod image;
pub mod record;
pub mod reset;
pub mod retained;
pub mod tasks;
pub mod update;
