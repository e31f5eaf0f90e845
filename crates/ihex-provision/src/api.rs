//! The gateway's MQTT JSON API as far as provisioning needs it (sans-IO): building the `assign` and
//! `list` commands, and reading the events that answer them.
//!
//! Commands go to the commands topic (`CommandsTopic` by default), answers come back on the events
//! topic (docs/mqtt-api.md): `command_result`, `command_rejected` for invalid commands, `node_list`
//! for `list`. They are read as the gateway core's own event types ([`GatewayEvent`]), so the tool
//! and the gateway cannot disagree on their shape; fields a newer gateway adds are ignored.
//! [`Event`] keeps any event as a name and an untyped payload, for `wait-event`'s `key=value`
//! filters.

pub use ihex_gateway_core::event::Event as GatewayEvent;
use ihex_gateway_core::event::{self as gateway, CommandResult};
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

/// `{"cmd":"fw_update","image":…,"nodes":…,"force":…,"request_id":…}`.
pub fn fw_update_command(image: &str, nodes: &str, force: bool, request_id: &str) -> String {
    json!({"cmd": "fw_update", "image": image, "nodes": nodes, "force": force, "request_id": request_id})
        .to_string()
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
    /// The node acknowledged: the gateway's `command_result`.
    Ok(CommandResult),
    /// The node refused, did not answer in time, or the gateway rejected the command.
    Failed {
        /// The refusal, timeout or rejection reason.
        reason: String,
        /// The gateway's whole answer.
        answer: Box<GatewayEvent>,
    },
}

/// If `event` answers `request_id`, how: a `command_result` with `ok` succeeded; any other result, or
/// a `command_rejected`, failed.
pub fn outcome(event: &GatewayEvent, request_id: &str) -> Option<Outcome> {
    let failed = |reason: String| Outcome::Failed {
        reason,
        answer: Box::new(event.clone()),
    };
    match event {
        GatewayEvent::CommandResult(r) if r.request_id.as_deref() == Some(request_id) => {
            Some(match (r.result, &r.reason) {
                (gateway::Outcome::Ok, _) => Outcome::Ok(r.clone()),
                (_, Some(reason)) => failed(reason.clone()),
                (_, None) => failed("the gateway gave no reason".into()),
            })
        }
        GatewayEvent::CommandRejected(r) if r.request_id.as_deref() == Some(request_id) => {
            Some(failed(r.reason.clone()))
        }
        _ => None,
    }
}

/// If `event` is the gateway's answer to our `list` (`node_list` with our request ID), the IDs it
/// lists (online or lost: both own their ID).
pub fn list_answer(event: &GatewayEvent, request_id: &str) -> Option<Vec<NodeId>> {
    match event {
        GatewayEvent::NodeList(l) if l.request_id.as_deref() == Some(request_id) => {
            Some(l.nodes.iter().map(|n| n.id.0).collect())
        }
        _ => None,
    }
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
mod fw_tests {
    use super::*;

    #[test]
    fn fw_update_command_is_the_documented_json() {
        let c: Value =
            serde_json::from_str(&fw_update_command("a.ihex", "111,112", false, "r")).unwrap();
        assert_eq!(
            c,
            json!({"cmd":"fw_update","image":"a.ihex","nodes":"111,112","force":false,"request_id":"r"})
        );
    }

    #[test]
    fn progress_and_report_events_parse_as_the_gateways() {
        let p: GatewayEvent = serde_json::from_str(
            r#"{"event":"fw_progress","payload":{"request_id":"u1","node":"111","phase":"receiving","percent":62}}"#,
        )
        .unwrap();
        assert!(matches!(p, GatewayEvent::FwProgress(ref p) if p.percent == 62));
        let r: GatewayEvent = serde_json::from_str(
            r#"{"event":"fw_report","payload":{"request_id":"u1","image_id":"7a3c19e4","version":"1.3.0","duration_ms":41230,
 "frames_sent":8560,"bus_share":50,"nodes":[{"node":"111","outcome":"updated","reason":null,"duration_ms":40110},
 {"node":"112","outcome":"refused","reason":"downgrade","duration_ms":310}]}}"#,
        )
        .unwrap();
        let GatewayEvent::FwReport(r) = r else {
            panic!()
        };
        assert!(!r.all_updated());
        assert_eq!(r.nodes[1].reason.as_deref(), Some("downgrade"));
    }
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

    fn gateway_event(json: &str) -> GatewayEvent {
        serde_json::from_str(json).unwrap()
    }

    #[test]
    fn outcomes_follow_the_request_id() {
        let ok = gateway_event(
            r#"{"event":"command_result","payload":{"request_id":"r1","cmd":"assign","node":"5","result":"ok","reason":null}}"#,
        );
        assert!(matches!(outcome(&ok, "r1"), Some(Outcome::Ok(r)) if r.node.to_string() == "5"));
        assert_eq!(outcome(&ok, "r2"), None);
        let to = gateway_event(
            r#"{"event":"command_result","payload":{"request_id":"r1","cmd":"assign","node":"5","result":"timeout","reason":"no AssignReply within 500 ms"}}"#,
        );
        assert!(
            matches!(outcome(&to, "r1"), Some(Outcome::Failed { reason, .. }) if reason == "no AssignReply within 500 ms")
        );
        let rej = gateway_event(
            r#"{"event":"command_rejected","payload":{"request_id":"r1","reason":"unknown node 9; known: 2"}}"#,
        );
        assert!(
            matches!(outcome(&rej, "r1"), Some(Outcome::Failed { reason, .. }) if reason == "unknown node 9; known: 2")
        );
        let other = gateway_event(
            r#"{"event":"node_online","payload":{"id":"111","role":"static","first_seen":true}}"#,
        );
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
        let state = |id: &str, online: bool| {
            json!({"id": id, "online": online, "role": null, "ports": null, "version": null,
                   "led": null, "buzzer": null, "relay": null, "loops": [], "connections": [],
                   "reported": null, "last_seen_ms": 0, "first_seen_ms": 0})
        };
        let list = json!({"event": "node_list", "payload": {"request_id": "q",
                          "nodes": [state("111", true), state("2", false)]}});
        let e: GatewayEvent = serde_json::from_value(list).unwrap();
        let ids: Vec<u16> = list_answer(&e, "q")
            .unwrap()
            .iter()
            .map(|i| i.get())
            .collect();
        assert_eq!(ids, [0x111, 0x2]);
        assert_eq!(list_answer(&e, "other"), None);
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
