//! The demo (cargo feature `demo`, on by default): the embedded MQTT broker ([`broker`]), the
//! simulated island (the `sim-node` library on an in-memory bus, plugged into the shell's CAN tasks
//! as a [`FrameLink`]), its control client on the `ihex/sim` topic ([`sim`]) and the start-up
//! [`banner`]. None of it is linked into a build with `--no-default-features` (the Pi's).
//!
//! The simulator never blocks the gateway: it runs on its own tasks, and its control messages come
//! through its own MQTT client, not through the gateway's core.

pub mod banner;
pub mod broker;
pub mod sim;

use std::path::{Path, PathBuf};

use ihex_proto::filter;
use sim_node::{
    bus::{MemBus, MemEndpoint, MemSender},
    link::Link as SimLink,
    Island, IslandDesc, IslandHandle,
};
use socketcan::CanFrame;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use tracing::info;

use crate::{
    can::{CanLink, FrameLink, FrameSender},
    config::{Broker, Config, Link},
    error::GatewayError,
};

/// The island the demo runs when no `--island-file` is given: two static elements, a mobile element
/// docked on `111` port 3 and one waiting to be docked.
pub const BUILTIN_ISLAND: &str = r#"
[[static]]
id = "111"
ports = 6

[[static]]
id = "112"
ports = 6

[[mobile]]
id = "2"
port = 0
dock = { static = "111", port = 3 }

[[mobile]]
id = "3"
port = 1
"#;

/// Loads an island description: the file, or [`BUILTIN_ISLAND`].
pub fn load_island(island_file: Option<&Path>) -> Result<IslandDesc, GatewayError> {
    let desc = match island_file {
        Some(p) => IslandDesc::load(p),
        None => IslandDesc::parse(BUILTIN_ISLAND),
    };
    desc.map_err(|e| GatewayError::Sim(e.to_string()))
}

/// The gateway's endpoint on the simulated island's in-memory bus.
struct MemLink(MemEndpoint);

/// Transmit half of [`MemLink`].
struct MemLinkSender(MemSender);

impl FrameLink for MemLink {
    type Sender = MemLinkSender;

    fn sender(&self) -> MemLinkSender {
        MemLinkSender(self.0.sender())
    }

    async fn recv(&mut self) -> Option<CanFrame> {
        self.0.recv().await
    }
}

impl FrameSender for MemLinkSender {
    async fn send(&self, frame: CanFrame) -> Result<(), String> {
        self.0.send(frame).await.map_err(|e| e.to_string())
    }
}

/// A running simulated island and its control client (subscribed, not yet running).
struct SimIsland {
    handle: IslandHandle,
    desc: IslandDesc,
    file: Option<PathBuf>,
    /// Taken when the gateway runs.
    control: Option<sim::Control>,
}

/// What the demo adds to a gateway: built (broker accepting, island running, control client
/// subscribed) before the gateway runs.
pub struct Demo {
    broker: Option<std::net::SocketAddr>,
    island: Option<SimIsland>,
}

impl Demo {
    /// Builds the parts `config` asks for; the CAN link is returned when the island is simulated.
    /// The island file is checked before the broker starts, so a typo fails fast.
    pub async fn build(config: &Config) -> Result<(Demo, Option<CanLink>), GatewayError> {
        let island = match &config.can.link {
            Link::Simulated { island_file } => {
                let desc = load_island(island_file.as_deref())?;
                let bus = MemBus::new();
                // Created before the island starts, so no boot frame is missed.
                let endpoint = bus.endpoint();
                endpoint.set_filters(&filter::gateway_filters());
                let handle = Island::start(&desc, SimLink::Mem(bus))
                    .map_err(|e| GatewayError::Sim(e.to_string()))?;
                info!(
                    statics = desc.statics.len(),
                    mobiles = desc.mobiles.len(),
                    file = island_file
                        .as_ref()
                        .map_or("built-in".into(), |f| f.display().to_string()),
                    "simulated island started"
                );
                Some((desc, handle, endpoint, island_file.clone()))
            }
            Link::SocketCan(_) => None,
        };
        let broker = match &config.mqtt.broker {
            Broker::Embedded { listen } => {
                let listen = *listen;
                tokio::task::spawn_blocking(move || broker::start(listen))
                    .await
                    .map_err(|e| GatewayError::Task(e.to_string()))??;
                info!(%listen, "embedded MQTT broker ready");
                Some(listen)
            }
            Broker::External { .. } => None,
        };
        let (island, link) = match island {
            Some((desc, handle, endpoint, file)) => {
                let control = sim::Control::connect(config, handle.clone()).await?;
                let island = SimIsland {
                    handle,
                    desc,
                    file,
                    control: Some(control),
                };
                (
                    Some(island),
                    Some(CanLink::frames("simulated island", MemLink(endpoint))),
                )
            }
            None => (None, None),
        };
        Ok((Demo { broker, island }, link))
    }

    /// Starts the island's control client and prints the banner (embedded broker + island).
    pub fn spawn(&mut self, config: &Config, tasks: &mut JoinSet<()>, cancel: CancellationToken) {
        let Some(island) = &mut self.island else {
            return;
        };
        if let Some(control) = island.control.take() {
            tasks.spawn(control.run(cancel));
        }
        if let Some(listen) = self.broker {
            let text = banner::banner(
                &config.topics,
                &listen.ip().to_string(),
                listen.port(),
                &island.desc,
                island.file.as_deref(),
            );
            println!("{text}");
        }
    }

    /// Stops the simulated island.
    pub async fn shutdown(self) {
        if let Some(island) = self.island {
            island.handle.shutdown().await;
        }
    }
}
