//! Shared rig of the gateway's end-to-end tests: a real Mosquitto, a leased vcan interface, the
//! gateway running in-process (`mc_gateway::run`) and a simulated island (`sim-node`) on the same
//! interface, plus an MQTT test client that records everything under the island's prefix.
#![allow(dead_code)]

use std::time::Duration;

use ihex_proto::NodeId;
use ihex_tests::broker::Mosquitto;
use mc_gateway::{config::Options, CancellationToken, Config};
use rumqttc::{AsyncClient, Event, Incoming, MqttOptions, QoS};
use serde_json::Value;
use sim_node::{link::Link, Island, IslandDesc, IslandHandle};
use tokio::{sync::mpsc, task::JoinHandle};

/// Generous deadline for one expected message (scaled in the VM by `IHEX_TEST_TIME_SCALE`).
pub const WAIT: Duration = Duration::from_secs(10);

/// The demo's island, so the tests exercise what a user sees: static 111 and 112, mobile 2 docked on
/// 111 port 3 (its own port 0), mobile 3 free (its own port 1).
pub const ISLAND: &str = mc_gateway::demo::BUILTIN_ISLAND;

pub fn id(hex: &str) -> NodeId {
    sim_node::desc::parse_node_id(hex).expect("node id")
}

/// One MQTT message seen by the test client.
#[derive(Clone, Debug)]
pub struct Seen {
    pub topic: String,
    pub payload: Vec<u8>,
    /// Delivered as a retained message (sent on subscribing), not live.
    pub retain: bool,
}

impl Seen {
    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.payload).unwrap_or(Value::Null)
    }
}

/// A test MQTT client subscribed to `filter`; reconnects (and re-subscribes) on its own.
pub struct Client {
    pub client: AsyncClient,
    rx: mpsc::UnboundedReceiver<Seen>,
    task: JoinHandle<()>,
    /// Everything received so far, in order.
    pub log: Vec<Seen>,
}

impl Client {
    pub fn connect(broker: std::net::SocketAddr, name: &str, filters: &[String]) -> Client {
        let mut o = MqttOptions::new(name, broker.ip().to_string(), broker.port());
        o.set_keep_alive(Duration::from_secs(5))
            .set_max_packet_size(1 << 21, 1 << 21);
        let (client, mut el) = AsyncClient::new(o, 64);
        let (tx, rx) = mpsc::unbounded_channel();
        let c = client.clone();
        let filters = filters.to_vec();
        let task = tokio::spawn(async move {
            loop {
                match el.poll().await {
                    Ok(Event::Incoming(Incoming::ConnAck(_))) => {
                        for f in &filters {
                            let _ = c.try_subscribe(f.clone(), QoS::AtLeastOnce);
                        }
                    }
                    Ok(Event::Incoming(Incoming::Publish(p))) => {
                        let _ = tx.send(Seen {
                            topic: p.topic,
                            payload: p.payload.to_vec(),
                            retain: p.retain,
                        });
                    }
                    Ok(_) => {}
                    Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                }
            }
        });
        Client {
            client,
            rx,
            task,
            log: Vec::new(),
        }
    }

    /// Waits for the first message (from now on) that `pred` accepts; panics with `what` on timeout.
    pub async fn expect(&mut self, what: &str, pred: impl Fn(&Seen) -> bool) -> Seen {
        let deadline = tokio::time::Instant::now() + ihex_tests::time::scaled(WAIT);
        loop {
            match tokio::time::timeout_at(deadline, self.rx.recv()).await {
                Ok(Some(m)) => {
                    self.log.push(m.clone());
                    if pred(&m) {
                        return m;
                    }
                }
                Ok(None) => panic!("test client stopped while waiting for {what}"),
                Err(_) => panic!(
                    "timed out waiting for {what}; seen:\n{}",
                    self.log
                        .iter()
                        .map(|m| format!("  {} {}", m.topic, String::from_utf8_lossy(&m.payload)))
                        .collect::<Vec<_>>()
                        .join("\n")
                ),
            }
        }
    }

    /// Waits for an event named `name` on `events` whose payload passes `pred`.
    pub async fn expect_event(
        &mut self,
        events: &str,
        name: &str,
        pred: impl Fn(&Value) -> bool,
    ) -> Value {
        let what = format!("{name} on {events}");
        self.expect(&what, |m| {
            let v = m.json();
            m.topic == events && v["event"] == name && pred(&v["payload"])
        })
        .await
        .json()
    }

    /// Everything received so far without waiting more.
    pub fn drain(&mut self) -> &[Seen] {
        while let Ok(m) = self.rx.try_recv() {
            self.log.push(m);
        }
        &self.log
    }

    pub async fn publish(&self, topic: &str, payload: impl Into<Vec<u8>>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, false, payload.into())
            .await
            .expect("queue publish");
    }
}

impl Drop for Client {
    fn drop(&mut self) {
        self.task.abort();
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
        let iface = ihex_tests::can::lease();
        let gateway = Gateway::start(addr, &iface, name);
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
