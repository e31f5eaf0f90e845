//! Why an image is refused, and why a key file does not parse.

use core::fmt;

use crate::board::Board;
use crate::FirmwareVersion;

/// Why an image is refused. A node reports each as a refusal reason on the bus and keeps running
/// its current image.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ImageError {
    /// Shorter than the format or the header requires.
    Truncated {
        /// Bytes required.
        need: u32,
        /// Bytes present.
        got: u32,
    },
    /// Longer than header block plus payload.
    TrailingData {
        /// Bytes the header accounts for.
        need: u32,
        /// Bytes present.
        got: u32,
    },
    /// Not an iHEX image (magic).
    BadMagic,
    /// A header format this version does not know.
    UnsupportedFormat(u8),
    /// A byte the format reserves (header or padding) is not zero.
    Reserved {
        /// Offset of the first such byte in the image.
        offset: u16,
    },
    /// Flags this version does not know.
    UnknownFlags(u16),
    /// The header announces an empty payload.
    EmptyPayload,
    /// Signed with a key the node does not trust (the header's key ID is not the node's key's).
    UnknownKey,
    /// The signature does not verify with the node's key.
    BadSignature,
    /// Built for another board.
    WrongBoard {
        /// The image's board.
        image: Board,
        /// The node's board.
        node: Board,
    },
    /// Linked to run at another address than the node's slot.
    WrongAddress {
        /// The image's load address.
        image: u32,
        /// Where the node's slot runs a payload.
        slot: u32,
    },
    /// Speaks another major version of the CAN protocol.
    IncompatibleProtocol {
        /// The image's protocol major.
        image: u8,
        /// The node's protocol major.
        node: u8,
    },
    /// The payload does not fit the slot.
    TooLarge {
        /// Image bytes (header block + payload).
        len: u32,
        /// What the slot holds.
        max: u32,
    },
    /// Older than the running firmware, and the update was not forced.
    Downgrade {
        /// The image's version.
        image: FirmwareVersion,
        /// The running version.
        running: FirmwareVersion,
    },
    /// The payload (or the header block as stored) does not hash to what the header says.
    Corrupted,
}

impl fmt::Display for ImageError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ImageError::Truncated { need, got } => {
                write!(f, "truncated: {got} bytes, the image needs {need}")
            }
            ImageError::TrailingData { need, got } => {
                write!(f, "{got} bytes, but header and payload account for {need}")
            }
            ImageError::BadMagic => f.write_str("not an iHEX image (bad magic)"),
            ImageError::UnsupportedFormat(v) => write!(f, "unsupported image format {v}"),
            ImageError::Reserved { offset } => {
                write!(f, "reserved byte at offset {offset} is not zero")
            }
            ImageError::UnknownFlags(x) => write!(f, "unknown header flags {x:#06x}"),
            ImageError::EmptyPayload => f.write_str("empty payload"),
            ImageError::UnknownKey => f.write_str("signed with a key this node does not trust"),
            ImageError::BadSignature => f.write_str("bad signature"),
            ImageError::WrongBoard { image, node } => {
                write!(f, "built for board {image}, this is {node}")
            }
            ImageError::WrongAddress { image, slot } => {
                write!(
                    f,
                    "linked at {image:#010x}, the slot runs code at {slot:#010x}"
                )
            }
            ImageError::IncompatibleProtocol { image, node } => {
                write!(f, "speaks protocol {image}.x, the island speaks {node}.x")
            }
            ImageError::TooLarge { len, max } => {
                write!(f, "{len} bytes do not fit the {max}-byte slot")
            }
            ImageError::Downgrade { image, running } => {
                write!(f, "downgrade from {running} to {image} (not forced)")
            }
            ImageError::Corrupted => f.write_str("corrupted: hash mismatch"),
        }
    }
}

impl core::error::Error for ImageError {}

/// Why a key file's text is not a key.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum KeyTextError {
    /// No line with the key.
    Missing,
    /// The key line is not 64 hex digits.
    NotHex,
    /// More than one key line.
    Several,
    /// The bytes are not a valid ed25519 public key.
    NotAPoint,
}

impl fmt::Display for KeyTextError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            KeyTextError::Missing => "no key line (64 hex digits) found",
            KeyTextError::NotHex => "the key line is not 64 hex digits",
            KeyTextError::Several => "more than one key line",
            KeyTextError::NotAPoint => "not a valid ed25519 public key",
        })
    }
}

impl core::error::Error for KeyTextError {}
