//! State read-back (protocol 1.1): which nodes the bridge asks for their whole state, when, and
//! what it does with the answer. A node is asked (`StateQuery` for every group, one node at a time
//! per node, at most [`MAX_QUERIES`] nodes at once) whenever the bridge is unsure of it: first
//! heard, back after `node_lost`, booted, after a command to it timed out, and every node after the
//! bus came back. Its reply — one `StateReport` per part, closed by `End` with the number of parts —
//! is collected here; a complete reply is applied by the bridge (registry and docking record).
//!
//! A node that does not answer (protocol 1.0: it refuses the unknown kind with a `BadFrame` fault,
//! or stays silent) is asked [`SILENT_LIMIT`] times at most and then not again until it boots with
//! a newer protocol: its state documents keep showing what it acknowledged and reported in its
//! health replies, as before read-back existed. A reply with a part missing is asked again, up to
//! [`INCOMPLETE_LIMIT`] times in a row.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use ihex_proto::{Message, NodeId, Packet, Seq, StateParts, StateReport};

use super::output::Outputs;

/// Nodes asked at the same time (each reply is up to 16 frames).
pub const MAX_QUERIES: usize = 4;
/// Queries in a row without an answer after which a node is taken for one that cannot answer.
pub const SILENT_LIMIT: u32 = 3;
/// Replies in a row with a part missing after which the bridge stops asking until next time.
pub const INCOMPLETE_LIMIT: u32 = 3;
/// Most parts kept of one reply (a full reply has 15 and its `End`).
const MAX_PARTS: usize = 32;

/// The protocol version that introduced read-back and dock links.
pub const READ_BACK_VERSION: (u8, u8) = (1, 1);

/// A complete reply.
#[derive(Debug)]
pub(super) struct Reply {
    /// Who answered.
    pub(super) node: NodeId,
    /// The groups answered.
    pub(super) parts: StateParts,
    /// The parts, in the order they came (without `End`).
    pub(super) reports: Vec<StateReport>,
    /// When the question was sent: anything the bridge learnt after it is newer than the reply.
    pub(super) asked: Instant,
}

#[derive(Debug)]
struct Asking {
    seq: Seq,
    asked: Instant,
    deadline: Instant,
    reports: Vec<StateReport>,
}

#[derive(Debug, Default)]
struct NodeQuery {
    /// The bridge is unsure of this node: ask when possible.
    due: bool,
    asking: Option<Asking>,
    silent: u32,
    incomplete: u32,
    /// It cannot answer (protocol 1.0): not asked until it boots with a newer protocol.
    unsupported: bool,
}

/// Every node's read-back.
#[derive(Debug)]
pub(super) struct ReadBack {
    timeout: Duration,
    seq: Seq,
    nodes: BTreeMap<NodeId, NodeQuery>,
    /// Complete replies applied since start.
    replies: u64,
}

impl ReadBack {
    /// `timeout`: how long a reply may take before the question counts as unanswered.
    pub(super) fn new(timeout: Duration) -> Self {
        ReadBack {
            timeout,
            seq: 0,
            nodes: BTreeMap::new(),
            replies: 0,
        }
    }

    /// The bridge is unsure of `id`: ask it (unless it cannot answer).
    pub(super) fn want(&mut self, id: NodeId) {
        let q = self.nodes.entry(id).or_default();
        if !q.unsupported {
            q.due = true;
        }
    }

    /// False for a node known not to understand read-back or dock links.
    pub(super) fn supports(&self, id: NodeId) -> bool {
        !self.nodes.get(&id).is_some_and(|q| q.unsupported)
    }

    /// `id` booted announcing protocol `version`: asked if it can answer, never otherwise.
    pub(super) fn on_boot(&mut self, id: NodeId, version: (u8, u8)) {
        let q = self.nodes.entry(id).or_default();
        q.asking = None;
        q.silent = 0;
        q.incomplete = 0;
        q.unsupported = version < READ_BACK_VERSION;
        q.due = !q.unsupported;
    }

    /// `id` was lost: a question in flight is void; it is asked again when it is back.
    pub(super) fn on_lost(&mut self, id: NodeId) {
        if let Some(q) = self.nodes.get_mut(&id) {
            if q.asking.take().is_some() {
                q.due = !q.unsupported;
            }
        }
    }

    /// `id` refused a frame of a read-back kind as unknown (`BadFrame`): it speaks protocol 1.0.
    pub(super) fn on_unknown_kind(&mut self, id: NodeId) {
        let q = self.nodes.entry(id).or_default();
        if !q.unsupported {
            tracing::info!(node = %id, "node does not know state read-back (protocol 1.0?): its state documents show what it acknowledged and reports");
        }
        q.unsupported = true;
        q.due = false;
        q.asking = None;
    }

    /// A part of a reply from `src`; the complete reply when this was its `End`.
    pub(super) fn on_report(&mut self, src: NodeId, report: StateReport) -> Option<Reply> {
        let q = self.nodes.get_mut(&src)?;
        let asking = q.asking.as_mut()?;
        let StateReport::End { seq, parts, count } = report else {
            if asking.reports.len() < MAX_PARTS {
                asking.reports.push(report);
            }
            return None;
        };
        if seq != asking.seq {
            // The end of an older reply: what was collected belongs to it.
            asking.reports.clear();
            return None;
        }
        let asking = q.asking.take()?;
        q.silent = 0;
        q.unsupported = false;
        if usize::from(count) != asking.reports.len() {
            q.incomplete += 1;
            q.due = q.incomplete < INCOMPLETE_LIMIT;
            tracing::debug!(node = %src, count, got = asking.reports.len(), "state reply with parts missing");
            return None;
        }
        q.incomplete = 0;
        self.replies += 1;
        Some(Reply {
            node: src,
            parts,
            reports: asking.reports,
            asked: asking.asked,
        })
    }

    /// Questions without an answer in time count as silence; asked again, up to the limit.
    pub(super) fn expire(&mut self, now: Instant) {
        for (id, q) in &mut self.nodes {
            if q.asking.as_ref().is_some_and(|a| a.deadline <= now) {
                q.asking = None;
                q.silent += 1;
                if q.silent >= SILENT_LIMIT {
                    tracing::info!(node = %id, "node does not answer state queries; not asking again until it boots");
                    q.unsupported = true;
                    q.due = false;
                } else {
                    q.due = true;
                }
            }
        }
    }

    /// Sends the questions that are due to nodes that are `online`, at most [`MAX_QUERIES`] at
    /// once.
    pub(super) fn poll(
        &mut self,
        online: impl Fn(NodeId) -> bool,
        now: Instant,
        out: &mut Outputs,
    ) {
        let mut asking = self.nodes.values().filter(|q| q.asking.is_some()).count();
        let mut next_seq = self.seq;
        for (&id, q) in &mut self.nodes {
            if asking >= MAX_QUERIES {
                break;
            }
            if !q.due || q.asking.is_some() || !online(id) {
                continue;
            }
            let seq = next_seq;
            next_seq = seq.wrapping_add(1);
            q.due = false;
            q.asking = Some(Asking {
                seq,
                asked: now,
                deadline: now + self.timeout,
                reports: Vec::new(),
            });
            asking += 1;
            out.send(Packet::command(
                id,
                Message::StateQuery {
                    seq,
                    parts: StateParts::ALL,
                },
            ));
        }
        self.seq = next_seq;
    }

    /// When the earliest question in flight counts as unanswered.
    pub(super) fn next_deadline(&self) -> Option<Instant> {
        self.nodes
            .values()
            .filter_map(|q| q.asking.as_ref().map(|a| a.deadline))
            .min()
    }

    /// True while a question is due or in flight for `id`.
    pub(super) fn pending(&self, id: NodeId) -> bool {
        self.nodes
            .get(&id)
            .is_some_and(|q| q.due || q.asking.is_some())
    }

    /// Complete replies applied since start.
    pub(super) fn replies(&self) -> u64 {
        self.replies
    }
}
