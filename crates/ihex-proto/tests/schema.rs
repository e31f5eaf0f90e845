//! The schema against the codec: an entry for every kind, signals that tile each payload exactly,
//! signal values equal to the typed fields of every valid message, and ranges exactly as wide as
//! what `Packet::decode` accepts. A protocol change that forgets the schema fails here.

use std::collections::{BTreeMap, BTreeSet};

use ihex_proto::schema::{self, Direction, MessageSchema, Mux, Signal};
use ihex_proto::{Header, Kind, Message, Packet, StateReport};
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
/// every layout (every value in the selector's range) cover each payload bit exactly once.
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
    // A selector value that selects no layout would leave its frames' bits undescribed.
    if let Some(selector) = selectors.first() {
        layouts.extend((selector.min..=selector.max).map(Some));
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

/// The checks above see each multiplexed layout separately (on a small example), and the signals
/// of a frame follow its selector.
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
    // So does a selector value that selects nothing.
    let mut wider = m.signals.to_vec();
    wider[0].max = 4;
    let wider = MessageSchema {
        signals: Vec::leak(wider),
        ..m
    };
    assert!(std::panic::catch_unwind(|| check_entry(&wider)).is_err());
}

/// Every part number selects a layout: each known part its fields, every other number the raw
/// bytes of `Other`; the eight dock parts share one layout.
#[test]
fn state_reports_are_multiplexed_on_the_part() {
    let m = schema::of(Kind::StateReport);
    let part = m.selector().unwrap();
    assert_eq!((part.name, part.start, part.bits), ("part", 0, 8));
    let names = |part: u8| -> Vec<&str> {
        let mut data = [0u8; 8];
        data[0] = part;
        m.signals_in(&data).skip(1).map(|s| s.name).collect()
    };
    assert_eq!(names(0x00)[0], "led_mode");
    assert_eq!(names(0x02)[0], "power_relay");
    assert_eq!(names(0x10)[0], "dock_closed");
    for port in 1..8 {
        assert_eq!(names(0x10 | port), names(0x10));
    }
    assert_eq!(names(0x20)[0], "firmware_major");
    assert_eq!(names(0x23)[0], "uid_7");
    assert_eq!(names(0xFF)[0], "end_seq");
    for raw in 0..=u8::MAX {
        let known = StateReport::is_known_part(raw);
        assert_eq!(names(raw)[0] == "data_1", !known, "part {raw:#04x}");
        assert_eq!(part.label(raw.into()).is_some(), known, "part {raw:#04x}");
    }
    for kind in Kind::ALL {
        let multiplexed = schema::of(kind).selector().is_some();
        assert_eq!(multiplexed, kind == Kind::StateReport, "{kind:?}");
    }
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

/// The layouts of a kind: the signal names of each (one layout unless it is multiplexed).
fn layouts(m: &MessageSchema) -> BTreeSet<Vec<&'static str>> {
    let mut data = vec![0u8; m.data_len() as usize];
    let Some(selector) = m.selector() else {
        return [m.signals_in(&data).map(|s| s.name).collect()].into();
    };
    (selector.min..=selector.max)
        .map(|raw| {
            put(selector, &mut data, raw);
            m.signals_in(&data).map(|s| s.name).collect()
        })
        .collect()
}

/// A signal's range is exactly what the codec accepts: in valid frames of every kind and layout,
/// the raw value just above `max` (and just below `min`) of each signal is refused by `decode`,
/// and `max` and `min` themselves decode in at least one of them.
#[test]
fn signal_ranges_are_exactly_what_decode_accepts() {
    const PER_LAYOUT: usize = 16;
    // Generous: the rarest layout (one state-report part) comes in about 1 packet in 200.
    const MAX_DRAWS: usize = 200_000;
    let mut runner = TestRunner::deterministic();
    let strategy = strategy::packet();
    let wanted: BTreeSet<(u8, Vec<&str>)> = schema::all()
        .flat_map(|m| layouts(&m).into_iter().map(move |l| (m.kind as u8, l)))
        .collect();
    let mut samples: BTreeMap<(u8, Vec<&str>), Vec<Packet>> = BTreeMap::new();
    let enough = |samples: &BTreeMap<_, Vec<Packet>>, layout| {
        samples.get(layout).is_some_and(|v| v.len() >= PER_LAYOUT)
    };
    for _ in 0..MAX_DRAWS {
        if wanted.iter().all(|l| enough(&samples, l)) {
            break;
        }
        let p = strategy.new_tree(&mut runner).unwrap().current();
        let data = p.msg.encode();
        let layout = schema::of(p.msg.kind())
            .signals_in(&data)
            .map(|s| s.name)
            .collect();
        let v = samples.entry((p.msg.kind() as u8, layout)).or_default();
        if v.len() < PER_LAYOUT {
            v.push(p);
        }
    }
    let missing: Vec<_> = wanted.iter().filter(|l| !enough(&samples, l)).collect();
    assert!(
        missing.is_empty(),
        "the strategy rarely or never makes these layouts: {missing:?}"
    );
    let unknown: Vec<_> = samples.keys().filter(|l| !wanted.contains(*l)).collect();
    assert!(
        unknown.is_empty(),
        "layouts no selector value selects: {unknown:?}"
    );
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
    let every_signal: BTreeSet<(u8, &str)> = schema::all()
        .flat_map(|m| m.signals.iter().map(move |s| (m.kind as u8, s.name)))
        .collect();
    assert_eq!(
        bounds.keys().copied().collect::<BTreeSet<_>>(),
        every_signal,
        "every signal of every layout tried"
    );
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
    // A state report's LED and buzzer parts read like LedSet and BuzzerSet, at the same offsets.
    let report = schema::of(Kind::StateReport);
    for (part, set, fields) in [
        (
            "led_",
            led,
            &["mode", "r", "brightness", "period", "duty"][..],
        ),
        (
            "buzzer_",
            buzzer,
            &["mode", "freq", "on", "off", "count"][..],
        ),
    ] {
        for f in fields {
            let a = report.signal(&format!("{part}{f}")).unwrap();
            let b = set.signal(f).unwrap();
            assert_eq!(
                (a.start, a.bits, a.factor, a.unit, a.min, a.max, a.values),
                (b.start, b.bits, b.factor, b.unit, b.min, b.max, b.values),
                "{part}{f}"
            );
        }
    }
    assert_eq!(report.signal("power_identify").unwrap().unit, "s");
    for m in [report, schema::of(Kind::DockLink)] {
        let partner = m
            .signals
            .iter()
            .find(|s| s.name.ends_with("partner"))
            .unwrap();
        assert_eq!((partner.bits, partner.min, partner.max), (16, 0x001, 0xFFF));
    }
}
