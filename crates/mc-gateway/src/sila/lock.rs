//! `LockController` (`org.silastandard/core/LockController/v1`): a SiLA client's lock on the server
//! is a gateway lease on the whole island, taken and released through the same command path as
//! MQTT's `lease` and `release`. The lease's token stays inside the server, found by the client's
//! lock identifier; the commands of `IslandControl`, `FirmwareUpdate` and `CancelController`
//! carry it when their call's `LockIdentifier` metadata names the lock; such a call also renews
//! the lease for the lock's `Timeout` (SiLA's timeout counts from the last call with the lock
//! identifier). `IsLocked` is true while the island holds any lease, whoever took it.

use std::{
    sync::{Arc, Mutex},
    time::{Duration, Instant},
};

use prost::Message;
use serde_json::{json, Value};
use tokio::sync::mpsc;
use tonic::{Request, Response, Status};

use super::{
    command::Failure,
    control::{vouched, Gateway},
    defined_error,
    proto::{framework, lock_controller as pb},
    sila_error, undefined_error, validation_error, CANCEL_CONTROLLER, FIRMWARE_UPDATE,
    ISLAND_CONTROL, LOCK_CONTROLLER,
};
use crate::feed::{self, ViewRequest};

/// The gRPC header that carries the `LockIdentifier` metadata (SiLA's mapping: the feature's
/// identifier, lower case, dots and slashes as dashes; a binary header with the protobuf message).
pub const LOCK_IDENTIFIER_HEADER: &str =
    "sila-org.silastandard-core-lockcontroller-v1-metadata-lockidentifier-bin";

/// The longest lease the gateway grants, s (`Timeout` 0, "no timeout", gets it).
const LONGEST: i64 = 86_400;

/// How long after a renewal a call with the lock identifier renews the lease again (a burst of
/// calls renews it once).
const RENEW_AFTER: Duration = Duration::from_secs(1);

/// The lock a SiLA client holds: its identifier, the lease's token, its time to live and when
/// it was last given that time.
#[derive(Clone, Debug)]
struct Held {
    identifier: String,
    token: String,
    seconds: i64,
    renewed: Instant,
}

/// The lock taken through this server, if any (one: the lock is on the whole island).
#[derive(Debug, Default)]
pub struct Locks(Mutex<Option<Held>>);

impl Locks {
    fn held(&self) -> Option<Held> {
        self.0.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    fn set(&self, held: Option<Held>) {
        *self.0.lock().unwrap_or_else(|e| e.into_inner()) = held;
    }

    /// [`Locks::lease_of`], and the lease renewed for the lock's `Timeout` from now (through the
    /// command path, as `user`) when the call names the lock and it was not renewed within the
    /// last second. A renewal the gateway refuses (the lease ended meanwhile) is left for the
    /// command itself to tell.
    pub async fn lease_for<T>(
        &self,
        request: &Request<T>,
        gateway: &Gateway,
        user: Option<String>,
    ) -> Result<Option<String>, Status> {
        let Some(token) = self.lease_of(request)? else {
            return Ok(None);
        };
        let seconds = {
            let mut held = self.0.lock().unwrap_or_else(|e| e.into_inner());
            match held.as_mut() {
                Some(h) if h.token == token && h.renewed.elapsed() >= RENEW_AFTER => {
                    h.renewed = Instant::now();
                    Some(h.seconds)
                }
                _ => None,
            }
        };
        if let Some(seconds) = seconds {
            let renewed = gateway
                .ask(
                    |id| {
                        json!({"cmd": "renew", "lease": token, "seconds": seconds,
                               "request_id": id})
                        .to_string()
                    },
                    user,
                )
                .await;
            if let Ok((_, json)) = renewed {
                if answer(&json).0 != "lease_granted" {
                    tracing::debug!(answer = %json, "the SiLA lock's lease was not renewed");
                }
            }
        }
        Ok(Some(token))
    }

    /// The lease token the call's `LockIdentifier` metadata names: `None` without the metadata,
    /// `InvalidLockIdentifier` when it names no lock of this server.
    pub fn lease_of<T>(&self, request: &Request<T>) -> Result<Option<String>, Status> {
        let Some(value) = request.metadata().get_bin(LOCK_IDENTIFIER_HEADER) else {
            return Ok(None);
        };
        let identifier = value
            .to_bytes()
            .ok()
            .and_then(|b| pb::MetadataLockIdentifier::decode(b.as_ref()).ok())
            .and_then(|m| m.lock_identifier)
            .ok_or_else(|| {
                sila_error(framework::si_la_error::Error::FrameworkError(
                    framework::FrameworkError {
                        error_type: framework::framework_error::ErrorType::InvalidMetadata as i32,
                        message: "the LockIdentifier metadata is not a \
                                  Metadata_LockIdentifier message with a String"
                            .into(),
                    },
                ))
            })?
            .value;
        match self.held() {
            Some(h) if h.identifier == identifier => Ok(Some(h.token)),
            Some(_) => Err(invalid_identifier(
                "the LockIdentifier metadata names another lock than the one held on this server",
            )),
            None => Err(invalid_identifier(
                "the LockIdentifier metadata names no lock: the server is not locked through \
                 LockServer (its lock may have ended: see IsLocked)",
            )),
        }
    }
}

fn invalid_identifier(message: &str) -> Status {
    defined_error(LOCK_CONTROLLER, "InvalidLockIdentifier", message)
}

/// The `LockController` feature.
pub struct LockControl {
    /// The way into the core.
    pub gateway: Arc<Gateway>,
    /// The lock this server holds, shared with `IslandControl`.
    pub locks: Arc<Locks>,
    /// Views of the core (whether any lease is held).
    pub views: mpsc::Sender<ViewRequest>,
}

/// The payload of the event that answered a command, and the event's name.
fn answer(json: &str) -> (String, Value) {
    let v: Value = serde_json::from_str(json).unwrap_or_default();
    let event = v["event"].as_str().unwrap_or_default().to_owned();
    (event, v["payload"].clone())
}

/// A failure of the way into the core as the SiLA error.
fn status(f: &Failure) -> Status {
    undefined_error(f.message())
}

#[tonic::async_trait]
impl pb::lock_controller_server::LockController for LockControl {
    async fn lock_server(
        &self,
        request: Request<pb::LockServerParameters>,
    ) -> Result<Response<pb::LockServerResponses>, Status> {
        let user = vouched(&request);
        let client = request
            .remote_addr()
            .map_or_else(|| "client".to_owned(), |a| a.ip().to_string());
        let p = request.into_inner();
        let missing = |parameter: &str| {
            validation_error(
                LOCK_CONTROLLER,
                "LockServer",
                parameter,
                &format!("missing parameter {parameter}"),
            )
        };
        let identifier = p
            .lock_identifier
            .ok_or_else(|| missing("LockIdentifier"))?
            .value;
        let timeout = p.timeout.ok_or_else(|| missing("Timeout"))?.value;
        if identifier.is_empty() {
            return Err(validation_error(
                LOCK_CONTROLLER,
                "LockServer",
                "LockIdentifier",
                "LockIdentifier must not be empty",
            ));
        }
        if !(0..=LONGEST).contains(&timeout) {
            return Err(validation_error(
                LOCK_CONTROLLER,
                "LockServer",
                "Timeout",
                &format!("Timeout must be 0 (the longest lease, {LONGEST} s) to {LONGEST} s; got {timeout}"),
            ));
        }
        if self.locks.held().is_some() && self.is_locked().await {
            return Err(defined_error(
                LOCK_CONTROLLER,
                "ServerAlreadyLocked",
                "this server is already locked by a SiLA client (UnlockServer with its identifier ends it)",
            ));
        }
        let seconds = if timeout == 0 { LONGEST } else { timeout };
        let owner = format!("sila:{client}");
        let (_, json) = self
            .gateway
            .ask(
                |id| {
                    json!({"cmd": "lease", "owner": owner, "nodes": "all", "seconds": seconds,
                           "note": "SiLA LockServer", "request_id": id})
                    .to_string()
                },
                user,
            )
            .await
            .map_err(|f| status(&f))?;
        match answer(&json) {
            (e, p) if e == "lease_granted" => {
                let token = p["token"].as_str().unwrap_or_default().to_owned();
                self.locks.set(Some(Held {
                    identifier,
                    token,
                    seconds,
                    renewed: Instant::now(),
                }));
                Ok(Response::new(pb::LockServerResponses {}))
            }
            (_, p) => Err(defined_error(
                LOCK_CONTROLLER,
                "ServerAlreadyLocked",
                p["reason"]
                    .as_str()
                    .unwrap_or("the gateway refused the lease"),
            )),
        }
    }

    async fn unlock_server(
        &self,
        request: Request<pb::UnlockServerParameters>,
    ) -> Result<Response<pb::UnlockServerResponses>, Status> {
        let user = vouched(&request);
        let identifier = request
            .into_inner()
            .lock_identifier
            .ok_or_else(|| {
                validation_error(
                    LOCK_CONTROLLER,
                    "UnlockServer",
                    "LockIdentifier",
                    "missing parameter LockIdentifier",
                )
            })?
            .value;
        let Some(held) = self.locks.held() else {
            return Err(defined_error(
                LOCK_CONTROLLER,
                "ServerNotLocked",
                "this server is not locked by a SiLA client",
            ));
        };
        if held.identifier != identifier {
            return Err(invalid_identifier(
                "UnlockServer's LockIdentifier is not the one the server was locked with",
            ));
        }
        let token = held.token.clone();
        let (_, json) = self
            .gateway
            .ask(
                |id| json!({"cmd": "release", "lease": token, "request_id": id}).to_string(),
                user,
            )
            .await
            .map_err(|f| status(&f))?;
        self.locks.set(None);
        match answer(&json) {
            (e, _) if e == "lease_ended" => Ok(Response::new(pb::UnlockServerResponses {})),
            // The lease ended by itself (expired or broken): the server was not locked any more.
            (_, p) => Err(defined_error(
                LOCK_CONTROLLER,
                "ServerNotLocked",
                &format!(
                    "the lock had already ended ({})",
                    p["reason"]
                        .as_str()
                        .unwrap_or("the gateway refused the release")
                ),
            )),
        }
    }

    async fn get_is_locked(
        &self,
        _: Request<pb::GetIsLockedParameters>,
    ) -> Result<Response<pb::GetIsLockedResponses>, Status> {
        Ok(Response::new(pb::GetIsLockedResponses {
            is_locked: Some(framework::Boolean {
                value: self.is_locked().await,
            }),
        }))
    }

    async fn get_fcp_affected_by_metadata_lock_identifier(
        &self,
        _: Request<pb::GetFcpAffectedByMetadataLockIdentifierParameters>,
    ) -> Result<Response<pb::GetFcpAffectedByMetadataLockIdentifierResponses>, Status> {
        Ok(Response::new(
            pb::GetFcpAffectedByMetadataLockIdentifierResponses {
                affected_calls: [ISLAND_CONTROL, FIRMWARE_UPDATE, CANCEL_CONTROLLER]
                    .into_iter()
                    .map(|f| framework::String {
                        value: f.to_owned(),
                    })
                    .collect(),
            },
        ))
    }
}

impl LockControl {
    /// Whether the island holds any lease now.
    async fn is_locked(&self) -> bool {
        feed::ask(&self.views, false)
            .await
            .is_some_and(|v| !v.leases.leases.is_empty())
    }
}
