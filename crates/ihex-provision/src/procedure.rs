//! Guided procedures from a file: a TOML procedure file (`name`, `[[steps]]`, the fields of the
//! gateway's `procedure` command, docs/procedures.md) becomes that JSON command, checked by the
//! gateway's own parser before anything is sent; [`run`] sends it and follows the procedure's
//! events to its one `procedure_ended`.

use std::time::Duration;

use serde_json::{Map, Value};
use tokio::time::Instant;

use crate::{
    api::Event,
    can::Topics,
    mqtt::{Broker, MqttError, Session},
};

/// Errors of a procedure file or run.
#[derive(Debug, thiserror::Error)]
pub enum ProcedureFileError {
    /// Not TOML.
    #[error("not a TOML procedure file: {0}")]
    Toml(String),
    /// A key the file may not set (the tool sets `cmd` and `request_id`).
    #[error("`{0}` is set by ihex-provision, not by the procedure file; remove it")]
    Reserved(&'static str),
    /// The gateway's parser refuses the command the file makes.
    #[error("{0}")]
    Invalid(String),
    /// The broker session failed.
    #[error(transparent)]
    Mqtt(#[from] MqttError),
    /// The gateway refused the command.
    #[error("the gateway refused the procedure: {0}")]
    Rejected(String),
    /// No `procedure_ended` in time.
    #[error("no procedure_ended for request {0} within {1:?} (is the gateway running on this broker and island?)")]
    NoAnswer(String, Duration),
}

/// The `procedure` command (JSON text) of a TOML procedure file, with `request_id`.
pub fn command_from_toml(text: &str, request_id: &str) -> Result<String, ProcedureFileError> {
    let table: toml::Table = text
        .parse()
        .map_err(|e: toml::de::Error| ProcedureFileError::Toml(e.to_string()))?;
    let mut members = Map::new();
    members.insert("cmd".into(), Value::from("procedure"));
    members.insert("request_id".into(), Value::from(request_id));
    for (k, v) in table {
        for reserved in ["cmd", "request_id"] {
            if k == reserved {
                return Err(ProcedureFileError::Reserved(reserved));
            }
        }
        let v = serde_json::to_value(v).map_err(|e| ProcedureFileError::Toml(e.to_string()))?;
        members.insert(k, v);
    }
    let json = Value::Object(members).to_string();
    ihex_gateway_core::command::parse(json.as_bytes(), usize::MAX)
        .map_err(|r| ProcedureFileError::Invalid(r.error.to_string()))?;
    Ok(json)
}

/// Sends `command` (from [`command_from_toml`], whose `request_id` it carries) and hands every
/// event of the procedure it starts to `on_event` until its `procedure_ended`, which it returns.
/// Waits at most `timeout` in all.
pub async fn run(
    broker: &Broker,
    topics: &Topics,
    command: &str,
    request_id: &str,
    timeout: Duration,
    mut on_event: impl FnMut(&Event),
) -> Result<Event, ProcedureFileError> {
    let deadline = Instant::now() + timeout;
    let mut session =
        Session::connect(broker, std::slice::from_ref(&topics.events), timeout).await?;
    let result = async {
        session.publish(&topics.commands, command).await?;
        let mut id = None;
        while let Some(msg) = session.recv_until(deadline).await? {
            let Ok(e) = Event::parse(&msg.payload) else {
                continue;
            };
            let ours = match e.name.as_str() {
                "command_rejected" => {
                    if e.request_id() == Some(request_id) {
                        let reason = e.payload["reason"].as_str().unwrap_or_default();
                        return Err(ProcedureFileError::Rejected(reason.to_owned()));
                    }
                    false
                }
                "procedure_started" if e.request_id() == Some(request_id) => {
                    id = e.payload["id"].as_u64();
                    true
                }
                "procedure_step" | "procedure_mismatch" | "procedure_ended" => {
                    id.is_some() && e.payload["id"].as_u64() == id
                }
                _ => false,
            };
            if ours {
                on_event(&e);
                if e.name == "procedure_ended" {
                    return Ok(e);
                }
            }
        }
        Err(ProcedureFileError::NoAnswer(request_id.to_owned(), timeout))
    }
    .await;
    session.close().await;
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    const SAMPLE: &str = include_str!("../../../examples/procedures/sample-handover.toml");

    #[test]
    fn the_sample_file_is_a_valid_procedure_command() {
        let json = command_from_toml(SAMPLE, "r1").unwrap();
        let v: Value = serde_json::from_str(&json).unwrap();
        assert_eq!(v["cmd"], "procedure");
        assert_eq!(v["request_id"], "r1");
        assert_eq!(v["name"], "sample-handover");
        assert_eq!(v["steps"].as_array().unwrap().len(), 3);
        assert_eq!(v["steps"][0]["blink"]["period_ms"], 500);
    }

    #[test]
    fn a_bad_file_is_refused_with_the_gateways_reason() {
        let e = command_from_toml(
            "name = \"x\"\n[[steps]]\nnode = \"111\"\nwait = \"near\"\ncolor = \"red\"\n",
            "r",
        )
        .unwrap_err();
        assert_eq!(
            e.to_string(),
            "procedure: step 1: `step.wait` must be \"docked\" or \"undocked\"; got \"near\""
        );
        let e = command_from_toml("cmd = \"led\"\n", "r").unwrap_err();
        assert!(matches!(e, ProcedureFileError::Reserved("cmd")), "{e}");
        let e = command_from_toml("name = \n", "r").unwrap_err();
        assert!(matches!(e, ProcedureFileError::Toml(_)), "{e}");
    }
}
