//! CAN receive, transmit and error-state tasks around embassy's bxCAN halves.
//!
//! Bus-off recovery is the controller's own (ABOM, set by embassy when it enables the peripheral):
//! after 128 × 11 recessive bits it rejoins the bus; meanwhile the transmitter waits for a free
//! mailbox and the node's transmit queue fills and drops (counted). The status task reports the
//! error counters to the core, which puts them in health replies and fault reports.

use defmt::{info, warn};
use embassy_futures::select::{select, Either};
use embassy_stm32::can::{CanRx, CanTx, Frame};
use embassy_time::Timer;

use super::watchdog::{beat, Beat};
use crate::can::{apply_filters, banks_for, rx_frame, status, verify_filters};
use crate::event::{Event, CAN_TX, EVENTS, FILTERS, FILTERS_DONE};

/// Error counter poll period.
pub const STATUS_POLL_MS: u64 = 100;

/// Receives frames for the node; reinstalls the acceptance filters when the node ID changes.
#[embassy_executor::task]
pub async fn can_rx(mut rx: CanRx<'static>) {
    loop {
        match select(rx.read(), FILTERS.wait()).await {
            Either::First(Ok(env)) => EVENTS.send(Event::Frame(rx_frame(&env.frame))).await,
            Either::First(Err(e)) => warn!("can rx: bus error {}", e),
            Either::Second(own) => match banks_for(own) {
                Ok(banks) => match apply_filters(&mut rx.modify_filters(), &banks) {
                    Ok(n) => {
                        info!("CAN filters for {}: {} bank(s)", own, n);
                        verify_filters(&banks);
                        FILTERS_DONE.signal(());
                    }
                    Err(e) => warn!("can filters not applied: {}", e),
                },
                Err(e) => warn!("can filters not computed: {}", e),
            },
        }
    }
}

/// Transmits the node's frames in order.
#[embassy_executor::task]
pub async fn can_tx(mut tx: CanTx<'static>) {
    loop {
        let packet = CAN_TX.receive().await;
        let Some(frame) = packet.to_frame::<Frame>() else {
            warn!("can tx: packet does not encode: {}", packet);
            continue;
        };
        tx.write(&frame).await;
    }
}

/// Polls the error counters; reports changes (and once a second regardless) to the node.
#[embassy_executor::task]
pub async fn can_status() {
    let mut last = None;
    let mut ticks = 0u32;
    loop {
        Timer::after_millis(STATUS_POLL_MS).await;
        beat(Beat::CanStatus as usize);
        let s = status();
        ticks = ticks.wrapping_add(1);
        if last != Some(s) || ticks.is_multiple_of(10) {
            if last.map(|l: crate::event::CanStatus| l.bus_off) != Some(s.bus_off) && s.bus_off {
                warn!(
                    "CAN bus-off (tec {}, rec {}); hardware recovery running",
                    s.tec, s.rec
                );
            }
            last = Some(s);
            // try_send: a full queue means the node is busy; the next poll repeats the state.
            let _ = EVENTS.try_send(Event::CanStatus(s));
        }
    }
}
