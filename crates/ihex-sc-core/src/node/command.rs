//! Gateway commands: decoding, addressing, actuators, docking, health, and their acks.

use ihex_proto::{
    field, filter::ID_MASK, AckResult, BootRole, BuzzerCommand, DecodeError, DockPartner,
    FaultCode, Header, Kind, LedCommand, Message, NodeId, Packet, Port, Rgb, Seq,
};

use super::Node;
use crate::{BuzzerOutput, LedOutput, Millis};

/// Byte offset of the port field in `DockConfirm`, `DockRefuse` and `DockLink` (the ack's `detail`).
const PORT_OFFSET: u8 = field::dock_confirm::PORT as u8;
const _: () = assert!(
    field::dock_refuse::PORT == field::dock_confirm::PORT
        && field::dock_link::PORT == field::dock_confirm::PORT
);

impl Node {
    /// Addressing, decoding and dispatch of one received frame.
    pub(super) fn on_frame(
        &mut self,
        raw_id: u32,
        extended: bool,
        remote: bool,
        data: &[u8],
        now: Millis,
    ) {
        if !extended || remote {
            return;
        }
        let raw_id = raw_id & ID_MASK;
        let dest = ((raw_id >> Header::DEST_SHIFT) & Header::NODE_MASK) as u16;
        let to_me = self.config.node_id.is_some_and(|id| id.get() == dest);
        if !to_me && dest != NodeId::BROADCAST.get() {
            return;
        }
        let packet = match Packet::decode(raw_id, data) {
            Ok(p) => p,
            Err(e) => {
                // Only frames for this node alone: one bad broadcast must not make every node
                // on the bus answer with a fault at once.
                if to_me {
                    let kind = ((raw_id >> Header::KIND_SHIFT) & Header::KIND_MASK) as u8;
                    self.fault(FaultCode::BadFrame, kind, bad_frame_detail(e, data.len()));
                }
                return;
            }
        };
        match packet.msg {
            Message::AssignSelect { uid_head } => self.on_assign_select(uid_head),
            Message::AssignCommit {
                uid_tail,
                new_id,
                seq,
            } => self.on_assign_commit(uid_tail, new_id, seq, now),
            // Reports (from other nodes) are not for us; check_addresses already keeps them out.
            msg if !msg.kind().is_command() => {}
            // An unconfigured node takes part in nothing but ID assignment.
            _ if self.config.node_id.is_none() => {}
            msg => {
                self.heard_gateway();
                self.on_command(msg, now);
            }
        }
    }

    /// A decoded, addressed command (the node has an ID).
    fn on_command(&mut self, msg: Message, now: Millis) {
        match msg {
            Message::PowerSet { seq, on } => {
                if self.has_relay() {
                    self.relay = on;
                    self.ack(Kind::PowerSet, seq, AckResult::Ok, 0);
                } else {
                    self.ack(Kind::PowerSet, seq, AckResult::Unsupported, 0);
                }
            }
            Message::LedSet { seq, cmd } => {
                self.led = cmd;
                self.ack(Kind::LedSet, seq, AckResult::Ok, 0);
            }
            Message::BuzzerSet { seq, cmd } => {
                self.set_buzzer(cmd, now);
                self.ack(Kind::BuzzerSet, seq, AckResult::Ok, 0);
            }
            Message::Identify { seq, seconds } => {
                self.identify_until = (seconds > 0).then(|| now.add_ms(u64::from(seconds) * 1000));
                self.ack(Kind::Identify, seq, AckResult::Ok, 0);
            }
            Message::DockConfirm { seq, port } => self.on_dock_confirm(seq, port),
            Message::DockRefuse { seq, port, .. } => {
                if let Some(refusal) = self.dock_refusal(port) {
                    self.ack(Kind::DockRefuse, seq, refusal.0, refusal.1);
                    return;
                }
                // A refusal after a confirmation withdraws it.
                self.withdraw(port);
                self.ack(Kind::DockRefuse, seq, AckResult::Ok, 0);
            }
            Message::DockLink { seq, port, partner } => self.on_dock_link(seq, port, partner),
            Message::HealthCheck { seq } => {
                let h = self.health(seq, now);
                self.report(Message::HealthReply(h));
            }
            Message::StateQuery { seq, parts } => self.on_state_query(seq, parts, now),
            Message::FwBegin {
                image_id,
                len,
                force,
            } => self.on_fw_begin(image_id, len, force),
            Message::FwData { index, data } => self.on_fw_data(index, data),
            Message::FwQuery { image_id } => self.on_fw_query(image_id),
            Message::FwEnd { image_id, action } => self.on_fw_end(image_id, action),
            // Assignment is dispatched before this; reports never get here.
            _ => {}
        }
    }

    fn on_dock_confirm(&mut self, seq: Seq, port: Port) {
        if let Some((result, detail)) = self.dock_refusal(port) {
            self.ack(Kind::DockConfirm, seq, result, detail);
            return;
        }
        if !self.loops[port.get() as usize].closed() {
            self.ack(Kind::DockConfirm, seq, AckResult::InvalidState, PORT_OFFSET);
            self.fault(FaultCode::DockConfirmNotDocked, port.get(), 0);
            return;
        }
        self.confirmed |= port.mask();
        self.relay = true;
        self.ack(Kind::DockConfirm, seq, AckResult::Ok, 0);
    }

    /// `DockLink`: remember (or forget) which mobile element is docked on a confirmed port.
    fn on_dock_link(&mut self, seq: Seq, port: Port, partner: Option<DockPartner>) {
        if let Some((result, detail)) = self.dock_refusal(port) {
            self.ack(Kind::DockLink, seq, result, detail);
            return;
        }
        // A link is only kept while the port is confirmed; clearing is always fine.
        if partner.is_some() && self.confirmed & port.mask() == 0 {
            self.ack(Kind::DockLink, seq, AckResult::InvalidState, PORT_OFFSET);
            return;
        }
        self.links[port.get() as usize] = partner;
        self.ack(Kind::DockLink, seq, AckResult::Ok, 0);
    }

    /// Why a dock command for `port` cannot apply to this node at all, as `(result, detail)`.
    fn dock_refusal(&self, port: Port) -> Option<(AckResult, u8)> {
        if !self.has_relay() {
            Some((AckResult::Unsupported, 0))
        } else if port.get() >= self.config.ports {
            Some((AckResult::InvalidValue, PORT_OFFSET))
        } else {
            None
        }
    }

    /// Only a static element with dock ports has a dock relay.
    pub(super) fn has_relay(&self) -> bool {
        self.config.role == BootRole::Static && self.config.ports > 0
    }

    fn set_buzzer(&mut self, cmd: BuzzerCommand, now: Millis) {
        self.buzzer = cmd;
        self.buzzer_end = match buzzer_output(cmd) {
            BuzzerOutput::Pattern {
                on_ms,
                off_ms,
                count,
                ..
            } if count > 0 => {
                let len = u64::from(count) * (u64::from(on_ms) + u64::from(off_ms));
                Some(now.add_ms(len))
            }
            _ => None,
        };
    }

    fn ack(&mut self, kind: Kind, seq: Seq, result: AckResult, detail: u8) {
        self.report(Message::Ack {
            kind,
            seq,
            result,
            detail,
        });
    }
}

/// The LED drive for a command: brightness applied to every channel.
pub(crate) fn led_output(cmd: LedCommand) -> LedOutput {
    let scale = |c: Rgb, b: u8| {
        let s = |v: u8| (u16::from(v) * u16::from(b) / 255) as u8;
        Rgb::new(s(c.r), s(c.g), s(c.b))
    };
    match cmd {
        LedCommand::Off => LedOutput::default(),
        LedCommand::Steady { color, brightness } => LedOutput {
            duty: scale(color, brightness),
            blink: None,
        },
        LedCommand::Blink {
            color,
            brightness,
            period_10ms,
            duty_pct,
        } => LedOutput {
            duty: scale(color, brightness),
            blink: Some((ihex_proto::unit::to_ms(period_10ms), duty_pct)),
        },
    }
}

/// The buzzer drive for a command: 10 ms units in milliseconds.
pub(crate) fn buzzer_output(cmd: BuzzerCommand) -> BuzzerOutput {
    match cmd {
        BuzzerCommand::Off => BuzzerOutput::Off,
        BuzzerCommand::Continuous { freq_hz } => BuzzerOutput::Tone { freq_hz },
        BuzzerCommand::Pattern {
            freq_hz,
            on_10ms,
            off_10ms,
            count,
        } => BuzzerOutput::Pattern {
            freq_hz,
            on_ms: ihex_proto::unit::to_ms(on_10ms),
            off_ms: ihex_proto::unit::to_ms(off_10ms),
            count,
        },
    }
}

/// `detail` of a `BadFrame` fault: byte 0 = error class (1 unknown kind, 2 length, 3 value,
/// 4 address, 0 other), byte 1 = the frame's data length, bytes 2–3 = the offending raw value
/// (low 16 bits) for a value error.
fn bad_frame_detail(e: DecodeError, len: usize) -> u32 {
    let (class, raw) = match e {
        DecodeError::UnknownKind(_) => (1, 0),
        DecodeError::Length { .. } => (2, 0),
        DecodeError::Value { raw, .. } => (3, raw & 0xFFFF),
        DecodeError::Address { .. } => (4, 0),
        DecodeError::StandardId | DecodeError::Remote => (0, 0),
    };
    class | ((len.min(255) as u32) << 8) | (raw << 16)
}
