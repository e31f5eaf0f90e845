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

/// The positions (`hex`) an island description gives its static elements.
pub fn island_layout(desc: &IslandDesc) -> crate::config::web::Layout {
    desc.statics
        .iter()
        .filter_map(|s| s.hex.map(|(q, r)| (s.id, crate::config::web::Hex { q, r })))
        .collect()
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
    fn send(&self, frame: CanFrame) -> Result<(), String> {
        self.0.try_send(frame).map_err(|e| e.to_string())
    }
}

/// A running simulated island and its control client (subscribed, not yet running).
struct SimIsland {
    handle: IslandHandle,
    /// Taken when the gateway runs.
    control: Option<sim::Control>,
}

/// What the demo adds to a gateway, built in two steps before the gateway runs: [`Demo::prepare`]
/// (the island file read, the broker accepting) and [`Demo::start_island`] (the island booted, its
/// control client subscribed).
pub struct Demo {
    broker: Option<std::net::SocketAddr>,
    /// The island to simulate, and the file it came from.
    desc: Option<(IslandDesc, Option<PathBuf>)>,
    island: Option<SimIsland>,
}

impl Demo {
    /// Reads the island file and starts the embedded broker, whichever of the two `config` asks
    /// for: the start-up errors a person most often meets (a typo in the file, port 1883 taken)
    /// come before anything else has started or said anything.
    pub async fn prepare(config: &Config) -> Result<Demo, GatewayError> {
        let desc = match &config.can.link {
            Link::Simulated { island_file } => {
                Some((load_island(island_file.as_deref())?, island_file.clone()))
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
        Ok(Demo {
            broker,
            desc,
            island: None,
        })
    }

    /// Boots the simulated island, when there is one, and subscribes its control client; returns
    /// the gateway's CAN link to it.
    pub async fn start_island(&mut self, config: &Config) -> Result<Option<CanLink>, GatewayError> {
        let Some((desc, island_file)) = &self.desc else {
            return Ok(None);
        };
        let bus = MemBus::new();
        // Created before the island starts, so no boot frame is missed.
        let endpoint = bus.endpoint();
        endpoint.set_filters(&filter::gateway_filters());
        let handle =
            Island::start(desc, SimLink::Mem(bus)).map_err(|e| GatewayError::Sim(e.to_string()))?;
        info!(
            statics = desc.statics.len(),
            mobiles = desc.mobiles.len(),
            file = island_file
                .as_ref()
                .map_or("built-in".into(), |f| f.display().to_string()),
            "simulated island started"
        );
        let control = sim::Control::connect(config, handle.clone()).await?;
        self.island = Some(SimIsland {
            handle,
            control: Some(control),
        });
        Ok(Some(CanLink::frames("simulated island", MemLink(endpoint))))
    }

    /// Positions of static elements the island file gives, for the island view.
    pub fn layout(&self) -> crate::config::web::Layout {
        self.desc
            .as_ref()
            .map(|(desc, _)| island_layout(desc))
            .unwrap_or_default()
    }

    /// Starts the island's control client and prints the banner (embedded broker + island), with
    /// the island view's and the SiLA server's addresses when they run.
    pub fn spawn(
        &mut self,
        config: &Config,
        tasks: &mut JoinSet<()>,
        cancel: CancellationToken,
        view_url: Option<&str>,
        sila_url: Option<&str>,
    ) {
        let (Some(island), Some((desc, file))) = (&mut self.island, &self.desc) else {
            return;
        };
        if let Some(control) = island.control.take() {
            tasks.spawn(control.run(cancel));
        }
        if let Some(listen) = self.broker {
            let log = crate::log::current_file(&config.log, time::OffsetDateTime::now_utc());
            let host = listen.ip().to_string();
            let text = banner::banner(&banner::Banner {
                topics: &config.topics,
                host: &host,
                port: listen.port(),
                desc,
                file: file.as_deref(),
                view_url,
                sila_url,
                log: log.as_deref(),
            });
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::web::Hex;

    #[test]
    fn the_island_file_places_its_hexagons() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../examples/islands/bench.toml"
        );
        let layout = island_layout(&load_island(Some(Path::new(path))).unwrap());
        let id = |s: &str| s.parse::<ihex_proto::NodeId>().unwrap();
        // The flower: seven placed, the factory-fresh board left to the automatic arrangement.
        assert_eq!(layout.len(), 7);
        assert_eq!(layout[&id("100")], Hex { q: 0, r: 0 });
        assert_eq!(layout[&id("101")], Hex { q: 0, r: -1 });
        assert!(!layout.contains_key(&id("1f0")));
        // The built-in island places nothing.
        assert!(island_layout(&load_island(None).unwrap()).is_empty());
    }
}
