//! Validated newtypes for node addresses, dock ports and sequence numbers.

use core::fmt;

/// A 12-bit node address. Valid sub-controller IDs are `0x001..=0xFFD`; the rest are reserved.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
pub struct NodeId(u16);

impl NodeId {
    /// Largest raw value (12 bits).
    pub const MAX_RAW: u16 = 0xFFF;
    /// The main controller (gateway).
    pub const GATEWAY: NodeId = NodeId(0x000);
    /// Every node: only valid as a destination.
    pub const BROADCAST: NodeId = NodeId(0xFFF);
    /// Source address of a sub-controller that has not been given an ID yet.
    pub const UNCONFIGURED: NodeId = NodeId(0xFFE);
    /// Lowest assignable sub-controller ID.
    pub const FIRST_SC: NodeId = NodeId(0x001);
    /// Highest assignable sub-controller ID.
    pub const LAST_SC: NodeId = NodeId(0xFFD);

    /// Any 12-bit address, reserved ones included. `None` when `raw` does not fit in 12 bits.
    pub const fn new(raw: u16) -> Option<Self> {
        if raw <= Self::MAX_RAW {
            Some(NodeId(raw))
        } else {
            None
        }
    }

    /// An address a sub-controller may be given (`0x001..=0xFFD`), `None` otherwise.
    pub const fn new_sc(raw: u16) -> Option<Self> {
        if raw >= Self::FIRST_SC.0 && raw <= Self::LAST_SC.0 {
            Some(NodeId(raw))
        } else {
            None
        }
    }

    /// The raw 12-bit value.
    pub const fn get(self) -> u16 {
        self.0
    }

    /// True for `0x001..=0xFFD`, the IDs a sub-controller may own.
    pub const fn is_sc(self) -> bool {
        self.0 >= Self::FIRST_SC.0 && self.0 <= Self::LAST_SC.0
    }
}

/// Deserialises the raw number, refusing values above 12 bits (a derived impl would let them
/// through and corrupt the neighbouring identifier fields when encoded).
#[cfg(feature = "serde")]
impl<'de> serde::Deserialize<'de> for NodeId {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let raw = u16::deserialize(d)?;
        NodeId::new(raw).ok_or_else(|| {
            serde::de::Error::invalid_value(
                serde::de::Unexpected::Unsigned(raw.into()),
                &"a 12-bit node ID (0..=0xFFF)",
            )
        })
    }
}

/// Strips an optional `0x` / `0X` prefix.
pub(crate) fn strip_hex_prefix(s: &str) -> &str {
    s.strip_prefix("0x")
        .or_else(|| s.strip_prefix("0X"))
        .unwrap_or(s)
}

impl core::str::FromStr for NodeId {
    type Err = crate::ParseError;

    /// 1 to 3 hex digits in either case, optionally prefixed `0x` (`"111"`, `"FfD"`, `"0x2"`):
    /// any 12-bit address, reserved ones included (check [`NodeId::is_sc`] where only a
    /// sub-controller may be meant). No sign, no spaces.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let digits = strip_hex_prefix(s);
        if digits.is_empty() || digits.len() > 3 || !digits.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(crate::ParseError::NodeId);
        }
        u16::from_str_radix(digits, 16)
            .ok()
            .and_then(NodeId::new)
            .ok_or(crate::ParseError::NodeId)
    }
}

impl fmt::Display for NodeId {
    /// Lower-case hex without prefix, the form the MQTT API uses (`"111"`).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:x}", self.0)
    }
}

#[cfg(feature = "defmt")]
impl defmt::Format for NodeId {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(f, "{=u16:03x}", self.0)
    }
}

/// A dock port on an element (`0..=7`; a hexagon uses `0..=5`).
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
#[cfg_attr(feature = "serde", derive(serde::Serialize))]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Port(u8);

impl Port {
    /// Number of ports the protocol can address (one bit each in a byte-wide bitmap).
    pub const COUNT: u8 = 8;

    /// `None` when `raw >= Port::COUNT`.
    pub const fn new(raw: u8) -> Option<Self> {
        if raw < Self::COUNT {
            Some(Port(raw))
        } else {
            None
        }
    }

    /// The port number.
    pub const fn get(self) -> u8 {
        self.0
    }

    /// This port's bit in a port bitmap.
    pub const fn mask(self) -> u8 {
        1 << self.0
    }
}

/// Deserialises the raw number, refusing ports above 7.
#[cfg(feature = "serde")]
impl<'de> serde::Deserialize<'de> for Port {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let raw = u8::deserialize(d)?;
        Port::new(raw).ok_or_else(|| {
            serde::de::Error::invalid_value(
                serde::de::Unexpected::Unsigned(raw.into()),
                &"a dock port (0..=7)",
            )
        })
    }
}

impl fmt::Display for Port {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// Command sequence number, echoed in the [`crate::Message::Ack`] that answers the command. Wraps at 255.
pub type Seq = u8;
