//! The MQTT side: exactly one task owns rumqttc's `EventLoop::poll()`. It connects with keep-alive,
//! clean session and a retained `offline` last will, (re)subscribes the command topic on *every*
//! ConnAck, publishes `online` (retained), forwards commands to the core and carries out its
//! publications (QoS 1). rumqttc reconnects whenever `poll()` is called again but has no back-off, so
//! this task sleeps with a capped exponential delay between failed polls.
//!
//! Publications are never lost silently: while the broker is unreachable they wait in a bounded queue
//! of [`crate::config::MqttConfig::queue`] entries (the oldest is dropped, logged and counted in
//! [`MqttStats`] when it is full), and those rumqttc had accepted but the broker had not acknowledged
//! when the connection broke are taken back from the event loop and sent again after reconnecting.

use std::{
    collections::VecDeque,
    sync::{
        atomic::{AtomicU64, Ordering},
        Arc,
    },
    time::Duration,
};

use rumqttc::{
    AsyncClient, ClientError, ConnectReturnCode, Event, EventLoop, Incoming, LastWill, MqttOptions,
    NetworkOptions, Outgoing, QoS, Request, SubscribeReasonCode,
};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::{config::MqttConfig, error::MqttError, topic::Topics};

/// Payload of the availability topic while the gateway runs.
pub const ONLINE: &str = "online";
/// Payload of the availability topic once it stops (also the last will).
pub const OFFLINE: &str = "offline";
/// First delay after a failed connection attempt; doubles up to [`RECONNECT_MAX`].
pub const RECONNECT_MIN: Duration = Duration::from_millis(100);
/// Longest delay between connection attempts.
pub const RECONNECT_MAX: Duration = Duration::from_secs(5);
/// Capacity of rumqttc's own request channel (our queue in front of it holds the backlog).
const REQUEST_CHANNEL: usize = 64;
/// How long shutdown waits for `offline` and the DISCONNECT to go out.
const SHUTDOWN_GRACE: Duration = Duration::from_secs(2);

/// One message to publish with QoS 1: a serialised core publication under its concrete topic.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Outbound {
    /// Concrete topic name.
    pub topic: String,
    /// Payload bytes (JSON text).
    pub payload: Vec<u8>,
    /// Retained or not.
    pub retain: bool,
}

/// What the MQTT task hands to the gateway core.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum MqttInput {
    /// A message on the command topic (raw payload; the core validates it).
    Command(Vec<u8>),
    /// A ConnAck: the session is (re)established and subscribed.
    Connected,
}

/// Counters of the MQTT side, readable while the gateway runs.
#[derive(Debug, Default)]
pub struct MqttStats {
    /// Successful connections (ConnAck accepted).
    pub connects: AtomicU64,
    /// Publications dropped because the queue was full while disconnected.
    pub dropped: AtomicU64,
    /// Publications handed to rumqttc.
    pub published: AtomicU64,
    /// Messages received on the command topic.
    pub commands: AtomicU64,
}

/// The rumqttc options of the gateway's own client: [`client_options`] plus the retained `offline`
/// last will and the incoming size limit.
pub fn options(
    cfg: &MqttConfig,
    topics: &Topics,
    max_incoming: usize,
) -> Result<MqttOptions, MqttError> {
    let mut o = client_options(cfg, cfg.client_id.clone())?;
    o.set_last_will(LastWill::new(
        &topics.availability,
        OFFLINE,
        QoS::AtLeastOnce,
        true,
    ))
    // An oversized command must reach the core (to be rejected with a reason) rather than
    // break the connection, so the incoming limit sits well above the command limit.
    .set_max_packet_size(max_incoming, 1 << 20);
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
    let transport = match ca {
        Some(path) => {
            let pem = std::fs::read(path).map_err(|source| MqttError::TlsCa {
                path: path.to_owned(),
                source,
            })?;
            rumqttc::Transport::tls(pem, None, None)
        }
        None => rumqttc::Transport::tls_with_default_config(),
    };
    o.set_transport(transport);
    Ok(())
}

#[cfg(not(feature = "tls"))]
fn set_tls(_: &mut MqttOptions, _: Option<&std::path::Path>) -> Result<(), MqttError> {
    Err(MqttError::TlsUnavailable)
}

/// The MQTT task's fixed parts.
pub struct MqttTask {
    /// Connection options (see [`options`]).
    pub options: MqttOptions,
    /// Topic names.
    pub topics: Topics,
    /// Publications held while disconnected.
    pub queue: usize,
    /// Counters.
    pub stats: Arc<MqttStats>,
}

impl MqttTask {
    /// Runs until `cancel`: then publishes `offline` (retained) and disconnects.
    #[tracing::instrument(name = "mqtt", skip_all, fields(client_id = %self.options.client_id()))]
    pub async fn run(
        self,
        mut publications: mpsc::Receiver<Outbound>,
        inputs: mpsc::Sender<MqttInput>,
        cancel: CancellationToken,
    ) {
        let (client, mut el) = AsyncClient::new(self.options.clone(), REQUEST_CHANNEL);
        let mut net = NetworkOptions::new();
        // Without it every QoS 1 round trip waits for Nagle (~40 ms).
        net.set_tcp_nodelay(true);
        net.set_connection_timeout(5);
        el.set_network_options(net);

        let mut backlog: VecDeque<Outbound> = VecDeque::new();
        let mut connected = false;
        let mut delay = RECONNECT_MIN;
        let mut inputs_open = true;
        'run: loop {
            // `poll()` is not cancel-safe (dropping it mid-connect or mid-write loses the
            // connection or part of a packet), so one poll future lives until it completes while
            // publications keep arriving beside it.
            let ev = {
                let poll = el.poll();
                tokio::pin!(poll);
                loop {
                    if connected {
                        self.flush(&client, &mut backlog);
                    }
                    tokio::select! {
                        _ = cancel.cancelled() => break 'run,
                        p = publications.recv(), if inputs_open => match p {
                            Some(p) => self.enqueue(&mut backlog, p),
                            None => inputs_open = false,
                        },
                        ev = &mut poll => break ev,
                    }
                }
            };
            match ev {
                Ok(Event::Incoming(Incoming::ConnAck(ack))) => {
                    if ack.code != ConnectReturnCode::Success {
                        warn!(code = ?ack.code, "broker refused the connection");
                        continue;
                    }
                    connected = true;
                    delay = RECONNECT_MIN;
                    let n = self.stats.connects.fetch_add(1, Ordering::Relaxed) + 1;
                    info!(
                        connects = n,
                        backlog = backlog.len(),
                        "connected to the broker"
                    );
                    self.on_connack(&client);
                    if inputs.send(MqttInput::Connected).await.is_err() {
                        break;
                    }
                }
                Ok(Event::Incoming(Incoming::Publish(p))) => {
                    let input = if p.topic == self.topics.commands {
                        self.stats.commands.fetch_add(1, Ordering::Relaxed);
                        MqttInput::Command(p.payload.to_vec())
                    } else {
                        debug!(topic = %p.topic, "message on an unexpected topic ignored");
                        continue;
                    };
                    if inputs.send(input).await.is_err() {
                        break;
                    }
                }
                Ok(Event::Incoming(Incoming::SubAck(s))) => {
                    if s.return_codes
                        .iter()
                        .any(|c| matches!(c, SubscribeReasonCode::Failure))
                    {
                        warn!(?s, "broker refused a subscription");
                    }
                }
                Ok(_) => {}
                Err(e) => {
                    if connected {
                        warn!(error = %e, "connection to the broker lost");
                    } else {
                        debug!(error = %e, retry_in = ?delay, "cannot reach the broker");
                    }
                    connected = false;
                    self.take_back(&mut el, &mut backlog);
                    tokio::select! {
                        _ = cancel.cancelled() => break,
                        _ = tokio::time::sleep(delay) => {}
                    }
                    delay = (delay * 2).min(RECONNECT_MAX);
                }
            }
        }
        if connected {
            self.goodbye(&client, &mut el, &mut publications, &mut backlog)
                .await;
        }
        let dropped = self.stats.dropped.load(Ordering::Relaxed);
        info!(dropped, unsent = backlog.len(), "MQTT task stopped");
    }

    /// Subscribes and announces `online`; runs on every ConnAck (a clean session forgets both).
    fn on_connack(&self, client: &AsyncClient) {
        let t = &self.topics.commands;
        if let Err(e) = client.try_subscribe(t.clone(), QoS::AtLeastOnce) {
            warn!(topic = %t, error = %e, "cannot queue the subscription");
        }
        if let Err(e) =
            client.try_publish(&self.topics.availability, QoS::AtLeastOnce, true, ONLINE)
        {
            warn!(error = %e, "cannot queue the online announcement");
        }
    }

    fn enqueue(&self, backlog: &mut VecDeque<Outbound>, p: Outbound) {
        if backlog.len() >= self.queue {
            let old = backlog.pop_front();
            let n = self.stats.dropped.fetch_add(1, Ordering::Relaxed) + 1;
            // One line per power of two keeps a long outage from flooding the log.
            if n.is_power_of_two() {
                warn!(dropped_total = n, topic = ?old.map(|o| o.topic), "MQTT queue full: oldest publication dropped");
            }
        }
        backlog.push_back(p);
    }

    /// Hands queued publications to rumqttc until its channel is full.
    fn flush(&self, client: &AsyncClient, backlog: &mut VecDeque<Outbound>) {
        while let Some(p) = backlog.pop_front() {
            match client.try_publish(
                p.topic.clone(),
                QoS::AtLeastOnce,
                p.retain,
                p.payload.clone(),
            ) {
                Ok(()) => {
                    self.stats.published.fetch_add(1, Ordering::Relaxed);
                }
                Err(ClientError::TryRequest(_)) | Err(ClientError::Request(_)) => {
                    backlog.push_front(p);
                    return;
                }
            }
        }
    }

    /// After a broken connection rumqttc keeps unacknowledged and unsent requests in `pending`, but
    /// clears them when the next (clean) session starts: move the publications back to the front of
    /// our queue, in order. Subscriptions and `online` are redone on ConnAck anyway.
    fn take_back(&self, el: &mut EventLoop, backlog: &mut VecDeque<Outbound>) {
        let mut back: Vec<Outbound> = el
            .pending
            .drain(..)
            .filter_map(|r| match r {
                Request::Publish(p) if p.topic != self.topics.availability => Some(Outbound {
                    topic: p.topic,
                    payload: p.payload.to_vec(),
                    retain: p.retain,
                }),
                _ => None,
            })
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
        while let Some(p) = back.pop() {
            backlog.push_front(p);
        }
        while backlog.len() > self.queue {
            backlog.pop_back();
            self.stats.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Sends what is still queued, then `offline` (retained), then DISCONNECT, polling the event loop
    /// until the DISCONNECT is written or [`SHUTDOWN_GRACE`] passes.
    async fn goodbye(
        &self,
        client: &AsyncClient,
        el: &mut EventLoop,
        publications: &mut mpsc::Receiver<Outbound>,
        backlog: &mut VecDeque<Outbound>,
    ) {
        while let Ok(p) = publications.try_recv() {
            self.enqueue(backlog, p);
        }
        let deadline = tokio::time::Instant::now() + SHUTDOWN_GRACE;
        let mut said_goodbye = false;
        loop {
            self.flush(client, backlog);
            if backlog.is_empty() && !said_goodbye {
                said_goodbye = client
                    .try_publish(&self.topics.availability, QoS::AtLeastOnce, true, OFFLINE)
                    .and_then(|()| client.try_disconnect())
                    .is_ok();
            }
            match tokio::time::timeout_at(deadline, el.poll()).await {
                Ok(Ok(Event::Outgoing(Outgoing::Disconnect))) => {
                    info!("published offline and disconnected");
                    return;
                }
                Ok(Ok(_)) => {}
                Ok(Err(e)) => {
                    warn!(error = %e, "connection ended during shutdown");
                    return;
                }
                Err(_) => {
                    warn!(unsent = backlog.len(), "shutdown grace period over");
                    return;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Broker, MqttConfig};

    fn task(queue: usize) -> MqttTask {
        let cfg = MqttConfig {
            broker: Broker::External {
                host: "127.0.0.1".into(),
                port: 1,
            },
            client_id: "t".into(),
            credentials: Some(("u".into(), "p".into())),
            tls: None,
            keep_alive: Duration::from_secs(20),
            queue,
        };
        let topics = Topics::seed();
        MqttTask {
            options: options(&cfg, &topics, 1 << 20).unwrap(),
            topics,
            queue,
            stats: Arc::default(),
        }
    }

    fn publication(n: u8) -> Outbound {
        Outbound {
            topic: "EventsTopic".into(),
            payload: vec![n],
            retain: false,
        }
    }

    #[test]
    fn options_follow_the_seed() {
        let t = task(4);
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
            queue: 1,
        };
        assert!(matches!(
            options(&cfg, &Topics::seed(), 1024),
            Err(MqttError::TlsUnavailable)
        ));
    }

    #[test]
    fn a_full_queue_drops_the_oldest_and_counts() {
        let t = task(3);
        let mut q = VecDeque::new();
        for n in 0..5 {
            t.enqueue(&mut q, publication(n));
        }
        let kept: Vec<u8> = q.iter().map(|p| p.payload[0]).collect();
        assert_eq!(kept, vec![2, 3, 4]);
        assert_eq!(t.stats.dropped.load(Ordering::Relaxed), 2);
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
        let mut t = task(100);
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

    #[tokio::test]
    async fn requests_of_a_broken_connection_are_taken_back_in_order() {
        let t = task(10);
        let (client, mut el) = AsyncClient::new(t.options.clone(), 8);
        client
            .try_publish("EventsTopic", QoS::AtLeastOnce, false, vec![1])
            .unwrap();
        client
            .try_subscribe("CommandsTopic", QoS::AtLeastOnce)
            .unwrap();
        client
            .try_publish("ihex/node/1/state", QoS::AtLeastOnce, true, vec![2])
            .unwrap();
        client
            .try_publish(
                "ihex/gateway/availability",
                QoS::AtLeastOnce,
                true,
                "online",
            )
            .unwrap();
        // What rumqttc does on a connection error: unsent requests move to `pending`.
        el.clean();
        let mut q = VecDeque::from([publication(9)]);
        t.take_back(&mut el, &mut q);
        let got: Vec<(String, u8, bool)> = q
            .iter()
            .map(|p| (p.topic.clone(), p.payload[0], p.retain))
            .collect();
        assert_eq!(
            got,
            vec![
                ("EventsTopic".into(), 1, false),
                ("ihex/node/1/state".into(), 2, true),
                ("EventsTopic".into(), 9, false),
            ]
        );
        assert!(el.pending.is_empty());
    }
}
