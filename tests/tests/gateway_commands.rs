//! Gateway end to end over vcan + Mosquitto: every command reaches the right simulated node and
//! changes its state; bad input is rejected with a reason and the gateway keeps serving.
#![cfg(feature = "vcan")]

mod gateway_support;

use std::time::Duration;

use gateway_support::{id, Rig};
use ihex_proto::Rgb;
use ihex_sc_core::BuzzerOutput;
use ihex_tests::broker::{Mosquitto, Setup};
use ihex_tests::mqtt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_command_reaches_the_right_node() {
    let mut rig = Rig::start("cmds").await;
    let before_112 = rig.island.actuators(id("112")).await.unwrap();

    // LED, steady red at full brightness, to 111 only.
    rig.command_ok(r#"{"cmd":"led","node":"111","color":"red""#, "led")
        .await;
    let a = rig.island.actuators(id("111")).await.unwrap();
    assert_eq!(a.led.duty, Rgb::new(255, 0, 0));
    assert_eq!(a.led.blink, None);
    assert_eq!(
        rig.island.actuators(id("112")).await.unwrap().led,
        before_112.led,
        "112 untouched"
    );

    // LED by hex colour with brightness and blink, to the mobile element 2.
    rig.command_ok(
        r##"{"cmd":"led","node":"2","color":"#00ff00","brightness":128,"blink":{"period_ms":500}"##,
        "blink",
    )
    .await;
    let a = rig.island.actuators(id("2")).await.unwrap();
    assert_eq!(a.led.duty.g, 128);
    assert_eq!((a.led.duty.r, a.led.duty.b), (0, 0));
    assert!(a.led.blink.is_some(), "{a:?}");

    // Buzzer on, then a pattern, then off.
    rig.command_ok(
        r#"{"cmd":"buzzer","node":"112","mode":"on","freq_hz":1000"#,
        "bz-on",
    )
    .await;
    assert_eq!(
        rig.island.actuators(id("112")).await.unwrap().buzzer,
        BuzzerOutput::Tone { freq_hz: 1000 }
    );
    rig.command_ok(r#"{"cmd":"buzzer","node":"112","mode":"pattern","freq_hz":440,"on_ms":100,"off_ms":200,"count":0"#, "bz-pat").await;
    assert!(matches!(
        rig.island.actuators(id("112")).await.unwrap().buzzer,
        BuzzerOutput::Pattern { freq_hz: 440, .. }
    ));
    rig.command_ok(r#"{"cmd":"buzzer","node":"112","mode":"off""#, "bz-off")
        .await;
    assert_eq!(
        rig.island.actuators(id("112")).await.unwrap().buzzer,
        BuzzerOutput::Off
    );

    // Power (relay) of 112 on and off.
    rig.command_ok(r#"{"cmd":"power","node":"112","on":true"#, "pw-on")
        .await;
    assert!(rig.island.actuators(id("112")).await.unwrap().relay);
    rig.command_ok(r#"{"cmd":"power","node":"112","on":false"#, "pw-off")
        .await;
    assert!(!rig.island.actuators(id("112")).await.unwrap().relay);

    // Identify makes the LED blink even though 112's LED was off.
    rig.command_ok(r#"{"cmd":"identify","node":"112","seconds":5"#, "ident")
        .await;
    let a = rig.island.actuators(id("112")).await.unwrap();
    assert!(
        a.led.blink.is_some() && a.led.duty != Rgb::new(0, 0, 0),
        "{a:?}"
    );

    // To all nodes: every online node turns blue.
    rig.command(r#"{"cmd":"led","node":"all","color":"blue","request_id":"all"}"#)
        .await;
    let events = rig.events();
    rig.client
        .expect_event(&events, "command_result", |p| p["request_id"] == "all")
        .await;
    for n in ["111", "2"] {
        let a = rig.island.actuators(id(n)).await.unwrap();
        assert_eq!(a.led.duty, Rgb::new(0, 0, 255), "{n}: {a:?}");
    }

    // List: every online node is in the answer.
    rig.command(r#"{"cmd":"list","request_id":"ls"}"#).await;
    let list = rig
        .client
        .expect_event(&events, "node_list", |_| true)
        .await;
    let text = list.to_string();
    for n in ["\"111\"", "\"112\"", "\"2\""] {
        assert!(text.contains(n), "{n} missing from {text}");
    }

    rig.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_is_rejected_and_the_gateway_keeps_serving() {
    let mut rig = Rig::start("bad").await;
    let events = rig.events();
    let huge = format!(
        r#"{{"cmd":"led","node":"111","color":"red","pad":"{}"}}"#,
        "x".repeat(10_000)
    );
    let cases: Vec<(&str, String)> = vec![
        ("malformed json", "{\"cmd\":".into()),
        ("not json at all", "\u{1}\u{2}garbage".into()),
        ("unknown command", r#"{"cmd":"dance","node":"111"}"#.into()),
        (
            "unknown node",
            r#"{"cmd":"led","node":"abc","color":"red"}"#.into(),
        ),
        (
            "node id out of range",
            r#"{"cmd":"led","node":"fff0","color":"red"}"#.into(),
        ),
        (
            "brightness out of range",
            r#"{"cmd":"led","node":"111","color":"red","brightness":300}"#.into(),
        ),
        (
            "unknown colour",
            r#"{"cmd":"led","node":"111","color":"ultraviolet"}"#.into(),
        ),
        (
            "frequency out of range",
            r#"{"cmd":"buzzer","node":"111","mode":"on","freq_hz":5}"#.into(),
        ),
        ("oversized payload", huge),
    ];
    for (what, payload) in &cases {
        rig.command(payload).await;
        let r = rig
            .client
            .expect_event(&events, "command_rejected", |_| true)
            .await;
        let reason = r["payload"]["reason"]
            .as_str()
            .unwrap_or_default()
            .to_owned();
        assert!(
            !reason.is_empty(),
            "{what}: rejection without a reason: {r}"
        );
    }
    // Nothing reached the node.
    let a = rig.island.actuators(id("111")).await.unwrap();
    assert_eq!(a.led.duty, Rgb::new(0, 0, 0), "{a:?}");
    // And the gateway still serves.
    rig.command_ok(r#"{"cmd":"led","node":"111","color":"white""#, "after")
        .await;
    assert_eq!(
        rig.island.actuators(id("111")).await.unwrap().led.duty,
        Rgb::new(255, 255, 255)
    );
    rig.shutdown().await;
}

/// A burst of QoS 1 commands larger than the MQTT task's intake (1,024 inputs), from a broker with
/// an unlimited in-flight window (Mosquitto's `max_inflight_messages 0`: the burst arrives whole),
/// while the core takes commands a few at a time (a 16-frame transmit queue: it takes them while
/// fewer than 8 frames wait): none is shed, every command is
/// answered exactly once.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_beyond_the_intake_is_answered_whole() {
    const BURST: usize = 5000;
    let broker = Mosquitto::start_with(&Setup {
        global: "max_inflight_messages 0\nmax_queued_messages 0\n".into(),
        ..Setup::default()
    })
    .expect("start mosquitto");
    let mut rig = Rig::start_with_broker(broker, "burst", |o| o.tx_queue = Some(16)).await;
    let events = rig.events();
    // A publisher whose own window lets the whole burst reach the broker at once.
    let mut options = mqtt::options(rig.addr, "burst-publisher");
    options.set_inflight(u16::MAX);
    let publisher = mqtt::Client::subscribe_on_connect(options, &[]);
    let nodes = ["111", "112", "2"];
    for i in 0..BURST {
        let json = format!(
            r#"{{"cmd":"led","node":"{}","color":[{},{},0],"request_id":"b{i}"}}"#,
            nodes[i % nodes.len()],
            i & 0xff,
            i >> 8
        );
        publisher.publish(&rig.gateway.commands(), json).await;
    }
    let deadline = tokio::time::Instant::now() + ihex_tests::time::scaled(Duration::from_secs(60));
    let mut answers = Vec::new();
    while answers.len() < BURST && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(200)).await;
        answers = rig
            .client
            .drain()
            .iter()
            .filter(|m| m.topic == events)
            .map(|m| m.json())
            .filter(|v| v["event"] == "command_result")
            .filter(|v| {
                v["payload"]["request_id"]
                    .as_str()
                    .is_some_and(|r| r.starts_with('b'))
            })
            .collect();
    }
    let mut ids: Vec<&str> = answers
        .iter()
        .map(|v| v["payload"]["request_id"].as_str().unwrap_or_default())
        .collect();
    let mut expected: Vec<String> = (0..BURST).map(|i| format!("b{i}")).collect();
    let others: Vec<String> = rig
        .client
        .drain()
        .iter()
        .filter(|m| m.topic == events)
        .map(|m| m.json())
        .filter(|v| v["event"] != "command_result")
        .map(|v| v.to_string())
        .collect();
    assert_eq!(
        ids.len(),
        BURST,
        "{} of {BURST} commands answered; the first missing: {:?}; the other events: {others:#?}",
        ids.len(),
        expected.iter().find(|e| !ids.contains(&e.as_str()))
    );
    // Answers come as the nodes ack, so not in the order published.
    ids.sort_unstable();
    expected.sort_unstable();
    assert_eq!(ids, expected, "each answered once");
    for a in &answers {
        assert_eq!(a["payload"]["result"], "ok", "{a}");
    }
    rig.shutdown().await;
}
