//! Home Assistant MQTT discovery, sans-IO: one Home Assistant device per element (the gateway as
//! its parent), whose entities read the topics the gateway already publishes and whose commands
//! take the JSON API's path. Nothing here changes the existing topic tree: discovery configs go
//! under Home Assistant's discovery prefix, and the only topics added are the command topics and
//! the light's state, under the island prefix.
//!
//! The bridge calls [`Ha`] when a state document is published (configs and the light state follow
//! it, each only when it changed), on every MQTT (re)connection and on Home Assistant's birth
//! message (every config again), and when a node is forgotten (its device and light state are
//! emptied). [`discovery`] builds the configs, [`light`] the light state, [`command`] turns a
//! message on a command topic into a [`crate::command::Command`], [`topic`] names everything;
//! [`schema`] holds the keys Home Assistant accepts, to check the configs against.

pub mod command;
pub mod discovery;
mod glue;
pub mod light;
pub mod schema;
pub mod topic;

use std::collections::BTreeMap;

use ihex_proto::{LedCommand, NodeId};

use crate::command::{Rejection, Request};
use crate::event::{to_json, NodeState};
use crate::registry::NodeEntry;
use crate::topic::Topics;
pub use light::LightState;
pub use topic::{Entity, HaTopic, HaTopics};

/// What the discovery configs need to know besides the nodes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct HaConfig {
    /// The gateway's topics; the Home Assistant ones are [`Topics::ha`].
    pub topics: Topics,
    /// The island's name, when it has one (device names).
    pub island: Option<String>,
    /// The page every device links to in Home Assistant ("Visit"): the gateway's web page.
    pub configuration_url: Option<String>,
    /// The publishing program's version (`origin.sw_version`, the gateway device's `sw_version`).
    pub sw_version: String,
}

/// A Home Assistant message, as a Rust value; the adapter serialises it once.
#[derive(Clone, PartialEq, Debug)]
pub enum HaPublication {
    /// A device's discovery config (retained).
    Config {
        /// The gateway's config or an element's.
        topic: HaTopic,
        /// The config's compact JSON, serialised when it is built: a config waiting to be published
        /// is 3 KB of text, not a tree of values many times that size.
        config: String,
    },
    /// An element's light state (retained).
    Light {
        /// The element.
        node: NodeId,
        /// Its state.
        state: LightState,
    },
}

impl HaPublication {
    /// A discovery config, serialised here, once: it waits for publication as its text.
    fn config(topic: HaTopic, config: &serde_json::Value) -> HaPublication {
        HaPublication::Config {
            topic,
            config: to_json(config),
        }
    }

    /// Where it goes.
    pub fn topic(&self) -> HaTopic {
        match self {
            HaPublication::Config { topic, .. } => *topic,
            HaPublication::Light { node, .. } => HaTopic::LightState(*node),
        }
    }

    /// Appends the compact JSON that is published to `out`.
    pub fn write_payload(&self, out: &mut bytes::BytesMut) {
        match self {
            HaPublication::Config { config, .. } => out.extend_from_slice(config.as_bytes()),
            HaPublication::Light { state, .. } => crate::json_writer::write_light_state(state, out),
        }
    }
}

/// Discovery state: what was last published for each element, so a config or light state goes out
/// again only when it changed (or when everything must be republished).
#[derive(Debug)]
pub struct Ha {
    config: HaConfig,
    /// What each element's published config was built from.
    configs: BTreeMap<NodeId, discovery::Element>,
    lights: BTreeMap<NodeId, LightState>,
}

impl Ha {
    /// Nothing published yet.
    pub fn new(config: HaConfig) -> Ha {
        Ha {
            config,
            configs: BTreeMap::new(),
            lights: BTreeMap::new(),
        }
    }

    /// The configuration in use.
    pub fn config(&self) -> &HaConfig {
        &self.config
    }

    /// The gateway device's config.
    pub fn gateway(&self) -> HaPublication {
        HaPublication::config(HaTopic::GatewayConfig, &discovery::gateway(&self.config))
    }

    /// An element's state document `doc` was published: its config and light state, each when it
    /// changed or when `force`.
    pub fn on_state(
        &mut self,
        doc: &NodeState,
        entry: &NodeEntry,
        force: bool,
    ) -> Vec<HaPublication> {
        let id = doc.id.0;
        let mut out = Vec::new();
        let shown = self.configs.get(&id);
        if force || !shown.is_some_and(|e| e.shows(doc, entry.uid)) {
            let element = discovery::Element::of(doc, entry.uid);
            out.push(HaPublication::config(
                HaTopic::DeviceConfig(id),
                &discovery::element(&self.config, &element),
            ));
            self.configs.insert(id, element);
        }
        let light = LightState::from_led(entry.led);
        if force || self.lights.get(&id) != Some(&light) {
            self.lights.insert(id, light.clone());
            out.push(HaPublication::Light {
                node: id,
                state: light,
            });
        }
        out
    }

    /// Every config again (Home Assistant started and announced itself): the gateway's first.
    pub fn configs(&self) -> Vec<HaPublication> {
        let mut out = vec![self.gateway()];
        out.extend(self.configs.iter().map(|(&id, element)| {
            HaPublication::config(
                HaTopic::DeviceConfig(id),
                &discovery::element(&self.config, element),
            )
        }));
        out
    }

    /// `id` was forgotten: the retained topics to empty — its device config first (Home Assistant
    /// removes the device), then its light state.
    pub fn on_forgotten(&mut self, id: NodeId) -> [HaTopic; 2] {
        self.configs.remove(&id);
        self.lights.remove(&id);
        [HaTopic::DeviceConfig(id), HaTopic::LightState(id)]
    }

    /// A message on a command topic, as the command it stands for; `led_of` tells the LED command
    /// a node last acknowledged.
    pub fn parse_command(
        &self,
        topic: &str,
        payload: &[u8],
        max_bytes: usize,
        led_of: impl Fn(NodeId) -> Option<LedCommand>,
    ) -> Result<Request, Rejection> {
        command::parse(&self.config.topics.ha, topic, payload, max_bytes, led_of)
    }
}
