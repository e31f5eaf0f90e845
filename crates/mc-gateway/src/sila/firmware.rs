//! `FirmwareUpdate` (`de.ihex/bench/FirmwareUpdate/v1`): the MQTT API's `fw_update` as a SiLA
//! observable command. `UpdateFirmware` sends the `fw_update` JSON into the core like every other
//! SiLA command and is confirmed once the core answers that the update started; from then on one
//! execution follows the update's `fw_progress` events (its intermediate responses and its
//! `ExecutionInfo`) and its `fw_report` (the result; an update stopped by `fw_cancel` finishes
//! with the error `Cancelled`). [`Execution`] is that state, fed the events, without I/O; the
//! adapter keeps the executions ([`Executions`], bounded) and hands each subscriber the latest
//! state through a `watch` channel, as the observable properties do.

use std::{
    collections::{BTreeMap, VecDeque},
    pin::Pin,
    sync::{Arc, Mutex},
    time::{Duration, Instant},
};

use futures_util::{Stream, StreamExt};
use ihex_gateway_core::bridge::FW_CANCELLED;
use serde_json::{json, Value};
use tokio::sync::{broadcast::error::RecvError, watch};
use tokio_stream::wrappers::WatchStream;
use tonic::{Request, Response, Status};

use super::{
    command::Failure,
    control::{vouched, Gateway},
    defined_error,
    lock::Locks,
    proto::{firmware_update as pb, framework},
    sila_error, undefined_error, validation_error, FIRMWARE_UPDATE,
};
use crate::feed::{Feed, Kind, Published};

/// How long a finished execution's result stays readable.
pub const KEEP_AFTER: Duration = Duration::from_secs(600);
/// Finished executions kept at most (the oldest goes first); one runs at a time.
pub const MAX_KEPT: usize = 16;

/// The command's identifier in the feature.
const COMMAND: &str = "UpdateFirmware";

/// How an update ended for one element: a line of `fw_report`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Outcome {
    /// Node ID in hex.
    pub element: String,
    /// `updated`, `refused`, … (docs/mqtt-api.md).
    pub outcome: String,
    /// The image's version.
    pub version: String,
    /// Why; empty for `updated`.
    pub reason: String,
}

/// Why an execution did not finish successfully, or why the command was not accepted.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// A parameter the gateway refused: the validation error naming it.
    Invalid {
        /// `Image` or `Elements`.
        parameter: &'static str,
        /// The gateway's reason.
        why: String,
    },
    /// One of the feature's defined execution errors.
    Defined {
        /// Its identifier (`UpdateRunning`, …).
        identifier: &'static str,
        /// What a person reads.
        message: String,
    },
    /// Anything else (the gateway stopping, its core not answering).
    Undefined(String),
}

impl Refusal {
    fn defined(identifier: &'static str, message: impl Into<String>) -> Refusal {
        Refusal::Defined {
            identifier,
            message: message.into(),
        }
    }

    /// As the SiLA error of `UpdateFirmware`.
    pub fn to_status(&self) -> Status {
        match self {
            Refusal::Invalid { parameter, why } => {
                validation_error(FIRMWARE_UPDATE, COMMAND, parameter, why)
            }
            Refusal::Defined {
                identifier,
                message,
            } => defined_error(FIRMWARE_UPDATE, identifier, message),
            Refusal::Undefined(m) => undefined_error(m),
        }
    }
}

/// The `fw_update` JSON for the parameters, answered under `request_id`, carrying the token
/// `lease` when given.
pub fn to_json(image: &str, elements: &str, request_id: &str, lease: Option<&str>) -> String {
    let mut v = json!({"cmd": "fw_update", "image": image, "nodes": elements,
                       "request_id": request_id});
    if let Some(token) = lease {
        v["lease"] = json!(token);
    }
    v.to_string()
}

/// What the core's answer to the `fw_update` (its `command_result` or `command_rejected`, the
/// event's JSON) means for the command: `Ok` when the update started.
pub fn started(answer: &str) -> Result<(), Refusal> {
    let v: Value = serde_json::from_str(answer).unwrap_or_default();
    let text = |k: &str| v["payload"][k].as_str().unwrap_or_default().to_owned();
    let reason = text("reason");
    match (v["event"].as_str(), text("result").as_str()) {
        (Some("command_result"), "ok") => Ok(()),
        (Some("command_result"), _) if reason.contains("already running") => Err(Refusal::defined(
            "UpdateRunning",
            format!("{reason}; wait for its end, or stop it with CancelController"),
        )),
        (Some("command_result"), _) => Err(Refusal::defined(
            "ImageNotUsable",
            format!("{reason} (upload the image to ihex/fw/upload/NAME over MQTT first)"),
        )),
        (Some("command_rejected"), _) if reason.starts_with("unknown node") => {
            Err(Refusal::defined(
                "UnknownElement",
                format!("{reason} (IslandControl's Elements property lists them)"),
            ))
        }
        (Some("command_rejected"), _) if reason.contains("an update is running") => {
            Err(Refusal::defined(
                "UpdateRunning",
                format!("{reason}, or stop it with CancelController"),
            ))
        }
        (Some("command_rejected"), _) if reason.contains("`image`") => Err(Refusal::Invalid {
            parameter: "Image",
            why: reason,
        }),
        (Some("command_rejected"), _) if reason.contains("`nodes`") => Err(Refusal::Invalid {
            parameter: "Elements",
            why: reason,
        }),
        (Some("command_rejected"), _) => Err(Refusal::defined("NotAllowed", reason)),
        _ => Err(Refusal::Undefined(format!(
            "the gateway answered the firmware update with {answer}"
        ))),
    }
}

/// Where an update is, as its execution shows it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct State {
    /// Counts the intermediate responses (a new one changes it).
    pub step: u64,
    /// The last element's progress: element, phase, percent.
    pub latest: Option<(String, String, i64)>,
    /// The share done, 0.0 to 1.0 (f64 bits, so that the state stays `Eq`).
    progress: u64,
    /// The estimated time left.
    pub remaining: Duration,
    /// The result, once the report is in.
    pub result: Option<Result<Vec<Outcome>, Refusal>>,
    /// When the report came in.
    pub finished_at: Option<Instant>,
}

impl State {
    /// The share done, 0.0 to 1.0.
    pub fn progress(&self) -> f64 {
        f64::from_bits(self.progress)
    }

    /// As `ExecutionInfo` at `now`: the lifetime is the estimated time left plus
    /// [`KEEP_AFTER`] while it runs, what remains of [`KEEP_AFTER`] after.
    pub fn info(&self, now: Instant) -> framework::ExecutionInfo {
        use framework::execution_info::CommandStatus;
        let (status, lifetime) = match (&self.result, self.finished_at) {
            (Some(r), Some(at)) => {
                let left = KEEP_AFTER.saturating_sub(now.saturating_duration_since(at));
                let status = if r.is_ok() {
                    CommandStatus::FinishedSuccessfully
                } else {
                    CommandStatus::FinishedWithError
                };
                (status, left)
            }
            _ => (CommandStatus::Running, self.remaining + KEEP_AFTER),
        };
        framework::ExecutionInfo {
            command_status: status as i32,
            progress_info: Some(framework::Real {
                value: self.progress(),
            }),
            estimated_remaining_time: Some(duration(self.remaining)),
            updated_lifetime_of_execution: Some(duration(lifetime)),
        }
    }
}

/// One update followed from its events. No I/O.
#[derive(Clone, Debug)]
pub struct Execution {
    request_id: String,
    started: Instant,
    percent: BTreeMap<String, i64>,
    state: State,
}

impl Execution {
    /// The update the core started for the `fw_update` with `request_id`, at `now`.
    pub fn new(request_id: String, now: Instant) -> Execution {
        Execution {
            request_id,
            started: now,
            percent: BTreeMap::new(),
            state: State {
                step: 0,
                latest: None,
                progress: 0f64.to_bits(),
                remaining: Duration::ZERO,
                result: None,
                finished_at: None,
            },
        }
    }

    /// The state now.
    pub fn state(&self) -> &State {
        &self.state
    }

    /// True once its report is in.
    pub fn is_finished(&self) -> bool {
        self.state.result.is_some()
    }

    /// An event the gateway published at `now` (its JSON); true when it changed the state (an
    /// `fw_progress` or the `fw_report` of this update).
    pub fn handle_event(&mut self, json: &str, now: Instant) -> bool {
        if self.is_finished() || !json.contains(&self.request_id) {
            return false;
        }
        let Ok(v) = serde_json::from_str::<Value>(json) else {
            return false;
        };
        let p = &v["payload"];
        if p["request_id"].as_str() != Some(self.request_id.as_str()) {
            return false;
        }
        let text = |v: &Value| v.as_str().unwrap_or_default().to_owned();
        match v["event"].as_str() {
            Some("fw_progress") => {
                let element = text(&p["node"]);
                let percent = p["percent"].as_i64().unwrap_or_default();
                self.percent.insert(element.clone(), percent);
                self.state.step += 1;
                self.state.latest = Some((element, text(&p["phase"]), percent));
                // The transfer is the long part; the restart and confirmation after it are
                // counted within the last percent.
                let sum: i64 = self.percent.values().sum();
                let share = (sum as f64 / (100.0 * self.percent.len() as f64)).min(0.99);
                self.state.progress = share.to_bits();
                let elapsed = now.saturating_duration_since(self.started);
                // At the rate so far; nothing while no element has any of it yet.
                self.state.remaining =
                    Duration::try_from_secs_f64(elapsed.as_secs_f64() * (1.0 - share) / share)
                        .unwrap_or(Duration::ZERO);
                true
            }
            Some("fw_report") => {
                let version = text(&p["version"]);
                let outcomes: Vec<Outcome> = p["nodes"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .map(|n| Outcome {
                        element: text(&n["node"]),
                        outcome: text(&n["outcome"]),
                        version: version.clone(),
                        reason: text(&n["reason"]),
                    })
                    .collect();
                let cancelled = outcomes.iter().any(|o| o.reason == FW_CANCELLED);
                self.state.result = Some(if cancelled {
                    let lines: Vec<String> = outcomes
                        .iter()
                        .map(|o| match o.reason.as_str() {
                            "" => format!("{} {}", o.element, o.outcome),
                            r => format!("{} {} ({r})", o.element, o.outcome),
                        })
                        .collect();
                    Err(Refusal::defined(
                        "Cancelled",
                        format!(
                            "the firmware update was cancelled before every element was done: {}; \
                             the elements it stopped run their image as before",
                            lines.join(", ")
                        ),
                    ))
                } else {
                    Ok(outcomes)
                });
                self.state.progress = 1f64.to_bits();
                self.state.remaining = Duration::ZERO;
                self.state.finished_at = Some(now);
                true
            }
            _ => false,
        }
    }
}

fn duration(d: Duration) -> framework::Duration {
    framework::Duration {
        seconds: i64::try_from(d.as_secs()).unwrap_or(i64::MAX),
        nanos: i32::try_from(d.subsec_nanos()).unwrap_or_default(),
    }
}

/// One execution as the server keeps it.
struct Kept {
    uuid: String,
    state: watch::Receiver<State>,
}

/// The executions of this server: the running one and up to [`MAX_KEPT`] finished ones, each
/// for [`KEEP_AFTER`].
#[derive(Default)]
pub struct Executions(Mutex<VecDeque<Kept>>);

impl Executions {
    fn lock(&self) -> std::sync::MutexGuard<'_, VecDeque<Kept>> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Keeps a new execution; drops the expired ones and the oldest beyond [`MAX_KEPT`].
    fn insert(&self, uuid: String, state: watch::Receiver<State>, now: Instant) {
        let mut kept = self.lock();
        kept.retain(|k| {
            k.state
                .borrow()
                .finished_at
                .is_none_or(|at| now.saturating_duration_since(at) < KEEP_AFTER)
        });
        while kept.len() >= MAX_KEPT {
            let Some(i) = kept
                .iter()
                .position(|k| k.state.borrow().finished_at.is_some())
            else {
                break;
            };
            kept.remove(i);
        }
        kept.push_back(Kept { uuid, state });
    }

    /// The state of the execution `uuid`, while it is kept.
    pub fn get(&self, uuid: &str, now: Instant) -> Option<watch::Receiver<State>> {
        let kept = self.lock();
        let k = kept.iter().find(|k| k.uuid == uuid)?;
        let expired = k
            .state
            .borrow()
            .finished_at
            .is_some_and(|at| now.saturating_duration_since(at) >= KEEP_AFTER);
        (!expired).then(|| k.state.clone())
    }

    /// The executions still running, by UUID.
    pub fn running(&self) -> Vec<String> {
        self.lock()
            .iter()
            .filter(|k| k.state.borrow().result.is_none())
            .map(|k| k.uuid.clone())
            .collect()
    }
}

/// The `FirmwareUpdate` feature.
pub struct FirmwareUpdate {
    /// The way into the core.
    pub gateway: Arc<Gateway>,
    /// The locks SiLA clients hold, for the `LockIdentifier` metadata.
    pub locks: Arc<Locks>,
    /// The executions, shared with `CancelController`.
    pub executions: Arc<Executions>,
}

/// A stream of a command's values.
type Values<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

/// The framework error for an execution UUID this server does not keep.
fn invalid_uuid(uuid: &str) -> Status {
    sila_error(framework::si_la_error::Error::FrameworkError(
        framework::FrameworkError {
            error_type: framework::framework_error::ErrorType::InvalidCommandExecutionUuid as i32,
            message: format!(
                "no UpdateFirmware execution {uuid:?} on this server (a finished one is kept for \
                 {} s)",
                KEEP_AFTER.as_secs()
            ),
        },
    ))
}

/// Reads the update's events from `live` into `execution` and hands every change to `tx`, until
/// its report (or the gateway stops).
async fn follow(
    mut execution: Execution,
    mut live: tokio::sync::broadcast::Receiver<Arc<Published>>,
    feed: Arc<Feed>,
    tx: watch::Sender<State>,
    cancel: tokio_util::sync::CancellationToken,
) {
    while !execution.is_finished() {
        let p = tokio::select! {
            () = cancel.cancelled() => return,
            p = live.recv() => p,
        };
        match p {
            Ok(p) => {
                if matches!(p.kind, Kind::Event("fw_progress" | "fw_report"))
                    && execution.handle_event(&p.json, Instant::now())
                {
                    tx.send_replace(execution.state().clone());
                }
            }
            // Progress may be lost; the report, if it was among the missed, is among the kept
            // events.
            Err(RecvError::Lagged(_)) => {
                for p in feed.recent_events(feed.seq()) {
                    if matches!(p.kind, Kind::Event("fw_report"))
                        && execution.handle_event(&p.json, Instant::now())
                    {
                        tx.send_replace(execution.state().clone());
                    }
                }
            }
            Err(RecvError::Closed) => return,
        }
    }
}

/// A parameter's value, or the validation error for a missing one.
fn given(value: Option<framework::String>, parameter: &str) -> Result<String, Status> {
    value.map(|v| v.value).ok_or_else(|| {
        validation_error(
            FIRMWARE_UPDATE,
            COMMAND,
            parameter,
            &format!("missing parameter {parameter}"),
        )
    })
}

impl FirmwareUpdate {
    /// The execution `uuid` names, or the framework's error.
    fn execution(
        &self,
        request: Request<framework::CommandExecutionUuid>,
    ) -> Result<watch::Receiver<State>, Status> {
        let uuid = request.into_inner().value;
        self.executions
            .get(&uuid, Instant::now())
            .ok_or_else(|| invalid_uuid(&uuid))
    }

    /// A stream of `to` of every new state, ending after the one that finished the execution
    /// (or when the gateway stops).
    fn stream<T: Send + 'static>(
        &self,
        rx: watch::Receiver<State>,
        to: impl Fn(&State) -> Option<T> + Send + 'static,
    ) -> Values<T> {
        let s = WatchStream::new(rx)
            .scan(false, |done, state| {
                let last = std::mem::replace(done, state.result.is_some());
                std::future::ready((!last).then_some(state))
            })
            .filter_map(move |state| std::future::ready(to(&state).map(Ok)))
            .take_until(self.gateway.cancel.clone().cancelled_owned());
        Box::pin(s)
    }
}

#[tonic::async_trait]
impl pb::firmware_update_server::FirmwareUpdate for FirmwareUpdate {
    async fn update_firmware(
        &self,
        request: Request<pb::UpdateFirmwareParameters>,
    ) -> Result<Response<framework::CommandConfirmation>, Status> {
        let user = vouched(&request);
        let lease = self
            .locks
            .lease_for(&request, &self.gateway, user.clone())
            .await?;
        let p = request.into_inner();
        let image = given(p.image, "Image")?;
        let elements = given(p.elements, "Elements")?;
        if !ihex_gateway_core::command::is_image_name(&image) {
            return Err(Refusal::Invalid {
                parameter: "Image",
                why: format!(
                    "Image must be a name of letters, digits, '.', '-', '_' (not starting with \
                     '.', at most 128 characters); got {image:?}"
                ),
            }
            .to_status());
        }
        // Subscribed before the command goes in: the update's first events follow its answer
        // at once.
        let live = self.gateway.feed.subscribe();
        let (request_id, answer) = self
            .gateway
            .ask(|id| to_json(&image, &elements, id, lease.as_deref()), user)
            .await
            .map_err(|f| match f {
                Failure::NotAllowed(m) => Refusal::defined("NotAllowed", m),
                f => Refusal::Undefined(f.message().to_owned()),
            })
            .map_err(|r| r.to_status())?;
        started(&answer).map_err(|r| r.to_status())?;
        let now = Instant::now();
        let execution = Execution::new(request_id, now);
        let (tx, rx) = watch::channel(execution.state().clone());
        let uuid = uuid::Uuid::new_v4().to_string();
        self.executions.insert(uuid.clone(), rx, now);
        tokio::spawn(follow(
            execution,
            live,
            self.gateway.feed.clone(),
            tx,
            self.gateway.cancel.clone(),
        ));
        Ok(Response::new(framework::CommandConfirmation {
            command_execution_uuid: Some(framework::CommandExecutionUuid { value: uuid }),
            lifetime_of_execution: Some(duration(KEEP_AFTER)),
        }))
    }

    type UpdateFirmware_InfoStream = Values<framework::ExecutionInfo>;

    async fn update_firmware_info(
        &self,
        request: Request<framework::CommandExecutionUuid>,
    ) -> Result<Response<Self::UpdateFirmware_InfoStream>, Status> {
        let rx = self.execution(request)?;
        Ok(Response::new(
            self.stream(rx, |s| Some(s.info(Instant::now()))),
        ))
    }

    type UpdateFirmware_IntermediateStream = Values<pb::UpdateFirmwareIntermediateResponses>;

    async fn update_firmware_intermediate(
        &self,
        request: Request<framework::CommandExecutionUuid>,
    ) -> Result<Response<Self::UpdateFirmware_IntermediateStream>, Status> {
        let rx = self.execution(request)?;
        let text = |v: &str| {
            Some(framework::String {
                value: v.to_owned(),
            })
        };
        Ok(Response::new(self.stream(rx, move |s| {
            // The finishing state brings no new progress.
            if s.result.is_some() {
                return None;
            }
            let (element, phase, percent) = s.latest.as_ref()?;
            Some(pb::UpdateFirmwareIntermediateResponses {
                element_id: text(element),
                phase: text(phase),
                percent: Some(framework::Integer { value: *percent }),
            })
        })))
    }

    async fn update_firmware_result(
        &self,
        request: Request<framework::CommandExecutionUuid>,
    ) -> Result<Response<pb::UpdateFirmwareResponses>, Status> {
        let rx = self.execution(request)?;
        let state = rx.borrow().clone();
        let text = |v: &str| {
            Some(framework::String {
                value: v.to_owned(),
            })
        };
        match state.result {
            None => Err(sila_error(framework::si_la_error::Error::FrameworkError(
                framework::FrameworkError {
                    error_type: framework::framework_error::ErrorType::CommandExecutionNotFinished
                        as i32,
                    message: "the firmware update is still running: UpdateFirmware_Info says when \
                              it has finished"
                        .into(),
                },
            ))),
            Some(Err(r)) => Err(r.to_status()),
            Some(Ok(outcomes)) => Ok(Response::new(pb::UpdateFirmwareResponses {
                outcomes: outcomes
                    .iter()
                    .map(|o| pb::update_firmware_responses::OutcomesStruct {
                        element_id: text(&o.element),
                        outcome: text(&o.outcome),
                        version: text(&o.version),
                        reason: text(&o.reason),
                    })
                    .collect(),
            })),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn progress(node: &str, phase: &str, percent: i64) -> String {
        json!({"event":"fw_progress","payload":{"request_id":"sila-ab-3","node":node,"phase":phase,"percent":percent}})
            .to_string()
    }

    fn report(reason: Option<&str>) -> String {
        json!({"event":"fw_report","payload":{"request_id":"sila-ab-3","image_id":"7a3c19e4","version":"1.3.0",
            "duration_ms":41230,"frames_sent":8560,"bus_share":50,"nodes":[
                {"node":"111","outcome":"updated","reason":null,"duration_ms":40110},
                {"node":"2","outcome":if reason.is_some() {"failed"} else {"updated"},"reason":reason,"duration_ms":310}]}})
        .to_string()
    }

    #[test]
    fn progress_and_report_become_the_executions_state() {
        let t0 = Instant::now();
        let mut e = Execution::new("sila-ab-3".into(), t0);
        assert!(e.handle_event(
            &progress("111", "receiving", 50),
            t0 + Duration::from_secs(10)
        ));
        assert_eq!(e.state().progress(), 0.5);
        assert_eq!(e.state().remaining, Duration::from_secs(10));
        assert!(e.handle_event(&progress("2", "begin", 0), t0 + Duration::from_secs(10)));
        assert_eq!(e.state().progress(), 0.25);
        assert_eq!(
            e.state().latest,
            Some(("2".into(), "begin".into(), 0)),
            "the latest element's progress"
        );
        let other = progress("2", "receiving", 5).replace("sila-ab-3", "sila-ab-4");
        assert!(!e.handle_event(&other, t0), "another update's progress");
        let info = e.state().info(t0);
        assert_eq!(info.command_status, 1, "running");
        assert!(e.handle_event(&report(None), t0 + Duration::from_secs(40)));
        let Some(Ok(outcomes)) = &e.state().result else {
            panic!("{:?}", e.state())
        };
        assert_eq!(
            outcomes[0],
            Outcome {
                element: "111".into(),
                outcome: "updated".into(),
                version: "1.3.0".into(),
                reason: String::new()
            }
        );
        let info = e.state().info(t0 + Duration::from_secs(40));
        assert_eq!(
            (info.command_status, info.progress_info.unwrap().value),
            (2, 1.0)
        );
        assert_eq!(info.updated_lifetime_of_execution.unwrap().seconds, 600);
        assert!(
            !e.handle_event(&progress("2", "receiving", 5), t0),
            "finished"
        );
    }

    #[test]
    fn a_cancelled_update_finishes_with_the_error_cancelled() {
        let t0 = Instant::now();
        let mut e = Execution::new("sila-ab-3".into(), t0);
        assert!(e.handle_event(&report(Some(FW_CANCELLED)), t0));
        let Some(Err(Refusal::Defined {
            identifier,
            message,
        })) = &e.state().result
        else {
            panic!("{:?}", e.state())
        };
        assert_eq!(*identifier, "Cancelled");
        assert!(
            message.contains("111 updated, 2 failed (cancelled by fw_cancel)"),
            "{message}"
        );
        assert_eq!(e.state().info(t0).command_status, 3, "finished with error");
    }

    #[test]
    fn the_cores_answers_become_the_documented_errors() {
        let result = |result: &str, reason: &str| {
            json!({"event":"command_result","payload":{"request_id":"s","cmd":"fw_update","node":"all",
                "result":result,"reason":reason}})
            .to_string()
        };
        let rejected = |reason: &str| {
            json!({"event":"command_rejected","payload":{"request_id":"s","reason":reason}})
                .to_string()
        };
        let id = |r: Result<(), Refusal>| match r {
            Ok(()) => "ok",
            Err(Refusal::Defined { identifier, .. }) => identifier,
            Err(Refusal::Invalid { parameter, .. }) => parameter,
            Err(Refusal::Undefined(_)) => "undefined",
        };
        assert_eq!(id(started(&result("ok", ""))), "ok");
        assert_eq!(
            id(started(&result(
                "failed",
                "x.ihex: no image of that name was uploaded"
            ))),
            "ImageNotUsable"
        );
        assert_eq!(
            id(started(&result("failed", "an update is already running"))),
            "UpdateRunning"
        );
        assert_eq!(
            id(started(&rejected("unknown node 5; known: 2, 111"))),
            "UnknownElement"
        );
        assert_eq!(
            id(started(&rejected(
                "fw_update: an update is running; wait for its fw_report"
            ))),
            "UpdateRunning"
        );
        assert_eq!(
            id(started(&rejected("fw_update: `nodes` must be \"all\" …"))),
            "Elements"
        );
        assert_eq!(
            id(started(&rejected("fw_update: every element is leased: …"))),
            "NotAllowed"
        );
        assert_eq!(id(started("{}")), "undefined");
    }

    #[test]
    fn finished_executions_are_kept_for_a_while_and_bounded() {
        let t0 = Instant::now();
        let kept = Executions::default();
        let finished = |at: Instant| {
            let mut e = Execution::new("r".into(), at);
            e.handle_event(&report(None).replace("sila-ab-3", "r"), at);
            watch::channel(e.state().clone()).1
        };
        kept.insert("old".into(), finished(t0), t0);
        assert!(kept
            .get("old", t0 + KEEP_AFTER - Duration::from_secs(1))
            .is_some());
        assert!(kept.get("old", t0 + KEEP_AFTER).is_none(), "expired");
        let running = watch::channel(Execution::new("q".into(), t0).state().clone()).1;
        kept.insert("running".into(), running, t0);
        for i in 0..MAX_KEPT * 2 {
            kept.insert(format!("f{i}"), finished(t0), t0);
        }
        assert_eq!(kept.lock().len(), MAX_KEPT);
        assert_eq!(kept.running(), vec!["running".to_owned()]);
        assert!(kept.get("nothing", t0).is_none());
    }
}
