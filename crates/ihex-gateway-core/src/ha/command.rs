//! Commands from Home Assistant: a payload on an entity's command topic becomes the same
//! [`Command`] the JSON API gives, so it takes the same path (node check, sequence number, ack,
//! `command_result`). Parsing follows the JSON API's rules — one pass, every field typed and
//! range-checked, unknown or repeated fields refused, reasons in the API's words — with the Home
//! Assistant platform's name (`light`, `switch`, `siren`, `button`) where a JSON command names its
//! `cmd`.
//!
//! What each entity accepts is what Home Assistant sends for it:
//! - `led` (JSON-schema light): `{"state":"ON"|"OFF","color":{"r","g","b"},"brightness":0-255,
//!   "effect":"off"|"blink"}`. A field left out keeps what the node last acknowledged (Home
//!   Assistant sends only what changes), else white, full brightness, steady.
//! - `relay` (switch): `ON` or `OFF`.
//! - `buzzer` (siren): `{"state":"ON"|"OFF","tone":…,"duration":seconds}` with the tones of
//!   [`TONES`]; a duration counts beeps, so it needs a beeping tone.
//! - `identify` (button): `PRESS`, an identify of [`DEFAULT_IDENTIFY_S`] seconds.

use ihex_proto::{unit, BuzzerCommand, LedCommand, NodeId, Rgb};

use super::light::{EFFECTS, EFFECT_BLINK, EFFECT_OFF};
use super::topic::{Entity, HaTopics};
use crate::command::field::Fields;
use crate::command::json::{Arena, Json, Quote};
use crate::command::{
    Command, CommandError, NodeAction, Rejection, Request, DEFAULT_DUTY_PCT, DEFAULT_FREQ_HZ,
    DEFAULT_IDENTIFY_S,
};
use crate::event::Target;

/// The `request_id` of every command from Home Assistant, echoed in its `command_result`.
pub const REQUEST_ID: &str = "homeassistant";

/// The siren's tones: name, and beep length and pause in ms (`None`: a continuous tone).
pub const TONES: [(&str, Option<(u16, u16)>); 3] = [
    ("continuous", None),
    ("beep", Some((200, 800))),
    ("fast_beep", Some((100, 100))),
];

/// Blink period of the `blink` effect when the strip was not blinking already, ms.
pub const BLINK_PERIOD_MS: u16 = 500;

const STATE: &str = "\"ON\" or \"OFF\"";
const COLOR: &str = "an object like {\"r\":255,\"g\":0,\"b\":0}";
const CHANNEL: &str = "an integer 0 to 255";
const LIGHT_FIELDS: &[&str] = &["state", "color", "brightness", "effect"];
const COLOR_FIELDS: &[&str] = &["r", "g", "b"];
const SIREN_FIELDS: &[&str] = &["state", "tone", "duration"];

/// The Home Assistant platform of an entity, as reasons name it.
pub fn platform(entity: Entity) -> &'static str {
    match entity {
        Entity::Led => "light",
        Entity::Relay => "switch",
        Entity::Buzzer => "siren",
        Entity::Identify => "button",
    }
}

/// Parses a message on a command topic into the command it stands for; `led_of` tells the LED
/// command a node last acknowledged (what a light command leaves out keeps).
pub fn parse(
    topics: &HaTopics,
    topic: &str,
    payload: &[u8],
    max_bytes: usize,
    led_of: impl Fn(NodeId) -> Option<LedCommand>,
) -> Result<Request, Rejection> {
    let reject = |error| Rejection {
        request_id: Some(REQUEST_ID.to_owned()),
        error,
    };
    let (id, entity) = target(topics, topic).map_err(reject)?;
    if payload.len() > max_bytes {
        return Err(reject(CommandError::TooLarge {
            len: payload.len(),
            max: max_bytes,
        }));
    }
    let text =
        std::str::from_utf8(payload).map_err(|e| reject(CommandError::NotUtf8(e.valid_up_to())))?;
    let action = match entity {
        Entity::Led => light(text, led_of(id)).map(NodeAction::Led),
        Entity::Relay => {
            word(platform(entity), text, &["ON", "OFF"]).map(|w| NodeAction::Power(w == "ON"))
        }
        Entity::Buzzer => siren(text).map(NodeAction::Buzzer),
        Entity::Identify => word(platform(entity), text, &["PRESS"])
            .map(|_| NodeAction::Identify(DEFAULT_IDENTIFY_S)),
    }
    .map_err(reject)?;
    Ok(Request {
        request_id: Some(REQUEST_ID.to_owned()),
        // Home Assistant's commands carry no time limit, and no lease token: a leased element
        // refuses them.
        ttl: None,
        lease: None,
        user: None,
        command: Command::Node {
            target: Target::Node(id),
            action,
        },
    })
}

/// The node and entity a command topic names.
fn target(topics: &HaTopics, topic: &str) -> Result<(NodeId, Entity), CommandError> {
    let invalid = |message: String| CommandError::Invalid {
        cmd: "homeassistant",
        message,
    };
    let entities: Vec<&str> = Entity::ALL.iter().map(|e| e.name()).collect();
    let (node, entity) = topics.parse_command(topic).ok_or_else(|| {
        invalid(format!(
            "{topic} is not a command topic of this gateway; expected {}/<node>/<entity>/set",
            topics.root
        ))
    })?;
    let id = match node.parse::<NodeId>() {
        Ok(id) if id.is_sc() => id,
        _ => {
            return Err(invalid(format!(
                "`{node}` in {topic} is not a node id in hex, \"1\" to \"ffd\""
            )))
        }
    };
    let entity = Entity::ALL
        .into_iter()
        .find(|e| e.name() == entity)
        .ok_or_else(|| {
            invalid(format!(
                "unknown entity `{entity}` in {topic}; expected one of: {}",
                entities.join(", ")
            ))
        })?;
    Ok((id, entity))
}

/// A plain payload that must be one of `words`.
fn word<'a>(cmd: &'static str, text: &str, words: &[&'a str]) -> Result<&'a str, CommandError> {
    words
        .iter()
        .find(|w| **w == text)
        .copied()
        .ok_or_else(|| CommandError::Invalid {
            cmd,
            message: format!(
                "the payload must be {}; got {}",
                words.join(" or "),
                Quote(&Json::String(text))
            ),
        })
}

/// The members of a JSON object payload.
fn object<'a>(
    cmd: &'static str,
    text: &'a str,
    example: &str,
    arena: &'a mut Arena,
) -> Result<&'a [(&'a str, Json<'a>)], CommandError> {
    // Home Assistant's commands are a person's clicks: an arena of their own each.
    match arena
        .parse(text)
        .map_err(|e| CommandError::Json(e.to_string()))?
    {
        Json::Object(members) => Ok(members),
        other => Err(CommandError::Invalid {
            cmd,
            message: format!(
                "the payload must be a JSON object like {example}; got {}",
                other.kind()
            ),
        }),
    }
}

fn light(text: &str, current: Option<LedCommand>) -> Result<LedCommand, CommandError> {
    let mut arena = Arena::default();
    let members = object("light", text, r#"{"state":"ON"}"#, &mut arena)?;
    let f = Fields::object("light", members, LIGHT_FIELDS)?;
    let state = f.required("state", f.str("state", STATE)?, STATE)?;
    let color = match f.get("color") {
        None => None,
        Some(Json::Object(channels)) => {
            let c = Fields::new("light", "color.", channels, COLOR_FIELDS, "")?;
            let ch = |name: &str| c.required(name, c.u8_in(name, 0, 255)?, CHANNEL);
            Some(Rgb::new(ch("r")?, ch("g")?, ch("b")?))
        }
        Some(other) => return Err(f.bad("color", COLOR, other)),
    };
    let brightness = f.u8_in("brightness", 0, 255)?;
    let effects = format!("\"{}\"", EFFECTS.join("\" or \""));
    let effect = match f.str("effect", &effects)? {
        None => None,
        Some(e) if EFFECTS.contains(&e) => Some(e),
        Some(e) => return Err(f.bad("effect", &effects, &Json::String(e))),
    };
    match state {
        "OFF" => return Ok(LedCommand::Off),
        "ON" => {}
        other => return Err(f.bad("state", STATE, &Json::String(other))),
    }
    let (was_color, was_brightness, was_blink) = match current {
        Some(LedCommand::Steady { color, brightness }) => (Some(color), Some(brightness), None),
        Some(LedCommand::Blink {
            color,
            brightness,
            period_10ms,
            duty_pct,
        }) => (Some(color), Some(brightness), Some((period_10ms, duty_pct))),
        Some(LedCommand::Off) | None => (None, None, None),
    };
    let color = color.or(was_color).unwrap_or(Rgb::new(255, 255, 255));
    let brightness = brightness.or(was_brightness).unwrap_or(255);
    let blink = match effect {
        Some(EFFECT_OFF) => None,
        Some(EFFECT_BLINK) => Some(was_blink.unwrap_or(default_blink())),
        _ => was_blink,
    };
    Ok(match blink {
        None => LedCommand::Steady { color, brightness },
        Some((period_10ms, duty_pct)) => LedCommand::Blink {
            color,
            brightness,
            period_10ms,
            duty_pct,
        },
    })
}

/// The `blink` effect's period and duty cycle, in the protocol's units.
fn default_blink() -> (u8, u8) {
    let period = unit::from_ms(u32::from(BLINK_PERIOD_MS)).unwrap_or(u8::MAX);
    (period, DEFAULT_DUTY_PCT)
}

fn siren(text: &str) -> Result<BuzzerCommand, CommandError> {
    let mut arena = Arena::default();
    let example = r#"{"state":"ON","tone":"beep","duration":5}"#;
    let members = object("siren", text, example, &mut arena)?;
    let f = Fields::object("siren", members, SIREN_FIELDS)?;
    let state = f.required("state", f.str("state", STATE)?, STATE)?;
    let names: Vec<&str> = TONES.iter().map(|(n, _)| *n).collect();
    let tones = format!("one of: {}", names.join(", "));
    let tone = match f.str("tone", &tones)? {
        None => TONES[0],
        Some(t) => *TONES
            .iter()
            .find(|(n, _)| *n == t)
            .ok_or_else(|| f.bad("tone", &tones, &Json::String(t)))?,
    };
    let cmd = match (tone, f.get("duration")) {
        ((_, None), Some(_)) => {
            let beeping: Vec<&str> = TONES
                .iter()
                .filter(|(_, b)| b.is_some())
                .map(|(n, _)| *n)
                .collect();
            return Err(f.invalid(format!(
                "`duration` needs a beeping tone ({}); the continuous tone sounds until it is \
                 turned off",
                beeping.join(", ")
            )));
        }
        ((_, None), None) => BuzzerCommand::Continuous {
            freq_hz: DEFAULT_FREQ_HZ,
        },
        ((name, Some((on_ms, off_ms))), _) => {
            // A duration is a number of beeps: as many whole periods as fit, at most 255.
            let period_ms = i64::from(on_ms) + i64::from(off_ms);
            let max_s = 255 * period_ms / 1000;
            let count = match f.int("duration", 1, max_s).map_err(|_| {
                let expected = format!("an integer 1 to {max_s} (seconds) for tone {name}");
                f.bad(
                    "duration",
                    &expected,
                    f.get("duration").unwrap_or(&Json::Null),
                )
            })? {
                None => 0,
                Some(s) => u8::try_from((s * 1000 / period_ms).max(1)).unwrap_or(u8::MAX),
            };
            let units = |ms: u16| unit::from_ms(u32::from(ms)).unwrap_or(u8::MAX);
            BuzzerCommand::Pattern {
                freq_hz: DEFAULT_FREQ_HZ,
                on_10ms: units(on_ms),
                off_10ms: units(off_ms),
                count,
            }
        }
    };
    match state {
        "OFF" => Ok(BuzzerCommand::Off),
        "ON" => Ok(cmd),
        other => Err(f.bad("state", STATE, &Json::String(other))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::test_util::id;

    fn topics() -> HaTopics {
        HaTopics::defaults(Some("lab"))
    }

    fn parse_with(
        entity: &str,
        payload: &str,
        current: Option<LedCommand>,
    ) -> Result<NodeAction, String> {
        let topic = format!("lab/ihex/ha/111/{entity}/set");
        match parse(&topics(), &topic, payload.as_bytes(), 4096, |n| {
            assert_eq!(n, id(0x111));
            current
        }) {
            Ok(r) => {
                assert_eq!(r.request_id.as_deref(), Some(REQUEST_ID));
                let Command::Node { target, action } = r.command else {
                    panic!("{r:?}")
                };
                assert_eq!(target, Target::Node(id(0x111)));
                Ok(action)
            }
            Err(r) => {
                assert_eq!(r.request_id.as_deref(), Some(REQUEST_ID));
                Err(r.error.to_string())
            }
        }
    }

    fn ok(entity: &str, payload: &str) -> NodeAction {
        parse_with(entity, payload, None).unwrap_or_else(|e| panic!("{payload}: {e}"))
    }

    fn err(entity: &str, payload: &str) -> String {
        match parse_with(entity, payload, None) {
            Ok(a) => panic!("{payload}: accepted as {a:?}"),
            Err(e) => e,
        }
    }

    #[test]
    fn the_documented_light_command_is_red_at_half_brightness() {
        assert_eq!(
            ok(
                "led",
                r#"{"state":"ON","color":{"r":255,"g":0,"b":0},"brightness":128}"#
            ),
            NodeAction::Led(LedCommand::Steady {
                color: Rgb::new(255, 0, 0),
                brightness: 128
            })
        );
        assert_eq!(
            ok("led", r#"{"state":"OFF"}"#),
            NodeAction::Led(LedCommand::Off)
        );
    }

    #[test]
    fn what_a_light_command_leaves_out_keeps_the_acknowledged_state() {
        let blinking = LedCommand::Blink {
            color: Rgb::new(1, 2, 3),
            brightness: 9,
            period_10ms: 20,
            duty_pct: 30,
        };
        // Only brightness: colour and blink stay.
        assert_eq!(
            parse_with("led", r#"{"state":"ON","brightness":200}"#, Some(blinking)),
            Ok(NodeAction::Led(LedCommand::Blink {
                color: Rgb::new(1, 2, 3),
                brightness: 200,
                period_10ms: 20,
                duty_pct: 30
            }))
        );
        // The "off" effect stops the blink, keeping colour and brightness.
        assert_eq!(
            parse_with("led", r#"{"state":"ON","effect":"off"}"#, Some(blinking)),
            Ok(NodeAction::Led(LedCommand::Steady {
                color: Rgb::new(1, 2, 3),
                brightness: 9
            }))
        );
        // From nothing known: white, full brightness; "blink" starts the default blink.
        assert_eq!(
            parse_with(
                "led",
                r#"{"state":"ON","effect":"blink"}"#,
                Some(LedCommand::Off)
            ),
            Ok(NodeAction::Led(LedCommand::Blink {
                color: Rgb::new(255, 255, 255),
                brightness: 255,
                period_10ms: 50,
                duty_pct: DEFAULT_DUTY_PCT
            }))
        );
    }

    #[test]
    fn switch_siren_and_button() {
        assert_eq!(ok("relay", "ON"), NodeAction::Power(true));
        assert_eq!(ok("relay", "OFF"), NodeAction::Power(false));
        assert_eq!(
            ok("identify", "PRESS"),
            NodeAction::Identify(DEFAULT_IDENTIFY_S)
        );
        assert_eq!(
            ok("buzzer", r#"{"state":"ON"}"#),
            NodeAction::Buzzer(BuzzerCommand::Continuous { freq_hz: 2000 })
        );
        assert_eq!(
            ok("buzzer", r#"{"state":"ON","tone":"beep","duration":5}"#),
            NodeAction::Buzzer(BuzzerCommand::Pattern {
                freq_hz: 2000,
                on_10ms: 20,
                off_10ms: 80,
                count: 5
            })
        );
        assert_eq!(
            ok(
                "buzzer",
                r#"{"state":"ON","tone":"fast_beep","duration":2}"#
            ),
            NodeAction::Buzzer(BuzzerCommand::Pattern {
                freq_hz: 2000,
                on_10ms: 10,
                off_10ms: 10,
                count: 10
            })
        );
        assert_eq!(
            ok("buzzer", r#"{"state":"ON","tone":"beep"}"#),
            NodeAction::Buzzer(BuzzerCommand::Pattern {
                freq_hz: 2000,
                on_10ms: 20,
                off_10ms: 80,
                count: 0
            })
        );
        assert_eq!(
            ok("buzzer", r#"{"state":"OFF"}"#),
            NodeAction::Buzzer(BuzzerCommand::Off)
        );
    }

    #[test]
    fn bad_payloads_are_refused_with_a_reason() {
        for (entity, payload, reason) in [
            ("relay", "on", r#"switch: the payload must be ON or OFF; got "on""#),
            ("identify", "", r#"button: the payload must be PRESS; got """#),
            (
                "led",
                r#"{"state":"ON","color":{"h":1,"s":2}}"#,
                "light: unknown field `color.h`; expected one of: r, g, b",
            ),
            (
                "led",
                r#"{"state":"ON","brightness":256}"#,
                "light: `brightness` must be an integer 0 to 255; got 256",
            ),
            (
                "led",
                r#"{"state":"ON","transition":2}"#,
                "light: unknown field `transition`; expected one of: state, color, brightness, effect",
            ),
            (
                "led",
                r#"{"state":"ON","effect":"rainbow"}"#,
                r#"light: `effect` must be "off" or "blink"; got "rainbow""#,
            ),
            ("led", r#"{"brightness":3}"#, r#"light: missing `state`: "ON" or "OFF""#),
            (
                "led",
                r#"{"state":"ON","cmd":"led"}"#,
                "light: unknown field `cmd`; expected one of: state, color, brightness, effect",
            ),
            (
                "led",
                "[1]",
                r#"light: the payload must be a JSON object like {"state":"ON"}; got an array"#,
            ),
            (
                "buzzer",
                r#"{"state":"ON","duration":3}"#,
                "siren: `duration` needs a beeping tone (beep, fast_beep); the continuous tone \
                 sounds until it is turned off",
            ),
            (
                "buzzer",
                r#"{"state":"ON","tone":"fast_beep","duration":52}"#,
                "siren: `duration` must be an integer 1 to 51 (seconds) for tone fast_beep; got 52",
            ),
            (
                "buzzer",
                r#"{"state":"ON","tone":"wail"}"#,
                r#"siren: `tone` must be one of: continuous, beep, fast_beep; got "wail""#,
            ),
            (
                "buzzer",
                r#"{"state":"ON","volume_level":0.5}"#,
                "siren: unknown field `volume_level`; expected one of: state, tone, duration",
            ),
            (
                "docking",
                "x",
                "homeassistant: unknown entity `docking` in lab/ihex/ha/111/docking/set; \
                 expected one of: led, relay, buzzer, identify",
            ),
        ] {
            assert_eq!(err(entity, payload), reason, "{entity} {payload}");
        }
        let r = parse(&topics(), "lab/ihex/ha/fff/led/set", b"{}", 4096, |_| None);
        assert_eq!(
            r.unwrap_err().error.to_string(),
            r#"homeassistant: `fff` in lab/ihex/ha/fff/led/set is not a node id in hex, "1" to "ffd""#
        );
        let r = parse(&topics(), "lab/ihex/ha/1/relay/set", &[b' '; 10], 8, |_| {
            None
        });
        assert_eq!(
            r.unwrap_err().error.to_string(),
            "command is 10 bytes; the limit is 8 bytes"
        );
    }
}
