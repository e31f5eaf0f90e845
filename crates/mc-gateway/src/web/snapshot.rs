//! The JSON the island view serves besides the publications themselves: the snapshot of
//! `GET /api/island` ([`Snapshot`], versioned by [`VERSION`]) and the once-a-second `health` event
//! ([`Health`]); `docs/web.md` documents both, and `tests/web.rs` checks the snapshot's shape on
//! the demo island.

use std::{collections::BTreeMap, time::Instant};

use ihex_gateway_core::{
    bridge::{BusHealth, CommandCounters},
    event::NodeState,
    lease::LeasesDocument,
    procedure::ProceduresDocument,
};
use serde::Serialize;
use serde_json::value::RawValue;

use super::api::App;
use crate::{
    config::web::{Controls, Hex},
    feed::{unix_ms, CoreView},
};

/// Version of the snapshot's shape: raised when a field changes meaning or disappears (added fields
/// do not raise it).
pub const VERSION: u32 = 1;

/// `GET /api/island`: everything the page draws, as of one moment of the core.
#[derive(Serialize)]
pub struct Snapshot<'a> {
    /// [`VERSION`].
    pub version: u32,
    /// The last publication this snapshot reflects: live messages numbered up to it are already in.
    pub seq: u64,
    /// When it was taken, milliseconds since the Unix epoch.
    pub time_ms: u64,
    /// The island name, `null` without one.
    pub island: Option<&'a str>,
    /// Who may use the controls: `open`, `token` or `read_only`.
    pub controls: Controls,
    /// Configured hexagon positions of static elements, by node ID.
    pub layout: BTreeMap<String, Hex>,
    /// The gateway's health.
    pub gateway: GatewayHealth,
    /// The bus's health.
    pub bus: BusView<'a>,
    /// Every known node's state document, as the retained topics carry it (ages as of `time_ms`).
    pub nodes: Vec<NodeState>,
    /// The last events (up to [`crate::feed::RECENT_EVENTS`]), newest first.
    pub events: Vec<TimelineEntry>,
    /// The leases held now, as the retained leases document carries them.
    pub leases: LeasesDocument,
    /// The procedures running now, as the retained procedures document carries them.
    pub procedures: ProceduresDocument,
}

/// One event of the timeline.
#[derive(Serialize)]
pub struct TimelineEntry {
    /// Its publication number.
    pub seq: u64,
    /// When it was published, milliseconds since the Unix epoch.
    pub time_ms: u64,
    /// The event exactly as published on the events topic.
    pub event: Box<RawValue>,
}

/// The gateway's own health.
#[derive(Serialize)]
pub struct GatewayHealth {
    /// The gateway's version.
    pub version: &'static str,
    /// Connected to the MQTT broker right now.
    pub mqtt_connected: bool,
    /// Connections to the broker after the first one.
    pub mqtt_reconnects: u64,
    /// Seconds since the gateway started running.
    pub uptime_s: u64,
    /// Commands in flight and how the others ended (`in_flight`, `sent`, `ok`, `refused`,
    /// `timeout`, `failed`, `rejected`).
    pub commands: CommandCounters,
}

/// The bus as the gateway sees it.
#[derive(Serialize)]
pub struct BusView<'a> {
    /// The CAN link (`SocketCAN can0`, `simulated island (built in)`).
    pub link: &'a str,
    /// The bitrate the load is computed for, bit/s.
    pub bitrate: u32,
    /// Frames per second through the gateway over the last health period (received and sent).
    pub frames_per_s: f64,
    /// Those frames' bits per second as a percentage of the bitrate (without stuff bits: a lower
    /// bound of the gateway's share of the bus).
    pub load_percent: f64,
    /// Counters since start (`bus_down`, `error_frames`, `bus_off`, ...).
    #[serde(flatten)]
    pub health: BusHealth,
}

/// The `health` server-sent event.
#[derive(Serialize)]
pub struct Health<'a> {
    /// When the core was asked, milliseconds since the Unix epoch.
    pub time_ms: u64,
    /// The gateway's health.
    pub gateway: GatewayHealth,
    /// The bus's health.
    pub bus: BusView<'a>,
    /// Milliseconds since each node was last heard, by node ID (only while a page listens).
    pub last_seen_ms: Option<BTreeMap<String, u64>>,
}

/// Frames and bits per second between two views of the bus counters.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rates {
    prev: Option<(Instant, u64, u64)>,
    /// Frames per second over the last interval.
    pub frames_per_s: f64,
    /// Bits per second over the last interval as a percentage of the bitrate.
    pub load_percent: f64,
}

impl Rates {
    /// Takes the counters seen at `at` (frames and bits since start); the rates cover the interval
    /// since the previous call (none before the second call).
    pub fn update(&mut self, at: Instant, frames: u64, bits: u64, bitrate: u32) {
        if let Some((t, f, b)) = self.prev {
            let secs = at.saturating_duration_since(t).as_secs_f64();
            if secs > 0.0 {
                self.frames_per_s = frames.saturating_sub(f) as f64 / secs;
                self.load_percent =
                    bits.saturating_sub(b) as f64 / secs / f64::from(bitrate.max(1)) * 100.0;
            }
        }
        self.prev = Some((at, frames, bits));
    }
}

impl App {
    /// Feeds a view's counters to the rates and returns them.
    pub(super) fn update_rates(&self, view: &CoreView) -> Rates {
        let mut rates = self.rates.lock().unwrap_or_else(|e| e.into_inner());
        let b = &view.bus;
        rates.update(
            view.at,
            b.frames_received + b.frames_sent,
            b.frame_bits,
            self.info.bitrate,
        );
        *rates
    }

    fn gateway_health(&self, view: &CoreView) -> GatewayHealth {
        use std::sync::atomic::Ordering::Relaxed;
        GatewayHealth {
            version: env!("CARGO_PKG_VERSION"),
            mqtt_connected: self.mqtt.connected.load(Relaxed),
            mqtt_reconnects: self.mqtt.connects.load(Relaxed).saturating_sub(1),
            uptime_s: view.at.saturating_duration_since(self.started).as_secs(),
            commands: view.commands,
        }
    }

    fn bus_view(&self, view: &CoreView, rates: Rates) -> BusView<'_> {
        BusView {
            link: &self.info.link,
            bitrate: self.info.bitrate,
            frames_per_s: rates.frames_per_s,
            load_percent: rates.load_percent,
            health: view.bus,
        }
    }
}

impl<'a> Health<'a> {
    /// The health message of `view`.
    pub fn new(app: &'a App, view: &CoreView, rates: Rates) -> Health<'a> {
        Health {
            time_ms: unix_ms_of(view.at),
            gateway: app.gateway_health(view),
            bus: app.bus_view(view, rates),
            last_seen_ms: view.nodes.as_ref().map(|nodes| {
                nodes
                    .iter()
                    .map(|n| (n.id.to_string(), n.last_seen_ms))
                    .collect()
            }),
        }
    }
}

impl<'a> Snapshot<'a> {
    /// The snapshot of `view` (taken with every node) and of the events published up to it.
    pub fn new(app: &'a App, view: CoreView) -> Snapshot<'a> {
        let rates = *app.rates.lock().unwrap_or_else(|e| e.into_inner());
        let events = app
            .feed
            .recent_events(view.seq)
            .iter()
            .rev()
            .filter_map(|p| {
                // The feed keeps what the core serialised, which is JSON by construction.
                let event = RawValue::from_string(p.json.to_string()).ok()?;
                Some(TimelineEntry {
                    seq: p.seq,
                    time_ms: p.time_ms,
                    event,
                })
            })
            .collect();
        Snapshot {
            version: VERSION,
            seq: view.seq,
            time_ms: unix_ms_of(view.at),
            island: app.info.island.as_deref(),
            controls: app.info.controls,
            layout: app
                .info
                .layout
                .iter()
                .map(|(id, hex)| (id.to_string(), *hex))
                .collect(),
            gateway: app.gateway_health(&view),
            bus: app.bus_view(&view, rates),
            nodes: view.nodes.unwrap_or_default(),
            events,
            leases: view.leases,
            procedures: view.procedures,
        }
    }
}

/// The wall-clock time of `at` (an instant of the view), milliseconds since the Unix epoch.
fn unix_ms_of(at: Instant) -> u64 {
    let now = std::time::SystemTime::now();
    let ago = Instant::now().saturating_duration_since(at);
    unix_ms(now.checked_sub(ago).unwrap_or(now))
}

/// Compact JSON of a view type. Serialising these types cannot fail (plain structs, string keys);
/// should it ever, an empty object is served rather than a panic.
pub fn to_json<T: Serialize>(value: &T) -> String {
    serde_json::to_string(value).unwrap_or_else(|_| String::from("{}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn rates_cover_the_interval_since_the_previous_view() {
        let t0 = Instant::now();
        let mut r = Rates::default();
        r.update(t0, 100, 10_000, 500_000);
        assert_eq!(
            (r.frames_per_s, r.load_percent),
            (0.0, 0.0),
            "one view: no rate yet"
        );
        // 50 frames of 131 bits in half a second.
        r.update(
            t0 + Duration::from_millis(500),
            150,
            10_000 + 50 * 131,
            500_000,
        );
        assert!((r.frames_per_s - 100.0).abs() < 1e-9, "{r:?}");
        assert!((r.load_percent - 2.62).abs() < 1e-9, "{r:?}");
        // The same instant again (a view answered twice) keeps the last rates.
        r.update(t0 + Duration::from_millis(500), 150, 16_550, 500_000);
        assert!((r.frames_per_s - 100.0).abs() < 1e-9);
    }
}
