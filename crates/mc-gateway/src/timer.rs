//! A task loop's one deadline timer: registered with tokio once, moved only when its deadline is.
//!
//! A `sleep_until` made afresh on every turn of a loop inserts a timer into tokio's wheel and
//! removes it again each time. Worse, tokio 1.54 wakes its own I/O driver (an eventfd write, and a
//! spurious return of the next `epoll_wait`) whenever a timer is registered earlier than the wake-up
//! it computed when it last parked, which a fresh timer per turn does far more often than a timer
//! that stays registered: moving a registered timer later is one compare-and-swap.

use std::future::Future;
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use tokio::time::Sleep;

/// How far ahead a disarmed timer is parked: it never fires in a gateway's lifetime, and moving it
/// there is the cheap way (later, not deregistered), so arming it again stays cheap too.
const PARKED: Duration = Duration::from_secs(60 * 60 * 24 * 365);

/// The deadline a loop waits for, kept across its turns.
pub struct Timer {
    sleep: Pin<Box<Sleep>>,
    /// The deadline set, `None` when disarmed.
    deadline: Option<Instant>,
}

impl Default for Timer {
    fn default() -> Self {
        Timer::new()
    }
}

impl Timer {
    /// A disarmed timer.
    pub fn new() -> Timer {
        let parked = tokio::time::Instant::now() + PARKED;
        Timer {
            sleep: Box::pin(tokio::time::sleep_until(parked)),
            deadline: None,
        }
    }

    /// Fires at `deadline`, or never with `None`. Setting the deadline it already has does nothing.
    pub fn set(&mut self, deadline: Option<Instant>) {
        if deadline == self.deadline {
            return;
        }
        let at = match deadline {
            Some(d) => tokio::time::Instant::from_std(d),
            None => tokio::time::Instant::now() + PARKED,
        };
        self.sleep.as_mut().reset(at);
        self.deadline = deadline;
    }

    /// Completes once the deadline has passed (at once if it already has); pending forever while
    /// disarmed. Cancel-safe: it only waits.
    pub fn expired(&mut self) -> Expired<'_> {
        Expired(self)
    }
}

/// The future of [`Timer::expired`].
pub struct Expired<'a>(&'a mut Timer);

impl Future for Expired<'_> {
    type Output = ();

    fn poll(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<()> {
        let timer = &mut *self.0;
        // Disarmed: no waker is kept, as only the loop that owns the timer arms it, before its
        // next wait.
        if timer.deadline.is_none() {
            return Poll::Pending;
        }
        timer.sleep.as_mut().poll(cx)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Long enough to tell "fired" from "not yet" on a loaded machine: timers never fire early.
    const STEP: Duration = Duration::from_millis(40);

    async fn fires_within(timer: &mut Timer, limit: Duration) -> bool {
        tokio::time::timeout(limit, timer.expired()).await.is_ok()
    }

    #[tokio::test]
    async fn a_timer_fires_at_its_deadline_and_never_while_disarmed() {
        let mut timer = Timer::new();
        assert!(
            !fires_within(&mut timer, STEP).await,
            "disarmed from the start"
        );
        let start = Instant::now();
        timer.set(Some(start + STEP));
        assert!(fires_within(&mut timer, 50 * STEP).await);
        assert!(start.elapsed() >= STEP);
        // Expired and left as it is, it stays expired: the loop must move it.
        assert!(fires_within(&mut timer, STEP).await);
        timer.set(None);
        assert!(!fires_within(&mut timer, 2 * STEP).await, "disarmed again");
    }

    #[tokio::test]
    async fn a_deadline_moves_later_and_earlier() {
        let mut timer = Timer::new();
        let start = Instant::now();
        timer.set(Some(start + STEP));
        // Polled once, so registered with the driver at the first deadline.
        assert!(!fires_within(&mut timer, Duration::from_millis(1)).await);
        timer.set(Some(start + 3 * STEP));
        assert!(fires_within(&mut timer, 50 * STEP).await);
        assert!(start.elapsed() >= 3 * STEP, "not at the first deadline");
        let start = Instant::now();
        timer.set(Some(start + 50 * STEP));
        assert!(!fires_within(&mut timer, Duration::from_millis(1)).await);
        timer.set(Some(start + STEP));
        assert!(fires_within(&mut timer, 20 * STEP).await, "moved earlier");
    }
}
