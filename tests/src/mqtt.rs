//! A test MQTT client that reports everything its connection sees — connection answers, messages
//! with their retain flag, subscription and publish acknowledgements — so tests can assert what a
//! broker really answered (a refused login, a SUBACK failure code, a message that never came).
//!
//! One task owns rumqttc's event loop; after an error it waits a little and polls again, which
//! makes rumqttc reconnect. [`Client::subscribe_on_connect`] filters are subscribed again after
//! every ConnAck.
//!
//! The one MQTT test client of the repository: tests that only care about messages use
//! [`Client::subscribed`], [`Client::expect_msg`] and [`Message`]; tests of what the broker
//! answered match the whole [`Seen`].

use std::net::SocketAddr;
use std::time::Duration;

use rumqttc::{
    AsyncClient, ConnectReturnCode, ConnectionError, Event, Incoming, MqttOptions, QoS,
    SubscribeReasonCode,
};
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

/// Deadline for one expected report (before [`crate::time::scaled`]).
pub const WAIT: Duration = Duration::from_secs(10);

/// Something the client's connection saw.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Seen {
    /// The broker answered CONNECT.
    ConnAck(ConnectReturnCode),
    /// A message arrived.
    Message {
        /// Its topic.
        topic: String,
        /// Its payload.
        payload: Vec<u8>,
        /// The RETAIN flag as delivered (set only for retained messages sent on subscription).
        retain: bool,
    },
    /// A SUBACK, one code per filter of the SUBSCRIBE.
    SubAck(Vec<SubscribeReasonCode>),
    /// A PUBACK for our QoS 1 publish with this packet id.
    PubAck(u16),
    /// The connection failed or broke (rumqttc's error text).
    Error(String),
}

/// A message as a test that only cares about messages sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Message {
    /// Its topic.
    pub topic: String,
    /// Its payload.
    pub payload: Vec<u8>,
    /// The RETAIN flag as delivered.
    pub retain: bool,
}

impl Message {
    /// The payload as JSON; `Null` when it is not JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.payload).unwrap_or(serde_json::Value::Null)
    }
}

impl Seen {
    /// The message, if this is one.
    pub fn message(&self) -> Option<Message> {
        match self {
            Seen::Message {
                topic,
                payload,
                retain,
            } => Some(Message {
                topic: topic.clone(),
                payload: payload.clone(),
                retain: *retain,
            }),
            _ => None,
        }
    }

    /// The payload as JSON, if this is a message with a JSON payload.
    pub fn json(&self) -> Option<serde_json::Value> {
        match self {
            Seen::Message { payload, .. } => serde_json::from_slice(payload).ok(),
            _ => None,
        }
    }

    /// True for a message on `topic`.
    pub fn is_on(&self, topic: &str) -> bool {
        matches!(self, Seen::Message { topic: t, .. } if t == topic)
    }
}

/// Options for a test client of `broker`: keep-alive 5 s, clean session, room for big packets.
pub fn options(broker: SocketAddr, client_id: &str) -> MqttOptions {
    let mut o = MqttOptions::new(client_id, broker.ip().to_string(), broker.port());
    o.set_keep_alive(Duration::from_secs(5))
        .set_max_packet_size(1 << 21, 1 << 21);
    o
}

/// A connected (or connecting) test client.
pub struct Client {
    /// rumqttc's handle, to publish and subscribe.
    pub client: AsyncClient,
    rx: mpsc::UnboundedReceiver<Seen>,
    task: JoinHandle<()>,
    /// Everything seen so far, in order (filled by the waiting methods).
    pub log: Vec<Seen>,
    /// How long a waiting method waits (before [`crate::time::scaled`]).
    wait: Duration,
}

impl Client {
    /// Starts a client; `filters` are subscribed (QoS 1) after every ConnAck that accepts.
    /// Must be called inside a tokio runtime.
    pub fn subscribe_on_connect(options: MqttOptions, filters: &[&str]) -> Client {
        let (client, mut el) = AsyncClient::new(options, 64);
        let (tx, rx) = mpsc::unbounded_channel();
        let c = client.clone();
        let filters: Vec<String> = filters.iter().map(|f| f.to_string()).collect();
        let task = tokio::spawn(async move {
            loop {
                let seen = match el.poll().await {
                    Ok(Event::Incoming(Incoming::ConnAck(ack))) => {
                        if ack.code == ConnectReturnCode::Success {
                            for f in &filters {
                                let _ = c.try_subscribe(f.clone(), QoS::AtLeastOnce);
                            }
                        }
                        Seen::ConnAck(ack.code)
                    }
                    Ok(Event::Incoming(Incoming::Publish(p))) => Seen::Message {
                        topic: p.topic,
                        payload: p.payload.to_vec(),
                        retain: p.retain,
                    },
                    Ok(Event::Incoming(Incoming::SubAck(s))) => Seen::SubAck(s.return_codes),
                    Ok(Event::Incoming(Incoming::PubAck(a))) => Seen::PubAck(a.pkid),
                    Ok(_) => continue,
                    // rumqttc reports a refusing ConnAck as an error; it is an answer all the same.
                    Err(ConnectionError::ConnectionRefused(code)) => {
                        if tx.send(Seen::ConnAck(code)).is_err() {
                            return;
                        }
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                    Err(e) => {
                        let _ = tx.send(Seen::Error(e.to_string()));
                        tokio::time::sleep(Duration::from_millis(100)).await;
                        continue;
                    }
                };
                if tx.send(seen).is_err() {
                    return;
                }
            }
        });
        Client {
            client,
            rx,
            task,
            log: Vec::new(),
            wait: WAIT,
        }
    }

    /// A client of `broker` with the [`options`] of a test client, named `client_id`, that
    /// subscribes `filters` after every ConnAck.
    pub fn subscribed(broker: SocketAddr, client_id: &str, filters: &[impl AsRef<str>]) -> Client {
        let filters: Vec<&str> = filters.iter().map(AsRef::as_ref).collect();
        Client::subscribe_on_connect(options(broker, client_id), &filters)
    }

    /// Waits `wait` (scaled) instead of [`WAIT`] from now on.
    pub fn set_wait(&mut self, wait: Duration) {
        self.wait = wait;
    }

    /// Waits for the first message from now on that `pred` accepts; panics with `what` and
    /// everything seen on timeout.
    pub async fn expect_msg(&mut self, what: &str, pred: impl Fn(&Message) -> bool) -> Message {
        let seen = self
            .expect(what, |s| s.message().is_some_and(|m| pred(&m)))
            .await;
        seen.message()
            .expect("expect returned what the predicate accepted")
    }

    /// Waits for an event named `name` on the topic `events` whose payload passes `pred`; returns
    /// the whole event.
    pub async fn expect_event(
        &mut self,
        events: &str,
        name: &str,
        pred: impl Fn(&serde_json::Value) -> bool,
    ) -> serde_json::Value {
        let what = format!("{name} on {events}");
        self.expect_msg(&what, |m| {
            let v = m.json();
            m.topic == events && v["event"] == name && pred(&v["payload"])
        })
        .await
        .json()
    }

    /// The messages of the log from index `from` on (an index of [`Client::log`]).
    pub fn messages_since(&self, from: usize) -> Vec<Message> {
        self.log
            .get(from..)
            .unwrap_or_default()
            .iter()
            .filter_map(Seen::message)
            .collect()
    }

    /// Starts a client that subscribes nothing by itself.
    pub fn connect(options: MqttOptions) -> Client {
        Client::subscribe_on_connect(options, &[])
    }

    /// Waits for the first report from now on that `pred` accepts; panics with `what` and
    /// everything seen on timeout.
    pub async fn expect(&mut self, what: &str, pred: impl Fn(&Seen) -> bool) -> Seen {
        let deadline = tokio::time::Instant::now() + crate::time::scaled(self.wait);
        loop {
            match tokio::time::timeout_at(deadline, self.rx.recv()).await {
                Ok(Some(s)) => {
                    self.log.push(s.clone());
                    if pred(&s) {
                        return s;
                    }
                }
                Ok(None) => panic!("the test client stopped while waiting for {what}"),
                Err(_) => panic!("timed out waiting for {what}; seen:\n{}", self.dump()),
            }
        }
    }

    /// Like [`Client::expect`], but a report already in the log counts too.
    pub async fn seen(&mut self, what: &str, pred: impl Fn(&Seen) -> bool) -> Seen {
        self.drain();
        if let Some(s) = self.log.iter().find(|s| pred(s)) {
            return s.clone();
        }
        self.expect(what, pred).await
    }

    /// Waits for the next ConnAck and returns its code.
    pub async fn connack(&mut self) -> ConnectReturnCode {
        match self
            .expect("CONNACK", |s| matches!(s, Seen::ConnAck(_)))
            .await
        {
            Seen::ConnAck(code) => code,
            _ => unreachable!("expect returned what the predicate accepted"),
        }
    }

    /// Subscribes `filter` (QoS 1) and returns the SUBACK's code for it.
    pub async fn subscribe(&mut self, filter: &str) -> SubscribeReasonCode {
        self.client
            .subscribe(filter, QoS::AtLeastOnce)
            .await
            .expect("queue SUBSCRIBE");
        match self
            .expect(&format!("SUBACK for {filter}"), |s| {
                matches!(s, Seen::SubAck(_))
            })
            .await
        {
            Seen::SubAck(codes) => codes.first().copied().expect("one code per filter"),
            _ => unreachable!("expect returned what the predicate accepted"),
        }
    }

    /// Publishes with QoS 1 (not retained) without waiting for the PUBACK.
    pub async fn publish(&self, topic: &str, payload: impl Into<Vec<u8>>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, false, payload.into())
            .await
            .expect("queue PUBLISH");
    }

    /// Publishes with QoS 1 and the RETAIN flag, without waiting for the PUBACK.
    pub async fn publish_retained(&self, topic: &str, payload: impl Into<Vec<u8>>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, true, payload.into())
            .await
            .expect("queue PUBLISH");
    }

    /// Waits for a message on `topic` whose payload passes `pred`.
    pub async fn expect_message(&mut self, topic: &str, pred: impl Fn(&[u8]) -> bool) -> Seen {
        self.expect(
            &format!("a message on {topic}"),
            |s| matches!(s, Seen::Message { topic: t, payload, .. } if t == topic && pred(payload)),
        )
        .await
    }

    /// Everything received so far without waiting.
    pub fn drain(&mut self) -> &[Seen] {
        while let Ok(s) = self.rx.try_recv() {
            self.log.push(s);
        }
        &self.log
    }

    /// The log, one report per line, for failure messages.
    pub fn dump(&self) -> String {
        self.log
            .iter()
            .map(|s| match s {
                Seen::Message {
                    topic,
                    payload,
                    retain,
                } => format!(
                    "  {topic}{} {}",
                    if *retain { " (retained)" } else { "" },
                    String::from_utf8_lossy(payload)
                ),
                other => format!("  {other:?}"),
            })
            .collect::<Vec<_>>()
            .join("\n")
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        self.task.abort();
    }
}
