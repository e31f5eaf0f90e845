//! The gateway's logic, sans-IO: JSON commands and CAN packets in, frames to send and publications
//! (events, retained node states) out. No sockets, no clocks of its own: the adapters feed it one
//! `handle_*` call per input, call [`Bridge::handle_timeout`] at [`Bridge::poll_timeout`], and carry
//! out what [`Bridge::poll_transmit`] and [`Bridge::poll_publication`] return — so every behaviour
//! (command validation, acknowledgement tracking, health and lost-node detection, the one-at-a-time
//! docking sequence, bus diagnostics) is tested without a bus or a broker.
//!
//! This file only routes each input to the concern that owns it. A concept with a machine of its
//! own keeps the bridge's glue beside it, in its folder: [`crate::command`] (`pending`: pending
//! commands, sequence numbers, acks and timeouts), [`crate::docking`] (`glue`: the docking
//! sequence's frames and events), [`crate::ha`] (`glue`: discovery and commands from Home
//! Assistant), [`crate::fwupdate`] (`glue`: `fw_update` and uploads). The bridge's own concerns are
//! submodules here: `health` (health checks, presence, lost detection), `diagnostics` (error
//! frames, drops, undecodable frames, faults, rate limits), `forget` (the `forget` command and
//! renumbered boards), `readback` (asking nodes for their state and applying their answers),
//! `inherited` (state documents an earlier run left retained for nodes this run does not hear),
//! `output` (the queues the adapters drain, each frame tagged with the concern that queued it,
//! and what gives when they cannot keep up), `timer` (every timer in one table).

pub(crate) mod diagnostics;
mod forget;
mod health;
mod inherited;
pub(crate) mod output;
pub(crate) mod readback;
#[cfg(test)]
pub(crate) mod test_support;
mod timer;
#[cfg(test)]
mod traffic;

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use ihex_proto::{
    AckResult, BootRole, DecodeError, FaultCode, FwPhase, Kind, Message, NodeId, Packet, Port,
    StateParts, StateReport, Uid,
};

pub use crate::command::pending::CommandCounters;
pub use crate::fwupdate::FwLoad;
pub use diagnostics::{BusEvent, BusHealth, ERROR_EVENT_WINDOW};
pub use output::{
    FrameOwner, PayloadWriter, Publication, PublicationCounters, Transmit, ANSWER_BACKLOG,
    COMMAND_SHARE, TRANSMIT_WINDOW,
};
pub use readback::{INCOMPLETE_LIMIT, MAX_QUERIES, READ_BACK_VERSION, SILENT_LIMIT};

use crate::command::json::Arena;
use crate::command::pending::{Accepted, Pending};
use crate::command::{self, Command, CommandError, FwNodes, Request};
use crate::docking::glue::{self as dock, DockParts};
use crate::docking::Docking;
use crate::event::{
    CommandRejected, CommandResult, Connection, Event, HexId, NodeList, NodeState, Outcome, Target,
};
use crate::fwupdate::FwUpdates;
use crate::ha::Ha;
use crate::origin::Origin;
use crate::registry::{millis, Registry, Seen};
use diagnostics::Diagnostics;
use health::Health;
use inherited::Inherited;
use output::{FrameFate, Next, Outputs};
use readback::{ReadBack, Reply};
use timer::Timer;

/// The part of the [`TRANSMIT_WINDOW`] a firmware update's frames may fill: a command that comes
/// while they are out is handed on at once, never behind a full window of update frames.
pub const FW_WINDOW: usize = TRANSMIT_WINDOW / 2;
/// The `reason` `fw_report` gives the elements an `fw_cancel` stopped (outcome `failed`).
pub const FW_CANCELLED: &str = "cancelled by fw_cancel";

/// Tunables of the bridge (the CLI/TOML configuration fills these in).
#[derive(Clone, Debug)]
pub struct BridgeConfig {
    /// Period of the broadcast health check (seed: 1 s).
    pub health_period: Duration,
    /// Consecutive missed health replies after which a node is `node_lost` (default 3).
    pub lost_after_misses: u32,
    /// How long to wait for the mobile element's handshake after confirming a docking.
    pub dock_timeout: Duration,
    /// How long a command may wait for the bus, and then for the node's ack, before its
    /// `command_result` says `failed` (never sent) or `timeout` (sent, not acknowledged).
    pub command_timeout: Duration,
    /// Largest accepted command payload in bytes; larger ones are `command_rejected`.
    pub max_command_bytes: usize,
    /// Frames the transmit queue holds before further frames fail (`CAN transmit queue full`).
    pub tx_queue: usize,
    /// Events (other than answers) held for the adapter before the oldest is dropped and counted.
    pub event_queue: usize,
    /// Firmware updates (`fw_update`): bus share and timeouts.
    pub fw: crate::fwupdate::FwConfig,
    /// Guided procedures running at once at most (`procedure` beyond them is refused).
    pub max_procedures: usize,
    /// `--require-identity`: commands (other than `list`) without a vouched identity are
    /// `command_rejected`; the refusal names this root of the per-user command topics. `None`:
    /// they are taken.
    pub require_identity: Option<String>,
}

/// Default period of the broadcast health check (the seed's 1 s).
pub const DEFAULT_HEALTH_PERIOD: Duration = Duration::from_secs(1);
/// Default number of missed health replies before `node_lost`.
pub const DEFAULT_LOST_AFTER: u32 = 3;
/// Default wait for a mobile element's handshake.
pub const DEFAULT_DOCK_TIMEOUT: Duration = Duration::from_secs(5);
/// Default wait for a node's ack.
pub const DEFAULT_COMMAND_TIMEOUT: Duration = Duration::from_millis(500);
/// Default largest command payload, bytes.
pub const DEFAULT_MAX_COMMAND_BYTES: usize = 4096;
/// Default bound of the transmit queue, frames.
pub const DEFAULT_TX_QUEUE: usize = 256;
/// Default bound of the event queue, events.
pub const DEFAULT_EVENT_QUEUE: usize = 1024;

/// How long a frame handed to the adapter may stay unconfirmed (no echo, no failure) before the
/// bridge stops waiting for it: its command then ends `timeout` with a reason saying the frame may
/// still reach the bus, and its place in the [`TRANSMIT_WINDOW`] is given to the next frame.
pub const TRANSMIT_CONFIRM_TIMEOUT: Duration = Duration::from_secs(1);

/// Shortest time between two `publications_dropped` events.
pub const DROP_REPORT_PERIOD: Duration = Duration::from_secs(10);

impl Default for BridgeConfig {
    fn default() -> Self {
        BridgeConfig {
            health_period: DEFAULT_HEALTH_PERIOD,
            lost_after_misses: DEFAULT_LOST_AFTER,
            dock_timeout: DEFAULT_DOCK_TIMEOUT,
            command_timeout: DEFAULT_COMMAND_TIMEOUT,
            max_command_bytes: DEFAULT_MAX_COMMAND_BYTES,
            tx_queue: DEFAULT_TX_QUEUE,
            event_queue: DEFAULT_EVENT_QUEUE,
            fw: crate::fwupdate::FwConfig::default(),
            max_procedures: crate::procedure::DEFAULT_MAX_PROCEDURES,
            require_identity: None,
        }
    }
}

/// Shortest accepted health period: a zero period would make the gateway do nothing but health checks.
pub const MIN_HEALTH_PERIOD: Duration = Duration::from_millis(10);

/// How a command reached the gateway.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Delivery {
    /// When the adapter received it (its `ttl_ms` counts from here).
    pub received: Instant,
    /// It was a retained message (the broker replays those on every subscription): never executed.
    pub retained: bool,
    /// The interface it came through and who sent it.
    pub origin: Origin,
}

impl Delivery {
    /// A live message received at `now` on the shared MQTT command topic, without an identity.
    pub fn live(now: Instant) -> Self {
        Delivery {
            received: now,
            retained: false,
            origin: Origin::default(),
        }
    }

    /// The same delivery, from `origin`.
    pub fn with_origin(self, origin: Origin) -> Self {
        Delivery { origin, ..self }
    }
}

/// The gateway state machine.
#[derive(Debug)]
pub struct Bridge {
    pub(crate) config: BridgeConfig,
    pub(crate) out: Outputs,
    pub(crate) registry: Registry,
    docking: Docking,
    pending: Pending,
    health: Health,
    diagnostics: Diagnostics,
    /// Home Assistant discovery, when enabled ([`Bridge::with_home_assistant`]).
    pub(crate) ha: Option<Ha>,
    readback: ReadBack,
    inherited: Inherited,
    /// Until when a node heard but not yet read back has its state document (and Home Assistant
    /// config) held back: the lost period from start. A restarted gateway publishes nothing
    /// half-known; the documents an earlier run left retained stay meanwhile.
    hold_until: Instant,
    /// Nodes whose document is held back.
    held: BTreeSet<NodeId>,
    /// The time of the last input (state documents taken later are built as of it).
    now: Instant,
    /// When the next `publications_dropped` may go out.
    next_drop_report: Instant,
    fw: FwUpdates,
    /// Where each JSON command's tree is parsed (reused from one command to the next).
    arena: Arena,
    /// The leases held now.
    pub(crate) lease_table: crate::lease::LeaseTable,
    /// The time of day, as the adapter told it (for leases' ends).
    pub(crate) clock: crate::lease::WallClock,
    /// `leases_reset` was published (at this run's first MQTT connection).
    pub(crate) leases_announced: bool,
    /// The guided procedures running now.
    pub(crate) procedures: crate::procedure::Procedures,
    /// Where the command being handled came from (the default between commands): its answers
    /// carry it.
    pub(crate) origin: Origin,
}

impl Bridge {
    /// A bridge started at `now`; the first health check is due at once.
    pub fn new(mut config: BridgeConfig, now: Instant) -> Self {
        config.health_period = config.health_period.max(MIN_HEALTH_PERIOD);
        Bridge {
            out: Outputs::new(config.tx_queue, config.event_queue),
            registry: Registry::new(),
            docking: Docking::new(config.dock_timeout, Docking::DEFAULT_QUEUE),
            pending: Pending::new(config.command_timeout),
            health: Health::new(config.health_period, config.lost_after_misses, now),
            diagnostics: Diagnostics::new(),
            ha: None,
            readback: ReadBack::new(config.command_timeout),
            inherited: Inherited::new(config.health_period, config.lost_after_misses, now),
            hold_until: now + config.health_period * config.lost_after_misses.saturating_add(1),
            held: BTreeSet::new(),
            fw: FwUpdates::new(config.fw.clone()),
            procedures: crate::procedure::Procedures::new(config.max_procedures),
            config,
            now,
            next_drop_report: now,
            arena: Arena::default(),
            lease_table: crate::lease::LeaseTable::new(),
            clock: crate::lease::WallClock::default(),
            leases_announced: false,
            origin: Origin::default(),
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> &BridgeConfig {
        &self.config
    }

    /// The node registry (read-only).
    pub fn registry(&self) -> &Registry {
        &self.registry
    }

    /// The state document of every known node as of `now`, by ascending ID (what `list` answers and
    /// what the retained topics hold, with ages computed at `now`).
    pub fn node_states(&self, now: Instant) -> Vec<NodeState> {
        self.registry
            .iter()
            .map(|e| e.state(self.docking.links_of(e.id), now))
            .collect()
    }

    /// The state document of one node as of `now`, if it is known.
    pub fn node_state(&self, id: NodeId, now: Instant) -> Option<NodeState> {
        let e = self.registry.get(id)?;
        Some(e.state(self.docking.links_of(id), now))
    }

    /// The docking connections recorded now.
    pub fn connections(&self) -> Vec<Connection> {
        self.docking.connections()
    }

    /// The docking sequence (read-only): the docking in progress and the reports waiting.
    pub fn docking(&self) -> &Docking {
        &self.docking
    }

    /// What the bus has done since start.
    pub fn bus_health(&self) -> BusHealth {
        BusHealth {
            bus_down: self.health.bus_down(),
            ..self.diagnostics.health()
        }
    }

    /// Commands in flight now, and how the finished ones ended.
    pub fn command_counters(&self) -> CommandCounters {
        self.pending.counters()
    }

    /// Publications taken and dropped since start, and what waits now.
    pub fn publication_counters(&self) -> PublicationCounters {
        self.out.publish.counters()
    }

    /// True when publications wait for [`Bridge::poll_publication`].
    pub fn publications_waiting(&self) -> bool {
        self.out.publish.waiting()
    }

    /// Events dropped since start because the event queue was full.
    pub fn publications_dropped(&self) -> u64 {
        self.out.publish.total_dropped()
    }

    /// True while the bridge is about to ask `id` for its state, or waits for its answer (its
    /// state document may still change without anything happening on the node).
    pub fn reading_back(&self, id: NodeId) -> bool {
        self.readback.pending(id)
    }

    /// Complete state replies applied since start.
    pub fn read_backs(&self) -> u64 {
        self.readback.replies()
    }

    /// Frames waiting in the transmit queue, and frames handed out and not yet confirmed.
    pub fn transmit_backlog(&self) -> (usize, usize) {
        (self.out.transmit.queued(), self.out.transmit.in_flight())
    }

    /// False while [`ANSWER_BACKLOG`] answers wait for the adapter, or while the transmit queue is
    /// filled to its command share ([`COMMAND_SHARE`]): the adapter should then stop taking
    /// commands (and leave them with the broker) until it has taken publications or the bus has
    /// taken frames, so that answers are never dropped, their queue stays bounded, and commands
    /// that come faster than the bus carries them wait instead of failing `transmit queue full`.
    /// Checked before each command: one call may queue up to two frames.
    pub fn wants_commands(&self) -> bool {
        self.out.publish.answers_waiting() < ANSWER_BACKLOG && self.out.transmit.takes_commands()
    }

    /// Queues an acknowledged frame of the bridge's own (`owner`'s) to `dest` as of the input
    /// being handled; false, and nothing sent, when every sequence number is in use.
    pub(crate) fn send_own(
        &mut self,
        owner: FrameOwner,
        dest: NodeId,
        kind: Kind,
        msg: impl FnOnce(ihex_proto::Seq) -> Message,
    ) -> bool {
        let now = self.now;
        self.pending
            .send_internal(owner, dest, kind, msg, now, &mut self.out)
            .is_some()
    }

    /// The origin the answers to the command being handled carry.
    pub(crate) fn origin_for_answer(&self) -> Option<Origin> {
        self.origin.for_answer()
    }

    /// Records the time of the input being handled (state documents taken later are built as of it).
    pub(crate) fn set_now(&mut self, now: Instant) {
        self.now = now;
    }

    /// A message arrived on `CommandsTopic` just now (raw bytes: the bridge parses and validates
    /// them and answers bad input with a `command_rejected` event). See
    /// [`Bridge::handle_delivered_command`].
    pub fn handle_command(&mut self, payload: &[u8], now: Instant) {
        let _ = self.handle_delivered_command(payload, Delivery::live(now), now);
    }

    /// A message arrived on `CommandsTopic` as `delivery` says. Every message gets exactly one
    /// answer: `command_rejected` (invalid, retained, unknown node, …), `node_list`, or later one
    /// `command_result`. Returns the `request_id` that answer carries (`None` when the message had
    /// none that could be read): what a caller following the command to its answer matches.
    pub fn handle_delivered_command(
        &mut self,
        payload: &[u8],
        delivery: Delivery,
        now: Instant,
    ) -> Option<String> {
        self.set_now(now);
        if delivery.retained {
            let request_id = command::request_id(payload);
            self.origin = delivery.origin;
            self.reject(request_id.clone(), CommandError::Retained);
            self.origin = Origin::default();
            return request_id;
        }
        match command::parse_in(payload, self.config.max_command_bytes, &mut self.arena) {
            Ok(req) => {
                let request_id = req.request_id.clone();
                self.execute(req, delivery, now);
                request_id
            }
            Err(rej) => {
                let request_id = rej.request_id.clone();
                self.origin = delivery.origin;
                self.reject(rej.request_id, rej.error);
                self.origin = Origin::default();
                request_id
            }
        }
    }

    /// Carries out a valid command (from the JSON API or from Home Assistant) delivered as
    /// `delivery` says; its answers carry its origin.
    pub(crate) fn execute(&mut self, mut req: Request, mut delivery: Delivery, now: Instant) {
        if let Some(user) = req.user.take() {
            delivery.origin.claimed = Some(user);
        }
        self.origin = std::mem::take(&mut delivery.origin);
        if let Some(root) = &self.config.require_identity {
            if self.origin.user.is_none() && !matches!(req.command, Command::List) {
                let topic = root.clone();
                self.reject(req.request_id, CommandError::NoIdentity { topic });
                return self.origin = Origin::default();
            }
        }
        self.execute_from(req, delivery, now);
        self.origin = Origin::default();
    }

    /// [`Bridge::execute`] once the origin is known.
    fn execute_from(&mut self, req: Request, delivery: Delivery, now: Instant) {
        let request_id = req.request_id;
        let expires = req.ttl.map(|ttl| delivery.received + ttl);
        if let (Some(expires), Some(ttl)) = (expires, req.ttl) {
            if expires <= now && !matches!(req.command, Command::List) {
                return self.expired_on_arrival(request_id, &req.command, ttl, delivery, now);
            }
        }
        if let Some(error) = self.lease_refusal(&req.command, req.lease.as_deref(), now) {
            return self.reject(request_id, error);
        }
        let acc = Accepted {
            now,
            expires,
            origin: self.origin.for_answer(),
        };
        let sent = match req.command {
            Command::List => {
                let nodes = self.node_states(now);
                self.out
                    .emit(Event::NodeList(NodeList { request_id, nodes }));
                Ok(())
            }
            Command::Node { target, action } => {
                if let Target::Node(id) = target {
                    if self.registry.get(id).is_none() {
                        let known = self.registry.known_list();
                        let error = CommandError::UnknownNode {
                            id: HexId(id),
                            known,
                        };
                        return self.reject(request_id, error);
                    }
                }
                let registry = &self.registry;
                self.pending.send(
                    request_id,
                    target,
                    action,
                    || registry.online_ids(),
                    acc,
                    &mut self.out,
                )
            }
            Command::FwUpdate {
                image,
                nodes,
                force,
            } => {
                let token = req.lease.as_deref();
                return self.request_fw_update(request_id, image, nodes, force, token);
            }
            Command::FwCancel => {
                self.fw_cancel(request_id, req.lease.as_deref(), now);
                Ok(())
            }
            cmd @ (Command::Lease { .. }
            | Command::Renew { .. }
            | Command::Release
            | Command::BreakLease { .. }) => {
                self.lease_command(request_id, cmd, req.lease, now);
                Ok(())
            }
            Command::Assign { uid, new_id, force } => {
                if !force && self.registry.get(new_id).is_some_and(|e| e.online) {
                    return self.reject(request_id, CommandError::IdInUse(HexId(new_id)));
                }
                self.pending
                    .send_assign(request_id, uid, new_id, acc, &mut self.out)
            }
            Command::Forget { id } => {
                self.forget_command(request_id, id, now);
                Ok(())
            }
            Command::Procedure(spec) => {
                self.procedure_command(request_id, *spec, now);
                Ok(())
            }
            Command::ProcedureCancel { id } => {
                self.procedure_cancel(request_id, id, now);
                Ok(())
            }
        };
        if let Err((request_id, error)) = sent {
            self.reject(request_id, error);
        }
        self.finish_input(now);
    }

    /// A command whose ttl ended before the bridge got it: `expired`, never queued.
    fn expired_on_arrival(
        &mut self,
        request_id: Option<String>,
        cmd: &Command,
        ttl: Duration,
        delivery: Delivery,
        now: Instant,
    ) {
        let node = match cmd {
            Command::Node { target, .. } => *target,
            Command::Assign { new_id, .. } => Target::Node(*new_id),
            Command::Forget { id } => Target::Node(*id),
            Command::List
            | Command::FwUpdate { .. }
            | Command::FwCancel
            | Command::Lease { .. }
            | Command::Renew { .. }
            | Command::Release
            | Command::BreakLease { .. }
            | Command::Procedure(_)
            | Command::ProcedureCancel { .. } => Target::All,
        };
        let waited = millis(now.saturating_duration_since(delivery.received));
        self.pending.count_expired();
        self.out.emit(Event::CommandResult(CommandResult {
            request_id,
            cmd: cmd.name().into(),
            node,
            result: Outcome::Expired,
            reason: Some(format!(
                "not sent: its ttl ({} ms after the gateway received it) ended before it could be \
                 queued ({waited} ms)",
                ttl.as_millis()
            )),
            acked: None,
            refused: None,
            missing: None,
            origin: self.origin.for_answer(),
        }));
    }

    /// A valid iHEX packet arrived on the bus (including the echo of one of our own frames, which
    /// confirms it was sent).
    pub fn handle_packet(&mut self, packet: Packet, now: Instant) {
        self.set_now(now);
        if packet.src == NodeId::GATEWAY {
            return self.handle_transmitted(packet, now);
        }
        self.diagnostics
            .count_frame(Message::len_of(packet.msg.kind()), false);
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
                self.on_assign_reply(seq, result, new_id, uid_tail, now);
            }
            self.finish_input(now);
            return;
        }
        let seen = self
            .health
            .on_heard(&mut self.registry, src, &packet.msg, now, &mut self.out);
        if matches!(seen, Seen::New | Seen::Back) {
            self.readback.want(src);
        }
        match packet.msg {
            Message::BootUp { version, reset, .. } => {
                self.readback.on_boot(src, version);
                self.fw.on_boot_up(src, reset, now, &mut self.out);
            }
            // Handled by `on_heard`.
            Message::HealthReply(_) => {}
            Message::FwStatus(st) => {
                // Any status tells whether the image it runs is on trial: a confirmation clears
                // the flag in its state document at once, not at the next read-back.
                let trial = match st.phase {
                    FwPhase::Trial => Some(true),
                    FwPhase::Idle | FwPhase::Reverted => Some(false),
                    _ => None,
                };
                if let (Some(trial), Some(fw)) = (
                    trial,
                    self.registry.get_mut(src).and_then(|e| e.firmware.as_mut()),
                ) {
                    fw.1 = trial;
                }
                self.fw.on_status(src, st, now, &mut self.out)
            }
            Message::Ack {
                kind, seq, result, ..
            } => self.on_ack(src, kind, seq, result, now),
            Message::Fault {
                code: FaultCode::BadFrame,
                arg,
                detail,
            } if is_read_back_kind(arg) && detail & 0xff == BAD_FRAME_UNKNOWN_KIND => {
                // Our question to a node of protocol 1.0: the answer is that it cannot be asked.
                self.readback.on_unknown_kind(src);
            }
            Message::Fault { code, arg, detail } => {
                self.diagnostics
                    .on_fault(src, code, arg, detail, now, &mut self.out)
            }
            Message::StateReport(report) => {
                if let Some(reply) = self.readback.on_report(src, report) {
                    self.apply_reply(reply, now);
                }
            }
            Message::DockDetected { port } => {
                if let Some(e) = self.registry.get_mut(src) {
                    e.loops |= port.mask();
                }
                let relay_on = self.registry.get(src).is_some_and(relay_on);
                let steps = self.docking.on_detected(src, port, relay_on, now);
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
                let closed = self.closed_static_loops();
                let steps = self.docking.on_handshake(src, port, &closed, now);
                self.apply(steps, now);
            }
            Message::AssignReply {
                seq,
                result,
                new_id,
                uid_tail,
            } => self.on_assign_reply(seq, result, new_id, uid_tail, now),
            // Command kinds never come addressed to the gateway (the decoder checks addresses).
            _ => tracing::debug!(?packet, "ignoring unexpected packet"),
        }
        self.finish_input(now);
    }

    /// A frame arrived that passed the filters but is not a valid iHEX packet.
    pub fn handle_undecodable(&mut self, raw_id: u32, data: &[u8], err: DecodeError, now: Instant) {
        let len = u8::try_from(data.len()).unwrap_or(u8::MAX);
        self.diagnostics.count_frame(len, false);
        self.set_now(now);
        self.diagnostics
            .on_undecodable(raw_id, data, err, now, &mut self.out);
    }

    /// A bus condition (error frame, bus-off, interface down/up, drops).
    pub fn handle_bus_event(&mut self, event: BusEvent, now: Instant) {
        self.set_now(now);
        match event {
            BusEvent::BusOff => {
                self.health.on_bus_down();
                self.readback.on_bus_down();
                self.fw.on_bus(true, now, &mut self.out);
            }
            BusEvent::InterfaceDown => {
                self.health.on_bus_down();
                self.readback.on_bus_down();
                self.fw.on_bus(true, now, &mut self.out);
                // The kernel drops what a downed interface had queued — or it went out just before:
                // nobody can tell any more.
                for (p, owner) in self.out.transmit.clear_in_flight() {
                    let why = "the CAN interface went down before confirming it was sent";
                    self.on_frame_fate(p, owner, FrameFate::Unconfirmed(why), now);
                }
            }
            BusEvent::Recovered => {
                if self.health.bus_down() {
                    // Whatever changed while the bus was away, nobody heard it: ask everyone.
                    for e in self.registry.iter() {
                        self.readback.want(e.id);
                    }
                }
                self.health.on_recovered(now);
                self.fw.on_bus(false, now, &mut self.out);
            }
            _ => {}
        }
        self.diagnostics.on_bus_event(event, now, &mut self.out);
        self.finish_input(now);
    }

    /// The adapter confirms that a frame from [`Bridge::poll_transmit`] went on the bus: its echo
    /// arrived (SocketCAN with `CAN_RAW_RECV_OWN_MSGS`), or, on a link that cannot tell, it was
    /// written. [`Bridge::handle_packet`] calls this for frames from the gateway's own address.
    pub fn handle_transmitted(&mut self, packet: Packet, now: Instant) {
        self.set_now(now);
        let owner = self.release(&packet);
        self.on_frame_fate(packet, owner, FrameFate::Transmitted, now);
        self.finish_input(now);
    }

    /// The adapter did not write a frame because its [`Transmit::not_after`] had passed: its
    /// command ends `expired` or `failed`, and the frame is never sent.
    pub fn handle_withdrawn(&mut self, packet: Packet, now: Instant) {
        self.set_now(now);
        let owner = self.release(&packet);
        self.on_frame_fate(packet, owner, FrameFate::Withdrawn, now);
        self.finish_input(now);
    }

    /// A frame from [`Bridge::poll_transmit`] could not be transmitted.
    pub fn handle_send_failed(&mut self, packet: Packet, reason: &str, now: Instant) {
        self.set_now(now);
        let owner = self.release(&packet);
        self.on_frame_fate(packet, owner, FrameFate::Failed(reason), now);
        self.finish_input(now);
    }

    /// Frees the place of `packet` in the transmit window, and tells who queued it.
    fn release(&mut self, packet: &Packet) -> FrameOwner {
        if let Some(owner) = self.out.transmit.release(packet) {
            return owner;
        }
        tracing::debug!(
            ?packet,
            "fate of a frame not in the transmit window (late, or another gateway's)"
        );
        // Its tag left the window with it: the concern that sends frames of its kind gets it. A
        // command's frame is found by the frame itself, so a relay off the docking sequence sent
        // goes to the commands just as well.
        match packet.msg.kind() {
            Kind::StateQuery => FrameOwner::ReadBack,
            Kind::DockConfirm | Kind::DockRefuse | Kind::DockLink => FrameOwner::Docking,
            Kind::HealthCheck => FrameOwner::HealthCheck,
            Kind::FwBegin | Kind::FwData | Kind::FwEnd | Kind::FwQuery => FrameOwner::FwUpdate,
            _ => FrameOwner::Command,
        }
    }

    /// Tells the concern that queued `packet` what became of it: the one place where a frame's
    /// fate is routed. A failure no concern answered for becomes a `bus_error` (`send_failed`).
    fn on_frame_fate(
        &mut self,
        packet: Packet,
        owner: FrameOwner,
        fate: FrameFate<'_>,
        now: Instant,
    ) {
        if let FrameFate::Failed(_) = fate {
            self.diagnostics.count_send_failure();
        }
        let answered = match owner {
            FrameOwner::Command => self.pending.on_fate(&packet, fate, now, &mut self.out),
            FrameOwner::Docking => {
                // The frame's number is freed first; a failed confirm then ends the docking.
                self.pending.on_fate(&packet, fate, now, &mut self.out);
                let steps = dock::on_fate(&mut self.docking, &packet, fate, now);
                let answered = !steps.is_empty();
                self.apply(steps, now);
                answered
            }
            FrameOwner::ReadBack => {
                self.readback.on_fate(packet.dest, fate, now);
                false
            }
            FrameOwner::Procedure => {
                // A light that could not be set is no reason to stop the procedure: the step
                // waits on the docking, not on the LED; the frame's number is freed.
                self.pending.on_fate(&packet, fate, now, &mut self.out);
                false
            }
            FrameOwner::HealthCheck | FrameOwner::FwUpdate => false,
        };
        if let (FrameFate::Failed(reason), false) = (fate, answered) {
            self.diagnostics
                .on_send_failed(&packet, reason, now, &mut self.out);
        }
    }

    /// The MQTT session is (re)established: queue the retained node states again (a restarted broker
    /// may have lost them), and with Home Assistant discovery every config and light state.
    pub fn handle_mqtt_connected(&mut self, now: Instant) {
        self.set_now(now);
        if let Some(ha) = &self.ha {
            self.out.publish.push_kept(Publication::Ha(ha.gateway()));
        }
        let ids: Vec<NodeId> = self.registry.iter().map(|e| e.id).collect();
        for id in ids {
            if self.holds(id, now) {
                self.held.insert(id);
            } else {
                self.out.publish.push_state(id, true);
            }
        }
        self.out.dirty.clear();
        self.leases_on_connected(now);
        // An earlier run's procedures ended with it: its retained document is replaced.
        self.publish_procedures(now);
    }

    /// A retained state document of `id` the broker delivered when the adapter subscribed to the
    /// state topics (an earlier run's, or this run's own). One that says `online` for a node this
    /// run does not hear within the lost period is republished offline (see [`Bridge::poll_timeout`]).
    pub fn handle_retained_state(&mut self, id: NodeId, payload: &[u8], now: Instant) {
        self.set_now(now);
        let known = self.registry.get(id).is_some();
        self.inherited.on_retained(id, payload, known);
        self.republish_inherited(now);
        self.finish_input(now);
    }

    /// Republishes, offline, the inherited documents of nodes not heard in time.
    fn republish_inherited(&mut self, now: Instant) {
        let registry = &self.registry;
        let lost = self
            .inherited
            .take_lost(now, self.health.bus_down(), |id| registry.get(id).is_some());
        for doc in lost {
            tracing::info!(node = %doc.id, "state document of an earlier run says online, node not heard since start: republished offline");
            self.out.publish.push_kept(Publication::State(doc));
        }
    }

    /// The image file of an `fw_update` ([`Bridge::poll_fw_load`]) was read (`Ok`), or could not
    /// be (`Err`: why, for the `command_result`). A good image starts the update.
    pub fn handle_fw_image(&mut self, load: FwLoad, bytes: Result<Vec<u8>, String>, now: Instant) {
        self.set_now(now);
        self.fw.on_image(load, bytes, now, &mut self.out);
        let docked = self.docking.connections();
        self.fw
            .set_docked(docked.iter().map(|c| (c.n_1.id.0, c.n.id.0)));
        self.finish_input(now);
    }

    /// An image uploaded over MQTT under `name` (the last level of its topic; `retained`: the
    /// broker delivered it as retained). It is checked and kept for `fw_update`, and answered
    /// with `fw_upload` (`stored`, or `rejected` with the reason).
    pub fn handle_fw_upload(&mut self, name: &str, bytes: Vec<u8>, retained: bool, now: Instant) {
        self.set_now(now);
        self.fw.on_upload(name, bytes, retained, &mut self.out);
        self.finish_input(now);
    }

    /// Stops a running firmware update (the gateway is shutting down): its nodes are told to drop
    /// the transfer and `fw_report` says `failed` with `reason` for every node not done yet.
    pub fn cancel_fw_update(&mut self, reason: &str, now: Instant) {
        self.set_now(now);
        self.fw.cancel(reason, now, &mut self.out);
        self.finish_input(now);
    }

    /// `fw_cancel`: stops the running update like [`Bridge::cancel_fw_update`], answered with
    /// `command_result` `ok` before its `fw_report` (every element not done yet `failed`, reason
    /// `cancelled by fw_cancel`). Refused when no update runs, while its image is still read, and
    /// when a lease holds one of its elements not done yet and the command lacks its token.
    fn fw_cancel(&mut self, request_id: Option<String>, lease: Option<&str>, now: Instant) {
        let open = match self.fw.open_nodes() {
            Some(open) => open,
            None if self.fw.busy() => return self.reject(request_id, CommandError::FwLoading),
            None => return self.reject(request_id, CommandError::FwNotRunning),
        };
        for id in open {
            if let Err(e) = self.lease_table.check(id, lease, &self.clock, now) {
                return self.reject(request_id, e.into());
            }
        }
        self.out.emit(Event::CommandResult(CommandResult {
            request_id,
            cmd: "fw_cancel".into(),
            node: Target::All,
            result: Outcome::Ok,
            reason: None,
            acked: None,
            refused: None,
            missing: None,
            origin: self.origin.for_answer(),
        }));
        self.fw.cancel(FW_CANCELLED, now, &mut self.out);
    }

    /// True while a firmware update is loading or running.
    pub fn fw_update_running(&self) -> bool {
        self.fw.busy()
    }

    /// An `fw_update` whose image file the adapter must read and hand to
    /// [`Bridge::handle_fw_image`]; `None` when there is none.
    #[must_use]
    pub fn poll_fw_load(&mut self) -> Option<FwLoad> {
        self.fw.poll_load()
    }

    /// Runs every timer of the timer table, in its order: firmware update rounds, frames never
    /// confirmed, command withdrawals and ack timeouts, read-back answers, inherited documents,
    /// the docking handshake, the health broadcast and lost nodes, the report of dropped
    /// publications. Each acts on what is due by `now`.
    pub fn handle_timeout(&mut self, now: Instant) {
        self.set_now(now);
        for timer in Timer::VALUES {
            self.expire(timer, now);
        }
        self.finish_input(now);
    }

    /// When [`Bridge::handle_timeout`] must run next: the earliest deadline of the timer table.
    #[must_use]
    pub fn poll_timeout(&self) -> Instant {
        // The health check always has a deadline: the fallback is never taken.
        self.timers()
            .next_timeout()
            .unwrap_or_else(|| self.health.next_deadline())
    }

    /// The next frame to transmit at `now`, `None` when there is none or when
    /// [`TRANSMIT_WINDOW`] frames are already handed out and not yet confirmed (each must be
    /// answered by [`Bridge::handle_transmitted`], [`Bridge::handle_send_failed`] or
    /// [`Bridge::handle_withdrawn`]). A firmware update's frames come last, only when nothing
    /// else waits, within the update's bus share, and only while fewer than [`FW_WINDOW`] frames
    /// are out: the rest of the window is always free for a command that comes meanwhile.
    #[must_use]
    pub fn poll_transmit(&mut self, now: Instant) -> Option<Transmit> {
        self.set_now(now);
        loop {
            if self.out.transmit.queued() == 0 && self.out.transmit.in_flight() < FW_WINDOW {
                if let Some(p) = self.fw.poll_transmit() {
                    self.out.transmit.push(p, None, FrameOwner::FwUpdate);
                }
            }
            match self.out.transmit.pop(now)? {
                Ok(t) => {
                    self.pending.on_handed(&t.packet, now);
                    self.diagnostics
                        .count_frame(Message::len_of(t.packet.msg.kind()), true);
                    return Some(t);
                }
                Err(late) => {
                    // Its command's deadline passed: answering it withdraws the frame.
                    self.pending.expire(now, &mut self.out);
                    self.out.transmit.withdraw(&late);
                    self.finish_input(now);
                }
            }
        }
    }

    /// The next event or state document to publish, `None` when there is none. State documents are
    /// built when taken (the latest, as of the last input), at most one per node waits, and one
    /// that has not changed since it was last published is skipped.
    #[must_use]
    pub fn poll_publication(&mut self) -> Option<Publication> {
        loop {
            match self.out.publish.pop()? {
                Next::Event(e) => return Some(Publication::Event(e)),
                Next::Kept(p) => return Some(p),
                Next::State { id, forced } => {
                    let links = self.docking.links_of(id);
                    let changed = self.registry.state_changed(id, &links);
                    if !(changed || forced) {
                        continue;
                    }
                    let Some(entry) = self.registry.get(id) else {
                        continue;
                    };
                    let doc = entry.state(links, self.now);
                    self.out.publish.count_state();
                    // Home Assistant's config and light state follow the document.
                    if let Some(ha) = &mut self.ha {
                        let follow = ha.on_state(&doc, entry, forced);
                        self.out
                            .publish
                            .push_kept_next(follow.into_iter().map(Publication::Ha));
                    }
                    return Some(Publication::State(doc));
                }
            }
        }
    }

    /// `fw_update`: resolves the nodes against the registry and asks the adapter for the image.
    fn request_fw_update(
        &mut self,
        request_id: Option<String>,
        image: String,
        nodes: FwNodes,
        force: bool,
        lease: Option<&str>,
    ) {
        if self.fw.busy() {
            return self.reject(request_id, CommandError::FwBusy);
        }
        let nodes = match nodes {
            FwNodes::All => {
                let ids = self.registry.online_ids();
                if ids.is_empty() {
                    return self.reject(request_id, CommandError::FwNoNodes);
                }
                ids
            }
            FwNodes::List(ids) => {
                if let Some(&id) = ids.iter().find(|&&id| self.registry.get(id).is_none()) {
                    let known = self.registry.known_list();
                    let error = CommandError::UnknownNode {
                        id: HexId(id),
                        known,
                    };
                    return self.reject(request_id, error);
                }
                ids
            }
        };
        let now = self.now;
        let skipped = self.lease_skips(&nodes, lease, now);
        let nodes: Vec<NodeId> = nodes
            .into_iter()
            .filter(|id| !skipped.iter().any(|(s, _)| s == id))
            .collect();
        if nodes.is_empty() {
            let reasons: Vec<&str> = skipped.iter().map(|(_, why)| why.as_str()).collect();
            let error = CommandError::Invalid {
                cmd: "fw_update",
                message: format!("every element is leased: {}", reasons.join("; ")),
            };
            return self.reject(request_id, error);
        }
        self.fw.request(
            FwLoad {
                request_id,
                image,
                nodes,
                force,
                skipped,
            },
            now,
            &mut self.out,
        );
    }

    pub(crate) fn reject(&mut self, request_id: Option<String>, error: CommandError) {
        tracing::info!(%error, "command rejected");
        self.pending.count_rejected();
        self.out.emit(Event::CommandRejected(CommandRejected {
            request_id,
            reason: error.to_string(),
            origin: self.origin.for_answer(),
        }));
    }

    fn on_ack(&mut self, src: NodeId, kind: Kind, seq: u8, result: AckResult, now: Instant) {
        self.pending.on_ack(
            src,
            kind,
            seq,
            result,
            &mut self.registry,
            now,
            &mut self.out,
        );
        if kind == Kind::DockConfirm && result != AckResult::Ok {
            let steps = self
                .docking
                .on_confirm_refused(src, seq, &result.to_string(), now);
            self.apply(steps, now);
        }
    }

    /// Carries out docking steps.
    fn apply(&mut self, steps: Vec<crate::docking::Step>, now: Instant) {
        let parts = DockParts {
            pending: &mut self.pending,
            docking: &mut self.docking,
            diagnostics: &mut self.diagnostics,
            readback: &self.readback,
        };
        dock::apply(steps, parts, now, &mut self.out);
    }

    fn on_assign_reply(
        &mut self,
        seq: u8,
        result: AckResult,
        new_id: NodeId,
        uid_tail: [u8; 4],
        now: Instant,
    ) {
        if let Some(uid) =
            self.pending
                .on_assign_reply(seq, result, new_id, uid_tail, &mut self.out)
        {
            // The board announces its new ID with a BootUp without restarting.
            self.health
                .expect_announcement(new_id, now, self.config.command_timeout);
            self.learn_uid(new_id, uid, now);
        }
    }

    /// The closed signal loops of the online static elements whose relay is on (static element,
    /// its port): where a mobile element whose handshake no docking awaited can have got power.
    fn closed_static_loops(&self) -> Vec<(NodeId, Port)> {
        self.registry
            .iter()
            .filter(|e| e.online && e.role == Some(BootRole::Static) && relay_on(e))
            .flat_map(|e| {
                (0..8u8)
                    .filter(move |p| e.loops & (1 << p) != 0)
                    .filter_map(Port::new)
                    .map(move |p| (e.id, p))
            })
            .collect()
    }

    /// Pairs a docked mobile element recorded nowhere (its handshake was lost) with the one free
    /// closed loop of a powered static element — once the mobile element has answered a health
    /// check (its handshake, sent at boot, came before) and no read-back of a static element is
    /// outstanding (its own record of the docking comes first,
    /// silently, after a gateway restart). Static elements of protocol 1.0 keep no record and are
    /// left out: a docking they had before a restart stays unknown, as documented.
    fn adopt_unrecorded(&mut self, now: Instant) {
        if self.health.bus_down() {
            return;
        }
        let statics_settled = self
            .registry
            .iter()
            .filter(|e| e.role == Some(BootRole::Static))
            .all(|e| !self.readback.pending(e.id));
        if !statics_settled {
            return;
        }
        let mobiles: Vec<(NodeId, Port)> = self
            .registry
            .iter()
            .filter(|e| e.online && e.role == Some(BootRole::Mobile) && e.health.is_some())
            .filter_map(|e| {
                let low = (0..8u8).find(|p| e.loops & (1 << p) != 0)?;
                Some((e.id, Port::new(low)?))
            })
            .collect();
        if mobiles.is_empty() {
            return;
        }
        let closed: Vec<(NodeId, Port)> = self
            .closed_static_loops()
            .into_iter()
            .filter(|(s, _)| self.readback.supports(*s))
            .collect();
        let steps = self.docking.adopt_unrecorded(&mobiles, &closed, now);
        self.apply(steps, now);
    }

    /// A node's complete answer to a state query: what it reports replaces what the bridge
    /// assumed, except what a node acknowledged after the question (that is newer); a static
    /// element's ports reconcile the docking record.
    fn apply_reply(&mut self, reply: Reply, now: Instant) {
        let Reply {
            node,
            parts,
            reports,
            asked,
        } = reply;
        let Some(e) = self.registry.get_mut(node) else {
            return;
        };
        // Each actuator on its own: an LED acknowledged after the question does not make the
        // reported buzzer any older.
        let older = |acked: Option<Instant>| acked.is_none_or(|t| t < asked);
        let acked = e.acked_at;
        let mut docks = Vec::new();
        let mut firmware = None;
        let (mut low, mut high) = (None, None);
        for r in reports {
            match r {
                StateReport::Led(cmd) if older(acked.led) => e.led = Some(cmd),
                StateReport::Buzzer(cmd) if older(acked.buzzer) => e.buzzer = Some(cmd),
                StateReport::Power(p) => {
                    if older(acked.relay) {
                        e.relay = Some(p.relay);
                    }
                    e.loops = p.loops;
                    e.role = Some(p.role);
                    e.ports = Some(p.ports);
                }
                StateReport::Dock { port, state } => docks.push((port, state)),
                StateReport::Firmware { version, trial } => {
                    e.firmware = Some((version, trial));
                    firmware = Some((version, trial));
                }
                StateReport::ImageHash(h) => e.image_hash = Some(h),
                StateReport::UidLow(l) => low = Some(l),
                StateReport::UidHigh(h) => high = Some(h),
                StateReport::Protocol { version } => e.version = Some(version),
                _ => {}
            }
        }
        if let (Some(l), Some(h)) = (low, high) {
            e.uid = Some(Uid::from_low_high(l, h));
        }
        let is_static = e.role == Some(BootRole::Static);
        self.out.mark_changed(node);
        if let Some((version, trial)) = firmware {
            self.fw
                .on_firmware(node, version, trial, now, &mut self.out);
        }
        if parts.contains(StateParts::DOCKING) && is_static {
            let steps = self.docking.reconcile(node, &docks, asked);
            self.apply(steps, now);
        }
    }

    /// True while `id`'s state document is held back: it is online, not read back yet (nor known
    /// not to answer) and the lost period since start has not passed.
    fn holds(&self, id: NodeId, now: Instant) -> bool {
        now < self.hold_until
            && self.registry.get(id).is_some_and(|e| e.online)
            && !self.readback.settled(id)
    }

    /// Ends an input: frames the full transmit queue refused fail, and every node whose state may
    /// have changed gets its (coalesced) state document queued.
    fn finish_input(&mut self, now: Instant) {
        loop {
            let refused = self.out.transmit.take_refused();
            if refused.is_empty() {
                break;
            }
            let reason = format!(
                "CAN transmit queue full ({} frames)",
                self.out.transmit.cap()
            );
            for (p, owner) in refused {
                self.on_frame_fate(p, owner, FrameFate::Failed(&reason), now);
            }
        }
        self.procedures_on_input(now);
        // Most inputs leave none, and even an empty set's iterator walks its (empty) tree.
        if !self.out.unsure.is_empty() {
            for id in std::mem::take(&mut self.out.unsure) {
                self.readback.want(id);
            }
        }
        if !self.health.bus_down() {
            let registry = &self.registry;
            let online = |id| registry.get(id).is_some_and(|e| e.online);
            self.readback.poll(online, now, &mut self.out);
        }
        let mut dirty = std::mem::take(&mut self.out.dirty);
        dirty.sort_unstable();
        dirty.dedup();
        for id in dirty.drain(..) {
            if self.holds(id, now) {
                self.held.insert(id);
            } else {
                self.out.publish.push_state(id, false);
            }
        }
        // Read back since (or the hold is over): what was held goes out now.
        if !self.held.is_empty() {
            let ready: Vec<NodeId> = self
                .held
                .iter()
                .copied()
                .filter(|&id| !self.holds(id, now))
                .collect();
            for id in ready {
                self.held.remove(&id);
                self.out.publish.push_state(id, true);
            }
        }
        // Kept, with its capacity, for the next input.
        self.out.dirty = dirty;
    }
}

/// The node's relay is on as far as the bridge knows: acknowledged or read back, or in its last
/// health reply (either may be the newer).
fn relay_on(e: &crate::registry::NodeEntry) -> bool {
    e.relay == Some(true)
        || e.health
            .is_some_and(|h| h.flags.contains(ihex_proto::HealthFlags::RELAY))
}

/// `BadFrame` detail class of a frame whose kind the node does not know.
const BAD_FRAME_UNKNOWN_KIND: u32 = 1;

/// The kinds protocol 1.1 added: a 1.0 node refuses them as unknown.
fn is_read_back_kind(kind: u8) -> bool {
    kind == Kind::StateQuery as u8 || kind == Kind::DockLink as u8
}

#[cfg(test)]
mod tests {
    use super::test_support::*;
    use super::*;
    use ihex_proto::{DecodeError, HealthFlags, Kind, Message, NodeId, Packet};
    use serde_json::{json, Value};
    use std::time::Instant;

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
    fn mqtt_reconnect_republishes_every_state() {
        let (mut b, t0) = with_nodes(&[1, 2, 3]);
        b.handle_mqtt_connected(t0 + S);
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
            b.handle_command(input, t0);
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
        b.handle_command(&big, t0);
        let reason = drain(&mut b).one("command_rejected")["reason"].clone();
        assert_eq!(reason, "command is 5000 bytes; the limit is 4096 bytes");
    }

    /// Every frame through the bridge is counted with its bits on the wire (67 + 8 per data byte,
    /// no stuff bits), received or sent, valid or not, addressed to the gateway or not.
    #[test]
    fn frames_are_counted_with_their_bits() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        let health_check = 67 + 8 * u64::from(Message::len_of(Kind::HealthCheck));
        let reply = 67 + 8 * u64::from(Message::len_of(Kind::HealthReply));
        let h = b.bus_health();
        // At least the health check and both replies (the state read-back adds its own frames).
        assert!(h.frames_sent >= 1 && h.frames_received >= 2, "{h:?}");
        assert!(h.frame_bits >= health_check + 2 * reply);

        let sent = command(
            &mut b,
            json!({"cmd": "power", "node": "111", "on": true}),
            t0,
        )
        .sent;
        b.handle_undecodable(0x1f00_0001, &[1, 2, 3], DecodeError::UnknownKind(0x1f), t0);
        // A frame between two nodes.
        b.handle_packet(
            Packet {
                src: id(0x111),
                dest: id(2),
                msg: Message::PowerSet { seq: 0, on: true },
            },
            t0,
        );
        // The echo of our own frame: counted once, as sent.
        for p in sent {
            b.handle_packet(p, t0);
        }
        drain(&mut b);
        let h2 = b.bus_health();
        assert_eq!(
            (
                h2.frames_sent - h.frames_sent,
                h2.frames_received - h.frames_received
            ),
            (1, 2)
        );
        let power = 67 + 8 * u64::from(Message::len_of(Kind::PowerSet));
        assert_eq!(h2.frame_bits - h.frame_bits, power + (67 + 24) + power);
    }

    #[test]
    fn packets_not_for_the_gateway_are_ignored() {
        let (mut b, t0) = with_nodes(&[]);
        b.handle_packet(
            Packet::command(id(2), Message::PowerSet { seq: 0, on: true }),
            t0,
        );
        let out = drain(&mut b);
        assert!(out.events.is_empty() && out.states.is_empty() && out.sent.is_empty());
        assert!(b.registry().get(id(2)).is_none());
    }

    #[test]
    fn read_access_tells_states_links_and_counters() {
        let (mut b, t0) = with_nodes(&[2, 0x111]);
        command(
            &mut b,
            json!({"cmd": "led", "node": "2", "color": "red"}),
            t0,
        );
        command(
            &mut b,
            json!({"cmd": "led", "node": "9", "color": "red"}),
            t0,
        );
        assert_eq!(
            b.command_counters(),
            CommandCounters {
                in_flight: 1,
                sent: 1,
                rejected: 1,
                ..CommandCounters::default()
            }
        );
        b.handle_timeout(t0 + BridgeConfig::default().command_timeout);
        let c = b.command_counters();
        assert_eq!((c.in_flight, c.timeout), (0, 1));

        for _ in 0..3 {
            b.handle_undecodable(0x1f00_0001, &[1], DecodeError::UnknownKind(0x1f), t0);
        }
        b.handle_bus_event(BusEvent::InterfaceDown, t0);
        let h = b.bus_health();
        assert_eq!(
            (
                h.bus_down,
                h.interface_down,
                h.undecodable_frames,
                h.events_suppressed
            ),
            (true, 1, 3, 2)
        );
        b.handle_bus_event(BusEvent::Recovered, t0 + MS);
        assert!(!b.bus_health().bus_down);

        dock(&mut b, 0x111, 3, 2, t0);
        assert_eq!(b.connections().len(), 1);
        let ids: Vec<_> = b.node_states(t0 + S).iter().map(|s| s.id.0).collect();
        assert_eq!(ids, [id(2), id(0x111)]);
        let s = b.node_state(id(0x111), t0 + S).unwrap();
        assert_eq!(
            (s.online, s.connections.len(), s.loops.clone()),
            (true, 1, vec![3])
        );
        assert!(b.node_state(id(9), t0).is_none());
    }

    /// The bytes a cell of the docs' reason table stands for: `<N spaces>`, `<bytes 41 42>`, or the
    /// command itself.
    fn documented_input(cell: &str) -> Vec<u8> {
        if let Some(n) = cell
            .strip_prefix('<')
            .and_then(|c| c.strip_suffix(" spaces>"))
        {
            return vec![b' '; n.parse().unwrap()];
        }
        if let Some(hex) = cell
            .strip_prefix("<bytes ")
            .and_then(|c| c.strip_suffix('>'))
        {
            return hex
                .split(' ')
                .map(|b| u8::from_str_radix(b, 16).unwrap())
                .collect();
        }
        cell.as_bytes().to_vec()
    }

    /// Every rejection reason docs/mqtt-api.md lists is, word for word, what the gateway says to
    /// that command (`UPDATE_DOCS=1` rewrites the reasons from the gateway's answers).
    #[test]
    fn every_documented_rejection_reason_is_the_gateways() {
        const BEGIN: &str = "<!-- rejection reasons: checked by ihex-gateway-core's tests -->\n";
        const END: &str = "<!-- end of rejection reasons -->";
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/mqtt-api.md");
        let doc = std::fs::read_to_string(&path).unwrap();
        let start = doc.find(BEGIN).expect("begin marker") + BEGIN.len();
        let end = start + doc[start..].find(END).expect("end marker");
        let mut rows = doc[start..end].lines().skip(2).peekable();
        assert!(rows.peek().is_some(), "no rows in the reason table");
        let mut updated = String::new();
        let mut wrong = Vec::new();
        for row in rows {
            let cells: Vec<&str> = row
                .strip_prefix("| ")
                .and_then(|r| r.strip_suffix(" |"))
                .unwrap_or_else(|| panic!("not a table row: {row}"))
                .split(" | ")
                .collect();
            let [input, reason] = cells[..] else {
                panic!("a row needs a command and a reason: {row}")
            };
            let input = input.trim_matches('`');
            let documented = reason
                .strip_prefix("``")
                .and_then(|r| r.strip_suffix("``"))
                .unwrap_or_else(|| panic!("reasons are ``quoted``: {row}"))
                .trim();
            let (repeat, input) = match input.split_once(" × ") {
                Some((n, rest)) => (n.parse().unwrap(), rest),
                None => (1, input),
            };
            let (mut b, t0) = with_nodes(&[2, 0x111]);
            let payload = documented_input(input);
            for _ in 1..repeat {
                b.handle_command(&payload, t0);
            }
            drain(&mut b);
            b.handle_command(&payload, t0);
            let out = drain(&mut b);
            assert!(out.sent.is_empty(), "{input}: sent {:?}", out.sent);
            let actual = out.one("command_rejected")["reason"]
                .as_str()
                .unwrap()
                .to_owned();
            if actual != documented {
                wrong.push(format!(
                    "{input}\n  docs:    {documented}\n  gateway: {actual}"
                ));
            }
            let shown = if repeat > 1 {
                format!("{repeat} × {input}")
            } else {
                input.to_owned()
            };
            updated.push_str(&format!("| `{shown}` | `` {actual} `` |\n"));
        }
        if wrong.is_empty() {
            return;
        }
        if std::env::var_os("UPDATE_DOCS").is_some() {
            let header: String = doc[start..end]
                .lines()
                .take(2)
                .map(|l| format!("{l}\n"))
                .collect();
            let text = format!("{}{header}{updated}{}", &doc[..start], &doc[end..]);
            std::fs::write(&path, text).unwrap();
        } else {
            panic!(
                "docs/mqtt-api.md's reasons differ from the gateway's (UPDATE_DOCS=1 rewrites them):\n{}",
                wrong.join("\n")
            );
        }
    }

    #[test]
    fn retained_commands_are_never_executed() {
        let (mut b, t0) = with_nodes(&[2]);
        let retained = Delivery {
            retained: true,
            ..Delivery::live(t0)
        };
        let cmd = json!({"cmd": "power", "node": "2", "on": true, "request_id": "old"});
        let id = b.handle_delivered_command(cmd.to_string().as_bytes(), retained.clone(), t0);
        assert_eq!(id.as_deref(), Some("old"));
        let out = drain(&mut b);
        assert!(out.sent.is_empty());
        let r = out.one("command_rejected");
        assert_eq!(r["request_id"], "old");
        assert!(r["reason"]
            .as_str()
            .unwrap()
            .starts_with("retained message on the command topic: not executed"));
        // Even a retained `list` or a broken retained message gets its one answer.
        b.handle_delivered_command(b"{\"cmd\":\"list\"}", retained.clone(), t0);
        b.handle_delivered_command(b"garbage", retained, t0);
        let out = drain(&mut b);
        assert_eq!(out.named("command_rejected").len(), 2);
        assert!(out.named("node_list").is_empty());
    }

    #[test]
    fn rejections_echo_the_request_id_whenever_it_can_be_read_and_say_which() {
        let (mut b, t0) = with_nodes(&[2]);
        let big = format!(
            r#"{{"request_id":"big","cmd":"led","node":"2","color":"red","pad":"{}"}}"#,
            "x".repeat(5000)
        );
        for (payload, id) in [
            (big.into_bytes(), json!("big")),
            (
                br#"{"request_id":"cut","cmd":"led","node":"#.to_vec(),
                json!("cut"),
            ),
            (
                [
                    br#"{"request_id":"bin","x":""#.as_slice(),
                    &[0xc3, 0x28],
                    br#""}"#,
                ]
                .concat(),
                json!("bin"),
            ),
            (
                br#"{"request_id":"ttl","cmd":"led","node":"2","off":true,"ttl_ms":0}"#.to_vec(),
                json!("ttl"),
            ),
            (br#"["request_id","no"]"#.to_vec(), Value::Null),
        ] {
            let returned = b.handle_delivered_command(&payload, Delivery::live(t0), t0);
            let out = drain(&mut b);
            let what = String::from_utf8_lossy(&payload[..40.min(payload.len())]);
            assert_eq!(out.one("command_rejected")["request_id"], id, "{what}");
            assert_eq!(json!(returned), id, "the id the caller is told, {what}");
        }
        let valid = br#"{"request_id":"fine","cmd":"led","node":"2","off":true}"#;
        let returned = b.handle_delivered_command(valid, Delivery::live(t0), t0);
        assert_eq!(returned.as_deref(), Some("fine"));
        b.handle_command(
            br#"{"cmd":"led","node":"2","off":true,"ttl_ms":"soon"}"#,
            t0,
        );
        assert_eq!(
            drain(&mut b).one("command_rejected")["reason"],
            "led: `ttl_ms` must be an integer 1 to 3600000, in ms; got \"soon\""
        );
    }

    #[test]
    fn under_overload_answers_are_kept_states_coalesced_and_drops_reported() {
        let t0 = Instant::now();
        let config = BridgeConfig {
            event_queue: 4,
            ..BridgeConfig::default()
        };
        let mut b = Bridge::new(config, t0);
        b.handle_timeout(t0);
        // Nobody takes publications: 20 nodes come online (20 events, 20 state documents), every
        // command is answered (rejections here: the nodes are unknown).
        for n in 1..=20u16 {
            b.handle_packet(Packet::report(id(n), reply(0, 0)), t0 + MS);
        }
        read_back_all(&mut b, t0 + MS);
        for n in 0..(ANSWER_BACKLOG - 1) {
            assert!(b.wants_commands());
            let cmd =
                json!({"cmd": "led", "node": "fff", "off": true, "request_id": n.to_string()});
            b.handle_command(cmd.to_string().as_bytes(), t0 + MS);
        }
        // Node 5's state changes twice meanwhile: one document, the latest.
        b.handle_packet(
            Packet::report(id(5), reply(1, HealthFlags::RELAY)),
            t0 + 2 * MS,
        );
        b.handle_command(br#"{"cmd":"list","request_id":"L"}"#, t0 + 2 * MS);
        assert!(!b.wants_commands(), "the answer backlog is full");
        let c = b.publication_counters();
        assert_eq!(
            (c.answers_waiting, c.events_waiting, c.states_waiting),
            (ANSWER_BACKLOG, 4, 20)
        );
        assert_eq!(c.dropped, 16);
        assert_eq!(c.dropped_by_event.get("node_online"), Some(&16));
        b.handle_timeout(t0 + 3 * MS);
        let out = drain(&mut b);
        assert_eq!(out.named("command_rejected").len(), ANSWER_BACKLOG - 1);
        assert_eq!(out.named("node_list").len(), 1);
        let online: Vec<_> = out
            .named("node_online")
            .iter()
            .map(|e| e["payload"]["id"].clone())
            .collect();
        assert_eq!(
            online,
            [json!("11"), json!("12"), json!("13"), json!("14")],
            "the newest events are kept"
        );
        assert_eq!(out.states.len(), 20);
        let (_, five) = out.states.iter().find(|(n, _)| *n == id(5)).unwrap();
        assert_eq!(five["relay"], true, "the latest document");
        let d = out.one("publications_dropped");
        assert_eq!(
            d,
            &json!({"dropped": 16, "total": 16, "events": {"node_online": 16}})
        );
        assert!(b.wants_commands());
        // One report per period at most; nothing to report, nothing sent.
        b.handle_timeout(t0 + DROP_REPORT_PERIOD);
        assert!(drain(&mut b).named("publications_dropped").is_empty());
    }

    /// Each frame's fate goes to the concern that queued it, as its tag says: a state query that
    /// could not be sent is asked again, a command's frame ends its command `failed`, a health
    /// check nobody answers for is a `bus_error`.
    #[test]
    fn a_frames_fate_goes_to_the_concern_that_queued_it() {
        let (mut b, t0) = with_nodes(&[]);
        b.handle_packet(Packet::report(id(2), reply(0, 0)), t0 + MS);
        let query = b.poll_transmit(t0 + MS).unwrap();
        assert_eq!(query.owner, FrameOwner::ReadBack);
        b.handle_send_failed(query.packet, "test", t0 + MS);
        let again = b.poll_transmit(t0 + MS).expect("asked again");
        assert_eq!(again.packet.msg.kind(), Kind::StateQuery);
        assert!(drain(&mut b).named("bus_error").len() == 1);
        answer_queries(
            &mut b,
            &Out {
                queries: vec![again.packet],
                ..Out::default()
            },
            t0 + MS,
        );

        b.handle_command(br#"{"cmd":"identify","node":"2","seconds":1}"#, t0 + MS);
        let cmd = b.poll_transmit(t0 + MS).unwrap();
        assert_eq!(cmd.owner, FrameOwner::Command);
        b.handle_send_failed(cmd.packet, "test", t0 + MS);
        let out = drain(&mut b);
        assert_eq!(out.one("command_result")["result"], "failed");
        assert!(out.named("bus_error").is_empty(), "answered by its command");

        b.handle_timeout(t0 + S);
        let check = b.poll_transmit(t0 + S).unwrap();
        assert_eq!(check.owner, FrameOwner::HealthCheck);
        b.handle_send_failed(check.packet, "test", t0 + S);
        let out = drain(&mut b);
        assert_eq!(out.one("bus_error")["error"], "send_failed");
    }

    /// Issue 29: a restarted gateway publishes no half-known document: a node's state document
    /// (and its Home Assistant config) waits for its read-back, or for the lost period from start
    /// when none comes; a node read back is published at once.
    #[test]
    fn a_node_is_published_once_read_back_or_when_the_lost_period_ends() {
        let t0 = Instant::now();
        let ha = crate::ha::HaConfig {
            topics: crate::topic::Topics::seed_on(None),
            island: None,
            configuration_url: None,
            sw_version: "0.1.0".into(),
        };
        let mut b = Bridge::new(BridgeConfig::default(), t0).with_home_assistant(ha);
        b.handle_timeout(t0);
        b.handle_mqtt_connected(t0);
        drain(&mut b);
        b.handle_packet(Packet::report(id(0x111), reply(0, 0)), t0 + MS);
        b.handle_packet(Packet::report(id(0x112), reply(0, 0)), t0 + MS);
        let out = drain(&mut b);
        assert_eq!(out.named("node_online").len(), 2, "events are not held");
        assert!(out.states.is_empty(), "{:?}", out.states);
        assert!(out.ha.is_empty(), "{:?}", out.ha);
        // A reconnection meanwhile republishes only what may be published.
        b.handle_mqtt_connected(t0 + 2 * MS);
        assert!(drain(&mut b).states.is_empty());
        // 111 answers: its document (and config) go out; 112 stays silent.
        let q111 = out.queries.iter().find(|q| q.dest == id(0x111)).unwrap();
        let Message::StateQuery { seq, parts } = q111.msg else {
            unreachable!()
        };
        let end = StateReport::End {
            seq,
            parts,
            count: 0,
        };
        b.handle_packet(
            Packet::report(id(0x111), Message::StateReport(end)),
            t0 + 3 * MS,
        );
        let out = drain(&mut b);
        let ids: Vec<NodeId> = out.states.iter().map(|(n, _)| *n).collect();
        assert_eq!(ids, [id(0x111)]);
        assert!(!out.ha.is_empty());
        // The lost period from start ends: 112's document goes out as it is known by then.
        let lost_period =
            BridgeConfig::default().health_period * (BridgeConfig::default().lost_after_misses + 1);
        assert!(b.poll_timeout() <= t0 + lost_period);
        for k in 1..4u32 {
            b.handle_timeout(t0 + S * k);
            for n in [0x111, 0x112] {
                b.handle_packet(Packet::report(id(n), reply(k as u8, 0)), t0 + S * k);
            }
        }
        assert!(drain(&mut b).states.iter().all(|(n, _)| *n != id(0x112)));
        b.handle_timeout(t0 + lost_period);
        let out = drain(&mut b);
        assert!(
            out.states.iter().any(|(n, _)| *n == id(0x112)),
            "{:?}",
            out.states
        );
    }

    /// A burst far above what the bus carries, taken as the adapter takes it (up to 64 commands a
    /// turn while [`Bridge::wants_commands`]), with the echoes of the written frames coming back a
    /// few per turn and each node acking its frame in the turn after its echo: the commands wait
    /// with the broker rather than fill the transmit queue, the window stays full while frames
    /// wait, and every command ends `ok`, once.
    #[test]
    fn a_burst_of_commands_waits_for_the_bus_instead_of_failing() {
        const BURST: usize = 2000;
        const TAKEN_PER_TURN: usize = 64;
        const ECHOES_PER_TURN: usize = 3;
        let nodes = [2u16, 3, 4, 5, 6];
        let (mut b, t0) = with_nodes(&nodes);
        drain(&mut b);
        let cap = BridgeConfig::default().tx_queue;
        let mut offered = 0;
        let mut written: std::collections::VecDeque<Packet> = Default::default();
        let mut echoed: Vec<Packet> = Vec::new();
        let mut results: std::collections::BTreeMap<String, Vec<Value>> = Default::default();
        let mut now = t0 + MS;
        let mut turns = 0;
        while results.len() < BURST {
            turns += 1;
            assert!(turns < 10 * BURST, "stalled with {} results", results.len());
            now += Duration::from_micros(100);
            // The acks of last turn's echoes, then this turn's echoes.
            for f in echoed.drain(..) {
                let seq = f.msg.ack_seq().unwrap();
                let a = ack(Kind::Identify, seq, AckResult::Ok);
                b.handle_packet(Packet::report(f.dest, a), now);
            }
            for _ in 0..ECHOES_PER_TURN {
                let Some(f) = written.pop_front() else { break };
                b.handle_packet(f, now);
                echoed.push(f);
            }
            for _ in 0..TAKEN_PER_TURN {
                if offered == BURST || !b.wants_commands() {
                    break;
                }
                let node = nodes[offered % nodes.len()];
                let cmd = json!({"cmd": "identify", "node": format!("{node:x}"), "seconds": 1,
                                 "request_id": offered.to_string()});
                b.handle_command(cmd.to_string().as_bytes(), now);
                offered += 1;
            }
            if b.poll_timeout() <= now {
                b.handle_timeout(now);
            }
            while let Some(t) = b.poll_transmit(now) {
                if matches!(t.packet.msg, Message::Identify { .. }) {
                    written.push_back(t.packet);
                } else {
                    // Health checks: confirmed at once, nobody answers within the test.
                    b.handle_transmitted(t.packet, now);
                }
            }
            let (queued, in_flight) = b.transmit_backlog();
            assert!(queued <= cap / COMMAND_SHARE + 1, "{queued} frames wait");
            if queued > 0 {
                assert_eq!(in_flight, TRANSMIT_WINDOW, "the window is kept full");
            }
            while let Some(p) = b.poll_publication() {
                let v: Value = serde_json::from_str(&p.to_json()).unwrap();
                if v["event"] == "command_result" {
                    let r = v["payload"]["request_id"].as_str().unwrap().to_owned();
                    results.entry(r).or_default().push(v["payload"].clone());
                }
            }
        }
        assert_eq!(offered, BURST);
        for (r, answers) in &results {
            assert_eq!(answers.len(), 1, "one answer for {r}: {answers:?}");
            assert_eq!(answers[0]["result"], "ok", "{r}: {answers:?}");
        }
        assert_eq!(b.command_counters().failed, 0);
    }

    #[test]
    fn echoes_of_our_own_frames_confirm_them() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_command(br#"{"cmd":"identify","node":"2","seconds":1}"#, t0);
        let frame = b.poll_transmit(t0).unwrap().packet;
        assert_eq!(b.transmit_backlog(), (0, 1));
        assert_eq!(frame.src, NodeId::GATEWAY);
        b.handle_packet(frame, t0 + MS);
        assert_eq!(b.transmit_backlog(), (0, 0));
        let out = drain(&mut b);
        assert!(
            out.events.is_empty(),
            "an echo is no event: {:?}",
            out.events
        );
    }
}
