//! Command and acknowledgement tracking: sequence numbers, the commands sent and not yet answered
//! (indexed by key and by deadline), acks and assign replies matched to them, timeouts, and the one
//! `command_result` each accepted command ends with.

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use ihex_proto::{AckResult, Kind, Message, NodeId, Packet, Seq, Uid};

use super::output::Outputs;
use crate::command::{CommandError, NodeAction};
use crate::event::{CommandResult, Event, HexId, Outcome, Refusal, Target};
use crate::registry::Registry;

/// How many commands are in flight, and how the finished ones ended (since start).
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default)]
pub struct CommandCounters {
    /// Sent and not answered yet.
    pub in_flight: usize,
    /// Accepted and sent on the bus.
    pub sent: u64,
    /// Ended `ok`.
    pub ok: u64,
    /// Ended `refused`.
    pub refused: u64,
    /// Ended `timeout`.
    pub timeout: u64,
    /// Ended `failed` (not sent).
    pub failed: u64,
    /// Answered with `command_rejected` (never sent).
    pub rejected: u64,
}

/// A command sent and not yet answered.
#[derive(Debug)]
struct PendingCommand {
    request_id: Option<String>,
    target: Target,
    deadline: Instant,
    what: What,
}

#[derive(Debug)]
enum What {
    /// To one node.
    Node(NodeAction),
    /// To all: one result once every node online at send time answered, or at the timeout.
    Broadcast {
        action: NodeAction,
        expected: BTreeSet<NodeId>,
        acked: BTreeSet<NodeId>,
        refused: BTreeMap<NodeId, String>,
    },
    /// `assign`: answered by an `AssignReply` carrying the UID's tail.
    Assign { uid: Uid, new_id: NodeId },
}

impl What {
    fn cmd(&self) -> &'static str {
        match self {
            What::Node(a) | What::Broadcast { action: a, .. } => a.name(),
            What::Assign { .. } => "assign",
        }
    }
}

/// Key of a pending command: (destination, command kind, seq).
type PendingKey = (NodeId, Kind, Seq);

/// The pending commands, also indexed by deadline: the core loop asks for the next deadline on every
/// turn, and a scan of thousands of unanswered commands (a node that never acks, a flood of commands)
/// made that turn quadratic.
#[derive(Debug, Default)]
struct Pending {
    by_key: BTreeMap<PendingKey, PendingCommand>,
    by_deadline: BTreeSet<(Instant, PendingKey)>,
}

impl Pending {
    fn insert(&mut self, key: PendingKey, p: PendingCommand) {
        self.by_deadline.insert((p.deadline, key));
        if let Some(old) = self.by_key.insert(key, p) {
            self.by_deadline.remove(&(old.deadline, key));
        }
    }

    fn remove(&mut self, key: &PendingKey) -> Option<PendingCommand> {
        let p = self.by_key.remove(key)?;
        self.by_deadline.remove(&(p.deadline, *key));
        Some(p)
    }

    fn get(&self, key: &PendingKey) -> Option<&PendingCommand> {
        self.by_key.get(key)
    }

    /// Mutable access for progress (acks of a broadcast); the deadline must not change.
    fn get_mut(&mut self, key: &PendingKey) -> Option<&mut PendingCommand> {
        self.by_key.get_mut(key)
    }

    fn contains_key(&self, key: &PendingKey) -> bool {
        self.by_key.contains_key(key)
    }

    fn iter(&self) -> impl Iterator<Item = (&PendingKey, &PendingCommand)> {
        self.by_key.iter()
    }

    fn len(&self) -> usize {
        self.by_key.len()
    }

    fn next_deadline(&self) -> Option<Instant> {
        self.by_deadline.first().map(|(d, _)| *d)
    }

    /// Keys whose deadline is at or before `now`, earliest first.
    fn overdue(&self, now: Instant) -> Vec<PendingKey> {
        self.by_deadline
            .iter()
            .take_while(|(d, _)| *d <= now)
            .map(|(_, k)| *k)
            .collect()
    }
}

/// Sequence numbers and the commands waiting for their answer.
#[derive(Debug)]
pub(super) struct Commands {
    timeout: Duration,
    /// Keyed by (destination, command kind, seq); broadcasts use [`NodeId::BROADCAST`].
    pending: Pending,
    next_seq: Seq,
    counters: CommandCounters,
}

impl Commands {
    pub(super) fn new(timeout: Duration) -> Self {
        Commands {
            timeout,
            pending: Pending::default(),
            next_seq: 0,
            counters: CommandCounters::default(),
        }
    }

    /// The counters, with the number in flight as of now.
    pub(super) fn counters(&self) -> CommandCounters {
        CommandCounters {
            in_flight: self.pending.len(),
            ..self.counters
        }
    }

    /// Counts a command answered with `command_rejected`.
    pub(super) fn count_rejected(&mut self) {
        self.counters.rejected += 1;
    }

    /// The earliest command deadline.
    pub(super) fn next_deadline(&self) -> Option<Instant> {
        self.pending.next_deadline()
    }

    #[cfg(test)]
    pub(super) fn is_empty(&self) -> bool {
        self.pending.by_key.is_empty()
    }

    /// A sequence number not in use by a pending command of this kind to this destination.
    pub(super) fn alloc_seq(&mut self, dest: NodeId, kind: Kind) -> Option<Seq> {
        for _ in 0..=u8::MAX {
            let seq = self.next_seq;
            self.next_seq = seq.wrapping_add(1);
            if !self.pending.contains_key(&(dest, kind, seq)) {
                return Some(seq);
            }
        }
        None
    }

    /// A sequence number for a frame nobody waits an answer for in this table (docking frames):
    /// a free one if there is one, else the next in turn.
    pub(super) fn any_seq(&mut self, dest: NodeId, kind: Kind) -> Seq {
        self.alloc_seq(dest, kind).unwrap_or(self.next_seq)
    }

    /// Sends `action` to `target` and waits for its answer; `expected` are the nodes online now
    /// (the ones a broadcast waits for).
    pub(super) fn send(
        &mut self,
        request_id: Option<String>,
        target: Target,
        action: NodeAction,
        expected: impl FnOnce() -> Vec<NodeId>,
        now: Instant,
        out: &mut Outputs,
    ) -> Result<(), (Option<String>, CommandError)> {
        let kind = action.to_message(0).kind();
        let Some(seq) = self.alloc_seq(target.dest(), kind) else {
            let error = CommandError::Busy {
                cmd: action.name(),
                node: target,
            };
            return Err((request_id, error));
        };
        // The parser built `action` from checked values: no second range check here.
        let packet = Packet::command(target.dest(), action.to_message(seq));
        let what = match target {
            Target::Node(_) => What::Node(action),
            Target::All => What::Broadcast {
                action,
                expected: expected().into_iter().collect(),
                acked: BTreeSet::new(),
                refused: BTreeMap::new(),
            },
        };
        let deadline = now + self.timeout;
        self.pending.insert(
            (target.dest(), kind, seq),
            PendingCommand {
                request_id,
                target,
                deadline,
                what,
            },
        );
        self.counters.sent += 1;
        out.send(packet);
        Ok(())
    }

    /// Sends `AssignSelect` + `AssignCommit` for the board `uid` and waits for its `AssignReply`.
    pub(super) fn send_assign(
        &mut self,
        request_id: Option<String>,
        uid: Uid,
        new_id: NodeId,
        now: Instant,
        out: &mut Outputs,
    ) -> Result<(), (Option<String>, CommandError)> {
        let Some(seq) = self.alloc_seq(NodeId::BROADCAST, Kind::AssignCommit) else {
            let node = Target::Node(new_id);
            let error = CommandError::Busy {
                cmd: "assign",
                node,
            };
            return Err((request_id, error));
        };
        let select = Packet::command(
            NodeId::BROADCAST,
            Message::AssignSelect {
                uid_head: uid.head(),
            },
        );
        let commit = Packet::command(
            NodeId::BROADCAST,
            Message::AssignCommit {
                uid_tail: uid.tail(),
                new_id,
                seq,
            },
        );
        let deadline = now + self.timeout;
        self.pending.insert(
            (NodeId::BROADCAST, Kind::AssignCommit, seq),
            PendingCommand {
                request_id,
                target: Target::Node(new_id),
                deadline,
                what: What::Assign { uid, new_id },
            },
        );
        self.counters.sent += 1;
        // Select before commit: a node only takes the commit after the matching select.
        out.send(select);
        out.send(commit);
        Ok(())
    }

    /// An `Ack` from `src` (not for a `DockConfirm`: the docking sequence owns those).
    pub(super) fn on_ack(
        &mut self,
        src: NodeId,
        kind: Kind,
        seq: Seq,
        result: AckResult,
        registry: &mut Registry,
        out: &mut Outputs,
    ) {
        if let Some(p) = self.pending.remove(&(src, kind, seq)) {
            let What::Node(action) = p.what else { return };
            if result == AckResult::Ok {
                apply_action_state(registry, out, src, action);
                self.emit_result(p, Outcome::Ok, None, out);
            } else {
                self.emit_result(p, Outcome::Refused, Some(result.to_string()), out);
            }
            return;
        }
        let key = (NodeId::BROADCAST, kind, seq);
        let Some(p) = self.pending.get_mut(&key) else {
            tracing::debug!(%src, ?kind, seq, "ack for no pending command (late or not ours)");
            return;
        };
        let What::Broadcast {
            action,
            expected,
            acked,
            refused,
        } = &mut p.what
        else {
            return;
        };
        let action = *action;
        if result == AckResult::Ok {
            acked.insert(src);
        } else {
            refused.insert(src, result.to_string());
        }
        let complete = !expected.is_empty()
            && expected
                .iter()
                .all(|id| acked.contains(id) || refused.contains_key(id));
        if result == AckResult::Ok {
            apply_action_state(registry, out, src, action);
        }
        if complete {
            if let Some(p) = self.pending.remove(&key) {
                self.finish_broadcast(p, out);
            }
        }
    }

    /// An `AssignReply` (from the board's new ID, or from an unconfigured board).
    pub(super) fn on_assign_reply(
        &mut self,
        seq: Seq,
        result: AckResult,
        new_id: NodeId,
        uid_tail: [u8; 4],
        out: &mut Outputs,
    ) {
        let key = (NodeId::BROADCAST, Kind::AssignCommit, seq);
        let matches = matches!(self.pending.get(&key), Some(PendingCommand { what: What::Assign { uid, .. }, .. }) if uid.tail() == uid_tail);
        if !matches {
            tracing::debug!(seq, %new_id, "assign reply for no pending assign");
            return;
        }
        if let Some(p) = self.pending.remove(&key) {
            let wanted = match p.what {
                What::Assign { new_id, .. } => new_id,
                _ => new_id,
            };
            if result == AckResult::Ok && new_id != wanted {
                let reason = format!("the board answered with id {new_id} instead of {wanted}");
                self.emit_result(p, Outcome::Refused, Some(reason), out);
            } else if result == AckResult::Ok {
                self.emit_result(p, Outcome::Ok, None, out);
            } else {
                self.emit_result(p, Outcome::Refused, Some(result.to_string()), out);
            }
        }
    }

    /// `packet` could not be sent: if it carried a pending command, that command ends `failed`
    /// (returns true); otherwise the caller reports it.
    pub(super) fn on_send_failed(
        &mut self,
        packet: &Packet,
        reason: &str,
        out: &mut Outputs,
    ) -> bool {
        let key = match packet.msg {
            Message::AssignSelect { uid_head } => self
                .pending
                .iter()
                .find(|(_, p)| matches!(p.what, What::Assign { uid, .. } if uid.head() == uid_head))
                .map(|(k, _)| *k),
            Message::AssignCommit { seq, .. } => Some((NodeId::BROADCAST, Kind::AssignCommit, seq)),
            ref m => m.ack_seq().map(|seq| (packet.dest, m.kind(), seq)),
        };
        match key.and_then(|k| self.pending.remove(&k)) {
            Some(p) => {
                self.emit_result(p, Outcome::Failed, Some(format!("not sent: {reason}")), out);
                true
            }
            None => false,
        }
    }

    /// Ends every command whose deadline passed.
    pub(super) fn expire(&mut self, now: Instant, out: &mut Outputs) {
        for k in self.pending.overdue(now) {
            if let Some(p) = self.pending.remove(&k) {
                self.finish_timed_out(p, out);
            }
        }
    }

    fn finish_timed_out(&mut self, p: PendingCommand, out: &mut Outputs) {
        match &p.what {
            What::Broadcast { .. } => self.finish_broadcast(p, out),
            What::Assign { .. } => {
                let reason = format!(
                    "no AssignReply within {} ms (is a board with this uid on the bus?)",
                    self.timeout.as_millis()
                );
                self.emit_result(p, Outcome::Timeout, Some(reason), out);
            }
            What::Node(_) => {
                let reason = format!("no ack within {} ms", self.timeout.as_millis());
                self.emit_result(p, Outcome::Timeout, Some(reason), out);
            }
        }
    }

    fn finish_broadcast(&mut self, p: PendingCommand, out: &mut Outputs) {
        let What::Broadcast {
            expected,
            acked,
            refused,
            ..
        } = &p.what
        else {
            return;
        };
        let missing: Vec<HexId> = expected
            .iter()
            .filter(|id| !acked.contains(id) && !refused.contains_key(id))
            .map(|&id| HexId(id))
            .collect();
        let answered = acked.len() + refused.len();
        let (outcome, reason) = if !refused.is_empty() {
            (
                Outcome::Refused,
                Some(format!(
                    "{} of {answered} answering nodes refused",
                    refused.len()
                )),
            )
        } else if !missing.is_empty() {
            (
                Outcome::Timeout,
                Some(format!(
                    "{} of {} online nodes did not answer",
                    missing.len(),
                    expected.len()
                )),
            )
        } else if acked.is_empty() {
            (Outcome::Timeout, Some("no node answered".to_string()))
        } else {
            (Outcome::Ok, None)
        };
        let result = CommandResult {
            request_id: p.request_id.clone(),
            cmd: p.what.cmd().into(),
            node: Target::All,
            result: outcome,
            reason,
            acked: Some(acked.iter().map(|&id| HexId(id)).collect()),
            refused: Some(
                refused
                    .iter()
                    .map(|(&id, r)| Refusal {
                        id: HexId(id),
                        reason: r.clone(),
                    })
                    .collect(),
            ),
            missing: Some(missing),
        };
        self.count(outcome);
        out.emit(Event::CommandResult(result));
    }

    fn emit_result(
        &mut self,
        p: PendingCommand,
        result: Outcome,
        reason: Option<String>,
        out: &mut Outputs,
    ) {
        if let What::Broadcast { .. } = p.what {
            if result != Outcome::Failed {
                return self.finish_broadcast(p, out);
            }
        }
        self.count(result);
        out.emit(Event::CommandResult(CommandResult {
            request_id: p.request_id,
            cmd: p.what.cmd().into(),
            node: p.target,
            result,
            reason,
            acked: None,
            refused: None,
            missing: None,
        }));
    }

    fn count(&mut self, outcome: Outcome) {
        let c = &mut self.counters;
        match outcome {
            Outcome::Ok => c.ok += 1,
            Outcome::Refused => c.refused += 1,
            Outcome::Timeout => c.timeout += 1,
            Outcome::Failed => c.failed += 1,
        }
    }
}

/// Records what a node acknowledged in its state document.
fn apply_action_state(
    registry: &mut Registry,
    out: &mut Outputs,
    node: NodeId,
    action: NodeAction,
) {
    if let Some(e) = registry.get_mut(node) {
        match action {
            NodeAction::Led(cmd) => e.led = Some(cmd),
            NodeAction::Buzzer(cmd) => e.buzzer = Some(cmd),
            NodeAction::Power(on) => e.relay = Some(on),
            NodeAction::Identify(_) => {}
        }
        out.touch(node);
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::*;
    use super::super::*;
    use ihex_proto::{
        AckResult, BootRole, Kind, LedCommand, Message, NodeId, Packet, ResetReason, Rgb,
    };
    use serde_json::{json, Value};

    #[test]
    fn led_command_acked_updates_state_and_reports_ok() {
        let (mut b, t0) = with_nodes(&[2]);
        let out = command(
            &mut b,
            json!({"cmd": "led", "node": "2", "color": "green", "request_id": "r1"}),
            t0 + 100 * MS,
        );
        assert_eq!(out.sent.len(), 1);
        let p = out.sent[0];
        assert_eq!(p.dest, id(2));
        let Message::LedSet { seq, cmd } = p.msg else {
            panic!("{p:?}")
        };
        assert_eq!(
            cmd,
            LedCommand::Steady {
                color: Rgb::new(0, 255, 0),
                brightness: 255
            }
        );
        assert!(out.events.is_empty(), "no result before the ack");
        assert_eq!(
            b.poll_timeout(),
            t0 + 100 * MS + BridgeConfig::default().command_timeout
        );
        b.handle_packet(
            Packet::report(id(2), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + S + MS,
        );
        let out = drain(&mut b);
        assert_eq!(
            out.one("command_result"),
            &json!({"request_id": "r1", "cmd": "led", "node": "2", "result": "ok", "reason": null})
        );
        let (_, st) = out
            .states
            .iter()
            .find(|(n, _)| *n == id(2))
            .expect("state published");
        assert_eq!(
            st["led"],
            json!({"mode": "steady", "color": "#00ff00", "brightness": 255})
        );
        // The late duplicate of that ack is ignored.
        b.handle_packet(
            Packet::report(id(2), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + S + MS,
        );
        assert!(drain(&mut b).events.is_empty());
    }

    #[test]
    fn refused_and_timed_out_commands() {
        let (mut b, t0) = with_nodes(&[2]);
        let out = command(&mut b, json!({"cmd": "power", "node": "2", "on": true}), t0);
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(2), ack(Kind::PowerSet, seq, AckResult::InvalidState)),
            t0 + MS,
        );
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(r["result"], "refused");
        assert_eq!(r["reason"], "invalid_state");
        assert_eq!(
            r["request_id"],
            Value::Null,
            "results are published without a request_id too"
        );

        let out = command(
            &mut b,
            json!({"cmd": "identify", "node": "2", "seconds": 3, "request_id": "x"}),
            t0,
        );
        assert_eq!(
            out.sent[0].msg,
            Message::Identify {
                seq: out.sent[0].msg.ack_seq().unwrap(),
                seconds: 3
            }
        );
        let timeout = BridgeConfig::default().command_timeout;
        b.handle_timeout(t0 + timeout - MS);
        assert!(drain(&mut b).named("command_result").is_empty());
        assert_eq!(b.poll_timeout(), t0 + timeout);
        b.handle_timeout(t0 + timeout);
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(
            (r["result"].as_str(), r["request_id"].as_str()),
            (Some("timeout"), Some("x"))
        );
        assert_eq!(r["reason"], "no ack within 500 ms");
    }

    #[test]
    fn send_failure_reports_failed() {
        let (mut b, t0) = with_nodes(&[2]);
        let out = command(
            &mut b,
            json!({"cmd": "buzzer", "node": "2", "mode": "off", "request_id": "b"}),
            t0,
        );
        b.handle_send_failed(out.sent[0], "No buffer space available", t0 + MS);
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(r["result"], "failed");
        assert_eq!(r["reason"], "not sent: No buffer space available");
        // A health check that cannot be sent is a bus_error.
        b.handle_send_failed(
            Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: 0 }),
            "down",
            t0,
        );
        assert_eq!(drain(&mut b).one("bus_error")["error"], "send_failed");
    }

    #[test]
    fn broadcast_collects_one_result() {
        let (mut b, t0) = with_nodes(&[2, 3]);
        let out = command(
            &mut b,
            json!({"cmd": "led", "node": "all", "off": true, "request_id": "all1"}),
            t0,
        );
        assert_eq!(out.sent.len(), 1);
        assert_eq!(out.sent[0].dest, NodeId::BROADCAST);
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(3), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + MS,
        );
        assert!(
            drain(&mut b).named("command_result").is_empty(),
            "node 2 has not answered yet"
        );
        b.handle_packet(
            Packet::report(id(2), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + MS,
        );
        let out = drain(&mut b);
        assert_eq!(
            out.one("command_result"),
            &json!({"request_id": "all1", "cmd": "led", "node": "all", "result": "ok", "reason": null,
                    "acked": ["2", "3"], "refused": [], "missing": []})
        );
        assert_eq!(
            out.states.len(),
            1,
            "node 2's led state; node 3's was published on its ack"
        );

        // One node silent: one timeout result naming it.
        let out = command(
            &mut b,
            json!({"cmd": "power", "node": "all", "on": false}),
            t0 + S,
        );
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(2), ack(Kind::PowerSet, seq, AckResult::Ok)),
            t0 + S + MS,
        );
        b.handle_timeout(t0 + S + BridgeConfig::default().command_timeout);
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(r["result"], "timeout");
        assert_eq!(r["acked"], json!(["2"]));
        assert_eq!(r["missing"], json!(["3"]));
        assert_eq!(r["reason"], "1 of 2 online nodes did not answer");
    }

    #[test]
    fn assign_sends_select_and_commit_and_reports_the_reply() {
        let (mut b, t0) = with_nodes(&[2]);
        let uid = "00112233445566778899aabb";
        let out = command(
            &mut b,
            json!({"cmd": "assign", "uid": uid, "new_id": "2", "request_id": "a"}),
            t0,
        );
        assert!(out.one("command_rejected")["reason"]
            .as_str()
            .unwrap()
            .contains("node 2 is online"));
        let out = command(
            &mut b,
            json!({"cmd": "assign", "uid": uid, "new_id": "123", "request_id": "a"}),
            t0,
        );
        assert_eq!(out.sent.len(), 2);
        assert_eq!(
            out.sent[0].msg,
            Message::AssignSelect {
                uid_head: [0x00, 0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77]
            }
        );
        let Message::AssignCommit {
            uid_tail,
            new_id,
            seq,
        } = out.sent[1].msg
        else {
            panic!()
        };
        assert_eq!((uid_tail, new_id), ([0x88, 0x99, 0xaa, 0xbb], id(0x123)));
        // A reply for another board's uid does not count.
        let other = Message::AssignReply {
            seq,
            result: AckResult::Ok,
            new_id,
            uid_tail: [0; 4],
        };
        b.handle_packet(Packet::report(id(0x123), other), t0 + MS);
        assert!(drain(&mut b).named("command_result").is_empty());
        let reply = Message::AssignReply {
            seq,
            result: AckResult::Ok,
            new_id,
            uid_tail,
        };
        b.handle_packet(Packet::report(id(0x123), reply), t0 + MS);
        let out = drain(&mut b);
        assert_eq!(
            out.one("command_result"),
            &json!({"request_id": "a", "cmd": "assign", "node": "123", "result": "ok", "reason": null})
        );
        // An unconfigured board refusing (e.g. flash failure) answers from 0xffe.
        let out = command(
            &mut b,
            json!({"cmd": "assign", "uid": uid, "new_id": "124"}),
            t0 + S,
        );
        let Message::AssignCommit { seq, .. } = out.sent[1].msg else {
            panic!()
        };
        let refused = Message::AssignReply {
            seq,
            result: AckResult::StoreFailed,
            new_id: NodeId::UNCONFIGURED,
            uid_tail,
        };
        b.handle_packet(Packet::report(NodeId::UNCONFIGURED, refused), t0 + S + MS);
        let r = drain(&mut b);
        let r = r.one("command_result");
        assert_eq!(
            (r["result"].as_str(), r["reason"].as_str()),
            (Some("refused"), Some("store_failed"))
        );
    }

    #[test]
    fn reboot_forgets_acknowledged_actuator_state() {
        let (mut b, t0) = with_nodes(&[2]);
        let out = command(
            &mut b,
            json!({"cmd": "led", "node": "2", "color": "red"}),
            t0,
        );
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(2), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + MS,
        );
        let out = drain(&mut b);
        assert_eq!(out.states[0].1["led"]["mode"], "steady");
        let boot = Message::BootUp {
            version: (1, 0),
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        b.handle_packet(Packet::report(id(2), boot), t0 + S);
        let out = drain(&mut b);
        assert_eq!(out.one("node_rebooted")["reset"], "power_on");
        assert_eq!(out.states[0].1["led"], Value::Null);
    }

    #[test]
    fn broadcast_refusals_are_listed() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        let out = command(
            &mut b,
            json!({"cmd": "power", "node": "all", "on": true}),
            t0,
        );
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(2), ack(Kind::PowerSet, seq, AckResult::Unsupported)),
            t0 + MS,
        );
        b.handle_packet(
            Packet::report(id(0x111), ack(Kind::PowerSet, seq, AckResult::Ok)),
            t0 + MS,
        );
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(r["result"], "refused");
        assert_eq!(r["refused"], json!([{"id": "2", "reason": "unsupported"}]));
        assert_eq!(r["acked"], json!(["111"]));
        assert_eq!(r["reason"], "1 of 2 answering nodes refused");
        let (_, st) = out.states.iter().find(|(n, _)| *n == id(0x111)).unwrap();
        assert_eq!(st["relay"], true);
    }
}
