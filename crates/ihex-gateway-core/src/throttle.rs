//! Rate limit for error events: at most one event per kind of error per window, so that a babbling
//! node or a noisy bus cannot flood MQTT. The next event published for a kind carries the number of
//! events suppressed since the previous one.

use std::collections::HashMap;
use std::time::{Duration, Instant};

/// Per-key rate limiter (sans-IO: the caller passes `now`).
#[derive(Debug)]
pub struct Throttle {
    window: Duration,
    slots: HashMap<String, Slot>,
}

#[derive(Debug)]
struct Slot {
    last: Instant,
    suppressed: u32,
}

impl Throttle {
    /// Keys kept before quiet ones are forgotten.
    pub const MAX_KEYS: usize = 1024;

    /// One event per key per `window`.
    pub fn new(window: Duration) -> Self {
        Throttle {
            window,
            slots: HashMap::new(),
        }
    }

    /// `Some(suppressed)` if an event for `key` may be published now (with the count of events
    /// dropped since the last one), `None` if it must be dropped.
    pub fn admit(&mut self, key: &str, now: Instant) -> Option<u32> {
        if self.slots.len() >= Self::MAX_KEYS && !self.slots.contains_key(key) {
            // Keys come from bus input (node IDs, fault codes): forget the quiet ones rather than
            // grow without bound. A forgotten key only loses its suppressed count.
            let window = self.window;
            self.slots
                .retain(|_, s| now.saturating_duration_since(s.last) < window);
        }
        match self.slots.get_mut(key) {
            Some(slot) if now.saturating_duration_since(slot.last) < self.window => {
                slot.suppressed = slot.suppressed.saturating_add(1);
                None
            }
            Some(slot) => {
                let n = slot.suppressed;
                *slot = Slot {
                    last: now,
                    suppressed: 0,
                };
                Some(n)
            }
            None => {
                self.slots.insert(
                    key.to_owned(),
                    Slot {
                        last: now,
                        suppressed: 0,
                    },
                );
                Some(0)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_per_window_per_key_with_suppressed_count() {
        let t0 = Instant::now();
        let w = Duration::from_secs(1);
        let mut t = Throttle::new(w);
        assert_eq!(t.admit("a", t0), Some(0));
        assert_eq!(t.admit("a", t0 + Duration::from_millis(10)), None);
        assert_eq!(t.admit("a", t0 + Duration::from_millis(999)), None);
        assert_eq!(
            t.admit("b", t0 + Duration::from_millis(999)),
            Some(0),
            "keys are independent"
        );
        assert_eq!(t.admit("a", t0 + w), Some(2));
        assert_eq!(t.admit("a", t0 + w + w), Some(0));
    }

    #[test]
    fn key_count_stays_bounded() {
        let t0 = Instant::now();
        let w = Duration::from_secs(1);
        let mut t = Throttle::new(w);
        for k in 0..Throttle::MAX_KEYS {
            assert_eq!(t.admit(&k.to_string(), t0), Some(0));
        }
        // A new key after the window: the quiet ones are dropped.
        assert_eq!(t.admit("new", t0 + w), Some(0));
        assert_eq!(t.slots.len(), 1);
        // Within the window nothing can be dropped, so the map may exceed the bound only then.
        assert_eq!(t.admit("0", t0 + w), Some(0));
    }
}
