//! The physical limit of a classic CAN bus: the frame rates that the bit lengths of extended data
//! frames (`ihex_proto::bus`, with and without worst-case bit stuffing; re-exported here) allow at
//! a given bitrate. The tests check the stuffing bound against concrete bit patterns.

pub use ihex_proto::bus::{frame_bits, frame_bits_worst, stuffed_region_bits, worst_stuff_bits};

/// Back-to-back frames per second at `bitrate` for frames of `bits` bits.
pub fn frames_per_second(bitrate: u32, bits: u32) -> f64 {
    f64::from(bitrate) / f64::from(bits)
}

/// The bus's frame-rate limits for one frame size.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Limit {
    /// Data bytes per frame.
    pub data_len: u8,
    /// Bits per frame without stuffing.
    pub bits: u32,
    /// Bits per frame with worst-case stuffing.
    pub bits_worst: u32,
    /// Frames per second without stuffing (the best case).
    pub fps_best: f64,
    /// Frames per second with worst-case stuffing (what a full bus is guaranteed to carry).
    pub fps_worst: f64,
}

impl Limit {
    /// The limits of frames with `data_len` data bytes at `bitrate`.
    pub fn new(bitrate: u32, data_len: u8) -> Limit {
        Limit {
            data_len,
            bits: frame_bits(data_len),
            bits_worst: frame_bits_worst(data_len),
            fps_best: frames_per_second(bitrate, frame_bits(data_len)),
            fps_worst: frames_per_second(bitrate, frame_bits_worst(data_len)),
        }
    }
}

/// The bus's limit for acknowledged commands: each command frame and its node's ack share the
/// bus, so a pair takes the bits of both.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PairLimit {
    /// Data bytes of the command frame.
    pub command_len: u8,
    /// Data bytes of the ack frame.
    pub ack_len: u8,
    /// Bits per pair without stuffing.
    pub bits: u32,
    /// Bits per pair with worst-case stuffing.
    pub bits_worst: u32,
    /// Pairs per second without stuffing (the best case).
    pub pps_best: f64,
    /// Pairs per second with worst-case stuffing (what a full bus is guaranteed to carry).
    pub pps_worst: f64,
}

impl PairLimit {
    /// The limits of pairs of a `command_len`-byte command and an `ack_len`-byte ack at `bitrate`.
    pub fn new(bitrate: u32, command_len: u8, ack_len: u8) -> PairLimit {
        let bits = frame_bits(command_len) + frame_bits(ack_len);
        let bits_worst = frame_bits_worst(command_len) + frame_bits_worst(ack_len);
        PairLimit {
            command_len,
            ack_len,
            bits,
            bits_worst,
            pps_best: frames_per_second(bitrate, bits),
            pps_worst: frames_per_second(bitrate, bits_worst),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn led_command_and_ack_pair_is_230_bits_plain_and_280_worst() {
        // LedSet (8 bytes) and Ack (4 bytes), docs/protocol.md.
        let p = PairLimit::new(500_000, 8, 4);
        assert_eq!((p.bits, p.bits_worst), (131 + 99, 160 + 120));
        assert_eq!(p.pps_worst.round(), 1786.0);
        assert_eq!(p.pps_best.round(), 2174.0);
    }

    #[test]
    fn eight_byte_frame_is_131_bits_plain_and_160_worst() {
        assert_eq!(frame_bits(8), 131);
        assert_eq!(worst_stuff_bits(8), 29);
        assert_eq!(frame_bits_worst(8), 160);
    }

    #[test]
    fn empty_frame() {
        // 53 stuffed-region bits -> 13 stuff bits at most.
        assert_eq!(frame_bits(0), 67);
        assert_eq!(frame_bits_worst(0), 80);
    }

    /// Counts stuff bits of a concrete bit sequence the way a transmitter inserts them.
    fn stuff_count(bits: &[bool]) -> u32 {
        let (mut run, mut last, mut stuffed) = (0, None, 0);
        for &b in bits {
            if Some(b) == last {
                run += 1;
            } else {
                run = 1;
                last = Some(b);
            }
            if run == 5 {
                stuffed += 1;
                // The stuff bit is the complement and starts the next run.
                last = Some(!b);
                run = 1;
            }
        }
        stuffed
    }

    #[test]
    fn worst_case_formula_matches_the_worst_pattern() {
        // Worst pattern: 5 equal bits, then runs of 4 that each equal the previous stuff bit.
        for n in 0..=8u8 {
            let len = stuffed_region_bits(n) as usize;
            let mut bits = vec![false; 5];
            let mut level = true;
            while bits.len() < len {
                bits.extend(std::iter::repeat_n(level, 4));
                level = !level;
            }
            bits.truncate(len);
            assert_eq!(stuff_count(&bits), worst_stuff_bits(n), "n = {n}");
        }
    }

    #[test]
    fn no_pattern_of_a_short_region_beats_the_formula() {
        // Exhaustive over every 13-bit region: the formula's bound holds for that length.
        let len = 13;
        let bound = (len - 1) / 4;
        for v in 0u32..(1 << len) {
            let bits: Vec<bool> = (0..len).map(|i| v >> i & 1 == 1).collect();
            assert!(stuff_count(&bits) <= bound, "{v:013b}");
        }
    }

    #[test]
    fn rates_at_500_kbit() {
        let l = Limit::new(500_000, 8);
        assert!((l.fps_best - 3816.79).abs() < 0.01);
        assert!((l.fps_worst - 3125.0).abs() < 1e-9);
    }
}
