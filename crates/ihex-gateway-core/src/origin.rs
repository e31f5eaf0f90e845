//! Where a command came from: the interface it arrived through and who sent it — an identity
//! something other than the sender vouches for (the broker's authenticated username on a per-user
//! command topic, the island view's token, `local` for loopback), and a name the sender put in
//! the command itself, kept apart as claimed. The adapters establish the origin; the bridge carries
//! it to the command's answer (`command_result`, `command_rejected`) and refuses commands without
//! a vouched identity when told to ([`crate::BridgeConfig::require_identity`]).

use serde::{Deserialize, Serialize};

/// The interface a command arrived through (also the metrics' `interface` label).
#[derive(
    Clone, Copy, Debug, Default, Hash, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Interface {
    /// The MQTT command topics (the shared one and the per-user ones).
    #[default]
    Mqtt,
    /// Home Assistant's command topics.
    Ha,
    /// The island view's `POST /api/command`.
    Web,
    /// The SiLA 2 server.
    Sila,
    /// A procedure the gateway runs.
    Procedure,
    /// `ihex-provision` through the gateway.
    Provision,
}

impl Interface {
    /// Every interface.
    pub const ALL: [Interface; 6] = [
        Interface::Mqtt,
        Interface::Ha,
        Interface::Web,
        Interface::Sila,
        Interface::Procedure,
        Interface::Provision,
    ];

    /// Its name as the MQTT API and the metrics write it.
    pub fn as_str(self) -> &'static str {
        match self {
            Interface::Mqtt => "mqtt",
            Interface::Ha => "ha",
            Interface::Web => "web",
            Interface::Sila => "sila",
            Interface::Procedure => "procedure",
            Interface::Provision => "provision",
        }
    }
}

impl std::fmt::Display for Interface {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Where a command came from.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Origin {
    /// The interface.
    pub interface: Interface,
    /// The identity something other than the sender vouches for: the MQTT username of a per-user
    /// command topic (the broker's ACL lets only that user publish there), the island view's
    /// token name, a TLS client certificate's name, or `local`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub user: Option<String>,
    /// The name the command's own `user` field gave: recorded, not vouched for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub claimed: Option<String>,
}

impl Origin {
    /// From `interface`, vouched for as `user` (if anyone).
    pub fn new(interface: Interface, user: Option<String>) -> Origin {
        Origin {
            interface,
            user,
            claimed: None,
        }
    }

    /// The shared MQTT command topic, no identity and no claim: what answers leave out (their
    /// shape stays as it was for the clients that never send an identity).
    pub fn is_plain(&self) -> bool {
        *self == Origin::default()
    }

    /// The origin an answer carries: `None` when it is [plain](Origin::is_plain).
    pub fn for_answer(&self) -> Option<Origin> {
        (!self.is_plain()).then(|| self.clone())
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use ihex_proto::{AckResult, Kind, Packet};
    use serde_json::json;

    use super::*;
    use crate::bridge::test_support::{ack, drain, id, with_nodes};
    use crate::{Bridge, BridgeConfig, Delivery};

    const MS: Duration = Duration::from_millis(1);

    fn send(b: &mut Bridge, cmd: serde_json::Value, origin: Origin, now: std::time::Instant) {
        let d = Delivery::live(now).with_origin(origin);
        b.handle_delivered_command(cmd.to_string().as_bytes(), d, now);
    }

    #[test]
    fn answers_carry_the_origin_and_the_claim_apart() {
        let (mut b, t0) = with_nodes(&[2]);
        let alice = Origin::new(Interface::Mqtt, Some("alice".into()));
        let cmd =
            json!({"cmd": "power", "node": "2", "on": true, "request_id": "a", "user": "bob"});
        send(&mut b, cmd, alice, t0);
        let out = drain(&mut b);
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(2), ack(Kind::PowerSet, seq, AckResult::Ok)),
            t0 + MS,
        );
        let out = drain(&mut b);
        let r = out.one("command_result");
        assert_eq!(
            r["origin"],
            json!({"interface": "mqtt", "user": "alice", "claimed": "bob"})
        );

        // Rejected: the same, from the island view.
        let web = Origin::new(Interface::Web, Some("local".into()));
        send(
            &mut b,
            json!({"cmd": "power", "node": "9", "on": true}),
            web,
            t0,
        );
        let r = drain(&mut b).one("command_rejected").clone();
        assert_eq!(r["origin"], json!({"interface": "web", "user": "local"}));

        // The plain shared topic: the answers look as they always did.
        send(
            &mut b,
            json!({"cmd": "power", "node": "9", "on": true}),
            Origin::default(),
            t0,
        );
        let r = drain(&mut b).one("command_rejected").clone();
        assert!(r.get("origin").is_none(), "{r}");
        // And a command after one with an origin does not inherit it.
        b.handle_command(br#"{"cmd":"power","node":"2","on":false}"#, t0 + 2 * MS);
        let out = drain(&mut b);
        let seq = out.sent[0].msg.ack_seq().unwrap();
        b.handle_packet(
            Packet::report(id(2), ack(Kind::PowerSet, seq, AckResult::Ok)),
            t0 + 3 * MS,
        );
        let r = drain(&mut b).one("command_result").clone();
        assert!(r.get("origin").is_none(), "{r}");
    }

    #[test]
    fn require_identity_refuses_commands_without_a_vouched_one() {
        let t0 = std::time::Instant::now();
        let config = BridgeConfig {
            require_identity: Some("lab/ihex/cmd".into()),
            ..BridgeConfig::default()
        };
        let mut b = Bridge::new(config, t0);
        let _ = drain(&mut b);
        // A claim is not an identity.
        let cmd =
            json!({"cmd": "power", "node": "2", "on": true, "user": "bob", "request_id": "x"});
        send(&mut b, cmd.clone(), Origin::default(), t0);
        let r = drain(&mut b).one("command_rejected").clone();
        assert_eq!(r["request_id"], "x");
        assert!(
            r["reason"]
                .as_str()
                .unwrap()
                .starts_with("no vouched identity"),
            "{r}"
        );
        assert!(
            r["reason"]
                .as_str()
                .unwrap()
                .contains("lab/ihex/cmd/<user>"),
            "{r}"
        );
        assert_eq!(r["origin"], json!({"interface": "mqtt", "claimed": "bob"}));
        // Reading is never refused.
        send(&mut b, json!({"cmd": "list"}), Origin::default(), t0);
        assert_eq!(drain(&mut b).named("node_list").len(), 1);
        // A vouched identity passes (to the next check: node 2 is unknown here).
        let alice = Origin::new(Interface::Mqtt, Some("alice".into()));
        send(&mut b, cmd, alice, t0);
        let r = drain(&mut b).one("command_rejected").clone();
        assert!(
            r["reason"].as_str().unwrap().starts_with("unknown node"),
            "{r}"
        );
    }

    #[test]
    fn a_user_field_must_be_a_string() {
        let (mut b, t0) = with_nodes(&[2]);
        b.handle_command(br#"{"cmd":"power","node":"2","on":true,"user":7}"#, t0);
        let r = drain(&mut b).one("command_rejected").clone();
        assert!(r["reason"].as_str().unwrap().contains("`user`"), "{r}");
    }

    #[test]
    fn interfaces_serialise_as_their_names() {
        for i in Interface::ALL {
            assert_eq!(serde_json::to_value(i).unwrap(), json!(i.as_str()));
        }
    }
}
