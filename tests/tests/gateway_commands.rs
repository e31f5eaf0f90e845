//! Gateway end to end over vcan + Mosquitto: every command reaches the right simulated node and
//! changes its state; bad input is rejected with a reason and the gateway keeps serving.
#![cfg(feature = "vcan")]

mod gateway_support;

use gateway_support::{id, Rig};
use ihex_proto::Rgb;
use ihex_sc_core::BuzzerOutput;

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
