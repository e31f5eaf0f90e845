//! The node configuration record kept in the last flash page: layout, encoding and validation.
//!
//! Pure code (no HAL): the flash access itself is in [`crate::config`]. The record is 16 bytes,
//! a multiple of the F303's flash write unit:
//!
//! | bytes  | field                                  |
//! |--------|----------------------------------------|
//! | 0..4   | magic `b"iHEX"`                        |
//! | 4      | layout version ([`VERSION`])           |
//! | 5      | role the ID was given under (0 static, 1 mobile) |
//! | 6..8   | node ID, u16 little-endian             |
//! | 8..12  | reserved, zero                         |
//! | 12..16 | CRC-32 (ISO-HDLC) of bytes 0..12, LE   |
//!
//! An erased page (all `0xFF`) is a factory-fresh board: no ID, the node stays unconfigured.

use ihex_proto::{BootRole, NodeId};

/// Encoded size in bytes.
pub const LEN: usize = 16;
/// Record marker.
pub const MAGIC: [u8; 4] = *b"iHEX";
/// Layout version; bump on any layout change.
pub const VERSION: u8 = 1;

/// What the board remembers across resets.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Record {
    /// The stored node ID (`0x001..=0xFFD`).
    pub node_id: NodeId,
    /// The role jumper's reading when the ID was stored (diagnostics: a moved jumper is logged).
    pub role: BootRole,
}

/// Why stored bytes are not a valid record.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum RecordError {
    /// The page is erased: a factory-fresh board.
    Erased,
    /// Something else than a record is stored there.
    BadMagic,
    /// A record of an unknown layout version.
    BadVersion(u8),
    /// The checksum does not match (interrupted write, worn flash).
    BadCrc,
    /// The role byte is neither 0 nor 1.
    BadRole(u8),
    /// The ID is not an assignable sub-controller ID.
    BadId(u16),
}

impl Record {
    /// The 16 bytes to write.
    pub fn encode(&self) -> [u8; LEN] {
        let mut b = [0u8; LEN];
        b[0..4].copy_from_slice(&MAGIC);
        b[4] = VERSION;
        b[5] = match self.role {
            BootRole::Static => 0,
            BootRole::Mobile => 1,
        };
        b[6..8].copy_from_slice(&self.node_id.get().to_le_bytes());
        let crc = crc32(&b[..12]);
        b[12..16].copy_from_slice(&crc.to_le_bytes());
        b
    }

    /// Parses and validates stored bytes.
    pub fn decode(b: &[u8; LEN]) -> Result<Record, RecordError> {
        if b.iter().all(|&x| x == 0xFF) {
            return Err(RecordError::Erased);
        }
        if b[0..4] != MAGIC {
            return Err(RecordError::BadMagic);
        }
        if b[4] != VERSION {
            return Err(RecordError::BadVersion(b[4]));
        }
        if crc32(&b[..12]).to_le_bytes() != b[12..16] {
            return Err(RecordError::BadCrc);
        }
        let role = match b[5] {
            0 => BootRole::Static,
            1 => BootRole::Mobile,
            r => return Err(RecordError::BadRole(r)),
        };
        let raw = u16::from_le_bytes([b[6], b[7]]);
        let node_id = NodeId::new_sc(raw).ok_or(RecordError::BadId(raw))?;
        Ok(Record { node_id, role })
    }
}

/// CRC-32/ISO-HDLC (the zlib/Ethernet CRC), bitwise: 16 bytes once per boot do not need a table.
pub fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &byte in data {
        crc ^= byte as u32;
        for _ in 0..8 {
            let lsb = crc & 1;
            crc >>= 1;
            if lsb != 0 {
                crc ^= 0xEDB8_8320;
            }
        }
    }
    !crc
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(id: u16, role: BootRole) -> Record {
        Record {
            node_id: NodeId::new_sc(id).unwrap(),
            role,
        }
    }

    #[test]
    fn crc_check_value() {
        // The catalogue check value of CRC-32/ISO-HDLC.
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }

    #[test]
    fn golden_bytes() {
        let b = rec(0x111, BootRole::Static).encode();
        assert_eq!(
            &b[..12],
            &[b'i', b'H', b'E', b'X', 1, 0, 0x11, 0x01, 0, 0, 0, 0]
        );
        assert_eq!(
            u32::from_le_bytes([b[12], b[13], b[14], b[15]]),
            crc32(&b[..12])
        );
    }

    #[test]
    fn round_trip_every_id_and_role() {
        for id in 0x001..=0xFFD {
            for role in [BootRole::Static, BootRole::Mobile] {
                let r = rec(id, role);
                assert_eq!(Record::decode(&r.encode()), Ok(r));
            }
        }
    }

    #[test]
    fn erased_page_is_factory_fresh() {
        assert_eq!(Record::decode(&[0xFF; LEN]), Err(RecordError::Erased));
    }

    #[test]
    fn every_single_bit_flip_is_rejected() {
        let good = rec(0x2AB, BootRole::Mobile).encode();
        for i in 0..LEN * 8 {
            let mut b = good;
            b[i / 8] ^= 1 << (i % 8);
            assert!(Record::decode(&b).is_err(), "bit {i} flipped was accepted");
        }
    }

    #[test]
    fn reserved_ids_and_bad_roles_are_rejected_even_with_a_good_crc() {
        for (raw, role_byte, want) in [
            (0x000u16, 0u8, RecordError::BadId(0x000)),
            (0xFFE, 0, RecordError::BadId(0xFFE)),
            (0xFFF, 1, RecordError::BadId(0xFFF)),
            (0x123, 7, RecordError::BadRole(7)),
        ] {
            let mut b = [0u8; LEN];
            b[0..4].copy_from_slice(&MAGIC);
            b[4] = VERSION;
            b[5] = role_byte;
            b[6..8].copy_from_slice(&raw.to_le_bytes());
            let crc = crc32(&b[..12]);
            b[12..16].copy_from_slice(&crc.to_le_bytes());
            assert_eq!(Record::decode(&b), Err(want));
        }
    }

    #[test]
    fn other_versions_and_garbage_are_rejected() {
        let mut b = rec(0x001, BootRole::Static).encode();
        b[4] = 2;
        assert_eq!(Record::decode(&b), Err(RecordError::BadVersion(2)));
        assert_eq!(Record::decode(&[0u8; LEN]), Err(RecordError::BadMagic));
    }
}
