//! The one text form of node IDs, UIDs and firmware versions (`FromStr`), shared by the gateway,
//! the simulator and the tools, and the enumerations' names.

use ihex_proto::{AckResult, FaultCode, FirmwareVersion, NodeId, ParseError, ResetReason, Uid};

#[test]
fn node_ids_parse_as_one_to_three_hex_digits_with_an_optional_0x() {
    let ok = [
        ("111", 0x111),
        ("FfD", 0xffd),
        ("2", 0x2),
        ("002", 0x2),
        ("0x2", 0x2),
        ("0XABC", 0xabc),
        ("0", 0),
        ("fff", 0xfff),
    ];
    for (text, raw) in ok {
        assert_eq!(
            text.parse::<NodeId>(),
            Ok(NodeId::new(raw).unwrap()),
            "{text}"
        );
    }
    for bad in [
        "", "0x", "1000", "-1", "+1", " 1", "1 ", "x1", "0x1000", "1.0", "１",
    ] {
        assert_eq!(bad.parse::<NodeId>(), Err(ParseError::NodeId), "{bad:?}");
    }
}

#[test]
fn node_ids_round_trip_through_display() {
    for raw in 0..=NodeId::MAX_RAW {
        let id = NodeId::new(raw).unwrap();
        assert_eq!(id.to_string().parse::<NodeId>(), Ok(id));
    }
}

#[test]
fn uids_parse_as_24_hex_digits_ignoring_separators() {
    let want = Uid([
        0x01, 0x23, 0x45, 0x67, 0x89, 0xab, 0xcd, 0xef, 0x01, 0x23, 0x45, 0x67,
    ]);
    for text in [
        "0123456789abcdef01234567",
        "0123456789ABCDEF01234567",
        "0x0123456789abcdef01234567",
        "01:23:45:67:89:ab:cd:ef:01:23:45:67",
        "01234567-89abcdef-01234567",
        "01234567 89abcdef 01234567",
    ] {
        assert_eq!(text.parse::<Uid>(), Ok(want), "{text}");
    }
    assert_eq!(want.to_string(), "0123456789abcdef01234567");
    for bad in [
        "",
        "0123456789abcdef0123456",
        "0123456789abcdef012345678",
        "0123456789abcdef0123456g",
        "0123456789abcdef01234567 00",
    ] {
        assert_eq!(bad.parse::<Uid>(), Err(ParseError::Uid), "{bad:?}");
    }
}

#[test]
fn enumerations_name_their_values_and_keep_unknown_ones() {
    assert_eq!(AckResult::InvalidValue.to_string(), "invalid_value");
    assert_eq!(AckResult::from_raw(42), AckResult::Other(42));
    assert_eq!(AckResult::Other(42).to_string(), "other_42");
    assert_eq!(FaultCode::BadFrame.to_string(), "bad_frame");
    assert_eq!(ResetReason::Watchdog.to_string(), "watchdog");
    for raw in 0..=u8::MAX {
        assert_eq!(AckResult::from_raw(raw).to_raw(), raw);
        assert_eq!(FaultCode::from_raw(raw).to_raw(), raw);
        assert_eq!(ResetReason::from_raw(raw).to_raw(), raw);
    }
    for known in AckResult::KNOWN {
        assert_eq!(AckResult::from_raw(known.to_raw()), *known);
        assert!(known.name().is_some());
    }
}

/// `text` (what events publish) is `Display`'s text, and `from_text` reads back every value.
#[test]
fn enumeration_texts_read_back_every_value() {
    for raw in 0..=u8::MAX {
        let r = ResetReason::from_raw(raw);
        let text = r.text();
        assert_eq!(text, r.to_string());
        assert_eq!(ResetReason::from_text(text), Some(r), "{text}");
        let a = AckResult::from_raw(raw);
        assert_eq!(AckResult::from_text(&a.to_string()), Some(a));
    }
    assert_eq!(ResetReason::Other(7).to_string(), "other_7");
    assert_eq!(ResetReason::Other(42).to_string(), "other_42");
    assert_eq!(ResetReason::Other(250).to_string(), "other_250");
    for bad in [
        "",
        "other_",
        "other_256",
        "other_x",
        "Watchdog",
        "watchdog ",
    ] {
        assert_eq!(ResetReason::from_text(bad), None, "{bad:?}");
    }
}

#[test]
fn firmware_versions_parse_as_three_numbers() {
    let v = FirmwareVersion::new;
    for (text, want) in [
        ("0.1.0", v(0, 1, 0)),
        ("1.2.3", v(1, 2, 3)),
        ("255.255.255", v(255, 255, 255)),
        ("10.0.7", v(10, 0, 7)),
        // Semver suffixes have no room on the wire: ignored.
        ("1.2.3-rc.1", v(1, 2, 3)),
        ("1.2.3+build.5", v(1, 2, 3)),
    ] {
        assert_eq!(text.parse::<FirmwareVersion>(), Ok(want), "{text}");
    }
    for bad in [
        "", "1", "1.2", "1.2.3.4", "256.0.0", "1.2.256", "1000.0.0", "01.2.3", "1.02.3", "1..3",
        ".1.2", "1.2.", "1.2.3-", "1.2.3+", "1.2.x", " 1.2.3", "1.2.3 ", "v1.2.3", "-1.2.3",
    ] {
        assert_eq!(
            bad.parse::<FirmwareVersion>(),
            Err(ParseError::Version),
            "{bad:?}"
        );
    }
    assert_eq!(v(1, 2, 3).to_string(), "1.2.3");
    assert!(
        v(1, 2, 3) < v(1, 10, 0),
        "versions order by number, not by text"
    );
    // `const`: a firmware turns its crate version into this at compile time.
    const CRATE: Option<FirmwareVersion> = FirmwareVersion::parse(env!("CARGO_PKG_VERSION"));
    assert!(CRATE.is_some());
    for major in [0u8, 9, 10, 99, 100, 255] {
        let text = format!("{major}.{major}.{major}");
        assert_eq!(text.parse(), Ok(v(major, major, major)));
    }
}
