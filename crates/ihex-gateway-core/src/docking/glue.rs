//! Docking glue: carries out the [`Step`]s of the one-at-a-time docking sequence
//! ([`crate::docking`]) as frames (confirm, refuse, relay off, dock links) and events
//! (`new_connection`, `connection_removed`, `dock_failed`, the `unexpected_handshake` fault).
//!
//! Once a docking completes, the static element is told who docked on its port (`DockLink`), so
//! that it can report the connection to a gateway that restarts; a link that is no longer true is
//! cleared the same way. Nodes known to speak protocol 1.0 are not sent links.

use std::time::Instant;

use ihex_proto::{DockPartner, DockRefuseReason, Kind, Message, NodeId, Packet, Port};

use super::{Docking, Step};
use crate::bridge::diagnostics::Diagnostics;
use crate::bridge::output::{FrameFate, FrameOwner, Outputs};
use crate::bridge::readback::ReadBack;
use crate::command::pending::Pending;
use crate::event::{DockFailed, Event, HexId};

/// What the docking steps need besides the outputs.
pub(crate) struct DockParts<'a> {
    /// Sequence numbers for the frames.
    pub(crate) pending: &'a mut Pending,
    /// The sequence itself (told which confirm was sent).
    pub(crate) docking: &'a mut Docking,
    /// The rate limit of the `unexpected_handshake` fault.
    pub(crate) diagnostics: &'a mut Diagnostics,
    /// Which nodes understand dock links.
    pub(crate) readback: &'a ReadBack,
}

/// Carries out the docking sequence's steps.
pub(crate) fn apply(steps: Vec<Step>, parts: DockParts<'_>, now: Instant, out: &mut Outputs) {
    let DockParts {
        pending,
        docking,
        diagnostics,
        readback,
    } = parts;
    for step in steps {
        match step {
            Step::Confirm { node, port } => {
                let msg = |seq| Message::DockConfirm { seq, port };
                // Without a free sequence number the confirm is not sent; the docking then ends
                // with its handshake timeout.
                if let Some(seq) = pending.send_internal(
                    FrameOwner::Docking,
                    node,
                    Kind::DockConfirm,
                    msg,
                    now,
                    out,
                ) {
                    docking.confirm_sent(node, port, seq);
                }
            }
            Step::Adopt { node, port } => {
                let msg = |seq| Message::DockConfirm { seq, port };
                pending.send_internal(FrameOwner::Docking, node, Kind::DockConfirm, msg, now, out);
            }
            Step::RefuseBusy { node, port } => {
                send_dock_refuse(pending, out, node, port, DockRefuseReason::Busy, now)
            }
            Step::Withdraw { node, port } => {
                send_dock_refuse(pending, out, node, port, DockRefuseReason::NotAllowed, now)
            }
            Step::PowerOff { node } => {
                let msg = |seq| Message::PowerSet { seq, on: false };
                pending.send_internal(FrameOwner::Docking, node, Kind::PowerSet, msg, now, out);
            }
            Step::Connected(c) => {
                out.mark_changed(c.n.id.0);
                out.mark_changed(c.n_1.id.0);
                out.emit(Event::NewConnection(c));
                out.dock_changes.push((true, c));
                if let (Some(port), Some(mport)) = (Port::new(c.n_1.port), Port::new(c.n.port)) {
                    let partner = DockPartner {
                        node: c.n.id.0,
                        port: mport,
                    };
                    send_dock_link(pending, readback, out, c.n_1.id.0, port, Some(partner), now);
                }
            }
            Step::Restored(c) => {
                out.mark_changed(c.n.id.0);
                out.mark_changed(c.n_1.id.0);
            }
            Step::Unlink { node, port } => {
                send_dock_link(pending, readback, out, node, port, None, now);
            }
            Step::Removed(c) => {
                out.mark_changed(c.n.id.0);
                out.mark_changed(c.n_1.id.0);
                out.emit(Event::ConnectionRemoved(c));
                out.dock_changes.push((false, c));
            }
            Step::Failed {
                node,
                port,
                reason,
                relay,
            } => {
                out.emit(Event::DockFailed(DockFailed {
                    node: HexId(node),
                    port: port.get(),
                    reason,
                    relay,
                }));
            }
            Step::UnexpectedHandshake { node, port, why } => {
                diagnostics.on_unexpected_handshake(node, port, why, now, out);
            }
        }
    }
}

/// What the fate of one of the sequence's frames means to it: a confirm that could not be sent
/// ends the docking it was for (the steps that follow; none when it was not that docking's).
pub(crate) fn on_fate(
    docking: &mut Docking,
    packet: &Packet,
    fate: FrameFate<'_>,
    now: Instant,
) -> Vec<Step> {
    match (fate, packet.msg) {
        (FrameFate::Failed(reason), Message::DockConfirm { seq, .. }) => {
            docking.on_confirm_failed(packet.dest, seq, reason, now)
        }
        _ => Vec::new(),
    }
}

/// Tells static `node` which mobile element is docked on its `port` (`None`: none any more).
fn send_dock_link(
    pending: &mut Pending,
    readback: &ReadBack,
    out: &mut Outputs,
    node: NodeId,
    port: Port,
    partner: Option<DockPartner>,
    now: Instant,
) {
    if readback.supports(node) {
        let msg = |seq| Message::DockLink { seq, port, partner };
        pending.send_internal(FrameOwner::Docking, node, Kind::DockLink, msg, now, out);
    }
}

/// Tells static `node` not to power (or to stop powering) its dock `port`.
fn send_dock_refuse(
    pending: &mut Pending,
    out: &mut Outputs,
    node: NodeId,
    port: Port,
    reason: DockRefuseReason,
    now: Instant,
) {
    let msg = |seq| Message::DockRefuse { seq, port, reason };
    pending.send_internal(FrameOwner::Docking, node, Kind::DockRefuse, msg, now, out);
}

#[cfg(test)]
mod tests {
    use crate::bridge::test_support::*;
    use crate::bridge::*;
    use crate::docking::Docking;
    use ihex_proto::{
        AckResult, BootRole, DockRefuseReason, HealthFlags, Kind, Message, Packet, ResetReason,
    };
    use serde_json::json;

    #[test]
    fn docking_sequence_publishes_the_seed_events() {
        let (mut b, t0) = with_nodes(&[0x111]);
        b.handle_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0 + S,
        );
        let out = drain(&mut b);
        assert_eq!(out.sent.len(), 1);
        let Message::DockConfirm { seq, port: p } = out.sent[0].msg else {
            panic!("{:?}", out.sent)
        };
        assert_eq!((out.sent[0].dest, p), (id(0x111), port(3)));
        // The next health check (t0 + 1 s) is due before the handshake deadline (t0 + 6 s).
        assert_eq!(b.poll_timeout(), t0 + S);
        b.handle_packet(
            Packet::report(id(0x111), ack(Kind::DockConfirm, seq, AckResult::Ok)),
            t0 + S + MS,
        );
        assert!(drain(&mut b).events.is_empty());
        // The mobile element boots (first heard: node_online) and handshakes.
        let boot = Message::BootUp {
            version: (1, 0),
            role: BootRole::Mobile,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        b.handle_packet(Packet::report(id(2), boot), t0 + 2 * S);
        b.handle_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0 + 2 * S,
        );
        let out = drain(&mut b);
        let names: Vec<_> = out
            .events
            .iter()
            .map(|e| e["event"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["node_online", "new_connection"]);
        assert_eq!(
            out.raw_events[1],
            r#"{"event":"new_connection","payload":{"n":{"id":"2","port":0},"n-1":{"id":"111","port":3}}}"#
        );
        let st = |n: u16| {
            out.states
                .iter()
                .rev()
                .find(|(i, _)| *i == id(n))
                .map(|(_, s)| s.clone())
                .unwrap()
        };
        assert_eq!(
            st(0x111)["connections"],
            json!([{"port": 3, "peer": "2", "peer_port": 0}])
        );
        assert_eq!(
            st(2)["connections"],
            json!([{"port": 0, "peer": "111", "peer_port": 3}])
        );
        // Undocking.
        b.handle_packet(
            Packet::report(id(0x111), Message::DockRemoved { port: port(3) }),
            t0 + 3 * S,
        );
        let out = drain(&mut b);
        assert_eq!(
            out.raw_events,
            [
                r#"{"event":"connection_removed","payload":{"n":{"id":"2","port":0},"n-1":{"id":"111","port":3}}}"#
            ]
        );
    }

    #[test]
    fn handshake_timeout_powers_off_and_reports() {
        let (mut b, t0) = with_nodes(&[0x10]);
        b.handle_packet(
            Packet::report(id(0x10), Message::DockDetected { port: port(1) }),
            t0,
        );
        drain(&mut b);
        let deadline = t0 + BridgeConfig::default().dock_timeout;
        assert_eq!(deadline, t0 + 5 * S);
        // Keep the node online meanwhile.
        for k in 1..=4u32 {
            b.handle_timeout(t0 + S * k);
            b.handle_packet(Packet::report(id(0x10), reply(k as u8, 0)), t0 + S * k);
        }
        let out = drain(&mut b);
        assert!(out.named("dock_failed").is_empty(), "{:?}", out.events);
        b.handle_timeout(deadline - MS);
        assert!(drain(&mut b).named("dock_failed").is_empty());
        b.handle_timeout(deadline);
        let out = drain(&mut b);
        assert!(out
            .sent
            .iter()
            .any(|p| p.dest == id(0x10) && matches!(p.msg, Message::PowerSet { on: false, .. })));
        assert_eq!(
            out.one("dock_failed"),
            &json!({"node": "10", "port": 1, "reason": "handshake timeout after 5000 ms",
                    "relay": false})
        );
        // A handshake now is unexpected: no connection, and a fault once nothing claimed it in a
        // quarter of the docking timeout (its report might still have come).
        b.handle_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            deadline + MS,
        );
        let out = drain(&mut b);
        assert!(out.named("fault").is_empty(), "{:?}", out.events);
        assert!(out.named("new_connection").is_empty());
        let window_end = deadline + MS + BridgeConfig::default().dock_timeout / 4;
        assert!(b.poll_timeout() <= window_end);
        b.handle_timeout(window_end - MS);
        assert!(drain(&mut b).named("fault").is_empty());
        b.handle_timeout(window_end);
        let out = drain(&mut b);
        assert_eq!(out.one("fault")["code"], "unexpected_handshake");
        assert!(out.named("new_connection").is_empty());
    }

    /// Issue 29: a relay the user switched on before a docking stays on when the docking fails
    /// (withdrawing the confirmation of its last port would switch it off), and `dock_failed`
    /// says so.
    #[test]
    fn a_failed_docking_leaves_a_relay_the_user_switched_on_on() {
        let (mut b, t0) = with_nodes(&[0x10]);
        let sent = command(
            &mut b,
            json!({"cmd": "power", "node": "10", "on": true}),
            t0,
        )
        .sent;
        let m = sent[0].msg;
        b.handle_packet(
            Packet::report(id(0x10), ack(m.kind(), m.ack_seq().unwrap(), AckResult::Ok)),
            t0,
        );
        b.handle_packet(
            Packet::report(id(0x10), Message::DockDetected { port: port(1) }),
            t0,
        );
        drain(&mut b);
        let deadline = t0 + BridgeConfig::default().dock_timeout;
        for k in 1..=4u32 {
            b.handle_timeout(t0 + S * k);
            b.handle_packet(Packet::report(id(0x10), reply(k as u8, 1)), t0 + S * k);
        }
        drain(&mut b);
        b.handle_timeout(deadline);
        let out = drain(&mut b);
        let touched: Vec<_> = out
            .sent
            .iter()
            .filter(|p| {
                p.dest == id(0x10)
                    && matches!(p.msg, Message::PowerSet { .. } | Message::DockRefuse { .. })
            })
            .collect();
        assert!(touched.is_empty(), "{touched:?}");
        assert_eq!(
            out.one("dock_failed"),
            &json!({"node": "10", "port": 1, "reason": "handshake timeout after 5000 ms",
                    "relay": true})
        );
    }

    #[test]
    fn docking_queue_full_refuses_busy() {
        let (mut b, t0) = with_nodes(&[1]);
        for p in 0..=Docking::DEFAULT_QUEUE as u8 {
            b.handle_packet(
                Packet::report(id(1), Message::DockDetected { port: port(p % 8) }),
                t0,
            );
        }
        let out = drain(&mut b);
        assert_eq!(
            out.sent.len(),
            1,
            "one confirm, the other ports wait: {:?}",
            out.sent
        );
        // Ports 1..=7 queued; 8 distinct ports exist, so fill the queue from a second node.
        b.handle_packet(
            Packet::report(id(9), Message::DockDetected { port: port(0) }),
            t0,
        );
        let out = drain(&mut b);
        assert!(out.sent.is_empty(), "queued (queue had 7 of 8)");
        b.handle_packet(
            Packet::report(id(9), Message::DockDetected { port: port(1) }),
            t0,
        );
        let out = drain(&mut b);
        assert!(
            matches!(
                out.sent[..],
                [Packet {
                    msg: Message::DockRefuse {
                        reason: DockRefuseReason::Busy,
                        ..
                    },
                    ..
                }]
            ),
            "{:?}",
            out.sent
        );
    }

    #[test]
    fn lost_mobile_element_removes_its_connection() {
        let (mut b, t0) = with_nodes(&[0x111, 2]);
        dock(&mut b, 0x111, 3, 2, t0 + MS);
        let mut removed = None;
        for k in 1..=4u32 {
            b.handle_timeout(t0 + S * k);
            b.handle_packet(
                Packet::report(id(0x111), reply(k as u8, 0)),
                t0 + S * k + MS,
            );
            let out = drain(&mut b);
            if !out.named("node_lost").is_empty() {
                removed = Some(out);
            }
        }
        let out = removed.expect("node 2 lost");
        assert_eq!(out.one("node_lost")["id"], "2");
        assert_eq!(
            out.one("connection_removed")["n"],
            json!({"id": "2", "port": 0})
        );
    }

    #[test]
    fn undocking_during_a_pending_docking_cancels_it_and_the_queue_moves_on() {
        let (mut b, t0) = with_nodes(&[1, 9]);
        b.handle_packet(
            Packet::report(id(1), Message::DockDetected { port: port(0) }),
            t0,
        );
        b.handle_packet(
            Packet::report(id(9), Message::DockDetected { port: port(4) }),
            t0,
        );
        let out = drain(&mut b);
        assert_eq!(out.sent.len(), 1, "only the first is confirmed");
        b.handle_packet(
            Packet::report(id(1), Message::DockRemoved { port: port(0) }),
            t0 + MS,
        );
        let out = drain(&mut b);
        let f = out.one("dock_failed");
        assert_eq!(
            (f["node"].as_str(), f["port"].as_u64()),
            (Some("1"), Some(0))
        );
        assert!(f["reason"].as_str().unwrap().starts_with("cancelled"));
        assert!(matches!(
            out.sent[..],
            [Packet { msg: Message::DockConfirm { .. }, dest, .. }] if dest == id(9)
        ));
        // The confirm to 9 cannot be sent: that docking fails too.
        b.handle_send_failed(out.sent[0], "CAN transmit queue full", t0 + 2 * MS);
        let out = drain(&mut b);
        assert_eq!(
            out.one("dock_failed")["reason"],
            "confirm not sent: CAN transmit queue full"
        );
        // Idle again: a new report is confirmed at once.
        b.handle_packet(
            Packet::report(id(1), Message::DockDetected { port: port(0) }),
            t0 + S,
        );
        assert_eq!(drain(&mut b).sent.len(), 1);
    }

    #[test]
    fn timeout_with_other_elements_docked_withdraws_only_that_port() {
        let (mut b, t0) = with_nodes(&[0x111]);
        dock(&mut b, 0x111, 3, 2, t0);
        b.handle_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(4) }),
            t0,
        );
        drain(&mut b);
        b.handle_timeout(t0 + BridgeConfig::default().dock_timeout);
        let out = drain(&mut b);
        assert!(out.sent.iter().any(|p| p.dest == id(0x111)
            && matches!(
                p.msg,
                Message::DockRefuse { reason: DockRefuseReason::NotAllowed, port: p4, .. } if p4 == port(4)
            )));
        assert!(!out
            .sent
            .iter()
            .any(|p| matches!(p.msg, Message::PowerSet { .. })));
        assert_eq!(out.one("dock_failed")["port"], 4);
    }

    #[test]
    fn an_element_powered_while_docked_is_adopted_by_the_free_closed_loop() {
        // The demo island's start: 2 sits on 0x111 port 3 with the relay off; the gateway only
        // knows the closed loop from 0x111's health replies. A `power` command switches the relay
        // on, 2 boots and handshakes with no docking pending. (0x112's loop 1 is closed too, but
        // its relay is off: nobody there has power.)
        let (mut b, t0) = with_nodes(&[0x111, 0x112]);
        let mut health = reply(1, HealthFlags::RELAY);
        if let Message::HealthReply(h) = &mut health {
            h.loops = 1 << 3;
        }
        let mut unpowered = reply(1, 0);
        if let Message::HealthReply(h) = &mut unpowered {
            h.loops = 1 << 1;
        }
        b.handle_timeout(t0 + S);
        b.handle_packet(Packet::report(id(0x111), health), t0 + S);
        b.handle_packet(Packet::report(id(0x112), unpowered), t0 + S);
        drain(&mut b);
        let boot = Message::BootUp {
            version: (1, 2),
            role: BootRole::Mobile,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        b.handle_packet(Packet::report(id(2), boot), t0 + S + MS);
        b.handle_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0 + S + MS,
        );
        let out = drain(&mut b);
        assert!(out.named("fault").is_empty(), "{:?}", out.events);
        assert_eq!(
            out.raw_named("new_connection"),
            [
                r#"{"event":"new_connection","payload":{"n":{"id":"2","port":0},"n-1":{"id":"111","port":3}}}"#
            ]
        );
        // The port is confirmed (it holds the relay like any docking), then linked.
        let to_111: Vec<_> = out
            .sent
            .iter()
            .filter(|p| p.dest == id(0x111))
            .map(|p| p.msg)
            .collect();
        assert!(
            matches!(
                to_111[..],
                [
                    Message::DockConfirm { port: p3, .. },
                    Message::DockLink { port: l3, partner: Some(m), .. }
                ] if p3 == port(3) && l3 == port(3) && m.node == id(2)
            ),
            "{to_111:?}"
        );
        let st = out
            .states
            .iter()
            .rev()
            .find(|(i, _)| *i == id(0x111))
            .unwrap();
        assert_eq!(
            st.1["connections"],
            json!([{"port": 3, "peer": "2", "peer_port": 0}])
        );
        // 0x111's own report of that closed loop, if it comes now, starts no docking.
        b.handle_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0 + S + 2 * MS,
        );
        let out = drain(&mut b);
        assert!(out.sent.is_empty() && out.events.is_empty(), "{out:?}");
    }

    #[test]
    fn a_docked_element_whose_handshake_was_lost_is_found_by_its_health_replies() {
        // 3 got power on 0x111 port 3 while the bus was down: its handshake is gone, but its
        // health replies show a closed loop, as do 0x111's (relay on).
        let (mut b, t0) = with_nodes(&[0x111]);
        let with_loops = |flags: u8, loops: u8| {
            let mut r = reply(1, flags);
            if let Message::HealthReply(h) = &mut r {
                h.loops = loops;
            }
            r
        };
        b.handle_timeout(t0 + S);
        b.handle_packet(
            Packet::report(id(0x111), with_loops(HealthFlags::RELAY, 1 << 3)),
            t0 + S,
        );
        b.handle_packet(
            Packet::report(id(3), with_loops(HealthFlags::MOBILE, 1 << 1)),
            t0 + S,
        );
        b.handle_timeout(t0 + S + MS);
        let out = drain(&mut b);
        assert_eq!(
            out.raw_named("new_connection"),
            [
                r#"{"event":"new_connection","payload":{"n":{"id":"3","port":1},"n-1":{"id":"111","port":3}}}"#
            ]
        );
        assert!(out.sent.iter().any(|p| p.dest == id(0x111)
            && matches!(p.msg, Message::DockLink { partner: Some(m), .. } if m.node == id(3))));
        b.handle_timeout(t0 + 2 * S);
        assert!(drain(&mut b).named("new_connection").is_empty());
    }
}
