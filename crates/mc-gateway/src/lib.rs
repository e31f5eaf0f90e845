//! iHEX main controller: bridges MQTT JSON commands and events to the island's CAN bus.
#![warn(missing_docs)]

pub mod bridge;
