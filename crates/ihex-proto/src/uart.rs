//! Node-ID configuration over the ST-Link virtual COM port (USART2, 115200 8N1): 2-byte messages.
//!
//! | message        | byte 0                | byte 1          | meaning                                  |
//! |----------------|-----------------------|-----------------|------------------------------------------|
//! | set ID         | `0xA0 \| id[11:8]`    | `id[7:0]`       | store `id` (`0x001..=0xFFD`) and restart CAN |
//! | query ID       | `0xB0`                | `0x00`          | report the stored ID                     |
//! | reply: ID      | `0x50 \| id[11:8]`    | `id[7:0]`       | the ID now in force (`0xFFE` = none yet) |
//! | reply: error   | `0xE0`                | [`UartError`] code | the request was refused               |
//!
//! The high nibble of the first byte is the marker (the seed's `'A'`): the 12-bit ID fills the rest.
//! A byte that cannot start a request is answered with a `Malformed` error and dropped, so a receiver
//! that lost sync finds it again at the next marker; an idle gap (the adapter's timeout) also resets it.

use crate::NodeId;

/// High nibble of a set-ID request.
pub const SET_MARKER: u8 = 0xA;
/// High nibble of a query request.
pub const QUERY_MARKER: u8 = 0xB;
/// High nibble of an ID reply.
pub const REPLY_ID_MARKER: u8 = 0x5;
/// High nibble of an error reply.
pub const REPLY_ERR_MARKER: u8 = 0xE;
/// Baud rate of the configuration port.
pub const BAUD: u32 = 115_200;

/// A request received over UART.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum UartRequest {
    /// Store this node ID.
    SetId(NodeId),
    /// Report the stored ID.
    Query,
}

/// Why a UART request was refused. The discriminant is the wire code.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum UartError {
    /// The ID is reserved (`0x000` gateway, `0xFFE`, `0xFFF` broadcast).
    ReservedId = 1,
    /// Not a valid 2-byte request.
    Malformed = 2,
    /// The ID could not be written to flash.
    StoreFailed = 3,
}

impl UartError {
    /// From the wire code.
    pub const fn from_raw(raw: u8) -> Option<Self> {
        match raw {
            1 => Some(UartError::ReservedId),
            2 => Some(UartError::Malformed),
            3 => Some(UartError::StoreFailed),
            _ => None,
        }
    }
}

impl core::fmt::Display for UartError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            UartError::ReservedId => "reserved node ID (use 0x001..=0xFFD)",
            UartError::Malformed => "malformed request",
            UartError::StoreFailed => "could not store the ID in flash",
        })
    }
}

impl core::error::Error for UartError {}

impl UartRequest {
    /// The two bytes of this request.
    pub const fn encode(self) -> [u8; 2] {
        match self {
            UartRequest::SetId(id) => [(SET_MARKER << 4) | (id.get() >> 8) as u8, id.get() as u8],
            UartRequest::Query => [QUERY_MARKER << 4, 0],
        }
    }
}

/// A reply sent back over UART.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum UartReply {
    /// The ID in force ([`NodeId::UNCONFIGURED`] when none).
    Id(NodeId),
    /// The request was refused.
    Error(UartError),
}

impl UartReply {
    /// The two bytes of this reply.
    pub const fn encode(self) -> [u8; 2] {
        match self {
            UartReply::Id(id) => [
                (REPLY_ID_MARKER << 4) | (id.get() >> 8) as u8,
                id.get() as u8,
            ],
            UartReply::Error(e) => [REPLY_ERR_MARKER << 4, e as u8],
        }
    }

    /// Parses a reply (host side); `None` when the bytes are no reply.
    pub const fn decode(b: [u8; 2]) -> Option<Self> {
        match b[0] >> 4 {
            REPLY_ID_MARKER => match NodeId::new((((b[0] & 0xF) as u16) << 8) | b[1] as u16) {
                Some(id) => Some(UartReply::Id(id)),
                None => None,
            },
            REPLY_ERR_MARKER if b[0] & 0xF == 0 => match UartError::from_raw(b[1]) {
                Some(e) => Some(UartReply::Error(e)),
                None => None,
            },
            _ => None,
        }
    }
}

/// Byte-at-a-time request decoder (sans-IO): feed received bytes, get requests or errors out.
#[derive(Clone, Copy, Default, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct UartDecoder {
    first: Option<u8>,
}

impl UartDecoder {
    /// An idle decoder.
    pub const fn new() -> Self {
        UartDecoder { first: None }
    }

    /// Forgets a half-received request (call after an idle gap).
    pub fn reset(&mut self) {
        self.first = None;
    }

    /// True while a request is half received.
    pub const fn is_pending(&self) -> bool {
        self.first.is_some()
    }

    /// Feeds one byte; returns a result once a request is complete or a byte cannot start one.
    ///
    /// Only `0xA_` and `0xB0` can start a request. After `0xB0`, anything but `0x00` is answered with
    /// `Malformed`, and if that byte can itself start a request it is kept as the new first byte, so
    /// a query that lost its second byte does not swallow the request after it.
    pub fn push(&mut self, byte: u8) -> Option<Result<UartRequest, UartError>> {
        let Some(b0) = self.first.take() else {
            return if Self::starts_request(byte) {
                self.first = Some(byte);
                None
            } else {
                Some(Err(UartError::Malformed))
            };
        };
        Some(if b0 >> 4 == SET_MARKER {
            let raw = (((b0 & 0xF) as u16) << 8) | byte as u16;
            NodeId::new_sc(raw)
                .map(UartRequest::SetId)
                .ok_or(UartError::ReservedId)
        } else if byte == 0 {
            Ok(UartRequest::Query)
        } else {
            if Self::starts_request(byte) {
                self.first = Some(byte);
            }
            Err(UartError::Malformed)
        })
    }

    /// True for a byte that can open a request: a set marker or the query byte `0xB0`.
    const fn starts_request(byte: u8) -> bool {
        byte >> 4 == SET_MARKER || byte == QUERY_MARKER << 4
    }
}
