//! The `mc-gateway` binary itself: `--help`, a bad option, and a demo run stopped with SIGTERM that
//! exits 0, announces `offline` and leaves a JSON-lines log file.
#![cfg(feature = "demo")]

use std::{
    io::{BufRead, BufReader},
    net::TcpListener,
    process::{Command, Stdio},
    time::{Duration, Instant},
};

const BIN: &str = env!("CARGO_BIN_EXE_mc-gateway");

#[test]
fn help_explains_the_options_and_lab_defaults() {
    let out = Command::new(BIN).arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for needle in [
        "--broker",
        "192.168.1.101:1883",
        "--can",
        "can0",
        "--island",
        "IHEX_BROKER",
    ] {
        assert!(text.contains(needle), "--help lacks {needle}");
    }
}

#[test]
fn a_bad_option_value_fails_with_its_name() {
    let out = Command::new(BIN)
        .args(["--lost-after", "0", "--log-dir", "-"])
        .env_remove("IHEX_CONFIG")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("lost-after"), "{err}");
}

#[test]
fn sigterm_stops_the_demo_cleanly_and_flushes_the_log() {
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let dir = tempfile::tempdir().unwrap();
    let mut child = Command::new(BIN)
        .args(["--broker-listen", &format!("127.0.0.1:{port}")])
        .arg("--log-dir")
        .arg(dir.path())
        .env_remove("IHEX_CONFIG")
        .env_remove("IHEX_BROKER")
        .env_remove("IHEX_CAN")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    // The banner is printed once broker, island and tasks run.
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut banner = String::new();
    for line in lines.by_ref() {
        let line = line.unwrap();
        banner.push_str(&line);
        banner.push('\n');
        if line.contains("Ctrl-C stops the gateway") || Instant::now() > deadline {
            break;
        }
    }
    assert!(
        banner.contains(&format!("mosquitto_pub -h 127.0.0.1 -p {port}")),
        "{banner}"
    );
    // Let the MQTT task connect before asking it to say goodbye.
    std::thread::sleep(Duration::from_millis(500));
    // SAFETY: plain kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    let status = child.wait().unwrap();
    assert!(status.success(), "exit status {status}");

    let files: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(files.len(), 1, "{files:?}");
    let text = std::fs::read_to_string(&files[0]).unwrap();
    let records: Vec<serde_json::Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).expect("every line is JSON"))
        .collect();
    let said = |m: &str| records.iter().any(|r| r["fields"]["message"] == m);
    assert!(said("gateway running"), "{text}");
    assert!(said("published offline and disconnected"), "{text}");
    assert!(said("gateway stopped"), "the last line was flushed: {text}");
}
