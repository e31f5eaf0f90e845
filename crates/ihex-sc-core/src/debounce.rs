//! Signal-loop debouncing: a level counts only after it has stayed unchanged for [`DEBOUNCE_MS`].

use crate::{Millis, DEBOUNCE_MS};

/// The debounced state of one dock port's signal loop.
///
/// Loops are binary, so "the raw level differs from the stable one" is all the state needed: the
/// time the raw level last moved away from the stable level. Any report of the stable level cancels
/// it, so a contact bouncing for any length of time yields one change, `DEBOUNCE_MS` after its last
/// bounce, and a glitch shorter than `DEBOUNCE_MS` yields none.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub(crate) struct Debounce {
    /// The level in force (`true` = closed = docked). Every loop starts open.
    stable: bool,
    /// Since when the raw level has differed from `stable`, if it does.
    pending: Option<Millis>,
}

impl Debounce {
    /// The debounced level (`true` = closed).
    pub(crate) const fn closed(&self) -> bool {
        self.stable
    }

    /// Records the raw level seen at `now`.
    pub(crate) fn input(&mut self, closed: bool, now: Millis) {
        if closed == self.stable {
            self.pending = None;
        } else if self.pending.is_none() {
            self.pending = Some(now);
        }
    }

    /// When the pending level will count, if one is pending.
    pub(crate) fn deadline(&self) -> Option<Millis> {
        self.pending.map(|since| since.add_ms(DEBOUNCE_MS))
    }

    /// Commits a pending level that has been stable long enough; returns the new level if it changed.
    pub(crate) fn poll(&mut self, now: Millis) -> Option<bool> {
        let since = self.pending?;
        if now.since(since) < DEBOUNCE_MS {
            return None;
        }
        self.pending = None;
        self.stable = !self.stable;
        Some(self.stable)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bouncing_contact_changes_once_after_the_last_bounce() {
        let mut d = Debounce::default();
        for (i, level) in [true, false, true, false, true].into_iter().enumerate() {
            d.input(level, Millis(i as u64 * 5));
            assert_eq!(d.poll(Millis(i as u64 * 5)), None);
        }
        // The last edge was at 20 ms.
        assert_eq!(d.deadline(), Some(Millis(20 + DEBOUNCE_MS)));
        assert_eq!(d.poll(Millis(20 + DEBOUNCE_MS - 1)), None);
        assert_eq!(d.poll(Millis(20 + DEBOUNCE_MS)), Some(true));
        assert!(d.closed());
        assert_eq!(d.poll(Millis(1000)), None);
    }

    #[test]
    fn short_glitch_is_ignored() {
        let mut d = Debounce::default();
        d.input(true, Millis(0));
        d.input(false, Millis(DEBOUNCE_MS - 1));
        assert_eq!(d.deadline(), None);
        assert_eq!(d.poll(Millis(10 * DEBOUNCE_MS)), None);
        assert!(!d.closed());
    }

    #[test]
    fn repeated_reports_of_the_same_level_do_not_restart_the_timer() {
        let mut d = Debounce::default();
        d.input(true, Millis(0));
        d.input(true, Millis(30));
        assert_eq!(d.poll(Millis(DEBOUNCE_MS)), Some(true));
    }
}
