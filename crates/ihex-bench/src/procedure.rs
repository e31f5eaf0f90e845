//! Docking → `procedure_step` `done`, in the gateway's sans-IO core: how long the gateway's own work
//! takes from the mobile element's handshake (the frame that completes a docking) to the step's
//! `done` event serialised for MQTT, as the shell would take it — `new_connection` first, the
//! procedure's events, the next frames. What the shell adds (socket reads, the MQTT client) is the
//! same as for any event and is measured by the live benchmark's frame → event latency.
//!
//! Each sample runs a one-step procedure (`docked` on element 111, port `k mod 6`, mobile element
//! 2) on a bridge that knows 111: the procedure command, the docking's detection and confirm (acked
//! as the node does), then the timed handshake, then the undocking that resets the island.

use std::time::{Duration, Instant};

use ihex_gateway_core::event::Event;
use ihex_gateway_core::{Bridge, BridgeConfig, PayloadWriter, Publication};
use ihex_proto::{AckResult, BootRole, Message, NodeId, Packet, Port, ResetReason};
use serde::{Deserialize, Serialize};

use crate::stats::Summary;

/// What `ihex-bench procedure` writes (`procedure.json`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ProcedureResults {
    /// Handshake in → `procedure_step` `done` serialised, in the core (µs).
    pub docking_to_done: Summary,
}

const STATIC: NodeId = match NodeId::new(0x111) {
    Some(id) => id,
    None => NodeId::GATEWAY,
};
const MOBILE: NodeId = match NodeId::new(2) {
    Some(id) => id,
    None => NodeId::GATEWAY,
};

/// Hands out every frame (confirmed) and acks each as its node would; serialises every
/// publication. True when a `procedure_step` `done` was among them.
fn drain(b: &mut Bridge, text: &mut PayloadWriter, now: Instant) -> bool {
    let mut done = false;
    loop {
        let mut any = false;
        while let Some(t) = b.poll_transmit(now) {
            any = true;
            let p = t.packet;
            b.handle_transmitted(p, now);
            if let Some(seq) = p.msg.ack_seq() {
                let ack = Message::Ack {
                    kind: p.msg.kind(),
                    seq,
                    result: AckResult::Ok,
                    detail: 0,
                };
                b.handle_packet(Packet::report(p.dest, ack), now);
            }
        }
        while let Some(p) = b.poll_publication() {
            any = true;
            let _ = text.write(&p);
            if let Publication::Event(Event::ProcedureStep(s)) = &p {
                done |= s.state == ihex_gateway_core::procedure::StepState::Done;
            }
        }
        if !any {
            return done;
        }
    }
}

/// `samples` dockings, each confirming a procedure's step.
pub fn run(samples: usize) -> ProcedureResults {
    let t0 = Instant::now();
    let config = BridgeConfig {
        // No health checks and no command timeouts inside the measured loop.
        health_period: Duration::from_secs(3600),
        command_timeout: Duration::from_secs(3600),
        ..BridgeConfig::default()
    };
    let mut b = Bridge::new(config, t0);
    let mut text = PayloadWriter::default();
    let boot = Message::BootUp {
        version: (1, 3),
        role: BootRole::Static,
        ports: 6,
        reset: ResetReason::PowerOn,
    };
    b.handle_packet(Packet::report(STATIC, boot), t0);
    drain(&mut b, &mut text, t0);
    let mut us = Vec::with_capacity(samples);
    for k in 0..samples {
        let now = Instant::now();
        let port = (k % 6) as u8;
        let Some(p) = Port::new(port) else { continue };
        let cmd = format!(
            r#"{{"cmd":"procedure","name":"bench","steps":[{{"node":"111","port":{port},"mobile":"2","wait":"docked","color":"green","timeout_s":60}}]}}"#
        );
        b.handle_command(cmd.as_bytes(), now);
        drain(&mut b, &mut text, now);
        b.handle_packet(
            Packet::report(STATIC, Message::DockDetected { port: p }),
            now,
        );
        drain(&mut b, &mut text, now);
        let handshake = Packet::report(
            MOBILE,
            Message::Handshake {
                port: Port::new(0).unwrap_or(p),
            },
        );
        let start = Instant::now();
        b.handle_packet(handshake, start);
        let done = drain(&mut b, &mut text, start);
        let took = start.elapsed();
        if done {
            us.push(took.as_secs_f64() * 1e6);
        }
        let now = Instant::now();
        b.handle_packet(
            Packet::report(STATIC, Message::DockRemoved { port: p }),
            now,
        );
        drain(&mut b, &mut text, now);
    }
    ProcedureResults {
        docking_to_done: Summary::of(us),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_docking_confirms_its_step() {
        let r = run(50);
        assert_eq!(r.docking_to_done.n, 50, "every sample's step was done");
        assert!(r.docking_to_done.p50_us > 0.0);
    }
}
