//! The typed fields of a message as the signal values a DBC tool should show: the oracle that the
//! schema (`schema.rs`) and cantools (`dbc.rs`) are compared with. Written from the typed
//! `Message` (a match on every variant), never from the schema, so a new kind fails to compile
//! here until its signals are written down.
#![allow(dead_code)]

use ihex_proto::{
    unit, BootRole, BuzzerCommand, DockPartner, HealthFlags, LedCommand, Message, StateParts,
    StateReport,
};

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
            let mut v = vec![n("seq", seq)];
            v.extend(buzzer(cmd, ["mode", "freq", "on", "off", "count"]));
            v
        }
        Message::LedSet { seq, cmd } => {
            let mut v = vec![n("seq", seq)];
            v.extend(led(
                cmd,
                ["mode", "r", "g", "b", "brightness", "period", "duty"],
            ));
            v
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
        Message::StateQuery { seq, parts } => {
            let mut v = vec![n("seq", seq)];
            v.extend(groups(
                parts,
                ["actuators", "docking", "identity", "parts_unassigned"],
            ));
            v
        }
        Message::StateReport(r) => state_report(&r),
        Message::DockLink { seq, port, partner } => {
            let mut v = vec![n("seq", seq), n("port", port.get())];
            v.extend(dock_partner(partner, ["partner", "partner_port"]));
            v
        }
        Message::FwBegin {
            image_id,
            len,
            force,
        } => vec![
            n("image_id", image_id),
            n("len", len),
            named("force", force, Some(if force { "on" } else { "off" })),
            n("flags_reserved", 0u8),
        ],
        Message::FwEnd { image_id, action } => vec![
            n("image_id", image_id),
            named("action", action.to_raw(), Some(action.name())),
        ],
        Message::FwQuery { image_id } => vec![n("image_id", image_id)],
        Message::FwStatus(st) => vec![
            named("phase", st.phase.to_raw(), st.phase.name()),
            named("reason", st.reason.to_raw(), st.reason.name()),
            n("first_missing", st.first_missing),
            n("run", st.run),
            n("missing", st.missing),
        ],
        Message::FwData { index, data } => {
            let mut v = vec![n("index", index)];
            const NAMES: [&str; 6] = ["data_0", "data_1", "data_2", "data_3", "data_4", "data_5"];
            v.extend(data.iter().zip(NAMES).map(|(b, name)| n(name, *b)));
            v
        }
    }
}

/// The fields of a buzzer command after `seq`, named `names`.
fn buzzer(cmd: BuzzerCommand, names: [&'static str; 5]) -> Vec<Expected> {
    let (mode, freq, on, off, count) = match cmd {
        BuzzerCommand::Off => (named(names[0], 0u8, Some("off")), 0, 0, 0, 0),
        BuzzerCommand::Continuous { freq_hz } => {
            (named(names[0], 1u8, Some("continuous")), freq_hz, 0, 0, 0)
        }
        BuzzerCommand::Pattern {
            freq_hz,
            on_10ms,
            off_10ms,
            count,
        } => (
            named(names[0], 2u8, Some("pattern")),
            freq_hz,
            on_10ms,
            off_10ms,
            count,
        ),
    };
    vec![
        mode,
        n(names[1], freq),
        ms(names[2], on),
        ms(names[3], off),
        n(names[4], count),
    ]
}

/// The fields of an LED command after `seq`, named `names`.
fn led(cmd: LedCommand, names: [&'static str; 7]) -> Vec<Expected> {
    let (mode, color, brightness, period, duty) = match cmd {
        LedCommand::Off => (named(names[0], 0u8, Some("off")), [0; 3], 0, 0, 0),
        LedCommand::Steady { color, brightness } => (
            named(names[0], 1u8, Some("steady")),
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
            named(names[0], 2u8, Some("blink")),
            [color.r, color.g, color.b],
            brightness,
            period_10ms,
            duty_pct,
        ),
    };
    vec![
        mode,
        n(names[1], color[0]),
        n(names[2], color[1]),
        n(names[3], color[2]),
        n(names[4], brightness),
        ms(names[5], period),
        n(names[6], duty),
    ]
}

/// A state-groups bitmap: bits 0, 1, 2 and bits 3 to 7 as one number.
fn groups(parts: StateParts, names: [&'static str; 4]) -> Vec<Expected> {
    vec![
        n(names[0], parts.0 & 1),
        n(names[1], (parts.0 >> 1) & 1),
        n(names[2], (parts.0 >> 2) & 1),
        n(names[3], parts.0 >> 3),
    ]
}

/// A dock partner: its node ID and port, 0xFFF and 0 for none.
fn dock_partner(partner: Option<DockPartner>, names: [&'static str; 2]) -> Vec<Expected> {
    let (node, port) = partner.map_or((0xFFF, 0), |p| (p.node.get(), p.port.get()));
    vec![n(names[0], node), n(names[1], port)]
}

fn bytes(names: &[&'static str], bytes: &[u8]) -> Vec<Expected> {
    assert_eq!(names.len(), bytes.len());
    names
        .iter()
        .zip(bytes)
        .map(|(name, b)| n(name, *b))
        .collect()
}

/// A state report: `part` with its name, then the fields of that part.
fn state_report(r: &StateReport) -> Vec<Expected> {
    let part = r.part();
    let label = match r {
        StateReport::Led(_) => Some("led".to_string()),
        StateReport::Buzzer(_) => Some("buzzer".into()),
        StateReport::Power(_) => Some("power".into()),
        StateReport::Dock { port, .. } => Some(format!("dock_{}", port.get())),
        StateReport::Firmware { .. } => Some("firmware".into()),
        StateReport::ImageHash(_) => Some("image_hash".into()),
        StateReport::UidLow(_) => Some("uid_low".into()),
        StateReport::UidHigh(_) => Some("uid_high".into()),
        StateReport::Protocol { .. } => Some("protocol".into()),
        StateReport::End { .. } => Some("end".into()),
        StateReport::Other { .. } => None,
    };
    let mut v = vec![named("part", part, label.as_deref())];
    match *r {
        StateReport::Led(cmd) => v.extend(led(
            cmd,
            [
                "led_mode",
                "led_r",
                "led_g",
                "led_b",
                "led_brightness",
                "led_period",
                "led_duty",
            ],
        )),
        StateReport::Buzzer(cmd) => {
            v.extend(buzzer(
                cmd,
                [
                    "buzzer_mode",
                    "buzzer_freq",
                    "buzzer_on",
                    "buzzer_off",
                    "buzzer_count",
                ],
            ));
            v.push(n("buzzer_reserved", 0u8));
        }
        StateReport::Power(p) => v.extend([
            named(
                "power_relay",
                p.relay,
                Some(if p.relay { "on" } else { "off" }),
            ),
            n("power_loops", p.loops),
            n("power_confirmed", p.confirmed),
            n("power_identify", p.identify_s),
            match p.role {
                BootRole::Static => named("power_role", 0u8, Some("static")),
                BootRole::Mobile => named("power_role", 1u8, Some("mobile")),
            },
            n("power_ports", p.ports),
            n("power_reserved", 0u8),
        ]),
        StateReport::Dock { state, .. } => {
            v.extend([
                n("dock_closed", state.closed),
                n("dock_confirmed", state.confirmed),
                n("dock_linked", state.partner.is_some()),
                n("dock_flags_reserved", 0u8),
            ]);
            v.extend(dock_partner(
                state.partner,
                ["dock_partner", "dock_partner_port"],
            ));
            v.push(n("dock_reserved", 0u8));
        }
        StateReport::Firmware { version, trial } => v.extend([
            n("firmware_major", version.major),
            n("firmware_minor", version.minor),
            n("firmware_patch", version.patch),
            n("firmware_trial", trial),
            n("firmware_flags_reserved", 0u8),
            n("firmware_reserved", 0u8),
        ]),
        StateReport::ImageHash(h) => v.extend(bytes(
            &[
                "image_hash_0",
                "image_hash_1",
                "image_hash_2",
                "image_hash_3",
                "image_hash_4",
                "image_hash_5",
                "image_hash_6",
            ],
            &h,
        )),
        StateReport::UidLow(u) => v.extend(uid(0, &u)),
        StateReport::UidHigh(u) => {
            v.extend(uid(7, &u));
            v.push(n("uid_high_reserved", 0u8));
        }
        StateReport::Protocol {
            version: (major, minor),
        } => v.extend([
            n("protocol_major", major),
            n("protocol_minor", minor),
            n("protocol_reserved", 0u8),
            n("protocol_reserved_7", 0u8),
        ]),
        StateReport::End { seq, parts, count } => {
            v.push(n("end_seq", seq));
            v.extend(groups(
                parts,
                [
                    "end_actuators",
                    "end_docking",
                    "end_identity",
                    "end_parts_unassigned",
                ],
            ));
            v.extend([n("end_count", count), n("end_reserved", 0u8)]);
        }
        StateReport::Other { data, .. } => v.extend(bytes(
            &[
                "data_1", "data_2", "data_3", "data_4", "data_5", "data_6", "data_7",
            ],
            &data,
        )),
    }
    v
}

/// A small multiplexed message for the tests of the multiplexing machinery (beside `StateReport`):
/// 6 bytes, `part` in byte 0 selects `a` (byte 1) and `b` (bytes 2–5) for part 0, `c`
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
