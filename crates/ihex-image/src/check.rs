//! The node's checks, in the order a node can make them while an image arrives in pieces.

use crate::board::{Board, Layout};
use crate::error::ImageError;
use crate::header::{field, Digest, Header, HEADER_BLOCK, HEADER_LEN, SIGNED_LEN};
use crate::key::{PublicKey, SIGNATURE_LEN};
use crate::FirmwareVersion;

/// What a node accepts: its board and slot, the protocol it speaks, what it runs now.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Policy {
    /// The node's board.
    pub board: Board,
    /// Where the node's slot runs a payload ([`Layout::app_start`]).
    pub load_addr: u32,
    /// The largest image (header block + payload) the slot takes ([`Layout::max_image_len`]).
    pub max_image_len: u32,
    /// The node's CAN protocol major.
    pub protocol_major: u8,
    /// The running firmware's version.
    pub running: FirmwareVersion,
    /// Accept an older version than `running` (a forced downgrade).
    pub allow_downgrade: bool,
}

impl Policy {
    /// The policy of a `board` with `layout`, speaking `protocol_major`, running `running`;
    /// downgrades refused.
    pub const fn new(
        board: Board,
        layout: &Layout,
        protocol_major: u8,
        running: FirmwareVersion,
    ) -> Self {
        Policy {
            board,
            load_addr: layout.app_start(),
            max_image_len: layout.max_image_len(),
            protocol_major,
            running,
            allow_downgrade: false,
        }
    }
}

/// Checks the first [`SIGNED_LEN`] bytes of an image: format, key ID, signature, then the policy
/// (board, load address, protocol major, size, downgrade), in that order — so that every reason
/// after the signature is about an authentic header.
pub fn check_signed(bytes: &[u8], key: &PublicKey, policy: &Policy) -> Result<Header, ImageError> {
    let signed = bytes.get(..SIGNED_LEN).ok_or(ImageError::Truncated {
        need: SIGNED_LEN as u32,
        got: bytes.len() as u32,
    })?;
    let header = Header::parse(signed)?;
    if header.key_id != key.id() {
        return Err(ImageError::UnknownKey);
    }
    let mut signature = [0u8; SIGNATURE_LEN];
    signature.copy_from_slice(&signed[field::SIGNATURE]);
    key.verify(&signed[..HEADER_LEN], &signature)?;
    if header.board != policy.board {
        return Err(ImageError::WrongBoard {
            image: header.board,
            node: policy.board,
        });
    }
    if header.load_addr != policy.load_addr {
        return Err(ImageError::WrongAddress {
            image: header.load_addr,
            slot: policy.load_addr,
        });
    }
    if header.protocol.0 != policy.protocol_major {
        return Err(ImageError::IncompatibleProtocol {
            image: header.protocol.0,
            node: policy.protocol_major,
        });
    }
    // `payload_len` is a u32 from the wire: the sum can exceed u32.
    let len = u64::from(header.payload_len) + HEADER_BLOCK as u64;
    if len > u64::from(policy.max_image_len) {
        return Err(ImageError::TooLarge {
            len: u32::try_from(len).unwrap_or(u32::MAX),
            max: policy.max_image_len,
        });
    }
    if header.version < policy.running && !policy.allow_downgrade {
        return Err(ImageError::Downgrade {
            image: header.version,
            running: policy.running,
        });
    }
    Ok(header)
}

/// Compares the length of a whole image file (as announced by a transfer, or as read) with what
/// its header accounts for.
pub fn check_len(header: &Header, len: u32) -> Result<(), ImageError> {
    let need = header.image_len();
    if len < need {
        Err(ImageError::Truncated { need, got: len })
    } else if len > need {
        Err(ImageError::TrailingData { need, got: len })
    } else {
        Ok(())
    }
}

/// SHA-512, fed in pieces (a node re-reading its flash a page at a time).
pub struct Hasher(salty::Sha512);

impl Hasher {
    /// An empty hash.
    pub fn new() -> Self {
        Hasher(salty::Sha512::new())
    }

    /// Adds `data`.
    pub fn update(&mut self, data: &[u8]) {
        self.0.update(data);
    }

    /// The digest of everything added.
    pub fn finish(self) -> Digest {
        Digest(self.0.finalize())
    }

    /// The digest of `data`.
    pub fn digest(data: &[u8]) -> Digest {
        let mut h = Hasher::new();
        h.update(data);
        h.finish()
    }
}

impl Default for Hasher {
    fn default() -> Self {
        Hasher::new()
    }
}

/// What the first [`HEADER_BLOCK`] bytes of a good format-1 image hash to: the signed header
/// followed by zero padding. (A format-2 image's block is checked in two parts: the signed bytes
/// against [`Hasher::digest`] of them, the notes area with [`Header::check_notes`].)
pub fn header_block_digest(signed: &[u8; SIGNED_LEN]) -> Digest {
    let mut h = Hasher::new();
    h.update(signed);
    h.update(&[0u8; HEADER_BLOCK - SIGNED_LEN]);
    h.finish()
}

/// Every check on an image held in memory: [`check_signed`], [`check_len`], zero padding, payload
/// hash.
pub fn verify_image(image: &[u8], key: &PublicKey, policy: &Policy) -> Result<Header, ImageError> {
    let header = check_signed(image, key, policy)?;
    check_len(&header, u32::try_from(image.len()).unwrap_or(u32::MAX))?;
    header.check_notes(&image[SIGNED_LEN..HEADER_BLOCK])?;
    header.check_payload(&Hasher::digest(&image[HEADER_BLOCK..]))?;
    Ok(header)
}
