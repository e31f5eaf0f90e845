//! Exact bytes: the header layout, the identity record, and the crypto against published vectors.

mod common;

use common::{header_for, key, payload, unhex};
use ihex_image::{
    header_block_digest, Board, Digest, FirmwareVersion, FwInfo, Hasher, Header, KeyId, PublicKey,
    SigningKey, HEADER_BLOCK, SIGNED_LEN,
};

#[test]
fn header_bytes() {
    let h = Header {
        board: Board::NUCLEO_F303RE,
        protocol: (1, 1),
        version: FirmwareVersion::new(2, 10, 255),
        payload_len: 0x0001_2345,
        load_addr: 0x0800_7200,
        key_id: KeyId([0xA0, 0xA1, 0xA2, 0xA3, 0xA4, 0xA5, 0xA6, 0xA7]),
        payload_hash: Digest([0x55; 64]),
        notes_hash: None,
    };
    let b = h.encode();
    assert_eq!(
        b[..32].to_vec(),
        unhex(
            "69 48 58 49  01 00  01 00  01 01  02 0a ff  00  00 00
             45 23 01 00  00 72 00 08  a0 a1 a2 a3 a4 a5 a6 a7"
        )
    );
    assert_eq!(b[32..96], [0x55; 64]);
    assert_eq!(b[96..], [0; 32]);
    assert_eq!(Header::parse(&b), Ok(h));
    assert_eq!(h.image_len(), 512 + 0x0001_2345);
}

#[test]
fn fw_info_bytes() {
    let info = FwInfo {
        board: Board::NUCLEO_F303RE,
        protocol: (1, 0),
        version: FirmwareVersion::new(0, 1, 0),
    };
    let b = info.encode();
    assert_eq!(b.to_vec(), unhex("69 48 46 49 01 00 01 00 00 01 00 00"));
    assert_eq!(FwInfo::parse(&b), Some(info));
    let mut bad = b;
    bad[11] = 1;
    assert_eq!(FwInfo::parse(&bad), None);
    assert_eq!(FwInfo::parse(&b[..11]), None);
}

#[test]
fn test_key_files_agree_and_have_the_documented_id() {
    let k = key();
    assert_eq!(k.public(), ihex_image::test_key::PUBLIC);
    assert_eq!(k.public().id().to_string(), "cc18347fc8cabc5b");
    assert_eq!(
        PublicKey::from_text(ihex_image::test_key::PUBLIC_TEXT),
        Ok(k.public())
    );
    // The key files written by the tool parse back to the same key.
    assert_eq!(
        SigningKey::from_text(&k.secret_text()).unwrap().public(),
        k.public()
    );
    assert_eq!(PublicKey::from_text(&k.public_text()), Ok(k.public()));
}

/// RFC 8032 section 7.1, tests 1–3: salty signs and verifies standard Ed25519.
#[test]
fn rfc8032_vectors() {
    let cases = [
        (
            "9d61b19deffd5a60ba844af492ec2cc44449c5697b326919703bac031cae7f60",
            "d75a980182b10ab7d54bfed3c964073a0ee172f3daa62325af021a68f707511a",
            "",
            "e5564300c360ac729086e2cc806e828a84877f1eb8e5d974d873e065224901555fb8821590a33bacc61e39701cf9b46bd25bf5f0595bbe24655141438e7a100b",
        ),
        (
            "4ccd089b28ff96da9db6c346ec114e0f5b8a319f35aba624da8cf6ed4fb8a6fb",
            "3d4017c3e843895a92b70aa74d1b7ebc9c982ccf2ec4968cc0cd55f12af4660c",
            "72",
            "92a009a9f0d4cab8720e820b5f642540a2b27b5416503f8fb3762223ebdb69da085ac1e43e15996e458f3613d0f11d8c387b2eaeb4302aeeb00d291612bb0c00",
        ),
        (
            "c5aa8df43f9f837bedb7442f31dcb7b166d38535076f094b85ce3a2e0b4458f7",
            "fc51cd8e6218a1a38da47ed00230f0580816ed13ba3303ac5deb911548908025",
            "af82",
            "6291d657deec24024827e69c3abe01a30ce548a284743a445e3680d7db5ac3ac18ff9b538d16f290ae67f760984dc6594a7c15e9716ed28dc027beceea1ec40a",
        ),
    ];
    for (seed, public, msg, sig) in cases {
        let k = SigningKey::from_seed(unhex(seed).try_into().unwrap());
        let public = PublicKey::from_bytes(unhex(public).try_into().unwrap());
        assert_eq!(k.public(), public);
        let sig: [u8; 64] = unhex(sig).try_into().unwrap();
        assert_eq!(k.sign(&unhex(msg)), sig);
        assert_eq!(public.verify(&unhex(msg), &sig), Ok(()));
        let mut bad = sig;
        bad[0] ^= 1;
        assert!(public.verify(&unhex(msg), &bad).is_err());
    }
}

/// FIPS 180-2 "abc", and the hasher fed in pieces equals one pass.
#[test]
fn sha512_vectors() {
    assert_eq!(
        Hasher::digest(b"abc").to_string(),
        "ddaf35a193617abacc417349ae20413112e6fa4e89a97ea20a9eeee64b55d39a\
         2192992a274fc1a836ba3c23a3feebbd454d4423643ce80e2a9ac94fa54ca49f"
    );
    let data = payload(5000);
    let mut h = Hasher::new();
    for piece in data.chunks(333) {
        h.update(piece);
    }
    assert_eq!(h.finish(), Hasher::digest(&data));
    assert_eq!(
        Hasher::digest(b"abc").prefix::<7>(),
        [0xdd, 0xaf, 0x35, 0xa1, 0x93, 0x61, 0x7a]
    );
}

/// The test key's signature of a fixed header is deterministic (Ed25519), so it is pinned here.
#[test]
fn signed_header_block() {
    let p = payload(1000);
    let img = common::sign_raw(&header_for(&p), &p, &key());
    assert_eq!(&img[..128], &header_for(&p).encode()[..]);
    let again = common::sign_raw(&header_for(&p), &p, &key());
    assert_eq!(img, again, "ed25519 signatures are deterministic");
    let signed: [u8; SIGNED_LEN] = img[..SIGNED_LEN].try_into().unwrap();
    assert_eq!(
        header_block_digest(&signed),
        Hasher::digest(&img[..HEADER_BLOCK])
    );
}
