//! Release notes (header format 2): carried, authenticated, shown; format 1 read as before.

mod common;

use common::{key, payload, policy};
use ihex_image::{
    pack, pack_with_notes, verify_image, Board, FirmwareVersion, Header, ImageError, Inspection,
    NOTES_LEN, SIGNED_LEN,
};

const V: FirmwareVersion = FirmwareVersion::new(1, 3, 0);
const NOTES: &str = "1.3.0: faster docking handshake\nfixes the buzzer after a reset";

#[test]
fn an_image_with_notes_is_format_2_verifies_and_shows_them() {
    let img = pack_with_notes(
        Board::NUCLEO_F303RE,
        (1, 0),
        V,
        &payload(900),
        NOTES,
        &key(),
    )
    .unwrap();
    assert_eq!(img[4], 2);
    let h = verify_image(&img, &key().public(), &policy()).unwrap();
    assert!(h.notes_hash.is_some());
    let i = Inspection::of(&img, Some(&key().public())).unwrap();
    assert!(i.is_good(), "{i}");
    assert_eq!(i.notes.as_deref(), Some(NOTES));
    assert!(i.to_string().contains("faster docking handshake"), "{i}");
}

#[test]
fn an_image_without_notes_is_still_format_1() {
    let img = pack(Board::NUCLEO_F303RE, (1, 0), V, &payload(900), &key()).unwrap();
    assert_eq!(img[4], 1);
    let h = Header::parse(&img).unwrap();
    assert_eq!(h.notes_hash, None);
    verify_image(&img, &key().public(), &policy()).unwrap();
    assert_eq!(Inspection::of(&img, None).unwrap().notes, None);
}

#[test]
fn changed_notes_do_not_verify() {
    let mut img = pack_with_notes(
        Board::NUCLEO_F303RE,
        (1, 0),
        V,
        &payload(900),
        NOTES,
        &key(),
    )
    .unwrap();
    img[SIGNED_LEN] ^= 0x20;
    assert_eq!(
        verify_image(&img, &key().public(), &policy()),
        Err(ImageError::Corrupted)
    );
    let i = Inspection::of(&img, Some(&key().public())).unwrap();
    assert!(!i.is_good());
    assert_eq!(i.notes, None, "unauthenticated notes are not shown");
}

#[test]
fn notes_too_long_or_with_nul_are_refused() {
    let long = "x".repeat(NOTES_LEN + 1);
    for notes in [long.as_str(), "a\0b"] {
        assert!(
            pack_with_notes(Board::NUCLEO_F303RE, (1, 0), V, &payload(10), notes, &key()).is_err()
        );
    }
    let fits = "x".repeat(NOTES_LEN);
    let img =
        pack_with_notes(Board::NUCLEO_F303RE, (1, 0), V, &payload(10), &fits, &key()).unwrap();
    verify_image(&img, &key().public(), &policy()).unwrap();
}
