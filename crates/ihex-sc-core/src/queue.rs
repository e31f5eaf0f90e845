//! The bounded output queue and what it sacrifices when full.
//!
//! The adapter drains the queue after every call, so it only fills when the adapter cannot send
//! (bus-off, a stuck transmitter) while inputs keep arriving. Then the *least useful* output goes:
//!
//! 1. the oldest [`Message::HealthReply`] or [`Message::StateReport`] (the gateway asks again; a
//!    newer reply says more, and a state reply that lost a report no longer matches its `End` count),
//! 2. then the oldest [`Message::BootUp`],
//! 3. then the oldest dock / handshake / assignment report,
//!
//! and never a [`Message::Fault`], an [`Message::Ack`] or a non-frame output (UART reply, ID to
//! store, filter change): those are what the gateway and the adapter cannot recover from losing. An
//! incoming output less important than everything queued is the one dropped. Only when the queue
//! holds nothing but such essentials and another essential arrives is that newest one lost; every
//! drop is counted ([`crate::Node::dropped_outputs`]).

use ihex_proto::Message;

use crate::Output;

/// How many outputs the queue holds.
pub const OUTPUT_QUEUE_LEN: usize = 32;

/// Rank at and above which an output is never sacrificed for another.
const ESSENTIAL: u8 = 3;

/// Lower = dropped first.
fn rank(o: &Output) -> u8 {
    match o {
        Output::Frame(p) => match p.msg {
            Message::HealthReply(_) | Message::StateReport(_) | Message::FwStatus(_) => 0,
            Message::BootUp { .. } => 1,
            Message::Ack { .. } | Message::Fault { .. } => ESSENTIAL,
            _ => 2,
        },
        _ => ESSENTIAL,
    }
}

/// FIFO of outputs with priority-aware dropping.
#[derive(Debug, Default)]
pub(crate) struct OutputQueue {
    items: heapless::Vec<Output, OUTPUT_QUEUE_LEN>,
    dropped: u32,
}

impl OutputQueue {
    /// Appends `o`, making room by the rules of the module docs when full.
    pub(crate) fn push(&mut self, o: Output) {
        let Err(o) = self.items.push(o) else { return };
        self.dropped = self.dropped.saturating_add(1);
        let new_rank = rank(&o);
        // The oldest of the least important queued outputs.
        let victim = self
            .items
            .iter()
            .enumerate()
            .min_by_key(|(i, item)| (rank(item), *i))
            .map(|(i, item)| (i, rank(item)));
        if let Some((i, r)) = victim {
            if r < ESSENTIAL && r <= new_rank {
                self.items.remove(i);
                // Room was just made, so this cannot fail.
                let _ = self.items.push(o);
            }
        }
    }

    /// True while another output fits without dropping one.
    pub(crate) fn has_room(&self) -> bool {
        !self.items.is_full()
    }

    /// Takes the oldest output.
    pub(crate) fn pop(&mut self) -> Option<Output> {
        if self.items.is_empty() {
            None
        } else {
            Some(self.items.remove(0))
        }
    }

    /// Outputs dropped because the queue was full, since boot.
    pub(crate) const fn dropped(&self) -> u32 {
        self.dropped
    }

    /// Queued outputs, oldest first.
    #[cfg(test)]
    pub(crate) fn iter(&self) -> impl Iterator<Item = &Output> {
        self.items.iter()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::{
        AckResult, BootRole, FaultCode, HealthFlags, HealthReply, Kind, NodeId, Packet, ResetReason,
    };

    fn id() -> NodeId {
        NodeId::new_sc(0x111).unwrap()
    }
    fn health(seq: u8) -> Output {
        let h = HealthReply {
            seq,
            flags: HealthFlags(0),
            loops: 0,
            tec: 0,
            rec: 0,
            uptime_s: 0,
        };
        Output::Frame(Packet::report(id(), Message::HealthReply(h)))
    }
    fn boot() -> Output {
        let m = Message::BootUp {
            version: (1, 0),
            role: BootRole::Static,
            ports: 6,
            reset: ResetReason::PowerOn,
        };
        Output::Frame(Packet::report(id(), m))
    }
    fn ack(seq: u8) -> Output {
        let m = Message::Ack {
            kind: Kind::LedSet,
            seq,
            result: AckResult::Ok,
            detail: 0,
        };
        Output::Frame(Packet::report(id(), m))
    }
    fn fault() -> Output {
        let m = Message::Fault {
            code: FaultCode::BusOff,
            arg: 0,
            detail: 1,
        };
        Output::Frame(Packet::report(id(), m))
    }

    #[test]
    fn full_queue_drops_health_then_boot_never_acks() {
        let mut q = OutputQueue::default();
        q.push(boot());
        q.push(health(1));
        q.push(health(2));
        for s in 0..(OUTPUT_QUEUE_LEN as u8 - 3) {
            q.push(ack(s));
        }
        q.push(fault());
        assert_eq!(q.dropped(), 1);
        assert!(
            !q.iter().any(|o| *o == health(1)),
            "oldest health reply goes first"
        );
        assert!(q.iter().any(|o| *o == health(2)));
        q.push(fault());
        assert!(!q.iter().any(|o| *o == health(2)));
        q.push(fault());
        assert!(!q.iter().any(|o| *o == boot()));
        // Only essentials left: a new health reply is the one dropped, the acks all stay.
        q.push(health(9));
        assert!(!q.iter().any(|o| *o == health(9)));
        assert_eq!(q.dropped(), 4);
        for s in 0..(OUTPUT_QUEUE_LEN as u8 - 3) {
            assert!(q.iter().any(|o| *o == ack(s)));
        }
        // Order of what remains is preserved.
        assert_eq!(q.pop(), Some(ack(0)));
    }
}
