//! The lab broker's security, as documented in `docs/deploy.md` and configured by
//! `deploy/mosquitto/central.conf` and `acl`: TLS with a private CA, a password per user, and a
//! per-island ACL that confines each island's credentials to its own topic prefix.
//!
//! What Mosquitto 2.0 does with MQTT 3.1.1 (checked here, so a change shows up): a refused login
//! gets CONNACK 5 "not authorised"; a PUBLISH outside the ACL is acknowledged (3.1.1's PUBACK has no
//! reason code) and dropped, and the broker logs "Denied PUBLISH"; a SUBSCRIBE outside the ACL is
//! granted (SUBACK 0x01, not 0x80: with an `acl_file` Mosquitto checks reads when it delivers, not
//! when it subscribes) and delivers nothing, retained messages included.
#![cfg(feature = "tls")]

mod lab_support;

use ihex_tests::mqtt::Seen;
use lab_support::{client, event, gateway_config, password, Central, Gateway};
use rumqttc::{ConnectReturnCode, QoS, SubscribeReasonCode};

fn login(user: &str) -> Option<(&str, &str)> {
    Some((user, password(user)))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_and_passwords_let_only_the_right_clients_in() {
    let central = Central::start(&["error", "warning"]);
    let ca = central.ca_file();
    let gw = Gateway::start(gateway_config(
        central.addr(),
        "bench-a",
        login("gw-bench-a"),
        Some(&ca),
    ));
    let mut lab = client(
        central.addr(),
        "lab-1",
        login("lab"),
        Some(&ca),
        &["bench-a/#"],
    );
    assert_eq!(lab.connack().await, ConnectReturnCode::Success);
    lab.expect_message("bench-a/ihex/gateway/availability", |p| p == b"online")
        .await;
    lab.publish(
        "bench-a/CommandsTopic",
        r#"{"cmd":"led","node":"111","color":"red","request_id":"over-tls"}"#,
    )
    .await;
    let r = lab
        .expect("command_result over TLS", |s| {
            event(s, "bench-a/EventsTopic", "command_result")
                .is_some_and(|p| p["request_id"] == "over-tls")
        })
        .await;
    assert_eq!(
        event(&r, "bench-a/EventsTopic", "command_result").unwrap()["result"],
        "ok"
    );

    // A wrong password, and no user at all: CONNACK 5.
    let mut wrong = client(
        central.addr(),
        "wrong",
        Some(("gw-bench-a", "guess")),
        Some(&ca),
        &[],
    );
    assert_eq!(wrong.connack().await, ConnectReturnCode::NotAuthorized);
    let mut anonymous = client(central.addr(), "anon", None, Some(&ca), &[]);
    assert_eq!(anonymous.connack().await, ConnectReturnCode::NotAuthorized);

    // Plain TCP to the TLS listener, and TLS trusting another CA: no MQTT session at all.
    let mut plain =
        ihex_tests::mqtt::Client::connect(ihex_tests::mqtt::options(central.addr(), "plain"));
    let e = plain
        .expect("the plain connection to fail", |s| {
            matches!(s, Seen::Error(_) | Seen::ConnAck(_))
        })
        .await;
    assert!(matches!(e, Seen::Error(_)), "{e:?}");
    let stranger = ihex_tests::tls::Pki::new("another CA", &["127.0.0.1"]).unwrap();
    let other_ca = central.broker.dir().join("other-ca.crt");
    std::fs::write(&other_ca, &stranger.ca).unwrap();
    let mut untrusting = client(
        central.addr(),
        "untrusting",
        login("lab"),
        Some(&other_ca),
        &[],
    );
    let e = untrusting
        .expect("the TLS handshake to fail", |s| {
            matches!(s, Seen::Error(_) | Seen::ConnAck(_))
        })
        .await;
    match e {
        Seen::Error(text) => assert!(
            text.to_lowercase().contains("certificate") || text.contains("Tls"),
            "{text}"
        ),
        other => panic!("a client not trusting the broker's CA connected: {other:?}"),
    }
    gw.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_island_is_confined_to_its_own_prefix() {
    let central = Central::start(&["error", "warning", "notice", "debug"]);
    let ca = central.ca_file();
    let a = Gateway::start(gateway_config(
        central.addr(),
        "bench-a",
        login("gw-bench-a"),
        Some(&ca),
    ));
    let b = Gateway::start(gateway_config(
        central.addr(),
        "bench-b",
        login("gw-bench-b"),
        Some(&ca),
    ));
    let mut lab = client(
        central.addr(),
        "lab-2",
        login("lab"),
        Some(&ca),
        &["bench-a/#", "bench-b/#"],
    );
    for island in ["bench-a", "bench-b"] {
        let avail = format!("{island}/ihex/gateway/availability");
        lab.seen(&format!("{island} online"), |s| {
            matches!(s, Seen::Message { topic, payload, .. } if *topic == avail && payload == b"online")
        })
        .await;
        // Each gateway works under its ACL: it gets commands and publishes answers and states.
        lab.publish(
            &format!("{island}/CommandsTopic"),
            format!(r#"{{"cmd":"led","node":"111","color":"green","request_id":"{island}"}}"#),
        )
        .await;
        let events = format!("{island}/EventsTopic");
        lab.expect(&format!("{island}'s answer"), |s| {
            event(s, &events, "command_result")
                .is_some_and(|p| p["request_id"] == island && p["result"] == "ok")
        })
        .await;
        lab.expect_message(&format!("{island}/ihex/node/111/state"), |p| {
            String::from_utf8_lossy(p).contains("#00ff00")
        })
        .await;
    }

    // bench-a's credentials cannot read bench-b: the SUBSCRIBE is granted, nothing arrives, not
    // even bench-b's retained documents. (The subscription to its own prefix comes second: its
    // SUBACK is the sentinel after which bench-b's retained messages would have come.)
    let mut intruder = client(
        central.addr(),
        "intruder",
        login("gw-bench-a"),
        Some(&ca),
        &[],
    );
    assert_eq!(intruder.connack().await, ConnectReturnCode::Success);
    assert_eq!(
        intruder.subscribe("bench-b/#").await,
        SubscribeReasonCode::Success(QoS::AtLeastOnce),
        "Mosquitto 2.0 grants a subscription its ACL denies (and delivers nothing)"
    );
    assert_eq!(
        intruder
            .subscribe("bench-a/ihex/gateway/availability")
            .await,
        SubscribeReasonCode::Success(QoS::AtLeastOnce)
    );
    // Live traffic of bench-b: an answer the lab sees, then a sentinel on bench-a.
    lab.publish(
        "bench-b/CommandsTopic",
        r#"{"cmd":"list","request_id":"b-live"}"#,
    )
    .await;
    lab.expect("bench-b's node_list", |s| {
        event(s, "bench-b/EventsTopic", "node_list").is_some_and(|p| p["request_id"] == "b-live")
    })
    .await;
    // Its SUBACK first: a sentinel published before the subscription is in place is never seen.
    assert_eq!(
        intruder.subscribe("bench-a/EventsTopic").await,
        SubscribeReasonCode::Success(QoS::AtLeastOnce)
    );
    lab.publish(
        "bench-a/CommandsTopic",
        r#"{"cmd":"list","request_id":"a-sentinel"}"#,
    )
    .await;
    intruder
        .expect("bench-a's sentinel", |s| {
            event(s, "bench-a/EventsTopic", "node_list")
                .is_some_and(|p| p["request_id"] == "a-sentinel")
        })
        .await;
    let leaked: Vec<&str> = intruder
        .log
        .iter()
        .filter_map(|s| match s {
            Seen::Message { topic, .. } if topic.starts_with("bench-b/") => Some(topic.as_str()),
            _ => None,
        })
        .collect();
    assert!(
        leaked.is_empty(),
        "bench-a's credentials read bench-b: {leaked:?}"
    );

    // bench-a's credentials cannot write bench-b: a command and a forged retained state document
    // are acknowledged (MQTT 3.1.1 cannot say no) and dropped.
    intruder
        .publish(
            "bench-b/CommandsTopic",
            r#"{"cmd":"list","request_id":"forged"}"#,
        )
        .await;
    intruder
        .client
        .publish(
            "bench-b/ihex/node/111/state",
            QoS::AtLeastOnce,
            true,
            r#"{"id":"111","forged":true}"#,
        )
        .await
        .unwrap();
    let mut acks = 0;
    while acks < 2 {
        intruder
            .expect("PUBACK of the denied publications", |s| {
                matches!(s, Seen::PubAck(_))
            })
            .await;
        acks += 1;
    }
    // Then the lab's own command to bench-b: the gateway answers it, and nothing before it.
    lab.publish(
        "bench-b/CommandsTopic",
        r#"{"cmd":"list","request_id":"after"}"#,
    )
    .await;
    lab.expect("bench-b's answer to the lab", |s| {
        event(s, "bench-b/EventsTopic", "node_list").is_some_and(|p| p["request_id"] == "after")
    })
    .await;
    let forged: Vec<&str> = lab
        .log
        .iter()
        .filter_map(|s| match s {
            Seen::Message { topic, payload, .. }
                if topic.starts_with("bench-b/")
                    && String::from_utf8_lossy(payload).contains("forged") =>
            {
                Some(topic.as_str())
            }
            _ => None,
        })
        .collect();
    assert!(
        forged.is_empty(),
        "a publication outside the ACL got through: {forged:?}"
    );
    // A dashboard connecting now sees the gateway's document, not the forged one.
    let mut late = client(
        central.addr(),
        "late",
        login("lab"),
        Some(&ca),
        &["bench-b/ihex/node/111/state"],
    );
    let doc = late
        .expect_message("bench-b/ihex/node/111/state", |_| true)
        .await;
    assert!(
        doc.json()
            .is_some_and(|d| d["online"] == true && d.get("forged").is_none()),
        "{doc:?}"
    );
    let log = central.broker.log();
    assert!(
        log.contains("Denied PUBLISH from intruder") && log.contains("'bench-b/CommandsTopic'"),
        "the broker logs the denied publish:\n{log}"
    );
    a.shutdown().await;
    b.shutdown().await;
}
