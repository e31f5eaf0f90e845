//! The bus-share cap: a token bucket counted in bits on the wire (worst-case stuffing), refilled
//! at `share × bitrate` with the time passed in, so an update never takes more than its share of
//! the bus over any window longer than the bucket's burst.

use std::time::{Duration, Instant};

/// How much an idle sender may send at once: 10 ms of its share (at least one frame).
const BURST: Duration = Duration::from_millis(10);
const NANOS: u128 = 1_000_000_000;

/// A token bucket in bits.
#[derive(Clone, Debug)]
pub struct BitBucket {
    /// Bits per second the share allows.
    rate: u64,
    /// Largest number of bits held, in bit·nanoseconds (bits × 10⁹), to refill without rounding.
    capacity: u128,
    /// Bits held now, in bit·nanoseconds.
    tokens: u128,
    last: Instant,
}

impl BitBucket {
    /// A full bucket allowing `share_percent` (1–100) of a bus at `bitrate` bit/s.
    pub fn new(bitrate: u32, share_percent: u8, now: Instant) -> Self {
        let rate = u64::from(bitrate) * u64::from(share_percent.clamp(1, 100)) / 100;
        let burst = (u128::from(rate) * BURST.as_nanos())
            .max(u128::from(ihex_proto::bus::frame_bits_worst(8)) * NANOS);
        BitBucket {
            rate,
            capacity: burst,
            tokens: burst,
            last: now,
        }
    }

    /// Bits per second the share allows.
    pub fn rate(&self) -> u64 {
        self.rate
    }

    /// Adds what `now - last` earned (time never runs backwards here).
    pub fn refill(&mut self, now: Instant) {
        let elapsed = now.saturating_duration_since(self.last);
        self.last = self.last.max(now);
        let earned = elapsed.as_nanos().saturating_mul(u128::from(self.rate));
        self.tokens = self.tokens.saturating_add(earned).min(self.capacity);
    }

    /// Takes `bits` if the bucket holds them.
    pub fn try_take(&mut self, bits: u32) -> bool {
        let cost = u128::from(bits) * NANOS;
        if self.tokens >= cost {
            self.tokens -= cost;
            true
        } else {
            false
        }
    }

    /// When the bucket will hold `bits` (now if it does).
    pub fn ready_at(&self, bits: u32) -> Instant {
        let cost = u128::from(bits) * NANOS;
        let short = cost.saturating_sub(self.tokens);
        if short == 0 || self.rate == 0 {
            return self.last;
        }
        let nanos = short.div_ceil(u128::from(self.rate));
        self.last + Duration::from_nanos(u64::try_from(nanos).unwrap_or(u64::MAX))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn never_more_than_the_share_plus_one_burst_over_a_window() {
        let t0 = Instant::now();
        let mut b = BitBucket::new(500_000, 50, t0);
        let frame = ihex_proto::bus::frame_bits_worst(8);
        let mut sent_bits = 0u64;
        let mut now = t0;
        // Ask for a frame every 50 µs (far more than the share) for one second.
        while now < t0 + Duration::from_secs(1) {
            b.refill(now);
            if b.try_take(frame) {
                sent_bits += u64::from(frame);
            }
            now += Duration::from_micros(50);
        }
        let allowed = 250_000 + 250_000 / 100; // one second at 50 %, plus the 10 ms burst
        assert!(sent_bits <= allowed, "{sent_bits} bits > {allowed}");
        // And the cap is not a starvation: at least 95 % of the share was used.
        assert!(sent_bits >= 237_500, "{sent_bits} bits");
    }

    #[test]
    fn ready_at_is_when_a_frame_fits() {
        let t0 = Instant::now();
        let mut b = BitBucket::new(500_000, 50, t0);
        while b.try_take(160) {}
        let at = b.ready_at(160);
        assert!(at > t0);
        b.refill(at);
        assert!(b.try_take(160));
    }
}
