//! The bridge's timers in one table (quinn-proto's `connection/timer.rs`): [`Timer`] names each
//! one, [`Bridge::timers`] reads their deadlines into a [`TimerTable`] whose
//! [`TimerTable::next_timeout`] is [`Bridge::poll_timeout`], and [`Bridge::handle_timeout`] runs
//! every timer's expiry in the order of [`Timer::VALUES`]. Each expiry acts only on what is due by
//! `now`, so running all of them is what a timeout means.
//!
//! A new timer (a lease's end, a procedure step) is one more line in the `timers!` list below; the
//! compiler then asks for its arm in [`Bridge::deadline`] and in [`Bridge::expire`].

use std::time::Instant;

use super::{dock, Bridge, DockParts, FrameFate, DROP_REPORT_PERIOD, TRANSMIT_CONFIRM_TIMEOUT};
use crate::event::{Event, PublicationsDropped};

/// Declares [`Timer`] and [`Timer::VALUES`] from one list, so that no timer is left out of the
/// table.
macro_rules! timers {
    ($($(#[$doc:meta])* $name:ident,)+) => {
        /// One of the bridge's timers.
        #[derive(Clone, Copy, PartialEq, Eq, Debug)]
        pub(crate) enum Timer {
            $($(#[$doc])* $name,)+
        }

        impl Timer {
            /// Every timer, in the order [`Bridge::handle_timeout`] runs their expiries.
            pub(crate) const VALUES: [Timer; [$(Timer::$name),+].len()] = [$(Timer::$name),+];
        }
    };
}

timers! {
    /// A firmware update's rounds and waits.
    FwUpdate,
    /// A frame handed to the adapter and not confirmed within [`TRANSMIT_CONFIRM_TIMEOUT`].
    TransmitConfirm,
    /// A command's deadline: withdrawn while queued, `timeout` without an ack.
    Commands,
    /// A state query's answer.
    ReadBack,
    /// An earlier run's retained `online` document of a node this run has not heard.
    Inherited,
    /// The pending docking's handshake; then a docked mobile element recorded nowhere is paired.
    Docking,
    /// The next broadcast health check and the lost-node count.
    Health,
    /// The next report of dropped publications.
    DropReport,
    /// The end of the lost period from start, until which the documents of nodes not read back
    /// are held (released by `finish_input`, which every input ends with).
    Hold,
    /// The earliest end of a lease.
    Leases,
    /// The earliest timeout of a procedure's step.
    Procedures,
}

/// The deadline of every [`Timer`], by [`Timer::VALUES`] index.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TimerTable {
    deadlines: [Option<Instant>; Timer::VALUES.len()],
}

impl TimerTable {
    /// The deadline of `timer`, if it runs.
    #[cfg(test)]
    pub(crate) fn get(&self, timer: Timer) -> Option<Instant> {
        self.deadlines[timer as usize]
    }

    /// The earliest deadline.
    pub(crate) fn next_timeout(&self) -> Option<Instant> {
        self.deadlines.iter().flatten().min().copied()
    }
}

impl Bridge {
    /// Every timer's deadline now.
    pub(crate) fn timers(&self) -> TimerTable {
        TimerTable {
            deadlines: Timer::VALUES.map(|t| self.deadline(t)),
        }
    }

    /// When `timer` expires next (`None`: it does not run now).
    fn deadline(&self, timer: Timer) -> Option<Instant> {
        match timer {
            Timer::FwUpdate => self.fw.deadline(),
            Timer::TransmitConfirm => self
                .out
                .transmit
                .oldest_in_flight()
                .map(|t| t + TRANSMIT_CONFIRM_TIMEOUT),
            Timer::Commands => {
                let queued = self.out.transmit.next_not_after();
                match (self.pending.next_deadline(), queued) {
                    (Some(a), Some(b)) => Some(a.min(b)),
                    (a, b) => a.or(b),
                }
            }
            Timer::ReadBack => self.readback.next_deadline(),
            Timer::Inherited => self.inherited.next_deadline(),
            Timer::Docking => self.docking.deadline(),
            Timer::Health => Some(self.health.next_deadline()),
            Timer::Leases => self.lease_table.next_deadline(),
            Timer::Procedures => self.procedures.next_deadline(),
            Timer::DropReport => self
                .out
                .publish
                .has_unreported()
                .then_some(self.next_drop_report),
            Timer::Hold => (!self.held.is_empty()).then_some(self.hold_until),
        }
    }

    /// Carries out what `timer` has due by `now`.
    pub(super) fn expire(&mut self, timer: Timer, now: Instant) {
        match timer {
            Timer::FwUpdate => self.fw.tick(now, &mut self.out),
            Timer::TransmitConfirm => {
                let Some(cutoff) = now.checked_sub(TRANSMIT_CONFIRM_TIMEOUT) else {
                    return;
                };
                for (p, owner) in self.out.transmit.expire_in_flight(cutoff) {
                    tracing::warn!(
                        ?p,
                        "frame not confirmed on the bus within {} ms",
                        TRANSMIT_CONFIRM_TIMEOUT.as_millis()
                    );
                    let why = "the CAN interface did not confirm sending it";
                    self.on_frame_fate(p, owner, FrameFate::Unconfirmed(why), now);
                }
            }
            Timer::Commands => self.pending.expire(now, &mut self.out),
            Timer::Leases => self.expire_leases(now),
            Timer::Procedures => self.expire_procedures(now),
            Timer::ReadBack => self.readback.expire(now),
            Timer::Inherited => self.republish_inherited(now),
            Timer::Docking => {
                let steps = self.docking.tick(now);
                self.apply(steps, now);
                self.adopt_unrecorded(now);
            }
            Timer::Health => {
                let Bridge {
                    registry,
                    docking,
                    pending,
                    health,
                    diagnostics,
                    readback,
                    out,
                    ..
                } = self;
                health.tick(registry, now, out, |id, out| {
                    readback.on_lost(id);
                    let steps = docking.on_lost(id);
                    let parts = DockParts {
                        pending: &mut *pending,
                        docking: &mut *docking,
                        diagnostics: &mut *diagnostics,
                        readback: &*readback,
                    };
                    dock::apply(steps, parts, now, out);
                });
            }
            Timer::DropReport => {
                if !(self.out.publish.has_unreported() && now >= self.next_drop_report) {
                    return;
                }
                let (dropped, events) = self.out.publish.take_unreported();
                let total = self.out.publish.total_dropped();
                self.out
                    .emit(Event::PublicationsDropped(PublicationsDropped {
                        dropped,
                        total,
                        events,
                    }));
                self.next_drop_report = now + DROP_REPORT_PERIOD;
            }
            // What is due is released by `finish_input` after every timer has run.
            Timer::Hold => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bridge::test_support::*;

    /// `poll_timeout` is the earliest deadline of the table, and a bridge with a command waiting
    /// for its ack has that command's deadline in it.
    #[test]
    fn poll_timeout_is_the_tables_earliest_deadline() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_command(br#"{"cmd":"identify","node":"2","seconds":1}"#, t0);
        let t = b.timers();
        assert!(t.get(Timer::Commands).is_some());
        assert!(t.get(Timer::Health).is_some());
        assert_eq!(Some(b.poll_timeout()), t.next_timeout());
        let earliest = Timer::VALUES.iter().filter_map(|&x| t.get(x)).min();
        assert_eq!(t.next_timeout(), earliest);
    }
}
