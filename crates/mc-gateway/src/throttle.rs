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
}
