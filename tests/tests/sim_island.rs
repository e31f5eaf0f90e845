//! `sim-node` over real SocketCAN: the island scenarios of `crates/sim-node/tests/scenario`, the same
//! code the in-memory tests run, on a leased vcan interface. Every virtual node has its own raw socket
//! with its kernel acceptance filters; the test plays the gateway on another socket.
#![cfg(feature = "vcan")]

#[path = "../../crates/sim-node/tests/scenario/mod.rs"]
mod scenario;

use std::time::Duration;

use ihex_proto::{Message, NodeId, StateParts};
use ihex_tests::{can, time::scaled};
use scenario::id;
use sim_node::Link;

fn vcan() -> Link {
    Link::socketcan(can::lease())
}

#[tokio::test]
async fn boot() {
    scenario::boot(vcan()).await;
}

#[tokio::test]
async fn dock_and_undock() {
    scenario::dock_and_undock(vcan()).await;
}

#[tokio::test]
async fn bad_requests() {
    scenario::bad_requests(vcan()).await;
}

#[tokio::test]
async fn power_cycle() {
    scenario::power_cycle(vcan()).await;
}

#[tokio::test]
async fn off_bus() {
    scenario::off_bus(vcan()).await;
}

#[tokio::test]
async fn actuators() {
    scenario::actuators(vcan()).await;
}

#[tokio::test]
async fn firmware_update() {
    scenario::firmware_update(vcan()).await;
}

#[tokio::test]
async fn bounce() {
    scenario::bounce(vcan()).await;
}

#[tokio::test]
async fn uart_id() {
    scenario::uart_id(vcan()).await;
}

#[tokio::test]
async fn docked_at_start() {
    scenario::docked_at_start(vcan()).await;
}

#[tokio::test]
async fn can_assignment() {
    scenario::can_assignment(vcan()).await;
}

#[tokio::test]
async fn state_query() {
    scenario::state_query(vcan()).await;
}

/// Regression (issue #16): the virtual nodes stopped hearing the bus for good once their
/// interface went down and up. Now every endpoint reopens its socket: the island answers again,
/// commands, state queries and a new docking included.
#[tokio::test]
async fn nodes_hear_the_bus_again_after_the_interface_goes_down_and_up() {
    let iface = can::lease();
    let link = Link::socketcan(&iface);
    let (mut gw, island) = scenario::start(&link, scenario::ISLAND).await;
    let health = |seq| Message::HealthCheck { seq };
    let reply_from = |src: NodeId, seq: u8| {
        move |p: &ihex_proto::Packet| {
            p.src == src && matches!(p.msg, Message::HealthReply(h) if h.seq == seq)
        }
    };
    gw.send(id(0x111), health(1)).await;
    gw.expect("health reply before the outage", reply_from(id(0x111), 1))
        .await;

    can::set_link(&iface, false);
    // Long enough for every endpoint to notice and to back off a few times.
    tokio::time::sleep(Duration::from_millis(500)).await;
    can::set_link(&iface, true);

    // The first write after the outage may still report it (the socket's pending error goes to
    // whichever call comes first), and the nodes reopen on their own back-off: ask until answered.
    let deadline = tokio::time::Instant::now() + scaled(Duration::from_secs(15));
    let mut seq = 10u8;
    loop {
        seq += 1;
        if gw.try_send(NodeId::BROADCAST, health(seq)).await.is_ok() {
            let wait = scaled(Duration::from_millis(300));
            if gw.within(wait, reply_from(id(0x111), seq)).await.is_some()
                && gw.within(wait, reply_from(id(0x112), seq)).await.is_some()
            {
                break;
            }
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the island did not answer again after {iface} went down and up"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }

    // Fully working again: a state query, and a docking with its power-up and handshake.
    gw.send(
        id(0x112),
        Message::StateQuery {
            seq: 0x50,
            parts: StateParts(StateParts::IDENTITY),
        },
    )
    .await;
    // The identity group: Firmware, ImageHash, UidLow, UidHigh, Protocol, then End.
    assert_eq!(
        scenario::state_reply(&mut gw, id(0x112), 0x50).await.len(),
        6
    );
    scenario::dock_and_confirm(&mut gw, &island, 30).await;
    island.shutdown().await;
}
