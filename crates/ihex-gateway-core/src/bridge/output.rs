//! What the bridge hands to the adapters: frames to transmit, and publications (events and retained
//! node state documents) as typed values, each queue in the order the bridge produced it. The
//! adapter serialises a publication exactly once ([`Publication::to_json`]) and sends it on
//! [`Publication::topic`].

use std::collections::{BTreeSet, VecDeque};

use ihex_proto::{NodeId, Packet};

use crate::event::{self, Event, NodeState};

/// Logical MQTT topics; the adapter maps them to names under the island prefix
/// ([`crate::topic::Topics::resolve`]).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum Topic {
    /// `EventsTopic`: every JSON event.
    Events,
    /// The retained state document of one node.
    NodeState(NodeId),
}

/// One message for MQTT, as a Rust value: an event, or a node's retained state document.
#[derive(Clone, PartialEq, Debug)]
pub enum Publication {
    /// A JSON event for [`Topic::Events`] (not retained).
    Event(Event),
    /// A node's state document for [`Topic::NodeState`] (retained).
    State(NodeState),
}

impl Publication {
    /// Where it goes.
    pub fn topic(&self) -> Topic {
        match self {
            Publication::Event(_) => Topic::Events,
            Publication::State(s) => Topic::NodeState(s.id.0),
        }
    }

    /// Retained (state documents) or not (events).
    pub fn retain(&self) -> bool {
        matches!(self, Publication::State(_))
    }

    /// The compact JSON text that is published: `{"event":…,"payload":…}` or the state document.
    pub fn to_json(&self) -> String {
        match self {
            Publication::Event(e) => e.to_json(),
            Publication::State(s) => event::to_json(s),
        }
    }
}

/// The bridge's output queues, filled by every concern and drained by the adapters.
#[derive(Debug, Default)]
pub(super) struct Outputs {
    /// Frames to transmit, oldest first.
    pub(super) transmit: VecDeque<Packet>,
    /// Publications, oldest first.
    pub(super) publish: VecDeque<Publication>,
    /// Nodes whose state document may have changed since it was last published.
    pub(super) dirty: BTreeSet<NodeId>,
}

impl Outputs {
    /// Queues a frame.
    pub(super) fn send(&mut self, packet: Packet) {
        self.transmit.push_back(packet);
    }

    /// Queues an event.
    pub(super) fn emit(&mut self, event: Event) {
        tracing::debug!(event = event.name(), "event");
        self.publish.push_back(Publication::Event(event));
    }

    /// Marks a node's state document for publication (if it changed) at the end of the input.
    pub(super) fn touch(&mut self, id: NodeId) {
        self.dirty.insert(id);
    }
}
