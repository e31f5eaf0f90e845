//! The SC core's behaviour contract, one input at a time (see the crate docs).

mod common;

use common::*;
use ihex_proto::{
    uart::{UartError, UartReply, UartRequest},
    AckResult, BootRole, BuzzerCommand, FaultCode, HealthFlags, Kind, LedCommand, Message, NodeId,
    Packet, ResetReason, Rgb, PROTOCOL_VERSION,
};
use ihex_sc_core::{
    BuzzerOutput, LedOutput, Millis, Node, Output, DEBOUNCE_MS, HANDSHAKE_SETTLE_MS,
    IDENTIFY_BUZZER, IDENTIFY_LED, UART_IDLE_RESET_MS,
};

fn ack(kind: Kind, seq: u8, result: AckResult, detail: u8) -> Message {
    Message::Ack {
        kind,
        seq,
        result,
        detail,
    }
}

// ---- boot ----

#[test]
fn boot_announces_with_id() {
    let mut n = Node::new(config(BootRole::Static, 6, Some(id())), Millis(0));
    let out = drain(&mut n);
    assert_eq!(
        out,
        [Output::Frame(Packet::report(
            id(),
            Message::BootUp {
                version: PROTOCOL_VERSION,
                role: BootRole::Static,
                ports: 6,
                reset: ihex_proto::ResetReason::PowerOn
            }
        ))]
    );
    assert_eq!(
        n.poll_at(),
        None,
        "a static node has no timer pending after boot"
    );
    assert!(
        n.actuators_changed(),
        "the first call reports the initial state"
    );
    assert!(!n.actuators_changed());
    assert_eq!(n.actuators(), Default::default());
}

#[test]
fn unconfigured_node_is_silent() {
    let mut n = Node::new(config(BootRole::Static, 6, None), Millis(0));
    assert!(drain(&mut n).is_empty());
    assert_eq!(n.node_id(), None);
    // Broadcast commands and health checks: nothing, and no actuator change.
    feed(
        &mut n,
        Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: 1 }),
        1,
    );
    let led = LedCommand::Steady {
        color: Rgb::new(255, 0, 0),
        brightness: 255,
    };
    feed(
        &mut n,
        Packet::command(NodeId::BROADCAST, Message::LedSet { seq: 2, cmd: led }),
        2,
    );
    // Dock events are not reported either.
    settle_loop(&mut n, 0, true, 10);
    // A garbage frame to the unconfigured address.
    n.handle_frame(0x0B_FFE_000, true, false, &[1, 2, 3], Millis(100));
    assert!(drain(&mut n).is_empty());
    assert_eq!(n.actuators().led, LedOutput::default());
}

#[test]
fn reserved_stored_id_counts_as_unconfigured() {
    let mut n = Node::new(
        config(BootRole::Static, 6, Some(NodeId::BROADCAST)),
        Millis(0),
    );
    assert_eq!(n.node_id(), None);
    assert!(drain(&mut n).is_empty());
}

// ---- addressing and decoding ----

#[test]
fn frames_for_others_and_reports_are_ignored() {
    let mut n = static_node();
    let other = NodeId::new_sc(0x112).unwrap();
    feed(
        &mut n,
        Packet::command(other, Message::PowerSet { seq: 1, on: true }),
        1,
    );
    feed(
        &mut n,
        Packet::report(other, Message::DockDetected { port: port(0) }),
        2,
    );
    assert!(drain(&mut n).is_empty());
    assert!(!n.actuators().relay);
}

#[test]
fn standard_and_remote_frames_are_ignored() {
    let mut n = static_node();
    let (raw, data) = Packet::command(id(), Message::PowerSet { seq: 1, on: true }).encode();
    n.handle_frame(raw, false, false, &data, Millis(1));
    n.handle_frame(raw, true, true, &data, Millis(2));
    n.handle_frame(0x123, false, false, &[], Millis(3));
    assert!(drain(&mut n).is_empty());
    assert!(!n.actuators().relay);
}

#[test]
fn bad_frame_to_own_id_is_a_fault() {
    let mut n = static_node();
    // LedSet with a 3-byte payload.
    let raw = (Kind::LedSet as u32) << 24 | u32::from(ID) << 12;
    n.handle_frame(raw, true, false, &[1, 2, 3], Millis(1));
    let m = msgs(&mut n);
    assert_eq!(m.len(), 1);
    match m[0] {
        Message::Fault {
            code: FaultCode::BadFrame,
            arg,
            detail,
        } => {
            assert_eq!(arg, Kind::LedSet as u8);
            assert_eq!(detail & 0xFF, 2, "length error class");
            assert_eq!((detail >> 8) & 0xFF, 3, "data length");
        }
        ref other => panic!("expected a BadFrame fault, got {other:?}"),
    }
    // An unknown kind.
    n.handle_frame(
        0x1F << 24 | u32::from(ID) << 12,
        true,
        false,
        &[],
        Millis(2),
    );
    assert!(matches!(
        msgs(&mut n)[..],
        [Message::Fault {
            code: FaultCode::BadFrame,
            arg: 0x1F,
            ..
        }]
    ));
    // A command claiming to come from another node.
    let raw = (Kind::PowerSet as u32) << 24 | u32::from(ID) << 12 | 0x222;
    n.handle_frame(raw, true, false, &[0, 1], Millis(3));
    assert!(matches!(
        msgs(&mut n)[..],
        [Message::Fault {
            code: FaultCode::BadFrame,
            arg: 0,
            ..
        }]
    ));
    assert!(!n.actuators().relay);
}

#[test]
fn bad_broadcast_frame_is_dropped_silently() {
    let mut n = static_node();
    let raw = (Kind::LedSet as u32) << 24 | 0xFFF << 12;
    n.handle_frame(raw, true, false, &[1, 2, 3], Millis(1));
    assert!(drain(&mut n).is_empty());
}

// ---- actuator commands ----

#[test]
fn led_set_scales_colour_and_acks() {
    let mut n = static_node();
    n.actuators_changed();
    let led = LedCommand::Steady {
        color: Rgb::new(255, 128, 0),
        brightness: 128,
    };
    cmd(&mut n, Message::LedSet { seq: 7, cmd: led }, 1);
    assert_eq!(msgs(&mut n), [ack(Kind::LedSet, 7, AckResult::Ok, 0)]);
    assert_eq!(
        n.actuators().led,
        LedOutput {
            duty: Rgb::new(128, 64, 0),
            blink: None
        }
    );
    assert!(n.actuators_changed());
    assert!(!n.actuators_changed());

    let led = LedCommand::Blink {
        color: Rgb::new(10, 20, 255),
        brightness: 255,
        period_10ms: 50,
        duty_pct: 25,
    };
    cmd(&mut n, Message::LedSet { seq: 8, cmd: led }, 2);
    assert_eq!(msgs(&mut n), [ack(Kind::LedSet, 8, AckResult::Ok, 0)]);
    assert_eq!(
        n.actuators().led,
        LedOutput {
            duty: Rgb::new(10, 20, 255),
            blink: Some((500, 25))
        }
    );

    cmd(
        &mut n,
        Message::LedSet {
            seq: 9,
            cmd: LedCommand::Off,
        },
        3,
    );
    assert_eq!(msgs(&mut n), [ack(Kind::LedSet, 9, AckResult::Ok, 0)]);
    assert_eq!(n.actuators().led, LedOutput::default());
}

#[test]
fn led_set_with_invalid_duty_is_a_bad_frame() {
    let mut n = static_node();
    let raw = (Kind::LedSet as u32) << 24 | u32::from(ID) << 12;
    n.handle_frame(
        raw,
        true,
        false,
        &[1, 2, 255, 0, 0, 255, 10, 100],
        Millis(1),
    );
    match msgs(&mut n)[..] {
        [Message::Fault {
            code: FaultCode::BadFrame,
            arg,
            detail,
        }] => {
            assert_eq!(arg, Kind::LedSet as u8);
            assert_eq!(detail & 0xFF, 3, "value error class");
            assert_eq!(detail >> 16, 100, "offending value");
        }
        ref m => panic!("unexpected {m:?}"),
    }
    assert_eq!(n.actuators().led, LedOutput::default());
}

#[test]
fn buzzer_commands_and_pattern_end() {
    let mut n = static_node();
    cmd(
        &mut n,
        Message::BuzzerSet {
            seq: 1,
            cmd: BuzzerCommand::Continuous { freq_hz: 440 },
        },
        0,
    );
    assert_eq!(msgs(&mut n), [ack(Kind::BuzzerSet, 1, AckResult::Ok, 0)]);
    assert_eq!(n.actuators().buzzer, BuzzerOutput::Tone { freq_hz: 440 });
    assert_eq!(
        n.poll_at(),
        None,
        "a continuous tone does not end by itself"
    );

    let pattern = BuzzerCommand::Pattern {
        freq_hz: 1000,
        on_10ms: 10,
        off_10ms: 20,
        count: 3,
    };
    cmd(
        &mut n,
        Message::BuzzerSet {
            seq: 2,
            cmd: pattern,
        },
        1000,
    );
    assert_eq!(msgs(&mut n), [ack(Kind::BuzzerSet, 2, AckResult::Ok, 0)]);
    assert_eq!(
        n.actuators().buzzer,
        BuzzerOutput::Pattern {
            freq_hz: 1000,
            on_ms: 100,
            off_ms: 200,
            count: 3
        }
    );
    // 3 × (100 + 200) ms.
    assert_eq!(n.poll_at(), Some(Millis(1900)));
    n.actuators_changed();
    n.tick(Millis(1899));
    assert!(!n.actuators_changed());
    n.tick(Millis(1900));
    assert!(n.actuators_changed());
    assert_eq!(n.actuators().buzzer, BuzzerOutput::Off);
    assert_eq!(n.poll_at(), None);

    // An endless pattern does not end by itself; the adapter's "done" is for finite ones only.
    let endless = BuzzerCommand::Pattern {
        freq_hz: 1000,
        on_10ms: 1,
        off_10ms: 1,
        count: 0,
    };
    cmd(
        &mut n,
        Message::BuzzerSet {
            seq: 3,
            cmd: endless,
        },
        2000,
    );
    assert_eq!(n.poll_at(), None);
    n.handle_buzzer_done(Millis(2100));
    assert_ne!(n.actuators().buzzer, BuzzerOutput::Off);

    cmd(
        &mut n,
        Message::BuzzerSet {
            seq: 4,
            cmd: BuzzerCommand::Off,
        },
        3000,
    );
    assert_eq!(
        msgs(&mut n).last(),
        Some(&ack(Kind::BuzzerSet, 4, AckResult::Ok, 0))
    );
    assert_eq!(n.actuators().buzzer, BuzzerOutput::Off);
}

#[test]
fn buzzer_done_ends_a_finite_pattern_early() {
    let mut n = static_node();
    let pattern = BuzzerCommand::Pattern {
        freq_hz: 1000,
        on_10ms: 10,
        off_10ms: 10,
        count: 5,
    };
    cmd(
        &mut n,
        Message::BuzzerSet {
            seq: 2,
            cmd: pattern,
        },
        0,
    );
    n.handle_buzzer_done(Millis(950));
    assert_eq!(n.actuators().buzzer, BuzzerOutput::Off);
    assert_eq!(n.poll_at(), None);
}

#[test]
fn power_set_switches_relay_on_static_node() {
    let mut n = static_node();
    cmd(&mut n, Message::PowerSet { seq: 3, on: true }, 1);
    assert_eq!(msgs(&mut n), [ack(Kind::PowerSet, 3, AckResult::Ok, 0)]);
    assert!(n.actuators().relay);
    cmd(&mut n, Message::PowerSet { seq: 4, on: false }, 2);
    assert_eq!(msgs(&mut n), [ack(Kind::PowerSet, 4, AckResult::Ok, 0)]);
    assert!(!n.actuators().relay);
}

#[test]
fn power_and_dock_commands_unsupported_without_relay() {
    for (role, ports) in [(BootRole::Mobile, 2), (BootRole::Static, 0)] {
        let mut n = Node::new(config(role, ports, Some(id())), Millis(0));
        drain(&mut n);
        cmd(&mut n, Message::PowerSet { seq: 1, on: true }, 1);
        cmd(
            &mut n,
            Message::DockConfirm {
                seq: 2,
                port: port(0),
            },
            2,
        );
        let refuse = Message::DockRefuse {
            seq: 3,
            port: port(0),
            reason: ihex_proto::DockRefuseReason::Busy,
        };
        cmd(&mut n, refuse, 3);
        let acks: Vec<_> = msgs(&mut n)
            .into_iter()
            .filter(|m| m.kind() == Kind::Ack)
            .collect();
        assert_eq!(
            acks,
            [
                ack(Kind::PowerSet, 1, AckResult::Unsupported, 0),
                ack(Kind::DockConfirm, 2, AckResult::Unsupported, 0),
                ack(Kind::DockRefuse, 3, AckResult::Unsupported, 0),
            ],
            "{role:?} with {ports} ports"
        );
        assert!(!n.actuators().relay);
    }
}

#[test]
fn broadcast_commands_are_acked_by_each_node() {
    let mut n = static_node();
    let led = LedCommand::Steady {
        color: Rgb::new(0, 255, 0),
        brightness: 255,
    };
    feed(
        &mut n,
        Packet::command(NodeId::BROADCAST, Message::LedSet { seq: 5, cmd: led }),
        1,
    );
    let out = drain(&mut n);
    assert_eq!(
        out,
        [Output::Frame(Packet::report(
            id(),
            ack(Kind::LedSet, 5, AckResult::Ok, 0)
        ))]
    );
    assert_eq!(n.actuators().led.duty, Rgb::new(0, 255, 0));
}

// ---- identify ----

#[test]
fn identify_overrides_and_restores() {
    let mut n = static_node();
    let led = LedCommand::Steady {
        color: Rgb::new(0, 0, 255),
        brightness: 255,
    };
    cmd(&mut n, Message::LedSet { seq: 1, cmd: led }, 0);
    cmd(
        &mut n,
        Message::BuzzerSet {
            seq: 2,
            cmd: BuzzerCommand::Continuous { freq_hz: 300 },
        },
        0,
    );
    cmd(&mut n, Message::Identify { seq: 3, seconds: 2 }, 100);
    assert_eq!(
        msgs(&mut n).last(),
        Some(&ack(Kind::Identify, 3, AckResult::Ok, 0))
    );
    assert!(n.is_identifying());
    assert_eq!(n.actuators().led, IDENTIFY_LED);
    assert_eq!(n.actuators().buzzer, IDENTIFY_BUZZER);
    assert_eq!(n.poll_at(), Some(Millis(2100)));

    // A command during identify changes what returns afterwards, not what shows now.
    let led2 = LedCommand::Steady {
        color: Rgb::new(255, 0, 0),
        brightness: 255,
    };
    cmd(&mut n, Message::LedSet { seq: 4, cmd: led2 }, 500);
    assert_eq!(n.actuators().led, IDENTIFY_LED);
    n.actuators_changed();
    n.tick(Millis(2099));
    assert!(!n.actuators_changed());
    n.tick(Millis(2100));
    assert!(n.actuators_changed());
    assert!(!n.is_identifying());
    assert_eq!(
        n.actuators().led,
        LedOutput {
            duty: Rgb::new(255, 0, 0),
            blink: None
        }
    );
    assert_eq!(n.actuators().buzzer, BuzzerOutput::Tone { freq_hz: 300 });
}

#[test]
fn identify_zero_stops_it() {
    let mut n = static_node();
    cmd(
        &mut n,
        Message::Identify {
            seq: 1,
            seconds: 200,
        },
        0,
    );
    cmd(&mut n, Message::Identify { seq: 2, seconds: 0 }, 10);
    assert_eq!(
        msgs(&mut n),
        [
            ack(Kind::Identify, 1, AckResult::Ok, 0),
            ack(Kind::Identify, 2, AckResult::Ok, 0)
        ]
    );
    assert!(!n.is_identifying());
    assert_eq!(n.actuators(), Default::default());
    assert_eq!(n.poll_at(), None);
}

// ---- health ----

#[test]
fn health_reply_flags_loops_counters_uptime() {
    let mut n = static_node();
    feed(
        &mut n,
        Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: 9 }),
        500,
    );
    match msgs(&mut n)[..] {
        [Message::HealthReply(h)] => {
            assert_eq!(h.seq, 9);
            assert_eq!(h.flags, HealthFlags(0));
            assert_eq!((h.loops, h.tec, h.rec, h.uptime_s), (0, 0, 0, 0));
        }
        ref m => panic!("unexpected {m:?}"),
    }

    let t = settle_loop(&mut n, 2, true, 1000);
    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 1,
            port: port(2),
        },
        t,
    );
    let led = LedCommand::Blink {
        color: Rgb::new(1, 1, 1),
        brightness: 255,
        period_10ms: 10,
        duty_pct: 50,
    };
    cmd(&mut n, Message::LedSet { seq: 2, cmd: led }, t);
    cmd(
        &mut n,
        Message::BuzzerSet {
            seq: 3,
            cmd: BuzzerCommand::Continuous { freq_hz: 440 },
        },
        t,
    );
    n.handle_can_status(130, 5, false, Millis(t));
    cmd(
        &mut n,
        Message::Identify {
            seq: 4,
            seconds: 100,
        },
        t,
    );
    drain(&mut n);
    cmd(&mut n, Message::HealthCheck { seq: 10 }, 61_500);
    match msgs(&mut n)[..] {
        [Message::HealthReply(h)] => {
            let want = HealthFlags::RELAY
                | HealthFlags::LED_ON
                | HealthFlags::LED_BLINK
                | HealthFlags::BUZZER
                | HealthFlags::ERROR_PASSIVE
                | HealthFlags::IDENTIFY;
            assert_eq!(h.flags, HealthFlags(want));
            assert_eq!((h.loops, h.tec, h.rec, h.uptime_s), (0b100, 130, 5, 61));
        }
        ref m => panic!("unexpected {m:?}"),
    }
}

#[test]
fn health_reply_of_mobile_node_and_uptime_saturation() {
    let mut n = Node::new(config(BootRole::Mobile, 1, Some(id())), Millis(5));
    drain(&mut n);
    let t = 1000 * u64::from(u32::MAX);
    cmd(&mut n, Message::HealthCheck { seq: 1 }, t);
    let hs: Vec<_> = msgs(&mut n)
        .into_iter()
        .filter_map(|m| match m {
            Message::HealthReply(h) => Some(h),
            _ => None,
        })
        .collect();
    assert_eq!(hs.len(), 1);
    assert_eq!(hs[0].flags, HealthFlags(HealthFlags::MOBILE));
    assert_eq!(hs[0].uptime_s, ihex_proto::HealthReply::MAX_UPTIME_S);
}

// ---- signal loop and docking ----

#[test]
fn bouncing_loop_yields_one_event() {
    let mut n = static_node();
    let mut t = 100;
    for i in 0..20 {
        n.handle_loop_level(port(1), i % 2 == 0, Millis(t));
        t += 3;
    }
    // Last report (i = 19) was "open"; close it once more and hold.
    n.handle_loop_level(port(1), true, Millis(t));
    assert_eq!(n.poll_at(), Some(Millis(t + DEBOUNCE_MS)));
    n.tick(Millis(t + DEBOUNCE_MS - 1));
    assert!(drain(&mut n).is_empty());
    n.tick(Millis(t + DEBOUNCE_MS));
    assert_eq!(msgs(&mut n), [Message::DockDetected { port: port(1) }]);
    assert_eq!(n.loops(), 0b10);
    n.tick(Millis(t + 10 * DEBOUNCE_MS));
    assert!(drain(&mut n).is_empty());
}

#[test]
fn glitch_shorter_than_debounce_yields_nothing() {
    let mut n = static_node();
    n.handle_loop_level(port(0), true, Millis(100));
    n.handle_loop_level(port(0), false, Millis(100 + DEBOUNCE_MS - 1));
    n.tick(Millis(1000));
    assert!(drain(&mut n).is_empty());
    assert_eq!(n.loops(), 0);
    assert_eq!(n.poll_at(), None);
}

#[test]
fn periodic_level_reports_debounce_without_ticks() {
    let mut n = static_node();
    for t in (0..=DEBOUNCE_MS).step_by(10) {
        n.handle_loop_level(port(3), true, Millis(t));
    }
    assert_eq!(msgs(&mut n), [Message::DockDetected { port: port(3) }]);
}

#[test]
fn levels_of_ports_beyond_config_are_ignored() {
    let mut n = static_node();
    settle_loop(&mut n, 6, true, 0);
    settle_loop(&mut n, 7, true, 100);
    assert!(drain(&mut n).is_empty());
    assert_eq!(n.loops(), 0);
}

#[test]
fn full_docking_sequence() {
    let mut n = static_node();
    n.actuators_changed();
    let t = settle_loop(&mut n, 3, true, 1000);
    assert_eq!(msgs(&mut n), [Message::DockDetected { port: port(3) }]);
    assert!(!n.actuators().relay, "no power before the gateway confirms");

    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 11,
            port: port(3),
        },
        t + 5,
    );
    assert_eq!(msgs(&mut n), [ack(Kind::DockConfirm, 11, AckResult::Ok, 0)]);
    assert!(n.actuators().relay);
    assert!(n.actuators_changed());

    n.handle_loop_level(port(3), false, Millis(t + 1000));
    assert!(n.actuators().relay, "still debouncing the open edge");
    n.tick(Millis(t + 1000 + DEBOUNCE_MS));
    assert!(!n.actuators().relay);
    assert!(n.actuators_changed());
    assert_eq!(msgs(&mut n), [Message::DockRemoved { port: port(3) }]);
}

#[test]
fn confirm_without_dock_is_refused_with_fault() {
    let mut n = static_node();
    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 4,
            port: port(2),
        },
        10,
    );
    assert_eq!(
        msgs(&mut n),
        [
            ack(Kind::DockConfirm, 4, AckResult::InvalidState, 1),
            Message::Fault {
                code: FaultCode::DockConfirmNotDocked,
                arg: 2,
                detail: 0
            },
        ]
    );
    assert!(!n.actuators().relay);
}

#[test]
fn confirm_for_port_beyond_config_is_invalid_value() {
    let mut n = static_node();
    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 4,
            port: port(6),
        },
        10,
    );
    assert_eq!(
        msgs(&mut n),
        [ack(Kind::DockConfirm, 4, AckResult::InvalidValue, 1)]
    );
    let refuse = Message::DockRefuse {
        seq: 5,
        port: port(7),
        reason: ihex_proto::DockRefuseReason::NotAllowed,
    };
    cmd(&mut n, refuse, 11);
    assert_eq!(
        msgs(&mut n),
        [ack(Kind::DockRefuse, 5, AckResult::InvalidValue, 1)]
    );
}

#[test]
fn refuse_keeps_relay_off_and_withdraws_a_confirmation() {
    let mut n = static_node();
    let t = settle_loop(&mut n, 0, true, 0);
    drain(&mut n);
    let refuse = |seq| Message::DockRefuse {
        seq,
        port: port(0),
        reason: ihex_proto::DockRefuseReason::Busy,
    };
    cmd(&mut n, refuse(1), t);
    assert_eq!(msgs(&mut n), [ack(Kind::DockRefuse, 1, AckResult::Ok, 0)]);
    assert!(!n.actuators().relay);
    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 2,
            port: port(0),
        },
        t,
    );
    assert!(n.actuators().relay);
    cmd(&mut n, refuse(3), t);
    assert!(!n.actuators().relay);
    assert_eq!(
        msgs(&mut n),
        [
            ack(Kind::DockConfirm, 2, AckResult::Ok, 0),
            ack(Kind::DockRefuse, 3, AckResult::Ok, 0)
        ]
    );
}

#[test]
fn relay_stays_on_while_any_confirmed_port_is_docked() {
    let mut n = static_node();
    let t = settle_loop(&mut n, 0, true, 0);
    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 1,
            port: port(0),
        },
        t,
    );
    let t = settle_loop(&mut n, 4, true, t + 100);
    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 2,
            port: port(4),
        },
        t,
    );
    drain(&mut n);
    let t = settle_loop(&mut n, 0, false, t + 100);
    assert_eq!(msgs(&mut n), [Message::DockRemoved { port: port(0) }]);
    assert!(n.actuators().relay, "port 4 is still docked and confirmed");
    settle_loop(&mut n, 4, false, t + 100);
    assert_eq!(msgs(&mut n), [Message::DockRemoved { port: port(4) }]);
    assert!(!n.actuators().relay);
}

#[test]
fn unconfirmed_undock_leaves_a_forced_relay_alone() {
    let mut n = static_node();
    cmd(&mut n, Message::PowerSet { seq: 1, on: true }, 0);
    let t = settle_loop(&mut n, 1, true, 10);
    settle_loop(&mut n, 1, false, t + 10);
    assert!(n.actuators().relay);
    assert_eq!(
        msgs(&mut n),
        [
            ack(Kind::PowerSet, 1, AckResult::Ok, 0),
            Message::DockDetected { port: port(1) },
            Message::DockRemoved { port: port(1) }
        ]
    );
}

// ---- mobile role ----

#[test]
fn mobile_handshakes_with_first_closed_loop() {
    let mut n = Node::new(config(BootRole::Mobile, 3, Some(id())), Millis(0));
    assert!(matches!(
        msgs(&mut n)[..],
        [Message::BootUp {
            role: BootRole::Mobile,
            ports: 3,
            ..
        }]
    ));
    assert_eq!(n.poll_at(), Some(Millis(HANDSHAKE_SETTLE_MS)));
    n.handle_loop_level(port(2), true, Millis(5));
    n.tick(Millis(5 + DEBOUNCE_MS));
    assert_eq!(msgs(&mut n), [Message::Handshake { port: port(2) }]);
    assert_eq!(n.poll_at(), None);
    // Later loop changes of a mobile element are not dock reports.
    settle_loop(&mut n, 1, true, 500);
    settle_loop(&mut n, 2, false, 600);
    assert!(drain(&mut n).is_empty());
}

#[test]
fn mobile_without_closed_loop_handshakes_port_zero_after_settle() {
    let mut n = Node::new(config(BootRole::Mobile, 2, Some(id())), Millis(1000));
    drain(&mut n);
    n.tick(Millis(1000 + HANDSHAKE_SETTLE_MS - 1));
    assert!(drain(&mut n).is_empty());
    n.tick(Millis(1000 + HANDSHAKE_SETTLE_MS));
    assert_eq!(msgs(&mut n), [Message::Handshake { port: port(0) }]);
    n.tick(Millis(100_000));
    assert!(drain(&mut n).is_empty(), "one handshake per boot");
}

#[test]
fn unconfigured_mobile_does_not_handshake_until_it_has_an_id() {
    let mut n = Node::new(config(BootRole::Mobile, 2, None), Millis(0));
    settle_loop(&mut n, 1, true, 0);
    n.tick(Millis(10_000));
    assert!(drain(&mut n).is_empty());
    for b in UartRequest::SetId(id()).encode() {
        n.handle_uart_byte(b, Millis(10_001));
    }
    let m = msgs(&mut n);
    assert!(matches!(
        m[..],
        [Message::BootUp { role: BootRole::Mobile, .. }, Message::Handshake { port: p }] if p == port(1)
    ));
}

// ---- UART node ID ----

fn uart(n: &mut Node, bytes: &[u8], now: u64) {
    for &b in bytes {
        n.handle_uart_byte(b, Millis(now));
    }
}

#[test]
fn uart_set_id_on_unconfigured_node() {
    let mut n = Node::new(config(BootRole::Static, 4, None), Millis(0));
    let new = NodeId::new_sc(0x2AB).unwrap();
    uart(&mut n, &UartRequest::SetId(new).encode(), 10);
    let out = drain(&mut n);
    assert_eq!(
        out,
        [
            Output::StoreId(new),
            Output::FiltersChanged,
            Output::Uart(UartReply::Id(new).encode()),
            Output::Frame(Packet::report(
                new,
                Message::BootUp {
                    version: PROTOCOL_VERSION,
                    role: BootRole::Static,
                    ports: 4,
                    reset: ihex_proto::ResetReason::PowerOn
                }
            )),
        ]
    );
    assert_eq!(n.node_id(), Some(new));
    assert_eq!(n.config().node_id, Some(new));
    // Now it answers commands to its new ID.
    feed(
        &mut n,
        Packet::command(new, Message::HealthCheck { seq: 1 }),
        20,
    );
    assert!(matches!(msgs(&mut n)[..], [Message::HealthReply(_)]));
}

#[test]
fn uart_set_same_id_does_not_reannounce() {
    let mut n = static_node();
    uart(&mut n, &UartRequest::SetId(id()).encode(), 10);
    assert_eq!(
        drain(&mut n),
        [
            Output::StoreId(id()),
            Output::FiltersChanged,
            Output::Uart(UartReply::Id(id()).encode())
        ]
    );
}

#[test]
fn uart_changing_id_reannounces_from_new_id() {
    let mut n = static_node();
    let new = NodeId::new_sc(0xFFD).unwrap();
    uart(&mut n, &[0xAF, 0xFD], 10);
    let out = drain(&mut n);
    assert_eq!(out.len(), 4);
    assert!(
        matches!(out[3], Output::Frame(Packet { src, msg: Message::BootUp { .. }, .. }) if src == new)
    );
    // The old ID is no longer ours.
    feed(
        &mut n,
        Packet::command(id(), Message::HealthCheck { seq: 1 }),
        20,
    );
    assert!(drain(&mut n).is_empty());
}

#[test]
fn uart_query() {
    let mut n = Node::new(config(BootRole::Static, 4, None), Millis(0));
    uart(&mut n, &UartRequest::Query.encode(), 1);
    assert_eq!(
        drain(&mut n),
        [Output::Uart(UartReply::Id(NodeId::UNCONFIGURED).encode())]
    );
    let mut n = static_node();
    uart(&mut n, &[0xB0, 0x00], 1);
    assert_eq!(drain(&mut n), [Output::Uart([0x51, 0x11])]);
}

#[test]
fn uart_malformed_and_reserved() {
    let mut n = static_node();
    uart(&mut n, &[0x42], 1);
    assert_eq!(
        drain(&mut n),
        [Output::Uart(
            UartReply::Error(UartError::Malformed).encode()
        )]
    );
    uart(&mut n, &[0xB0, 0x01], 2);
    assert_eq!(
        drain(&mut n),
        [Output::Uart(
            UartReply::Error(UartError::Malformed).encode()
        )]
    );
    for reserved in [[0xA0, 0x00], [0xAF, 0xFE], [0xAF, 0xFF]] {
        uart(&mut n, &reserved, 3);
        assert_eq!(
            drain(&mut n),
            [Output::Uart(
                UartReply::Error(UartError::ReservedId).encode()
            )]
        );
    }
    assert_eq!(n.node_id(), Some(id()));
}

#[test]
fn uart_idle_gap_drops_half_request() {
    let mut n = static_node();
    n.handle_uart_byte(0xA2, Millis(100));
    assert_eq!(n.poll_at(), Some(Millis(100 + UART_IDLE_RESET_MS)));
    n.tick(Millis(100 + UART_IDLE_RESET_MS));
    assert_eq!(n.poll_at(), None);
    // 0x22 alone cannot start a request: it is malformed, not the tail of "set 0x222".
    n.handle_uart_byte(0x22, Millis(300));
    assert_eq!(
        drain(&mut n),
        [Output::Uart(
            UartReply::Error(UartError::Malformed).encode()
        )]
    );
    assert_eq!(n.node_id(), Some(id()));

    // The same without a tick in between.
    n.handle_uart_byte(0xA2, Millis(1000));
    n.handle_uart_byte(0x22, Millis(1000 + UART_IDLE_RESET_MS));
    assert_eq!(
        drain(&mut n),
        [Output::Uart(
            UartReply::Error(UartError::Malformed).encode()
        )]
    );
    // Within the gap the request completes.
    n.handle_uart_byte(0xA2, Millis(2000));
    n.handle_uart_byte(0x22, Millis(2000 + UART_IDLE_RESET_MS - 1));
    assert_eq!(n.node_id(), NodeId::new_sc(0x222));
}

#[test]
fn store_failure_is_reported() {
    let mut n = static_node();
    uart(&mut n, &[0xA1, 0x11], 1);
    drain(&mut n);
    n.handle_store_failed(Millis(2));
    assert_eq!(
        drain(&mut n),
        [
            Output::Frame(Packet::report(
                id(),
                Message::Fault {
                    code: FaultCode::ConfigStore,
                    arg: 0,
                    detail: 0
                }
            )),
            Output::Uart(UartReply::Error(UartError::StoreFailed).encode()),
        ]
    );
}

// ---- CAN assignment ----

fn select(n: &mut Node, head: [u8; 8], now: u64) {
    feed(
        n,
        Packet::command(NodeId::BROADCAST, Message::AssignSelect { uid_head: head }),
        now,
    );
}

fn commit(n: &mut Node, tail: [u8; 4], new_id: NodeId, seq: u8, now: u64) {
    let m = Message::AssignCommit {
        uid_tail: tail,
        new_id,
        seq,
    };
    feed(n, Packet::command(NodeId::BROADCAST, m), now);
}

fn head() -> [u8; 8] {
    UID[..8].try_into().unwrap()
}
fn tail() -> [u8; 4] {
    UID[8..].try_into().unwrap()
}

#[test]
fn can_assignment_select_and_commit() {
    let mut n = Node::new(config(BootRole::Static, 6, None), Millis(0));
    let new = NodeId::new_sc(0x042).unwrap();
    select(&mut n, head(), 1);
    assert!(drain(&mut n).is_empty());
    commit(&mut n, tail(), new, 77, 2);
    let out = drain(&mut n);
    assert_eq!(out[..2], [Output::StoreId(new), Output::FiltersChanged]);
    assert_eq!(
        out[2],
        Output::Frame(Packet::report(
            new,
            Message::AssignReply {
                seq: 77,
                result: AckResult::Ok,
                new_id: new,
                uid_tail: tail()
            }
        ))
    );
    assert!(
        matches!(out[3], Output::Frame(Packet { src, msg: Message::BootUp { .. }, .. }) if src == new)
    );
    assert_eq!(out.len(), 4);
    assert_eq!(n.node_id(), Some(new));
}

#[test]
fn can_assignment_wrong_uid_stays_silent() {
    let mut n = Node::new(config(BootRole::Static, 6, None), Millis(0));
    let new = NodeId::new_sc(0x042).unwrap();
    let mut other_head = head();
    other_head[0] ^= 0xFF;
    select(&mut n, other_head, 1);
    commit(&mut n, tail(), new, 1, 2);
    assert!(drain(&mut n).is_empty());
    // Selected, but the tail differs: deselected and silent...
    select(&mut n, head(), 3);
    commit(&mut n, [0, 0, 0, 0], new, 2, 4);
    assert!(drain(&mut n).is_empty());
    // ...so even the right tail now needs a new select.
    commit(&mut n, tail(), new, 3, 5);
    assert!(drain(&mut n).is_empty());
    assert_eq!(n.node_id(), None);
}

#[test]
fn configured_node_can_be_renumbered() {
    let mut n = static_node();
    let new = NodeId::new_sc(0x300).unwrap();
    select(&mut n, head(), 1);
    commit(&mut n, tail(), new, 5, 2);
    let m = msgs(&mut n);
    assert!(matches!(
        m[..],
        [Message::AssignReply { seq: 5, .. }, Message::BootUp { .. }]
    ));
    assert_eq!(n.node_id(), Some(new));
    // A repeated commit (the reply was lost) is answered again, without a new boot-up.
    commit(&mut n, tail(), new, 6, 3);
    let m = msgs(&mut n);
    assert!(matches!(m[..], [Message::AssignReply { seq: 6, .. }]));
}

// ---- CAN status ----

#[test]
fn error_passive_fault_once_per_episode() {
    let mut n = static_node();
    n.handle_can_status(100, 0, false, Millis(1));
    assert!(drain(&mut n).is_empty());
    n.handle_can_status(128, 3, false, Millis(2));
    n.handle_can_status(140, 3, false, Millis(3));
    assert_eq!(
        msgs(&mut n),
        [Message::Fault {
            code: FaultCode::ErrorPassive,
            arg: 0,
            detail: 128 << 8 | 3
        }]
    );
    n.handle_can_status(90, 0, false, Millis(4));
    n.handle_can_status(0, 200, false, Millis(5));
    assert_eq!(
        msgs(&mut n),
        [Message::Fault {
            code: FaultCode::ErrorPassive,
            arg: 0,
            detail: 200
        }]
    );
}

#[test]
fn bus_off_reported_after_recovery_with_count() {
    let mut n = static_node();
    n.handle_can_status(255, 0, true, Millis(1));
    n.handle_can_status(255, 0, true, Millis(2));
    assert!(
        !msgs(&mut n).iter().any(|m| matches!(
            m,
            Message::Fault {
                code: FaultCode::BusOff,
                ..
            }
        )),
        "nothing can be sent while bus-off"
    );
    n.handle_can_status(0, 0, false, Millis(3));
    assert_eq!(
        msgs(&mut n),
        [Message::Fault {
            code: FaultCode::BusOff,
            arg: 0,
            detail: 1
        }]
    );
    n.handle_can_status(255, 0, true, Millis(4));
    n.handle_can_status(0, 0, false, Millis(5));
    assert_eq!(
        msgs(&mut n)
            .into_iter()
            .filter(|m| matches!(
                m,
                Message::Fault {
                    code: FaultCode::BusOff,
                    ..
                }
            ))
            .collect::<Vec<_>>(),
        [Message::Fault {
            code: FaultCode::BusOff,
            arg: 0,
            detail: 2
        }]
    );
}

// ---- footprint ----

#[test]
fn node_is_small_enough_for_the_firmware() {
    // sc-fw has 16 KiB of static RAM for everything; the node state must stay a small part of it.
    // About half is the firmware update's receiver: the received-chunks bitmap of a 128 KiB slot
    // (683 bytes), the signed header (192), four chunks being assembled, and the output queue's
    // room for a 24-byte chunk to write.
    let size = std::mem::size_of::<Node>();
    println!(
        "size_of::<Node>() = {size}, Output = {}",
        std::mem::size_of::<Output>()
    );
    assert!(size <= 3072, "Node grew to {size} bytes");
}

/// A confirmed, linked dock on port 3 of a fresh static node (relay on), outputs drained.
fn docked_static() -> (Node, u64) {
    let mut n = static_node();
    let t = settle_loop(&mut n, 3, true, 0);
    cmd(
        &mut n,
        Message::DockConfirm {
            seq: 1,
            port: port(3),
        },
        t,
    );
    let partner = ihex_proto::DockPartner {
        node: NodeId::new_sc(0x2).unwrap(),
        port: port(0),
    };
    cmd(
        &mut n,
        Message::DockLink {
            seq: 2,
            port: port(3),
            partner: Some(partner),
        },
        t,
    );
    drain(&mut n);
    assert!(n.actuators().relay);
    (n, t)
}

#[test]
fn a_software_reset_keeps_the_relay_and_the_docking_when_the_adapter_restores_them() {
    let (old, t) = docked_static();
    let kept = old.retained();
    let mut c = config(BootRole::Static, 6, Some(id()));
    c.reset = ResetReason::Software;
    let mut n = Node::new(c, Millis(t));
    n.handle_loop_level(port(3), true, Millis(t));
    n.restore(kept, Millis(t));
    assert!(n.actuators().relay, "the relay is on from the first output");
    n.tick(Millis(t + 500));
    let m = msgs(&mut n);
    assert!(
        !m.iter().any(|m| matches!(
            m,
            Message::DockDetected { .. } | Message::DockRemoved { .. }
        )),
        "a restored dock is neither detected again nor removed: {m:?}"
    );
    assert!(n.actuators().relay);
    assert_eq!(n.retained(), kept, "the link survives too");
}

#[test]
fn a_restored_port_whose_mobile_left_during_the_reset_is_withdrawn() {
    let (old, t) = docked_static();
    let mut n = Node::new(config(BootRole::Static, 6, Some(id())), Millis(t));
    n.restore(old.retained(), Millis(t));
    drain(&mut n);
    n.tick(Millis(t + ihex_sc_core::DEBOUNCE_MS + 1));
    assert_eq!(msgs(&mut n), vec![Message::DockRemoved { port: port(3) }]);
    assert!(!n.actuators().relay);
}

#[test]
fn without_a_restore_a_reset_drops_the_relay_and_detects_the_dock_again() {
    let (_old, t) = docked_static();
    let mut n = Node::new(config(BootRole::Static, 6, Some(id())), Millis(t));
    drain(&mut n);
    settle_loop(&mut n, 3, true, t);
    assert!(!n.actuators().relay);
    assert_eq!(msgs(&mut n), vec![Message::DockDetected { port: port(3) }]);
}
