//! Helpers of the bridge's tests: drive a [`Bridge`], collect what one input made it do.

use std::time::{Duration, Instant};

use ihex_proto::{AckResult, HealthFlags, HealthReply, Kind, Message, NodeId, Packet, StateReport};
use serde_json::Value;

use super::{Bridge, BridgeConfig, Publication};
use crate::topic::Topic;

pub(crate) use ihex_proto::test_util::{id, port};
pub(crate) const MS: Duration = Duration::from_millis(1);
pub(crate) const S: Duration = Duration::from_secs(1);

/// What one call made the bridge do.
#[derive(Default, Debug)]
pub(crate) struct Out {
    /// Frames sent, state queries aside.
    pub(crate) sent: Vec<Packet>,
    /// State queries sent.
    pub(crate) queries: Vec<Packet>,
    pub(crate) events: Vec<Value>,
    pub(crate) raw_events: Vec<String>,
    pub(crate) states: Vec<(NodeId, Value)>,
    /// Home Assistant configs and light states, with their topics.
    pub(crate) ha: Vec<(Topic, Value)>,
    /// Retained topics emptied.
    pub(crate) cleared: Vec<Topic>,
    /// Leases documents published.
    pub(crate) leases: Vec<Value>,
    /// Running procedures documents published.
    pub(crate) procedures: Vec<Value>,
}

impl Out {
    pub(crate) fn named(&self, name: &str) -> Vec<&Value> {
        self.events.iter().filter(|e| e["event"] == name).collect()
    }
    /// The events named `name` as published, byte for byte.
    pub(crate) fn raw_named(&self, name: &str) -> Vec<&str> {
        self.events
            .iter()
            .zip(&self.raw_events)
            .filter(|(e, _)| e["event"] == name)
            .map(|(_, raw)| raw.as_str())
            .collect()
    }
    pub(crate) fn one(&self, name: &str) -> &Value {
        let v = self.named(name);
        assert_eq!(v.len(), 1, "expected one {name} in {:#?}", self.events);
        &v[0]["payload"]
    }
}

/// Drains every output as a healthy adapter does: every frame is written and confirmed on the bus
/// at once (at the time of the last input), publications are serialised once (`to_json`).
pub(crate) fn drain(b: &mut Bridge) -> Out {
    drain_with(b, true)
}

/// [`drain`], but the frames are handed out and left unconfirmed (the window fills).
pub(crate) fn drain_unconfirmed(b: &mut Bridge) -> Out {
    drain_with(b, false)
}

fn drain_with(b: &mut Bridge, confirm: bool) -> Out {
    let mut out = Out::default();
    let now = b.now;
    while let Some(t) = b.poll_transmit(now) {
        let p = t.packet;
        p.validate().expect("the bridge only sends valid packets");
        if matches!(p.msg, Message::StateQuery { .. }) {
            out.queries.push(p);
        } else {
            out.sent.push(p);
        }
        if confirm {
            b.handle_transmitted(p, now);
        }
    }
    while let Some(p) = b.poll_publication() {
        let payload = p.to_json();
        match p {
            Publication::Event(_) => {
                assert!(!p.retain(), "events are not retained");
                out.events.push(serde_json::from_str(&payload).unwrap());
                out.raw_events.push(payload);
            }
            Publication::State(ref s) => {
                assert!(p.retain(), "node states are retained");
                out.states
                    .push((s.id.0, serde_json::from_str(&payload).unwrap()));
            }
            Publication::Ha(_) => {
                assert!(p.retain(), "Home Assistant configs and states are retained");
                out.ha
                    .push((p.topic(), serde_json::from_str(&payload).unwrap()));
            }
            Publication::Cleared(t) => {
                assert!(p.retain() && payload.is_empty(), "{t:?}");
                out.cleared.push(t);
            }
            Publication::Leases(_) => {
                assert!(p.retain(), "the leases document is retained");
                assert_eq!(p.topic(), Topic::Leases);
                out.leases.push(serde_json::from_str(&payload).unwrap());
            }
            Publication::Procedures(_) => {
                assert!(p.retain(), "the procedures document is retained");
                assert_eq!(p.topic(), Topic::Procedures);
                out.procedures.push(serde_json::from_str(&payload).unwrap());
            }
        }
    }
    out
}

pub(crate) fn reply(seq: u8, flags: u8) -> Message {
    Message::HealthReply(HealthReply {
        seq,
        flags: HealthFlags(flags),
        loops: 0,
        tec: 0,
        rec: 0,
        uptime_s: 1,
    })
}

pub(crate) fn ack(kind: Kind, seq: u8, result: AckResult) -> Message {
    Message::Ack {
        kind,
        seq,
        result,
        detail: 0,
    }
}

/// Answers every state query in `out` at `now` with an empty, complete reply (a node with nothing
/// to report beyond what the bridge knows).
pub(crate) fn answer_queries(b: &mut Bridge, out: &Out, now: Instant) {
    for q in &out.queries {
        let Message::StateQuery { seq, parts } = q.msg else {
            continue;
        };
        let end = StateReport::End {
            seq,
            parts,
            count: 0,
        };
        b.handle_packet(Packet::report(q.dest, Message::StateReport(end)), now);
    }
}

/// A bridge at `t0` whose first health check went out and was answered by `nodes` (and their
/// state queries by empty replies).
pub(crate) fn with_nodes(nodes: &[u16]) -> (Bridge, Instant) {
    let t0 = Instant::now();
    let mut b = Bridge::new(BridgeConfig::default(), t0);
    b.handle_timeout(t0);
    let out = drain(&mut b);
    assert_eq!(
        out.sent,
        vec![Packet::command(
            NodeId::BROADCAST,
            Message::HealthCheck { seq: 0 }
        )]
    );
    for &n in nodes {
        b.handle_packet(Packet::report(id(n), reply(0, 0)), t0 + MS);
    }
    // Four questions at a time: answer until none is left.
    loop {
        let out = drain(&mut b);
        if out.queries.is_empty() {
            break;
        }
        answer_queries(&mut b, &out, t0 + MS);
    }
    (b, t0)
}

/// Docks `mobile` on `static_id`'s `port` at `now`, as the elements tell it when no docking is
/// pending: the static element reports the detection, the mobile element handshakes on its port 0.
/// Returns what that made the bridge do (drained).
pub(crate) fn dock(b: &mut Bridge, static_id: u16, port: u8, mobile: u16, now: Instant) -> Out {
    let detected = Message::DockDetected {
        port: self::port(port),
    };
    b.handle_packet(Packet::report(id(static_id), detected), now);
    let handshake = Message::Handshake {
        port: self::port(0),
    };
    b.handle_packet(Packet::report(id(mobile), handshake), now);
    drain(b)
}

pub(crate) fn command(b: &mut Bridge, json: Value, now: Instant) -> Out {
    b.handle_command(json.to_string().as_bytes(), now);
    drain(b)
}

/// Hands out the waiting frames (confirmed) and answers every state query among them with an
/// empty, complete reply, until none is left — without taking publications: the nodes are read
/// back, so their state documents (held until then) are queued.
pub(crate) fn read_back_all(b: &mut Bridge, now: Instant) {
    loop {
        let mut queries = Vec::new();
        while let Some(t) = b.poll_transmit(now) {
            let p = t.packet;
            b.handle_transmitted(p, now);
            if matches!(p.msg, Message::StateQuery { .. }) {
                queries.push(p);
            }
        }
        if queries.is_empty() {
            return;
        }
        let out = Out {
            queries,
            ..Out::default()
        };
        answer_queries(b, &out, now);
    }
}
