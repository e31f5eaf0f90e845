//! The keys Home Assistant accepts in a device-based discovery config, per platform, and a check of
//! a config against them — what the tests hold every config the gateway publishes to.
//!
//! Source: Home Assistant 2026.2's MQTT integration (`homeassistant/components/mqtt/`:
//! `schemas.py` — `DEVICE_DISCOVERY_SCHEMA`, `MQTT_ENTITY_COMMON_SCHEMA`, the device, origin and
//! availability schemas; `config.py` — `MQTT_BASE_SCHEMA`, `MQTT_RO_SCHEMA`, `MQTT_RW_SCHEMA`;
//! each platform's `DISCOVERY_SCHEMA` in `light/schema_json.py`, `switch.py`, `siren.py`,
//! `button.py`, `binary_sensor.py`, `event.py`, `sensor.py`), which the documentation pages
//! (`light.mqtt`, `switch.mqtt`, `siren.mqtt`, `button.mqtt`, `binary_sensor.mqtt`, `event.mqtt`,
//! `sensor.mqtt`, and `mqtt` for device-based discovery) describe. Why the check matters: a
//! platform's discovery schema silently drops a key it does not know (`REMOVE_EXTRA`), and an
//! unknown key at the top of a device config makes Home Assistant refuse the whole device.
//!
//! Keys are the full names; abbreviations (`cmps`, `dev`, `o`, `stat_t`, …) are not used by the
//! gateway, so the check refuses them like any unknown key. `object_id` is left out on purpose:
//! Home Assistant deprecated it for `default_entity_id` (removal announced for 2026.4).

use serde_json::{Map, Value};

/// Top-level keys of a device-based discovery config (`DEVICE_DISCOVERY_SCHEMA`).
pub const DEVICE_CONFIG: &[&str] = &[
    "device",
    "origin",
    "components",
    "availability",
    "availability_mode",
    "availability_template",
    "availability_topic",
    "payload_available",
    "payload_not_available",
    "state_topic",
    "command_topic",
    "qos",
    "encoding",
];
/// Required top-level keys.
pub const DEVICE_CONFIG_REQUIRED: &[&str] = &["device", "origin", "components"];

/// Keys of `device` (`MQTT_ENTITY_DEVICE_INFO_SCHEMA`); `identifiers` or `connections` required.
pub const DEVICE: &[&str] = &[
    "identifiers",
    "connections",
    "manufacturer",
    "model",
    "model_id",
    "name",
    "hw_version",
    "serial_number",
    "sw_version",
    "via_device",
    "suggested_area",
    "configuration_url",
];

/// Keys of `origin` (`MQTT_ORIGIN_INFO_SCHEMA`); `name` required.
pub const ORIGIN: &[&str] = &["name", "sw_version", "support_url"];

/// Keys of one entry of an `availability` list; `topic` required.
pub const AVAILABILITY_ITEM: &[&str] = &[
    "topic",
    "payload_available",
    "payload_not_available",
    "value_template",
];

/// `availability_mode` values.
pub const AVAILABILITY_MODES: &[&str] = &["all", "any", "latest"];

/// Keys every entity platform takes (`MQTT_ENTITY_COMMON_SCHEMA` with the availability schemas,
/// `MQTT_BASE_SCHEMA`), and `platform`, which names the platform in `components`.
pub const ENTITY_COMMON: &[&str] = &[
    "platform",
    "availability",
    "availability_mode",
    "availability_template",
    "availability_topic",
    "payload_available",
    "payload_not_available",
    "device",
    "entity_picture",
    "origin",
    "enabled_by_default",
    "entity_category",
    "icon",
    "json_attributes_topic",
    "json_attributes_template",
    "default_entity_id",
    "unique_id",
    "qos",
    "encoding",
];

/// One platform: the keys it adds to [`ENTITY_COMMON`], and those it requires (`unique_id` is
/// required of every entity in a device-based config).
pub struct Platform {
    /// The platform (`light`, …).
    pub name: &'static str,
    /// Its own keys.
    pub keys: &'static [&'static str],
    /// Required keys.
    pub required: &'static [&'static str],
}

/// The platforms the gateway uses.
pub const PLATFORMS: &[Platform] = &[
    // light/schema_json.py: MQTT_RW_SCHEMA + the JSON schema's keys + `schema`.
    Platform {
        name: "light",
        keys: &[
            "command_topic",
            "optimistic",
            "retain",
            "state_topic",
            "schema",
            "brightness",
            "brightness_scale",
            "color_temp_kelvin",
            "effect",
            "effect_list",
            "flash",
            "flash_time_long",
            "flash_time_short",
            "max_mireds",
            "min_mireds",
            "max_kelvin",
            "min_kelvin",
            "name",
            "supported_color_modes",
            "transition",
            "white_scale",
        ],
        required: &["unique_id", "command_topic"],
    },
    // switch.py: MQTT_RW_SCHEMA + …
    Platform {
        name: "switch",
        keys: &[
            "command_topic",
            "optimistic",
            "retain",
            "state_topic",
            "command_template",
            "name",
            "payload_off",
            "payload_on",
            "state_off",
            "state_on",
            "value_template",
            "device_class",
        ],
        required: &["unique_id", "command_topic"],
    },
    // siren.py: MQTT_RW_SCHEMA + …
    Platform {
        name: "siren",
        keys: &[
            "command_topic",
            "optimistic",
            "retain",
            "state_topic",
            "available_tones",
            "command_template",
            "command_off_template",
            "name",
            "payload_off",
            "payload_on",
            "state_off",
            "state_on",
            "state_value_template",
            "support_duration",
            "support_volume_set",
        ],
        required: &["unique_id", "command_topic"],
    },
    // button.py: MQTT_BASE_SCHEMA + …
    Platform {
        name: "button",
        keys: &[
            "command_template",
            "command_topic",
            "device_class",
            "name",
            "payload_press",
            "retain",
        ],
        required: &["unique_id", "command_topic"],
    },
    // binary_sensor.py: MQTT_RO_SCHEMA + …
    Platform {
        name: "binary_sensor",
        keys: &[
            "state_topic",
            "value_template",
            "device_class",
            "expire_after",
            "force_update",
            "name",
            "off_delay",
            "payload_off",
            "payload_on",
        ],
        required: &["unique_id", "state_topic"],
    },
    // event.py: MQTT_RO_SCHEMA + …
    Platform {
        name: "event",
        keys: &[
            "state_topic",
            "value_template",
            "device_class",
            "name",
            "event_types",
        ],
        required: &["unique_id", "state_topic", "event_types"],
    },
    // sensor.py: MQTT_RO_SCHEMA + …
    Platform {
        name: "sensor",
        keys: &[
            "state_topic",
            "value_template",
            "device_class",
            "expire_after",
            "force_update",
            "last_reset_value_template",
            "name",
            "options",
            "suggested_display_precision",
            "state_class",
            "unit_of_measurement",
        ],
        required: &["unique_id", "state_topic"],
    },
];

/// Every problem of `config` as a device-based discovery config (empty: none).
pub fn check_device_config(config: &Value) -> Vec<String> {
    let mut problems = Vec::new();
    let Some(top) = config.as_object() else {
        return vec!["the config is not a JSON object".into()];
    };
    keys(
        "config",
        top,
        DEVICE_CONFIG,
        DEVICE_CONFIG_REQUIRED,
        &mut problems,
    );
    match top.get("device").and_then(Value::as_object) {
        Some(dev) => {
            keys("device", dev, DEVICE, &[], &mut problems);
            let has = |k: &str| {
                dev.get(k)
                    .and_then(Value::as_array)
                    .is_some_and(|a| !a.is_empty())
            };
            if !has("identifiers") && !has("connections") {
                problems.push("device: needs `identifiers` or `connections`".into());
            }
        }
        None => problems.push("`device` is not an object".into()),
    }
    match top.get("origin").and_then(Value::as_object) {
        Some(o) => keys("origin", o, ORIGIN, &["name"], &mut problems),
        None => problems.push("`origin` is not an object".into()),
    }
    availability("config", top, &mut problems);
    let Some(components) = top.get("components").and_then(Value::as_object) else {
        problems.push("`components` is not an object".into());
        return problems;
    };
    for (id, c) in components {
        let Some(c) = c.as_object() else {
            problems.push(format!("components.{id}: not an object"));
            continue;
        };
        let Some(name) = c.get("platform").and_then(Value::as_str) else {
            problems.push(format!("components.{id}: no `platform`"));
            continue;
        };
        let Some(p) = PLATFORMS.iter().find(|p| p.name == name) else {
            problems.push(format!(
                "components.{id}: platform {name} is not in the table"
            ));
            continue;
        };
        let allowed: Vec<&str> = ENTITY_COMMON.iter().chain(p.keys).copied().collect();
        let what = format!("components.{id} ({name})");
        keys(&what, c, &allowed, p.required, &mut problems);
        availability(&what, c, &mut problems);
        if let Some(e) = c.get("default_entity_id").and_then(Value::as_str) {
            if !e.starts_with(&format!("{name}.")) {
                problems.push(format!(
                    "{what}: default_entity_id {e} is not in domain {name}"
                ));
            }
        }
    }
    problems
}

/// Unknown and missing keys of one object.
fn keys(
    what: &str,
    object: &Map<String, Value>,
    allowed: &[&str],
    required: &[&str],
    problems: &mut Vec<String>,
) {
    for k in object.keys() {
        if !allowed.contains(&k.as_str()) {
            problems.push(format!("{what}: unknown key `{k}`"));
        }
    }
    for k in required {
        if !object.contains_key(*k) {
            problems.push(format!("{what}: missing required key `{k}`"));
        }
    }
}

/// The `availability` list and `availability_mode` of one object, if present.
fn availability(what: &str, object: &Map<String, Value>, problems: &mut Vec<String>) {
    if let Some(list) = object.get("availability") {
        match list.as_array() {
            Some(items) => {
                for item in items {
                    match item.as_object() {
                        Some(i) => keys(
                            &format!("{what}: availability"),
                            i,
                            AVAILABILITY_ITEM,
                            &["topic"],
                            problems,
                        ),
                        None => {
                            problems.push(format!("{what}: an availability entry is not an object"))
                        }
                    }
                }
            }
            None => problems.push(format!("{what}: `availability` is not a list")),
        }
        if object.contains_key("availability_topic") {
            problems.push(format!(
                "{what}: `availability` and `availability_topic` exclude each other"
            ));
        }
    }
    if let Some(mode) = object.get("availability_mode") {
        if !mode
            .as_str()
            .is_some_and(|m| AVAILABILITY_MODES.contains(&m))
        {
            problems.push(format!(
                "{what}: availability_mode {mode} is not all, any or latest"
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn the_check_finds_unknown_missing_and_misplaced_keys() {
        let bad = json!({
            "dev": {"ids": ["x"]},
            "origin": {"name": "o", "url": "u"},
            "components": {
                "a": {"platform": "light", "unique_id": "u", "cmd_t": "t"},
                "b": {"platform": "switch", "command_topic": "t", "default_entity_id": "light.x"},
                "c": {"platform": "event", "unique_id": "e", "state_topic": "s"},
                "d": {"platform": "vacuum", "unique_id": "v"},
            },
            "availability": [{"topic": "t", "tpl": "x"}],
            "availability_mode": "most",
        });
        let problems = check_device_config(&bad);
        for expected in [
            "config: unknown key `dev`",
            "config: missing required key `device`",
            "origin: unknown key `url`",
            "components.a (light): unknown key `cmd_t`",
            "components.a (light): missing required key `command_topic`",
            "components.b (switch): missing required key `unique_id`",
            "components.b (switch): default_entity_id light.x is not in domain switch",
            "components.c (event): missing required key `event_types`",
            "components.d: platform vacuum is not in the table",
            "config: availability: unknown key `tpl`",
            "config: availability_mode \"most\" is not all, any or latest",
        ] {
            assert!(
                problems.iter().any(|p| p == expected),
                "{expected} not in {problems:#?}"
            );
        }
        let good = json!({
            "device": {"identifiers": ["x"]},
            "origin": {"name": "o"},
            "components": {"b": {"platform": "button", "unique_id": "u", "command_topic": "t"}},
        });
        assert_eq!(check_device_config(&good), Vec::<String>::new());
    }
}
