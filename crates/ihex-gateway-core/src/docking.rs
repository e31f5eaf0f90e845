//! The one-docking-at-a-time sequence (the seed's new-member mutex) and the record of docking
//! connections. Inputs are dock reports, handshakes, confirm acks and time; outputs are [`Step`]s that
//! the bridge turns into frames and events.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use ihex_proto::{NodeId, Port};

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
    /// Publish `new_connection`.
    Connected(Connection),
    /// Publish `connection_removed`.
    Removed(Connection),
    /// Publish `dock_failed`.
    Failed {
        /// The static element.
        node: NodeId,
        /// Its dock port.
        port: Port,
        /// Why.
        reason: String,
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
}

/// Docking state: at most one pending docking, a bounded FIFO of waiting reports, the connections.
#[derive(Debug)]
pub struct Docking {
    timeout: Duration,
    queue_cap: usize,
    pending: Option<Pending>,
    queue: VecDeque<(NodeId, Port)>,
    /// (static, its port) -> (mobile, its port).
    connections: BTreeMap<(NodeId, Port), (NodeId, Port)>,
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
            connections: BTreeMap::new(),
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

    /// When the pending handshake is overdue.
    pub fn deadline(&self) -> Option<Instant> {
        self.pending.map(|p| p.deadline)
    }

    /// Remembers the sequence number of the confirm just sent for the pending docking.
    pub fn confirm_sent(&mut self, seq: u8) {
        if let Some(p) = &mut self.pending {
            p.confirm_seq = Some(seq);
        }
    }

    /// The connections of `id`, seen from `id` (as static or as mobile element).
    pub fn links_of(&self, id: NodeId) -> Vec<Link> {
        let mut links = Vec::new();
        for (&(s, sp), &(m, mp)) in &self.connections {
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
        self.connections.iter().map(|(&s, &m)| conn(s, m)).collect()
    }

    fn start(&mut self, node: NodeId, port: Port, now: Instant, out: &mut Vec<Step>) {
        // A new docking on a port that still has a recorded connection means the old element left
        // without a DockRemoved reaching us.
        if let Some(m) = self.connections.remove(&(node, port)) {
            out.push(Step::Removed(conn((node, port), m)));
        }
        self.pending = Some(Pending {
            node,
            port,
            deadline: now + self.timeout,
            confirm_seq: None,
        });
        out.push(Step::Confirm { node, port });
    }

    fn next(&mut self, now: Instant, out: &mut Vec<Step>) {
        self.pending = None;
        if let Some((node, port)) = self.queue.pop_front() {
            self.start(node, port, now, out);
        }
    }

    /// `DockDetected{port}` from the static `node`.
    pub fn on_detected(&mut self, node: NodeId, port: Port, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        match self.pending {
            None => self.start(node, port, now, &mut out),
            // Repeated report of what is already in progress or waiting: nothing new to do.
            Some(p) if p.node == node && p.port == port => {}
            Some(_) if self.queue.contains(&(node, port)) => {}
            Some(_) if self.queue.len() < self.queue_cap => self.queue.push_back((node, port)),
            Some(_) => out.push(Step::RefuseBusy { node, port }),
        }
        out
    }

    /// `DockRemoved{port}` from the static `node`.
    pub fn on_removed(&mut self, node: NodeId, port: Port, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        self.queue.retain(|&q| q != (node, port));
        if let Some(m) = self.connections.remove(&(node, port)) {
            out.push(Step::Removed(conn((node, port), m)));
        }
        if let Some(p) = self.pending {
            if p.node == node && p.port == port {
                out.push(Step::Failed {
                    node,
                    port,
                    reason: "cancelled: the element was undocked before its handshake".into(),
                });
                self.next(now, &mut out);
            }
        }
        out
    }

    /// `Handshake{port}` from `node` (the mobile element and its own port).
    pub fn on_handshake(&mut self, node: NodeId, port: Port, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        let Some(p) = self.pending else {
            out.push(Step::UnexpectedHandshake {
                node,
                port,
                why: "no docking is pending",
            });
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
        // A mobile element is docked by one port at a time: a previous record of that port is stale.
        let stale: Vec<_> = self
            .connections
            .iter()
            .filter(|(_, &m)| m == (node, port))
            .map(|(&s, &m)| (s, m))
            .collect();
        for (s, m) in stale {
            self.connections.remove(&s);
            out.push(Step::Removed(conn(s, m)));
        }
        self.connections.insert((p.node, p.port), (node, port));
        out.push(Step::Connected(conn((p.node, p.port), (node, port))));
        self.next(now, &mut out);
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
            .filter(|(_, &(m, _))| m == node)
            .map(|(&s, &m)| (s, m))
            .collect();
        gone.into_iter()
            .map(|(s, m)| {
                self.connections.remove(&s);
                Step::Removed(conn(s, m))
            })
            .collect()
    }

    /// Handshake timeout.
    pub fn tick(&mut self, now: Instant) -> Vec<Step> {
        let mut out = Vec::new();
        if let Some(p) = self.pending {
            if now >= p.deadline {
                // The relay is the element's only one: switching it off would also cut the power of
                // elements already docked on its other ports.
                let others = self.connections.keys().any(|&(s, _)| s == p.node);
                out.push(if others {
                    Step::Withdraw {
                        node: p.node,
                        port: p.port,
                    }
                } else {
                    Step::PowerOff { node: p.node }
                });
                out.push(Step::Failed {
                    node: p.node,
                    port: p.port,
                    reason: format!("handshake timeout after {} ms", self.timeout.as_millis()),
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

    fn id(raw: u16) -> NodeId {
        NodeId::new(raw).unwrap()
    }
    fn port(raw: u8) -> Port {
        Port::new(raw).unwrap()
    }
    const T: Duration = Duration::from_secs(5);

    #[test]
    fn confirm_handshake_connect() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 2);
        assert_eq!(
            d.on_detected(id(0x111), port(3), t0),
            vec![Step::Confirm {
                node: id(0x111),
                port: port(3)
            }]
        );
        d.confirm_sent(9);
        assert_eq!(d.deadline(), Some(t0 + T));
        let steps = d.on_handshake(id(2), port(0), t0 + Duration::from_secs(1));
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
        d.on_detected(id(1), port(0), t0);
        assert!(
            d.on_detected(id(1), port(0), t0).is_empty(),
            "repeat of the pending one"
        );
        assert!(d.on_detected(id(2), port(1), t0).is_empty());
        assert!(
            d.on_detected(id(2), port(1), t0).is_empty(),
            "repeat of a queued one"
        );
        assert!(d.on_detected(id(3), port(2), t0).is_empty());
        assert_eq!(
            d.on_detected(id(4), port(3), t0),
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
                    reason: "handshake timeout after 5000 ms".into()
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
        let steps = d.on_handshake(id(9), port(4), t0 + T);
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
        d.on_detected(id(1), port(0), t0);
        d.on_detected(id(2), port(1), t0);
        d.on_detected(id(3), port(2), t0);
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
        assert!(matches!(
            d.on_handshake(id(2), port(0), t0)[..],
            [Step::UnexpectedHandshake { .. }]
        ));
        d.on_detected(id(1), port(0), t0);
        assert!(matches!(
            d.on_handshake(id(1), port(0), t0)[..],
            [Step::UnexpectedHandshake { .. }]
        ));
        assert!(d.connections().is_empty());
        assert!(
            d.pending().is_some(),
            "still waiting for the real handshake"
        );
    }

    #[test]
    fn timeout_withdraws_only_the_port_when_others_are_docked() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(1), port(0), t0);
        d.on_handshake(id(2), port(0), t0);
        d.on_detected(id(1), port(1), t0);
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
        d.on_detected(id(1), port(5), t0);
        d.confirm_sent(7);
        assert!(d.on_confirm_refused(id(1), 6, "busy", t0).is_empty());
        let steps = d.on_confirm_refused(id(1), 7, "invalid_state", t0);
        assert_eq!(
            steps,
            vec![Step::Failed {
                node: id(1),
                port: port(5),
                reason: "confirm refused: invalid_state".into()
            }]
        );
        assert_eq!(d.pending(), None);
    }

    #[test]
    fn lost_mobile_removes_its_connection_and_redock_replaces_stale_record() {
        let t0 = Instant::now();
        let mut d = Docking::new(T, 4);
        d.on_detected(id(1), port(0), t0);
        d.on_handshake(id(2), port(0), t0);
        // Docked again on the same port without a DockRemoved in between.
        let steps = d.on_detected(id(1), port(0), t0);
        assert_eq!(
            steps[0],
            Step::Removed(conn((id(1), port(0)), (id(2), port(0))))
        );
        d.on_handshake(id(3), port(1), t0);
        assert!(
            d.on_lost(id(1)).is_empty(),
            "a lost static element keeps its records"
        );
        assert_eq!(
            d.on_lost(id(3)),
            vec![Step::Removed(conn((id(1), port(0)), (id(3), port(1))))]
        );
        assert!(d.connections().is_empty());
    }
}
