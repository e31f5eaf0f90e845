//! JSON events published on `EventsTopic` and the retained per-node state documents: typed serde DTOs
//! whose serialised form *is* the MQTT API described in `docs/mqtt-api.md`.
//!
//! Every DTO also implements `Deserialize`, so test harnesses and tools (provisioning, dashboards written
//! in Rust) can read events back with the same types instead of poking at untyped JSON.

use std::borrow::Cow;
use std::fmt;

use bytes::BytesMut;
use ihex_proto::{BuzzerCommand, LedCommand, NodeId, ResetReason};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// A node ID in its MQTT form: lower-case hex without leading zeros or prefix (`"111"`, `"2"`).
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
pub struct HexId(pub NodeId);

impl fmt::Display for HexId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.fmt(f)
    }
}

impl Serialize for HexId {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut buf = [0; 4];
        s.serialize_str(hex(self.0, &mut buf))
    }
}

/// A node's protocol version, shown as `"major.minor"` in events and state documents (what
/// `format!("{major}.{minor}")` writes, without the formatting machinery or an allocation: every
/// `BootUp` event and every state document carries one).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub struct Version(pub u8, pub u8);

impl Version {
    /// `"major.minor"` in `buf`.
    fn text(self, buf: &mut [u8; 7]) -> &str {
        std::str::from_utf8(self.digits(buf)).unwrap_or_default()
    }

    /// [`Version::text`]'s ASCII bytes, for writers that need no `str`.
    pub(crate) fn digits(self, buf: &mut [u8; 7]) -> &[u8] {
        let dot = ihex_proto::write_decimal(self.0, buf, 0);
        buf[dot] = b'.';
        let len = ihex_proto::write_decimal(self.1, buf, dot + 1);
        &buf[..len]
    }
}

impl From<(u8, u8)> for Version {
    fn from((major, minor): (u8, u8)) -> Self {
        Version(major, minor)
    }
}

impl fmt::Display for Version {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.text(&mut [0; 7]))
    }
}

impl std::str::FromStr for Version {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let (major, minor) = s
            .split_once('.')
            .ok_or_else(|| format!("{s:?} is not a major.minor version"))?;
        let part = |p: &str| {
            p.parse::<u8>()
                .map_err(|e| format!("{s:?} is not a major.minor version: {e}"))
        };
        Ok(Version(part(major)?, part(minor)?))
    }
}

impl Serialize for Version {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.text(&mut [0; 7]))
    }
}

impl<'de> Deserialize<'de> for Version {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        String::deserialize(d)?
            .parse()
            .map_err(serde::de::Error::custom)
    }
}

/// `id` as its [`fmt::Display`] writes it (lower-case hex, no leading zeros), without the
/// formatting machinery: nearly every publication names a node, and `collect_str` was a tenth of
/// an event's serialisation.
pub(crate) fn hex(id: NodeId, buf: &mut [u8; 4]) -> &str {
    std::str::from_utf8(hex_digits(id, buf)).unwrap_or_default()
}

/// [`hex`]'s ASCII bytes, for writers that need no `str`.
pub(crate) fn hex_digits(id: NodeId, buf: &mut [u8; 4]) -> &[u8] {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut v = id.get();
    let mut i = buf.len();
    loop {
        i -= 1;
        buf[i] = DIGITS[usize::from(v & 0xf)];
        v >>= 4;
        if v == 0 || i == 0 {
            break;
        }
    }
    &buf[i..]
}

impl<'de> Deserialize<'de> for HexId {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse()
            .map(HexId)
            .map_err(|e| serde::de::Error::custom(format!("{s:?}: {e}")))
    }
}

/// Who a command is for: one node, or every node through one broadcast frame (`"all"`).
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Debug)]
pub enum Target {
    /// One node.
    Node(NodeId),
    /// Every node (`"all"`).
    All,
}

impl Target {
    /// The target of a frame sent to `dest`.
    pub fn from_dest(dest: NodeId) -> Target {
        if dest == NodeId::BROADCAST {
            Target::All
        } else {
            Target::Node(dest)
        }
    }

    /// The CAN destination of the command frame.
    pub fn dest(self) -> NodeId {
        match self {
            Target::Node(id) => id,
            Target::All => NodeId::BROADCAST,
        }
    }
}

impl fmt::Display for Target {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Target::Node(id) => id.fmt(f),
            Target::All => f.write_str("all"),
        }
    }
}

impl Serialize for Target {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Target::Node(id) => HexId(*id).serialize(s),
            Target::All => s.serialize_str("all"),
        }
    }
}

impl<'de> Deserialize<'de> for Target {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        if s == "all" {
            return Ok(Target::All);
        }
        s.parse()
            .map(Target::Node)
            .map_err(|e| serde::de::Error::custom(format!("{s:?}: {e}, or \"all\"")))
    }
}

/// One end of a docking connection: an element and its dock port.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct End {
    /// The element.
    pub id: HexId,
    /// Its dock port.
    pub port: u8,
}

/// Payload of `new_connection` / `connection_removed`, in the seed's exact shape and key order:
/// `{"n": {"id": "2", "port": 0}, "n-1": {"id": "111", "port": 3}}`.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct Connection {
    /// The mobile element that docked, and its own port.
    pub n: End,
    /// The static element it docked onto, and that element's dock port.
    #[serde(rename = "n-1")]
    pub n_1: End,
}

/// Static island element or mobile element.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Wired on the bus, has dock ports.
    Static,
    /// Docks onto a static element.
    Mobile,
}

impl Role {
    /// The name in every document and event (`"static"`, `"mobile"`), as serde writes it.
    pub fn name(self) -> &'static str {
        match self {
            Role::Static => "static",
            Role::Mobile => "mobile",
        }
    }
}

/// Payload of `node_online`: a node was heard for the first time, or again after `node_lost`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct NodeOnline {
    /// The node.
    pub id: HexId,
    /// Its role, when the frame that announced it tells (`BootUp`, `HealthReply`).
    pub role: Option<Role>,
    /// True the first time this gateway hears the node, false when it returns after `node_lost`.
    pub first_seen: bool,
}

/// Payload of `node_lost`: the node missed `missed` consecutive health checks.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct NodeLost {
    /// The node.
    pub id: HexId,
    /// Consecutive health checks it did not answer.
    pub missed: u32,
    /// Milliseconds since anything was last heard from it.
    pub last_seen_ms: u64,
}

/// Payload of `node_rebooted`: a `BootUp` from a node that was known and online.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct NodeRebooted {
    /// The node.
    pub id: HexId,
    /// Why it restarted: `power_on`, `watchdog`, `software`, `pin` or `other_<n>`.
    pub reset: ResetReason,
    /// Firmware/protocol version `"major.minor"`.
    pub version: Version,
    /// Its role.
    pub role: Role,
}

/// Payload of `node_forgotten`: the gateway dropped a node from its registry, its retained state
/// document and its Home Assistant device.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct NodeForgotten {
    /// The node's former ID.
    pub id: HexId,
    /// `forget` (the `forget` command) or `renumbered` (the board now answers as `new_id`).
    pub reason: String,
    /// The board's new ID when it was renumbered, else `null`.
    pub new_id: Option<HexId>,
}

/// How a command ended.
#[derive(Clone, Copy, PartialEq, Eq, Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The node (every node, for `"all"`) acknowledged it.
    Ok,
    /// A node answered with a refusal; `reason` names the ack result.
    Refused,
    /// Sent (or handed to the CAN interface, see the reason), but no (or not every) answer within
    /// the command timeout: the node may or may not have acted on it.
    Timeout,
    /// The frame was never sent on the bus (the transmit queue was full or behind, the interface
    /// down, a write failed): the node did not act on it.
    Failed,
    /// Its `ttl_ms` ended before it could be sent: never sent, the node did not act on it.
    Expired,
}

/// One node's refusal of a broadcast command.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct Refusal {
    /// The node.
    pub id: HexId,
    /// The ack result name (`invalid_value`, `busy`, …).
    pub reason: String,
}

/// Payload of `command_result`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct CommandResult {
    /// The command's `request_id`, `null` when it had none.
    pub request_id: Option<String>,
    /// The command name (`led`, `buzzer`, `power`, `identify`, `assign`): one of the gateway's
    /// own names when it answers (no copy per answer), an owned one when read back.
    pub cmd: Cow<'static, str>,
    /// The node (for `assign`: the new ID) or `"all"`.
    pub node: Target,
    /// How it ended.
    pub result: Outcome,
    /// Why, for anything but `ok` (`null` for `ok`).
    pub reason: Option<String>,
    /// Broadcasts only: nodes that acknowledged with `ok`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub acked: Option<Vec<HexId>>,
    /// Broadcasts only: nodes that refused.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refused: Option<Vec<Refusal>>,
    /// Broadcasts only: nodes that were online when the command was sent and did not answer.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub missing: Option<Vec<HexId>>,
    /// The command's interface and identity; absent for the shared command topic without one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<crate::origin::Origin>,
}

/// Payload of `command_rejected`: the command was not sent because it is invalid.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct CommandRejected {
    /// The command's `request_id` when it could be read, else `null`.
    pub request_id: Option<String>,
    /// What was wrong and what is accepted.
    pub reason: String,
    /// The command's interface and identity; absent for the shared command topic without one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<crate::origin::Origin>,
}

/// Payload of `fault`: a node's `Fault` report, or a protocol violation the gateway noticed.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct FaultEvent {
    /// The node concerned.
    pub node: HexId,
    /// Fault name (`dock_confirm_not_docked`, `bus_off`, …, `unexpected_handshake`, `other_<n>`).
    pub code: String,
    /// Code-specific argument (a port, a kind).
    pub arg: u8,
    /// Code-specific detail.
    pub detail: u32,
    /// Human-readable explanation.
    pub message: String,
    /// Faults of this node and code not published since the previous one (rate limit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub suppressed: Option<u32>,
}

/// Payload of `bus_error`: a condition of the CAN bus or interface, or frames the gateway cannot use.
#[derive(Clone, PartialEq, Eq, Debug, Default, Serialize, Deserialize)]
pub struct BusError {
    /// `error_frame`, `bus_off`, `interface_down`, `recovered`, `rx_dropped`, `undecodable_frame`,
    /// `send_failed`.
    pub error: String,
    /// Human-readable explanation.
    pub message: String,
    /// `rx_dropped`: frames dropped since the last report.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub count: Option<u64>,
    /// `error_frame`: the class bits decoded (`tx_timeout`, `lost_arbitration`, `controller`, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub classes: Option<Vec<String>>,
    /// `error_frame` with the controller class: controller status (`rx_passive`, `tx_warning`, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub controller: Option<Vec<String>>,
    /// `error_frame` with the protocol class: violation types (`bit`, `form`, `stuff`, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub protocol: Option<Vec<String>>,
    /// `error_frame`: transmit error counter, when the frame carries it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tec: Option<u8>,
    /// `error_frame`: receive error counter, when the frame carries it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rec: Option<u8>,
    /// `undecodable_frame`: the 29-bit identifier as `0x…`; `send_failed`: the frame's identifier.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub raw_id: Option<String>,
    /// `undecodable_frame` / `error_frame`: the data bytes in hex.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data: Option<String>,
    /// Events of this same kind not published since the previous one (rate limit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub suppressed: Option<u32>,
}

/// Payload of `dock_failed`: a docking on `node`'s `port` did not complete.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct DockFailed {
    /// The static element that reported the docking.
    pub node: HexId,
    /// Its dock port.
    pub port: u8,
    /// Why (`handshake timeout after 5000 ms`, `confirm refused: invalid_state`, …).
    pub reason: String,
    /// The static element's relay as the gateway left it: `false` switched off (it was off
    /// before the docking and nothing else is docked there), `true` left on (it was on before
    /// the docking, or other elements are docked there), `null` not touched by the gateway.
    #[serde(default)]
    pub relay: Option<bool>,
}

/// Payload of `node_list`, the answer to the `list` command.
#[derive(Clone, PartialEq, Debug, Serialize, Deserialize)]
pub struct NodeList {
    /// The `list` command's `request_id`, `null` when it had none.
    pub request_id: Option<String>,
    /// Every known node, by ascending ID.
    pub nodes: Vec<NodeState>,
}

/// Payload of `publications_dropped`: events the gateway dropped because it could not publish them
/// as fast as they came (never answers or state documents), reported at most once per
/// [`crate::bridge::DROP_REPORT_PERIOD`].
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct PublicationsDropped {
    /// Events dropped since the previous report.
    pub dropped: u64,
    /// Events dropped since the gateway started.
    pub total: u64,
    /// `dropped` by event name (`bus_error`, `node_online`, …).
    pub events: std::collections::BTreeMap<String, u64>,
}

/// Payload of `audit_error`: the audit trail could not record (a full disk, the directory's size
/// limit, a failing disk). Commands are carried out and answered all the same; the records lost
/// are counted, and a `gap` record says how many once the trail records again.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct AuditError {
    /// What went wrong.
    pub reason: String,
    /// Records lost since the trail last recorded.
    pub lost: u64,
}

/// Payload of `sim_result` (demo only): how a control message on the `ihex/sim` topic ended.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct SimResult {
    /// The control message's `request_id`, `null` when it had none.
    pub request_id: Option<String>,
    /// The control message's name (`dock`, `undock`, `power_cycle`, `off_bus`, `on_bus`).
    pub sim: String,
    /// `ok`, `refused` (the island said no: unknown element, port taken, ...) or `timeout`.
    pub result: Outcome,
    /// Why, for anything but `ok` (`null` for `ok`).
    pub reason: Option<String>,
}

/// One JSON event: `{"event": "<name>", "payload": {...}}`. The rare large payloads are boxed: every
/// event waiting to be published is as large as the largest variant.
#[derive(Clone, PartialEq, Debug, Serialize, Deserialize)]
#[serde(tag = "event", content = "payload", rename_all = "snake_case")]
pub enum Event {
    /// A mobile element docked and handshook.
    NewConnection(Connection),
    /// A recorded connection ended (undocked, or the mobile element was lost).
    ConnectionRemoved(Connection),
    /// A node was heard for the first time or after being lost.
    NodeOnline(NodeOnline),
    /// A node stopped answering health checks.
    NodeLost(NodeLost),
    /// A known, online node announced a restart.
    NodeRebooted(NodeRebooted),
    /// A node was forgotten (the `forget` command, or it was renumbered).
    NodeForgotten(NodeForgotten),
    /// A command was acknowledged, refused, timed out or could not be sent.
    CommandResult(CommandResult),
    /// A command was invalid and not sent.
    CommandRejected(CommandRejected),
    /// A node reported a fault, or misbehaved.
    Fault(FaultEvent),
    /// The bus or interface reported a problem, or a frame could not be decoded.
    BusError(Box<BusError>),
    /// A docking did not complete.
    DockFailed(DockFailed),
    /// Answer to `list`.
    NodeList(NodeList),
    /// Events were dropped because they could not be published as fast as they came.
    PublicationsDropped(PublicationsDropped),
    /// Demo only: a simulated island control message was carried out or refused.
    SimResult(SimResult),
    /// Demo only: a simulated island control message was not understood.
    SimRejected(CommandRejected),
    /// Where one node is in a firmware update (throttled).
    FwProgress(crate::fwupdate::FwProgress),
    /// A firmware update ended: every node's outcome.
    FwReport(Box<crate::fwupdate::FwReport>),
    /// A node confirmed the new image after the update had given it another outcome.
    FwCorrection(Box<crate::fwupdate::FwCorrection>),
    /// An image uploaded over MQTT was stored, or rejected.
    FwUpload(Box<crate::fwupdate::FwUpload>),
    /// Answer to `lease` and `renew`: the lease and its token.
    LeaseGranted(Box<crate::lease::LeaseGranted>),
    /// A lease ended: released, broken (both answers) or expired.
    LeaseEnded(Box<crate::lease::LeaseEnded>),
    /// The gateway started: leases of an earlier run ended with it.
    LeasesReset(crate::lease::LeasesReset),
    /// Answer to `procedure`: it runs.
    ProcedureStarted(Box<crate::procedure::glue::ProcedureStarted>),
    /// A procedure's step started or ended.
    ProcedureStep(Box<crate::procedure::ProcedureStep>),
    /// A docking or undocking during a procedure's step that is not the one it waits for.
    ProcedureMismatch(Box<crate::procedure::ProcedureMismatch>),
    /// A procedure's one final outcome (and the answer to `procedure_cancel`).
    ProcedureEnded(Box<crate::procedure::ProcedureEnded>),
    /// The audit trail could not record.
    AuditError(AuditError),
}

impl Event {
    /// The event's name as published (`new_connection`, …).
    pub fn name(&self) -> &'static str {
        match self {
            Event::NewConnection(_) => "new_connection",
            Event::ConnectionRemoved(_) => "connection_removed",
            Event::NodeOnline(_) => "node_online",
            Event::NodeLost(_) => "node_lost",
            Event::NodeRebooted(_) => "node_rebooted",
            Event::NodeForgotten(_) => "node_forgotten",
            Event::CommandResult(_) => "command_result",
            Event::CommandRejected(_) => "command_rejected",
            Event::Fault(_) => "fault",
            Event::BusError(_) => "bus_error",
            Event::DockFailed(_) => "dock_failed",
            Event::NodeList(_) => "node_list",
            Event::PublicationsDropped(_) => "publications_dropped",
            Event::SimResult(_) => "sim_result",
            Event::SimRejected(_) => "sim_rejected",
            Event::FwProgress(_) => "fw_progress",
            Event::FwReport(_) => "fw_report",
            Event::FwCorrection(_) => "fw_correction",
            Event::FwUpload(_) => "fw_upload",
            Event::LeaseGranted(_) => "lease_granted",
            Event::LeaseEnded(_) => "lease_ended",
            Event::LeasesReset(_) => "leases_reset",
            Event::ProcedureStarted(_) => "procedure_started",
            Event::ProcedureStep(_) => "procedure_step",
            Event::ProcedureMismatch(_) => "procedure_mismatch",
            Event::ProcedureEnded(_) => "procedure_ended",
            Event::AuditError(_) => "audit_error",
        }
    }

    /// Compact JSON text, as published.
    pub fn to_json(&self) -> String {
        to_json(self)
    }
}

/// Compact JSON of a DTO, as text (tests, logs and the simulator; the gateway publishes
/// [`write_json`]'s bytes).
pub(crate) fn to_json<T: Serialize>(value: &T) -> String {
    let mut out = BytesMut::new();
    write_json(value, &mut out);
    String::from_utf8(out.into()).unwrap_or_else(|_| String::from("{}"))
}

/// Appends `value`'s compact JSON to `out`. Serialising these types cannot fail (plain structs,
/// string keys only); should it ever, `{}` is written rather than panicking the gateway.
pub(crate) fn write_json<T: Serialize>(value: &T, out: &mut BytesMut) {
    let start = out.len();
    if serde_json::to_writer(Append(&mut *out), value).is_err() {
        out.truncate(start);
        out.extend_from_slice(b"{}");
    }
}

/// `io::Write` straight onto a `BytesMut`, as `Vec<u8>`'s: serde_json writes an event in some
/// 25 small pieces, and `bytes`' own `Writer` takes each through the generic `write_all` loop
/// (about 1,250 more instructions per event, callgrind).
struct Append<'a>(&'a mut BytesMut);

impl std::io::Write for Append<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.0.extend_from_slice(buf);
        Ok(buf.len())
    }

    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.0.extend_from_slice(buf);
        Ok(())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// The LED state a node acknowledged.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct LedState {
    /// `off`, `steady` or `blink` (the gateway's own names when it builds a state document: no
    /// copy per document; owned when read back).
    pub mode: Cow<'static, str>,
    /// `#rrggbb`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub color: Option<String>,
    /// 0–255.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub brightness: Option<u8>,
    /// Blink period in ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub period_ms: Option<u16>,
    /// Blink duty cycle in %.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duty: Option<u8>,
}

impl From<LedCommand> for LedState {
    fn from(cmd: LedCommand) -> Self {
        let hex = color_text;
        match cmd {
            LedCommand::Off => LedState {
                mode: "off".into(),
                color: None,
                brightness: None,
                period_ms: None,
                duty: None,
            },
            LedCommand::Steady { color, brightness } => LedState {
                mode: "steady".into(),
                color: Some(hex(color)),
                brightness: Some(brightness),
                period_ms: None,
                duty: None,
            },
            LedCommand::Blink {
                color,
                brightness,
                period_10ms,
                duty_pct,
            } => LedState {
                mode: "blink".into(),
                color: Some(hex(color)),
                brightness: Some(brightness),
                period_ms: Some(ihex_proto::unit::to_ms(period_10ms)),
                duty: Some(duty_pct),
            },
        }
    }
}

/// `#rrggbb` in lower-case hex, as `format!("#{}", Hex(&[r, g, b]))` writes it but without the
/// formatting machinery (a third of taking an answered command's state document).
fn color_text(c: ihex_proto::Rgb) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut text = String::with_capacity(7);
    text.push('#');
    for b in [c.r, c.g, c.b] {
        text.push(char::from(DIGITS[usize::from(b >> 4)]));
        text.push(char::from(DIGITS[usize::from(b & 0xf)]));
    }
    text
}

/// The buzzer state a node acknowledged.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct BuzzerState {
    /// `off`, `on` or `pattern` (static or owned, as [`LedState::mode`]).
    pub mode: Cow<'static, str>,
    /// Tone frequency.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub freq_hz: Option<u16>,
    /// Beep length in ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub on_ms: Option<u16>,
    /// Pause length in ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub off_ms: Option<u16>,
    /// Number of beeps, 0 = until told otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub count: Option<u8>,
}

impl From<BuzzerCommand> for BuzzerState {
    fn from(cmd: BuzzerCommand) -> Self {
        let none = BuzzerState {
            mode: Cow::Borrowed(""),
            freq_hz: None,
            on_ms: None,
            off_ms: None,
            count: None,
        };
        match cmd {
            BuzzerCommand::Off => BuzzerState {
                mode: "off".into(),
                ..none
            },
            BuzzerCommand::Continuous { freq_hz } => BuzzerState {
                mode: "on".into(),
                freq_hz: Some(freq_hz),
                ..none
            },
            BuzzerCommand::Pattern {
                freq_hz,
                on_10ms,
                off_10ms,
                count,
            } => BuzzerState {
                mode: "pattern".into(),
                freq_hz: Some(freq_hz),
                on_ms: Some(ihex_proto::unit::to_ms(on_10ms)),
                off_ms: Some(ihex_proto::unit::to_ms(off_10ms)),
                count: Some(count),
            },
        }
    }
}

/// What the node itself reported in its last `HealthReply`.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct Reported {
    /// Relay on.
    pub relay: bool,
    /// LED strip lit.
    pub led_on: bool,
    /// LED strip blinking.
    pub led_blink: bool,
    /// Buzzer sounding.
    pub buzzer: bool,
    /// Identify running.
    pub identify: bool,
    /// CAN controller error-passive.
    pub error_passive: bool,
    /// CAN transmit error counter.
    pub tec: u8,
    /// CAN receive error counter.
    pub rec: u8,
    /// Seconds since the node booted.
    pub uptime_s: u32,
}

/// The firmware a node runs, as it reports it.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct Firmware {
    /// `"major.minor.patch"`.
    pub version: String,
    /// Running a trial image that has not confirmed itself yet.
    pub trial: bool,
    /// The first 7 bytes of the running image's hash, 14 hex digits (all zero: unknown).
    pub image_hash: String,
}

/// A docking connection seen from one element: its port, and who is at the other end on which port.
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct Link {
    /// This element's port.
    pub port: u8,
    /// The element at the other end.
    pub peer: HexId,
    /// The other element's port.
    pub peer_port: u8,
}

/// The retained state document of one node (published on its state topic and listed by `node_list`).
#[derive(Clone, PartialEq, Eq, Debug, Serialize, Deserialize)]
pub struct NodeState {
    /// The node.
    pub id: HexId,
    /// Answering health checks.
    pub online: bool,
    /// Static or mobile, once known.
    pub role: Option<Role>,
    /// Number of dock ports, from its `BootUp`.
    pub ports: Option<u8>,
    /// Protocol version `"major.minor"`, from its `BootUp`.
    pub version: Option<Version>,
    /// The firmware it runs, read back from the node (`null` until read, or from a node that
    /// cannot be asked).
    pub firmware: Option<Firmware>,
    /// The board's 96-bit unique ID, 24 hex digits, read back from the node (what `assign`
    /// selects a board by).
    pub uid: Option<String>,
    /// The LED state: read back from the node, or last acknowledged by it, whichever is newer.
    pub led: Option<LedState>,
    /// The buzzer state: read back from the node, or last acknowledged by it, whichever is newer.
    pub buzzer: Option<BuzzerState>,
    /// Relay state: read back, last acknowledged `power` command or last health report, whichever
    /// is newer.
    pub relay: Option<bool>,
    /// Dock ports whose signal loop is closed (something docked), ascending.
    pub loops: Vec<u8>,
    /// Docking connections of this element.
    pub connections: Vec<Link>,
    /// The node's last health report.
    pub reported: Option<Reported>,
    /// Milliseconds since the node was last heard, at the time of publication.
    pub last_seen_ms: u64,
    /// Milliseconds since this gateway first heard the node, at the time of publication.
    pub first_seen_ms: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id(raw: u16) -> HexId {
        HexId(NodeId::new(raw).unwrap())
    }

    #[test]
    fn colors_read_as_format_writes_them() {
        for (r, g, b) in [
            (0, 0, 0),
            (0x12, 0xab, 0xff),
            (255, 255, 255),
            (1, 0x10, 0xf0),
        ] {
            let c = ihex_proto::Rgb::new(r, g, b);
            let text = format!("#{}", ihex_proto::Hex(&[r, g, b]));
            assert_eq!(color_text(c), text);
            assert_eq!(text.len(), 7);
        }
    }

    #[test]
    fn versions_read_as_format_writes_them() {
        for v in [
            (0, 0),
            (1, 0),
            (1, 2),
            (9, 10),
            (10, 99),
            (100, 255),
            (255, 9),
        ] {
            let text = Version::from(v).to_string();
            assert_eq!(text, format!("{}.{}", v.0, v.1));
            assert_eq!(text.parse(), Ok(Version::from(v)));
        }
    }

    #[test]
    fn ids_serialise_as_their_display_text() {
        for raw in [0, 1, 0xf, 0x10, 0xab, 0x111, 0x7ff, NodeId::MAX_RAW] {
            let h = id(raw);
            assert_eq!(serde_json::to_string(&h).unwrap(), format!("\"{h}\""));
            let t = Target::Node(h.0);
            assert_eq!(serde_json::to_string(&t).unwrap(), format!("\"{t}\""));
        }
        assert_eq!(serde_json::to_string(&Target::All).unwrap(), "\"all\"");
    }

    #[test]
    fn new_connection_is_byte_for_byte_the_seed_shape() {
        let ev = Event::NewConnection(Connection {
            n: End {
                id: id(0x2),
                port: 0,
            },
            n_1: End {
                id: id(0x111),
                port: 3,
            },
        });
        assert_eq!(
            ev.to_json(),
            r#"{"event":"new_connection","payload":{"n":{"id":"2","port":0},"n-1":{"id":"111","port":3}}}"#
        );
        let removed = Event::ConnectionRemoved(Connection {
            n: End {
                id: id(0xabc),
                port: 5,
            },
            n_1: End {
                id: id(0x10),
                port: 1,
            },
        });
        assert_eq!(
            removed.to_json(),
            r#"{"event":"connection_removed","payload":{"n":{"id":"abc","port":5},"n-1":{"id":"10","port":1}}}"#
        );
    }

    #[test]
    fn events_round_trip_through_json() {
        let ev = Event::CommandResult(CommandResult {
            request_id: Some("r1".into()),
            cmd: "led".into(),
            node: Target::All,
            result: Outcome::Timeout,
            reason: Some("1 of 2 nodes did not answer".into()),
            acked: Some(vec![id(1)]),
            refused: Some(vec![]),
            missing: Some(vec![id(0xffd)]),
            origin: None,
        });
        let text = ev.to_json();
        assert!(text.contains(r#""node":"all""#), "{text}");
        assert!(text.contains(r#""missing":["ffd"]"#), "{text}");
        let back: Event = serde_json::from_str(&text).unwrap();
        assert_eq!(back, ev);
    }

    #[test]
    fn command_result_without_request_id_carries_null() {
        let ev = Event::CommandResult(CommandResult {
            request_id: None,
            cmd: "power".into(),
            node: Target::Node(NodeId::new(0x2a).unwrap()),
            result: Outcome::Ok,
            reason: None,
            acked: None,
            refused: None,
            missing: None,
            origin: None,
        });
        assert_eq!(
            ev.to_json(),
            r#"{"event":"command_result","payload":{"request_id":null,"cmd":"power","node":"2a","result":"ok","reason":null}}"#
        );
    }

    #[test]
    fn led_and_buzzer_states_report_milliseconds() {
        let led = LedState::from(LedCommand::Blink {
            color: ihex_proto::Rgb::new(255, 0, 16),
            brightness: 200,
            period_10ms: 50,
            duty_pct: 25,
        });
        assert_eq!(
            to_json(&led),
            r##"{"mode":"blink","color":"#ff0010","brightness":200,"period_ms":500,"duty":25}"##
        );
        let buz = BuzzerState::from(BuzzerCommand::Pattern {
            freq_hz: 2000,
            on_10ms: 10,
            off_10ms: 255,
            count: 3,
        });
        assert_eq!(
            to_json(&buz),
            r#"{"mode":"pattern","freq_hz":2000,"on_ms":100,"off_ms":2550,"count":3}"#
        );
    }
}
