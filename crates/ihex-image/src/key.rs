//! The verifying side of ed25519 (salty): public keys, their short IDs, signature checks.

use core::fmt;

use crate::error::{ImageError, KeyTextError};
use crate::hex;

/// Size of an ed25519 signature.
pub const SIGNATURE_LEN: usize = 64;

/// An ed25519 public key: what a node trusts.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct PublicKey([u8; 32]);

/// The first 8 bytes of the SHA-512 of a public key: names the key in a header, so that a node can
/// tell "signed by a key I do not trust" from "signature broken".
#[derive(Clone, Copy, PartialEq, Eq, Hash, Default)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct KeyId(pub [u8; 8]);

impl PublicKey {
    /// The key from its 32 bytes (checked when used: an invalid point verifies nothing).
    pub const fn from_bytes(bytes: [u8; 32]) -> Self {
        PublicKey(bytes)
    }

    /// Parses a public key file's text (`#` comments, one line of 64 hex digits) and checks that
    /// it is a valid curve point.
    pub fn from_text(text: &str) -> Result<Self, KeyTextError> {
        let key = PublicKey(hex::parse_key_text(text)?);
        salty::PublicKey::try_from(&key.0).map_err(|_| KeyTextError::NotAPoint)?;
        Ok(key)
    }

    /// The 32 bytes.
    pub const fn to_bytes(&self) -> [u8; 32] {
        self.0
    }

    /// The key's ID.
    pub fn id(&self) -> KeyId {
        let digest = salty::Sha512::new().updated(&self.0).finalize();
        let mut id = [0u8; 8];
        id.copy_from_slice(&digest[..8]);
        KeyId(id)
    }

    /// Checks `signature` over `message`.
    pub fn verify(
        &self,
        message: &[u8],
        signature: &[u8; SIGNATURE_LEN],
    ) -> Result<(), ImageError> {
        let key = salty::PublicKey::try_from(&self.0).map_err(|_| ImageError::BadSignature)?;
        key.verify(message, &salty::Signature::from(signature))
            .map_err(|_| ImageError::BadSignature)
    }
}

impl fmt::Display for PublicKey {
    /// 64 hex digits, the key file's line.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        hex::write(f, &self.0)
    }
}

impl fmt::Debug for PublicKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "PublicKey({self})")
    }
}

#[cfg(feature = "defmt")]
impl defmt::Format for PublicKey {
    fn format(&self, f: defmt::Formatter) {
        defmt::write!(f, "{=[u8]:02x}", &self.0[..])
    }
}

impl fmt::Display for KeyId {
    /// 16 hex digits.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        hex::write(f, &self.0)
    }
}

impl fmt::Debug for KeyId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "KeyId({self})")
    }
}
