//! The one-docking-at-a-time sequence (the seed's new-member mutex) and the record of docking
//! connections. Inputs are dock reports, handshakes, confirm acks, time, and what static elements
//! report of their ports when asked (state read-back); outputs are [`Step`]s that the bridge turns
//! into frames and events.
//!
//! A connection becomes known in two ways: a docking completes (handshake: `new_connection`, and the
//! static element is told its partner with `DockLink`), or a static element reports a link it was
//! given earlier (read-back after a gateway restart or a bus outage: recorded *silently*, because
//! that docking already existed and its `new_connection` was published when it happened).
//!
//! A mobile element that gets power while already docked — on a port whose relay is on for
//! another element, or switched on by a `power` command after a failed docking — sends its
//! handshake with no docking pending. It is *adopted*: when exactly one closed signal loop of an
//! online static element whose relay is on has no element recorded on it, that is where it docked
//! (the static element is sent `DockConfirm`, so the port powers and unpowers it like any docking,
//! then the usual `new_connection` and `DockLink`). Otherwise the handshake is kept for a quarter
//! of the docking timeout: a report of a new docking by a static element whose relay is on in that
//! time is answered by it at once (the handshake overtook the report). Only a handshake still
//! unmatched when that window ends is an `unexpected_handshake` fault.
//!
//! A docking that fails (no handshake in time) leaves the static element's relay as it was before
//! the docking: switched off when it was off and nothing else is docked there, left on when it was
//! on (a `power` command) or other elements are docked there; `dock_failed` says which.

pub(crate) mod glue;

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use ihex_proto::{DockState, NodeId, Port};

use crate::event::{Connection, End, HexId, Link};

/// What the bridge must do for the docking sequence.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Step {
    /// Send `DockConfirm{port}` to the static `node` (the bridge then calls [`Docking::confirm_sent`]).
    Confirm {
        /// The static element.
        node: NodeId,
        /// Its dock port.
        port: Port,
    },
    /// Send `DockRefuse{port, Busy}` to `node`: the queue is full.
    RefuseBusy {
        /// The static element.
        node: NodeId,
        /// Its dock port.
        port: Port,
    },
    /// Send `PowerSet{on: false}` to `node`: its docking failed and nothing else is docked on it.
    PowerOff {
        /// The static element.
        node: NodeId,
    },
    /// Send `DockRefuse{port, NotAllowed}` to `node`: its docking on `port` failed, but other
    /// elements docked on it stay powered (the node switches its relay off only with no confirmed
    /// port left).
    Withdraw {
        /// The static element.
        node: NodeId,
        /// Its dock port.
        port: Port,
    },
    /// Send `DockConfirm{port}` to the static `node` for a docking completed without a pending
    /// confirm (an adopted handshake): the port then holds the relay like any confirmed docking.
    /// Nothing waits for its acknowledgement.
    Adopt {
        /// The static element.
        node: NodeId,
        /// Its dock port.
        port: Port,
    },
    /// Publish `new_connection`.
    Connected(Connection),
    /// Publish `connection_removed`.
    Removed(Connection),
    /// A connection learnt from a static element's report: recorded without an event (both
    /// elements' state documents change).
    Restored(Connection),
    /// Send `DockLink { port, partner: none }` to the static `node`: the link it holds for that
    /// port is no longer true (its mobile element was lost, or docked elsewhere).
    Unlink {
        /// The static element.
        node: NodeId,
        /// Its dock port.
        port: Port,
    },
    /// Publish `dock_failed`.
    Failed {
        /// The static element.
        node: NodeId,
        /// Its dock port.
        port: Port,
        /// Why.
        reason: String,
        /// The relay as the failure left it: `Some(false)` switched off ([`Step::PowerOff`]),
        /// `Some(true)` left on, `None` not touched by the gateway.
        relay: Option<bool>,
    },
    /// A handshake nobody waited for: publish a `fault` (`unexpected_handshake`), record nothing.
    UnexpectedHandshake {
        /// The element that sent it.
        node: NodeId,
        /// The port it named.
        port: Port,
        /// Why it was not expected.
        why: &'static str,
    },
}

/// A docking waiting for its handshake.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Pending {
    /// The static element.
    pub node: NodeId,
    /// Its dock port.
    pub port: Port,
    /// When the handshake is overdue.
    pub deadline: Instant,
    /// Sequence number of the `DockConfirm` sent, once sent.
    pub confirm_seq: Option<u8>,
    /// The static element's relay was on before this docking (a `power` command, or other
    /// elements docked there): a failure leaves it on.
    pub relay_was_on: bool,
}

/// Docking state: at most one pending docking, a bounded FIFO of waiting reports, the connections,
/// and the handshakes no docking has claimed yet.
#[derive(Debug)]
pub struct Docking {
    timeout: Duration,
    queue_cap: usize,
    pending: Option<Pending>,
    /// Reports waiting for their turn, and whether the relay was on when each came.
    queue: VecDeque<(NodeId, Port)>,
    queued_relay_on: BTreeMap<(NodeId, Port), bool>,
    /// (static, its port) -> the mobile element and its port, and when it was recorded.
    connections: BTreeMap<(NodeId, Port), Record>,
    /// Handshakes that came with no docking pending and no free closed loop to adopt them: (the
    /// mobile element, its port, when, why it could not be placed), oldest first, at most
    /// `queue_cap`. One still here a quarter of the timeout later is a fault.
    unclaimed: VecDeque<(NodeId, Port, Instant, &'static str)>,
}

/// A recorded connection, seen from its static element's port.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
struct Record {
    mobile: (NodeId, Port),
    since: Instant,
    /// Adopted before its static element's `DockDetected` may have reached us: the first such
    /// report within the docking timeout is this docking's, not a new one.
    adopted: bool,
}

fn conn(stat: (NodeId, Port), mobile: (NodeId, Port)) -> Connection {
    Connection {
        n: End {
            id: HexId(mobile.0),
            port: mobile.1.get(),
        },
        n_1: End {
            id: HexId(stat.0),
            port: stat.1.get(),
        },
    }
}

impl Docking {
    /// Default bound of the waiting queue.
    pub const DEFAULT_QUEUE: usize = 8;

    /// Idle, with this handshake timeout and queue bound.
    pub fn new(timeout: Duration, queue_cap: usize) -> Self {
        Docking {
            timeout,
            queue_cap,
            pending: None,
            queue: VecDeque::new(),
            queued_relay_on: BTreeMap::new(),
            connections: BTreeMap::new(),
            unclaimed: VecDeque::new(),
        }
    }

    /// The docking in progress.
    pub fn pending(&self) -> Option<Pending> {
        self.pending
    }

    /// Reports waiting for their turn, oldest first.
    pub fn queued(&self) -> impl Iterator<Item = &(NodeId, Port)> {
        self.queue.iter()
    }

    /// When [`Docking::tick`] must run next: the pending handshake is overdue, or an unclaimed
    /// handshake's window ends.
    pub fn deadline(&self) -> Option<Instant> {
        let unclaimed = self.unclaimed.front().map(|u| u.2 + self.timeout / 4);
        match (self.pending.map(|p| p.deadline), unclaimed) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// Remembers the sequence number of the confirm just sent to `node` for its `port`, if that is
    /// the pending docking (a confirm of a docking already completed by a handshake is not).
    pub fn confirm_sent(&mut self, node: NodeId, port: Port, seq: u8) {
        if let Some(p) = &mut self.pending {
            if p.node == node && p.port == port {
                p.confirm_seq = Some(seq);
            }
        }
    }

    /// The connections of `id`, seen from `id` (as static or as mobile element).
    pub fn links_of(&self, id: NodeId) -> Vec<Link> {
        let mut links = Vec::new();
        for (
            &(s, sp),
            &Record {
                mobile: (m, mp), ..
            },
        ) in &self.connections
        {
            if s == id {
                links.push(Link {
                    port: sp.get(),
                    peer: HexId(m),
                    peer_port: mp.get(),
                });
            }
            if m == id {
                links.push(Link {
                    port: mp.get(),
                    peer: HexId(s),
                    peer_port: sp.get(),
                });
            }
        }
        links
    }

    /// Every recorded connection.
    pub fn connections(&self) -> Vec<Connection> {
        self.connections
            .iter()
            .map(|(&s, r)| conn(s, r.mobile))
            .collect()
    }

    fn start(
        &mut self,
        node: NodeId,
        port: Port,
        relay_was_on: bool,
        now: Instant,
        out: &mut Vec<Step>,
    ) {
        // A new docking on a port that still has a recorded connection means the old element left
        // without a DockRemoved reaching us.
        if let Some(r) = self.connections.remove(&(node, port)) {
            out.push(Step::Removed(conn((node, port), r.mobile)));
        }
        self.pending = Some(Pending {
            node,
            port,
            deadline: now + self.timeout,
            confirm_seq: None,
            relay_was_on,
        });
        out.push(Step::Confirm { node, port });
    }

    /// A handshake that overtook the report of the docking just started (the element got power
    /// before the confirm, from a relay already on) completes it at once.
    fn claim_unclaimed(&mut self, node: NodeId, port: Port, now: Instant, out: &mut Vec<Step>) {
        self.expire_unclaimed(now, out);
        let Some(i) = self.unclaimed.iter().position(|&(m, ..)| m != node) else {
            return;
        };
        if let Some((m, mp, ..)) = self.unclaimed.remove(i) {
            self.complete((node, port), (m, mp), false, now, out);
            self.next(now, out);
        }
    }

    /// Ends the unclaimed handshakes older than a quarter of the docking timeout: the race with the
    /// report lasts one debounce, and a stale one must not be given to a later docking. Each is
    /// now an `unexpected_handshake` fault.
    fn expire_unclaimed(&mut self, now: Instant, out: &mut Vec<Step>) {
        let keep = self.timeout / 4;
        while let Some(&(node, port, at, why)) = self.unclaimed.front() {
            if now.saturating_duration_since(at) < keep {
                break;
            }
            self.unclaimed.pop_front();
            out.push(Step::UnexpectedHandshake { node, port, why });
        }
    }

    /// Records the docking of `mobile` on the static element's port `stat` and publishes it.
    fn complete(
        &mut self,
        stat: (NodeId, Port),
        mobile: (NodeId, Port),
        adopted: bool,
        now: Instant,
        out: &mut Vec<Step>,
    ) {
        // A mobile element is docked by one port at a time: a previous record of that port is stale,
        // and so is the link its static element may still hold.
        self.forget_mobile(mobile, out);
        self.connections.insert(
            stat,
            Record {
                mobile,
                since: now,
                adopted,
            },
        );
        out.push(Step::Connected(conn(stat, mobile)));
    }

    fn next(&mut self, now: Instant, out: &mut Vec<Step>) {
        self.pending = None;
        if let Some((node, port)) = self.queue.pop_front() {
            let relay_was_on = self.queued_relay_on.remove(&(node, port)).unwrap_or(false);
            self.start(node, port, relay_was_on, now, out);
        }
    }

    /// `DockDetected{port}` from the static `node`; `relay_on`: its relay is on, so the element
    /// there may already have power (and its handshake may have overtaken this report).
    pub fn on_detected(
        &mut self,
        node: NodeId,
        port: Port,
        relay_on: bool,
        now: Instant,
    ) -> Vec<Step> {
        let mut out = Vec::new();
        if let Some(r) = self.connections.get_mut(&(node, port)) {
            if r.adopted && now.saturating_duration_since(r.since) < self.timeout {
                // The report of the docking a handshake already completed, overtaken by it.
                r.adopted = false;
                return out;
            }
        }
        match self.pending {
            None => {
                self.start(node, port, relay_on, now, &mut out);
                if relay_on {
                    self.claim_unclaimed(node, port, now, &mut out);
                }
            }
            // Repeated report of what is already in progress or waiting: nothing new to do.
            Some(p) if p.node == node && p.port == port => {}
            Some(_) if self.queue.contains(&(node, port)) => {}
            Some(_) if self.queue.len() < self.queue_cap => {
                self.queue.push_back((node, port));
                self.queued_relay_on.insert((node, port), relay_on);
            }
            Some(_) => out.push(Step::RefuseBusy { node, port }),
        }
        out
    }

    /// `DockRemoved{port}` from the static `node`.
    pub fn on_removed(&mut self, node: NodeId, port: Port, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        self.queue.retain(|&q| q != (node, port));
        self.queued_relay_on.remove(&(node, port));
        if let Some(r) = self.connections.remove(&(node, port)) {
            out.push(Step::Removed(conn((node, port), r.mobile)));
        }
        if let Some(p) = self.pending {
            if p.node == node && p.port == port {
                out.push(Step::Failed {
                    node,
                    port,
                    reason: "cancelled: the element was undocked before its handshake".into(),
                    relay: None,
                });
                self.next(now, &mut out);
            }
        }
        out
    }

    /// `Handshake{port}` from `node` (the mobile element and its own port). `closed` lists the
    /// closed signal loops of the online static elements whose relay is on (static element, its
    /// port): where a handshake that no docking waits for may be adopted.
    pub fn on_handshake(
        &mut self,
        node: NodeId,
        port: Port,
        closed: &[(NodeId, Port)],
        now: Instant,
    ) -> Vec<Step> {
        let mut out = Vec::new();
        let Some(p) = self.pending else {
            self.on_unawaited_handshake(node, port, closed, now, &mut out);
            return out;
        };
        if p.node == node {
            out.push(Step::UnexpectedHandshake {
                node,
                port,
                why: "the element that reported the docking cannot be the docked one",
            });
            return out;
        }
        self.complete((p.node, p.port), (node, port), false, now, &mut out);
        self.next(now, &mut out);
        out
    }

    /// A handshake with no docking pending: the element got power while already docked.
    fn on_unawaited_handshake(
        &mut self,
        node: NodeId,
        port: Port,
        closed: &[(NodeId, Port)],
        now: Instant,
        out: &mut Vec<Step>,
    ) {
        let free: Vec<(NodeId, Port)> = closed
            .iter()
            .copied()
            .filter(|s| s.0 != node && !self.connections.contains_key(s))
            .collect();
        match free[..] {
            [stat] => {
                // Its report, if still waiting for its turn, is answered by this handshake.
                self.queue.retain(|&q| q != stat);
                out.push(Step::Adopt {
                    node: stat.0,
                    port: stat.1,
                });
                self.complete(stat, (node, port), true, now, out);
            }
            // Already recorded where it is (it restarted on a port that stayed powered): nothing
            // changed.
            [] if self.connections.values().any(|r| r.mobile == (node, port)) => {}
            _ => {
                // Not a fault yet: its static element's report may still come (the handshake
                // overtook it). `expire_unclaimed` reports it if nothing claims it in time.
                self.expire_unclaimed(now, out);
                self.unclaimed.retain(|&(m, ..)| m != node);
                if self.unclaimed.len() >= self.queue_cap {
                    if let Some((node, port, _, why)) = self.unclaimed.pop_front() {
                        out.push(Step::UnexpectedHandshake { node, port, why });
                    }
                }
                let why = if free.is_empty() {
                    "no docking is pending and no closed signal loop is free for it"
                } else {
                    "no docking is pending and several closed signal loops are free for it"
                };
                self.unclaimed.push_back((node, port, now, why));
            }
        }
    }

    /// Pairs a mobile element that is docked but recorded nowhere with the one place it can be:
    /// its handshake never reached us (it got power while our bus was down, or while another
    /// docking was pending). `mobiles`: online mobile elements with a closed loop (the element,
    /// its lowest closed port); `closed`: the closed loops of online static elements whose relay is
    /// on. Only with no docking in progress or waiting, and exactly one unrecorded element of each.
    pub fn adopt_unrecorded(
        &mut self,
        mobiles: &[(NodeId, Port)],
        closed: &[(NodeId, Port)],
        now: Instant,
    ) -> Vec<Step> {
        let mut out = Vec::new();
        if self.pending.is_some() || !self.queue.is_empty() || !self.unclaimed.is_empty() {
            return out;
        }
        let docked: Vec<NodeId> = self.connections.values().map(|r| r.mobile.0).collect();
        let lone: Vec<(NodeId, Port)> = mobiles
            .iter()
            .copied()
            .filter(|m| !docked.contains(&m.0))
            .collect();
        let free: Vec<(NodeId, Port)> = closed
            .iter()
            .copied()
            .filter(|s| !self.connections.contains_key(s))
            .collect();
        if let ([mobile], [stat]) = (&lone[..], &free[..]) {
            out.push(Step::Adopt {
                node: stat.0,
                port: stat.1,
            });
            self.complete(*stat, *mobile, true, now, &mut out);
        }
        out
    }

    /// The static `node` answered the confirm `seq` with a refusal named `reason`.
    pub fn on_confirm_refused(
        &mut self,
        node: NodeId,
        seq: u8,
        reason: &str,
        now: Instant,
    ) -> Vec<Step> {
        self.fail_confirm(node, seq, format!("confirm refused: {reason}"), now)
    }

    /// The confirm for the pending docking could not be sent.
    pub fn on_confirm_failed(
        &mut self,
        node: NodeId,
        seq: u8,
        reason: &str,
        now: Instant,
    ) -> Vec<Step> {
        self.fail_confirm(node, seq, format!("confirm not sent: {reason}"), now)
    }

    /// Ends the pending docking if `seq` is its confirm to `node`, and moves on to the next report.
    fn fail_confirm(&mut self, node: NodeId, seq: u8, reason: String, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        if let Some(p) = self.pending {
            if p.node == node && p.confirm_seq == Some(seq) {
                out.push(Step::Failed {
                    node,
                    port: p.port,
                    reason,
                    relay: None,
                });
                self.next(now, &mut out);
            }
        }
        out
    }

    /// `node` went lost: the connections where it is the mobile element end (it is no longer powered
    /// or no longer there); a static element's connections stay until it reports `DockRemoved`.
    pub fn on_lost(&mut self, node: NodeId) -> Vec<Step> {
        let gone: Vec<_> = self
            .connections
            .iter()
            .filter(|(_, r)| r.mobile.0 == node)
            .map(|(&s, r)| (s, r.mobile))
            .collect();
        let mut out = Vec::new();
        for (s, m) in gone {
            self.connections.remove(&s);
            out.push(Step::Removed(conn(s, m)));
            out.push(Step::Unlink {
                node: s.0,
                port: s.1,
            });
        }
        out
    }

    /// Removes every record of the mobile element's `end` (it is docked once at most), asking the
    /// static elements concerned to forget their link.
    fn forget_mobile(&mut self, end: (NodeId, Port), out: &mut Vec<Step>) {
        let stale: Vec<_> = self
            .connections
            .iter()
            .filter(|(_, r)| r.mobile.0 == end.0)
            .map(|(&s, r)| (s, r.mobile))
            .collect();
        for (s, m) in stale {
            self.connections.remove(&s);
            out.push(Step::Removed(conn(s, m)));
            out.push(Step::Unlink {
                node: s.0,
                port: s.1,
            });
        }
    }

    /// What the static element `node` reported of its ports when asked at `asked` (every port it
    /// did not list is open, unconfirmed and unlinked): a link it holds that the record lacks is
    /// restored silently; a record of a port that is no longer linked, made before the question,
    /// ends (`connection_removed`). The docking in progress is left alone.
    pub fn reconcile(
        &mut self,
        node: NodeId,
        reported: &[(Port, DockState)],
        asked: Instant,
    ) -> Vec<Step> {
        let mut out = Vec::new();
        let pending = self.pending.map(|p| (p.node, p.port));
        let gone: Vec<_> = self
            .connections
            .iter()
            .filter(|(&(s, sp), r)| {
                s == node
                    && r.since < asked
                    && Some((s, sp)) != pending
                    && !reported.iter().any(|(p, st)| {
                        *p == sp && st.partner.map(|m| (m.node, m.port)) == Some(r.mobile)
                    })
            })
            .map(|(&s, r)| (s, r.mobile))
            .collect();
        for (s, m) in gone {
            self.connections.remove(&s);
            out.push(Step::Removed(conn(s, m)));
        }
        for &(port, state) in reported {
            let Some(m) = state.partner else { continue };
            let mobile = (m.node, m.port);
            let known = self.connections.get(&(node, port)).map(|r| r.mobile);
            if known == Some(mobile) || Some((node, port)) == pending {
                continue;
            }
            if let Some(old) = known {
                self.connections.remove(&(node, port));
                out.push(Step::Removed(conn((node, port), old)));
            }
            self.forget_mobile(mobile, &mut out);
            self.connections.insert(
                (node, port),
                Record {
                    mobile,
                    since: asked,
                    adopted: false,
                },
            );
            out.push(Step::Restored(conn((node, port), mobile)));
        }
        out
    }

    /// `node` is forgotten: every connection it is part of ends, its waiting reports are dropped,
    /// and a docking it reported that is still pending fails (the next report starts).
    pub fn forget(&mut self, node: NodeId, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        let gone: Vec<_> = self
            .connections
            .iter()
            .filter(|(&(s, _), r)| s == node || r.mobile.0 == node)
            .map(|(&s, r)| (s, r.mobile))
            .collect();
        for (s, m) in gone {
            self.connections.remove(&s);
            out.push(Step::Removed(conn(s, m)));
        }
        self.queue.retain(|&(n, _)| n != node);
        self.queued_relay_on.retain(|&(n, _), _| n != node);
        if let Some(p) = self.pending {
            if p.node == node {
                out.push(Step::Failed {
                    node,
                    port: p.port,
                    reason: "cancelled: the element was forgotten".into(),
                    relay: None,
                });
                self.next(now, &mut out);
            }
        }
        out
    }

    /// Handshake timeout, and the end of unclaimed handshakes' window.
    pub fn tick(&mut self, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        self.expire_unclaimed(now, &mut out);
        if let Some(p) = self.pending {
            if now >= p.deadline {
                // The relay is the element's only one: switching it off would also cut the power of
                // elements already docked on its other ports. Withdrawing the confirmation of the
                // last confirmed port switches it off too (the node's rule), so a relay that was
                // on before this docking keeps the confirmation until the loop opens.
                let others = self.connections.keys().any(|&(s, _)| s == p.node);
                let relay = if others {
                    out.push(Step::Withdraw {
                        node: p.node,
                        port: p.port,
                    });
                    true
                } else if p.relay_was_on {
                    true
                } else {
                    out.push(Step::PowerOff { node: p.node });
                    false
                };
                out.push(Step::Failed {
                    node: p.node,
                    port: p.port,
                    reason: format!("handshake timeout after {} ms", self.timeout.as_millis()),
                    relay: Some(relay),
                });
                self.next(now, &mut out);
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::test_util::{id, port};

    const T: Duration = Duration::from_secs(5);

    #[test]
    fn confirm_handshake_connect() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 2);
        assert_eq!(
            d.on_detected(id(0x111), port(3), false, t0),
            vec![Step::Confirm {
                node: id(0x111),
                port: port(3)
            }]
        );
        d.confirm_sent(id(0x111), port(3), 9);
        assert_eq!(d.deadline(), Some(t0 + T));
        let steps = d.on_handshake(id(2), port(0), &[], t0 + Duration::from_secs(1));
        assert_eq!(
            steps,
            vec![Step::Connected(conn(
                (id(0x111), port(3)),
                (id(2), port(0))
            ))]
        );
        assert_eq!(d.pending(), None);
        assert_eq!(
            d.links_of(id(2)),
            vec![Link {
                port: 0,
                peer: HexId(id(0x111)),
                peer_port: 3
            }]
        );
        assert_eq!(
            d.links_of(id(0x111)),
            vec![Link {
                port: 3,
                peer: HexId(id(2)),
                peer_port: 0
            }]
        );
        let steps = d.on_removed(id(0x111), port(3), t0 + Duration::from_secs(2));
        assert_eq!(
            steps,
            vec![Step::Removed(conn((id(0x111), port(3)), (id(2), port(0))))]
        );
        assert!(d.connections().is_empty());
    }

    #[test]
    fn queue_is_fifo_bounded_and_deduplicated() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 2);
        d.on_detected(id(1), port(0), false, t0);
        assert!(
            d.on_detected(id(1), port(0), false, t0).is_empty(),
            "repeat of the pending one"
        );
        assert!(d.on_detected(id(2), port(1), false, t0).is_empty());
        assert!(
            d.on_detected(id(2), port(1), false, t0).is_empty(),
            "repeat of a queued one"
        );
        assert!(d.on_detected(id(3), port(2), false, t0).is_empty());
        assert_eq!(
            d.on_detected(id(4), port(3), false, t0),
            vec![Step::RefuseBusy {
                node: id(4),
                port: port(3)
            }]
        );
        // Timeout of the first: relay off, failure, then the next in line is confirmed.
        let steps = d.tick(t0 + T);
        assert_eq!(
            steps,
            vec![
                Step::PowerOff { node: id(1) },
                Step::Failed {
                    node: id(1),
                    port: port(0),
                    reason: "handshake timeout after 5000 ms".into(),
                    relay: Some(false),
                },
                Step::Confirm {
                    node: id(2),
                    port: port(1)
                },
            ]
        );
        assert_eq!(d.deadline(), Some(t0 + T + T));
        assert!(d.tick(t0 + T + T - Duration::from_millis(1)).is_empty());
        // Handshake completes it and starts the third.
        let steps = d.on_handshake(id(9), port(4), &[], t0 + T);
        assert_eq!(
            steps.last(),
            Some(&Step::Confirm {
                node: id(3),
                port: port(2)
            })
        );
    }

    #[test]
    fn removal_cancels_pending_and_queued() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(1), port(0), false, t0);
        d.on_detected(id(2), port(1), false, t0);
        d.on_detected(id(3), port(2), false, t0);
        assert!(
            d.on_removed(id(2), port(1), t0).is_empty(),
            "queued one dropped silently"
        );
        let steps = d.on_removed(id(1), port(0), t0);
        assert!(matches!(&steps[0], Step::Failed { node, .. } if *node == id(1)));
        assert_eq!(
            steps[1],
            Step::Confirm {
                node: id(3),
                port: port(2)
            }
        );
        assert_eq!(d.queued().count(), 0);
    }

    #[test]
    fn unexpected_handshakes_record_nothing() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        // Not a fault yet: its report may still come. A fault when a quarter of the timeout
        // passed without one.
        assert!(d.on_handshake(id(2), port(0), &[], t0).is_empty());
        assert_eq!(d.deadline(), Some(t0 + T / 4));
        assert!(d.tick(t0 + T / 4 - Duration::from_millis(1)).is_empty());
        assert!(matches!(
            d.tick(t0 + T / 4)[..],
            [Step::UnexpectedHandshake { .. }]
        ));
        assert_eq!(d.deadline(), None);
        // Kept for that window only: a report after that is a docking of its own.
        d.on_detected(id(1), port(0), false, t0 + T);
        assert!(d.connections().is_empty());
        assert!(matches!(
            d.on_handshake(id(1), port(0), &[], t0 + T)[..],
            [Step::UnexpectedHandshake { .. }]
        ));
        assert!(d.connections().is_empty());
        assert!(
            d.pending().is_some(),
            "still waiting for the real handshake"
        );
    }

    #[test]
    fn a_handshake_with_no_docking_pending_is_adopted_by_the_one_free_closed_loop() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(0x111), port(1), false, t0);
        d.on_handshake(id(3), port(0), &[], t0);
        // 2 got power on 0x111 port 3 (the relay was on): port 1 is taken, port 3 is free; a loop
        // of the mobile element itself does not count.
        let closed = [(id(0x111), port(1)), (id(0x111), port(3)), (id(2), port(0))];
        let c = conn((id(0x111), port(3)), (id(2), port(0)));
        assert_eq!(
            d.on_handshake(id(2), port(0), &closed, t0 + T),
            vec![
                Step::Adopt {
                    node: id(0x111),
                    port: port(3)
                },
                Step::Connected(c)
            ]
        );
        assert!(d.links_of(id(2)).len() == 1);
        // The static element's report of that docking, overtaken by the handshake, starts nothing.
        assert!(d.on_detected(id(0x111), port(3), false, t0 + T).is_empty());
        assert_eq!(d.pending(), None);
        // The same handshake again (the element restarted on a port that stayed powered): no
        // change, no fault.
        assert!(d.on_handshake(id(2), port(0), &closed, t0 + T).is_empty());
        // Two free loops: nobody can tell which, so nothing recorded, and a fault once no report
        // claimed it.
        let two = [(id(0x112), port(0)), (id(0x112), port(1))];
        assert!(d.on_handshake(id(4), port(0), &two, t0 + T).is_empty());
        assert!(matches!(
            d.tick(t0 + T + T / 4)[..],
            [Step::UnexpectedHandshake { .. }]
        ));
        assert_eq!(d.connections().len(), 2);
    }

    #[test]
    fn a_docked_element_whose_handshake_was_lost_is_paired_with_the_one_free_powered_loop() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(0x111), port(3), false, t0);
        d.on_handshake(id(2), port(0), &[], t0);
        let mobiles = [(id(2), port(0)), (id(3), port(1))];
        let c = conn((id(0x112), port(2)), (id(3), port(1)));
        // Not while a docking is in progress: its handshake may still come.
        d.on_detected(id(0x111), port(4), false, t0);
        assert!(d
            .adopt_unrecorded(&mobiles, &[(id(0x112), port(2))], t0)
            .is_empty());
        d.tick(t0 + T);
        // 2 is recorded on 0x111 port 3; 3 on the one free loop.
        let closed = [(id(0x111), port(3)), (id(0x112), port(2))];
        assert_eq!(
            d.adopt_unrecorded(&mobiles, &closed, t0 + T),
            vec![
                Step::Adopt {
                    node: id(0x112),
                    port: port(2)
                },
                Step::Connected(c)
            ]
        );
        assert!(d.adopt_unrecorded(&mobiles, &closed, t0 + T).is_empty());
        // Two unrecorded elements for two loops: nobody can tell which is where.
        let mut d = Docking::new(T, 4);
        let two = [(id(0x111), port(3)), (id(0x112), port(2))];
        assert!(d.adopt_unrecorded(&mobiles, &two, t0).is_empty());
    }

    #[test]
    fn a_handshake_that_overtook_the_dock_report_completes_the_docking_at_once() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        // Issue 29: no fault for it, neither now nor later.
        assert!(d.on_handshake(id(2), port(0), &[], t0).is_empty());
        let c = conn((id(0x111), port(3)), (id(2), port(0)));
        assert_eq!(
            d.on_detected(
                id(0x111),
                port(3),
                true,
                t0 + T / 4 - Duration::from_millis(1)
            ),
            vec![
                Step::Confirm {
                    node: id(0x111),
                    port: port(3)
                },
                Step::Connected(c)
            ]
        );
        assert_eq!(d.pending(), None);
        assert!(d.tick(t0 + T / 4).is_empty(), "claimed: no fault");
        // Used once: the next report waits for its own handshake.
        d.on_detected(id(0x111), port(4), false, t0 + T);
        assert!(d.pending().is_some());
        // A confirm sent for the docking already completed does not stand for the pending one.
        d.confirm_sent(id(0x111), port(3), 5);
        assert_eq!(d.pending().and_then(|p| p.confirm_seq), None);
    }

    #[test]
    fn timeout_withdraws_only_the_port_when_others_are_docked() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(1), port(0), false, t0);
        d.on_handshake(id(2), port(0), &[], t0);
        d.on_detected(id(1), port(1), false, t0);
        let steps = d.tick(t0 + T);
        assert_eq!(
            steps[0],
            Step::Withdraw {
                node: id(1),
                port: port(1)
            }
        );
        assert!(matches!(steps[1], Step::Failed { .. }));
        assert_eq!(
            d.connections().len(),
            1,
            "the docked element keeps its connection"
        );
    }

    #[test]
    fn refused_confirm_fails_only_for_matching_seq() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(1), port(5), false, t0);
        d.confirm_sent(id(1), port(5), 7);
        assert!(d.on_confirm_refused(id(1), 6, "busy", t0).is_empty());
        let steps = d.on_confirm_refused(id(1), 7, "invalid_state", t0);
        assert_eq!(
            steps,
            vec![Step::Failed {
                node: id(1),
                port: port(5),
                reason: "confirm refused: invalid_state".into(),
                relay: None,
            }]
        );
        assert_eq!(d.pending(), None);
    }

    #[test]
    fn lost_mobile_removes_its_connection_and_redock_replaces_stale_record() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(1), port(0), false, t0);
        d.on_handshake(id(2), port(0), &[], t0);
        // Docked again on the same port without a DockRemoved in between.
        let steps = d.on_detected(id(1), port(0), false, t0);
        assert_eq!(
            steps[0],
            Step::Removed(conn((id(1), port(0)), (id(2), port(0))))
        );
        d.on_handshake(id(3), port(1), &[], t0);
        assert!(
            d.on_lost(id(1)).is_empty(),
            "a lost static element keeps its records"
        );
        assert_eq!(
            d.on_lost(id(3)),
            vec![
                Step::Removed(conn((id(1), port(0)), (id(3), port(1)))),
                Step::Unlink {
                    node: id(1),
                    port: port(0)
                }
            ]
        );
        assert!(d.connections().is_empty());
    }

    #[test]
    fn a_forgotten_element_leaves_no_connection_report_or_pending_docking() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(0x111), port(3), false, t0);
        d.on_handshake(id(2), port(0), &[], t0);
        // 111 reports another docking (pending), then one more (queued); 112 one (queued).
        d.on_detected(id(0x111), port(4), false, t0);
        d.on_detected(id(0x111), port(5), false, t0);
        d.on_detected(id(0x112), port(1), false, t0);
        let steps = d.forget(id(0x111), t0);
        assert_eq!(
            steps,
            vec![
                Step::Removed(conn((id(0x111), port(3)), (id(2), port(0)))),
                Step::Failed {
                    node: id(0x111),
                    port: port(4),
                    reason: "cancelled: the element was forgotten".into(),
                    relay: None,
                },
                Step::Confirm {
                    node: id(0x112),
                    port: port(1)
                },
            ],
            "111's queued port 5 is dropped; 112's report goes next"
        );
        assert!(d.connections().is_empty());
        assert_eq!(d.queued().count(), 0);
        // Forgetting a mobile element ends its connection too.
        d.on_handshake(id(3), port(1), &[], t0);
        assert_eq!(
            d.forget(id(3), t0),
            vec![Step::Removed(conn((id(0x112), port(1)), (id(3), port(1))))]
        );
    }

    fn linked(m: u16, mp: u8) -> DockState {
        DockState {
            closed: true,
            confirmed: true,
            partner: Some(ihex_proto::DockPartner {
                node: id(m),
                port: port(mp),
            }),
        }
    }

    #[test]
    fn a_static_elements_report_restores_links_silently_and_ends_stale_records() {
        let t0 = Instant::now();
        let later = t0 + Duration::from_secs(1);
        let mut d = Docking::new(T, 4);
        // A restarted gateway knows nothing; 0x111 reports mobile 2 (port 0) on its port 3.
        let steps = d.reconcile(id(0x111), &[(port(3), linked(2, 0))], t0);
        let c = conn((id(0x111), port(3)), (id(2), port(0)));
        assert_eq!(steps, vec![Step::Restored(c)]);
        assert_eq!(d.connections(), vec![c]);
        // The same report again changes nothing.
        assert!(d
            .reconcile(id(0x111), &[(port(3), linked(2, 0))], later)
            .is_empty());
        // A closed port without a link is not a connection; the recorded one is gone.
        let open = DockState {
            closed: true,
            confirmed: true,
            partner: None,
        };
        assert_eq!(
            d.reconcile(id(0x111), &[(port(3), open)], later),
            vec![Step::Removed(c)]
        );
        // A record made after the question was asked is not judged by its answer.
        d.on_detected(id(0x111), port(1), false, later);
        d.on_handshake(id(5), port(0), &[], later);
        assert!(d.reconcile(id(0x111), &[], t0).is_empty());
        assert_eq!(d.connections().len(), 1);
        // A mobile element reported on a new port is no longer where it was recorded.
        let steps = d.reconcile(id(0x112), &[(port(0), linked(5, 0))], later + T);
        assert_eq!(
            steps,
            vec![
                Step::Removed(conn((id(0x111), port(1)), (id(5), port(0)))),
                Step::Unlink {
                    node: id(0x111),
                    port: port(1)
                },
                Step::Restored(conn((id(0x112), port(0)), (id(5), port(0)))),
            ]
        );
        // The docking in progress is left alone.
        d.on_detected(id(0x112), port(4), false, later + T);
        assert!(d
            .reconcile(
                id(0x112),
                &[(port(0), linked(5, 0)), (port(4), linked(9, 0))],
                later + T
            )
            .is_empty());
    }
}
