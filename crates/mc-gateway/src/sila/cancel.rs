//! `CancelController` (`org.silastandard/core.commands/CancelController/v1`): stops this server's
//! running observable command — the one firmware update `FirmwareUpdate` follows — with the MQTT
//! API's `fw_cancel`, through the same command path as every SiLA command (the `LockIdentifier`
//! metadata's lease token included). The execution then finishes with `FirmwareUpdate`'s error
//! `Cancelled`, once the update's `fw_report` is in.

use std::{sync::Arc, time::Instant};

use serde_json::{json, Value};
use tonic::{Request, Response, Status};

use super::{
    control::{vouched, Gateway},
    defined_error,
    firmware::Executions,
    lock::Locks,
    proto::cancel_controller as pb,
    undefined_error, validation_error, CANCEL_CONTROLLER,
};

/// The `CancelController` feature.
pub struct CancelControl {
    /// The way into the core.
    pub gateway: Arc<Gateway>,
    /// The locks SiLA clients hold, for the `LockIdentifier` metadata.
    pub locks: Arc<Locks>,
    /// `FirmwareUpdate`'s executions.
    pub executions: Arc<Executions>,
}

/// The error for an execution UUID that names no running command.
fn invalid_uuid(message: String) -> Status {
    defined_error(CANCEL_CONTROLLER, "InvalidCommandExecutionUUID", &message)
}

impl CancelControl {
    /// Sends `fw_cancel` (with the lease of the lock the call names) and reads its answer:
    /// `Ok(false)` when no update was running any more.
    async fn fw_cancel<T>(&self, request: &Request<T>) -> Result<bool, Status> {
        let user = vouched(request);
        let lease = self
            .locks
            .lease_for(request, &self.gateway, user.clone())
            .await?;
        let (_, answer) = self
            .gateway
            .ask(
                |id| {
                    let mut v = json!({"cmd": "fw_cancel", "request_id": id});
                    if let Some(token) = &lease {
                        v["lease"] = json!(token);
                    }
                    v.to_string()
                },
                user,
            )
            .await
            .map_err(|f| undefined_error(f.message()))?;
        let v: Value = serde_json::from_str(&answer).unwrap_or_default();
        let reason = v["payload"]["reason"].as_str().unwrap_or_default();
        match (v["event"].as_str(), v["payload"]["result"].as_str()) {
            (Some("command_result"), Some("ok")) => Ok(true),
            // It ended meanwhile (its report is in).
            _ if reason.contains("no firmware update is running") => Ok(false),
            // A lease on an element of the update, its image still read: the gateway's reason.
            _ => Err(undefined_error(&format!(
                "the gateway did not cancel the firmware update: {reason}"
            ))),
        }
    }
}

#[tonic::async_trait]
impl pb::cancel_controller_server::CancelController for CancelControl {
    async fn cancel_command(
        &self,
        request: Request<pb::CancelCommandParameters>,
    ) -> Result<Response<pb::CancelCommandResponses>, Status> {
        let uuid = request
            .get_ref()
            .command_execution_uuid
            .as_ref()
            .and_then(|u| u.uuid.as_ref())
            .map(|u| u.value.clone())
            .ok_or_else(|| {
                validation_error(
                    CANCEL_CONTROLLER,
                    "CancelCommand",
                    "CommandExecutionUUID",
                    "missing parameter CommandExecutionUUID",
                )
            })?;
        let running = self.executions.running().contains(&uuid);
        if !running {
            let why = match self.executions.get(&uuid, Instant::now()) {
                Some(_) => "has already finished (its result says how)",
                None => "is not known to this server",
            };
            return Err(invalid_uuid(format!(
                "the command execution {uuid} {why}: only a running FirmwareUpdate.UpdateFirmware \
                 can be cancelled"
            )));
        }
        if !self.fw_cancel(&request).await? {
            return Err(invalid_uuid(format!(
                "the command execution {uuid} finished before it could be cancelled (its result \
                 says how)"
            )));
        }
        Ok(Response::new(pb::CancelCommandResponses {}))
    }

    async fn cancel_all(
        &self,
        request: Request<pb::CancelAllParameters>,
    ) -> Result<Response<pb::CancelAllResponses>, Status> {
        // Only a firmware update runs long enough to be cancelled; other commands end with their
        // answer.
        if !self.executions.running().is_empty() {
            self.fw_cancel(&request).await?;
        }
        Ok(Response::new(pb::CancelAllResponses {}))
    }
}
