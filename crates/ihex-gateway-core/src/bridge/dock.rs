//! Docking glue: carries out the [`Step`]s of the one-at-a-time docking sequence
//! ([`crate::docking`]) as frames (confirm, refuse, relay off) and events (`new_connection`,
//! `connection_removed`, `dock_failed`, the `unexpected_handshake` fault).

use std::time::Instant;

use ihex_proto::{DockRefuseReason, Kind, Message, NodeId, Packet, Port};

use super::commands::Commands;
use super::diagnostics::Diagnostics;
use super::output::Outputs;
use crate::docking::{Docking, Step};
use crate::event::{DockFailed, Event, HexId};

/// What the docking steps need besides the outputs.
pub(super) struct DockParts<'a> {
    /// Sequence numbers for the frames.
    pub(super) commands: &'a mut Commands,
    /// The sequence itself (told which confirm was sent).
    pub(super) docking: &'a mut Docking,
    /// The rate limit of the `unexpected_handshake` fault.
    pub(super) diagnostics: &'a mut Diagnostics,
}

/// Carries out the docking sequence's steps.
pub(super) fn apply(steps: Vec<Step>, parts: DockParts<'_>, now: Instant, out: &mut Outputs) {
    let DockParts {
        commands,
        docking,
        diagnostics,
    } = parts;
    for step in steps {
        match step {
            Step::Confirm { node, port } => {
                let seq = commands.any_seq(node, Kind::DockConfirm);
                docking.confirm_sent(seq);
                out.send(Packet::command(node, Message::DockConfirm { seq, port }));
            }
            Step::RefuseBusy { node, port } => {
                send_dock_refuse(commands, out, node, port, DockRefuseReason::Busy)
            }
            Step::Withdraw { node, port } => {
                send_dock_refuse(commands, out, node, port, DockRefuseReason::NotAllowed)
            }
            Step::PowerOff { node } => {
                let seq = commands.any_seq(node, Kind::PowerSet);
                out.send(Packet::command(node, Message::PowerSet { seq, on: false }));
            }
            Step::Connected(c) => {
                out.touch(c.n.id.0);
                out.touch(c.n_1.id.0);
                out.emit(Event::NewConnection(c));
            }
            Step::Removed(c) => {
                out.touch(c.n.id.0);
                out.touch(c.n_1.id.0);
                out.emit(Event::ConnectionRemoved(c));
            }
            Step::Failed { node, port, reason } => {
                out.emit(Event::DockFailed(DockFailed {
                    node: HexId(node),
                    port: port.get(),
                    reason,
                }));
            }
            Step::UnexpectedHandshake { node, port, why } => {
                diagnostics.on_unexpected_handshake(node, port, why, now, out);
            }
        }
    }
}

/// Tells static `node` not to power (or to stop powering) its dock `port`.
fn send_dock_refuse(
    commands: &mut Commands,
    out: &mut Outputs,
    node: NodeId,
    port: Port,
    reason: DockRefuseReason,
) {
    let seq = commands.any_seq(node, Kind::DockRefuse);
    out.send(Packet::command(
        node,
        Message::DockRefuse { seq, port, reason },
    ));
}

#[cfg(test)]
mod tests {
    use super::super::test_support::*;
    use super::super::*;
    use ihex_proto::{AckResult, BootRole, DockRefuseReason, Kind, Message, Packet, ResetReason};
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
            &json!({"node": "10", "port": 1, "reason": "handshake timeout after 5000 ms"})
        );
        // A handshake now is unexpected: a fault, no connection.
        b.handle_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            deadline + MS,
        );
        let out = drain(&mut b);
        assert_eq!(out.one("fault")["code"], "unexpected_handshake");
        assert!(out.named("new_connection").is_empty());
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
        b.handle_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0 + MS,
        );
        b.handle_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0 + MS,
        );
        drain(&mut b);
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
        b.handle_packet(
            Packet::report(id(0x111), Message::DockDetected { port: port(3) }),
            t0,
        );
        b.handle_packet(
            Packet::report(id(2), Message::Handshake { port: port(0) }),
            t0,
        );
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
}
