//! Helpers of the bridge's tests: drive a [`Bridge`], collect what one input made it do.

use std::time::{Duration, Instant};

use ihex_proto::{AckResult, HealthFlags, HealthReply, Kind, Message, NodeId, Packet, Port};
use serde_json::Value;

use super::{Bridge, BridgeConfig, Publication};

pub(super) fn id(raw: u16) -> NodeId {
    NodeId::new(raw).unwrap()
}
pub(super) fn port(raw: u8) -> Port {
    Port::new(raw).unwrap()
}
pub(super) const MS: Duration = Duration::from_millis(1);
pub(super) const S: Duration = Duration::from_secs(1);

/// What one call made the bridge do.
#[derive(Default, Debug)]
pub(super) struct Out {
    pub(super) sent: Vec<Packet>,
    pub(super) events: Vec<Value>,
    pub(super) raw_events: Vec<String>,
    pub(super) states: Vec<(NodeId, Value)>,
}

impl Out {
    pub(super) fn named(&self, name: &str) -> Vec<&Value> {
        self.events.iter().filter(|e| e["event"] == name).collect()
    }
    pub(super) fn one(&self, name: &str) -> &Value {
        let v = self.named(name);
        assert_eq!(v.len(), 1, "expected one {name} in {:#?}", self.events);
        &v[0]["payload"]
    }
}

/// Drains every output, serialising publications the way the adapter does (once, `to_json`).
pub(super) fn drain(b: &mut Bridge) -> Out {
    let mut out = Out::default();
    while let Some(p) = b.poll_transmit() {
        p.validate().expect("the bridge only sends valid packets");
        out.sent.push(p)
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
        }
    }
    out
}

pub(super) fn reply(seq: u8, flags: u8) -> Message {
    Message::HealthReply(HealthReply {
        seq,
        flags: HealthFlags(flags),
        loops: 0,
        tec: 0,
        rec: 0,
        uptime_s: 1,
    })
}

pub(super) fn ack(kind: Kind, seq: u8, result: AckResult) -> Message {
    Message::Ack {
        kind,
        seq,
        result,
        detail: 0,
    }
}

/// A bridge at `t0` whose first health check went out and was answered by `nodes`.
pub(super) fn with_nodes(nodes: &[u16]) -> (Bridge, Instant) {
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
    drain(&mut b);
    (b, t0)
}

pub(super) fn command(b: &mut Bridge, json: Value, now: Instant) -> Out {
    b.handle_command(json.to_string().as_bytes(), now);
    drain(b)
}
