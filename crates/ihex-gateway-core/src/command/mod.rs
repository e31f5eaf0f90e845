//! JSON commands from `CommandsTopic`, parsed and checked in one pass: the text becomes a [`json`]
//! tree once (keeping repeated keys, so they can be refused), then each field is read once by
//! `field` as the type it must be and within the protocol's range, straight into the protocol's
//! own values — so nothing out of range ever becomes a frame and no later check is needed. Every
//! failure is a [`CommandError`] whose text says, in the API's words, which field was wrong, what
//! it accepts and what it got; parsing never panics, whatever the bytes.

pub(crate) mod field;
pub mod json;
pub(crate) mod pending;

use std::time::Duration;

use ihex_proto::{BuzzerCommand, LedCommand, Message, NodeId, Port, Rgb, Seq, Uid};

use crate::event::{HexId, Target};
use crate::lease::{Scope, MAX_LEASE_S, MAX_NOTE_CHARS, MAX_OWNER_CHARS};
use field::{ms_expected, Fields};
use json::{Arena, Json, Quote};

/// Every command name, for error messages.
pub const COMMAND_NAMES: &str =
    "led, buzzer, power, identify, assign, forget, list, fw_update, fw_cancel, lease, renew, release, break_lease, procedure, procedure_cancel";

/// Default buzzer tone when a command gives none, in Hz.
pub const DEFAULT_FREQ_HZ: u16 = 2000;
/// Default `identify` duration in seconds.
pub const DEFAULT_IDENTIFY_S: u8 = 5;
/// Default blink duty cycle in %.
pub const DEFAULT_DUTY_PCT: u8 = 50;

/// Why a command was rejected. The `Display` text is the `reason` of `command_rejected`.
#[derive(Clone, PartialEq, Eq, Debug, thiserror::Error)]
pub enum CommandError {
    /// Larger than `max_command_bytes`.
    #[error("command is {len} bytes; the limit is {max} bytes")]
    TooLarge {
        /// Payload size.
        len: usize,
        /// The configured limit.
        max: usize,
    },
    /// `--require-identity`: the command came without an identity anyone vouches for.
    #[error(
        "no vouched identity: this gateway takes commands only on a per-user command topic \
         ({topic}/<user>, which the broker lets only <user> publish to) or from an interface that \
         establishes who sent them"
    )]
    NoIdentity {
        /// The per-user topics' root as the adapter names it.
        topic: String,
    },
    /// Not UTF-8.
    #[error(
        "command is not valid UTF-8 (invalid byte at offset {0}); send a JSON object as UTF-8 text"
    )]
    NotUtf8(usize),
    /// Not JSON.
    #[error("malformed JSON: {0}")]
    Json(String),
    /// JSON, but not an object.
    #[error(
        "a command must be a JSON object like {{\"cmd\": \"led\", \"node\": \"2\", \"color\": \"red\"}}; \
         got {0}"
    )]
    NotObject(&'static str),
    /// `request_id` present but not a string (the value, quoted).
    #[error("`request_id` must be a string; got {0}")]
    RequestId(String),
    /// `cmd` or `request_id` given twice.
    #[error("duplicate field `{0}` (each field may appear once)")]
    Duplicate(&'static str),
    /// No `cmd`.
    #[error("missing field `cmd`; expected one of: {COMMAND_NAMES}")]
    MissingCmd,
    /// `cmd` not a string or not a known name.
    #[error("unknown cmd {0}; expected one of: {COMMAND_NAMES}")]
    UnknownCmd(String),
    /// A field is missing, repeated, unknown, of the wrong type or out of range.
    #[error("{cmd}: {message}")]
    Invalid {
        /// The command name.
        cmd: &'static str,
        /// What is wrong and what is accepted.
        message: String,
    },
    /// The addressed node has never been heard on the bus.
    #[error("unknown node {id}; known: {known}")]
    UnknownNode {
        /// The node asked for.
        id: HexId,
        /// The known nodes, comma-separated (or `none yet`).
        known: String,
    },
    /// `assign` to an ID that an online node already has.
    #[error(
        "assign: node {0} is online with that id; assigning it to a second board would put two nodes \
         with one id on the bus (add \"force\": true to assign anyway)"
    )]
    IdInUse(HexId),
    /// `forget` of a node that still answers health checks.
    #[error(
        "forget: node {0} is online; only a lost node can be forgotten (an online one would be \
         registered again at its next health reply)"
    )]
    ForgetOnline(HexId),
    /// A retained message on the command topic: never executed, because the broker hands it out
    /// again on every subscription (each gateway start and reconnect).
    #[error(
        "retained message on the command topic: not executed (a retained command would run again \
         at every gateway start and reconnect); publish commands without the retain flag, and clear \
         this one by publishing an empty retained message to the topic"
    )]
    Retained,
    /// `fw_update` while another update is loading or running.
    #[error("fw_update: an update is running; wait for its fw_report")]
    FwBusy,
    /// `fw_cancel` with no update running.
    #[error("fw_cancel: no firmware update is running (the fw_report of the last one says how it ended)")]
    FwNotRunning,
    /// `fw_cancel` while the update's image is still being read (before its `command_result`).
    #[error(
        "fw_cancel: the update is still reading its image; send fw_cancel again once its \
         command_result is out"
    )]
    FwLoading,
    /// A lease refuses the command, or a lease command was refused.
    #[error(transparent)]
    Lease(#[from] crate::lease::LeaseError),
    /// A procedure could not start, or `procedure_cancel` named none running.
    #[error(transparent)]
    Procedure(#[from] crate::procedure::ProcedureError),
    /// `fw_update` to `"all"` with no node online.
    #[error("fw_update: no node is online")]
    FwNoNodes,
    /// Too many unanswered commands of one kind to one node: every sequence number is in use.
    #[error(
        "{cmd}: 256 {cmd} commands to node {node} are still unanswered; wait for their results"
    )]
    Busy {
        /// The command name.
        cmd: &'static str,
        /// The target.
        node: Target,
    },
}

/// A command to one node or to all, answered with an `Ack`.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum NodeAction {
    /// `led`.
    Led(LedCommand),
    /// `buzzer`.
    Buzzer(BuzzerCommand),
    /// `power`: relay on or off.
    Power(bool),
    /// `identify` for this many seconds (0 stops).
    Identify(u8),
}

impl NodeAction {
    /// The command name.
    pub fn name(&self) -> &'static str {
        match self {
            NodeAction::Led(_) => "led",
            NodeAction::Buzzer(_) => "buzzer",
            NodeAction::Power(_) => "power",
            NodeAction::Identify(_) => "identify",
        }
    }

    /// The frame payload, with the given sequence number.
    pub fn to_message(&self, seq: Seq) -> Message {
        match *self {
            NodeAction::Led(cmd) => Message::LedSet { seq, cmd },
            NodeAction::Buzzer(cmd) => Message::BuzzerSet { seq, cmd },
            NodeAction::Power(on) => Message::PowerSet { seq, on },
            NodeAction::Identify(seconds) => Message::Identify { seq, seconds },
        }
    }
}

/// A validated command.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum Command {
    /// `led`, `buzzer`, `power`, `identify`.
    Node {
        /// One node or all.
        target: Target,
        /// What to do.
        action: NodeAction,
    },
    /// `assign`: give the board with this unique ID a node ID.
    Assign {
        /// The board's 96-bit unique ID.
        uid: Uid,
        /// The ID to give it (`0x001..=0xFFD`).
        new_id: NodeId,
        /// Assign even when a node with `new_id` is online.
        force: bool,
    },
    /// `forget`: drop a lost node from the registry, its retained state and its Home Assistant device.
    Forget {
        /// The node.
        id: NodeId,
    },
    /// `list`: publish `node_list`.
    List,
    /// `fw_update`: send a signed image from the gateway's firmware directory to nodes.
    FwUpdate {
        /// The image's file name in the firmware directory (checked: a plain name).
        image: String,
        /// Which nodes.
        nodes: FwNodes,
        /// Let the nodes take an older version than theirs.
        force: bool,
    },
    /// `fw_cancel`: stop the running firmware update (its `fw_report` says which elements it
    /// stopped).
    FwCancel,
    /// `lease`: hold elements (or the island) so that only commands with the token reach them.
    Lease {
        /// Who holds it.
        owner: String,
        /// Why, shown to whoever it keeps out.
        note: Option<String>,
        /// What it covers.
        scope: crate::lease::Scope,
        /// How long from now.
        ttl: Duration,
    },
    /// `renew`: the lease whose token the command carries lasts `ttl` from now.
    Renew {
        /// How long from now.
        ttl: Duration,
    },
    /// `release`: end the lease whose token the command carries.
    Release,
    /// `break_lease`: end someone else's lease (an administrative privilege).
    BreakLease {
        /// The lease's public id.
        id: u32,
        /// Why, published with the `lease_ended` event.
        reason: String,
    },
    /// `procedure`: run a guided procedure (its steps inline).
    Procedure(Box<crate::procedure::Spec>),
    /// `procedure_cancel`: end a running procedure.
    ProcedureCancel {
        /// The procedure's id.
        id: u32,
    },
}

/// The nodes of an `fw_update`.
#[derive(Clone, PartialEq, Eq, Debug)]
pub enum FwNodes {
    /// Every node online when the update starts.
    All,
    /// These nodes (at least one, no repeats).
    List(Vec<NodeId>),
}

impl Command {
    /// The command name.
    pub fn name(&self) -> &'static str {
        match self {
            Command::Node { action, .. } => action.name(),
            Command::Assign { .. } => "assign",
            Command::Forget { .. } => "forget",
            Command::List => "list",
            Command::FwUpdate { .. } => "fw_update",
            Command::FwCancel => "fw_cancel",
            Command::Lease { .. } => "lease",
            Command::Renew { .. } => "renew",
            Command::Release => "release",
            Command::BreakLease { .. } => "break_lease",
            Command::Procedure(_) => "procedure",
            Command::ProcedureCancel { .. } => "procedure_cancel",
        }
    }
}

/// A command and its optional request id and time to live.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Request {
    /// Echoed in `command_result` / `node_list`.
    pub request_id: Option<String>,
    /// `ttl_ms`: after this long from its receipt the command is never sent (`expired`).
    pub ttl: Option<Duration>,
    /// What to do.
    pub command: Command,
    /// `lease`: the token of a lease the sender holds (needed by commands to leased elements,
    /// and by `renew` and `release`).
    pub lease: Option<String>,
    /// `user`: the name the sender gives itself (recorded as claimed, never vouched for).
    pub user: Option<String>,
}

/// A rejected command: the reason, and the request id if it could be read.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Rejection {
    /// The command's `request_id`, when the payload was an object with a string `request_id`.
    pub request_id: Option<String>,
    /// Why.
    pub error: CommandError,
}

/// What the `node` field accepts.
const NODE_OR_ALL: &str = "a node id in hex, \"1\" to \"ffd\", or \"all\"";
/// What a node ID field accepts.
const NODE_ID: &str = "a node id in hex, \"1\" to \"ffd\"";
/// What `blink` accepts.
const BLINK: &str = "an object like {\"period_ms\":500,\"duty\":50}";
/// What the buzzer's `mode` accepts.
const MODE: &str = "\"off\", \"on\" or \"pattern\"";
/// What `uid` accepts.
const UID: &str = "24 hex digits (the board's 96-bit unique ID)";

/// Fields of each command besides `cmd` and `request_id`.
const LED_FIELDS: &[&str] = &["node", "color", "brightness", "blink", "off"];
const BLINK_FIELDS: &[&str] = &["period_ms", "duty"];
const BUZZER_FIELDS: &[&str] = &["node", "mode", "freq_hz", "on_ms", "off_ms", "count"];
const POWER_FIELDS: &[&str] = &["node", "on"];
const IDENTIFY_FIELDS: &[&str] = &["node", "seconds"];
const ASSIGN_FIELDS: &[&str] = &["uid", "new_id", "force"];
const FORGET_FIELDS: &[&str] = &["node"];

/// Largest `ttl_ms`, ms (an hour: a command that may wait longer has no deadline worth the name).
pub const MAX_TTL_MS: u32 = 3_600_000;

/// How much of a payload [`request_id`] reads at most.
pub const REQUEST_ID_SCAN: usize = 1 << 20;

/// The `request_id` of a payload that is not (or not only) a valid command, when it can be read:
/// the first string-valued top-level member `request_id` of a JSON object among the first
/// [`REQUEST_ID_SCAN`] bytes, before any syntax error (the rest is skipped, not stored).
pub fn request_id(payload: &[u8]) -> Option<String> {
    json::top_level_string(&payload[..payload.len().min(REQUEST_ID_SCAN)], "request_id")
}
const FW_UPDATE_FIELDS: &[&str] = &["image", "nodes", "force"];
/// What `fw_update`'s `image` accepts.
const FW_IMAGE: &str =
    "the name of an uploaded image or of a file in the gateway's firmware directory (letters, digits, '.', '-', '_')";
/// What `fw_update`'s `nodes` accepts.
const FW_NODES: &str = "\"all\" or node ids in hex separated by commas, like \"111,112\"";

/// Parses and validates one command payload. Node existence is not checked here (the registry is the
/// bridge's); everything else is.
pub fn parse(payload: &[u8], max_bytes: usize) -> Result<Request, Rejection> {
    parse_in(payload, max_bytes, &mut Arena::default())
}

/// [`parse`], the JSON tree built in `arena` (a caller that parses many commands keeps one).
pub fn parse_in(payload: &[u8], max_bytes: usize, arena: &mut Arena) -> Result<Request, Rejection> {
    let reject = |request_id: Option<String>, error| Rejection { request_id, error };
    if payload.len() > max_bytes {
        return Err(reject(
            request_id(payload),
            CommandError::TooLarge {
                len: payload.len(),
                max: max_bytes,
            },
        ));
    }
    let text = std::str::from_utf8(payload)
        .map_err(|e| reject(request_id(payload), CommandError::NotUtf8(e.valid_up_to())))?;
    let value = arena
        .parse(text)
        .map_err(|e| reject(request_id(payload), CommandError::Json(e.to_string())))?;
    let Json::Object(members) = value else {
        return Err(reject(None, CommandError::NotObject(value.kind())));
    };
    let one = |name: &'static str| {
        let mut it = members.iter().filter(|(n, _)| *n == name).map(|(_, v)| v);
        match (it.next(), it.next()) {
            (_, Some(_)) => Err(CommandError::Duplicate(name)),
            (v, None) => Ok(v),
        }
    };
    // The request id first: a rejection echoes it whenever it can be read.
    let request_id = match one("request_id").map_err(|e| reject(None, e))? {
        None | Some(Json::Null) => None,
        Some(Json::String(s)) => Some(s.to_string()),
        Some(other) => {
            let error = CommandError::RequestId(Quote(other).to_string());
            return Err(reject(None, error));
        }
    };
    let command = match one("cmd") {
        Err(e) => Err(e),
        Ok(None) => Err(CommandError::MissingCmd),
        Ok(Some(Json::String(cmd))) => command(cmd, members),
        Ok(Some(other)) => Err(CommandError::UnknownCmd(Quote(other).to_string())),
    };
    let ttl = command.and_then(|c| {
        let ttl = field::ttl(c.name(), members)?;
        let lease = field::lease(c.name(), members)?;
        let user = field::user(c.name(), members)?;
        if lease.is_none() && matches!(c, Command::Renew { .. } | Command::Release) {
            return Err(CommandError::Invalid {
                cmd: c.name(),
                message: "missing `lease`: the token `lease_granted` answered".into(),
            });
        }
        Ok((c, ttl, lease, user))
    });
    match ttl {
        Ok((command, ttl, lease, user)) => Ok(Request {
            request_id,
            ttl,
            command,
            lease,
            user,
        }),
        Err(error) => Err(reject(request_id, error)),
    }
}

fn command(cmd: &str, members: &[(&str, Json<'_>)]) -> Result<Command, CommandError> {
    match cmd {
        "led" => led(&Fields::new("led", "", members, LED_FIELDS, "")?),
        "buzzer" => buzzer(&Fields::new("buzzer", "", members, BUZZER_FIELDS, "")?),
        "power" => {
            let f = Fields::new("power", "", members, POWER_FIELDS, "")?;
            Ok(Command::Node {
                target: target(&f)?,
                action: NodeAction::Power(f.required("on", f.bool("on")?, "true or false")?),
            })
        }
        "identify" => {
            let f = Fields::new("identify", "", members, IDENTIFY_FIELDS, "")?;
            Ok(Command::Node {
                target: target(&f)?,
                action: NodeAction::Identify(
                    f.u8_in("seconds", 0, 255)?.unwrap_or(DEFAULT_IDENTIFY_S),
                ),
            })
        }
        "assign" => {
            let hint = " (assign is broadcast and selects the board by its `uid`)";
            assign(&Fields::new("assign", "", members, ASSIGN_FIELDS, hint)?)
        }
        "forget" => {
            let f = Fields::new("forget", "", members, FORGET_FIELDS, "")?;
            let v = f.get("node").ok_or_else(|| f.missing("node", NODE_ID))?;
            match v {
                Json::String(s) => match s.parse::<NodeId>() {
                    Ok(id) if id.is_sc() => Ok(Command::Forget { id }),
                    _ => Err(f.bad("node", NODE_ID, v)),
                },
                _ => Err(f.bad("node", NODE_ID, v)),
            }
        }
        "list" => {
            Fields::new("list", "", members, &[], "")?;
            Ok(Command::List)
        }
        "fw_update" => fw_update(&Fields::new(
            "fw_update",
            "",
            members,
            FW_UPDATE_FIELDS,
            "",
        )?),
        "fw_cancel" => {
            Fields::new("fw_cancel", "", members, &[], "")?;
            Ok(Command::FwCancel)
        }
        "lease" => lease(&Fields::new("lease", "", members, LEASE_FIELDS, "")?),
        "renew" => {
            let f = Fields::new("renew", "", members, &["seconds"], "")?;
            Ok(Command::Renew {
                ttl: lease_seconds(&f)?,
            })
        }
        "release" => {
            Fields::new("release", "", members, &[], "")?;
            Ok(Command::Release)
        }
        "break_lease" => {
            let f = Fields::new("break_lease", "", members, &["id", "reason"], "")?;
            let id = f.int("id", 1, i64::from(u32::MAX))?;
            let id = f.required("id", id, "the lease's id from the leases document")?;
            let reason = f.required(
                "reason",
                f.str("reason", "text")?,
                "why it is broken (text)",
            )?;
            if reason.trim().is_empty() || reason.chars().count() > MAX_NOTE_CHARS {
                let expected = format!("1 to {MAX_NOTE_CHARS} characters saying why");
                return Err(f.bad("reason", &expected, &Json::String(reason)));
            }
            Ok(Command::BreakLease {
                id: u32::try_from(id).unwrap_or(u32::MAX),
                reason: reason.to_owned(),
            })
        }
        "procedure" => procedure(&Fields::new(
            "procedure",
            "",
            members,
            &["name", "steps"],
            "",
        )?),
        "procedure_cancel" => {
            let f = Fields::new("procedure_cancel", "", members, &["id"], "")?;
            let id = f.int("id", 1, i64::from(u32::MAX))?;
            let id = f.required("id", id, "the procedure's id from procedure_started")?;
            Ok(Command::ProcedureCancel {
                id: u32::try_from(id).unwrap_or(u32::MAX),
            })
        }
        _ => Err(CommandError::UnknownCmd(
            Quote(&Json::String(cmd)).to_string(),
        )),
    }
}

/// Fields of one step of `procedure`.
const STEP_FIELDS: &[&str] = &[
    "text",
    "light",
    "color",
    "brightness",
    "blink",
    "beep",
    "wait",
    "node",
    "port",
    "mobile",
    "timeout_s",
];
/// What `procedure`'s `steps` accepts.
const STEPS: &str = "an array of 1 to 64 step objects";
/// What a step's `wait` accepts.
const WAIT: &str = "\"docked\" or \"undocked\"";
/// What a step's `text` accepts.
const TEXT: &str = "text of at most 200 characters";

fn procedure(f: &Fields<'_>) -> Result<Command, CommandError> {
    use crate::procedure::{Spec, MAX_STEPS};
    let name_expected = format!("a name of 1 to {MAX_OWNER_CHARS} printable characters");
    let name = f.str("name", &name_expected)?.unwrap_or("procedure");
    if name.trim().is_empty()
        || name.chars().count() > MAX_OWNER_CHARS
        || name.chars().any(char::is_control)
    {
        return Err(f.bad("name", &name_expected, &Json::String(name)));
    }
    let list = f.get("steps").ok_or_else(|| f.missing("steps", STEPS))?;
    let items = match list {
        Json::Array(items) if (1..=MAX_STEPS).contains(&items.len()) => items,
        other => return Err(f.bad("steps", STEPS, other)),
    };
    let mut steps = Vec::with_capacity(items.len());
    for (i, item) in items.iter().enumerate() {
        let in_step = |e: CommandError| match e {
            CommandError::Invalid { cmd, message } => CommandError::Invalid {
                cmd,
                message: format!("step {}: {message}", i + 1),
            },
            other => other,
        };
        let Json::Object(members) = item else {
            return Err(in_step(f.invalid(format!(
                "a step must be an object like {{\"wait\":\"docked\",\"node\":\"111\",\"color\":\"green\"}}; got {}",
                item.kind()
            ))));
        };
        let s = Fields::new("procedure", "step.", members, STEP_FIELDS, "").map_err(in_step)?;
        steps.push(step(&s).map_err(in_step)?);
    }
    let spec = Spec {
        name: name.to_owned(),
        steps,
    };
    if spec.longest() > Duration::from_secs(u64::from(MAX_LEASE_S)) {
        return Err(f.invalid(format!(
            "the steps' timeouts add up to {} s; a procedure may last at most {MAX_LEASE_S} s (its lease's longest)",
            spec.longest().as_secs()
        )));
    }
    Ok(Command::Procedure(Box::new(spec)))
}

/// One element id of a step (`node`, `mobile`).
fn step_node(f: &Fields<'_>, name: &str) -> Result<Option<NodeId>, CommandError> {
    let Some(v) = f.get(name) else {
        return Ok(None);
    };
    match v {
        Json::String(s) => match s.parse::<NodeId>() {
            Ok(id) if id.is_sc() => Ok(Some(id)),
            _ => Err(f.bad(name, NODE_ID, v)),
        },
        _ => Err(f.bad(name, NODE_ID, v)),
    }
}

fn step(f: &Fields<'_>) -> Result<crate::procedure::Step, CommandError> {
    use crate::procedure::{Step, Wait, DEFAULT_STEP_TIMEOUT_S, MAX_STEP_TIMEOUT_S};
    let text = f.str("text", TEXT)?;
    if let Some(t) = text {
        if t.chars().count() > MAX_NOTE_CHARS {
            return Err(f.bad("text", TEXT, &Json::String(t)));
        }
    }
    let node = f.required("node", step_node(f, "node")?, NODE_ID)?;
    let mobile = step_node(f, "mobile")?;
    let port = match f.u8_in("port", 0, 7)? {
        Some(p) => Port::new(p),
        None => None,
    };
    let wait = match f.required("wait", f.str("wait", WAIT)?, WAIT)? {
        "docked" => Wait::Docked { node, port, mobile },
        "undocked" => Wait::Undocked { node, port, mobile },
        other => return Err(f.bad("wait", WAIT, &Json::String(other))),
    };
    let light = match f.get("light") {
        None => vec![node],
        Some(_) => match node_list(f, "light")? {
            FwNodes::List(ids) => ids,
            FwNodes::All => {
                let v = Json::String("all");
                return Err(f.bad("light", "node ids in hex separated by commas", &v));
            }
        },
    };
    let led = match led_pattern(f)? {
        LedCommand::Off => {
            return Err(
                f.invalid("`step.color` must light the elements (a colour other than off)".into())
            )
        }
        led => led,
    };
    let timeout_s = f
        .int("timeout_s", 1, i64::from(MAX_STEP_TIMEOUT_S))?
        .unwrap_or(i64::from(DEFAULT_STEP_TIMEOUT_S));
    Ok(Step {
        text: text.map(str::to_owned),
        light,
        led,
        beep: f.bool("beep")?.unwrap_or(false),
        wait,
        timeout: Duration::from_secs(u64::try_from(timeout_s).unwrap_or(1)),
    })
}

/// Fields of `lease` besides the common ones.
const LEASE_FIELDS: &[&str] = &["owner", "note", "nodes", "seconds"];

/// `seconds` of `lease` and `renew`: required, 1 to [`MAX_LEASE_S`].
fn lease_seconds(f: &Fields<'_>) -> Result<Duration, CommandError> {
    let s = f.int("seconds", 1, i64::from(MAX_LEASE_S))?;
    let expected = format!("an integer 1 to {MAX_LEASE_S}, the lease's time to live");
    let s = f.required("seconds", s, &expected)?;
    Ok(Duration::from_secs(u64::try_from(s).unwrap_or(1)))
}

fn lease(f: &Fields<'_>) -> Result<Command, CommandError> {
    let owner_expected = format!("a name of 1 to {MAX_OWNER_CHARS} printable characters");
    let owner = f.required("owner", f.str("owner", &owner_expected)?, &owner_expected)?;
    let n = owner.chars().count();
    if owner.trim().is_empty() || n > MAX_OWNER_CHARS || owner.chars().any(char::is_control) {
        return Err(f.bad("owner", &owner_expected, &Json::String(owner)));
    }
    let note_expected = format!("text of at most {MAX_NOTE_CHARS} characters");
    let note = f.str("note", &note_expected)?;
    if let Some(n) = note {
        if n.chars().count() > MAX_NOTE_CHARS || n.chars().any(char::is_control) {
            return Err(f.bad("note", &note_expected, &Json::String(n)));
        }
    }
    let scope = match node_list(f, "nodes")? {
        FwNodes::All => Scope::Island,
        FwNodes::List(ids) => Scope::Nodes(ids),
    };
    Ok(Command::Lease {
        owner: owner.to_owned(),
        note: note.map(str::to_owned),
        scope,
        ttl: lease_seconds(f)?,
    })
}

/// `node`: one node, or `"all"`.
fn target(f: &Fields<'_>) -> Result<Target, CommandError> {
    let v = f
        .get("node")
        .ok_or_else(|| f.missing("node", NODE_OR_ALL))?;
    match v {
        Json::String(s) if *s == "all" => Ok(Target::All),
        Json::String(s) => match s.parse::<NodeId>() {
            Ok(id) if id.is_sc() => Ok(Target::Node(id)),
            _ => Err(f.bad("node", NODE_OR_ALL, v)),
        },
        _ => Err(f.bad("node", NODE_OR_ALL, v)),
    }
}

/// Named colours accepted by `led`.
pub const COLOR_NAMES: [(&str, Rgb); 12] = [
    ("red", Rgb::new(255, 0, 0)),
    ("green", Rgb::new(0, 255, 0)),
    ("blue", Rgb::new(0, 0, 255)),
    ("white", Rgb::new(255, 255, 255)),
    ("yellow", Rgb::new(255, 255, 0)),
    ("cyan", Rgb::new(0, 255, 255)),
    ("magenta", Rgb::new(255, 0, 255)),
    ("orange", Rgb::new(255, 128, 0)),
    ("purple", Rgb::new(128, 0, 128)),
    ("pink", Rgb::new(255, 105, 180)),
    ("warmwhite", Rgb::new(255, 180, 107)),
    ("black", Rgb::new(0, 0, 0)),
];

fn color_help() -> String {
    let names: Vec<&str> = COLOR_NAMES.iter().map(|(n, _)| *n).collect();
    format!(
        "a name ({}, off), \"#rrggbb\" or [r, g, b] with 0-255 each",
        names.join(", ")
    )
}

/// `color`; `None` = the colour "off".
fn color(f: &Fields<'_>, v: &Json<'_>) -> Result<Option<Rgb>, CommandError> {
    let bad = || f.bad("color", &color_help(), v);
    match v {
        // Case does not matter; compared in place rather than lowercased into a copy: a colour
        // is read for every LED command.
        Json::String(s) => {
            if s.eq_ignore_ascii_case("off") {
                return Ok(None);
            }
            if let Some(hex) = s.strip_prefix('#') {
                let ch = |i: usize| {
                    hex.get(i..i + 2)
                        .and_then(|h| u8::from_str_radix(h, 16).ok())
                };
                return match (hex.len(), ch(0), ch(2), ch(4)) {
                    (6, Some(r), Some(g), Some(b)) => Ok(Some(Rgb::new(r, g, b))),
                    _ => Err(bad()),
                };
            }
            COLOR_NAMES
                .iter()
                .find(|(n, _)| n.eq_ignore_ascii_case(s))
                .map(|(_, c)| Some(*c))
                .ok_or_else(bad)
        }
        Json::Array(items) if items.len() == 3 => {
            let mut ch = [0u8; 3];
            for (slot, item) in ch.iter_mut().zip(items.iter()) {
                match item {
                    Json::Number(n) => match n.as_u64().and_then(|c| u8::try_from(c).ok()) {
                        Some(c) => *slot = c,
                        None => return Err(bad()),
                    },
                    _ => return Err(bad()),
                }
            }
            Ok(Some(Rgb::new(ch[0], ch[1], ch[2])))
        }
        _ => Err(bad()),
    }
}

fn led(f: &Fields<'_>) -> Result<Command, CommandError> {
    let target = target(f)?;
    Ok(Command::Node {
        target,
        action: NodeAction::Led(led_pattern(f)?),
    })
}

/// `color`, `brightness`, `blink` and `off` of `led` (and of a procedure's step).
fn led_pattern(f: &Fields<'_>) -> Result<LedCommand, CommandError> {
    let brightness = f.u8_in("brightness", 0, 255)?.unwrap_or(255);
    let blink = match f.get("blink") {
        None => None,
        Some(Json::Object(members)) => {
            let b = Fields::new("led", "blink.", members, BLINK_FIELDS, "")?;
            let period = b.required("period_ms", b.duration("period_ms")?, &ms_expected())?;
            let duty = b.u8_in("duty", 1, 99)?.unwrap_or(DEFAULT_DUTY_PCT);
            Some((period, duty))
        }
        Some(other) => return Err(f.bad("blink", BLINK, other)),
    };
    let off = f.bool("off")?;
    // Validate the colour even when `off` wins, so a typo is reported rather than silently ignored.
    let rgb = match f.get("color") {
        Some(v) => color(f, v)?,
        None if off == Some(true) => None,
        None => {
            return Err(f.invalid(format!(
                "missing `color`: {}, or `\"off\": true`",
                color_help()
            )))
        }
    };
    let cmd = match (off, rgb, blink) {
        (Some(true), _, _) | (_, None, _) => LedCommand::Off,
        (_, Some(color), None) => LedCommand::Steady { color, brightness },
        (_, Some(color), Some((period_10ms, duty_pct))) => LedCommand::Blink {
            color,
            brightness,
            period_10ms,
            duty_pct,
        },
    };
    Ok(cmd)
}

fn buzzer(f: &Fields<'_>) -> Result<Command, CommandError> {
    let target = target(f)?;
    let mode = f.required("mode", f.str("mode", MODE)?, MODE)?;
    // Fields a mode does not use are not read (docs/mqtt-api.md: they are ignored).
    let freq = || {
        let f = f.u16_in(
            "freq_hz",
            BuzzerCommand::MIN_FREQ_HZ,
            BuzzerCommand::MAX_FREQ_HZ,
        )?;
        Ok::<_, CommandError>(f.unwrap_or(DEFAULT_FREQ_HZ))
    };
    let cmd = match mode {
        "off" => BuzzerCommand::Off,
        "on" => BuzzerCommand::Continuous { freq_hz: freq()? },
        "pattern" => {
            let need = |name: &str| {
                f.duration(name)?.ok_or_else(|| {
                    f.invalid(format!(
                        "mode \"pattern\" needs `{name}` ({} to {} ms)",
                        ihex_proto::unit::MIN_MS,
                        ihex_proto::unit::MAX_MS
                    ))
                })
            };
            BuzzerCommand::Pattern {
                freq_hz: freq()?,
                on_10ms: need("on_ms")?,
                off_10ms: need("off_ms")?,
                count: f.u8_in("count", 0, 255)?.unwrap_or(0),
            }
        }
        _ => return Err(f.bad("mode", MODE, &Json::String(mode))),
    };
    Ok(Command::Node {
        target,
        action: NodeAction::Buzzer(cmd),
    })
}

fn assign(f: &Fields<'_>) -> Result<Command, CommandError> {
    let uid_text = f.required("uid", f.str("uid", UID)?, UID)?;
    let uid: Uid = uid_text
        .parse()
        .map_err(|_| f.bad("uid", UID, &Json::String(uid_text)))?;
    let new_id_text = f.required("new_id", f.str("new_id", NODE_ID)?, NODE_ID)?;
    let new_id = match new_id_text.parse::<NodeId>() {
        Ok(id) if id.is_sc() => id,
        _ => return Err(f.bad("new_id", NODE_ID, &Json::String(new_id_text))),
    };
    Ok(Command::Assign {
        uid,
        new_id,
        force: f.bool("force")?.unwrap_or(false),
    })
}

/// A firmware image name `fw_update` and an upload may use: 1 to 128 of `A-Za-z0-9._-`, not
/// starting with `.` — a plain file name, never a path.
pub fn is_image_name(name: &str) -> bool {
    !name.is_empty()
        && !name.starts_with('.')
        && name.len() <= 128
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_'))
}

fn fw_update(f: &Fields<'_>) -> Result<Command, CommandError> {
    let image = f.required("image", f.str("image", FW_IMAGE)?, FW_IMAGE)?;
    if !is_image_name(image) {
        return Err(f.bad("image", FW_IMAGE, &Json::String(image)));
    }
    Ok(Command::FwUpdate {
        image: image.to_string(),
        nodes: node_list(f, "nodes")?,
        force: f.bool("force")?.unwrap_or(false),
    })
}

/// `"all"` or node ids separated by commas (`fw_update`'s and `lease`'s `nodes`).
fn node_list(f: &Fields<'_>, name: &str) -> Result<FwNodes, CommandError> {
    let text = f.required(name, f.str(name, FW_NODES)?, FW_NODES)?;
    let bad = || f.bad(name, FW_NODES, &Json::String(text));
    if text == "all" {
        return Ok(FwNodes::All);
    }
    let mut ids = Vec::new();
    for part in text.split(',').map(str::trim) {
        match part.parse::<NodeId>() {
            Ok(id) if id.is_sc() && !ids.contains(&id) => ids.push(id),
            _ => return Err(bad()),
        }
    }
    Ok(FwNodes::List(ids))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fw_update_forms() {
        let r = ok(r#"{"cmd":"fw_update","image":"sc-fw-1.3.0.ihex","nodes":"all"}"#);
        assert_eq!(
            r.command,
            Command::FwUpdate {
                image: "sc-fw-1.3.0.ihex".into(),
                nodes: FwNodes::All,
                force: false
            }
        );
        let r = ok(r#"{"cmd":"fw_update","image":"a.ihex","nodes":"111, 2","force":true}"#);
        let Command::FwUpdate { nodes, force, .. } = r.command else {
            panic!()
        };
        assert_eq!(nodes, FwNodes::List(vec![node_id(0x111), node_id(0x2)]));
        assert!(force);
        for (json, says) in [
            (
                r#"{"cmd":"fw_update","image":"../etc/passwd","nodes":"all"}"#,
                "image",
            ),
            (
                r#"{"cmd":"fw_update","image":".hidden","nodes":"all"}"#,
                "image",
            ),
            (
                r#"{"cmd":"fw_update","image":"a.ihex","nodes":"111,111"}"#,
                "nodes",
            ),
            (
                r#"{"cmd":"fw_update","image":"a.ihex","nodes":"fff"}"#,
                "nodes",
            ),
            (r#"{"cmd":"fw_update","image":"a.ihex"}"#, "nodes"),
            (r#"{"cmd":"fw_update","nodes":"all"}"#, "image"),
        ] {
            let e = err(json.as_bytes()).error.to_string();
            assert!(
                e.starts_with("fw_update: ") && e.contains(says),
                "{json}: {e}"
            );
        }
    }

    fn node_id(raw: u16) -> NodeId {
        NodeId::new_sc(raw).unwrap()
    }

    fn ok(json: &str) -> Request {
        parse(json.as_bytes(), 4096).unwrap_or_else(|r| panic!("{json}: rejected: {}", r.error))
    }

    fn err(json: &[u8]) -> Rejection {
        match parse(json, 4096) {
            Ok(r) => panic!("{}: accepted as {r:?}", String::from_utf8_lossy(json)),
            Err(r) => r,
        }
    }

    fn node(raw: u16) -> Target {
        Target::Node(NodeId::new(raw).unwrap())
    }

    #[test]
    fn led_colour_forms() {
        let r = ok(r#"{"cmd":"led","node":"2","color":"red","request_id":"a"}"#);
        assert_eq!(r.request_id.as_deref(), Some("a"));
        assert_eq!(
            r.command,
            Command::Node {
                target: node(2),
                action: NodeAction::Led(LedCommand::Steady {
                    color: Rgb::new(255, 0, 0),
                    brightness: 255
                })
            }
        );
        let r = ok(r##"{"cmd":"led","node":"ABC","color":"#0A10fF","brightness":7}"##);
        assert_eq!(
            r.command,
            Command::Node {
                target: node(0xabc),
                action: NodeAction::Led(LedCommand::Steady {
                    color: Rgb::new(10, 16, 255),
                    brightness: 7
                })
            }
        );
        let r = ok(r#"{"cmd":"led","node":"all","color":[1,2,3],"blink":{"period_ms":504}}"#);
        assert_eq!(
            r.command,
            Command::Node {
                target: Target::All,
                action: NodeAction::Led(LedCommand::Blink {
                    color: Rgb::new(1, 2, 3),
                    brightness: 255,
                    period_10ms: 50,
                    duty_pct: 50
                })
            }
        );
    }

    #[test]
    fn colours_are_read_in_any_case() {
        let led =
            |color: &str| ok(&format!(r#"{{"cmd":"led","node":"1","color":"{color}"}}"#)).command;
        assert_eq!(led("#FF8000"), led("#ff8000"));
        assert_eq!(led("#Ff8000"), led("#ff8000"));
        assert_eq!(led("RED"), led("red"));
        assert_eq!(led("Red"), led("red"));
        assert_ne!(led("red"), led("#ff8000"));
    }

    #[test]
    fn led_off_forms() {
        let off = Command::Node {
            target: node(1),
            action: NodeAction::Led(LedCommand::Off),
        };
        assert_eq!(ok(r#"{"cmd":"led","node":"1","off":true}"#).command, off);
        assert_eq!(ok(r#"{"cmd":"led","node":"1","color":"OFF"}"#).command, off);
        assert_eq!(
            ok(r#"{"cmd":"led","node":"1","color":"blue","off":true}"#).command,
            off
        );
        // `off: false` is no switch-off: the colour is used.
        assert!(matches!(
            ok(r#"{"cmd":"led","node":"1","color":"blue","off":false}"#).command,
            Command::Node {
                action: NodeAction::Led(LedCommand::Steady { .. }),
                ..
            }
        ));
    }

    #[test]
    fn ms_values_round_to_10ms_within_range() {
        let period = |ms: i64| {
            let json =
                format!(r#"{{"cmd":"led","node":"1","color":"red","blink":{{"period_ms":{ms}}}}}"#);
            match parse(json.as_bytes(), 4096).map(|r| r.command) {
                Ok(Command::Node {
                    action: NodeAction::Led(LedCommand::Blink { period_10ms, .. }),
                    ..
                }) => Ok(period_10ms),
                Ok(other) => panic!("{other:?}"),
                Err(r) => Err(r.error.to_string()),
            }
        };
        assert_eq!(period(10), Ok(1));
        assert_eq!(period(14), Ok(1));
        assert_eq!(period(15), Ok(2));
        assert_eq!(period(2550), Ok(255));
        assert!(period(9).unwrap_err().contains("10 to 2550"));
        assert!(period(2551).unwrap_err().contains("got 2551"));
        assert!(period(-1).is_err());
    }

    #[test]
    fn buzzer_modes() {
        assert_eq!(
            ok(r#"{"cmd":"buzzer","node":"3","mode":"on"}"#).command,
            Command::Node {
                target: node(3),
                action: NodeAction::Buzzer(BuzzerCommand::Continuous {
                    freq_hz: DEFAULT_FREQ_HZ
                })
            }
        );
        assert_eq!(
            ok(r#"{"cmd":"buzzer","node":"3","mode":"pattern","freq_hz":440,"on_ms":100,"off_ms":200,"count":4}"#)
                .command,
            Command::Node {
                target: node(3),
                action: NodeAction::Buzzer(BuzzerCommand::Pattern {
                    freq_hz: 440,
                    on_10ms: 10,
                    off_10ms: 20,
                    count: 4
                })
            }
        );
        assert_eq!(
            ok(r#"{"cmd":"buzzer","node":"3","mode":"off"}"#).command,
            Command::Node {
                target: node(3),
                action: NodeAction::Buzzer(BuzzerCommand::Off)
            }
        );
        let e = err(br#"{"cmd":"buzzer","node":"3","mode":"pattern","on_ms":100}"#);
        assert!(
            e.error.to_string().contains("needs `off_ms`"),
            "{}",
            e.error
        );
        let e = err(br#"{"cmd":"buzzer","node":"3","mode":"on","freq_hz":19}"#);
        assert!(e.error.to_string().contains("20 to 20000"), "{}", e.error);
        let e = err(br#"{"cmd":"buzzer","node":"3","mode":"loud"}"#);
        assert!(e.error.to_string().contains("\"loud\""), "{}", e.error);
    }

    #[test]
    fn power_identify_list_assign() {
        assert_eq!(
            ok(r#"{"cmd":"power","node":"ffd","on":false}"#).command,
            Command::Node {
                target: node(0xffd),
                action: NodeAction::Power(false)
            }
        );
        assert_eq!(
            ok(r#"{"cmd":"identify","node":"2"}"#).command,
            Command::Node {
                target: node(2),
                action: NodeAction::Identify(DEFAULT_IDENTIFY_S)
            }
        );
        assert_eq!(
            ok(r#"{"cmd":"list","request_id":"x"}"#).command,
            Command::List
        );
        let r = ok(r#"{"cmd":"assign","uid":"00112233445566778899AaBb","new_id":"123"}"#);
        assert_eq!(
            r.command,
            Command::Assign {
                uid: Uid([0x00, 0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0x77, 0x88, 0x99, 0xaa, 0xbb]),
                new_id: NodeId::new(0x123).unwrap(),
                force: false
            }
        );
    }

    #[test]
    fn bad_input_matrix_gives_clear_reasons() {
        let cases: &[(&[u8], &str)] = &[
            (b"{not json", "malformed JSON"),
            (b"", "malformed JSON"),
            (b"[1,2]", "got an array"),
            (b"\"led\"", "got a string"),
            (b"null", "got null"),
            (b"\xff\xfe{}", "not valid UTF-8"),
            (br#"{"node":"2"}"#, "missing field `cmd`"),
            (
                br#"{"cmd":"dance","node":"2"}"#,
                "unknown cmd \"dance\"; expected one of: led",
            ),
            (br#"{"cmd":7}"#, "unknown cmd 7"),
            (br#"{"cmd":"led","color":"red"}"#, "led: missing `node`"),
            (
                br#"{"cmd":"led","node":2,"color":"red"}"#,
                "or \"all\"; got 2",
            ),
            (
                br#"{"cmd":"led","node":"0","color":"red"}"#,
                "\"1\" to \"ffd\"",
            ),
            (
                br#"{"cmd":"led","node":"fff","color":"red"}"#,
                "\"1\" to \"ffd\"",
            ),
            (br#"{"cmd":"led","node":"2"}"#, "led: missing `color`"),
            (br#"{"cmd":"led","node":"2","color":"mauve"}"#, "\"mauve\""),
            (br##"{"cmd":"led","node":"2","color":"#12345"}"##, "#rrggbb"),
            (br#"{"cmd":"led","node":"2","color":[1,2]}"#, "[r, g, b]"),
            (br#"{"cmd":"led","node":"2","color":[1,2,256]}"#, "0-255"),
            (
                br#"{"cmd":"led","node":"2","color":"red","brightness":256}"#,
                "`brightness` must be an integer 0 to 255; got 256",
            ),
            (
                br#"{"cmd":"led","node":"2","color":"red","brightness":1.5}"#,
                "must be an integer 0 to 255; got 1.5",
            ),
            (
                br#"{"cmd":"led","node":"2","color":"red","blink":{"period_ms":500,"duty":100}}"#,
                "1 to 99",
            ),
            (
                br#"{"cmd":"led","node":"2","color":"red","colour":"red"}"#,
                "unknown field `colour`",
            ),
            (
                br#"{"cmd":"power","node":"2","on":"yes"}"#,
                "power: `on` must be true or false; got \"yes\"",
            ),
            (br#"{"cmd":"power","node":"2"}"#, "power: missing `on`"),
            (
                br#"{"cmd":"identify","node":"2","seconds":300}"#,
                "0 to 255",
            ),
            (
                br#"{"cmd":"assign","uid":"0011","new_id":"5"}"#,
                "24 hex digits",
            ),
            (
                br#"{"cmd":"assign","uid":"00112233445566778899aabg","new_id":"5"}"#,
                "24 hex digits",
            ),
            (
                br#"{"cmd":"assign","uid":"00112233445566778899aabb","new_id":"ffe"}"#,
                "`new_id`",
            ),
            (
                br#"{"cmd":"assign","node":"2","uid":"00112233445566778899aabb","new_id":"5"}"#,
                "broadcast",
            ),
            (br#"{"cmd":"list","node":"2"}"#, "unknown field `node`"),
            (
                br#"{"cmd":"list","request_id":5}"#,
                "`request_id` must be a string",
            ),
        ];
        for (input, needle) in cases {
            let e = err(input);
            let text = e.error.to_string();
            assert!(
                text.contains(needle),
                "{}: reason {text:?} lacks {needle:?}",
                String::from_utf8_lossy(input)
            );
        }
    }

    /// Repeated keys are refused at every level, never decided by "the last one wins".
    #[test]
    fn duplicate_keys_are_refused_with_a_reason() {
        let cases: &[(&[u8], &str)] = &[
            (
                br#"{"cmd":"power","node":"2","on":true,"on":false}"#,
                "power: duplicate field `on` (each field may appear once)",
            ),
            (
                br#"{"cmd":"led","node":"2","color":"red","blink":{"period_ms":500,"period_ms":100}}"#,
                "led: duplicate field `blink.period_ms` (each field may appear once)",
            ),
            (
                br#"{"cmd":"led","cmd":"led","node":"2","color":"red"}"#,
                "duplicate field `cmd` (each field may appear once)",
            ),
            (
                br#"{"cmd":"list","request_id":"a","request_id":"b"}"#,
                "duplicate field `request_id` (each field may appear once)",
            ),
        ];
        for (input, reason) in cases {
            assert_eq!(err(input).error.to_string(), *reason);
        }
    }

    /// No reason quotes a parser's internals (type names, serde's wording), whatever the value of
    /// whichever field.
    #[test]
    fn reasons_never_leak_parser_internals() {
        let base: &[(&str, &[(&str, &str)])] = &[
            (
                "led",
                &[
                    ("node", r#""2""#),
                    ("color", r#""red""#),
                    ("brightness", "1"),
                    ("blink", r#"{"period_ms":500}"#),
                    ("off", "false"),
                ],
            ),
            (
                "buzzer",
                &[
                    ("node", r#""2""#),
                    ("mode", r#""pattern""#),
                    ("freq_hz", "440"),
                    ("on_ms", "100"),
                    ("off_ms", "100"),
                    ("count", "1"),
                ],
            ),
            ("power", &[("node", r#""2""#), ("on", "true")]),
            ("identify", &[("node", r#""2""#), ("seconds", "1")]),
            (
                "assign",
                &[
                    ("uid", r#""00112233445566778899aabb""#),
                    ("new_id", r#""5""#),
                    ("force", "true"),
                ],
            ),
        ];
        let values = [
            r#""x""#,
            "1.5",
            "-1",
            "[1]",
            "{}",
            "true",
            "1e9",
            "99999999999999999999",
            r#"{"period_ms":"x"}"#,
            r#"{"duty":[]}"#,
        ];
        let mut rejected = 0;
        for (cmd, fields) in base {
            for (field, _) in *fields {
                for value in values {
                    let members: Vec<String> = fields
                        .iter()
                        .map(|(f, v)| format!(r#""{f}":{}"#, if f == field { value } else { v }))
                        .collect();
                    let json = format!(r#"{{"cmd":"{cmd}",{}}}"#, members.join(","));
                    let Err(r) = parse(json.as_bytes(), 4096) else {
                        continue;
                    };
                    rejected += 1;
                    let reason = r.error.to_string();
                    assert!(reason.starts_with(&format!("{cmd}: ")), "{json}: {reason}");
                    for internal in [
                        "invalid type",
                        "expected struct",
                        "Dto",
                        "i64",
                        "u8",
                        "invalid value",
                    ] {
                        assert!(!reason.contains(internal), "{json}: {reason}");
                    }
                }
            }
        }
        assert!(rejected > 150, "only {rejected} inputs were rejected");
    }

    #[test]
    fn request_id_is_kept_on_rejection_when_readable() {
        let e = err(br#"{"cmd":"led","node":"2","request_id":"r9"}"#);
        assert_eq!(e.request_id.as_deref(), Some("r9"));
        let e = err(br#"{"cmd":"led","request_id":5}"#);
        assert_eq!(e.request_id, None);
    }

    #[test]
    fn oversized_payload_is_rejected_before_parsing() {
        let big = format!(r#"{{"cmd":"list","request_id":"{}"}}"#, "x".repeat(100));
        let e = parse(big.as_bytes(), 64).unwrap_err();
        assert_eq!(
            e.error,
            CommandError::TooLarge {
                len: big.len(),
                max: 64
            }
        );
        assert!(parse(big.as_bytes(), big.len()).is_ok());
    }

    #[test]
    fn deeply_nested_json_is_an_error_not_a_crash() {
        let deep = "[".repeat(100_000);
        assert!(matches!(
            parse(deep.as_bytes(), usize::MAX).unwrap_err().error,
            CommandError::Json(_)
        ));
    }
}

#[cfg(test)]
mod doc_tests {
    use super::*;

    const API_DOC: &str = include_str!("../../../../docs/mqtt-api.md");

    /// Every `mosquitto_pub … -m '<json>'` example in docs/mqtt-api.md is a valid command (the
    /// firmware upload publishes a file, `-f`, on its own topic).
    #[test]
    fn every_documented_command_example_parses() {
        let mut n = 0;
        let commands = API_DOC
            .lines()
            .filter(|l| l.starts_with("mosquitto_pub") && !l.contains("/fw/upload/"));
        for line in commands {
            let json = line
                .split("-m '")
                .nth(1)
                .and_then(|s| s.strip_suffix('\''))
                .expect(line);
            if let Err(r) = parse(json.as_bytes(), 4096) {
                panic!("documented example rejected: {json}: {}", r.error);
            }
            n += 1;
        }
        assert!(n >= 10, "found only {n} examples");
    }
}
