//! The firmware's own identity: what it is built as ([`IHEX_FW_INFO`], read back by the packer),
//! the key it trusts ([`FW_PUBLIC_KEY`], from `IHEX_FW_PUBKEY` at build time), and what it tells
//! the node core about the image it *runs* — the signed header at the start of the active slot
//! ([`crate::update::running_header`]), which moves with the image when the bootloader swaps or
//! reverts.

use defmt::warn;
use ihex_image::board::F303RE;
use ihex_image::{Board, FirmwareVersion, FwInfo, Header, PublicKey};
use ihex_sc_core::{FirmwareIdentity, UpdateConfig};

use crate::update::BootState;

include!(concat!(env!("OUT_DIR"), "/pubkey.rs"));

/// This build's version, from the crate's (checked at compile time).
pub const VERSION: FirmwareVersion = match FirmwareVersion::parse(env!("CARGO_PKG_VERSION")) {
    Some(v) => v,
    None => panic!("the crate version must be MAJOR.MINOR.PATCH with numbers up to 255"),
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

/// What the node reports about its firmware: the running image's version and hash from its
/// header, or — an application flashed without one — this build's version and an all-zero
/// (unknown) hash; on trial while the bootloader says so.
pub fn identity(header: Option<&Header>, boot: BootState) -> FirmwareIdentity {
    let trial = boot == BootState::Trial;
    match header {
        Some(h) => {
            if h.version != VERSION {
                warn!(
                    "image header says {} but this code was built as {}",
                    h.version, VERSION
                );
            }
            FirmwareIdentity {
                version: h.version,
                image_hash: h.payload_hash.prefix::<7>(),
                trial,
            }
        }
        None => FirmwareIdentity {
            version: VERSION,
            image_hash: [0; 7],
            trial,
        },
    }
}

/// What the node core needs to take updates on this board.
pub fn update_config(boot: BootState) -> UpdateConfig {
    UpdateConfig {
        board: Board::NUCLEO_F303RE,
        key: PublicKey::from_bytes(FW_PUBLIC_KEY),
        layout: &F303RE,
        reverted: boot == BootState::Reverted,
    }
}
