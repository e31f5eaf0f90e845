//! Gateway end to end: the broker is stopped and restarted mid-run; the gateway reconnects,
//! re-subscribes, republishes its retained state and goes on publishing. Shutdown leaves `offline`.
#![cfg(feature = "vcan")]

mod gateway_support;

use std::time::Duration;

use gateway_support::{id, Client, Rig};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gateway_survives_a_broker_restart() {
    let mut rig = Rig::start("restart").await;
    let topics = rig.gateway.config.topics.clone();
    rig.command_ok(r#"{"cmd":"led","node":"111","color":"red""#, "before")
        .await;

    rig.broker().stop();
    // Things happen on the island while the broker is away...
    rig.island.dock(id("3"), id("112"), 2).await.expect("dock");
    tokio::time::sleep(Duration::from_millis(500)).await;
    rig.broker().restart().expect("restart mosquitto");

    // ...a fresh client (the restarted broker kept nothing) sees the gateway back online, the state
    // made during the outage in the retained node states, and commands work again.
    let mut fresh = Client::connect(rig.addr, "late-dashboard", &["restart/#".to_owned()]);
    fresh
        .expect("online again", |m| {
            m.topic == topics.availability && m.payload == b"online"
        })
        .await;
    let s112 = topics.node_state(id("112"));
    fresh
        .expect("112's retained state with the docking", |m| {
            m.topic == s112 && m.json()["connections"].to_string().contains("\"3\"")
        })
        .await;
    fresh
        .client
        .publish(
            &topics.commands,
            rumqttc::QoS::AtLeastOnce,
            false,
            r#"{"cmd":"led","node":"111","color":"green","request_id":"after"}"#,
        )
        .await
        .unwrap();
    let r = fresh
        .expect_event(&topics.events, "command_result", |p| {
            p["request_id"] == "after"
        })
        .await;
    assert_eq!(r["payload"]["result"], "ok");
    assert_eq!(
        rig.island.actuators(id("111")).await.unwrap().led.duty.g,
        255
    );

    // Clean shutdown leaves `offline` retained.
    let broker = rig.addr;
    rig.gateway.shutdown().await;
    let mut late = Client::connect(
        broker,
        "after-shutdown",
        std::slice::from_ref(&topics.availability),
    );
    late.expect("offline retained", |m| {
        m.topic == topics.availability && m.payload == b"offline"
    })
    .await;
    rig.island.shutdown().await;
}

/// A frozen broker link (the proxy forwards nothing either way and closes nothing, as a dead
/// network path) is given up within `broker_ack_timeout_ms` of the first publication it leaves
/// unacknowledged, and the gateway connects again: not at the keep-alive, which is set far longer
/// here. What it published into the frozen link arrives after the reconnect.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frozen_broker_link_is_replaced_within_the_ack_bound() {
    use gateway_support::{Gateway, ISLAND};
    use ihex_tests::proxy::{Direction, Mode, Proxy};
    use sim_node::{link::Link, Island, IslandDesc};

    const BOUND_MS: u64 = 2000;
    const KEEP_ALIVE_S: u64 = 120;
    let broker = ihex_tests::broker::Mosquitto::start().expect("start mosquitto");
    let proxy = Proxy::start(broker.addr()).await.expect("proxy");
    let iface = ihex_tests::can::lease();
    let gateway = Gateway::start_with(proxy.addr(), &iface, "frozen", |o| {
        o.keep_alive = Some(KEEP_ALIVE_S);
        o.broker_ack_timeout_ms = Some(BOUND_MS);
    });
    let topics = gateway.config.topics.clone();
    let mut client = Client::connect(broker.addr(), "frozen-watch", &["frozen/#".to_owned()]);
    let online =
        |m: &gateway_support::Seen| m.topic == topics.availability && m.payload == b"online";
    client.expect("gateway online", online).await;
    assert_eq!(proxy.accepted(), 1);

    // Only the gateway's link freezes: a new connection passes.
    for link in proxy.links() {
        link.set(Mode::HalfOpen(Direction::Both));
    }
    let frozen = tokio::time::Instant::now();
    // The island boots: its nodes' events go into the frozen link, unacknowledged.
    let desc = IslandDesc::parse(ISLAND).expect("island");
    let island = Island::start(&desc, Link::socketcan(iface.clone())).expect("start island");

    client.expect("gateway online again", online).await;
    let took = frozen.elapsed();
    assert_eq!(proxy.accepted(), 2, "one new connection");
    let limit = ihex_tests::time::scaled(Duration::from_millis(BOUND_MS + 3000));
    assert!(
        took <= limit,
        "the frozen link was replaced after {took:?}, more than the bound ({BOUND_MS} ms) and the \
         time to reconnect ({limit:?} in all; keep-alive {KEEP_ALIVE_S} s)"
    );
    for n in ["111", "112", "2"] {
        client
            .expect_event(&topics.events, "node_online", |p| p["id"] == n)
            .await;
    }
    gateway.shutdown().await;
    island.shutdown().await;
}
