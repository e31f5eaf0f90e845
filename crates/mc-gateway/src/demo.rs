//! The embedded demo's island: the `sim-node` library running a described island on an in-memory bus,
//! its control messages (dock, undock, power cycle, bus on/off) received on the `ihex/sim` topic, and
//! the start-up banner that tells a newcomer what to type.

use std::{path::Path, time::Duration};

use ihex_proto::NodeId;
use serde::Deserialize;
use sim_node::{bus::MemBus, desc::parse_node_id, link::Link, Island, IslandDesc, IslandHandle};
use tracing::{info, warn};

use crate::{config::Config, error::GatewayError};

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

/// A running simulated island and the gateway's endpoint on its bus.
pub struct SimIsland {
    /// Controls the island.
    pub handle: IslandHandle,
    /// The gateway's endpoint (created before the island starts, so no boot frame is missed).
    pub endpoint: sim_node::bus::MemEndpoint,
}

/// Loads the description (file or [`BUILTIN_ISLAND`]) and starts the island on a new in-memory bus.
pub fn start(island_file: Option<&Path>) -> Result<SimIsland, GatewayError> {
    let desc = match island_file {
        Some(p) => IslandDesc::load(p).map_err(|e| GatewayError::Sim(e.to_string()))?,
        None => IslandDesc::parse(BUILTIN_ISLAND).map_err(|e| GatewayError::Sim(e.to_string()))?,
    };
    let bus = MemBus::new();
    let endpoint = bus.endpoint();
    let handle =
        Island::start(&desc, Link::Mem(bus)).map_err(|e| GatewayError::Sim(e.to_string()))?;
    info!(
        statics = desc.statics.len(),
        mobiles = desc.mobiles.len(),
        "simulated island started"
    );
    Ok(SimIsland { handle, endpoint })
}

/// A control message on the simulation topic.
#[derive(Deserialize, Debug, PartialEq, Eq)]
#[serde(tag = "sim", rename_all = "snake_case")]
pub enum SimCommand {
    /// Dock a mobile element on a static element's port.
    Dock {
        /// Mobile element id (hex).
        mobile: String,
        /// Static element id (hex).
        #[serde(rename = "static")]
        static_id: String,
        /// Dock port of the static element.
        port: u8,
    },
    /// Undock a mobile element.
    Undock {
        /// Mobile element id.
        mobile: String,
    },
    /// Remove and restore an element's power.
    PowerCycle {
        /// Element id.
        node: String,
    },
    /// Disconnect an element from the bus (it keeps running).
    OffBus {
        /// Element id.
        node: String,
    },
    /// Reconnect an element to the bus.
    OnBus {
        /// Element id.
        node: String,
    },
}

fn id(s: &str) -> Result<NodeId, String> {
    parse_node_id(s)
}

/// Carries out one control message; errors are logged (the demo has no one to answer).
pub async fn handle(island: &IslandHandle, payload: &[u8]) {
    let cmd: SimCommand = match serde_json::from_slice(payload) {
        Ok(c) => c,
        Err(e) => {
            warn!(error = %e, "bad simulation command (see docs/gateway.md)");
            return;
        }
    };
    let result = async {
        match &cmd {
            SimCommand::Dock {
                mobile,
                static_id,
                port,
            } => island
                .dock(id(mobile)?, id(static_id)?, *port)
                .await
                .map_err(|e| e.to_string()),
            SimCommand::Undock { mobile } => {
                island.undock(id(mobile)?).await.map_err(|e| e.to_string())
            }
            SimCommand::PowerCycle { node } => island
                .power_cycle(id(node)?)
                .await
                .map_err(|e| e.to_string()),
            SimCommand::OffBus { node } => island
                .set_on_bus(id(node)?, false)
                .await
                .map_err(|e| e.to_string()),
            SimCommand::OnBus { node } => island
                .set_on_bus(id(node)?, true)
                .await
                .map_err(|e| e.to_string()),
        }
    };
    match tokio::time::timeout(Duration::from_secs(2), result).await {
        Ok(Ok(())) => info!(?cmd, "simulation command done"),
        Ok(Err(e)) => warn!(?cmd, error = %e, "simulation command refused"),
        Err(_) => warn!(?cmd, "simulation command timed out"),
    }
}

/// The copy-paste instructions printed when the demo starts.
pub fn banner(config: &Config, host: &str, port: u16) -> String {
    let t = &config.topics;
    let b = format!("-h {host} -p {port}");
    format!(
        "\n\
iHEX gateway demo: embedded MQTT broker on {host}:{port}, simulated island (static 111, 112; mobile 2
docked on 111 port 3, mobile 3 free).

Watch every event:
  mosquitto_sub {b} -t '{events}' -v
Watch the retained node states and the gateway's availability:
  mosquitto_sub {b} -t '{nodes}/+/state' -t '{avail}' -v
Turn node 111's LEDs red:
  mosquitto_pub {b} -q 1 -t '{cmds}' -m '{{\"cmd\":\"led\",\"node\":\"111\",\"color\":\"red\"}}'
List the nodes:
  mosquitto_pub {b} -q 1 -t '{cmds}' -m '{{\"cmd\":\"list\"}}'
Dock mobile 3 on port 2 of 112 (publishes new_connection), then undock it (connection_removed):
  mosquitto_pub {b} -t '{sim}' -m '{{\"sim\":\"dock\",\"mobile\":\"3\",\"static\":\"112\",\"port\":2}}'
  mosquitto_pub {b} -t '{sim}' -m '{{\"sim\":\"undock\",\"mobile\":\"3\"}}'
Take 112 off the bus (node_lost after a few health checks) and back (node_online):
  mosquitto_pub {b} -t '{sim}' -m '{{\"sim\":\"off_bus\",\"node\":\"112\"}}'
  mosquitto_pub {b} -t '{sim}' -m '{{\"sim\":\"on_bus\",\"node\":\"112\"}}'
Ctrl-C stops the gateway. Commands: docs/mqtt-api.md; options: mc-gateway --help, docs/gateway.md.
",
        events = t.events,
        nodes = t.node_state_root,
        avail = t.availability,
        cmds = t.commands,
        sim = t.sim,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_builtin_island_parses() {
        let d = IslandDesc::parse(BUILTIN_ISLAND).unwrap();
        assert_eq!((d.statics.len(), d.mobiles.len()), (2, 2));
    }

    #[test]
    fn simulation_commands_parse() {
        let c: SimCommand =
            serde_json::from_str(r#"{"sim":"dock","mobile":"3","static":"112","port":2}"#).unwrap();
        assert_eq!(
            c,
            SimCommand::Dock {
                mobile: "3".into(),
                static_id: "112".into(),
                port: 2
            }
        );
        let c: SimCommand = serde_json::from_str(r#"{"sim":"off_bus","node":"112"}"#).unwrap();
        assert_eq!(c, SimCommand::OffBus { node: "112".into() });
        assert!(serde_json::from_str::<SimCommand>(r#"{"sim":"explode"}"#).is_err());
    }

    #[test]
    fn the_banner_uses_the_configured_topics() {
        let mut cfg =
            crate::config::Config::resolve(Default::default(), Default::default()).unwrap();
        cfg.topics =
            crate::topic::Topics::new(Some("lab"), "CommandsTopic", "EventsTopic", "a", "n");
        let text = banner(&cfg, "127.0.0.1", 1884);
        assert!(text.contains("mosquitto_pub -h 127.0.0.1 -p 1884 -q 1 -t 'lab/CommandsTopic'"));
        assert!(text.contains("mosquitto_sub -h 127.0.0.1 -p 1884 -t 'lab/EventsTopic' -v"));
        assert!(text.contains("-t 'lab/ihex/sim'"));
    }
}
