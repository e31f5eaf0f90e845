//! The one place that touches rumqttc's public but undocumented [`MqttState`] fields: an upgrade of
//! rumqttc is an audit of this file.
//!
//! Checked against **rumqttc 0.25.1** (`src/state.rs`). The connection ([`super::conn`]) drives
//! `MqttState` itself instead of through rumqttc's `EventLoop`, so it relies on these fields, whose
//! meaning rumqttc documents only in its source:
//!
//! - `events: VecDeque<Event>` — every packet `handle_incoming_packet` was given is pushed here as
//!   `Event::Incoming` (the event loop hands them to the user from this queue), and every packet
//!   `handle_outgoing_packet` encoded as `Event::Outgoing` (a collision resolved by a PUBACK pushes
//!   one too). Nothing drains it but its reader: [`State::next_incoming`] returns the incoming
//!   ones, the outgoing notices are dropped as they come ([`State::handle_outgoing`]).
//! - `collision: Option<Publish>` — a publication whose packet id was still in flight when it was
//!   queued (the broker acknowledged out of order); rumqttc sends it once that id's PUBACK comes.
//!   While one waits, nothing more may be published ([`State::collided`]).
//! - `await_pingresp: bool` — a PINGREQ went out and its PINGRESP has not come; a second PINGREQ
//!   meanwhile is `StateError::AwaitPingResp` ([`State::awaits_pingresp`]). Cleared by the
//!   PINGRESP and by `clean()`.
//!
//! `inflight()`, `clean()`, `handle_outgoing_packet` and `handle_incoming_packet` are documented
//! methods and keep their meaning: the publications sent and not acknowledged, those taken back
//! (oldest first) after a connection broke, and the packet each request or reply turns into.

use rumqttc::{Event, Incoming, MqttState, Packet, Publish, Request, StateError};

/// rumqttc's MQTT 3.1.1 client state (packet ids, the in-flight window, acks, collisions, the
/// ping), read and written only through these methods.
#[derive(Debug)]
pub struct State(MqttState);

impl State {
    /// A clean state with an in-flight window of `inflight` publications; with `manual_acks`,
    /// received QoS 1 publications are acknowledged only by a [`Request::PubAck`].
    pub fn new(inflight: u16, manual_acks: bool) -> State {
        State(MqttState::new(inflight, manual_acks))
    }

    /// Publications sent and not acknowledged yet.
    pub fn inflight(&self) -> u16 {
        self.0.inflight()
    }

    /// A publication waits for its packet id to be acknowledged: nothing more may be published.
    pub fn collided(&self) -> bool {
        self.0.collision.is_some()
    }

    /// A PINGREQ went out and its PINGRESP has not come.
    pub fn awaits_pingresp(&self) -> bool {
        self.0.await_pingresp
    }

    /// The packet `request` turns into (none for a refused or void one). The state's notice of
    /// the outgoing packet is dropped: the caller knows what it queued, and a burst of
    /// publications between two reads would pile the notices up.
    pub fn handle_outgoing(&mut self, request: Request) -> Result<Option<Packet>, StateError> {
        let packet = self.0.handle_outgoing_packet(request)?;
        if let Some(Event::Outgoing(_)) = self.0.events.back() {
            self.0.events.pop_back();
        }
        Ok(packet)
    }

    /// Takes in a packet from the broker; returns the reply to send, if any (a PUBACK unless acks
    /// are manual, a publication a collision held back). The packet is then read with
    /// [`State::next_incoming`].
    pub fn handle_incoming(&mut self, packet: Incoming) -> Result<Option<Packet>, StateError> {
        self.0.handle_incoming_packet(packet)
    }

    /// The next packet from the broker not yet read, oldest first (outgoing notices skipped).
    pub fn next_incoming(&mut self) -> Option<Event> {
        while let Some(event) = self.0.events.pop_front() {
            if let Event::Incoming(_) = event {
                return Some(event);
            }
        }
        None
    }

    /// Forgets the packets of a broken connection not yet read.
    pub fn forget_incoming(&mut self) {
        self.0.events.clear();
    }

    /// After a connection broke: the publications the broker had not acknowledged, oldest first,
    /// then the one a collision held back (never sent), and a clean state for the next connection
    /// (no ping awaited, nothing in flight, no collision). `clean()` leaves the collision, whose
    /// packet id the next connection would never acknowledge: kept, it would stop publishing for
    /// good.
    pub fn take_back(&mut self) -> Vec<Publish> {
        let collided = self.0.collision.take();
        self.0
            .clean()
            .into_iter()
            .filter_map(|r| match r {
                Request::Publish(p) => Some(p),
                _ => None,
            })
            .chain(collided)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rumqttc::{PubAck, QoS};

    fn publish(state: &mut State, payload: &'static str) -> Option<Packet> {
        let p = Publish::new("t", QoS::AtLeastOnce, payload);
        state.handle_outgoing(Request::Publish(p)).unwrap()
    }

    #[test]
    fn a_collision_at_a_broken_connection_is_taken_back_and_cleared() {
        let mut state = State::new(2, true);
        assert!(publish(&mut state, "a").is_some());
        assert!(publish(&mut state, "b").is_some());
        // The broker acknowledges the second first: the next packet id (1) is still in flight.
        state
            .handle_incoming(Incoming::PubAck(PubAck::new(2)))
            .unwrap();
        assert!(
            publish(&mut state, "c").is_none(),
            "held back by the collision"
        );
        assert!(state.collided());
        let back: Vec<_> = state.take_back().into_iter().map(|p| p.payload).collect();
        assert_eq!(
            back,
            ["a", "c"],
            "the unacknowledged one, then the collided one"
        );
        assert!(!state.collided(), "the next connection may publish");
        assert_eq!(state.inflight(), 0);
    }
}
