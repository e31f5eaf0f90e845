//! Firmware transfer: the messages that carry a signed image (`ihex-image`) from the gateway to
//! many nodes at once, and each node's status.
//!
//! All five kinds sit at the bottom of the priority order (`0x1B..=0x1F`), so commands, docking,
//! health and state traffic always win arbitration over an update. In order:
//!
//! * [`crate::Message::FwBegin`] `[image_id:u32, len:u24, flags]` — start (or resume) a transfer;
//! * [`crate::Message::FwEnd`] `[image_id:u32, action]` — [`FwAction::Commit`] (verify, mark,
//!   reset) or [`FwAction::Abort`];
//! * [`crate::Message::FwQuery`] `[image_id:u32]` — every addressed node answers with its status;
//! * [`crate::Message::FwStatus`] `[phase, reason, first:u16, run:u16, missing:u16]` — a node's
//!   phase, refusal reason, and the first run of frames it still misses;
//! * [`crate::Message::FwData`] `[index:u16, 6 bytes]` — image bytes `6 × index ..`.
//!
//! The image ID is the first 4 bytes (little-endian) of the image's payload SHA-512, which the
//! node checks against the image's header: a begin with the same ID and length resumes a
//! transfer, anything else starts over. The node behaviour is in `ihex-sc-core`; the exchange,
//! with a worked example, in `docs/protocol.md`.

use crate::field::fw_status as f;
use crate::Kind;

/// Image bytes per [`crate::Message::FwData`] frame.
pub const FW_DATA_LEN: usize = 6;
/// The largest image a transfer can address: 65 536 frames of 6 bytes.
pub const FW_MAX_LEN: u32 = (u16::MAX as u32 + 1) * FW_DATA_LEN as u32;
/// The largest `len` a [`crate::Message::FwBegin`] can carry (24 bits).
pub const FW_BEGIN_MAX_LEN: u32 = 0xFF_FFFF;

enum_with_unknown! {
    /// Where a node is in a transfer ([`FwStatus::phase`]).
    pub enum FwPhase {
        /// No transfer of the image asked about.
        Idle = 0 => "idle",
        /// Collecting the signed header (frames 0–31); nothing written yet.
        Header = 1 => "header",
        /// Header accepted; erasing its DFU slot (frames are not taken meanwhile).
        Erasing = 2 => "erasing",
        /// Writing; the status says which frames are still missing.
        Receiving = 3 => "receiving",
        /// Every frame written: waiting for the commit.
        Complete = 4 => "complete",
        /// Commit received: re-reading and hashing the written image.
        Verifying = 5 => "verifying",
        /// Verified and marked for the bootloader: the node resets to swap it in.
        Rebooting = 6 => "rebooting",
        /// Refused (see the reason); the running image is untouched.
        Refused = 7 => "refused",
        /// No transfer; the node runs a new image on trial that has not confirmed itself yet.
        Trial = 8 => "trial",
        /// No transfer; the last update was reverted (its image never confirmed itself).
        Reverted = 9 => "reverted",
    }
}

enum_with_unknown! {
    /// Why a node refused an image ([`FwStatus::reason`]); `None` in every other phase.
    pub enum FwRefusal {
        /// No refusal.
        None = 0 => "none",
        /// The signature does not verify with the node's key.
        BadSignature = 1 => "bad_signature",
        /// Signed with a key the node does not trust.
        UnknownKey = 2 => "unknown_key",
        /// Built for another board.
        WrongBoard = 3 => "wrong_board",
        /// Shorter than its header says.
        Truncated = 4 => "truncated",
        /// The bytes written do not hash to what the header says.
        Corrupted = 5 => "corrupted",
        /// Speaks another major version of the CAN protocol.
        IncompatibleProtocol = 6 => "incompatible_protocol",
        /// Older than the running firmware, and not forced.
        Downgrade = 7 => "downgrade",
        /// Does not fit the node's slot.
        TooLarge = 8 => "too_large",
        /// Not an image this node can take (format, flags, load address), or not the image the
        /// begin announced.
        BadImage = 9 => "bad_image",
        /// Erasing, writing or marking the flash failed.
        FlashError = 10 => "flash_error",
        /// The node runs an image on trial: it must confirm itself (or be reverted) first.
        Unconfirmed = 11 => "unconfirmed",
        /// The node is verifying or installing another image.
        Busy = 12 => "busy",
    }
}

/// What a [`crate::Message::FwEnd`] asks for.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum FwAction {
    /// Verify what was written, mark it for the bootloader and reset.
    Commit,
    /// Drop the transfer.
    Abort,
}

impl FwAction {
    /// Wire value.
    pub const fn to_raw(self) -> u8 {
        match self {
            FwAction::Commit => 1,
            FwAction::Abort => 2,
        }
    }

    /// The name in events and logs.
    pub const fn name(self) -> &'static str {
        match self {
            FwAction::Commit => "commit",
            FwAction::Abort => "abort",
        }
    }

    /// Every action with its wire value and name.
    pub const TABLE: &'static [(u8, &'static str)] = &[
        (FwAction::Commit.to_raw(), FwAction::Commit.name()),
        (FwAction::Abort.to_raw(), FwAction::Abort.name()),
    ];

    /// From the wire value; `None` for values without a meaning.
    pub const fn from_raw(raw: u8) -> Option<FwAction> {
        match raw {
            1 => Some(FwAction::Commit),
            2 => Some(FwAction::Abort),
            _ => None,
        }
    }
}

/// A node's state in a transfer, answering [`crate::Message::FwQuery`] (and sent unasked when
/// the node becomes ready, completes, refuses or is about to reset).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FwStatus {
    /// The phase.
    pub phase: FwPhase,
    /// Why it refused (phase [`FwPhase::Refused`]), else [`FwRefusal::None`].
    pub reason: FwRefusal,
    /// The first frame index still missing (0 when none).
    pub first_missing: u16,
    /// How many frames from `first_missing` on are missing without a gap (0 when none).
    pub run: u16,
    /// How many frames are missing in all (saturating at 65 535).
    pub missing: u16,
}

impl FwStatus {
    /// A status with nothing missing.
    pub const fn phase(phase: FwPhase, reason: FwRefusal) -> Self {
        FwStatus {
            phase,
            reason,
            first_missing: 0,
            run: 0,
            missing: 0,
        }
    }

    pub(crate) fn encode_into(&self, b: &mut [u8; 8]) {
        b[f::PHASE] = self.phase.to_raw();
        b[f::REASON] = self.reason.to_raw();
        b[f::FIRST_MISSING].copy_from_slice(&self.first_missing.to_le_bytes());
        b[f::RUN].copy_from_slice(&self.run.to_le_bytes());
        b[f::MISSING].copy_from_slice(&self.missing.to_le_bytes());
    }

    pub(crate) fn decode(d: &[u8]) -> FwStatus {
        let u16_at = |r: core::ops::Range<usize>| u16::from_le_bytes([d[r.start], d[r.start + 1]]);
        FwStatus {
            phase: FwPhase::from_raw(d[f::PHASE]),
            reason: FwRefusal::from_raw(d[f::REASON]),
            first_missing: u16_at(f::FIRST_MISSING),
            run: u16_at(f::RUN),
            missing: u16_at(f::MISSING),
        }
    }
}

/// Kinds of this family, in priority order.
pub const FW_KINDS: [Kind; 5] = [
    Kind::FwBegin,
    Kind::FwEnd,
    Kind::FwQuery,
    Kind::FwStatus,
    Kind::FwData,
];
