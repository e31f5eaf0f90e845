//! JSON commands from `CommandsTopic`: typed DTOs, parsing and validation against the protocol's value
//! ranges, so that nothing out of range ever becomes a frame. Every failure is a [`CommandError`] whose
//! text says what was wrong and what is accepted; parsing never panics, whatever the bytes.

use ihex_proto::{BuzzerCommand, LedCommand, Message, NodeId, Rgb, Seq, Uid};
use serde::de::DeserializeOwned;
use serde::Deserialize;
use serde_json::{Map, Value};

use crate::event::{HexId, Target};

/// Every command name, for error messages.
pub const COMMAND_NAMES: &str = "led, buzzer, power, identify, assign, list";

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
    /// `request_id` present but not a string.
    #[error("`request_id` must be a string; got {0}")]
    RequestId(&'static str),
    /// No `cmd`.
    #[error("missing field `cmd`; expected one of: {COMMAND_NAMES}")]
    MissingCmd,
    /// `cmd` not a string or not a known name.
    #[error("unknown cmd {0}; expected one of: {COMMAND_NAMES}")]
    UnknownCmd(String),
    /// A field is missing, has the wrong type or an out-of-range value.
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
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
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
    /// `list`: publish `node_list`.
    List,
}

impl Command {
    /// The command name.
    pub fn name(&self) -> &'static str {
        match self {
            Command::Node { action, .. } => action.name(),
            Command::Assign { .. } => "assign",
            Command::List => "list",
        }
    }
}

/// A command and its optional request id.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Request {
    /// Echoed in `command_result` / `node_list`.
    pub request_id: Option<String>,
    /// What to do.
    pub command: Command,
}

/// A rejected command: the reason, and the request id if it could be read.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Rejection {
    /// The command's `request_id`, when the payload was an object with a string `request_id`.
    pub request_id: Option<String>,
    /// Why.
    pub error: CommandError,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct LedDto {
    node: String,
    color: Option<Value>,
    brightness: Option<i64>,
    blink: Option<BlinkDto>,
    off: Option<bool>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BlinkDto {
    period_ms: i64,
    duty: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BuzzerDto {
    node: String,
    mode: String,
    freq_hz: Option<i64>,
    on_ms: Option<i64>,
    off_ms: Option<i64>,
    count: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PowerDto {
    node: String,
    on: bool,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct IdentifyDto {
    node: String,
    seconds: Option<i64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct AssignDto {
    uid: String,
    new_id: String,
    force: Option<bool>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ListDto {}

fn type_name(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// Parses and validates one command payload. Node existence is not checked here (the registry is the
/// bridge's); everything else is.
pub fn parse(payload: &[u8], max_bytes: usize) -> Result<Request, Rejection> {
    let reject = |request_id: Option<String>, error| Rejection { request_id, error };
    if payload.len() > max_bytes {
        return Err(reject(
            None,
            CommandError::TooLarge {
                len: payload.len(),
                max: max_bytes,
            },
        ));
    }
    let text = std::str::from_utf8(payload)
        .map_err(|e| reject(None, CommandError::NotUtf8(e.valid_up_to())))?;
    let value: Value =
        serde_json::from_str(text).map_err(|e| reject(None, CommandError::Json(e.to_string())))?;
    let Value::Object(mut map) = value else {
        return Err(reject(None, CommandError::NotObject(type_name(&value))));
    };
    let request_id = match map.remove("request_id") {
        None | Some(Value::Null) => None,
        Some(Value::String(s)) => Some(s),
        Some(other) => return Err(reject(None, CommandError::RequestId(type_name(&other)))),
    };
    let command = parse_object(map).map_err(|error| reject(request_id.clone(), error))?;
    Ok(Request {
        request_id,
        command,
    })
}

fn parse_object(mut map: Map<String, Value>) -> Result<Command, CommandError> {
    let cmd = match map.remove("cmd") {
        None => return Err(CommandError::MissingCmd),
        Some(Value::String(s)) => s,
        Some(other) => return Err(CommandError::UnknownCmd(other.to_string())),
    };
    let rest = Value::Object(map);
    match cmd.as_str() {
        "led" => led(dto("led", rest)?),
        "buzzer" => buzzer(dto("buzzer", rest)?),
        "power" => {
            let d: PowerDto = dto("power", rest)?;
            Ok(Command::Node {
                target: target("power", &d.node)?,
                action: NodeAction::Power(d.on),
            })
        }
        "identify" => {
            let d: IdentifyDto = dto("identify", rest)?;
            let seconds = match d.seconds {
                None => DEFAULT_IDENTIFY_S,
                Some(s) => u8_in("identify", "seconds", s, 0, 255)?,
            };
            Ok(Command::Node {
                target: target("identify", &d.node)?,
                action: NodeAction::Identify(seconds),
            })
        }
        "assign" => assign(dto("assign", rest)?),
        "list" => {
            let _: ListDto = dto("list", rest)?;
            Ok(Command::List)
        }
        _ => Err(CommandError::UnknownCmd(format!("{cmd:?}"))),
    }
}

fn dto<T: DeserializeOwned>(cmd: &'static str, v: Value) -> Result<T, CommandError> {
    serde_json::from_value(v).map_err(|e| {
        let mut message = e.to_string();
        if cmd == "assign" && message.contains("unknown field `node`") {
            message.push_str(" (assign is broadcast and selects the board by its `uid`)");
        }
        CommandError::Invalid { cmd, message }
    })
}

fn invalid(cmd: &'static str, message: String) -> CommandError {
    CommandError::Invalid { cmd, message }
}

fn target(cmd: &'static str, node: &str) -> Result<Target, CommandError> {
    if node == "all" {
        return Ok(Target::All);
    }
    match node.parse::<NodeId>() {
        Ok(id) if id.is_sc() => Ok(Target::Node(id)),
        _ => Err(invalid(
            cmd,
            format!("`node` must be a node id in hex, \"1\" to \"ffd\", or \"all\"; got {node:?}"),
        )),
    }
}

fn u8_in(cmd: &'static str, field: &str, v: i64, lo: u8, hi: u8) -> Result<u8, CommandError> {
    if v < i64::from(lo) || v > i64::from(hi) {
        return Err(invalid(
            cmd,
            format!("`{field}` must be {lo} to {hi}; got {v}"),
        ));
    }
    Ok(v as u8)
}

/// A duration in ms to the protocol's 10 ms units: 10–2550 ms accepted, rounded to the nearest 10 ms.
fn ms_to_10ms(cmd: &'static str, field: &str, ms: i64) -> Result<u8, CommandError> {
    u32::try_from(ms)
        .ok()
        .and_then(ihex_proto::unit::from_ms)
        .ok_or_else(|| {
            invalid(
                cmd,
                format!(
                    "`{field}` must be {} to {} (ms, rounded to the nearest 10 ms); got {ms}",
                    ihex_proto::unit::MIN_MS,
                    ihex_proto::unit::MAX_MS
                ),
            )
        })
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

/// `None` = the colour "off".
fn color(v: &Value) -> Result<Option<Rgb>, CommandError> {
    let bad = |got: String| {
        invalid(
            "led",
            format!("`color` must be {}; got {got}", color_help()),
        )
    };
    match v {
        Value::String(s) => {
            let lower = s.to_ascii_lowercase();
            if lower == "off" {
                return Ok(None);
            }
            if let Some(hex) = lower.strip_prefix('#') {
                if hex.len() == 6 && hex.bytes().all(|b| b.is_ascii_hexdigit()) {
                    let ch = |i: usize| u8::from_str_radix(&hex[i..i + 2], 16).unwrap_or(0);
                    return Ok(Some(Rgb::new(ch(0), ch(2), ch(4))));
                }
                return Err(bad(format!("{s:?}")));
            }
            COLOR_NAMES
                .iter()
                .find(|(n, _)| *n == lower)
                .map(|(_, c)| Some(*c))
                .ok_or_else(|| bad(format!("{s:?}")))
        }
        Value::Array(items) if items.len() == 3 => {
            let mut ch = [0u8; 3];
            for (slot, item) in ch.iter_mut().zip(items) {
                match item.as_i64() {
                    Some(n) if (0..=255).contains(&n) => *slot = n as u8,
                    _ => return Err(bad(v.to_string())),
                }
            }
            Ok(Some(Rgb::new(ch[0], ch[1], ch[2])))
        }
        other => Err(bad(other.to_string())),
    }
}

fn led(d: LedDto) -> Result<Command, CommandError> {
    let target = target("led", &d.node)?;
    let brightness = match d.brightness {
        None => 255,
        Some(b) => u8_in("led", "brightness", b, 0, 255)?,
    };
    let blink = match &d.blink {
        None => None,
        Some(b) => {
            let period = ms_to_10ms("led", "blink.period_ms", b.period_ms)?;
            let duty = match b.duty {
                None => DEFAULT_DUTY_PCT,
                Some(v) => u8_in("led", "blink.duty", v, 1, 99)?,
            };
            Some((period, duty))
        }
    };
    // Validate the colour even when `off` wins, so a typo is reported rather than silently ignored.
    let rgb = match &d.color {
        Some(v) => color(v)?,
        None if d.off == Some(true) => None,
        None => {
            return Err(invalid(
                "led",
                format!("missing `color` ({}) or `\"off\": true`", color_help()),
            ))
        }
    };
    let cmd = match (d.off, rgb, blink) {
        (Some(true), _, _) | (_, None, _) => LedCommand::Off,
        (_, Some(color), None) => LedCommand::Steady { color, brightness },
        (_, Some(color), Some((period_10ms, duty_pct))) => LedCommand::Blink {
            color,
            brightness,
            period_10ms,
            duty_pct,
        },
    };
    Ok(Command::Node {
        target,
        action: NodeAction::Led(cmd),
    })
}

fn buzzer(d: BuzzerDto) -> Result<Command, CommandError> {
    let target = target("buzzer", &d.node)?;
    let freq = || -> Result<u16, CommandError> {
        match d.freq_hz {
            None => Ok(DEFAULT_FREQ_HZ),
            Some(f)
                if (i64::from(BuzzerCommand::MIN_FREQ_HZ)
                    ..=i64::from(BuzzerCommand::MAX_FREQ_HZ))
                    .contains(&f) =>
            {
                Ok(f as u16)
            }
            Some(f) => Err(invalid(
                "buzzer",
                format!(
                    "`freq_hz` must be {} to {}; got {f}",
                    BuzzerCommand::MIN_FREQ_HZ,
                    BuzzerCommand::MAX_FREQ_HZ
                ),
            )),
        }
    };
    let cmd = match d.mode.as_str() {
        "off" => BuzzerCommand::Off,
        "on" => BuzzerCommand::Continuous { freq_hz: freq()? },
        "pattern" => {
            let need = |field: &str, v: Option<i64>| {
                v.ok_or_else(|| {
                    invalid(
                        "buzzer",
                        format!("mode \"pattern\" needs `{field}` (10 to 2550 ms)"),
                    )
                })
            };
            BuzzerCommand::Pattern {
                freq_hz: freq()?,
                on_10ms: ms_to_10ms("buzzer", "on_ms", need("on_ms", d.on_ms)?)?,
                off_10ms: ms_to_10ms("buzzer", "off_ms", need("off_ms", d.off_ms)?)?,
                count: match d.count {
                    None => 0,
                    Some(c) => u8_in("buzzer", "count", c, 0, 255)?,
                },
            }
        }
        other => {
            return Err(invalid(
                "buzzer",
                format!("`mode` must be \"off\", \"on\" or \"pattern\"; got {other:?}"),
            ))
        }
    };
    Ok(Command::Node {
        target,
        action: NodeAction::Buzzer(cmd),
    })
}

fn assign(d: AssignDto) -> Result<Command, CommandError> {
    let uid: Uid = d
        .uid
        .parse()
        .map_err(|e| invalid("assign", format!("`uid`: {e}; got {:?}", d.uid)))?;
    let new_id = match d.new_id.parse::<NodeId>() {
        Ok(id) if id.is_sc() => id,
        _ => {
            return Err(invalid(
                "assign",
                format!(
                    "`new_id` must be a node id in hex, \"1\" to \"ffd\"; got {:?}",
                    d.new_id
                ),
            ))
        }
    };
    Ok(Command::Assign {
        uid,
        new_id,
        force: d.force.unwrap_or(false),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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
            (br#"{"cmd":"led","color":"red"}"#, "missing field `node`"),
            (
                br#"{"cmd":"led","node":2,"color":"red"}"#,
                "expected a string",
            ),
            (
                br#"{"cmd":"led","node":"0","color":"red"}"#,
                "\"1\" to \"ffd\"",
            ),
            (
                br#"{"cmd":"led","node":"fff","color":"red"}"#,
                "\"1\" to \"ffd\"",
            ),
            (br#"{"cmd":"led","node":"2"}"#, "missing `color`"),
            (br#"{"cmd":"led","node":"2","color":"mauve"}"#, "\"mauve\""),
            (br##"{"cmd":"led","node":"2","color":"#12345"}"##, "#rrggbb"),
            (br#"{"cmd":"led","node":"2","color":[1,2]}"#, "[r, g, b]"),
            (br#"{"cmd":"led","node":"2","color":[1,2,256]}"#, "0-255"),
            (
                br#"{"cmd":"led","node":"2","color":"red","brightness":256}"#,
                "`brightness` must be 0 to 255",
            ),
            (
                br#"{"cmd":"led","node":"2","color":"red","brightness":1.5}"#,
                "floating point",
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
                "expected a boolean",
            ),
            (br#"{"cmd":"power","node":"2"}"#, "missing field `on`"),
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

    const API_DOC: &str = include_str!("../../../docs/mqtt-api.md");

    /// Every `mosquitto_pub … -m '<json>'` example in docs/mqtt-api.md is a valid command.
    #[test]
    fn every_documented_command_example_parses() {
        let mut n = 0;
        for line in API_DOC.lines().filter(|l| l.starts_with("mosquitto_pub")) {
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

    /// The rejection reasons quoted in docs/mqtt-api.md are the real ones.
    #[test]
    fn documented_rejection_reasons_are_real() {
        let cases: &[&[u8]] = &[
            br#"{"cmd":"led","node":"2","color":"red","brightness":300,"request_id":"r9"}"#,
            br#"{"cmd":"led","node""#,
            br#"{"cmd":"dance"}"#,
            br#"{"cmd":"led","node":"2","colour":"red"}"#,
            br#"{"cmd":"buzzer","node":"2","mode":"pattern","on_ms":100}"#,
        ];
        let missing: Vec<String> = cases
            .iter()
            .map(|input| parse(input, 4096).unwrap_err().error.to_string())
            .filter(|reason| !API_DOC.contains(reason.as_str()))
            .collect();
        assert!(missing.is_empty(), "docs lack the reasons {missing:#?}");
    }
}
