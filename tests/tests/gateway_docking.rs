//! Gateway end to end over vcan + Mosquitto: the docking sequence produces the seed's events (also
//! when the mobile element's handshake overtakes the dock report: no false fault), a failed
//! docking leaves a relay the user switched on on, and a node taken off the bus is reported lost
//! and then online again.
#![cfg(feature = "vcan")]

mod gateway_support;

use gateway_support::{id, Rig};
use serde_json::Value;

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

/// Issue 29: with 112's relay already on, the mobile element gets power at once and its handshake
/// overtakes 112's dock report (a debounce later). That is a normal docking: `new_connection`,
/// and no `unexpected_handshake` fault before or after it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_handshake_that_overtakes_the_dock_report_is_no_fault() {
    let mut rig = Rig::start("overtake").await;
    let events = rig.events();
    rig.command_ok(r#"{"cmd":"power","node":"112","on":true"#, "on")
        .await;
    let before = rig.client.log.len();
    rig.island.dock(id("3"), id("112"), 2).await.expect("dock");
    let m = rig
        .client
        .expect_event(&events, "new_connection", |p| p["n"]["id"] == "3")
        .await;
    assert_eq!(
        m["payload"]["n-1"],
        serde_json::json!({"id": "112", "port": 2})
    );
    // Past the window in which an unmatched handshake would become a fault (a quarter of the
    // docking timeout), with a command whose answer comes after it.
    tokio::time::sleep(ihex_tests::time::scaled(std::time::Duration::from_millis(
        1500,
    )))
    .await;
    rig.command_ok(r#"{"cmd":"identify","node":"3","seconds":0"#, "later")
        .await;
    let faults: Vec<Value> = rig.client.log[before..]
        .iter()
        .filter(|m| m.topic == events && m.json()["event"] == "fault")
        .map(|m| m.json())
        .collect();
    assert!(faults.is_empty(), "{faults:?}");
    assert!(rig.island.view(id("3")).await.unwrap().powered);
    rig.shutdown().await;
}

/// Issue 29: a docking that fails (the mobile element is off the bus: no handshake) on 112, whose
/// relay the user had switched on, leaves the relay on, and `dock_failed` says so.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_docking_leaves_the_relay_the_user_switched_on_on() {
    let mut rig = Rig::start("dockfail").await;
    let events = rig.events();
    rig.command_ok(r#"{"cmd":"power","node":"112","on":true"#, "on")
        .await;
    rig.island.set_on_bus(id("3"), false).await.unwrap();
    rig.island.dock(id("3"), id("112"), 2).await.expect("dock");
    let failed = rig
        .client
        .expect_event(&events, "dock_failed", |p| p["node"] == "112")
        .await;
    assert_eq!(failed["payload"]["port"], 2, "{failed}");
    assert_eq!(failed["payload"]["relay"], true, "{failed}");
    // Whatever the gateway sent after the failure has reached 112 by the time a later command
    // is answered.
    rig.command_ok(r#"{"cmd":"identify","node":"112","seconds":0"#, "after")
        .await;
    assert!(
        rig.island.actuators(id("112")).await.unwrap().relay,
        "the relay the user switched on is still on"
    );
    rig.shutdown().await;
}
