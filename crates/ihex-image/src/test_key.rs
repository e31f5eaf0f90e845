//! **The test key** — for tests and the simulator only; its secret half is committed
//! (`crates/ihex-image/test-key/`), so anybody can sign anything with it.
//!
//! A firmware built with this public key (the default when `IHEX_FW_PUBKEY` is not set, with a
//! build warning) accepts images from anyone who has this repository. A lab generates its own key
//! pair (`ihex-provision fw keygen`), keeps the secret off the bench, and builds its firmware with
//! `IHEX_FW_PUBKEY=path/to/lab.pub` (see `docs/firmware-update.md`).

use crate::hex::parse_key_text;
use crate::key::PublicKey;

/// The secret key file's text.
pub const SECRET_TEXT: &str = include_str!("../test-key/ihex-test-key.secret");
/// The public key file's text.
pub const PUBLIC_TEXT: &str = include_str!("../test-key/ihex-test-key.pub");

/// The secret seed (32 bytes).
pub const SEED: [u8; 32] = match parse_key_text(SECRET_TEXT) {
    Ok(k) => k,
    Err(_) => panic!("test-key/ihex-test-key.secret is not a key file"),
};

/// The public key.
pub const PUBLIC: PublicKey = match parse_key_text(PUBLIC_TEXT) {
    Ok(k) => PublicKey::from_bytes(k),
    Err(_) => panic!("test-key/ihex-test-key.pub is not a key file"),
};
