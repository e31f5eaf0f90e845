//! Independent watchdog, fed only while every periodic task shows progress.
//!
//! Tasks that loop on a timer (node, CAN status, each signal loop) bump a heartbeat slot at least
//! every 100 ms. This task checks the slots every [`CHECK_MS`]; a slot that has not moved for two
//! checks in a row means a hung task, and the IWDG is no longer refreshed, so the chip resets after
//! [`TIMEOUT_MS`]. A hung executor stops this task too, with the same result. After any reset the relay
//! pin is a floating input held low by its external pull-down: the dock is unpowered (safe state).

use core::sync::atomic::{AtomicU32, Ordering};

use defmt::error;
use embassy_stm32::gpio::Output;
use embassy_stm32::peripherals::IWDG;
use embassy_stm32::wdg::IndependentWatchdog;
use embassy_stm32::Peri;
use embassy_time::Timer;

/// IWDG timeout.
pub const TIMEOUT_MS: u32 = 2_000;
/// Heartbeat check period.
pub const CHECK_MS: u64 = 500;

/// A heartbeat slot.
#[derive(Clone, Copy, defmt::Format)]
pub enum Beat {
    /// The node task.
    Node = 0,
    /// The CAN status poller.
    CanStatus = 1,
    /// Signal loop 0 (loop `n` uses slot `Loop0 + n`).
    Loop0 = 2,
}

/// Number of slots: node, CAN status, six signal loops.
pub const SLOTS: usize = 8;
static BEATS: [AtomicU32; SLOTS] = [const { AtomicU32::new(0) }; SLOTS];

/// Records progress of the task owning `slot` (`Beat::Loop0 as usize + port` for the loops).
pub fn beat(slot: usize) {
    if let Some(b) = BEATS.get(slot) {
        b.fetch_add(1, Ordering::Relaxed);
    }
}

/// Starts the IWDG and feeds it while every heartbeat slot moves; toggles the status LED meanwhile.
#[embassy_executor::task]
pub async fn watchdog(iwdg: Peri<'static, IWDG>, mut status_led: Output<'static>) {
    // Freeze the IWDG while a debugger halts the core, so stepping through code does not reset it.
    embassy_stm32::pac::DBGMCU
        .apb1fzr()
        .modify(|w| w.set_iwdg(true));
    let mut wdg = IndependentWatchdog::new(iwdg, TIMEOUT_MS * 1_000);
    wdg.unleash();
    let mut last = [0u32; SLOTS];
    let mut stale = [0u8; SLOTS];
    loop {
        Timer::after_millis(CHECK_MS).await;
        let mut healthy = true;
        for i in 0..SLOTS {
            let now = BEATS[i].load(Ordering::Relaxed);
            stale[i] = if now == last[i] {
                stale[i].saturating_add(1)
            } else {
                0
            };
            last[i] = now;
            if stale[i] >= 2 {
                healthy = false;
                if stale[i] == 2 {
                    error!("watchdog: task in heartbeat slot {} stopped; letting the IWDG reset the node", i);
                }
            }
        }
        if healthy {
            wdg.pet();
            status_led.toggle();
        }
    }
}
