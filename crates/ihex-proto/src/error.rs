//! The one error type of the protocol crate: why a frame or a byte string is not a valid message.

use core::fmt;

use crate::Kind;

/// Why a frame could not be decoded. Decoding never panics; every malformed input maps to one of these.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum DecodeError {
    /// An 11-bit standard identifier: iHEX uses 29-bit identifiers only.
    StandardId,
    /// A remote (RTR) frame: iHEX never uses them.
    Remote,
    /// The kind field holds a value no message is assigned to.
    UnknownKind(u8),
    /// The data length does not match what the kind requires.
    Length {
        /// The message kind.
        kind: Kind,
        /// Bytes required.
        expected: u8,
        /// Bytes received.
        got: u8,
    },
    /// A field holds a value outside its range (`field` names it as in `docs/protocol.md`).
    Value {
        /// The message kind.
        kind: Kind,
        /// Name of the offending field.
        field: &'static str,
        /// The raw value (the first byte of multi-byte fields is enough to find it in a dump).
        raw: u32,
    },
    /// The source or destination does not fit the message (for example a broadcast source).
    Address {
        /// The message kind.
        kind: Kind,
    },
}

impl fmt::Display for DecodeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DecodeError::StandardId => {
                f.write_str("standard 11-bit identifier (iHEX uses 29-bit identifiers)")
            }
            DecodeError::Remote => f.write_str("remote frame (iHEX does not use RTR)"),
            DecodeError::UnknownKind(k) => write!(f, "unknown message kind 0x{k:02x}"),
            DecodeError::Length {
                kind,
                expected,
                got,
            } => {
                write!(f, "{kind:?}: expected {expected} data bytes, got {got}")
            }
            DecodeError::Value { kind, field, raw } => {
                write!(f, "{kind:?}: field `{field}` out of range ({raw:#x})")
            }
            DecodeError::Address { kind } => {
                write!(f, "{kind:?}: invalid source/destination for this kind")
            }
        }
    }
}

impl core::error::Error for DecodeError {}

/// Why a text is not a [`crate::NodeId`], a [`crate::Uid`] or a [`crate::FirmwareVersion`]. The one
/// parser for each lives in their `FromStr`, so every tool (gateway, simulator, provisioning)
/// accepts the same forms.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ParseError {
    /// Not 1 to 3 hex digits (after an optional `0x`).
    NodeId,
    /// Not 24 hex digits (after an optional `0x`, ignoring `:`, `-` and spaces).
    Uid,
    /// Not `MAJOR.MINOR.PATCH` with each number `0..=255`.
    Version,
}

impl fmt::Display for ParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParseError::NodeId => f.write_str(
                "a node ID is 1 to 3 hex digits, optionally prefixed 0x (\"111\", \"0x2\")",
            ),
            ParseError::Uid => f.write_str(
                "a UID is the board's 96-bit unique ID as 24 hex digits, byte 0 first \
                 (\"0123456789abcdef01234567\"; `:`, `-` and spaces between digits are ignored)",
            ),
            ParseError::Version => f.write_str(
                "a firmware version is MAJOR.MINOR.PATCH, each 0 to 255 without leading zeros \
                 (\"1.2.3\"; a -pre-release or +build suffix is ignored)",
            ),
        }
    }
}

impl core::error::Error for ParseError {}
