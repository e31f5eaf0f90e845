//! The audit trail end to end, with a real Mosquitto: `deploy/mosquitto/identity.conf` and
//! `identity.acl` (passwords, `pattern write +/ihex/cmd/%u`) and the gateway on the simulated
//! island with `--require-identity`. Two users' commands are answered and recorded under their
//! names; a user publishing on another user's topic is refused by the broker and nothing is
//! recorded as that user; the chain verifies. A full audit directory (`--audit-max-bytes`, and a
//! real full tmpfs when this runs as root) leaves every command answered, publishes `audit_error`
//! and raises the health flag.
#![cfg(all(feature = "demo", feature = "web"))]

use std::path::Path;
use std::time::Duration;

use ihex_audit::dir::{chain_files, file_lines, verify_dir};
use ihex_audit::{Entry, Kind};
use ihex_tests::broker::{self, Mosquitto, Setup};
use ihex_tests::mqtt::{self, Client};
use mc_gateway::{config::Options, CancellationToken, Config, Gateway};
use rumqttc::QoS;
use serde_json::Value;

const ISLAND: &str = "bench-a";
const USERS: [(&str, &str); 3] = [
    ("gw-bench-a", "pass-gw"),
    ("alice", "pass-alice"),
    ("bob", "pass-bob"),
];

fn deploy_file(name: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../deploy/mosquitto")
        .join(name);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The broker as `identity.conf` and `identity.acl` configure it, on a free loopback port.
fn identity_broker() -> Mosquitto {
    let conf = broker::rewrite(
        &deploy_file("identity.conf"),
        &[
            ("listener", "{port} 127.0.0.1"),
            ("password_file", "{dir}/passwd"),
            ("acl_file", "{dir}/acl"),
        ],
    )
    .expect("identity.conf has the lines the test replaces");
    let setup = Setup {
        conf: Some(conf),
        files: vec![
            (
                "passwd".into(),
                broker::password_file(&USERS).expect("mosquitto_passwd"),
            ),
            ("acl".into(), deploy_file("identity.acl").into_bytes()),
        ],
        // `debug`: Mosquitto logs a denied PUBLISH only there.
        log_types: ["error", "warning", "notice", "debug"]
            .map(Into::into)
            .to_vec(),
        ..Setup::default()
    };
    Mosquitto::start_with(&setup)
        .expect("mosquitto must be installed for this test (`cargo xtask setup` installs it)")
}

fn user_client(broker: std::net::SocketAddr, user: &str, filters: &[&str]) -> Client {
    let mut o = mqtt::options(broker, &format!("test-{user}"));
    let pass = USERS.iter().find(|(u, _)| *u == user).unwrap().1;
    o.set_credentials(user, pass);
    Client::subscribe_on_connect(o, filters)
}

/// Starts the gateway on the simulated island; returns its stop token and task.
async fn gateway(
    cli: Options,
) -> (
    CancellationToken,
    tokio::task::JoinHandle<Result<(), mc_gateway::error::GatewayError>>,
    Option<std::net::SocketAddr>,
) {
    let config = Config::resolve(cli, Options::default()).unwrap();
    let gateway = Gateway::build(config, Default::default()).await.unwrap();
    let view = gateway.view_addr();
    let stop = CancellationToken::new();
    let run = tokio::spawn(gateway.run(stop.clone()));
    (stop, run, view)
}

fn entries(dir: &Path) -> Vec<Entry> {
    chain_files(dir)
        .unwrap()
        .iter()
        .flat_map(|f| file_lines(f).unwrap())
        .map(|l| serde_json::from_slice(&l.bytes).unwrap())
        .collect()
}

async fn command(c: &Client, user: &str, json: &str) {
    c.client
        .publish(
            format!("{ISLAND}/ihex/cmd/{user}"),
            QoS::AtLeastOnce,
            false,
            json,
        )
        .await
        .unwrap();
}

async fn answer(c: &mut Client, events: &str, request_id: &str) -> Value {
    let event = c
        .expect_msg(&format!("the answer to {request_id}"), |m| {
            m.topic == events && m.json()["payload"]["request_id"] == request_id
        })
        .await
        .json();
    event["payload"].clone()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_user_is_recorded_under_the_name_the_broker_vouches_for() {
    let mosq = identity_broker();
    let audit = tempfile::tempdir().unwrap();
    let cli = Options {
        broker: Some(mosq.addr().to_string()),
        username: Some("gw-bench-a".into()),
        password: Some("pass-gw".into()),
        island: Some(ISLAND.into()),
        sim: Some(true),
        http: Some("off".into()),
        log_dir: Some("-".into()),
        audit_dir: Some(audit.path().to_str().unwrap().into()),
        require_identity: Some(true),
        ..Options::default()
    };
    let (stop, run, _) = gateway(cli).await;
    let events = format!("{ISLAND}/EventsTopic");
    let mut alice = user_client(mosq.addr(), "alice", &[&events]);
    let mut bob = user_client(mosq.addr(), "bob", &[&events]);
    // The gateway is up once its retained availability says so.
    alice
        .expect_msg("the gateway online", |m| {
            m.topic == events && m.json()["event"] == "node_online"
        })
        .await;

    command(
        &alice,
        "alice",
        r#"{"cmd":"power","node":"111","on":true,"request_id":"a1"}"#,
    )
    .await;
    let a1 = answer(&mut alice, &events, "a1").await;
    assert_eq!(a1["result"], "ok", "{a1}");
    assert_eq!(
        a1["origin"],
        serde_json::json!({"interface": "mqtt", "user": "alice"})
    );
    // Bob names himself alice in the JSON: recorded as his claim, vouched as bob.
    command(
        &bob,
        "bob",
        r#"{"cmd":"power","node":"112","on":true,"request_id":"b1","user":"alice"}"#,
    )
    .await;
    let b1 = answer(&mut bob, &events, "b1").await;
    assert_eq!(
        b1["origin"],
        serde_json::json!({"interface": "mqtt", "user": "bob", "claimed": "alice"})
    );

    // Bob on alice's topic, and on the shared topic: the broker drops both.
    command(
        &bob,
        "alice",
        r#"{"cmd":"power","node":"111","on":false,"request_id":"forged"}"#,
    )
    .await;
    bob.client
        .publish(
            format!("{ISLAND}/CommandsTopic"),
            QoS::AtLeastOnce,
            false,
            r#"{"cmd":"power","node":"111","on":false,"request_id":"shared"}"#,
        )
        .await
        .unwrap();
    // After them on the same connection: when its answer is in, the forged ones would have been.
    command(&bob, "bob", r#"{"cmd":"list","request_id":"b2"}"#).await;
    answer(&mut bob, &events, "b2").await;
    assert!(
        !bob.log.iter().chain(alice.log.iter()).any(|s| s
            .message()
            .is_some_and(|m| m.json()["payload"]["request_id"] == "forged"
                || m.json()["payload"]["request_id"] == "shared")),
        "the broker let a forged command through"
    );
    let log = mosq.log();
    assert!(
        log.contains("Denied PUBLISH from test-bob") && log.contains("'bench-a/ihex/cmd/alice'"),
        "{log}"
    );

    stop.cancel();
    run.await.unwrap().unwrap();

    let report = verify_dir(audit.path(), None).unwrap();
    assert_eq!(report.broken, None, "{report:?}");
    let all = entries(audit.path());
    assert_eq!(all.first().unwrap().record.kind, Kind::Start);
    assert_eq!(all.last().unwrap().record.kind, Kind::Stop);
    let of = |kind: Kind, request_id: &str| {
        all.iter()
            .filter(|e| e.record.kind == kind && e.record.request_id.as_deref() == Some(request_id))
            .map(|e| &e.record)
            .collect::<Vec<_>>()
    };
    for (rid, user) in [("a1", "alice"), ("b1", "bob"), ("b2", "bob")] {
        let cmd = of(Kind::Command, rid);
        assert_eq!(cmd.len(), 1, "{rid}: {all:#?}");
        assert_eq!(cmd[0].user.as_deref(), Some(user), "{rid}");
        assert_eq!(cmd[0].interface.as_deref(), Some("mqtt"));
        let ans = of(Kind::Answer, rid);
        assert_eq!(ans.len(), 1, "{rid}: {all:#?}");
        if rid != "b2" {
            // `list`'s answer (`node_list`) carries no origin; the command record has it.
            assert_eq!(ans[0].user.as_deref(), Some(user), "{rid}");
        }
    }
    assert_eq!(of(Kind::Command, "a1")[0].elements, ["111"]);
    assert_eq!(of(Kind::Command, "b1")[0].claimed.as_deref(), Some("alice"));
    assert!(of(Kind::Command, "forged").is_empty() && of(Kind::Command, "shared").is_empty());
    let as_alice: Vec<_> = all
        .iter()
        .filter(|e| e.record.user.as_deref() == Some("alice"))
        .map(|e| e.record.request_id.clone())
        .collect();
    assert_eq!(as_alice, [Some("a1".into()), Some("a1".into())], "{all:#?}");
}

/// Sends `n` commands on the shared topic and checks each gets its answer.
async fn every_command_answered(c: &mut Client, commands: &str, events: &str, n: usize) {
    for i in 0..n {
        let rid = format!("c{i}");
        let json = format!(r#"{{"cmd":"power","node":"111","on":true,"request_id":"{rid}"}}"#);
        c.client
            .publish(commands, QoS::AtLeastOnce, false, json)
            .await
            .unwrap();
        let a = answer(c, events, &rid).await;
        assert_eq!(a["result"], "ok", "{a}");
    }
}

async fn full_trail_still_answers(audit_dir: &Path, max_bytes: Option<u64>) {
    let mosq = Mosquitto::start().expect("mosquitto");
    let cli = Options {
        broker: Some(mosq.addr().to_string()),
        sim: Some(true),
        http: Some("127.0.0.1:0".into()),
        log_dir: Some("-".into()),
        audit_dir: Some(audit_dir.to_str().unwrap().into()),
        audit_max_bytes: max_bytes,
        ..Options::default()
    };
    let (stop, run, view) = gateway(cli).await;
    let view = view.unwrap();
    let events = "EventsTopic";
    let mut c = Client::subscribed(mosq.addr(), "test-full", &[events]);
    c.expect_msg("the island online", |m| m.json()["event"] == "node_online")
        .await;
    every_command_answered(&mut c, "CommandsTopic", events, 40).await;
    let is_error = |m: &ihex_tests::mqtt::Message| m.json()["event"] == "audit_error";
    let seen = c.log.iter().filter_map(|s| s.message()).find(is_error);
    let error = match seen {
        Some(m) => m.json(),
        None => c.expect_msg("audit_error", is_error).await.json(),
    };
    assert!(error["payload"]["lost"].as_u64().unwrap() >= 1, "{error}");
    // Still answered while nothing is recorded.
    every_command_answered(&mut c, "CommandsTopic", events, 5).await;
    let (status, body) = tokio::task::spawn_blocking(move || http_get(view, "/healthz"))
        .await
        .unwrap();
    let health: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(
        (status, &health["status"]),
        (200, &Value::from("ok")),
        "{body}"
    );
    assert!(health["audit"].as_str().is_some(), "{body}");
    let (_, metrics) = tokio::task::spawn_blocking(move || http_get(view, "/metrics"))
        .await
        .unwrap();
    assert!(metrics.contains("\nihex_audit_up 0"), "{metrics}");
    // The island view's list: the records written, without the chain's link, and why it stopped.
    let (status, body) = tokio::task::spawn_blocking(move || http_get(view, "/api/audit"))
        .await
        .unwrap();
    let audit: Value = serde_json::from_str(&body).unwrap();
    assert_eq!((status, &audit["on"]), (200, &Value::from(true)), "{body}");
    assert!(audit["problem"].as_str().is_some(), "{body}");
    let records = audit["records"].as_array().unwrap();
    assert_eq!(records[0]["kind"], "start", "{body}");
    assert!(
        records
            .iter()
            .all(|r| r.get("prev").is_none() && r["seq"].is_u64()),
        "{body}"
    );
    assert!(
        records
            .iter()
            .any(|r| r["kind"] == "answer" && r["data"]["event"] == "command_result"),
        "{body}"
    );

    stop.cancel();
    run.await.unwrap().unwrap();
    // What was written is a whole chain.
    let report = verify_dir(audit_dir, None).unwrap();
    assert_eq!(report.broken, None, "{report:?}");
    assert!(report.records >= 3, "{report:?}");
}

fn http_get(addr: std::net::SocketAddr, path: &str) -> (u16, String) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(addr).unwrap();
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_audit_directory_never_costs_a_commands_answer() {
    let dir = tempfile::tempdir().unwrap();
    full_trail_still_answers(dir.path(), Some(8192)).await;
}

/// The same on a real full file system: a 64 KiB tmpfs (needs root to mount; elsewhere the quota
/// test above covers the writer's behaviour).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_never_costs_a_commands_answer() {
    let dir = tempfile::tempdir().unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=64k", "tmpfs"])
        .arg(dir.path())
        .status()
        .is_ok_and(|s| s.success());
    if !mounted {
        eprintln!("skipped: cannot mount a tmpfs here (not root)");
        return;
    }
    /// Unmounts the tmpfs however the test ends.
    struct Mounted<'a>(&'a Path);
    impl Drop for Mounted<'_> {
        fn drop(&mut self) {
            let _ = std::process::Command::new("umount").arg(self.0).status();
        }
    }
    let _mounted = Mounted(dir.path());
    // Nearly full before the gateway starts.
    let filler = dir.path().join("filler");
    let _ = std::fs::write(&filler, vec![0u8; 56 * 1024]);
    let audit = dir.path().join("audit");
    full_trail_still_answers(&audit, None).await;
    let _ = std::process::Command::new("umount")
        .arg(dir.path())
        .status();
}
