//! The checks of the gateway core's fuzz targets, as plain functions: the libFuzzer targets in
//! `fuzz_targets/` call them on nightly, and `tests/seeds.rs` feeds them the seed corpus on stable.
//!
//! [`command`] drives a [`Bridge`] through its public API only, as an adapter does: a small island
//! answers every frame the bridge sends (health replies, acks, empty state reports), and time runs
//! until nothing can still be pending.

use std::time::{Duration, Instant};

use ihex_gateway_core::{Bridge, BridgeConfig, Event, Publication};
use ihex_proto::{AckResult, HealthFlags, HealthReply, Message, NodeId, Packet, StateReport};

/// The island's nodes: "2", "3", "111", "112" in the API's hex spelling.
const ISLAND: [u16; 4] = [0x2, 0x3, 0x111, 0x112];

/// How long after the command the check keeps time running: far beyond the command timeout
/// (500 ms) and the retries of every command kind, so each accepted command has ended.
const SETTLE: Duration = Duration::from_secs(30);
/// One step of that time.
const STEP: Duration = Duration::from_millis(250);

/// The events that answer a command (docs/mqtt-api.md, "Answers to commands"; `list` answers with
/// `node_list`).
const ANSWERS: [&str; 3] = ["command_result", "command_rejected", "node_list"];

/// `input` as one message on the command topic of a bridge with a known island. Panics (the
/// fuzzer's finding) when the bridge panics, when the input gets no answer or more than one, when
/// a rejected command sent a frame, when an event does not read back as an [`Event`], or when a
/// command is still in flight after [`SETTLE`].
pub fn command(input: &[u8]) {
    let (mut bridge, t0) = island();
    let mut now = t0 + Duration::from_millis(2);
    bridge.handle_command(input, now);
    let mut out = Outputs::default();
    let end = now + SETTLE;
    loop {
        drain(&mut bridge, now, &mut out);
        if now >= end {
            break;
        }
        now += STEP;
        bridge.handle_timeout(now);
    }
    assert_eq!(
        out.answers.len(),
        1,
        "{:?} got {} answers: {:?}",
        String::from_utf8_lossy(input),
        out.answers.len(),
        out.answers
    );
    if out.answers[0].0 == "command_rejected" {
        assert!(
            out.commands_sent.is_empty(),
            "{:?} was rejected but sent {:?}",
            String::from_utf8_lossy(input),
            out.commands_sent
        );
    }
    assert_eq!(
        bridge.command_counters().in_flight,
        0,
        "{:?} is still in flight {SETTLE:?} later",
        String::from_utf8_lossy(input)
    );
}

/// What the bridge gave out while the check ran.
#[derive(Default)]
struct Outputs {
    /// Answers: (event name, JSON).
    answers: Vec<(&'static str, String)>,
    /// Frames sent other than health checks and state queries (the bridge's own traffic).
    commands_sent: Vec<Packet>,
}

fn id(raw: u16) -> NodeId {
    NodeId::new(raw).expect("the island's IDs are valid node IDs")
}

/// A bridge whose first health check was answered by every node of [`ISLAND`], and their state
/// read back: the island is known and online.
fn island() -> (Bridge, Instant) {
    let t0 = Instant::now();
    let mut bridge = Bridge::new(BridgeConfig::default(), t0);
    bridge.handle_timeout(t0);
    let mut out = Outputs::default();
    let now = t0 + Duration::from_millis(1);
    drain(&mut bridge, now, &mut out);
    assert!(out.answers.is_empty() && out.commands_sent.is_empty());
    for &raw in &ISLAND {
        assert!(
            bridge.registry().get(id(raw)).is_some(),
            "node {raw:x} is not known after its health reply"
        );
    }
    (bridge, t0)
}

/// Takes every frame and publication at `now`; the island answers each frame at once, and the
/// answers are drained too, until the bridge has nothing more to give.
fn drain(bridge: &mut Bridge, now: Instant, out: &mut Outputs) {
    loop {
        let mut progressed = false;
        while let Some(load) = bridge.poll_fw_load() {
            progressed = true;
            bridge.handle_fw_image(load, Err("no such image (fuzz island)".into()), now);
        }
        while let Some(t) = bridge.poll_transmit(now) {
            progressed = true;
            let packet = t.packet;
            assert_eq!(packet.validate(), Ok(()), "the bridge sent {packet:?}");
            bridge.handle_transmitted(packet, now);
            answer(bridge, packet, now, out);
        }
        while let Some(p) = bridge.poll_publication() {
            progressed = true;
            if let Publication::Event(_) = p {
                let json = p.to_json();
                let event: Event = serde_json::from_str(&json)
                    .unwrap_or_else(|e| panic!("{json} does not read back as an event: {e}"));
                if let Some(name) = ANSWERS.into_iter().find(|n| *n == event.name()) {
                    out.answers.push((name, json));
                }
            }
        }
        if !progressed {
            return;
        }
    }
}

/// What the island answers to `packet`: every node acks with `ok`.
fn answer(bridge: &mut Bridge, packet: Packet, now: Instant, out: &mut Outputs) {
    let nodes: Vec<NodeId> = if packet.dest == NodeId::BROADCAST {
        ISLAND.iter().map(|&n| id(n)).collect()
    } else {
        vec![packet.dest]
    };
    let replies: Vec<Packet> = match packet.msg {
        Message::HealthCheck { seq } => nodes
            .iter()
            .map(|&n| {
                let reply = HealthReply {
                    seq,
                    flags: HealthFlags(0),
                    loops: 0,
                    tec: 0,
                    rec: 0,
                    uptime_s: 1,
                };
                Packet::report(n, Message::HealthReply(reply))
            })
            .collect(),
        Message::StateQuery { seq, parts } => {
            let end = StateReport::End {
                seq,
                parts,
                count: 0,
            };
            vec![Packet::report(packet.dest, Message::StateReport(end))]
        }
        Message::AssignCommit {
            uid_tail,
            new_id,
            seq,
        } => {
            out.commands_sent.push(packet);
            let reply = Message::AssignReply {
                seq,
                result: AckResult::Ok,
                new_id,
                uid_tail,
            };
            vec![Packet::report(new_id, reply)]
        }
        msg => {
            out.commands_sent.push(packet);
            match msg.ack_seq() {
                Some(seq) => nodes
                    .iter()
                    .map(|&n| {
                        let ack = Message::Ack {
                            kind: msg.kind(),
                            seq,
                            result: AckResult::Ok,
                            detail: 0,
                        };
                        Packet::report(n, ack)
                    })
                    .collect(),
                None => Vec::new(),
            }
        }
    };
    for reply in replies {
        bridge.handle_packet(reply, now);
    }
}
