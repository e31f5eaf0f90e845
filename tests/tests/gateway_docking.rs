//! Gateway end to end over vcan + Mosquitto: the docking sequence produces the seed's events, and a
//! node taken off the bus is reported lost and then online again.
#![cfg(feature = "vcan")]

mod gateway_support;

use gateway_support::{id, Rig};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn docking_and_undocking_publish_the_seed_events() {
    let mut rig = Rig::start("dock").await;
    let events = rig.events();
    rig.island.dock(id("3"), id("112"), 2).await.expect("dock");
    let m = rig
        .client
        .expect("new_connection of 3", |m| {
            let v = m.json();
            m.topic == events && v["event"] == "new_connection" && v["payload"]["n"]["id"] == "3"
        })
        .await;
    // The seed's shape exactly: ids as lower-case hex strings, no extra keys.
    let want: serde_json::Value = serde_json::from_str(
        r#"{"event": "new_connection", "payload": {"n": {"id": "3", "port": 1}, "n-1": {"id": "112", "port": 2}}}"#,
    )
    .unwrap();
    assert_eq!(m.json(), want, "{}", String::from_utf8_lossy(&m.payload));
    assert!(
        rig.island.actuators(id("112")).await.unwrap().relay,
        "static SC powered the dock"
    );
    assert!(rig.island.view(id("3")).await.unwrap().powered);

    rig.island.undock(id("3")).await.expect("undock");
    let m = rig
        .client
        .expect("connection_removed of 3", |m| {
            let v = m.json();
            m.topic == events
                && v["event"] == "connection_removed"
                && v["payload"]["n"]["id"] == "3"
        })
        .await;
    let mut want = want;
    want["event"] = "connection_removed".into();
    assert_eq!(m.json(), want);
    rig.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_node_off_the_bus_is_lost_then_online_again() {
    let mut rig = Rig::start("lost").await;
    let events = rig.events();
    rig.island.set_on_bus(id("112"), false).await.unwrap();
    rig.client
        .expect_event(&events, "node_lost", |p| p["id"] == "112")
        .await;
    // Its retained state says so too.
    let state = format!("{}/112/state", rig.gateway.config.topics.node_state_root);
    rig.client
        .expect("112 state offline", |m| {
            m.topic == state && m.json()["online"] == false
        })
        .await;
    rig.island.set_on_bus(id("112"), true).await.unwrap();
    rig.client
        .expect_event(&events, "node_online", |p| p["id"] == "112")
        .await;
    // The others were never lost.
    let lost_others = rig.client.drain().iter().any(|m| {
        let v = m.json();
        m.topic == events && v["event"] == "node_lost" && v["payload"]["id"] != "112"
    });
    assert!(!lost_others);
    rig.shutdown().await;
}
