//! Linker set-up for QEMU's mps2-an386 (Cortex-M4): code in SSRAM1 at 0, data in SSRAM2 at 0x2000_0000.
//! Also packs an update image on the host (test key), which the binary verifies on the Cortex-M4.

use std::{env, fs, path::PathBuf};

fn main() {
    let out = PathBuf::from(env::var("OUT_DIR").unwrap());
    fs::write(
        out.join("memory.x"),
        "MEMORY\n{\n  FLASH : ORIGIN = 0x00000000, LENGTH = 4M\n  RAM : ORIGIN = 0x20000000, LENGTH = 4M\n}\n",
    )
    .unwrap();
    let payload: Vec<u8> = (0..4000u32).map(|i| (i * 31 + 7) as u8).collect();
    let image = ihex_image::pack(
        ihex_image::Board::NUCLEO_F303RE,
        (1, 0),
        ihex_image::FirmwareVersion::new(1, 2, 3),
        &payload,
        &ihex_image::SigningKey::test_key(),
    )
    .unwrap();
    fs::write(out.join("test-image.img"), image).unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
    println!("cargo:rerun-if-changed=build.rs");
}
