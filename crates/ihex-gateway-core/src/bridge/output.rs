//! What the bridge hands to the adapters, and what gives when they cannot keep up.
//!
//! Frames: a bounded queue of frames not yet handed to the adapter, in front of a small window of
//! frames handed to it and not yet confirmed on the bus (its echo, or its failure). A frame is
//! handed out only while the window has room, so a command waiting for the bus waits *here*, where
//! it can still be withdrawn when its deadline passes; at most [`TRANSMIT_WINDOW`] frames are ever
//! beyond recall.
//!
//! Publications, by class: *answers* (`command_result`, `command_rejected`, `node_list`, and the
//! `publications_dropped` report) are never dropped — the adapter stops taking commands instead
//! ([`super::Bridge::wants_commands`]); *retained state documents* are coalesced, one entry per node
//! whose document is built when it is taken, so the latest is always published and none is ever
//! dropped; *other events* wait in a queue of `event_queue` entries whose oldest is dropped and
//! counted when it is full. Home Assistant's discovery configs and light states, and emptied
//! retained topics, are kept like answers. The adapter serialises a publication exactly once
//! ([`PayloadWriter`]) and sends it on [`Publication::topic`].

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Instant;

use bytes::{Bytes, BytesMut};
use ihex_proto::{NodeId, Packet};

use crate::event::{self, Event, NodeState};
use crate::ha::HaPublication;
use crate::json_writer;
use crate::topic::Topic;

/// Frames handed to the adapter and not yet confirmed sent or failed: the most that can still
/// reach the bus after their command was answered (a CAN controller and the kernel's queue keep
/// a frame until the bus takes it).
pub const TRANSMIT_WINDOW: usize = 8;

/// Commands are taken while fewer than `1 / COMMAND_SHARE` of the transmit queue's frames wait
/// (see [`super::Bridge::wants_commands`]).
pub const COMMAND_SHARE: usize = 2;

/// Answers waiting for the adapter beyond which [`super::Bridge::wants_commands`] says no.
pub const ANSWER_BACKLOG: usize = 256;

/// One message for MQTT, as a Rust value: an event, or a node's retained state document.
#[derive(Clone, PartialEq, Debug)]
pub enum Publication {
    /// A JSON event for [`Topic::Events`] (not retained).
    Event(Event),
    /// A node's state document for [`Topic::NodeState`] (retained).
    State(NodeState),
    /// A Home Assistant discovery config or light state for [`Topic::Ha`] (retained).
    Ha(HaPublication),
    /// The leases document for [`Topic::Leases`] (retained).
    Leases(crate::lease::LeasesDocument),
    /// The running procedures document for [`Topic::Procedures`] (retained).
    Procedures(crate::procedure::ProceduresDocument),
    /// An empty retained message: the broker drops what the topic held (a forgotten node's state
    /// document, Home Assistant device and light state).
    Cleared(Topic),
}

impl Publication {
    /// Where it goes.
    pub fn topic(&self) -> Topic {
        match self {
            Publication::Event(_) => Topic::Events,
            Publication::State(s) => Topic::NodeState(s.id.0),
            Publication::Ha(h) => Topic::Ha(h.topic()),
            Publication::Leases(_) => Topic::Leases,
            Publication::Procedures(_) => Topic::Procedures,
            Publication::Cleared(t) => *t,
        }
    }

    /// Retained (everything but events) or not (events).
    pub fn retain(&self) -> bool {
        !matches!(self, Publication::Event(_))
    }

    /// Appends what is published to `out`: compact JSON (`{"event":…,"payload":…}`, the state
    /// document, a Home Assistant config or light state), or nothing for [`Publication::Cleared`].
    pub fn write_payload(&self, out: &mut BytesMut) {
        match self {
            // The two publications of every answered command: written by hand, the same bytes.
            Publication::Event(Event::CommandResult(r)) => {
                json_writer::write_command_result(r, out)
            }
            Publication::Event(e) => event::write_json(e, out),
            Publication::State(s) => json_writer::write_node_state(s, out),
            Publication::Ha(h) => h.write_payload(out),
            Publication::Leases(l) => event::write_json(l, out),
            Publication::Procedures(p) => event::write_json(p, out),
            Publication::Cleared(_) => {}
        }
    }

    /// What is published, as text.
    pub fn to_json(&self) -> String {
        let mut out = BytesMut::new();
        self.write_payload(&mut out);
        String::from_utf8(out.into()).unwrap_or_default()
    }
}

/// Writes publications' text into shared chunks of memory: one allocation per 16 KiB of text
/// instead of one per publication, and no room reserved beyond the text. A chunk is freed
/// (or written again) once every publication in it was dropped, i.e. acknowledged by the broker.
#[derive(Debug, Default)]
pub struct PayloadWriter {
    chunk: BytesMut,
}

/// Bytes of publication text allocated at a time.
const CHUNK: usize = 16 * 1024;

impl PayloadWriter {
    /// The text [`Publication::write_payload`] writes, as bytes that share this writer's chunk.
    pub fn write(&mut self, publication: &Publication) -> Bytes {
        // Room for the largest frequent publication (a state document) without growing mid-way,
        // which would copy the text written so far.
        if self.chunk.capacity() < CHUNK / 16 {
            self.chunk.reserve(CHUNK);
        }
        publication.write_payload(&mut self.chunk);
        self.chunk.split().freeze()
    }
}

/// A frame to transmit, with the latest moment it may still be written to the bus.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Transmit {
    /// The frame.
    pub packet: Packet,
    /// A command's frame must not be written after this (its command was answered `expired` or
    /// `failed` by then): the adapter reports it with [`super::Bridge::handle_withdrawn`] instead.
    /// `None` for frames without a deadline (health checks, docking).
    pub not_after: Option<Instant>,
    /// The concern that queued it.
    pub owner: FrameOwner,
}

/// What became of a frame the bridge queued, as its owner is told.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(crate) enum FrameFate<'a> {
    /// It went on the bus (its echo, or the adapter wrote it).
    Transmitted,
    /// The adapter did not write it: its deadline had passed.
    Withdrawn,
    /// It could not be sent, for this reason.
    Failed(&'a str),
    /// Handed out and never confirmed (why): it may or may not reach the bus.
    Unconfirmed(&'static str),
}

/// The concern that queued a frame: its echo, withdrawal, failure or lack of confirmation goes
/// back to it, routed by one `match` on this tag in the bridge. A new concern that sends frames
/// adds its variant here, and the compiler asks for its arm there.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum FrameOwner {
    /// A command from the JSON API or Home Assistant (for `assign`, its select and its commit).
    Command,
    /// The docking sequence: confirms, refusals, relay off, dock links.
    Docking,
    /// A guided procedure's lights and beeps.
    Procedure,
    /// The broadcast health check.
    HealthCheck,
    /// A state query of the read-back.
    ReadBack,
    /// A firmware update's frame.
    FwUpdate,
}

/// How publications fared since start, and what waits now.
#[derive(Clone, PartialEq, Eq, Debug, Default)]
pub struct PublicationCounters {
    /// Events taken by the adapter (answers included).
    pub events: u64,
    /// State documents taken by the adapter.
    pub states: u64,
    /// Events dropped because the event queue was full (never answers or state documents).
    pub dropped: u64,
    /// Dropped events by name.
    pub dropped_by_event: BTreeMap<&'static str, u64>,
    /// Answers waiting now.
    pub answers_waiting: usize,
    /// Other events waiting now.
    pub events_waiting: usize,
    /// Nodes whose state document waits to be published now.
    pub states_waiting: usize,
}

/// The next publication in order: an event, a publication that is kept whatever the load, or a
/// node whose state document is to be built now.
pub(crate) enum Next {
    Event(Event),
    Kept(Publication),
    State { id: NodeId, forced: bool },
}

/// The publication queues: answers, coalesced state documents, other events; taken in the order
/// they were first queued.
#[derive(Debug)]
pub(crate) struct PublishQueue {
    stamp: u64,
    answers: VecDeque<(u64, Event)>,
    /// Home Assistant's retained configs and light states, and emptied retained topics: as few as
    /// the island has elements, and dropping one would leave a retained topic wrong.
    kept: VecDeque<(u64, Publication)>,
    events: VecDeque<(u64, Event)>,
    states: VecDeque<(u64, NodeId)>,
    /// Per node ID, whether it has an entry in `states` ([`QUEUED`]) and whether that must be
    /// published even if unchanged ([`FORCED`]): a flat table, because every frame from a node
    /// queues its document (4 KiB, where a map cost a search and a rebalance per frame).
    queued: Vec<u8>,
    event_cap: usize,
    counters: PublicationCounters,
    /// Drops not reported by a `publications_dropped` event yet, by event name.
    unreported: BTreeMap<&'static str, u64>,
}

/// [`PublishQueue::queued`]: the node's document is queued.
const QUEUED: u8 = 1;
/// [`PublishQueue::queued`]: the queued document goes out even if unchanged.
const FORCED: u8 = 2;

/// Events that answer a command (or an upload, or end an update a client waits for): never
/// dropped.
fn is_answer(e: &Event) -> bool {
    matches!(
        e,
        Event::CommandResult(_)
            | Event::CommandRejected(_)
            | Event::NodeList(_)
            | Event::PublicationsDropped(_)
            | Event::FwUpload(_)
            | Event::FwReport(_)
            | Event::FwCorrection(_)
            | Event::LeaseGranted(_)
            | Event::LeaseEnded(_)
    )
}

impl PublishQueue {
    pub(crate) fn new(event_cap: usize) -> Self {
        PublishQueue {
            stamp: 0,
            answers: VecDeque::new(),
            kept: VecDeque::new(),
            events: VecDeque::new(),
            states: VecDeque::new(),
            queued: vec![0; usize::from(NodeId::MAX_RAW) + 1],
            event_cap: event_cap.max(1),
            counters: PublicationCounters::default(),
            unreported: BTreeMap::new(),
        }
    }

    fn next_stamp(&mut self) -> u64 {
        self.stamp += 1;
        self.stamp
    }

    pub(crate) fn push_event(&mut self, event: Event) {
        let stamp = self.next_stamp();
        if is_answer(&event) {
            self.answers.push_back((stamp, event));
            return;
        }
        if self.events.len() >= self.event_cap {
            if let Some((_, old)) = self.events.pop_front() {
                let name = old.name();
                self.counters.dropped += 1;
                *self.counters.dropped_by_event.entry(name).or_default() += 1;
                *self.unreported.entry(name).or_default() += 1;
                // One line per power of two keeps a long overload from flooding the log.
                if self.counters.dropped.is_power_of_two() {
                    tracing::warn!(
                        publications_dropped = self.counters.dropped,
                        event = name,
                        queue = self.event_cap,
                        "event queue full: oldest event dropped (answers and state documents are kept)"
                    );
                }
            }
        }
        self.events.push_back((stamp, event));
    }

    /// Queues a publication that is never dropped, after everything queued before it.
    pub(crate) fn push_kept(&mut self, publication: Publication) {
        let stamp = self.next_stamp();
        self.kept.push_back((stamp, publication));
    }

    /// Queues publications that follow the one just taken, ahead of everything else.
    pub(crate) fn push_kept_next(
        &mut self,
        publications: impl DoubleEndedIterator<Item = Publication>,
    ) {
        for p in publications.rev() {
            self.kept.push_front((0, p));
        }
    }

    /// Queues `id`'s state document (built when taken); `forced` publishes it even if unchanged.
    pub(crate) fn push_state(&mut self, id: NodeId, forced: bool) {
        let flags = &mut self.queued[usize::from(id.get())];
        let was = *flags;
        *flags |= QUEUED | if forced { FORCED } else { 0 };
        if was & QUEUED == 0 {
            let stamp = self.next_stamp();
            self.states.push_back((stamp, id));
        }
    }

    pub(crate) fn pop(&mut self) -> Option<Next> {
        let head = |q: &VecDeque<(u64, Event)>| q.front().map_or(u64::MAX, |(s, _)| *s);
        let a = head(&self.answers);
        let e = head(&self.events);
        let s = self.states.front().map_or(u64::MAX, |(s, _)| *s);
        let k = self.kept.front().map_or(u64::MAX, |(s, _)| *s);
        if a == u64::MAX && e == u64::MAX && s == u64::MAX && k == u64::MAX {
            return None;
        }
        if k <= a && k <= e && k <= s {
            let (_, p) = self.kept.pop_front()?;
            return Some(Next::Kept(p));
        }
        if s < a && s < e {
            let (_, id) = self.states.pop_front()?;
            let forced = std::mem::take(&mut self.queued[usize::from(id.get())]) & FORCED != 0;
            return Some(Next::State { id, forced });
        }
        let (_, event) = if a < e {
            self.answers.pop_front()?
        } else {
            self.events.pop_front()?
        };
        self.counters.events += 1;
        Some(Next::Event(event))
    }

    pub(crate) fn count_state(&mut self) {
        self.counters.states += 1;
    }

    pub(crate) fn waiting(&self) -> bool {
        !(self.answers.is_empty()
            && self.kept.is_empty()
            && self.events.is_empty()
            && self.states.is_empty())
    }

    pub(crate) fn answers_waiting(&self) -> usize {
        self.answers.len()
    }

    pub(crate) fn counters(&self) -> PublicationCounters {
        PublicationCounters {
            answers_waiting: self.answers.len(),
            events_waiting: self.events.len(),
            states_waiting: self.states.len(),
            ..self.counters.clone()
        }
    }

    /// True when drops wait to be reported.
    pub(crate) fn has_unreported(&self) -> bool {
        !self.unreported.is_empty()
    }

    /// The drops since the last report, by name, and their sum; clears them.
    pub(crate) fn take_unreported(&mut self) -> (u64, BTreeMap<String, u64>) {
        let by_name = std::mem::take(&mut self.unreported);
        let n = by_name.values().sum();
        (
            n,
            by_name
                .into_iter()
                .map(|(k, v)| (k.to_owned(), v))
                .collect(),
        )
    }

    pub(crate) fn total_dropped(&self) -> u64 {
        self.counters.dropped
    }
}

/// A frame waiting in the bridge.
#[derive(Clone, Copy, Debug)]
struct Queued {
    packet: Packet,
    not_after: Option<Instant>,
    owner: FrameOwner,
}

/// A frame handed to the adapter, waiting for its echo or failure.
#[derive(Clone, Copy, Debug)]
struct InFlight {
    packet: Packet,
    /// When it was handed out.
    handed: Instant,
    owner: FrameOwner,
}

/// Frames not yet handed to the adapter, and those handed and not yet confirmed.
#[derive(Debug)]
pub(crate) struct TransmitQueue {
    queue: VecDeque<Queued>,
    cap: usize,
    /// Handed to the adapter, waiting for its echo or failure.
    in_flight: Vec<InFlight>,
    /// Frames refused because the queue was full: the bridge reports them as failed sends.
    refused: Vec<(Packet, FrameOwner)>,
}

impl TransmitQueue {
    pub(crate) fn new(cap: usize) -> Self {
        TransmitQueue {
            queue: VecDeque::new(),
            cap: cap.max(1),
            in_flight: Vec::new(),
            refused: Vec::new(),
        }
    }

    /// Queues a frame; when the queue is full it is refused (the bridge then fails it).
    pub(crate) fn push(&mut self, packet: Packet, not_after: Option<Instant>, owner: FrameOwner) {
        if self.queue.len() >= self.cap {
            self.refused.push((packet, owner));
        } else {
            self.queue.push_back(Queued {
                packet,
                not_after,
                owner,
            });
        }
    }

    /// The capacity of the queue.
    pub(crate) fn cap(&self) -> usize {
        self.cap
    }

    /// True while a command's frames may be queued: fewer than [`COMMAND_SHARE`] of the queue's
    /// frames wait. Beyond that the adapter leaves commands with the broker, so commands that
    /// arrive faster than the bus takes them wait there (unacknowledged) instead of filling the
    /// queue and failing; the other part stays free for the frames the bridge sends on its own
    /// (docking, health checks, read-back) and for the second frame of an `assign`.
    pub(crate) fn takes_commands(&self) -> bool {
        self.queue.len() < self.cap.div_ceil(COMMAND_SHARE)
    }

    pub(crate) fn take_refused(&mut self) -> Vec<(Packet, FrameOwner)> {
        std::mem::take(&mut self.refused)
    }

    /// The next frame, if the window has room; `Err` with the frame when its deadline passed (it
    /// stays queued for the caller to withdraw).
    pub(crate) fn pop(&mut self, now: Instant) -> Option<Result<Transmit, Packet>> {
        if self.in_flight.len() >= TRANSMIT_WINDOW {
            return None;
        }
        let q = *self.queue.front()?;
        if q.not_after.is_some_and(|d| d <= now) {
            return Some(Err(q.packet));
        }
        self.queue.pop_front();
        self.in_flight.push(InFlight {
            packet: q.packet,
            handed: now,
            owner: q.owner,
        });
        Some(Ok(Transmit {
            packet: q.packet,
            not_after: q.not_after,
            owner: q.owner,
        }))
    }

    /// Removes a queued frame equal to `packet`; true if there was one.
    pub(crate) fn withdraw(&mut self, packet: &Packet) -> bool {
        match self.queue.iter().position(|q| q.packet == *packet) {
            Some(i) => {
                self.queue.remove(i);
                true
            }
            None => false,
        }
    }

    /// Frames ahead of `packet` in the queue (all of them if it is not queued).
    pub(crate) fn ahead_of(&self, packet: &Packet) -> usize {
        self.queue
            .iter()
            .position(|q| q.packet == *packet)
            .unwrap_or(self.queue.len())
    }

    /// The frame's fate is known (echoed, withdrawn, failed): its place in the window is free.
    /// Its owner if it was in the window.
    pub(crate) fn release(&mut self, packet: &Packet) -> Option<FrameOwner> {
        let i = self.in_flight.iter().position(|f| f.packet == *packet)?;
        Some(self.in_flight.swap_remove(i).owner)
    }

    /// Frames in the window handed out at or before `cutoff`: removed and returned.
    pub(crate) fn expire_in_flight(&mut self, cutoff: Instant) -> Vec<(Packet, FrameOwner)> {
        let mut gone = Vec::new();
        self.in_flight.retain(|f| {
            let keep = f.handed > cutoff;
            if !keep {
                gone.push((f.packet, f.owner));
            }
            keep
        });
        gone
    }

    /// Every frame in the window: removed and returned (the interface went down).
    pub(crate) fn clear_in_flight(&mut self) -> Vec<(Packet, FrameOwner)> {
        self.in_flight
            .drain(..)
            .map(|f| (f.packet, f.owner))
            .collect()
    }

    /// When the oldest frame in the window was handed out.
    pub(crate) fn oldest_in_flight(&self) -> Option<Instant> {
        self.in_flight.iter().map(|f| f.handed).min()
    }

    /// The earliest deadline of a queued frame.
    pub(crate) fn next_not_after(&self) -> Option<Instant> {
        self.queue.iter().filter_map(|q| q.not_after).min()
    }

    pub(crate) fn queued(&self) -> usize {
        self.queue.len()
    }

    pub(crate) fn in_flight(&self) -> usize {
        self.in_flight.len()
    }
}

/// The bridge's output queues, filled by every concern and drained by the adapters.
#[derive(Debug)]
pub(crate) struct Outputs {
    /// Frames to transmit.
    pub(crate) transmit: TransmitQueue,
    /// Publications.
    pub(crate) publish: PublishQueue,
    /// Nodes whose state document may have changed since it was last published, in any order and
    /// possibly repeated (nearly every frame marks its node: a set would allocate a tree node
    /// per input; the bridge sorts and dedups once per input instead).
    pub(crate) dirty: Vec<NodeId>,
    /// Nodes whose real state the bridge is no longer sure of (a command to them timed out).
    pub(crate) unsure: BTreeSet<NodeId>,
    /// Connections made (`true`) or ended (`false`) since the procedures last saw them.
    pub(crate) dock_changes: Vec<(bool, crate::event::Connection)>,
}

impl Outputs {
    pub(crate) fn new(tx_queue: usize, event_queue: usize) -> Self {
        Outputs {
            transmit: TransmitQueue::new(tx_queue),
            publish: PublishQueue::new(event_queue),
            dirty: Vec::new(),
            unsure: BTreeSet::new(),
            dock_changes: Vec::new(),
        }
    }

    /// Queues a frame of `owner`'s without a deadline.
    pub(crate) fn send(&mut self, packet: Packet, owner: FrameOwner) {
        self.transmit.push(packet, None, owner);
    }

    /// Queues a command's frame that must not be written after `not_after`.
    pub(crate) fn send_until(&mut self, packet: Packet, not_after: Instant) {
        self.transmit
            .push(packet, Some(not_after), FrameOwner::Command);
    }

    /// Queues an event.
    pub(crate) fn emit(&mut self, event: Event) {
        tracing::debug!(event = event.name(), "event");
        self.publish.push_event(event);
    }

    /// Marks a node's state document for publication (if it changed) at the end of the input.
    pub(crate) fn mark_changed(&mut self, id: NodeId) {
        self.dirty.push(id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::event::{BusError, CommandRejected};
    use ihex_proto::test_util::id;

    fn bus_error(n: u64) -> Event {
        Event::BusError(Box::new(BusError {
            error: "rx_dropped".into(),
            count: Some(n),
            ..BusError::default()
        }))
    }

    fn rejected(n: u32) -> Event {
        Event::CommandRejected(CommandRejected {
            request_id: Some(n.to_string()),
            reason: "x".into(),
            origin: None,
        })
    }

    #[test]
    fn answers_are_kept_states_coalesced_events_shed_oldest_first() {
        let mut q = PublishQueue::new(2);
        for n in 0..5 {
            q.push_event(bus_error(n));
            q.push_event(rejected(n as u32));
            q.push_state(id(7), false);
        }
        q.push_state(id(8), true);
        q.push_state(id(7), true);
        let c = q.counters();
        assert_eq!(
            (
                c.dropped,
                c.answers_waiting,
                c.events_waiting,
                c.states_waiting
            ),
            (3, 5, 2, 2)
        );
        assert_eq!(c.dropped_by_event.get("bus_error"), Some(&3));
        let mut order = Vec::new();
        while let Some(n) = q.pop() {
            order.push(match n {
                Next::Event(Event::BusError(b)) => format!("e{}", b.count.unwrap()),
                Next::Event(Event::CommandRejected(r)) => format!("a{}", r.request_id.unwrap()),
                Next::Event(e) => panic!("{e:?}"),
                Next::Kept(p) => panic!("{p:?}"),
                Next::State { id, forced } => format!("s{id}{}", if forced { "!" } else { "" }),
            });
        }
        // Node 7's one entry keeps its first place and became forced; the kept events are the newest.
        assert_eq!(
            order,
            ["a0", "s7!", "a1", "a2", "e3", "a3", "e4", "a4", "s8!"]
        );
        let (n, by) = q.take_unreported();
        assert_eq!((n, by.get("bus_error")), (3, Some(&3)));
        assert!(!q.has_unreported());
    }

    #[test]
    fn kept_publications_keep_their_order_and_follow_ups_go_next() {
        let mut q = PublishQueue::new(1);
        let cleared = |n| Publication::Cleared(Topic::NodeState(id(n)));
        q.push_kept(cleared(1));
        q.push_state(id(2), true);
        for n in 0..3 {
            q.push_event(bus_error(n));
        }
        q.push_kept(cleared(3));
        let mut order = Vec::new();
        while let Some(n) = q.pop() {
            order.push(match n {
                Next::Kept(Publication::Cleared(Topic::NodeState(n))) => format!("k{n}"),
                Next::Kept(p) => panic!("{p:?}"),
                Next::Event(Event::BusError(b)) => format!("e{}", b.count.unwrap()),
                Next::Event(e) => panic!("{e:?}"),
                Next::State { id, .. } => {
                    // What follows a document goes out before anything queued earlier.
                    q.push_kept_next([cleared(8), cleared(9)].into_iter());
                    format!("s{id}")
                }
            });
        }
        assert_eq!(
            order,
            ["k1", "s2", "k8", "k9", "e2", "k3"],
            "kept ones are never shed, even past the event queue's size"
        );
        assert_eq!(q.counters().dropped, 2);
    }

    #[test]
    fn transmit_window_bounds_frames_beyond_recall() {
        use ihex_proto::Message;
        let t0 = Instant::now();
        let mut t = TransmitQueue::new(3);
        let frame = |seq| Packet::command(id(2), Message::Identify { seq, seconds: 1 });
        for seq in 0..(TRANSMIT_WINDOW as u8 + 4) {
            t.push(frame(seq), None, FrameOwner::Command);
        }
        assert_eq!(t.queued(), 3);
        assert_eq!(t.take_refused().len(), TRANSMIT_WINDOW + 1);
        let mut t = TransmitQueue::new(64);
        for seq in 0..(TRANSMIT_WINDOW as u8 + 2) {
            t.push(frame(seq), None, FrameOwner::Command);
        }
        for _ in 0..TRANSMIT_WINDOW {
            assert!(matches!(t.pop(t0), Some(Ok(_))));
        }
        assert!(t.pop(t0).is_none(), "the window is full");
        assert_eq!(t.release(&frame(0)), Some(FrameOwner::Command));
        assert_eq!(t.release(&frame(0)), None, "released once");
        assert_eq!(
            t.pop(t0).unwrap().unwrap().packet,
            frame(TRANSMIT_WINDOW as u8)
        );
        // A frame past its deadline is not handed out; it waits to be withdrawn.
        let late = frame(200);
        let mut t = TransmitQueue::new(4);
        t.push(late, Some(t0), FrameOwner::Command);
        assert_eq!(t.pop(t0), Some(Err(late)));
        assert!(t.withdraw(&late));
        assert!(t.pop(t0).is_none());
    }

    #[test]
    fn payload_writer_gives_each_publication_its_text_alone() {
        let mut w = PayloadWriter::default();
        // Kept alive, as publications waiting for the broker's ack are: many chunks fill up.
        let mut kept = Vec::new();
        for n in 0..(2 * CHUNK / 40) as u32 {
            let p = Publication::Event(rejected(n));
            let bytes = w.write(&p);
            assert_eq!(bytes, p.to_json().as_bytes(), "publication {n}");
            kept.push((p, bytes));
        }
        let (a, b) = (&kept[0].1, &kept[1].1);
        assert_eq!(
            a.as_ptr().wrapping_add(a.len()),
            b.as_ptr(),
            "one chunk, no room left between two texts"
        );
        // Larger than a chunk: grows in one piece.
        let big = Publication::Event(Event::CommandRejected(CommandRejected {
            request_id: None,
            reason: "y".repeat(3 * CHUNK),
            origin: None,
        }));
        let bytes = w.write(&big);
        assert_eq!(bytes, big.to_json().as_bytes());
        assert_eq!(w.write(&Publication::Cleared(Topic::Events)), "");
        for (p, bytes) in &kept {
            assert_eq!(
                bytes,
                p.to_json().as_bytes(),
                "not overwritten by later text"
            );
        }
    }
}
