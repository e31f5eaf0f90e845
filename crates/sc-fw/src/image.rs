//! The firmware's own identity: what it is built as ([`IHEX_FW_INFO`], read back by the packer) and
//! the key it trusts ([`FW_PUBLIC_KEY`], from `IHEX_FW_PUBKEY` at build time). The identity of the
//! image it *runs* is the signed header at the start of the active slot
//! ([`crate::update::running_header`]), which moves with the image when the bootloader swaps or
//! reverts.

use ihex_image::{Board, FwInfo, Version};

include!(concat!(env!("OUT_DIR"), "/pubkey.rs"));

/// This build's version (the crate version).
pub const VERSION: Version = match Version::from_decimal(
    env!("CARGO_PKG_VERSION_MAJOR"),
    env!("CARGO_PKG_VERSION_MINOR"),
    env!("CARGO_PKG_VERSION_PATCH"),
) {
    Some(v) => v,
    None => panic!("the crate version must be MAJOR.MINOR.PATCH with parts 0..=255"),
};

/// What this build is: board, protocol, version.
pub const INFO: FwInfo = FwInfo {
    board: Board::NUCLEO_F303RE,
    protocol: ihex_proto::PROTOCOL_VERSION,
    version: VERSION,
};

/// [`INFO`] in flash under a fixed symbol, where `ihex-provision fw pack` reads it from the ELF
/// (so an image's header always tells the version of the code inside it).
#[used]
#[no_mangle]
pub static IHEX_FW_INFO: [u8; FwInfo::LEN] = INFO.encode();

/// The build record as stored (read through a volatile load so the linker keeps the symbol).
pub fn stored_info() -> Option<FwInfo> {
    // SAFETY: a plain read of an initialised static.
    let b = unsafe { core::ptr::read_volatile(&IHEX_FW_INFO) };
    FwInfo::parse(&b)
}
