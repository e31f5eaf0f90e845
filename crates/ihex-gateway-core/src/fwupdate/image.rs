//! The gateway's look at an image before it sends it: a well-formed header, the length it says,
//! a zero-padded header block and a payload that hashes to the signed hash. The signature and
//! the board/protocol/downgrade policy are each node's to check (the node holds the trusted key);
//! this catches a truncated, corrupted or wrong file before it costs the bus anything.

use ihex_image::{check_len, Hasher, Header, ImageError, HEADER_BLOCK, SIGNED_LEN};
use ihex_proto::{FirmwareVersion, FW_DATA_LEN, FW_MAX_LEN};

/// Why an image was not sent.
#[derive(Clone, PartialEq, Eq, Debug, thiserror::Error)]
pub enum FwImageError {
    /// The image's own checks failed.
    #[error("bad image: {0}")]
    Image(ImageError),
    /// Longer than a transfer can address.
    #[error("image of {len} bytes is longer than a transfer can carry ({max} bytes)")]
    TooLong {
        /// The image's length.
        len: usize,
        /// [`FW_MAX_LEN`].
        max: u32,
    },
}

/// A checked image, ready to be cut into frames.
#[derive(Clone, Debug)]
pub struct FwImage {
    bytes: Vec<u8>,
    header: Header,
}

impl FwImage {
    /// Checks `bytes` (see the module docs).
    pub fn check(bytes: Vec<u8>) -> Result<FwImage, FwImageError> {
        let len = u32::try_from(bytes.len())
            .ok()
            .filter(|&l| l <= FW_MAX_LEN)
            .ok_or(FwImageError::TooLong {
                len: bytes.len(),
                max: FW_MAX_LEN,
            })?;
        let header = Header::parse(&bytes).map_err(FwImageError::Image)?;
        check_len(&header, len).map_err(FwImageError::Image)?;
        header
            .check_notes(&bytes[SIGNED_LEN..HEADER_BLOCK])
            .map_err(FwImageError::Image)?;
        header
            .check_payload(&Hasher::digest(&bytes[HEADER_BLOCK..]))
            .map_err(FwImageError::Image)?;
        Ok(FwImage { bytes, header })
    }

    /// The release notes the image carries (header format 2), checked against the signed header.
    pub fn notes(&self) -> Option<&str> {
        self.header.notes_hash?;
        ihex_image::notes_text(&self.bytes[SIGNED_LEN..HEADER_BLOCK]).filter(|n| !n.is_empty())
    }

    /// The signed header.
    pub fn header(&self) -> &Header {
        &self.header
    }

    /// The whole image file.
    pub fn bytes(&self) -> &[u8] {
        &self.bytes
    }

    /// The ID a transfer names the image by ([`Header::image_id`]).
    pub fn image_id(&self) -> u32 {
        self.header.image_id()
    }

    /// The firmware version inside.
    pub fn version(&self) -> FirmwareVersion {
        self.header.version
    }

    /// Length in bytes (header block + payload).
    pub fn len(&self) -> u32 {
        // `check` bounds it by FW_MAX_LEN.
        self.bytes.len() as u32
    }

    /// Never true for a checked image; here for clippy's `len_without_is_empty`.
    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Number of data frames.
    pub fn frames(&self) -> u32 {
        self.len().div_ceil(FW_DATA_LEN as u32)
    }

    /// The bytes of frame `index`, zero-filled past the end.
    pub fn frame(&self, index: u16) -> [u8; FW_DATA_LEN] {
        let mut out = [0u8; FW_DATA_LEN];
        let at = usize::from(index) * FW_DATA_LEN;
        if let Some(rest) = self.bytes.get(at..) {
            let n = rest.len().min(FW_DATA_LEN);
            out[..n].copy_from_slice(&rest[..n]);
        }
        out
    }
}
