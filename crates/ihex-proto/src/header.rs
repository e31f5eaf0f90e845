//! The 29-bit identifier: message kind (= priority), destination and source node.

use embedded_can::{ExtendedId, Id};

use crate::{DecodeError, NodeId};

/// Message kind. The numeric value is the top 5 bits of the identifier, so a *lower* value wins
/// arbitration: power and docking first, LED, identify and health traffic last.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Kind {
    /// Gateway → node: switch the power relay.
    PowerSet = 0x00,
    /// Node → gateway: something went wrong (like CANopen EMCY).
    Fault = 0x01,
    /// Node → gateway: a dock port's signal loop closed.
    DockDetected = 0x02,
    /// Node → gateway: a dock port's signal loop opened.
    DockRemoved = 0x03,
    /// Gateway → node: go ahead, power the docked element.
    DockConfirm = 0x04,
    /// Gateway → node: do not power the docked element.
    DockRefuse = 0x05,
    /// Mobile node → gateway: "I just powered up docked by this port of mine".
    Handshake = 0x06,
    /// Node → gateway: acknowledgement (or refusal) of a command.
    Ack = 0x07,
    /// Gateway → all: first 8 bytes of the unique ID of the node to be numbered.
    AssignSelect = 0x08,
    /// Gateway → all: last 4 bytes of the unique ID and the new node ID.
    AssignCommit = 0x09,
    /// Node → gateway: result of a node-ID assignment.
    AssignReply = 0x0A,
    /// Node → gateway: announcement after reset.
    BootUp = 0x0B,
    /// Gateway → node: buzzer off, continuous or pattern.
    BuzzerSet = 0x0C,
    /// Gateway → node: LED strip colour, brightness, blink.
    LedSet = 0x0D,
    /// Gateway → node: blink and beep so a person can find the element.
    Identify = 0x0E,
    /// Gateway → all (or one): are you there?
    HealthCheck = 0x0F,
    /// Node → gateway: state snapshot answering a health check.
    HealthReply = 0x10,
    /// Gateway → node (or all): report these groups of your state.
    StateQuery = 0x11,
    /// Node → gateway: one part of the node's state, answering a state query.
    StateReport = 0x12,
    /// Gateway → static node: this mobile element is the one docked on your port.
    DockLink = 0x13,
    /// Gateway → node (or all): a firmware transfer starts (or resumes).
    FwBegin = 0x1B,
    /// Gateway → node (or all): commit (verify, install, reset) or abort a transfer.
    FwEnd = 0x1C,
    /// Gateway → node (or all): report your transfer status.
    FwQuery = 0x1D,
    /// Node → gateway: transfer phase, refusal reason, what is missing.
    FwStatus = 0x1E,
    /// Gateway → node (or all): six image bytes; the lowest priority of all.
    FwData = 0x1F,
}

impl Kind {
    /// Every assigned kind, in numeric (= priority) order. Kinds need not be contiguous: unassigned
    /// values between them are reserved for other additions.
    pub const ALL: [Kind; 25] = [
        Kind::PowerSet,
        Kind::Fault,
        Kind::DockDetected,
        Kind::DockRemoved,
        Kind::DockConfirm,
        Kind::DockRefuse,
        Kind::Handshake,
        Kind::Ack,
        Kind::AssignSelect,
        Kind::AssignCommit,
        Kind::AssignReply,
        Kind::BootUp,
        Kind::BuzzerSet,
        Kind::LedSet,
        Kind::Identify,
        Kind::HealthCheck,
        Kind::HealthReply,
        Kind::StateQuery,
        Kind::StateReport,
        Kind::DockLink,
        Kind::FwBegin,
        Kind::FwEnd,
        Kind::FwQuery,
        Kind::FwStatus,
        Kind::FwData,
    ];

    /// The kind with this 5-bit value, `None` for unassigned values.
    pub const fn from_raw(raw: u8) -> Option<Kind> {
        Some(match raw {
            0x00 => Kind::PowerSet,
            0x01 => Kind::Fault,
            0x02 => Kind::DockDetected,
            0x03 => Kind::DockRemoved,
            0x04 => Kind::DockConfirm,
            0x05 => Kind::DockRefuse,
            0x06 => Kind::Handshake,
            0x07 => Kind::Ack,
            0x08 => Kind::AssignSelect,
            0x09 => Kind::AssignCommit,
            0x0A => Kind::AssignReply,
            0x0B => Kind::BootUp,
            0x0C => Kind::BuzzerSet,
            0x0D => Kind::LedSet,
            0x0E => Kind::Identify,
            0x0F => Kind::HealthCheck,
            0x10 => Kind::HealthReply,
            0x11 => Kind::StateQuery,
            0x12 => Kind::StateReport,
            0x13 => Kind::DockLink,
            0x1B => Kind::FwBegin,
            0x1C => Kind::FwEnd,
            0x1D => Kind::FwQuery,
            0x1E => Kind::FwStatus,
            0x1F => Kind::FwData,
            _ => return None,
        })
    }

    /// The kind's name as in `docs/protocol.md` (`"PowerSet"`): the DBC message name and the
    /// value names of an [`crate::Message::Ack`]'s `kind`.
    pub const fn name(self) -> &'static str {
        match self {
            Kind::PowerSet => "PowerSet",
            Kind::Fault => "Fault",
            Kind::DockDetected => "DockDetected",
            Kind::DockRemoved => "DockRemoved",
            Kind::DockConfirm => "DockConfirm",
            Kind::DockRefuse => "DockRefuse",
            Kind::Handshake => "Handshake",
            Kind::Ack => "Ack",
            Kind::AssignSelect => "AssignSelect",
            Kind::AssignCommit => "AssignCommit",
            Kind::AssignReply => "AssignReply",
            Kind::BootUp => "BootUp",
            Kind::BuzzerSet => "BuzzerSet",
            Kind::LedSet => "LedSet",
            Kind::Identify => "Identify",
            Kind::HealthCheck => "HealthCheck",
            Kind::HealthReply => "HealthReply",
            Kind::StateQuery => "StateQuery",
            Kind::StateReport => "StateReport",
            Kind::DockLink => "DockLink",
            Kind::FwBegin => "FwBegin",
            Kind::FwEnd => "FwEnd",
            Kind::FwQuery => "FwQuery",
            Kind::FwStatus => "FwStatus",
            Kind::FwData => "FwData",
        }
    }

    /// True for kinds the gateway sends (commands); false for node reports.
    pub const fn is_command(self) -> bool {
        matches!(
            self,
            Kind::PowerSet
                | Kind::DockConfirm
                | Kind::DockRefuse
                | Kind::AssignSelect
                | Kind::AssignCommit
                | Kind::BuzzerSet
                | Kind::LedSet
                | Kind::Identify
                | Kind::HealthCheck
                | Kind::StateQuery
                | Kind::DockLink
                | Kind::FwBegin
                | Kind::FwEnd
                | Kind::FwQuery
                | Kind::FwData
        )
    }

    /// True for commands that a node answers with [`crate::Message::Ack`] (they carry a sequence number).
    pub const fn is_acknowledged(self) -> bool {
        matches!(
            self,
            Kind::PowerSet
                | Kind::DockConfirm
                | Kind::DockRefuse
                | Kind::BuzzerSet
                | Kind::LedSet
                | Kind::Identify
                | Kind::DockLink
        )
    }
}

/// The decoded identifier of an iHEX frame.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Header {
    /// Message kind (and priority).
    pub kind: Kind,
    /// Addressed node, [`NodeId::GATEWAY`] or [`NodeId::BROADCAST`].
    pub dest: NodeId,
    /// Sending node.
    pub src: NodeId,
}

impl Header {
    /// Bit offset of the kind field.
    pub const KIND_SHIFT: u32 = 24;
    /// Bit offset of the destination field.
    pub const DEST_SHIFT: u32 = 12;
    /// Bit offset of the source field.
    pub const SRC_SHIFT: u32 = 0;
    /// Mask of the kind field (after shifting).
    pub const KIND_MASK: u32 = 0x1F;
    /// Mask of a node field (after shifting).
    pub const NODE_MASK: u32 = 0xFFF;

    /// The raw 29-bit identifier.
    pub const fn to_raw(self) -> u32 {
        ((self.kind as u32) << Self::KIND_SHIFT)
            | ((self.dest.get() as u32) << Self::DEST_SHIFT)
            | ((self.src.get() as u32) << Self::SRC_SHIFT)
    }

    /// Splits a raw 29-bit identifier; fails only on an unassigned kind (bits above 28 are ignored).
    pub const fn from_raw(raw: u32) -> Result<Header, DecodeError> {
        let k = ((raw >> Self::KIND_SHIFT) & Self::KIND_MASK) as u8;
        let kind = match Kind::from_raw(k) {
            Some(kind) => kind,
            None => return Err(DecodeError::UnknownKind(k)),
        };
        // Both fields are masked to 12 bits, so `new` cannot fail.
        let dest = NodeId::new(((raw >> Self::DEST_SHIFT) & Self::NODE_MASK) as u16);
        let src = NodeId::new(((raw >> Self::SRC_SHIFT) & Self::NODE_MASK) as u16);
        match (dest, src) {
            (Some(dest), Some(src)) => Ok(Header { kind, dest, src }),
            _ => Err(DecodeError::UnknownKind(k)),
        }
    }

    /// The identifier as an embedded-can extended ID.
    pub fn to_id(self) -> ExtendedId {
        // `to_raw` is at most 29 bits by construction.
        ExtendedId::new(self.to_raw()).unwrap_or(ExtendedId::MAX)
    }

    /// Decodes an embedded-can identifier; standard identifiers are not iHEX frames.
    pub fn from_id(id: Id) -> Result<Header, DecodeError> {
        match id {
            Id::Standard(_) => Err(DecodeError::StandardId),
            Id::Extended(e) => Header::from_raw(e.as_raw()),
        }
    }

    /// Checks that source and destination make sense for the kind:
    /// commands come from the gateway to a node or to all (assignment to all only, a dock link to one
    /// node only), reports go from a node to the gateway, and only an
    /// [`crate::Message::AssignReply`] may come from [`NodeId::UNCONFIGURED`].
    pub const fn check_addresses(self) -> Result<(), DecodeError> {
        let ok = if self.kind.is_command() {
            self.src.get() == NodeId::GATEWAY.get()
                && match self.kind {
                    Kind::AssignSelect | Kind::AssignCommit => {
                        self.dest.get() == NodeId::BROADCAST.get()
                    }
                    // A link names the mobile element on one static element's port: it cannot
                    // be true of every node at once.
                    Kind::DockLink => self.dest.is_sc(),
                    _ => self.dest.is_sc() || self.dest.get() == NodeId::BROADCAST.get(),
                }
        } else {
            self.dest.get() == NodeId::GATEWAY.get()
                && (self.src.is_sc()
                    || (matches!(self.kind, Kind::AssignReply)
                        && self.src.get() == NodeId::UNCONFIGURED.get()))
        };
        if ok {
            Ok(())
        } else {
            Err(DecodeError::Address { kind: self.kind })
        }
    }
}
