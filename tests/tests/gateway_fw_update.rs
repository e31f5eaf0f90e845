//! Firmware update end to end over vcan + Mosquitto: the real gateway updates a simulated island
//! whose nodes run the real update receiver over a simulated flash with embassy-boot's swap.
//! 1. `fw_update` of an image in the gateway's `--fw-dir`, signed with a key the nodes do not
//!    trust: every node refuses, and keeps its version.
//! 2. The real `ihex-provision fw update` uploads that image over MQTT: the gateway (with the
//!    test key as `--fw-key`) rejects the upload, and the CLI fails saying why.
//! 3. `ihex-provision fw update` of the test-signed image, a local file: uploaded, every node
//!    updated, the CLI exits 0 and every node reports the new version. During the transfer a
//!    command to a node under update and a docking complete (their latency belongs to
//!    `cargo xtask bench`, not here).
//!
//! And a rollout on a small island with docked mobile elements (`a_rollout_never_strands_a_docked_element`):
//! images made by `ihex-provision fw demo-image`; "update all" ends with every element `updated`
//! and every mobile element powered, docked and online; the same command again skips every
//! element (resume); a reverting image with `--canary 1` stops after the canary; a reverting image
//! on a static element leaves its docked mobile element powered and docked; piped output is
//! plain progress lines.
#![cfg(feature = "vcan")]

mod gateway_support;

use std::time::Duration;

use gateway_support::{id, Client, Gateway};
use ihex_proto::FirmwareVersion;
use ihex_tests::broker::Mosquitto;
use serde_json::Value;
use sim_node::board::{sim_image, SimFirmware};
use sim_node::{link::Link, Island, IslandDesc};

/// Static elements in the island: the issue's 20.
const NODES: u16 = 20;
/// Payload of the test images: large enough that commands and a docking land inside the transfer,
/// small enough that it takes seconds under emulation.
const PAYLOAD: usize = 8 * 1024;
/// How long a whole update may take (scaled in the VM).
const UPDATE_WAIT: Duration = Duration::from_secs(60);

fn island(n: u16) -> String {
    let statics: String = (0..n)
        .map(|i| format!("[[static]]\nid = \"{:x}\"\nports = 6\n\n", 0x101 + i))
        .collect();
    // A mobile element, undocked: it docks during the update.
    format!("{statics}[[mobile]]\nid = \"2\"\nport = 0\n")
}

async fn report(client: &mut Client, events: &str, request_id: &str) -> Value {
    let deadline = ihex_tests::time::scaled(UPDATE_WAIT);
    let wait = client.expect_event(events, "fw_report", |p| p["request_id"] == request_id);
    ihex_tests::within_or_panic(deadline, "fw_report", wait).await["payload"].clone()
}

/// Runs `ihex-provision fw update IMAGE --nodes all` against the test's broker and island name;
/// the output is read while it runs (its progress lines must never block it).
fn provision_update(
    broker: std::net::SocketAddr,
    island: &str,
    image: &std::path::Path,
) -> tokio::task::JoinHandle<std::process::Output> {
    provision_update_with(broker, island, image, &["--nodes", "all"])
}

/// `ihex-provision fw update IMAGE ARGS…`, as [`provision_update`].
fn provision_update_with(
    broker: std::net::SocketAddr,
    island: &str,
    image: &std::path::Path,
    extra: &[&str],
) -> tokio::task::JoinHandle<std::process::Output> {
    let bin =
        ihex_tests::bin::workspace_binary("ihex-provision", ihex_tests::bin::PROVISION_BIN_ENV)
            .unwrap_or_else(|e| panic!("{e}"));
    let timeout = ihex_tests::time::scaled(UPDATE_WAIT).as_secs().to_string();
    let child = tokio::process::Command::new(bin)
        .args(["fw", "update"])
        .arg(image)
        .args(extra)
        .args(["--timeout-secs", &timeout])
        .args(["--broker", &broker.to_string(), "--island", island])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .expect("run ihex-provision");
    tokio::spawn(async move {
        child
            .wait_with_output()
            .await
            .expect("ihex-provision output")
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_island_is_updated_with_one_command() {
    let _alone = ONE_AT_A_TIME.lock().await;
    let broker = Mosquitto::start().expect("start mosquitto");
    let addr = broker.addr();
    let iface = ihex_tests::can::lease();
    let work = std::env::temp_dir().join(format!("ihex-fw-{}", std::process::id()));
    // The gateway's firmware directory, and the lab PC's folder the CLI uploads from.
    let (fw_dir, lab) = (work.join("gateway"), work.join("lab"));
    std::fs::create_dir_all(&fw_dir).unwrap();
    std::fs::create_dir_all(&lab).unwrap();
    let new_version = FirmwareVersion::new(9, 0, 1);
    let test_key = ihex_image::SigningKey::test_key();
    let good = sim_image(
        new_version,
        SimFirmware { confirms: true },
        PAYLOAD,
        &test_key,
    )
    .unwrap();
    std::fs::write(lab.join("good.ihex"), &good).unwrap();
    let stranger = ihex_image::SigningKey::generate().unwrap();
    let foreign = sim_image(
        new_version,
        SimFirmware { confirms: true },
        PAYLOAD,
        &stranger,
    )
    .unwrap();
    std::fs::write(fw_dir.join("foreign.ihex"), &foreign).unwrap();
    std::fs::write(lab.join("foreign.ihex"), &foreign).unwrap();
    let key_file = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../crates/ihex-image/test-key/ihex-test-key.pub");

    let name = "fw";
    let dir = fw_dir.clone();
    // The default 50 % share paces a real bus; the simulated nodes run on an emulated CPU in the
    // VM, as many times slower as the tests' deadlines are stretched: pace the update alike.
    let slowdown = ihex_tests::time::scaled(Duration::from_secs(1)).as_secs_f64();
    let bus_share = (50.0 / slowdown).clamp(5.0, 50.0) as u8;
    let gateway = Gateway::start_with(addr, &iface, name, move |o| {
        o.fw_dir = Some(dir);
        o.fw_key = Some(key_file);
        o.fw_bus_share = Some(bus_share);
        // `nodes: all` is every node online: 20 emulated nodes miss the rig's 200 ms health
        // checks under load, and a node counted lost would be left out of the update.
        o.health_period_ms =
            Some(ihex_tests::time::scaled(Duration::from_secs(1)).as_millis() as u64);
    });
    let mut client = Client::connect(addr, "test-fw", &[format!("{name}/#")]);
    let avail = gateway.config.topics.availability.clone();
    client
        .expect("gateway online", |m| {
            m.topic == avail && m.payload == b"online"
        })
        .await;
    let desc = IslandDesc::parse(&island(NODES)).expect("island");
    let island = Island::start(&desc, Link::socketcan(iface.clone())).expect("start island");
    let events = gateway.events();
    let ids: Vec<String> = (0..NODES).map(|i| format!("{:x}", 0x101 + i)).collect();
    for n in &ids {
        client
            .expect_event(&events, "node_online", |p| p["id"] == n.as_str())
            .await;
    }
    let old_version = island.view(id("101")).await.unwrap().firmware.version;
    assert_ne!(old_version, new_version);
    let commands = gateway.commands();

    // 1. From the firmware directory, signed with a key the nodes do not trust: every node
    //    refuses, and keeps its image.
    client
        .publish(
            &commands,
            r#"{"cmd":"fw_update","image":"foreign.ihex","nodes":"all","request_id":"f1"}"#,
        )
        .await;
    let r = client
        .expect_event(&events, "command_result", |p| p["request_id"] == "f1")
        .await;
    assert_eq!(r["payload"]["result"], "ok", "{r}");
    let rep = report(&mut client, &events, "f1").await;
    let nodes = rep["nodes"].as_array().unwrap();
    assert_eq!(nodes.len(), usize::from(NODES), "{rep}");
    for n in nodes {
        assert_eq!(n["outcome"], "refused", "{rep}");
        assert_eq!(n["reason"], "unknown_key", "{rep}");
    }
    for n in &ids {
        assert_eq!(
            island.view(id(n)).await.unwrap().firmware.version,
            old_version
        );
    }

    // 2. The CLI uploads the foreign image: the gateway rejects it, the CLI says why.
    let wait = ihex_tests::time::scaled(gateway_support::WAIT);
    let cli = provision_update(addr, name, &lab.join("foreign.ihex"));
    let out = ihex_tests::within_or_panic(wait, "ihex-provision with a foreign image", cli)
        .await
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("the gateway rejected the image") && stderr.contains("gateway's key"),
        "{stderr}"
    );
    let r = client
        .expect_event(&events, "fw_upload", |p| p["name"] == "foreign.ihex")
        .await;
    assert_eq!(r["payload"]["result"], "rejected", "{r}");

    // 3. The test-signed image, from the lab's folder, to all: one CLI run.
    let started = std::time::Instant::now();
    let cli = provision_update(addr, name, &lab.join("good.ihex"));
    let r = client
        .expect_event(&events, "fw_upload", |p| p["name"] == "good.ihex")
        .await;
    assert_eq!(r["payload"]["result"], "stored", "{r}");
    assert_eq!(r["payload"]["signature"], "verified", "{r}");
    // Once the broadcast runs, a command to a node under update and a docking must complete.
    let target = ids[0].clone();
    client
        .expect_event(&events, "fw_progress", |p| {
            p["node"] == target.as_str() && p["phase"] == "receiving"
        })
        .await;
    let led = format!(r#"{{"cmd":"led","node":"{target}","color":"red","request_id":"during"}}"#);
    client.publish(&commands, led).await;
    ihex_tests::within_or_panic(wait, "dock", island.dock(id("2"), id(&target), 3))
        .await
        .expect("dock");
    let (mut acked, mut docked) = (None, false);
    while acked.is_none() || !docked {
        let m = client
            .expect(
                "the command's result and the docking during the update",
                |m| {
                    let v = m.json();
                    m.topic == events
                        && ((v["event"] == "command_result"
                            && v["payload"]["request_id"] == "during")
                            || (v["event"] == "new_connection" && v["payload"]["n"]["id"] == "2"))
                },
            )
            .await
            .json();
        if m["event"] == "command_result" {
            acked = Some(m["payload"]["result"].clone());
        } else {
            docked = true;
        }
    }
    assert_eq!(acked.unwrap(), "ok");
    let out = ihex_tests::within_or_panic(
        ihex_tests::time::scaled(UPDATE_WAIT),
        "ihex-provision fw update",
        cli,
    )
    .await
    .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!(
        "{NODES} nodes, {PAYLOAD} B payload, {bus_share} % bus share: uploaded and updated in \
         {:?}\n{stdout}",
        started.elapsed()
    );
    assert!(
        out.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains(&format!("{NODES} of {NODES} nodes updated")),
        "{stdout}"
    );
    for n in &ids {
        let fw = island.view(id(n)).await.unwrap().firmware;
        // (`updated` is the node's own answer that its image is confirmed; the island's view
        // keeps the identity of the boot, trial flag included.)
        assert_eq!(fw.version, new_version, "node {n}");
    }

    gateway.shutdown().await;
    island.shutdown().await;
    drop(broker);
    let _ = std::fs::remove_dir_all(&work);
}

/// The two tests run one after the other: each paces its island to the emulated CPU alone, and
/// side by side they starve each other's nodes (counted lost, left out of `nodes: all`).
static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// `ihex-provision fw demo-image` into `dir`; returns the image's path.
fn demo_image(dir: &std::path::Path, version: &str, reverts: bool) -> std::path::PathBuf {
    let bin =
        ihex_tests::bin::workspace_binary("ihex-provision", ihex_tests::bin::PROVISION_BIN_ENV)
            .unwrap_or_else(|e| panic!("{e}"));
    let out = dir.join(format!("demo-{version}.img"));
    let mut cmd = std::process::Command::new(bin);
    cmd.args([
        "fw",
        "demo-image",
        "--version",
        version,
        "--size",
        "4096",
        "--out",
    ])
    .arg(&out);
    if reverts {
        cmd.arg("--reverts");
    }
    let done = cmd.output().expect("run ihex-provision fw demo-image");
    assert!(done.status.success(), "{done:?}");
    out
}

/// Runs the CLI to its end; returns (success, stdout).
async fn finish(cli: tokio::task::JoinHandle<std::process::Output>, what: &str) -> (bool, String) {
    let out = ihex_tests::within_or_panic(ihex_tests::time::scaled(UPDATE_WAIT), what, cli)
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
    eprintln!("{what}:\n{stdout}{}", String::from_utf8_lossy(&out.stderr));
    (out.status.success(), stdout)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rollout_never_strands_a_docked_element() {
    let _alone = ONE_AT_A_TIME.lock().await;
    let broker = Mosquitto::start().expect("start mosquitto");
    let addr = broker.addr();
    let iface = ihex_tests::can::lease();
    let lab = std::env::temp_dir().join(format!("ihex-rollout-{}", std::process::id()));
    std::fs::create_dir_all(&lab).unwrap();
    let name = "roll";
    let slowdown = ihex_tests::time::scaled(Duration::from_secs(1)).as_secs_f64();
    let bus_share = (50.0 / slowdown).clamp(5.0, 50.0) as u8;
    let gateway = Gateway::start_with(addr, &iface, name, move |o| {
        o.fw_bus_share = Some(bus_share);
        o.health_period_ms =
            Some(ihex_tests::time::scaled(Duration::from_secs(1)).as_millis() as u64);
    });
    let mut client = Client::connect(addr, "test-rollout", &[format!("{name}/#")]);
    let avail = gateway.config.topics.availability.clone();
    client
        .expect("gateway online", |m| {
            m.topic == avail && m.payload == b"online"
        })
        .await;
    // Two static elements, each powering a docked mobile element, and one free static element.
    let desc = IslandDesc::parse(
        r#"
[[static]]
id = "101"
[[static]]
id = "102"
[[static]]
id = "103"
[[mobile]]
id = "2"
dock = { static = "101", port = 3 }
[[mobile]]
id = "3"
dock = { static = "102", port = 1 }
"#,
    )
    .expect("island");
    let island = Island::start(&desc, Link::socketcan(iface.clone())).expect("start island");
    let events = gateway.events();
    let all = ["101", "102", "103", "2", "3"];
    // Both dockings announced and every element's firmware read back, in whatever order.
    let mut missing: std::collections::BTreeSet<String> = all
        .iter()
        .map(|n| format!("state {n}"))
        .chain(["docked 2".into(), "docked 3".into()])
        .collect();
    while !missing.is_empty() {
        let m = client
            .expect("the dockings and every element's firmware", |_| true)
            .await;
        let v = m.json();
        if m.topic == events && v["event"] == "new_connection" {
            missing.remove(&format!(
                "docked {}",
                v["payload"]["n"]["id"].as_str().unwrap_or("")
            ));
        } else if m.topic.ends_with("/state") && v["online"] == true && v["firmware"].is_object() {
            missing.remove(&format!("state {}", v["id"].as_str().unwrap_or("")));
        }
    }
    let good = demo_image(&lab, "9.0.1", false);
    let v901 = FirmwareVersion::new(9, 0, 1);
    let docked_and_powered = |island: &sim_node::IslandHandle| {
        let island = island.clone();
        async move {
            for (m, s) in [("2", "101"), ("3", "102")] {
                let v = island.view(id(m)).await.unwrap();
                assert!(v.powered, "{m} has power");
                assert_eq!(v.docked.map(|(st, _)| st), Some(id(s)), "{m} still docked");
            }
        }
    };

    // "Update all": mobiles first, the statics powering them last; every element updated.
    let cli = provision_update_with(addr, name, &good, &["--nodes", "all"]);
    let (ok, stdout) = finish(cli, "update all").await;
    assert!(ok, "{stdout}");
    assert!(stdout.contains("5 of 5 nodes updated"), "{stdout}");
    // Piped: plain progress lines.
    assert!(stdout.contains(" receiving "), "{stdout}");
    let wave_of = |n: &str| {
        stdout
            .lines()
            .position(|l| l.starts_with("-- ") && l.contains(n))
            .unwrap_or_else(|| panic!("{n} in no wave: {stdout}"))
    };
    assert!(wave_of("2,3") < wave_of(": 101,102"), "{stdout}");
    for n in all {
        assert_eq!(
            island.view(id(n)).await.unwrap().firmware.version,
            v901,
            "{n}"
        );
    }
    docked_and_powered(&island).await;

    // The same command again: everything is on 9.0.1 already (resume retries only the rest).
    // The trial flag of the state documents clears once the element has confirmed.
    let mut unconfirmed: std::collections::BTreeSet<&str> = all.into_iter().collect();
    while !unconfirmed.is_empty() {
        let m = client
            .expect("every element confirmed in its state", |_| true)
            .await;
        let v = m.json();
        if m.topic.ends_with("/state")
            && v["firmware"]["version"] == "9.0.1"
            && v["firmware"]["trial"] == false
        {
            unconfirmed.remove(v["id"].as_str().unwrap_or(""));
        }
    }
    let cli = provision_update_with(addr, name, &good, &["--nodes", "all"]);
    let (ok, stdout) = finish(cli, "update all again").await;
    assert!(ok, "{stdout}");
    assert!(stdout.contains("nothing to update"), "{stdout}");
    assert_eq!(
        stdout.matches("already runs 9.0.1: skipped").count(),
        5,
        "{stdout}"
    );

    // A reverting image with a canary: the canary reverts, nothing else is touched.
    let bad = demo_image(&lab, "9.0.2", true);
    let cli = provision_update_with(addr, name, &bad, &["--nodes", "all", "--canary", "1"]);
    let (ok, stdout) = finish(cli, "canary").await;
    assert!(!ok, "{stdout}");
    assert!(stdout.contains("2 reverted"), "{stdout}");
    assert!(stdout.contains("stopping: the canary wave"), "{stdout}");
    for n in ["101", "102", "103", "3"] {
        assert_eq!(
            island.view(id(n)).await.unwrap().firmware.version,
            v901,
            "{n}"
        );
    }

    // The reverting image on a static element with a docked mobile: two restarts of 101, and 2
    // keeps its power and its docking throughout.
    let cli = provision_update_with(addr, name, &bad, &["--nodes", "101"]);
    let (ok, stdout) = finish(cli, "reverting static").await;
    assert!(!ok, "{stdout}");
    assert!(stdout.contains(" 101 reverted"), "{stdout}");
    docked_and_powered(&island).await;

    gateway.shutdown().await;
    island.shutdown().await;
    drop(broker);
    let _ = std::fs::remove_dir_all(&lab);
}
