//! The SiLA 2 server (`docs/sila.md`): the island as a lab-automation server that orchestrators
//! discover and drive. gRPC (tonic) with the code generated from the vendored protos in `sila/`
//! ([`proto`]); the features `SiLAService` ([`service`]) and our `IslandControl` ([`control`]) and
//! `FirmwareUpdate` ([`firmware`]), whose definitions (`sila/features/*.sila.xml`) are served
//! verbatim; `LockController` ([`lock`]) maps SiLA's server lock onto a gateway lease on the whole
//! island, `CancelController` ([`cancel`]) stops the running firmware update.
//!
//! `IslandControl`'s commands take the island view's path into the core: the JSON command of the
//! MQTT API ([`command`]) on an input of their own (so they count as [`Interface::Sila`]), their
//! answer read back from the core's [`Feed`]. Its properties come from the model task, which keeps
//! the [`island::Island`] current from the same feed and hands it to every subscriber through a
//! `watch` channel: a slow or vanished client only ever misses intermediate values and never
//! holds up the gateway.
//!
//! [`Interface::Sila`]: ihex_gateway_core::origin::Interface::Sila

pub mod announce;
pub mod cancel;
pub mod codec;
pub mod command;
pub mod control;
pub mod firmware;
pub mod identity;
pub mod island;
pub mod lock;
pub mod service;
pub mod tls;

use std::{net::SocketAddr, path::PathBuf, sync::Arc, time::Duration};

use prost::Message;
use tokio::{
    net::TcpListener,
    sync::{broadcast::error::RecvError, mpsc, watch},
    task::JoinSet,
};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::{
    config::{sila::Security, Config},
    error::SilaError,
    feed::{self, Feed, Kind, ViewRequest},
    mqtt::MqttInput,
};
use island::{Docking, Element, Island};

/// The generated gRPC code, in modules that follow the protos' packages.
#[allow(
    missing_docs,
    non_camel_case_types,
    clippy::all,
    clippy::pedantic,
    rustdoc::all
)]
pub mod proto {
    /// `sila2.*`.
    pub mod sila2 {
        /// `sila2.org.*`.
        pub mod org {
            /// `sila2.org.silastandard`: the framework's types.
            pub mod silastandard {
                tonic::include_proto!("sila2.org.silastandard");
                /// `sila2.org.silastandard.core.*`.
                pub mod core {
                    /// `SiLAService`.
                    pub mod silaservice {
                        /// Version 1.
                        pub mod v1 {
                            tonic::include_proto!("sila2.org.silastandard.core.silaservice.v1");
                        }
                    }
                    /// `LockController`.
                    pub mod lockcontroller {
                        /// Version 1.
                        pub mod v1 {
                            tonic::include_proto!("sila2.org.silastandard.core.lockcontroller.v1");
                        }
                    }
                    /// `sila2.org.silastandard.core.commands.*`.
                    pub mod commands {
                        /// `CancelController`.
                        pub mod cancelcontroller {
                            /// Version 1.
                            pub mod v1 {
                                tonic::include_proto!(
                                    "sila2.org.silastandard.core.commands.cancelcontroller.v1"
                                );
                            }
                        }
                    }
                }
            }
        }
        /// `sila2.de.*`.
        pub mod de {
            /// `sila2.de.ihex.*`.
            pub mod ihex {
                /// `sila2.de.ihex.bench.*`.
                pub mod bench {
                    /// `IslandControl`.
                    pub mod islandcontrol {
                        /// Version 1.
                        pub mod v1 {
                            tonic::include_proto!("sila2.de.ihex.bench.islandcontrol.v1");
                        }
                    }
                    /// `FirmwareUpdate`.
                    pub mod firmwareupdate {
                        /// Version 1.
                        pub mod v1 {
                            tonic::include_proto!("sila2.de.ihex.bench.firmwareupdate.v1");
                        }
                    }
                }
            }
        }
    }
    pub use sila2::de::ihex::bench::firmwareupdate::v1 as firmware_update;
    pub use sila2::de::ihex::bench::islandcontrol::v1 as island_control;
    pub use sila2::org::silastandard as framework;
    pub use sila2::org::silastandard::core::commands::cancelcontroller::v1 as cancel_controller;
    pub use sila2::org::silastandard::core::lockcontroller::v1 as lock_controller;
    pub use sila2::org::silastandard::core::silaservice::v1 as sila_service;
}

/// `SiLAService`'s feature definition, served verbatim.
pub const SILA_SERVICE_FDL: &str = include_str!("../../sila/features/SiLAService.sila.xml");
/// `IslandControl`'s feature definition, served verbatim.
pub const ISLAND_CONTROL_FDL: &str = include_str!("../../sila/features/IslandControl.sila.xml");
/// `LockController`'s feature definition, served verbatim.
pub const LOCK_CONTROLLER_FDL: &str = include_str!("../../sila/features/LockController.sila.xml");
/// `FirmwareUpdate`'s feature definition, served verbatim.
pub const FIRMWARE_UPDATE_FDL: &str = include_str!("../../sila/features/FirmwareUpdate.sila.xml");
/// `CancelController`'s feature definition, served verbatim.
pub const CANCEL_CONTROLLER_FDL: &str =
    include_str!("../../sila/features/CancelController.sila.xml");
/// `FirmwareUpdate`'s fully qualified identifier.
pub const FIRMWARE_UPDATE: &str = "de.ihex/bench/FirmwareUpdate/v1";
/// `CancelController`'s fully qualified identifier.
pub const CANCEL_CONTROLLER: &str = "org.silastandard/core.commands/CancelController/v1";
/// `LockController`'s fully qualified identifier.
pub const LOCK_CONTROLLER: &str = "org.silastandard/core/LockController/v1";
/// `SiLAService`'s fully qualified identifier.
pub const SILA_SERVICE: &str = "org.silastandard/core/SiLAService/v1";
/// `IslandControl`'s fully qualified identifier.
pub const ISLAND_CONTROL: &str = "de.ihex/bench/IslandControl/v1";
/// Commands from SiLA clients waiting for the core.
pub const SILA_INPUTS: usize = 64;
/// Calls one client connection may have open at once (each subscription is one for as long as
/// it lasts). tonic's default is no limit; 128 leaves room for any one orchestrator's
/// subscriptions while bounding what a single connection can make the gateway hold.
pub const STREAMS_PER_CONNECTION: u32 = 128;
/// The HTTP/2 flow-control window the server offers each call: how much a client may send it
/// before the server has read it. SiLA parameters are small; hyper's default (1 MiB) would let
/// every call park a mebibyte in the gateway. 64 KiB is HTTP/2's own initial window.
const STREAM_WINDOW: u32 = 64 * 1024;
/// The same for a whole connection (all its calls together).
const CONNECTION_WINDOW: u32 = 256 * 1024;
/// How much longer than the command timeout a command waits for its answer (the core answers
/// every command within its timeout; this covers a core busy with a burst).
const ANSWER_MARGIN: Duration = Duration::from_secs(5);

/// The SiLA error of a failed call: gRPC `ABORTED` with the `SiLAError` message, base64-encoded,
/// as the details (the SiLA 2 wire mapping).
pub fn sila_error(error: proto::framework::si_la_error::Error) -> tonic::Status {
    use base64::Engine as _;
    let bytes = proto::framework::SiLaError { error: Some(error) }.encode_to_vec();
    tonic::Status::aborted(base64::engine::general_purpose::STANDARD.encode(bytes))
}

/// A defined execution error of `feature` (fully qualified) named `identifier`.
pub fn defined_error(feature: &str, identifier: &str, message: &str) -> tonic::Status {
    sila_error(proto::framework::si_la_error::Error::DefinedExecutionError(
        proto::framework::DefinedExecutionError {
            error_identifier: format!("{feature}/DefinedExecutionError/{identifier}"),
            message: message.to_owned(),
        },
    ))
}

/// A validation error naming `parameter` of `command` of `feature` (both as in the definition).
pub fn validation_error(
    feature: &str,
    command: &str,
    parameter: &str,
    message: &str,
) -> tonic::Status {
    sila_error(proto::framework::si_la_error::Error::ValidationError(
        proto::framework::ValidationError {
            parameter: format!("{feature}/Command/{command}/Parameter/{parameter}"),
            message: message.to_owned(),
        },
    ))
}

/// An undefined execution error (what no defined error describes).
pub fn undefined_error(message: &str) -> tonic::Status {
    sila_error(
        proto::framework::si_la_error::Error::UndefinedExecutionError(
            proto::framework::UndefinedExecutionError {
                message: message.to_owned(),
            },
        ),
    )
}

/// What the server shares with the rest of the gateway while it runs.
pub struct Parts {
    /// The core's publications.
    pub feed: Arc<Feed>,
    /// Views of the core.
    pub views: mpsc::Sender<ViewRequest>,
    /// The core's command input for SiLA clients.
    pub commands: mpsc::Sender<MqttInput>,
}

/// A SiLA server whose address is bound and whose identity is read, ready to serve.
pub struct Sila {
    listener: TcpListener,
    addr: SocketAddr,
    identity: identity::Identity,
    /// Where the identity is kept (`None`: nowhere, a name change lasts until the gateway stops).
    identity_file: Option<PathBuf>,
    description: String,
    answer_wait: Duration,
    /// The certificate and key it serves TLS with; `None`: plaintext.
    tls: Option<tls::Pem>,
    /// Announced over mDNS.
    announce: bool,
}

impl Sila {
    /// Listens where `config` says and reads (or makes) the server's identity. `None` when the
    /// server is off, or when the default address is taken (a warning says so).
    pub async fn bind(config: &Config) -> Result<Option<Sila>, SilaError> {
        let sila = &config.sila;
        let Some(listen) = sila.listen else {
            return Ok(None);
        };
        let listener = match TcpListener::bind(listen).await {
            Ok(l) => l,
            Err(source) if !sila.configured => {
                warn!(
                    addr = %listen,
                    error = %source,
                    "SiLA server off: its default address is taken (choose one with --sila ADDR:PORT)"
                );
                return Ok(None);
            }
            Err(source) => {
                return Err(SilaError::Bind {
                    addr: listen,
                    source,
                })
            }
        };
        let addr = listener.local_addr().map_err(|source| SilaError::Bind {
            addr: listen,
            source,
        })?;
        let island = config.island.as_deref();
        let default_name = match island {
            Some(i) => format!("iHEX {i}"),
            None => "iHEX island".to_owned(),
        };
        let dir =
            crate::config::state_dir(std::env::var_os("XDG_STATE_HOME"), std::env::var_os("HOME"));
        let (mut identity, identity_file) = match dir {
            Some(dir) => {
                let path = identity::file(&dir, island);
                (identity::load_or_create(&path, &default_name)?, Some(path))
            }
            None => {
                warn!("SiLA server: neither XDG_STATE_HOME nor HOME is set: its UUID changes at every start");
                (identity::Identity::new(default_name), None)
            }
        };
        let tls = match &sila.security {
            Security::Insecure => None,
            Security::Files { cert, key } => Some(tls::Pem {
                cert: tls::read(cert)?,
                key: tls::read(key)?,
            }),
            Security::SelfSigned => {
                Some(self_signed(&mut identity, identity_file.as_deref(), addr)?)
            }
        };
        let description = format!(
            "iHEX island{}: hexagonal bench elements on a CAN bus, served by mc-gateway {}",
            island.map(|i| format!(" {i}")).unwrap_or_default(),
            env!("CARGO_PKG_VERSION")
        );
        Ok(Some(Sila {
            listener,
            addr,
            identity,
            identity_file,
            description,
            answer_wait: config.bridge.command_timeout + ANSWER_MARGIN,
            tls,
            announce: sila.announce,
        }))
    }

    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Where clients reach it, for people: `grpcs://ADDR:PORT`, or `grpc://ADDR:PORT` in
    /// plaintext.
    pub fn url(&self) -> String {
        let scheme = if self.tls.is_some() { "grpcs" } else { "grpc" };
        format!("{scheme}://{}", self.addr)
    }

    /// Serves SiLA clients and keeps the island model current on `tasks` until `cancel`.
    pub fn spawn(self, parts: Parts, tasks: &mut JoinSet<()>, cancel: CancellationToken) {
        let (elements_tx, elements) = watch::channel(Arc::new(Vec::new()));
        let (dockings_tx, dockings) = watch::channel(Arc::new(Vec::new()));
        let views = parts.views.clone();
        tasks.spawn(model(
            parts.feed.clone(),
            parts.views,
            elements_tx,
            dockings_tx,
            cancel.clone(),
        ));
        info!(
            addr = %self.addr,
            uuid = %self.identity.uuid,
            name = %self.identity.name,
            tls = self.tls.is_some(),
            "SiLA server listening"
        );
        if self.announce {
            let what = announce::Announcement {
                uuid: self.identity.uuid.clone(),
                version: env!("CARGO_PKG_VERSION").to_owned(),
                server_name: self.identity.name.clone(),
                description: self.description.clone(),
                ca: self.tls.as_ref().map(|t| t.cert.clone()),
            };
            let host = tls::host_name().unwrap_or_else(|| "ihex-gateway".to_owned());
            let announcer = announce::Announcer::start(self.addr, &host, &what);
            let until = cancel.clone();
            // Withdrawn (goodbye packets) when the gateway stops.
            tasks.spawn(async move {
                until.cancelled().await;
                drop(announcer);
            });
        }
        let prefix: String = self.identity.uuid.chars().take(8).collect();
        let service = service::Service::new(self.identity, self.identity_file, self.description);
        let gateway = Arc::new(control::Gateway {
            feed: parts.feed,
            commands: parts.commands,
            prefix,
            next: Default::default(),
            answer_wait: self.answer_wait,
            cancel: cancel.clone(),
        });
        let locks = Arc::new(lock::Locks::default());
        let lock = lock::LockControl {
            gateway: gateway.clone(),
            locks: locks.clone(),
            views,
        };
        let executions = Arc::new(firmware::Executions::default());
        let firmware = firmware::FirmwareUpdate {
            gateway: gateway.clone(),
            locks: locks.clone(),
            executions: executions.clone(),
        };
        let cancel_control = cancel::CancelControl {
            gateway: gateway.clone(),
            locks: locks.clone(),
            executions,
        };
        let control = control::Control {
            gateway,
            locks,
            elements,
            dockings,
        };
        let incoming =
            tonic::transport::server::TcpIncoming::from(self.listener).with_nodelay(Some(true));
        // Flow control with fixed windows (adaptive windows grow them to the bandwidth-delay
        // product, which on a LAN buys nothing for messages this small).
        let mut builder = tonic::transport::Server::builder()
            .initial_stream_window_size(STREAM_WINDOW)
            .initial_connection_window_size(CONNECTION_WINDOW)
            .http2_adaptive_window(Some(false))
            .max_concurrent_streams(STREAMS_PER_CONNECTION);
        if let Some(pem) = &self.tls {
            let identity = tonic::transport::Identity::from_pem(&pem.cert, &pem.key);
            let config = tonic::transport::ServerTlsConfig::new().identity(identity);
            builder = match builder.tls_config(config) {
                Ok(b) => b,
                Err(e) => {
                    // Checked in `bind`; a failure here leaves the server off, the gateway on.
                    tracing::error!(error = %e, "SiLA server off: its TLS configuration is unusable");
                    return;
                }
            };
        }
        let server = builder
            .add_service(proto::sila_service::si_la_service_server::SiLaServiceServer::new(service))
            .add_service(
                proto::island_control::island_control_server::IslandControlServer::new(control),
            )
            .add_service(
                proto::lock_controller::lock_controller_server::LockControllerServer::new(lock),
            )
            .add_service(
                proto::firmware_update::firmware_update_server::FirmwareUpdateServer::new(firmware),
            )
            .add_service(
                proto::cancel_controller::cancel_controller_server::CancelControllerServer::new(
                    cancel_control,
                ),
            )
            .serve_with_incoming_shutdown(incoming, cancel.cancelled_owned());
        tasks.spawn(async move {
            if let Err(e) = server.await {
                tracing::error!(error = %e, "SiLA server failed");
            }
        });
    }
}

/// The self-signed certificate kept beside the identity file, made (again) when there is none or
/// when the names it must carry changed; without an identity file one for this run only.
fn self_signed(
    identity: &mut identity::Identity,
    file: Option<&std::path::Path>,
    addr: SocketAddr,
) -> Result<tls::Pem, SilaError> {
    let names = tls::names(
        addr,
        tls::host_name().as_deref(),
        &tls::interface_addresses(),
    );
    let make = |identity: &identity::Identity| {
        tls::self_signed(&identity.uuid, &names).map_err(SilaError::Tls)
    };
    let Some(file) = file else {
        return make(identity);
    };
    let (cert, key) = tls::files(file);
    if identity.cert_names == names && cert.is_file() && key.is_file() {
        return Ok(tls::Pem {
            cert: tls::read(&cert)?,
            key: tls::read(&key)?,
        });
    }
    let pem = make(identity)?;
    let kept = tls::save(&pem, (&cert, &key)).and_then(|()| {
        identity.cert_names = names;
        identity::save(file, identity)
    });
    match kept {
        Ok(()) => info!(
            cert = %cert.display(),
            "SiLA server: new self-signed certificate (clients trust this file)"
        ),
        Err(e) => warn!(error = %e, "SiLA server: its certificate is for this run only"),
    }
    Ok(pem)
}

/// The model task: keeps the island's elements and dockings current from the feed and hands
/// every change to the subscribers' `watch` channels.
async fn model(
    feed: Arc<Feed>,
    views: mpsc::Sender<ViewRequest>,
    elements: watch::Sender<Arc<Vec<Arc<Element>>>>,
    dockings: watch::Sender<Arc<Vec<Docking>>>,
    cancel: CancellationToken,
) {
    let mut live = feed.subscribe();
    let mut island = Island::default();
    let mut resync = true;
    loop {
        if resync {
            resync = false;
            let view = tokio::select! {
                _ = cancel.cancelled() => return,
                v = feed::ask(&views, true) => v,
            };
            let docs = view.and_then(|v| v.nodes).unwrap_or_default();
            island.handle_snapshot(&docs);
            show(&mut island, &elements, &dockings);
        }
        let changed = tokio::select! {
            _ = cancel.cancelled() => return,
            r = live.recv() => match r {
                Ok(p) => match p.kind {
                    Kind::State => p.state.as_ref().is_some_and(|s| island.handle_state(s)),
                    // The one event that changes the properties; the others are not read.
                    Kind::Event("node_forgotten") => island.handle_forgotten(&p.json),
                    Kind::Event(_) => false,
                    // Leases and procedures are not part of IslandControl's properties.
                    Kind::Leases | Kind::Procedures => false,
                },
                // Missed documents: start again from a whole view.
                Err(RecvError::Lagged(_)) => {
                    resync = true;
                    false
                }
                Err(RecvError::Closed) => {
                    cancel.cancelled().await;
                    return;
                }
            },
        };
        if changed {
            show(&mut island, &elements, &dockings);
        }
    }
}

/// Hands the island's current elements and dockings to the subscribers (dockings only when they
/// changed, so a docking stream's values are dockings and undockings).
fn show(
    island: &mut Island,
    elements: &watch::Sender<Arc<Vec<Arc<Element>>>>,
    dockings: &watch::Sender<Arc<Vec<Docking>>>,
) {
    elements.send_replace(Arc::new(island.elements()));
    if !island.take_dockings_changed() {
        return;
    }
    let d = island.dockings();
    dockings.send_if_modified(|old| {
        if **old == d {
            return false;
        }
        *old = Arc::new(d);
        true
    });
}
