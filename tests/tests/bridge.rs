//! The reference topology for a lab with many islands (`docs/deploy.md`): the gateway publishes to
//! a Mosquitto on its own Pi (`deploy/mosquitto/island.conf`), which bridges the island's topics to
//! the lab's central broker (`central.conf`, TLS, passwords, per-island ACL). The link between the
//! two brokers runs through the test proxy and is cut for 60 s (`IHEX_BRIDGE_CUT_S`) while events
//! flow: the central broker sees the bridge's last will, and afterwards it has every QoS 1 event the
//! gateway published, in order, and its retained state documents are the island's current ones.
#![cfg(feature = "tls")]

mod lab_support;

use std::collections::BTreeMap;
use std::time::Duration;

use ihex_tests::broker::{self, Mosquitto, Setup};
use ihex_tests::mqtt::{self, Seen};
use ihex_tests::proxy::{Mode, Proxy};
use lab_support::{client, deploy_file, event, gateway_config, password, Central, Gateway};
use rumqttc::ConnectReturnCode;
use tokio::time::Instant;

/// How long the bridge is cut, seconds (`IHEX_BRIDGE_CUT_S`, default 60 as the issue asks).
fn cut_for() -> Duration {
    let s = std::env::var("IHEX_BRIDGE_CUT_S")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .unwrap_or(60);
    Duration::from_secs(s)
}

/// Every retained message under `filter` on a broker, as a client connecting now sees it.
async fn retained(mut c: mqtt::Client, filter: &str) -> BTreeMap<String, String> {
    assert_eq!(c.connack().await, ConnectReturnCode::Success);
    c.subscribe(filter).await;
    c.subscribe("bench-a/retained-end").await;
    let mut out = BTreeMap::new();
    for s in c.drain() {
        if let Seen::Message { topic, payload, .. } = s {
            out.insert(topic.clone(), String::from_utf8_lossy(payload).into_owned());
        }
    }
    out
}

/// The events a client saw, in order.
fn events(c: &mqtt::Client) -> Vec<String> {
    c.log
        .iter()
        .filter_map(|s| match s {
            Seen::Message { topic, payload, .. } if topic == "bench-a/EventsTopic" => {
                Some(String::from_utf8_lossy(payload).into_owned())
            }
            _ => None,
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cut_bridge_loses_no_event_and_leaves_the_central_state_current() {
    let central = Central::start(&["error", "warning", "notice"]);
    let mut link = Proxy::start(central.addr()).await.expect("proxy");
    let island_conf = broker::rewrite(
        &deploy_file("island.conf"),
        &[
            ("listener", "{port} 127.0.0.1"),
            ("address", &link.addr().to_string()),
            ("remote_password", password("gw-bench-a")),
            ("bridge_cafile", "{dir}/ca.crt"),
            // The documented back-off (2 s, up to 30 s) would only make the test wait longer.
            ("restart_timeout", "1 2"),
        ],
    )
    .expect("island.conf has the lines the test replaces");
    let local = Mosquitto::start_with(&Setup {
        conf: Some(island_conf),
        files: vec![("ca.crt".into(), central.pki.ca.clone().into_bytes())],
        log_types: vec!["error".into(), "warning".into(), "notice".into()],
        ..Setup::default()
    })
    .expect("start the island's broker");
    let ca = central.ca_file();

    let gw = Gateway::start(gateway_config(local.addr(), "bench-a", None, None));
    // On the Pi: what the gateway really published (ground truth), and a bench script.
    let mut pi = client(local.addr(), "pi-observer", None, None, &["bench-a/#"]);
    let script = client(local.addr(), "bench-script", None, None, &[]);
    // In the lab: a dashboard on the central broker, connected all along.
    let mut lab = client(
        central.addr(),
        "dashboard",
        Some(("lab", password("lab"))),
        Some(&ca),
        &["bench-a/#"],
    );
    lab.seen("the gateway online through the bridge", |s| {
        matches!(s, Seen::Message { topic, payload, .. }
            if topic == "bench-a/ihex/gateway/availability" && payload == b"online")
    })
    .await;
    // Commands flow the other way too: lab -> central -> bridge -> Pi -> gateway.
    lab.publish(
        "bench-a/CommandsTopic",
        r#"{"cmd":"list","request_id":"via-bridge"}"#,
    )
    .await;
    lab.expect("the answer to a command sent through the bridge", |s| {
        event(s, "bench-a/EventsTopic", "node_list")
            .is_some_and(|p| p["request_id"] == "via-bridge")
    })
    .await;

    // Events flow: a command every 200 ms, a docking change every 2 s, before, during and after
    // the cut.
    let cut = cut_for();
    let run = |from: u32, for_: Duration| {
        let script = &script;
        async move {
            let until = Instant::now() + for_;
            let mut n = from;
            while Instant::now() < until {
                n += 1;
                let c = ihex_tests::fault::plan::unique_color(n);
                script
                    .publish(
                        "bench-a/CommandsTopic",
                        format!(
                            r#"{{"cmd":"led","node":"111","color":[{},{},{}],"request_id":"b{n}"}}"#,
                            c[0], c[1], c[2]
                        ),
                    )
                    .await;
                if n.is_multiple_of(10) {
                    let sim = if n.is_multiple_of(20) {
                        r#"{"sim":"dock","mobile":"3","static":"112","port":2}"#
                    } else {
                        r#"{"sim":"undock","mobile":"3"}"#
                    };
                    script.publish("bench-a/ihex/sim", sim).await;
                }
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            n
        }
    };
    let n = run(0, Duration::from_secs(3)).await;
    // The central broker unreachable: the live bridge connection cut, new ones refused. (Accepting
    // them and closing them at once instead hung Debian's Mosquitto 2.0.11 in about half of the
    // runs: docs/deploy.md, "Known problems".)
    link.refuse();
    link.set(Mode::Cut);
    let cut_at = Instant::now();
    lab.expect(
        "the bridge's state 0 (its last will) on the central broker",
        |s| {
            matches!(s, Seen::Message { topic, payload, .. }
            if topic == "bench-a/ihex/bridge/state" && payload == b"0")
        },
    )
    .await;
    let n = run(n, cut.saturating_sub(cut_at.elapsed())).await;
    link.set(Mode::Pass);
    link.listen().expect("listen again");
    let n = run(n, Duration::from_secs(3)).await;
    // The last answers on the Pi, then everything at the centre.
    pi.expect("the last command's answer on the Pi", |s| {
        event(s, "bench-a/EventsTopic", "command_result")
            .is_some_and(|p| p["request_id"] == format!("b{n}"))
    })
    .await;
    lab.expect("the last command's answer through the bridge", |s| {
        event(s, "bench-a/EventsTopic", "command_result")
            .is_some_and(|p| p["request_id"] == format!("b{n}"))
    })
    .await;
    lab.drain();
    pi.drain();

    // No event lost, none reordered: the centre's events are the Pi's (from when the dashboard
    // subscribed), each at least once (QoS 1 may repeat one after the reconnection).
    let at_pi = events(&pi);
    let at_lab = events(&lab);
    let first = at_lab.first().expect("events at the centre");
    let from = at_pi
        .iter()
        .position(|e| e == first)
        .expect("the centre's first event was published on the Pi");
    let mut dedup = at_lab.clone();
    dedup.dedup();
    let missing: Vec<&String> = at_pi[from..]
        .iter()
        .filter(|e| !at_lab.contains(e))
        .collect();
    assert!(
        missing.is_empty(),
        "{} of {} events published on the Pi never reached the central broker, e.g. {:?}",
        missing.len(),
        at_pi.len() - from,
        missing.first()
    );
    assert_eq!(
        dedup,
        at_pi[from..],
        "the central broker got the island's events in another order"
    );
    let results = at_pi[from..]
        .iter()
        .filter(|e| e.contains("command_result"))
        .count();
    assert!(
        results as u32 >= n - 2,
        "{results} answers for {n} commands"
    );
    assert!(
        lab.log
            .iter()
            .any(|s| matches!(s, Seen::Message { topic, payload, .. }
            if topic == "bench-a/ihex/bridge/state" && payload == b"1")),
        "the bridge's state went back to 1"
    );
    eprintln!(
        "bridge cut {:?}: {} events published on the Pi, {} delivered at the centre ({} repeated)",
        cut,
        at_pi.len() - from,
        at_lab.len(),
        at_lab.len() - dedup.len()
    );

    // The retained state at the centre is the island's, document for document — once the bridge
    // has forwarded the last publications (a state document may follow the last answer by a
    // moment, and the centre gets it a hop later): read both until they agree, for a while.
    let docs = |m: &BTreeMap<String, String>| -> BTreeMap<String, String> {
        m.iter()
            .filter(|(t, _)| {
                t.ends_with("/state") && t.contains("/node/") || t.ends_with("availability")
            })
            .map(|(t, p)| (t.clone(), p.clone()))
            .collect()
    };
    let mut attempt = 0;
    let (on_pi, at_centre) = loop {
        attempt += 1;
        let on_pi = retained(
            client(
                local.addr(),
                &format!("pi-retained-{attempt}"),
                None,
                None,
                &[],
            ),
            "bench-a/ihex/#",
        )
        .await;
        let at_centre = retained(
            client(
                central.addr(),
                &format!("lab-retained-{attempt}"),
                Some(("lab", password("lab"))),
                Some(&ca),
                &[],
            ),
            "bench-a/ihex/#",
        )
        .await;
        if docs(&on_pi) == docs(&at_centre) || attempt == 20 {
            break (on_pi, at_centre);
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    };
    assert!(docs(&on_pi).len() >= 5, "{on_pi:?}");
    assert_eq!(
        docs(&at_centre),
        docs(&on_pi),
        "retained state at the centre differs from the Pi's (still after {attempt} readings)"
    );
    gw.shutdown().await;
    drop(local);
}
