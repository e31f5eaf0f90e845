//! Command and acknowledgement tracking: sequence numbers, the commands sent and not yet answered
//! (indexed by key and by deadline), what became of each command's frame (queued, handed to the
//! adapter, confirmed on the bus), acks and assign replies matched to them, and the one
//! `command_result` each accepted command ends with.
//!
//! A command's frame waits in the bridge's transmit queue until the adapter has room. If its
//! deadline — `ttl_ms` after the gateway received it, or `command_timeout` after it was accepted,
//! whichever is first — passes while it still waits there, it is withdrawn and never sent: the
//! result is `expired` (the ttl) or `failed` (the timeout). Once the adapter confirmed the frame on
//! the bus, the node has `command_timeout` to acknowledge it; without an ack the result is
//! `timeout` (the node may or may not have acted: an ack can be lost). A frame handed to the
//! adapter but never confirmed (no echo within [`crate::bridge::TRANSMIT_CONFIRM_TIMEOUT`], or the
//! interface went down) also ends `timeout`, with a reason saying it may still reach the bus.
//!
//! Frames the bridge sends on its own and that nodes acknowledge (docking confirms, refusals, relay
//! off, dock links) are tracked here too, without a result, so that no sequence number is ever in
//! use twice: the allocator refuses rather than reuse a live one.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap};

use rustc_hash::FxHashMap;
use std::time::{Duration, Instant};

use ihex_proto::{AckResult, Kind, Message, NodeId, Packet, Seq, Uid};

use crate::bridge::output::{FrameFate, FrameOwner, Outputs};
use crate::bridge::TRANSMIT_CONFIRM_TIMEOUT;
use crate::command::{CommandError, NodeAction};
use crate::event::{CommandResult, Event, HexId, Outcome, Refusal, Target};
use crate::origin::Origin;
use crate::registry::{millis, Registry};

/// How many commands are in flight, and how the finished ones ended (since start).
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct CommandCounters {
    /// Accepted and not answered yet.
    pub in_flight: usize,
    /// Accepted (queued for the bus).
    pub sent: u64,
    /// Ended `ok`.
    pub ok: u64,
    /// Ended `refused`.
    pub refused: u64,
    /// Ended `timeout`.
    pub timeout: u64,
    /// Ended `failed` (not sent).
    pub failed: u64,
    /// Ended `expired` (its `ttl_ms` passed before it could be sent).
    pub expired: u64,
    /// Answered with `command_rejected` (never sent).
    pub rejected: u64,
}

/// What became of a command's frame.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Fate {
    /// In the bridge's transmit queue: can still be withdrawn.
    Queued,
    /// Handed to the adapter at this time, not confirmed yet.
    Handed(Instant),
    /// Confirmed on the bus at this time.
    OnBus(Instant),
    /// Handed to the adapter, which could not confirm it (the reason): it may still be sent.
    Unconfirmed(&'static str),
}

/// A command sent and not yet answered.
#[derive(Debug)]
struct PendingCommand {
    request_id: Option<String>,
    target: Target,
    deadline: Instant,
    what: What,
    /// The frame that carries it (for `assign`, the commit).
    frame: Packet,
    /// `assign`'s select, queued before `frame`.
    select: Option<Packet>,
    /// When the bridge accepted it.
    accepted: Instant,
    /// When its `ttl_ms` ends, if it has one.
    expires: Option<Instant>,
    fate: Fate,
    /// Where it came from, for its answer (boxed: most commands have none, and every pending
    /// command would grow by it).
    origin: Option<Box<Origin>>,
}

#[derive(Debug)]
enum What {
    /// To one node.
    Node(NodeAction),
    /// To all: one result once every node online at send time answered, or at the timeout.
    Broadcast {
        action: NodeAction,
        /// Boxed: a broadcast is rare, and its sets would make every pending command larger.
        answers: Box<Answers>,
    },
    /// `assign`: answered by an `AssignReply` carrying the UID's tail.
    Assign { uid: Uid, new_id: NodeId },
    /// A frame of the bridge's own (docking): keeps its sequence number reserved until it is
    /// acknowledged or its time is up; no result.
    Internal,
}

impl What {
    fn cmd(&self) -> &'static str {
        match self {
            What::Node(a) | What::Broadcast { action: a, .. } => a.name(),
            What::Assign { .. } => "assign",
            What::Internal => "internal",
        }
    }
}

/// Who a broadcast waits for, and who answered.
#[derive(Debug, Default)]
struct Answers {
    expected: BTreeSet<NodeId>,
    acked: BTreeSet<NodeId>,
    refused: BTreeMap<NodeId, String>,
}

/// Key of a pending command: (destination, command kind, seq).
type PendingKey = (NodeId, Kind, Seq);

/// The key a frame's acknowledgement is matched by, if it is acknowledged.
fn key_of(p: &Packet) -> Option<PendingKey> {
    match p.msg {
        Message::AssignCommit { seq, .. } => Some((NodeId::BROADCAST, Kind::AssignCommit, seq)),
        ref m => m.ack_seq().map(|seq| (p.dest, m.kind(), seq)),
    }
}

/// A [`PendingKey`] packed into one integer (destination, then kind, then seq), ordered as the
/// tuple: the tables are searched on every command, ack and echo.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
struct Packed(u32);

impl Packed {
    fn new((dest, kind, seq): PendingKey) -> Packed {
        Packed(u32::from(dest.get()) << 16 | u32::from(kind as u8) << 8 | u32::from(seq))
    }

    /// The key again; `None` cannot happen for a key packed by [`Packed::new`].
    fn key(self) -> Option<PendingKey> {
        let dest = NodeId::new((self.0 >> 16) as u16)?;
        let kind = Kind::from_raw((self.0 >> 8) as u8)?;
        Some((dest, kind, self.0 as u8))
    }

    /// Its destination and kind, without the seq.
    fn stream(self) -> u32 {
        self.0 >> 8
    }
}

/// A pending command, its key, and the stamp and deadline of its one live entry in the deadline
/// heap (never later than the command's deadline; `None` once [`PendingTable::overdue`] took it).
#[derive(Debug)]
struct Slot {
    key: Packed,
    stamp: u64,
    due: Option<Instant>,
    command: PendingCommand,
}

/// The pending commands: dense in a vector, found by key through a hash table, ordered by a heap of
/// deadlines, with one set of the seqs in use per destination and kind. B-trees of commands by key
/// and by (deadline, key) cost a third of a command's instructions (callgrind; two inserts, a
/// removal and rebalancing moves of whole entries per command); these cost a hash and a heap push
/// each. The hash table holds indices, not commands, so that growing it in a burst of commands
/// copies 8-byte entries while the commands' vector grows in place (a large `realloc` remaps).
///
/// A deadline moved earlier is pushed again rather than moved: the heap entry whose stamp is no
/// longer the command's is stale, skipped when it reaches the top and purged when stale entries
/// outnumber live ones. A deadline moved later (a command's frame confirmed on the bus: the node's
/// time starts) is not pushed: most commands are answered before their first deadline, and the
/// live entry, when it comes due, is pushed again with the later one. That halves the heap's work
/// per command; the heap's top is the earliest live deadline or earlier.
#[derive(Debug, Default)]
struct PendingTable {
    index: FxHashMap<Packed, u32>,
    slots: Vec<Slot>,
    deadlines: BinaryHeap<Reverse<(Instant, Packed, u64)>>,
    /// Seqs in use per (destination, kind), as 256-bit sets (bit `seq % 64` of word `seq / 64`).
    taken: FxHashMap<u32, [u64; 4]>,
    next_stamp: u64,
}

impl PendingTable {
    fn insert(&mut self, key: PendingKey, p: PendingCommand) {
        let key = Packed::new(key);
        let stamp = self.push_deadline(p.deadline, key);
        let slot = Slot {
            key,
            stamp,
            due: Some(p.deadline),
            command: p,
        };
        match self.index.get(&key) {
            Some(&i) => self.slots[i as usize] = slot,
            None => {
                self.index.insert(key, self.slots.len() as u32);
                self.slots.push(slot);
                let (word, bit) = seq_bit(key.0 as u8);
                self.taken.entry(key.stream()).or_default()[word] |= bit;
            }
        }
        self.drop_stale();
    }

    fn remove(&mut self, key: &PendingKey) -> Option<PendingCommand> {
        let key = Packed::new(*key);
        let i = self.index.remove(&key)? as usize;
        let slot = self.slots.swap_remove(i);
        if let Some(moved) = self.slots.get(i) {
            self.index.insert(moved.key, i as u32);
        }
        if let Some(set) = self.taken.get_mut(&key.stream()) {
            let (word, bit) = seq_bit(key.0 as u8);
            set[word] &= !bit;
            if *set == [0; 4] {
                self.taken.remove(&key.stream());
            }
        }
        // After a burst, give most of the room back.
        if self.slots.capacity() > 256 && self.slots.len() < self.slots.capacity() / 4 {
            self.slots.shrink_to(self.slots.len() * 2);
            self.index.shrink_to(self.slots.len() * 2);
        }
        self.drop_stale();
        Some(slot.command)
    }

    fn slot(&self, key: Packed) -> Option<&Slot> {
        let i = *self.index.get(&key)?;
        self.slots.get(i as usize)
    }

    fn get(&self, key: &PendingKey) -> Option<&PendingCommand> {
        self.slot(Packed::new(*key)).map(|s| &s.command)
    }

    /// Mutable access for progress (acks of a broadcast, the frame's fate); the deadline changes
    /// only through [`PendingTable::set_deadline`].
    fn get_mut(&mut self, key: &PendingKey) -> Option<&mut PendingCommand> {
        let i = *self.index.get(&Packed::new(*key))?;
        self.slots.get_mut(i as usize).map(|s| &mut s.command)
    }

    fn set_deadline(&mut self, key: &PendingKey, deadline: Instant) {
        let key = Packed::new(*key);
        let Some(&i) = self.index.get(&key) else {
            return;
        };
        let Some(slot) = self.slots.get_mut(i as usize) else {
            return;
        };
        slot.command.deadline = deadline;
        if slot.due.is_none_or(|due| deadline < due) {
            self.schedule(i as usize, deadline);
            self.drop_stale();
        }
    }

    /// Makes `deadline` the live heap entry of the command in slot `i`.
    fn schedule(&mut self, i: usize, deadline: Instant) {
        let stamp = self.push_deadline(deadline, self.slots[i].key);
        let slot = &mut self.slots[i];
        slot.stamp = stamp;
        slot.due = Some(deadline);
    }

    /// Pushes `key`'s new deadline; the returned stamp makes it the live one.
    fn push_deadline(&mut self, deadline: Instant, key: Packed) -> u64 {
        self.next_stamp += 1;
        self.deadlines
            .push(Reverse((deadline, key, self.next_stamp)));
        self.next_stamp
    }

    /// Whether a heap entry is its command's live deadline.
    fn live(&self, &Reverse((_, key, stamp)): &Reverse<(Instant, Packed, u64)>) -> bool {
        self.slot(key).is_some_and(|s| s.stamp == stamp)
    }

    /// Drops stale entries from the heap's top, and all of them once they outnumber the live ones.
    fn drop_stale(&mut self) {
        if self.deadlines.len() > 2 * self.slots.len() + 64 {
            let mut heap = std::mem::take(&mut self.deadlines);
            heap.retain(|e| self.live(e));
            self.deadlines = heap;
        }
        while let Some(top) = self.deadlines.peek() {
            if self.live(top) {
                break;
            }
            self.deadlines.pop();
        }
    }

    /// The seqs pending for `dest` and `kind`, as a 256-bit set (bit `seq` of word `seq / 64`).
    fn taken_seqs(&self, dest: NodeId, kind: Kind) -> [u64; 4] {
        let stream = Packed::new((dest, kind, 0)).stream();
        self.taken.get(&stream).copied().unwrap_or_default()
    }

    fn iter(&self) -> impl Iterator<Item = (PendingKey, &PendingCommand)> {
        self.slots
            .iter()
            .filter_map(|s| Some((s.key.key()?, &s.command)))
    }

    /// The earliest deadline, or earlier: a deadline moved later is found when the earlier one
    /// comes ([`PendingTable::overdue`] returns only keys really due).
    fn next_deadline(&self) -> Option<Instant> {
        self.deadlines.peek().map(|Reverse((d, _, _))| *d)
    }

    /// Keys whose deadline is at or before `now`, earliest first, taken off the heap: the caller
    /// ends each of them or gives it a new deadline. A command whose deadline was moved later is
    /// pushed again with it instead.
    fn overdue(&mut self, now: Instant) -> Vec<PendingKey> {
        let mut keys = Vec::new();
        while let Some(top) = self.deadlines.peek() {
            let &Reverse((deadline, key, stamp)) = top;
            if deadline > now {
                break;
            }
            self.deadlines.pop();
            let Some(&i) = self.index.get(&key) else {
                continue;
            };
            let slot = &mut self.slots[i as usize];
            if slot.stamp != stamp {
                continue; // stale
            }
            if slot.command.deadline > now {
                let later = slot.command.deadline;
                self.schedule(i as usize, later);
            } else {
                // No live entry (stamps start at 1) until the caller gives it a new deadline.
                slot.stamp = 0;
                slot.due = None;
                keys.extend(key.key());
            }
        }
        self.drop_stale();
        keys
    }
}

/// Where `seq` is in a 256-bit set: the word and the bit.
fn seq_bit(seq: Seq) -> (usize, u64) {
    (usize::from(seq >> 6), 1 << (seq & 63))
}

/// When and how a command reached the bridge.
#[derive(Clone, Debug)]
pub(crate) struct Accepted {
    /// Accepted now.
    pub(crate) now: Instant,
    /// Its ttl ends then, if it has one.
    pub(crate) expires: Option<Instant>,
    /// Where it came from, as its answer says it (`None`: the plain shared topic).
    pub(crate) origin: Option<Origin>,
}

/// Sequence numbers and the commands waiting for their answer.
#[derive(Debug)]
pub(crate) struct Pending {
    timeout: Duration,
    /// Keyed by (destination, command kind, seq); broadcasts use [`NodeId::BROADCAST`].
    pending: PendingTable,
    next_seq: Seq,
    counters: CommandCounters,
    /// Commands (not internal frames) pending.
    commands_pending: usize,
}

impl Pending {
    pub(crate) fn new(timeout: Duration) -> Self {
        Pending {
            timeout,
            pending: PendingTable::default(),
            next_seq: 0,
            counters: CommandCounters::default(),
            commands_pending: 0,
        }
    }

    /// The counters, with the number in flight as of now.
    pub(crate) fn counters(&self) -> CommandCounters {
        CommandCounters {
            in_flight: self.commands_pending,
            ..self.counters
        }
    }

    /// Counts a command answered with `command_rejected`.
    pub(crate) fn count_rejected(&mut self) {
        self.counters.rejected += 1;
    }

    /// Counts a command answered `expired` before it was queued.
    pub(crate) fn count_expired(&mut self) {
        self.counters.expired += 1;
    }

    /// The earliest command deadline.
    pub(crate) fn next_deadline(&self) -> Option<Instant> {
        self.pending.next_deadline()
    }

    /// A sequence number not in use by a pending frame of this kind to this destination; `None`
    /// when all 256 are in use.
    fn alloc_seq(&mut self, dest: NodeId, kind: Kind) -> Option<Seq> {
        let taken = self.pending.taken_seqs(dest, kind);
        for _ in 0..=u8::MAX {
            let seq = self.next_seq;
            self.next_seq = seq.wrapping_add(1);
            let (word, bit) = seq_bit(seq);
            if taken[word] & bit == 0 {
                return Some(seq);
            }
        }
        None
    }

    fn insert(&mut self, key: PendingKey, p: PendingCommand) {
        if !matches!(p.what, What::Internal) {
            self.commands_pending += 1;
        }
        self.pending.insert(key, p);
    }

    fn remove(&mut self, key: &PendingKey) -> Option<PendingCommand> {
        let p = self.pending.remove(key)?;
        if !matches!(p.what, What::Internal) {
            self.commands_pending -= 1;
        }
        Some(p)
    }

    /// The latest moment a command accepted as `acc` may still be written to the bus.
    fn not_after(&self, acc: &Accepted) -> Instant {
        let by_timeout = acc.now + self.timeout;
        acc.expires.map_or(by_timeout, |e| e.min(by_timeout))
    }

    /// Sends `action` to `target` and waits for its answer; `expected` are the nodes online now
    /// (the ones a broadcast waits for).
    pub(crate) fn send(
        &mut self,
        request_id: Option<String>,
        target: Target,
        action: NodeAction,
        expected: impl FnOnce() -> Vec<NodeId>,
        acc: Accepted,
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
        let frame = Packet::command(target.dest(), action.to_message(seq));
        let what = match target {
            Target::Node(_) => What::Node(action),
            Target::All => What::Broadcast {
                action,
                answers: Box::new(Answers {
                    expected: expected().into_iter().collect(),
                    ..Answers::default()
                }),
            },
        };
        let not_after = self.not_after(&acc);
        self.insert(
            (target.dest(), kind, seq),
            PendingCommand {
                request_id,
                target,
                deadline: not_after,
                what,
                frame,
                select: None,
                accepted: acc.now,
                expires: acc.expires,
                fate: Fate::Queued,
                origin: acc.origin.map(Box::new),
            },
        );
        self.counters.sent += 1;
        out.send_until(frame, not_after);
        Ok(())
    }

    /// Sends `AssignSelect` + `AssignCommit` for the board `uid` and waits for its `AssignReply`.
    pub(crate) fn send_assign(
        &mut self,
        request_id: Option<String>,
        uid: Uid,
        new_id: NodeId,
        acc: Accepted,
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
        let not_after = self.not_after(&acc);
        self.insert(
            (NodeId::BROADCAST, Kind::AssignCommit, seq),
            PendingCommand {
                request_id,
                target: Target::Node(new_id),
                deadline: not_after,
                what: What::Assign { uid, new_id },
                frame: commit,
                select: Some(select),
                accepted: acc.now,
                expires: acc.expires,
                fate: Fate::Queued,
                origin: acc.origin.map(Box::new),
            },
        );
        self.counters.sent += 1;
        // Select before commit: a node only takes the commit after the matching select.
        out.send_until(select, not_after);
        out.send_until(commit, not_after);
        Ok(())
    }

    /// Queues an acknowledged frame of the bridge's own to `dest`, built by `msg` from a free
    /// sequence number (returned); `None`, and nothing sent, when every number is in use.
    pub(crate) fn send_internal(
        &mut self,
        owner: FrameOwner,
        dest: NodeId,
        kind: Kind,
        msg: impl FnOnce(Seq) -> Message,
        now: Instant,
        out: &mut Outputs,
    ) -> Option<Seq> {
        let Some(seq) = self.alloc_seq(dest, kind) else {
            tracing::warn!(%dest, ?kind, "every sequence number is in use: frame not sent");
            return None;
        };
        let frame = Packet::command(dest, msg(seq));
        self.insert(
            (dest, kind, seq),
            PendingCommand {
                request_id: None,
                target: Target::from_dest(dest),
                deadline: now + self.timeout,
                what: What::Internal,
                frame,
                select: None,
                accepted: now,
                expires: None,
                fate: Fate::Queued,
                origin: None,
            },
        );
        out.send(frame, owner);
        Some(seq)
    }

    /// An `Ack` from `src`. Ends the command it answers; for a frame of the bridge's own, frees its
    /// sequence number (what the ack means to the concern that sent the frame, e.g. the docking
    /// sequence, is the caller's to route: a late ack finds no entry here and still counts there).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn on_ack(
        &mut self,
        src: NodeId,
        kind: Kind,
        seq: Seq,
        result: AckResult,
        registry: &mut Registry,
        now: Instant,
        out: &mut Outputs,
    ) {
        let key = (src, kind, seq);
        if let Some(p) = self.pending.get(&key) {
            if matches!(p.what, What::Internal) {
                let frame = p.frame;
                self.remove(&key);
                if result != AckResult::Ok {
                    tracing::debug!(%src, ?kind, seq, %result, "the node refused a frame of the gateway's own");
                    return;
                }
                // What the node now shows (a procedure's light, the relay the docking switched
                // off) is in its state document like a command's.
                let action = match frame.msg {
                    Message::LedSet { cmd, .. } => Some(NodeAction::Led(cmd)),
                    Message::BuzzerSet { cmd, .. } => Some(NodeAction::Buzzer(cmd)),
                    Message::PowerSet { on, .. } => Some(NodeAction::Power(on)),
                    _ => None,
                };
                if let Some(action) = action {
                    apply_action_state(registry, out, src, action, now);
                }
                return;
            }
            let Some(p) = self.remove(&key) else {
                return;
            };
            let What::Node(action) = p.what else {
                return;
            };
            if result == AckResult::Ok {
                apply_action_state(registry, out, src, action, now);
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
        let What::Broadcast { action, answers } = &mut p.what else {
            return;
        };
        let action = *action;
        let Answers {
            expected,
            acked,
            refused,
        } = &mut **answers;
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
            apply_action_state(registry, out, src, action, now);
        }
        if complete {
            if let Some(p) = self.remove(&key) {
                self.finish_broadcast(p, None, out);
            }
        }
    }

    /// An `AssignReply` (from the board's new ID, or from an unconfigured board). Returns the
    /// board's UID when it confirmed its new ID: the gateway now knows which board `new_id` is.
    pub(crate) fn on_assign_reply(
        &mut self,
        seq: Seq,
        result: AckResult,
        new_id: NodeId,
        uid_tail: [u8; 4],
        out: &mut Outputs,
    ) -> Option<Uid> {
        let key = (NodeId::BROADCAST, Kind::AssignCommit, seq);
        let matches = matches!(self.pending.get(&key), Some(PendingCommand { what: What::Assign { uid, .. }, .. }) if uid.tail() == uid_tail);
        if !matches {
            tracing::debug!(seq, %new_id, "assign reply for no pending assign");
            return None;
        }
        let p = self.remove(&key)?;
        let (wanted, uid) = match p.what {
            What::Assign { new_id, uid } => (new_id, Some(uid)),
            _ => (new_id, None),
        };
        if result == AckResult::Ok && new_id != wanted {
            let reason = format!("the board answered with id {new_id} instead of {wanted}");
            self.emit_result(p, Outcome::Refused, Some(reason), out);
            None
        } else if result == AckResult::Ok {
            self.emit_result(p, Outcome::Ok, None, out);
            uid
        } else {
            self.emit_result(p, Outcome::Refused, Some(result.to_string()), out);
            None
        }
    }

    /// The pending entry `packet` carries: its key, if any.
    fn carrier(&self, packet: &Packet) -> Option<PendingKey> {
        match packet.msg {
            Message::AssignSelect { .. } => self
                .pending
                .iter()
                .find(|(_, p)| p.select.as_ref() == Some(packet))
                .map(|(k, _)| k),
            _ => key_of(packet).filter(|k| {
                self.pending
                    .get(k)
                    .is_some_and(|p| p.frame == *packet || p.select.as_ref() == Some(packet))
            }),
        }
    }

    /// What became of `packet` (a frame queued here). True when a command's frame could not be
    /// sent and its command ended `failed`; otherwise the caller reports a failure.
    pub(crate) fn on_fate(
        &mut self,
        packet: &Packet,
        fate: FrameFate<'_>,
        now: Instant,
        out: &mut Outputs,
    ) -> bool {
        match fate {
            FrameFate::Transmitted => self.on_transmitted(packet, now),
            FrameFate::Withdrawn => self.on_withdrawn(packet, now, out),
            FrameFate::Failed(reason) => return self.on_send_failed(packet, reason, out),
            FrameFate::Unconfirmed(why) => self.on_unconfirmed(packet, why, now, out),
        }
        false
    }

    /// `packet` left the bridge's queue for the adapter.
    pub(crate) fn on_handed(&mut self, packet: &Packet, now: Instant) {
        if matches!(packet.msg, Message::AssignSelect { .. }) {
            return;
        }
        if let Some(p) = self.carrier(packet).and_then(|k| self.pending.get_mut(&k)) {
            if p.fate == Fate::Queued {
                p.fate = Fate::Handed(now);
            }
        }
    }

    /// The adapter confirmed `packet` on the bus: the node has `command_timeout` from now to answer.
    fn on_transmitted(&mut self, packet: &Packet, now: Instant) {
        if matches!(packet.msg, Message::AssignSelect { .. }) {
            return;
        }
        let Some(key) = self.carrier(packet) else {
            return;
        };
        if let Some(p) = self.pending.get_mut(&key) {
            if matches!(p.fate, Fate::OnBus(_)) {
                return;
            }
            p.fate = Fate::OnBus(now);
        }
        self.pending.set_deadline(&key, now + self.timeout);
    }

    /// The adapter can no longer tell whether `packet` reaches the bus (`why`); a command past its
    /// deadline ends now.
    fn on_unconfirmed(
        &mut self,
        packet: &Packet,
        why: &'static str,
        now: Instant,
        out: &mut Outputs,
    ) {
        if matches!(packet.msg, Message::AssignSelect { .. }) {
            return;
        }
        let Some(key) = self.carrier(packet) else {
            return;
        };
        let overdue = match self.pending.get_mut(&key) {
            Some(p) if matches!(p.fate, Fate::Handed(_) | Fate::Queued) => {
                p.fate = Fate::Unconfirmed(why);
                p.accepted + self.timeout <= now
            }
            _ => return,
        };
        if overdue {
            self.pending.set_deadline(&key, now);
            self.expire(now, out);
        } else {
            let d = self.pending.get(&key).map(|p| p.accepted + self.timeout);
            if let Some(d) = d {
                self.pending.set_deadline(&key, d);
            }
        }
    }

    /// `packet` could not be sent: if it carried a command, that command ends `failed` (returns
    /// true); otherwise the caller reports it (a frame of the bridge's own frees its number).
    fn on_send_failed(&mut self, packet: &Packet, reason: &str, out: &mut Outputs) -> bool {
        let Some(key) = self.carrier(packet) else {
            return false;
        };
        let Some(p) = self.remove(&key) else {
            return false;
        };
        if matches!(p.what, What::Internal) {
            return false;
        }
        // The commit must not follow a select that failed, nor the other way round.
        withdraw(&p, out);
        self.emit_result(p, Outcome::Failed, Some(format!("not sent: {reason}")), out);
        true
    }

    /// The adapter did not write `packet` because its `not_after` had passed.
    fn on_withdrawn(&mut self, packet: &Packet, now: Instant, out: &mut Outputs) {
        let Some(key) = self.carrier(packet) else {
            return;
        };
        if let Some(p) = self.remove(&key) {
            self.end_unsent(p, 0, now, out);
        }
    }

    /// Ends every command whose deadline passed: a frame still queued is withdrawn (`expired` or
    /// `failed`), a frame on the bus without an answer is a `timeout`.
    pub(crate) fn expire(&mut self, now: Instant, out: &mut Outputs) {
        for k in self.pending.overdue(now) {
            let Some(p) = self.pending.get(&k) else {
                continue;
            };
            let internal = matches!(p.what, What::Internal);
            match p.fate {
                // Its fate is the adapter's to tell (echo, failure, or no echo in time).
                Fate::Handed(t) if t + TRANSMIT_CONFIRM_TIMEOUT > now => {
                    self.pending.set_deadline(&k, t + TRANSMIT_CONFIRM_TIMEOUT)
                }
                // A frame of our own keeps its number while it may still reach the bus.
                Fate::Queued | Fate::Handed(_) if internal => {
                    self.pending.set_deadline(&k, now + self.timeout)
                }
                _ if internal => {
                    self.remove(&k);
                }
                Fate::Queued => {
                    if let Some(p) = self.remove(&k) {
                        let ahead = out.transmit.ahead_of(&p.frame);
                        withdraw(&p, out);
                        self.end_unsent(p, ahead, now, out);
                    }
                }
                Fate::Handed(_) => {
                    if let Some(p) = self.remove(&k) {
                        let why = "the CAN interface did not confirm sending it";
                        self.finish_timed_out(p, Some(why), out);
                    }
                }
                Fate::OnBus(_) => {
                    if let Some(p) = self.remove(&k) {
                        self.finish_timed_out(p, None, out);
                    }
                }
                Fate::Unconfirmed(why) => {
                    if let Some(p) = self.remove(&k) {
                        self.finish_timed_out(p, Some(why), out);
                    }
                }
            }
        }
    }

    /// A command whose frame never left the gateway: `expired` if its ttl is over, else `failed`.
    fn end_unsent(&mut self, p: PendingCommand, ahead: usize, now: Instant, out: &mut Outputs) {
        if let Some(expires) = p.expires.filter(|&e| e <= now) {
            let waited = millis(now.saturating_duration_since(p.accepted));
            let ttl = millis(expires.saturating_duration_since(p.accepted));
            let reason = format!(
                "not sent: its ttl ({ttl} ms after it was accepted) ended while it waited {waited} ms for the CAN bus"
            );
            self.emit_result(p, Outcome::Expired, Some(reason), out);
        } else {
            let reason = format!(
                "not sent within {} ms: the CAN transmit queue was behind ({ahead} frames ahead of it)",
                self.timeout.as_millis()
            );
            self.emit_result(p, Outcome::Failed, Some(reason), out);
        }
    }

    /// A command that may or may not have been carried out: its nodes' state is read back.
    fn finish_timed_out(
        &mut self,
        p: PendingCommand,
        unconfirmed: Option<&str>,
        out: &mut Outputs,
    ) {
        match &p.what {
            What::Node(_) => {
                if let Target::Node(id) = p.target {
                    out.unsure.insert(id);
                }
            }
            What::Broadcast { answers, .. } => out.unsure.extend(
                answers
                    .expected
                    .iter()
                    .filter(|id| !answers.acked.contains(id) && !answers.refused.contains_key(id)),
            ),
            What::Assign { .. } | What::Internal => {}
        }
        let tail = unconfirmed
            .map(|why| format!("; {why}, so it may still reach the bus"))
            .unwrap_or_default();
        match &p.what {
            What::Broadcast { .. } => self.finish_broadcast(p, unconfirmed.map(|_| tail), out),
            What::Assign { .. } => {
                let reason = format!(
                    "no AssignReply within {} ms (is a board with this uid on the bus?){tail}",
                    self.timeout.as_millis()
                );
                self.emit_result(p, Outcome::Timeout, Some(reason), out);
            }
            What::Node(_) => {
                let reason = format!("no ack within {} ms{tail}", self.timeout.as_millis());
                self.emit_result(p, Outcome::Timeout, Some(reason), out);
            }
            What::Internal => {}
        }
    }

    fn finish_broadcast(&mut self, p: PendingCommand, tail: Option<String>, out: &mut Outputs) {
        let What::Broadcast { answers, .. } = &p.what else {
            return;
        };
        let Answers {
            expected,
            acked,
            refused,
        } = &**answers;
        let missing: Vec<HexId> = expected
            .iter()
            .filter(|id| !acked.contains(id) && !refused.contains_key(id))
            .map(|&id| HexId(id))
            .collect();
        let answered = acked.len() + refused.len();
        let tail = tail.unwrap_or_default();
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
                    "{} of {} online nodes did not answer{tail}",
                    missing.len(),
                    expected.len()
                )),
            )
        } else if acked.is_empty() {
            (Outcome::Timeout, Some(format!("no node answered{tail}")))
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
            origin: p.origin.map(|o| *o),
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
            if matches!(result, Outcome::Ok | Outcome::Refused | Outcome::Timeout) {
                return self.finish_broadcast(p, None, out);
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
            origin: p.origin.map(|o| *o),
        }));
    }

    fn count(&mut self, outcome: Outcome) {
        let c = &mut self.counters;
        match outcome {
            Outcome::Ok => c.ok += 1,
            Outcome::Refused => c.refused += 1,
            Outcome::Timeout => c.timeout += 1,
            Outcome::Failed => c.failed += 1,
            Outcome::Expired => c.expired += 1,
        }
    }
}

/// Takes a command's frames out of the transmit queue (those still there).
fn withdraw(p: &PendingCommand, out: &mut Outputs) {
    if let Some(s) = &p.select {
        out.transmit.withdraw(s);
    }
    out.transmit.withdraw(&p.frame);
}

/// Records what a node acknowledged at `now` in its state document.
fn apply_action_state(
    registry: &mut Registry,
    out: &mut Outputs,
    node: NodeId,
    action: NodeAction,
    now: Instant,
) {
    if let Some(e) = registry.get_mut(node) {
        match action {
            NodeAction::Led(cmd) => {
                e.led = Some(cmd);
                e.acked_at.led = Some(now);
            }
            NodeAction::Buzzer(cmd) => {
                e.buzzer = Some(cmd);
                e.acked_at.buzzer = Some(now);
            }
            NodeAction::Power(on) => {
                e.relay = Some(on);
                e.acked_at.relay = Some(now);
            }
            NodeAction::Identify(_) => return,
        }
        out.mark_changed(node);
    }
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    use crate::bridge::test_support::*;
    use crate::bridge::*;
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

    /// Fills the transmit window with frames nobody confirms: later frames wait in the bridge.
    fn fill_window(b: &mut Bridge, now: Instant) {
        for n in 0..TRANSMIT_WINDOW {
            let cmd = json!({"cmd": "identify", "node": "3", "seconds": n as u64 + 1});
            b.handle_command(cmd.to_string().as_bytes(), now);
        }
        assert_eq!(drain_unconfirmed(b).sent.len(), TRANSMIT_WINDOW);
        assert_eq!(b.transmit_backlog(), (0, TRANSMIT_WINDOW));
    }

    #[test]
    fn a_command_still_queued_at_its_deadline_is_withdrawn_and_never_sent() {
        let (mut b, t0) = with_nodes(&[2, 3]);
        fill_window(&mut b, t0);
        b.handle_command(
            json!({"cmd": "power", "node": "2", "on": true, "request_id": "p"})
                .to_string()
                .as_bytes(),
            t0,
        );
        assert!(
            drain_unconfirmed(&mut b).sent.is_empty(),
            "the window is full"
        );
        let timeout = BridgeConfig::default().command_timeout;
        assert_eq!(b.poll_timeout(), t0 + timeout);
        b.handle_timeout(t0 + timeout);
        let out = drain_unconfirmed(&mut b);
        let r = out
            .named("command_result")
            .into_iter()
            .find(|r| r["payload"]["request_id"] == "p")
            .expect("the power command's result")["payload"]
            .clone();
        assert_eq!(r["result"], "failed");
        assert_eq!(
            r["reason"],
            "not sent within 500 ms: the CAN transmit queue was behind (0 frames ahead of it)"
        );
        // The window's frames were never confirmed: their commands end `timeout`, saying so.
        let unconfirmed: Vec<_> = out
            .named("command_result")
            .into_iter()
            .filter(|r| r["payload"]["cmd"] == "identify")
            .collect();
        assert!(unconfirmed.is_empty(), "they wait for their echo first");
        b.handle_timeout(t0 + TRANSMIT_CONFIRM_TIMEOUT);
        let out = drain_unconfirmed(&mut b);
        let results = out.named("command_result");
        assert_eq!(results.len(), TRANSMIT_WINDOW);
        for r in results {
            assert_eq!(r["payload"]["result"], "timeout");
            assert_eq!(
                r["payload"]["reason"],
                "no ack within 500 ms; the CAN interface did not confirm sending it, so it may still reach the bus"
            );
        }
        // The window is free again, and the withdrawn power frame is never handed out.
        assert!(out
            .sent
            .iter()
            .all(|p| !matches!(p.msg, Message::PowerSet { .. })));
        assert_eq!(b.transmit_backlog().0, 0);
        let c = b.command_counters();
        assert_eq!((c.failed, c.timeout, c.in_flight), (1, 8, 0));
    }

    #[test]
    fn ttl_expires_a_command_that_could_not_be_sent_in_time() {
        let (mut b, t0) = with_nodes(&[2, 3]);
        fill_window(&mut b, t0);
        let cmd =
            json!({"cmd": "led", "node": "2", "color": "red", "ttl_ms": 100, "request_id": "t"});
        b.handle_command(cmd.to_string().as_bytes(), t0);
        assert!(drain(&mut b).events.is_empty());
        assert_eq!(
            b.poll_timeout(),
            t0 + 100 * MS,
            "the ttl is the first deadline"
        );
        // The adapter has room again just after the ttl: the frame is not handed out any more.
        b.handle_transmitted(
            Packet::command(id(3), Message::Identify { seq: 0, seconds: 1 }),
            t0 + 100 * MS,
        );
        let t = b.poll_transmit(t0 + 100 * MS);
        assert!(t.is_none(), "{t:?}");
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(
            (r["result"].as_str(), r["request_id"].as_str()),
            (Some("expired"), Some("t"))
        );
        assert_eq!(
            r["reason"],
            "not sent: its ttl (100 ms after it was accepted) ended while it waited 100 ms for the CAN bus"
        );
        assert_eq!(b.command_counters().expired, 1);

        // A command whose ttl ended before the bridge got it is never queued.
        let received = t0 + S;
        let late = Delivery::live(received);
        let cmd = json!({"cmd": "power", "node": "2", "on": true, "ttl_ms": 50});
        b.handle_delivered_command(cmd.to_string().as_bytes(), late, received + 50 * MS);
        let out = drain(&mut b);
        assert!(out.sent.is_empty());
        let r = out.one("command_result");
        assert_eq!(r["result"], "expired");
        assert_eq!(
            r["reason"],
            "not sent: its ttl (50 ms after the gateway received it) ended before it could be queued (50 ms)"
        );

        // Once on the bus, a ttl changes nothing: the node has its full timeout to answer.
        let (mut b, t0) = with_nodes(&[2]);
        let out = command(
            &mut b,
            json!({"cmd": "led", "node": "2", "off": true, "ttl_ms": 10}),
            t0,
        );
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(2), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + 400 * MS,
        );
        assert_eq!(drain(&mut b).one("command_result")["result"], "ok");
    }

    #[test]
    fn the_ack_window_starts_when_the_frame_is_on_the_bus() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_command(
            json!({"cmd": "led", "node": "2", "off": true})
                .to_string()
                .as_bytes(),
            t0,
        );
        let frame = b.poll_transmit(t0).unwrap().packet;
        let timeout = BridgeConfig::default().command_timeout;
        // Written, echoed late (a busy bus): no verdict before the echo plus the timeout.
        b.handle_timeout(t0 + timeout);
        assert!(drain_unconfirmed(&mut b).events.is_empty());
        b.handle_transmitted(frame, t0 + 600 * MS);
        b.handle_timeout(t0 + 600 * MS + timeout - MS);
        assert!(drain(&mut b).named("command_result").is_empty());
        b.handle_timeout(t0 + 600 * MS + timeout);
        let out = drain(&mut b);
        assert_eq!(out.one("command_result")["reason"], "no ack within 500 ms");
    }

    #[test]
    fn frames_the_adapter_withdrew_or_lost_with_the_interface() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_command(
            json!({"cmd": "power", "node": "2", "on": false, "ttl_ms": 20})
                .to_string()
                .as_bytes(),
            t0,
        );
        let t = b.poll_transmit(t0).unwrap();
        assert_eq!(t.not_after, Some(t0 + 20 * MS));
        // The adapter could not write it before `not_after`: never sent.
        b.handle_withdrawn(t.packet, t0 + 30 * MS);
        assert_eq!(drain(&mut b).one("command_result")["result"], "expired");

        b.handle_command(
            json!({"cmd": "power", "node": "2", "on": false})
                .to_string()
                .as_bytes(),
            t0 + S,
        );
        let t = b.poll_transmit(t0 + S).unwrap();
        assert_eq!(
            t.not_after,
            Some(t0 + S + BridgeConfig::default().command_timeout)
        );
        b.handle_bus_event(BusEvent::InterfaceDown, t0 + S + MS);
        assert_eq!(b.transmit_backlog(), (0, 0), "the window is cleared");
        b.handle_timeout(t0 + S + BridgeConfig::default().command_timeout);
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(r["result"], "timeout");
        assert_eq!(
            r["reason"],
            "no ack within 500 ms; the CAN interface went down before confirming it was sent, so it may still reach the bus"
        );
    }

    #[test]
    fn sequence_numbers_of_the_bridges_own_frames_are_never_reused() {
        // Unanswered power commands stay pending for a minute.
        let (mut b, t0) = {
            let t0 = Instant::now();
            let config = BridgeConfig {
                command_timeout: Duration::from_secs(60),
                ..BridgeConfig::default()
            };
            let mut b = Bridge::new(config, t0);
            b.handle_timeout(t0);
            drain(&mut b);
            b.handle_packet(Packet::report(id(0x10), reply(0, 0)), t0);
            drain(&mut b);
            (b, t0)
        };
        let mut seqs = std::collections::BTreeSet::new();
        for _ in 0..255 {
            let out = command(
                &mut b,
                json!({"cmd": "power", "node": "10", "on": true}),
                t0,
            );
            assert!(seqs.insert(out.sent[0].msg.ack_seq().unwrap()));
        }
        b.handle_packet(
            Packet::report(id(0x10), Message::DockDetected { port: port(1) }),
            t0,
        );
        drain(&mut b);
        b.handle_timeout(t0 + BridgeConfig::default().dock_timeout);
        let out = drain(&mut b);
        let off = out
            .sent
            .iter()
            .find_map(|p| match p.msg {
                Message::PowerSet { seq, on: false } => Some(seq),
                _ => None,
            })
            .expect("relay off after the failed docking");
        assert!(
            seqs.insert(off),
            "the relay-off frame took the one free number"
        );
        // Every number is in use now: a command is refused, none is reused.
        let out = command(
            &mut b,
            json!({"cmd": "power", "node": "10", "on": true}),
            t0 + 6 * S,
        );
        assert!(out.sent.is_empty());
        assert_eq!(
            out.one("command_rejected")["reason"],
            "power: 256 power commands to node 10 are still unanswered; wait for their results"
        );
        // The node acknowledges the relay-off: that number is free again, and only that one.
        b.handle_packet(
            Packet::report(id(0x10), ack(Kind::PowerSet, off, AckResult::Ok)),
            t0 + 6 * S,
        );
        let out = command(
            &mut b,
            json!({"cmd": "power", "node": "10", "on": true}),
            t0 + 6 * S,
        );
        assert_eq!(out.sent[0].msg.ack_seq(), Some(off));
    }
}

#[cfg(test)]
mod pending_tests {
    use super::*;

    fn entry(id: u16, seq: Seq, deadline: Instant) -> (PendingKey, PendingCommand) {
        let dest = NodeId::new(id).unwrap();
        let frame = Packet::command(dest, Message::PowerSet { seq, on: true });
        let key = (dest, Kind::PowerSet, seq);
        let command = PendingCommand {
            request_id: None,
            target: Target::Node(dest),
            deadline,
            what: What::Internal,
            frame,
            select: None,
            accepted: deadline,
            expires: None,
            fate: Fate::Queued,
            origin: None,
        };
        (key, command)
    }

    #[test]
    fn deadlines_come_out_earliest_first_and_moved_ones_only_once() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut p = PendingTable::default();
        for (i, at) in [30u64, 10, 20, 40].into_iter().enumerate() {
            let (k, c) = entry(2, i as u8, t0 + ms(at));
            p.insert(k, c);
        }
        let key = |seq| (NodeId::new(2).unwrap(), Kind::PowerSet, seq);
        // seq 1 (10 ms) moves past seq 0 (30 ms), then back before it: only its last deadline counts.
        p.set_deadline(&key(1), t0 + ms(35));
        p.set_deadline(&key(1), t0 + ms(25));
        // Moved later: its first deadline comes first, and is pushed again, not overdue.
        assert_eq!(p.next_deadline(), Some(t0 + ms(10)));
        assert_eq!(p.overdue(t0 + ms(10)), vec![]);
        assert_eq!(p.next_deadline(), Some(t0 + ms(20)));
        p.remove(&key(2));
        assert_eq!(
            p.next_deadline(),
            Some(t0 + ms(25)),
            "a removed command's deadline is gone"
        );
        // Moved earlier: pushed at once.
        p.set_deadline(&key(3), t0 + ms(15));
        assert_eq!(p.next_deadline(), Some(t0 + ms(15)));
        p.set_deadline(&key(3), t0 + ms(40));
        assert_eq!(p.overdue(t0 + ms(30)), vec![key(1), key(0)]);
        // Taken off the heap: not overdue twice, though still pending until the caller acts.
        assert_eq!(p.overdue(t0 + ms(30)), vec![]);
        assert_eq!(p.next_deadline(), Some(t0 + ms(40)));
        assert_eq!(p.overdue(t0 + ms(40)), vec![key(3)]);
        assert!(p.get(&key(0)).is_some());
    }

    #[test]
    fn moving_deadlines_does_not_grow_the_heap_without_bound() {
        let t0 = Instant::now();
        let mut p = PendingTable::default();
        for seq in 0..4 {
            let (k, c) = entry(3, seq, t0);
            p.insert(k, c);
        }
        for i in 0..10_000u64 {
            let k = (NodeId::new(3).unwrap(), Kind::PowerSet, (i % 4) as u8);
            p.set_deadline(&k, t0 + Duration::from_millis(10_000 - i));
        }
        // Their first deadlines (t0) come first and are pushed again with the last ones.
        assert_eq!(p.overdue(t0), vec![]);
        assert!(
            p.deadlines.len() <= 2 * 4 + 64 + 1,
            "{} heap entries",
            p.deadlines.len()
        );
        assert_eq!(
            p.next_deadline(),
            Some(t0 + Duration::from_millis(10_000 - 9_999))
        );
    }

    #[test]
    fn removing_from_the_middle_keeps_every_other_command_found() {
        let t0 = Instant::now();
        let mut p = PendingTable::default();
        let id = NodeId::new(5).unwrap();
        let key = |seq| (id, Kind::PowerSet, seq);
        for seq in 0..=255u8 {
            let (k, c) = entry(5, seq, t0 + Duration::from_millis(u64::from(seq)));
            p.insert(k, c);
        }
        for seq in (0..=255u8).filter(|s| s % 3 == 1) {
            assert_eq!(
                p.remove(&key(seq)).map(|c| c.frame),
                Some(entry(5, seq, t0).1.frame)
            );
        }
        for seq in 0..=255u8 {
            let found = p.get(&key(seq)).map(|c| c.frame);
            let want = (seq % 3 != 1).then(|| entry(5, seq, t0).1.frame);
            assert_eq!(found, want, "seq {seq}");
        }
        assert_eq!(p.iter().count(), 256 - 85);
        // A burst to a second node, then most commands gone: the room it took is given back.
        for seq in 0..=255u8 {
            let (k, c) = entry(6, seq, t0);
            p.insert(k, c);
        }
        assert!(p.slots.capacity() >= 256 + 171);
        for seq in 0..=255u8 {
            p.remove(&(NodeId::new(6).unwrap(), Kind::PowerSet, seq));
        }
        for seq in (0..=255u8).filter(|s| s % 3 != 1 && *s > 9) {
            p.remove(&key(seq));
        }
        assert_eq!(p.slots.len(), 7);
        assert!(p.slots.capacity() <= 256, "capacity {}", p.slots.capacity());
        assert_eq!(
            p.get(&key(9)).map(|c| c.deadline),
            Some(t0 + Duration::from_millis(9))
        );
        assert_eq!(p.next_deadline(), Some(t0));
    }

    #[test]
    fn taken_seqs_follow_inserts_and_removals() {
        let t0 = Instant::now();
        let mut p = PendingTable::default();
        let id = NodeId::new(4).unwrap();
        for seq in [0u8, 63, 64, 255] {
            let (k, c) = entry(4, seq, t0);
            p.insert(k, c);
        }
        let want = [1 | 1 << 63, 1, 0, 1 << 63];
        assert_eq!(p.taken_seqs(id, Kind::PowerSet), want);
        assert_eq!(p.taken_seqs(id, Kind::LedSet), [0; 4], "per kind");
        for seq in [0u8, 63, 64, 255] {
            p.remove(&(id, Kind::PowerSet, seq));
        }
        assert_eq!(p.taken_seqs(id, Kind::PowerSet), [0; 4]);
        assert!(p.taken.is_empty(), "empty sets are dropped");
    }
}
