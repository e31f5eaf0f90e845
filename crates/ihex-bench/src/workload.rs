//! A fixed, deterministic workload for the gateway's sans-IO [`Bridge`]: the work the gateway does
//! per bridged frame without any I/O, for instruction counting (callgrind).
//!
//! * CAN → event: raw frame (id + bytes) → [`Packet::decode`] → [`Bridge::handle_packet`] → the
//!   `node_rebooted` event, serialised to JSON and its topic name resolved as the MQTT adapter
//!   does. `BootUp` from a known node is used because it maps 1:1 to an event and is not
//!   rate-limited (`Fault` is: one event per node and code per second).
//! * command → frame: JSON `led` command bytes → [`Bridge::handle_command`] (parse, validate, track the
//!   pending ack) → [`Packet::encode`] to the frame's id and bytes → [`Bridge::handle_transmitted`]
//!   (the frame's echo, as the gateway's SocketCAN adapter reports it).
//!
//! * command → frame with leases held: the same, with [`LEASES`] leases held on the first nodes;
//!   a command to a leased node carries its lease's token, so every command passes the lease
//!   check and goes out: the difference to the plain path is what the check costs per command.
//!
//! Inputs are prepared once, before the measured loop, and reused round-robin, so that running
//! `n` and `2n` iterations differs only by `n` iterations of the loop: (I(2n) − I(n)) / n is the
//! cost of one bridged frame, exactly repeatable.

use std::hint::black_box;
use std::time::{Duration, Instant};

use ihex_gateway_core::topic::Topics;
use ihex_gateway_core::{Bridge, BridgeConfig, Delivery, Interface, Origin, PayloadWriter};
use ihex_proto::{AckResult, BootRole, Message, NodeId, Packet, ResetReason};
use mc_gateway::audit::Audit;
use mc_gateway::config::AuditConfig;

/// Nodes made known before the loop (commands and reports rotate over them).
pub const NODES: u16 = 64;

/// Which path the workload drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Path {
    /// CAN report → published event.
    CanToEvent,
    /// MQTT command → CAN frame.
    CommandToFrame,
    /// MQTT command → CAN frame while [`LEASES`] leases are held.
    CommandLeased,
    /// MQTT command → CAN frame → the node's ack → `command_result`, audit trail off.
    CommandAnswered,
    /// The same with the audit trail on: the command and answer records made by the core task and
    /// written by the writer (run inline here, into a temporary directory), chain hashes included.
    CommandAudited,
}

/// Leases held in [`Path::CommandLeased`], one node each.
pub const LEASES: u16 = 8;

/// What one run produced (so that nothing is optimised away, and so it can be checked).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Output {
    /// Events/state documents published.
    pub publications: usize,
    /// Frames sent.
    pub frames: usize,
    /// Bytes of JSON and topic names produced.
    pub bytes: usize,
}

fn node(i: u16) -> NodeId {
    NodeId::new(1 + i % NODES).expect("1..=64 are SC ids")
}

/// The `BootUp` report of workload item `i` (varies the node and the reset code).
pub fn boot_up(i: u32) -> Packet {
    Packet::report(
        node(i as u16),
        Message::BootUp {
            version: (1, 0),
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::Other(4 + (i / u32::from(NODES) % 200) as u8),
        },
    )
}

/// The JSON `led` command of workload item `i`.
pub fn led_command(i: u32) -> String {
    format!(
        r#"{{"cmd":"led","node":"{}","color":[{},{},{}],"brightness":200}}"#,
        node(i as u16),
        i & 0xff,
        i >> 8 & 0xff,
        (i * 7) & 0xff
    )
}

fn drain(
    bridge: &mut Bridge,
    topics: &Topics,
    text: &mut PayloadWriter,
    out: &mut Output,
    now: Instant,
) {
    drain_answered(bridge, topics, text, out, now, false, None);
}

/// [`drain`], with each frame acknowledged by its node when `ack`, and each publication handed to
/// the audit trail when it is on.
fn drain_answered(
    bridge: &mut Bridge,
    topics: &Topics,
    text: &mut PayloadWriter,
    out: &mut Output,
    now: Instant,
    ack: bool,
    audit: Option<&Audit>,
) {
    // As the gateway's shell does: the frame encoded, then confirmed by its echo.
    while let Some(t) = bridge.poll_transmit(now) {
        let (id, data) = t.packet.encode();
        black_box((id, &data));
        bridge.handle_transmitted(t.packet, now);
        out.frames += 1;
        if ack {
            let msg = &t.packet.msg;
            if let Some(seq) = msg.ack_seq() {
                let answer = Message::Ack {
                    kind: msg.kind(),
                    seq,
                    result: AckResult::Ok,
                    detail: 0,
                };
                bridge.handle_packet(Packet::report(t.packet.dest, answer), now);
            }
        }
    }
    // As the gateway's shell does: the topic resolved, the publication serialised once.
    while let Some(p) = bridge.poll_publication() {
        let name = topics.resolve(p.topic());
        let payload = text.write(&p);
        if let Some(a) = audit {
            a.published(&p, &payload);
        }
        out.bytes += black_box(name.len() + payload.len());
        out.publications += 1;
    }
}

/// A bridge with [`NODES`] known nodes and every output of that set-up drained.
pub fn prepared_bridge(now: Instant) -> (Bridge, Topics) {
    let config = BridgeConfig {
        // No health checks and no command timeouts inside the measured loop.
        health_period: Duration::from_secs(3600),
        command_timeout: Duration::from_secs(3600),
        ..BridgeConfig::default()
    };
    let mut bridge = Bridge::new(config, now);
    let topics = Topics::seed();
    let mut sink = Output::default();
    for i in 0..u32::from(NODES) {
        bridge.handle_packet(boot_up(i), now);
    }
    // A first reboot of each node settles its state document (actuators reset).
    for i in 0..u32::from(NODES) {
        bridge.handle_packet(boot_up(i), now);
    }
    drain(
        &mut bridge,
        &topics,
        &mut PayloadWriter::default(),
        &mut sink,
        now,
    );
    (bridge, topics)
}

/// Takes a lease on each of the first [`LEASES`] nodes; their tokens, by node.
fn take_leases(bridge: &mut Bridge, now: Instant) -> Vec<String> {
    (0..LEASES)
        .map(|i| {
            let cmd = format!(
                r#"{{"cmd":"lease","owner":"bench-{i}","nodes":"{}","seconds":86400}}"#,
                node(i)
            );
            bridge.handle_command(cmd.as_bytes(), now);
            while bridge.poll_transmit(now).is_some() {}
            let mut token = String::new();
            while let Some(p) = bridge.poll_publication() {
                if let ihex_gateway_core::Publication::Event(
                    ihex_gateway_core::event::Event::LeaseGranted(g),
                ) = p
                {
                    token = g.token.clone();
                }
            }
            token
        })
        .collect()
}

/// Runs `n` iterations of `path` and returns what they produced.
pub fn run(path: Path, n: u32) -> Output {
    let now = Instant::now();
    let (mut bridge, topics) = prepared_bridge(now);
    let mut out = Output::default();
    let mut text = PayloadWriter::default();
    // Prepared inputs, reused round-robin: constant set-up cost whatever n is.
    const DISTINCT: u32 = 256;
    match path {
        Path::CanToEvent => {
            let frames: Vec<(u32, heapless_bytes::Bytes)> = (0..DISTINCT)
                .map(|i| {
                    let (id, data) = boot_up(i).encode();
                    (id, heapless_bytes::Bytes::from(&data[..]))
                })
                .collect();
            for i in 0..n {
                let (id, data) = &frames[(i % DISTINCT) as usize];
                match Packet::decode(*id, data.as_slice()) {
                    Ok(p) => bridge.handle_packet(p, now),
                    Err(e) => bridge.handle_undecodable(*id, data.as_slice(), e, now),
                }
                drain(&mut bridge, &topics, &mut text, &mut out, now);
            }
        }
        Path::CommandLeased => {
            let tokens = take_leases(&mut bridge, now);
            let commands: Vec<String> = (0..DISTINCT)
                .map(|i| {
                    let c = led_command(i);
                    match tokens.get((i % u32::from(NODES)) as usize) {
                        Some(t) => format!("{},\"lease\":\"{t}\"}}", &c[..c.len() - 1]),
                        None => c,
                    }
                })
                .collect();
            for i in 0..n {
                bridge.handle_command(commands[(i % DISTINCT) as usize].as_bytes(), now);
                drain(&mut bridge, &topics, &mut text, &mut out, now);
            }
        }
        Path::CommandToFrame => {
            let commands: Vec<String> = (0..DISTINCT).map(led_command).collect();
            for i in 0..n {
                bridge.handle_command(commands[(i % DISTINCT) as usize].as_bytes(), now);
                drain(&mut bridge, &topics, &mut text, &mut out, now);
            }
        }
        Path::CommandAnswered | Path::CommandAudited => {
            let dir = std::env::temp_dir().join(format!("ihex-bench-audit-{}", std::process::id()));
            let config = AuditConfig {
                dir: Some(dir.clone()),
                anchor: None,
                max_bytes: None,
            };
            let mut audit = (path == Path::CommandAudited)
                .then(|| Audit::open(&config))
                .flatten();
            // As the gateway's MQTT task hands commands over (the payload shared, not copied).
            let commands: Vec<bytes::Bytes> =
                (0..DISTINCT).map(|i| led_command(i).into()).collect();
            let origin = Origin::new(Interface::Mqtt, Some("alice".into()));
            for i in 0..n {
                let payload = commands[(i % DISTINCT) as usize].clone();
                let delivery = Delivery::live(now).with_origin(origin.clone());
                if let Some((a, _)) = &audit {
                    a.command(&delivery.origin, &payload, false);
                }
                bridge.handle_delivered_command(&payload, delivery, now);
                let a = audit.as_ref().map(|(a, _)| a);
                drain_answered(&mut bridge, &topics, &mut text, &mut out, now, true, a);
                if let Some((_, w)) = &mut audit {
                    w.write_waiting();
                }
            }
            drop(audit);
            let _ = std::fs::remove_dir_all(&dir);
        }
    }
    out
}

/// A frame's data bytes, owned, without pulling `heapless` in as a dependency.
mod heapless_bytes {
    /// Up to 8 bytes.
    #[derive(Clone, Copy, Debug)]
    pub struct Bytes {
        len: usize,
        buf: [u8; 8],
    }

    impl Bytes {
        /// The bytes.
        pub fn as_slice(&self) -> &[u8] {
            &self.buf[..self.len]
        }
    }

    impl From<&[u8]> for Bytes {
        fn from(s: &[u8]) -> Self {
            let mut buf = [0; 8];
            let len = s.len().min(8);
            buf[..len].copy_from_slice(&s[..len]);
            Bytes { len, buf }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_report_becomes_exactly_one_event() {
        let out = run(Path::CanToEvent, 1000);
        assert_eq!(
            out.publications, 1000,
            "one node_rebooted per BootUp, no state churn"
        );
        assert_eq!(out.frames, 0);
    }

    #[test]
    fn every_command_becomes_exactly_one_frame() {
        let out = run(Path::CommandToFrame, 1000);
        assert_eq!(out.frames, 1000);
        assert_eq!(
            out.publications, 0,
            "no rejection, no result before the ack"
        );
    }

    #[test]
    fn every_command_to_a_leased_node_with_its_token_becomes_one_frame() {
        let out = run(Path::CommandLeased, 1000);
        assert_eq!(out.frames, 1000);
        assert_eq!(out.publications, 0, "no rejection");
    }

    #[test]
    fn the_audit_trail_changes_nothing_the_gateway_sends() {
        let plain = run(Path::CommandAnswered, 300);
        // Each command: its frame, its command_result and the element's new state document.
        assert_eq!((plain.frames, plain.publications), (300, 600));
        let audited = run(Path::CommandAudited, 300);
        assert_eq!(
            audited, plain,
            "the trail changes nothing the gateway sends"
        );
    }

    #[test]
    fn led_command_is_accepted_json() {
        let now = Instant::now();
        let (mut bridge, topics) = prepared_bridge(now);
        bridge.handle_command(led_command(300).as_bytes(), now);
        let mut out = Output::default();
        drain(
            &mut bridge,
            &topics,
            &mut PayloadWriter::default(),
            &mut out,
            now,
        );
        assert_eq!((out.frames, out.publications), (1, 0));
    }
}
