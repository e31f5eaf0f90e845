//! Property tests: round trips for every valid packet, no panics on any input, and the filter,
//! bit-timing and UART translations against their reference semantics.

use embedded_can::{ExtendedId, Frame, Id, StandardId};
use ihex_proto::filter::{
    accepts, bxcan_bits, kernel_bits, to_bxcan, to_kernel, Filter, FilterError, EFF, ID_MASK, RTR,
};
use ihex_proto::timing::{BitTiming, TimingError};
use ihex_proto::uart::{UartDecoder, UartError, UartRequest};
use ihex_proto::{DecodeError, Kind, Message, NodeId, Packet, StateReport};
use proptest::prelude::*;

mod common;
mod strategy;
use common::TestFrame;
use strategy::{packet, sc_id, state_report};

/// A raw identifier biased towards assigned kinds and meaningful addresses, so that random frames
/// reach the payload checks instead of all failing on the kind or the addresses.
fn raw_id() -> impl Strategy<Value = u32> {
    let node = prop_oneof![
        1 => Just(0x000u32),
        1 => Just(0xFFE),
        2 => Just(0xFFF),
        4 => 0x001u32..=0xFFD,
    ];
    prop_oneof![
        1 => any::<u32>(),
        2 => (0u32..=0x1F, node.clone(), node.clone()).prop_map(|(k, d, s)| (k << 24) | (d << 12) | s),
        // Addressed the way the kind is sent: commands from the gateway, reports to it.
        4 => (0usize..Kind::ALL.len(), node).prop_map(|(i, n)| {
            let k = Kind::ALL[i];
            let (dest, src) = if k.is_command() { (n, 0) } else { (0, n) };
            ((k as u32) << 24) | (dest << 12) | src
        }),
    ]
}

/// A raw identifier and payload: random bytes, mostly of the length the identifier's kind needs.
fn raw_frame(max_len: usize) -> impl Strategy<Value = (u32, Vec<u8>)> {
    (raw_id(), proptest::bool::weighted(0.75)).prop_flat_map(move |(id, fit)| {
        let len = match Kind::from_raw(((id >> 24) & 0x1F) as u8) {
            Some(k) if fit => Message::len_of(k) as usize..=Message::len_of(k) as usize,
            _ => 0..=max_len,
        };
        // Small byte values reach the modes, ports and flags that random bytes rarely hit.
        let byte = prop_oneof![2 => any::<u8>(), 3 => 0u8..=9, 2 => Just(0)];
        // A state report's first byte picks its layout: mostly a part number that exists.
        let part = prop_oneof![
            1 => any::<u8>(),
            1 => Just(StateReport::END),
            4 => (0u8..=0x3F).prop_filter("a known part", |p| StateReport::is_known_part(*p)),
        ];
        let report = id >> 24 & 0x1F == Kind::StateReport as u32;
        (Just(id), proptest::collection::vec(byte, len), part).prop_map(
            move |(id, mut data, part)| {
                if report && !data.is_empty() {
                    data[0] = part;
                }
                (id, data)
            },
        )
    })
}

// ---------------------------------------------------------------------------------------------
// Messages and packets.

proptest! {
    #![proptest_config(ProptestConfig { cases: 2048, ..ProptestConfig::default() })]

    #[test]
    fn every_valid_packet_round_trips(p in packet()) {
        prop_assert_eq!(p.validate(), Ok(()));
        let (id, data) = p.encode();
        prop_assert!(id <= ID_MASK);
        prop_assert_eq!(data.len(), Message::len_of(p.msg.kind()) as usize);
        prop_assert_eq!(Packet::decode(id, &data), Ok(p));
        let frame: TestFrame = p.to_frame().unwrap();
        prop_assert!(frame.is_extended() && !frame.is_remote_frame());
        prop_assert_eq!(Packet::from_frame(&frame), Ok(p));
    }

    #[test]
    fn decode_never_panics_and_accepted_input_re_encodes_identically((id, data) in raw_frame(12)) {
        if let Ok(p) = Packet::decode(id, &data) {
            prop_assert_eq!(p.validate(), Ok(()));
            let (rid, rdata) = p.encode();
            prop_assert_eq!(rid, id & ID_MASK);
            prop_assert_eq!(rdata.as_slice(), data.as_slice());
        }
    }

    #[test]
    fn from_frame_never_panics_and_agrees_with_decode(
        (id, data) in raw_frame(8),
        extended in any::<bool>(),
        remote in any::<bool>(),
    ) {
        let can_id: Id = if extended {
            ExtendedId::new(id & ID_MASK).unwrap().into()
        } else {
            StandardId::new((id & 0x7FF) as u16).unwrap().into()
        };
        let frame = if remote {
            TestFrame::new_remote(can_id, data.len()).unwrap()
        } else {
            TestFrame::new(can_id, &data).unwrap()
        };
        let got = Packet::from_frame(&frame);
        if remote {
            prop_assert_eq!(got, Err(DecodeError::Remote));
        } else if !extended {
            prop_assert_eq!(got, Err(DecodeError::StandardId));
        } else {
            prop_assert_eq!(got, Packet::decode(id & ID_MASK, &data));
            if let Ok(p) = got {
                let back: TestFrame = p.to_frame().unwrap();
                prop_assert_eq!(back, frame);
            }
        }
    }

    #[test]
    fn decode_errors_say_why((id, data) in raw_frame(8)) {
        match Packet::decode(id, &data) {
            Ok(_) => {}
            Err(DecodeError::UnknownKind(k)) => {
                prop_assert_eq!(u32::from(k), (id >> 24) & 0x1F);
                prop_assert!(Kind::from_raw(k).is_none());
            }
            Err(DecodeError::Length { kind, expected, got }) => {
                prop_assert_eq!(kind as u32, (id >> 24) & 0x1F);
                prop_assert_eq!(expected, Message::len_of(kind));
                prop_assert_eq!(got as usize, data.len());
                prop_assert_ne!(got, expected);
            }
            Err(DecodeError::Address { kind }) => {
                prop_assert_eq!(kind as u32, (id >> 24) & 0x1F);
            }
            Err(DecodeError::Value { kind, field, .. }) => {
                prop_assert_eq!(kind as u32, (id >> 24) & 0x1F);
                prop_assert_eq!(data.len(), Message::len_of(kind) as usize);
                prop_assert!(!field.is_empty());
            }
            Err(e) => prop_assert!(false, "unexpected error {:?}", e),
        }
    }
}

/// The random-frame properties above only test re-encoding on the frames that decode: make sure
/// the generator produces plenty of those, of every kind.
#[test]
fn random_frames_reach_every_kind() {
    use proptest::strategy::ValueTree;
    let mut runner = proptest::test_runner::TestRunner::deterministic();
    let strategy = raw_frame(8);
    let mut decoded = [0u32; 32];
    let n = 20_000;
    for _ in 0..n {
        let (id, data) = strategy.new_tree(&mut runner).unwrap().current();
        if let Ok(p) = Packet::decode(id, &data) {
            decoded[p.msg.kind() as usize] += 1;
        }
    }
    let total: u32 = decoded.iter().sum();
    assert!(total * 10 > n, "only {total} of {n} random frames decode");
    let never: Vec<Kind> = Kind::ALL
        .into_iter()
        .filter(|k| decoded[*k as usize] == 0)
        .collect();
    assert!(never.is_empty(), "kinds never decoded: {never:?}");
}

/// A valid frame with one byte changed: near-valid input reaches the checks of every layout
/// (random bytes rarely satisfy a state report's reserved bytes).
fn mutated(packets: impl Strategy<Value = Packet>) -> impl Strategy<Value = (u32, Vec<u8>)> {
    (packets, any::<prop::sample::Index>(), any::<u8>()).prop_map(|(p, i, v)| {
        let (id, data) = p.encode();
        let mut data = data.to_vec();
        if !data.is_empty() {
            let i = i.index(data.len());
            data[i] = v;
        }
        (id, data)
    })
}

/// Valid state reports only: the layouts with the most rules.
fn report_packet() -> impl Strategy<Value = Packet> {
    (state_report(), sc_id()).prop_map(|(r, node)| Packet::report(node, Message::StateReport(r)))
}

/// A one-byte change of a valid frame decodes to something that re-encodes to it, or is refused
/// for a value (never for its kind, length or addresses, which the change does not touch).
fn check_mutated(id: u32, data: &[u8]) -> Result<(), TestCaseError> {
    match Packet::decode(id, data) {
        Ok(p) => {
            let (rid, rdata) = p.encode();
            prop_assert_eq!(rid, id);
            prop_assert_eq!(rdata.as_slice(), data);
        }
        Err(DecodeError::Value { kind, field, .. }) => {
            prop_assert_eq!(kind as u32, id >> 24);
            prop_assert!(!field.is_empty());
        }
        Err(e) => prop_assert!(false, "a one-byte change gave {:?}", e),
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2048, ..ProptestConfig::default() })]

    #[test]
    fn mutated_frames_decode_canonically_or_say_why((id, data) in mutated(packet())) {
        check_mutated(id, &data)?;
    }

    #[test]
    fn mutated_state_reports_decode_canonically_or_say_why((id, data) in mutated(report_packet())) {
        check_mutated(id, &data)?;
    }
}

/// The mutation generator reaches every state-report part, known and unknown, and its
/// rejections.
#[test]
fn mutated_reports_reach_every_part() {
    use proptest::strategy::ValueTree;
    let mut runner = proptest::test_runner::TestRunner::deterministic();
    let strategy = mutated(report_packet());
    let mut parts = std::collections::BTreeSet::new();
    let mut refused = 0;
    for _ in 0..4096 {
        let (id, data) = strategy.new_tree(&mut runner).unwrap().current();
        match Packet::decode(id, &data) {
            Ok(Packet {
                msg: Message::StateReport(r),
                ..
            }) => {
                parts.insert(match r {
                    StateReport::Other { .. } => 0x100,
                    StateReport::Dock { .. } => u16::from(StateReport::DOCK),
                    r => u16::from(r.part()),
                });
            }
            Ok(p) => panic!("{p:?} from a state-report identifier"),
            Err(_) => refused += 1,
        }
    }
    // Led, Buzzer, Power, Dock, Firmware, ImageHash, UidLow, UidHigh, Protocol, End and Other.
    assert_eq!(parts.len(), 11, "parts reached: {parts:x?}");
    assert!(refused > 0);
}

// ---------------------------------------------------------------------------------------------
// Filters.

/// A filter whose id and mask are built from a few shapes, so that random frames often hit it.
fn filter(accept_only: bool) -> impl Strategy<Value = Filter> {
    let mask = prop_oneof![
        any::<u32>(),
        Just(ID_MASK | EFF | RTR),
        Just(0x00FF_F000 | EFF | RTR),
        Just(0x1F00_0000 | EFF),
        Just(0x7FF | EFF),
        Just(0x2000_0111),
        (any::<u32>(), any::<u32>()).prop_map(|(a, b)| a & b),
    ];
    let action = if accept_only {
        Just(true).boxed()
    } else {
        any::<bool>().boxed()
    };
    (action, any::<u32>(), mask, any::<bool>()).prop_map(|(acc, id, mask, std)| {
        // Standard-frame filters mostly keep the high bits clear (the rest are "never matches").
        let id = if std && id & 1 == 0 {
            id & (0x7FF | RTR)
        } else {
            id
        };
        if acc {
            Filter::accept(id, mask)
        } else {
            Filter::reject(id, mask)
        }
    })
}

/// A valid match word: a standard ID has no bits above 10, bit 31 is never set.
fn normalise(word: u32) -> u32 {
    if word & EFF != 0 {
        word & (ID_MASK | EFF | RTR)
    } else {
        word & (0x7FF | RTR)
    }
}

/// Frame words: random ones and ones a few bit flips away from a filter's ID.
fn words(filters: &[Filter], seeds: &[(usize, u32, u32, u32)]) -> Vec<u32> {
    let mut out = Vec::new();
    for &(i, a, b, c) in seeds {
        out.push(normalise(a));
        if !filters.is_empty() {
            let f = filters[i % filters.len()];
            out.push(normalise(f.id ^ (a & b & c)));
            out.push(normalise((f.id & f.mask) | (a & !f.mask)));
        }
    }
    out
}

fn seeds() -> impl Strategy<Value = Vec<(usize, u32, u32, u32)>> {
    proptest::collection::vec(any::<(usize, u32, u32, u32)>(), 1..16)
}

/// How the kernel treats a socket with this plan, per `net/can/raw.c` and `af_can.c`.
fn kernel_passes(plan: &ihex_proto::filter::KernelPlan, word: u32) -> bool {
    let can_id = kernel_bits(word);
    if plan.filters.is_empty() {
        false
    } else if plan.join {
        plan.filters.iter().all(|k| k.kernel_matches(can_id))
    } else {
        plan.filters.iter().any(|k| k.kernel_matches(can_id))
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 1024, ..ProptestConfig::default() })]

    #[test]
    fn kernel_filters_agree_with_accepts(
        filters in proptest::collection::vec(filter(false), 0..6),
        seeds in seeds(),
    ) {
        let plan = to_kernel(&filters).unwrap();
        for w in words(&filters, &seeds) {
            let want = accepts(&filters, w);
            let kernel = kernel_passes(&plan, w);
            if plan.software_check {
                prop_assert!(!want || kernel, "kernel must pass a superset: word {:#010x}", w);
            } else {
                prop_assert_eq!(kernel, want, "word {:#010x} plan {:?}", w, plan);
            }
        }
    }

    #[test]
    fn bxcan_banks_agree_with_accepts(
        filters in proptest::collection::vec(filter(true), 0..10),
        eff in proptest::collection::vec(any::<bool>(), 10),
        seeds in seeds(),
    ) {
        // Mostly fix the EFF bit, as bxCAN requires; sometimes leave it open to see the error.
        let filters: Vec<Filter> = filters
            .into_iter()
            .zip(eff)
            .map(|(f, fix)| if fix || f.mask & 3 != 0 { Filter::accept(f.id, f.mask | EFF) } else { f })
            .collect();
        match to_bxcan(&filters) {
            Ok(banks) => {
                prop_assert!(!banks.is_empty() && banks.len() <= ihex_proto::filter::BXCAN_BANKS);
                for w in words(&filters, &seeds) {
                    let hw = banks.iter().any(|b| b.matches(bxcan_bits(w)));
                    prop_assert_eq!(hw, accepts(&filters, w), "word {:#010x} banks {:?}", w, banks);
                }
            }
            Err(FilterError::EffNotFixed) => prop_assert!(filters.iter().any(|f| f.mask & EFF == 0)),
            Err(FilterError::NeverMatches) => prop_assert!(filters.iter().any(|f| f.never_matches())),
            Err(e) => prop_assert!(false, "unexpected {:?}", e),
        }
    }

    #[test]
    fn sc_filters_accept_exactly_own_and_broadcast(own in sc_id(), w in any::<u32>()) {
        let w = normalise(w);
        let fs = ihex_proto::filter::sc_filters(Some(own));
        let banks = to_bxcan(&fs).unwrap();
        prop_assert!(banks.len() <= 2);
        let dest = (w >> 12) & 0xFFF;
        let want = w & (EFF | RTR) == EFF && (dest == u32::from(own.get()) || dest == 0xFFF);
        prop_assert_eq!(accepts(&fs, w), want);
        prop_assert_eq!(banks.iter().any(|b| b.matches(bxcan_bits(w))), want);
        let plan = to_kernel(&fs).unwrap();
        prop_assert_eq!(kernel_passes(&plan, w), want);
    }
}

// ---------------------------------------------------------------------------------------------
// Bit timing.

/// Brute force over every bxCAN setting: the exact ones, as (prescaler, quanta, |sample point
/// error| in units of 1/(1000·quanta)) for the best split of each.
fn exact_settings(clk: u32, rate: u32) -> Vec<(u32, u32, u64)> {
    let mut v = Vec::new();
    for tq in 8u32..=25 {
        for pre in 1u32..=1024 {
            if u64::from(pre) * u64::from(tq) * u64::from(rate) == u64::from(clk) {
                let best = (1u32..=16)
                    .filter(|bs1| (1..=8).contains(&(tq - 1).saturating_sub(*bs1)) && *bs1 < tq - 1)
                    .map(|bs1| (u64::from(1 + bs1) * 1000).abs_diff(875 * u64::from(tq)))
                    .min();
                if let Some(err) = best {
                    v.push((pre, tq, err));
                }
            }
        }
    }
    v
}

fn clock_and_rate() -> impl Strategy<Value = (u32, u32)> {
    prop_oneof![
        // Exact by construction: rate × quanta × prescaler.
        (1_000u32..=1_000_000, 8u32..=25, 1u32..=1024).prop_filter_map(
            "clock over u32",
            |(r, q, p)| {
                let clk = u64::from(r) * u64::from(q) * u64::from(p);
                u32::try_from(clk).ok().map(|c| (c, r))
            }
        ),
        (
            prop_oneof![
                Just(8_000_000u32),
                Just(36_000_000),
                Just(42_000_000),
                Just(48_000_000),
                1u32..=200_000_000
            ],
            prop_oneof![
                Just(125_000u32),
                Just(250_000),
                Just(500_000),
                Just(1_000_000),
                1u32..=2_000_000
            ]
        ),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 512, ..ProptestConfig::default() })]

    #[test]
    fn bit_timing_is_exact_valid_and_best((clk, rate) in clock_and_rate()) {
        let exact = exact_settings(clk, rate);
        match BitTiming::compute(clk, rate) {
            Ok(t) => {
                prop_assert!(t.is_valid(), "{:?}", t);
                prop_assert_eq!(t.sjw, 1);
                prop_assert!((8..=25).contains(&t.quanta()));
                prop_assert_eq!(u64::from(t.prescaler) * u64::from(t.quanta()) * u64::from(rate), u64::from(clk));
                prop_assert_eq!(t.bitrate(clk), rate);
                prop_assert_eq!(t.btr() & !0x037F_03FF, 0);
                // No exact setting has a sample point nearer 87.5 %.
                let q = u64::from(t.quanta());
                let err = (u64::from(1 + t.bs1 as u32) * 1000).abs_diff(875 * q);
                for (pre, tq, best) in exact {
                    // Compare err/q with best/tq without division.
                    prop_assert!(err * u64::from(tq) <= best * q, "prescaler {} × {} quanta is better", pre, tq);
                }
            }
            Err(TimingError::NoExactTiming) => prop_assert!(exact.is_empty(), "missed {:?}", exact),
            Err(TimingError::Zero) => prop_assert!(clk == 0 || rate == 0),
        }
    }
}

// ---------------------------------------------------------------------------------------------
// UART.

#[test]
fn every_set_id_encodes_and_decodes() {
    for raw in 0..=0xFFFu16 {
        let bytes = [0xA0 | (raw >> 8) as u8, raw as u8];
        let mut d = UartDecoder::new();
        assert_eq!(d.push(bytes[0]), None);
        let got = d.push(bytes[1]);
        match NodeId::new_sc(raw) {
            Some(id) => {
                assert_eq!(UartRequest::SetId(id).encode(), bytes);
                assert_eq!(got, Some(Ok(UartRequest::SetId(id))));
            }
            None => assert_eq!(got, Some(Err(UartError::ReservedId)), "{raw:#x}"),
        }
        assert!(!d.is_pending());
    }
}

fn request() -> impl Strategy<Value = UartRequest> {
    prop_oneof![
        Just(UartRequest::Query),
        sc_id().prop_map(UartRequest::SetId)
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2048, ..ProptestConfig::default() })]

    #[test]
    fn uart_streams_never_panic_and_resync(
        garbage in proptest::collection::vec(any::<u8>(), 0..64),
        req in request(),
    ) {
        let mut d = UartDecoder::new();
        let mut outputs = 0;
        for &b in &garbage {
            let pending = d.is_pending();
            if d.push(b).is_some() {
                outputs += 1;
            } else {
                // Silence means the byte was held as the first of a request.
                prop_assert!(!pending && d.is_pending());
            }
        }
        prop_assert!(outputs <= garbage.len());
        // After an idle gap the next request is understood whatever came before.
        let mut after_gap = d;
        after_gap.reset();
        let [a, b] = req.encode();
        prop_assert_eq!(after_gap.push(a), None);
        prop_assert_eq!(after_gap.push(b), Some(Ok(req)));
        // Without a gap, two queries in a row always end in a recognised query.
        let mut no_gap = d;
        let last = [0xB0, 0x00, 0xB0, 0x00].iter().filter_map(|b| no_gap.push(*b)).last();
        prop_assert_eq!(last, Some(Ok(UartRequest::Query)));
        prop_assert!(!no_gap.is_pending());
    }
}
