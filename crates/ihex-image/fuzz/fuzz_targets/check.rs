//! Fuzz target `check`: arbitrary bytes as an image (header parse, the node's checks, whole-image
//! verification, inspection) and as a firmware ELF (flattening, the identity record). Nothing may
//! panic; a header that parses must re-encode to its bytes; a packed image must verify.
//!
//! Input layout: byte 0 picks what to do with the rest (even: image, odd: ELF).
#![no_main]

use ihex_image::board::F303RE;
use ihex_image::{
    check_signed, elf, test_key, verify_image, Board, FirmwareVersion, Header, Inspection, Policy,
    HEADER_LEN,
};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|input: &[u8]| {
    let Some((&mode, data)) = input.split_first() else {
        return;
    };
    if mode % 2 == 0 {
        let mut policy = Policy::new(
            Board::NUCLEO_F303RE,
            &F303RE,
            1,
            FirmwareVersion::new(1, 0, 0),
        );
        policy.allow_downgrade = mode & 2 != 0;
        if let Ok(h) = Header::parse(data) {
            assert_eq!(&h.encode()[..], &data[..HEADER_LEN]);
        }
        let _ = check_signed(data, &test_key::PUBLIC, &policy);
        let _ = verify_image(data, &test_key::PUBLIC, &policy);
        let _ = Inspection::of(data, Some(&test_key::PUBLIC));
    } else {
        let _ = elf::fw_info(data);
        if let Ok(flat) = elf::flatten(data, F303RE.app_start(), F303RE.max_payload_len()) {
            assert!(flat.bytes.len() <= F303RE.max_payload_len() as usize);
        }
    }
});
