//! What the live benchmark measures, as written to `live.json` and read back by the report.

use serde::{Deserialize, Serialize};

use crate::bus::{Limit, PairLimit};
use crate::stats::Summary;

/// One CAN → MQTT rate trial.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Trial {
    /// Rate asked for, frames/s.
    pub offered_fps: f64,
    /// Rate the writer achieved, frames/s.
    pub sent_fps: f64,
    /// Frames sent.
    pub sent: usize,
    /// Distinct matching events received.
    pub received: usize,
    /// Fraction lost (0–1).
    pub loss: f64,
    /// Last event after the last frame, ms (a growing backlog shows here before loss does).
    pub lag_ms: f64,
    /// Gateway CPU time during the trial, ms.
    pub gateway_cpu_ms: f64,
    /// What the gateway said about lost commands (`command_result` failures, rejections).
    #[serde(default)]
    pub note: Option<String>,
    /// Command trials: `command_result` events with result `ok` received (each command's answer
    /// after the bench acked its frame as the node); `None` for report trials.
    #[serde(default)]
    pub results: Option<usize>,
    /// Where the machine's CPU went during the trial, per 1,000 delivered reports or commands.
    #[serde(default)]
    pub share: Option<CpuShare>,
}

/// CPU time of each process of a live trial, ms per 1,000 delivered reports (or commands): the
/// gateway, the broker and the benchmark itself share the machine, so their sum bounds the rate.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CpuShare {
    /// The gateway in user space.
    pub gateway_user: f64,
    /// The gateway in the kernel (system calls, the socket and TCP paths it drives).
    pub gateway_system: f64,
    /// Mosquitto, user + system.
    pub broker: f64,
    /// The benchmark process (CAN writer, acks, MQTT client), user + system.
    pub bench: f64,
    /// Times the gateway's threads were switched out (blocked or preempted): about once per
    /// wake-up.
    #[serde(default)]
    pub gateway_switches: f64,
    /// Of `gateway_switches`, the voluntary ones (the gateway blocked: one per time its thread
    /// parked with nothing to do); the rest were preemptions by another process.
    #[serde(default)]
    pub gateway_voluntary: f64,
    /// The same for Mosquitto (0 when the broker runs elsewhere and is not counted).
    #[serde(default)]
    pub broker_switches: f64,
}

impl CpuShare {
    /// All three processes together.
    pub fn total(&self) -> f64 {
        self.gateway_user + self.gateway_system + self.broker + self.bench
    }

    /// The most per second the three processes' CPU allows on `cpus` CPUs, whatever the gateway.
    pub fn ceiling(&self, cpus: usize) -> f64 {
        1e6 * cpus.max(1) as f64 / self.total().max(f64::MIN_POSITIVE)
    }
}

impl Trial {
    /// No loss (and for commands every `command_result` delivered) and no backlog left behind.
    pub fn sustained(&self) -> bool {
        self.received == self.sent
            && self.results.is_none_or(|r| r == self.sent)
            && self.lag_ms <= 250.0
    }
}

/// Bare SocketCAN pair figures.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Bare {
    /// Writer → reader rate of a burst, frames/s.
    pub rate_fps: f64,
    /// Frames of the burst.
    pub sent: usize,
    /// Frames the reader got.
    pub received: usize,
    /// Round trip writer → echo thread → writer.
    pub rtt: Summary,
    /// Round trip of one byte to another process and back over two pipes (`ihex-bench echo`):
    /// the cost of two process switches, which every bridged frame makes several of.
    #[serde(default)]
    pub process_rtt: Summary,
    /// CPU of the benchmark process (writer and reader thread) per 1,000 frames of the burst, ms:
    /// the cost of forwarding a raw frame (one write, one read), the yardstick of the gateway's CPU
    /// per 1,000 commands.
    #[serde(default)]
    pub cpu_ms_per_1k: f64,
}

/// The bare MQTT path of the same run: two clients of the benchmark through the broker the
/// gateway uses, QoS 1, no gateway. Each direction is the gateway's side of it played by a
/// second client, so the ratio of the gateway's rate to it is the share the gateway leaves of
/// what the broker link gives.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct MqttBare {
    /// Ingress (commands' way): the benchmark's main client publishes command-sized messages,
    /// a second client subscribed in the gateway's place receives them. Highest zero-loss
    /// rate, messages/s.
    pub ingress_mps: f64,
    /// Egress (events' way): the second client publishes event-sized messages in the gateway's
    /// place, the main client receives them. Highest zero-loss rate, messages/s.
    pub egress_mps: f64,
    /// Every ingress trial.
    pub ingress_trials: Vec<Trial>,
    /// Every egress trial.
    pub egress_trials: Vec<Trial>,
}

/// Everything the live run measures.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct LiveResults {
    /// Kernel, CPU count and model as seen where the run happened.
    pub environment: String,
    /// Where the broker ran: started beside the gateway, or elsewhere at an address (the host's
    /// Mosquitto seen from the microVM).
    #[serde(default)]
    pub broker_layout: String,
    /// Which CPUs the measured processes had (`live --pin`); empty: wherever the kernel put them.
    #[serde(default)]
    pub cpu_layout: String,
    /// The bare MQTT path through the same broker, when measured.
    #[serde(default)]
    pub mqtt_bare: Option<MqttBare>,
    /// CPUs online where the run happened.
    pub cpus: usize,
    /// The bare SocketCAN pair.
    pub bare: Bare,
    /// Every CAN → MQTT trial, in the order run.
    pub trials: Vec<Trial>,
    /// Highest sustained CAN → MQTT rate found, frames/s.
    pub can_to_mqtt_fps: f64,
    /// The trial at twice that rate.
    pub at_double: Trial,
    /// Every MQTT → CAN trial (commands paced at a rate), in the order run.
    #[serde(default)]
    pub command_trials: Vec<Trial>,
    /// The plain MQTT → CAN forwarder ([`crate`]'s `forward`) beside the gateway, at the command
    /// cost trial's rate (its last trial): its CPU per 1,000 frames is what a raw frame forward
    /// costs.
    #[serde(default)]
    pub raw_forward: Option<Trial>,
    /// The command cost trials: the gateway's and the plain forwarder's, alternately in the same
    /// boot at the same rate (empty in results from before they were measured so).
    #[serde(default)]
    pub cost_rounds: Vec<CostRound>,
    /// MQTT → CAN: highest command rate delivered as frames with zero loss, commands/s.
    pub mqtt_to_can_cps: f64,
    /// MQTT → CAN burst: commands published back to back.
    pub commands_sent: usize,
    /// MQTT → CAN burst: frames seen on the bus.
    pub commands_delivered: usize,
    /// MQTT → CAN burst: delivered frames per second.
    #[serde(default)]
    pub burst_cps: f64,
    /// MQTT → CAN burst: what the gateway said about the commands it did not send.
    #[serde(default)]
    pub burst_note: Option<String>,
    /// Command → frame latency, idle bus.
    pub cmd_to_frame_idle: Summary,
    /// Frame → event latency, idle bus.
    pub frame_to_event_idle: Summary,
    /// What the gateway added to an idle command, in kernel timestamps: from the command's packet
    /// entering the machine's network stack to its frame on the bus (`None`: not measured).
    #[serde(default)]
    pub cmd_to_frame_idle_kernel: Option<Summary>,
    /// What the gateway added to an idle report, in kernel timestamps: from the frame on the bus
    /// to the event's packet leaving for the broker.
    #[serde(default)]
    pub frame_to_event_idle_kernel: Option<Summary>,
    /// The plain forwarder ([`LiveResults::raw_forward`]) at idle: message → frame, end to end.
    #[serde(default)]
    pub raw_cmd_to_frame_idle: Option<Summary>,
    /// The plain forwarder at idle, in kernel timestamps as [`LiveResults::cmd_to_frame_idle_kernel`].
    #[serde(default)]
    pub raw_cmd_to_frame_idle_kernel: Option<Summary>,
    /// Command → frame latency with the bus at its physical frame rate.
    pub cmd_to_frame_load: Summary,
    /// Frame → event latency with the bus at its physical frame rate.
    pub frame_to_event_load: Summary,
    /// Background frames per second asked for / achieved during the loaded series.
    pub load_offered_fps: f64,
    /// Background frames per second achieved.
    pub load_sent_fps: f64,
    /// MQTT publish → own delivery round through the broker (baseline for the added latency).
    pub mqtt_loop: Summary,
    /// Gateway CPU ms per 1,000 CAN → event frames.
    pub cpu_ms_per_1k_reports: f64,
    /// Gateway CPU ms per 1,000 commands → frames.
    pub cpu_ms_per_1k_commands: f64,
    /// Every process's CPU in the CAN → event cost trial, per 1,000 reports.
    #[serde(default)]
    pub share_reports: Option<CpuShare>,
    /// Every process's CPU in the command cost trial, per 1,000 commands.
    #[serde(default)]
    pub share_commands: Option<CpuShare>,
    /// Gateway CPU ms per 1,000 background frames it reads and drops or records (no event).
    pub cpu_ms_per_1k_background: f64,
    /// Gateway peak resident memory, KiB (VmHWM).
    pub gateway_vmhwm_kib: u64,
    /// Gateway resident memory at the end, KiB (VmRSS).
    pub gateway_vmrss_kib: u64,
    /// Gateway resident memory once online, before any traffic, KiB (VmRSS).
    #[serde(default)]
    pub gateway_vmrss_start_kib: u64,
    /// Bus limits of the report frame (BootUp) and of the background frame (HealthReply).
    pub limit_report: Limit,
    /// Bus limit of the background frame.
    pub limit_background: Limit,
    /// Bus limit of the command frame (LedSet).
    pub limit_command: Limit,
    /// Bus limit of acknowledged commands: a LedSet and its Ack per command.
    #[serde(default)]
    pub limit_command_pair: PairLimit,
    /// Notes about the run (fallbacks taken, anomalies).
    pub notes: Vec<String>,
}

/// One round of the command cost comparison: a gateway command trial, then a plain forwarder
/// trial at the same rate, one after the other. A round's ratio compares two trials minutes
/// closer than two halves of a run, so the machine's drift (the host's other load slows the
/// vCPUs and is charged to whatever runs) cancels in it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CostRound {
    /// Commands (and frames, for the forwarder) offered per second (0 in results from before the
    /// rounds recorded it: one rate then).
    #[serde(default)]
    pub rate: f64,
    /// Gateway CPU per 1,000 acknowledged commands, ms.
    pub gateway_ms: f64,
    /// Plain forwarder CPU per 1,000 frames, ms.
    pub forward_ms: f64,
    /// Where the CPU went in the gateway's trial (absent from older results).
    #[serde(default)]
    pub gateway_share: Option<CpuShare>,
    /// The same for the forwarder's trial: its `gateway_*` figures are the forwarder's.
    #[serde(default)]
    pub forward_share: Option<CpuShare>,
    /// CPU per 1,000 answered commands of the gateway's sans-IO core alone, no I/O (the
    /// `answered` workload on the gateway's CPU, right after the round's two trials; absent from
    /// older results).
    #[serde(default)]
    pub core_ms: Option<f64>,
}

impl CostRound {
    /// Gateway / forwarder.
    pub fn ratio(&self) -> f64 {
        self.gateway_ms / self.forward_ms
    }

    /// The core alone / the forwarder: what the gateway's own work, without its I/O, adds to a
    /// raw forward's CPU ([`CostRound::core_ms`]).
    pub fn core_share(&self) -> Option<f64> {
        Some(self.core_ms? / self.forward_ms)
    }

    /// The round whose gateway CPU is the median of `rounds`' (the lower middle one of an even
    /// count), which the headline figures are taken from.
    pub fn median(rounds: &[CostRound]) -> Option<&CostRound> {
        let mut by_cpu: Vec<&CostRound> = rounds.iter().collect();
        by_cpu.sort_by(|a, b| a.gateway_ms.total_cmp(&b.gateway_ms));
        by_cpu.get(by_cpu.len().checked_sub(1)? / 2).copied()
    }
}

/// The cost rounds' verdict: the median of their ratios, and the lowest and highest.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CostRatio {
    /// Median of the rounds' ratios.
    pub median: f64,
    /// Lowest ratio.
    pub min: f64,
    /// Highest ratio.
    pub max: f64,
    /// Rounds counted (those where both processes used CPU).
    pub rounds: usize,
    /// The median of the rounds' [`CostRound::core_share`] (`None`: no round measured the core
    /// alone).
    pub core_share: Option<f64>,
}

impl LiveResults {
    /// The cost rounds by rate, in the order the rates were measured; the first is the headline
    /// (the gateway's CPU per 1,000 commands is its median round's).
    pub fn cost_series(&self) -> Vec<(f64, Vec<CostRound>)> {
        let mut series: Vec<(f64, Vec<CostRound>)> = Vec::new();
        for c in &self.cost_rounds {
            match series.iter_mut().find(|(rate, _)| *rate == c.rate) {
                Some((_, rounds)) => rounds.push(*c),
                None => series.push((c.rate, vec![*c])),
            }
        }
        series
    }

    /// [`LiveResults::cost_ratio_of`] the headline rate's rounds.
    pub fn cost_ratio(&self) -> Option<CostRatio> {
        Self::cost_ratio_of(&self.cost_series().first()?.1)
    }

    /// The median and range of `rounds`' ratios (`None`: no round measured both).
    pub fn cost_ratio_of(rounds: &[CostRound]) -> Option<CostRatio> {
        let measured = || {
            rounds
                .iter()
                .filter(|c| c.gateway_ms > 0.0 && c.forward_ms > 0.0)
        };
        let mut r: Vec<f64> = measured().map(CostRound::ratio).collect();
        r.sort_by(f64::total_cmp);
        let mut core: Vec<f64> = measured().filter_map(CostRound::core_share).collect();
        core.sort_by(f64::total_cmp);
        Some(CostRatio {
            median: crate::stats::percentile(&r, 50.0),
            min: *r.first()?,
            max: *r.last()?,
            rounds: r.len(),
            core_share: (!core.is_empty()).then(|| crate::stats::percentile(&core, 50.0)),
        })
    }

    /// CPU per 1,000 frames of a raw MQTT → CAN forward, ms: the plain forwarder's when it ran
    /// and forwarded something (the median of the headline rate's cost rounds when there were
    /// rounds), else the bare SocketCAN pair's (no MQTT in it). With which one.
    pub fn raw_forward_cpu(&self) -> Option<(f64, &'static str)> {
        let series = self.cost_series();
        let mut rounds: Vec<f64> = series
            .first()
            .map_or(&[][..], |(_, rounds)| rounds)
            .iter()
            .map(|c| c.forward_ms)
            .filter(|&ms| ms > 0.0)
            .collect();
        if !rounds.is_empty() {
            rounds.sort_by(f64::total_cmp);
            return Some((
                crate::stats::percentile(&rounds, 50.0),
                "plain MQTT->CAN forwarder, median of the rounds",
            ));
        }
        match &self.raw_forward {
            Some(f) if f.received > 0 => Some((
                f.gateway_cpu_ms * 1000.0 / f.received as f64,
                "plain MQTT->CAN forwarder",
            )),
            _ => (self.bare.cpu_ms_per_1k > 0.0)
                .then_some((self.bare.cpu_ms_per_1k, "bare SocketCAN pair")),
        }
    }
}

/// The island view's latency (`ihex-bench web`, the demo gateway on the host).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct WebResults {
    /// Probes measured (after the warm-up).
    pub probes: usize,
    /// Probes whose result did not reach both readers within 2 s.
    pub lost: usize,
    /// How the measured probes ended, by `result`, with their counts.
    pub outcomes: Vec<(String, usize)>,
    /// LED command published → its `command_result` read from `/api/events` (the page's stream):
    /// an upper bound of the publication-to-page delay.
    pub command_to_page: Summary,
    /// The same command → its `command_result` at an MQTT subscriber of the embedded broker.
    pub command_to_mqtt: Summary,
    /// Per probe, the stream's arrival minus the MQTT subscriber's (negative: the page was first).
    pub page_minus_mqtt: Summary,
}

/// Instructions per command of the whole demo gateway process (`ihex-bench process`, callgrind on
/// this machine; see `process.rs`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ProcessResults {
    /// The gateway binary measured.
    pub gateway: String,
    /// With the SiLA server off, then on.
    pub runs: Vec<ProcessCost>,
}

/// One run of [`ProcessResults`].
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ProcessCost {
    /// The SiLA server was on.
    pub sila: bool,
    /// `None`: each command answered `ok` before the next was sent; `Some(k)`: published `k`
    /// back to back, the next `k` once all of them were answered.
    #[serde(default)]
    pub burst: Option<usize>,
    /// Commands counted.
    pub commands: usize,
    /// How long they took, s (the idle count covers as long a pause).
    pub seconds: f64,
    /// Instructions of the process while the commands ran.
    pub instructions_commands: u64,
    /// Instructions of the process during the pause after them.
    pub instructions_idle: u64,
    /// (commands - idle) / commands.
    pub per_command: f64,
    /// Where they went: per command, each task's inclusive count and some of its parts, the
    /// pause's subtracted ([`ProcessPhase`]); empty in results written before it was counted.
    #[serde(default)]
    pub phases: Vec<ProcessPhase>,
}

/// One line of [`ProcessCost::phases`].
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ProcessPhase {
    /// What it is (`core task`, `  command in`: a part is indented under its task).
    pub name: String,
    /// Instructions per command; `None` when callgrind had none of its functions (inlined).
    pub per_command: Option<f64>,
}

/// The SiLA server's round trip and memory (`ihex-bench sila`, the demo gateway on the host).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct SilaResults {
    /// Probes of each interface measured (after the warm-up).
    pub probes: usize,
    /// SiLA probes that failed or took longer than 2 s.
    pub sila_lost: usize,
    /// MQTT probes whose `command_result` was not `ok` within 2 s.
    pub mqtt_lost: usize,
    /// `IslandControl.SetLight` called → its response (the element acknowledged, its state changed).
    pub sila_round_trip: Summary,
    /// The same LED command published on MQTT → its `command_result` at an MQTT subscriber,
    /// alternating with the SiLA probes on the same gateway.
    pub mqtt_round_trip: Summary,
    /// Subscribed SiLA clients (each its own connection) in the last memory figure.
    pub clients: usize,
    /// Of them, those that received a new element state after the last commands.
    pub clients_updated: usize,
    /// Gateway memory (VmHWM, VmRSS in KiB) with `--sila off`, after the same MQTT commands.
    pub memory_off_kib: (u64, u64),
    /// With the SiLA server on and no SiLA client yet.
    pub memory_idle_kib: (u64, u64),
    /// With the SiLA server on, after the probes, with [`SilaResults::clients`] clients connected
    /// (each its own HTTP/2 connection) but not yet subscribed.
    #[serde(default)]
    pub memory_connected_kib: (u64, u64),
    /// With the SiLA server on, after the probes, with [`SilaResults::clients`] subscribed clients.
    pub memory_clients_kib: (u64, u64),
}

/// A firmware update of a simulated island (`ihex-bench fw`, the demo gateway on the host).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct FwResults {
    /// Static elements updated at once.
    pub nodes: u16,
    /// Size of the signed image, bytes.
    pub image_bytes: usize,
    /// The gateway's bus-share cap, %.
    pub bus_share_cap: u8,
    /// `fw_update` to all: command published → `fw_report` received, s.
    pub broadcast_s: f64,
    /// The report's own duration, ms.
    pub broadcast_report_ms: u64,
    /// Frames the update sent.
    pub broadcast_frames: u64,
    /// The report's outcomes, by name, with their counts.
    pub broadcast_outcomes: Vec<(String, usize)>,
    /// `fw_update` to one element: command → report, s (a sequential update is `nodes` of these).
    pub one_node_s: f64,
    /// Frames the one-element update sent.
    pub one_node_frames: u64,
    /// The one-element report's outcomes.
    pub one_node_outcomes: Vec<(String, usize)>,
    /// LED command → `command_result` on the idle island.
    pub command_idle: Summary,
    /// The same during the update to all (one every 250 ms, to an element being updated).
    pub command_during: Summary,
    /// A docking on the idle island: the simulator's dock → `new_connection`, ms.
    #[serde(default)]
    pub docking_idle_ms: f64,
    /// A docking during the update: the simulator's dock → `new_connection`, ms.
    pub docking_during_ms: Option<f64>,
    /// Mobile elements docked (each on its own static element) for the last update.
    #[serde(default)]
    pub docked_mobiles: u16,
    /// `fw_update` to all with those mobile elements docked: command → report, s.
    #[serde(default)]
    pub docked_s: f64,
    /// That report's outcomes.
    #[serde(default)]
    pub docked_outcomes: Vec<(String, usize)>,
}

/// Islands per broker (`ihex-bench islands`, issue 15): N gateways, each on its own SocketCAN
/// interface with a `sim-node` island, all on one Mosquitto, under a steady report and command load.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct IslandsResults {
    /// Kernel, CPU count and model as seen where the run happened.
    pub environment: String,
    /// CPUs online where the run happened.
    pub cpus: usize,
    /// Islands (gateway + sim-node pairs), `vcan0..`.
    pub islands: usize,
    /// Simulated elements per island.
    pub nodes_per_island: u16,
    /// Seconds from starting the simulators until every gateway had reported all its nodes online.
    pub online_s: f64,
    /// Length of the measurement, s.
    pub secs: f64,
    /// Report frames per second per island asked for.
    pub report_rate: f64,
    /// LED commands per second per island asked for.
    pub command_rate: f64,
    /// Report frames written (each should become one `node_rebooted` event).
    pub reports_sent: usize,
    /// Their events received.
    pub events_received: usize,
    /// Report frame written → its event at the bench's MQTT client (subscribed to `+/EventsTopic`).
    pub event_latency: Summary,
    /// LED commands published.
    pub commands_sent: usize,
    /// Their `command_result` events with result `ok`.
    pub commands_ok: usize,
    /// Their `command_result` events with another result, or `command_rejected`.
    pub commands_not_ok: usize,
    /// Command published → its `command_result` (any result) at the bench's client.
    pub command_rtt: Summary,
    /// Command published → the same command delivered back to the bench's client (subscribed to
    /// `+/CommandsTopic` too): the broker hop alone, the part of `command_rtt` no gateway is in.
    #[serde(default)]
    pub command_to_broker: Summary,
    /// Mosquitto's CPU (utime + stime) over the measurement, ms.
    pub broker_cpu_ms: f64,
    /// PUBLISH packets Mosquitto received and sent per second over the measurement (its `$SYS`
    /// counters; `None` when they did not come).
    pub broker_msgs_per_s: Option<f64>,
    /// The gateways' CPU over the measurement, summed, ms.
    pub gateways_cpu_ms: f64,
    /// The busiest gateway's CPU over the measurement, ms.
    pub gateway_cpu_max_ms: f64,
    /// The simulators' CPU over the measurement, summed, ms.
    pub sims_cpu_ms: f64,
    /// The benchmark process's own CPU over the measurement, ms.
    pub bench_cpu_ms: f64,
    /// The gateways' resident memory at the end (VmRSS), KiB: largest and sum.
    pub gateway_rss_max_kib: u64,
    /// Sum of the gateways' VmRSS, KiB.
    pub gateway_rss_sum_kib: u64,
    /// The largest gateway peak (VmHWM), KiB.
    pub gateway_hwm_max_kib: u64,
    /// The simulators' VmRSS summed, KiB.
    pub sims_rss_sum_kib: u64,
    /// Share of all CPUs busy over the measurement (`/proc/stat`), 0–1.
    pub machine_busy: f64,
    /// `/proc/loadavg`'s 1-minute figure at the end.
    pub load_avg_1m: f64,
    /// The idle islands (no load, health checks only) measured the same way just before.
    #[serde(default)]
    pub idle: Cost,
    /// Other events seen during the measurement, by name, with their counts (e.g. `node_lost`).
    pub other_events: Vec<(String, usize)>,
    /// Notes about the run (anomalies).
    pub notes: Vec<String>,
}

/// CPU used over a stretch of time by the processes of the islands-per-broker run.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Cost {
    /// Length of the stretch, s.
    pub secs: f64,
    /// Mosquitto's CPU, ms.
    pub broker_cpu_ms: f64,
    /// The gateways' CPU summed, ms.
    pub gateways_cpu_ms: f64,
    /// The simulators' CPU summed, ms.
    pub sims_cpu_ms: f64,
    /// Share of all CPUs busy (`/proc/stat`), 0–1.
    pub machine_busy: f64,
}

impl Cost {
    /// A CPU time over the stretch as % of one CPU.
    pub fn pct(&self, cpu_ms: f64) -> f64 {
        cpu_ms / (self.secs.max(1e-9) * 1000.0) * 100.0
    }
}

impl IslandsResults {
    /// A CPU time over the measurement as % of one CPU.
    pub fn pct(&self, cpu_ms: f64) -> f64 {
        cpu_ms / (self.secs.max(1e-9) * 1000.0) * 100.0
    }

    /// Mosquitto's CPU per 1,000 PUBLISH packets it handled (received + sent), ms.
    pub fn broker_ms_per_1k(&self) -> Option<f64> {
        let msgs = self.broker_msgs_per_s? * self.secs;
        (msgs > 0.0).then(|| self.broker_cpu_ms * 1000.0 / msgs)
    }

    /// Reports whose event never came.
    pub fn events_lost(&self) -> usize {
        self.reports_sent.saturating_sub(self.events_received)
    }
}
