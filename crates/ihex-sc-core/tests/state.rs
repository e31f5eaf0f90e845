//! State read-back (`StateQuery` → `StateReport`s) and dock links (`DockLink`), per the crate docs.

mod common;

use common::*;
use ihex_proto::{
    AckResult, BootRole, BuzzerCommand, DockPartner, DockState, Kind, LedCommand, Message, NodeId,
    Packet, PowerState, Rgb, StateParts, StateReport, Uid, PROTOCOL_VERSION,
};
use ihex_sc_core::{Millis, Node};

fn ack(kind: Kind, seq: u8, result: AckResult, detail: u8) -> Message {
    Message::Ack {
        kind,
        seq,
        result,
        detail,
    }
}

fn query(n: &mut Node, seq: u8, parts: u8, now: u64) {
    cmd(
        n,
        Message::StateQuery {
            seq,
            parts: StateParts(parts),
        },
        now,
    );
}

/// The state reports queued, `End` included.
fn reports(n: &mut Node) -> Vec<StateReport> {
    msgs(n)
        .into_iter()
        .map(|m| match m {
            Message::StateReport(r) => r,
            other => panic!("expected only state reports, got {other:?}"),
        })
        .collect()
}

fn end(seq: u8, parts: u8, count: u8) -> StateReport {
    StateReport::End {
        seq,
        parts: StateParts(parts),
        count,
    }
}

fn partner(node: u16, p: u8) -> Option<DockPartner> {
    Some(DockPartner {
        node: NodeId::new_sc(node).unwrap(),
        port: port(p),
    })
}

fn link(n: &mut Node, seq: u8, p: u8, partner: Option<DockPartner>, now: u64) {
    cmd(
        n,
        Message::DockLink {
            seq,
            port: port(p),
            partner,
        },
        now,
    );
}

fn confirm(n: &mut Node, seq: u8, p: u8, now: u64) {
    cmd(n, Message::DockConfirm { seq, port: port(p) }, now);
}

/// A static node with a mobile docked, confirmed and linked on port 3 and something (not yet
/// confirmed) on port 5; outputs drained. Returns the time reached.
fn docked_node() -> (Node, u64) {
    let mut n = static_node();
    let t = settle_loop(&mut n, 3, true, 100);
    let t = settle_loop(&mut n, 5, true, t);
    confirm(&mut n, 1, 3, t);
    link(&mut n, 2, 3, partner(0x002, 0), t);
    assert_eq!(
        msgs(&mut n),
        [
            Message::DockDetected { port: port(3) },
            Message::DockDetected { port: port(5) },
            ack(Kind::DockConfirm, 1, AckResult::Ok, 0),
            ack(Kind::DockLink, 2, AckResult::Ok, 0),
        ]
    );
    (n, t)
}

// ---- state query ----

#[test]
fn full_query_reports_every_part_in_order_then_end() {
    let (mut n, t) = docked_node();
    let led = LedCommand::Blink {
        color: Rgb::new(10, 20, 30),
        brightness: 128,
        period_10ms: 50,
        duty_pct: 25,
    };
    cmd(&mut n, Message::LedSet { seq: 3, cmd: led }, t);
    let bz = BuzzerCommand::Pattern {
        freq_hz: 440,
        on_10ms: 10,
        off_10ms: 20,
        count: 0,
    };
    cmd(&mut n, Message::BuzzerSet { seq: 4, cmd: bz }, t);
    msgs(&mut n);

    query(&mut n, 0x31, 0b111, t + 1);
    let uid = Uid(UID);
    assert_eq!(
        reports(&mut n),
        [
            StateReport::Led(led),
            StateReport::Buzzer(bz),
            StateReport::Power(PowerState {
                relay: true,
                loops: 0b0010_1000,
                confirmed: 0b0000_1000,
                identify_s: 0,
                role: BootRole::Static,
                ports: 6,
            }),
            StateReport::Dock {
                port: port(3),
                state: DockState {
                    closed: true,
                    confirmed: true,
                    partner: partner(0x002, 0),
                },
            },
            StateReport::Dock {
                port: port(5),
                state: DockState {
                    closed: true,
                    confirmed: false,
                    partner: None,
                },
            },
            StateReport::Firmware {
                version: FIRMWARE.version,
                trial: false,
            },
            StateReport::ImageHash(FIRMWARE.image_hash),
            StateReport::UidLow(uid.low()),
            StateReport::UidHigh(uid.high()),
            StateReport::Protocol {
                version: PROTOCOL_VERSION
            },
            end(0x31, 0b111, 10),
        ]
    );
    // A query changes nothing.
    n.actuators_changed();
    query(&mut n, 0x32, 0b111, t + 2);
    assert_eq!(reports(&mut n).len(), 11);
    assert!(!n.actuators_changed());
}

#[test]
fn each_group_alone_and_nothing_at_all() {
    let (mut n, t) = docked_node();
    query(&mut n, 1, StateParts::ACTUATORS, t);
    let r = reports(&mut n);
    assert_eq!(r.len(), 4);
    assert_eq!(r[0], StateReport::Led(LedCommand::Off));
    assert_eq!(r[1], StateReport::Buzzer(BuzzerCommand::Off));
    assert!(matches!(
        r[2],
        StateReport::Power(PowerState { relay: true, .. })
    ));
    assert_eq!(r[3], end(1, 0b001, 3));

    query(&mut n, 2, StateParts::DOCKING, t);
    let r = reports(&mut n);
    let ports: Vec<u8> = r
        .iter()
        .filter_map(|r| match r {
            StateReport::Dock { port, .. } => Some(port.get()),
            _ => None,
        })
        .collect();
    assert_eq!(ports, [3, 5]);
    assert_eq!(r.last(), Some(&end(2, 0b010, 2)));

    query(&mut n, 3, StateParts::IDENTITY, t);
    let r = reports(&mut n);
    assert_eq!(r.len(), 6);
    assert!(matches!(r[0], StateReport::Firmware { .. }));
    assert_eq!(r[5], end(3, 0b100, 5));

    // Nothing asked: just the closing report, so the gateway still knows the node heard it.
    query(&mut n, 4, 0, t);
    assert_eq!(reports(&mut n), [end(4, 0, 0)]);
}

#[test]
fn groups_this_version_does_not_know_are_ignored() {
    let mut n = static_node();
    // Bit 3 and up are not defined: only the identity group is answered, and End says so.
    query(&mut n, 9, 0xF8 | StateParts::IDENTITY, 10);
    let r = reports(&mut n);
    assert_eq!(r.len(), 6);
    assert_eq!(r[5], end(9, StateParts::IDENTITY, 5));
    query(&mut n, 10, 0xF8, 10);
    assert_eq!(reports(&mut n), [end(10, 0, 0)]);
}

#[test]
fn nothing_docked_means_no_dock_reports() {
    let mut n = static_node();
    query(&mut n, 5, StateParts::DOCKING, 10);
    assert_eq!(reports(&mut n), [end(5, 0b010, 0)]);
}

#[test]
fn broadcast_query_is_answered_and_unconfigured_node_stays_silent() {
    let mut n = static_node();
    feed(
        &mut n,
        Packet::command(
            NodeId::BROADCAST,
            Message::StateQuery {
                seq: 7,
                parts: StateParts::ALL,
            },
        ),
        10,
    );
    let r = reports(&mut n);
    assert_eq!(r.last(), Some(&end(7, 0b111, 8)));

    let mut fresh = Node::new(config(BootRole::Static, 6, None), Millis(0));
    feed(
        &mut fresh,
        Packet::command(
            NodeId::BROADCAST,
            Message::StateQuery {
                seq: 7,
                parts: StateParts::ALL,
            },
        ),
        10,
    );
    assert!(drain(&mut fresh).is_empty());
}

#[test]
fn mobile_reports_its_loops_in_power_and_no_dock_parts() {
    let mut n = Node::new(config(BootRole::Mobile, 2, Some(id())), Millis(0));
    drain(&mut n);
    let t = settle_loop(&mut n, 1, true, 10);
    drain(&mut n);
    query(&mut n, 1, StateParts::ACTUATORS | StateParts::DOCKING, t);
    assert_eq!(
        reports(&mut n),
        [
            StateReport::Led(LedCommand::Off),
            StateReport::Buzzer(BuzzerCommand::Off),
            StateReport::Power(PowerState {
                relay: false,
                loops: 0b10,
                confirmed: 0,
                identify_s: 0,
                role: BootRole::Mobile,
                ports: 2,
            }),
            end(1, 0b011, 3),
        ]
    );
}

#[test]
fn reports_show_the_command_not_the_identify_override() {
    let mut n = static_node();
    let led = LedCommand::Steady {
        color: Rgb::new(0, 255, 0),
        brightness: 10,
    };
    cmd(&mut n, Message::LedSet { seq: 1, cmd: led }, 0);
    cmd(&mut n, Message::Identify { seq: 2, seconds: 3 }, 1000);
    msgs(&mut n);
    let power = |r: &[StateReport]| match r[2] {
        StateReport::Power(p) => p,
        ref other => panic!("expected Power, got {other:?}"),
    };

    query(&mut n, 1, StateParts::ACTUATORS, 1000);
    let r = reports(&mut n);
    assert_eq!(r[0], StateReport::Led(led), "commanded, exactly as sent");
    assert_eq!(power(&r).identify_s, 3);
    // Seconds remaining round up: 1 ms left is still "1".
    query(&mut n, 2, StateParts::ACTUATORS, 2000);
    assert_eq!(power(&reports(&mut n)).identify_s, 2);
    query(&mut n, 3, StateParts::ACTUATORS, 2001);
    assert_eq!(power(&reports(&mut n)).identify_s, 2);
    query(&mut n, 4, StateParts::ACTUATORS, 3999);
    assert_eq!(power(&reports(&mut n)).identify_s, 1);
    query(&mut n, 5, StateParts::ACTUATORS, 4000);
    assert_eq!(power(&reports(&mut n)).identify_s, 0);
}

#[test]
fn a_finite_buzzer_pattern_reports_off_once_it_has_ended() {
    let mut n = static_node();
    let bz = BuzzerCommand::Pattern {
        freq_hz: 1000,
        on_10ms: 10,
        off_10ms: 10,
        count: 2,
    };
    cmd(&mut n, Message::BuzzerSet { seq: 1, cmd: bz }, 0);
    msgs(&mut n);
    query(&mut n, 1, StateParts::ACTUATORS, 399);
    assert_eq!(reports(&mut n)[1], StateReport::Buzzer(bz));
    query(&mut n, 2, StateParts::ACTUATORS, 400);
    assert_eq!(reports(&mut n)[1], StateReport::Buzzer(BuzzerCommand::Off));
}

#[test]
fn identity_comes_from_the_config() {
    let mut cfg = config(BootRole::Static, 0, Some(id()));
    cfg.firmware.trial = true;
    cfg.uid = Uid([0xF0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 0x0F]);
    let mut n = Node::new(cfg, Millis(0));
    drain(&mut n);
    query(&mut n, 8, StateParts::IDENTITY, 1);
    assert_eq!(
        reports(&mut n),
        [
            StateReport::Firmware {
                version: FIRMWARE.version,
                trial: true
            },
            StateReport::ImageHash(FIRMWARE.image_hash),
            StateReport::UidLow([0xF0, 1, 2, 3, 4, 5, 6]),
            StateReport::UidHigh([7, 8, 9, 10, 0x0F]),
            StateReport::Protocol {
                version: PROTOCOL_VERSION
            },
            end(8, 0b100, 5),
        ]
    );
}

#[test]
fn largest_reply_fits_the_output_queue() {
    // 8 ports, all docked and confirmed: 3 + 8 + 5 reports and End.
    let mut n = Node::new(config(BootRole::Static, 8, Some(id())), Millis(0));
    drain(&mut n);
    let mut t = 0;
    for p in 0..8 {
        t = settle_loop(&mut n, p, true, t);
    }
    for p in 0..8 {
        confirm(&mut n, p, p, t);
    }
    drain(&mut n);
    query(&mut n, 1, 0xFF, t);
    let r = reports(&mut n);
    assert_eq!(r.len(), 17);
    assert_eq!(r[16], end(1, 0b111, 16));
    assert_eq!(n.dropped_outputs(), 0);
}

// ---- dock links ----

#[test]
fn link_is_kept_on_a_confirmed_port_and_cleared_on_request() {
    let (mut n, t) = docked_node();
    let dock3 = |n: &mut Node| {
        query(n, 1, StateParts::DOCKING, t);
        reports(n)
            .into_iter()
            .find_map(|r| match r {
                StateReport::Dock { port: p, state } if p == port(3) => Some(state),
                _ => None,
            })
            .expect("port 3 is docked")
    };
    assert_eq!(dock3(&mut n).partner, partner(0x002, 0));
    // Relinking replaces.
    link(&mut n, 3, 3, partner(0x004, 2), t);
    assert_eq!(msgs(&mut n), [ack(Kind::DockLink, 3, AckResult::Ok, 0)]);
    assert_eq!(dock3(&mut n).partner, partner(0x004, 2));
    // Clearing.
    link(&mut n, 4, 3, None, t);
    assert_eq!(msgs(&mut n), [ack(Kind::DockLink, 4, AckResult::Ok, 0)]);
    assert_eq!(
        dock3(&mut n),
        DockState {
            closed: true,
            confirmed: true,
            partner: None
        }
    );
    // Clearing a port that has no link (or is not even confirmed) is fine too.
    link(&mut n, 5, 0, None, t);
    assert_eq!(msgs(&mut n), [ack(Kind::DockLink, 5, AckResult::Ok, 0)]);
    // A link changes no actuator.
    assert!(n.actuators().relay);
}

#[test]
fn link_refusals() {
    // Not confirmed (port 5 is docked but not confirmed; port 0 is empty).
    let (mut n, t) = docked_node();
    link(&mut n, 1, 5, partner(0x003, 0), t);
    link(&mut n, 2, 0, partner(0x003, 0), t);
    // Beyond the node's 6 ports.
    link(&mut n, 3, 6, partner(0x003, 0), t);
    link(&mut n, 4, 7, None, t);
    assert_eq!(
        msgs(&mut n),
        [
            ack(Kind::DockLink, 1, AckResult::InvalidState, 1),
            ack(Kind::DockLink, 2, AckResult::InvalidState, 1),
            ack(Kind::DockLink, 3, AckResult::InvalidValue, 1),
            ack(Kind::DockLink, 4, AckResult::InvalidValue, 1),
        ]
    );
    // Mobile and port-less elements have no dock ports to link.
    for cfg in [
        config(BootRole::Mobile, 6, Some(id())),
        config(BootRole::Static, 0, Some(id())),
    ] {
        let mut m = Node::new(cfg, Millis(0));
        drain(&mut m);
        link(&mut m, 9, 0, partner(0x003, 0), 1);
        link(&mut m, 10, 0, None, 1);
        assert_eq!(
            msgs(&mut m),
            [
                ack(Kind::DockLink, 9, AckResult::Unsupported, 0),
                ack(Kind::DockLink, 10, AckResult::Unsupported, 0),
            ]
        );
    }
}

#[test]
fn link_goes_when_the_loop_opens() {
    let (mut n, t) = docked_node();
    let t = settle_loop(&mut n, 3, false, t + 10);
    assert_eq!(msgs(&mut n), [Message::DockRemoved { port: port(3) }]);
    query(&mut n, 1, StateParts::DOCKING, t);
    let r = reports(&mut n);
    assert!(
        !r.iter()
            .any(|r| matches!(r, StateReport::Dock { port: p, .. } if *p == port(3))),
        "{r:?}"
    );
    // Docked again and confirmed: no link until the gateway sends one.
    let t = settle_loop(&mut n, 3, true, t);
    confirm(&mut n, 2, 3, t);
    msgs(&mut n);
    query(&mut n, 2, StateParts::DOCKING, t);
    assert!(matches!(
        reports(&mut n)[0],
        StateReport::Dock {
            state: DockState {
                confirmed: true,
                partner: None,
                ..
            },
            ..
        }
    ));
}

#[test]
fn link_goes_when_the_confirmation_is_withdrawn() {
    let (mut n, t) = docked_node();
    cmd(
        &mut n,
        Message::DockRefuse {
            seq: 7,
            port: port(3),
            reason: ihex_proto::DockRefuseReason::NotAllowed,
        },
        t,
    );
    assert_eq!(msgs(&mut n), [ack(Kind::DockRefuse, 7, AckResult::Ok, 0)]);
    assert!(!n.actuators().relay);
    query(&mut n, 1, StateParts::DOCKING, t);
    assert_eq!(
        reports(&mut n)[0],
        StateReport::Dock {
            port: port(3),
            state: DockState {
                closed: true,
                confirmed: false,
                partner: None
            }
        }
    );
    // Relinking needs a new confirmation.
    link(&mut n, 8, 3, partner(0x002, 0), t);
    assert_eq!(
        msgs(&mut n),
        [ack(Kind::DockLink, 8, AckResult::InvalidState, 1)]
    );
}

#[test]
fn links_do_not_survive_a_reset() {
    let (n, _) = docked_node();
    // A reset is a new node from the same config: nothing is confirmed, nothing linked.
    let mut n = Node::new(*n.config(), Millis(0));
    drain(&mut n);
    let t = settle_loop(&mut n, 3, true, 0);
    drain(&mut n);
    query(&mut n, 1, StateParts::DOCKING, t);
    assert_eq!(
        reports(&mut n)[0],
        StateReport::Dock {
            port: port(3),
            state: DockState {
                closed: true,
                confirmed: false,
                partner: None
            }
        }
    );
}

#[test]
fn broadcast_dock_link_is_not_a_valid_frame() {
    // The protocol refuses a broadcast link, so a node never acts on one.
    let mut n = static_node();
    let (raw, data) = Packet::command(
        id(),
        Message::DockLink {
            seq: 1,
            port: port(0),
            partner: None,
        },
    )
    .encode();
    let broadcast = (raw & !(0xFFF << 12)) | (0xFFF << 12);
    n.handle_frame(broadcast, true, false, &data, Millis(1));
    assert!(
        drain(&mut n).is_empty(),
        "a bad broadcast is dropped silently"
    );
}
