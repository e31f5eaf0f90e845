//! Simulated firmware: the images `sim-node`'s boards accept as their firmware (board `SIM`), and
//! what their payload tells the simulator — whether the image confirms itself after an update.
//! Here, beside the image format, so that the simulator and the lab's tools (`ihex-provision fw
//! demo-image`) make the same payload.

use crate::{pack_with_notes, Board, FirmwareVersion, SigningKey, ToolError};
use ihex_proto::PROTOCOL_VERSION;

/// What a simulated image's payload says about the simulated firmware.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct SimFirmware {
    /// It passes its self-test, so it confirms itself after an update once it has joined the bus.
    /// `false` makes an image that the node resets away from at once, and the bootloader reverts.
    pub confirms: bool,
}

impl SimFirmware {
    const MAGIC: &'static [u8; 8] = b"iHEX-SIM";
    const LEN: usize = 12;

    /// The payload: magic, the flags, the version, then filler up to `len` bytes (at least 12).
    /// Deterministic: a version's payload (and so its image hash) is the same on every board, and
    /// differs from every other version's, as real firmware builds do.
    pub fn payload(&self, version: FirmwareVersion, len: usize) -> Vec<u8> {
        let mut p = SimFirmware::MAGIC.to_vec();
        p.push(u8::from(self.confirms));
        p.extend_from_slice(&[version.major, version.minor, version.patch]);
        let mut x = u32::from_le_bytes([version.major, version.minor, version.patch, 0x5A]);
        while p.len() < len.max(SimFirmware::LEN) {
            x = x.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            p.push((x >> 24) as u8);
        }
        p
    }

    /// Reads a payload; `None` if it is not a simulated firmware.
    pub fn parse(payload: &[u8]) -> Option<SimFirmware> {
        if payload.len() < SimFirmware::LEN || &payload[..8] != SimFirmware::MAGIC || payload[8] > 1
        {
            return None;
        }
        Some(SimFirmware {
            confirms: payload[8] == 1,
        })
    }
}

/// The payload size of a simulated image when none is given: about what the real firmware packs to.
pub const SIM_PAYLOAD_LEN: usize = 50 * 1024;

/// A simulated image: `firmware` as version `version`, `payload_len` bytes, signed with `key`.
pub fn sim_image(
    version: FirmwareVersion,
    firmware: SimFirmware,
    payload_len: usize,
    key: &SigningKey,
) -> Result<Vec<u8>, ToolError> {
    sim_image_with_notes(version, firmware, payload_len, "", key)
}

/// [`sim_image`] carrying release notes (header format 2 when `notes` is not empty).
pub fn sim_image_with_notes(
    version: FirmwareVersion,
    firmware: SimFirmware,
    payload_len: usize,
    notes: &str,
    key: &SigningKey,
) -> Result<Vec<u8>, ToolError> {
    pack_with_notes(
        Board::SIM,
        PROTOCOL_VERSION,
        version,
        &firmware.payload(version, payload_len),
        notes,
        key,
    )
}
