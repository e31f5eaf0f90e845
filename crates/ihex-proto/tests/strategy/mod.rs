//! Proptest strategies producing only valid values: every message and packet the codec accepts.
//! Shared by the property tests (`prop.rs`), the schema tests (`schema.rs`) and the cantools round
//! trip (`dbc.rs`); a new message kind gets its strategy here.
#![allow(dead_code)]

use ihex_proto::{
    AckResult, BootRole, BuzzerCommand, DockPartner, DockRefuseReason, DockState, FaultCode,
    FirmwareVersion, FwAction, FwPhase, FwRefusal, FwStatus, HealthFlags, HealthReply, Kind,
    LedCommand, Message, NodeId, Packet, Port, PowerState, ResetReason, Rgb, StateParts,
    StateReport, FW_BEGIN_MAX_LEN,
};
use proptest::prelude::*;

/// A sub-controller ID, the bounds often.
pub fn sc_id() -> impl Strategy<Value = NodeId> {
    prop_oneof![
        Just(NodeId::FIRST_SC),
        Just(NodeId::LAST_SC),
        (0x001u16..=0xFFD).prop_map(|r| NodeId::new_sc(r).unwrap()),
    ]
}

/// A dock port.
pub fn port() -> impl Strategy<Value = Port> {
    (0u8..Port::COUNT).prop_map(|p| Port::new(p).unwrap())
}

/// A buzzer frequency the command accepts, the bounds often.
pub fn freq() -> impl Strategy<Value = u16> {
    prop_oneof![
        Just(BuzzerCommand::MIN_FREQ_HZ),
        Just(BuzzerCommand::MAX_FREQ_HZ),
        BuzzerCommand::MIN_FREQ_HZ..=BuzzerCommand::MAX_FREQ_HZ,
    ]
}

/// Any assigned kind.
pub fn kind() -> impl Strategy<Value = Kind> {
    (0usize..Kind::ALL.len()).prop_map(|i| Kind::ALL[i])
}

/// Any colour.
pub fn rgb() -> impl Strategy<Value = Rgb> {
    any::<[u8; 3]>().prop_map(|[r, g, b]| Rgb::new(r, g, b))
}

/// A valid LED command of every mode.
pub fn led() -> impl Strategy<Value = LedCommand> {
    prop_oneof![
        Just(LedCommand::Off),
        (rgb(), any::<u8>())
            .prop_map(|(color, brightness)| LedCommand::Steady { color, brightness }),
        (rgb(), any::<u8>(), 1u8..=255, 1u8..=99).prop_map(
            |(color, brightness, period_10ms, duty_pct)| {
                LedCommand::Blink {
                    color,
                    brightness,
                    period_10ms,
                    duty_pct,
                }
            }
        ),
    ]
}

/// A valid buzzer command of every mode.
pub fn buzzer() -> impl Strategy<Value = BuzzerCommand> {
    prop_oneof![
        Just(BuzzerCommand::Off),
        freq().prop_map(|freq_hz| BuzzerCommand::Continuous { freq_hz }),
        (freq(), 1u8..=255, 1u8..=255, any::<u8>()).prop_map(
            |(freq_hz, on_10ms, off_10ms, count)| {
                BuzzerCommand::Pattern {
                    freq_hz,
                    on_10ms,
                    off_10ms,
                    count,
                }
            }
        ),
    ]
}

/// A role.
pub fn role() -> impl Strategy<Value = BootRole> {
    prop_oneof![Just(BootRole::Static), Just(BootRole::Mobile)]
}

/// A dock partner, or none.
pub fn partner() -> impl Strategy<Value = Option<DockPartner>> {
    prop_oneof![
        1 => Just(None),
        3 => (sc_id(), port()).prop_map(|(node, port)| Some(DockPartner { node, port })),
    ]
}

/// Any valid state report: every known part, and unknown part numbers with any data.
pub fn state_report() -> impl Strategy<Value = StateReport> {
    prop_oneof![
        led().prop_map(StateReport::Led),
        buzzer().prop_map(StateReport::Buzzer),
        (any::<(bool, u8, u8, u8)>(), role(), 0u8..=Port::COUNT).prop_map(
            |((relay, loops, confirmed, identify_s), role, ports)| {
                StateReport::Power(PowerState {
                    relay,
                    loops,
                    confirmed,
                    identify_s,
                    role,
                    ports,
                })
            }
        ),
        (port(), any::<(bool, bool)>(), partner()).prop_map(
            |(port, (closed, confirmed), partner)| {
                StateReport::Dock {
                    port,
                    state: DockState {
                        closed,
                        confirmed,
                        partner,
                    },
                }
            }
        ),
        (any::<(u8, u8, u8)>(), any::<bool>()).prop_map(|((major, minor, patch), trial)| {
            StateReport::Firmware {
                version: FirmwareVersion::new(major, minor, patch),
                trial,
            }
        }),
        any::<[u8; 7]>().prop_map(StateReport::ImageHash),
        any::<[u8; 7]>().prop_map(StateReport::UidLow),
        any::<[u8; 5]>().prop_map(StateReport::UidHigh),
        any::<(u8, u8)>().prop_map(|version| StateReport::Protocol { version }),
        any::<(u8, u8, u8)>().prop_map(|(seq, parts, count)| StateReport::End {
            seq,
            parts: StateParts(parts),
            count,
        }),
        (any::<u8>(), any::<[u8; 7]>())
            .prop_filter("an unknown part number", |(part, _)| {
                !StateReport::is_known_part(*part)
            })
            .prop_map(|(part, data)| StateReport::Other { part, data }),
    ]
}

/// A valid message of every kind.
pub fn message() -> impl Strategy<Value = Message> {
    prop_oneof![
        (any::<u8>(), any::<bool>()).prop_map(|(seq, on)| Message::PowerSet { seq, on }),
        (any::<u8>(), any::<u8>(), any::<u32>()).prop_map(|(c, arg, detail)| Message::Fault {
            code: FaultCode::from_raw(c),
            arg,
            detail
        }),
        port().prop_map(|port| Message::DockDetected { port }),
        port().prop_map(|port| Message::DockRemoved { port }),
        (any::<u8>(), port()).prop_map(|(seq, port)| Message::DockConfirm { seq, port }),
        (any::<u8>(), port(), any::<u8>()).prop_map(|(seq, port, r)| Message::DockRefuse {
            seq,
            port,
            reason: DockRefuseReason::from_raw(r)
        }),
        port().prop_map(|port| Message::Handshake { port }),
        (kind(), any::<u8>(), any::<u8>(), any::<u8>()).prop_map(|(kind, seq, r, detail)| {
            Message::Ack {
                kind,
                seq,
                result: AckResult::from_raw(r),
                detail,
            }
        }),
        any::<[u8; 8]>().prop_map(|uid_head| Message::AssignSelect { uid_head }),
        (any::<[u8; 4]>(), sc_id(), any::<u8>()).prop_map(|(uid_tail, new_id, seq)| {
            Message::AssignCommit {
                uid_tail,
                new_id,
                seq,
            }
        }),
        (
            any::<u8>(),
            any::<u8>(),
            prop_oneof![sc_id(), Just(NodeId::UNCONFIGURED)],
            any::<[u8; 4]>()
        )
            .prop_map(|(seq, r, new_id, uid_tail)| Message::AssignReply {
                seq,
                result: AckResult::from_raw(r),
                new_id,
                uid_tail
            }),
        (
            any::<(u8, u8)>(),
            any::<bool>(),
            0u8..=Port::COUNT,
            any::<u8>()
        )
            .prop_map(|(version, mobile, ports, r)| Message::BootUp {
                version,
                role: if mobile {
                    BootRole::Mobile
                } else {
                    BootRole::Static
                },
                ports,
                reset: ResetReason::from_raw(r),
            }),
        (any::<u8>(), buzzer()).prop_map(|(seq, cmd)| Message::BuzzerSet { seq, cmd }),
        (any::<u8>(), led()).prop_map(|(seq, cmd)| Message::LedSet { seq, cmd }),
        (any::<u8>(), any::<u8>()).prop_map(|(seq, seconds)| Message::Identify { seq, seconds }),
        any::<u8>().prop_map(|seq| Message::HealthCheck { seq }),
        (
            any::<[u8; 5]>(),
            prop_oneof![
                Just(HealthReply::MAX_UPTIME_S),
                0..=HealthReply::MAX_UPTIME_S
            ]
        )
            .prop_map(|([seq, flags, loops, tec, rec], uptime_s)| {
                Message::HealthReply(HealthReply {
                    seq,
                    flags: HealthFlags(flags),
                    loops,
                    tec,
                    rec,
                    uptime_s,
                })
            }),
        (any::<u8>(), any::<u8>()).prop_map(|(seq, parts)| Message::StateQuery {
            seq,
            parts: StateParts(parts)
        }),
        state_report().prop_map(Message::StateReport),
        (any::<u8>(), port(), partner()).prop_map(|(seq, port, partner)| Message::DockLink {
            seq,
            port,
            partner
        }),
        fw_message(),
    ]
}

/// A firmware-transfer message.
pub fn fw_message() -> impl Strategy<Value = Message> {
    prop_oneof![
        (any::<u32>(), 0..=FW_BEGIN_MAX_LEN, any::<bool>()).prop_map(|(image_id, len, force)| {
            Message::FwBegin {
                image_id,
                len,
                force,
            }
        }),
        (
            any::<u32>(),
            prop_oneof![Just(FwAction::Commit), Just(FwAction::Abort)]
        )
            .prop_map(|(image_id, action)| Message::FwEnd { image_id, action }),
        any::<u32>().prop_map(|image_id| Message::FwQuery { image_id }),
        (
            any::<u8>(),
            any::<u8>(),
            any::<u16>(),
            any::<u16>(),
            any::<u16>()
        )
            .prop_map(|(phase, reason, first_missing, run, missing)| {
                Message::FwStatus(FwStatus {
                    phase: FwPhase::from_raw(phase),
                    reason: FwRefusal::from_raw(reason),
                    first_missing,
                    run,
                    missing,
                })
            }),
        (any::<u16>(), any::<[u8; 6]>()).prop_map(|(index, data)| Message::FwData { index, data }),
    ]
}

/// Any valid packet: a valid message with addresses its kind allows.
pub fn packet() -> impl Strategy<Value = Packet> {
    (message(), sc_id(), any::<bool>()).prop_map(|(msg, node, alt)| {
        let kind = msg.kind();
        if kind.is_command() {
            let dest = match kind {
                Kind::AssignSelect | Kind::AssignCommit => NodeId::BROADCAST,
                Kind::DockLink => node,
                _ if alt => NodeId::BROADCAST,
                _ => node,
            };
            Packet::command(dest, msg)
        } else if kind == Kind::AssignReply && alt {
            Packet::report(NodeId::UNCONFIGURED, msg)
        } else {
            Packet::report(node, msg)
        }
    })
}
