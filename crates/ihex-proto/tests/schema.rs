//! The schema against the codec: an entry for every kind, signals that tile each payload exactly,
//! signal values equal to the typed fields of every valid message, and ranges exactly as wide as
//! what `Packet::decode` accepts. A protocol change that forgets the schema fails here.

use std::collections::{BTreeMap, BTreeSet};

use ihex_proto::schema::{self, Direction, MessageSchema, Mux, Signal};
use ihex_proto::{Header, Kind, Message, Packet};
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::TestRunner;

mod signals;
mod strategy;

/// Text that every DBC reader takes: printable ASCII without quotes or backslashes.
fn dbc_safe(text: &str) -> bool {
    text.bytes()
        .all(|b| (b' '..=b'~').contains(&b) && b != b'"' && b != b'\\')
}

fn is_identifier(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_lowercase())
        && name
            .bytes()
            .all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_')
}

fn full(bits: u8) -> u32 {
    if bits >= 32 {
        u32::MAX
    } else {
        (1 << bits) - 1
    }
}

/// Writes `raw` into the bits of `s`.
fn put(s: &Signal, data: &mut [u8], raw: u32) {
    for i in 0..s.bits as usize {
        let bit = s.start as usize + i;
        let mask = 1 << (bit % 8);
        if (raw >> i) & 1 == 1 {
            data[bit / 8] |= mask;
        } else {
            data[bit / 8] &= !mask;
        }
    }
}

/// One entry's own consistency: names, ranges, value tables, multiplexing, and that the signals of
/// every layout (every selector value a signal is selected by) cover each payload bit exactly once.
fn check_entry(m: &MessageSchema) {
    let kind = m.kind;
    assert!(dbc_safe(m.summary) && !m.summary.is_empty(), "{kind:?}");
    let mut names = BTreeSet::new();
    let selectors: Vec<&Signal> = m
        .signals
        .iter()
        .filter(|s| s.mux == Mux::Selector)
        .collect();
    assert!(selectors.len() <= 1, "{kind:?}: several selectors");
    let mut layouts = BTreeSet::new();
    for s in m.signals {
        let what = format!("{kind:?}.{}", s.name);
        assert!(is_identifier(s.name), "{what}: not a DBC identifier");
        assert!(names.insert(s.name), "{what}: twice");
        assert!((1..=32).contains(&s.bits), "{what}: {} bits", s.bits);
        assert!(!s.signed, "{what}: no iHEX field is signed");
        assert!(s.factor >= 1, "{what}");
        assert!(s.min <= s.max && s.max <= full(s.bits), "{what}: range");
        assert!(dbc_safe(s.unit) && dbc_safe(s.comment) && !s.comment.is_empty());
        let raws: Vec<u32> = s.values.iter().map(|(v, _)| u32::from(*v)).collect();
        assert!(raws.windows(2).all(|w| w[0] < w[1]), "{what}: value order");
        assert!(raws.iter().all(|v| (s.min..=s.max).contains(v)), "{what}");
        let labels: BTreeSet<_> = s.values.iter().map(|(_, l)| *l).collect();
        assert_eq!(labels.len(), s.values.len(), "{what}: value names twice");
        assert!(labels.iter().all(|l| dbc_safe(l) && !l.is_empty()));
        if let Mux::When(values) = s.mux {
            let selector = selectors
                .first()
                .unwrap_or_else(|| panic!("{what}: no selector"));
            assert!(!values.is_empty(), "{what}: selected by no value");
            assert!(
                values.windows(2).all(|w| w[0] < w[1]),
                "{what}: value order"
            );
            for v in values {
                let v = u32::from(*v);
                assert!(
                    (selector.min..=selector.max).contains(&v),
                    "{what}: selector {v}"
                );
                layouts.insert(Some(v));
            }
        }
    }
    if layouts.is_empty() {
        assert!(
            selectors.is_empty(),
            "{kind:?}: a selector that selects nothing"
        );
        layouts.insert(None);
    }
    for layout in layouts {
        let mut owner = vec![None; m.data_len() as usize * 8];
        for s in m.signals.iter().filter(|s| s.present_for(layout)) {
            let what = format!("{kind:?}.{} (selector {layout:?})", s.name);
            for bit in s.start as usize..s.start as usize + s.bits as usize {
                let slot = owner
                    .get_mut(bit)
                    .unwrap_or_else(|| panic!("{what}: bit {bit} past the data"));
                assert!(slot.is_none(), "{what}: bit {bit} also in {slot:?}");
                *slot = Some(s.name);
            }
        }
        // The codec reads every byte (unused ones must be zero), so a tool must see every bit.
        let uncovered: Vec<usize> = (0..owner.len()).filter(|b| owner[*b].is_none()).collect();
        assert!(
            uncovered.is_empty(),
            "{kind:?} (selector {layout:?}): bits {uncovered:?} in no signal"
        );
    }
}

#[test]
fn every_kind_has_a_consistent_entry_that_tiles_its_payload() {
    // Every assigned kind value is in Kind::ALL, so iterating ALL misses none.
    let assigned: Vec<Kind> = (0..=Header::KIND_MASK as u8)
        .filter_map(Kind::from_raw)
        .collect();
    assert_eq!(assigned, Kind::ALL);
    assert_eq!(schema::all().count(), Kind::ALL.len());
    for kind in Kind::ALL {
        let m = schema::of(kind);
        assert_eq!(m.kind, kind);
        assert_eq!(m.name(), format!("{kind:?}"));
        assert_eq!(m.data_len(), Message::len_of(kind));
        assert_eq!(
            m.direction() == Direction::Command,
            kind.is_command(),
            "{kind:?}"
        );
        check_entry(&m);
    }
}

/// The checks above see each multiplexed layout separately (on an example: no kind is multiplexed
/// yet), and the signals of a frame follow its selector.
#[test]
fn a_multiplexed_entry_is_checked_layout_by_layout() {
    let m = signals::mux_example();
    check_entry(&m);
    let names = |data: &[u8]| -> Vec<&str> { m.signals_in(data).map(|s| s.name).collect() };
    assert_eq!(names(&[0, 1, 2, 3, 4, 5]), ["part", "a", "b"]);
    assert_eq!(names(&[2, 1, 2, 3, 4, 5]), ["part", "c", "d"]);
    assert_eq!(names(&[9, 1, 2, 3, 4, 5]), ["part"]);
    assert_eq!(m.selector().map(|s| s.name), Some("part"));
    assert_eq!(schema::of(Kind::LedSet).selector(), None);
    // A layout whose signals overlap fails the check.
    let mut broken = m.signals.to_vec();
    broken[3].bits = 24; // c now reaches into d in parts 1 to 3
    let broken = MessageSchema {
        signals: Vec::leak(broken),
        ..m
    };
    assert!(std::panic::catch_unwind(|| check_entry(&broken)).is_err());
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2048, ..ProptestConfig::default() })]

    /// Reading the signals of an encoded message gives its typed fields, and writing the typed
    /// fields through the signals gives the codec's bytes.
    #[test]
    fn signals_read_and_write_the_typed_fields(p in strategy::packet()) {
        let data = p.msg.encode();
        let m = schema::of(p.msg.kind());
        let expected = signals::expected(&p.msg);
        let mut names: Vec<_> = m.signals_in(&data).map(|s| s.name).collect();
        let mut want: Vec<_> = expected.iter().map(|e| e.name).collect();
        names.sort_unstable();
        want.sort_unstable();
        prop_assert_eq!(names, want, "{:?}", p.msg.kind());
        let mut rebuilt = vec![0u8; data.len()];
        for e in &expected {
            let s = m.signal(e.name).unwrap();
            let raw = s.raw(&data).unwrap();
            prop_assert_eq!(raw, e.raw, "{:?}.{}", p.msg.kind(), e.name);
            prop_assert_eq!(s.physical(raw), e.physical, "{}", e.name);
            prop_assert_eq!(s.label(raw).map(str::to_string), e.label.clone(), "{}", e.name);
            prop_assert!((s.min..=s.max).contains(&raw), "{} = {} out of its range", e.name, raw);
            put(s, &mut rebuilt, e.raw);
        }
        prop_assert_eq!(rebuilt.as_slice(), data.as_slice());
    }
}

/// A signal's range is exactly what the codec accepts: in valid frames of every kind, the raw
/// value just above `max` (and just below `min`) of each signal is refused by `decode`, and `max`
/// and `min` themselves decode in at least one of them.
#[test]
fn signal_ranges_are_exactly_what_decode_accepts() {
    const PER_KIND: usize = 16;
    let mut runner = TestRunner::deterministic();
    let strategy = strategy::packet();
    let mut samples: BTreeMap<u8, Vec<Packet>> = BTreeMap::new();
    while samples.len() < Kind::ALL.len() || samples.values().any(|v| v.len() < PER_KIND) {
        let p = strategy.new_tree(&mut runner).unwrap().current();
        let v = samples.entry(p.msg.kind() as u8).or_default();
        if v.len() < PER_KIND {
            v.push(p);
        }
    }
    let mut refused = 0;
    // (kind, signal) -> (max decoded somewhere, min decoded somewhere)
    let mut bounds: BTreeMap<(u8, &str), (bool, bool)> = BTreeMap::new();
    for packets in samples.values() {
        for p in packets {
            let (id, data) = p.encode();
            let m = schema::of(p.msg.kind());
            let with = |s: &Signal, raw| {
                let mut d = data.to_vec();
                put(s, &mut d, raw);
                Packet::decode(id, &d)
            };
            for s in m.signals_in(&data) {
                let ok = bounds.entry((m.kind as u8, s.name)).or_default();
                ok.0 |= with(s, s.max).is_ok();
                ok.1 |= with(s, s.min).is_ok();
                let outside = [
                    (s.max < full(s.bits)).then(|| s.max + 1),
                    s.min.checked_sub(1),
                ];
                for raw in outside.into_iter().flatten() {
                    let got = with(s, raw);
                    assert!(
                        got.is_err(),
                        "{:?}.{} = {raw} is outside [{}, {}] but decodes: {got:?}",
                        m.kind,
                        s.name,
                        s.min,
                        s.max
                    );
                    refused += 1;
                }
            }
        }
    }
    assert!(refused > 100, "only {refused} out-of-range values tried");
    for ((kind, name), (max_ok, min_ok)) in bounds {
        assert!(max_ok, "kind {kind:#04x}.{name}: its max never decodes");
        assert!(min_ok, "kind {kind:#04x}.{name}: its min never decodes");
    }
}

#[test]
fn value_names_are_the_codec_names() {
    let ack = schema::of(Kind::Ack);
    let kind = ack.signal("kind").unwrap();
    assert_eq!(kind.values.len(), Kind::ALL.len());
    for k in Kind::ALL {
        assert_eq!(kind.label(k as u32), Some(k.name()));
    }
    let led = schema::of(Kind::LedSet);
    assert_eq!(led.signal("period").unwrap().unit, "ms");
    assert_eq!(led.signal("period").unwrap().physical(50), 500);
    assert_eq!(led.signal("duty").unwrap().unit, "%");
    let buzzer = schema::of(Kind::BuzzerSet);
    assert_eq!(buzzer.signal("freq").unwrap().unit, "Hz");
    assert_eq!(buzzer.signal("off").unwrap().physical(255), 2550);
    let health = schema::of(Kind::HealthReply);
    assert_eq!(health.signal("uptime").unwrap().unit, "s");
    assert_eq!(health.signal("uptime").unwrap().max, 0xFF_FFFF);
    assert_eq!(
        schema::of(Kind::Identify).signal("seconds").unwrap().unit,
        "s"
    );
}
