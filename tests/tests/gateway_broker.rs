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
