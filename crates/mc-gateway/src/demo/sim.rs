//! Control of the simulated island over MQTT: its own client subscribes the `ihex/sim` topic,
//! carries out each message on the island (dock, undock, power cycle, bus off/on) and answers on the
//! events topic like a command is answered — `sim_result` (`ok`, `refused` with the island's reason,
//! `timeout`) or `sim_rejected` for a message it cannot read. The gateway's core never waits on it.

use std::time::Duration;

use ihex_gateway_core::event::{CommandRejected, Event, Outcome, SimResult};
use ihex_proto::NodeId;
use rumqttc::{AsyncClient, Event as MqttEvent, EventLoop, Incoming, NetworkOptions, QoS};
use serde_json::{Map, Value};
use sim_node::{IslandError, IslandHandle};
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::{config::Config, error::GatewayError, mqtt, topic::Topics};

/// Every control message name, for error messages.
pub const SIM_NAMES: &str = "dock, undock, power_cycle, off_bus, on_bus";
/// How long one control message may take on the island.
const APPLY_TIMEOUT: Duration = Duration::from_secs(2);
/// How long building the demo waits for the control client's subscription.
const READY_TIMEOUT: Duration = Duration::from_secs(5);

/// A control message on the simulation topic.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimCommand {
    /// Dock a mobile element on a static element's port.
    Dock {
        /// Mobile element.
        mobile: NodeId,
        /// Static element.
        static_id: NodeId,
        /// Dock port of the static element.
        port: u8,
    },
    /// Undock a mobile element.
    Undock {
        /// Mobile element.
        mobile: NodeId,
    },
    /// Remove and restore an element's power.
    PowerCycle {
        /// Element.
        node: NodeId,
    },
    /// Disconnect an element from the bus (it keeps running).
    OffBus {
        /// Element.
        node: NodeId,
    },
    /// Reconnect an element to the bus.
    OnBus {
        /// Element.
        node: NodeId,
    },
}

impl SimCommand {
    /// The message name (`"sim"` field).
    pub fn name(&self) -> &'static str {
        match self {
            SimCommand::Dock { .. } => "dock",
            SimCommand::Undock { .. } => "undock",
            SimCommand::PowerCycle { .. } => "power_cycle",
            SimCommand::OffBus { .. } => "off_bus",
            SimCommand::OnBus { .. } => "on_bus",
        }
    }
}

/// A control message and its optional request id.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Request {
    /// Echoed in the answer.
    pub request_id: Option<String>,
    /// What to do.
    pub command: SimCommand,
}

/// Why a control message was not understood, with its request id when it could be read.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rejection {
    /// The message's `request_id`, when readable.
    pub request_id: Option<String>,
    /// What was wrong and what is accepted.
    pub reason: String,
}

fn node_field(map: &Map<String, Value>, sim: &str, field: &str) -> Result<NodeId, String> {
    let bad = |got: &Value| {
        format!("{sim}: `{field}` must be an element id in hex, \"1\" to \"ffd\"; got {got}")
    };
    match map.get(field) {
        None | Some(Value::Null) => Err(format!(
            "{sim}: missing `{field}` (an element id in hex, \"1\" to \"ffd\")"
        )),
        Some(v @ Value::String(s)) => sim_node::desc::parse_node_id(s).map_err(|_| bad(v)),
        Some(v) => Err(bad(v)),
    }
}

/// Parses one control message.
pub fn parse(payload: &[u8]) -> Result<Request, Rejection> {
    let reject = |request_id: Option<String>, reason: String| Rejection { request_id, reason };
    let value: Value = serde_json::from_slice(payload)
        .map_err(|e| reject(None, format!("malformed JSON: {e}")))?;
    let Value::Object(mut map) = value else {
        return Err(reject(
            None,
            format!(
                "a simulation command must be a JSON object like \
                 {{\"sim\":\"dock\",\"mobile\":\"3\",\"static\":\"112\",\"port\":2}}; got {value}"
            ),
        ));
    };
    let request_id = match map.remove("request_id") {
        None | Some(Value::Null) => None,
        Some(Value::String(s)) => Some(s),
        Some(other) => {
            return Err(reject(
                None,
                format!("`request_id` must be a string; got {other}"),
            ))
        }
    };
    let sim = match map.remove("sim") {
        Some(Value::String(s)) => s,
        None => {
            let reason = format!("missing field `sim`; expected one of: {SIM_NAMES}");
            return Err(reject(request_id, reason));
        }
        Some(other) => {
            let reason = format!("unknown sim {other}; expected one of: {SIM_NAMES}");
            return Err(reject(request_id, reason));
        }
    };
    let fields: &[&str] = match sim.as_str() {
        "dock" => &["mobile", "static", "port"],
        "undock" => &["mobile"],
        "power_cycle" | "off_bus" | "on_bus" => &["node"],
        _ => {
            let reason = format!("unknown sim {sim:?}; expected one of: {SIM_NAMES}");
            return Err(reject(request_id, reason));
        }
    };
    if let Some(k) = map.keys().find(|k| !fields.contains(&k.as_str())) {
        let reason = format!(
            "{sim}: unknown field `{k}`; expected one of: {}",
            fields.join(", ")
        );
        return Err(reject(request_id, reason));
    }
    let command = match sim.as_str() {
        "dock" => (|| {
            let port = match map.get("port") {
                Some(Value::Number(n)) => n.as_u64().and_then(|p| u8::try_from(p).ok()),
                _ => None,
            };
            let port = port.ok_or_else(|| match map.get("port") {
                None | Some(Value::Null) => "dock: missing `port` (an integer 0 to 255)".into(),
                Some(v) => format!("dock: `port` must be an integer 0 to 255; got {v}"),
            })?;
            Ok(SimCommand::Dock {
                mobile: node_field(&map, &sim, "mobile")?,
                static_id: node_field(&map, &sim, "static")?,
                port,
            })
        })(),
        "undock" => node_field(&map, &sim, "mobile").map(|mobile| SimCommand::Undock { mobile }),
        "power_cycle" => node_field(&map, &sim, "node").map(|node| SimCommand::PowerCycle { node }),
        "off_bus" => node_field(&map, &sim, "node").map(|node| SimCommand::OffBus { node }),
        _ => node_field(&map, &sim, "node").map(|node| SimCommand::OnBus { node }),
    };
    match command {
        Ok(command) => Ok(Request {
            request_id,
            command,
        }),
        Err(reason) => Err(reject(request_id, reason)),
    }
}

/// Carries out one control message on the island.
pub async fn apply(island: &IslandHandle, command: SimCommand) -> Result<(), IslandError> {
    match command {
        SimCommand::Dock {
            mobile,
            static_id,
            port,
        } => island.dock(mobile, static_id, port).await,
        SimCommand::Undock { mobile } => island.undock(mobile).await,
        SimCommand::PowerCycle { node } => island.power_cycle(node).await,
        SimCommand::OffBus { node } => island.set_on_bus(node, false).await,
        SimCommand::OnBus { node } => island.set_on_bus(node, true).await,
    }
}

/// Reads, carries out and answers one control message.
pub async fn handle(island: &IslandHandle, payload: &[u8]) -> Event {
    let req = match parse(payload) {
        Ok(req) => req,
        Err(r) => {
            return Event::SimRejected(CommandRejected {
                origin: None,
                request_id: r.request_id,
                reason: r.reason,
            })
        }
    };
    let (result, reason) =
        match tokio::time::timeout(APPLY_TIMEOUT, apply(island, req.command)).await {
            Ok(Ok(())) => (Outcome::Ok, None),
            Ok(Err(e)) => (Outcome::Refused, Some(e.to_string())),
            Err(_) => (
                Outcome::Timeout,
                Some(format!(
                    "the simulated island did not answer within {} s",
                    APPLY_TIMEOUT.as_secs()
                )),
            ),
        };
    Event::SimResult(SimResult {
        request_id: req.request_id,
        sim: req.command.name().into(),
        result,
        reason,
    })
}

/// The island's MQTT control client: connected and subscribed by [`Control::connect`], serving
/// once [`Control::run`] runs.
pub struct Control {
    client: AsyncClient,
    eventloop: EventLoop,
    topics: Topics,
    island: IslandHandle,
}

impl Control {
    /// Connects a client of its own (`<client id>-sim`, no last will) and waits until the sim topic
    /// is subscribed, at most a few seconds: a broker that is not there yet only delays the
    /// subscription, which then happens as soon as it connects.
    pub async fn connect(config: &Config, island: IslandHandle) -> Result<Control, GatewayError> {
        let client_id = format!("{}-sim", config.mqtt.client_id);
        let options = mqtt::client_options(&config.mqtt, client_id)?;
        let (client, mut eventloop) = AsyncClient::new(options, 16);
        let mut net = NetworkOptions::new();
        net.set_tcp_nodelay(true);
        eventloop.set_network_options(net);
        let mut control = Control {
            client,
            eventloop,
            topics: config.topics.clone(),
            island,
        };
        let subscribed = tokio::time::timeout(READY_TIMEOUT, async {
            loop {
                match control.eventloop.poll().await {
                    Ok(MqttEvent::Incoming(Incoming::SubAck(_))) => return,
                    Ok(ev) => control.on_event(ev).await,
                    Err(e) => {
                        debug!(error = %e, "simulation control cannot reach the broker yet");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                }
            }
        })
        .await;
        if subscribed.is_err() {
            warn!(topic = %control.topics.sim, "simulation control not subscribed yet; it keeps trying");
        }
        Ok(control)
    }

    /// Serves control messages until `cancel`.
    #[tracing::instrument(name = "sim_control", skip_all)]
    pub async fn run(mut self, cancel: CancellationToken) {
        let mut delay = mqtt::RECONNECT_MIN;
        loop {
            let ev = tokio::select! {
                _ = cancel.cancelled() => return,
                ev = self.eventloop.poll() => ev,
            };
            match ev {
                Ok(ev) => {
                    delay = mqtt::RECONNECT_MIN;
                    self.on_event(ev).await;
                }
                Err(e) => {
                    debug!(error = %e, "simulation control lost the broker");
                    tokio::select! {
                        _ = cancel.cancelled() => return,
                        _ = tokio::time::sleep(delay) => {}
                    }
                    delay = (delay * 2).min(mqtt::RECONNECT_MAX);
                }
            }
        }
    }

    async fn on_event(&mut self, ev: MqttEvent) {
        match ev {
            // A clean session forgets subscriptions: subscribe on every connection.
            MqttEvent::Incoming(Incoming::ConnAck(_)) => {
                if let Err(e) = self
                    .client
                    .try_subscribe(self.topics.sim.clone(), QoS::AtLeastOnce)
                {
                    warn!(error = %e, "cannot queue the simulation subscription");
                }
            }
            MqttEvent::Incoming(Incoming::Publish(p)) if p.topic == self.topics.sim => {
                let answer = handle(&self.island, &p.payload).await;
                self.answer(&answer);
            }
            _ => {}
        }
    }

    fn answer(&self, event: &Event) {
        let json = event.to_json();
        // Logged like the core's events: the log alone tells what happened on the bench.
        info!(event = event.name(), payload = %json, "event published");
        if let Err(e) =
            self.client
                .try_publish(self.topics.events.clone(), QoS::AtLeastOnce, false, json)
        {
            warn!(error = %e, "cannot queue the simulation answer");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn id(s: &str) -> NodeId {
        s.parse().unwrap()
    }

    #[test]
    fn control_messages_parse() {
        let r = parse(br#"{"sim":"dock","mobile":"3","static":"112","port":2,"request_id":"d"}"#)
            .unwrap();
        assert_eq!(r.request_id.as_deref(), Some("d"));
        assert_eq!(
            r.command,
            SimCommand::Dock {
                mobile: id("3"),
                static_id: id("112"),
                port: 2
            }
        );
        let r = parse(br#"{"sim":"off_bus","node":"112"}"#).unwrap();
        assert_eq!(r.command, SimCommand::OffBus { node: id("112") });
    }

    #[test]
    fn mistakes_are_explained() {
        let cases: &[(&[u8], &str)] = &[
            (b"{nope", "malformed JSON"),
            (b"[1]", "must be a JSON object"),
            (
                br#"{"sim":"explode"}"#,
                "unknown sim \"explode\"; expected one of: dock",
            ),
            (br#"{"mobile":"3"}"#, "missing field `sim`"),
            (br#"{"sim":"undock"}"#, "undock: missing `mobile`"),
            (
                br#"{"sim":"undock","mobile":"zz"}"#,
                "undock: `mobile` must be an element id",
            ),
            (
                br#"{"sim":"dock","mobile":"3","static":"112","port":"2"}"#,
                "dock: `port` must be an integer 0 to 255; got \"2\"",
            ),
            (
                br#"{"sim":"on_bus","node":"1","x":1}"#,
                "on_bus: unknown field `x`",
            ),
        ];
        for (input, needle) in cases {
            let r = parse(input).unwrap_err();
            assert!(
                r.reason.contains(needle),
                "{}: {}",
                String::from_utf8_lossy(input),
                r.reason
            );
        }
        let r = parse(br#"{"sim":"nope","request_id":"q"}"#).unwrap_err();
        assert_eq!(r.request_id.as_deref(), Some("q"));
    }
}
