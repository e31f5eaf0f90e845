//! The firmware's own image: what it is built as ([`IHEX_FW_INFO`], read back by the packer), the
//! key it trusts ([`FW_PUBLIC_KEY`], from `IHEX_FW_PUBKEY` at build time), and the identity of the
//! image it runs — the signed header at the start of the active slot, which moves with the image
//! when the bootloader swaps or reverts.

use embassy_stm32::flash::{Blocking, Flash, FLASH_BASE};
use ihex_image::board::F303RE;
use ihex_image::{Board, FwInfo, Header, Version, HEADER_LEN};

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

/// The header in front of the running application; `None` when the slot holds none (an
/// application flashed directly with probe-rs: its first page, header included, was erased).
pub fn running_header(flash: &mut Flash<'_, Blocking>) -> Option<Header> {
    let mut b = [0u8; HEADER_LEN];
    flash
        .blocking_read(F303RE.active.start - FLASH_BASE as u32, &mut b)
        .ok()?;
    Header::parse(&b).ok()
}

/// The build record as stored (read through a volatile load so the linker keeps the symbol).
pub fn stored_info() -> Option<FwInfo> {
    // SAFETY: a plain read of an initialised static.
    let b = unsafe { core::ptr::read_volatile(&IHEX_FW_INFO) };
    FwInfo::parse(&b)
}
