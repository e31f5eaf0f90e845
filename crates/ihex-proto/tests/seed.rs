//! The seed's worked examples, verbatim.

use ihex_proto::filter::{self, Filter};
use ihex_proto::timing::BitTiming;

#[test]
fn seed_mask_filter_example() {
    let f = Filter::accept(0xA000_0431, 0x2000_0111);
    assert!(f.matches(0x2135_3011));
    assert!(!f.matches(0x2135_3110));
    // The failing bits are exactly 0 and 8.
    let diff = (0x2135_3110u32 ^ 0xA000_0431) & 0x2000_0111;
    assert_eq!(diff, (1 << 0) | (1 << 8));
    assert!(filter::accepts(&[f], 0x2135_3011));
    assert!(!filter::accepts(&[f], 0x2135_3110));
    let r = Filter::reject(0xA000_0431, 0x2000_0111);
    assert!(!filter::accepts(&[r], 0x2135_3011));
    assert!(filter::accepts(&[r], 0x2135_3110));
}

#[test]
fn seed_bit_timing_36mhz_500k() {
    let t = BitTiming::compute(36_000_000, 500_000).unwrap();
    assert_eq!((t.prescaler, t.bs1, t.bs2, t.sjw), (9, 6, 1, 1));
    assert_eq!(t.sample_point_permille(), 875);
    assert_eq!(t.bitrate(36_000_000), 500_000);
    assert_eq!(t.btr(), 0x0005_0008);
}
