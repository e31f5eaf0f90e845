//! The broker: reachable, TLS, login, and a real publish/subscribe round trip on a doctor topic
//! under the island's prefix (`ISLAND/ihex/doctor/<pid>`), which the per-island ACL
//! (`deploy/mosquitto/acl`: `topic readwrite ISLAND/#`) allows. Mosquitto with MQTT 3.1.1 does not
//! refuse what an ACL denies, it drops it silently; only the round trip shows it.

use std::time::Duration;

use rumqttc::{
    AsyncClient, ConnectReturnCode, ConnectionError, Event, Packet, QoS, SubscribeReasonCode,
};

use super::Verdict;
use crate::config::Config;

/// Identifier of the connection check.
pub const CONNECT: &str = "broker.connect";
/// Identifier of the round-trip check.
pub const TOPICS: &str = "broker.topics";

/// How the connection attempt ended.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Connect {
    /// CONNACK accepted.
    Accepted,
    /// CONNACK with a refusal code.
    Refused(ConnectReturnCode),
    /// No session: the reason in words (address, TLS, timeout).
    Failed(String),
}

/// What talking to the broker showed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Facts {
    /// `host:port`.
    pub broker: String,
    /// Over TLS.
    pub tls: bool,
    /// The user name logged in with, if any.
    pub user: Option<String>,
    /// The doctor's topic.
    pub topic: String,
    /// The connection.
    pub connect: Connect,
    /// The SUBACK granted the subscription (`None`: no SUBACK in time).
    pub subscribed: Option<bool>,
    /// The message published on [`Facts::topic`] came back through the subscription.
    pub echoed: bool,
}

/// The doctor's topic for this configuration: under the island's prefix, unique per process.
pub fn topic(config: &Config) -> String {
    let leaf = format!("ihex/doctor/{}", std::process::id());
    match &config.island {
        Some(island) => format!("{island}/{leaf}"),
        None => leaf,
    }
}

/// Connects as the gateway would (its credentials and TLS, another client id so the gateway's
/// own session is not taken over), subscribes to the doctor topic, publishes on it and waits for
/// the message to come back; each step within `timeout`.
pub async fn gather(config: &Config, timeout: Duration) -> Facts {
    let broker = match &config.mqtt.broker {
        crate::config::Broker::External { host, port } => format!("{host}:{port}"),
        crate::config::Broker::Embedded { listen } => listen.to_string(),
    };
    let mut facts = Facts {
        broker: broker.clone(),
        tls: config.mqtt.tls.is_some(),
        user: config.mqtt.credentials.as_ref().map(|(u, _)| u.clone()),
        topic: topic(config),
        connect: Connect::Failed(String::new()),
        subscribed: None,
        echoed: false,
    };
    let client_id = format!("{}-doctor-{}", config.mqtt.client_id, std::process::id());
    let options = match crate::mqtt::client_options(&config.mqtt, client_id) {
        Ok(o) => o,
        Err(e) => {
            facts.connect = Connect::Failed(e.to_string());
            return facts;
        }
    };
    let (client, mut events) = AsyncClient::new(options, 10);
    let step = |d| tokio::time::Instant::now() + d;

    let deadline = step(timeout);
    facts.connect = loop {
        match tokio::time::timeout_at(deadline, events.poll()).await {
            Err(_) => {
                break Connect::Failed(format!(
                    "no answer from broker {broker} within {} s: check --broker, the network and firewalls",
                    timeout.as_secs()
                ))
            }
            Ok(Ok(Event::Incoming(Packet::ConnAck(_)))) => break Connect::Accepted,
            Ok(Ok(_)) => {}
            Ok(Err(ConnectionError::ConnectionRefused(code))) => break Connect::Refused(code),
            Ok(Err(e)) => break Connect::Failed(crate::mqtt::explain(&e, &broker, facts.tls)),
        }
    };
    if facts.connect != Connect::Accepted {
        return facts;
    }

    let payload = format!("doctor {}", std::process::id());
    let queued = client
        .try_subscribe(facts.topic.clone(), QoS::AtLeastOnce)
        .and_then(|()| {
            client.try_publish(
                facts.topic.clone(),
                QoS::AtLeastOnce,
                false,
                payload.clone(),
            )
        });
    if queued.is_ok() {
        let deadline = step(timeout);
        loop {
            match tokio::time::timeout_at(deadline, events.poll()).await {
                Err(_) | Ok(Err(_)) => break,
                Ok(Ok(Event::Incoming(Packet::SubAck(ack)))) => {
                    facts.subscribed = Some(
                        ack.return_codes
                            .iter()
                            .all(|c| matches!(c, SubscribeReasonCode::Success(_))),
                    );
                }
                Ok(Ok(Event::Incoming(Packet::Publish(p))))
                    if p.topic == facts.topic && p.payload.as_ref() == payload.as_bytes() =>
                {
                    facts.echoed = true;
                    break;
                }
                Ok(Ok(_)) => {}
            }
        }
    }
    let _ = client.try_disconnect();
    // Let the DISCONNECT go out (the broker then drops no will and logs a clean close).
    let _ = tokio::time::timeout(Duration::from_millis(200), events.poll()).await;
    facts
}

/// Judges the connection and the round trip.
pub fn check(f: &Facts) -> Vec<Verdict> {
    let how = format!(
        "{}{}",
        if f.tls { "TLS" } else { "plain TCP" },
        f.user
            .as_ref()
            .map_or(", no login".to_owned(), |u| format!(", user {u}"))
    );
    let skipped = || Verdict::skip(TOPICS, "no session with the broker (above)");
    let connect = match &f.connect {
        Connect::Accepted => Verdict::pass(CONNECT, format!("{} accepted the session ({how})", f.broker)),
        Connect::Refused(code @ (ConnectReturnCode::BadUserNamePassword | ConnectReturnCode::NotAuthorized)) => {
            return vec![
                Verdict::fail(
                    CONNECT,
                    format!("{} refused the login ({code:?}; {how})", f.broker),
                    "check the user name and password (username in gateway.toml, \
                     IHEX_MQTT_PASSWORD in /etc/ihex/gateway.env) against the broker's password file \
                     (mosquitto_passwd)",
                ),
                skipped(),
            ]
        }
        Connect::Refused(code) => {
            return vec![
                Verdict::fail(
                    CONNECT,
                    format!("{} refused the connection ({code:?}; {how})", f.broker),
                    "check --client-id and the broker's log (journalctl -u mosquitto)",
                ),
                skipped(),
            ]
        }
        Connect::Failed(why) => {
            return vec![
                Verdict::fail(
                    CONNECT,
                    format!("no session with {} ({how})", f.broker),
                    why.clone(),
                ),
                skipped(),
            ]
        }
    };
    let who = f.user.as_deref().unwrap_or("anonymous");
    let acl = format!(
        "the broker's ACL does not let {who} read and write {}: give it `topic readwrite {}#` \
         (deploy/mosquitto/acl), or correct the island name (--island); the broker logs \"Denied PUBLISH\"",
        f.topic,
        f.topic.split("ihex/doctor/").next().unwrap_or("")
    );
    let topics = match (f.subscribed, f.echoed) {
        (_, true) => Verdict::pass(TOPICS, format!("published and received on {}", f.topic)),
        (Some(false), false) => Verdict::fail(
            TOPICS,
            format!("the broker refused the subscription to {}", f.topic),
            acl,
        ),
        (None, false) => Verdict::fail(
            TOPICS,
            format!("no SUBACK for {} in time", f.topic),
            "the broker is overloaded or the network drops packets: check the broker's log",
        ),
        (Some(true), false) => Verdict::fail(
            TOPICS,
            format!("a message published on {} never came back", f.topic),
            acl,
        ),
    };
    vec![connect, topics]
}
