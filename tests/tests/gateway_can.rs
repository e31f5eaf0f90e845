//! Gateway end to end over vcan: error frames, undecodable frames and an interface going down and up
//! are reported as `bus_error` events, and the gateway serves again afterwards.
#![cfg(feature = "vcan")]

mod gateway_support;

use embedded_can::{ExtendedId, Frame as _};
use gateway_support::WAIT;
use gateway_support::{id, Rig};
use ihex_proto::{Message, Packet};
use ihex_tests::can::set_link;
use socketcan::{tokio::CanSocket, CanErrorFrame, CanFrame};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bus_errors_are_reported_and_the_gateway_recovers() {
    let mut rig = Rig::start("canerr").await;
    let events = rig.events();

    // The interface goes down and comes back: reported both ways, and commands work again.
    // (Each kind of bus error is rate-limited to one event per second, so every step below
    // produces a different kind.)
    set_link(&rig.iface, false);
    rig.client
        .expect_event(&events, "bus_error", |p| p["error"] == "interface_down")
        .await;
    set_link(&rig.iface, true);
    rig.client
        .expect_event(&events, "bus_error", |p| p["error"] == "recovered")
        .await;
    // The gateway transmits again: its LED command shows up on the wire. (The simulated nodes
    // reopen their own sockets on their own back-off, so no ack is awaited here; their recovery
    // is tested in sim_island.rs.)
    let sock = CanSocket::open(&rig.iface).expect("reopen test socket");
    rig.command(r#"{"cmd":"led","node":"111","color":"green"}"#)
        .await;
    let seen = ihex_tests::within_or_panic(WAIT, "LedSet on the wire after recovery", async {
        loop {
            let f = sock.read_frame().await.expect("read");
            if let Ok(p) = Packet::from_frame(&f) {
                if p.dest == id("111") && matches!(p.msg, Message::LedSet { .. }) {
                    return p;
                }
            }
        }
    })
    .await;
    assert_eq!(seen.src, ihex_proto::NodeId::GATEWAY);

    // A frame to the gateway of an unassigned kind.
    let junk = CanFrame::new(ExtendedId::new(31 << 24 | 0x111).unwrap(), &[1, 2, 3]).unwrap();
    sock.write_frame(junk).await.expect("write junk");
    rig.client
        .expect_event(&events, "bus_error", |p| p["error"] == "undecodable_frame")
        .await;

    // A controller error frame and a bus-off, as a real driver would deliver them.
    let ctrl = CanErrorFrame::new_error(0x04, &[0, 0x04, 0, 0, 0, 0, 0, 0]).unwrap();
    sock.write_frame(CanFrame::Error(ctrl))
        .await
        .expect("write error frame");
    let e = rig
        .client
        .expect_event(&events, "bus_error", |p| p["error"] == "error_frame")
        .await;
    assert!(e["payload"]["message"].is_string(), "{e}");
    let off = CanErrorFrame::new_error(0x40, &[]).unwrap();
    sock.write_frame(CanFrame::Error(off))
        .await
        .expect("write bus-off");
    rig.client
        .expect_event(&events, "bus_error", |p| p["error"] == "bus_off")
        .await;
    rig.shutdown().await;
}
