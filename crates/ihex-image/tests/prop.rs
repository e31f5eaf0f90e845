//! Property tests: parsing and checking never panic, packing round-trips, any change is caught.

mod common;

use common::{key, policy};
use ihex_image::{
    check_signed, pack, verify_image, Board, FirmwareVersion, Header, Inspection, HEADER_LEN,
};
use proptest::prelude::*;

proptest! {
    #[test]
    fn header_parse_never_panics_and_is_canonical(b in proptest::collection::vec(any::<u8>(), 0..200)) {
        if let Ok(h) = Header::parse(&b) {
            prop_assert_eq!(&h.encode()[..], &b[..HEADER_LEN]);
        }
    }

    #[test]
    fn checks_never_panic(b in proptest::collection::vec(any::<u8>(), 0..700)) {
        let _ = check_signed(&b, &key().public(), &policy());
        let _ = verify_image(&b, &key().public(), &policy());
        let _ = Inspection::of(&b, Some(&key().public()));
    }

}

// Each case signs and/or verifies (milliseconds in portable ed25519): fewer cases.
proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn pack_then_verify(
        payload in proptest::collection::vec(any::<u8>(), 1..3000),
        minor in 0u8..=255,
        patch in 0u8..=255,
    ) {
        let v = FirmwareVersion::new(1, minor.max(3), patch);
        let img = pack(Board::NUCLEO_F303RE, (1, 0), v, &payload, &key()).unwrap();
        let h = verify_image(&img, &key().public(), &policy()).unwrap();
        prop_assert_eq!(h.version, v);
        prop_assert_eq!(h.payload_len as usize, payload.len());
        prop_assert_eq!(&img[512..], &payload[..]);
    }

    #[test]
    fn any_byte_changed_is_refused(pos in 0usize..1512, x in 1u8..=255) {
        let mut img = common::image(FirmwareVersion::new(1, 2, 3));
        img[pos] ^= x;
        prop_assert!(verify_image(&img, &key().public(), &policy()).is_err());
    }
}
