//! The doctor's one session on the CAN interface (the adapter for [`traffic`] and
//! [`island`]): it broadcasts a `HealthCheck`, a `StateQuery` for the identity
//! group and an `FwQuery`, and takes in every frame and error frame for the listening time. None
//! of the three changes a node's state, so it is safe while the gateway runs.

use std::time::Duration;

use embedded_can::{Frame as _, Id};
use ihex_proto::{Message, NodeId, Packet, StateParts};
use socketcan::{CanFrame, SocketOptions};

use super::{island, traffic};

/// Sequence number of the doctor's probes (any value: nodes echo it, the doctor counts every
/// answer, also to the gateway's own health checks).
const SEQ: u8 = 0xD0;

/// What one listening session saw.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Facts {
    /// Frames and error frames.
    pub traffic: traffic::Facts,
    /// The nodes' answers.
    pub island: island::Facts,
}

impl Facts {
    /// Takes in one received frame.
    pub fn observe(&mut self, frame: &CanFrame) {
        if let CanFrame::Error(ef) = frame {
            let mut data = [0u8; 8];
            let d = frame.data();
            data[..d.len().min(8)].copy_from_slice(&d[..d.len().min(8)]);
            self.traffic.observe_error(ef.error_bits(), data);
            return;
        }
        self.traffic.frames += 1;
        match (frame.id(), Packet::from_frame(frame)) {
            (Id::Extended(_), Ok(p)) => self.island.observe(&p),
            _ => self.traffic.foreign += 1,
        }
    }
}

/// The probes, in the order sent.
pub fn probes() -> [Packet; 3] {
    [
        Packet::command(NodeId::BROADCAST, Message::HealthCheck { seq: SEQ }),
        Packet::command(
            NodeId::BROADCAST,
            Message::StateQuery {
                seq: SEQ,
                parts: StateParts(StateParts::IDENTITY),
            },
        ),
        Packet::command(NodeId::BROADCAST, Message::FwQuery { image_id: 0 }),
    ]
}

/// Opens `iface`, sends the probes, and listens for `listen`.
pub async fn gather(iface: &str, listen: Duration) -> std::io::Result<Facts> {
    let sock = socketcan::tokio::CanSocket::open(iface)?;
    sock.set_error_filter_accept_all()?;
    let deadline = tokio::time::Instant::now() + listen;
    let mut facts = Facts::default();
    for p in probes() {
        let Some(frame) = p.to_frame::<CanFrame>() else {
            continue;
        };
        // A controller that cannot get frames out (nobody acknowledges, bus-off) blocks writes:
        // give each at most a tenth of the listening time.
        match tokio::time::timeout(listen / 10, sock.write_frame(frame)).await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => facts.traffic.send_failed(e.to_string()),
            Err(_) => facts.traffic.send_failed("transmit timed out".into()),
        }
    }
    loop {
        match tokio::time::timeout_at(deadline, sock.read_frame()).await {
            Err(_) => break,
            Ok(Ok(frame)) => facts.observe(&frame),
            Ok(Err(e)) => return Err(e),
        }
    }
    Ok(facts)
}
