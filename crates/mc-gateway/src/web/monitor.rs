//! What monitoring reads, open to anyone who reaches the port (no token, like the other reads):
//! `GET /metrics` (Prometheus text, [`crate::metrics`]), `GET /healthz` (liveness: the core task
//! answers) and `GET /readyz` (readiness: connected to the broker and the bus up). Each asks the
//! core task for a view, as the island view does; a core that does not answer within
//! `VIEW_TIMEOUT` makes all three answer `503`.

use std::sync::{atomic::Ordering, Arc};

use axum::{
    extract::State,
    http::{header, StatusCode},
    response::{IntoResponse, Response},
    routing::get,
    Router,
};
use serde::Serialize;

use super::{
    api::{error, json, App},
    snapshot, VIEW_TIMEOUT,
};
use crate::{
    feed::{self, CoreView},
    metrics::{Scrape, CONTENT_TYPE},
};

/// The monitoring routes.
pub fn routes() -> Router<Arc<App>> {
    Router::new()
        .route("/metrics", get(metrics))
        .route("/healthz", get(healthz))
        .route("/readyz", get(readyz))
}

/// A view of the core, or the `503` that says why there is none.
async fn view(app: &App, nodes: bool) -> Result<CoreView, Response> {
    match tokio::time::timeout(VIEW_TIMEOUT, feed::ask(&app.views, nodes)).await {
        Ok(Some(view)) => Ok(view),
        Ok(None) => Err(error(
            StatusCode::SERVICE_UNAVAILABLE,
            "the gateway is stopping",
        )),
        Err(_) => Err(error(
            StatusCode::SERVICE_UNAVAILABLE,
            "the gateway's core did not answer in time",
        )),
    }
}

/// `GET /metrics`.
async fn metrics(State(app): State<Arc<App>>) -> Response {
    let view = match view(&app, true).await {
        Ok(v) => v,
        Err(r) => return r,
    };
    let rates = *app.rates.lock().unwrap_or_else(|e| e.into_inner());
    let text = Scrape {
        view: &view,
        mqtt: &app.mqtt,
        counted: &app.counted,
        bitrate: app.info.bitrate,
        bus_load: rates.load_percent / 100.0,
        started: app.started,
        audit: app.audit.as_deref(),
    }
    .encode();
    (
        StatusCode::OK,
        [
            (header::CONTENT_TYPE, CONTENT_TYPE),
            (header::CACHE_CONTROL, "no-store"),
        ],
        text,
    )
        .into_response()
}

/// `GET /healthz`: `200 {"status":"ok"}` while the core task answers; while the audit trail cannot
/// record, the body says why in `audit` (still `200`: restarting the gateway would not help, and
/// its commands are still carried out and answered).
async fn healthz(State(app): State<Arc<App>>) -> Response {
    match view(&app, false).await {
        Ok(_) => {
            let problem = app.audit.as_ref().and_then(|a| a.problem());
            let body = match problem {
                None => r#"{"status":"ok"}"#.to_owned(),
                Some(why) => serde_json::json!({"status": "ok", "audit": why}).to_string(),
            };
            json(StatusCode::OK, body)
        }
        Err(r) => r,
    }
}

/// The body of `GET /readyz`.
#[derive(Serialize)]
struct Readiness {
    ready: bool,
    mqtt_connected: bool,
    bus_up: bool,
    /// What is not ready, in words (empty when ready).
    not_ready: Vec<String>,
}

/// `GET /readyz`: `200` when connected to the broker and the bus is up, else `503`; the body says
/// which (`docs/metrics.md`).
async fn readyz(State(app): State<Arc<App>>) -> Response {
    let view = match view(&app, false).await {
        Ok(v) => v,
        Err(r) => return r,
    };
    let link = app.mqtt.broker_link();
    let mqtt_connected = link.connected && app.mqtt.connected.load(Ordering::Relaxed);
    let bus_up = !view.bus.bus_down;
    let mut not_ready = Vec::new();
    if !mqtt_connected {
        let why = link
            .last_error
            .map_or_else(String::new, |e| format!(" ({e})"));
        not_ready.push(format!("mqtt: not connected to the broker{why}"));
    }
    if !bus_up {
        not_ready.push(format!("bus: {} is bus-off or down", app.info.link));
    }
    let ready = not_ready.is_empty();
    let status = if ready {
        StatusCode::OK
    } else {
        StatusCode::SERVICE_UNAVAILABLE
    };
    json(
        status,
        snapshot::to_json(&Readiness {
            ready,
            mqtt_connected,
            bus_up,
            not_ready,
        }),
    )
}
