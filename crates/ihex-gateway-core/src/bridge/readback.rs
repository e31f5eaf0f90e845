//! State read-back (protocol 1.1): which nodes the bridge asks for their whole state, when, and
//! what it does with the answer. A node is asked (`StateQuery` for every group, one node at a time
//! per node, at most [`MAX_QUERIES`] nodes at once) whenever the bridge is unsure of it: first
//! heard, back after `node_lost`, booted, after a command to it timed out, and every node after the
//! bus came back. Its reply — one `StateReport` per part, closed by `End` with the number of parts —
//! is collected here; a complete reply is applied by the bridge (registry and docking record).
//!
//! A node that does not answer (protocol 1.0: it refuses the unknown kind with a `BadFrame` fault,
//! or stays silent) is asked [`SILENT_LIMIT`] times at most and then not again until it boots with
//! a newer protocol. Only a question the bus confirmed (its echo) counts: the wait for the answer
//! starts there, and a question still in our own transmit path at its deadline is asked again, not
//! held against the node: its state documents keep showing what it acknowledged and reported in its
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
pub(crate) struct Reply {
    /// Who answered.
    pub(crate) node: NodeId,
    /// The groups answered.
    pub(crate) parts: StateParts,
    /// The parts, in the order they came (without `End`).
    pub(crate) reports: Vec<StateReport>,
    /// When the question was sent: anything the bridge learnt after it is newer than the reply.
    pub(crate) asked: Instant,
}

#[derive(Debug)]
struct Asking {
    seq: Seq,
    asked: Instant,
    deadline: Instant,
    /// The bus confirmed the question (until then its silence is not the node's).
    sent: bool,
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
pub(crate) struct ReadBack {
    timeout: Duration,
    seq: Seq,
    nodes: BTreeMap<NodeId, NodeQuery>,
    /// False only when no node is due: [`ReadBack::poll`] runs after every input and would
    /// otherwise walk every node each time. Set by whatever may make a node due, cleared by the
    /// walk that finds none left.
    maybe_due: bool,
    /// Complete replies applied since start.
    replies: u64,
}

impl ReadBack {
    /// `timeout`: how long a reply may take before the question counts as unanswered.
    pub(crate) fn new(timeout: Duration) -> Self {
        ReadBack {
            timeout,
            seq: 0,
            nodes: BTreeMap::new(),
            maybe_due: false,
            replies: 0,
        }
    }

    /// The bridge is unsure of `id`: ask it (unless it cannot answer).
    pub(crate) fn want(&mut self, id: NodeId) {
        let q = self.nodes.entry(id).or_default();
        if !q.unsupported {
            q.due = true;
            self.maybe_due = true;
        }
    }

    /// False for a node known not to understand read-back or dock links.
    pub(crate) fn supports(&self, id: NodeId) -> bool {
        !self.nodes.get(&id).is_some_and(|q| q.unsupported)
    }

    /// `id` booted announcing protocol `version`: asked if it can answer, never otherwise.
    pub(crate) fn on_boot(&mut self, id: NodeId, version: (u8, u8)) {
        let q = self.nodes.entry(id).or_default();
        q.asking = None;
        q.silent = 0;
        q.incomplete = 0;
        q.unsupported = version < READ_BACK_VERSION;
        q.due = !q.unsupported;
        self.maybe_due |= q.due;
    }

    /// `id` was lost: a question in flight is void; it is asked again when it is back.
    pub(crate) fn on_lost(&mut self, id: NodeId) {
        if let Some(q) = self.nodes.get_mut(&id) {
            if q.asking.take().is_some() {
                q.due = !q.unsupported;
                self.maybe_due |= q.due;
            }
        }
    }

    /// The query to `id` never went out (the transmit queue was full, the write failed): not the
    /// node's silence; it is asked again.
    pub(crate) fn on_not_sent(&mut self, id: NodeId) {
        if let Some(q) = self.nodes.get_mut(&id) {
            if q.asking.take().is_some() {
                q.due = !q.unsupported;
                self.maybe_due |= q.due;
            }
        }
    }

    /// The question to `id` is on the bus: the node has the whole timeout from now to answer.
    pub(crate) fn on_transmitted(&mut self, id: NodeId, now: Instant) {
        if let Some(a) = self.nodes.get_mut(&id).and_then(|q| q.asking.as_mut()) {
            if !a.sent {
                a.sent = true;
                a.deadline = a.deadline.max(now + self.timeout);
            }
        }
    }

    /// Our own bus went away: the questions in flight are void, not unanswered (the silence is
    /// ours); they are asked again when it is back.
    pub(crate) fn on_bus_down(&mut self) {
        for q in self.nodes.values_mut() {
            if q.asking.take().is_some() {
                q.due = !q.unsupported;
                self.maybe_due |= q.due;
            }
        }
    }

    /// `id` refused a frame of a read-back kind as unknown (`BadFrame`): it speaks protocol 1.0.
    pub(crate) fn on_unknown_kind(&mut self, id: NodeId) {
        let q = self.nodes.entry(id).or_default();
        if !q.unsupported {
            tracing::info!(node = %id, "node does not know state read-back (protocol 1.0?): its state documents show what it acknowledged and reports");
        }
        q.unsupported = true;
        q.due = false;
        q.asking = None;
    }

    /// A part of a reply from `src`; the complete reply when this was its `End`.
    pub(crate) fn on_report(&mut self, src: NodeId, report: StateReport) -> Option<Reply> {
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
            self.maybe_due |= q.due;
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

    /// Questions without an answer in time count as silence; asked again, up to the limit. One the
    /// bus never confirmed is only asked again.
    pub(crate) fn expire(&mut self, now: Instant) {
        for (id, q) in &mut self.nodes {
            if let Some(a) = q.asking.take_if(|a| a.deadline <= now) {
                if !a.sent {
                    q.due = !q.unsupported;
                    self.maybe_due |= q.due;
                    continue;
                }
                q.silent += 1;
                if q.silent >= SILENT_LIMIT {
                    tracing::info!(node = %id, "node does not answer state queries; not asking again until it boots");
                    q.unsupported = true;
                    q.due = false;
                } else {
                    q.due = true;
                    self.maybe_due = true;
                }
            }
        }
    }

    /// Sends the questions that are due to nodes that are `online`, at most [`MAX_QUERIES`] at
    /// once.
    pub(crate) fn poll(
        &mut self,
        online: impl Fn(NodeId) -> bool,
        now: Instant,
        out: &mut Outputs,
    ) {
        if !self.maybe_due {
            return;
        }
        let mut asking = self.nodes.values().filter(|q| q.asking.is_some()).count();
        let mut still_due = false;
        let mut next_seq = self.seq;
        for (&id, q) in &mut self.nodes {
            if asking >= MAX_QUERIES {
                still_due = true;
                break;
            }
            if !q.due || q.asking.is_some() || !online(id) {
                still_due |= q.due;
                continue;
            }
            let seq = next_seq;
            next_seq = seq.wrapping_add(1);
            q.due = false;
            q.asking = Some(Asking {
                seq,
                asked: now,
                deadline: now + self.timeout,
                sent: false,
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
        self.maybe_due = still_due;
    }

    /// When the earliest question in flight counts as unanswered.
    pub(crate) fn next_deadline(&self) -> Option<Instant> {
        self.nodes
            .values()
            .filter_map(|q| q.asking.as_ref().map(|a| a.deadline))
            .min()
    }

    /// True while a question is due or in flight for `id`.
    pub(crate) fn pending(&self, id: NodeId) -> bool {
        self.nodes
            .get(&id)
            .is_some_and(|q| q.due || q.asking.is_some())
    }

    /// Complete replies applied since start.
    pub(crate) fn replies(&self) -> u64 {
        self.replies
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::*;
    use super::super::*;
    use ihex_proto::{
        BootRole, DockPartner, DockState, FirmwareVersion, LedCommand, PowerState, ResetReason,
        Rgb, Uid,
    };
    use serde_json::{json, Value};

    const RED: LedCommand = LedCommand::Steady {
        color: Rgb { r: 255, g: 0, b: 0 },
        brightness: 255,
    };

    fn power(role: BootRole, relay: bool, loops: u8) -> StateReport {
        StateReport::Power(PowerState {
            relay,
            loops,
            confirmed: loops,
            identify_s: 0,
            role,
            ports: 6,
        })
    }

    fn linked(m: u16, mp: u8) -> DockState {
        DockState {
            closed: true,
            confirmed: true,
            partner: Some(DockPartner {
                node: id(m),
                port: port(mp),
            }),
        }
    }

    /// `node` answers the query `q` with `parts`, closed by its `End`.
    fn answer(b: &mut Bridge, q: &Packet, parts: &[StateReport], now: Instant) {
        let Message::StateQuery { seq, parts: asked } = q.msg else {
            panic!("not a query: {q:?}")
        };
        for &r in parts {
            b.handle_packet(Packet::report(q.dest, Message::StateReport(r)), now);
        }
        let end = StateReport::End {
            seq,
            parts: asked,
            count: parts.len() as u8,
        };
        b.handle_packet(Packet::report(q.dest, Message::StateReport(end)), now);
    }

    fn query_to(out: &Out, n: u16) -> Packet {
        *out.queries
            .iter()
            .find(|q| q.dest == id(n))
            .unwrap_or_else(|| panic!("no query to {n:x} in {:?}", out.queries))
    }

    fn last_state(out: &Out, n: u16) -> Value {
        out.states
            .iter()
            .rev()
            .find(|(i, _)| *i == id(n))
            .map(|(_, s)| s.clone())
            .unwrap_or_else(|| panic!("no state of {n:x}"))
    }

    #[test]
    fn a_restarted_gateway_rebuilds_dockings_and_states_without_new_connection() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        b.handle_timeout(t0);
        drain(&mut b);
        // A static element with mobile 2 docked on its port 3 (linked by the gateway before its
        // restart), and the mobile element, answer the first health check.
        b.handle_packet(Packet::report(id(0x111), reply(0, 0)), t0 + MS);
        b.handle_packet(Packet::report(id(2), reply(0, 0)), t0 + MS);
        let out = drain(&mut b);
        assert_eq!(out.queries.len(), 2, "both are asked: {:?}", out.queries);
        assert!(b.reading_back(id(0x111)) && b.reading_back(id(2)));
        let uid = Uid([1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12]);
        answer(
            &mut b,
            &query_to(&out, 0x111),
            &[
                StateReport::Led(RED),
                StateReport::Buzzer(ihex_proto::BuzzerCommand::Off),
                power(BootRole::Static, true, 1 << 3),
                StateReport::Dock {
                    port: port(3),
                    state: linked(2, 0),
                },
                StateReport::Firmware {
                    version: FirmwareVersion::new(1, 2, 3),
                    trial: false,
                },
                StateReport::ImageHash([0xab, 0, 0, 0, 0, 0, 0x01]),
                StateReport::UidLow(uid.low()),
                StateReport::UidHigh(uid.high()),
            ],
            t0 + 2 * MS,
        );
        answer(
            &mut b,
            &query_to(&out, 2),
            &[power(BootRole::Mobile, false, 1)],
            t0 + 2 * MS,
        );
        let out = drain(&mut b);
        assert!(
            out.named("new_connection").is_empty(),
            "an existing docking is no new connection: {:?}",
            out.events
        );
        assert!(
            out.sent.is_empty(),
            "nothing to tell anyone: {:?}",
            out.sent
        );
        assert_eq!(b.connections().len(), 1);
        assert_eq!(b.read_backs(), 2);
        assert!(!b.reading_back(id(0x111)));
        let s = last_state(&out, 0x111);
        assert_eq!(
            s["connections"],
            json!([{"port": 3, "peer": "2", "peer_port": 0}])
        );
        assert_eq!(
            s["led"],
            serde_json::to_value(crate::event::LedState::from(RED)).unwrap()
        );
        assert_eq!(s["relay"], true);
        assert_eq!(s["role"], "static");
        assert_eq!(
            s["firmware"],
            json!({"version": "1.2.3", "trial": false, "image_hash": "ab000000000001"})
        );
        assert_eq!(s["uid"], uid.to_string());
        assert_eq!(
            last_state(&out, 2)["connections"],
            json!([{"port": 0, "peer": "111", "peer_port": 3}])
        );
        // The mobile element undocks: the restored connection ends like any other.
        b.handle_packet(
            Packet::report(id(0x111), Message::DockRemoved { port: port(3) }),
            t0 + S,
        );
        assert_eq!(drain(&mut b).named("connection_removed").len(), 1);
    }

    #[test]
    fn a_completed_docking_is_linked_and_a_lost_mobile_unlinked() {
        let (mut b, t0) = with_nodes(&[0x111, 2]);
        b.handle_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0 + S,
        );
        let out = drain(&mut b);
        let Message::DockConfirm { seq, .. } = out.sent[0].msg else {
            panic!("{:?}", out.sent)
        };
        b.handle_packet(
            Packet::report(id(0x111), ack(Kind::DockConfirm, seq, AckResult::Ok)),
            t0 + S,
        );
        b.handle_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0 + S,
        );
        let out = drain(&mut b);
        assert_eq!(out.named("new_connection").len(), 1);
        let partner = Some(DockPartner {
            node: id(2),
            port: port(0),
        });
        assert!(
            matches!(out.sent[..], [Packet { dest, msg: Message::DockLink { port: p, partner: ref got, .. }, .. }]
                if dest == id(0x111) && p == port(3) && *got == partner),
            "{:?}",
            out.sent
        );
        // The mobile element goes silent until it is lost: the link is cleared.
        let mut now = t0 + S;
        let mut cleared = false;
        for _ in 0..10 {
            now += S;
            b.handle_timeout(now);
            let out = drain(&mut b);
            if let Some(Message::HealthCheck { seq }) = out.sent.first().map(|p| p.msg) {
                b.handle_packet(Packet::report(id(0x111), reply(seq, 0)), now);
            }
            cleared |= out.sent.iter().any(|p| {
                matches!(p.msg, Message::DockLink { port: p3, partner: None, .. } if p3 == port(3))
            });
            if cleared {
                break;
            }
        }
        assert!(cleared, "the static element is told its link is gone");
    }

    #[test]
    fn state_read_back_replaces_what_was_assumed_but_not_a_newer_ack() {
        let (mut b, t0) = with_nodes(&[5]);
        // The node reboots: it is asked again, and its reply is the truth.
        let boot = Message::BootUp {
            version: (1, 1),
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::Watchdog,
        };
        b.handle_packet(Packet::report(id(5), boot), t0 + S);
        let out = drain(&mut b);
        let q = query_to(&out, 5);
        // Meanwhile an LED command is acknowledged: it is newer than the reply to come.
        let out = command(
            &mut b,
            json!({"cmd": "led", "node": "5", "color": "blue"}),
            t0 + S,
        );
        let Message::LedSet { seq, cmd: blue } = out.sent[0].msg else {
            panic!("{:?}", out.sent)
        };
        b.handle_packet(
            Packet::report(id(5), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + S,
        );
        drain(&mut b);
        answer(
            &mut b,
            &q,
            &[
                StateReport::Led(RED),
                StateReport::Buzzer(ihex_proto::BuzzerCommand::Off),
                power(BootRole::Static, true, 0),
            ],
            t0 + S + MS,
        );
        drain(&mut b);
        let s = serde_json::to_value(b.node_state(id(5), t0 + S + MS)).unwrap();
        assert_eq!(
            s["led"],
            serde_json::to_value(crate::event::LedState::from(blue)).unwrap()
        );
        // Only the LED was acknowledged since: the buzzer and relay the node reports are the truth
        // (the reboot had made them unknown).
        assert_eq!(s["buzzer"]["mode"], "off", "{s}");
        assert_eq!(s["relay"], true);
        // A command that timed out leaves the bridge unsure: the node is asked, its answer wins.
        let out = command(
            &mut b,
            json!({"cmd": "led", "node": "5", "color": "green"}),
            t0 + 2 * S,
        );
        assert!(out.queries.is_empty());
        // The node keeps answering health checks (it is online) but never this command.
        let mut now = t0 + 2 * S;
        let (mut result, mut query) = (None, None);
        while query.is_none() && now < t0 + 60 * S {
            now = b.poll_timeout().max(now + MS);
            b.handle_timeout(now);
            let out = drain(&mut b);
            for p in &out.sent {
                if let Message::HealthCheck { seq } = p.msg {
                    b.handle_packet(Packet::report(id(5), reply(seq, 0)), now);
                }
            }
            if let Some(r) = out.named("command_result").first() {
                result = Some(r["payload"]["result"].clone());
            }
            query = out.queries.iter().find(|q| q.dest == id(5)).copied();
        }
        assert_eq!(result, Some(json!("timeout")));
        let q = query.expect("the node of a timed-out command is asked");
        drain(&mut b);
        answer(&mut b, &q, &[StateReport::Led(RED)], now);
        let s = last_state(&drain(&mut b), 5);
        assert_eq!(
            s["led"],
            serde_json::to_value(crate::event::LedState::from(RED)).unwrap()
        );
    }

    #[test]
    fn nodes_of_protocol_1_0_are_not_asked_again() {
        let (mut b, t0) = with_nodes(&[]);
        // A node that refuses the query as an unknown kind.
        b.handle_packet(Packet::report(id(7), reply(0, 0)), t0 + MS);
        let out = drain(&mut b);
        query_to(&out, 7);
        let refusal = Message::Fault {
            code: ihex_proto::FaultCode::BadFrame,
            arg: Kind::StateQuery as u8,
            detail: BAD_FRAME_UNKNOWN_KIND,
        };
        b.handle_packet(Packet::report(id(7), refusal), t0 + 2 * MS);
        let out = drain(&mut b);
        assert!(out.named("node_fault").is_empty(), "{:?}", out.events);
        assert!(!b.reading_back(id(7)));
        // A node that stays silent is asked SILENT_LIMIT times, then left alone.
        b.handle_packet(Packet::report(id(8), reply(0, 0)), t0 + MS);
        let mut asked = 0;
        let mut now = t0 + MS;
        for _ in 0..20 {
            let out = drain(&mut b);
            assert!(out.queries.iter().all(|q| q.dest != id(7)));
            asked += out.queries.iter().filter(|q| q.dest == id(8)).count();
            now += S;
            // Both keep answering health checks, so they stay online.
            for p in &out.sent {
                if let Message::HealthCheck { seq } = p.msg {
                    b.handle_packet(Packet::report(id(7), reply(seq, 0)), now);
                    b.handle_packet(Packet::report(id(8), reply(seq, 0)), now);
                }
            }
            b.handle_timeout(now);
        }
        assert_eq!(asked, SILENT_LIMIT as usize);
        assert!(!b.reading_back(id(8)));
        // A boot with protocol 1.1 makes it a node that can be asked.
        let boot = Message::BootUp {
            version: READ_BACK_VERSION,
            role: BootRole::Mobile,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        b.handle_packet(Packet::report(id(8), boot), now);
        query_to(&drain(&mut b), 8);
    }

    #[test]
    fn questions_the_bus_never_confirmed_are_not_the_nodes_silence() {
        let (mut b, t0) = with_nodes(&[]);
        b.handle_packet(Packet::report(id(8), reply(0, 0)), t0 + MS);
        let mut now = t0 + MS;
        let mut asked = 0;
        // Our own transmit path never confirms the questions (a loaded gateway, a stuck echo):
        // asked again and again, never given up on.
        for _ in 0..3 * SILENT_LIMIT {
            let out = drain_unconfirmed(&mut b);
            asked += out.queries.iter().filter(|q| q.dest == id(8)).count();
            for p in out.sent {
                b.handle_transmitted(p, now);
            }
            now += S;
            b.handle_packet(Packet::report(id(8), reply(0, 0)), now);
            b.handle_timeout(now);
        }
        assert!(asked > SILENT_LIMIT as usize, "asked {asked} times");
        assert!(b.reading_back(id(8)), "still to be asked");
        // A question confirmed late has the whole timeout from its confirmation.
        let out = drain_unconfirmed(&mut b);
        let q = *out.queries.first().expect("a question");
        now += S - MS;
        b.handle_transmitted(q, now);
        b.handle_timeout(now + MS);
        let out = drain(&mut b);
        assert!(
            out.queries.is_empty(),
            "answer still awaited: {:?}",
            out.queries
        );
        answer_queries(
            &mut b,
            &Out {
                queries: vec![q],
                ..Out::default()
            },
            now + 2 * MS,
        );
        assert!(!b.reading_back(id(8)));
    }

    #[test]
    fn everyone_is_asked_after_the_bus_came_back() {
        let (mut b, t0) = with_nodes(&[1, 2, 3, 4, 5, 6]);
        assert_eq!(b.read_backs(), 6);
        b.handle_bus_event(BusEvent::InterfaceDown, t0 + S);
        assert!(drain(&mut b).queries.is_empty());
        b.handle_bus_event(BusEvent::Recovered, t0 + 2 * S);
        let out = drain(&mut b);
        assert_eq!(
            out.queries.len(),
            MAX_QUERIES,
            "at most {MAX_QUERIES} at once"
        );
        answer_queries(&mut b, &out, t0 + 2 * S);
        let out = drain(&mut b);
        assert_eq!(out.queries.len(), 2);
        answer_queries(&mut b, &out, t0 + 2 * S);
        assert_eq!(b.read_backs(), 12);
    }

    #[test]
    fn questions_cut_by_our_own_outage_are_not_the_nodes_silence() {
        let (mut b, t0) = with_nodes(&[3]);
        let mut now = t0 + S;
        for _ in 0..2 * SILENT_LIMIT {
            b.handle_bus_event(BusEvent::Recovered, now);
            // Recovered after an outage asks again; here the first one follows no outage.
            b.handle_bus_event(BusEvent::InterfaceDown, now);
            b.handle_bus_event(BusEvent::Recovered, now + MS);
            let out = drain(&mut b);
            query_to(&out, 3);
            now += S;
            b.handle_bus_event(BusEvent::BusOff, now);
            b.handle_timeout(now + 10 * S);
            drain(&mut b);
            now += 11 * S;
        }
        b.handle_bus_event(BusEvent::Recovered, now);
        let out = drain(&mut b);
        answer_queries(&mut b, &out, now);
        assert_eq!(b.read_backs(), 2, "still asked, and it answers");
    }

    #[test]
    fn the_boot_up_announcing_an_assigned_id_is_no_reboot() {
        let (mut b, t0) = with_nodes(&[9]);
        let boot = Message::BootUp {
            version: READ_BACK_VERSION,
            role: BootRole::Mobile,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        let out = command(
            &mut b,
            json!({"cmd": "assign", "uid": "00112233445566778899aabb", "new_id": "123"}),
            t0 + S,
        );
        let Message::AssignCommit {
            uid_tail,
            new_id,
            seq,
        } = out.sent[1].msg
        else {
            panic!("{:?}", out.sent)
        };
        let reply = Message::AssignReply {
            seq,
            result: AckResult::Ok,
            new_id,
            uid_tail,
        };
        b.handle_packet(Packet::report(id(0x123), reply), t0 + S);
        b.handle_packet(Packet::report(id(0x123), boot), t0 + S + MS);
        let out = drain(&mut b);
        assert_eq!(out.one("command_result")["result"], "ok");
        assert!(out.named("node_rebooted").is_empty(), "{:?}", out.events);
        // Later BootUps of that board, and any of another known node, are reboots.
        b.handle_packet(Packet::report(id(0x123), boot), t0 + 2 * S);
        b.handle_packet(Packet::report(id(9), boot), t0 + 2 * S);
        assert_eq!(drain(&mut b).named("node_rebooted").len(), 2);
    }
}
