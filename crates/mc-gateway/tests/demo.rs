//! The embedded demo in-process: embedded rumqttd broker + simulated island on the in-memory bus,
//! driven by a real MQTT client. (The SocketCAN end-to-end tests are in `tests/tests/gateway_*.rs`.)
#![cfg(feature = "demo")]

use std::{
    net::{SocketAddr, TcpListener},
    time::Duration,
};

use ihex_tests::broker::{Mosquitto, Setup};
use ihex_tests::free_port;
use ihex_tests::mqtt::Client;
use mc_gateway::{config::Options, error::BrokerError, CancellationToken, Config, GatewayError};
use rumqttc::QoS;
use serde_json::Value;
use tokio::sync::mpsc;

const WAIT: Duration = Duration::from_secs(20);

fn demo_config(port: u16) -> Config {
    let cli = Options {
        broker_listen: Some(format!("127.0.0.1:{port}").parse().unwrap()),
        health_period_ms: Some(200),
        log_dir: Some("-".into()),
        ..Options::default()
    };
    let c = Config::resolve(cli, Options::default()).unwrap();
    assert!(c.is_demo());
    c
}

/// The test MQTT client of the demo broker on `port`, subscribed to everything.
fn client(port: u16, name: &str) -> Client {
    let mut c = Client::subscribed(SocketAddr::from(([127, 0, 0, 1], port)), name, &["#"]);
    c.set_wait(WAIT);
    c
}

/// The payload of the next message for which `pred(topic, payload)` holds.
async fn expect(c: &mut Client, what: &str, pred: impl Fn(&str, &[u8]) -> bool) -> Vec<u8> {
    c.expect_msg(what, |m| pred(&m.topic, &m.payload))
        .await
        .payload
}

fn event(p: &[u8]) -> Value {
    serde_json::from_slice(p).unwrap_or(Value::Null)
}

/// Cancels the gateway and waits for its clean exit.
async fn stop_cleanly(
    stop: &CancellationToken,
    gw: tokio::task::JoinHandle<Result<(), GatewayError>>,
) {
    stop.cancel();
    tokio::time::timeout(WAIT, gw)
        .await
        .expect("gateway stops")
        .unwrap()
        .expect("clean exit");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_demo_answers_commands_docks_and_says_goodbye() {
    let port = free_port();
    let stop = CancellationToken::new();
    let stats = std::sync::Arc::new(mc_gateway::mqtt::MqttStats::default());
    let gw = tokio::spawn(mc_gateway::run_with_stats(
        demo_config(port),
        stop.clone(),
        stats.clone(),
    ));
    // run() returns only after the broker accepts connections; the client retries until then.
    let mut rx = client(port, "demo-test");
    let c = rx.client.clone();
    expect(&mut rx, "online", |t, p| {
        t == "ihex/gateway/availability" && p == b"online"
    })
    .await;
    // The island booted before this client connected: its retained state tells.
    expect(&mut rx, "node 111 online", |t, p| {
        t == "ihex/node/111/state" && event(p)["online"] == true
    })
    .await;

    c.publish(
        "CommandsTopic",
        QoS::AtLeastOnce,
        false,
        r#"{"cmd":"led","node":"111","color":"red","request_id":"r1"}"#,
    )
    .await
    .unwrap();
    let r = expect(&mut rx, "command_result", |t, p| {
        t == "EventsTopic" && event(p)["payload"]["request_id"] == "r1"
    })
    .await;
    assert_eq!(
        event(&r)["payload"]["result"],
        "ok",
        "{}",
        String::from_utf8_lossy(&r)
    );
    expect(&mut rx, "111's retained state turns red", |t, p| {
        t == "ihex/node/111/state" && event(p)["led"]["color"] == "#ff0000"
    })
    .await;

    c.publish(
        "ihex/sim",
        QoS::AtLeastOnce,
        false,
        r#"{"sim":"dock","mobile":"3","static":"112","port":2}"#,
    )
    .await
    .unwrap();
    let d = expect(&mut rx, "new_connection", |t, p| {
        t == "EventsTopic"
            && event(p)["event"] == "new_connection"
            && event(p)["payload"]["n"]["id"] == "3"
    })
    .await;
    let want: Value = serde_json::from_str(
        r#"{"event": "new_connection", "payload": {"n": {"id": "3", "port": 1}, "n-1": {"id": "112", "port": 2}}}"#,
    )
    .unwrap();
    assert_eq!(event(&d), want);

    // A mistaken control message is answered on the events topic, with the island's reason.
    c.publish(
        "ihex/sim",
        QoS::AtLeastOnce,
        false,
        r#"{"sim":"dock","mobile":"9","static":"112","port":2,"request_id":"s1"}"#,
    )
    .await
    .unwrap();
    let r = expect(&mut rx, "sim_result", |t, p| {
        t == "EventsTopic" && event(p)["event"] == "sim_result"
    })
    .await;
    assert_eq!(
        event(&r)["payload"],
        serde_json::json!({"request_id": "s1", "sim": "dock", "result": "refused",
                           "reason": "no element \"9\" in this island"})
    );
    c.publish("ihex/sim", QoS::AtLeastOnce, false, "{not json")
        .await
        .unwrap();
    let r = expect(&mut rx, "sim_rejected", |t, p| {
        t == "EventsTopic" && event(p)["event"] == "sim_rejected"
    })
    .await;
    assert!(event(&r)["payload"]["reason"]
        .as_str()
        .unwrap()
        .starts_with("malformed JSON"));

    c.publish("CommandsTopic", QoS::AtLeastOnce, false, "{not json")
        .await
        .unwrap();
    expect(&mut rx, "command_rejected", |t, p| {
        t == "EventsTopic" && event(p)["event"] == "command_rejected"
    })
    .await;

    stop_cleanly(&stop, gw).await;
    expect(&mut rx, "offline", |t, p| {
        t == "ihex/gateway/availability" && p == b"offline"
    })
    .await;
}

/// A burst of QoS 1 commands to one element, from a broker that sends them without waiting for
/// acknowledgements (Mosquitto's `max_inflight_messages 0`), faster than the simulated island
/// reads its in-memory bus: the frames wait for the island as on a real bus (where arbitration and
/// the bit rate pace the gateway), the commands behind them wait unacknowledged, and every command
/// is answered `ok` — none refused for the 256 unanswered commands an element may have, none lost
/// with a frame the island's end of the bus dropped.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_to_one_element_is_answered_ok_whole() {
    const BURST: usize = 5000;
    let broker = Mosquitto::start_with(&Setup {
        global: "max_inflight_messages 0\nmax_queued_messages 0\n".into(),
        ..Setup::default()
    })
    .expect("start mosquitto");
    let cli = Options {
        broker: Some(broker.addr().to_string()),
        sim: Some(true),
        http: Some("off".into()),
        sila: Some("off".into()),
        log_dir: Some("-".into()),
        ..Options::default()
    };
    let stop = CancellationToken::new();
    let config = Config::resolve(cli, Options::default()).unwrap();
    let gw = tokio::spawn(mc_gateway::run(config, stop.clone()));
    let mut rx = Client::subscribed(broker.addr(), "burst-events", &["#"]);
    rx.set_wait(WAIT);
    expect(&mut rx, "node 111 online", |t, p| {
        t == "ihex/node/111/state" && event(p)["online"] == true
    })
    .await;
    // A publisher whose own window lets the whole burst reach the broker at once.
    let mut options = ihex_tests::mqtt::options(broker.addr(), "burst-publisher");
    options.set_inflight(u16::MAX);
    let publisher = Client::subscribe_on_connect(options, &[]);
    for i in 0..BURST {
        let json = format!(
            r#"{{"cmd":"led","node":"111","color":[{},{},1],"request_id":"burst-{i}"}}"#,
            i & 0xff,
            i >> 8
        );
        publisher.publish("CommandsTopic", json).await;
    }
    let answer = |m: &ihex_tests::mqtt::Seen| {
        let m = m.message()?;
        let v = event(&m.payload);
        let ours = v["payload"]["request_id"]
            .as_str()
            .is_some_and(|r| r.starts_with("burst-"));
        (m.topic == "EventsTopic" && ours).then_some(v)
    };
    let deadline = tokio::time::Instant::now() + ihex_tests::time::scaled(Duration::from_secs(60));
    let mut answers: Vec<Value> = Vec::new();
    while answers.len() < BURST && tokio::time::Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(200)).await;
        answers = rx.drain().iter().filter_map(answer).collect();
    }
    let not_ok: Vec<&Value> = answers
        .iter()
        .filter(|v| v["event"] != "command_result" || v["payload"]["result"] != "ok")
        .collect();
    assert!(
        not_ok.is_empty(),
        "{} of {} answers not ok, the first: {:#?}",
        not_ok.len(),
        answers.len(),
        &not_ok[..not_ok.len().min(3)]
    );
    assert_eq!(answers.len(), BURST, "answered");
    let mut ids: Vec<&str> = answers
        .iter()
        .filter_map(|v| v["payload"]["request_id"].as_str())
        .collect();
    ids.sort_unstable();
    ids.dedup();
    assert_eq!(ids.len(), BURST, "each answered once");
    stop_cleanly(&stop, gw).await;
}

#[tokio::test]
async fn a_taken_broker_port_is_a_clear_error() {
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let r = mc_gateway::run(demo_config(port), CancellationToken::new()).await;
    match r {
        Err(GatewayError::Broker(BrokerError::Bind { addr, .. })) => assert_eq!(addr.port(), port),
        other => panic!("expected a bind error, got {other:?}"),
    }
}

/// The MQTT task started before its broker exists: it retries with back-off, and what it was asked to
/// publish meanwhile (held in its queue) reaches the broker once it appears; meanwhile its status
/// says why it is not connected.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn publications_queued_before_the_broker_exists_are_delivered() {
    use mc_gateway::{
        config::{Broker, MqttConfig},
        mqtt::{self, MqttInput, MqttStats, MqttTask, Outbound},
        topic::Topics,
    };
    let port = free_port();
    let cfg = MqttConfig {
        broker: Broker::External {
            host: "127.0.0.1".into(),
            port,
        },
        client_id: "early-gateway".into(),
        credentials: None,
        tls: None,
        keep_alive: Duration::from_secs(20),
        ack_timeout: Duration::from_secs(5),
    };
    let topics = Topics::seed();
    let stats = std::sync::Arc::new(MqttStats::default());
    let task = MqttTask {
        options: mqtt::options(&cfg, &topics).unwrap(),
        topics,
        ha: false,
        broker: format!("127.0.0.1:{port}"),
        stats: stats.clone(),
        ack_timeout: Duration::from_secs(5),
    };
    let (pub_tx, pub_rx) = mpsc::channel(16);
    let (in_tx, mut in_rx) = mpsc::channel(16);
    let stop = CancellationToken::new();
    let run = tokio::spawn(task.run(pub_rx, in_tx, stop.clone()));
    for n in 0..5 {
        let p = Outbound {
            topic: format!("early/{n}"),
            payload: format!("{n}").into_bytes().into(),
            retain: true,
        };
        pub_tx.send(p).await.unwrap();
    }
    // Let a few connection attempts fail.
    tokio::time::sleep(Duration::from_millis(700)).await;
    assert_eq!(stats.connects.load(std::sync::atomic::Ordering::Relaxed), 0);
    let link = stats.broker_link();
    assert!(!link.connected && link.failed_attempts >= 2, "{link:?}");
    let why = link.last_error.expect("the reason it is not connected");
    assert!(
        why.starts_with(&format!("nothing accepts connections at 127.0.0.1:{port}")),
        "{why}"
    );
    let addr = format!("127.0.0.1:{port}").parse().unwrap();
    tokio::task::spawn_blocking(move || mc_gateway::demo::broker::start(addr))
        .await
        .unwrap()
        .expect("embedded broker");
    let connected = tokio::time::timeout(WAIT, in_rx.recv())
        .await
        .expect("connects");
    assert_eq!(connected, Some(MqttInput::Connected));
    let link = stats.broker_link();
    assert!(link.connected && link.last_error.is_none(), "{link:?}");

    // A client arriving later finds every queued (retained) publication.
    let mut rx = client(port, "late-reader");
    let mut seen = std::collections::BTreeSet::new();
    while seen.len() < 5 {
        let p = expect(&mut rx, "the queued publications", |t, _| {
            t.starts_with("early/")
        })
        .await;
        seen.insert(String::from_utf8(p).unwrap());
    }
    assert_eq!(
        seen.into_iter().collect::<Vec<_>>(),
        vec!["0", "1", "2", "3", "4"]
    );
    assert_eq!(
        stats.published.load(std::sync::atomic::Ordering::Relaxed),
        5
    );
    stop.cancel();
    run.await.unwrap();
}
