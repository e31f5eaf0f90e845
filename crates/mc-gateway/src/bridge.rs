//! The gateway's logic, sans-IO: JSON commands and CAN packets in, frames to send and MQTT publications
//! out. No sockets, no clocks of its own: the async adapters (`can`, `mqtt`) feed it and carry out its
//! [`Action`]s, so every behaviour — command validation, acknowledgement tracking, health and lost-node
//! detection, the one-at-a-time docking sequence — is tested without a bus or a broker.

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::{Duration, Instant};

use ihex_proto::{
    AckResult, DecodeError, DockRefuseReason, FaultCode, Kind, Message, NodeId, Packet, Port, Seq,
    Uid,
};

use crate::command::{self, Command, CommandError, NodeAction};
use crate::docking::{Docking, Step};
use crate::error_frame;
use crate::event::{
    BusError, CommandRejected, CommandResult, DockFailed, Event, FaultEvent, HexId, NodeList,
    NodeLost, NodeOnline, NodeRebooted, Outcome, Refusal, Role, Target,
};
use crate::registry::{millis, Registry, Seen};
use crate::throttle::Throttle;

/// Tunables of the bridge (the CLI/TOML configuration fills these in).
#[derive(Clone, Debug)]
pub struct BridgeConfig {
    /// Period of the broadcast health check (seed: 1 s).
    pub health_period: Duration,
    /// Consecutive missed health replies after which a node is `node_lost` (default 3).
    pub lost_after_misses: u32,
    /// How long to wait for the mobile element's handshake after confirming a docking.
    pub dock_timeout: Duration,
    /// How long to wait for a node's ack before a `command_result` with `"timeout"`.
    pub command_timeout: Duration,
    /// Largest accepted command payload in bytes; larger ones are `command_rejected`.
    pub max_command_bytes: usize,
}

impl Default for BridgeConfig {
    fn default() -> Self {
        BridgeConfig {
            health_period: Duration::from_secs(1),
            lost_after_misses: 3,
            dock_timeout: Duration::from_secs(5),
            command_timeout: Duration::from_millis(500),
            max_command_bytes: 4096,
        }
    }
}

/// Logical MQTT topics; the `mqtt` adapter maps them to names under the island prefix.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum Topic {
    /// `EventsTopic`: every JSON event.
    Events,
    /// The retained state document of one node.
    NodeState(NodeId),
}

/// What the adapters must do for the bridge.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Action {
    /// Transmit on the CAN bus.
    Send(Packet),
    /// Publish `payload` (JSON) on `topic`, QoS 1.
    Publish {
        /// Where.
        topic: Topic,
        /// JSON text.
        payload: String,
        /// Retained (node state) or not (events).
        retain: bool,
    },
}

/// Bus conditions the CAN adapter observes besides frames.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum BusEvent {
    /// An error frame arrived (`can_id` with the error class bits, `data` as received).
    ErrorFrame {
        /// Error class bits (`CAN_ERR_*` of linux/can/error.h).
        class: u32,
        /// The error frame's 8 data bytes.
        data: [u8; 8],
    },
    /// The controller went bus-off.
    BusOff,
    /// The interface went down or vanished (the adapter retries opening it).
    InterfaceDown,
    /// The interface is back up after `BusOff` or `InterfaceDown`.
    Recovered,
    /// The kernel dropped received frames (count since the last report).
    RxDropped(u32),
}

/// Shortest accepted health period: a zero period would make the gateway do nothing but health checks.
pub const MIN_HEALTH_PERIOD: Duration = Duration::from_millis(10);

/// How long the rate limit of error events (`fault`, `bus_error`) holds back repeats of one kind.
pub const ERROR_EVENT_WINDOW: Duration = Duration::from_secs(1);

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

    #[cfg(test)]
    fn is_empty(&self) -> bool {
        self.by_key.is_empty()
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

/// The gateway state machine.
#[derive(Debug)]
pub struct Bridge {
    config: BridgeConfig,
    actions: VecDeque<Action>,
    registry: Registry,
    docking: Docking,
    /// Keyed by (destination, command kind, seq); broadcasts use [`NodeId::BROADCAST`].
    pending: Pending,
    next_seq: Seq,
    health_seq: Seq,
    /// Sequence number of the health check whose replies are being collected.
    outstanding_health: Option<Seq>,
    next_health: Instant,
    throttle: Throttle,
    /// Frames dropped by the kernel and not reported yet (the rate limit sums them up).
    rx_dropped: u64,
    /// Nodes whose state document may have changed since the last publication.
    dirty: BTreeSet<NodeId>,
    /// Our own interface is bus-off or down: nodes cannot answer, so nobody is counted as lost.
    bus_down: bool,
}

fn fault_text(c: FaultCode, arg: u8, detail: u32) -> String {
    match c {
        FaultCode::DockConfirmNotDocked => {
            format!("dock confirm for port {arg}, whose signal loop is open")
        }
        FaultCode::BusOff => {
            format!("CAN controller went bus-off and recovered ({detail} times since boot)")
        }
        FaultCode::ErrorPassive => {
            format!(
                "CAN controller is error-passive (TEC {}, REC {})",
                detail >> 8 & 0xff,
                detail & 0xff
            )
        }
        FaultCode::RxOverrun => format!("{detail} received frames lost"),
        FaultCode::WatchdogReset => "reset by the watchdog".into(),
        FaultCode::ConfigStore => "writing the configuration to flash failed".into(),
        FaultCode::UnexpectedMessage => format!("unexpected message of kind {arg:#04x}"),
        FaultCode::BadFrame => format!("undecodable frame of kind {arg:#04x} addressed to it"),
        FaultCode::Other(v) => {
            format!("fault code {v} unknown to this gateway (arg {arg}, detail {detail})")
        }
    }
}

fn decode_error_key(e: &DecodeError) -> &'static str {
    match e {
        DecodeError::StandardId => "standard_id",
        DecodeError::Remote => "remote",
        DecodeError::UnknownKind(_) => "unknown_kind",
        DecodeError::Length { .. } => "length",
        DecodeError::Value { .. } => "value",
        DecodeError::Address { .. } => "address",
    }
}

impl Bridge {
    /// A bridge started at `now`; the first health check is due at once.
    pub fn new(mut config: BridgeConfig, now: Instant) -> Self {
        config.health_period = config.health_period.max(MIN_HEALTH_PERIOD);
        let docking = Docking::new(config.dock_timeout, Docking::DEFAULT_QUEUE);
        Bridge {
            config,
            actions: VecDeque::new(),
            registry: Registry::new(),
            docking,
            pending: Pending::default(),
            next_seq: 0,
            health_seq: 0,
            outstanding_health: None,
            next_health: now,
            throttle: Throttle::new(ERROR_EVENT_WINDOW),
            rx_dropped: 0,
            dirty: BTreeSet::new(),
            bus_down: false,
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> &BridgeConfig {
        &self.config
    }

    /// The node registry (read-only), e.g. for diagnostics.
    pub fn registry(&self) -> &Registry {
        &self.registry
    }

    /// A message arrived on `CommandsTopic` (raw bytes: the bridge parses and validates them and answers
    /// bad input with a `command_rejected` event).
    pub fn on_command(&mut self, payload: &[u8], now: Instant) {
        let req = match command::parse(payload, self.config.max_command_bytes) {
            Ok(req) => req,
            Err(rej) => return self.reject(rej.request_id, rej.error),
        };
        let request_id = req.request_id;
        match req.command {
            Command::List => {
                let nodes = self
                    .registry
                    .iter()
                    .map(|e| e.state(self.docking.links_of(e.id), now))
                    .collect();
                self.emit(Event::NodeList(NodeList { request_id, nodes }));
            }
            Command::Node { target, action } => {
                if let Target::Node(id) = target {
                    if self.registry.get(id).is_none() {
                        let known = self.registry.known_list();
                        return self.reject(
                            request_id,
                            CommandError::UnknownNode {
                                id: HexId(id),
                                known,
                            },
                        );
                    }
                }
                let kind = action.to_message(0).kind();
                let Some(seq) = self.alloc_seq(target.dest(), kind) else {
                    return self.reject(
                        request_id,
                        CommandError::Busy {
                            cmd: action.name(),
                            node: target,
                        },
                    );
                };
                let packet = Packet::command(target.dest(), action.to_message(seq));
                if let Err(e) = packet.validate() {
                    // The parser checks every range first; this guards against the two drifting apart.
                    let message = format!("the protocol refuses this value: {e}");
                    return self.reject(
                        request_id,
                        CommandError::Invalid {
                            cmd: action.name(),
                            message,
                        },
                    );
                }
                let what = match target {
                    Target::Node(_) => What::Node(action),
                    Target::All => What::Broadcast {
                        action,
                        expected: self.registry.online_ids().into_iter().collect(),
                        acked: BTreeSet::new(),
                        refused: BTreeMap::new(),
                    },
                };
                let deadline = now + self.config.command_timeout;
                self.pending.insert(
                    (target.dest(), kind, seq),
                    PendingCommand {
                        request_id,
                        target,
                        deadline,
                        what,
                    },
                );
                self.actions.push_back(Action::Send(packet));
            }
            Command::Assign { uid, new_id, force } => {
                if !force && self.registry.get(new_id).is_some_and(|e| e.online) {
                    return self.reject(request_id, CommandError::IdInUse(HexId(new_id)));
                }
                let Some(seq) = self.alloc_seq(NodeId::BROADCAST, Kind::AssignCommit) else {
                    let node = Target::Node(new_id);
                    return self.reject(
                        request_id,
                        CommandError::Busy {
                            cmd: "assign",
                            node,
                        },
                    );
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
                let deadline = now + self.config.command_timeout;
                self.pending.insert(
                    (NodeId::BROADCAST, Kind::AssignCommit, seq),
                    PendingCommand {
                        request_id,
                        target: Target::Node(new_id),
                        deadline,
                        what: What::Assign { uid, new_id },
                    },
                );
                // Select before commit: a node only takes the commit after the matching select.
                self.actions.push_back(Action::Send(select));
                self.actions.push_back(Action::Send(commit));
            }
        }
    }

    /// A valid iHEX packet arrived on the bus.
    pub fn on_packet(&mut self, packet: Packet, now: Instant) {
        if packet.dest != NodeId::GATEWAY {
            // Another controller's command seen on the bus: not ours to act on.
            tracing::debug!(?packet, "ignoring packet not addressed to the gateway");
            return;
        }
        let src = packet.src;
        if !src.is_sc() {
            // Only an unconfigured node's AssignReply gets here (the decoder refuses other sources).
            if let Message::AssignReply {
                seq,
                result,
                new_id,
                uid_tail,
            } = packet.msg
            {
                self.on_assign_reply(seq, result, new_id, uid_tail);
            }
            self.flush_states(now);
            return;
        }
        let seen = self.registry.touch(src, now);
        if let Some(e) = self.registry.get_mut(src) {
            // Learn the role first, so that `node_online` can already tell it.
            match packet.msg {
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
                    let mobile = h.flags.contains(ihex_proto::HealthFlags::MOBILE);
                    e.role = Some(if mobile {
                        ihex_proto::BootRole::Mobile
                    } else {
                        ihex_proto::BootRole::Static
                    });
                }
                _ => {}
            }
        }
        let role = self.registry.get(src).and_then(|e| e.role());
        match seen {
            Seen::New => self.emit(Event::NodeOnline(NodeOnline {
                id: HexId(src),
                role,
                first_seen: true,
            })),
            Seen::Back => self.emit(Event::NodeOnline(NodeOnline {
                id: HexId(src),
                role,
                first_seen: false,
            })),
            Seen::Known => {}
        }
        self.dirty.insert(src);
        match packet.msg {
            Message::BootUp { version, reset, .. } => {
                if seen == Seen::Known {
                    self.emit(Event::NodeRebooted(NodeRebooted {
                        id: HexId(src),
                        reset: reset.to_string(),
                        version: format!("{}.{}", version.0, version.1),
                        role: role.unwrap_or(Role::Static),
                    }));
                }
                if let Some(e) = self.registry.get_mut(src) {
                    e.reset_actuators();
                }
            }
            Message::HealthReply(h) => {
                self.registry.record_health(src, h, self.outstanding_health);
            }
            Message::Ack {
                kind, seq, result, ..
            } => self.on_ack(src, kind, seq, result, now),
            Message::Fault { code, arg, detail } => {
                let name = code.to_string();
                if let Some(suppressed) = self.throttle.admit(&format!("fault:{src}:{name}"), now) {
                    self.emit(Event::Fault(FaultEvent {
                        node: HexId(src),
                        code: name,
                        arg,
                        detail,
                        message: fault_text(code, arg, detail),
                        suppressed: (suppressed > 0).then_some(suppressed),
                    }));
                }
            }
            Message::DockDetected { port } => {
                if let Some(e) = self.registry.get_mut(src) {
                    e.loops |= port.mask();
                }
                let steps = self.docking.on_detected(src, port, now);
                self.apply(steps, now);
            }
            Message::DockRemoved { port } => {
                if let Some(e) = self.registry.get_mut(src) {
                    e.loops &= !port.mask();
                }
                let steps = self.docking.on_removed(src, port, now);
                self.apply(steps, now);
            }
            Message::Handshake { port } => {
                let steps = self.docking.on_handshake(src, port, now);
                self.apply(steps, now);
            }
            Message::AssignReply {
                seq,
                result,
                new_id,
                uid_tail,
            } => self.on_assign_reply(seq, result, new_id, uid_tail),
            // Command kinds never come addressed to the gateway (the decoder checks addresses).
            _ => tracing::debug!(?packet, "ignoring unexpected packet"),
        }
        self.flush_states(now);
    }

    /// A frame arrived that passed the filters but is not a valid iHEX packet.
    pub fn on_undecodable(&mut self, raw_id: u32, data: &[u8], err: DecodeError, now: Instant) {
        let key = decode_error_key(&err);
        let Some(suppressed) = self.throttle.admit(&format!("undecodable:{key}"), now) else {
            return;
        };
        let hex = error_frame::hex(&data[..data.len().min(64)]);
        self.emit(Event::BusError(BusError {
            error: "undecodable_frame".into(),
            message: format!("frame {raw_id:#010x} [{hex}] is not an iHEX packet: {err}"),
            raw_id: Some(format!("{raw_id:#010x}")),
            data: Some(hex),
            suppressed: (suppressed > 0).then_some(suppressed),
            ..BusError::default()
        }));
    }

    /// A bus condition (error frame, bus-off, interface down/up, drops).
    pub fn on_bus_event(&mut self, event: BusEvent, now: Instant) {
        let (key, mut err) = match event {
            BusEvent::ErrorFrame { class, data } => (
                format!("error_frame:{:x}", class & 0x1FFF_FFFF),
                error_frame::decode(class, data),
            ),
            BusEvent::BusOff => (
                "bus_off".into(),
                BusError {
                    error: "bus_off".into(),
                    message:
                        "the CAN controller is bus-off; frames cannot be sent until it recovers"
                            .into(),
                    ..BusError::default()
                },
            ),
            BusEvent::InterfaceDown => (
                "interface_down".into(),
                BusError {
                    error: "interface_down".into(),
                    message: "the CAN interface is down or gone; the gateway keeps retrying it"
                        .into(),
                    ..BusError::default()
                },
            ),
            BusEvent::Recovered => (
                "recovered".into(),
                BusError {
                    error: "recovered".into(),
                    message: "the CAN interface is up again".into(),
                    ..BusError::default()
                },
            ),
            BusEvent::RxDropped(n) => {
                self.rx_dropped = self.rx_dropped.saturating_add(u64::from(n));
                let count = self.rx_dropped;
                (
                    "rx_dropped".into(),
                    BusError {
                        error: "rx_dropped".into(),
                        message: format!("the kernel dropped {count} received frames"),
                        count: Some(count),
                        ..BusError::default()
                    },
                )
            }
        };
        match event {
            BusEvent::BusOff | BusEvent::InterfaceDown => {
                // The silence that follows is ours, not the nodes': stop health checks (and with
                // them lost detection) until the interface is back.
                self.bus_down = true;
                self.outstanding_health = None;
            }
            BusEvent::Recovered if self.bus_down => {
                self.bus_down = false;
                self.next_health = now;
            }
            _ => {}
        }
        let Some(suppressed) = self.throttle.admit(&key, now) else {
            return;
        };
        if matches!(event, BusEvent::RxDropped(_)) {
            self.rx_dropped = 0;
        }
        err.suppressed = (suppressed > 0).then_some(suppressed);
        self.emit(Event::BusError(err));
    }

    /// A frame from [`Action::Send`] could not be transmitted.
    pub fn on_send_failed(&mut self, packet: Packet, reason: &str, now: Instant) {
        let kind = packet.msg.kind();
        let key = match packet.msg {
            Message::DockConfirm { seq, .. } => {
                let steps = self
                    .docking
                    .on_confirm_failed(packet.dest, seq, reason, now);
                let handled = !steps.is_empty();
                self.apply(steps, now);
                self.flush_states(now);
                if handled {
                    return;
                }
                None
            }
            Message::AssignSelect { uid_head } => self
                .pending
                .iter()
                .find(|(_, p)| matches!(p.what, What::Assign { uid, .. } if uid.head() == uid_head))
                .map(|(k, _)| *k),
            Message::AssignCommit { seq, .. } => Some((NodeId::BROADCAST, Kind::AssignCommit, seq)),
            ref m => m.ack_seq().map(|seq| (packet.dest, kind, seq)),
        };
        if let Some(p) = key.and_then(|k| self.pending.remove(&k)) {
            self.emit_result(p, Outcome::Failed, Some(format!("not sent: {reason}")));
            return;
        }
        let (raw_id, _) = packet.encode();
        let Some(suppressed) = self.throttle.admit(&format!("send_failed:{kind:?}"), now) else {
            return;
        };
        self.emit(Event::BusError(BusError {
            error: "send_failed".into(),
            message: format!(
                "{kind:?} to {} not sent: {reason}",
                Target::from_dest(packet.dest)
            ),
            raw_id: Some(format!("{raw_id:#010x}")),
            suppressed: (suppressed > 0).then_some(suppressed),
            ..BusError::default()
        }));
    }

    /// The MQTT session is (re)established: queue the retained node states again (a restarted broker
    /// may have lost them).
    pub fn on_mqtt_connected(&mut self, now: Instant) {
        let ids: Vec<NodeId> = self.registry.iter().map(|e| e.id).collect();
        for id in ids {
            self.publish_state(id, now, true);
        }
        self.dirty.clear();
    }

    /// Advances timers: health broadcast, lost nodes, ack and docking timeouts.
    pub fn tick(&mut self, now: Instant) {
        for k in self.pending.overdue(now) {
            if let Some(p) = self.pending.remove(&k) {
                self.finish_timed_out(p);
            }
        }
        let steps = self.docking.tick(now);
        self.apply(steps, now);
        if now >= self.next_health && self.bus_down {
            self.next_health = now + self.config.health_period;
        } else if now >= self.next_health {
            if self.outstanding_health.is_none() {
                self.registry.start_round();
            } else {
                for (id, missed) in self.registry.close_round(self.config.lost_after_misses) {
                    let last_seen_ms = self
                        .registry
                        .get(id)
                        .map_or(0, |e| millis(now.saturating_duration_since(e.last_seen)));
                    self.emit(Event::NodeLost(NodeLost {
                        id: HexId(id),
                        missed,
                        last_seen_ms,
                    }));
                    self.dirty.insert(id);
                    let steps = self.docking.on_lost(id);
                    self.apply(steps, now);
                }
            }
            let seq = self.health_seq;
            self.health_seq = seq.wrapping_add(1);
            self.outstanding_health = Some(seq);
            self.actions.push_back(Action::Send(Packet::command(
                NodeId::BROADCAST,
                Message::HealthCheck { seq },
            )));
            self.next_health += self.config.health_period;
            if self.next_health <= now {
                // Far behind (a suspended process): skip the missed checks instead of bursting them.
                self.next_health = now + self.config.health_period;
            }
        }
        self.flush_states(now);
    }

    /// When [`Bridge::tick`] must run next.
    pub fn next_deadline(&self) -> Instant {
        let mut next = self.next_health;
        if let Some(d) = self.pending.next_deadline() {
            next = next.min(d);
        }
        if let Some(d) = self.docking.deadline() {
            next = next.min(d);
        }
        next
    }

    /// Next action for the adapters, `None` when drained.
    pub fn poll_action(&mut self) -> Option<Action> {
        self.actions.pop_front()
    }

    fn emit(&mut self, event: Event) {
        tracing::debug!(event = event.name(), "event");
        self.actions.push_back(Action::Publish {
            topic: Topic::Events,
            payload: event.to_json(),
            retain: false,
        });
    }

    fn reject(&mut self, request_id: Option<String>, error: CommandError) {
        tracing::info!(%error, "command rejected");
        self.emit(Event::CommandRejected(CommandRejected {
            request_id,
            reason: error.to_string(),
        }));
    }

    /// Tells static `node` not to power (or to stop powering) its dock `port`.
    fn send_dock_refuse(&mut self, node: NodeId, port: Port, reason: DockRefuseReason) {
        let seq = self
            .alloc_seq(node, Kind::DockRefuse)
            .unwrap_or(self.next_seq);
        let msg = Message::DockRefuse { seq, port, reason };
        self.actions
            .push_back(Action::Send(Packet::command(node, msg)));
    }

    /// A sequence number not in use by a pending command of this kind to this destination.
    fn alloc_seq(&mut self, dest: NodeId, kind: Kind) -> Option<Seq> {
        for _ in 0..=u8::MAX {
            let seq = self.next_seq;
            self.next_seq = seq.wrapping_add(1);
            if !self.pending.contains_key(&(dest, kind, seq)) {
                return Some(seq);
            }
        }
        None
    }

    fn publish_state(&mut self, id: NodeId, now: Instant, force: bool) {
        let Some(e) = self.registry.get(id) else {
            return;
        };
        let doc = e.state(self.docking.links_of(id), now);
        let changed = self.registry.state_changed(id, &doc);
        if changed || force {
            let payload = crate::event::to_json(&doc);
            self.actions.push_back(Action::Publish {
                topic: Topic::NodeState(id),
                payload,
                retain: true,
            });
        }
    }

    fn flush_states(&mut self, now: Instant) {
        for id in std::mem::take(&mut self.dirty) {
            self.publish_state(id, now, false);
        }
    }

    fn apply_action_state(&mut self, node: NodeId, action: NodeAction) {
        if let Some(e) = self.registry.get_mut(node) {
            match action {
                NodeAction::Led(cmd) => e.led = Some(cmd),
                NodeAction::Buzzer(cmd) => e.buzzer = Some(cmd),
                NodeAction::Power(on) => e.relay = Some(on),
                NodeAction::Identify(_) => {}
            }
            self.dirty.insert(node);
        }
    }

    fn on_ack(&mut self, src: NodeId, kind: Kind, seq: Seq, result: AckResult, now: Instant) {
        if kind == Kind::DockConfirm {
            if result != AckResult::Ok {
                let steps = self
                    .docking
                    .on_confirm_refused(src, seq, &result.to_string(), now);
                self.apply(steps, now);
            }
            return;
        }
        if let Some(p) = self.pending.remove(&(src, kind, seq)) {
            let What::Node(action) = p.what else { return };
            if result == AckResult::Ok {
                self.apply_action_state(src, action);
                self.emit_result(p, Outcome::Ok, None);
            } else {
                self.emit_result(p, Outcome::Refused, Some(result.to_string()));
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
            self.apply_action_state(src, action);
        }
        if complete {
            if let Some(p) = self.pending.remove(&key) {
                self.finish_broadcast(p);
            }
        }
    }

    fn on_assign_reply(&mut self, seq: Seq, result: AckResult, new_id: NodeId, uid_tail: [u8; 4]) {
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
                self.emit_result(p, Outcome::Refused, Some(reason));
            } else if result == AckResult::Ok {
                self.emit_result(p, Outcome::Ok, None);
            } else {
                self.emit_result(p, Outcome::Refused, Some(result.to_string()));
            }
        }
    }

    fn finish_timed_out(&mut self, p: PendingCommand) {
        match &p.what {
            What::Broadcast { .. } => self.finish_broadcast(p),
            What::Assign { .. } => {
                let reason = format!(
                    "no AssignReply within {} ms (is a board with this uid on the bus?)",
                    self.config.command_timeout.as_millis()
                );
                self.emit_result(p, Outcome::Timeout, Some(reason));
            }
            What::Node(_) => {
                let reason = format!(
                    "no ack within {} ms",
                    self.config.command_timeout.as_millis()
                );
                self.emit_result(p, Outcome::Timeout, Some(reason));
            }
        }
    }

    fn finish_broadcast(&mut self, p: PendingCommand) {
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
        self.emit(Event::CommandResult(result));
    }

    fn emit_result(&mut self, p: PendingCommand, result: Outcome, reason: Option<String>) {
        if let What::Broadcast { .. } = p.what {
            if result != Outcome::Failed {
                return self.finish_broadcast(p);
            }
        }
        self.emit(Event::CommandResult(CommandResult {
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

    /// Carries out the docking sequence's steps.
    fn apply(&mut self, steps: Vec<Step>, now: Instant) {
        for step in steps {
            match step {
                Step::Confirm { node, port } => {
                    let seq = self
                        .alloc_seq(node, Kind::DockConfirm)
                        .unwrap_or(self.next_seq);
                    self.docking.confirm_sent(seq);
                    self.actions.push_back(Action::Send(Packet::command(
                        node,
                        Message::DockConfirm { seq, port },
                    )));
                }
                Step::RefuseBusy { node, port } => {
                    self.send_dock_refuse(node, port, DockRefuseReason::Busy)
                }
                Step::Withdraw { node, port } => {
                    self.send_dock_refuse(node, port, DockRefuseReason::NotAllowed)
                }
                Step::PowerOff { node } => {
                    let seq = self
                        .alloc_seq(node, Kind::PowerSet)
                        .unwrap_or(self.next_seq);
                    self.actions.push_back(Action::Send(Packet::command(
                        node,
                        Message::PowerSet { seq, on: false },
                    )));
                }
                Step::Connected(c) => {
                    self.dirty.insert(c.n.id.0);
                    self.dirty.insert(c.n_1.id.0);
                    self.emit(Event::NewConnection(c));
                }
                Step::Removed(c) => {
                    self.dirty.insert(c.n.id.0);
                    self.dirty.insert(c.n_1.id.0);
                    self.emit(Event::ConnectionRemoved(c));
                }
                Step::Failed { node, port, reason } => {
                    self.emit(Event::DockFailed(DockFailed {
                        node: HexId(node),
                        port: port.get(),
                        reason,
                    }));
                }
                Step::UnexpectedHandshake { node, port, why } => {
                    let key = format!("fault:{node}:unexpected_handshake");
                    let Some(suppressed) = self.throttle.admit(&key, now) else {
                        continue;
                    };
                    self.emit(Event::Fault(FaultEvent {
                        node: HexId(node),
                        code: "unexpected_handshake".into(),
                        arg: port.get(),
                        detail: 0,
                        message: format!("handshake from {node} (its port {port}) ignored: {why}"),
                        suppressed: (suppressed > 0).then_some(suppressed),
                    }));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::{BootRole, HealthFlags, HealthReply, LedCommand, Port, ResetReason, Rgb};
    use serde_json::{json, Value};

    fn id(raw: u16) -> NodeId {
        NodeId::new(raw).unwrap()
    }
    fn port(raw: u8) -> Port {
        Port::new(raw).unwrap()
    }
    const MS: Duration = Duration::from_millis(1);
    const S: Duration = Duration::from_secs(1);

    /// What one call made the bridge do.
    #[derive(Default, Debug)]
    struct Out {
        sent: Vec<Packet>,
        events: Vec<Value>,
        raw_events: Vec<String>,
        states: Vec<(NodeId, Value)>,
    }

    impl Out {
        fn named(&self, name: &str) -> Vec<&Value> {
            self.events.iter().filter(|e| e["event"] == name).collect()
        }
        fn one(&self, name: &str) -> &Value {
            let v = self.named(name);
            assert_eq!(v.len(), 1, "expected one {name} in {:#?}", self.events);
            &v[0]["payload"]
        }
    }

    fn drain(b: &mut Bridge) -> Out {
        let mut out = Out::default();
        while let Some(a) = b.poll_action() {
            match a {
                Action::Send(p) => {
                    p.validate().expect("the bridge only sends valid packets");
                    out.sent.push(p)
                }
                Action::Publish {
                    topic: Topic::Events,
                    payload,
                    retain,
                } => {
                    assert!(!retain, "events are not retained");
                    out.events.push(serde_json::from_str(&payload).unwrap());
                    out.raw_events.push(payload);
                }
                Action::Publish {
                    topic: Topic::NodeState(id),
                    payload,
                    retain,
                } => {
                    assert!(retain, "node states are retained");
                    out.states
                        .push((id, serde_json::from_str(&payload).unwrap()));
                }
            }
        }
        out
    }

    fn reply(seq: u8, flags: u8) -> Message {
        Message::HealthReply(HealthReply {
            seq,
            flags: HealthFlags(flags),
            loops: 0,
            tec: 0,
            rec: 0,
            uptime_s: 1,
        })
    }

    fn ack(kind: Kind, seq: u8, result: AckResult) -> Message {
        Message::Ack {
            kind,
            seq,
            result,
            detail: 0,
        }
    }

    /// A bridge at `t0` whose first health check went out and was answered by `nodes`.
    fn with_nodes(nodes: &[u16]) -> (Bridge, Instant) {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        b.tick(t0);
        let out = drain(&mut b);
        assert_eq!(
            out.sent,
            vec![Packet::command(
                NodeId::BROADCAST,
                Message::HealthCheck { seq: 0 }
            )]
        );
        for &n in nodes {
            b.on_packet(Packet::report(id(n), reply(0, 0)), t0 + MS);
        }
        drain(&mut b);
        (b, t0)
    }

    fn command(b: &mut Bridge, json: Value, now: Instant) -> Out {
        b.on_command(json.to_string().as_bytes(), now);
        drain(b)
    }

    #[test]
    fn first_health_check_is_due_at_once_then_every_period() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        assert_eq!(b.next_deadline(), t0);
        b.tick(t0);
        assert_eq!(drain(&mut b).sent.len(), 1);
        assert_eq!(b.next_deadline(), t0 + S);
        b.tick(t0 + S - MS);
        assert!(drain(&mut b).sent.is_empty());
        b.tick(t0 + S);
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
        b.tick(t0);
        drain(&mut b);
        b.on_packet(
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
        b.on_packet(
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
            b.tick(t0 + S * u32::from(round));
            let out = drain(&mut b);
            assert!(
                out.named("node_lost").is_empty(),
                "round {round}: {:?}",
                out.events
            );
            b.on_packet(
                Packet::report(id(3), reply(round, 0)),
                t0 + S * u32::from(round) + MS,
            );
        }
        b.tick(t0 + 4 * S);
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
        b.on_packet(Packet::report(id(3), reply(4, 0)), t0 + 4 * S + MS);
        b.tick(t0 + 5 * S);
        assert!(drain(&mut b).named("node_lost").is_empty());
        b.on_packet(Packet::report(id(2), reply(5, 0)), t0 + 5 * S + MS);
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
        b.on_packet(Packet::report(id(5), boot), t0 + S);
        let out = drain(&mut b);
        assert_eq!(
            out.one("node_rebooted"),
            &json!({"id": "5", "reset": "watchdog", "version": "1.0", "role": "mobile"})
        );
        assert!(out.named("node_online").is_empty());
        // A never-seen node's BootUp is just node_online, with its role.
        b.on_packet(Packet::report(id(6), boot), t0 + S);
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
            b.next_deadline(),
            t0 + 100 * MS + BridgeConfig::default().command_timeout
        );
        b.on_packet(
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
        b.on_packet(
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
        b.on_packet(
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
        b.tick(t0 + timeout - MS);
        assert!(drain(&mut b).named("command_result").is_empty());
        assert_eq!(b.next_deadline(), t0 + timeout);
        b.tick(t0 + timeout);
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
        b.on_send_failed(out.sent[0], "No buffer space available", t0 + MS);
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(r["result"], "failed");
        assert_eq!(r["reason"], "not sent: No buffer space available");
        // A health check that cannot be sent is a bus_error.
        b.on_send_failed(
            Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: 0 }),
            "down",
            t0,
        );
        assert_eq!(drain(&mut b).one("bus_error")["error"], "send_failed");
    }

    #[test]
    fn unknown_node_is_rejected_with_the_known_list() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        let out = command(
            &mut b,
            json!({"cmd": "led", "node": "1a2", "color": "red", "request_id": "q"}),
            t0,
        );
        assert!(out.sent.is_empty());
        assert_eq!(
            out.one("command_rejected"),
            &json!({"request_id": "q", "reason": "unknown node 1a2; known: 2, 111"})
        );
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
        b.on_packet(
            Packet::report(id(3), ack(Kind::LedSet, seq, AckResult::Ok)),
            t0 + MS,
        );
        assert!(
            drain(&mut b).named("command_result").is_empty(),
            "node 2 has not answered yet"
        );
        b.on_packet(
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
        b.on_packet(
            Packet::report(id(2), ack(Kind::PowerSet, seq, AckResult::Ok)),
            t0 + S + MS,
        );
        b.tick(t0 + S + BridgeConfig::default().command_timeout);
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(r["result"], "timeout");
        assert_eq!(r["acked"], json!(["2"]));
        assert_eq!(r["missing"], json!(["3"]));
        assert_eq!(r["reason"], "1 of 2 online nodes did not answer");
    }

    #[test]
    fn docking_sequence_publishes_the_seed_events() {
        let (mut b, t0) = with_nodes(&[0x111]);
        b.on_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0 + S,
        );
        let out = drain(&mut b);
        assert_eq!(out.sent.len(), 1);
        let Message::DockConfirm { seq, port: p } = out.sent[0].msg else {
            panic!("{:?}", out.sent)
        };
        assert_eq!((out.sent[0].dest, p), (id(0x111), port(3)));
        // The next health check (t0 + 1 s) is due before the handshake deadline (t0 + 6 s).
        assert_eq!(b.next_deadline(), t0 + S);
        b.on_packet(
            Packet::report(id(0x111), ack(Kind::DockConfirm, seq, AckResult::Ok)),
            t0 + S + MS,
        );
        assert!(drain(&mut b).events.is_empty());
        // The mobile element boots (first heard: node_online) and handshakes.
        let boot = Message::BootUp {
            version: (1, 0),
            role: BootRole::Mobile,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        b.on_packet(Packet::report(id(2), boot), t0 + 2 * S);
        b.on_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0 + 2 * S,
        );
        let out = drain(&mut b);
        let names: Vec<_> = out
            .events
            .iter()
            .map(|e| e["event"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["node_online", "new_connection"]);
        assert_eq!(
            out.raw_events[1],
            r#"{"event":"new_connection","payload":{"n":{"id":"2","port":0},"n-1":{"id":"111","port":3}}}"#
        );
        let st = |n: u16| {
            out.states
                .iter()
                .rev()
                .find(|(i, _)| *i == id(n))
                .map(|(_, s)| s.clone())
                .unwrap()
        };
        assert_eq!(
            st(0x111)["connections"],
            json!([{"port": 3, "peer": "2", "peer_port": 0}])
        );
        assert_eq!(
            st(2)["connections"],
            json!([{"port": 0, "peer": "111", "peer_port": 3}])
        );
        // Undocking.
        b.on_packet(
            Packet::report(id(0x111), Message::DockRemoved { port: port(3) }),
            t0 + 3 * S,
        );
        let out = drain(&mut b);
        assert_eq!(
            out.raw_events,
            [
                r#"{"event":"connection_removed","payload":{"n":{"id":"2","port":0},"n-1":{"id":"111","port":3}}}"#
            ]
        );
    }

    #[test]
    fn handshake_timeout_powers_off_and_reports() {
        let (mut b, t0) = with_nodes(&[0x10]);
        b.on_packet(
            Packet::report(id(0x10), Message::DockDetected { port: port(1) }),
            t0,
        );
        drain(&mut b);
        let deadline = t0 + BridgeConfig::default().dock_timeout;
        assert_eq!(deadline, t0 + 5 * S);
        // Keep the node online meanwhile.
        for k in 1..=4u32 {
            b.tick(t0 + S * k);
            b.on_packet(Packet::report(id(0x10), reply(k as u8, 0)), t0 + S * k);
        }
        let out = drain(&mut b);
        assert!(out.named("dock_failed").is_empty(), "{:?}", out.events);
        b.tick(deadline - MS);
        assert!(drain(&mut b).named("dock_failed").is_empty());
        b.tick(deadline);
        let out = drain(&mut b);
        assert!(out
            .sent
            .iter()
            .any(|p| p.dest == id(0x10) && matches!(p.msg, Message::PowerSet { on: false, .. })));
        assert_eq!(
            out.one("dock_failed"),
            &json!({"node": "10", "port": 1, "reason": "handshake timeout after 5000 ms"})
        );
        // A handshake now is unexpected: a fault, no connection.
        b.on_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            deadline + MS,
        );
        let out = drain(&mut b);
        assert_eq!(out.one("fault")["code"], "unexpected_handshake");
        assert!(out.named("new_connection").is_empty());
    }

    #[test]
    fn docking_queue_full_refuses_busy() {
        let (mut b, t0) = with_nodes(&[1]);
        for p in 0..=Docking::DEFAULT_QUEUE as u8 {
            b.on_packet(
                Packet::report(id(1), Message::DockDetected { port: port(p % 8) }),
                t0,
            );
        }
        let out = drain(&mut b);
        assert_eq!(
            out.sent.len(),
            1,
            "one confirm, the other ports wait: {:?}",
            out.sent
        );
        // Ports 1..=7 queued; 8 distinct ports exist, so fill the queue from a second node.
        b.on_packet(
            Packet::report(id(9), Message::DockDetected { port: port(0) }),
            t0,
        );
        let out = drain(&mut b);
        assert!(out.sent.is_empty(), "queued (queue had 7 of 8)");
        b.on_packet(
            Packet::report(id(9), Message::DockDetected { port: port(1) }),
            t0,
        );
        let out = drain(&mut b);
        assert!(
            matches!(
                out.sent[..],
                [Packet {
                    msg: Message::DockRefuse {
                        reason: DockRefuseReason::Busy,
                        ..
                    },
                    ..
                }]
            ),
            "{:?}",
            out.sent
        );
    }

    #[test]
    fn lost_mobile_element_removes_its_connection() {
        let (mut b, t0) = with_nodes(&[0x111, 2]);
        b.on_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0 + MS,
        );
        b.on_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0 + MS,
        );
        drain(&mut b);
        let mut removed = None;
        for k in 1..=4u32 {
            b.tick(t0 + S * k);
            b.on_packet(
                Packet::report(id(0x111), reply(k as u8, 0)),
                t0 + S * k + MS,
            );
            let out = drain(&mut b);
            if !out.named("node_lost").is_empty() {
                removed = Some(out);
            }
        }
        let out = removed.expect("node 2 lost");
        assert_eq!(out.one("node_lost")["id"], "2");
        assert_eq!(
            out.one("connection_removed")["n"],
            json!({"id": "2", "port": 0})
        );
    }

    #[test]
    fn faults_are_named_and_rate_limited() {
        let (mut b, t0) = with_nodes(&[4]);
        let fault = Message::Fault {
            code: FaultCode::RxOverrun,
            arg: 0,
            detail: 12,
        };
        b.on_packet(Packet::report(id(4), fault), t0);
        let out = drain(&mut b);
        assert_eq!(
            out.one("fault"),
            &json!({"node": "4", "code": "rx_overrun", "arg": 0, "detail": 12, "message": "12 received frames lost"})
        );
        for _ in 0..50 {
            b.on_packet(Packet::report(id(4), fault), t0 + MS);
        }
        assert!(drain(&mut b).named("fault").is_empty());
        b.on_packet(Packet::report(id(4), fault), t0 + S);
        assert_eq!(drain(&mut b).one("fault")["suppressed"], 50);
    }

    #[test]
    fn undecodable_frames_and_bus_events_are_rate_limited_bus_errors() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        let err = DecodeError::UnknownKind(0x1f);
        for _ in 0..5 {
            b.on_undecodable(0x1f00_0001, &[1, 2], err, t0);
        }
        let out = drain(&mut b);
        let e = out.one("bus_error");
        assert_eq!(e["error"], "undecodable_frame");
        assert_eq!(e["raw_id"], "0x1f000001");
        assert_eq!(e["data"], "0102");
        assert!(e["message"]
            .as_str()
            .unwrap()
            .contains("unknown message kind 0x1f"));
        b.on_undecodable(0x1f00_0001, &[], err, t0 + S);
        assert_eq!(drain(&mut b).one("bus_error")["suppressed"], 4);

        b.on_bus_event(
            BusEvent::ErrorFrame {
                class: 0x4,
                data: [0, 0x10, 0, 0, 0, 0, 0, 0],
            },
            t0,
        );
        let out = drain(&mut b);
        assert_eq!(out.one("bus_error")["controller"], json!(["rx_passive"]));
        b.on_bus_event(BusEvent::BusOff, t0);
        b.on_bus_event(BusEvent::Recovered, t0);
        b.on_bus_event(BusEvent::InterfaceDown, t0);
        let kinds: Vec<_> = drain(&mut b)
            .events
            .iter()
            .map(|e| e["payload"]["error"].clone())
            .collect();
        assert_eq!(
            kinds,
            [
                json!("bus_off"),
                json!("recovered"),
                json!("interface_down")
            ]
        );
        b.on_bus_event(BusEvent::RxDropped(3), t0);
        b.on_bus_event(BusEvent::RxDropped(4), t0 + MS);
        b.on_bus_event(BusEvent::RxDropped(5), t0 + S);
        let out = drain(&mut b);
        let counts: Vec<_> = out
            .events
            .iter()
            .map(|e| e["payload"]["count"].clone())
            .collect();
        assert_eq!(
            counts,
            [json!(3), json!(9)],
            "drops while throttled are summed, not lost"
        );
    }

    #[test]
    fn mqtt_reconnect_republishes_every_state() {
        let (mut b, t0) = with_nodes(&[1, 2, 3]);
        b.on_mqtt_connected(t0 + S);
        let out = drain(&mut b);
        let ids: Vec<_> = out
            .states
            .iter()
            .map(|(n, s)| (*n, s["id"].clone()))
            .collect();
        assert_eq!(
            ids,
            [
                (id(1), json!("1")),
                (id(2), json!("2")),
                (id(3), json!("3"))
            ]
        );
        assert!(out.states.iter().all(|(_, s)| s["last_seen_ms"] == 999));
    }

    #[test]
    fn list_reports_every_node() {
        let (mut b, t0) = with_nodes(&[0xa, 0x1]);
        let out = command(&mut b, json!({"cmd": "list", "request_id": "L"}), t0 + S);
        let l = out.one("node_list");
        assert_eq!(l["request_id"], "L");
        let ids: Vec<_> = l["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .map(|n| n["id"].clone())
            .collect();
        assert_eq!(ids, [json!("1"), json!("a")]);
        assert!(out.sent.is_empty());
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
        b.on_packet(Packet::report(id(0x123), other), t0 + MS);
        assert!(drain(&mut b).named("command_result").is_empty());
        let reply = Message::AssignReply {
            seq,
            result: AckResult::Ok,
            new_id,
            uid_tail,
        };
        b.on_packet(Packet::report(id(0x123), reply), t0 + MS);
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
        b.on_packet(Packet::report(NodeId::UNCONFIGURED, refused), t0 + S + MS);
        let r = drain(&mut b);
        let r = r.one("command_result");
        assert_eq!(
            (r["result"].as_str(), r["reason"].as_str()),
            (Some("refused"), Some("store_failed"))
        );
    }

    #[test]
    fn bad_input_never_panics_and_always_answers_once() {
        let (mut b, t0) = with_nodes(&[2]);
        let mut inputs: Vec<Vec<u8>> = vec![
            b"".to_vec(),
            b"{".to_vec(),
            b"[]".to_vec(),
            b"42".to_vec(),
            vec![0xff, 0x00, 0x80],
            br#"{"cmd":"led","node":"2","color":"red","brightness":-1}"#.to_vec(),
            br#"{"cmd":"buzzer","node":"2","mode":"on","freq_hz":1e9}"#.to_vec(),
            br#"{"cmd":"identify","node":"all","seconds":null,"extra":1}"#.to_vec(),
            vec![b' '; 5000],
        ];
        // Deterministic pseudo-random byte strings, some with a JSON-looking prefix.
        let mut x: u32 = 0x1234_5678;
        for n in 0..300 {
            let mut v: Vec<u8> = if n % 2 == 0 {
                br#"{"cmd":"led","node":""#.to_vec()
            } else {
                Vec::new()
            };
            for _ in 0..(n % 40) {
                x ^= x << 13;
                x ^= x >> 17;
                x ^= x << 5;
                v.push((x & 0xff) as u8);
            }
            inputs.push(v);
        }
        for input in &inputs {
            b.on_command(input, t0);
            let out = drain(&mut b);
            assert!(out.sent.is_empty(), "{input:?} sent {:?}", out.sent);
            assert_eq!(
                out.named("command_rejected").len(),
                1,
                "{input:?}: {:?}",
                out.events
            );
        }
        let big = vec![b' '; 5000];
        b.on_command(&big, t0);
        let reason = drain(&mut b).one("command_rejected")["reason"].clone();
        assert_eq!(reason, "command is 5000 bytes; the limit is 4096 bytes");
    }

    #[test]
    fn own_bus_outage_suspends_lost_detection() {
        let (mut b, t0) = with_nodes(&[2]);
        b.on_bus_event(BusEvent::InterfaceDown, t0 + MS);
        assert_eq!(drain(&mut b).one("bus_error")["error"], "interface_down");
        for k in 1..=10u32 {
            b.tick(t0 + S * k);
            let out = drain(&mut b);
            assert!(
                out.sent.is_empty(),
                "no health checks while down: {:?}",
                out.sent
            );
            assert!(out.named("node_lost").is_empty());
        }
        b.on_bus_event(BusEvent::Recovered, t0 + 10 * S + MS);
        drain(&mut b);
        assert_eq!(
            b.next_deadline(),
            t0 + 10 * S + MS,
            "a health check at once"
        );
        b.tick(t0 + 10 * S + MS);
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
            b.tick(t0 + 10 * S + MS + S * k);
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
        b.tick(t0);
        assert!(b.next_deadline() > t0);
    }

    #[test]
    fn undocking_during_a_pending_docking_cancels_it_and_the_queue_moves_on() {
        let (mut b, t0) = with_nodes(&[1, 9]);
        b.on_packet(
            Packet::report(id(1), Message::DockDetected { port: port(0) }),
            t0,
        );
        b.on_packet(
            Packet::report(id(9), Message::DockDetected { port: port(4) }),
            t0,
        );
        let out = drain(&mut b);
        assert_eq!(out.sent.len(), 1, "only the first is confirmed");
        b.on_packet(
            Packet::report(id(1), Message::DockRemoved { port: port(0) }),
            t0 + MS,
        );
        let out = drain(&mut b);
        let f = out.one("dock_failed");
        assert_eq!(
            (f["node"].as_str(), f["port"].as_u64()),
            (Some("1"), Some(0))
        );
        assert!(f["reason"].as_str().unwrap().starts_with("cancelled"));
        assert!(matches!(
            out.sent[..],
            [Packet { msg: Message::DockConfirm { .. }, dest, .. }] if dest == id(9)
        ));
        // The confirm to 9 cannot be sent: that docking fails too.
        b.on_send_failed(out.sent[0], "CAN transmit queue full", t0 + 2 * MS);
        let out = drain(&mut b);
        assert_eq!(
            out.one("dock_failed")["reason"],
            "confirm not sent: CAN transmit queue full"
        );
        // Idle again: a new report is confirmed at once.
        b.on_packet(
            Packet::report(id(1), Message::DockDetected { port: port(0) }),
            t0 + S,
        );
        assert_eq!(drain(&mut b).sent.len(), 1);
    }

    #[test]
    fn timeout_with_other_elements_docked_withdraws_only_that_port() {
        let (mut b, t0) = with_nodes(&[0x111]);
        b.on_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0,
        );
        b.on_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0,
        );
        b.on_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(4) }),
            t0,
        );
        drain(&mut b);
        b.tick(t0 + BridgeConfig::default().dock_timeout);
        let out = drain(&mut b);
        assert!(out.sent.iter().any(|p| p.dest == id(0x111)
            && matches!(
                p.msg,
                Message::DockRefuse { reason: DockRefuseReason::NotAllowed, port: p4, .. } if p4 == port(4)
            )));
        assert!(!out
            .sent
            .iter()
            .any(|p| matches!(p.msg, Message::PowerSet { .. })));
        assert_eq!(out.one("dock_failed")["port"], 4);
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
        b.on_packet(
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
        b.on_packet(Packet::report(id(2), boot), t0 + S);
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
        b.on_packet(
            Packet::report(id(2), ack(Kind::PowerSet, seq, AckResult::Unsupported)),
            t0 + MS,
        );
        b.on_packet(
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

    /// Deterministic chaos: random reports, acks of what was sent, commands, bus events and time.
    /// Nothing panics, every frame sent is valid, every event reads back as an [`Event`], and every
    /// command that was accepted ends in exactly one `command_result`.
    #[test]
    fn random_traffic_keeps_every_invariant() {
        let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
        let mut rnd = move |n: u64| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x % n
        };
        let t0 = Instant::now();
        let mut now = t0;
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        let nodes = [1u16, 2, 3, 0x111, 0x112];
        let targets = ["1", "2", "3", "111", "112", "all", "5a"];
        let mut sent: Vec<Packet> = Vec::new();
        let (mut accepted, mut results, mut events) = (0usize, 0usize, 0usize);
        let mut seen = BTreeMap::new();
        for _ in 0..20_000 {
            match rnd(10) {
                0..=3 => {
                    // A valid report from a random node: random bytes, kept when they decode.
                    let kinds = [
                        Kind::Fault,
                        Kind::DockDetected,
                        Kind::DockRemoved,
                        Kind::Handshake,
                        Kind::BootUp,
                        Kind::HealthReply,
                        Kind::AssignReply,
                    ];
                    let kind = kinds[rnd(kinds.len() as u64) as usize];
                    let src = id(nodes[rnd(nodes.len() as u64) as usize]);
                    let mut data = [0u8; 8];
                    for d in &mut data {
                        let range = if rnd(2) == 0 { 8 } else { 256 };
                        *d = rnd(range) as u8;
                    }
                    let len = Message::len_of(kind) as usize;
                    if let Ok(msg) = Message::decode(kind, &data[..len]) {
                        b.on_packet(Packet::report(src, msg), now);
                    }
                }
                4..=5 if !sent.is_empty() => {
                    // Answer something that was sent (possibly twice, possibly late).
                    let p = sent[rnd(sent.len() as u64) as usize];
                    let from = if p.dest == NodeId::BROADCAST {
                        id(nodes[rnd(nodes.len() as u64) as usize])
                    } else {
                        p.dest
                    };
                    let result = AckResult::from_raw(rnd(7) as u8);
                    let msg = match p.msg {
                        Message::AssignCommit {
                            uid_tail,
                            new_id,
                            seq,
                        } => Message::AssignReply {
                            seq,
                            result,
                            new_id,
                            uid_tail,
                        },
                        m => match m.ack_seq() {
                            Some(seq) => ack(m.kind(), seq, result),
                            None => continue,
                        },
                    };
                    let src = match msg {
                        Message::AssignReply { new_id, .. } => new_id,
                        _ => from,
                    };
                    b.on_packet(Packet::report(src, msg), now);
                }
                6 => {
                    let node = targets[rnd(targets.len() as u64) as usize];
                    let cmd = match rnd(6) {
                        0 => json!({"cmd": "led", "node": node, "color": [rnd(300), 0, 1]}),
                        1 => json!({"cmd": "buzzer", "node": node, "mode": "pattern",
                                    "on_ms": rnd(3000), "off_ms": 100}),
                        2 => json!({"cmd": "power", "node": node, "on": rnd(2) == 0}),
                        3 => json!({"cmd": "identify", "node": node, "seconds": rnd(300)}),
                        4 => json!({"cmd": "assign", "uid": "00112233445566778899aabb",
                                    "new_id": targets[rnd(5) as usize], "force": rnd(2) == 0}),
                        _ => json!({"cmd": "list"}),
                    };
                    b.on_command(cmd.to_string().as_bytes(), now);
                    if cmd["cmd"] != "list" {
                        accepted += 1; // corrected below when rejected
                    }
                }
                7 => {
                    let ev = match rnd(5) {
                        0 => BusEvent::BusOff,
                        1 => BusEvent::Recovered,
                        2 => BusEvent::RxDropped(rnd(5) as u32),
                        3 => BusEvent::ErrorFrame {
                            class: rnd(0x400) as u32,
                            data: [rnd(256) as u8; 8],
                        },
                        _ => BusEvent::InterfaceDown,
                    };
                    b.on_bus_event(ev, now);
                }
                8 if !sent.is_empty() && rnd(4) == 0 => {
                    let p = sent[rnd(sent.len() as u64) as usize];
                    b.on_send_failed(p, "test", now);
                }
                _ => {
                    now += Duration::from_millis(rnd(400));
                    b.tick(now);
                }
            }
            let out = drain(&mut b);
            for raw in &out.raw_events {
                let ev: Event = serde_json::from_str(raw).unwrap_or_else(|e| panic!("{raw}: {e}"));
                events += 1;
                *seen.entry(ev.name()).or_insert(0usize) += 1;
                match ev {
                    Event::CommandResult(_) => results += 1,
                    Event::CommandRejected(_) => accepted -= 1,
                    _ => {}
                }
            }
            sent.extend(
                out.sent
                    .iter()
                    .filter(|p| p.msg.kind() != Kind::HealthCheck),
            );
            if sent.len() > 64 {
                sent.drain(..32);
            }
        }
        // Everything still pending times out.
        now += Duration::from_secs(60);
        b.tick(now);
        let out = drain(&mut b);
        results += out.named("command_result").len();
        assert!(b.pending.is_empty());
        for name in [
            "new_connection",
            "connection_removed",
            "dock_failed",
            "node_online",
            "node_lost",
            "node_rebooted",
            "command_result",
            "command_rejected",
            "fault",
            "bus_error",
            "node_list",
        ] {
            assert!(seen.contains_key(name), "no {name} in {seen:?}");
        }
        assert!(
            accepted > 100 && events > 1000,
            "the test exercised little: {accepted} {events}"
        );
        assert_eq!(results, accepted, "one command_result per accepted command");
    }

    #[test]
    fn packets_not_for_the_gateway_are_ignored() {
        let (mut b, t0) = with_nodes(&[]);
        b.on_packet(
            Packet::command(id(2), Message::PowerSet { seq: 0, on: true }),
            t0,
        );
        let out = drain(&mut b);
        assert!(out.events.is_empty() && out.states.is_empty() && out.sent.is_empty());
        assert!(b.registry().get(id(2)).is_none());
    }
}
