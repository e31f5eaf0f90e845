//! Golden register values and regression cases for the filter translations (SocketCAN and bxCAN).

use ihex_proto::filter::{
    self, accepts, bxcan_bits, kernel_bits, to_bxcan, to_kernel, BxcanBank, Filter, FilterError,
    KernelFilter, EFF, RTR, WORD_MASK,
};
use ihex_proto::test_util::id as node;
use ihex_proto::{Message, NodeId, Packet, Port};

/// The match word of an extended data frame.
fn ext(id: u32) -> u32 {
    id | EFF
}

#[test]
fn to_node_filter_words() {
    let f = Filter::to_node(node(0x111));
    assert_eq!(f.id, 0x2011_1000);
    assert_eq!(f.mask, 0x60FF_F000);
    let b = Filter::to_node(NodeId::BROADCAST);
    assert_eq!((b.id, b.mask), (0x20FF_F000, 0x60FF_F000));
    let g = filter::gateway_filters();
    assert_eq!((g[0].id, g[0].mask), (0x2000_0000, 0x60FF_F000));
}

#[test]
fn from_node_filter_words_and_what_they_accept() {
    let f = Filter::from_node(NodeId::GATEWAY);
    assert_eq!((f.id, f.mask), (0x2000_0000, 0x6000_0FFF));
    let own = Packet::command(node(0x111), Message::HealthCheck { seq: 1 });
    let report = Packet::report(
        node(0x111),
        Message::DockDetected {
            port: Port::new(1).unwrap(),
        },
    );
    let word = |p: &Packet| ext(p.header().to_raw());
    assert!(filter::accepts(&[f], word(&own)));
    assert!(!filter::accepts(&[f], word(&report)));
    let k = to_kernel(&[f]).unwrap();
    assert_eq!(
        (k.filters[0].can_id, k.filters[0].can_mask),
        (0x8000_0000, 0xC000_0FFF)
    );
}

#[test]
fn sc_filters_are_two_mask_banks_with_these_register_values() {
    let fs = filter::sc_filters(Some(node(0x111)));
    let banks = to_bxcan(&fs).unwrap();
    assert_eq!(
        banks.as_slice(),
        &[
            BxcanBank::Mask32 {
                id: 0x07FF_8004,
                mask: 0x07FF_8006
            },
            BxcanBank::Mask32 {
                id: 0x0088_8004,
                mask: 0x07FF_8006
            },
        ]
    );
    // An unconfigured node listens to broadcasts only: one bank.
    let banks = to_bxcan(&filter::sc_filters(None)).unwrap();
    assert_eq!(
        banks.as_slice(),
        &[BxcanBank::Mask32 {
            id: 0x07FF_8004,
            mask: 0x07FF_8006
        }]
    );
}

#[test]
fn sc_filters_accept_exactly_own_and_broadcast() {
    let own = node(0x111);
    let fs = filter::sc_filters(Some(own));
    let banks = to_bxcan(&fs).unwrap();
    assert!(banks.len() <= 2);
    // Every destination, with a few kinds and sources, as data and remote, extended and standard.
    for dest in 0..=0xFFFu32 {
        for (kind, src) in [(0x00u32, 0x000u32), (0x0D, 0x000), (0x1F, 0xABC)] {
            let id = (kind << 24) | (dest << 12) | src;
            let want = dest == 0x111 || dest == 0xFFF;
            let w = ext(id);
            assert_eq!(accepts(&fs, w), want, "dest {dest:03x}");
            assert_eq!(
                banks.iter().any(|b| b.matches(bxcan_bits(w))),
                want,
                "dest {dest:03x}"
            );
            // Remote frames and standard frames never pass.
            assert!(!accepts(&fs, w | RTR));
            assert!(!banks.iter().any(|b| b.matches(bxcan_bits(w | RTR))));
            let std = id & 0x7FF;
            assert!(!accepts(&fs, std));
            assert!(!banks.iter().any(|b| b.matches(bxcan_bits(std))));
        }
    }
}

#[test]
fn gateway_kernel_filter() {
    let plan = to_kernel(&filter::gateway_filters()).unwrap();
    assert_eq!(
        plan.filters.as_slice(),
        &[KernelFilter {
            can_id: 0x8000_0000,
            can_mask: 0xC0FF_F000
        }]
    );
    assert!(!plan.join && !plan.software_check);
    // An extended data frame to the gateway passes, to a node or as a remote frame it does not.
    assert!(plan.filters[0].kernel_matches(kernel_bits(ext(0x0B00_0111))));
    assert!(!plan.filters[0].kernel_matches(kernel_bits(ext(0x0B11_1000))));
    assert!(!plan.filters[0].kernel_matches(kernel_bits(ext(0x0B00_0111) | RTR)));
    assert!(!plan.filters[0].kernel_matches(0x111));
}

#[test]
fn seed_filters_as_kernel_filters() {
    let f = Filter::accept(0xA000_0431, 0x2000_0111);
    let plan = to_kernel(&[f]).unwrap();
    // Bit 31 of the seed ID lies outside the mask and is dropped; EFF moves to the kernel's bit 31.
    assert_eq!(
        plan.filters.as_slice(),
        &[KernelFilter {
            can_id: 0x8000_0011,
            can_mask: 0x8000_0111
        }]
    );
    assert!(plan.filters[0].kernel_matches(kernel_bits(0x2135_3011)));
    assert!(!plan.filters[0].kernel_matches(kernel_bits(0x2135_3110)));
    let r = Filter::reject(0xA000_0431, 0x2000_0111);
    let plan = to_kernel(&[r]).unwrap();
    assert_eq!(
        plan.filters.as_slice(),
        &[KernelFilter {
            can_id: 0xA000_0011,
            can_mask: 0x8000_0111
        }]
    );
    assert!(plan.filters[0].inverted());
    assert!(!plan.filters[0].kernel_matches(kernel_bits(0x2135_3011)));
    assert!(plan.filters[0].kernel_matches(kernel_bits(0x2135_3110)));
}

#[test]
fn seed_filter_as_bxcan_bank() {
    let banks = to_bxcan(&[Filter::accept(0xA000_0431, 0x2000_0111)]).unwrap();
    assert_eq!(
        banks.as_slice(),
        &[BxcanBank::Mask32 {
            id: 0x0000_008C,
            mask: 0x0000_088C
        }]
    );
    assert!(banks[0].matches(bxcan_bits(0x2135_3011)));
    assert!(!banks[0].matches(bxcan_bits(0x2135_3110)));
    assert_eq!(
        to_bxcan(&[Filter::reject(0xA000_0431, 0x2000_0111)]),
        Err(FilterError::RejectUnsupported)
    );
}

#[test]
fn id_filters_share_list_banks() {
    let a = Filter::accept_id(ext(0x0D11_1000));
    let b = Filter::accept_id(ext(0x0C11_1000));
    let c = Filter::accept_id(0x123); // standard ID 0x123
    let banks = to_bxcan(&[a, b, c]).unwrap();
    assert_eq!(
        banks.as_slice(),
        &[
            BxcanBank::List32 {
                ids: [0x6888_8004, 0x6088_8004]
            },
            BxcanBank::List32 {
                ids: [0x2460_0000, 0x2460_0000]
            },
        ]
    );
    assert!(banks[1].matches(bxcan_bits(0x123)));
    assert!(!banks[1].matches(bxcan_bits(0x123 | RTR)));
    assert!(!banks[1].matches(bxcan_bits(ext(0x123))));
}

/// Regression: the mask of a standard-frame mask filter used the extended (EXID) layout.
#[test]
fn standard_mask_filter_bank_uses_stid_layout() {
    // Standard data frames whose low 4 bits are 0x5.
    let f = Filter::accept(0x005, 0x00F | EFF | RTR);
    let banks = to_bxcan(&[f]).unwrap();
    assert_eq!(
        banks.as_slice(),
        &[BxcanBank::Mask32 {
            id: 0x00A0_0000,
            mask: 0x01E0_0006
        }]
    );
    for sid in 0..=0x7FFu32 {
        let want = sid & 0xF == 5;
        assert_eq!(f.matches(sid), want);
        assert_eq!(banks[0].matches(bxcan_bits(sid)), want, "std id {sid:03x}");
        assert!(!banks[0].matches(bxcan_bits(sid | RTR)));
        assert!(!banks[0].matches(bxcan_bits(ext(sid))));
    }
}

/// Regression: an empty set accepts everything, but gave zero banks (bxCAN then receives nothing).
#[test]
fn empty_set_passes_everything_on_bxcan_too() {
    let banks = to_bxcan(&[]).unwrap();
    assert_eq!(banks.as_slice(), &[BxcanBank::Mask32 { id: 0, mask: 0 }]);
    for w in [0, 0x7FF, ext(0x1FFF_FFFF), ext(0) | RTR, 0x123 | RTR] {
        assert!(accepts(&[], w));
        assert!(banks[0].matches(bxcan_bits(w)));
    }
    let plan = to_kernel(&[]).unwrap();
    assert_eq!(
        plan.filters.as_slice(),
        &[KernelFilter {
            can_id: 0,
            can_mask: 0
        }]
    );
}

/// Regression: the kernel reduces the mask of a standard-only filter to the 11 standard bits, so a
/// standard filter comparing higher bits against ones matched in the kernel but never in `accepts`.
#[test]
fn standard_filter_comparing_high_bits_never_matches_in_kernel_either() {
    let never = Filter::accept(0x800 | 0x123, 0xFFF | EFF | RTR);
    assert!(never.never_matches());
    assert!(!accepts(&[never], 0x123));
    // The raw kernel filter would let 0x123 through (the kernel ignores bit 11 for SFF filters) ...
    let raw = KernelFilter {
        can_id: 0x923,
        can_mask: 0xC000_0FFF,
    };
    assert!(raw.kernel_matches(0x123));
    // ... so to_kernel leaves it out: with no other accept filter nothing may pass.
    let plan = to_kernel(&[never]).unwrap();
    assert!(plan.filters.is_empty());
    // Next to a live accept it is simply dropped.
    let live = Filter::accept_id(0x124);
    let plan = to_kernel(&[never, live]).unwrap();
    assert_eq!(
        plan.filters.as_slice(),
        &[KernelFilter {
            can_id: 0x124,
            can_mask: 0xDFFF_FFFF
        }]
    );
    // A never-matching reject rejects nothing.
    let plan = to_kernel(&[Filter::reject(0x923, 0xFFF | EFF | RTR)]).unwrap();
    assert_eq!(
        plan.filters.as_slice(),
        &[KernelFilter {
            can_id: 0,
            can_mask: 0
        }]
    );
    assert_eq!(to_bxcan(&[never]), Err(FilterError::NeverMatches));
}

#[test]
fn kernel_error_filters_never_see_data_frames() {
    let k = KernelFilter {
        can_id: 0,
        can_mask: 0x2000_0000,
    };
    assert!(!k.kernel_matches(0));
    assert!(!k.kernel_matches(kernel_bits(ext(0x0100_0001))));
}

#[test]
fn one_accept_with_rejects_is_joined_several_need_software() {
    let acc = Filter::to_node(node(0x111));
    let rej = Filter::reject(ext(0x0D00_0000), 0x1F00_0000 | EFF); // no LED frames
    let plan = to_kernel(&[acc, rej]).unwrap();
    assert!(plan.join && !plan.software_check);
    assert_eq!(plan.filters.len(), 2);
    let both = Filter::to_node(NodeId::BROADCAST);
    let plan = to_kernel(&[acc, both, rej]).unwrap();
    assert!(!plan.join && plan.software_check);
    assert_eq!(plan.filters.len(), 2);
    assert!(plan.filters.iter().all(|k| !k.inverted()));
}

#[test]
fn too_many_filters_is_an_error() {
    let many: Vec<Filter> = (0..33).map(|i| Filter::accept(ext(i), WORD_MASK)).collect();
    assert_eq!(to_kernel(&many), Err(FilterError::TooMany));
    let banks: Vec<Filter> = (0..15)
        .map(|i| Filter::accept(ext(i << 12), 0xFFF000 | EFF))
        .collect();
    assert_eq!(to_bxcan(&banks), Err(FilterError::TooMany));
    assert_eq!(to_bxcan(&banks[..14]).map(|b| b.len()), Ok(14));
    assert_eq!(
        to_bxcan(&[Filter::accept(0, 0x7FF)]),
        Err(FilterError::EffNotFixed)
    );
}
