//! Shared by the image tests: hex, a node policy, images signed with the test key.
#![allow(dead_code)]

use ihex_image::{
    board::F303RE, pack, Board, FirmwareVersion, Hasher, Header, Policy, SigningKey, HEADER_BLOCK,
};

pub fn unhex(s: &str) -> Vec<u8> {
    let s: String = s.split_whitespace().collect();
    (0..s.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
        .collect()
}

pub fn key() -> SigningKey {
    SigningKey::test_key()
}

/// A node on the F303RE running 1.2.3, protocol 1.
pub fn policy() -> Policy {
    Policy::new(
        Board::NUCLEO_F303RE,
        &F303RE,
        1,
        FirmwareVersion::new(1, 2, 3),
    )
}

/// A deterministic payload of `len` bytes.
pub fn payload(len: usize) -> Vec<u8> {
    (0..len).map(|i| (i * 7 + 3) as u8).collect()
}

/// A good image of version `v` with a 1000-byte payload.
pub fn image(v: FirmwareVersion) -> Vec<u8> {
    pack(Board::NUCLEO_F303RE, (1, 0), v, &payload(1000), &key()).unwrap()
}

/// Signs any header (also ones `pack` would not make) in front of `payload`.
pub fn sign_raw(header: &Header, payload: &[u8], key: &SigningKey) -> Vec<u8> {
    let h = header.encode();
    let mut img = h.to_vec();
    img.extend_from_slice(&key.sign(&h));
    img.resize(HEADER_BLOCK, 0);
    img.extend_from_slice(payload);
    img
}

/// The header `pack` would write for `payload`, to modify before [`sign_raw`].
pub fn header_for(payload: &[u8]) -> Header {
    Header {
        board: Board::NUCLEO_F303RE,
        protocol: (1, 0),
        version: FirmwareVersion::new(1, 2, 3),
        payload_len: payload.len() as u32,
        load_addr: F303RE.app_start(),
        key_id: key().public().id(),
        payload_hash: Hasher::digest(payload),
        notes_hash: None,
    }
}
