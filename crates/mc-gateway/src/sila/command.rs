//! `IslandControl`'s commands as gateway commands: the typed SiLA parameters checked against the
//! feature's constraints and written as the MQTT API's JSON, and the gateway's answer to that JSON
//! (`command_result` or `command_rejected`) read back as the SiLA outcome. No I/O.

use serde_json::{json, Value};

/// One `IslandControl` command with its parameters as the client sent them.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Request {
    /// `SetLight`.
    SetLight {
        /// `ElementId`.
        element: String,
        /// `Color`.
        color: String,
        /// `Brightness`, percent.
        brightness: i64,
        /// `BlinkPeriod`, ms (0: steady).
        blink_period: i64,
        /// `BlinkDuty`, percent.
        blink_duty: i64,
    },
    /// `SetPower`.
    SetPower {
        /// `ElementId`.
        element: String,
        /// `On`.
        on: bool,
    },
    /// `Beep`.
    Beep {
        /// `ElementId`.
        element: String,
        /// `Frequency`, Hz.
        frequency: i64,
        /// `Count`.
        count: i64,
    },
    /// `Identify`.
    Identify {
        /// `ElementId`.
        element: String,
        /// `Seconds`.
        seconds: i64,
    },
}

/// How long one beep and the pause after it last, ms (`Beep` takes a count, the buzzer a pattern).
const BEEP_MS: u64 = 100;

/// Why a command did not do what it asked: the feature's defined execution errors, and the
/// framework's validation error naming a parameter.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Failure {
    /// A parameter outside its constraints.
    Invalid {
        /// The parameter's identifier (`Brightness`).
        parameter: &'static str,
        /// What it accepts and what it got.
        why: String,
    },
    /// `UnknownElement`.
    UnknownElement(String),
    /// `NotAllowed`.
    NotAllowed(String),
    /// `NoAnswer`.
    NoAnswer(String),
    /// `RefusedByNode`.
    RefusedByNode(String),
}

impl Failure {
    /// The defined execution error's identifier, `None` for a validation error.
    pub fn error_identifier(&self) -> Option<&'static str> {
        Some(match self {
            Failure::Invalid { .. } => return None,
            Failure::UnknownElement(_) => "UnknownElement",
            Failure::NotAllowed(_) => "NotAllowed",
            Failure::NoAnswer(_) => "NoAnswer",
            Failure::RefusedByNode(_) => "RefusedByNode",
        })
    }

    /// The message a person reads.
    pub fn message(&self) -> &str {
        match self {
            Failure::Invalid { why, .. } => why,
            Failure::UnknownElement(m)
            | Failure::NotAllowed(m)
            | Failure::NoAnswer(m)
            | Failure::RefusedByNode(m) => m,
        }
    }
}

impl Request {
    /// The command's identifier in the feature.
    pub fn identifier(&self) -> &'static str {
        match self {
            Request::SetLight { .. } => "SetLight",
            Request::SetPower { .. } => "SetPower",
            Request::Beep { .. } => "Beep",
            Request::Identify { .. } => "Identify",
        }
    }

    /// Checks the parameters against the feature's constraints.
    pub fn check(&self) -> Result<(), Failure> {
        let element = match self {
            Request::SetLight { element, .. }
            | Request::SetPower { element, .. }
            | Request::Beep { element, .. }
            | Request::Identify { element, .. } => element,
        };
        if element.is_empty()
            || element.len() > 3
            || !element.bytes().all(|b| b.is_ascii_hexdigit())
        {
            return Err(Failure::Invalid {
                parameter: "ElementId",
                why: format!(
                    "ElementId must be a node ID in hex, \"1\" to \"ffd\"; got {element:?}"
                ),
            });
        }
        match self {
            Request::SetLight {
                brightness,
                blink_period,
                blink_duty,
                ..
            } => {
                range("Brightness", *brightness, 0, 100, "percent")?;
                if *blink_period != 0 {
                    range("BlinkPeriod", *blink_period, 10, 2550, "ms (0: steady)")?;
                }
                range("BlinkDuty", *blink_duty, 1, 99, "percent")
            }
            Request::SetPower { .. } => Ok(()),
            Request::Beep {
                frequency, count, ..
            } => {
                range("Frequency", *frequency, 20, 20000, "Hz")?;
                range("Count", *count, 0, 255, "beeps")
            }
            Request::Identify { seconds, .. } => range("Seconds", *seconds, 0, 255, "s"),
        }
    }

    /// The gateway command, as JSON on the command topic, answered under `request_id`, carrying
    /// the token `lease` when given; call after [`Request::check`].
    pub fn to_json(&self, request_id: &str, lease: Option<&str>) -> String {
        let v = match self {
            Request::SetLight {
                element,
                color,
                brightness,
                blink_period,
                blink_duty,
            } => {
                // Percent to the LED's 0-255, rounded to the nearest step.
                let level = (brightness * 255 + 50) / 100;
                let mut v =
                    json!({"cmd": "led", "node": element, "color": color, "brightness": level});
                if *blink_period != 0 {
                    v["blink"] = json!({"period_ms": blink_period, "duty": blink_duty});
                }
                v
            }
            Request::SetPower { element, on } => {
                json!({"cmd": "power", "node": element, "on": on})
            }
            Request::Beep {
                element, count: 0, ..
            } => json!({"cmd": "buzzer", "node": element, "mode": "off"}),
            Request::Beep {
                element,
                frequency,
                count,
            } => json!({
                "cmd": "buzzer", "node": element, "mode": "pattern", "freq_hz": frequency,
                "on_ms": BEEP_MS, "off_ms": BEEP_MS, "count": count,
            }),
            Request::Identify { element, seconds } => {
                json!({"cmd": "identify", "node": element, "seconds": seconds})
            }
        };
        let mut v = v;
        v["request_id"] = json!(request_id);
        if let Some(token) = lease {
            v["lease"] = json!(token);
        }
        v.to_string()
    }
}

/// `value` within `lo..=hi`, else the validation error naming `parameter`.
fn range(parameter: &'static str, value: i64, lo: i64, hi: i64, unit: &str) -> Result<(), Failure> {
    if (lo..=hi).contains(&value) {
        return Ok(());
    }
    Err(Failure::Invalid {
        parameter,
        why: format!("{parameter} must be {lo} to {hi} {unit}; got {value}"),
    })
}

/// The parameters a `command_rejected` reason can name, by the JSON field the reason quotes.
const FIELDS: [(&str, &str); 7] = [
    ("`color`", "Color"),
    ("`brightness`", "Brightness"),
    ("`blink.period_ms`", "BlinkPeriod"),
    ("`blink.duty`", "BlinkDuty"),
    ("`freq_hz`", "Frequency"),
    ("`count`", "Count"),
    ("`seconds`", "Seconds"),
];

/// The outcome an event published by the gateway gives the command answered under `request_id`;
/// `None` when the event is not its answer.
pub fn outcome(event: &str, request_id: &str) -> Option<Result<(), Failure>> {
    let v: Value = serde_json::from_str(event).ok()?;
    let payload = v.get("payload")?;
    if payload.get("request_id")?.as_str()? != request_id {
        return None;
    }
    let text = |k: &str| payload.get(k).and_then(Value::as_str).unwrap_or_default();
    match v.get("event")?.as_str()? {
        "command_result" => {
            let node = text("node");
            let reason = text("reason");
            Some(match text("result") {
                "ok" => Ok(()),
                "refused" => Err(Failure::RefusedByNode(format!(
                    "element {node} refused the command: {reason}"
                ))),
                "timeout" => Err(Failure::NoAnswer(format!(
                    "element {node} did not answer ({reason}); it may be off, undocked or \
                     unpowered: check the Elements property"
                ))),
                _ => Err(Failure::NoAnswer(format!(
                    "the command to element {node} was not sent on the bus ({reason}): check the \
                     gateway's CAN bus"
                ))),
            })
        }
        "command_rejected" => {
            let reason = text("reason");
            if reason.starts_with("unknown node") {
                return Some(Err(Failure::UnknownElement(format!(
                    "{reason} (the Elements property lists them)"
                ))));
            }
            if let Some((_, parameter)) = FIELDS.iter().find(|(f, _)| reason.contains(f)) {
                return Some(Err(Failure::Invalid {
                    parameter,
                    why: reason.to_owned(),
                }));
            }
            Some(Err(Failure::NotAllowed(reason.to_owned())))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn light(brightness: i64, blink_period: i64) -> Request {
        Request::SetLight {
            element: "111".into(),
            color: "red".into(),
            brightness,
            blink_period,
            blink_duty: 50,
        }
    }

    #[test]
    fn commands_become_the_mqtt_apis_json() {
        assert_eq!(
            light(50, 0).to_json("s1", None),
            r#"{"brightness":128,"cmd":"led","color":"red","node":"111","request_id":"s1"}"#
        );
        assert_eq!(
            light(100, 500).to_json("s2", None),
            r#"{"blink":{"duty":50,"period_ms":500},"brightness":255,"cmd":"led","color":"red","node":"111","request_id":"s2"}"#
        );
        let beep = Request::Beep {
            element: "2".into(),
            frequency: 440,
            count: 3,
        };
        assert_eq!(
            beep.to_json("b", None),
            r#"{"cmd":"buzzer","count":3,"freq_hz":440,"mode":"pattern","node":"2","off_ms":100,"on_ms":100,"request_id":"b"}"#
        );
        let stop = Request::Beep {
            element: "2".into(),
            frequency: 440,
            count: 0,
        };
        assert_eq!(
            stop.to_json("b", None),
            r#"{"cmd":"buzzer","mode":"off","node":"2","request_id":"b"}"#
        );
    }

    #[test]
    fn out_of_range_parameters_name_the_parameter() {
        assert_eq!(light(50, 0).check(), Ok(()));
        let e = light(101, 0).check().unwrap_err();
        assert_eq!(
            e,
            Failure::Invalid {
                parameter: "Brightness",
                why: "Brightness must be 0 to 100 percent; got 101".into()
            }
        );
        assert!(matches!(
            light(50, 5).check(),
            Err(Failure::Invalid {
                parameter: "BlinkPeriod",
                ..
            })
        ));
        let bad_id = Request::Identify {
            element: "1x".into(),
            seconds: 3,
        };
        assert!(matches!(
            bad_id.check(),
            Err(Failure::Invalid {
                parameter: "ElementId",
                ..
            })
        ));
    }

    #[test]
    fn answers_become_outcomes() {
        let ok = r#"{"event":"command_result","payload":{"request_id":"s1","cmd":"led","node":"111","result":"ok","reason":null}}"#;
        assert_eq!(outcome(ok, "s1"), Some(Ok(())));
        assert_eq!(outcome(ok, "s2"), None, "another command's answer");
        let refused = r#"{"event":"command_result","payload":{"request_id":"s1","cmd":"power","node":"2","result":"refused","reason":"unsupported"}}"#;
        assert_eq!(
            outcome(refused, "s1"),
            Some(Err(Failure::RefusedByNode(
                "element 2 refused the command: unsupported".into()
            )))
        );
        let timeout = r#"{"event":"command_result","payload":{"request_id":"s1","cmd":"led","node":"2","result":"timeout","reason":"no ack within 500 ms"}}"#;
        assert!(matches!(
            outcome(timeout, "s1"),
            Some(Err(Failure::NoAnswer(_)))
        ));
        let unknown = r#"{"event":"command_rejected","payload":{"request_id":"s1","reason":"unknown node 5; known: 2, 111"}}"#;
        assert_eq!(
            outcome(unknown, "s1"),
            Some(Err(Failure::UnknownElement(
                "unknown node 5; known: 2, 111 (the Elements property lists them)".into()
            )))
        );
        let color = r#"{"event":"command_rejected","payload":{"request_id":"s1","reason":"led: `color` must be a name; got \"mauve\""}}"#;
        assert!(matches!(
            outcome(color, "s1"),
            Some(Err(Failure::Invalid {
                parameter: "Color",
                ..
            }))
        ));
        let leased = r#"{"event":"command_rejected","payload":{"request_id":"s1","reason":"node 2 is leased to run-42"}}"#;
        assert!(matches!(
            outcome(leased, "s1"),
            Some(Err(Failure::NotAllowed(_)))
        ));
        let other =
            r#"{"event":"node_online","payload":{"id":"2","role":"mobile","first_seen":true}}"#;
        assert_eq!(outcome(other, "s1"), None);
    }
}
