//! Signal loops: one pull-up EXTI input per dock port, reporting raw levels (the core debounces).
//!
//! Every edge is reported, and the level is re-read every [`POLL_MS`] and reported when it differs
//! from the last report: an edge that lands while the previous one is being handled (EXTI is re-armed
//! only when the task waits again) cannot leave the core with a stale level.

use embassy_futures::select::select;
use embassy_stm32::exti::ExtiInput;
use embassy_stm32::mode::Async;
use embassy_time::Timer;
use ihex_proto::Port;

use super::watchdog::{beat, Beat};
use crate::event::{Event, EVENTS};

/// Level re-check period (also the heartbeat period).
pub const POLL_MS: u64 = 100;

/// Watches one dock port's loop. `active_low` comes from the pin map (low = docked).
#[embassy_executor::task(pool_size = 6)]
pub async fn signal_loop(port: Port, mut pin: ExtiInput<'static, Async>, active_low: bool) {
    let closed = |pin: &ExtiInput<'static, Async>| pin.is_low() == active_low;
    let mut reported = closed(&pin);
    EVENTS
        .send(Event::Loop {
            port,
            closed: reported,
        })
        .await;
    loop {
        let edge = matches!(
            select(pin.wait_for_any_edge(), Timer::after_millis(POLL_MS)).await,
            embassy_futures::select::Either::First(())
        );
        beat(Beat::Loop0 as usize + port.get() as usize);
        let now = closed(&pin);
        if edge || now != reported {
            reported = now;
            EVENTS.send(Event::Loop { port, closed: now }).await;
        }
    }
}
