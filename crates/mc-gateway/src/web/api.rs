//! The island view's HTTP API: the snapshot, the event stream, the command input, and who may use
//! the last one.
//!
//! Controls (`POST /api/command`) are checked in this order: `403` when the view is read-only (a
//! non-loopback address without a token); `401` when a token is configured and the request does not
//! carry it as `Authorization: Bearer TOKEN`; `403` for a request from another site (an `Origin`
//! that is not this host) or, without a token, one that names a non-loopback host (a DNS name
//! rebound to 127.0.0.1); `415` unless the body is declared `application/json` (which also keeps
//! other sites' plain form posts out). Reading is open to anyone who reaches the port.

use ihex_gateway_core::{Interface, Origin};
use std::{
    convert::Infallible,
    sync::{Arc, Mutex},
    time::{Duration, Instant},
};

use axum::{
    body::Bytes,
    extract::{rejection::BytesRejection, DefaultBodyLimit, State},
    http::{header, HeaderMap, HeaderValue, StatusCode},
    response::{
        sse::{Event, KeepAlive, Sse},
        IntoResponse, Response,
    },
    routing::{get, post},
    Router,
};
use futures_util::{
    future::ready,
    stream::{self, Stream, StreamExt},
};
use tokio::sync::{mpsc, watch};
use tokio_stream::wrappers::{errors::BroadcastStreamRecvError, BroadcastStream, WatchStream};
use tokio_util::sync::CancellationToken;

use super::{assets, snapshot, Info, VIEW_TIMEOUT};
use crate::{
    config::web::Controls,
    feed::{self, Feed, Kind, Published, ViewRequest},
    mqtt::{MqttInput, MqttStats},
};

/// How long a browser waits before reconnecting a lost event stream (sent as the SSE `retry`).
pub const RECONNECT: Duration = Duration::from_secs(1);

/// What every handler shares.
pub struct App {
    pub(super) feed: Arc<Feed>,
    pub(super) views: mpsc::Sender<ViewRequest>,
    pub(super) commands: mpsc::Sender<MqttInput>,
    pub(super) mqtt: Arc<MqttStats>,
    pub(super) counted: crate::metrics::Counted,
    pub(super) audit: Option<Arc<crate::audit::AuditStatus>>,
    pub(super) started: Instant,
    pub(super) info: Info,
    pub(super) token: Option<String>,
    pub(super) health: watch::Receiver<Option<Arc<str>>>,
    pub(super) rates: Mutex<snapshot::Rates>,
    pub(super) cancel: CancellationToken,
}

/// The view's routes; command bodies up to `max_command` bytes reach the core (which answers an
/// oversized command with `command_rejected`, as it does on MQTT).
pub fn router(app: Arc<App>, max_command: usize) -> Router {
    Router::new()
        .route("/api/island", get(island))
        .route("/api/events", get(events))
        .route("/api/audit", get(audit))
        .route(
            "/api/command",
            post(command).layer(DefaultBodyLimit::max(max_command)),
        )
        .merge(super::monitor::routes())
        .merge(assets::routes())
        .with_state(app)
}

/// A JSON response.
pub(super) fn json(status: StatusCode, body: String) -> Response {
    (
        status,
        [
            (header::CONTENT_TYPE, "application/json"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        body,
    )
        .into_response()
}

/// An error as `{"error": "..."}`.
pub(super) fn error(status: StatusCode, why: &str) -> Response {
    json(
        status,
        snapshot::to_json(&serde_json::json!({ "error": why })),
    )
}

/// `GET /api/island`.
async fn island(State(app): State<Arc<App>>) -> Response {
    let view = tokio::time::timeout(VIEW_TIMEOUT, feed::ask(&app.views, true)).await;
    match view {
        Ok(Some(view)) => json(
            StatusCode::OK,
            snapshot::to_json(&snapshot::Snapshot::new(&app, view)),
        ),
        Ok(None) => error(StatusCode::SERVICE_UNAVAILABLE, "the gateway is stopping"),
        Err(_) => error(
            StatusCode::SERVICE_UNAVAILABLE,
            "the gateway's core did not answer in time",
        ),
    }
}

/// The server-sent event of one publication: `event` or `state`, numbered, the JSON as published.
fn sse_of(p: &Published) -> Event {
    let name = match p.kind {
        Kind::Event(_) => "event",
        Kind::State => "state",
        Kind::Leases => "leases",
        Kind::Procedures => "procedures",
    };
    Event::default()
        .event(name)
        .id(p.seq.to_string())
        .data(&*p.json)
}

/// `GET /api/events`: `hello` (with the current publication number and the reconnect delay), then
/// every publication and the `health` beats, until the gateway stops; `lagged` tells a reader that
/// fell too far behind how many publications it missed (it should fetch a new snapshot).
async fn events(State(app): State<Arc<App>>) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    // Subscribed before `hello` reads the number, so nothing falls between the two.
    let live = BroadcastStream::new(app.feed.subscribe()).map(|r| match r {
        Ok(p) => sse_of(&p),
        Err(BroadcastStreamRecvError::Lagged(n)) => Event::default()
            .event("lagged")
            .data(format!("{{\"missed\":{n}}}")),
    });
    let health = WatchStream::new(app.health.clone())
        .filter_map(|h| ready(h.map(|json| Event::default().event("health").data(&*json))));
    let hello = Event::default()
        .event("hello")
        .retry(RECONNECT)
        .data(format!("{{\"seq\":{}}}", app.feed.seq()));
    let s = stream::once(ready(hello))
        .chain(stream::select(live, health))
        .map(Ok)
        .take_until(app.cancel.clone().cancelled_owned());
    Sse::new(s).keep_alive(KeepAlive::default())
}

/// `GET /api/audit`: the audit trail's last records (oldest first) with their identities, and
/// whether it records (`docs/audit.md`); `{"on":false}` when it is off.
async fn audit(State(app): State<Arc<App>>) -> Response {
    let Some(status) = &app.audit else {
        return json(StatusCode::OK, r#"{"on":false,"records":[]}"#.to_owned());
    };
    let records: Vec<serde_json::Value> = crate::lock(&status.recent)
        .iter()
        .filter_map(|line| serde_json::from_slice(line).ok())
        .map(|mut v: serde_json::Value| {
            // The chain's link means nothing to a person.
            if let Some(o) = v.as_object_mut() {
                o.remove("prev");
            }
            v
        })
        .collect();
    let body = serde_json::json!({
        "on": true,
        "problem": status.problem(),
        "written": status.written.load(std::sync::atomic::Ordering::Relaxed),
        "lost": status.lost.load(std::sync::atomic::Ordering::Relaxed),
        "records": records,
    });
    json(StatusCode::OK, body.to_string())
}

/// `POST /api/command`: the body goes, unchanged, to the core's command input.
async fn command(
    State(app): State<Arc<App>>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Response {
    if let Err(refused) = authorize(app.info.controls, app.token.as_deref(), &headers) {
        return refused.into_response();
    }
    // axum's own answer (`413` over the body limit) is plain text; the API's errors are JSON.
    let body = match body {
        Ok(body) => body,
        Err(rejection) => return error(rejection.status(), &rejection.body_text()),
    };
    let json_body = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.split(';').next())
        .is_some_and(|v| v.trim().eq_ignore_ascii_case("application/json"));
    if !json_body {
        return error(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "send the command with Content-Type: application/json",
        );
    }
    // Whoever holds the token, or anyone on this host when the controls need none.
    let user = match app.info.controls {
        Controls::Token => "token",
        _ => "local",
    };
    let input = MqttInput::Command {
        payload: body,
        received: std::time::Instant::now(),
        retained: false,
        origin: Origin::new(Interface::Web, Some(user.to_owned())),
    };
    match app.commands.try_send(input) {
        Ok(()) => json(StatusCode::ACCEPTED, r#"{"accepted":true}"#.to_owned()),
        Err(mpsc::error::TrySendError::Full(_)) => error(
            StatusCode::SERVICE_UNAVAILABLE,
            "the gateway's command queue is full; try again",
        ),
        Err(mpsc::error::TrySendError::Closed(_)) => {
            error(StatusCode::SERVICE_UNAVAILABLE, "the gateway is stopping")
        }
    }
}

/// Why a request may not use the controls.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// The view is read-only (`403`).
    ReadOnly,
    /// No token where one is needed (`401`).
    NoToken,
    /// A token that is not the gateway's (`401`).
    WrongToken,
    /// An `Origin` other than this host (`403`).
    OtherSite,
    /// Without a token, a host name that is not loopback (`403`).
    NotLoopback,
}

impl Refusal {
    /// The status and the reason given.
    pub fn status_and_reason(self) -> (StatusCode, &'static str) {
        match self {
            Refusal::ReadOnly => (
                StatusCode::FORBIDDEN,
                "read-only: this view listens on a non-loopback address and the gateway has no \
                 --http-token; controls are off",
            ),
            Refusal::NoToken => (
                StatusCode::UNAUTHORIZED,
                "this gateway's controls need its token: Authorization: Bearer TOKEN",
            ),
            Refusal::WrongToken => (StatusCode::UNAUTHORIZED, "wrong token"),
            Refusal::OtherSite => (
                StatusCode::FORBIDDEN,
                "a command from another site is refused",
            ),
            Refusal::NotLoopback => (
                StatusCode::FORBIDDEN,
                "without a token, controls answer only to a loopback host name (localhost, \
                 127.0.0.1, [::1])",
            ),
        }
    }
}

impl IntoResponse for Refusal {
    fn into_response(self) -> Response {
        let (status, why) = self.status_and_reason();
        let mut r = error(status, why);
        if status == StatusCode::UNAUTHORIZED {
            r.headers_mut().insert(
                header::WWW_AUTHENTICATE,
                HeaderValue::from_static("Bearer realm=\"ihex\""),
            );
        }
        r
    }
}

/// Whether a request with `headers` may use controls of kind `controls` (see the module docs).
pub fn authorize(
    controls: Controls,
    token: Option<&str>,
    headers: &HeaderMap,
) -> Result<(), Refusal> {
    let text = |name: header::HeaderName| {
        headers
            .get(name)
            .and_then(|v| v.to_str().ok())
            .map(str::trim)
    };
    match (controls, token) {
        (Controls::ReadOnly, _) | (Controls::Token, None) => return Err(Refusal::ReadOnly),
        (Controls::Token, Some(token)) => {
            let given = text(header::AUTHORIZATION)
                .and_then(|v| v.strip_prefix("Bearer "))
                .map(str::trim)
                .ok_or(Refusal::NoToken)?;
            if !constant_time_eq::constant_time_eq(given.as_bytes(), token.as_bytes()) {
                return Err(Refusal::WrongToken);
            }
        }
        (Controls::Open, _) => {}
    }
    let host = text(header::HOST).unwrap_or_default();
    if let Some(origin) = text(header::ORIGIN) {
        let origin_host = origin
            .split_once("://")
            .map_or(origin, |(_, rest)| rest)
            .trim_end_matches('/');
        if !origin_host.eq_ignore_ascii_case(host) {
            return Err(Refusal::OtherSite);
        }
    }
    if controls == Controls::Open && !is_loopback_host(host) {
        return Err(Refusal::NotLoopback);
    }
    Ok(())
}

/// True for a `Host` header naming this machine: `localhost`, `127.x.x.x` or `[::1]`, with or
/// without a port.
fn is_loopback_host(host: &str) -> bool {
    let name = match host.strip_prefix('[') {
        Some(v6) => v6.split(']').next().unwrap_or_default(),
        None => host.rsplit_once(':').map_or(host, |(h, _)| h),
    };
    name.eq_ignore_ascii_case("localhost")
        || name
            .parse::<std::net::IpAddr>()
            .is_ok_and(|ip| ip.is_loopback())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, HeaderValue::from_str(v).unwrap());
        }
        h
    }

    #[test]
    fn who_may_use_the_controls() {
        use Refusal::*;
        let local = [("host", "127.0.0.1:8080")];
        /// Controls, token, request headers, verdict.
        type Case<'a> = (
            Controls,
            Option<&'a str>,
            &'a [(&'static str, &'a str)],
            Result<(), Refusal>,
        );
        let cases: &[Case] = &[
            (Controls::Open, None, &local, Ok(())),
            (
                Controls::Open,
                None,
                &[
                    ("host", "localhost:8080"),
                    ("origin", "http://localhost:8080"),
                ],
                Ok(()),
            ),
            (
                Controls::Open,
                None,
                &[("host", "evil.example:8080")],
                Err(NotLoopback),
            ),
            (Controls::Open, None, &[], Err(NotLoopback)),
            (
                Controls::Open,
                None,
                &[
                    ("host", "127.0.0.1:8080"),
                    ("origin", "http://evil.example"),
                ],
                Err(OtherSite),
            ),
            (Controls::ReadOnly, None, &local, Err(ReadOnly)),
            (
                Controls::ReadOnly,
                None,
                &[("host", "10.0.0.2:8080"), ("authorization", "Bearer x")],
                Err(ReadOnly),
            ),
            (
                Controls::Token,
                Some("s3cret"),
                &[("host", "10.0.0.2:8080")],
                Err(NoToken),
            ),
            (
                Controls::Token,
                Some("s3cret"),
                &[("host", "10.0.0.2"), ("authorization", "Basic s3cret")],
                Err(NoToken),
            ),
            (
                Controls::Token,
                Some("s3cret"),
                &[("host", "10.0.0.2"), ("authorization", "Bearer s3cre")],
                Err(WrongToken),
            ),
            (
                Controls::Token,
                Some("s3cret"),
                &[("host", "10.0.0.2"), ("authorization", "Bearer s3cret")],
                Ok(()),
            ),
            (
                Controls::Token,
                Some("s3cret"),
                &[
                    ("host", "pi.lab:8080"),
                    ("authorization", "Bearer s3cret"),
                    ("origin", "http://pi.lab:8080"),
                ],
                Ok(()),
            ),
            (
                Controls::Token,
                Some("s3cret"),
                &[
                    ("host", "pi.lab:8080"),
                    ("authorization", "Bearer s3cret"),
                    ("origin", "http://other.lab:8080"),
                ],
                Err(OtherSite),
            ),
        ];
        for (controls, token, h, want) in cases {
            assert_eq!(
                authorize(*controls, *token, &headers(h)),
                *want,
                "{controls:?} {token:?} {h:?}"
            );
        }
        for (refusal, status) in [
            (ReadOnly, 403),
            (NoToken, 401),
            (WrongToken, 401),
            (OtherSite, 403),
            (NotLoopback, 403),
        ] {
            let r = refusal.into_response();
            assert_eq!(r.status().as_u16(), status, "{refusal:?}");
            assert_eq!(
                r.headers().contains_key(header::WWW_AUTHENTICATE),
                status == 401,
                "{refusal:?}"
            );
        }
    }

    #[test]
    fn loopback_host_names() {
        for h in [
            "localhost",
            "localhost:8080",
            "127.0.0.1:80",
            "127.1.2.3",
            "[::1]:8080",
            "[::1]",
            "LocalHost:1",
        ] {
            assert!(is_loopback_host(h), "{h}");
        }
        for h in [
            "",
            "evil.example:8080",
            "192.168.1.5:8080",
            "[::2]:80",
            "localhost.evil.example",
            "0.0.0.0:8080",
        ] {
            assert!(!is_loopback_host(h), "{h}");
        }
    }
}
