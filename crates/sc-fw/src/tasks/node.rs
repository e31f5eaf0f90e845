//! The node task: owns the `ihex_sc_core::Node` and the flash, feeds it the events, runs its timers
//! and carries out its outputs — the firmware-update ones on the DFU slot and the bootloader state
//! ([`crate::update::Updater`]).

use defmt::{info, warn};
use embassy_futures::select::{select, Either};
use embassy_time::{with_timeout, Duration, Instant, Timer};
use ihex_proto::BootRole;
use ihex_sc_core::{FlashError, Millis, Node, Output};

use super::relay::Relay;
use super::watchdog::{beat, Beat};
use crate::config;
use crate::event::{Event, BUZZER, CAN_TX, EVENTS, FILTERS, FILTERS_DONE, LED, UART_TX};
use crate::record::Record;
use crate::update::{Part, Updater};

/// Longest sleep between two passes (keeps the heartbeat going when the core has no timer pending).
pub const MAX_SLEEP_MS: u64 = 100;
/// How long to wait for the CAN receive task to reinstall the filters before sending on.
pub const FILTER_WAIT_MS: u64 = 100;

/// Milliseconds since boot, the core's clock.
pub fn now() -> Millis {
    Millis(Instant::now().as_millis())
}

/// Runs the node forever. `self_test` is the start-up self-test's verdict (a new image on trial
/// confirms itself only if it passed).
#[embassy_executor::task]
pub async fn node(
    node: &'static mut Node,
    mut flash: Part,
    mut updater: Updater,
    mut relay: Relay,
    role: BootRole,
    self_test: bool,
) {
    let mut dropped_frames = 0u32;
    node.handle_self_test(self_test, now());
    let mut io = Io {
        flash: &mut flash,
        updater: &mut updater,
        role,
        dropped: &mut dropped_frames,
    };
    // The core reports its actuators as changed on the first call after `Node::new`.
    publish(node, &mut relay);
    drain(node, &mut io).await;
    loop {
        let t = now();
        let wake = match node.poll_at() {
            Some(at) if at.0 <= t.0 + MAX_SLEEP_MS => at,
            _ => t.add_ms(MAX_SLEEP_MS),
        };
        match select(EVENTS.receive(), Timer::at(Instant::from_millis(wake.0))).await {
            Either::First(ev) => {
                let t = now();
                match ev {
                    Event::Frame(f) => node.handle_frame(
                        f.raw_id,
                        f.extended,
                        f.remote,
                        &f.data[..f.len as usize],
                        t,
                    ),
                    Event::Loop { port, closed } => node.handle_loop_level(port, closed, t),
                    Event::UartByte(b) => node.handle_uart_byte(b, t),
                    Event::CanStatus(s) => node.handle_can_status(s.tec, s.rec, s.bus_off, t),
                    Event::BuzzerDone => node.handle_buzzer_done(t),
                }
            }
            Either::Second(()) => {}
        }
        // Timers due by now run whatever woke us.
        if node.poll_at().is_some_and(|at| at <= now()) {
            node.tick(now());
        }
        beat(Beat::Node as usize);
        // Actuators first: the relay must be off before the DockRemoved that goes with it leaves.
        publish(node, &mut relay);
        drain(node, &mut io).await;
    }
}

/// What carrying out the outputs needs.
struct Io<'a> {
    flash: &'a mut Part,
    updater: &'a mut Updater,
    role: BootRole,
    dropped: &'a mut u32,
}

fn publish(node: &mut Node, relay: &mut Relay) {
    if node.actuators_changed() {
        let a = node.actuators();
        relay.set(a.relay);
        LED.signal(a.led);
        BUZZER.signal(a.buzzer);
    }
}

async fn drain(node: &mut Node, io: &mut Io<'_>) {
    while let Some(out) = node.poll_output() {
        match out {
            Output::Frame(p) => {
                if CAN_TX.try_send(p).is_err() {
                    *io.dropped = io.dropped.wrapping_add(1);
                    warn!(
                        "can tx queue full, frame dropped ({} so far): {}",
                        *io.dropped, p
                    );
                }
            }
            Output::Uart(bytes) => {
                if UART_TX.try_send(bytes).is_err() {
                    warn!("uart tx queue full, reply dropped");
                }
            }
            Output::StoreId(id) => {
                let record = Record {
                    node_id: id,
                    role: io.role,
                };
                match config::store(io.flash, &record) {
                    Ok(()) => info!("node ID {} stored in flash", id),
                    Err(e) => {
                        warn!("storing node ID {} failed: {}", id, e);
                        node.handle_store_failed(now());
                    }
                }
            }
            Output::FiltersChanged => {
                // The frames queued after this one are sent from the new ID: install its filters
                // first so that the answers to them are not filtered out.
                FILTERS_DONE.reset();
                FILTERS.signal(node.node_id());
                if with_timeout(Duration::from_millis(FILTER_WAIT_MS), FILTERS_DONE.wait())
                    .await
                    .is_err()
                {
                    warn!("CAN filters not confirmed within {} ms", FILTER_WAIT_MS);
                }
            }
            // Firmware update: each result goes straight back to the core, whose next outputs
            // this loop then carries out.
            Output::EraseDfu { len } => {
                info!("update: erasing {} bytes of the DFU slot", len);
                let r = io.updater.erase_dfu(len).await.map_err(|_| FlashError);
                node.handle_fw_erased(r, now());
            }
            Output::WriteDfu { offset, data } => {
                if io.updater.write_dfu(offset, &data).is_err() {
                    node.handle_fw_write_failed(now());
                }
            }
            Output::HashDfu { offset, len } => {
                let r = io
                    .updater
                    .hash_dfu(offset, len)
                    .await
                    .map_err(|_| FlashError);
                node.handle_fw_hashed(r, now());
            }
            Output::MarkUpdated => {
                let r = io.updater.mark_updated().map_err(|_| FlashError);
                if r.is_ok() {
                    info!("update: verified and marked; resetting into it shortly");
                }
                node.handle_fw_marked(r, now());
            }
            Output::MarkBooted => {
                let r = io.updater.mark_booted().map_err(|_| FlashError);
                if r.is_ok() {
                    info!("update: this image is confirmed");
                }
                node.handle_fw_confirmed(r, now());
            }
            Output::Reset => {
                // The core waited for its last frames to leave; the bootloader takes it from here,
                // keeping the relay on if the block says so.
                info!("update: reset");
                crate::retained::write(&node.retained());
                cortex_m::peripheral::SCB::sys_reset();
            }
        }
    }
}
