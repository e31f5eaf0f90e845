//! The iHEX gateway's logic, sans-IO: the [`Bridge`] takes JSON commands, CAN packets, bus
//! conditions and the time as inputs, and gives frames to transmit and publications (events and
//! retained node state documents, as typed values) as outputs. It owns no socket, task or clock:
//! `mc-gateway` is the tokio shell that feeds it, and any other adapter (a web view, a test, a
//! benchmark) drives it the same way.
//!
//! The API follows quinn-proto's `Connection`: one `handle_*` method per kind of input, each taking
//! `now`; [`Bridge::handle_timeout`] at [`Bridge::poll_timeout`]; [`Bridge::poll_transmit`] and
//! [`Bridge::poll_publication`] for the outputs, in the order they were produced. Every frame taken
//! from `poll_transmit` is answered by [`Bridge::handle_transmitted`] (its echo),
//! [`Bridge::handle_send_failed`] or [`Bridge::handle_withdrawn`]; until then it holds one of the
//! few places of the transmit window, so a command waiting for the bus waits where it can still be
//! withdrawn. The adapter takes commands only while [`Bridge::wants_commands`] says so.
//!
//! ```
//! use std::time::Instant;
//! use ihex_gateway_core::{Bridge, BridgeConfig, Publication};
//!
//! let now = Instant::now();
//! let mut bridge = Bridge::new(BridgeConfig::default(), now);
//! bridge.handle_timeout(now); // the first health check is due at once
//! let health_check = bridge.poll_transmit(now).expect("a frame to send").packet;
//! assert_eq!(health_check.dest, ihex_proto::NodeId::BROADCAST);
//! bridge.handle_transmitted(health_check, now); // its echo: the frame went on the bus
//!
//! bridge.handle_command(br#"{"cmd":"led","node":"2","color":"red"}"#, now);
//! let Some(Publication::Event(event)) = bridge.poll_publication() else { panic!() };
//! assert_eq!(event.to_json(), r#"{"event":"command_rejected","payload":{"request_id":null,"reason":"unknown node 2; known: none yet"}}"#);
//! ```
//!
//! Modules: [`bridge`] (the state machine: it routes each input, one submodule per concern of its
//! own), [`command`] (parsing and validation of JSON commands, and the tracking of pending ones),
//! [`event`] (the MQTT API's events and state documents), [`registry`] (what is known of each
//! node), [`docking`] (the one-at-a-time docking sequence and its frames and events), [`throttle`]
//! (rate limit of error events), [`error_frame`] (SocketCAN error frames), [`topic`] (logical
//! topics and their names), [`ha`] (Home Assistant discovery and commands), [`fwupdate`] (the
//! firmware-update sender, uploads and `fw_update`), [`lease`] (who holds which elements, and the
//! refusal of everyone else's commands to them), [`origin`] (the interface and identity a command
//! came with). A concept's folder holds its machine and the
//! bridge's glue for it.
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod bridge;
pub mod command;
pub mod docking;
pub mod error_frame;
pub mod event;
pub mod fwupdate;
pub mod ha;
pub mod json_text;
mod json_writer;
pub mod lease;
pub mod origin;
pub mod procedure;
pub mod registry;
pub mod throttle;
pub mod topic;

pub use bridge::{
    Bridge, BridgeConfig, BusEvent, BusHealth, CommandCounters, Delivery, PayloadWriter,
    Publication, PublicationCounters, Transmit,
};
pub use event::{Event, NodeState};
pub use origin::{Interface, Origin};
pub use topic::Topic;
