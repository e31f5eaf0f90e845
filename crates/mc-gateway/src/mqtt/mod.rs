//! The MQTT side: exactly one task owns the broker [`Connection`] (see [`conn`]: rumqttc's packets
//! and codec, our client [`state`] and I/O, one write per batch of packets) and the [`Session`] (see [`session`]: every
//! rule of the MQTT session — manual acks per connection, commands held for the core and QoS 0
//! floods shed, the retained-state window, `online`, publications taken back after a break,
//! back-off, warnings, the keep-alive and the dead-link bound — as a sans-IO state machine).
//! [`MqttTask::run`] only carries the session's requests to the connection, the connection's
//! packets and the core's publications to the session, and the session's inputs to the core.
//!
//! It connects with keep-alive, clean session and a retained `offline` last will. Every packet the
//! broker delivers is read, up to the MQTT maximum ([`MAX_INCOMING`]), so an oversized command
//! reaches the core and is answered instead of breaking the connection. The socket options are set
//! through `crate::sys` only (the crate's one `unsafe` module).

use ihex_gateway_core::Origin;
use std::{
    sync::{
        atomic::{AtomicBool, AtomicU64, Ordering},
        Arc, Mutex,
    },
    time::{Duration, Instant},
};

use bytes::Bytes;
use rumqttc::{ConnectReturnCode, ConnectionError, Event, LastWill, MqttOptions, Outgoing, QoS};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::{config::MqttConfig, error::MqttError, timer::Timer, topic::Topics};

pub mod conn;
pub mod session;
pub mod state;
#[allow(unsafe_code)]
#[cfg(test)]
mod test_broker;
pub use conn::Connection;
pub use session::{
    Request, Session, Timing, DEFAULT_ACK_TIMEOUT, DEFAULT_KEEP_ALIVE, HELD_MAX, RECONNECT_MAX,
    RECONNECT_MIN, STAGING, WARN_FIRST, WARN_MAX,
};

/// Payload of the availability topic while the gateway runs.
pub const ONLINE: &str = "online";
/// Payload of the availability topic once it stops (also the last will).
pub const OFFLINE: &str = "offline";
/// The largest packet MQTT allows (remaining length 268 435 455 plus a 5-byte fixed header): the
/// incoming limit, so no packet a broker delivers can break the connection.
pub const MAX_INCOMING: usize = 268_435_455 + 5;
/// Largest outgoing packet (the gateway's own publications are small).
const MAX_OUTGOING: usize = 1 << 20;
/// Limit of one connection attempt: TCP connect, TLS handshake, CONNECT and CONNACK.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(5);
/// How long shutdown waits for the last publications, `offline` and the DISCONNECT to go out.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

/// One message to publish with QoS 1: a serialised core publication under its concrete topic.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Outbound {
    /// Concrete topic name.
    pub topic: String,
    /// Payload bytes (JSON text).
    pub payload: Bytes,
    /// Retained or not.
    pub retain: bool,
}

/// What the MQTT task hands to the gateway core.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MqttInput {
    /// A message on the command topic (raw payload; the core validates it).
    Command {
        /// The payload as received.
        payload: Bytes,
        /// When this task read it off the connection (a command's `ttl_ms` counts from here).
        received: Instant,
        /// The broker delivered it as a retained message (never executed).
        retained: bool,
        /// The interface and the identity it came with (a per-user topic names its user).
        origin: Origin,
    },
    /// A message on one of Home Assistant's command topics (the core reads the topic too).
    HaCommand {
        /// The topic, in full.
        topic: String,
        /// The raw payload.
        payload: Vec<u8>,
    },
    /// A message on Home Assistant's status topic (its birth message is `online`).
    HaStatus(Vec<u8>),
    /// A firmware image on an upload topic (`<root>/<name>`).
    FwUpload {
        /// The last level of the topic.
        name: String,
        /// The image bytes as received.
        payload: Bytes,
        /// The broker delivered it as a retained message (refused by the core).
        retained: bool,
    },
    /// A retained state document the broker delivered on subscribing to the state topics.
    RetainedState {
        /// The node whose topic it is.
        id: ihex_proto::NodeId,
        /// The document as received (empty: the topic was cleared).
        payload: Vec<u8>,
    },
    /// A ConnAck: the session is (re)established and subscribed.
    Connected,
}

/// Counters and state of the MQTT side, readable while the gateway runs (tests, benchmarks, a web
/// view).
#[derive(Debug, Default)]
pub struct MqttStats {
    /// Connected to the broker right now (from an accepted ConnAck to the next connection error).
    pub connected: AtomicBool,
    /// Successful connections (ConnAck accepted).
    pub connects: AtomicU64,
    /// Publications handed to rumqttc.
    pub published: AtomicU64,
    /// Messages received on the command topic.
    pub commands: AtomicU64,
    /// Commands shed unanswered because [`HELD_MAX`] commands already waited for the core (only
    /// QoS 0 floods get here: the broker holds QoS 1 commands back).
    pub commands_shed: AtomicU64,
    /// Events the core dropped because they could not be published as fast as they came (the
    /// core's count, mirrored here; never answers or state documents).
    pub publications_dropped: AtomicU64,
    /// The core has commands out whose answers it will publish (set by the core at every turn):
    /// each is answered by its node or, when its time runs out, `timeout`, so a command's PUBACK
    /// may wait to leave with an answer ([`conn::Connection::hold_acks`]).
    pub answers_due: AtomicBool,
    /// Failed connection attempts since the last successful one.
    pub failed_attempts: AtomicU64,
    /// Writes to the broker's socket (each a system call and a TCP segment that wakes the
    /// broker): how well acknowledgements and publications are batched.
    pub writes: Arc<AtomicU64>,
    /// Why the last attempt failed, or the connection broke; `None` while connected.
    last_error: Mutex<Option<String>>,
}

/// The broker link as a status view shows it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BrokerLink {
    /// Connected now.
    pub connected: bool,
    /// Failed attempts since the last successful connection.
    pub failed_attempts: u64,
    /// What went wrong last (with what to check), while not connected.
    pub last_error: Option<String>,
}

impl MqttStats {
    /// The broker link now.
    pub fn broker_link(&self) -> BrokerLink {
        BrokerLink {
            connected: self.connected.load(Ordering::Relaxed),
            failed_attempts: self.failed_attempts.load(Ordering::Relaxed),
            last_error: self.last_error.lock().map(|e| e.clone()).unwrap_or(None),
        }
    }

    fn set_error(&self, e: Option<String>) {
        if let Ok(mut last) = self.last_error.lock() {
            *last = e;
        }
    }
}

/// The rumqttc options of the gateway's own client: [`client_options`] plus the retained `offline`
/// last will, manual acks (a command is acknowledged once the core took it) and the incoming size
/// limit.
pub fn options(cfg: &MqttConfig, topics: &Topics) -> Result<MqttOptions, MqttError> {
    let mut o = client_options(cfg, cfg.client_id.clone())?;
    o.set_last_will(LastWill::new(
        &topics.availability,
        OFFLINE,
        QoS::AtLeastOnce,
        true,
    ))
    .set_manual_acks(true)
    // An oversized command must reach the core (to be rejected with a reason) rather than
    // break the connection: nothing a broker can deliver is refused.
    .set_max_packet_size(MAX_INCOMING, MAX_OUTGOING);
    Ok(o)
}

/// Options of any client of the configured broker: keep-alive, clean session, credentials, TLS.
pub fn client_options(cfg: &MqttConfig, client_id: String) -> Result<MqttOptions, MqttError> {
    let (host, port) = match &cfg.broker {
        crate::config::Broker::External { host, port } => (host.clone(), *port),
        crate::config::Broker::Embedded { listen } => (listen.ip().to_string(), listen.port()),
    };
    let mut o = MqttOptions::new(client_id, host, port);
    o.set_keep_alive(cfg.keep_alive).set_clean_session(true);
    if let Some((user, pass)) = &cfg.credentials {
        o.set_credentials(user.clone(), pass.clone());
    }
    if let Some(ca) = &cfg.tls {
        set_tls(&mut o, ca.as_deref())?;
    }
    Ok(o)
}

#[cfg(feature = "tls")]
fn set_tls(o: &mut MqttOptions, ca: Option<&std::path::Path>) -> Result<(), MqttError> {
    use rustls::pki_types::{pem::PemObject, CertificateDer};
    // Our crypto provider is ring (the `tls` feature). Installing it fails harmlessly when one is
    // installed already.
    let _ = rustls::crypto::ring::default_provider().install_default();
    let mut roots = rustls::RootCertStore::empty();
    match ca {
        Some(path) => {
            let pem = std::fs::read(path).map_err(|source| MqttError::TlsCa {
                path: path.to_owned(),
                source,
            })?;
            let certs = CertificateDer::pem_slice_iter(&pem).filter_map(Result::ok);
            let (added, _) = roots.add_parsable_certificates(certs);
            if added == 0 {
                return Err(MqttError::TlsCa {
                    path: path.to_owned(),
                    source: std::io::Error::new(
                        std::io::ErrorKind::InvalidData,
                        "no PEM certificate in the file",
                    ),
                });
            }
        }
        None => {
            // The system's roots; unreadable ones are skipped (the handshake then says which
            // certificate it could not verify).
            let native = rustls_native_certs::load_native_certs();
            roots.add_parsable_certificates(native.certs);
        }
    }
    let config = rustls::ClientConfig::builder()
        .with_root_certificates(roots)
        .with_no_client_auth();
    o.set_transport(rumqttc::Transport::tls_with_config(
        rumqttc::TlsConfiguration::Rustls(Arc::new(config)),
    ));
    Ok(())
}

#[cfg(not(feature = "tls"))]
fn set_tls(_: &mut MqttOptions, _: Option<&std::path::Path>) -> Result<(), MqttError> {
    Err(MqttError::TlsUnavailable)
}

/// The MQTT task's fixed parts.
pub struct MqttTask {
    /// Connection options (see [`options`]); their keep-alive is the session's too.
    pub options: MqttOptions,
    /// Topic names.
    pub topics: Topics,
    /// Subscribe Home Assistant's status and command topics (discovery is on).
    pub ha: bool,
    /// The broker as messages name it (`host:port`).
    pub broker: String,
    /// Counters.
    pub stats: Arc<MqttStats>,
    /// How long a PUBACK or PINGRESP may stay missing before the link is taken for dead
    /// ([`Timing::ack_timeout`]).
    pub ack_timeout: Duration,
}

/// Why a connection attempt failed, and what to check, in a person's words.
pub fn explain(e: &ConnectionError, broker: &str, tls: bool) -> String {
    let tls_hint = if tls {
        "; with TLS also check --tls-ca and that the broker's certificate names this host"
    } else {
        ""
    };
    match e {
        ConnectionError::ConnectionRefused(code) => match code {
            ConnectReturnCode::BadUserNamePassword | ConnectReturnCode::NotAuthorized => format!(
                "broker {broker} refused the login ({code:?}): check --username and --password \
                 (IHEX_MQTT_USERNAME, IHEX_MQTT_PASSWORD) against the broker's password file and ACL"
            ),
            ConnectReturnCode::BadClientId => format!(
                "broker {broker} refused the client id ({code:?}): check --client-id"
            ),
            other => format!("broker {broker} refused the connection ({other:?})"),
        },
        ConnectionError::Io(io) if io.kind() == std::io::ErrorKind::ConnectionRefused => format!(
            "nothing accepts connections at {broker} ({io}): is the broker running, and is that \
             its host and port (--broker)?"
        ),
        ConnectionError::Io(io) => format!(
            "cannot reach broker {broker} ({io}): check --broker, the network and firewalls{tls_hint}"
        ),
        ConnectionError::NetworkTimeout => format!(
            "no answer from broker {broker} within 5 s: check --broker, the network and \
             firewalls{tls_hint}"
        ),
        other => format!("connection to broker {broker} failed ({other}){tls_hint}"),
    }
}

impl MqttTask {
    /// Runs until `cancel`: then publishes what the core still hands over (until it closes the
    /// channel, within the grace period), `offline` (retained), and disconnects.
    #[tracing::instrument(name = "mqtt", skip_all, fields(client_id = %self.options.client_id()))]
    pub async fn run(
        self,
        mut publications: mpsc::Receiver<Outbound>,
        inputs: mpsc::Sender<MqttInput>,
        cancel: CancellationToken,
    ) {
        let mut conn = Connection::new(self.options.clone(), MAX_OUTGOING, CONNECT_TIMEOUT);
        conn.count_writes_in(self.stats.writes.clone());
        let tls = !matches!(self.options.transport(), rumqttc::Transport::Tcp);
        let timing = Timing {
            keep_alive: self.options.keep_alive(),
            ack_timeout: self.ack_timeout,
        };
        let mut session = Session::new(
            self.topics.clone(),
            self.ha,
            self.broker.clone(),
            self.stats.clone(),
            timing,
        );
        let mut publications_open = true;
        // An input handed over by the `inputs.reserve()` branch (the core's channel was full).
        let mut handed = 0;
        let mut timer = Timer::new();
        let mut cancelled = crate::shutdown::stopped(&cancel);
        // Everything queued between two polls leaves in one write: requests and publications are
        // queued first, then `poll()` (cancel-safe) writes them while waiting for the broker.
        // The loop ends when the core is gone.
        while let Some(delivered) = deliver(&mut session, &inputs) {
            if std::mem::take(&mut handed) + delivered > 0 {
                // The core takes what was just handed to it in its own turn, which runs now, before
                // this task writes: what it publishes in that turn (the answers of acks read with
                // the commands, a command's rejection) leaves in the same write as the commands'
                // PUBACKs instead of in a second one.
                tokio::task::yield_now().await;
                while publications_open && session.wants_publications() {
                    let Ok(p) = publications.try_recv() else {
                        break;
                    };
                    session.handle_publication(p);
                }
            }
            carry_out(&mut session, &mut conn);
            // Never while commands wait for the core: in a flood each write of PUBACKs also
            // acknowledges the broker's TCP stream, which delayed-ACK mode leaves to the next write.
            conn.hold_acks(self.stats.answers_due.load(Ordering::Relaxed) && !session.has_input());
            timer.set(session.poll_timeout());
            let wants_link = session.wants_link();
            let wants_publications = publications_open && session.wants_publications();
            let has_input = session.has_input();
            tokio::select! {
                _ = &mut cancelled => break,
                p = publications.recv(), if wants_publications => match p {
                    Some(p) => {
                        session.handle_publication(p);
                        // The rest of the core's turn, without another round of the loop.
                        while session.wants_publications() {
                            let Ok(p) = publications.try_recv() else { break };
                            session.handle_publication(p);
                        }
                    }
                    None => publications_open = false,
                },
                permit = inputs.reserve(), if has_input => {
                    let Ok(permit) = permit else { break };
                    if let Some(input) = session.poll_input() {
                        permit.send(input);
                        handed += 1;
                    }
                }
                _ = timer.expired() => session.handle_timeout(Instant::now()),
                ev = conn.poll(), if wants_link => {
                    // Every packet of the read, in this turn: a burst of commands reads as thousands
                    // of packets at once, and the broker's acknowledgements behind them must not
                    // wait a turn of this loop each (the session would take the link for dead).
                    let mut next = Some(ev);
                    while let Some(ev) = next.take() {
                        match ev {
                            Ok(Event::Incoming(packet)) => session.handle_incoming(packet, Instant::now()),
                            Ok(Event::Outgoing(_)) => {}
                            Err(e) => {
                                let why = explain(&e, &self.broker, tls);
                                let back = conn.take_back().into_iter().map(|p| Outbound {
                                    topic: p.topic,
                                    payload: p.payload,
                                    retain: p.retain,
                                });
                                session.handle_connection_lost(&e.to_string(), why, back.collect(), Instant::now());
                                break;
                            }
                        }
                        next = conn.next_read().map(Ok);
                    }
                }
            }
        }
        self.stats.connected.store(false, Ordering::Relaxed);
        if session.is_connected() {
            self.goodbye(&mut conn, &mut session, &mut publications)
                .await;
        }
        info!(
            unsent = session.staged() + publications.len(),
            commands_not_taken = session.held(),
            "MQTT task stopped"
        );
    }

    /// Sends what is still queued and what the core still hands over (until it closes the
    /// channel), then `offline` (retained), then DISCONNECT, polling the connection until the
    /// DISCONNECT is written or [`SHUTDOWN_GRACE`] passes.
    async fn goodbye(
        &self,
        conn: &mut Connection,
        session: &mut Session,
        publications: &mut mpsc::Receiver<Outbound>,
    ) {
        let deadline = tokio::time::Instant::now() + SHUTDOWN_GRACE;
        let mut said_goodbye = false;
        let mut open = true;
        loop {
            carry_out(session, conn);
            if session.staged() == 0 && !open && !said_goodbye {
                let offline = Bytes::from_static(OFFLINE.as_bytes());
                said_goodbye = conn
                    .publish(self.topics.availability.clone(), offline, true)
                    .is_ok();
                if said_goodbye {
                    conn.disconnect();
                }
            }
            let ev = tokio::select! {
                p = publications.recv(), if open && session.wants_publications() => {
                    match p {
                        Some(p) => session.handle_publication(p),
                        None => open = false,
                    }
                    continue;
                }
                ev = tokio::time::timeout_at(deadline, conn.poll()) => ev,
            };
            match ev {
                Ok(Ok(Event::Outgoing(Outgoing::Disconnect))) => {
                    info!("published offline and disconnected");
                    return;
                }
                Ok(Ok(Event::Incoming(packet))) => session.handle_incoming(packet, Instant::now()),
                Ok(Ok(_)) => {}
                Ok(Err(e)) => {
                    warn!(error = %e, "connection ended during shutdown");
                    return;
                }
                Err(_) => {
                    warn!(unsent = session.staged(), "shutdown grace period over");
                    return;
                }
            }
        }
    }
}

/// Hands the core the inputs it has room for: how many; `None` once the core is gone.
fn deliver(session: &mut Session, inputs: &mpsc::Sender<MqttInput>) -> Option<usize> {
    let mut delivered = 0;
    while session.has_input() {
        match inputs.try_reserve() {
            Ok(permit) => {
                if let Some(input) = session.poll_input() {
                    permit.send(input);
                    delivered += 1;
                }
            }
            Err(mpsc::error::TrySendError::Full(())) => break,
            Err(mpsc::error::TrySendError::Closed(())) => return None,
        }
    }
    Some(delivered)
}

/// Queues the session's requests, then its publications while the connection takes them.
fn carry_out(session: &mut Session, conn: &mut Connection) {
    while let Some(request) = session.poll_request() {
        match request {
            Request::Subscribe { filter, qos } => conn.subscribe(filter, qos),
            Request::Unsubscribe(filter) => conn.unsubscribe(filter),
            Request::Ack(pkid) => conn.ack(pkid),
            Request::Ping => conn.ping(),
            Request::Close(why) => conn.close(why),
        }
    }
    let now = Instant::now();
    while let Some(p) = session.poll_publication(now) {
        // Moved, not copied: a refused publication comes back whole.
        if let Err((topic, payload)) = conn.publish(p.topic, p.payload, p.retain) {
            session.handle_publication_refused(Outbound {
                topic,
                payload,
                retain: p.retain,
            });
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::session::tests::publication;
    use super::*;
    use crate::config::{Broker, MqttConfig};
    use rumqttc::Incoming;

    fn task() -> MqttTask {
        let cfg = MqttConfig {
            broker: Broker::External {
                host: "127.0.0.1".into(),
                port: 1,
            },
            client_id: "t".into(),
            credentials: Some(("u".into(), "p".into())),
            tls: None,
            keep_alive: Duration::from_secs(20),
            ack_timeout: Duration::from_secs(5),
        };
        let topics = Topics::seed();
        MqttTask {
            options: options(&cfg, &topics).unwrap(),
            topics,
            ha: false,
            broker: "127.0.0.1:1".into(),
            stats: Arc::default(),
            ack_timeout: Duration::from_secs(5),
        }
    }

    #[test]
    fn options_follow_the_seed() {
        let t = task();
        assert!(
            t.options.manual_acks(),
            "a command is acknowledged once the core took it"
        );
        assert_eq!(t.options.max_packet_size(), MAX_INCOMING);
        assert_eq!(t.options.keep_alive(), Duration::from_secs(20));
        assert!(t.options.clean_session());
        let will = t.options.last_will().expect("last will");
        assert_eq!(will.topic, "ihex/gateway/availability");
        assert_eq!(&will.message[..], b"offline");
        assert!(will.retain);
        assert_eq!(will.qos, QoS::AtLeastOnce);
        assert_eq!(
            t.options.credentials().map(|l| l.username),
            Some("u".into())
        );
    }

    #[cfg(not(feature = "tls"))]
    #[test]
    fn tls_without_the_feature_is_a_clear_error() {
        let cfg = MqttConfig {
            broker: Broker::External {
                host: "h".into(),
                port: 8883,
            },
            client_id: "t".into(),
            credentials: None,
            tls: Some(None),
            keep_alive: Duration::from_secs(20),
            ack_timeout: Duration::from_secs(5),
        };
        assert!(matches!(
            options(&cfg, &Topics::seed()),
            Err(MqttError::TlsUnavailable)
        ));
    }

    #[test]
    fn connection_failures_say_which_broker_and_what_to_check() {
        let refused = std::io::Error::from(std::io::ErrorKind::ConnectionRefused);
        let e = explain(&ConnectionError::Io(refused), "10.0.0.9:1883", false);
        assert_eq!(
            e,
            "nothing accepts connections at 10.0.0.9:1883 (connection refused): is the broker \
             running, and is that its host and port (--broker)?"
        );
        let auth = ConnectionError::ConnectionRefused(ConnectReturnCode::NotAuthorized);
        assert!(explain(&auth, "b:1883", false).starts_with(
            "broker b:1883 refused the login (NotAuthorized): check --username and --password"
        ));
        let e = explain(&ConnectionError::NetworkTimeout, "b:8883", true);
        assert!(
            e.starts_with("no answer from broker b:8883 within 5 s"),
            "{e}"
        );
        assert!(e.ends_with("check --tls-ca and that the broker's certificate names this host"));
    }

    /// A scripted broker: the gateway's client must not acknowledge a command before the core took
    /// it, and must hand on the retain flag.
    #[tokio::test]
    async fn a_command_is_acknowledged_only_once_the_core_took_it() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let (seen_tx, mut seen) = mpsc::unbounded_channel::<Vec<u8>>();
        tokio::spawn(async move {
            let (mut s, _) = listener.accept().await.unwrap();
            let mut buf = [0u8; 4096];
            let _ = s.read(&mut buf).await; // CONNECT
            s.write_all(&[0x20, 0x02, 0x00, 0x00]).await.unwrap(); // CONNACK accepted
            s.write_all(&command_publish(1, true)).await.unwrap();
            while let Ok(n) = s.read(&mut buf).await {
                if n == 0 || seen_tx.send(buf[..n].to_vec()).is_err() {
                    break;
                }
            }
        });
        let mut t = task();
        t.options = MqttOptions::new("acks", "127.0.0.1", port);
        t.options.set_manual_acks(true);
        let (pub_tx, pub_rx) = mpsc::channel(4);
        // The core's channel holds one input and nobody reads it yet.
        let (in_tx, mut in_rx) = mpsc::channel(1);
        let cancel = CancellationToken::new();
        let run = tokio::spawn(t.run(pub_rx, in_tx, cancel.clone()));
        let puback = test_broker::puback(1);
        let mut bytes = Vec::new();
        let quiet = tokio::time::sleep(Duration::from_millis(400));
        tokio::pin!(quiet);
        loop {
            tokio::select! {
                b = seen.recv() => bytes.extend(b.unwrap()),
                _ = &mut quiet => break,
            }
        }
        assert!(
            !bytes.windows(4).any(|w| w == puback),
            "acknowledged before the core took it: {bytes:02x?}"
        );
        assert_eq!(in_rx.recv().await, Some(MqttInput::Connected));
        match in_rx.recv().await {
            Some(MqttInput::Command {
                payload, retained, ..
            }) => {
                assert_eq!(&payload[..], b"{}");
                assert!(retained);
            }
            other => panic!("{other:?}"),
        }
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        while !bytes.windows(4).any(|w| w == puback) {
            let b = tokio::time::timeout_at(deadline, seen.recv()).await;
            bytes.extend(b.expect("PUBACK after the core took the command").unwrap());
        }
        cancel.cancel();
        drop(pub_tx);
        run.await.unwrap();
    }

    /// A QoS 1 PUBLISH of `{}` on `CommandsTopic` with packet id `pkid`, as a broker sends it.
    fn command_publish(pkid: u8, retain: bool) -> Vec<u8> {
        let mut p = vec![0x32 | u8::from(retain), 19, 0x00, 13];
        p.extend_from_slice(b"CommandsTopic");
        p.extend_from_slice(&[0x00, pkid, b'{', b'}']);
        p
    }

    /// The MQTT task as the gateway runs it (manual acks) against a scripted broker
    /// ([`test_broker::broker_seeing`]): what a test drives it with and watches.
    struct Scripted {
        broker: test_broker::Script,
        /// Every read of what the task wrote since [`Scripted::start`] returned.
        seen: mpsc::UnboundedReceiver<Vec<u8>>,
        writes: Arc<AtomicU64>,
        pub_tx: mpsc::Sender<Outbound>,
        in_rx: mpsc::Receiver<MqttInput>,
        cancel: CancellationToken,
        run: tokio::task::JoinHandle<()>,
    }

    impl Scripted {
        /// Starts client `name` with room for `core_room` inputs on the core's channel, the core
        /// saying `answers_due`; returns once it is connected, its subscriptions and `online`
        /// written, and nothing else is due.
        async fn start(name: &str, answers_due: bool, core_room: usize) -> Scripted {
            let (port, broker, mut seen) = test_broker::broker_seeing(None).await;
            let mut t = task();
            t.options = MqttOptions::new(name, "127.0.0.1", port);
            t.options.set_manual_acks(true);
            t.stats.answers_due.store(answers_due, Ordering::Relaxed);
            let writes = t.stats.writes.clone();
            let (pub_tx, pub_rx) = mpsc::channel(4);
            let (in_tx, mut in_rx) = mpsc::channel(core_room);
            let cancel = CancellationToken::new();
            let run = tokio::spawn(t.run(pub_rx, in_tx, cancel.clone()));
            assert_eq!(in_rx.recv().await, Some(MqttInput::Connected));
            tokio::time::sleep(Duration::from_millis(300)).await;
            while seen.try_recv().is_ok() {}
            Scripted {
                broker,
                seen,
                writes,
                pub_tx,
                in_rx,
                cancel,
                run,
            }
        }

        async fn stop(self) {
            self.cancel.cancel();
            drop(self.pub_tx);
            self.run.await.unwrap();
        }
    }

    /// A QoS 1 command (packet id 7) that the core takes and answers `later` (`None`: in the turn
    /// that took it), while the core says `answers_due`: the command's PUBACK and the answer leave
    /// in one write (one system call, one segment waking the broker), not two, and nothing leaves
    /// before the answer.
    async fn puback_and_answer(name: &str, answers_due: bool, later: Option<Duration>) {
        let mut t = Scripted::start(name, answers_due, 4).await;
        let (seen, writes) = (&mut t.seen, &t.writes);
        let before = writes.load(Ordering::Relaxed);
        t.broker.send(command_publish(7, false)).unwrap();
        match t.in_rx.recv().await {
            Some(MqttInput::Command { payload, .. }) => assert_eq!(&payload[..], b"{}"),
            other => panic!("{other:?}"),
        }
        if let Some(later) = later {
            tokio::time::sleep(later).await;
            assert_eq!(
                writes.load(Ordering::Relaxed),
                before,
                "the PUBACK left before the answer: {:02x?}",
                seen.try_recv()
            );
        }
        t.pub_tx.send(publication(1)).await.unwrap();
        let puback = test_broker::puback(7);
        let mut bytes = Vec::new();
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        while !(bytes.windows(4).any(|w| w == puback)
            && bytes.windows(11).any(|w| w == b"EventsTopic"))
        {
            let b = tokio::time::timeout_at(deadline, seen.recv()).await;
            bytes.extend(b.expect("the PUBACK and the answer").unwrap());
        }
        assert_eq!(
            writes.load(Ordering::Relaxed) - before,
            1,
            "the PUBACK and the answer took more than one write: {bytes:02x?}"
        );
        t.stop().await;
    }

    /// A command whose answer the core publishes in the turn that took it (a rejection, or the
    /// node's ack read with the command): the PUBACK waits for nothing and shares its write.
    #[tokio::test]
    async fn a_puback_and_what_the_core_publishes_in_the_same_turn_share_a_write() {
        puback_and_answer("batch", false, None).await;
    }

    /// A command taken while the core has answers due: its PUBACK waits for its answer, published
    /// later (after the node's ack), and leaves with it.
    #[tokio::test]
    async fn a_puback_waits_for_the_answer_while_answers_are_due() {
        puback_and_answer("answers-due", true, Some(Duration::from_millis(200))).await;
    }

    /// Commands waiting for the core (a flood): the PUBACK of each one taken leaves at once,
    /// answers due or not, with no publication to go with it.
    #[tokio::test]
    async fn pubacks_are_not_held_while_commands_wait_for_the_core() {
        // The core takes one input at a time, and only when this test reads it.
        let mut t = Scripted::start("flood", true, 1).await;
        // Three commands in one segment.
        let burst = (1..=3u8).flat_map(|pkid| command_publish(pkid, false));
        t.broker.send(burst.collect()).unwrap();
        let mut bytes = Vec::new();
        for pkid in 1..=3u8 {
            assert!(matches!(
                t.in_rx.recv().await,
                Some(MqttInput::Command { .. })
            ));
            // Taken while others wait: its PUBACK is written without an answer. (Nothing waits
            // after the last one, so its PUBACK is held for its answer: not looked for.)
            let puback = test_broker::puback(pkid.into());
            let deadline = tokio::time::Instant::now() + Duration::from_millis(500);
            while pkid < 3 && !bytes.windows(4).any(|w| w == puback) {
                let b = tokio::time::timeout_at(deadline, t.seen.recv()).await;
                bytes.extend(b.expect("the PUBACK within 500 ms").unwrap());
            }
        }
        t.stop().await;
    }

    /// A broker that answers CONNECT only after `delay` and counts connections: publications that
    /// arrive meanwhile must not abort the attempt (rumqttc's `poll()` is not cancel-safe).
    #[tokio::test]
    async fn publications_during_a_slow_connect_do_not_restart_it() {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let accepted = Arc::new(AtomicU64::new(0));
        let count = accepted.clone();
        tokio::spawn(async move {
            loop {
                let (mut s, _) = listener.accept().await.unwrap();
                count.fetch_add(1, Ordering::Relaxed);
                tokio::spawn(async move {
                    let mut buf = [0u8; 4096];
                    let _ = s.read(&mut buf).await; // CONNECT
                    tokio::time::sleep(Duration::from_millis(300)).await;
                    let _ = s.write_all(&[0x20, 0x02, 0x00, 0x00]).await; // CONNACK accepted
                                                                          // Swallow whatever follows (SUBSCRIBE, PUBLISH) without answering.
                    while let Ok(n) = s.read(&mut buf).await {
                        if n == 0 {
                            break;
                        }
                    }
                });
            }
        });
        let mut t = task();
        t.options = MqttOptions::new("slow", "127.0.0.1", port);
        let stats = t.stats.clone();
        let (pub_tx, pub_rx) = mpsc::channel(100);
        let (in_tx, mut in_rx) = mpsc::channel(10);
        let cancel = CancellationToken::new();
        let run = tokio::spawn(t.run(pub_rx, in_tx, cancel.clone()));
        for n in 0..40 {
            pub_tx.send(publication(n)).await.unwrap();
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        let connected = tokio::time::timeout(Duration::from_secs(10), in_rx.recv()).await;
        assert_eq!(connected.unwrap(), Some(MqttInput::Connected));
        assert_eq!(
            accepted.load(Ordering::Relaxed),
            1,
            "the connect attempt was restarted"
        );
        assert_eq!(stats.connects.load(Ordering::Relaxed), 1);
        cancel.cancel();
        run.await.unwrap();
    }

    /// A broker that accepts the connection, reads without acknowledging anything and hangs up:
    /// what the broker had not acknowledged comes back to the queue in order, `online` excepted.
    #[tokio::test]
    async fn publications_of_a_broken_connection_are_taken_back_in_order() {
        // The first write read, then hang up.
        let (port, _script) = test_broker::broker(Some(1)).await;
        let t = task();
        let mut options = MqttOptions::new("takeback", "127.0.0.1", port);
        options.set_manual_acks(true);
        let mut conn = Connection::new(options, MAX_OUTGOING, CONNECT_TIMEOUT);
        let ev = conn.poll().await.unwrap();
        assert!(
            matches!(ev, Event::Incoming(Incoming::ConnAck(_))),
            "{ev:?}"
        );
        let avail = t.topics.availability.clone();
        conn.publish("EventsTopic".into(), vec![1].into(), false)
            .unwrap();
        conn.subscribe("CommandsTopic".into(), QoS::AtLeastOnce);
        conn.publish("ihex/node/1/state".into(), vec![2].into(), true)
            .unwrap();
        conn.publish(avail, ONLINE.into(), true).unwrap();
        let err = tokio::time::timeout(Duration::from_secs(10), conn.poll()).await;
        assert!(err.expect("the broker hung up").is_err());
        assert!(!conn.is_up());
        let timing = Timing {
            keep_alive: Duration::from_secs(20),
            ack_timeout: Duration::from_secs(5),
        };
        let mut session = Session::new(t.topics.clone(), false, t.broker, t.stats, timing);
        let now = Instant::now();
        session.handle_connack(now);
        session.handle_publication(publication(9));
        let back = conn.take_back().into_iter().map(|p| Outbound {
            topic: p.topic,
            payload: p.payload,
            retain: p.retain,
        });
        session.handle_connection_lost("hung up", "hung up".into(), back.collect(), now);
        assert!(conn.take_back().is_empty(), "taken back once");
        session.handle_connack(now);
        let got: Vec<(String, u8, bool)> = std::iter::from_fn(|| session.poll_publication(now))
            .map(|p| (p.topic.clone(), p.payload[0], p.retain))
            .collect();
        assert_eq!(
            got,
            vec![
                (t.topics.availability.clone(), b'o', true),
                ("EventsTopic".into(), 1, false),
                ("ihex/node/1/state".into(), 2, true),
                ("EventsTopic".into(), 9, false),
            ]
        );
    }

    /// Publications beyond one write's worth are handed back even with room in the in-flight
    /// window, and taken again once the buffer was written.
    #[tokio::test]
    async fn one_write_holds_a_bounded_batch_of_publications() {
        let (port, _script) = test_broker::broker(None).await;
        let mut conn = Connection::new(
            MqttOptions::new("batch", "127.0.0.1", port),
            MAX_OUTGOING,
            CONNECT_TIMEOUT,
        );
        let ev = conn.poll().await.unwrap();
        assert!(
            matches!(ev, Event::Incoming(Incoming::ConnAck(_))),
            "{ev:?}"
        );
        // A Home Assistant config's size.
        let text = Bytes::from(vec![b'x'; 3000]);
        let mut taken = 0;
        while conn.publish("t".into(), text.clone(), true).is_ok() {
            taken += 1;
            assert!(
                taken < 100,
                "the in-flight window, not the batch, stopped it"
            );
        }
        assert_eq!(
            taken,
            conn::WRITE_BATCH.div_ceil(3000 + 6),
            "one write's worth"
        );
        // Nothing comes back from this broker: poll writes, then waits for input.
        let _ = tokio::time::timeout(Duration::from_millis(300), conn.poll()).await;
        assert!(
            conn.publish("t".into(), text, true).is_ok(),
            "room again once written"
        );
    }
}
