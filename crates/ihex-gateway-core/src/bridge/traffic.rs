//! Property test of the whole bridge: any sequence of reports, answers to what it sent, commands,
//! bus conditions, send failures and time keeps every invariant. Nothing panics, every frame sent
//! is valid, every event reads back as an [`Event`], and every accepted command ends in exactly one
//! `command_result`. proptest shrinks a failing sequence to a short one; the seeds of failures
//! found are kept in `proptest-regressions/bridge/traffic.txt` and replayed first.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use ihex_proto::{AckResult, Kind, Message, NodeId, Packet};
use proptest::prelude::*;
use proptest::strategy::ValueTree;
use proptest::test_runner::{Config, TestRunner};
use serde_json::json;

use super::test_support::*;
use super::{Bridge, BridgeConfig, BusEvent};
use crate::event::Event;

/// The nodes that speak.
const NODES: [u16; 5] = [1, 2, 3, 0x111, 0x112];
/// Command targets: the nodes, everyone, and one nobody has heard of.
const TARGETS: [&str; 7] = ["1", "2", "3", "111", "112", "all", "5a"];
/// The report kinds nodes send unasked.
const REPORTS: [Kind; 7] = [
    Kind::Fault,
    Kind::DockDetected,
    Kind::DockRemoved,
    Kind::Handshake,
    Kind::BootUp,
    Kind::HealthReply,
    Kind::AssignReply,
];

/// One input to the bridge. Indices pick from the lists above, or from the frames sent so far
/// counting back from the latest (modulo their number): a sequence shrunk by dropping earlier
/// inputs still picks the same recent frame.
#[derive(Clone, Debug)]
enum Input {
    /// A report of a random kind from a random node: random bytes, kept when they decode.
    Report {
        kind: usize,
        src: usize,
        data: [u8; 8],
    },
    /// An answer to a frame sent earlier (possibly twice, possibly late), from its destination or,
    /// for a broadcast, from any node.
    Answer {
        frame: usize,
        from: usize,
        result: u8,
    },
    /// A JSON command.
    Command {
        target: usize,
        which: u8,
        a: u16,
        flag: bool,
    },
    /// A bus condition.
    Bus { which: u8, n: u32, data: u8 },
    /// A frame sent earlier is reported as not sent.
    SendFailed { frame: usize },
    /// Time passes, then the timers run.
    Wait { ms: u64 },
}

fn input() -> impl Strategy<Value = Input> {
    // Small byte values half the time: ports, flags and codes are mostly small.
    let byte = prop_oneof![0u8..8, any::<u8>()];
    prop_oneof![
        16 => (0..REPORTS.len(), 0..NODES.len(), prop::array::uniform8(byte))
            .prop_map(|(kind, src, data)| Input::Report { kind, src, data }),
        8 => (0usize..64, 0..NODES.len(), 0u8..7)
            .prop_map(|(frame, from, result)| Input::Answer { frame, from, result }),
        4 => (0..TARGETS.len(), 0u8..6, 0u16..3000, any::<bool>())
            .prop_map(|(target, which, a, flag)| Input::Command { target, which, a, flag }),
        4 => (0u8..5, 0u32..5, any::<u8>())
            .prop_map(|(which, n, data)| Input::Bus { which, n, data }),
        1 => (0usize..64).prop_map(|frame| Input::SendFailed { frame }),
        7 => (0u64..400).prop_map(|ms| Input::Wait { ms }),
    ]
}

/// What a run saw, for the checks of coverage.
#[derive(Default, Debug)]
struct Seen {
    /// Commands accepted (not `list`, not rejected).
    accepted: usize,
    /// Events published, by name.
    events: BTreeMap<&'static str, usize>,
}

/// Feeds `inputs` to a bridge, drains it as a healthy adapter does after each one, and checks the
/// invariants; then lets everything pending time out. `Err` says which invariant broke.
fn run(inputs: &[Input]) -> Result<Seen, TestCaseError> {
    let t0 = Instant::now();
    let mut now = t0;
    let mut b = Bridge::new(BridgeConfig::default(), t0);
    let mut sent: Vec<Packet> = Vec::new();
    let mut seen = Seen::default();
    let (mut accepted, mut results) = (0usize, 0usize);
    let pick = |sent: &[Packet], i: usize| sent.iter().rev().nth(i % sent.len().max(1)).copied();
    for input in inputs {
        match *input {
            Input::Report { kind, src, data } => {
                let kind = REPORTS[kind];
                let len = usize::from(Message::len_of(kind));
                if let Ok(msg) = Message::decode(kind, &data[..len]) {
                    b.handle_packet(Packet::report(id(NODES[src]), msg), now);
                }
            }
            Input::Answer {
                frame,
                from,
                result,
            } => {
                let Some(p) = pick(&sent, frame) else {
                    continue;
                };
                let result = AckResult::from_raw(result);
                let msg = match p.msg {
                    Message::AssignCommit {
                        uid_tail,
                        new_id,
                        seq,
                    } => Message::AssignReply {
                        seq,
                        result,
                        new_id,
                        uid_tail,
                    },
                    m => match m.ack_seq() {
                        Some(seq) => ack(m.kind(), seq, result),
                        None => continue,
                    },
                };
                let src = match msg {
                    Message::AssignReply { new_id, .. } => new_id,
                    _ if p.dest == NodeId::BROADCAST => id(NODES[from]),
                    _ => p.dest,
                };
                b.handle_packet(Packet::report(src, msg), now);
            }
            Input::Command {
                target,
                which,
                a,
                flag,
            } => {
                let node = TARGETS[target];
                let cmd = match which {
                    0 => json!({"cmd": "led", "node": node, "color": [a % 300, 0, 1]}),
                    1 => json!({"cmd": "buzzer", "node": node, "mode": "pattern",
                                "on_ms": a, "off_ms": 100}),
                    2 => json!({"cmd": "power", "node": node, "on": flag}),
                    3 => json!({"cmd": "identify", "node": node, "seconds": a % 300}),
                    4 => json!({"cmd": "assign", "uid": "00112233445566778899aabb",
                                "new_id": TARGETS[usize::from(a) % 5], "force": flag}),
                    _ => json!({"cmd": "list"}),
                };
                b.handle_command(cmd.to_string().as_bytes(), now);
                if cmd["cmd"] != "list" {
                    accepted += 1; // taken back below when rejected
                }
            }
            Input::Bus { which, n, data } => {
                let event = match which {
                    0 => BusEvent::BusOff,
                    1 => BusEvent::Recovered,
                    2 => BusEvent::RxDropped(n),
                    3 => BusEvent::ErrorFrame {
                        class: u32::from(data) << 2,
                        data: [data; 8],
                    },
                    _ => BusEvent::InterfaceDown,
                };
                b.handle_bus_event(event, now);
            }
            Input::SendFailed { frame } => {
                if let Some(p) = pick(&sent, frame) {
                    b.handle_send_failed(p, "test", now);
                }
            }
            Input::Wait { ms } => {
                now += Duration::from_millis(ms);
                b.handle_timeout(now);
            }
        }
        let out = drain(&mut b);
        for raw in &out.raw_events {
            let event: Event = serde_json::from_str(raw)
                .map_err(|e| TestCaseError::fail(format!("{raw}: {e}")))?;
            *seen.events.entry(event.name()).or_insert(0) += 1;
            match event {
                Event::CommandResult(_) => results += 1,
                Event::CommandRejected(_) => accepted -= 1,
                _ => {}
            }
        }
        sent.extend(
            out.sent
                .iter()
                .filter(|p| p.msg.kind() != Kind::HealthCheck),
        );
        if sent.len() > 64 {
            sent.drain(..32);
        }
    }
    // Everything still pending times out.
    now += Duration::from_secs(60);
    b.handle_timeout(now);
    let out = drain(&mut b);
    results += out.named("command_result").len();
    prop_assert_eq!(b.command_counters().in_flight, 0);
    prop_assert_eq!(results, accepted, "one command_result per accepted command");
    seen.accepted = accepted;
    Ok(seen)
}

proptest! {
    #![proptest_config(Config {
        cases: 32,
        max_shrink_iters: 20_000,
        ..Config::default()
    })]

    #[test]
    fn random_traffic_keeps_every_invariant(inputs in prop::collection::vec(input(), 0..800)) {
        run(&inputs)?;
    }
}

/// One long sequence, the same on every run, reaches every kind of event: the generator exercises
/// what the property claims to cover.
#[test]
fn a_long_random_run_reaches_every_event() {
    let mut runner = TestRunner::deterministic();
    let inputs = prop::collection::vec(input(), 20_000)
        .new_tree(&mut runner)
        .expect("a sequence")
        .current();
    let seen = run(&inputs).expect("the invariants hold");
    for name in [
        "new_connection",
        "connection_removed",
        "dock_failed",
        "node_online",
        "node_lost",
        "node_rebooted",
        "command_result",
        "command_rejected",
        "fault",
        "bus_error",
        "node_list",
    ] {
        assert!(seen.events.contains_key(name), "no {name} in {seen:?}");
    }
    let events: usize = seen.events.values().sum();
    assert!(
        seen.accepted > 100 && events > 1000,
        "the run exercised little: {seen:?}"
    );
}
