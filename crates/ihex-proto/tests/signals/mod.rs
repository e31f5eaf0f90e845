//! The typed fields of a message as the signal values a DBC tool should show: the oracle that the
//! schema (`schema.rs`) and cantools (`dbc.rs`) are compared with. Written from the typed
//! `Message` (a match on every variant), never from the schema, so a new kind fails to compile
//! here until its signals are written down.
#![allow(dead_code)]

use ihex_proto::{unit, BuzzerCommand, HealthFlags, LedCommand, Message};

/// One signal as it should decode.
#[derive(Clone, Debug, PartialEq)]
pub struct Expected {
    /// Signal name.
    pub name: &'static str,
    /// Raw value in the data.
    pub raw: u32,
    /// Physical value (raw scaled: ms for the 10 ms fields).
    pub physical: i64,
    /// The value's name, for enumerations that know it.
    pub label: Option<String>,
}

fn n(name: &'static str, raw: impl Into<u32>) -> Expected {
    let raw = raw.into();
    Expected {
        name,
        raw,
        physical: raw.into(),
        label: None,
    }
}

fn ms(name: &'static str, units: u8) -> Expected {
    Expected {
        physical: unit::to_ms(units).into(),
        ..n(name, units)
    }
}

fn named(name: &'static str, raw: impl Into<u32>, label: Option<&str>) -> Expected {
    Expected {
        label: label.map(str::to_string),
        ..n(name, raw)
    }
}

fn uid(first: usize, bytes: &[u8]) -> Vec<Expected> {
    const NAMES: [&str; 12] = [
        "uid_0", "uid_1", "uid_2", "uid_3", "uid_4", "uid_5", "uid_6", "uid_7", "uid_8", "uid_9",
        "uid_10", "uid_11",
    ];
    bytes
        .iter()
        .enumerate()
        .map(|(i, b)| n(NAMES[first + i], *b))
        .collect()
}

/// Every signal of `msg` with the value it must decode to.
pub fn expected(msg: &Message) -> Vec<Expected> {
    match *msg {
        Message::PowerSet { seq, on } => vec![
            n("seq", seq),
            named("on", on, Some(if on { "on" } else { "off" })),
        ],
        Message::Fault { code, arg, detail } => vec![
            named("code", code.to_raw(), code.name()),
            n("arg", arg),
            n("detail", detail),
        ],
        Message::DockDetected { port } | Message::DockRemoved { port } => {
            vec![n("port", port.get())]
        }
        Message::Handshake { port } => vec![n("port", port.get())],
        Message::DockConfirm { seq, port } => vec![n("seq", seq), n("port", port.get())],
        Message::DockRefuse { seq, port, reason } => vec![
            n("seq", seq),
            n("port", port.get()),
            named("reason", reason.to_raw(), reason.name()),
        ],
        Message::Ack {
            kind,
            seq,
            result,
            detail,
        } => vec![
            named("kind", kind as u8, Some(&format!("{kind:?}"))),
            n("seq", seq),
            named("result", result.to_raw(), result.name()),
            n("detail", detail),
        ],
        Message::AssignSelect { uid_head } => uid(0, &uid_head),
        Message::AssignCommit {
            uid_tail,
            new_id,
            seq,
        } => {
            let mut v = uid(8, &uid_tail);
            v.push(n("id", new_id.get()));
            v.push(n("seq", seq));
            v
        }
        Message::AssignReply {
            seq,
            result,
            new_id,
            uid_tail,
        } => {
            let mut v = vec![
                n("seq", seq),
                named("result", result.to_raw(), result.name()),
                n("id", new_id.get()),
            ];
            v.extend(uid(8, &uid_tail));
            v
        }
        Message::BootUp {
            version: (major, minor),
            role,
            ports,
            reset,
        } => {
            let role = match role {
                ihex_proto::BootRole::Static => named("role", 0u8, Some("static")),
                ihex_proto::BootRole::Mobile => named("role", 1u8, Some("mobile")),
            };
            vec![
                n("major", major),
                n("minor", minor),
                role,
                n("ports", ports),
                named("reset", reset.to_raw(), reset.name()),
            ]
        }
        Message::BuzzerSet { seq, cmd } => {
            let (mode, freq, on, off, count) = match cmd {
                BuzzerCommand::Off => (named("mode", 0u8, Some("off")), 0, 0, 0, 0),
                BuzzerCommand::Continuous { freq_hz } => {
                    (named("mode", 1u8, Some("continuous")), freq_hz, 0, 0, 0)
                }
                BuzzerCommand::Pattern {
                    freq_hz,
                    on_10ms,
                    off_10ms,
                    count,
                } => (
                    named("mode", 2u8, Some("pattern")),
                    freq_hz,
                    on_10ms,
                    off_10ms,
                    count,
                ),
            };
            vec![
                n("seq", seq),
                mode,
                n("freq", freq),
                ms("on", on),
                ms("off", off),
                n("count", count),
            ]
        }
        Message::LedSet { seq, cmd } => {
            let (mode, color, brightness, period, duty) = match cmd {
                LedCommand::Off => (named("mode", 0u8, Some("off")), [0; 3], 0, 0, 0),
                LedCommand::Steady { color, brightness } => (
                    named("mode", 1u8, Some("steady")),
                    [color.r, color.g, color.b],
                    brightness,
                    0,
                    0,
                ),
                LedCommand::Blink {
                    color,
                    brightness,
                    period_10ms,
                    duty_pct,
                } => (
                    named("mode", 2u8, Some("blink")),
                    [color.r, color.g, color.b],
                    brightness,
                    period_10ms,
                    duty_pct,
                ),
            };
            vec![
                n("seq", seq),
                mode,
                n("r", color[0]),
                n("g", color[1]),
                n("b", color[2]),
                n("brightness", brightness),
                ms("period", period),
                n("duty", duty),
            ]
        }
        Message::Identify { seq, seconds } => vec![n("seq", seq), n("seconds", seconds)],
        Message::HealthCheck { seq } => vec![n("seq", seq)],
        Message::HealthReply(h) => {
            let flag = |name, mask| n(name, h.flags.contains(mask));
            vec![
                n("seq", h.seq),
                flag("relay", HealthFlags::RELAY),
                flag("led_on", HealthFlags::LED_ON),
                flag("led_blink", HealthFlags::LED_BLINK),
                flag("buzzer", HealthFlags::BUZZER),
                flag("mobile", HealthFlags::MOBILE),
                flag("error_passive", HealthFlags::ERROR_PASSIVE),
                flag("identify", HealthFlags::IDENTIFY),
                n("flag_7", h.flags.0 >> 7),
                n("loops", h.loops),
                n("tec", h.tec),
                n("rec", h.rec),
                n("uptime", h.uptime_s),
            ]
        }
    }
}

/// A multiplexed message for the tests of the multiplexing machinery (no iHEX kind is multiplexed
/// yet): 6 bytes, `part` in byte 0 selects `a` (byte 1) and `b` (bytes 2–5) for part 0, `c`
/// (bytes 1–2) and `d` (bytes 3–5) for parts 1 to 3.
pub fn mux_example() -> ihex_proto::schema::MessageSchema {
    use ihex_proto::schema::{MessageSchema, Mux, Signal};
    const fn sig(name: &'static str, start: u8, bits: u8, mux: Mux) -> Signal {
        Signal {
            name,
            start,
            bits,
            signed: false,
            factor: 1,
            offset: 0,
            unit: "",
            min: 0,
            max: if bits >= 32 {
                u32::MAX
            } else {
                (1 << bits) - 1
            },
            values: &[],
            comment: "example",
            mux,
        }
    }
    static SIGNALS: [Signal; 5] = [
        Signal {
            max: 3,
            values: &[(0, "zero"), (1, "one"), (2, "two"), (3, "three")],
            ..sig("part", 0, 8, Mux::Selector)
        },
        sig("a", 8, 8, Mux::When(&[0])),
        sig("b", 16, 32, Mux::When(&[0])),
        sig("c", 8, 16, Mux::When(&[1, 2, 3])),
        sig("d", 24, 24, Mux::When(&[1, 2, 3])),
    ];
    MessageSchema {
        kind: ihex_proto::Kind::Fault,
        summary: "A multiplexed example",
        signals: &SIGNALS,
    }
}
