//! `can` (assignment through the gateway's MQTT API) against a real Mosquitto broker on the loopback
//! and a scripted stand-in for the gateway that speaks its documented JSON (docs/mqtt-api.md): the
//! duplicate check, the request-id matching and every failure path, without a CAN bus.
//! Needs the `mosquitto` binary (Debian: `apt-get install mosquitto`).

use std::{
    net::{TcpListener, TcpStream},
    process::{Child, Command, Stdio},
    sync::{Arc, Mutex},
    time::{Duration, Instant},
};

use ihex_gateway_core::event::Outcome;
use ihex_proto::NodeId;
use ihex_provision::{
    api::{parse_uid, GatewayEvent},
    can::{assign, AssignError, Assignment, Topics},
    id::IdError,
    mqtt::Broker,
};
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use serde_json::{json, Value};

/// A Mosquitto on 127.0.0.1 and a free port, stopped on drop.
struct Mosquitto {
    child: Child,
    port: u16,
    _dir: std::path::PathBuf,
}

impl Mosquitto {
    fn start() -> Mosquitto {
        let port = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let dir =
            std::env::temp_dir().join(format!("ihex-provision-mosq-{}-{port}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let conf = dir.join("mosquitto.conf");
        std::fs::write(
            &conf,
            format!("listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"),
        )
        .unwrap();
        let bin = ["mosquitto", "/usr/sbin/mosquitto"]
            .into_iter()
            .find(|b| {
                Command::new(b)
                    .arg("-h")
                    .stdout(Stdio::null())
                    .stderr(Stdio::null())
                    .status()
                    .is_ok()
            })
            .expect("mosquitto not found: install it (Debian: apt-get install mosquitto)");
        let child = Command::new(bin)
            .arg("-c")
            .arg(&conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                Instant::now() < deadline,
                "mosquitto did not start on port {port}"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        Mosquitto {
            child,
            port,
            _dir: dir,
        }
    }

    fn broker(&self) -> Broker {
        Broker::parse(&format!("127.0.0.1:{}", self.port)).unwrap()
    }
}

impl Drop for Mosquitto {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self._dir);
    }
}

/// What the stand-in gateway knows and how it answers.
#[derive(Clone)]
struct Script {
    /// `node_list` entries: (id, online).
    nodes: Vec<(&'static str, bool)>,
    /// Answer `list` at all.
    answer_list: bool,
    /// The `result` for an assignment of this UID (default "ok").
    results: Vec<(String, &'static str, &'static str)>,
}

/// A stand-in gateway on `topics`: answers `list` with `node_list` and `assign` with `command_result`;
/// records every command it received. Publishes one retained node state first.
async fn fake_gateway(port: u16, topics: Topics, script: Script) -> Arc<Mutex<Vec<Value>>> {
    let seen = Arc::new(Mutex::new(Vec::new()));
    let mut opts = MqttOptions::new(
        format!("fake-gw-{port}-{}", topics.commands.replace('/', "-")),
        "127.0.0.1",
        port,
    );
    opts.set_keep_alive(Duration::from_secs(20));
    let (client, mut el) = AsyncClient::new(opts, 16);
    client
        .subscribe(topics.commands.clone(), QoS::AtLeastOnce)
        .await
        .unwrap();
    client
        .publish(
            format!("{}/5/state", topics.node_state_root),
            QoS::AtLeastOnce,
            true,
            r#"{"id":"5","online":true}"#,
        )
        .await
        .unwrap();
    // Wait for the subscription, so no command is missed.
    loop {
        if let Event::Incoming(Packet::SubAck(_)) = el.poll().await.unwrap() {
            break;
        }
    }
    let seen2 = seen.clone();
    tokio::spawn(async move {
        loop {
            let Ok(ev) = el.poll().await else { return };
            let Event::Incoming(Packet::Publish(p)) = ev else {
                continue;
            };
            let cmd: Value = serde_json::from_slice(&p.payload).unwrap();
            seen2.lock().unwrap().push(cmd.clone());
            let rid = cmd["request_id"].clone();
            let answer = match cmd["cmd"].as_str() {
                Some("list") if script.answer_list => {
                    let nodes: Vec<Value> = script
                        .nodes
                        .iter()
                        .map(|&(id, online)| state(id, online))
                        .collect();
                    json!({"event":"node_list","payload":{"request_id":rid,"nodes":nodes}})
                }
                Some("assign") => {
                    let uid = cmd["uid"].as_str().unwrap_or_default();
                    let (result, reason) = script
                        .results
                        .iter()
                        .find(|(u, _, _)| u == uid)
                        .map_or(("ok", None), |(_, r, why)| (*r, Some(*why)));
                    json!({"event":"command_result","payload":{"request_id":rid,"cmd":"assign",
                        "node":cmd["new_id"],"result":result,"reason":reason}})
                }
                _ => continue,
            };
            // Unrelated traffic first: the tool must pick its answer by request_id.
            let noise = json!({"event":"command_result","payload":{"request_id":"someone-else","cmd":"assign",
                "node":"7","result":"ok","reason":null}});
            for e in [noise, answer] {
                client
                    .publish(
                        topics.events.clone(),
                        QoS::AtLeastOnce,
                        false,
                        e.to_string(),
                    )
                    .await
                    .unwrap();
            }
        }
    });
    seen
}

/// A node's state document as the gateway publishes it (docs/mqtt-api.md), before any command.
fn state(id: &str, online: bool) -> Value {
    json!({"id": id, "online": online, "role": "static", "ports": 6, "version": "1.0",
           "led": null, "buzzer": null, "relay": false, "loops": [], "connections": [],
           "reported": null, "last_seen_ms": 10, "first_seen_ms": 1000})
}

fn topics(island: Option<&str>) -> Topics {
    Topics::new(island, "CommandsTopic", "EventsTopic", "ihex/node")
}

fn script() -> Script {
    Script {
        nodes: vec![("111", true), ("2", false)],
        answer_list: true,
        results: vec![(
            "ffffffffffffffffffffffff".into(),
            "timeout",
            "no reply from the selected board",
        )],
    }
}

fn assignment(uid: &str, id: u16) -> Assignment {
    Assignment {
        uid: parse_uid(uid).unwrap(),
        new_id: NodeId::new_sc(id).unwrap(),
        skip_duplicate_check: false,
        timeout: Duration::from_secs(5),
    }
}

const UID: &str = "0123456789abcdef01234567";

fn assigns(seen: &Mutex<Vec<Value>>) -> Vec<Value> {
    seen.lock()
        .unwrap()
        .iter()
        .filter(|c| c["cmd"] == "assign")
        .cloned()
        .collect()
}

#[tokio::test]
async fn assigns_a_free_id_and_refuses_taken_ones() {
    let mosq = Mosquitto::start();
    let t = topics(None);
    let seen = fake_gateway(mosq.port, t.clone(), script()).await;

    let ok = assign(&mosq.broker(), &t, &assignment(UID, 0x123))
        .await
        .unwrap();
    assert_eq!(ok.result, Outcome::Ok);
    assert_eq!(ok.node.to_string(), "123");
    let sent = assigns(&seen);
    assert_eq!(sent.len(), 1);
    assert_eq!(sent[0]["uid"], UID);
    assert_eq!(sent[0]["new_id"], "123");

    // 111 is online, 2 is lost (still owns its ID), 5 only has a retained state topic.
    for taken in [0x111, 0x2, 0x5] {
        let err = assign(&mosq.broker(), &t, &assignment(UID, taken))
            .await
            .unwrap_err();
        assert!(
            matches!(err, AssignError::Id(IdError::Duplicate { .. })),
            "{taken:x}: {err}"
        );
        assert!(err.to_string().contains("already assigned"), "{err}");
    }
    // Refused IDs never reached the gateway as an assign command.
    assert_eq!(assigns(&seen).len(), 1);

    // Overriding the check sends it anyway (the gateway has its own check for online nodes).
    let mut a = assignment(UID, 0x2);
    a.skip_duplicate_check = true;
    assign(&mosq.broker(), &t, &a).await.unwrap();
    assert_eq!(assigns(&seen).len(), 2);
}

#[tokio::test]
async fn a_failed_assignment_is_an_error_with_the_reason() {
    let mosq = Mosquitto::start();
    let t = topics(Some("lab-a"));
    let _seen = fake_gateway(mosq.port, t.clone(), script()).await;
    let err = assign(
        &mosq.broker(),
        &t,
        &assignment("ffffffffffffffffffffffff", 0x300),
    )
    .await
    .unwrap_err();
    match &err {
        AssignError::Failed { reason, answer } => {
            assert_eq!(reason, "no reply from the selected board");
            assert!(
                matches!(&**answer, GatewayEvent::CommandResult(r) if r.result == Outcome::Timeout),
                "{answer:?}"
            );
        }
        other => panic!("{other}"),
    }
}

#[tokio::test]
async fn no_gateway_means_no_blind_assignment() {
    let mosq = Mosquitto::start();
    // A gateway on another island: our commands go unanswered.
    let _seen = fake_gateway(mosq.port, topics(Some("other")), script()).await;
    let mut a = assignment(UID, 0x123);
    a.timeout = Duration::from_millis(700);
    let err = assign(&mosq.broker(), &topics(Some("mine")), &a)
        .await
        .unwrap_err();
    assert!(matches!(err, AssignError::NoList(_)), "{err}");

    // An assignment whose answer never reaches the tool.
    let quiet = Script {
        results: vec![],
        answer_list: true,
        nodes: vec![],
    };
    let t = topics(Some("quiet"));
    let seen = fake_gateway(mosq.port, t.clone(), quiet).await;
    a.skip_duplicate_check = true;
    // The stand-in does answer, but on its own events topic: the tool listens elsewhere and must time out.
    let mut deaf = t.clone();
    deaf.events = "nobody/EventsTopic".into();
    let err = assign(&mosq.broker(), &deaf, &a).await.unwrap_err();
    assert!(matches!(err, AssignError::NoAnswer(..)), "{err}");
    assert_eq!(assigns(&seen).len(), 1);
}

#[test]
fn cli_refuses_bad_input_before_touching_the_network() {
    // Port 1 on the loopback: nothing listens, so any attempt to connect would fail differently.
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_ihex-provision"))
            .args(args)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    for (id, what) in [
        ("fff", "reserved"),
        ("0", "reserved"),
        ("ffe", "reserved"),
        ("abcd", "1 to 3 hex digits"),
        ("1g", "hex"),
    ] {
        let (ok, err) = run(&["can", "--broker", "127.0.0.1:1", "--uid", UID, "--id", id]);
        assert!(
            !ok && err.contains(what) && !err.contains("MQTT"),
            "{id}: {err}"
        );
    }
    let (ok, err) = run(&[
        "can",
        "--broker",
        "127.0.0.1:1",
        "--uid",
        "0123",
        "--id",
        "12",
    ]);
    assert!(!ok && err.contains("24 hex digits"), "{err}");
    let (ok, err) = run(&["can", "--broker", "127.0.0.1:1", "--uid", UID, "--id", "12"]);
    assert!(!ok && err.contains("MQTT"), "{err}");
}

#[test]
fn cli_end_to_end() {
    let mosq = Mosquitto::start();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let seen = rt.block_on(fake_gateway(mosq.port, topics(Some("bench")), script()));
    let broker = format!("127.0.0.1:{}", mosq.port);
    let run = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_ihex-provision"))
            .args(args)
            .output()
            .unwrap();
        let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
        (out.status.success(), text(&out.stdout), text(&out.stderr))
    };
    let registry =
        std::env::temp_dir().join(format!("ihex-provision-can-{}.csv", std::process::id()));
    let _ = std::fs::remove_file(&registry);
    let reg = registry.to_str().unwrap();
    let (ok, out, err) = run(&[
        "can",
        "--broker",
        &broker,
        "--island",
        "bench",
        "--uid",
        UID,
        "--id",
        "42",
        "--registry",
        reg,
    ]);
    assert!(ok, "{err}");
    assert!(out.contains("assigned ID 42"), "{out}");
    let csv = std::fs::read_to_string(&registry).unwrap();
    assert!(csv.contains(&format!("042,{UID},")), "{csv}");
    let (ok, _, err) = run(&[
        "can", "--broker", &broker, "--island", "bench", "--uid", UID, "--id", "111",
    ]);
    assert!(!ok && err.contains("already assigned"), "{err}");
    // The registry refuses 42 before the gateway is even asked.
    let (ok, _, err) = run(&[
        "can",
        "--broker",
        &broker,
        "--island",
        "bench",
        "--uid",
        UID,
        "--id",
        "42",
        "--registry",
        reg,
    ]);
    assert!(
        !ok && err.contains("already assigned") && err.contains("line 2"),
        "{err}"
    );
    assert_eq!(assigns(&seen).len(), 1);
    assert_eq!(
        seen.lock()
            .unwrap()
            .iter()
            .filter(|c| c["cmd"] == "list")
            .count(),
        2
    );
    std::fs::remove_file(&registry).unwrap();
    drop(rt);
}
