//! The gateway's MQTT session as a sans-IO state machine (rumqttc's `state.rs`, quinn-proto's
//! `Connection`): what to subscribe, acknowledge, publish and hand to the core, when to ping,
//! reconnect or give a silent link up. No I/O and no clock: the MQTT task ([`super::MqttTask`])
//! feeds it what the connection and the core did (`handle_*`, with the time) and carries out what it
//! asks (`poll_*`), so every rule here is tested without a socket.
//!
//! The rules:
//! - **Commands wait for the core, acknowledged only once it took them** (manual acks), and only on
//!   the connection they came on: an ack from an older connection is void on a newer one (the
//!   broker sends an unacknowledged QoS 1 command again). QoS 1 commands wait here however many the
//!   broker sends without their acks (its in-flight window: Mosquitto's `max_inflight_messages`,
//!   20 by default, unlimited at 0), up to [`HELD_MAX_ACKED`], more than MQTT's 16-bit packet
//!   identifiers let a broker have unacknowledged: they are never shed. QoS 0 commands, which MQTT
//!   cannot hold back, wait here while fewer than [`HELD_MAX`] inputs do; beyond that they are shed
//!   and counted ([`MqttStats::commands_shed`]). An empty message on the command topic (how MQTT
//!   clears a retained message) is no command: ignored, not answered.
//! - **The retained-state window**: every ConnAck subscribes the state topics to hand the core the
//!   documents an earlier run left ([`MqttInput::RetainedState`]); the first live message there
//!   (this run's own publications coming back) ends that subscription.
//! - **Publications** wait here up to [`STAGING`] (the core keeps the rest); `online` goes first on
//!   every connection, and what the broker had not acknowledged when a connection broke is sent
//!   again first.
//! - **Reconnect** after a failure with a back-off of [`RECONNECT_MIN`] doubling to
//!   [`RECONNECT_MAX`]; a warning at the first failure, then at growing intervals ([`WARN_FIRST`]
//!   doubling to [`WARN_MAX`]), debug lines in between.
//! - **A dead link is noticed within the acknowledgement bound** ([`Timing::ack_timeout`]): a
//!   PINGREQ at every keep-alive, and when a PUBACK or PINGRESP the session waits for has not come
//!   for half the bound, a PINGREQ at once (PUBACKs may be waiting in the kernel under the socket's
//!   low-water mark; the PINGREQ lowers it, so they are read with its answer); when nothing is
//!   acknowledged for the whole bound the link is closed and the session reconnects.

use ihex_gateway_core::{Interface, Origin};
use std::{
    collections::VecDeque,
    sync::{atomic::Ordering, Arc},
    time::{Duration, Instant},
};

use bytes::Bytes;
use rumqttc::{Incoming, Publish, QoS, SubAck, SubscribeReasonCode};
use tracing::{debug, info, warn};

use super::{MqttInput, MqttStats, Outbound, ONLINE};
use crate::topic::Topics;

/// First delay after a failed connection attempt; doubles up to [`RECONNECT_MAX`].
pub const RECONNECT_MIN: Duration = Duration::from_millis(100);
/// Longest delay between connection attempts.
pub const RECONNECT_MAX: Duration = Duration::from_secs(5);
/// After the first warning about an unreachable broker, the next comes this much later; the
/// interval doubles up to [`WARN_MAX`].
pub const WARN_FIRST: Duration = Duration::from_secs(5);
/// Longest interval between two warnings about an unreachable broker.
pub const WARN_MAX: Duration = Duration::from_secs(300);
/// Publications taken from the core and waiting here for room in the connection's in-flight
/// window (the core holds the rest).
pub const STAGING: usize = 64;
/// Commands received and not yet taken by the core, beyond which QoS 0 commands are shed.
pub const HELD_MAX: usize = 1024;
/// Places the held inputs and the requests keep once empty: a burst from a broker without an
/// in-flight limit grows them to thousands (136 bytes per held command), given back when they
/// empty instead of kept for the rest of the run.
const KEPT: usize = 64;
/// Inputs held beyond which even a QoS 1 command is shed (acknowledged, counted): the other
/// inputs' bound plus every packet identifier a broker can have unacknowledged on one connection,
/// so a broker that follows the protocol never reaches it.
pub const HELD_MAX_ACKED: usize = HELD_MAX + u16::MAX as usize;
/// The keep-alive by default: the broker publishes the last will 15 s after a gateway went silent
/// (power cut, cable pulled), the gateway's ping every 10 s bounds how long an idle dead link goes
/// unnoticed (keep-alive + [`DEFAULT_ACK_TIMEOUT`]), and both ends still ride out a stall of 5 s
/// (Wi-Fi retransmissions, a busy broker). A ping costs 2 bytes each way.
pub const DEFAULT_KEEP_ALIVE: Duration = Duration::from_secs(10);
/// How long a PUBACK or PINGRESP may stay missing by default before the link is taken for dead:
/// far above a LAN broker's round trip (milliseconds, a busy Pi's tens of them), and short enough
/// that a frozen link costs seconds.
pub const DEFAULT_ACK_TIMEOUT: Duration = Duration::from_secs(5);

/// The session's clocks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Timing {
    /// A PINGREQ this often (zero: none); the broker takes the gateway for gone after 1.5 times
    /// this without a packet.
    pub keep_alive: Duration,
    /// How long a PUBACK or PINGRESP the session waits for may stay missing before the link is
    /// taken for dead.
    pub ack_timeout: Duration,
}

/// What the session asks of the connection, besides publications.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Request {
    /// Subscribe a filter.
    Subscribe {
        /// The filter.
        filter: String,
        /// Its QoS.
        qos: QoS,
    },
    /// Unsubscribe a filter.
    Unsubscribe(String),
    /// Acknowledge a received QoS 1 publication.
    Ack(u16),
    /// Send a PINGREQ.
    Ping,
    /// The link is taken for dead: close it (the connection then reports the loss, and
    /// [`Session::handle_connection_lost`] follows).
    Close(String),
}

/// A command the core has not taken yet, and how to acknowledge it.
#[derive(Debug)]
struct Held {
    input: MqttInput,
    /// The packet id to acknowledge once the core took it (QoS 1), and the connection it came on.
    ack: Option<(u16, u64)>,
}

/// The first of `queue`, which gives a burst's room back once it is empty (down to [`KEPT`]).
fn pop_front<T>(queue: &mut VecDeque<T>) -> Option<T> {
    let first = queue.pop_front();
    if queue.is_empty() {
        queue.shrink_to(KEPT);
    }
    first
}

/// The broker link as the session sees it.
#[derive(Debug)]
enum Link {
    /// No connection: after a failure, no attempt before `retry_at`.
    Down { retry_at: Option<Instant> },
    /// Connected since a ConnAck; `closing` once the session gave the link up.
    Up { closing: bool },
}

/// When to warn again about an unreachable broker.
#[derive(Debug)]
struct WarnSchedule {
    next: Option<Instant>,
    interval: Duration,
}

impl WarnSchedule {
    fn new() -> Self {
        WarnSchedule {
            next: None,
            interval: WARN_FIRST,
        }
    }

    /// True when a failure now deserves a warning (the first one, then at growing intervals).
    fn due(&mut self, now: Instant) -> bool {
        if self.next.is_some_and(|n| now < n) {
            return false;
        }
        self.next = Some(now + self.interval);
        self.interval = (self.interval * 2).min(WARN_MAX);
        true
    }
}

/// The acknowledgements the session waits for on this connection, and its timers.
#[derive(Debug, Default)]
struct Liveness {
    /// When the next keep-alive PINGREQ is due.
    ping_at: Option<Instant>,
    /// A PINGREQ awaits its PINGRESP since then.
    ping_sent: Option<Instant>,
    /// Publications handed to the connection and not acknowledged.
    unacked: usize,
    /// An acknowledgement has been owed since then without any coming (reset by each one).
    owed_since: Option<Instant>,
}

impl Liveness {
    fn start(now: Instant, keep_alive: Duration) -> Liveness {
        Liveness {
            ping_at: (!keep_alive.is_zero()).then(|| now + keep_alive),
            ..Liveness::default()
        }
    }

    fn owes(&self) -> bool {
        self.unacked > 0 || self.ping_sent.is_some()
    }

    /// A probe PINGREQ is due then (none while one is awaited).
    fn probe_at(&self, bound: Duration) -> Option<Instant> {
        match self.ping_sent {
            Some(_) => None,
            None => self.owed_since.map(|t| t + bound / 2),
        }
    }

    fn dead_at(&self, bound: Duration) -> Option<Instant> {
        self.owed_since.map(|t| t + bound)
    }

    fn next_timeout(&self, bound: Duration) -> Option<Instant> {
        [self.ping_at, self.probe_at(bound), self.dead_at(bound)]
            .into_iter()
            .flatten()
            .min()
    }

    fn published(&mut self, now: Instant) {
        self.unacked += 1;
        self.owed_since.get_or_insert(now);
    }

    fn unpublished(&mut self) {
        self.unacked = self.unacked.saturating_sub(1);
        if !self.owes() {
            self.owed_since = None;
        }
    }

    fn pinged(&mut self, now: Instant) {
        self.ping_sent = Some(now);
        self.owed_since.get_or_insert(now);
    }

    /// An acknowledgement came: the link is alive now.
    fn acknowledged(&mut self, now: Instant) {
        self.owed_since = self.owes().then_some(now);
    }
}

/// The MQTT session (see the module docs for its rules).
#[derive(Debug)]
pub struct Session {
    topics: Topics,
    /// Subscribe Home Assistant's status and command topics.
    ha: bool,
    /// The broker as messages name it.
    broker: String,
    stats: Arc<MqttStats>,
    timing: Timing,
    link: Link,
    /// Connection number: an ack only goes back on the connection its message came on.
    generation: u64,
    /// The delay before the next attempt after a failure.
    backoff: Duration,
    warn_at: WarnSchedule,
    /// Inputs the core has not taken, oldest first.
    held: VecDeque<Held>,
    /// What to ask of the connection, in order.
    requests: VecDeque<Request>,
    /// Publications waiting for room in the connection.
    staged: VecDeque<Outbound>,
    /// `online` is still to be published on this connection.
    announce: bool,
    /// Subscribed to the state topics for the retained documents (the window is open).
    reading_states: bool,
    liveness: Liveness,
}

impl Session {
    /// A session not connected yet (the first attempt may start at once).
    pub fn new(
        topics: Topics,
        ha: bool,
        broker: String,
        stats: Arc<MqttStats>,
        timing: Timing,
    ) -> Session {
        Session {
            topics,
            ha,
            broker,
            stats,
            timing,
            link: Link::Down { retry_at: None },
            generation: 0,
            backoff: RECONNECT_MIN,
            warn_at: WarnSchedule::new(),
            held: VecDeque::new(),
            requests: VecDeque::new(),
            staged: VecDeque::new(),
            announce: false,
            reading_states: false,
            liveness: Liveness::default(),
        }
    }

    /// Connected (a ConnAck accepted, no loss since).
    pub fn is_connected(&self) -> bool {
        matches!(self.link, Link::Up { .. })
    }

    /// The connection may be polled: connected, connecting, or a new attempt may start (false
    /// while the back-off after a failure runs).
    pub fn wants_link(&self) -> bool {
        !matches!(self.link, Link::Down { retry_at: Some(_) })
    }

    /// Room for more publications from the core.
    pub fn wants_publications(&self) -> bool {
        self.staged.len() < STAGING
    }

    /// Publications waiting here.
    pub fn staged(&self) -> usize {
        self.staged.len()
    }

    /// Inputs the core has not taken.
    pub fn held(&self) -> usize {
        self.held.len()
    }

    /// An input waits for the core.
    pub fn has_input(&self) -> bool {
        !self.held.is_empty()
    }

    /// When [`Session::handle_timeout`] is next due.
    #[must_use]
    pub fn poll_timeout(&self) -> Option<Instant> {
        match self.link {
            Link::Down { retry_at } => retry_at,
            Link::Up { closing: false } => self.liveness.next_timeout(self.timing.ack_timeout),
            Link::Up { closing: true } => None,
        }
    }

    /// The time passed: ends the back-off, asks for the keep-alive PINGREQ or a probe, or gives a
    /// silent link up.
    pub fn handle_timeout(&mut self, now: Instant) {
        match &mut self.link {
            Link::Down { retry_at } => {
                if retry_at.is_some_and(|t| now >= t) {
                    *retry_at = None;
                }
            }
            Link::Up { closing: true } => {}
            Link::Up { closing } => {
                let bound = self.timing.ack_timeout;
                let live = &mut self.liveness;
                if live.dead_at(bound).is_some_and(|t| now >= t) {
                    let why = format!(
                        "no acknowledgement from the broker for {bound:?} ({} publication(s) \
                         without PUBACK{}): the link is taken for dead",
                        live.unacked,
                        if live.ping_sent.is_some() {
                            ", a PINGREQ without PINGRESP"
                        } else {
                            ""
                        }
                    );
                    *closing = true;
                    self.requests.push_back(Request::Close(why));
                    return;
                }
                let keep_alive = live.ping_at.is_some_and(|t| now >= t);
                let probe = live.probe_at(bound).is_some_and(|t| now >= t);
                if keep_alive {
                    live.ping_at = Some(now + self.timing.keep_alive);
                }
                if (keep_alive || probe) && live.ping_sent.is_none() {
                    live.pinged(now);
                    self.requests.push_back(Request::Ping);
                }
            }
        }
    }

    /// A packet from the broker.
    pub fn handle_incoming(&mut self, packet: Incoming, now: Instant) {
        match packet {
            // rumqttc turns a refusing ConnAck into an error: this one is accepted.
            Incoming::ConnAck(_) => self.handle_connack(now),
            Incoming::Publish(p) => self.handle_publish(p, now),
            Incoming::PubAck(_) => self.handle_puback(now),
            Incoming::PingResp => self.handle_pingresp(now),
            Incoming::SubAck(s) => self.handle_suback(&s, now),
            Incoming::UnsubAck(_) => self.liveness.acknowledged(now),
            _ => {}
        }
    }

    /// An accepted ConnAck: a new connection with a clean session, so subscribe, announce `online`
    /// and tell the core (after the commands it has not taken yet).
    pub fn handle_connack(&mut self, now: Instant) {
        self.link = Link::Up { closing: false };
        self.generation += 1;
        self.backoff = RECONNECT_MIN;
        self.warn_at = WarnSchedule::new();
        let failed = self.stats.failed_attempts.swap(0, Ordering::Relaxed);
        self.stats.connected.store(true, Ordering::Relaxed);
        self.stats.set_error(None);
        let n = self.stats.connects.fetch_add(1, Ordering::Relaxed) + 1;
        info!(
            broker = %self.broker,
            connects = n,
            failed_attempts = failed,
            backlog = self.staged.len(),
            "connected to the broker"
        );
        self.requests.clear();
        let mut filters = vec![
            self.topics.commands.clone(),
            self.topics.user_command_filter(),
            self.topics.fw_upload_filter(),
        ];
        if self.ha {
            filters.push(self.topics.ha.status.clone());
            filters.push(self.topics.ha.command_filter());
        }
        for filter in filters {
            self.requests.push_back(Request::Subscribe {
                filter,
                qos: QoS::AtLeastOnce,
            });
        }
        // QoS 0: retained documents need no acknowledgement.
        self.requests.push_back(Request::Subscribe {
            filter: self.topics.node_state_filter(),
            qos: QoS::AtMostOnce,
        });
        self.reading_states = true;
        self.announce = true;
        self.liveness = Liveness::start(now, self.timing.keep_alive);
        // Never shed: it does not take a command's place.
        self.held.push_back(Held {
            input: MqttInput::Connected,
            ack: None,
        });
    }

    /// A publication from the broker: a command (or another input) for the core, a retained state
    /// document, or the end of the retained-state window.
    pub fn handle_publish(&mut self, p: Publish, now: Instant) {
        let ack = (p.qos != QoS::AtMostOnce).then_some((p.pkid, self.generation));
        let user = self.topics.parse_user_command(&p.topic);
        let input = if p.topic == self.topics.commands || user.is_some() {
            if p.payload.is_empty() {
                // How MQTT deletes a retained message: not a command, nothing to answer.
                debug!(
                    retained = p.retain,
                    "empty message on the command topic ignored (a retained command cleared)"
                );
                self.ack_now(ack);
                return;
            }
            self.stats.commands.fetch_add(1, Ordering::Relaxed);
            // The broker's ACL lets only the user named by the topic publish there.
            let user = user.map(str::to_owned);
            MqttInput::Command {
                payload: p.payload,
                received: now,
                retained: p.retain,
                origin: Origin::new(Interface::Mqtt, user),
            }
        } else if let Some(name) = self.topics.parse_fw_upload(&p.topic) {
            MqttInput::FwUpload {
                name: name.to_owned(),
                payload: p.payload,
                retained: p.retain,
            }
        } else if let Some(id) = self.topics.parse_node_state(&p.topic) {
            if !p.retain {
                // Retained messages come right after the subscription, before anything live: the
                // rest are our own publications, not wanted back.
                if std::mem::take(&mut self.reading_states) {
                    let filter = self.topics.node_state_filter();
                    self.requests.push_back(Request::Unsubscribe(filter));
                }
                self.ack_now(ack);
                return;
            }
            MqttInput::RetainedState {
                id,
                payload: p.payload.to_vec(),
            }
        } else if self.ha && p.topic == self.topics.ha.status {
            MqttInput::HaStatus(p.payload.to_vec())
        } else if self.ha && self.topics.ha.parse_command(&p.topic).is_some() {
            self.stats.commands.fetch_add(1, Ordering::Relaxed);
            MqttInput::HaCommand {
                topic: p.topic,
                payload: p.payload.to_vec(),
            }
        } else {
            debug!(topic = %p.topic, "message on an unexpected topic ignored");
            // Unacknowledged, it would hold a place of the broker's in-flight window.
            self.ack_now(ack);
            return;
        };
        self.hold(Held { input, ack });
    }

    /// A PUBACK: one publication less in flight.
    pub fn handle_puback(&mut self, now: Instant) {
        self.liveness.unacked = self.liveness.unacked.saturating_sub(1);
        self.liveness.acknowledged(now);
    }

    /// A PINGRESP.
    pub fn handle_pingresp(&mut self, now: Instant) {
        self.liveness.ping_sent = None;
        self.liveness.acknowledged(now);
    }

    /// A SUBACK: a refused subscription is a warning naming what to check.
    pub fn handle_suback(&mut self, s: &SubAck, now: Instant) {
        self.liveness.acknowledged(now);
        if s.return_codes
            .iter()
            .any(|c| matches!(c, SubscribeReasonCode::Failure))
        {
            warn!(
                broker = %self.broker,
                topic = %self.topics.commands,
                "broker refused the subscription to the command topic: check the broker's ACL for \
                 this user"
            );
        }
    }

    /// The connection broke or an attempt failed (`error`, and `why` in a person's words with
    /// what to check); `taken_back` are the publications the broker had not acknowledged, oldest
    /// first, to send again first. Starts the back-off.
    pub fn handle_connection_lost(
        &mut self,
        error: &str,
        why: String,
        taken_back: Vec<Outbound>,
        now: Instant,
    ) {
        let attempts = self.stats.failed_attempts.fetch_add(1, Ordering::Relaxed) + 1;
        let retry_in = self.backoff;
        if self.is_connected() {
            warn!(broker = %self.broker, error, "connection to the broker lost; reconnecting");
        } else if self.warn_at.due(now) {
            warn!(broker = %self.broker, attempts, ?retry_in, "{why}");
        } else {
            debug!(broker = %self.broker, attempts, ?retry_in, "{why}");
        }
        self.stats.connected.store(false, Ordering::Relaxed);
        self.stats.set_error(Some(why));
        self.link = Link::Down {
            retry_at: Some(now + retry_in),
        };
        self.backoff = (self.backoff * 2).min(RECONNECT_MAX);
        // Acks, subscriptions and pings of the lost connection are void; `online` is redone.
        self.requests.clear();
        self.announce = false;
        self.liveness = Liveness::default();
        let back: Vec<Outbound> = taken_back
            .into_iter()
            .filter(|p| p.topic != self.topics.availability)
            .collect();
        if !back.is_empty() {
            debug!(
                count = back.len(),
                "publications taken back for the next connection"
            );
            self.stats
                .published
                .fetch_sub(back.len() as u64, Ordering::Relaxed);
        }
        for p in back.into_iter().rev() {
            self.staged.push_front(p);
        }
    }

    /// A publication from the core, to send after those waiting.
    pub fn handle_publication(&mut self, p: Outbound) {
        self.staged.push_back(p);
    }

    /// The connection had no room for `p` (the last one polled): it goes back to the front.
    pub fn handle_publication_refused(&mut self, p: Outbound) {
        self.liveness.unpublished();
        if p.topic == self.topics.availability {
            self.announce = true;
        } else {
            self.stats.published.fetch_sub(1, Ordering::Relaxed);
            self.staged.push_front(p);
        }
    }

    /// The next input for the core, once it has room (its ack, if any, is then queued).
    #[must_use]
    pub fn poll_input(&mut self) -> Option<MqttInput> {
        let h = pop_front(&mut self.held)?;
        if let Some((pkid, generation)) = h.ack {
            if generation == self.generation && self.is_connected() {
                self.requests.push_back(Request::Ack(pkid));
            }
        }
        Some(h.input)
    }

    /// The next request for the connection (none while not connected).
    #[must_use]
    pub fn poll_request(&mut self) -> Option<Request> {
        if !self.is_connected() {
            return None;
        }
        pop_front(&mut self.requests)
    }

    /// The next publication for the connection: `online` first on each connection, then the
    /// staged ones (none while not connected, or once the link is given up). One the connection
    /// refuses comes back through [`Session::handle_publication_refused`].
    #[must_use]
    pub fn poll_publication(&mut self, now: Instant) -> Option<Outbound> {
        if !matches!(self.link, Link::Up { closing: false }) {
            return None;
        }
        let p = if std::mem::take(&mut self.announce) {
            Outbound {
                topic: self.topics.availability.clone(),
                payload: Bytes::from_static(ONLINE.as_bytes()),
                retain: true,
            }
        } else {
            let p = self.staged.pop_front()?;
            self.stats.published.fetch_add(1, Ordering::Relaxed);
            p
        };
        self.liveness.published(now);
        Some(p)
    }

    /// Keeps a command (or another input) for the core, unacknowledged; sheds it beyond
    /// [`HELD_MAX`] (QoS 0) or [`HELD_MAX_ACKED`] (QoS 1).
    fn hold(&mut self, h: Held) {
        // A QoS 1 command held back costs the broker a place in its in-flight window, which
        // bounds how many come; shedding it would break the one answer every command gets.
        let bound = if h.ack.is_some() {
            HELD_MAX_ACKED
        } else {
            HELD_MAX
        };
        if self.held.len() < bound {
            self.held.push_back(h);
            return;
        }
        // Acknowledged all the same: an unacknowledged message would hold a place of the broker's
        // in-flight window for the rest of the connection.
        self.ack_now(h.ack);
        let n = self.stats.commands_shed.fetch_add(1, Ordering::Relaxed) + 1;
        if n.is_power_of_two() {
            warn!(
                commands_shed = n,
                held = HELD_MAX,
                "command intake full: a command was dropped unanswered (publish commands with QoS 1 \
                 so that the broker holds them back while the gateway is busy)"
            );
        }
    }

    /// Acknowledges a publication of this connection that the core will not take.
    fn ack_now(&mut self, ack: Option<(u16, u64)>) {
        if let Some((pkid, _)) = ack {
            self.requests.push_back(Request::Ack(pkid));
        }
    }
}

#[cfg(test)]
pub(crate) mod tests;
