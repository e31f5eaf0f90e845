//! Numbering an island's sub-controllers: the library behind the `ihex-provision` tool.
//!
//! - [`serial`]: set or read a board's node ID over its ST-Link virtual COM port (the protocol's
//!   2-byte UART message, reply checked, then read back);
//! - [`can`]: assign an ID over CAN by the board's 96-bit unique ID, through the gateway's MQTT API;
//! - [`id`]: what IDs are allowed, and the registry file of IDs already handed out;
//! - [`api`] and [`mqtt`]: the gateway's JSON commands and events, and a short MQTT session;
//! - [`procedure`]: a TOML procedure file as the gateway's `procedure` command, sent and followed.
//!
//! Both paths refuse reserved (`000`, `ffe`, `fff`), oversized and duplicate IDs before anything is sent.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod api;
pub mod can;
pub mod id;
pub mod mqtt;
pub mod procedure;
pub mod serial;
