//! The island: which nodes answer the doctor's health check, their firmware and protocol
//! versions and unique IDs, boards without a node ID, and nodes on an older protocol.
//!
//! The protocol version travels in `BootUp` (after a reset) and, from 1.3 on, in the identity
//! group's `Protocol` part of a state reply; a node on an older protocol shows it in what it
//! understands: every version answers `HealthCheck`, 1.1 added `StateQuery` (answered with the
//! firmware version and UID), 1.2 `FwQuery`. The doctor asks all three and reads the version from
//! the answers ([`Node::protocol`]).

use std::{collections::BTreeMap, fmt, time::Duration};

use ihex_proto::{FirmwareVersion, Message, NodeId, Packet, StateReport, Uid, PROTOCOL_VERSION};

use super::Verdict;

/// Identifier of the island check.
pub const CHECK: &str = "island.nodes";

/// What one node showed.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Node {
    /// Answered a health check.
    pub health: bool,
    /// Its CAN error counters from the health reply (tx, rx) and its error-passive flag.
    pub errors: Option<(u8, u8, bool)>,
    /// Announced its protocol version in a `BootUp`.
    pub boot_version: Option<(u8, u8)>,
    /// Reported its protocol version in a state reply's `Protocol` part (1.3 and later).
    pub reported_version: Option<(u8, u8)>,
    /// Closed a state reply (`StateReport::End`): speaks 1.1 or later.
    pub state_readback: bool,
    /// Answered a firmware-status query: speaks 1.2 or later.
    pub fw_status: bool,
    /// Its firmware version.
    pub firmware: Option<FirmwareVersion>,
    /// UID bytes 0–6 and 7–11 as reported.
    pub uid_low: Option<[u8; 7]>,
    /// See `uid_low`.
    pub uid_high: Option<[u8; 5]>,
}

/// A protocol version as far as the doctor can tell.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Protocol {
    /// Announced in a `BootUp` or reported in a state reply.
    Exactly(u8, u8),
    /// The newest version whose messages it answered (it may be newer still).
    AtLeast(u8, u8),
}

impl Protocol {
    /// Major and minor.
    pub fn version(self) -> (u8, u8) {
        match self {
            Protocol::Exactly(a, b) | Protocol::AtLeast(a, b) => (a, b),
        }
    }
}

impl fmt::Display for Protocol {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Protocol::Exactly(a, b) => write!(f, "{a}.{b}"),
            Protocol::AtLeast(a, b) if (*a, *b) == PROTOCOL_VERSION => write!(f, "{a}.{b}"),
            Protocol::AtLeast(a, b) => write!(f, "{a}.{b} (no answer to newer queries)"),
        }
    }
}

impl Node {
    /// Its protocol version: announced or reported, else the newest whose query it answered.
    pub fn protocol(&self) -> Protocol {
        match self.boot_version.or(self.reported_version) {
            Some((a, b)) => Protocol::Exactly(a, b),
            None if self.fw_status => Protocol::AtLeast(1, 2),
            None if self.state_readback => Protocol::AtLeast(1, 1),
            None => Protocol::AtLeast(1, 0),
        }
    }

    /// Its unique ID, when both halves arrived.
    pub fn uid(&self) -> Option<Uid> {
        Some(Uid::from_low_high(self.uid_low?, self.uid_high?))
    }
}

/// What the island showed during the doctor's listening.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Facts {
    /// Every node heard, by ID.
    pub nodes: BTreeMap<NodeId, Node>,
    /// Boards without a node ID that spoke (an `AssignReply` from `ffe`): the UID tails they gave.
    pub unconfigured: Vec<[u8; 4]>,
}

impl Facts {
    /// Takes in one decoded frame.
    pub fn observe(&mut self, p: &Packet) {
        if p.src == NodeId::UNCONFIGURED {
            if let Message::AssignReply { uid_tail, .. } = p.msg {
                if !self.unconfigured.contains(&uid_tail) {
                    self.unconfigured.push(uid_tail);
                }
            }
            return;
        }
        if p.src == NodeId::GATEWAY {
            return;
        }
        let node = self.nodes.entry(p.src).or_default();
        match &p.msg {
            Message::HealthReply(h) => {
                node.health = true;
                node.errors = Some((
                    h.tec,
                    h.rec,
                    h.flags.contains(ihex_proto::HealthFlags::ERROR_PASSIVE),
                ));
            }
            Message::BootUp { version, .. } => node.boot_version = Some(*version),
            Message::FwStatus(_) => node.fw_status = true,
            Message::StateReport(r) => match r {
                StateReport::End { .. } => node.state_readback = true,
                StateReport::Firmware { version, .. } => node.firmware = Some(*version),
                StateReport::UidLow(b) => node.uid_low = Some(*b),
                StateReport::UidHigh(b) => node.uid_high = Some(*b),
                StateReport::Protocol { version } => node.reported_version = Some(*version),
                _ => {}
            },
            _ => {}
        }
    }
}

/// Judges the island after listening for `listen`.
pub fn check(f: &Facts, listen: Duration) -> Verdict {
    let secs = listen.as_secs_f32();
    let (major, minor) = PROTOCOL_VERSION;
    let unconfigured = if f.unconfigured.is_empty() {
        String::new()
    } else {
        let tails: Vec<String> = f
            .unconfigured
            .iter()
            .map(|t| ihex_proto::Hex(t).to_string())
            .collect();
        format!(
            "; without a node ID: UID …{} (give each one: ihex-provision can --uid UID --id ID)",
            tails.join(", …")
        )
    };
    let answering: Vec<(&NodeId, &Node)> = f.nodes.iter().filter(|(_, n)| n.health).collect();
    if answering.is_empty() {
        let heard: Vec<String> = f.nodes.keys().map(|id| id.to_string()).collect();
        let heard = if heard.is_empty() {
            String::new()
        } else {
            format!(" (heard from {} without a health reply)", heard.join(", "))
        };
        return Verdict::fail(
            CHECK,
            format!("no node answered a health check in {secs:.1} s{heard}{unconfigured}"),
            "power the boards, check each board's CAN wiring and that its firmware runs \
             (docs/firmware.md: the `loopback` binary tests a board's CAN on its own); a factory-fresh \
             board stays silent until it has a node ID (ihex-provision serial --port … --query)",
        );
    }
    let mut old = Vec::new();
    let listed: Vec<String> = answering
        .iter()
        .map(|(id, n)| {
            let protocol = n.protocol();
            if protocol.version() < PROTOCOL_VERSION {
                old.push(format!("{id} ({protocol})"));
            }
            let fw = n
                .firmware
                .map_or("firmware ?".into(), |v| format!("firmware {v}"));
            let uid = n.uid().map_or(String::new(), |u| format!(", uid {u}"));
            let errors = match n.errors {
                Some((tec, rec, passive)) if tec > 0 || rec > 0 || passive => format!(
                    ", CAN errors tx {tec} rx {rec}{}",
                    if passive { " error-passive" } else { "" }
                ),
                _ => String::new(),
            };
            format!("{id} ({fw}, protocol {protocol}{uid}{errors})")
        })
        .collect();
    let found = format!(
        "{} node(s) answered: {}{unconfigured}",
        answering.len(),
        listed.join("; ")
    );
    if !old.is_empty() {
        return Verdict::fail(
            CHECK,
            found,
            format!(
                "node(s) {} speak an older protocol than this gateway's {major}.{minor}: they miss \
                 newer features (state read-back from 1.1, firmware update over CAN from 1.2); flash \
                 the current firmware over USB (docs/firmware.md)",
                old.join(", ")
            ),
        );
    }
    Verdict::pass(CHECK, found)
}
