//! Home Assistant glue: discovery on or off, messages from Home Assistant (its birth message, a
//! command on an entity's command topic), and keeping an element's config current. The configs,
//! light states and command parsing are [`crate::ha`]'s; commands then take the JSON API's path.

use std::time::Instant;

use ihex_proto::NodeId;

use super::{Ha, HaConfig};
use crate::bridge::{Bridge, Delivery, Publication};
use crate::origin::{Interface, Origin};

/// Home Assistant's birth message (and the payload its status topic holds while it runs).
pub const HA_ONLINE: &[u8] = b"online";

impl Bridge {
    /// This bridge with Home Assistant discovery: configs and light states follow the state
    /// documents, and [`Bridge::handle_ha_command`] takes commands from Home Assistant.
    pub fn with_home_assistant(mut self, config: HaConfig) -> Bridge {
        self.ha = Some(Ha::new(config));
        self
    }

    /// The Home Assistant configuration, when discovery is on.
    pub fn home_assistant(&self) -> Option<&HaConfig> {
        self.ha.as_ref().map(Ha::config)
    }

    /// A message on Home Assistant's status topic: on `online` (Home Assistant started) every
    /// discovery config is published again; anything else (its last will, `offline`) needs nothing.
    pub fn handle_ha_status(&mut self, payload: &[u8], _now: Instant) {
        let Some(ha) = &self.ha else { return };
        if payload != HA_ONLINE {
            tracing::debug!(payload = %String::from_utf8_lossy(payload), "Home Assistant status");
            return;
        }
        tracing::info!("Home Assistant is online: publishing discovery again");
        let configs = ha.configs();
        for c in configs {
            self.out.publish.push_kept(Publication::Ha(c));
        }
    }

    /// A message on one of the Home Assistant command topics (`topic` in full): carried out like
    /// the JSON command it stands for, or answered with `command_rejected`.
    pub fn handle_ha_command(&mut self, topic: &str, payload: &[u8], now: Instant) {
        let Some(ha) = &self.ha else {
            tracing::debug!(%topic, "Home Assistant command while discovery is off: ignored");
            return;
        };
        let registry = &self.registry;
        let parsed = ha.parse_command(topic, payload, self.config.max_command_bytes, |id| {
            registry.get(id).and_then(|e| e.led)
        });
        match parsed {
            Ok(req) => {
                let ha = Origin::new(Interface::Ha, None);
                self.execute(req, Delivery::live(now).with_origin(ha), now)
            }
            Err(rej) => {
                self.origin = Origin::new(Interface::Ha, None);
                self.reject(rej.request_id, rej.error);
                self.origin = Origin::default();
            }
        }
    }

    /// Publishes `id`'s config and light state if they changed (something outside its state
    /// document did, such as its UID).
    pub(crate) fn refresh_ha(&mut self, id: NodeId, now: Instant) {
        // The very document the state topic carries (`node_state`), so the two never disagree.
        let Some(doc) = self.node_state(id, now) else {
            return;
        };
        let (Some(ha), Some(entry)) = (&mut self.ha, self.registry.get(id)) else {
            return;
        };
        let out = ha.on_state(&doc, entry, false);
        for h in out {
            self.out.publish.push_kept(Publication::Ha(h));
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeSet;
    use std::time::Instant;

    use crate::bridge::test_support::*;
    use crate::bridge::*;
    use crate::ha::discovery::{self, docking_template};
    use crate::ha::schema::check_device_config;
    use crate::ha::{HaConfig, HaTopic};
    use crate::topic::{Topic, Topics};
    use ihex_proto::{
        AckResult, BootRole, Kind, LedCommand, Message, Packet, ResetReason, Rgb, StateReport,
    };
    use serde_json::{json, Value};

    fn config(island: Option<&str>) -> HaConfig {
        let topics = Topics::seed_on(island);
        HaConfig {
            topics,
            island: island.map(Into::into),
            configuration_url: Some("http://pi.local:8080/".into()),
            sw_version: "0.1.0".into(),
        }
    }

    fn boot(role: BootRole, ports: u8) -> Message {
        Message::BootUp {
            version: (1, 1),
            role,
            ports,
            reset: ResetReason::PowerOn,
        }
    }

    /// The demo's island (static 111 and 112, mobile 2 docked on 111 port 3, mobile 3 free)
    /// booting in front of a bridge with discovery on; returns what it published.
    fn demo(island: Option<&str>) -> (Bridge, Instant, Out) {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0).with_home_assistant(config(island));
        b.handle_timeout(t0);
        drain(&mut b);
        b.handle_mqtt_connected(t0);
        let mut out = drain(&mut b);
        for (n, role, ports) in [
            (0x111, BootRole::Static, 6),
            (0x112, BootRole::Static, 6),
            (2, BootRole::Mobile, 1),
            (3, BootRole::Mobile, 2),
        ] {
            b.handle_packet(Packet::report(id(n), boot(role, ports)), t0 + MS);
            read_back_all(&mut b, t0 + MS);
            let o = drain(&mut b);
            out.ha.extend(o.ha);
            out.states.extend(o.states);
        }
        let o = dock(&mut b, 0x111, 3, 2, t0 + MS);
        out.ha.extend(o.ha);
        out.raw_events.extend(o.raw_events);
        out.states.extend(o.states);
        (b, t0, out)
    }

    fn configs(out: &Out) -> Vec<(HaTopic, &Value)> {
        out.ha
            .iter()
            .filter_map(|(t, v)| match t {
                Topic::Ha(t @ (HaTopic::DeviceConfig(_) | HaTopic::GatewayConfig)) => Some((*t, v)),
                _ => None,
            })
            .collect()
    }

    /// Renders a value template the way Home Assistant does for a message with `payload`.
    fn render(template: &str, payload: &str) -> String {
        let value_json: Value = serde_json::from_str(payload).unwrap();
        minijinja::Environment::new()
            .render_str(
                template,
                minijinja::context! { value => payload, value_json => minijinja::value::Serde(value_json) },
            )
            .unwrap_or_else(|e| panic!("{template}: {e:#}"))
    }

    #[test]
    fn the_demo_islands_configs_use_only_keys_home_assistant_documents() {
        let (_, _, out) = demo(Some("lab1"));
        let configs = configs(&out);
        let topics: Vec<HaTopic> = configs.iter().map(|(t, _)| *t).collect();
        assert_eq!(
            topics,
            [
                HaTopic::GatewayConfig,
                HaTopic::DeviceConfig(id(0x111)),
                HaTopic::DeviceConfig(id(0x112)),
                HaTopic::DeviceConfig(id(2)),
                HaTopic::DeviceConfig(id(3)),
            ],
            "the gateway first, then one device per element, each once"
        );
        let mut unique_ids = BTreeSet::new();
        for (t, config) in &configs {
            let problems = check_device_config(config);
            assert!(problems.is_empty(), "{t:?}: {problems:#?}\n{config:#}");
            for c in config["components"].as_object().unwrap().values() {
                let uid = c["unique_id"].as_str().unwrap().to_owned();
                assert!(uid.contains("lab1"), "{uid}");
                assert!(c["default_entity_id"].as_str().unwrap().contains("lab1"));
                assert!(unique_ids.insert(uid), "unique ids repeat");
            }
            assert_eq!(
                config["device"]["configuration_url"],
                "http://pi.local:8080/"
            );
        }
        let components = |n: usize| -> Vec<String> {
            configs[n].1["components"]
                .as_object()
                .unwrap()
                .keys()
                .cloned()
                .collect()
        };
        let with_relay = [
            "buzzer", "docking", "firmware", "identify", "led", "online", "relay",
        ];
        assert_eq!(components(1), with_relay, "static 111");
        assert_eq!(
            components(3),
            ["buzzer", "docking", "firmware", "identify", "led", "online"]
        );
        let d111 = configs[1].1;
        assert_eq!(
            d111["device"]["via_device"],
            configs[0].1["device"]["identifiers"][0]
        );
        assert_eq!(d111["device"]["model"], "static element");
        // Its firmware version once read back (below), never the protocol version of its BootUp.
        assert_eq!(d111["device"]["sw_version"], Value::Null);
        assert_eq!(d111["availability_mode"], "all");
        assert_eq!(
            d111["availability"][0]["topic"],
            "lab1/ihex/gateway/availability"
        );
        assert_eq!(d111["availability"][1]["topic"], "lab1/ihex/node/111/state");
        let led = &d111["components"]["led"];
        assert_eq!(led["command_topic"], "lab1/ihex/ha/111/led/set");
        assert_eq!(led["state_topic"], "lab1/ihex/ha/111/led");
        assert_eq!(
            d111["components"]["relay"]["state_topic"], "lab1/ihex/node/111/state",
            "the relay reads the existing state document"
        );
        assert_eq!(
            d111["components"]["docking"]["state_topic"],
            "lab1/EventsTopic"
        );
    }

    /// A restarted gateway (a fresh bridge) hears a node only by its health replies: the read-back
    /// gives the state document its protocol and firmware versions, and the device its
    /// `sw_version`, the firmware version.
    #[test]
    fn a_restarted_gateway_reads_both_versions_back() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0).with_home_assistant(config(None));
        b.handle_timeout(t0);
        b.handle_mqtt_connected(t0);
        drain(&mut b);
        b.handle_packet(Packet::report(id(0x111), reply(0, 0)), t0 + MS);
        let out = drain(&mut b);
        let q = out.queries.first().expect("111 is asked for its state");
        let Message::StateQuery { seq, parts } = q.msg else {
            unreachable!()
        };
        let fw = ihex_proto::FirmwareVersion::new(0, 1, 0);
        let reports = [
            StateReport::Firmware {
                version: fw,
                trial: false,
            },
            StateReport::Protocol { version: (1, 3) },
            StateReport::End {
                seq,
                parts,
                count: 2,
            },
        ];
        for r in reports {
            b.handle_packet(
                Packet::report(id(0x111), Message::StateReport(r)),
                t0 + 2 * MS,
            );
        }
        let out = drain(&mut b);
        let doc = &out
            .states
            .iter()
            .rev()
            .find(|(n, _)| *n == id(0x111))
            .expect("111's document")
            .1;
        assert_eq!(doc["version"], "1.3", "{doc}");
        assert_eq!(doc["firmware"]["version"], "0.1.0", "{doc}");
        let config = out
            .ha
            .iter()
            .rev()
            .find(|(t, _)| *t == Topic::Ha(HaTopic::DeviceConfig(id(0x111))))
            .expect("111's config again");
        assert_eq!(config.1["device"]["sw_version"], "0.1.0");
    }

    #[test]
    fn two_islands_on_one_broker_give_disjoint_devices() {
        let ids = |island| {
            let (_, _, out) = demo(Some(island));
            let mut set = BTreeSet::new();
            for (t, config) in configs(&out) {
                set.insert(config_topic(island, t));
                set.insert(config["device"]["identifiers"][0].to_string());
                for c in config["components"].as_object().unwrap().values() {
                    set.insert(c["unique_id"].to_string());
                    set.insert(c["default_entity_id"].to_string());
                    for k in ["command_topic", "state_topic"] {
                        if c[k].is_string() && !c[k].as_str().unwrap().contains("EventsTopic") {
                            set.insert(c[k].to_string());
                        }
                    }
                }
            }
            set
        };
        let (a, b) = (ids("island-a"), ids("island-b"));
        assert!(a.len() > 40, "{a:?}");
        assert!(
            a.is_disjoint(&b),
            "{:?}",
            a.intersection(&b).collect::<Vec<_>>()
        );
    }

    fn config_topic(island: &str, t: HaTopic) -> String {
        config(Some(island)).topics.resolve(Topic::Ha(t))
    }

    #[test]
    fn the_templates_read_the_existing_state_documents_and_events() {
        let (mut b, t0, out) = demo(None);
        // 111: relay on, buzzer beeping, both acknowledged.
        for cmd in [
            json!({"cmd": "power", "node": "111", "on": true}),
            json!({"cmd": "buzzer", "node": "111", "mode": "on"}),
        ] {
            let sent = command(&mut b, cmd, t0 + S).sent;
            let m = sent[0].msg;
            b.handle_packet(
                Packet::report(
                    id(0x111),
                    ack(m.kind(), m.ack_seq().unwrap(), AckResult::Ok),
                ),
                t0 + S,
            );
        }
        let states = drain(&mut b).states;
        let doc111 = states
            .iter()
            .rev()
            .find(|(n, _)| *n == id(0x111))
            .unwrap()
            .1
            .to_string();
        let doc3 = out
            .states
            .iter()
            .rev()
            .find(|(n, _)| *n == id(3))
            .unwrap()
            .1
            .to_string();
        assert_eq!(render(discovery::RELAY_STATE, &doc111), "ON");
        assert_eq!(
            render(discovery::RELAY_STATE, &doc3),
            "None",
            "never reported"
        );
        assert_eq!(render(discovery::BUZZER_STATE, &doc111), "ON");
        assert_eq!(render(discovery::BUZZER_STATE, &doc3), "None");
        assert_eq!(render(discovery::ONLINE_STATE, &doc111), "ON");
        assert_eq!(render(discovery::ONLINE_AVAILABILITY, &doc111), "online");
        // The firmware sensor shows the firmware version, never the protocol version.
        assert_eq!(
            render(discovery::VERSION_STATE, &doc111),
            "None",
            "not read back"
        );
        let read_back = doc111.replace(
            "\"firmware\":null",
            r#""firmware":{"version":"0.1.0","trial":false,"image_hash":"00000000000000"}"#,
        );
        assert_ne!(read_back, doc111);
        assert_eq!(render(discovery::VERSION_STATE, &read_back), "0.1.0");
        let offline = doc3.replace("\"online\":true", "\"online\":false");
        assert_eq!(render(discovery::ONLINE_STATE, &offline), "OFF");
        assert_eq!(render(discovery::ONLINE_AVAILABILITY, &offline), "offline");

        // The docking entity: the demo's new_connection as both ends see it; nothing for others.
        let docked = out
            .raw_events
            .iter()
            .find(|e| e.contains("new_connection"))
            .unwrap();
        let seen = |n: u16, event: &str| render(&docking_template(id(n)), event);
        let both = json!({"event_type": "docked", "static": "111", "static_port": 3,
                          "mobile": "2", "mobile_port": 0});
        for n in [0x111, 2] {
            let v: Value = serde_json::from_str(&seen(n, docked)).unwrap();
            assert_eq!(v, both);
        }
        assert_eq!(seen(0x112, docked), "");
        let removed = docked.replace("new_connection", "connection_removed");
        let v: Value = serde_json::from_str(&seen(2, &removed)).unwrap();
        assert_eq!(v["event_type"], "undocked");
        let online =
            r#"{"event":"node_online","payload":{"id":"111","role":"static","first_seen":true}}"#;
        assert_eq!(seen(0x111, online), "");
    }

    /// Issue 30: the gateway device's procedure sensor reads the retained procedures document: the
    /// current step of the running procedure, `idle` without one, every procedure as attributes.
    #[test]
    fn the_procedure_sensor_shows_the_current_step() {
        let (mut b, t0, out) = demo(Some("lab1"));
        let (_, gw) = configs(&out)
            .into_iter()
            .rfind(|(t, _)| *t == HaTopic::GatewayConfig)
            .expect("the gateway's config");
        let sensor = gw["components"]["procedure"].clone();
        assert_eq!(sensor["platform"], "sensor");
        assert_eq!(sensor["state_topic"], "lab1/ihex/procedures");
        assert_eq!(sensor["json_attributes_topic"], "lab1/ihex/procedures");
        let state =
            |doc: &Value| render(sensor["value_template"].as_str().unwrap(), &doc.to_string());
        let idle = serde_json::to_value(b.procedures(t0)).unwrap();
        assert_eq!(state(&idle), "idle");
        let out = command(
            &mut b,
            json!({"cmd": "procedure", "name": "handover", "steps": [
                {"text": "Place 3 on 112", "node": "112", "wait": "docked", "color": "green"},
                {"node": "111", "port": 5, "wait": "docked", "color": "green"}]}),
            t0 + S,
        );
        let doc = out.procedures.last().expect("the procedures document");
        assert_eq!(state(doc), "handover: step 1 of 2: Place 3 on 112");
        let attributes: Value = serde_json::from_str(&render(
            sensor["json_attributes_template"].as_str().unwrap(),
            &doc.to_string(),
        ))
        .unwrap();
        assert_eq!(attributes["procedures"][0]["wait"]["node"], "112");
        // Docked where it waits: step 2, without text.
        let out = dock(&mut b, 0x112, 1, 3, t0 + 2 * S);
        assert_eq!(
            state(out.procedures.last().unwrap()),
            "handover: step 2 of 2"
        );
        let long =
            json!({"procedures": [{"name": "p", "step": 1, "of": 1, "text": "x".repeat(300)}]});
        assert_eq!(state(&long).chars().count(), 255);
    }

    /// Acks every frame `sent` carries as `ok` from its destination.
    fn ack_all(b: &mut Bridge, sent: &[Packet], now: Instant) -> Out {
        for p in sent {
            let seq = p.msg.ack_seq().unwrap();
            b.handle_packet(
                Packet::report(p.dest, ack(p.msg.kind(), seq, AckResult::Ok)),
                now,
            );
        }
        drain(b)
    }

    #[test]
    fn commands_from_home_assistant_take_the_command_path() {
        let (mut b, t0, _) = demo(Some("lab1"));
        let now = t0 + S;
        let topic = |n: &str, e: &str| format!("lab1/ihex/ha/{n}/{e}/set");
        b.handle_ha_command(
            &topic("111", "led"),
            br#"{"state":"ON","color":{"r":255,"g":0,"b":0},"brightness":128}"#,
            now,
        );
        let out = drain(&mut b);
        assert_eq!(out.sent.len(), 1);
        assert_eq!(out.sent[0].dest, id(0x111));
        let Message::LedSet { cmd, .. } = out.sent[0].msg else {
            panic!("{:?}", out.sent)
        };
        assert_eq!(
            cmd,
            LedCommand::Steady {
                color: Rgb::new(255, 0, 0),
                brightness: 128
            }
        );
        let out = ack_all(&mut b, &out.sent, now);
        assert_eq!(
            out.one("command_result"),
            &json!({"request_id": "homeassistant", "cmd": "led", "node": "111",
                    "result": "ok", "reason": null, "origin": {"interface": "ha"}})
        );
        assert_eq!(
            out.ha,
            [(
                Topic::Ha(HaTopic::LightState(id(0x111))),
                json!({"state": "ON", "color_mode": "rgb", "color": {"r": 255, "g": 0, "b": 0},
                       "brightness": 128, "effect": "off"})
            )],
            "the light state follows the acknowledged command, the config is unchanged"
        );

        for (n, entity, payload, kind) in [
            ("111", "relay", "ON", Kind::PowerSet),
            (
                "2",
                "buzzer",
                r#"{"state":"ON","tone":"beep","duration":3}"#,
                Kind::BuzzerSet,
            ),
            ("3", "identify", "PRESS", Kind::Identify),
        ] {
            b.handle_ha_command(&topic(n, entity), payload.as_bytes(), now);
            let out = drain(&mut b);
            assert_eq!(out.sent.len(), 1, "{entity}");
            assert_eq!(
                (out.sent[0].dest, out.sent[0].msg.kind()),
                (id(u16::from_str_radix(n, 16).unwrap()), kind)
            );
            let out = ack_all(&mut b, &out.sent, now);
            assert_eq!(out.one("command_result")["result"], "ok", "{entity}");
            assert_eq!(out.one("command_result")["request_id"], "homeassistant");
        }

        // Refused like a JSON command, with the same event.
        b.handle_ha_command(
            &topic("111", "led"),
            br#"{"state":"ON","brightness":999}"#,
            now,
        );
        let out = drain(&mut b);
        assert!(out.sent.is_empty());
        assert_eq!(
            out.one("command_rejected"),
            &json!({"request_id": "homeassistant",
                    "reason": "light: `brightness` must be an integer 0 to 255; got 999",
                    "origin": {"interface": "ha"}})
        );
        b.handle_ha_command(&topic("7", "relay"), b"ON", now);
        assert_eq!(
            drain(&mut b).one("command_rejected")["reason"],
            "unknown node 7; known: 2, 3, 111, 112"
        );
    }

    #[test]
    fn discovery_again_on_every_connection_and_when_home_assistant_starts() {
        let (mut b, t0, _) = demo(None);
        b.handle_mqtt_connected(t0 + S);
        let out = drain(&mut b);
        let topics: Vec<Topic> = out.ha.iter().map(|(t, _)| *t).collect();
        assert_eq!(topics[0], Topic::Ha(HaTopic::GatewayConfig));
        for n in [2, 3, 0x111, 0x112] {
            assert!(topics.contains(&Topic::Ha(HaTopic::DeviceConfig(id(n)))));
            assert!(topics.contains(&Topic::Ha(HaTopic::LightState(id(n)))));
        }
        assert_eq!(out.states.len(), 4);

        b.handle_ha_status(b"online", t0 + S);
        let out = drain(&mut b);
        assert_eq!(out.ha.len(), 5, "the gateway and four elements");
        assert!(out.states.is_empty() && out.events.is_empty());
        b.handle_ha_status(b"offline", t0 + S);
        assert!(drain(&mut b).ha.is_empty());

        // A change that leaves the config and light alone publishes neither.
        b.handle_packet(Packet::report(id(0x112), reply(1, 0x01)), t0 + S);
        let out = drain(&mut b);
        assert_eq!(out.states.len(), 1, "the relay went on");
        assert!(out.ha.is_empty(), "{:?}", out.ha);
    }

    #[test]
    fn discovery_off_publishes_and_takes_nothing_of_home_assistants() {
        let t0 = Instant::now();
        let mut b = Bridge::new(BridgeConfig::default(), t0);
        b.handle_mqtt_connected(t0);
        b.handle_packet(Packet::report(id(2), boot(BootRole::Mobile, 1)), t0);
        b.handle_ha_status(b"online", t0);
        b.handle_ha_command("ihex/ha/2/led/set", br#"{"state":"ON"}"#, t0);
        let out = drain(&mut b);
        assert!(out.ha.is_empty() && out.sent.is_empty());
        assert!(out.named("command_rejected").is_empty());
        assert!(b.home_assistant().is_none());
    }

    #[test]
    fn forgotten_and_renumbered_elements_leave_no_device() {
        let (mut b, t0, _) = demo(Some("lab1"));
        // 3 goes lost (it stops answering), then is forgotten.
        for n in 1..=4u8 {
            let t = t0 + S * u32::from(n);
            b.handle_timeout(t);
            for m in [0x111, 0x112, 2] {
                b.handle_packet(Packet::report(id(m), reply(n, 0)), t + MS);
            }
        }
        drain(&mut b);
        let out = command(&mut b, json!({"cmd": "forget", "node": "3"}), t0 + S * 5);
        assert_eq!(
            out.cleared,
            [
                Topic::Ha(HaTopic::DeviceConfig(id(3))),
                Topic::Ha(HaTopic::LightState(id(3))),
                Topic::NodeState(id(3)),
            ],
            "the device first, so Home Assistant removes it before its state topics empty"
        );
        b.handle_ha_status(b"online", t0 + S * 5);
        let republished: Vec<Topic> = drain(&mut b).ha.into_iter().map(|(t, _)| t).collect();
        assert!(!republished.contains(&Topic::Ha(HaTopic::DeviceConfig(id(3)))));

        // 2's board, once assigned an ID through the gateway, is renumbered: 5 is forgotten.
        let uid = "00112233445566778899aabb";
        let assign = |b: &mut Bridge, new_id: u16, now| {
            let out = command(
                b,
                json!({"cmd": "assign", "uid": uid, "new_id": format!("{new_id:x}")}),
                now,
            );
            let Message::AssignCommit { seq, .. } = out.sent[1].msg else {
                panic!()
            };
            let reply = Message::AssignReply {
                seq,
                result: AckResult::Ok,
                new_id: id(new_id),
                uid_tail: [0x88, 0x99, 0xaa, 0xbb],
            };
            b.handle_packet(Packet::report(id(new_id), reply), now);
            drain(b)
        };
        let out = assign(&mut b, 5, t0 + S * 5);
        let serial = out
            .ha
            .iter()
            .find(|(t, _)| *t == Topic::Ha(HaTopic::DeviceConfig(id(5))))
            .map(|(_, c)| c["device"]["serial_number"].clone());
        assert_eq!(
            serial,
            Some(json!(uid)),
            "the UID is the device's serial number"
        );
        let out = assign(&mut b, 6, t0 + S * 6);
        assert!(
            out.cleared
                .contains(&Topic::Ha(HaTopic::DeviceConfig(id(5)))),
            "{:?}",
            out.cleared
        );
        assert!(!out
            .cleared
            .contains(&Topic::Ha(HaTopic::DeviceConfig(id(6)))));
        assert_eq!(out.one("node_forgotten")["new_id"], "6");
    }
}
