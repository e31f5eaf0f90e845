//! `IslandControl` (`de.ihex/bench/IslandControl/v1`): the adapter between its gRPC calls and the
//! core. Commands go into the core's SiLA input as the MQTT API's JSON and wait for their answer
//! in the feed; properties read the model task's `watch` channels.

use std::{
    pin::Pin,
    sync::{
        atomic::{AtomicU64, Ordering},
        Arc,
    },
    time::{Duration, Instant},
};

use futures_util::{Stream, StreamExt};
use ihex_gateway_core::origin::{Interface, Origin};
use tokio::sync::{broadcast::error::RecvError, mpsc, watch};
use tokio_stream::wrappers::WatchStream;
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status};

use super::{
    command::{outcome, Failure, Request as Command},
    defined_error,
    island::{Docking, Element},
    lock::Locks,
    proto::{framework, island_control as pb},
    undefined_error, validation_error, ISLAND_CONTROL,
};
use crate::{
    feed::{Feed, Kind},
    mqtt::MqttInput,
};

/// The way into the core that `IslandControl` and `LockController` share: gateway commands on
/// the SiLA input, their answers read back from the feed.
pub struct Gateway {
    /// The core's publications, where commands' answers appear.
    pub feed: Arc<Feed>,
    /// The core's command input for SiLA clients.
    pub commands: mpsc::Sender<MqttInput>,
    /// Starts every request ID of this server (`sila-PREFIX-N`).
    pub prefix: String,
    /// The number of the next request.
    pub next: AtomicU64,
    /// How long a command waits for its answer.
    pub answer_wait: Duration,
    /// Ends the property streams and waiting commands when the gateway stops.
    pub cancel: CancellationToken,
}

/// The events that answer a command (`request_id` in their payload).
fn answers(kind: &Kind) -> bool {
    matches!(
        kind,
        Kind::Event("command_result" | "command_rejected" | "lease_granted" | "lease_ended")
    )
}

impl Gateway {
    /// Sends the gateway command `json(request_id)` into the core and waits for the one event
    /// that answers it; that event's JSON.
    pub async fn ask(
        &self,
        json: impl FnOnce(&str) -> String,
        user: Option<String>,
    ) -> Result<(String, Arc<str>), Failure> {
        let id = format!(
            "sila-{}-{}",
            self.prefix,
            self.next.fetch_add(1, Ordering::Relaxed)
        );
        let quoted = format!("\"{id}\"");
        // Subscribed before the command goes in, so its answer cannot come first.
        let mut live = self.feed.subscribe();
        let input = MqttInput::Command {
            payload: json(&id).into(),
            received: Instant::now(),
            retained: false,
            origin: Origin::new(Interface::Sila, user),
        };
        match self.commands.try_send(input) {
            Ok(()) => {}
            Err(mpsc::error::TrySendError::Full(_)) => {
                return Err(Failure::NotAllowed(
                    "the gateway's command queue for SiLA clients is full; try again".into(),
                ))
            }
            Err(mpsc::error::TrySendError::Closed(_)) => {
                return Err(Failure::NoAnswer("the gateway is stopping".into()))
            }
        }
        let answer = async {
            loop {
                match live.recv().await {
                    Ok(p) => {
                        if answers(&p.kind) && p.json.contains(&quoted) {
                            let v: Option<serde_json::Value> = serde_json::from_str(&p.json).ok();
                            let mine = v
                                .as_ref()
                                .and_then(|v| v.get("payload")?.get("request_id")?.as_str())
                                == Some(id.as_str());
                            if mine {
                                return Ok(p.json.clone());
                            }
                        }
                    }
                    // Its answer may be among the missed ones: the wait then ends at its limit.
                    Err(RecvError::Lagged(_)) => {}
                    Err(RecvError::Closed) => {
                        return Err(Failure::NoAnswer("the gateway is stopping".into()))
                    }
                }
            }
        };
        let answer = tokio::select! {
            r = tokio::time::timeout(self.answer_wait, answer) => r.unwrap_or_else(|_| {
                Err(Failure::NoAnswer(format!(
                    "the gateway's core gave no answer within {} ms; the command {id} may still \
                     be carried out (its command_result on MQTT tells)",
                    self.answer_wait.as_millis()
                )))
            }),
            // A stopping gateway answers no more; the call must not hold up its shutdown.
            () = self.cancel.cancelled() => {
                Err(Failure::NoAnswer("the gateway is stopping".into()))
            }
        };
        answer.map(|json| (id, json))
    }
}

/// The `IslandControl` feature.
pub struct Control {
    /// The way into the core.
    pub gateway: Arc<Gateway>,
    /// The locks SiLA clients hold, for the `LockIdentifier` metadata.
    pub locks: Arc<Locks>,
    /// The elements, kept current by the model task.
    pub elements: watch::Receiver<Arc<Vec<Arc<Element>>>>,
    /// The dockings, kept current by the model task.
    pub dockings: watch::Receiver<Arc<Vec<Docking>>>,
}

/// A property's stream of values.
type Values<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

fn text(v: impl Into<String>) -> Option<framework::String> {
    Some(framework::String { value: v.into() })
}

fn boolean(value: bool) -> Option<framework::Boolean> {
    Some(framework::Boolean { value })
}

fn integer(value: i64) -> Option<framework::Integer> {
    Some(framework::Integer { value })
}

/// A parameter's value, or the validation error for a missing one.
fn given<T>(value: Option<T>, command: &str, parameter: &str) -> Result<T, Status> {
    value.ok_or_else(|| {
        validation_error(
            ISLAND_CONTROL,
            command,
            parameter,
            &format!("missing parameter {parameter}"),
        )
    })
}

impl Control {
    /// Runs `command` through the core (carrying `lease`, the token of the lock the call names)
    /// and waits for its one answer.
    async fn execute(
        &self,
        command: Command,
        lease: Option<String>,
        user: Option<String>,
    ) -> Result<(), Failure> {
        command.check()?;
        let (id, json) = self
            .gateway
            .ask(|id| command.to_json(id, lease.as_deref()), user)
            .await?;
        outcome(&json, &id).unwrap_or_else(|| {
            Err(Failure::NoAnswer(format!(
                "the gateway answered the command {id} with {json}"
            )))
        })
    }

    /// [`Control::execute`] with its failure as the SiLA error.
    async fn run<T>(&self, command: Command, request: &Request<T>) -> Result<(), Status> {
        let name = command.identifier();
        let user = vouched(request);
        let lease = self
            .locks
            .lease_for(request, &self.gateway, user.clone())
            .await?;
        self.execute(command, lease, user)
            .await
            .map_err(|f| match f {
                Failure::Invalid { parameter, why } => {
                    validation_error(ISLAND_CONTROL, name, parameter, &why)
                }
                f => match f.error_identifier() {
                    Some(e) => defined_error(ISLAND_CONTROL, e, f.message()),
                    None => undefined_error(f.message()),
                },
            })
    }

    /// A property's stream: the current value, then every change, until the gateway stops.
    fn stream<T, U>(&self, rx: &watch::Receiver<Arc<Vec<T>>>, to: fn(&[T]) -> U) -> Values<U>
    where
        T: Send + Sync + 'static,
        U: Send + 'static,
    {
        let s = WatchStream::new(rx.clone())
            .map(move |v| Ok(to(v.as_slice())))
            .take_until(self.gateway.cancel.clone().cancelled_owned());
        Box::pin(s)
    }
}

macro_rules! element_struct {
    ($ty:path, $e:expr) => {{
        let e: &Element = $e;
        $ty {
            element_id: text(e.id.clone()),
            role: text(e.role_name().to_owned()),
            online: boolean(e.online),
            firmware: text(e.firmware.clone()),
            uid: text(e.uid.clone()),
            light: text(e.light.clone()),
            relay: boolean(e.relay),
            docking: text(e.docking_text()),
        }
    }};
}

fn element_states(elements: &[Arc<Element>]) -> pb::SubscribeElementStatesResponses {
    pb::SubscribeElementStatesResponses {
        element_states: elements
            .iter()
            .map(|e| {
                element_struct!(
                    pb::subscribe_element_states_responses::ElementStatesStruct,
                    e
                )
            })
            .collect(),
    }
}

fn dockings(dockings: &[Docking]) -> pb::SubscribeDockingsResponses {
    pb::SubscribeDockingsResponses {
        dockings: dockings
            .iter()
            .map(|d| pb::subscribe_dockings_responses::DockingsStruct {
                static_element: text(d.static_element.clone()),
                port: integer(d.port),
                mobile_element: text(d.mobile_element.clone()),
                mobile_port: integer(d.mobile_port),
            })
            .collect(),
    }
}

/// The identity a SiLA call carries (docs/audit.md): `local` for a client on this host, none
/// otherwise (client certificates are not asked for).
pub fn vouched<T>(request: &Request<T>) -> Option<String> {
    let peer = request.remote_addr()?;
    peer.ip().is_loopback().then(|| "local".to_owned())
}

#[tonic::async_trait]
impl pb::island_control_server::IslandControl for Control {
    async fn set_light(
        &self,
        request: Request<pb::SetLightParameters>,
    ) -> Result<Response<pb::SetLightResponses>, Status> {
        let p = request.get_ref().clone();
        let c = "SetLight";
        let command = Command::SetLight {
            element: given(p.element_id, c, "ElementId")?.value,
            color: given(p.color, c, "Color")?.value,
            brightness: given(p.brightness, c, "Brightness")?.value,
            blink_period: given(p.blink_period, c, "BlinkPeriod")?.value,
            blink_duty: given(p.blink_duty, c, "BlinkDuty")?.value,
        };
        self.run(command, &request).await?;
        Ok(Response::new(pb::SetLightResponses {}))
    }

    async fn set_power(
        &self,
        request: Request<pb::SetPowerParameters>,
    ) -> Result<Response<pb::SetPowerResponses>, Status> {
        let p = request.get_ref().clone();
        let c = "SetPower";
        let command = Command::SetPower {
            element: given(p.element_id, c, "ElementId")?.value,
            on: given(p.on, c, "On")?.value,
        };
        self.run(command, &request).await?;
        Ok(Response::new(pb::SetPowerResponses {}))
    }

    async fn beep(
        &self,
        request: Request<pb::BeepParameters>,
    ) -> Result<Response<pb::BeepResponses>, Status> {
        let p = request.get_ref().clone();
        let c = "Beep";
        let command = Command::Beep {
            element: given(p.element_id, c, "ElementId")?.value,
            frequency: given(p.frequency, c, "Frequency")?.value,
            count: given(p.count, c, "Count")?.value,
        };
        self.run(command, &request).await?;
        Ok(Response::new(pb::BeepResponses {}))
    }

    async fn identify(
        &self,
        request: Request<pb::IdentifyParameters>,
    ) -> Result<Response<pb::IdentifyResponses>, Status> {
        let p = request.get_ref().clone();
        let c = "Identify";
        let command = Command::Identify {
            element: given(p.element_id, c, "ElementId")?.value,
            seconds: given(p.seconds, c, "Seconds")?.value,
        };
        self.run(command, &request).await?;
        Ok(Response::new(pb::IdentifyResponses {}))
    }

    async fn get_elements(
        &self,
        _: Request<pb::GetElementsParameters>,
    ) -> Result<Response<pb::GetElementsResponses>, Status> {
        let elements = self.elements.borrow().clone();
        Ok(Response::new(pb::GetElementsResponses {
            elements: elements
                .iter()
                .map(|e| element_struct!(pb::get_elements_responses::ElementsStruct, e))
                .collect(),
        }))
    }

    type Subscribe_ElementStatesStream = Values<pb::SubscribeElementStatesResponses>;

    async fn subscribe_element_states(
        &self,
        _: Request<pb::SubscribeElementStatesParameters>,
    ) -> Result<Response<Self::Subscribe_ElementStatesStream>, Status> {
        Ok(Response::new(self.stream(&self.elements, element_states)))
    }

    type Subscribe_DockingsStream = Values<pb::SubscribeDockingsResponses>;

    async fn subscribe_dockings(
        &self,
        _: Request<pb::SubscribeDockingsParameters>,
    ) -> Result<Response<Self::Subscribe_DockingsStream>, Status> {
        Ok(Response::new(self.stream(&self.dockings, dockings)))
    }
}
