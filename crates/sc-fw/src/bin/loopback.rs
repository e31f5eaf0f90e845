//! Bring-up self-test: bxCAN in loopback + silent mode sends iHEX frames to itself and checks them.
//!
//! Checks, each printed over defmt/RTT as PASS or FAIL: the bit timing register holds the protocol's
//! timing; the filter banks hold the protocol's register values; frames to this node and broadcasts
//! come back decoded identical to what was sent; a frame to another node is dropped by the hardware
//! filters. The green LED (LD2) then stays on for pass or blinks fast for fail. Silent mode keeps the
//! test off the real bus, so it is safe on a wired island. Needs no transceiver.
#![no_std]
#![no_main]

use defmt::{error, info, unwrap};
use embassy_executor::Spawner;
use embassy_stm32::can::{Can, Frame};
use embassy_stm32::gpio::{Level, Output, Speed};
use embassy_stm32::{bind_interrupts, can, peripherals};
use embassy_time::{with_timeout, Duration, Timer};
use ihex_proto::{Message, NodeId, Packet, Port};
use ihex_sc_fw::{can as sc_can, clock, take_board};
use {defmt_rtt as _, panic_probe as _};

bind_interrupts!(struct Irqs {
    USB_LP_CAN_RX0 => can::Rx0InterruptHandler<peripherals::CAN>;
    CAN_RX1 => can::Rx1InterruptHandler<peripherals::CAN>;
    CAN_SCE => can::SceInterruptHandler<peripherals::CAN>;
    USB_HP_CAN_TX => can::TxInterruptHandler<peripherals::CAN>;
});

/// The node ID the test pretends to have.
const OWN: u16 = 0x123;

#[embassy_executor::main]
async fn main(_spawner: Spawner) {
    let p = embassy_stm32::init(clock::config());
    let b = take_board!(p);
    let mut led = Output::new(b.status_led, Level::Low, Speed::Low);
    let own = unwrap!(NodeId::new_sc(OWN));
    let other = unwrap!(NodeId::new_sc(OWN + 1));
    let mut failures = 0u32;
    let mut check = |name: &str, ok: bool| {
        if ok {
            info!("PASS {=str}", name);
        } else {
            error!("FAIL {=str}", name);
            failures += 1;
        }
    };

    let timing = unwrap!(sc_can::bit_timing());
    info!(
        "bit timing {} -> {} bit/s, sample point {} per mille",
        timing,
        timing.bitrate(ihex_sc_fw::board::APB1_HZ),
        timing.sample_point_permille()
    );
    let mut can = Can::new(p.CAN, b.can_rx, b.can_tx, Irqs);
    can.modify_config()
        .set_bit_timing(unwrap!(sc_can::nominal(&timing)))
        .set_loopback(true)
        .set_silent(true)
        .set_automatic_retransmit(true);
    let banks = unwrap!(sc_can::banks_for(Some(own)));
    let applied = sc_can::apply_filters(&mut can.modify_filters(), &banks).is_ok();
    check("filters accepted by embassy", applied);
    can.enable().await;
    check(
        "bit timing register = protocol timing",
        sc_can::verify_bit_timing(&timing),
    );
    check(
        "filter bank registers = protocol banks",
        sc_can::verify_filters(&banks),
    );

    let port = unwrap!(Port::new(3));
    let cases: [(Packet, bool, &str); 5] = [
        (
            Packet::command(own, Message::PowerSet { seq: 1, on: true }),
            true,
            "PowerSet to own ID comes back",
        ),
        (
            Packet::command(own, Message::DockConfirm { seq: 2, port }),
            true,
            "DockConfirm to own ID comes back",
        ),
        (
            Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: 3 }),
            true,
            "broadcast HealthCheck comes back",
        ),
        (
            Packet::command(other, Message::Identify { seq: 4, seconds: 5 }),
            false,
            "frame to another node is filtered out",
        ),
        (
            Packet::report(own, Message::DockDetected { port }),
            false,
            "frame to the gateway is filtered out",
        ),
    ];
    for (packet, expect, name) in cases {
        let Some(frame) = packet.to_frame::<Frame>() else {
            check(name, false);
            continue;
        };
        can.write(&frame).await;
        let got = with_timeout(Duration::from_millis(50), can.read()).await;
        let ok = match (got, expect) {
            (Ok(Ok(env)), true) => Packet::from_frame(&env.frame) == Ok(packet),
            (Err(_timeout), false) => true,
            (Ok(Ok(env)), false) => {
                error!("unexpected frame {}", env.frame);
                false
            }
            (Ok(Err(e)), _) => {
                error!("bus error {}", e);
                false
            }
            (Err(_), true) => false,
        };
        check(name, ok);
    }

    if failures == 0 {
        info!("loopback self-test PASSED");
        led.set_high();
        loop {
            Timer::after_secs(1).await;
        }
    } else {
        error!("loopback self-test FAILED ({} checks)", failures);
        loop {
            led.toggle();
            Timer::after_millis(100).await;
        }
    }
}
