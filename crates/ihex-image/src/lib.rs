//! The iHEX firmware image: a signed header in front of the firmware, and every check a node makes
//! before it lets an image near its boot slot.
//!
//! An **image file** is exactly what ends up in a node's ACTIVE slot, byte for byte:
//!
//! | offset          | bytes | content |
//! |-----------------|------:|---------|
//! | `0`             | 128   | [`Header`]: magic, format, board, protocol, version, payload length, load address, key ID, payload SHA-512 |
//! | `128`           | 64    | ed25519 signature over bytes `0..128` |
//! | `192`           | 320   | zero; in format 2, the release notes (UTF-8, zero-padded), authenticated by the header's `notes_hash` |
//! | [`HEADER_BLOCK`] (512) | `payload_len` | the payload: the firmware as a flat binary, linked to run at `load_address` = slot start + 512 |
//!
//! The signature covers the header, and the header holds the payload's SHA-512, so one signature
//! check on 128 bytes plus one hash over the payload authenticate the whole image. The header stays
//! in the slot when the bootloader swaps images, so a running firmware reads its own identity
//! (version, image hash) from the start of its slot, and a reverted node shows the old identity by
//! construction. The field table is in [`header`]; the format is described in
//! `docs/firmware-update.md`.
//!
//! # For the node (no_std)
//!
//! The node receives an image in pieces and cannot hold it in RAM, so the check is incremental:
//!
//! 1. once the first [`SIGNED_LEN`] bytes are in, [`check_signed`] parses the header, checks the
//!    key ID and signature, then the [`Policy`] (board, load address, protocol major, size,
//!    downgrade) — each refusal is one [`ImageError`];
//! 2. [`check_len`] compares the transfer length with the header's;
//! 3. after the transfer, the node re-reads its DFU flash through a [`Hasher`]: the first
//!    [`HEADER_BLOCK`] bytes must hash to [`header_block_digest`] of the checked header (catches a
//!    flash write that went wrong and non-zero padding), the payload to the header's
//!    `payload_hash` ([`Header::check_payload`]).
//!
//! [`verify_image`] does all of it on an image held in memory (tools, simulator).
//!
//! # For tools (`std` feature)
//!
//! [`SigningKey`] (generate, load, save, sign), [`pack`] (sign a payload into an image file),
//! [`pack_elf`] (the same from a firmware ELF: [`elf::flatten`] lays its loadable segments out as a
//! flat binary at the slot's load address, [`elf::fw_info`] reads the firmware's own [`FwInfo`] for
//! the header), [`Inspection`] (what an image says about itself, and whether it verifies).
//!
//! The committed [`test_key`] signs images for tests and the simulator only.
#![cfg_attr(not(any(test, feature = "std")), no_std)]
#![warn(missing_docs)]
#![forbid(unsafe_code)]

pub mod board;
mod check;
mod error;
pub mod header;
mod hex;
mod key;
pub mod test_key;

#[cfg(feature = "std")]
pub mod elf;
#[cfg(feature = "std")]
pub mod sim;
#[cfg(feature = "std")]
mod tool;

pub use board::{Board, Layout, Region};
pub use check::{check_len, check_signed, header_block_digest, verify_image, Hasher, Policy};
pub use error::{ImageError, KeyTextError};
pub use header::{
    notes_area, notes_hash, notes_text, Digest, FwInfo, Header, FORMAT, FORMAT_1, HEADER_BLOCK,
    HEADER_LEN, MAGIC, NOTES_LEN, SIGNED_LEN,
};
pub use key::{KeyId, PublicKey, SIGNATURE_LEN};

/// The firmware version type (the protocol's: `StateReport::Firmware` carries it).
pub use ihex_proto::FirmwareVersion;

#[cfg(feature = "std")]
pub use tool::{
    load_public, pack, pack_elf, pack_elf_with_notes, pack_with_notes, Inspection, PackOverrides,
    SigningKey, ToolError,
};
