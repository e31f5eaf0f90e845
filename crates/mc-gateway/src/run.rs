//! The gateway as a program, in two steps (mini-redis' `main` + `server::run`):
//! [`Gateway::build`] makes and checks every resource — the CAN link (first socket open), the MQTT
//! options, and in the demo the embedded broker, the simulated island and its control client — and
//! [`Gateway::run`] only runs them: the CAN tasks, the MQTT task, and the core loop, one task that
//! owns the [`Bridge`], feeds it inputs and timeouts and carries out its outputs without waiting.
//! Every channel is bounded; one [`CancellationToken`] stops everything and a `JoinSet` awaits every
//! task.

use std::{sync::Arc, time::Instant};

use ihex_gateway_core::{Bridge, Publication};
use tokio::{sync::mpsc, task::JoinSet};
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};

use crate::{
    can::{CanInput, CanLink},
    config::{Config, Link},
    error::GatewayError,
    mqtt::{self, MqttInput, MqttStats, MqttTask, Outbound},
    topic::Topics,
};

/// Frames from the CAN tasks waiting for the core.
const CAN_INPUTS: usize = 1024;
/// Messages from the MQTT task waiting for the core.
const MQTT_INPUTS: usize = 256;
/// Publications from the core waiting for the MQTT task.
const PUBLICATIONS: usize = 1024;

/// Runs the gateway until `shutdown` is cancelled (then stops every task, publishes `offline` and
/// returns `Ok`), or until a task fails.
pub async fn run(config: Config, shutdown: CancellationToken) -> Result<(), GatewayError> {
    run_with_stats(config, shutdown, Arc::default()).await
}

/// [`run`], counting MQTT traffic in `stats` (tests and benchmarks read them).
pub async fn run_with_stats(
    config: Config,
    shutdown: CancellationToken,
    stats: Arc<MqttStats>,
) -> Result<(), GatewayError> {
    Gateway::build(config, stats).await?.run(shutdown).await
}

/// A gateway whose resources are built and checked, ready to run.
pub struct Gateway {
    config: Config,
    link: CanLink,
    mqtt: MqttTask,
    #[cfg(feature = "demo")]
    demo: crate::demo::Demo,
}

impl Gateway {
    /// Builds every resource `config` asks for; fails on anything that would stop the gateway later
    /// (a bad island file, a taken broker port, CAN filters the kernel refuses, TLS unavailable).
    pub async fn build(config: Config, stats: Arc<MqttStats>) -> Result<Gateway, GatewayError> {
        for w in &config.warnings {
            warn!("{w}");
        }
        if config.can.bitrate != ihex_proto::BITRATE {
            warn!(
                configured = config.can.bitrate,
                island = ihex_proto::BITRATE,
                "bitrate differs from the island's; the interface's own configuration decides"
            );
        }
        #[cfg(feature = "demo")]
        let (demo, island_link) = crate::demo::Demo::build(&config).await?;
        #[cfg(not(feature = "demo"))]
        let island_link: Option<CanLink> = match config.mqtt.broker {
            crate::config::Broker::Embedded { .. } => return Err(GatewayError::DemoUnavailable),
            crate::config::Broker::External { .. } => None,
        };
        let link = match (&config.can.link, island_link) {
            (Link::SocketCan(iface), _) => CanLink::socketcan(iface, config.can.rx_buffer)?,
            (Link::Simulated { .. }, Some(link)) => link,
            (Link::Simulated { .. }, None) => return Err(GatewayError::DemoUnavailable),
        };
        let max_incoming = config
            .bridge
            .max_command_bytes
            .saturating_mul(4)
            .max(1 << 20);
        let mqtt = MqttTask {
            options: mqtt::options(&config.mqtt, &config.topics, max_incoming)?,
            topics: config.topics.clone(),
            queue: config.mqtt.queue,
            stats,
        };
        Ok(Gateway {
            config,
            link,
            mqtt,
            #[cfg(feature = "demo")]
            demo,
        })
    }

    /// Runs until `shutdown` is cancelled (then stops every task, publishes `offline` and returns
    /// `Ok`), or until a task fails.
    pub async fn run(self, shutdown: CancellationToken) -> Result<(), GatewayError> {
        #[cfg(feature = "demo")]
        let Gateway {
            config,
            link,
            mqtt,
            mut demo,
        } = self;
        #[cfg(not(feature = "demo"))]
        let Gateway { config, link, mqtt } = self;
        let cancel = shutdown.child_token();
        let mut tasks = JoinSet::new();
        let (can_in_tx, can_in) = mpsc::channel(CAN_INPUTS);
        let (mqtt_in_tx, mqtt_in) = mpsc::channel(MQTT_INPUTS);
        let (pub_tx, pub_rx) = mpsc::channel(PUBLICATIONS);

        let can_tx = link.spawn(config.can.tx_queue, can_in_tx, &mut tasks, cancel.clone());
        tasks.spawn(mqtt.run(pub_rx, mqtt_in_tx, cancel.clone()));
        #[cfg(feature = "demo")]
        demo.spawn(&config, &mut tasks, cancel.clone());
        info!(
            island = config.island.as_deref().unwrap_or("none"),
            broker = %config.mqtt.broker,
            link = %config.can.link,
            commands = %config.topics.commands,
            events = %config.topics.events,
            "gateway running"
        );

        let core = Core {
            bridge: Bridge::new(config.bridge.clone(), Instant::now()),
            can_tx,
            pub_tx,
            topics: config.topics.clone(),
            dropped: 0,
            fw_dir: config.settings.fw_dir.clone(),
        };
        let result = core.run(can_in, mqtt_in, &mut tasks, &cancel).await;

        cancel.cancel();
        let mut failure = result.err();
        while let Some(r) = tasks.join_next().await {
            if let Err(e) = r {
                error!(error = %e, "gateway task failed");
                failure.get_or_insert(GatewayError::Task(e.to_string()));
            }
        }
        #[cfg(feature = "demo")]
        demo.shutdown().await;
        info!("gateway stopped");
        failure.map_or(Ok(()), Err)
    }
}

/// The task that owns the bridge.
struct Core {
    bridge: Bridge,
    can_tx: mpsc::Sender<ihex_proto::Packet>,
    pub_tx: mpsc::Sender<Outbound>,
    topics: Topics,
    dropped: u64,
    /// `--fw-dir`: where `fw_update` images are read from.
    fw_dir: Option<std::path::PathBuf>,
}

impl Core {
    async fn run(
        mut self,
        mut can_in: mpsc::Receiver<CanInput>,
        mut mqtt_in: mpsc::Receiver<MqttInput>,
        tasks: &mut JoinSet<()>,
        cancel: &CancellationToken,
    ) -> Result<(), GatewayError> {
        loop {
            self.carry_out();
            let deadline = tokio::time::Instant::from_std(self.bridge.poll_timeout());
            // Unbiased on purpose: a timer that is always due must not starve the inputs, nor a
            // flood of frames the timers.
            tokio::select! {
                _ = cancel.cancelled() => {
                    if self.bridge.fw_update_running() {
                        // Best effort: the aborts and the report go out if the tasks still run.
                        self.bridge.cancel_fw_update("the gateway stopped", Instant::now());
                        self.carry_out();
                    }
                    return Ok(());
                }
                r = tasks.join_next() => {
                    if cancel.is_cancelled() {
                        // Tasks end on cancellation; the caller joins the rest.
                        return Ok(());
                    }
                    // No task ends on its own while the gateway runs.
                    let why = match r {
                        Some(Err(e)) => e.to_string(),
                        _ => "a gateway task ended early".to_owned(),
                    };
                    error!(%why, "stopping the gateway");
                    return Err(GatewayError::Task(why));
                }
                _ = tokio::time::sleep_until(deadline) => self.bridge.handle_timeout(Instant::now()),
                Some(input) = can_in.recv() => {
                    let now = Instant::now();
                    match input {
                        CanInput::Packet(p) => self.bridge.handle_packet(p, now),
                        CanInput::Undecodable { raw_id, data, err } => self.bridge.handle_undecodable(raw_id, &data, err, now),
                        CanInput::Bus(ev) => self.bridge.handle_bus_event(ev, now),
                        CanInput::SendFailed(p, reason) => self.bridge.handle_send_failed(p, &reason, now),
                    }
                }
                Some(input) = mqtt_in.recv() => match input {
                    MqttInput::Command(payload) => self.bridge.handle_command(&payload, Instant::now()),
                    MqttInput::Connected => self.bridge.handle_mqtt_connected(Instant::now()),
                },
            }
        }
    }

    /// Drains the bridge's outputs without ever waiting: a full CAN queue is a failed send the bridge
    /// hears about, a full publication queue a counted drop.
    fn carry_out(&mut self) {
        while let Some(load) = self.bridge.poll_fw_load() {
            let bytes = crate::fw::read_image(self.fw_dir.as_deref(), &load.image);
            self.bridge.handle_fw_image(load, bytes, Instant::now());
        }
        loop {
            while let Some(packet) = self.bridge.poll_transmit() {
                let reason = match self.can_tx.try_send(packet) {
                    Ok(()) => continue,
                    Err(mpsc::error::TrySendError::Full(_)) => "CAN transmit queue full",
                    Err(mpsc::error::TrySendError::Closed(_)) => "CAN transmitter stopped",
                };
                self.bridge
                    .handle_send_failed(packet, reason, Instant::now());
            }
            let Some(publication) = self.bridge.poll_publication() else {
                return;
            };
            self.publish(publication);
        }
    }

    /// The one place publications leave the core: serialised once, logged (every event at info, so
    /// the log alone tells the island's story), handed to the MQTT task.
    fn publish(&mut self, publication: Publication) {
        let json = publication.to_json();
        match &publication {
            Publication::Event(e) => info!(event = e.name(), payload = %json, "event published"),
            Publication::State(s) => debug!(node = %s.id, payload = %json, "state published"),
        }
        let p = Outbound {
            topic: self.topics.resolve(publication.topic()),
            payload: json.into_bytes(),
            retain: publication.retain(),
        };
        if self.pub_tx.try_send(p).is_err() {
            self.dropped += 1;
            if self.dropped.is_power_of_two() {
                warn!(
                    dropped_total = self.dropped,
                    "publication queue full: event dropped"
                );
            }
        }
    }
}
