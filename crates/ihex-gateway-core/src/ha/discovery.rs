//! Device-based discovery configs (Home Assistant 2024.11 and later): one retained message per
//! device with its `device`, `origin`, shared availability and one entry per entity in
//! `components`. Keys are written in full, never abbreviated.
//!
//! State comes from the topics the gateway already publishes, through value templates: the
//! node's retained state document (relay, buzzer, online, version) and the events topic (docking).
//! Only the light has a state topic of its own ([`super::light`]), because Home Assistant's
//! JSON-schema light reads its state without a template.

use ihex_proto::{NodeId, Uid};
use serde_json::{json, Map, Value};

use super::command::TONES;
use super::light::EFFECTS;
use super::topic::{Entity, HaTopic};
use super::HaConfig;
use crate::event::{NodeState, Role};

/// Manufacturer of every device.
pub const MANUFACTURER: &str = "iHEX";
/// `origin.name`: the program that publishes the configs.
pub const ORIGIN: &str = "iHEX mc-gateway";

/// Availability of an element from its state document.
pub const ONLINE_AVAILABILITY: &str = "{{ 'online' if value_json.online else 'offline' }}";
/// The connectivity sensor from the state document.
pub const ONLINE_STATE: &str = "{{ 'ON' if value_json.online else 'OFF' }}";
/// The relay from the state document (`None`: unknown to Home Assistant).
pub const RELAY_STATE: &str =
    "{{ 'None' if value_json.relay is none else ('ON' if value_json.relay else 'OFF') }}";
/// The buzzer from the state document: on while its acknowledged mode is not `off`.
pub const BUZZER_STATE: &str = "{{ 'None' if value_json.buzzer is none else \
     ('OFF' if value_json.buzzer.mode == 'off' else 'ON') }}";
/// The firmware version the node runs (`major.minor.patch`), from the state document (not the
/// protocol version, which is its `version`).
pub const VERSION_STATE: &str =
    "{{ 'None' if value_json.firmware is none else value_json.firmware.version }}";
/// The procedure sensor's state, from the retained procedures document: the first running
/// procedure's current step (`sample-handover: step 1 of 3: Place the carrier on 112`), or `idle`;
/// at most 255 characters, Home Assistant's limit for a state.
pub const PROCEDURE_STATE: &str = "{% set p = value_json.procedures %}\
     {% if p | length == 0 %}idle{% else %}\
     {{ (p[0].name ~ ': step ' ~ p[0].step ~ ' of ' ~ p[0].of \
     ~ (': ' ~ p[0].text if p[0].text else ''))[:255] }}{% endif %}";
/// The procedure sensor's attributes: every running procedure, as the document lists them.
pub const PROCEDURE_ATTRIBUTES: &str = "{{ {'procedures': value_json.procedures} | tojson }}";

/// The event types of the docking entity.
pub const DOCKING_EVENTS: [&str; 2] = ["docked", "undocked"];

/// The docking entity's template for `id`: `new_connection` / `connection_removed` events on the
/// events topic in which `id` is either end become `docked` / `undocked`, with both ends;
/// every other event renders nothing, which Home Assistant ignores.
pub fn docking_template(id: NodeId) -> String {
    format!(
        "{{% set p = value_json.payload %}}\
         {{% if value_json.event in ['new_connection', 'connection_removed'] \
         and (p['n-1'].id == '{id}' or p.n.id == '{id}') %}}\
         {{% set kind = 'docked' if value_json.event == 'new_connection' else 'undocked' %}}\
         {{{{ {{'event_type': kind, 'static': p['n-1'].id, 'static_port': p['n-1'].port, \
         'mobile': p.n.id, 'mobile_port': p.n.port}} | tojson }}}}\
         {{% endif %}}"
    )
}

/// The parts every entity has: platform, `unique_id`, `default_entity_id`, name, QoS 1 (a
/// device-level `qos` is not passed on to the entities).
fn component(
    cfg: &HaConfig,
    device: &str,
    platform: &str,
    key: &str,
    name: &str,
) -> Map<String, Value> {
    let ha = &cfg.topics.ha;
    let mut c = Map::new();
    c.insert("platform".into(), platform.into());
    c.insert("unique_id".into(), ha.unique_id(device, key).into());
    c.insert(
        "default_entity_id".into(),
        ha.entity_id(platform, device, key).into(),
    );
    c.insert("name".into(), name.into());
    c.insert("qos".into(), 1.into());
    c
}

/// Adds `extra`'s members to `c`.
fn with(mut c: Map<String, Value>, extra: Value) -> Value {
    if let Value::Object(m) = extra {
        c.extend(m);
    }
    Value::Object(c)
}

fn origin(cfg: &HaConfig) -> Value {
    json!({"name": ORIGIN, "sw_version": cfg.sw_version})
}

/// Device fields every device shares.
fn device(cfg: &HaConfig, identifier: String, name: String, model: &str) -> Map<String, Value> {
    let mut d = Map::new();
    d.insert("identifiers".into(), json!([identifier]));
    d.insert("name".into(), name.into());
    d.insert("manufacturer".into(), MANUFACTURER.into());
    d.insert("model".into(), model.into());
    if let Some(url) = &cfg.configuration_url {
        d.insert("configuration_url".into(), url.clone().into());
    }
    d
}

/// A device name: `iHEX <what>`, with the island's name when it has one.
fn device_name(cfg: &HaConfig, what: &str) -> String {
    match &cfg.island {
        Some(island) => format!("iHEX {island} {what}"),
        None => format!("iHEX {what}"),
    }
}

/// The gateway's own device: its connection to the broker (the availability topic itself, so it
/// reads `offline` when the gateway's last will fires) — and the parent of every element.
pub fn gateway(cfg: &HaConfig) -> Value {
    let ha = &cfg.topics.ha;
    let id = ha.gateway_device();
    let mut dev = device(cfg, id.clone(), device_name(cfg, "gateway"), "mc-gateway");
    dev.insert("sw_version".into(), cfg.sw_version.clone().into());
    let connection = with(
        component(cfg, &id, "binary_sensor", "connection", "Connection"),
        json!({
            "state_topic": cfg.topics.availability,
            "payload_on": "online",
            "payload_off": "offline",
            "device_class": "connectivity",
            "entity_category": "diagnostic",
        }),
    );
    let procedure = with(
        component(cfg, &id, "sensor", "procedure", "Procedure step"),
        json!({
            "state_topic": cfg.topics.procedures,
            "value_template": PROCEDURE_STATE,
            "json_attributes_topic": cfg.topics.procedures,
            "json_attributes_template": PROCEDURE_ATTRIBUTES,
            "icon": "mdi:clipboard-list-outline",
            "availability": [{"topic": cfg.topics.availability}],
        }),
    );
    json!({
        "device": dev,
        "origin": origin(cfg),
        "components": {"connection": connection, "procedure": procedure},
    })
}

/// What an element's discovery config is built from besides the gateway's configuration. Kept
/// per element instead of the config itself (a JSON tree of some kilobytes): the config goes out
/// again only when this changes, and is rebuilt from it when everything is published again.
#[derive(Clone, PartialEq, Eq, Debug)]
pub struct Element {
    /// The element.
    pub id: NodeId,
    /// Static or mobile, when known.
    pub role: Option<Role>,
    /// Its firmware version (`major.minor.patch`) as the state document shows it.
    pub version: Option<String>,
    /// Its UID, when read.
    pub uid: Option<Uid>,
}

impl Element {
    /// The parts of `state` (and the UID) the config shows.
    pub fn of(state: &NodeState, uid: Option<Uid>) -> Element {
        Element {
            id: state.id.0,
            role: state.role,
            version: state.firmware.as_ref().map(|f| f.version.clone()),
            uid,
        }
    }

    /// True when `state` (and the UID) would give this same element: no config to publish.
    pub fn shows(&self, state: &NodeState, uid: Option<Uid>) -> bool {
        self.id == state.id.0
            && self.role == state.role
            && self.version.as_deref() == state.firmware.as_ref().map(|f| f.version.as_str())
            && self.uid == uid
    }
}

/// An element's device: LED strip, buzzer, identify, online, docking, firmware, and the relay when
/// the element is known to be static. Available while the gateway is online **and** the element
/// answers health checks; the online and firmware entities only need the gateway (so "offline" and
/// the last known version stay visible).
pub fn element(cfg: &HaConfig, state: &Element) -> Value {
    let t = &cfg.topics;
    let ha = &t.ha;
    let id = state.id;
    let dev_id = ha.device(id);
    let state_topic = t.node_state(id);
    let model = match state.role {
        Some(Role::Static) => "static element",
        Some(Role::Mobile) => "mobile element",
        None => "element",
    };
    let mut dev = device(
        cfg,
        dev_id.clone(),
        device_name(cfg, &id.to_string()),
        model,
    );
    if let Some(version) = &state.version {
        dev.insert("sw_version".into(), version.clone().into());
    }
    if let Some(uid) = state.uid {
        dev.insert("serial_number".into(), uid.to_string().into());
    }
    dev.insert("via_device".into(), ha.gateway_device().into());
    let gateway_only = json!([{"topic": t.availability}]);
    let c = |platform: &str, key: &str, name: &str| component(cfg, &dev_id, platform, key, name);

    let mut components = Map::new();
    components.insert(
        Entity::Led.name().into(),
        with(
            c("light", Entity::Led.name(), "LED strip"),
            json!({
                "schema": "json",
                "command_topic": ha.command(id, Entity::Led),
                "state_topic": ha.resolve(HaTopic::LightState(id)),
                "brightness": true,
                "supported_color_modes": ["rgb"],
                "effect": true,
                "effect_list": EFFECTS,
                "flash": false,
                "transition": false,
            }),
        ),
    );
    if state.role == Some(Role::Static) {
        components.insert(
            Entity::Relay.name().into(),
            with(
                c("switch", Entity::Relay.name(), "Relay"),
                json!({
                    "command_topic": ha.command(id, Entity::Relay),
                    "state_topic": state_topic,
                    "value_template": RELAY_STATE,
                    "device_class": "switch",
                }),
            ),
        );
    }
    let tones: Vec<&str> = TONES.iter().map(|(n, _)| *n).collect();
    components.insert(
        Entity::Buzzer.name().into(),
        with(
            c("siren", Entity::Buzzer.name(), "Buzzer"),
            json!({
                "command_topic": ha.command(id, Entity::Buzzer),
                "state_topic": state_topic,
                "state_value_template": BUZZER_STATE,
                "available_tones": tones,
                "support_duration": true,
                "support_volume_set": false,
            }),
        ),
    );
    components.insert(
        Entity::Identify.name().into(),
        with(
            c("button", Entity::Identify.name(), "Identify"),
            json!({
                "command_topic": ha.command(id, Entity::Identify),
                "device_class": "identify",
                "entity_category": "config",
            }),
        ),
    );
    components.insert(
        "online".into(),
        with(
            c("binary_sensor", "online", "Online"),
            json!({
                "state_topic": state_topic,
                "value_template": ONLINE_STATE,
                "device_class": "connectivity",
                "entity_category": "diagnostic",
                "availability": gateway_only,
            }),
        ),
    );
    components.insert(
        "docking".into(),
        with(
            c("event", "docking", "Docking"),
            json!({
                "state_topic": t.events,
                "value_template": docking_template(id),
                "event_types": DOCKING_EVENTS,
            }),
        ),
    );
    components.insert(
        "firmware".into(),
        with(
            c("sensor", "firmware", "Firmware"),
            json!({
                "state_topic": state_topic,
                "value_template": VERSION_STATE,
                "entity_category": "diagnostic",
                "availability": gateway_only,
            }),
        ),
    );
    json!({
        "device": dev,
        "origin": origin(cfg),
        "availability": [
            {"topic": t.availability},
            {"topic": state_topic, "value_template": ONLINE_AVAILABILITY},
        ],
        "availability_mode": "all",
        "components": components,
    })
}
