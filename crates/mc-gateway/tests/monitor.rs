//! `/readyz` and `/healthz` against a real broker: a gateway (simulated island) connected to a real
//! Mosquitto is ready; with the broker killed it answers `503` naming MQTT, and once the broker is
//! back it is ready again. `/healthz` stays `200` throughout (the process and its core answer).
#![cfg(all(feature = "demo", feature = "web"))]

use std::{
    io::{Read, Write},
    net::{SocketAddr, TcpStream},
    time::{Duration, Instant},
};

use ihex_tests::{broker::Mosquitto, time::scaled};
use mc_gateway::{config::Options, CancellationToken, Config, Gateway};
use serde_json::Value;

/// `GET path` over HTTP/1.0: the status and the body.
fn get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n").unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    (status, body.to_owned())
}

/// Polls `/readyz` (off the runtime's thread) until its status is `want`; returns the body.
async fn readyz_becomes(view: SocketAddr, want: u16, what: &str) -> Value {
    let deadline = Instant::now() + scaled(Duration::from_secs(30));
    loop {
        let (status, body) = tokio::task::spawn_blocking(move || get(view, "/readyz"))
            .await
            .unwrap();
        if status == want {
            return serde_json::from_str(&body).unwrap();
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}: {status} {body}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn healthz(view: SocketAddr) -> (u16, String) {
    tokio::task::spawn_blocking(move || get(view, "/healthz"))
        .await
        .unwrap()
}

#[tokio::test]
async fn readyz_follows_the_broker_and_healthz_the_process() {
    let mut mosq = Mosquitto::start()
        .expect("mosquitto must be installed for this test (`cargo xtask setup` installs it)");
    let cli = Options {
        broker: Some(mosq.addr().to_string()),
        sim: Some(true),
        http: Some("127.0.0.1:0".into()),
        log_dir: Some("-".into()),
        health_period_ms: Some(200),
        ..Options::default()
    };
    let config = Config::resolve(cli, Options::default()).unwrap();
    let gateway = Gateway::build(config, Default::default()).await.unwrap();
    let view = gateway.view_addr().expect("the view listens");
    let stop = CancellationToken::new();
    let run = tokio::spawn(gateway.run(stop.clone()));

    let ready = readyz_becomes(view, 200, "ready with the broker up").await;
    assert_eq!(
        ready,
        serde_json::json!({"ready": true, "mqtt_connected": true, "bus_up": true, "not_ready": []})
    );
    assert_eq!(healthz(view).await, (200, r#"{"status":"ok"}"#.to_owned()));

    mosq.stop();
    let unready = readyz_becomes(view, 503, "unready with the broker gone").await;
    assert_eq!(unready["ready"], false);
    assert_eq!(unready["mqtt_connected"], false);
    assert_eq!(unready["bus_up"], true);
    let why = unready["not_ready"].as_array().unwrap();
    assert_eq!(why.len(), 1, "{unready}");
    assert!(
        why[0].as_str().unwrap().starts_with("mqtt: not connected"),
        "{unready}"
    );
    assert_eq!(healthz(view).await.0, 200, "alive without its broker");

    mosq.restart().unwrap();
    readyz_becomes(view, 200, "ready again with the broker back").await;

    stop.cancel();
    run.await.unwrap().unwrap();
}
