//! The iHEX CAN protocol, shared verbatim by the gateway (SocketCAN) and the sub-controllers (bxCAN).
//!
//! Everything on the island's bus is a CAN 2.0B frame with a 29-bit extended identifier laid out as
//!
//! | bits  | 28 – 24 | 23 – 12             | 11 – 0         |
//! |-------|---------|---------------------|----------------|
//! | field | [`Kind`]  | destination [`NodeId`] | source [`NodeId`] |
//!
//! The kind sits in the most significant bits, so its numeric value *is* the arbitration priority:
//! power and docking traffic always wins over LED and health traffic. Node IDs are 12 bits;
//! [`NodeId::GATEWAY`] (`0x000`) is the main controller, [`NodeId::BROADCAST`] (`0xFFF`) addresses every
//! node and [`NodeId::UNCONFIGURED`] (`0xFFE`) is the source address of a sub-controller that has no ID yet.
//!
//! * [`Packet`] / [`Message`] — one typed value per interaction, with [`Packet::to_frame`] and
//!   [`Packet::from_frame`] generic over any [`embedded_can::Frame`] (socketcan and embassy frames alike).
//! * [`StateReport`] and friends — a node's state read back part by part ([`Message::StateQuery`]).
//! * [`FwStatus`] and friends — a signed firmware image sent to many nodes at once
//!   ([`Message::FwBegin`], [`Message::FwData`], [`Message::FwQuery`], [`Message::FwEnd`]).
//! * [`filter`] — accept/reject ID and mask filters with the seed's semantics, and their translation to
//!   SocketCAN kernel filters and bxCAN filter banks.
//! * [`timing`] — bxCAN bit timing from a peripheral clock and a bitrate; [`bus`] — bit lengths of
//!   frames on the wire (bus load).
//! * [`uart`] — the 2-byte node-ID configuration message spoken over the ST-Link virtual COM port.
//! * [`schema`] — every message described as data (signals, units, value names), and [`dbc`] — that
//!   description as a DBC file for CAN tools (`docs/ihex.dbc`).
//!
//! The full byte layout of every message, the kind table, the address rules, the filter and bit-timing
//! worked examples and the UART exchange are in `docs/protocol.md` (repository root); every byte
//! value there is a test in `tests/golden.rs`. Property tests are in `tests/prop.rs`, and a
//! cargo-fuzz target in `fuzz/` (`cargo +nightly fuzz run decode`).
#![cfg_attr(not(test), no_std)]
#![warn(missing_docs)]
#![forbid(unsafe_code)]

#[macro_use]
mod macros;
mod addr;
pub mod bus;
pub mod dbc;
mod decimal;
mod error;
pub mod field;
pub mod filter;
mod fw;
mod header;
mod hex;
mod message;
pub mod schema;
mod state;
#[cfg(any(test, feature = "test-util"))]
pub mod test_util;
pub mod timing;
pub mod uart;
pub mod unit;

pub use addr::{NodeId, Port, Seq};
pub use decimal::write_decimal;
pub use error::{DecodeError, ParseError};
pub use fw::{
    FwAction, FwPhase, FwRefusal, FwStatus, FW_BEGIN_MAX_LEN, FW_DATA_LEN, FW_KINDS, FW_MAX_LEN,
};
pub use header::{Header, Kind};
pub use hex::Hex;
pub use message::{
    AckResult, BootRole, BuzzerCommand, DockRefuseReason, FaultCode, HealthFlags, HealthReply,
    LedCommand, Message, Packet, ResetReason, Rgb, Uid,
};
pub use state::{DockPartner, DockState, FirmwareVersion, PowerState, StateParts, StateReport};

/// Bitrate of the island bus, in bit/s.
pub const BITRATE: u32 = 500_000;

/// Protocol version carried in [`Message::BootUp`]: bump the minor on additions, the major on any
/// change an old peer would misread. 1.1 added state read-back (`StateQuery`, `StateReport`) and
/// dock links (`DockLink`); 1.2 firmware transfer (`FwBegin`, `FwEnd`, `FwQuery`, `FwStatus`,
/// `FwData`); 1.3 the `Protocol` part of the state read-back.
pub const PROTOCOL_VERSION: (u8, u8) = (1, 3);
