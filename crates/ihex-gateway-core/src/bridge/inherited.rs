//! State documents an earlier run of the gateway left retained on the broker. The adapter hands
//! over the retained documents it gets when it subscribes to the state topics at start; a node
//! one of them shows `online` that this run has not heard by the time a node would have been
//! declared lost (the health period times `lost_after + 1`, counted from start; later while the
//! gateway's own bus is down) gets its document republished `online: false`, without connections:
//! the same document a `node_lost` leaves. No `node_lost` event goes out (this run never heard the
//! node). A node heard in time publishes its own document as usual.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use ihex_proto::NodeId;

use crate::event::NodeState;

/// Documents of nodes this run has not heard yet, and when they count as lost.
#[derive(Debug)]
pub(super) struct Inherited {
    deadline: Instant,
    period: Duration,
    docs: BTreeMap<NodeId, NodeState>,
}

impl Inherited {
    /// A run started at `now`, whose nodes are lost after `lost_after` missed health checks of
    /// `period`.
    pub(super) fn new(period: Duration, lost_after: u32, now: Instant) -> Self {
        Inherited {
            deadline: now + period * lost_after.saturating_add(1),
            period,
            docs: BTreeMap::new(),
        }
    }

    /// A retained document of `id` from the broker; `known`: this run has heard the node (its own
    /// document replaces the old one). Only a document saying `online` needs an answer.
    pub(super) fn on_retained(&mut self, id: NodeId, payload: &[u8], known: bool) {
        if known {
            return;
        }
        match serde_json::from_slice::<NodeState>(payload) {
            Ok(doc) if doc.online && doc.id.0 == id => {
                self.docs.insert(id, doc);
            }
            Ok(_) => {}
            // Empty (a cleared topic) or not a state document: nothing to correct.
            Err(e) => tracing::debug!(node = %id, error = %e, "retained state document not read"),
        }
    }

    /// When [`Inherited::take_lost`] must run next.
    pub(super) fn next_deadline(&self) -> Option<Instant> {
        (!self.docs.is_empty()).then_some(self.deadline)
    }

    /// The documents to republish offline at `now`: of nodes still not heard (`known` false) once
    /// the deadline passed. While `bus_down` nobody can be heard: the deadline moves on.
    pub(super) fn take_lost(
        &mut self,
        now: Instant,
        bus_down: bool,
        known: impl Fn(NodeId) -> bool,
    ) -> Vec<NodeState> {
        self.docs.retain(|&id, _| !known(id));
        if self.docs.is_empty() || now < self.deadline {
            return Vec::new();
        }
        if bus_down {
            self.deadline = now + self.period;
            return Vec::new();
        }
        std::mem::take(&mut self.docs)
            .into_values()
            .map(|mut doc| {
                doc.online = false;
                doc.connections.clear();
                doc
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::*;
    use super::super::*;
    use ihex_proto::Packet;
    use serde_json::{json, Value};

    /// A retained document as an earlier run published it.
    fn old_doc(id: &str, online: bool) -> Vec<u8> {
        json!({
            "id": id, "online": online, "role": "mobile", "ports": 6, "version": "1.2",
            "led": {"mode": "steady", "color": "#ff0000", "brightness": 255},
            "buzzer": {"mode": "off"}, "relay": false, "loops": [0],
            "connections": [{"port": 0, "peer": "111", "peer_port": 3}],
            "last_seen_ms": 12, "first_seen_ms": 5000
        })
        .to_string()
        .into_bytes()
    }

    #[test]
    fn an_old_online_document_of_a_node_not_heard_is_republished_offline_once() {
        let (mut b, t0) = with_nodes(&[0x111]);
        drain(&mut b);
        b.handle_retained_state(id(2), &old_doc("2", true), t0);
        // Offline already in the old run: nothing to correct.
        b.handle_retained_state(id(3), &old_doc("3", false), t0);
        // Heard by this run: its own document counts.
        b.handle_retained_state(id(0x111), &old_doc("111", true), t0);
        let lost_after = BridgeConfig::default().lost_after_misses;
        let lost_at = t0 + S * (lost_after + 1);
        assert!(b.poll_timeout() <= lost_at);
        for k in 1..=lost_after {
            b.handle_timeout(t0 + S * k);
            b.handle_packet(Packet::report(id(0x111), reply(k as u8, 0)), t0 + S * k);
        }
        b.handle_timeout(lost_at - MS);
        assert!(drain(&mut b).states.iter().all(|(i, _)| *i != id(2)));
        b.handle_timeout(lost_at);
        let out = drain(&mut b);
        let docs: Vec<&Value> = out
            .states
            .iter()
            .filter(|(i, _)| *i == id(2))
            .map(|(_, d)| d)
            .collect();
        assert_eq!(docs.len(), 1, "{:?}", out.states);
        assert_eq!(docs[0]["online"], false);
        assert_eq!(docs[0]["connections"], json!([]));
        assert_eq!(docs[0]["led"]["color"], "#ff0000", "the rest as it was");
        assert!(out.states.iter().all(|(i, _)| *i != id(3)));
        assert!(out.named("node_lost").is_empty());
        b.handle_timeout(lost_at + S);
        assert!(drain(&mut b).states.iter().all(|(i, _)| *i != id(2)));
    }

    #[test]
    fn a_node_heard_before_the_deadline_keeps_its_own_document() {
        let (mut b, t0) = with_nodes(&[]);
        b.handle_retained_state(id(2), &old_doc("2", true), t0);
        b.handle_packet(Packet::report(id(2), reply(0, 0)), t0 + S);
        b.handle_timeout(t0 + 10 * S);
        let out = drain(&mut b);
        assert!(out
            .states
            .iter()
            .filter(|(i, _)| *i == id(2))
            .all(|(_, d)| d["online"] == true));
    }

    #[test]
    fn while_our_bus_is_down_nobody_is_declared_lost() {
        let (mut b, t0) = with_nodes(&[]);
        b.handle_retained_state(id(2), &old_doc("2", true), t0);
        b.handle_bus_event(BusEvent::InterfaceDown, t0);
        b.handle_timeout(t0 + 10 * S);
        assert!(drain(&mut b).states.is_empty());
        b.handle_bus_event(BusEvent::Recovered, t0 + 10 * S);
        b.handle_timeout(t0 + 11 * S);
        let out = drain(&mut b);
        assert_eq!(out.states.len(), 1);
        assert_eq!(out.states[0].1["online"], false);
        // Garbage or an empty (cleared) topic is no document.
        b.handle_retained_state(id(4), b"", t0 + 11 * S);
        b.handle_retained_state(id(4), b"{not json", t0 + 11 * S);
        b.handle_timeout(t0 + 20 * S);
        assert!(drain(&mut b).states.is_empty());
    }
}
