//! iHEX main controller: bridges MQTT JSON commands and events to the island's CAN bus.
#![warn(missing_docs)]

pub mod bridge;
pub mod command;
pub mod docking;
pub mod error_frame;
pub mod event;
pub mod registry;
pub mod throttle;
