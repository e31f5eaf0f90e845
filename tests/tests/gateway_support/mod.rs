//! Shared rig of the gateway's end-to-end tests: a real Mosquitto, a leased vcan interface, the
//! gateway running in-process (`mc_gateway::run`) and a simulated island (`sim-node`) on the same
//! interface, plus an MQTT test client that records everything under the island's prefix.
#![allow(dead_code)]

use std::time::Duration;

use ihex_proto::NodeId;
use ihex_tests::{broker::Mosquitto, mqtt};
use mc_gateway::{config::Options, CancellationToken, Config};
use serde_json::Value;
use sim_node::{link::Link, Island, IslandDesc, IslandHandle};
use tokio::task::JoinHandle;

/// Generous deadline for one expected message (scaled in the VM by `IHEX_TEST_TIME_SCALE`).
pub const WAIT: Duration = Duration::from_secs(10);

/// The demo's island, so the tests exercise what a user sees: static 111 and 112, mobile 2 docked on
/// 111 port 3 (its own port 0), mobile 3 free (its own port 1).
pub const ISLAND: &str = mc_gateway::demo::BUILTIN_ISLAND;

pub fn id(hex: &str) -> NodeId {
    sim_node::desc::parse_node_id(hex).expect("node id")
}

/// One MQTT message seen by the test client.
pub use ihex_tests::mqtt::Message as Seen;

/// The rig's recorder: the one MQTT test client ([`mqtt::Client`]) subscribed to the island's
/// topics, with the messages it has seen so far in `log` (its ConnAcks, SubAcks and PubAcks left
/// out).
pub struct Client {
    /// rumqttc's handle, to publish and subscribe.
    pub client: rumqttc::AsyncClient,
    inner: mqtt::Client,
    /// Every message received so far, in order.
    pub log: Vec<Seen>,
    /// How much of the inner client's log is in `log`.
    synced: usize,
}

impl Client {
    pub fn connect(broker: std::net::SocketAddr, name: &str, filters: &[String]) -> Client {
        let inner = mqtt::Client::subscribed(broker, name, filters);
        Client {
            client: inner.client.clone(),
            inner,
            log: Vec::new(),
            synced: 0,
        }
    }

    fn sync(&mut self) {
        self.log.extend(self.inner.messages_since(self.synced));
        self.synced = self.inner.log.len();
    }

    /// Waits for the first message (from now on) that `pred` accepts; panics with `what` on timeout.
    pub async fn expect(&mut self, what: &str, pred: impl Fn(&Seen) -> bool) -> Seen {
        let m = self.inner.expect_msg(what, pred).await;
        self.sync();
        m
    }

    /// Waits for an event named `name` on `events` whose payload passes `pred`.
    pub async fn expect_event(
        &mut self,
        events: &str,
        name: &str,
        pred: impl Fn(&Value) -> bool,
    ) -> Value {
        let v = self.inner.expect_event(events, name, pred).await;
        self.sync();
        v
    }

    /// Everything received so far without waiting more.
    pub fn drain(&mut self) -> &[Seen] {
        self.inner.drain();
        self.sync();
        &self.log
    }

    pub async fn publish(&self, topic: &str, payload: impl Into<Vec<u8>>) {
        self.inner.publish(topic, payload).await;
    }
}

/// A gateway running in-process.
pub struct Gateway {
    pub config: Config,
    pub stop: CancellationToken,
    pub task: JoinHandle<Result<(), mc_gateway::GatewayError>>,
}

fn scaled_ms(ms: u64) -> u64 {
    ihex_tests::time::scaled(Duration::from_millis(ms)).as_millis() as u64
}

impl Gateway {
    /// Starts a gateway on `iface` against `broker`, island name `island`, with a fast health check.
    pub fn start(broker: std::net::SocketAddr, iface: &str, island: &str) -> Gateway {
        Gateway::start_with(broker, iface, island, |_| {})
    }

    /// [`Gateway::start`] with more options set by `tweak`.
    pub fn start_with(
        broker: std::net::SocketAddr,
        iface: &str,
        island: &str,
        tweak: impl FnOnce(&mut Options),
    ) -> Gateway {
        let mut cli = Options {
            broker: Some(broker.to_string()),
            can: Some(iface.into()),
            island: Some(island.into()),
            health_period_ms: Some(200),
            lost_after: Some(3),
            // Under emulation (the microVM) a node's ack can take longer than on hardware: stretch the
            // gateway's own deadlines like the tests' (IHEX_TEST_TIME_SCALE), so they only fail on a
            // missing answer, never on a slow one.
            command_timeout_ms: Some(scaled_ms(1000)),
            dock_timeout_ms: Some(scaled_ms(3000)),
            log_dir: Some("-".into()),
            // No SiLA server (its port, state files and mDNS) unless a test asks for one.
            sila: Some("off".into()),
            ..Options::default()
        };
        tweak(&mut cli);
        let config = Config::resolve(cli, Options::default()).expect("valid test config");
        let stop = CancellationToken::new();
        let task = tokio::spawn(mc_gateway::run(config.clone(), stop.clone()));
        Gateway { config, stop, task }
    }

    pub fn events(&self) -> String {
        self.config.topics.events.clone()
    }

    pub fn commands(&self) -> String {
        self.config.topics.commands.clone()
    }

    /// Stops the gateway and checks it ended cleanly.
    pub async fn shutdown(self) {
        self.stop.cancel();
        let r = ihex_tests::within_or_panic(WAIT, "gateway shutdown", self.task).await;
        r.expect("gateway task panicked")
            .expect("gateway returned an error");
    }
}

/// Broker + gateway + island + client, for one island on one leased interface.
pub struct Rig {
    /// The broker, when this rig owns it.
    pub broker: Option<Mosquitto>,
    /// Where the broker listens.
    pub addr: std::net::SocketAddr,
    pub iface: String,
    pub gateway: Gateway,
    pub island: IslandHandle,
    pub client: Client,
}

impl Rig {
    /// Starts everything and waits until the gateway is online and sees all four nodes.
    pub async fn start(name: &str) -> Rig {
        let broker = Mosquitto::start().expect("start mosquitto");
        Rig::start_on(broker, name).await
    }

    pub async fn start_on(broker: Mosquitto, name: &str) -> Rig {
        let addr = broker.addr();
        let mut rig = Rig::start_at(addr, name).await;
        rig.broker = Some(broker);
        rig
    }

    /// A rig on a broker someone else owns.
    pub async fn start_at(addr: std::net::SocketAddr, name: &str) -> Rig {
        Rig::start_at_with(addr, name, |_| {}).await
    }

    /// [`Rig::start`] with more gateway options set by `tweak`.
    pub async fn start_with(name: &str, tweak: impl FnOnce(&mut Options)) -> Rig {
        let broker = Mosquitto::start().expect("start mosquitto");
        let mut rig = Rig::start_at_with(broker.addr(), name, tweak).await;
        rig.broker = Some(broker);
        rig
    }

    /// [`Rig::start_on`] with more gateway options set by `tweak`.
    pub async fn start_with_broker(
        broker: Mosquitto,
        name: &str,
        tweak: impl FnOnce(&mut Options),
    ) -> Rig {
        let mut rig = Rig::start_at_with(broker.addr(), name, tweak).await;
        rig.broker = Some(broker);
        rig
    }

    /// [`Rig::start_at`] with more gateway options set by `tweak`.
    pub async fn start_at_with(
        addr: std::net::SocketAddr,
        name: &str,
        tweak: impl FnOnce(&mut Options),
    ) -> Rig {
        let iface = ihex_tests::can::lease();
        let gateway = Gateway::start_with(addr, &iface, name, tweak);
        let mut client = Client::connect(addr, &format!("test-{name}"), &[format!("{name}/#")]);
        let avail = gateway.config.topics.availability.clone();
        client
            .expect("gateway online", |m| {
                m.topic == avail && m.payload == b"online"
            })
            .await;
        // The gateway is subscribed once it announced itself; now boot the island so every node's
        // start is seen.
        let desc = IslandDesc::parse(ISLAND).expect("island");
        let island = Island::start(&desc, Link::socketcan(iface.clone())).expect("start island");
        let events = gateway.events();
        for n in ["111", "112", "2"] {
            client
                .expect_event(&events, "node_online", |p| p["id"] == n)
                .await;
        }
        Rig {
            broker: None,
            addr,
            iface,
            gateway,
            island,
            client,
        }
    }

    pub fn events(&self) -> String {
        self.gateway.events()
    }

    /// The broker this rig owns.
    pub fn broker(&mut self) -> &mut Mosquitto {
        self.broker.as_mut().expect("this rig owns its broker")
    }

    /// Publishes a command (QoS 1) on the island's command topic.
    pub async fn command(&self, json: &str) {
        self.client.publish(&self.gateway.commands(), json).await;
    }

    /// Sends a command with `request_id` and waits for its `command_result`.
    pub async fn command_ok(&mut self, json_without_close: &str, request_id: &str) -> Value {
        self.command(&format!(
            "{json_without_close},\"request_id\":\"{request_id}\"}}"
        ))
        .await;
        let events = self.events();
        let r = self
            .client
            .expect_event(&events, "command_result", |p| p["request_id"] == request_id)
            .await;
        assert_eq!(r["payload"]["result"], "ok", "{r}");
        r
    }

    pub async fn shutdown(self) {
        self.gateway.shutdown().await;
        self.island.shutdown().await;
    }
}
