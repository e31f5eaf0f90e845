//! The island view (cargo feature `web`, on by default): a live web page and a small JSON API served
//! by the gateway itself with axum, described in `docs/web.md`.
//!
//! - `GET /` and its assets ([`assets`]): plain HTML, CSS and JavaScript compiled into the binary.
//! - `GET /api/island` ([`api`]): the island as a versioned JSON snapshot ([`snapshot`]).
//! - `GET /api/events`: server-sent events — every publication of the core exactly as it went to
//!   MQTT (taken from [`crate::feed::Feed`], never serialised again), and once a second the health
//!   of the gateway and the bus.
//! - `POST /api/command`: a command in the JSON of the command topic, handed to the core's one
//!   command entry point; its answer is the usual `command_result` event.
//! - `GET /metrics`, `GET /healthz`, `GET /readyz` ([`monitor`]): Prometheus metrics and the
//!   liveness and readiness checks (`docs/metrics.md`).
//!
//! The view only reads the core through [`crate::feed`] and writes through the core's command
//! input, so it cannot make the core wait: a view request or a command that finds its queue full is
//! answered with `503`.

pub mod api;
pub mod assets;
pub mod monitor;
pub mod snapshot;

use std::{
    net::SocketAddr,
    sync::{Arc, Mutex},
    time::{Duration, Instant},
};

use tokio::{
    net::TcpListener,
    sync::{mpsc, watch},
    task::JoinSet,
};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::{
    config::{
        web::{Controls, Layout},
        Config,
    },
    error::WebError,
    feed::{self, Feed, ViewRequest},
    mqtt::{MqttInput, MqttStats},
};
use snapshot::{Health, Rates};

/// How often the page gets the gateway's and the bus's health (and so how often it hears from a
/// gateway that has nothing else to say: the page declares it lost after a few missed beats).
pub const HEALTH_PERIOD: Duration = Duration::from_secs(1);
/// How long a request waits for the core's answer before it gives up with `503`.
const VIEW_TIMEOUT: Duration = Duration::from_secs(2);

/// A bound island view, ready to be served.
pub struct Web {
    listener: TcpListener,
    addr: SocketAddr,
    info: Info,
    token: Option<String>,
    max_command: usize,
}

/// What the view says about the gateway that does not change while it runs.
#[derive(Clone, Debug)]
pub struct Info {
    /// The island name, if any.
    pub island: Option<String>,
    /// The CAN link as the start-up line names it.
    pub link: String,
    /// The bitrate the bus load is computed for, bit/s.
    pub bitrate: u32,
    /// Who may use the controls.
    pub controls: Controls,
    /// Configured positions of static elements (configuration over island file).
    pub layout: Layout,
}

/// The running gateway's parts the view uses.
pub struct Parts {
    /// The publications.
    pub feed: Arc<Feed>,
    /// Views of the core.
    pub views: mpsc::Sender<ViewRequest>,
    /// The core's command input for the view.
    pub commands: mpsc::Sender<MqttInput>,
    /// The MQTT task's counters.
    pub mqtt: Arc<MqttStats>,
    /// The core task's counts for the metrics.
    pub counted: crate::metrics::Counted,
    /// The audit trail's status and last lines, when it is on.
    pub audit: Option<Arc<crate::audit::AuditStatus>>,
}

impl Web {
    /// Listens where `config` says. `None` when the view is off, or when the default address is
    /// taken (a warning says so: a second gateway on one machine still runs); a configured address
    /// that cannot be used is an error.
    pub async fn bind(config: &Config) -> Result<Option<Web>, WebError> {
        let web = &config.web;
        let Some(listen) = web.listen else {
            return Ok(None);
        };
        let listener = match TcpListener::bind(listen).await {
            Ok(l) => l,
            Err(source) if !web.configured => {
                warn!(
                    addr = %listen,
                    error = %source,
                    "island view off: its default address is taken (choose one with --http ADDR:PORT)"
                );
                return Ok(None);
            }
            Err(source) => {
                return Err(WebError::Bind {
                    addr: listen,
                    source,
                })
            }
        };
        let addr = listener.local_addr().map_err(|source| WebError::Bind {
            addr: listen,
            source,
        })?;
        Ok(Some(Web {
            listener,
            addr,
            info: Info {
                island: config.island.clone(),
                link: config.can.link.to_string(),
                bitrate: config.can.bitrate,
                controls: web.controls(addr),
                layout: web.layout.clone(),
            },
            token: web.token.clone(),
            max_command: max_body(&config.bridge),
        }))
    }

    /// Adds the positions an island file gives (the simulated island's); the configuration's own
    /// positions win, and an island-file position already taken by a configured element is dropped
    /// (that element is then arranged automatically).
    pub fn with_island_layout(mut self, island: Layout) -> Web {
        let layout = &mut self.info.layout;
        for (id, hex) in island {
            if !layout.contains_key(&id) && !layout.values().any(|h| *h == hex) {
                layout.insert(id, hex);
            }
        }
        self
    }

    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The address a person opens: the listening address, or the loopback one when it listens on
    /// every interface.
    pub fn url(&self) -> String {
        url(self.addr)
    }

    /// Serves the view and its once-a-second health on `tasks` until `cancel`.
    pub fn spawn(self, parts: Parts, tasks: &mut JoinSet<()>, cancel: CancellationToken) {
        let (health_tx, health_rx) = watch::channel(None);
        let state = Arc::new(api::App {
            feed: parts.feed,
            views: parts.views,
            commands: parts.commands,
            mqtt: parts.mqtt,
            counted: parts.counted,
            audit: parts.audit,
            started: Instant::now(),
            info: self.info,
            token: self.token,
            health: health_rx,
            rates: Mutex::new(Rates::default()),
            cancel: cancel.clone(),
        });
        info!(
            url = %url(self.addr),
            controls = ?state.info.controls,
            "island view listening"
        );
        tasks.spawn(health_task(state.clone(), health_tx, cancel.clone()));
        let router = api::router(state, self.max_command);
        let listener = self.listener;
        tasks.spawn(async move {
            let serve = axum::serve(listener, router)
                .with_graceful_shutdown(cancel.clone().cancelled_owned());
            if let Err(e) = serve.await {
                // The listener failed for good (axum retries accept errors itself); the gateway
                // keeps running without its view rather than stopping the bench.
                warn!(error = %e, "island view stopped");
                cancel.cancelled().await;
            }
        });
    }
}

/// `http://ADDR/`, with the loopback address for a wildcard one.
pub fn url(addr: SocketAddr) -> String {
    let mut a = addr;
    if a.ip().is_unspecified() {
        a.set_ip(if a.is_ipv4() {
            std::net::Ipv4Addr::LOCALHOST.into()
        } else {
            std::net::Ipv6Addr::LOCALHOST.into()
        });
    }
    format!("http://{a}/")
}

/// Once every [`HEALTH_PERIOD`]: a view of the core (with every node's age when a page listens),
/// the bus rates since the previous one, and the health message for the pages.
async fn health_task(
    app: Arc<api::App>,
    health: watch::Sender<Option<Arc<str>>>,
    cancel: CancellationToken,
) {
    let mut tick = tokio::time::interval(HEALTH_PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = tick.tick() => {}
        }
        let with_nodes = app.feed.readers() > 0;
        let view = tokio::time::timeout(VIEW_TIMEOUT, feed::ask(&app.views, with_nodes)).await;
        let Ok(Some(view)) = view else {
            // The core is busy or stopping: the pages hear nothing and say so.
            continue;
        };
        let rates = app.update_rates(&view);
        let h = Health::new(&app, &view, rates);
        health.send_replace(Some(Arc::from(snapshot::to_json(&h))));
    }
}

/// The largest request body handed to the core as a command: well above the command limit, so an
/// oversized command is answered with the core's `command_rejected` reason, like one over MQTT.
fn max_body(bridge: &ihex_gateway_core::BridgeConfig) -> usize {
    bridge.max_command_bytes.saturating_mul(4).max(1 << 20)
}
