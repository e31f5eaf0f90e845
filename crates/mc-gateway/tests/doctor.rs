//! `mc-gateway doctor` on the host: every check's judgement from facts (boot configuration files in
//! `tests/data/boot/`, interface, traffic, island, clock, disk), and the command end to end against
//! a real Mosquitto with the shipped ACL (right login, wrong password, an island the ACL denies),
//! its `--json` document and its exit status. The checks that need a CAN bus run in the microVM:
//! `tests/tests/doctor.rs`.

use std::{
    path::{Path, PathBuf},
    process::Command,
    time::Duration,
};

use ihex_proto::{
    FirmwareVersion, FwPhase, FwRefusal, FwStatus, HealthFlags, HealthReply, Message, NodeId,
    Packet, StateParts, StateReport,
};
use ihex_tests::broker::{self, Mosquitto, Setup};
use mc_gateway::doctor::{
    boot::{self, Hat, Location},
    clock, disk, interface, island, traffic, Report, Status,
};
use socketcan::nl::CanState;

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/boot")
        .join(name)
}

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join(path)
}

fn statuses(v: &[mc_gateway::doctor::Verdict]) -> Vec<(&'static str, Status)> {
    v.iter().map(|v| (v.check, v.status)).collect()
}

// ---------------------------------------------------------------- boot configuration

#[test]
fn boot_config_right_and_as_shipped_pass() {
    for path in [
        data("right.txt"),
        repo("deploy/boot/config.txt"),
        data("separate-dtparams.txt"),
    ] {
        let v = boot::check_file(Location::Given(path.clone()), &Hat::default());
        assert_eq!(
            statuses(&v),
            [(boot::SPI, Status::Pass), (boot::OVERLAY, Status::Pass)],
            "{}: {v:#?}",
            path.display()
        );
    }
}

#[test]
fn boot_config_missing_overlay_fails_and_says_which_line_to_add() {
    let v = boot::check_file(
        Location::Given(data("missing-overlay.txt")),
        &Hat::default(),
    );
    assert_eq!(v[0].status, Status::Pass, "{v:#?}");
    assert_eq!(v[1].status, Status::Fail, "{v:#?}");
    assert!(v[1].found.contains("no dtoverlay=mcp2515-can0"), "{v:#?}");
    let action = v[1].action.as_deref().unwrap();
    assert!(
        action.contains("dtoverlay=mcp2515-can0,oscillator=8000000,interrupt=25"),
        "{action}"
    );
}

#[test]
fn boot_config_wrong_oscillator_fails_naming_both_values() {
    let v = boot::check_file(
        Location::Given(data("wrong-oscillator.txt")),
        &Hat::default(),
    );
    assert_eq!(v[0].status, Status::Pass);
    assert_eq!(v[1].status, Status::Fail, "{v:#?}");
    assert!(v[1].found.contains("oscillator=16000000"), "{}", v[1].found);
    assert!(v[1].found.contains("8000000"), "{}", v[1].found);
    // The same file is right for a 16 MHz HAT.
    let hat16 = Hat {
        oscillator: 16_000_000,
        interrupt: 25,
    };
    let v = boot::check_file(Location::Given(data("wrong-oscillator.txt")), &hat16);
    assert_eq!(v[1].status, Status::Pass, "{v:#?}");
    // And the right file is wrong for another interrupt GPIO.
    let other_int = Hat {
        oscillator: 8_000_000,
        interrupt: 12,
    };
    let v = boot::check_file(Location::Given(data("right.txt")), &other_int);
    assert_eq!(v[1].status, Status::Fail, "{v:#?}");
    assert!(v[1].found.contains("interrupt=25"), "{}", v[1].found);
}

#[test]
fn boot_config_none_section_and_spi_off_do_not_count() {
    let v = boot::check_file(
        Location::Given(data("overlay-in-none.txt")),
        &Hat::default(),
    );
    assert_eq!(
        statuses(&v),
        [(boot::SPI, Status::Fail), (boot::OVERLAY, Status::Fail)],
        "{v:#?}"
    );
    assert!(v[0].found.contains("switches SPI off"), "{}", v[0].found);
}

#[test]
fn boot_config_unreadable_fails_absent_skips() {
    let v = boot::check_file(Location::Given(data("no-such-file.txt")), &Hat::default());
    assert_eq!(v[0].status, Status::Fail);
    assert!(v[0].found.contains("cannot read"), "{}", v[0].found);
    let v = boot::check_file(Location::Absent, &Hat::default());
    assert_eq!(
        statuses(&v),
        [(boot::SPI, Status::Skip), (boot::OVERLAY, Status::Skip)]
    );
    assert!(v[0].found.contains("not a Raspberry Pi"));
}

// ---------------------------------------------------------------- CAN interface

fn can0() -> interface::Facts {
    interface::Facts {
        name: "can0".into(),
        missing: None,
        up: true,
        virtual_can: false,
        bit_timing: Some((500_000, 875)),
        clock: Some(4_000_000),
        state: Some(CanState::ErrorActive),
        berr: Some((0, 0)),
        restart_ms: Some(100),
        txqueuelen: Some(1024),
    }
}

fn judge(f: &interface::Facts) -> Vec<(&'static str, Status)> {
    statuses(&interface::check(f, 500_000, &Hat::default()))
}

#[test]
fn interface_as_deployed_passes() {
    assert!(
        judge(&can0()).iter().all(|(_, s)| *s == Status::Pass),
        "{:?}",
        judge(&can0())
    );
}

#[test]
fn interface_missing_or_down_fails_and_skips_the_rest() {
    let missing = interface::Facts {
        missing: Some("No such device".into()),
        ..can0()
    };
    assert_eq!(
        judge(&missing),
        [
            (interface::CHECK, Status::Fail),
            (interface::BITRATE, Status::Skip),
            (interface::CONTROLLER, Status::Skip),
            (interface::TXQUEUE, Status::Skip)
        ]
    );
    let down = interface::Facts {
        up: false,
        ..can0()
    };
    let v = interface::check(&down, 500_000, &Hat::default());
    assert_eq!(v[0].status, Status::Fail);
    assert!(v[0].found.contains("down"));
    assert!(v[0].action.as_deref().unwrap().contains("bitrate 500000"));
}

#[test]
fn interface_vcan_has_no_bitrate_and_that_is_not_a_failure() {
    let vcan = interface::Facts {
        name: "vcan0".into(),
        virtual_can: true,
        bit_timing: None,
        clock: None,
        state: None,
        berr: None,
        restart_ms: None,
        txqueuelen: Some(0),
        ..can0()
    };
    let v = interface::check(&vcan, 500_000, &Hat::default());
    assert_eq!(v[1].status, Status::Skip);
    assert_eq!(v[1].found, "virtual CAN: no bitrate");
    assert!(v.iter().all(|v| v.status != Status::Fail), "{v:#?}");
}

#[test]
fn interface_wrong_bitrate_sample_point_or_crystal_fails() {
    let slow = interface::Facts {
        bit_timing: Some((250_000, 875)),
        ..can0()
    };
    let v = interface::check(&slow, 500_000, &Hat::default());
    assert_eq!(v[1].status, Status::Fail);
    assert!(v[1].found.contains("250000"), "{}", v[1].found);
    let sp = interface::Facts {
        bit_timing: Some((500_000, 750)),
        ..can0()
    };
    assert_eq!(judge(&sp)[1], (interface::BITRATE, Status::Fail));
    // 8 MHz clock = a 16 MHz crystal declared in the overlay of an 8 MHz HAT.
    let crystal = interface::Facts {
        clock: Some(8_000_000),
        ..can0()
    };
    let v = interface::check(&crystal, 500_000, &Hat::default());
    assert_eq!(v[1].status, Status::Fail);
    assert!(v[1].found.contains("16000000 Hz crystal"), "{}", v[1].found);
    let unset = interface::Facts {
        bit_timing: None,
        ..can0()
    };
    assert_eq!(judge(&unset)[1], (interface::BITRATE, Status::Fail));
}

#[test]
fn interface_controller_states_and_restart() {
    for (state, word) in [
        (CanState::BusOff, "bus-off"),
        (CanState::ErrorPassive, "error-passive"),
        (CanState::ErrorWarning, "error-warning"),
        (CanState::Stopped, "stopped"),
    ] {
        let f = interface::Facts {
            state: Some(state),
            berr: Some((255, 3)),
            ..can0()
        };
        let v = interface::check(&f, 500_000, &Hat::default());
        assert_eq!(v[2].status, Status::Fail, "{state:?}");
        assert!(v[2].found.contains(word), "{}", v[2].found);
        assert!(v[2].found.contains("tx 255 rx 3"), "{}", v[2].found);
    }
    let bus_off = interface::Facts {
        state: Some(CanState::BusOff),
        ..can0()
    };
    let v = interface::check(&bus_off, 500_000, &Hat::default());
    let action = v[2].action.as_deref().unwrap();
    assert!(
        action.contains("120 Ω") && action.contains("500 kbit/s"),
        "{action}"
    );
    let no_restart = interface::Facts {
        restart_ms: Some(0),
        ..can0()
    };
    let v = interface::check(&no_restart, 500_000, &Hat::default());
    assert_eq!(v[2].status, Status::Fail);
    assert!(v[2].action.as_deref().unwrap().contains("restart-ms"));
    let short = interface::Facts {
        txqueuelen: Some(10),
        ..can0()
    };
    assert_eq!(judge(&short)[3], (interface::TXQUEUE, Status::Fail));
}

// ---------------------------------------------------------------- traffic

const LISTEN: Duration = Duration::from_secs(3);

#[test]
fn traffic_error_frames_say_what_they_mean() {
    let mut f = traffic::Facts {
        frames: 0,
        ..Default::default()
    };
    // CAN_ERR_ACK (0x20): nobody acknowledged.
    f.observe_error(0x20, [0; 8]);
    let v = traffic::check(&f, LISTEN);
    assert_eq!(v.status, Status::Fail);
    assert!(v.found.contains("no_ack ×1"), "{}", v.found);
    let action = v.action.unwrap();
    assert!(
        action.contains("no other node") && action.contains("termination"),
        "{action}"
    );

    // Bus-off outranks the rest.
    f.observe_error(0x40, [0; 8]);
    let v = traffic::check(&f, LISTEN);
    assert!(v.action.unwrap().starts_with("bus-off"));

    let mut p = traffic::Facts {
        frames: 5,
        ..Default::default()
    };
    p.observe_error(0x08, [0, 0, 0x04, 0, 0, 0, 0, 0]);
    let v = traffic::check(&p, LISTEN);
    assert_eq!(v.status, Status::Fail);
    assert!(v.action.unwrap().contains("bitrate"));
}

#[test]
fn traffic_silence_fails_frames_pass() {
    let v = traffic::check(&traffic::Facts::default(), LISTEN);
    assert_eq!(v.status, Status::Fail);
    assert!(v.found.contains("no frame"));
    let busy = traffic::Facts {
        frames: 12,
        ..Default::default()
    };
    let v = traffic::check(&busy, LISTEN);
    assert_eq!(v.status, Status::Pass, "{v:?}");
    assert!(v.found.starts_with("12 frames"));
    let stuck = traffic::Facts {
        frames: 0,
        send_failures: Some((3, "No buffer space available".into())),
        ..Default::default()
    };
    assert_eq!(traffic::check(&stuck, LISTEN).status, Status::Fail);
}

// ---------------------------------------------------------------- island

fn id(raw: u16) -> NodeId {
    NodeId::new(raw).unwrap()
}

fn health(src: u16) -> Packet {
    Packet::report(
        id(src),
        Message::HealthReply(HealthReply {
            seq: 0xD0,
            flags: HealthFlags(0),
            loops: 0,
            tec: 0,
            rec: 0,
            uptime_s: 10,
        }),
    )
}

/// The answers of a node of protocol `minor` (1.0 answers health checks only, 1.1 state queries
/// too, 1.2 firmware queries too).
fn answers(src: u16, minor: u8) -> Vec<Packet> {
    let mut out = vec![health(src)];
    if minor >= 1 {
        let r = |s| Packet::report(id(src), Message::StateReport(s));
        out.push(r(StateReport::Firmware {
            version: FirmwareVersion::new(0, 3, 1),
            trial: false,
        }));
        out.push(r(StateReport::UidLow([0x30, 0, 0x47, 0, 0x12, 0x51, 0x33])));
        out.push(r(StateReport::UidHigh([0x39, 0x33, 0x38, 0x34, 0x37])));
        if minor >= 3 {
            out.push(r(StateReport::Protocol {
                version: (1, minor),
            }));
        }
        out.push(r(StateReport::End {
            seq: 0xD0,
            parts: StateParts(StateParts::IDENTITY),
            count: if minor >= 3 { 4 } else { 3 },
        }));
    }
    if minor >= 2 {
        out.push(Packet::report(
            id(src),
            Message::FwStatus(FwStatus {
                phase: FwPhase::Idle,
                reason: FwRefusal::None,
                first_missing: 0,
                run: 0,
                missing: 0,
            }),
        ));
    }
    out
}

fn island_of(packets: &[Packet]) -> island::Facts {
    let mut f = island::Facts::default();
    for p in packets {
        f.observe(p);
    }
    f
}

#[test]
fn island_current_nodes_pass_with_versions_and_uids() {
    let f = island_of(&[answers(0x111, 3), answers(0x2, 3)].concat());
    let v = island::check(&f, LISTEN);
    assert_eq!(v.status, Status::Pass, "{v:?}");
    assert!(v.found.starts_with("2 node(s) answered"), "{}", v.found);
    assert!(
        v.found
            .contains("111 (firmware 0.3.1, protocol 1.3, uid 300047001251333933383437)"),
        "{}",
        v.found
    );
}

#[test]
fn island_old_protocol_fails_and_names_the_node() {
    let f = island_of(
        &[
            answers(0x111, 3),
            answers(0x114, 2),
            answers(0x112, 1),
            answers(0x113, 0),
        ]
        .concat(),
    );
    let v = island::check(&f, LISTEN);
    assert_eq!(v.status, Status::Fail, "{v:?}");
    let action = v.action.unwrap();
    assert!(action.contains("114 (1.2"), "{action}");
    assert!(action.contains("112 (1.1"), "{action}");
    assert!(action.contains("113 (1.0"), "{action}");
    assert!(!action.contains("111"), "{action}");
    // A BootUp gives the exact version.
    let mut f = island_of(&answers(0x111, 3));
    f.observe(&Packet::report(
        id(0x111),
        Message::BootUp {
            version: (1, 1),
            role: ihex_proto::BootRole::Static,
            ports: 6,
            reset: ihex_proto::ResetReason::PowerOn,
        },
    ));
    assert_eq!(island::check(&f, LISTEN).status, Status::Fail);
}

#[test]
fn island_silence_fails_and_unconfigured_boards_are_listed() {
    let v = island::check(&island::Facts::default(), LISTEN);
    assert_eq!(v.status, Status::Fail);
    assert!(v.found.starts_with("no node answered"));
    let mut f = island_of(&answers(0x111, 3));
    f.observe(&Packet::report(
        NodeId::UNCONFIGURED,
        Message::AssignReply {
            seq: 1,
            result: ihex_proto::AckResult::InvalidState,
            new_id: NodeId::UNCONFIGURED,
            uid_tail: [0x33, 0x38, 0x34, 0x37],
        },
    ));
    let v = island::check(&f, LISTEN);
    assert!(
        v.found.contains("without a node ID: UID …33383437"),
        "{}",
        v.found
    );
}

// ---------------------------------------------------------------- clock and disk

#[test]
fn clock_before_the_build_year_fails() {
    let v = clock::check(0, 2026);
    assert_eq!(v.status, Status::Fail);
    assert!(v.found.contains("1970"), "{}", v.found);
    // 2026-01-01T00:00:00Z and one second before it.
    assert_eq!(clock::check(1_767_225_600, 2026).status, Status::Pass);
    assert_eq!(clock::check(1_767_225_599, 2026).status, Status::Fail);
    assert_eq!(
        clock::check(clock::now_unix(), clock::BUILD_YEAR).status,
        Status::Pass
    );
}

#[test]
fn disk_space_below_the_minimum_fails() {
    let facts = |free| disk::Facts {
        dir: "/var/log/ihex".into(),
        exists: true,
        space: Ok((free, 32 << 30)),
    };
    assert_eq!(
        disk::check(disk::LOG, "log", &facts(disk::MIN_FREE)).status,
        Status::Pass
    );
    let v = disk::check(disk::LOG, "log", &facts(disk::MIN_FREE - 1));
    assert_eq!(v.status, Status::Fail);
    assert!(v.action.unwrap().contains("/var/log/ihex"));
    // A real directory: this one has room (the build just wrote to it).
    let here = disk::gather(Path::new(env!("CARGO_MANIFEST_DIR")));
    assert!(
        matches!(here.space, Ok((free, total)) if free > 0 && total >= free),
        "{here:?}"
    );
}

// ---------------------------------------------------------------- the command, with Mosquitto

const USER: &str = "gw-bench-a";
const PASSWORD: &str = "bench-a-secret";

/// A broker with passwords and the shipped per-island ACL (`deploy/mosquitto/acl`).
fn acl_broker() -> Mosquitto {
    let acl = std::fs::read(repo("deploy/mosquitto/acl")).expect("deploy/mosquitto/acl");
    Mosquitto::start_with(&Setup {
        anonymous: false,
        global: "password_file {dir}/passwd\nacl_file {dir}/acl\n".into(),
        files: vec![
            (
                "passwd".into(),
                broker::password_file(&[(USER, PASSWORD)]).expect("mosquitto_passwd"),
            ),
            ("acl".into(), acl),
        ],
        ..Setup::default()
    })
    .expect("start mosquitto (apt install mosquitto)")
}

/// Runs `mc-gateway doctor --json` with the simulated island (no CAN here), a boot file of the test
/// data, and the broker; returns the exit code and the report.
fn doctor(broker: &Mosquitto, island: &str, password: &str) -> (i32, Report, serde_json::Value) {
    let out = Command::new(env!("CARGO_BIN_EXE_mc-gateway"))
        .args(["doctor", "--json", "--sim", "--broker"])
        .arg(broker.addr().to_string())
        .args(["--island", island, "--username", USER, "--boot-config"])
        .arg(data("right.txt"))
        .env("IHEX_MQTT_PASSWORD", password)
        .env("XDG_STATE_HOME", std::env::temp_dir())
        .env_remove("IHEX_CONFIG")
        .output()
        .expect("run mc-gateway");
    let text = String::from_utf8_lossy(&out.stdout);
    let json: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|e| {
        panic!(
            "--json printed no JSON ({e}): {text}\n{}",
            String::from_utf8_lossy(&out.stderr)
        )
    });
    let checks = json["checks"]
        .as_array()
        .expect("checks")
        .iter()
        .map(|c| mc_gateway::doctor::Verdict {
            check: leak(c["check"].as_str().unwrap()),
            status: match c["status"].as_str().unwrap() {
                "pass" => Status::Pass,
                "fail" => Status::Fail,
                "skip" => Status::Skip,
                other => panic!("status {other:?}"),
            },
            found: c["found"].as_str().unwrap().to_owned(),
            action: c["action"].as_str().map(str::to_owned),
        })
        .collect();
    (out.status.code().unwrap_or(-1), Report::new(checks), json)
}

fn leak(s: &str) -> &'static str {
    Box::leak(s.to_owned().into_boxed_str())
}

#[test]
fn broker_right_login_and_acl_pass_and_exit_zero() {
    let broker = acl_broker();
    let (code, report, json) = doctor(&broker, "bench-a", PASSWORD);
    let connect = report.get("broker.connect").unwrap();
    assert_eq!(connect.status, Status::Pass, "{report:#?}");
    assert!(
        connect.found.contains("user gw-bench-a"),
        "{}",
        connect.found
    );
    let topics = report.get("broker.topics").unwrap();
    assert_eq!(topics.status, Status::Pass, "{report:#?}");
    assert!(
        topics.found.contains("bench-a/ihex/doctor/"),
        "{}",
        topics.found
    );
    // The simulated island has no CAN: those checks are skipped, and nothing failed.
    assert_eq!(report.get("can.interface").unwrap().status, Status::Skip);
    assert!(report.ok, "{report:#?}");
    assert_eq!(json["ok"], true);
    assert_eq!(code, 0, "{report:#?}");
    // The documented field names, in every check.
    for c in json["checks"].as_array().unwrap() {
        let keys: Vec<&String> = c.as_object().unwrap().keys().collect();
        assert_eq!(keys, ["action", "check", "found", "status"], "{c}");
    }
}

#[test]
fn broker_wrong_password_fails_with_what_to_check() {
    let broker = acl_broker();
    let (code, report, _) = doctor(&broker, "bench-a", "not-the-password");
    let connect = report.get("broker.connect").unwrap();
    assert_eq!(connect.status, Status::Fail, "{report:#?}");
    assert!(
        connect.found.contains("refused the login"),
        "{}",
        connect.found
    );
    assert!(connect
        .action
        .as_deref()
        .unwrap()
        .contains("IHEX_MQTT_PASSWORD"));
    assert_eq!(report.get("broker.topics").unwrap().status, Status::Skip);
    assert_eq!(code, 1);
}

#[test]
fn broker_acl_denying_the_island_fails_the_round_trip() {
    let broker = acl_broker();
    // gw-bench-a may only use bench-a/#: as the gateway of bench-b its messages are dropped.
    let (code, report, _) = doctor(&broker, "bench-b", PASSWORD);
    assert_eq!(
        report.get("broker.connect").unwrap().status,
        Status::Pass,
        "{report:#?}"
    );
    let topics = report.get("broker.topics").unwrap();
    assert_eq!(topics.status, Status::Fail, "{report:#?}");
    assert!(topics.found.contains("never came back"), "{}", topics.found);
    let action = topics.action.as_deref().unwrap();
    assert!(action.contains("topic readwrite bench-b/#"), "{action}");
    assert_eq!(code, 1);
}

#[test]
fn broker_unreachable_fails() {
    let mut broker = acl_broker();
    broker.stop();
    let (code, report, _) = doctor(&broker, "bench-a", PASSWORD);
    let connect = report.get("broker.connect").unwrap();
    assert_eq!(connect.status, Status::Fail);
    assert!(
        connect
            .action
            .as_deref()
            .unwrap()
            .contains("nothing accepts connections"),
        "{connect:?}"
    );
    assert_eq!(code, 1);
}

#[test]
fn text_report_has_one_line_per_check_with_marks() {
    let broker = acl_broker();
    let out = Command::new(env!("CARGO_BIN_EXE_mc-gateway"))
        .args(["doctor", "--sim", "--broker"])
        .arg(broker.addr().to_string())
        .args(["--island", "bench-a", "--username", USER, "--boot-config"])
        .arg(data("missing-overlay.txt"))
        .env("IHEX_MQTT_PASSWORD", PASSWORD)
        .output()
        .expect("run mc-gateway");
    let text = String::from_utf8_lossy(&out.stdout);
    let lines: Vec<&str> = text.lines().collect();
    assert!(lines[0].starts_with("✓ boot.spi"), "{text}");
    assert!(lines[1].starts_with("✗ boot.overlay"), "{text}");
    assert!(
        lines[1].contains(" → append dtoverlay=mcp2515-can0"),
        "{text}"
    );
    assert!(
        lines.iter().any(|l| l.starts_with("– can.interface")),
        "{text}"
    );
    assert!(
        lines.iter().any(|l| l.starts_with("✓ broker.topics")),
        "{text}"
    );
    assert!(
        lines.last().unwrap().contains("1 check(s) failed"),
        "{text}"
    );
    assert_eq!(out.status.code(), Some(1));
}

#[test]
fn help_names_the_subcommand_and_its_options() {
    let out = Command::new(env!("CARGO_BIN_EXE_mc-gateway"))
        .arg("--help")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("doctor"), "{text}");
    let out = Command::new(env!("CARGO_BIN_EXE_mc-gateway"))
        .args(["doctor", "--help"])
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for needle in [
        "--boot-config",
        "--hat-oscillator",
        "--hat-interrupt",
        "--listen-ms",
        "--json",
        "--config",
        "Exit status: 0 when no check failed",
    ] {
        assert!(text.contains(needle), "doctor --help lacks {needle}");
    }
    // No `help` subcommand appeared with `doctor`: the gateway's command line is as before.
    let out = Command::new(env!("CARGO_BIN_EXE_mc-gateway"))
        .arg("help")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
}
