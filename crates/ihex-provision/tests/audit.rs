//! `ihex-provision audit verify` and `audit show` on a trail written by the audit writer: a whole
//! chain verifies (exit 0), a tampered one names its first broken line (exit 1), and `show`
//! filters by element, time and user.

use std::process::{Command, Output};
use std::time::{Duration, UNIX_EPOCH};

use ihex_audit::dir::chain_files;
use ihex_audit::{Kind, Record, Writer, WriterOptions};
use serde_json::json;

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ihex-provision"))
        .args(args)
        .output()
        .unwrap()
}

fn text(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned() + &String::from_utf8_lossy(&o.stderr)
}

fn command(user: &str, node: &str, request_id: &str) -> Record {
    let mut r = Record::new(
        Kind::Command,
        json!({"command": {"cmd": "power", "node": node, "on": true, "request_id": request_id}}),
    );
    r.interface = Some("mqtt".into());
    r.user = Some(user.into());
    r.request_id = Some(request_id.into());
    r.elements = vec![node.into()];
    r
}

/// A trail of five records on 2025-11-25 and 2025-11-26 (two files).
fn trail() -> (tempfile::TempDir, ihex_audit::Head) {
    let dir = tempfile::tempdir().unwrap();
    let (mut w, _) = Writer::open(dir.path(), WriterOptions::default()).unwrap();
    let day1 = UNIX_EPOCH + Duration::from_secs(1_764_079_510); // 2025-11-25T14:05:10Z
    let day2 = day1 + Duration::from_secs(86_400);
    w.append(day1, &Record::new(Kind::Start, json!({"version": "0.1.0"})))
        .unwrap();
    w.append(day1, &command("alice", "111", "a1")).unwrap();
    w.append(day2, &command("bob", "2", "b1")).unwrap();
    let mut claimed = command("carol", "111", "c1");
    claimed.user = None;
    claimed.claimed = Some("carol".into());
    w.append(day2, &claimed).unwrap();
    let head = w
        .append(day2, &Record::new(Kind::Stop, serde_json::Value::Null))
        .unwrap();
    (dir, head)
}

#[test]
fn a_whole_trail_verifies_and_a_tampered_one_names_its_line() {
    let (dir, head) = trail();
    let d = dir.path().to_str().unwrap();
    let out = run(&["audit", "verify", d]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(
        text(&out).starts_with("ok: 5 records in 2 files"),
        "{}",
        text(&out)
    );
    let out = run(&["audit", "verify", d, "--head", &head.to_text()]);
    assert!(out.status.success(), "{}", text(&out));
    assert!(
        text(&out).contains("which the anchor confirms"),
        "{}",
        text(&out)
    );

    // Someone changes who asked: the line is named, the exit status is 1.
    let first = chain_files(dir.path()).unwrap()[0].clone();
    let name = first.file_name().unwrap().to_str().unwrap().to_owned();
    let edited = std::fs::read_to_string(&first)
        .unwrap()
        .replace("\"alice\"", "\"mallory\"");
    std::fs::write(&first, edited).unwrap();
    let out = run(&["audit", "verify", d]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out));
    assert!(
        text(&out).contains(&format!("BROKEN at {name}:2: edited")),
        "{}",
        text(&out)
    );

    let out = run(&["audit", "verify", d, "--head", "4:zz"]);
    assert!(!out.status.success());
    assert!(text(&out).contains("expected SEQ:SHA256"), "{}", text(&out));
}

#[test]
fn show_filters_by_element_time_and_user() {
    let (dir, _) = trail();
    let d = dir.path().to_str().unwrap();
    let out = run(&["audit", "show", d, "--element", "111"]);
    assert!(out.status.success(), "{}", text(&out));
    let t = text(&out);
    // The island-wide start and stop, and the two commands to 111; not bob's to 2.
    assert_eq!(t.lines().count(), 4, "{t}");
    assert!(
        t.contains("alice") && t.contains("unvouched (claims carol)"),
        "{t}"
    );
    assert!(!t.contains("bob"), "{t}");

    let out = run(&["audit", "show", d, "--since", "2025-11-26", "--user", "bob"]);
    let t = text(&out);
    assert_eq!(t.lines().count(), 1, "{t}");
    assert!(t.contains("bob") && t.contains("\"node\":\"2\""), "{t}");

    let out = run(&[
        "audit",
        "show",
        d,
        "--since",
        "2025-11-25T15:00:00Z",
        "--json",
    ]);
    let t = text(&out);
    assert_eq!(t.lines().count(), 3, "{t}");
    for line in t.lines() {
        let v: serde_json::Value = serde_json::from_str(line).unwrap();
        assert!(v.get("prev").is_none() && v.get("seq").is_some(), "{line}");
    }

    let out = run(&["audit", "show", d, "--since", "yesterday"]);
    assert!(!out.status.success());
    assert!(text(&out).contains("an age like 30m"), "{}", text(&out));
}
