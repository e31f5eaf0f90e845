//! The 128-byte image header, its field offsets, and the firmware's own identity record ([`FwInfo`]).
//!
//! Multi-byte integers are little-endian. Format 1 (format 2 differs only where noted):
//!
//! | offset | bytes | field | rule |
//! |-------:|------:|-------|------|
//! | 0  | 4  | `magic` | `b"iHXI"` |
//! | 4  | 1  | `format` | 1, or 2 ([`FORMAT`]) for an image with release notes |
//! | 5  | 1  | reserved | 0 |
//! | 6  | 2  | `board` | [`Board`] the image is built for |
//! | 8  | 1  | `protocol_major` | CAN protocol the firmware speaks |
//! | 9  | 1  | `protocol_minor` | |
//! | 10 | 3  | `version` | firmware major, minor, patch |
//! | 13 | 1  | reserved | 0 |
//! | 14 | 2  | `flags` | none defined in format 1: must be 0 |
//! | 16 | 4  | `payload_len` | bytes after [`HEADER_BLOCK`], ≥ 1 |
//! | 20 | 4  | `load_addr` | where the payload runs: the slot start + [`HEADER_BLOCK`] |
//! | 24 | 8  | `key_id` | [`KeyId`] of the signing key |
//! | 32 | 64 | `payload_hash` | SHA-512 of the payload |
//! | 96 | 32 | reserved (format 1) / `notes_hash` (format 2) | 0 / the first 32 bytes of the SHA-512 of the notes area |
//!
//! Every reserved byte must be zero, so that a later format can give them a meaning an old node
//! refuses instead of misreading.
//!
//! **Release notes** (format 2): UTF-8 text in the notes area, bytes [`field::NOTES`] of the header
//! block (after the signature, [`NOTES_LEN`] bytes, zero-padded), which is all zero in format 1. The
//! signed `notes_hash` authenticates them, so the notes a tool shows are the lab's. An image without
//! notes is written as format 1, which every node reads.

use core::fmt;

use ihex_proto::FirmwareVersion;

use crate::board::Board;
use crate::error::ImageError;
use crate::hex;
use crate::key::{KeyId, SIGNATURE_LEN};

/// Size of the signed header.
pub const HEADER_LEN: usize = 128;
/// Header plus signature: what a node must have before it can check anything.
pub const SIGNED_LEN: usize = HEADER_LEN + SIGNATURE_LEN;
/// Bytes reserved for the header at the start of the slot; the payload (the firmware's vector
/// table first) starts here. 512 keeps the vector table aligned as the Cortex-M4 `VTOR` requires
/// for the F303's 98 vectors.
pub const HEADER_BLOCK: usize = 512;
/// `magic`: the first bytes of every image.
pub const MAGIC: [u8; 4] = *b"iHXI";
/// The newest header format this crate writes and accepts (2: with release notes). An image
/// without release notes is written as format 1, which older nodes accept too.
pub const FORMAT: u8 = 2;
/// The first header format (no release notes), still read and written.
pub const FORMAT_1: u8 = 1;
/// Size of the release notes area (after the signature, up to the end of the header block).
pub const NOTES_LEN: usize = HEADER_BLOCK - SIGNED_LEN;

/// Byte offsets of the header fields (the table in the module docs).
pub mod field {
    use core::ops::Range;

    /// `b"iHXI"`.
    pub const MAGIC: Range<usize> = 0..4;
    /// Header format.
    pub const FORMAT: usize = 4;
    /// `board`, u16 LE.
    pub const BOARD: Range<usize> = 6..8;
    /// Protocol major.
    pub const PROTOCOL_MAJOR: usize = 8;
    /// Protocol minor.
    pub const PROTOCOL_MINOR: usize = 9;
    /// Version major, minor, patch.
    pub const VERSION: Range<usize> = 10..13;
    /// `flags`, u16 LE.
    pub const FLAGS: Range<usize> = 14..16;
    /// `payload_len`, u32 LE.
    pub const PAYLOAD_LEN: Range<usize> = 16..20;
    /// `load_addr`, u32 LE.
    pub const LOAD_ADDR: Range<usize> = 20..24;
    /// `key_id`.
    pub const KEY_ID: Range<usize> = 24..32;
    /// `payload_hash` (SHA-512).
    pub const PAYLOAD_HASH: Range<usize> = 32..96;
    /// Reserved bytes, zero in format 1.
    pub const RESERVED: [Range<usize>; 3] = [5..6, 13..14, 96..128];
    /// Reserved bytes, zero in format 2.
    pub const RESERVED_2: [Range<usize>; 2] = [5..6, 13..14];
    /// `notes_hash` (format 2): the first 32 bytes of the SHA-512 of [`NOTES`].
    pub const NOTES_HASH: Range<usize> = 96..128;
    /// The release notes area of the header block (zero in format 1).
    pub const NOTES: Range<usize> = super::SIGNED_LEN..super::HEADER_BLOCK;
    /// The signature, after the header.
    pub const SIGNATURE: Range<usize> = super::HEADER_LEN..super::SIGNED_LEN;
}

/// A SHA-512 digest.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Digest(pub [u8; 64]);

impl Digest {
    /// The first `N` bytes (what a node reports on the bus: `ImageHash` carries 7).
    pub fn prefix<const N: usize>(&self) -> [u8; N] {
        let mut out = [0u8; N];
        let n = N.min(64);
        out[..n].copy_from_slice(&self.0[..n]);
        out
    }
}

impl fmt::Display for Digest {
    /// Lower-case hex, as `sha512sum` prints it.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        hex::write(f, &self.0)
    }
}

impl fmt::Debug for Digest {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Digest({self})")
    }
}

#[cfg(feature = "defmt")]
impl defmt::Format for Digest {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(f, "{=[u8]:02x}", &self.0[..8])
    }
}

/// The signed header of an image (format [`FORMAT`]).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Header {
    /// The board the image is built for.
    pub board: Board,
    /// The CAN protocol version the firmware speaks (major, minor).
    pub protocol: (u8, u8),
    /// The firmware version.
    pub version: FirmwareVersion,
    /// Payload bytes after the header block.
    pub payload_len: u32,
    /// Address the payload is linked to run at (slot start + [`HEADER_BLOCK`]).
    pub load_addr: u32,
    /// The signing key's ID.
    pub key_id: KeyId,
    /// SHA-512 of the payload.
    pub payload_hash: Digest,
    /// Format 2: the first 32 bytes of the SHA-512 of the release notes area ([`notes_hash`]).
    /// `None`: format 1, no notes.
    pub notes_hash: Option<[u8; 32]>,
}

/// The `notes_hash` of a notes area ([`NOTES_LEN`] bytes).
pub fn notes_hash(area: &[u8]) -> [u8; 32] {
    crate::Hasher::digest(area).prefix::<32>()
}

/// The release notes area for `notes` (UTF-8, zero-padded); `None` when they do not fit.
pub fn notes_area(notes: &str) -> Option<[u8; NOTES_LEN]> {
    let b = notes.as_bytes();
    if b.len() > NOTES_LEN || b.contains(&0) {
        return None;
    }
    let mut area = [0u8; NOTES_LEN];
    area[..b.len()].copy_from_slice(b);
    Some(area)
}

/// The release notes in a notes area: the text up to the first zero byte; `None` if that is not
/// UTF-8.
pub fn notes_text(area: &[u8]) -> Option<&str> {
    let end = area.iter().position(|&b| b == 0).unwrap_or(area.len());
    core::str::from_utf8(&area[..end]).ok()
}

impl Header {
    /// The 128 header bytes (the signed message).
    pub fn encode(&self) -> [u8; HEADER_LEN] {
        let mut b = [0u8; HEADER_LEN];
        b[field::MAGIC].copy_from_slice(&MAGIC);
        b[field::FORMAT] = FORMAT_1;
        if let Some(h) = self.notes_hash {
            b[field::FORMAT] = FORMAT;
            b[field::NOTES_HASH].copy_from_slice(&h);
        }
        b[field::BOARD].copy_from_slice(&self.board.0.to_le_bytes());
        b[field::PROTOCOL_MAJOR] = self.protocol.0;
        b[field::PROTOCOL_MINOR] = self.protocol.1;
        b[field::VERSION].copy_from_slice(&[
            self.version.major,
            self.version.minor,
            self.version.patch,
        ]);
        b[field::PAYLOAD_LEN].copy_from_slice(&self.payload_len.to_le_bytes());
        b[field::LOAD_ADDR].copy_from_slice(&self.load_addr.to_le_bytes());
        b[field::KEY_ID].copy_from_slice(&self.key_id.0);
        b[field::PAYLOAD_HASH].copy_from_slice(&self.payload_hash.0);
        b
    }

    /// Parses the header at the start of `bytes` (at least [`HEADER_LEN`]), checking only the
    /// format: magic, format version, reserved bytes, flags, a non-empty payload. It does **not**
    /// check the signature: use [`crate::check_signed`] for anything a node acts on.
    pub fn parse(bytes: &[u8]) -> Result<Header, ImageError> {
        let b = bytes.get(..HEADER_LEN).ok_or(ImageError::Truncated {
            need: HEADER_LEN as u32,
            got: bytes.len() as u32,
        })?;
        if b[field::MAGIC] != MAGIC {
            return Err(ImageError::BadMagic);
        }
        let format = b[field::FORMAT];
        let reserved: &[core::ops::Range<usize>] = match format {
            FORMAT_1 => &field::RESERVED,
            FORMAT => &field::RESERVED_2,
            other => return Err(ImageError::UnsupportedFormat(other)),
        };
        for r in reserved.iter().cloned() {
            if let Some(i) = b[r.clone()].iter().position(|&x| x != 0) {
                return Err(ImageError::Reserved {
                    offset: (r.start + i) as u16,
                });
            }
        }
        let flags = u16::from_le_bytes([b[14], b[15]]);
        if flags != 0 {
            return Err(ImageError::UnknownFlags(flags));
        }
        let payload_len = u32::from_le_bytes([b[16], b[17], b[18], b[19]]);
        if payload_len == 0 {
            return Err(ImageError::EmptyPayload);
        }
        let mut key_id = [0u8; 8];
        key_id.copy_from_slice(&b[field::KEY_ID]);
        let mut hash = [0u8; 64];
        hash.copy_from_slice(&b[field::PAYLOAD_HASH]);
        Ok(Header {
            board: Board(u16::from_le_bytes([b[6], b[7]])),
            protocol: (b[field::PROTOCOL_MAJOR], b[field::PROTOCOL_MINOR]),
            version: FirmwareVersion::new(b[10], b[11], b[12]),
            payload_len,
            load_addr: u32::from_le_bytes([b[20], b[21], b[22], b[23]]),
            key_id: KeyId(key_id),
            payload_hash: Digest(hash),
            notes_hash: (format == FORMAT).then(|| {
                let mut h = [0u8; 32];
                h.copy_from_slice(&b[field::NOTES_HASH]);
                h
            }),
        })
    }

    /// The image's ID: the first 4 bytes of `payload_hash`, little-endian. A transfer names the
    /// image it carries by it (`ihex_proto::Message::FwBegin`), and a node checks it against the
    /// header it receives.
    pub fn image_id(&self) -> u32 {
        u32::from_le_bytes(self.payload_hash.prefix::<4>())
    }

    /// Length of the whole image file: header block plus payload.
    pub const fn image_len(&self) -> u32 {
        HEADER_BLOCK as u32 + self.payload_len
    }

    /// Checks the header block's notes area (bytes [`field::NOTES`]): zero in format 1, hashing to
    /// `notes_hash` in format 2.
    pub fn check_notes(&self, area: &[u8]) -> Result<(), ImageError> {
        match self.notes_hash {
            None => match area.iter().position(|&x| x != 0) {
                Some(i) => Err(ImageError::Reserved {
                    offset: (SIGNED_LEN + i) as u16,
                }),
                None => Ok(()),
            },
            Some(h) if notes_hash(area) == h => Ok(()),
            Some(_) => Err(ImageError::Corrupted),
        }
    }

    /// Compares a digest of the payload (as re-read from flash) with `payload_hash`.
    pub fn check_payload(&self, digest: &Digest) -> Result<(), ImageError> {
        if *digest == self.payload_hash {
            Ok(())
        } else {
            Err(ImageError::Corrupted)
        }
    }
}

/// What a firmware build says about itself: a 12-byte record the firmware keeps in flash under the
/// symbol `IHEX_FW_INFO`, from which the packer takes the header's board, protocol and version (so
/// an image cannot claim another version than the code inside it was built as).
///
/// | offset | bytes | field |
/// |-------:|------:|-------|
/// | 0 | 4 | `b"iHFI"` |
/// | 4 | 2 | board, u16 LE |
/// | 6 | 2 | protocol major, minor |
/// | 8 | 3 | version major, minor, patch |
/// | 11 | 1 | reserved, 0 |
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct FwInfo {
    /// The board the firmware is built for.
    pub board: Board,
    /// The CAN protocol version it speaks.
    pub protocol: (u8, u8),
    /// Its version.
    pub version: FirmwareVersion,
}

impl FwInfo {
    /// Encoded size.
    pub const LEN: usize = 12;
    /// Marker of the record.
    pub const MAGIC: [u8; 4] = *b"iHFI";
    /// The symbol name the firmware stores the record under.
    pub const SYMBOL: &'static str = "IHEX_FW_INFO";

    /// The 12 bytes (usable in a `static` initialiser).
    pub const fn encode(&self) -> [u8; FwInfo::LEN] {
        let board = self.board.0.to_le_bytes();
        [
            b'i',
            b'H',
            b'F',
            b'I',
            board[0],
            board[1],
            self.protocol.0,
            self.protocol.1,
            self.version.major,
            self.version.minor,
            self.version.patch,
            0,
        ]
    }

    /// Parses the record; `None` if it is not one.
    pub fn parse(b: &[u8]) -> Option<FwInfo> {
        if b.len() != FwInfo::LEN || b[..4] != FwInfo::MAGIC || b[11] != 0 {
            return None;
        }
        Some(FwInfo {
            board: Board(u16::from_le_bytes([b[4], b[5]])),
            protocol: (b[6], b[7]),
            version: FirmwareVersion::new(b[8], b[9], b[10]),
        })
    }
}
