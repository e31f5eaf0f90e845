//! Home Assistant's topic names and identifiers for one island: the discovery topics (under the
//! discovery prefix, outside the island prefix, because Home Assistant listens there), the command
//! and light state topics (under the island prefix like every other topic of the gateway), and the
//! device identifiers, `unique_id`s and entity ids — each of which includes the island name, so two
//! islands with the same node IDs on one broker give two distinct sets of devices.

use std::fmt::Write as _;

use ihex_proto::NodeId;

/// Default discovery prefix (Home Assistant's).
pub const DISCOVERY_PREFIX: &str = "homeassistant";
/// Default topic of Home Assistant's birth message (`online` when it starts).
pub const STATUS: &str = "homeassistant/status";
/// Root of the gateway's own Home Assistant topics, under the island prefix.
pub const ROOT: &str = "ihex/ha";

/// An element's entity that takes commands, as it appears in its command topic
/// (`<root>/<id>/<entity>/set`).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum Entity {
    /// The LED strip (`light`).
    Led,
    /// The relay (`switch`, static elements).
    Relay,
    /// The buzzer (`siren`).
    Buzzer,
    /// Identify (`button`).
    Identify,
}

impl Entity {
    /// Every entity that takes commands.
    pub const ALL: [Entity; 4] = [Entity::Led, Entity::Relay, Entity::Buzzer, Entity::Identify];

    /// The name in topics, component ids and `unique_id`s.
    pub fn name(self) -> &'static str {
        match self {
            Entity::Led => "led",
            Entity::Relay => "relay",
            Entity::Buzzer => "buzzer",
            Entity::Identify => "identify",
        }
    }
}

/// Home Assistant topics the core publishes on, by role; [`HaTopics::resolve`] names them.
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum HaTopic {
    /// The gateway's own device discovery config.
    GatewayConfig,
    /// An element's device discovery config.
    DeviceConfig(NodeId),
    /// An element's light state in Home Assistant's JSON schema.
    LightState(NodeId),
}

/// The concrete Home Assistant topics and identifiers of one gateway.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct HaTopics {
    /// Discovery prefix (`homeassistant`).
    pub discovery_prefix: String,
    /// Home Assistant's status topic (its birth message: `online`).
    pub status: String,
    /// Root of the command and light state topics, with the island prefix (`lab1/ihex/ha`).
    pub root: String,
    /// Identifier of the island's devices: `ihex`, or `ihex_` and the island name as given.
    device_id: String,
    /// The same as it may appear in a discovery topic level: characters other than ASCII letters,
    /// digits and `-` escaped as `_` and two hex digits per byte (so distinct islands stay distinct).
    object_id: String,
}

impl HaTopics {
    /// The names for `island` (validated, or `None`), with these Home Assistant topics.
    pub fn new(island: Option<&str>, discovery_prefix: &str, status: &str) -> HaTopics {
        let (device_id, object_id, root) = match island {
            Some(name) => (
                format!("ihex_{name}"),
                format!("ihex_{}", escape(name)),
                format!("{name}/{ROOT}"),
            ),
            None => ("ihex".to_owned(), "ihex".to_owned(), ROOT.to_owned()),
        };
        HaTopics {
            discovery_prefix: discovery_prefix.to_owned(),
            status: status.to_owned(),
            root,
            device_id,
            object_id,
        }
    }

    /// Home Assistant's defaults for `island`.
    pub fn defaults(island: Option<&str>) -> HaTopics {
        HaTopics::new(island, DISCOVERY_PREFIX, STATUS)
    }

    /// The concrete topic of `topic`.
    pub fn resolve(&self, topic: HaTopic) -> String {
        match topic {
            HaTopic::GatewayConfig => self.config_topic("gateway"),
            HaTopic::DeviceConfig(id) => self.config_topic(&id.to_string()),
            HaTopic::LightState(id) => crate::topic::node_topic(&self.root, id, Entity::Led.name()),
        }
    }

    fn config_topic(&self, device: &str) -> String {
        format!(
            "{}/device/{}_{device}/config",
            self.discovery_prefix, self.object_id
        )
    }

    /// The command topic of one entity of one element.
    pub fn command(&self, id: NodeId, entity: Entity) -> String {
        format!("{}/{id}/{}/set", self.root, entity.name())
    }

    /// The filter that subscribes every command topic.
    pub fn command_filter(&self) -> String {
        format!("{}/+/+/set", self.root)
    }

    /// The node and entity of a command topic, as written in it (`None`: not a command topic of
    /// this gateway).
    pub fn parse_command<'t>(&self, topic: &'t str) -> Option<(&'t str, &'t str)> {
        let rest = topic.strip_prefix(self.root.as_str())?.strip_prefix('/')?;
        let rest = rest.strip_suffix("/set")?;
        let (node, entity) = rest.split_once('/')?;
        (!entity.contains('/')).then_some((node, entity))
    }

    /// The device identifier of the gateway.
    pub fn gateway_device(&self) -> String {
        format!("{}_gateway", self.device_id)
    }

    /// The device identifier of an element.
    pub fn device(&self, id: NodeId) -> String {
        format!("{}_{id}", self.device_id)
    }

    /// The `unique_id` of an element's component (`component`: `led`, `relay`, …, or `gateway`'s
    /// own `connection`).
    pub fn unique_id(&self, device: &str, component: &str) -> String {
        format!("{device}_{component}")
    }

    /// The `default_entity_id` of an element's component: `<platform>.<slug>_<id>_<component>`.
    pub fn entity_id(&self, platform: &str, device: &str, component: &str) -> String {
        format!("{platform}.{}_{component}", slug(device))
    }
}

/// `name` as a discovery topic level allows it (`[a-zA-Z0-9_-]`), one to one: ASCII letters,
/// digits and `-` stay, every other byte becomes `_` and two lower-case hex digits.
fn escape(name: &str) -> String {
    let mut out = String::with_capacity(name.len());
    for b in name.bytes() {
        if b.is_ascii_alphanumeric() || b == b'-' {
            out.push(char::from(b));
        } else {
            // Writing to a String cannot fail.
            let _ = write!(out, "_{b:02x}");
        }
    }
    out
}

/// `text` as Home Assistant writes an object id: lower-case ASCII letters and digits, anything
/// else `_`.
fn slug(text: &str) -> String {
    text.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '_'
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_proto::test_util::id;

    #[test]
    fn names_without_island() {
        let t = HaTopics::defaults(None);
        assert_eq!(
            t.resolve(HaTopic::DeviceConfig(id(0x111))),
            "homeassistant/device/ihex_111/config"
        );
        assert_eq!(
            t.resolve(HaTopic::GatewayConfig),
            "homeassistant/device/ihex_gateway/config"
        );
        assert_eq!(t.resolve(HaTopic::LightState(id(2))), "ihex/ha/2/led");
        assert_eq!(t.resolve(HaTopic::LightState(id(0x7f0))), "ihex/ha/7f0/led");
        assert_eq!(t.command(id(2), Entity::Relay), "ihex/ha/2/relay/set");
        assert_eq!(t.command_filter(), "ihex/ha/+/+/set");
        assert_eq!(t.device(id(2)), "ihex_2");
        assert_eq!(t.unique_id(&t.device(id(2)), "led"), "ihex_2_led");
        assert_eq!(
            t.entity_id("light", &t.device(id(0xabc)), "led"),
            "light.ihex_abc_led"
        );
    }

    #[test]
    fn names_with_island() {
        let t = HaTopics::new(Some("Lab/B_2"), "ha", "ha/status");
        assert_eq!(
            t.resolve(HaTopic::DeviceConfig(id(0x111))),
            "ha/device/ihex_Lab_2fB_5f2_111/config"
        );
        assert_eq!(t.command(id(2), Entity::Led), "Lab/B_2/ihex/ha/2/led/set");
        assert_eq!(t.device(id(2)), "ihex_Lab/B_2_2");
        assert_eq!(
            t.entity_id("switch", &t.device(id(2)), "relay"),
            "switch.ihex_lab_b_2_2_relay"
        );
        assert_eq!(
            t.entity_id("binary_sensor", &t.gateway_device(), "connection"),
            "binary_sensor.ihex_lab_b_2_gateway_connection"
        );
    }

    #[test]
    fn discovery_topic_levels_are_what_home_assistant_accepts_and_one_to_one() {
        let names = ["a/b", "a_2fb", "a_b", "a-b", "Ü", "lab 1", "x+y"];
        let mut seen = std::collections::BTreeSet::new();
        for name in names {
            let t = HaTopics::defaults(Some(name));
            let topic = t.resolve(HaTopic::DeviceConfig(id(1)));
            let level = topic
                .strip_prefix("homeassistant/device/")
                .and_then(|l| l.strip_suffix("/config"))
                .unwrap();
            assert!(
                level
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-'),
                "{level}"
            );
            assert!(seen.insert(level.to_owned()), "{name} collides");
        }
    }

    #[test]
    fn command_topics_parse_back() {
        let t = HaTopics::defaults(Some("lab1"));
        for e in Entity::ALL {
            let topic = t.command(id(0x111), e);
            assert_eq!(t.parse_command(&topic), Some(("111", e.name())));
        }
        for other in [
            "lab1/ihex/ha/111/led",
            "lab1/ihex/ha/111/led/extra/set",
            "lab2/ihex/ha/111/led/set",
            "lab1/ihex/ha/set",
            "lab1/ihex/hax/1/led/set",
        ] {
            assert_eq!(t.parse_command(other), None, "{other}");
        }
    }
}
