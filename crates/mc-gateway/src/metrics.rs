//! The gateway's Prometheus metrics (`docs/metrics.md`): what `GET /metrics` serves, in the
//! Prometheus text format (version 0.0.4) written by `prometheus-client`.
//!
//! Nothing here keeps a copy of the core's state. A scrape asks the core task for a
//! [`CoreView`] (the same request the island view uses) and writes it out together with the MQTT
//! task's atomics; only what the core does not count is counted here, by the core task itself as
//! commands come in and answers go out ([`CommandMeter`]): command outcomes by interface, their
//! round trips, and firmware update outcomes. Every label set is bounded: interfaces, results and
//! outcomes are fixed words, and node IDs are the island's elements.

use ihex_gateway_core::Interface;
use std::{
    collections::VecDeque,
    sync::atomic::{AtomicU64, Ordering},
    time::{Duration, Instant},
};

use ihex_gateway_core::{event::Event, fwupdate::NodeOutcome, Publication};
use prometheus_client::{
    encoding::{EncodeLabelSet, EncodeLabelValue, LabelValueEncoder},
    metrics::{
        counter::{ConstCounter, Counter},
        family::Family,
        gauge::{ConstGauge, Gauge},
        histogram::Histogram,
        info::Info,
    },
    registry::Registry,
};

use crate::{feed::CoreView, mqtt::MqttStats};

/// The `Content-Type` of `GET /metrics`.
pub const CONTENT_TYPE: &str = prometheus_client::encoding::prometheus_text::CONTENT_TYPE;

/// Upper bounds of the command round-trip histogram, seconds: from a few milliseconds (an
/// acknowledgement on an idle bus) to the longest command timeout people configure.
pub const ROUND_TRIP_BUCKETS: [f64; 12] = [
    0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
];

/// Commands whose answer the meter waits for at most; beyond that the oldest is forgotten (its
/// answer is then counted without a round trip, under the interface `unknown`).
const PENDING_MAX: usize = 4096;
/// How long the meter waits for a command's answer (commands that are never answered with
/// `command_result` or `command_rejected`, such as `sim`, are forgotten after it).
const PENDING_FOR: Duration = Duration::from_secs(15 * 60);

/// The `interface` label: where a command came from (the core's [`Interface`]), or `unknown` for
/// an answer whose command the meter no longer knew (it keeps at most `PENDING_MAX` waiting).
#[derive(Clone, Copy, Debug, Hash, PartialEq, Eq)]
struct InterfaceLabel(Option<Interface>);

impl EncodeLabelValue for InterfaceLabel {
    fn encode(&self, encoder: &mut LabelValueEncoder) -> Result<(), std::fmt::Error> {
        let word = self.0.map_or("unknown", Interface::as_str);
        std::fmt::Write::write_str(encoder, word)
    }
}

/// How a command ended: `command_result`'s `result`, or `rejected` for `command_rejected`.
#[derive(Clone, Copy, Debug, Hash, PartialEq, Eq)]
pub enum CommandResult {
    /// `ok`.
    Ok,
    /// `refused`.
    Refused,
    /// `timeout`.
    Timeout,
    /// `failed`.
    Failed,
    /// `expired`.
    Expired,
    /// `command_rejected`.
    Rejected,
}

/// How one node's firmware update ended (`fw_report`'s per-node `outcome`), as a label value.
#[derive(Clone, Copy, Debug, Hash, PartialEq, Eq)]
pub struct FwOutcome(pub NodeOutcome);

impl EncodeLabelValue for FwOutcome {
    fn encode(&self, encoder: &mut LabelValueEncoder) -> Result<(), std::fmt::Error> {
        std::fmt::Write::write_str(encoder, self.0.as_str())
    }
}

/// The label value of each variant: its word as the MQTT API writes it.
macro_rules! label_words {
    ($ty:ty { $($variant:ident => $word:literal),+ $(,)? }) => {
        impl $ty {
            /// The label value.
            pub fn as_str(self) -> &'static str {
                match self {
                    $(<$ty>::$variant => $word,)+
                }
            }
        }

        impl EncodeLabelValue for $ty {
            fn encode(&self, encoder: &mut LabelValueEncoder) -> Result<(), std::fmt::Error> {
                std::fmt::Write::write_str(encoder, self.as_str())
            }
        }
    };
}

label_words!(CommandResult {
    Ok => "ok",
    Refused => "refused",
    Timeout => "timeout",
    Failed => "failed",
    Expired => "expired",
    Rejected => "rejected",
});

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct CommandLabels {
    interface: InterfaceLabel,
    result: CommandResult,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct InterfaceLabels {
    interface: InterfaceLabel,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct FwLabels {
    outcome: FwOutcome,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct NodeLabels {
    node: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct FirmwareLabels {
    node: String,
    version: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct BuildLabels {
    version: String,
}

type RoundTrips = Family<InterfaceLabels, Histogram, fn() -> Histogram>;

/// The counters the core task keeps for the metrics (shared with the scrapes: clones count into
/// the same metrics).
#[derive(Clone, Debug)]
pub struct Counted {
    commands: Family<CommandLabels, Counter>,
    round_trip: RoundTrips,
    fw_nodes: Family<FwLabels, Counter>,
}

/// The interfaces and results every series exists for from the start (at 0), so that a rate or a
/// ratio over them has data before the first command of a kind.
const INTERFACES: [Interface; 4] = [
    Interface::Mqtt,
    Interface::Web,
    Interface::Ha,
    Interface::Sila,
];
const RESULTS: [CommandResult; 6] = [
    CommandResult::Ok,
    CommandResult::Refused,
    CommandResult::Timeout,
    CommandResult::Failed,
    CommandResult::Expired,
    CommandResult::Rejected,
];

impl Default for Counted {
    fn default() -> Self {
        let c = Counted {
            commands: Family::default(),
            round_trip: Family::new_with_constructor(|| Histogram::new(ROUND_TRIP_BUCKETS)),
            fw_nodes: Family::default(),
        };
        for interface in INTERFACES.map(|i| InterfaceLabel(Some(i))) {
            for result in RESULTS {
                let _ = c
                    .commands
                    .get_or_create(&CommandLabels { interface, result });
            }
            let _ = c.round_trip.get_or_create(&InterfaceLabels { interface });
        }
        for outcome in NodeOutcome::ALL {
            let _ = c.fw_nodes.get_or_create(&FwLabels {
                outcome: FwOutcome(outcome),
            });
        }
        c
    }
}

/// A command waiting for its answer.
#[derive(Debug)]
struct Pending {
    request_id: Option<String>,
    from: Interface,
    received: Instant,
}

/// Pairs each command with its answer, in the core task: a command's interface and arrival are
/// noted when it enters the core, and its answer (`command_result` or `command_rejected`, with the
/// same `request_id`; commands without one pair with answers without one, in order) counts its
/// outcome and round trip when it is published.
#[derive(Debug, Default)]
pub struct CommandMeter {
    pending: VecDeque<Pending>,
    counted: Counted,
    /// The series answers were counted into, each looked up in its family once: the family's
    /// lookup takes a lock and hashes the labels, a scan of these few entries does neither.
    counters: Vec<(CommandLabels, Counter)>,
    round_trips: Vec<(Interface, Histogram)>,
}

impl CommandMeter {
    /// A meter counting into `counted`.
    pub fn new(counted: Counted) -> CommandMeter {
        CommandMeter {
            pending: VecDeque::new(),
            counted,
            counters: Vec::new(),
            round_trips: Vec::new(),
        }
    }

    /// A command from `from`, received at `received`, whose answer will carry `request_id`.
    pub fn noted(&mut self, from: Interface, request_id: Option<String>, received: Instant) {
        while self.pending.len() >= PENDING_MAX
            || self
                .pending
                .front()
                .is_some_and(|p| received.saturating_duration_since(p.received) > PENDING_FOR)
        {
            self.pending.pop_front();
        }
        self.pending.push_back(Pending {
            request_id,
            from,
            received,
        });
    }

    /// A publication leaves the core at `now`: answers and firmware reports are counted.
    pub fn published(&mut self, publication: &Publication, now: Instant) {
        let Publication::Event(event) = publication else {
            return;
        };
        let (request_id, result) = match event {
            Event::CommandResult(r) => (&r.request_id, outcome(r.result)),
            Event::CommandRejected(r) => (&r.request_id, CommandResult::Rejected),
            Event::FwReport(r) => {
                for n in &r.nodes {
                    self.counted
                        .fw_nodes
                        .get_or_create(&FwLabels {
                            outcome: FwOutcome(n.outcome),
                        })
                        .inc();
                }
                return;
            }
            _ => return,
        };
        let at = self
            .pending
            .iter()
            .position(|p| p.request_id == *request_id);
        let interface = match at.and_then(|i| self.pending.remove(i)) {
            Some(p) => {
                let secs = now.saturating_duration_since(p.received).as_secs_f64();
                self.round_trip(p.from).observe(secs);
                InterfaceLabel(Some(p.from))
            }
            None => InterfaceLabel(None),
        };
        self.counter(CommandLabels { interface, result }).inc();
    }

    fn counter(&mut self, labels: CommandLabels) -> &Counter {
        let family = &self.counted.commands;
        cached(&mut self.counters, labels, |l| {
            family.get_or_create(l).clone()
        })
    }

    fn round_trip(&mut self, from: Interface) -> &Histogram {
        let family = &self.counted.round_trip;
        cached(&mut self.round_trips, from, |&from| {
            let labels = InterfaceLabels {
                interface: InterfaceLabel(Some(from)),
            };
            family.get_or_create(&labels).clone()
        })
    }
}

/// The handle cached under `key`, made by `make` the first time: a family's `get_or_create` takes a
/// lock and hashes the labels, a few handles in a vector are found by comparison.
fn cached<K: PartialEq, V>(cache: &mut Vec<(K, V)>, key: K, make: impl FnOnce(&K) -> V) -> &V {
    let at = match cache.iter().position(|(k, _)| *k == key) {
        Some(at) => at,
        None => {
            let v = make(&key);
            cache.push((key, v));
            cache.len() - 1
        }
    };
    &cache[at].1
}

fn outcome(o: ihex_gateway_core::event::Outcome) -> CommandResult {
    use ihex_gateway_core::event::Outcome;
    match o {
        Outcome::Ok => CommandResult::Ok,
        Outcome::Refused => CommandResult::Refused,
        Outcome::Timeout => CommandResult::Timeout,
        Outcome::Failed => CommandResult::Failed,
        Outcome::Expired => CommandResult::Expired,
    }
}

/// What a scrape reads besides the core's view.
pub struct Scrape<'a> {
    /// The core's view, with every node.
    pub view: &'a CoreView,
    /// The MQTT task's counters.
    pub mqtt: &'a MqttStats,
    /// The core task's own counts.
    pub counted: &'a Counted,
    /// The bitrate the bus load is computed for, bit/s.
    pub bitrate: u32,
    /// The bus load over the last health period, as a share of the bitrate (0 to 1).
    pub bus_load: f64,
    /// When the gateway started running.
    pub started: Instant,
    /// The audit trail, when it is on.
    pub audit: Option<&'a crate::audit::AuditStatus>,
}

fn counter(registry: &mut Registry, name: &str, help: &str, v: u64) {
    registry.register(name, help, ConstCounter::new(v));
}

fn gauge(registry: &mut Registry, name: &str, help: &str, v: f64) {
    registry.register(name, help, ConstGauge::new(v));
}

impl Scrape<'_> {
    /// The exposition: every `ihex_` metric (`docs/metrics.md` lists them).
    pub fn encode(&self) -> String {
        let mut root = Registry::default();
        let r = root.sub_registry_with_prefix("ihex");
        r.register(
            "build",
            "The gateway's version",
            Info::new(BuildLabels {
                version: env!("CARGO_PKG_VERSION").to_owned(),
            }),
        );
        gauge(
            r,
            "uptime_seconds",
            "Seconds since the gateway started running",
            self.view
                .at
                .saturating_duration_since(self.started)
                .as_secs_f64(),
        );

        if let Some(a) = self.audit {
            gauge(
                r,
                "audit_up",
                "1 while the audit trail records, 0 while it cannot (docs/audit.md)",
                f64::from(u8::from(a.problem().is_none())),
            );
            counter(
                r,
                "audit_records",
                "Audit records written",
                a.written.load(Ordering::Relaxed),
            );
            counter(
                r,
                "audit_records_lost",
                "Audit records that could not be written (a full disk, a full queue)",
                a.lost.load(Ordering::Relaxed),
            );
        }

        let b = &self.view.bus;
        counter(
            r,
            "can_frames_received",
            "CAN frames received through the gateway's filters (error frames not included)",
            b.frames_received,
        );
        counter(
            r,
            "can_frames_sent",
            "CAN frames handed to the interface for sending",
            b.frames_sent,
        );
        r.register(
            "can_frame_bytes",
            "What the received and sent frames take on the wire, without stuff bits, in bytes",
            ConstCounter::new(b.frame_bits as f64 / 8.0),
        );
        gauge(
            r,
            "can_bitrate_bytes_per_second",
            "The bus's configured bitrate, in bytes per second (bit/s divided by 8)",
            f64::from(self.bitrate) / 8.0,
        );
        gauge(
            r,
            "can_bus_load_ratio",
            "The gateway's frames' share of the bitrate over the last second (0 to 1)",
            self.bus_load,
        );
        counter(
            r,
            "can_error_frames",
            "Error frames received (bus-off and restart frames not included)",
            b.error_frames,
        );
        counter(
            r,
            "can_bus_off",
            "Times the controller went bus-off",
            b.bus_off,
        );
        counter(
            r,
            "can_interface_down",
            "Times the interface went down or vanished",
            b.interface_down,
        );
        gauge(
            r,
            "can_bus_down",
            "1 while the gateway's interface is bus-off or down",
            f64::from(u8::from(b.bus_down)),
        );
        counter(
            r,
            "can_rx_dropped_frames",
            "Frames the kernel dropped on reception",
            b.rx_dropped,
        );
        counter(
            r,
            "can_undecodable_frames",
            "Frames that passed the filters but were no valid iHEX packet",
            b.undecodable_frames,
        );
        counter(
            r,
            "can_send_failures",
            "Gateway frames that could not be sent",
            b.send_failures,
        );
        counter(
            r,
            "element_faults",
            "fault reports received from elements",
            b.faults,
        );

        let online = Family::<NodeLabels, Gauge>::default();
        let heard = Family::<NodeLabels, Gauge<f64, AtomicU64>>::default();
        let firmware = Family::<FirmwareLabels, Gauge>::default();
        for n in self.view.nodes.iter().flatten() {
            let node = NodeLabels {
                node: n.id.to_string(),
            };
            online.get_or_create(&node).set(i64::from(n.online));
            heard
                .get_or_create(&node)
                .set(n.last_seen_ms as f64 / 1000.0);
            if let Some(fw) = &n.firmware {
                firmware
                    .get_or_create(&FirmwareLabels {
                        node: node.node,
                        version: fw.version.clone(),
                    })
                    .set(1);
            }
        }
        r.register(
            "element_online",
            "1 while the element answers health checks, by node ID",
            online,
        );
        r.register(
            "element_last_heard_seconds",
            "Seconds since the element was last heard, by node ID",
            heard,
        );
        r.register(
            "element_firmware_info",
            "The firmware version an element runs (read back from it), by node ID",
            firmware,
        );

        let c = &self.view.commands;
        gauge(
            r,
            "commands_in_flight",
            "Commands accepted and not answered yet",
            c.in_flight as f64,
        );
        r.register("commands", "Commands answered, by interface (mqtt, web, ha) and result (ok, refused, timeout, failed, expired, rejected)", self.counted.commands.clone());
        r.register(
            "command_round_trip_seconds",
            "From a command's arrival at the gateway to its answer's publication, by interface",
            self.counted.round_trip.clone(),
        );
        r.register(
            "fw_update_nodes",
            "Elements' firmware update outcomes (updated, refused, reverted, unreachable, failed)",
            self.counted.fw_nodes.clone(),
        );

        let m = self.mqtt;
        let load = |a: &AtomicU64| a.load(Ordering::Relaxed);
        gauge(
            r,
            "mqtt_connected",
            "1 while connected to the MQTT broker",
            f64::from(u8::from(m.connected.load(Ordering::Relaxed))),
        );
        counter(
            r,
            "mqtt_reconnects",
            "Connections to the broker after the first one",
            load(&m.connects).saturating_sub(1),
        );
        counter(
            r,
            "mqtt_publications",
            "Publications handed to the MQTT client",
            load(&m.published),
        );
        counter(
            r,
            "mqtt_commands_received",
            "Messages received on the command topic",
            load(&m.commands),
        );
        counter(r, "publications_dropped", "Events dropped because they could not be published as fast as they came (never answers or state documents)", load(&m.publications_dropped));

        let mut text = String::new();
        // Writing into a String cannot fail.
        let _ = prometheus_client::encoding::prometheus_text::encode(&mut text, &root);
        text
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ihex_gateway_core::{
        bridge::{BusHealth, CommandCounters},
        event::{self, CommandRejected, Outcome},
        fwupdate::{FwReport, NodeReport},
    };

    fn result(id: Option<&str>, result: Outcome) -> Publication {
        Publication::Event(Event::CommandResult(event::CommandResult {
            request_id: id.map(Into::into),
            cmd: "led".into(),
            node: event::Target::All,
            result,
            reason: None,
            acked: None,
            refused: None,
            missing: None,
            origin: None,
        }))
    }

    fn rejected(id: Option<&str>) -> Publication {
        Publication::Event(Event::CommandRejected(CommandRejected {
            request_id: id.map(Into::into),
            reason: "r".into(),
            origin: None,
        }))
    }

    fn scrape(counted: &Counted) -> String {
        let view = CoreView {
            seq: 0,
            at: Instant::now(),
            nodes: Some(vec![]),
            bus: BusHealth {
                frame_bits: 1000,
                ..BusHealth::default()
            },
            commands: CommandCounters::default(),
            leases: ihex_gateway_core::lease::LeasesDocument { leases: vec![] },
            procedures: Default::default(),
        };
        Scrape {
            view: &view,
            mqtt: &MqttStats::default(),
            counted,
            bitrate: 500_000,
            bus_load: 0.25,
            started: view.at,
            audit: None,
        }
        .encode()
    }

    /// The sample line of `series` (name and labels exactly as written).
    fn sample<'a>(text: &'a str, series: &str) -> &'a str {
        text.lines()
            .find_map(|l| l.strip_prefix(series).and_then(|v| v.strip_prefix(' ')))
            .unwrap_or_else(|| panic!("no {series} in\n{text}"))
    }

    #[test]
    fn answers_are_paired_with_their_commands_interface_and_arrival() {
        let counted = Counted::default();
        let mut m = CommandMeter::new(counted.clone());
        let t0 = Instant::now();
        m.noted(Interface::Web, Some("a".into()), t0);
        m.noted(Interface::Mqtt, Some("a".into()), t0);
        m.noted(Interface::Mqtt, None, t0);
        m.noted(Interface::Ha, Some("homeassistant".into()), t0);
        // Same request_id: first come, first answered.
        m.published(
            &result(Some("a"), Outcome::Ok),
            t0 + Duration::from_millis(20),
        );
        m.published(
            &result(Some("a"), Outcome::Timeout),
            t0 + Duration::from_millis(600),
        );
        m.published(&rejected(None), t0);
        m.published(&result(Some("homeassistant"), Outcome::Refused), t0);
        // An answer whose command the meter never saw.
        m.published(&result(Some("zzz"), Outcome::Failed), t0);
        // A series counted into before: the same series again.
        m.noted(Interface::Web, Some("b".into()), t0);
        m.published(&result(Some("b"), Outcome::Ok), t0);
        let text = scrape(&counted);
        for (series, v) in [
            (r#"ihex_commands_total{interface="web",result="ok"}"#, "2"),
            (
                r#"ihex_commands_total{interface="mqtt",result="timeout"}"#,
                "1",
            ),
            (
                r#"ihex_commands_total{interface="mqtt",result="rejected"}"#,
                "1",
            ),
            (
                r#"ihex_commands_total{interface="ha",result="refused"}"#,
                "1",
            ),
            (
                r#"ihex_commands_total{interface="unknown",result="failed"}"#,
                "1",
            ),
            (r#"ihex_commands_total{interface="mqtt",result="ok"}"#, "0"),
            (
                r#"ihex_command_round_trip_seconds_count{interface="mqtt"}"#,
                "2",
            ),
            (
                r#"ihex_command_round_trip_seconds_bucket{interface="web",le="0.025"}"#,
                "2",
            ),
            (
                r#"ihex_command_round_trip_seconds_bucket{interface="mqtt",le="0.5"}"#,
                "1",
            ),
            (
                r#"ihex_command_round_trip_seconds_bucket{interface="mqtt",le="1"}"#,
                "2",
            ),
        ] {
            assert_eq!(sample(&text, series), v, "{series}\n{text}");
        }
        assert!(m.pending.is_empty(), "{:?}", m.pending);
    }

    #[test]
    fn the_meter_forgets_unanswered_commands() {
        let mut m = CommandMeter::default();
        let t0 = Instant::now();
        for _ in 0..PENDING_MAX + 10 {
            m.noted(Interface::Mqtt, None, t0);
        }
        assert_eq!(m.pending.len(), PENDING_MAX);
        m.noted(
            Interface::Mqtt,
            None,
            t0 + PENDING_FOR + Duration::from_secs(1),
        );
        assert_eq!(m.pending.len(), 1, "the stale ones are gone");
    }

    #[test]
    fn firmware_reports_count_each_elements_outcome() {
        let counted = Counted::default();
        let mut m = CommandMeter::new(counted.clone());
        let node = |id: &str, outcome| NodeReport {
            node: event::HexId(id.parse().unwrap()),
            outcome,
            reason: None,
            duration_ms: 1,
        };
        let report = FwReport {
            request_id: None,
            image_id: "00000000".into(),
            version: "1.0.0".into(),
            notes: None,
            duration_ms: 1,
            frames_sent: 1,
            bus_share: 50,
            nodes: vec![
                node("111", NodeOutcome::Updated),
                node("112", NodeOutcome::Updated),
                node("2", NodeOutcome::Reverted),
            ],
        };
        m.published(
            &Publication::Event(Event::FwReport(Box::new(report))),
            Instant::now(),
        );
        let text = scrape(&counted);
        assert_eq!(
            sample(&text, r#"ihex_fw_update_nodes_total{outcome="updated"}"#),
            "2"
        );
        assert_eq!(
            sample(&text, r#"ihex_fw_update_nodes_total{outcome="reverted"}"#),
            "1"
        );
        assert_eq!(
            sample(&text, r#"ihex_fw_update_nodes_total{outcome="failed"}"#),
            "0"
        );
    }

    #[test]
    fn the_exposition_follows_prometheus_conventions() {
        let text = scrape(&Counted::default());
        assert_eq!(sample(&text, "ihex_can_frame_bytes_total"), "125.0");
        assert_eq!(sample(&text, "ihex_can_bus_load_ratio"), "0.25");
        assert_eq!(
            sample(&text, "ihex_can_bitrate_bytes_per_second"),
            "62500.0"
        );
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            let name = line.split(['{', ' ']).next().unwrap_or_default();
            assert!(name.starts_with("ihex_"), "{line}");
            assert!(!name.contains("bits"), "base units: {line}");
        }
        for line in text.lines().filter(|l| l.starts_with("# TYPE")) {
            if line.ends_with(" counter") {
                assert!(line.contains("_total "), "{line}");
            }
        }
        assert!(text.contains(&format!(
            "ihex_build_info{{version=\"{}\"}} 1",
            env!("CARGO_PKG_VERSION")
        )));
    }
}
