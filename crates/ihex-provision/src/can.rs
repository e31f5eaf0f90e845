//! Assigning a node ID over CAN by the board's unique ID, through the gateway's MQTT API.
//!
//! Order matters: every check that needs no network runs first; then the gateway is asked which IDs
//! are taken (its `list` answer plus the retained per-node state topics) and a duplicate is refused
//! before anything reaches the bus; only then is `assign` sent and its `command_result` awaited.

use std::{collections::BTreeSet, time::Duration};

use ihex_gateway_core::event::CommandResult;
use ihex_proto::{NodeId, Uid};
use tokio::time::Instant;

use crate::{
    api::{self, GatewayEvent, Outcome},
    id::IdError,
    mqtt::{Broker, MqttError, Session},
};

/// Topic names of the gateway (already under the island prefix, if any).
#[derive(Clone, Debug)]
pub struct Topics {
    /// Where commands go (`CommandsTopic`).
    pub commands: String,
    /// Where events come from (`EventsTopic`).
    pub events: String,
    /// Root of the retained `<root>/<id>/state` topics (`ihex/node`).
    pub node_state_root: String,
    /// The gateway's retained `online`/`offline` (its default name).
    pub availability: String,
    /// Root of the firmware upload topics `<root>/<name>`.
    pub fw_upload: String,
}

impl Topics {
    /// The gateway's default names, prefixed `ISLAND/` when an island name is given.
    pub fn new(
        island: Option<&str>,
        commands: &str,
        events: &str,
        node_state_root: &str,
    ) -> Topics {
        let p = |t: &str| island.map_or_else(|| t.to_owned(), |i| format!("{i}/{t}"));
        Topics {
            commands: p(commands),
            events: p(events),
            node_state_root: p(node_state_root),
            availability: p(ihex_gateway_core::topic::AVAILABILITY),
            fw_upload: p(ihex_gateway_core::topic::FW_UPLOAD),
        }
    }
}

/// Errors of an assignment over CAN.
#[derive(Debug, thiserror::Error)]
pub enum AssignError {
    /// The requested ID is invalid or taken.
    #[error(transparent)]
    Id(#[from] IdError),
    /// The broker session failed.
    #[error(transparent)]
    Mqtt(#[from] MqttError),
    /// The gateway did not say which IDs are taken.
    #[error("the gateway did not answer the node list within {0:?}; refusing to assign without the duplicate check (pass --skip-duplicate-check to override)")]
    NoList(Duration),
    /// The gateway or the node refused the assignment.
    #[error("assignment failed: {reason} ({})", answer.to_json())]
    Failed {
        /// Why.
        reason: String,
        /// The gateway's whole answer.
        answer: Box<GatewayEvent>,
    },
    /// No `command_result` in time.
    #[error("no command_result for request {0} within {1:?} (is the gateway running on this broker and island?)")]
    NoAnswer(String, Duration),
}

/// What an assignment needs.
#[derive(Clone, Debug)]
pub struct Assignment {
    /// The board's unique ID.
    pub uid: Uid,
    /// The node ID to give it (already validated by [`crate::id::parse_sc_id`]).
    pub new_id: NodeId,
    /// Skip asking the gateway which IDs are taken.
    pub skip_duplicate_check: bool,
    /// How long to wait for each answer.
    pub timeout: Duration,
}

/// Runs one assignment; returns the gateway's `command_result` on success.
pub async fn assign(
    broker: &Broker,
    topics: &Topics,
    a: &Assignment,
) -> Result<CommandResult, AssignError> {
    let state_filter = format!("{}/+/state", topics.node_state_root);
    let mut session =
        Session::connect(broker, &[topics.events.clone(), state_filter], a.timeout).await?;
    let result = run(&mut session, topics, a).await;
    session.close().await;
    result
}

async fn run(
    session: &mut Session,
    topics: &Topics,
    a: &Assignment,
) -> Result<CommandResult, AssignError> {
    if !a.skip_duplicate_check {
        let taken = taken_ids(session, topics, a.timeout).await?;
        if taken.contains(&a.new_id) {
            return Err(IdError::Duplicate {
                id: a.new_id,
                source_desc: "the gateway lists a node with this ID".into(),
            }
            .into());
        }
    }
    let request_id = api::new_request_id("assign");
    session
        .publish(
            &topics.commands,
            api::assign_command(&a.uid, a.new_id, &request_id),
        )
        .await?;
    let deadline = Instant::now() + a.timeout;
    while let Some(msg) = session.recv_until(deadline).await? {
        if msg.topic != topics.events {
            continue;
        }
        // Anything that is not one of the gateway's events is not an answer.
        let Ok(event) = serde_json::from_slice::<GatewayEvent>(&msg.payload) else {
            continue;
        };
        match api::outcome(&event, &request_id) {
            Some(Outcome::Ok(result)) => return Ok(result),
            Some(Outcome::Failed { reason, answer }) => {
                return Err(AssignError::Failed { reason, answer })
            }
            None => {}
        }
    }
    Err(AssignError::NoAnswer(request_id, a.timeout))
}

/// IDs the gateway knows — online or lost, both still own their ID: its `node_list` answer to `list`,
/// plus every retained node-state topic seen meanwhile.
async fn taken_ids(
    session: &mut Session,
    topics: &Topics,
    timeout: Duration,
) -> Result<BTreeSet<NodeId>, AssignError> {
    let request_id = api::new_request_id("list");
    session
        .publish(&topics.commands, api::list_command(&request_id))
        .await?;
    let mut taken = BTreeSet::new();
    let deadline = Instant::now() + timeout;
    while let Some(msg) = session.recv_until(deadline).await? {
        if let Some(id) = api::id_from_state_topic(&topics.node_state_root, &msg.topic) {
            // An empty retained message deletes the state: that node is gone for good.
            if !msg.payload.is_empty() {
                taken.insert(id);
            }
            continue;
        }
        let Ok(event) = serde_json::from_slice::<GatewayEvent>(&msg.payload) else {
            continue;
        };
        if let Some(listed) = api::list_answer(&event, &request_id) {
            taken.extend(listed);
            return Ok(taken);
        }
        if let Some(Outcome::Failed { reason, answer }) = api::outcome(&event, &request_id) {
            return Err(AssignError::Failed {
                reason: format!("node list: {reason}"),
                answer,
            });
        }
    }
    Err(AssignError::NoList(timeout))
}
