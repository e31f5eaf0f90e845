//! MQTT topic names: the seed's defaults, the island prefix, and the mapping of the bridge's logical
//! [`Topic`]s to concrete names (the Home Assistant ones through [`HaTopics`]).

use ihex_proto::NodeId;

use crate::ha::{HaTopic, HaTopics};

/// Logical MQTT topics; the adapter maps them to names under the island prefix
/// ([`Topics::resolve`]).
#[derive(Clone, Copy, PartialEq, Eq, Hash, Debug)]
pub enum Topic {
    /// `EventsTopic`: every JSON event.
    Events,
    /// The retained state document of one node.
    NodeState(NodeId),
    /// A Home Assistant topic (retained).
    Ha(HaTopic),
    /// The retained leases document of the island.
    Leases,
    /// The retained document of the procedures running on the island.
    Procedures,
}

/// Default command topic (the seed's name).
pub const COMMANDS: &str = "CommandsTopic";
/// Default event topic (the seed's name).
pub const EVENTS: &str = "EventsTopic";
/// Default availability topic (retained `online` / `offline`, the latter as the last will).
pub const AVAILABILITY: &str = "ihex/gateway/availability";
/// Default root of the retained per-node state topics: `<root>/<id>/state`.
pub const NODE_STATE_ROOT: &str = "ihex/node";
/// Topic of the simulated island's control commands (demo mode only).
pub const SIM: &str = "ihex/sim";
/// Default topic of the retained leases document (under the island prefix like every topic).
pub const LEASES: &str = "ihex/leases";
/// Default topic of the retained document of the procedures running now.
pub const PROCEDURES: &str = "ihex/procedures";
/// Root of the firmware upload topics `<root>/<name>`: signed images handed to the gateway.
pub const FW_UPLOAD: &str = "ihex/fw/upload";
/// Root of the per-user command topics `<root>/<user>`: a broker ACL (`pattern write
/// <island>/ihex/cmd/%u`) lets only `<user>` publish there, so the broker vouches for the sender.
pub const USER_COMMANDS: &str = "ihex/cmd";
/// Topic of the retained audit anchor: the head of the audit chain, published periodically.
pub const AUDIT_HEAD: &str = "ihex/audit/head";

/// The concrete topic names one gateway uses, every one already under the island prefix.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Topics {
    /// Subscribed: JSON commands.
    pub commands: String,
    /// Published: JSON events (QoS 1, not retained).
    pub events: String,
    /// Published retained: `online` / `offline`.
    pub availability: String,
    /// Root of `<root>/<id>/state` (retained).
    pub node_state_root: String,
    /// Subscribed in demo mode: simulated island control.
    pub sim: String,
    /// Root of the subscribed `<root>/<name>`: firmware images uploaded for `fw_update`.
    pub fw_upload: String,
    /// Published retained: the leases held now.
    pub leases: String,
    /// Published retained: the procedures running now.
    pub procedures: String,
    /// Root of the subscribed `<root>/<user>`: JSON commands from an authenticated user.
    pub user_commands: String,
    /// Published retained: the audit chain's head (`SEQ:SHA256`).
    pub audit_head: String,
    /// Home Assistant's topics (discovery, status) and the gateway's own for it; Home Assistant's
    /// defaults until [`Topics::with_ha`].
    pub ha: HaTopics,
}

impl Topics {
    /// Names from the configured bases; `island` (validated) prefixes every one of them as `NAME/`.
    pub fn new(
        island: Option<&str>,
        commands: &str,
        events: &str,
        availability: &str,
        node_state_root: &str,
    ) -> Topics {
        let p = |t: &str| match island {
            Some(name) => format!("{name}/{t}"),
            None => t.to_owned(),
        };
        Topics {
            commands: p(commands),
            events: p(events),
            availability: p(availability),
            node_state_root: p(node_state_root),
            sim: p(SIM),
            fw_upload: p(FW_UPLOAD),
            leases: p(LEASES),
            procedures: p(PROCEDURES),
            user_commands: p(USER_COMMANDS),
            audit_head: p(AUDIT_HEAD),
            ha: HaTopics::defaults(island),
        }
    }

    /// The same names with Home Assistant's discovery prefix and status topic as configured.
    pub fn with_ha(mut self, island: Option<&str>, discovery_prefix: &str, status: &str) -> Topics {
        self.ha = HaTopics::new(island, discovery_prefix, status);
        self
    }

    /// The seed's names without an island prefix.
    pub fn seed() -> Topics {
        Topics::seed_on(None)
    }

    /// The seed's names under `island`'s prefix.
    pub fn seed_on(island: Option<&str>) -> Topics {
        Topics::new(island, COMMANDS, EVENTS, AVAILABILITY, NODE_STATE_ROOT)
    }

    /// The retained state topic of one node (`<root>/<id>/state`, id in lower-case hex like events).
    pub fn node_state(&self, id: NodeId) -> String {
        node_topic(&self.node_state_root, id, "state")
    }

    /// The subscription of the upload topics (`<root>/+`).
    pub fn fw_upload_filter(&self) -> String {
        format!("{}/+", self.fw_upload)
    }

    /// The image name of an upload topic, `None` for any other topic.
    pub fn parse_fw_upload<'a>(&self, topic: &'a str) -> Option<&'a str> {
        topic
            .strip_prefix(self.fw_upload.as_str())?
            .strip_prefix('/')
            .filter(|name| !name.is_empty() && !name.contains('/'))
    }

    /// The subscription of the per-user command topics (`<root>/+`).
    pub fn user_command_filter(&self) -> String {
        format!("{}/+", self.user_commands)
    }

    /// The user of a per-user command topic, `None` for any other topic.
    pub fn parse_user_command<'a>(&self, topic: &'a str) -> Option<&'a str> {
        topic
            .strip_prefix(self.user_commands.as_str())?
            .strip_prefix('/')
            .filter(|user| !user.is_empty() && !user.contains('/'))
    }

    /// The filter that matches every node's state topic (`<root>/+/state`).
    pub fn node_state_filter(&self) -> String {
        format!("{}/+/state", self.node_state_root)
    }

    /// The node whose state topic `topic` is, if it is one.
    pub fn parse_node_state(&self, topic: &str) -> Option<NodeId> {
        let id = topic
            .strip_prefix(self.node_state_root.as_str())?
            .strip_prefix('/')?
            .strip_suffix("/state")?;
        let node: NodeId = id.parse().ok()?;
        // One spelling only: the one `node_state` writes.
        (self.node_state(node) == topic).then_some(node)
    }

    /// The concrete name of a logical topic.
    pub fn resolve(&self, topic: Topic) -> String {
        match topic {
            Topic::Events => self.events.clone(),
            Topic::NodeState(id) => self.node_state(id),
            Topic::Ha(t) => self.ha.resolve(t),
            Topic::Leases => self.leases.clone(),
            Topic::Procedures => self.procedures.clone(),
        }
    }
}

/// `root/ID/leaf`, without the formatting machinery: every state document, and with Home
/// Assistant discovery every light state, is published on one of these.
pub(crate) fn node_topic(root: &str, id: NodeId, leaf: &str) -> String {
    let mut buf = [0; 4];
    let id = crate::event::hex(id, &mut buf);
    let mut name = String::with_capacity(root.len() + id.len() + leaf.len() + 2);
    name.push_str(root);
    name.push('/');
    name.push_str(id);
    name.push('/');
    name.push_str(leaf);
    name
}

/// A topic or island name that cannot be used, and why.
#[derive(Clone, PartialEq, Eq, Debug, thiserror::Error)]
#[error("{name:?}: {why}")]
pub struct NameError {
    /// The name as given.
    pub name: String,
    /// What is wrong with it.
    pub why: &'static str,
}

/// Checks an island name: 1..=64 characters, no MQTT wildcards (`+`, `#`), no NUL, no empty topic
/// level (leading, trailing or doubled `/`), and no leading `$` (reserved for broker topics).
pub fn validate_island(name: &str) -> Result<(), NameError> {
    let bad = |why: &'static str| {
        Err(NameError {
            name: name.to_owned(),
            why,
        })
    };
    if name.is_empty() || name.chars().count() > 64 {
        return bad("must be 1 to 64 characters");
    }
    if name.contains(['+', '#', '\0']) {
        return bad("must not contain '+', '#' or NUL");
    }
    if name.starts_with('$') {
        return bad("must not start with '$'");
    }
    if name.split('/').any(str::is_empty) {
        return bad("must not have an empty topic level (leading, trailing or double '/')");
    }
    Ok(())
}

/// Checks a configured topic base: 1 to 256 bytes, no MQTT wildcards (`+`, `#`), no NUL.
pub fn validate_topic(name: &str) -> Result<(), NameError> {
    let bad = |why: &'static str| {
        Err(NameError {
            name: name.to_owned(),
            why,
        })
    };
    if name.is_empty() || name.len() > 256 {
        return bad("must be 1 to 256 bytes");
    }
    if name.contains(['+', '#', '\0']) {
        return bad("must not contain '+', '#' or NUL");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seed_names_without_island() {
        let t = Topics::seed();
        assert_eq!(t.commands, "CommandsTopic");
        assert_eq!(t.events, "EventsTopic");
        assert_eq!(t.availability, "ihex/gateway/availability");
        assert_eq!(
            t.node_state(NodeId::new(0x111).unwrap()),
            "ihex/node/111/state"
        );
        assert_eq!(t.resolve(Topic::Events), "EventsTopic");
    }

    #[test]
    fn per_user_command_topics_name_their_user() {
        let t = Topics::seed_on(Some("lab-a"));
        assert_eq!(t.user_command_filter(), "lab-a/ihex/cmd/+");
        assert_eq!(t.parse_user_command("lab-a/ihex/cmd/alice"), Some("alice"));
        assert_eq!(t.parse_user_command("lab-a/ihex/cmd/"), None);
        assert_eq!(t.parse_user_command("lab-a/ihex/cmd/a/b"), None);
        assert_eq!(t.parse_user_command("lab-b/ihex/cmd/alice"), None);
        assert_eq!(t.parse_user_command("lab-a/ihex/cmdx/alice"), None);
    }

    #[test]
    fn node_state_topics_parse_back() {
        let t = Topics::seed_on(Some("lab-a"));
        let id = NodeId::new(0x111).unwrap();
        assert_eq!(t.node_state_filter(), "lab-a/ihex/node/+/state");
        assert_eq!(t.parse_node_state(&t.node_state(id)), Some(id));
        for raw in 1..=NodeId::MAX_RAW {
            if let Some(id) = NodeId::new(raw) {
                assert_eq!(t.node_state(id), format!("lab-a/ihex/node/{id}/state"));
            }
        }
        for other in [
            "ihex/node/111/state",
            "lab-a/ihex/node/111",
            "lab-a/ihex/node/111/state/x",
            "lab-a/ihex/node/zz/state",
            "lab-a/ihex/node//state",
            "lab-a/ihex/node/0111/state",
        ] {
            assert_eq!(t.parse_node_state(other), None, "{other}");
        }
    }

    #[test]
    fn island_prefixes_every_topic() {
        let t = Topics::seed_on(Some("lab-a"));
        assert_eq!(t.commands, "lab-a/CommandsTopic");
        assert_eq!(t.events, "lab-a/EventsTopic");
        assert_eq!(t.availability, "lab-a/ihex/gateway/availability");
        assert_eq!(t.sim, "lab-a/ihex/sim");
        assert_eq!(t.fw_upload_filter(), "lab-a/ihex/fw/upload/+");
        assert_eq!(
            t.parse_fw_upload("lab-a/ihex/fw/upload/sc-1.2.ihex"),
            Some("sc-1.2.ihex")
        );
        for other in [
            "lab-a/ihex/fw/upload/",
            "lab-a/ihex/fw/upload",
            "lab-b/ihex/fw/upload/x",
        ] {
            assert_eq!(t.parse_fw_upload(other), None, "{other}");
        }
        let id = NodeId::new(0xabc).unwrap();
        assert_eq!(t.resolve(Topic::NodeState(id)), "lab-a/ihex/node/abc/state");
        let b = Topics::seed_on(Some("lab-b"));
        // Two islands never share a topic.
        for (x, y) in [
            (&t.commands, &b.commands),
            (&t.events, &b.events),
            (&t.sim, &b.sim),
            (&t.fw_upload, &b.fw_upload),
        ] {
            assert_ne!(x, y);
        }
    }

    #[test]
    fn island_names_are_checked() {
        for good in ["a", "lab1", "bench/2", "Ü-room"] {
            assert!(validate_island(good).is_ok(), "{good}");
        }
        let long = "x".repeat(65);
        for bad in [
            "",
            "a+b",
            "a#",
            "/a",
            "a/",
            "a//b",
            "$SYS",
            "a\0b",
            long.as_str(),
        ] {
            assert!(validate_island(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn topic_bases_are_checked() {
        assert!(validate_topic("EventsTopic").is_ok());
        assert!(validate_topic("").is_err());
        assert_eq!(
            validate_topic("a/#").unwrap_err().to_string(),
            "\"a/#\": must not contain '+', '#' or NUL"
        );
    }
}
