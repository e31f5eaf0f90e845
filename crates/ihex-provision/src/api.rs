//! The gateway's MQTT JSON API as far as provisioning needs it (sans-IO): building the `assign` and
//! `list` commands, and reading the events that answer them.
//!
//! Commands go to the commands topic (`CommandsTopic` by default), answers come back on the events
//! topic: `{"event": "command_result", "payload": {"request_id": …, "result": "ok" | "refused" |
//! "timeout" | "failed", "reason": …}}`, `command_rejected` for invalid commands, and `node_list`
//! (`{"request_id": …, "nodes": [{"id": "111", "online": true, …}]}`) for `list` (docs/mqtt-api.md).
//! The readers are lenient about fields they do not need, so a gateway that adds fields keeps working.

use ihex_proto::{NodeId, Uid};
use serde_json::{json, Value};

/// Errors in what the gateway answered, or in what the user asked for.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ApiError {
    /// The unique ID is not 24 hex digits (the text and why).
    #[error("unique ID {0}")]
    BadUid(String),
    /// An event that is not JSON of the expected shape.
    #[error("event is not {{\"event\": NAME, \"payload\": …}} JSON: {0}")]
    BadEvent(String),
}

/// Parses a 96-bit unique ID (`ihex_proto::Uid`'s form: 24 hex digits, separators allowed).
pub fn parse_uid(text: &str) -> Result<Uid, ApiError> {
    text.trim()
        .parse()
        .map_err(|e| ApiError::BadUid(format!("{text:?}: {e}")))
}

/// `{"cmd":"assign","uid":…,"new_id":…,"request_id":…}`.
pub fn assign_command(uid: &Uid, new_id: NodeId, request_id: &str) -> String {
    json!({"cmd": "assign", "uid": uid.to_string(), "new_id": new_id.to_string(), "request_id": request_id})
        .to_string()
}

/// `{"cmd":"list","request_id":…}`.
pub fn list_command(request_id: &str) -> String {
    json!({"cmd": "list", "request_id": request_id}).to_string()
}

/// A request ID unique enough for one broker: tool name, process, time.
pub fn new_request_id(what: &str) -> String {
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos());
    format!("ihex-provision-{what}-{}-{nanos:x}", std::process::id())
}

/// One event from the events topic.
#[derive(Clone, Debug, PartialEq)]
pub struct Event {
    /// `"node_online"`, `"command_result"`, …
    pub name: String,
    /// The event's payload (`Null` when absent).
    pub payload: Value,
}

impl Event {
    /// Parses an event's JSON text.
    pub fn parse(bytes: &[u8]) -> Result<Event, ApiError> {
        let v: Value =
            serde_json::from_slice(bytes).map_err(|e| ApiError::BadEvent(e.to_string()))?;
        let name = v
            .get("event")
            .and_then(Value::as_str)
            .ok_or_else(|| ApiError::BadEvent("no \"event\" name".into()))?
            .to_owned();
        Ok(Event {
            name,
            payload: v.get("payload").cloned().unwrap_or(Value::Null),
        })
    }

    /// The request ID this event answers, if any.
    pub fn request_id(&self) -> Option<&str> {
        self.payload.get("request_id").and_then(Value::as_str)
    }

    /// True when every `key=value` pair matches a top-level payload field (string, number or bool,
    /// compared as text): `id=111`, `port=3`.
    pub fn matches(&self, filters: &[(String, String)]) -> bool {
        filters.iter().all(|(k, want)| {
            self.payload.get(k).is_some_and(|v| match v {
                Value::String(s) => s == want,
                Value::Number(_) | Value::Bool(_) => {
                    serde_json::from_str::<Value>(want).ok().as_ref() == Some(v)
                }
                _ => false,
            })
        })
    }
}

/// How the gateway answered a command carrying our request ID.
#[derive(Clone, Debug, PartialEq)]
pub enum Outcome {
    /// The node acknowledged.
    Ok(Value),
    /// The node refused, did not answer in time, or the gateway rejected the command.
    Failed {
        /// `"timeout"`, the refusal reason, or the rejection reason.
        reason: String,
        /// The whole payload, for the user.
        payload: Value,
    },
}

/// If `event` answers `request_id`, how: a `command_result` whose status is `ok` succeeded; any other
/// status, or a `command_rejected`, failed.
pub fn outcome(event: &Event, request_id: &str) -> Option<Outcome> {
    if event.request_id() != Some(request_id) {
        return None;
    }
    let text = |k: &str| {
        event
            .payload
            .get(k)
            .and_then(Value::as_str)
            .map(str::to_owned)
    };
    match event.name.as_str() {
        "command_result" => {
            let status = text("status")
                .or_else(|| text("result"))
                .unwrap_or_default();
            if matches!(status.as_str(), "ok" | "acked" | "success") {
                Some(Outcome::Ok(event.payload.clone()))
            } else {
                let reason = text("reason").or_else(|| text("error")).unwrap_or(status);
                Some(Outcome::Failed {
                    reason,
                    payload: event.payload.clone(),
                })
            }
        }
        "command_rejected" => Some(Outcome::Failed {
            reason: text("reason").unwrap_or_else(|| "rejected".into()),
            payload: event.payload.clone(),
        }),
        _ => None,
    }
}

/// The node IDs in a `list` answer: every `id` in the payload's `nodes` array (objects with an `"id"`
/// field, or bare ID strings) or the keys of a `nodes` object. `None` when there is no `nodes` field.
pub fn listed_ids(payload: &Value) -> Option<Vec<NodeId>> {
    let parse = |s: &str| s.parse::<NodeId>().ok();
    match payload.get("nodes")? {
        Value::Array(nodes) => Some(
            nodes
                .iter()
                .filter_map(|n| n.get("id").unwrap_or(n).as_str())
                .filter_map(parse)
                .collect(),
        ),
        // `{"111": {...}, "2": {...}}`: a map keyed by ID.
        Value::Object(map) => Some(map.keys().filter_map(|k| parse(k)).collect()),
        _ => None,
    }
}

/// If `event` is the gateway's answer to our `list` (`node_list` with our request ID), the IDs it lists.
/// A `node_list` without a readable `nodes` array yields an empty list rather than a guess.
pub fn list_answer(event: &Event, request_id: &str) -> Option<Vec<NodeId>> {
    if event.name != "node_list" || event.request_id() != Some(request_id) {
        return None;
    }
    Some(listed_ids(&event.payload).unwrap_or_default())
}

/// The node ID in a retained node-state topic name (`<root>/<id>/state`).
pub fn id_from_state_topic(root: &str, topic: &str) -> Option<NodeId> {
    let id = topic
        .strip_prefix(root)?
        .strip_prefix('/')?
        .strip_suffix("/state")?;
    id.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn uid_parsing() {
        let uid = parse_uid("0123456789abcdefFEDCBA98").unwrap();
        assert_eq!(uid.0[0], 0x01);
        assert_eq!(uid.0[11], 0x98);
        assert_eq!(uid.to_string(), "0123456789abcdeffedcba98");
        assert_eq!(
            parse_uid("01:23:45:67:89:ab:cd:ef:fe:dc:ba:98").unwrap(),
            uid
        );
        for bad in [
            "",
            "0123",
            "0123456789abcdefFEDCBA9",
            "0123456789abcdefFEDCBA9800",
            "g123456789abcdefFEDCBA98",
        ] {
            assert!(parse_uid(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn commands_are_the_documented_json() {
        let uid = parse_uid("00112233445566778899aabb").unwrap();
        let v: Value =
            serde_json::from_str(&assign_command(&uid, NodeId::new_sc(0x123).unwrap(), "r1"))
                .unwrap();
        assert_eq!(
            v,
            json!({"cmd":"assign","uid":"00112233445566778899aabb","new_id":"123","request_id":"r1"})
        );
        let v: Value = serde_json::from_str(&list_command("r2")).unwrap();
        assert_eq!(v, json!({"cmd":"list","request_id":"r2"}));
        assert_ne!(new_request_id("a"), new_request_id("a"));
    }

    #[test]
    fn outcomes_follow_the_request_id() {
        let ok = Event::parse(
            br#"{"event":"command_result","payload":{"request_id":"r1","status":"ok"}}"#,
        )
        .unwrap();
        assert!(matches!(outcome(&ok, "r1"), Some(Outcome::Ok(_))));
        assert_eq!(outcome(&ok, "r2"), None);
        let to = Event::parse(
            br#"{"event":"command_result","payload":{"request_id":"r1","status":"timeout"}}"#,
        )
        .unwrap();
        assert!(
            matches!(outcome(&to, "r1"), Some(Outcome::Failed { reason, .. }) if reason == "timeout")
        );
        let rej = Event::parse(br#"{"event":"command_rejected","payload":{"request_id":"r1","reason":"unknown node"}}"#).unwrap();
        assert!(
            matches!(outcome(&rej, "r1"), Some(Outcome::Failed { reason, .. }) if reason == "unknown node")
        );
        let other = Event::parse(br#"{"event":"node_online","payload":{"id":"111"}}"#).unwrap();
        assert_eq!(outcome(&other, "r1"), None);
    }

    #[test]
    fn events_parse_and_match() {
        let e =
            Event::parse(br#"{"event":"node_online","payload":{"id":"111","port":3}}"#).unwrap();
        assert_eq!(e.name, "node_online");
        assert!(e.matches(&[("id".into(), "111".into()), ("port".into(), "3".into())]));
        assert!(!e.matches(&[("id".into(), "112".into())]));
        assert!(!e.matches(&[("missing".into(), "x".into())]));
        assert!(Event::parse(b"not json").is_err());
        assert!(Event::parse(br#"{"payload":{}}"#).is_err());
    }

    #[test]
    fn list_answers_and_state_topics() {
        let p = json!({"request_id":"r","nodes":[{"id":"111","online":true},{"id":"2"},"abc",{"id":"zz"}]});
        let ids: Vec<u16> = listed_ids(&p).unwrap().iter().map(|i| i.get()).collect();
        assert_eq!(ids, [0x111, 0x2, 0xabc]);
        assert_eq!(listed_ids(&json!({"status":"ok"})), None);
        let e = Event::parse(br#"{"event":"node_list","payload":{"request_id":"q","nodes":[{"id":"111","online":true}]}}"#).unwrap();
        assert_eq!(list_answer(&e, "q").unwrap(), [NodeId::new(0x111).unwrap()]);
        assert_eq!(list_answer(&e, "other"), None);
        let ids: Vec<u16> = listed_ids(&json!({"nodes":{"5":{},"fd":{}}}))
            .unwrap()
            .iter()
            .map(|i| i.get())
            .collect();
        assert_eq!(ids, [0x5, 0xfd]);
        assert_eq!(
            id_from_state_topic("ihex/node", "ihex/node/1a/state")
                .unwrap()
                .get(),
            0x1a
        );
        assert_eq!(id_from_state_topic("ihex/node", "ihex/node/1a/other"), None);
        assert_eq!(
            id_from_state_topic("lab/ihex/node", "ihex/node/1a/state"),
            None
        );
    }
}
