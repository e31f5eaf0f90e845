//! Gateway end to end over vcan + Mosquitto: the delivery contract (docs/gateway.md). A restarted
//! gateway reads the island back — dockings without a false `new_connection`, the real LED of a
//! node it never commanded — and does not execute the retained command it finds; an oversized
//! command gets its answer, with its `request_id`, and the gateway keeps serving.
#![cfg(feature = "vcan")]

mod gateway_support;

use gateway_support::{id, Client, Gateway, Rig, Seen};
use ihex_proto::Rgb;
use ihex_sc_core::BuzzerOutput;
use rumqttc::QoS;
use serde_json::{json, Value};

/// The state documents in `log` that show an online node with a field unknown (`null`): what a
/// restarted gateway must never publish (issue 29) — every one of them was known before.
fn half_known<'a>(log: impl Iterator<Item = &'a Seen>, root: &str) -> Vec<String> {
    const FIELDS: [&str; 8] = [
        "role", "ports", "version", "firmware", "uid", "led", "buzzer", "relay",
    ];
    log.filter(|m| m.topic.starts_with(root) && m.topic.ends_with("/state"))
        .filter_map(|m| {
            let d = m.json();
            let unknown: Vec<&str> = FIELDS.into_iter().filter(|f| d[f].is_null()).collect();
            (d["online"] == true && !unknown.is_empty()).then(|| {
                format!(
                    "{} ({} null): {}",
                    m.topic,
                    unknown.join(", "),
                    String::from_utf8_lossy(&m.payload)
                )
            })
        })
        .collect()
}

/// The last message on `topic` in `log`, as JSON.
fn last_on<'a>(log: impl DoubleEndedIterator<Item = &'a Seen>, topic: &str) -> Option<Value> {
    log.rev().find(|m| m.topic == topic).map(Seen::json)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_gateway_reads_the_island_back_and_runs_no_retained_command() {
    let mut rig = Rig::start("restart").await;
    let events = rig.events();
    rig.client
        .client
        .subscribe("homeassistant/device/+/config", QoS::AtLeastOnce)
        .await
        .unwrap();
    // The built-in island docks 2 on 111 port 3 at start.
    rig.client
        .expect_event(&events, "new_connection", |p| p["n"]["id"] == "2")
        .await;
    rig.command_ok(r#"{"cmd":"led","node":"112","color":"red""#, "red")
        .await;
    let Rig {
        broker,
        addr,
        iface,
        gateway,
        island,
        mut client,
    } = rig;
    let avail = gateway.config.topics.availability.clone();
    let commands = gateway.commands();
    let root = gateway.config.topics.node_state_root.clone();
    gateway.shutdown().await;
    client
        .expect("gateway offline", |m| {
            m.topic == avail && m.payload == b"offline"
        })
        .await;
    let before = client.log.len();

    // While no gateway runs: a retained buzzer-on, which the broker hands to the next subscriber.
    client
        .client
        .publish(
            &commands,
            QoS::AtLeastOnce,
            true,
            r#"{"cmd":"buzzer","node":"112","mode":"on","freq_hz":1000,"request_id":"stale"}"#,
        )
        .await
        .unwrap();
    // Stored by the broker before the next gateway subscribes: published after that, it would reach
    // the gateway live (without the retain flag) and rightly be carried out.
    client
        .expect("the retained command on the broker", |m| {
            m.topic == commands && m.payload.windows(7).any(|w| w == b"\"stale\"")
        })
        .await;

    let gateway = Gateway::start(addr, &iface, "restart");
    // A dashboard starting during the restart window: what it reads must be true or absent.
    let mut late = Client::connect(addr, "test-restart-late", &[format!("{root}/+/state")]);
    let rejected = client
        .expect_event(&events, "command_rejected", |p| p["request_id"] == "stale")
        .await;
    assert!(
        rejected["payload"]["reason"]
            .as_str()
            .unwrap()
            .starts_with("retained message on the command topic: not executed"),
        "{rejected}"
    );
    // The states converge to the island's truth, read back from the nodes — before or after the
    // rejection: the read-back (CAN) and the retained command (MQTT) are independent inputs.
    let s112 = format!("{root}/112/state");
    let red = |m: &Seen| m.topic == s112 && m.json()["led"]["color"] == "#ff0000";
    if !client.log[before..].iter().any(&red) {
        client.expect("112's read-back LED", red).await;
    }
    let s111 = format!("{root}/111/state");
    let s2 = format!("{root}/2/state");
    let docked_111 = json!([{"port": 3, "peer": "2", "peer_port": 0}]);
    let docked_2 = json!([{"port": 0, "peer": "111", "peer_port": 3}]);
    client.drain();
    for (topic, want) in [(&s111, &docked_111), (&s2, &docked_2)] {
        if last_on(client.log[before..].iter(), topic).is_some_and(|s| s["connections"] == *want) {
            continue;
        }
        client
            .expect("the docking read back", |m| {
                m.topic == *topic && m.json()["connections"] == *want
            })
            .await;
    }
    let (major, minor) = ihex_proto::PROTOCOL_VERSION;
    let protocol = format!("{major}.{minor}");
    let firmware = sim_node::desc::DEFAULT_FIRMWARE.to_string();
    // Firmware identity and the protocol version are read back too (issue 29: the version was
    // null after a restart, until the node rebooted), and Home Assistant's device shows the
    // firmware version (issue 33).
    for topic in [&s111, &s112, &s2] {
        let want = |d: &Value| d["version"] == protocol && d["firmware"]["version"] == firmware;
        if last_on(client.log[before..].iter(), topic).is_some_and(|d| want(&d)) {
            continue;
        }
        client
            .expect("both versions read back", |m| {
                m.topic == *topic && want(&m.json())
            })
            .await;
    }
    let ha_config = "homeassistant/device/ihex_restart_111/config";
    let sw = |m: &Seen| m.topic == ha_config && m.json()["device"]["sw_version"] == firmware;
    if !client.log[before..].iter().any(sw) {
        client.expect("111's sw_version", sw).await;
    }
    // A list answered now shows the same, and nothing announced the old docking as new.
    client
        .client
        .publish(
            &commands,
            QoS::AtLeastOnce,
            false,
            r#"{"cmd":"list","request_id":"l"}"#,
        )
        .await
        .unwrap();
    let list = client
        .expect_event(&events, "node_list", |p| p["request_id"] == "l")
        .await;
    let n111 = list["payload"]["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|n| n["id"] == "111")
        .cloned()
        .unwrap();
    assert_eq!(n111["connections"], docked_111);
    let false_news: Vec<_> = client.log[before..]
        .iter()
        .filter(|m| m.topic == events && m.json()["event"] == "new_connection")
        .collect();
    assert!(false_news.is_empty(), "{false_news:?}");
    // Nothing half-known was ever published by the restarted gateway, to a subscriber that was
    // there or one that came during the window.
    let wrong = half_known(client.drain()[before..].iter(), &root);
    assert!(wrong.is_empty(), "{wrong:#?}");
    late.expect("the late subscriber sees 111", |m| m.topic == s111)
        .await;
    let wrong = half_known(late.drain().iter(), &root);
    assert!(wrong.is_empty(), "{wrong:#?}");
    // The retained command was never executed.
    let a = island.actuators(id("112")).await.unwrap();
    assert_eq!(a.buzzer, BuzzerOutput::Off);
    assert_eq!(a.led.duty, Rgb::new(255, 0, 0));

    // Clear the retained message, as the rejection says.
    client
        .client
        .publish(&commands, QoS::AtLeastOnce, true, Vec::new())
        .await
        .unwrap();
    gateway.shutdown().await;
    island.shutdown().await;
    drop(broker);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_oversized_command_is_answered_and_the_gateway_keeps_serving() {
    let mut rig = Rig::start("big").await;
    let events = rig.events();
    // 1.5 MiB: beyond the gateway's limit (4 KiB) and beyond what a default MQTT client reads.
    let pad = "x".repeat(3 << 19);
    let big = format!(r#"{{"cmd":"list","request_id":"big","pad":"{pad}"}}"#);
    rig.command(&big).await;
    let r = rig
        .client
        .expect_event(&events, "command_rejected", |p| p["request_id"] == "big")
        .await;
    let reason = r["payload"]["reason"].as_str().unwrap().to_owned();
    assert_eq!(
        reason,
        format!("command is {} bytes; the limit is 4096 bytes", big.len())
    );
    // Still connected and serving (a command with a generous ttl_ms runs as any other).
    rig.command_ok(
        r#"{"cmd":"identify","node":"2","seconds":0,"ttl_ms":60000"#,
        "after",
    )
    .await;
    rig.shutdown().await;
}
