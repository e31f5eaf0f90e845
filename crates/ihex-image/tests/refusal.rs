//! Every reason a node refuses an image, each caused on purpose, and the good cases next to them.

mod common;

use common::{header_for, image, key, payload, policy, sign_raw};
use ihex_image::{
    board::F303RE, check_len, check_signed, pack, verify_image, Board, FirmwareVersion, Hasher,
    ImageError, Inspection, SigningKey, HEADER_BLOCK, SIGNED_LEN,
};

const V: FirmwareVersion = FirmwareVersion::new(1, 2, 3);

#[test]
fn a_good_image_verifies_and_inspects_clean() {
    let img = image(V);
    let h = verify_image(&img, &key().public(), &policy()).unwrap();
    assert_eq!(h.version, V);
    assert_eq!(h.payload_len, 1000);
    assert_eq!(h.load_addr, 0x0800_7200);
    let i = Inspection::of(&img, Some(&key().public())).unwrap();
    assert!(i.is_good(), "{i}");
    assert!(i.to_string().contains("signature     ok"));
}

#[test]
fn truncated() {
    let img = image(V);
    let k = key().public();
    let cut = &img[..img.len() - 1];
    assert_eq!(
        verify_image(cut, &k, &policy()),
        Err(ImageError::Truncated {
            need: 1512,
            got: 1511
        })
    );
    assert_eq!(
        check_signed(&img[..SIGNED_LEN - 1], &k, &policy()),
        Err(ImageError::Truncated {
            need: 192,
            got: 191
        })
    );
    // The node only knows the announced length: the header tells it is short.
    let h = check_signed(&img, &k, &policy()).unwrap();
    assert_eq!(
        check_len(&h, 1000),
        Err(ImageError::Truncated {
            need: 1512,
            got: 1000
        })
    );
    assert_eq!(
        check_len(&h, 1513),
        Err(ImageError::TrailingData {
            need: 1512,
            got: 1513
        })
    );
    let i = Inspection::of(cut, Some(&k)).unwrap();
    assert!(!i.is_good() && !i.payload_ok);
}

#[test]
fn corrupted_payload_or_padding() {
    let k = key().public();
    for at in [HEADER_BLOCK, HEADER_BLOCK + 500, HEADER_BLOCK + 999] {
        let mut img = image(V);
        img[at] ^= 0x10;
        assert_eq!(
            verify_image(&img, &k, &policy()),
            Err(ImageError::Corrupted)
        );
    }
    let mut img = image(V);
    img[300] = 1;
    assert_eq!(
        verify_image(&img, &k, &policy()),
        Err(ImageError::Reserved { offset: 300 })
    );
}

#[test]
fn bad_signature_and_unknown_key() {
    let k = key().public();
    // Any change of a signed header byte other than the key ID breaks the signature.
    let mut img = image(V);
    img[10] = 9; // version major
    assert_eq!(
        verify_image(&img, &k, &policy()),
        Err(ImageError::BadSignature)
    );
    let mut img = image(V);
    img[150] ^= 0x01; // in the signature
    assert_eq!(
        verify_image(&img, &k, &policy()),
        Err(ImageError::BadSignature)
    );
    // Signed with another key (its own ID in the header) or claiming the node's key ID.
    let other = SigningKey::from_seed([7; 32]);
    let p = payload(1000);
    let img = pack(Board::NUCLEO_F303RE, (1, 0), V, &p, &other).unwrap();
    assert_eq!(
        verify_image(&img, &k, &policy()),
        Err(ImageError::UnknownKey)
    );
    let forged = sign_raw(&header_for(&p), &p, &other);
    assert_eq!(
        verify_image(&forged, &k, &policy()),
        Err(ImageError::BadSignature)
    );
}

#[test]
fn every_bit_flip_in_the_signed_header_is_refused() {
    let img = image(V);
    let k = key().public();
    for bit in 0..SIGNED_LEN * 8 {
        let mut b = img.clone();
        b[bit / 8] ^= 1 << (bit % 8);
        assert!(
            check_signed(&b, &k, &policy()).is_err(),
            "bit {bit} flipped was accepted"
        );
    }
}

#[test]
fn wrong_board_and_wrong_address() {
    let k = key().public();
    let p = payload(100);
    let img = pack(Board::SIM, (1, 0), V, &p, &key()).unwrap();
    assert_eq!(
        verify_image(&img, &k, &policy()),
        Err(ImageError::WrongBoard {
            image: Board::SIM,
            node: Board::NUCLEO_F303RE
        })
    );
    let mut h = header_for(&p);
    h.load_addr = F303RE.active.start;
    assert_eq!(
        verify_image(&sign_raw(&h, &p, &key()), &k, &policy()),
        Err(ImageError::WrongAddress {
            image: 0x0800_7000,
            slot: 0x0800_7200
        })
    );
}

#[test]
fn incompatible_protocol() {
    let p = payload(100);
    let img = pack(Board::NUCLEO_F303RE, (2, 0), V, &p, &key()).unwrap();
    assert_eq!(
        verify_image(&img, &key().public(), &policy()),
        Err(ImageError::IncompatibleProtocol { image: 2, node: 1 })
    );
    // A newer minor of the same major is fine.
    let img = pack(Board::NUCLEO_F303RE, (1, 7), V, &p, &key()).unwrap();
    assert!(verify_image(&img, &key().public(), &policy()).is_ok());
}

#[test]
fn too_large() {
    let max = F303RE.max_payload_len() as usize;
    assert!(pack(Board::NUCLEO_F303RE, (1, 0), V, &payload(max + 1), &key()).is_err());
    assert!(pack(Board::NUCLEO_F303RE, (1, 0), V, &payload(0), &key()).is_err());
    let img = pack(Board::NUCLEO_F303RE, (1, 0), V, &payload(max), &key()).unwrap();
    assert!(verify_image(&img, &key().public(), &policy()).is_ok());
    // A header announcing more than the slot holds (signed by hand: pack refuses to).
    let p = payload(10);
    let mut h = header_for(&p);
    h.payload_len = max as u32 + 1;
    h.payload_hash = Hasher::digest(&p);
    assert_eq!(
        check_signed(&sign_raw(&h, &p, &key()), &key().public(), &policy()),
        Err(ImageError::TooLarge {
            len: 128 * 1024 + 1,
            max: 128 * 1024
        })
    );
    h.payload_len = u32::MAX;
    assert!(matches!(
        check_signed(&sign_raw(&h, &p, &key()), &key().public(), &policy()),
        Err(ImageError::TooLarge { .. })
    ));
}

#[test]
fn downgrade_unless_forced() {
    let k = key().public();
    let older = image(FirmwareVersion::new(1, 2, 2));
    assert_eq!(
        verify_image(&older, &k, &policy()),
        Err(ImageError::Downgrade {
            image: FirmwareVersion::new(1, 2, 2),
            running: V
        })
    );
    let mut forced = policy();
    forced.allow_downgrade = true;
    assert!(verify_image(&older, &k, &forced).is_ok());
    // The same version (a re-install) and newer ones are no downgrade.
    assert!(verify_image(&image(V), &k, &policy()).is_ok());
    assert!(verify_image(&image(FirmwareVersion::new(1, 3, 0)), &k, &policy()).is_ok());
}

#[test]
fn malformed_headers() {
    let k = key().public();
    let good = image(V);
    let mut b = good.clone();
    b[0] = b'x';
    assert_eq!(verify_image(&b, &k, &policy()), Err(ImageError::BadMagic));
    let mut b = good.clone();
    b[4] = 3;
    assert_eq!(
        verify_image(&b, &k, &policy()),
        Err(ImageError::UnsupportedFormat(3))
    );
    let mut b = good.clone();
    b[100] = 1;
    assert_eq!(
        verify_image(&b, &k, &policy()),
        Err(ImageError::Reserved { offset: 100 })
    );
    let mut b = good.clone();
    b[15] = 0x80;
    assert_eq!(
        verify_image(&b, &k, &policy()),
        Err(ImageError::UnknownFlags(0x8000))
    );
    let mut b = good;
    b[16..20].copy_from_slice(&[0; 4]);
    assert_eq!(
        verify_image(&b, &k, &policy()),
        Err(ImageError::EmptyPayload)
    );
    assert!(Inspection::of(&[0u8; 10], None).is_err());
}
