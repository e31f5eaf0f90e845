//! A short-lived MQTT session with the gateway's broker: subscribe, publish commands, read what comes
//! back until a deadline. One task owns rumqttc's event loop and forwards into a bounded channel.

use std::{collections::VecDeque, time::Duration};

use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use tokio::{sync::mpsc, task::JoinHandle, time::Instant};

/// Largest packet sent or received: a firmware upload (at most 128 KiB) and its topic fit.
pub const MAX_PACKET: usize = 1 << 20;

/// Errors of the MQTT session.
#[derive(Debug, thiserror::Error)]
pub enum MqttError {
    /// `--broker` is not `HOST[:PORT]`.
    #[error("broker address {0:?} is not HOST[:PORT]")]
    BadBroker(String),
    /// The connection failed or broke.
    #[error("MQTT connection to {broker}: {reason}")]
    Connection {
        /// `host:port`.
        broker: String,
        /// What rumqttc reported.
        reason: String,
    },
    /// A request could not be queued (the session is gone).
    #[error("MQTT client: {0}")]
    Client(#[from] rumqttc::ClientError),
    /// Not connected and subscribed in time.
    #[error("no MQTT session with {0} within {1:?} (is the broker running and reachable?)")]
    ConnectTimeout(String, Duration),
}

/// Where the broker is, and how to log in.
#[derive(Clone, Debug)]
pub struct Broker {
    /// Host name or address.
    pub host: String,
    /// TCP port.
    pub port: u16,
    /// Optional user name and password.
    pub credentials: Option<(String, String)>,
}

impl Broker {
    /// Parses `HOST[:PORT]` (port 1883 when absent; `[::1]:1883` for IPv6).
    pub fn parse(text: &str) -> Result<Broker, MqttError> {
        let bad = || MqttError::BadBroker(text.to_owned());
        let (host, port) = if let Some(rest) = text.strip_prefix('[') {
            let (h, p) = rest.split_once(']').ok_or_else(bad)?;
            (h, p.strip_prefix(':'))
        } else {
            match text.rsplit_once(':') {
                Some((h, p)) => (h, Some(p)),
                None => (text, None),
            }
        };
        let port = match port {
            Some(p) => p.parse::<u16>().ok().filter(|p| *p != 0).ok_or_else(bad)?,
            None => 1883,
        };
        if host.is_empty() || host.contains(char::is_whitespace) {
            return Err(bad());
        }
        Ok(Broker {
            host: host.to_owned(),
            port,
            credentials: None,
        })
    }

    fn label(&self) -> String {
        format!("{}:{}", self.host, self.port)
    }
}

/// A message received on a subscribed topic.
#[derive(Clone, Debug)]
pub struct Incoming {
    /// The topic it arrived on.
    pub topic: String,
    /// Its payload.
    pub payload: Vec<u8>,
    /// Whether the broker delivered it as a retained message.
    pub retain: bool,
}

enum Note {
    SubAck,
    Message(Incoming),
    Failed(String),
}

/// A connected, subscribed session.
pub struct Session {
    client: AsyncClient,
    rx: mpsc::Receiver<Note>,
    task: JoinHandle<()>,
    broker: String,
    early: VecDeque<Incoming>,
}

impl Session {
    /// Connects (clean session, keep-alive 20 s, TCP_NODELAY) and subscribes to `topics` at QoS 1;
    /// returns once every subscription is acknowledged, or fails after `timeout`.
    pub async fn connect(
        broker: &Broker,
        topics: &[String],
        timeout: Duration,
    ) -> Result<Session, MqttError> {
        let client_id = format!("ihex-provision-{}", std::process::id());
        let mut opts = MqttOptions::new(client_id, broker.host.clone(), broker.port);
        opts.set_keep_alive(Duration::from_secs(20))
            .set_clean_session(true)
            // Firmware uploads go out whole (rumqttc's default limit is 10 KiB).
            .set_max_packet_size(MAX_PACKET, MAX_PACKET);
        if let Some((user, pass)) = &broker.credentials {
            opts.set_credentials(user.clone(), pass.clone());
        }
        let (client, mut eventloop) = AsyncClient::new(opts, 16);
        let mut net = rumqttc::NetworkOptions::new();
        net.set_tcp_nodelay(true);
        net.set_connection_timeout(timeout.as_secs().max(1));
        eventloop.set_network_options(net);
        for t in topics {
            client.subscribe(t.clone(), QoS::AtLeastOnce).await?;
        }
        let (tx, rx) = mpsc::channel(64);
        let task = tokio::spawn(async move {
            loop {
                let note = match eventloop.poll().await {
                    Ok(Event::Incoming(Packet::SubAck(_))) => Note::SubAck,
                    Ok(Event::Incoming(Packet::Publish(p))) => Note::Message(Incoming {
                        topic: p.topic,
                        payload: p.payload.to_vec(),
                        retain: p.retain,
                    }),
                    Ok(_) => continue,
                    // A provisioning run is short: a broken connection ends it rather than retrying.
                    Err(e) => {
                        let _ = tx.send(Note::Failed(e.to_string())).await;
                        return;
                    }
                };
                if tx.send(note).await.is_err() {
                    return;
                }
            }
        });
        let mut session = Session {
            client,
            rx,
            task,
            broker: broker.label(),
            early: VecDeque::new(),
        };
        let deadline = Instant::now() + timeout;
        let mut acks = 0;
        while acks < topics.len() {
            match tokio::time::timeout_at(deadline, session.rx.recv()).await {
                Err(_) => return Err(MqttError::ConnectTimeout(session.broker.clone(), timeout)),
                Ok(None) => return Err(session.gone()),
                Ok(Some(Note::SubAck)) => acks += 1,
                Ok(Some(Note::Failed(reason))) => {
                    return Err(MqttError::Connection {
                        broker: session.broker.clone(),
                        reason,
                    })
                }
                // Retained messages may arrive before the last SubAck: keep them for `recv_until`.
                Ok(Some(Note::Message(m))) => session.early.push_back(m),
            }
        }
        Ok(session)
    }

    fn gone(&self) -> MqttError {
        MqttError::Connection {
            broker: self.broker.clone(),
            reason: "session ended".into(),
        }
    }

    /// Publishes `payload` on `topic` at QoS 1, not retained.
    pub async fn publish(&self, topic: &str, payload: impl Into<Vec<u8>>) -> Result<(), MqttError> {
        self.client
            .publish(topic, QoS::AtLeastOnce, false, payload)
            .await?;
        Ok(())
    }

    /// The next message, or `None` once `deadline` passes.
    pub async fn recv_until(&mut self, deadline: Instant) -> Result<Option<Incoming>, MqttError> {
        if let Some(m) = self.early.pop_front() {
            return Ok(Some(m));
        }
        loop {
            match tokio::time::timeout_at(deadline, self.rx.recv()).await {
                Err(_) => return Ok(None),
                Ok(None) => return Err(self.gone()),
                Ok(Some(Note::Message(m))) => return Ok(Some(m)),
                Ok(Some(Note::SubAck)) => {}
                Ok(Some(Note::Failed(reason))) => {
                    return Err(MqttError::Connection {
                        broker: self.broker.clone(),
                        reason,
                    })
                }
            }
        }
    }

    /// Disconnects cleanly (waits briefly so a just-published QoS 1 message is flushed).
    pub async fn close(self) {
        let Session {
            client, rx, task, ..
        } = self;
        // Dropping the receiver lets the event-loop task end instead of blocking on a full channel.
        drop(rx);
        let _ = client.disconnect().await;
        let _ = tokio::time::timeout(Duration::from_secs(2), task).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn broker_addresses() {
        let b = Broker::parse("192.168.1.101:1883").unwrap();
        assert_eq!((b.host.as_str(), b.port), ("192.168.1.101", 1883));
        let b = Broker::parse("broker.lab").unwrap();
        assert_eq!((b.host.as_str(), b.port), ("broker.lab", 1883));
        let b = Broker::parse("[::1]:1884").unwrap();
        assert_eq!((b.host.as_str(), b.port), ("::1", 1884));
        for bad in [
            "",
            ":1883",
            "host:",
            "host:0",
            "host:65536",
            "host:x",
            "[::1",
            "a b:1",
        ] {
            assert!(Broker::parse(bad).is_err(), "{bad:?}");
        }
    }
}
