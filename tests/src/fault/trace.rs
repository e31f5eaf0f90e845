//! What a fault run records, in the order it happened: commands sent, MQTT messages seen, frames on
//! the bus, the simulated island's truth, faults injected and the checkpoints taken after them.
//!
//! Every record carries the milliseconds since the run started on the harness's one monotonic
//! clock. The trace is plain data (serde), written as JSON lines next to a failed run so the
//! [checker](super::check) can be run on it again and the story read by a person.

use serde::{Deserialize, Serialize};

/// Milliseconds since the start of the run.
pub type Ms = u64;

/// A recorded run.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Trace {
    /// The gateway's settings the checker needs.
    pub params: Params,
    /// Everything that happened, by time.
    pub records: Vec<Record>,
}

/// The gateway's settings and the run's tolerances, in milliseconds.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct Params {
    /// The gateway's health period.
    pub health_period_ms: u64,
    /// Missed health checks after which the gateway reports a node lost.
    pub lost_after: u32,
    /// The gateway's command timeout.
    pub command_timeout_ms: u64,
    /// Time the machine may add to any expectation (scheduling, emulation): answers may come this
    /// much after the command timeout, a checkpoint is taken within this much of its due time.
    pub slack_ms: u64,
    /// The gateway's docking handshake timeout (traces written before it was recorded: 3000).
    #[serde(default = "default_dock_timeout_ms")]
    pub dock_timeout_ms: u64,
}

fn default_dock_timeout_ms() -> u64 {
    3000
}

impl Default for Params {
    fn default() -> Params {
        Params {
            health_period_ms: 500,
            lost_after: 3,
            command_timeout_ms: 1000,
            slack_ms: 1000,
            dock_timeout_ms: default_dock_timeout_ms(),
        }
    }
}

/// One thing that happened.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Record {
    /// When.
    pub at: Ms,
    /// What.
    #[serde(flatten)]
    pub entry: Entry,
}

/// The kinds of records.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Entry {
    /// The harness published a command on the command topic (QoS 1).
    Sent(Sent),
    /// The recorder, subscribed to everything under the island's prefix, received a message.
    Received {
        /// Topic.
        topic: String,
        /// Payload as text.
        payload: String,
        /// RETAIN flag as delivered.
        retain: bool,
    },
    /// The recorder's connection to the broker was (re)established.
    RecorderConnected,
    /// A frame the bus listener saw (29-bit id, data).
    Frame {
        /// Extended identifier.
        id: u32,
        /// Data bytes.
        data: Vec<u8>,
    },
    /// The bus listener lost its socket (`false`, frames may be missed from here) or has one
    /// again (`true`).
    Listening(bool),
    /// A fault was injected.
    FaultBegin {
        /// Number of the fault in this run.
        fault: u32,
        /// What.
        what: Fault,
    },
    /// The fault's cause was removed (broker restarted, proxy passing, link up, node back...).
    FaultEnd {
        /// Number of the fault.
        fault: u32,
    },
    /// The system was seen back after the fault (`how` says by what), the moment from which
    /// state must converge within 2 health periods.
    Recovered {
        /// Number of the fault.
        fault: u32,
        /// What was seen (`availability online`, `bus_error recovered`, ...).
        how: String,
    },
    /// Something done to the island that is not a fault (random activity).
    Island(IslandAction),
    /// The island's truth after a change.
    Truth(Vec<Element>),
    /// The island's truth and the broker's retained documents, taken after a recovery.
    Checkpoint {
        /// The fault this checkpoint follows (`None` at the end of the run).
        fault: Option<u32>,
        /// The island as it is.
        truth: Vec<Element>,
        /// Every retained message under the island's prefix: (topic, payload).
        retained: Vec<(String, String)>,
    },
    /// A note from the harness (the seed, a skipped step, a harness error).
    Note(String),
}

/// A command the harness sent.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct Sent {
    /// Number of the command in this run.
    pub n: u32,
    /// The payload exactly as published.
    pub payload: String,
    /// The `request_id` it carries, if any.
    pub request_id: Option<String>,
    /// Published with the RETAIN flag.
    pub retained: bool,
    /// Its `ttl_ms`, if any.
    pub ttl_ms: Option<u64>,
    /// The same command without `request_id` and `ttl_ms`, as the gateway core's parser reads it
    /// (what the checker matches frames against).
    pub action: String,
}

/// A fault the harness can inject.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(tag = "fault", rename_all = "snake_case")]
pub enum Fault {
    /// The broker is killed with SIGKILL and started again (sessions and retained messages lost).
    BrokerKill {
        /// How long it stays down.
        down_ms: u64,
    },
    /// The gateway process is killed with SIGKILL and started again.
    GatewayKill {
        /// How long it stays down.
        down_ms: u64,
    },
    /// The proxy between gateway and broker closes the connection and refuses new ones.
    ProxyCut {
        /// How long.
        ms: u64,
    },
    /// The proxy delays every chunk.
    ProxyDelay {
        /// The added latency per direction.
        delay_ms: u64,
        /// How long.
        ms: u64,
    },
    /// The proxy stops forwarding both ways without closing (a zombie connection).
    ProxyHalfOpen {
        /// How long.
        ms: u64,
        /// Long enough for the keep-alive of both ends to notice: the connection must be
        /// replaced (`offline`, then `online`).
        noticed: bool,
    },
    /// The CAN interface goes down and up again.
    CanDown {
        /// How long it stays down.
        ms: u64,
    },
    /// A node's power is removed and restored (a fresh boot).
    NodeReset {
        /// The element (hex id).
        node: String,
    },
    /// A node is taken off the bus and put back.
    OffBus {
        /// The element (hex id).
        node: String,
        /// How long.
        ms: u64,
    },
}

impl Fault {
    /// Whether the gateway's MQTT session may be lost: commands sent meanwhile may never reach it
    /// and answers may never reach the recorder.
    pub fn breaks_mqtt(&self) -> bool {
        matches!(
            self,
            Fault::BrokerKill { .. }
                | Fault::GatewayKill { .. }
                | Fault::ProxyCut { .. }
                | Fault::ProxyHalfOpen { .. }
        )
    }

    /// Whether the availability topic must go `offline` (the last will, or the broker itself gone)
    /// and then `online` again.
    pub fn expects_offline(&self) -> bool {
        match self {
            Fault::BrokerKill { .. } | Fault::GatewayKill { .. } | Fault::ProxyCut { .. } => true,
            Fault::ProxyHalfOpen { noticed, .. } => *noticed,
            _ => false,
        }
    }

    /// A short name for reports.
    pub fn name(&self) -> &'static str {
        match self {
            Fault::BrokerKill { .. } => "broker kill -9",
            Fault::GatewayKill { .. } => "gateway kill -9",
            Fault::ProxyCut { .. } => "proxy cut",
            Fault::ProxyDelay { .. } => "proxy delay",
            Fault::ProxyHalfOpen { .. } => "proxy half-open",
            Fault::CanDown { .. } => "CAN interface down",
            Fault::NodeReset { .. } => "node power cycle",
            Fault::OffBus { .. } => "node off the bus",
        }
    }
}

/// Random island activity (not a fault).
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
#[serde(tag = "action", rename_all = "snake_case")]
pub enum IslandAction {
    /// A mobile element docked.
    Dock {
        /// Mobile element.
        mobile: String,
        /// Static element.
        at: String,
        /// Its port.
        port: u8,
    },
    /// A mobile element undocked.
    Undock {
        /// Mobile element.
        mobile: String,
    },
}

/// One element of the simulated island as it really is.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct Element {
    /// Its node ID (hex), or its name when unconfigured.
    pub id: String,
    /// Mobile element (docks by `own_port`).
    pub mobile: bool,
    /// A mobile element's own dock port.
    pub own_port: u8,
    /// Has power.
    pub powered: bool,
    /// Connected to the bus.
    pub on_bus: bool,
    /// LED drive per channel (brightness applied), `[r, g, b]`.
    pub led: [u8; 3],
    /// LED blink gate `(period_ms, duty_pct)`, `None` = steady.
    pub blink: Option<(u16, u8)>,
    /// Buzzer: `off`, `on FREQ`, `pattern FREQ ON OFF COUNT`.
    pub buzzer: String,
    /// Dock relay on.
    pub relay: bool,
    /// A mobile element: docked on (static element, its port).
    pub docked: Option<(String, u8)>,
}
