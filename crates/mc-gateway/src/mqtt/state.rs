//! The MQTT 3.1.1 client state of one connection, sans-IO: packet ids, the publications in flight
//! (kept for sending again after a break), acks, the awaited PINGRESP and the packets received and
//! not yet read. Packets are rumqttc's types and its codec's; the state is ours.
//!
//! rumqttc's `MqttState` did this before, but for the gateway's use it copied every publication
//! (one to encode, one to keep), stamped every packet with the clock and queued a notice of every
//! packet sent beside the ones received: on the host that was a tenth of a bridged command's
//! instructions (callgrind). Here a publication is encoded from the copy that is kept. Packet ids
//! never collide: publications take free ids in `1..=inflight` (a full window refuses before one is
//! needed), subscriptions and unsubscriptions the ids above.

use std::collections::VecDeque;

use bytes::BytesMut;
use rumqttc::{Packet, PubAck, Publish, QoS, Request, StateError};

/// The state of one connection's session with the broker.
#[derive(Debug)]
pub struct State {
    /// Publications sent and not acknowledged, at index `pkid - 1`, with the order they were sent
    /// in.
    inflight: Vec<Option<(u64, Publish)>>,
    /// How many of `inflight` are taken.
    in_flight: u16,
    /// Where the search for the next free publication id starts (an index into `inflight`).
    next_publish: usize,
    /// The last id given to a subscription or unsubscription (above the publications').
    last_other: u16,
    /// Publications sent since the start: their order in [`State::take_back`].
    sent: u64,
    manual_acks: bool,
    await_pingresp: bool,
    /// Packets received and not read yet.
    received: VecDeque<Packet>,
}

impl State {
    /// A clean state with an in-flight window of `inflight` publications (at least one); with
    /// `manual_acks`, received QoS 1 publications are acknowledged only by a [`Request::PubAck`].
    pub fn new(inflight: u16, manual_acks: bool) -> State {
        let window = usize::from(inflight.clamp(1, u16::MAX - 1));
        State {
            inflight: std::iter::repeat_with(|| None).take(window).collect(),
            in_flight: 0,
            next_publish: 0,
            last_other: window as u16,
            sent: 0,
            manual_acks,
            await_pingresp: false,
            received: VecDeque::new(),
        }
    }

    /// Publications sent and not acknowledged yet.
    pub fn inflight(&self) -> u16 {
        self.in_flight
    }

    /// Whether the in-flight window is full: nothing more may be published.
    pub fn window_full(&self) -> bool {
        usize::from(self.in_flight) >= self.inflight.len()
    }

    /// A PINGREQ went out and its PINGRESP has not come.
    pub fn awaits_pingresp(&self) -> bool {
        self.await_pingresp
    }

    /// Encodes `request` into `out` (at most `max` bytes for the packet) and takes note of it: a
    /// QoS 1 publication gets a packet id and is kept until its PUBACK. Refused: a publication
    /// when the window is full, a second PINGREQ while one is awaited, an empty subscription, a
    /// packet over `max`.
    pub fn send(
        &mut self,
        request: Request,
        out: &mut BytesMut,
        max: usize,
    ) -> Result<(), StateError> {
        let packet = match request {
            Request::Publish(p) if p.qos == QoS::AtMostOnce => Packet::Publish(p),
            Request::Publish(p) => return self.publish(p, out, max),
            Request::PubAck(a) => Packet::PubAck(a),
            Request::Subscribe(mut s) => {
                if s.filters.is_empty() {
                    return Err(StateError::EmptySubscription);
                }
                s.pkid = self.other_pkid();
                Packet::Subscribe(s)
            }
            Request::Unsubscribe(mut u) => {
                u.pkid = self.other_pkid();
                Packet::Unsubscribe(u)
            }
            Request::PingReq(_) => {
                if self.await_pingresp {
                    return Err(StateError::AwaitPingResp);
                }
                self.await_pingresp = true;
                Packet::PingReq
            }
            Request::Disconnect(_) => Packet::Disconnect,
            // The gateway never sends these (QoS 2, or a server's packets).
            _ => return Err(StateError::InvalidState),
        };
        packet.write(out, max)?;
        Ok(())
    }

    /// A QoS 1 publication: the next free id, encoded, kept.
    fn publish(
        &mut self,
        mut p: Publish,
        out: &mut BytesMut,
        max: usize,
    ) -> Result<(), StateError> {
        let window = self.inflight.len();
        let Some(slot) = (0..window)
            .map(|i| (self.next_publish + i) % window)
            .find(|&i| self.inflight[i].is_none())
        else {
            return Err(StateError::InvalidState);
        };
        p.pkid = slot as u16 + 1;
        p.dup = false;
        // `Packet::write`'s size check, without wrapping the publication in a packet.
        let size = p.size();
        if size > max {
            return Err(StateError::Deserialization(
                rumqttc::mqttbytes::Error::OutgoingPacketTooLarge {
                    pkt_size: size,
                    max,
                },
            ));
        }
        p.write(out)?;
        self.sent += 1;
        self.inflight[slot] = Some((self.sent, p));
        self.in_flight += 1;
        self.next_publish = (slot + 1) % window;
        Ok(())
    }

    /// The next id for a subscription or unsubscription, above the publications' ids.
    fn other_pkid(&mut self) -> u16 {
        let lowest = self.inflight.len() as u16 + 1;
        self.last_other = match self.last_other.checked_add(1) {
            Some(id) if id >= lowest => id,
            _ => lowest,
        };
        self.last_other
    }

    /// Takes in a packet from the broker: acks free their publication, a PINGRESP ends the wait,
    /// and the packet is kept for [`State::next_incoming`]. A reply is encoded into `out` (a
    /// PUBACK for a QoS 1 publication unless acks are manual). A PUBACK for no publication in
    /// flight, a QoS 2 publication (the gateway subscribes at QoS 1 at most) and packets only a
    /// client sends are errors.
    pub fn handle_incoming(
        &mut self,
        packet: Packet,
        out: &mut BytesMut,
        max: usize,
    ) -> Result<(), StateError> {
        let reply = match &packet {
            Packet::Publish(p) => match p.qos {
                QoS::AtMostOnce => None,
                QoS::AtLeastOnce if self.manual_acks => None,
                QoS::AtLeastOnce => Some(Packet::PubAck(PubAck::new(p.pkid))),
                QoS::ExactlyOnce => return Err(StateError::WrongPacket),
            },
            Packet::PubAck(a) => {
                let slot = usize::from(a.pkid).wrapping_sub(1);
                match self.inflight.get_mut(slot).and_then(Option::take) {
                    Some(_) => self.in_flight -= 1,
                    None => return Err(StateError::Unsolicited(a.pkid)),
                }
                None
            }
            Packet::PingResp => {
                self.await_pingresp = false;
                None
            }
            Packet::SubAck(_) | Packet::UnsubAck(_) => None,
            _ => return Err(StateError::WrongPacket),
        };
        if let Some(reply) = reply {
            reply.write(out, max)?;
        }
        self.received.push_back(packet);
        Ok(())
    }

    /// The next packet from the broker not yet read, oldest first.
    pub fn next_incoming(&mut self) -> Option<Packet> {
        self.received.pop_front()
    }

    /// Forgets the packets of a broken connection not yet read.
    pub fn forget_incoming(&mut self) {
        self.received.clear();
    }

    /// After a connection broke: the publications the broker had not acknowledged, in the order
    /// they were sent, and a clean state for the next connection (nothing in flight, no ping
    /// awaited).
    pub fn take_back(&mut self) -> Vec<Publish> {
        let mut back: Vec<(u64, Publish)> =
            self.inflight.iter_mut().filter_map(Option::take).collect();
        back.sort_unstable_by_key(|(sent, _)| *sent);
        self.in_flight = 0;
        self.next_publish = 0;
        self.await_pingresp = false;
        back.into_iter()
            .map(|(_, mut p)| {
                p.pkid = 0;
                p
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rumqttc::{Subscribe, Unsubscribe};

    const MAX: usize = 1 << 20;

    fn publish(state: &mut State, payload: &'static str) -> Result<u16, StateError> {
        let mut out = BytesMut::new();
        let p = Publish::new("t", QoS::AtLeastOnce, payload);
        state.send(Request::Publish(p), &mut out, MAX)?;
        match Packet::read(&mut out, MAX) {
            Ok(Packet::Publish(p)) => Ok(p.pkid),
            other => panic!("not a publication: {other:?}"),
        }
    }

    fn ack(state: &mut State, pkid: u16) -> Result<(), StateError> {
        receive(state, Packet::PubAck(PubAck::new(pkid))).map(|_| ())
    }

    /// Takes in `packet`; returns the reply encoded, if any.
    fn receive(state: &mut State, packet: Packet) -> Result<Option<Packet>, StateError> {
        let mut out = BytesMut::new();
        state.handle_incoming(packet, &mut out, MAX)?;
        Ok(Packet::read(&mut out, MAX).ok())
    }

    #[test]
    fn publications_take_free_ids_and_their_acks_free_them() {
        let mut state = State::new(3, true);
        assert_eq!(publish(&mut state, "a").unwrap(), 1);
        assert_eq!(publish(&mut state, "b").unwrap(), 2);
        assert_eq!(publish(&mut state, "c").unwrap(), 3);
        assert!(state.window_full());
        assert!(publish(&mut state, "d").is_err(), "the window is full");
        // Acknowledged out of order: the id freed is the one reused.
        ack(&mut state, 2).unwrap();
        assert_eq!(state.inflight(), 2);
        assert_eq!(publish(&mut state, "d").unwrap(), 2);
        assert!(matches!(
            ack(&mut state, 2).and_then(|_| ack(&mut state, 2)),
            Err(StateError::Unsolicited(2))
        ));
        assert!(matches!(
            ack(&mut state, 0),
            Err(StateError::Unsolicited(0))
        ));
        assert!(matches!(
            ack(&mut state, 9),
            Err(StateError::Unsolicited(9))
        ));
        assert_eq!(state.next_incoming(), Some(Packet::PubAck(PubAck::new(2))));
    }

    #[test]
    fn what_was_not_acknowledged_is_taken_back_in_sending_order() {
        let mut state = State::new(3, true);
        for payload in ["a", "b", "c"] {
            publish(&mut state, payload).unwrap();
        }
        ack(&mut state, 1).unwrap();
        publish(&mut state, "d").unwrap(); // id 1 again, sent last
        let back: Vec<_> = state.take_back().into_iter().map(|p| p.payload).collect();
        assert_eq!(back, ["b", "c", "d"]);
        assert_eq!(state.inflight(), 0);
        assert!(state.take_back().is_empty(), "taken back once");
        assert_eq!(publish(&mut state, "e").unwrap(), 1, "a clean window");
    }

    #[test]
    fn subscriptions_never_share_an_id_with_a_publication() {
        let mut state = State::new(2, true);
        let mut out = BytesMut::new();
        let mut ids = Vec::new();
        for _ in 0..3 {
            let s = Subscribe::new("c", QoS::AtLeastOnce);
            state.send(Request::Subscribe(s), &mut out, MAX).unwrap();
            let u = Unsubscribe::new("c");
            state.send(Request::Unsubscribe(u), &mut out, MAX).unwrap();
        }
        while let Ok(p) = Packet::read(&mut out, MAX) {
            ids.push(match p {
                Packet::Subscribe(s) => s.pkid,
                Packet::Unsubscribe(u) => u.pkid,
                other => panic!("{other:?}"),
            });
        }
        assert_eq!(ids, [3, 4, 5, 6, 7, 8]);
        state.last_other = u16::MAX;
        assert_eq!(state.other_pkid(), 3, "wraps above the publications' ids");
    }

    #[test]
    fn pings_and_replies() {
        let mut state = State::new(2, false);
        let mut out = BytesMut::new();
        state
            .send(Request::PingReq(rumqttc::PingReq), &mut out, MAX)
            .unwrap();
        assert!(state.awaits_pingresp());
        assert!(matches!(
            state.send(Request::PingReq(rumqttc::PingReq), &mut out, MAX),
            Err(StateError::AwaitPingResp)
        ));
        receive(&mut state, Packet::PingResp).unwrap();
        assert!(!state.awaits_pingresp());
        // Automatic acks: a QoS 1 publication is answered by its PUBACK.
        let mut p = Publish::new("c", QoS::AtLeastOnce, "x");
        p.pkid = 7;
        assert_eq!(
            receive(&mut state, Packet::Publish(p)).unwrap(),
            Some(Packet::PubAck(PubAck::new(7)))
        );
        let mut q2 = Publish::new("c", QoS::ExactlyOnce, "x");
        q2.pkid = 8;
        assert!(matches!(
            receive(&mut state, Packet::Publish(q2)),
            Err(StateError::WrongPacket)
        ));
        assert!(matches!(
            receive(&mut state, Packet::PingReq),
            Err(StateError::WrongPacket)
        ));
        state.forget_incoming();
        assert_eq!(state.next_incoming(), None);
    }

    #[test]
    fn an_oversized_publication_is_refused_and_not_kept() {
        let mut state = State::new(2, true);
        let mut out = BytesMut::new();
        let p = Publish::new("t", QoS::AtLeastOnce, vec![0; 100]);
        assert!(state.send(Request::Publish(p), &mut out, 50).is_err());
        assert_eq!(state.inflight(), 0);
        assert!(out.is_empty());
    }
}
