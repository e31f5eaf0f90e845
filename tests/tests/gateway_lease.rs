//! Leases end to end over vcan + Mosquitto with the real gateway and `sim-node`: a second MQTT
//! client's command is refused while another client holds the element and accepted after the
//! lease expired; a gateway restart mid-lease ends the lease as docs/gateway.md says (an empty
//! retained leases document, `leases_reset`, the old token worthless, the element free).
#![cfg(feature = "vcan")]

mod gateway_support;

use std::time::Duration;

use gateway_support::{id, Client, Gateway, Rig};
use ihex_proto::Rgb;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lease_keeps_a_second_client_out_until_it_ends() {
    let mut rig = Rig::start("lease").await;
    let events = rig.events();
    let commands = rig.gateway.commands();
    let leases_topic = rig.gateway.config.topics.leases.clone();
    let mut other = Client::connect(rig.addr, "test-lease-other", std::slice::from_ref(&events));
    // Long enough that the other client's command surely arrives before the end, even emulated.
    let secs = ihex_tests::time::scaled(Duration::from_secs(3))
        .as_secs()
        .max(3);

    rig.command(&format!(
        r#"{{"cmd":"lease","owner":"run-42","nodes":"111","seconds":{secs},"note":"sample prep","request_id":"l1"}}"#
    ))
    .await;
    let granted = rig
        .client
        .expect_event(&events, "lease_granted", |p| p["request_id"] == "l1")
        .await;
    let token = granted["payload"]["token"].as_str().unwrap().to_owned();
    let doc = rig
        .client
        .expect("the retained leases document", |m| m.topic == leases_topic)
        .await
        .json();
    assert_eq!(doc["leases"][0]["owner"], "run-42", "{doc}");
    assert_eq!(doc["leases"][0]["nodes"][0], "111", "{doc}");

    // The second client is refused, with the holder named; nothing reaches the node.
    let before = rig.island.actuators(id("111")).await.unwrap().led;
    other
        .publish(
            &commands,
            r#"{"cmd":"led","node":"111","color":"red","request_id":"b1"}"#,
        )
        .await;
    let refused = other
        .expect_event(&events, "command_rejected", |p| p["request_id"] == "b1")
        .await;
    let reason = refused["payload"]["reason"].as_str().unwrap();
    assert!(
        reason.starts_with("111 is leased by run-42 until ")
            && reason.contains("(note: sample prep)"),
        "{reason}"
    );
    assert_eq!(rig.island.actuators(id("111")).await.unwrap().led, before);
    // Reading is not blocked.
    other
        .publish(&commands, r#"{"cmd":"list","request_id":"b-list"}"#)
        .await;
    other
        .expect_event(&events, "node_list", |p| p["request_id"] == "b-list")
        .await;
    // The holder's command carries the token and goes through.
    rig.command_ok(
        &format!(r#"{{"cmd":"led","node":"111","color":"green","lease":"{token}""#),
        "l-led",
    )
    .await;
    assert_eq!(
        rig.island.actuators(id("111")).await.unwrap().led.duty,
        Rgb::new(0, 255, 0)
    );

    // The lease expires: an event, an empty document, and the second client gets through.
    let ended = other
        .expect_event(&events, "lease_ended", |p| p["why"] == "expired")
        .await;
    assert_eq!(ended["payload"]["lease"]["owner"], "run-42");
    let doc = rig
        .client
        .expect("the emptied leases document", |m| {
            m.topic == leases_topic && m.json()["leases"] == serde_json::json!([])
        })
        .await;
    assert_eq!(doc.json(), serde_json::json!({"leases": []}));
    other
        .publish(
            &commands,
            r#"{"cmd":"led","node":"111","color":"red","request_id":"b2"}"#,
        )
        .await;
    let r = other
        .expect_event(&events, "command_result", |p| p["request_id"] == "b2")
        .await;
    assert_eq!(r["payload"]["result"], "ok", "{r}");
    assert_eq!(
        rig.island.actuators(id("111")).await.unwrap().led.duty,
        Rgb::new(255, 0, 0)
    );
    rig.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_restart_ends_the_leases_and_says_so() {
    let mut rig = Rig::start("lrestart").await;
    let events = rig.events();
    let commands = rig.gateway.commands();
    let leases_topic = rig.gateway.config.topics.leases.clone();
    rig.command(
        r#"{"cmd":"lease","owner":"run-7","nodes":"all","seconds":3600,"request_id":"l1"}"#,
    )
    .await;
    let granted = rig
        .client
        .expect_event(&events, "lease_granted", |p| p["request_id"] == "l1")
        .await;
    let token = granted["payload"]["token"].as_str().unwrap().to_owned();
    rig.client
        .expect("the retained leases document", |m| {
            m.topic == leases_topic && m.json()["leases"][0]["owner"] == "run-7"
        })
        .await;

    // Restart the gateway mid-lease (same broker, same island, same bus).
    rig.gateway.stop.cancel();
    (&mut rig.gateway.task)
        .await
        .expect("gateway task")
        .expect("gateway stopped cleanly");
    let mark = rig.client.drain().len();
    rig.gateway = Gateway::start(rig.addr, &rig.iface, "lrestart");
    rig.client
        .expect_event(&events, "leases_reset", |p| {
            p["reason"]
                .as_str()
                .unwrap()
                .contains("ended with the restart")
        })
        .await;
    // The new run may hear 111 before or after its first connection to the broker.
    let online_111 = |m: &gateway_support::Seen| {
        let v = m.json();
        m.topic == events && v["event"] == "node_online" && v["payload"]["id"] == "111"
    };
    if !rig.client.drain()[mark..].iter().any(online_111) {
        rig.client.expect("node_online of 111", online_111).await;
    }
    // A client arriving now reads the retained document: no lease.
    let mut late = Client::connect(
        rig.addr,
        "test-lrestart-late",
        std::slice::from_ref(&leases_topic),
    );
    let doc = late
        .expect("the retained leases document", |m| m.topic == leases_topic)
        .await;
    assert_eq!(doc.json(), serde_json::json!({"leases": []}));
    // The element is free, and the old token is worthless.
    rig.command_ok(r#"{"cmd":"led","node":"111","color":"blue""#, "after")
        .await;
    rig.client
        .publish(
            &commands,
            format!(r#"{{"cmd":"renew","lease":"{token}","seconds":60,"request_id":"old"}}"#),
        )
        .await;
    let r = rig
        .client
        .expect_event(&events, "command_rejected", |p| p["request_id"] == "old")
        .await;
    assert!(
        r["payload"]["reason"]
            .as_str()
            .unwrap()
            .starts_with("renew: no lease held now has this token"),
        "{r}"
    );
    rig.shutdown().await;
}
