//! The registry of nodes the gateway has heard: when, in which role, what they last reported, what they
//! last acknowledged, and whether they still answer health checks. Pure bookkeeping, no I/O.

use std::collections::BTreeMap;
use std::time::Instant;

use ihex_proto::{
    BootRole, BuzzerCommand, FirmwareVersion, HealthFlags, HealthReply, LedCommand, NodeId, Uid,
};

use crate::event::{Firmware, HexId, Link, NodeState, Reported, Role};

/// How a frame from a node changed its standing.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Seen {
    /// Never heard before: now registered and online.
    New,
    /// Was lost: online again.
    Back,
    /// Already known and online.
    Known,
}

/// Everything known about one node.
#[derive(Clone, Debug)]
pub struct NodeEntry {
    /// The node.
    pub id: NodeId,
    /// When it was first heard.
    pub first_seen: Instant,
    /// When it was last heard (any valid frame).
    pub last_seen: Instant,
    /// False once it missed `lost_after_misses` health checks in a row.
    pub online: bool,
    /// Consecutive health checks missed.
    pub misses: u32,
    /// It answered the health check currently outstanding.
    pub replied: bool,
    /// From `BootUp`, or from the `MOBILE` health flag.
    pub role: Option<BootRole>,
    /// Dock port count from `BootUp`.
    pub ports: Option<u8>,
    /// Protocol version from `BootUp`.
    pub version: Option<(u8, u8)>,
    /// Firmware version and trial flag, read back.
    pub firmware: Option<(FirmwareVersion, bool)>,
    /// First 7 bytes of the running image's hash, read back.
    pub image_hash: Option<[u8; 7]>,
    /// Unique ID, read back.
    pub uid: Option<Uid>,
    /// The last health report.
    pub health: Option<HealthReply>,
    /// LED command last acknowledged.
    pub led: Option<LedCommand>,
    /// Buzzer command last acknowledged.
    pub buzzer: Option<BuzzerCommand>,
    /// Relay: last acknowledged `power`, or last reported.
    pub relay: Option<bool>,
    /// Signal-loop bitmap (bit n = port n closed).
    pub loops: u8,
    /// When an acknowledgement last changed `led`, `buzzer` and `relay`, each on its own: a
    /// read-back asked before that is older for that actuator only.
    pub acked_at: Acked,
    /// What the state document last published showed (see [`Registry::state_changed`]).
    published: Option<Shown>,
}

/// When an acknowledgement last set each actuator of a node.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Acked {
    /// The LED.
    pub led: Option<Instant>,
    /// The buzzer.
    pub buzzer: Option<Instant>,
    /// The relay.
    pub relay: Option<Instant>,
}

impl NodeEntry {
    fn new(id: NodeId, now: Instant) -> Self {
        NodeEntry {
            id,
            first_seen: now,
            last_seen: now,
            online: true,
            misses: 0,
            // A node first heard mid-round has not been asked yet: do not count this round against it.
            replied: true,
            role: None,
            ports: None,
            version: None,
            firmware: None,
            image_hash: None,
            uid: None,
            health: None,
            led: None,
            buzzer: None,
            relay: None,
            loops: 0,
            acked_at: Acked::default(),
            published: None,
        }
    }

    /// The node's role for events.
    pub fn role(&self) -> Option<Role> {
        self.role.map(|r| match r {
            BootRole::Static => Role::Static,
            BootRole::Mobile => Role::Mobile,
        })
    }

    /// Forgets acknowledged actuator state: the node restarted with everything off.
    pub fn reset_actuators(&mut self) {
        self.led = None;
        self.buzzer = None;
        self.relay = None;
    }

    /// The state document as of `now`, with the node's docking links.
    pub fn state(&self, links: Vec<Link>, now: Instant) -> NodeState {
        NodeState {
            id: HexId(self.id),
            online: self.online,
            role: self.role(),
            ports: self.ports,
            version: self.version.map(Into::into),
            firmware: self.firmware.map(|(version, trial)| Firmware {
                version: version.to_string(),
                trial,
                image_hash: ihex_proto::Hex(&self.image_hash.unwrap_or_default()).to_string(),
            }),
            uid: self.uid.map(|u| u.to_string()),
            led: self.led.map(Into::into),
            buzzer: self.buzzer.map(Into::into),
            relay: self.relay,
            loops: (0..8).filter(|p| self.loops & (1 << p) != 0).collect(),
            connections: links,
            reported: self.health.map(|h| Reported {
                relay: h.flags.contains(HealthFlags::RELAY),
                led_on: h.flags.contains(HealthFlags::LED_ON),
                led_blink: h.flags.contains(HealthFlags::LED_BLINK),
                buzzer: h.flags.contains(HealthFlags::BUZZER),
                identify: h.flags.contains(HealthFlags::IDENTIFY),
                error_passive: h.flags.contains(HealthFlags::ERROR_PASSIVE),
                tec: h.tec,
                rec: h.rec,
                uptime_s: h.uptime_s,
            }),
            last_seen_ms: millis(now.saturating_duration_since(self.last_seen)),
            first_seen_ms: millis(now.saturating_duration_since(self.first_seen)),
        }
    }
}

/// Milliseconds of a duration, saturating.
pub(crate) fn millis(d: std::time::Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// What a node's state document shows apart from ages and health counters (tec, rec, uptime),
/// which change on every health reply: compared instead of the document itself, because every
/// frame from a node asks whether its document changed and building one allocates its strings.
#[derive(Clone, PartialEq, Eq, Debug)]
struct Shown {
    online: bool,
    role: Option<BootRole>,
    ports: Option<u8>,
    version: Option<(u8, u8)>,
    firmware: Option<(FirmwareVersion, bool, [u8; 7])>,
    uid: Option<Uid>,
    led: Option<LedCommand>,
    buzzer: Option<BuzzerCommand>,
    relay: Option<bool>,
    loops: u8,
    flags: Option<HealthFlags>,
    links: Vec<Link>,
}

impl Shown {
    fn of(e: &NodeEntry, links: &[Link]) -> Shown {
        Shown {
            online: e.online,
            role: e.role,
            ports: e.ports,
            version: e.version,
            firmware: e
                .firmware
                .map(|(v, trial)| (v, trial, e.image_hash.unwrap_or_default())),
            uid: e.uid,
            led: e.led,
            buzzer: e.buzzer,
            relay: e.relay,
            loops: e.loops,
            flags: e.health.map(|h| h.flags),
            links: links.to_vec(),
        }
    }
}

/// All known nodes, by ID.
#[derive(Debug, Default)]
pub struct Registry {
    nodes: BTreeMap<NodeId, NodeEntry>,
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Self::default()
    }

    /// Records that `id` was heard at `now` (registering it if new, reviving it if lost).
    pub fn record_heard(&mut self, id: NodeId, now: Instant) -> Seen {
        match self.nodes.get_mut(&id) {
            None => {
                self.nodes.insert(id, NodeEntry::new(id, now));
                Seen::New
            }
            Some(e) => {
                e.last_seen = now;
                e.misses = 0;
                if e.online {
                    Seen::Known
                } else {
                    e.online = true;
                    Seen::Back
                }
            }
        }
    }

    /// The entry of `id`.
    pub fn get(&self, id: NodeId) -> Option<&NodeEntry> {
        self.nodes.get(&id)
    }

    /// The entry of `id`, mutable.
    pub fn get_mut(&mut self, id: NodeId) -> Option<&mut NodeEntry> {
        self.nodes.get_mut(&id)
    }

    /// Every entry, by ascending ID.
    pub fn iter(&self) -> impl Iterator<Item = &NodeEntry> {
        self.nodes.values()
    }

    /// Removes `id` (the `forget` command, a renumbered board); returns its entry.
    pub fn remove(&mut self, id: NodeId) -> Option<NodeEntry> {
        self.nodes.remove(&id)
    }

    /// Records that the board `uid` answers as `id` now, and returns the other IDs the registry
    /// knew that board by: it was renumbered, and nothing answers to those any more.
    pub fn learn_uid(&mut self, id: NodeId, uid: Uid) -> Vec<NodeId> {
        if let Some(e) = self.nodes.get_mut(&id) {
            e.uid = Some(uid);
        }
        self.nodes
            .values()
            .filter(|e| e.id != id && e.uid == Some(uid))
            .map(|e| e.id)
            .collect()
    }

    /// IDs of nodes currently online.
    pub fn online_ids(&self) -> Vec<NodeId> {
        self.nodes
            .values()
            .filter(|e| e.online)
            .map(|e| e.id)
            .collect()
    }

    /// Known IDs as `"1, 2, 111"` (or `"none yet"`), for error messages.
    pub fn known_list(&self) -> String {
        if self.nodes.is_empty() {
            return "none yet".into();
        }
        let ids: Vec<String> = self.nodes.keys().map(|id| id.to_string()).collect();
        ids.join(", ")
    }

    /// Stores a health reply; returns true if it answers the outstanding check `seq`.
    pub fn record_health(
        &mut self,
        id: NodeId,
        reply: HealthReply,
        outstanding: Option<u8>,
    ) -> bool {
        let Some(e) = self.nodes.get_mut(&id) else {
            return false;
        };
        e.health = Some(reply);
        e.loops = reply.loops;
        e.relay = Some(reply.flags.contains(HealthFlags::RELAY));
        if e.role.is_none() {
            e.role = Some(if reply.flags.contains(HealthFlags::MOBILE) {
                BootRole::Mobile
            } else {
                BootRole::Static
            });
        }
        let answers = outstanding == Some(reply.seq);
        if answers {
            e.replied = true;
        }
        answers
    }

    /// Closes a health round before the next check goes out: every online node that did not answer
    /// gets a miss; those reaching `lost_after` go offline and are returned with their miss count.
    pub fn close_round(&mut self, lost_after: u32) -> Vec<(NodeId, u32)> {
        let mut lost = Vec::new();
        for e in self.nodes.values_mut() {
            if e.online && !e.replied {
                e.misses += 1;
                if e.misses >= lost_after.max(1) {
                    e.online = false;
                    lost.push((e.id, e.misses));
                }
            }
            e.replied = false;
        }
        lost
    }

    /// Starts a health round without judging the previous one (after start or a bus outage): every
    /// node must answer the check that goes out next.
    pub fn start_round(&mut self) {
        for e in self.nodes.values_mut() {
            e.replied = false;
        }
    }

    /// True when the state document of `id` with docking `links` would differ from the last one
    /// published (ignoring ages and health counters), and remembers it as published. Compares what
    /// the document is built from, without building it.
    pub fn state_changed(&mut self, id: NodeId, links: &[Link]) -> bool {
        let Some(e) = self.nodes.get_mut(&id) else {
            return false;
        };
        let shown = Shown::of(e, links);
        if e.published.as_ref() == Some(&shown) {
            return false;
        }
        e.published = Some(shown);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::test_util::id;
    use std::time::Duration;

    fn reply(seq: u8, flags: u8, uptime_s: u32) -> HealthReply {
        HealthReply {
            seq,
            flags: HealthFlags(flags),
            loops: 0b1001,
            tec: 0,
            rec: 0,
            uptime_s,
        }
    }

    #[test]
    fn record_heard_registers_and_revives() {
        let t0 = Instant::now();
        let mut r = Registry::new();
        assert_eq!(r.record_heard(id(5), t0), Seen::New);
        assert_eq!(r.record_heard(id(5), t0), Seen::Known);
        r.get_mut(id(5)).unwrap().replied = false;
        assert_eq!(r.close_round(1), vec![(id(5), 1)]);
        assert!(!r.get(id(5)).unwrap().online);
        assert_eq!(
            r.record_heard(id(5), t0 + Duration::from_secs(1)),
            Seen::Back
        );
        assert_eq!(r.get(id(5)).unwrap().misses, 0);
        assert_eq!(r.known_list(), "5");
    }

    #[test]
    fn misses_count_only_unanswered_rounds() {
        let t0 = Instant::now();
        let mut r = Registry::new();
        r.record_heard(id(1), t0);
        r.record_heard(id(2), t0);
        // Round 0 (nodes new this round): no misses.
        assert!(r.close_round(3).is_empty());
        // Round 1: node 1 answers, node 2 is silent.
        assert!(r.record_health(id(1), reply(1, 0, 1), Some(1)));
        assert!(
            !r.record_health(id(2), reply(0, 0, 1), Some(1)),
            "stale seq does not answer"
        );
        assert!(r.close_round(3).is_empty());
        assert_eq!(r.get(id(2)).unwrap().misses, 1);
        assert!(r.close_round(3).is_empty());
        assert_eq!(
            r.close_round(3),
            vec![(id(2), 3)],
            "node 1 did not answer rounds 2-3 either"
        );
    }

    #[test]
    fn health_sets_role_relay_and_loops_and_state_changes_ignore_counters() {
        let t0 = Instant::now();
        let mut r = Registry::new();
        r.record_heard(id(7), t0);
        r.record_health(
            id(7),
            reply(0, HealthFlags::MOBILE | HealthFlags::RELAY, 10),
            None,
        );
        let e = r.get(id(7)).unwrap();
        assert_eq!(e.role(), Some(Role::Mobile));
        assert_eq!(e.relay, Some(true));
        let doc = e.state(vec![], t0);
        assert_eq!(doc.loops, vec![0, 3]);
        assert!(r.state_changed(id(7), &[]));
        assert!(!r.state_changed(id(7), &[]));
        // Only the uptime moved: no publish.
        r.record_health(
            id(7),
            reply(1, HealthFlags::MOBILE | HealthFlags::RELAY, 11),
            None,
        );
        assert!(!r.state_changed(id(7), &[]));
        // The relay went off: publish.
        r.record_health(id(7), reply(2, HealthFlags::MOBILE, 12), None);
        assert!(r.state_changed(id(7), &[]));
        // A docking link appeared: publish.
        let link = Link {
            port: 1,
            peer: HexId(id(8)),
            peer_port: 0,
        };
        assert!(r.state_changed(id(7), std::slice::from_ref(&link)));
        assert!(!r.state_changed(id(7), &[link]));
    }
}
