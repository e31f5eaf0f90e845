//! Node presence: the broadcast health check every period, lost detection after missed replies,
//! `node_online` / `node_lost` / `node_rebooted`, the role a node announces, and the pause of all of
//! it while the gateway's own interface is down (the silence is then ours, not the nodes').
//!
//! A `BootUp` from a known node is a reboot — except the one a board sends when `assign` gave it
//! its ID: it announces itself under the new ID without restarting.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use ihex_proto::{BootRole, HealthFlags, Message, NodeId, Packet, Seq};

use super::output::Outputs;
use crate::event::{Event, HexId, NodeLost, NodeOnline, NodeRebooted, Role};
use crate::registry::{millis, Registry, Seen};

/// The health check schedule and the round whose replies are being collected.
#[derive(Debug)]
pub(super) struct Health {
    period: Duration,
    lost_after: u32,
    seq: Seq,
    /// Sequence number of the health check whose replies are being collected.
    outstanding: Option<Seq>,
    next: Instant,
    /// Our own interface is bus-off or down: nodes cannot answer, so nobody is counted as lost.
    bus_down: bool,
    /// IDs just given by `assign`, until when their announcement (a `BootUp`) is expected.
    announcing: BTreeMap<NodeId, Instant>,
}

impl Health {
    /// The first check is due at `now`.
    pub(super) fn new(period: Duration, lost_after: u32, now: Instant) -> Self {
        Health {
            period,
            lost_after,
            seq: 0,
            outstanding: None,
            next: now,
            bus_down: false,
            announcing: BTreeMap::new(),
        }
    }

    /// `assign` gave a board the ID `id` at `now`: the `BootUp` it sends within `within`
    /// announces the new ID and is no reboot.
    pub(super) fn expect_announcement(&mut self, id: NodeId, now: Instant, within: Duration) {
        // Announcements that never came are forgotten, so they cannot hide a real reboot later.
        self.announcing.retain(|_, until| *until > now);
        self.announcing.insert(id, now + within);
    }

    /// When the next health check is due.
    pub(super) fn next_deadline(&self) -> Instant {
        self.next
    }

    /// True while the gateway's own interface is bus-off or down.
    pub(super) fn bus_down(&self) -> bool {
        self.bus_down
    }

    /// A valid frame from the node `src`: registers or revives it, learns its role, and publishes
    /// `node_online` / `node_rebooted` as due; stores its health report. Returns how it was seen.
    pub(super) fn on_heard(
        &mut self,
        registry: &mut Registry,
        src: NodeId,
        msg: &Message,
        now: Instant,
        out: &mut Outputs,
    ) -> Seen {
        let seen = registry.record_heard(src, now);
        if let Some(e) = registry.get_mut(src) {
            // Learn the role first, so that `node_online` can already tell it.
            match *msg {
                Message::BootUp {
                    version,
                    role,
                    ports,
                    ..
                } => {
                    e.role = Some(role);
                    e.ports = Some(ports);
                    e.version = Some(version);
                }
                Message::HealthReply(h) if e.role.is_none() => {
                    let mobile = h.flags.contains(HealthFlags::MOBILE);
                    e.role = Some(if mobile {
                        BootRole::Mobile
                    } else {
                        BootRole::Static
                    });
                }
                _ => {}
            }
        }
        let role = registry.get(src).and_then(|e| e.role());
        match seen {
            Seen::New | Seen::Back => out.emit(Event::NodeOnline(NodeOnline {
                id: HexId(src),
                role,
                first_seen: seen == Seen::New,
            })),
            Seen::Known => {}
        }
        out.mark_changed(src);
        match *msg {
            Message::BootUp { version, reset, .. } => {
                let announced = self
                    .announcing
                    .remove(&src)
                    .is_some_and(|until| now <= until);
                if seen == Seen::Known && !announced {
                    out.emit(Event::NodeRebooted(NodeRebooted {
                        id: HexId(src),
                        reset,
                        version: version.into(),
                        role: role.unwrap_or(Role::Static),
                    }));
                }
                if let Some(e) = registry.get_mut(src) {
                    e.reset_actuators();
                }
            }
            Message::HealthReply(h) => {
                registry.record_health(src, h, self.outstanding);
            }
            _ => {}
        }
        seen
    }

    /// Our interface went bus-off or down: stop health checks (and with them lost detection).
    pub(super) fn on_bus_down(&mut self) {
        self.bus_down = true;
        self.outstanding = None;
    }

    /// Our interface is back: a health check at once, counting afresh.
    pub(super) fn on_recovered(&mut self, now: Instant) {
        if self.bus_down {
            self.bus_down = false;
            self.next = now;
        }
    }

    /// Sends the health check when due, after closing the previous round: each node that just
    /// became lost gets its `node_lost`, then `on_lost` (which ends its docking connections).
    pub(super) fn tick(
        &mut self,
        registry: &mut Registry,
        now: Instant,
        out: &mut Outputs,
        mut on_lost: impl FnMut(NodeId, &mut Outputs),
    ) {
        if now < self.next {
            return;
        }
        if self.bus_down {
            self.next = now + self.period;
            return;
        }
        if self.outstanding.is_none() {
            registry.start_round();
        } else {
            for (id, missed) in registry.close_round(self.lost_after) {
                let last_seen_ms = registry
                    .get(id)
                    .map_or(0, |e| millis(now.saturating_duration_since(e.last_seen)));
                out.emit(Event::NodeLost(NodeLost {
                    id: HexId(id),
                    missed,
                    last_seen_ms,
                }));
                out.mark_changed(id);
                on_lost(id, out);
            }
        }
        let seq = self.seq;
        self.seq = seq.wrapping_add(1);
        self.outstanding = Some(seq);
        out.send(Packet::command(
            NodeId::BROADCAST,
            Message::HealthCheck { seq },
        ));
        self.next += self.period;
        if self.next <= now {
            // Far behind (a suspended process): skip the missed checks instead of bursting them.
            self.next = now + self.period;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::*;
    use super::super::*;
    use ihex_proto::{BootRole, HealthFlags, Message, NodeId, Packet, ResetReason};
    use serde_json::json;
    use std::time::{Duration, Instant};

    #[test]
    fn first_health_check_is_due_at_once_then_every_period() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        assert_eq!(b.poll_timeout(), t0);
        b.handle_timeout(t0);
        assert_eq!(drain(&mut b).sent.len(), 1);
        assert_eq!(b.poll_timeout(), t0 + S);
        b.handle_timeout(t0 + S - MS);
        assert!(drain(&mut b).sent.is_empty());
        b.handle_timeout(t0 + S);
        assert_eq!(
            drain(&mut b).sent,
            vec![Packet::command(
                NodeId::BROADCAST,
                Message::HealthCheck { seq: 1 }
            )]
        );
    }

    #[test]
    fn new_node_goes_online_with_retained_state() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        b.handle_timeout(t0);
        drain(&mut b);
        b.handle_packet(
            Packet::report(id(0x111), reply(0, HealthFlags::RELAY)),
            t0 + MS,
        );
        let out = drain(&mut b);
        assert_eq!(
            out.one("node_online"),
            &json!({"id": "111", "role": "static", "first_seen": true})
        );
        assert_eq!(out.states.len(), 1);
        let (sid, st) = &out.states[0];
        assert_eq!(*sid, id(0x111));
        assert_eq!(st["online"], true);
        assert_eq!(st["relay"], true);
        assert_eq!(st["reported"]["relay"], true);
        // The same reply again changes nothing worth publishing.
        b.handle_packet(
            Packet::report(id(0x111), reply(0, HealthFlags::RELAY)),
            t0 + MS,
        );
        let out = drain(&mut b);
        assert!(out.events.is_empty() && out.states.is_empty(), "{out:?}");
    }

    #[test]
    fn silent_node_is_lost_after_n_misses_and_comes_back() {
        let (mut b, t0) = with_nodes(&[2, 3]);
        // Node 3 keeps answering, node 2 goes silent after the first round.
        for round in 1..=3u8 {
            b.handle_timeout(t0 + S * u32::from(round));
            let out = drain(&mut b);
            assert!(
                out.named("node_lost").is_empty(),
                "round {round}: {:?}",
                out.events
            );
            b.handle_packet(
                Packet::report(id(3), reply(round, 0)),
                t0 + S * u32::from(round) + MS,
            );
        }
        b.handle_timeout(t0 + 4 * S);
        let out = drain(&mut b);
        let lost = out.one("node_lost");
        assert_eq!(lost["id"], "2");
        assert_eq!(lost["missed"], 3);
        assert_eq!(lost["last_seen_ms"], 3999);
        assert!(out
            .states
            .iter()
            .any(|(n, s)| *n == id(2) && s["online"] == false));
        // Lost, it stays lost (no second event) until heard again.
        b.handle_packet(Packet::report(id(3), reply(4, 0)), t0 + 4 * S + MS);
        b.handle_timeout(t0 + 5 * S);
        assert!(drain(&mut b).named("node_lost").is_empty());
        b.handle_packet(Packet::report(id(2), reply(5, 0)), t0 + 5 * S + MS);
        let out = drain(&mut b);
        assert_eq!(
            out.one("node_online"),
            &json!({"id": "2", "role": "static", "first_seen": false})
        );
        assert!(out
            .states
            .iter()
            .any(|(n, s)| *n == id(2) && s["online"] == true));
    }

    #[test]
    fn boot_up_of_an_online_node_is_a_reboot() {
        let (mut b, t0) = with_nodes(&[5]);
        let boot = Message::BootUp {
            version: (1, 0),
            role: BootRole::Mobile,
            ports: 6,
            reset: ResetReason::Watchdog,
        };
        b.handle_packet(Packet::report(id(5), boot), t0 + S);
        let out = drain(&mut b);
        assert_eq!(
            out.one("node_rebooted"),
            &json!({"id": "5", "reset": "watchdog", "version": "1.0", "role": "mobile"})
        );
        assert!(out.named("node_online").is_empty());
        // A never-seen node's BootUp is just node_online, with its role.
        b.handle_packet(Packet::report(id(6), boot), t0 + S);
        let out = drain(&mut b);
        assert_eq!(
            out.one("node_online"),
            &json!({"id": "6", "role": "mobile", "first_seen": true})
        );
        assert!(out.named("node_rebooted").is_empty());
        assert_eq!(out.states[0].1["ports"], 6);
        assert_eq!(out.states[0].1["version"], "1.0");
    }

    #[test]
    fn own_bus_outage_suspends_lost_detection() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_bus_event(BusEvent::InterfaceDown, t0 + MS);
        assert_eq!(drain(&mut b).one("bus_error")["error"], "interface_down");
        for k in 1..=10u32 {
            b.handle_timeout(t0 + S * k);
            let out = drain(&mut b);
            assert!(
                out.sent.is_empty(),
                "no health checks while down: {:?}",
                out.sent
            );
            assert!(out.named("node_lost").is_empty());
        }
        b.handle_bus_event(BusEvent::Recovered, t0 + 10 * S + MS);
        drain(&mut b);
        assert_eq!(b.poll_timeout(), t0 + 10 * S + MS, "a health check at once");
        b.handle_timeout(t0 + 10 * S + MS);
        let out = drain(&mut b);
        assert!(matches!(
            out.sent[..],
            [Packet {
                msg: Message::HealthCheck { .. },
                ..
            }]
        ));
        // Back to normal: silence now counts again.
        for k in 1..=3u32 {
            b.handle_timeout(t0 + 10 * S + MS + S * k);
        }
        assert_eq!(drain(&mut b).one("node_lost")["missed"], 3);
    }

    #[test]
    fn zero_health_period_does_not_spin() {
        let t0 = Instant::now();
        let config = BridgeConfig {
            health_period: Duration::ZERO,
            ..BridgeConfig::default()
        };
        let mut b = Bridge::new(config, t0);
        b.handle_timeout(t0);
        assert!(b.poll_timeout() > t0);
    }
}
