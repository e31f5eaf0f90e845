//! Bus diagnostics: error frames, bus-off and interface state, kernel drops, undecodable frames,
//! frames that could not be sent, and the nodes' own fault reports — each published as a rate-limited
//! `bus_error` or `fault` event, and counted for [`BusHealth`].

use std::time::{Duration, Instant};

use ihex_proto::{DecodeError, FaultCode, NodeId, Packet, Port};

use super::output::Outputs;
use crate::error_frame;
use crate::event::{BusError, Event, FaultEvent, HexId, Target};
use crate::throttle::Throttle;

/// How long the rate limit of error events (`fault`, `bus_error`) holds back repeats of one kind.
pub const ERROR_EVENT_WINDOW: Duration = Duration::from_secs(1);

/// Bus conditions the CAN adapter observes besides frames.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum BusEvent {
    /// An error frame arrived (`can_id` with the error class bits, `data` as received).
    ErrorFrame {
        /// Error class bits (`CAN_ERR_*` of linux/can/error.h).
        class: u32,
        /// The error frame's 8 data bytes.
        data: [u8; 8],
    },
    /// The controller went bus-off.
    BusOff,
    /// The interface went down or vanished (the adapter retries opening it).
    InterfaceDown,
    /// The interface is back up after `BusOff` or `InterfaceDown`.
    Recovered,
    /// The kernel dropped received frames (count since the last report).
    RxDropped(u32),
}

/// What the bus has done since start: the gateway's traffic, and counts of every kind of trouble,
/// published or suppressed (serialised as the island view shows it, `docs/web.md`).
#[derive(Clone, Copy, PartialEq, Eq, Debug, Default, serde::Serialize, serde::Deserialize)]
pub struct BusHealth {
    /// The gateway's own interface is bus-off or down right now.
    pub bus_down: bool,
    /// Error frames received (bus-off and restart frames not included).
    pub error_frames: u64,
    /// Times the controller went bus-off.
    pub bus_off: u64,
    /// Times the interface went down or vanished.
    pub interface_down: u64,
    /// Frames the kernel reported dropped on reception.
    pub rx_dropped: u64,
    /// Frames that passed the filters but were no valid iHEX packet.
    pub undecodable_frames: u64,
    /// Gateway frames that could not be sent (commands included).
    pub send_failures: u64,
    /// `fault` reports received from nodes.
    pub faults: u64,
    /// `fault` and `bus_error` events held back by the rate limit.
    pub events_suppressed: u64,
    /// Frames received through the gateway's filters (valid or not; error frames not included).
    pub frames_received: u64,
    /// Frames handed to the CAN adapter for sending (those it could not send are `send_failures`).
    pub frames_sent: u64,
    /// Bits those received and sent frames take on the wire without stuff bits
    /// ([`ihex_proto::bus::frame_bits`]): the gateway's share of the bus load.
    pub frame_bits: u64,
}

/// The rate limit and the counters.
#[derive(Debug)]
pub(crate) struct Diagnostics {
    throttle: Throttle,
    /// Frames dropped by the kernel and not reported yet (the rate limit sums them up).
    rx_dropped: u64,
    health: BusHealth,
}

fn fault_text(c: FaultCode, arg: u8, detail: u32) -> String {
    match c {
        FaultCode::DockConfirmNotDocked => {
            format!("dock confirm for port {arg}, whose signal loop is open")
        }
        FaultCode::BusOff => {
            format!("CAN controller went bus-off and recovered ({detail} times since boot)")
        }
        FaultCode::ErrorPassive => {
            format!(
                "CAN controller is error-passive (TEC {}, REC {})",
                detail >> 8 & 0xff,
                detail & 0xff
            )
        }
        FaultCode::RxOverrun => format!("{detail} received frames lost"),
        FaultCode::WatchdogReset => "reset by the watchdog".into(),
        FaultCode::ConfigStore => "writing the configuration to flash failed".into(),
        FaultCode::UnexpectedMessage => format!("unexpected message of kind {arg:#04x}"),
        FaultCode::BadFrame => format!("undecodable frame of kind {arg:#04x} addressed to it"),
        FaultCode::Other(v) => {
            format!("fault code {v} unknown to this gateway (arg {arg}, detail {detail})")
        }
    }
}

fn decode_error_key(e: &DecodeError) -> &'static str {
    match e {
        DecodeError::StandardId => "standard_id",
        DecodeError::Remote => "remote",
        DecodeError::UnknownKind(_) => "unknown_kind",
        DecodeError::Length { .. } => "length",
        DecodeError::Value { .. } => "value",
        DecodeError::Address { .. } => "address",
    }
}

/// `Some(n)` for a rate-limited event that carries the count of suppressed ones.
fn suppressed(n: u32) -> Option<u32> {
    (n > 0).then_some(n)
}

impl Diagnostics {
    pub(crate) fn new() -> Self {
        Diagnostics {
            throttle: Throttle::new(ERROR_EVENT_WINDOW),
            rx_dropped: 0,
            health: BusHealth::default(),
        }
    }

    /// The counters; `bus_down` is filled in by the bridge.
    pub(crate) fn health(&self) -> BusHealth {
        self.health
    }

    /// `Some(suppressed)` when an event for `key` may be published now.
    fn admit(&mut self, key: &str, now: Instant) -> Option<u32> {
        let admitted = self.throttle.admit(key, now);
        if admitted.is_none() {
            self.health.events_suppressed += 1;
        }
        admitted
    }

    /// A node's `Fault` report.
    pub(crate) fn on_fault(
        &mut self,
        src: NodeId,
        code: FaultCode,
        arg: u8,
        detail: u32,
        now: Instant,
        out: &mut Outputs,
    ) {
        self.health.faults += 1;
        let name = code.to_string();
        if let Some(n) = self.admit(&format!("fault:{src}:{name}"), now) {
            out.emit(Event::Fault(FaultEvent {
                node: HexId(src),
                code: name,
                arg,
                detail,
                message: fault_text(code, arg, detail),
                suppressed: suppressed(n),
            }));
        }
    }

    /// A handshake nobody waited for: the gateway's own `unexpected_handshake` fault.
    pub(crate) fn on_unexpected_handshake(
        &mut self,
        node: NodeId,
        port: Port,
        why: &str,
        now: Instant,
        out: &mut Outputs,
    ) {
        let key = format!("fault:{node}:unexpected_handshake");
        let Some(n) = self.admit(&key, now) else {
            return;
        };
        out.emit(Event::Fault(FaultEvent {
            node: HexId(node),
            code: "unexpected_handshake".into(),
            arg: port.get(),
            detail: 0,
            message: format!("handshake from {node} (its port {port}) ignored: {why}"),
            suppressed: suppressed(n),
        }));
    }

    /// A frame that passed the filters but is not a valid iHEX packet.
    pub(crate) fn on_undecodable(
        &mut self,
        raw_id: u32,
        data: &[u8],
        err: DecodeError,
        now: Instant,
        out: &mut Outputs,
    ) {
        self.health.undecodable_frames += 1;
        let key = decode_error_key(&err);
        let Some(n) = self.admit(&format!("undecodable:{key}"), now) else {
            return;
        };
        let hex = ihex_proto::Hex(&data[..data.len().min(64)]).to_string();
        out.emit(Event::BusError(Box::new(BusError {
            error: "undecodable_frame".into(),
            message: format!("frame {raw_id:#010x} [{hex}] is not an iHEX packet: {err}"),
            raw_id: Some(format!("{raw_id:#010x}")),
            data: Some(hex),
            suppressed: suppressed(n),
            ..BusError::default()
        })));
    }

    /// A bus condition (error frame, bus-off, interface down/up, drops).
    pub(crate) fn on_bus_event(&mut self, event: BusEvent, now: Instant, out: &mut Outputs) {
        let (key, mut err) = match event {
            BusEvent::ErrorFrame { class, data } => {
                self.health.error_frames += 1;
                (
                    format!("error_frame:{:x}", class & 0x1FFF_FFFF),
                    error_frame::decode(class, data),
                )
            }
            BusEvent::BusOff => {
                self.health.bus_off += 1;
                (
                    "bus_off".into(),
                    BusError {
                        error: "bus_off".into(),
                        message:
                            "the CAN controller is bus-off; frames cannot be sent until it recovers"
                                .into(),
                        ..BusError::default()
                    },
                )
            }
            BusEvent::InterfaceDown => {
                self.health.interface_down += 1;
                (
                    "interface_down".into(),
                    BusError {
                        error: "interface_down".into(),
                        message: "the CAN interface is down or gone; the gateway keeps retrying it"
                            .into(),
                        ..BusError::default()
                    },
                )
            }
            BusEvent::Recovered => (
                "recovered".into(),
                BusError {
                    error: "recovered".into(),
                    message: "the CAN interface is up again".into(),
                    ..BusError::default()
                },
            ),
            BusEvent::RxDropped(n) => {
                self.health.rx_dropped += u64::from(n);
                self.rx_dropped = self.rx_dropped.saturating_add(u64::from(n));
                let count = self.rx_dropped;
                (
                    "rx_dropped".into(),
                    BusError {
                        error: "rx_dropped".into(),
                        message: format!("the kernel dropped {count} received frames"),
                        count: Some(count),
                        ..BusError::default()
                    },
                )
            }
        };
        let Some(n) = self.admit(&key, now) else {
            return;
        };
        if matches!(event, BusEvent::RxDropped(_)) {
            self.rx_dropped = 0;
        }
        err.suppressed = suppressed(n);
        out.emit(Event::BusError(Box::new(err)));
    }

    /// Counts a frame that could not be sent (whoever reports it).
    /// A frame with `data_len` data bytes was received (`sent = false`) or handed over for sending.
    pub(crate) fn count_frame(&mut self, data_len: u8, sent: bool) {
        if sent {
            self.health.frames_sent += 1;
        } else {
            self.health.frames_received += 1;
        }
        self.health.frame_bits += u64::from(ihex_proto::bus::frame_bits(data_len));
    }

    pub(crate) fn count_send_failure(&mut self) {
        self.health.send_failures += 1;
    }

    /// A gateway frame that is not a user command (health check, docking) was not sent.
    pub(crate) fn on_send_failed(
        &mut self,
        packet: &Packet,
        reason: &str,
        now: Instant,
        out: &mut Outputs,
    ) {
        let kind = packet.msg.kind();
        let (raw_id, _) = packet.encode();
        let Some(n) = self.admit(&format!("send_failed:{kind:?}"), now) else {
            return;
        };
        let message = format!(
            "{kind:?} to {} not sent: {reason}",
            Target::from_dest(packet.dest)
        );
        out.emit(Event::BusError(Box::new(BusError {
            error: "send_failed".into(),
            message,
            raw_id: Some(format!("{raw_id:#010x}")),
            suppressed: suppressed(n),
            ..BusError::default()
        })));
    }
}

#[cfg(test)]
mod tests {
    use super::super::test_support::*;
    use super::super::*;
    use ihex_proto::{DecodeError, FaultCode, Message, Packet};
    use serde_json::json;
    use std::time::Instant;

    #[test]
    fn faults_are_named_and_rate_limited() {
        let (mut b, t0) = with_nodes(&[4]);
        let fault = Message::Fault {
            code: FaultCode::RxOverrun,
            arg: 0,
            detail: 12,
        };
        b.handle_packet(Packet::report(id(4), fault), t0);
        let out = drain(&mut b);
        assert_eq!(
            out.one("fault"),
            &json!({"node": "4", "code": "rx_overrun", "arg": 0, "detail": 12, "message": "12 received frames lost"})
        );
        for _ in 0..50 {
            b.handle_packet(Packet::report(id(4), fault), t0 + MS);
        }
        assert!(drain(&mut b).named("fault").is_empty());
        b.handle_packet(Packet::report(id(4), fault), t0 + S);
        assert_eq!(drain(&mut b).one("fault")["suppressed"], 50);
    }

    #[test]
    fn undecodable_frames_and_bus_events_are_rate_limited_bus_errors() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        let err = DecodeError::UnknownKind(0x1f);
        for _ in 0..5 {
            b.handle_undecodable(0x1f00_0001, &[1, 2], err, t0);
        }
        let out = drain(&mut b);
        let e = out.one("bus_error");
        assert_eq!(e["error"], "undecodable_frame");
        assert_eq!(e["raw_id"], "0x1f000001");
        assert_eq!(e["data"], "0102");
        assert!(e["message"]
            .as_str()
            .unwrap()
            .contains("unknown message kind 0x1f"));
        b.handle_undecodable(0x1f00_0001, &[], err, t0 + S);
        assert_eq!(drain(&mut b).one("bus_error")["suppressed"], 4);

        b.handle_bus_event(
            BusEvent::ErrorFrame {
                class: 0x4,
                data: [0, 0x10, 0, 0, 0, 0, 0, 0],
            },
            t0,
        );
        let out = drain(&mut b);
        assert_eq!(out.one("bus_error")["controller"], json!(["rx_passive"]));
        b.handle_bus_event(BusEvent::BusOff, t0);
        b.handle_bus_event(BusEvent::Recovered, t0);
        b.handle_bus_event(BusEvent::InterfaceDown, t0);
        let kinds: Vec<_> = drain(&mut b)
            .events
            .iter()
            .map(|e| e["payload"]["error"].clone())
            .collect();
        assert_eq!(
            kinds,
            [
                json!("bus_off"),
                json!("recovered"),
                json!("interface_down")
            ]
        );
        b.handle_bus_event(BusEvent::RxDropped(3), t0);
        b.handle_bus_event(BusEvent::RxDropped(4), t0 + MS);
        b.handle_bus_event(BusEvent::RxDropped(5), t0 + S);
        let out = drain(&mut b);
        let counts: Vec<_> = out
            .events
            .iter()
            .map(|e| e["payload"]["count"].clone())
            .collect();
        assert_eq!(
            counts,
            [json!(3), json!(9)],
            "drops while throttled are summed, not lost"
        );
    }
}
