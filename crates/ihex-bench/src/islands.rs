//! Islands per broker (issue 15): `N` gateways, each on its own SocketCAN interface (`vcan0..`)
//! with a `sim-node` island of simulated elements, all on one Mosquitto. Under a steady load of
//! report frames and LED commands on every island, one MQTT client subscribed to `+/EventsTopic`
//! times each report frame to its event and each command to its `command_result`; the CPU of the
//! broker, the gateways and the simulators is read from `/proc` over the measurement.
//!
//! The report is a `Fault` with a code this protocol version does not define, written in the name
//! of a simulated element and numbered in its `detail`: exactly one `fault` event (`other_<n>`),
//! and nothing else. The gateway rate-limits faults per element and code (one a second), so the
//! code changes with every report of an element (247 codes, 20 elements: a pair comes back after
//! 4,940 reports). Not the live benchmark's `BootUp`: from an element the gateway reads back, a
//! `BootUp` is a reboot and costs a state read-back (a query and up to 16 reply frames, the
//! simulator's work, state documents) besides its event. The element itself never sees the frame
//! (its kernel filters pass commands and broadcasts only) and keeps answering health checks, so the
//! gateways run with their deployed health period.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use ihex_bench::results::{Cost, IslandsResults};
use ihex_bench::stats::Summary;
use ihex_gateway_core::event::{Event, Outcome};
use ihex_proto::{FaultCode, Message, NodeId, Packet};
use rumqttc::QoS;
use socketcan::CanSocket;

use crate::fw::island;
use crate::live::{
    cpu_ms, environment, frame, memory_kib, open_can, paced, start_mosquitto, write, Mqtt, Proc,
};

/// Settings of one run.
#[derive(Clone, Debug)]
pub struct Settings {
    /// The `mc-gateway` binary (one process per island).
    pub gateway: PathBuf,
    /// The `sim-node` binary (one process per island).
    pub sim_node: PathBuf,
    /// The `mosquitto` binary.
    pub mosquitto: PathBuf,
    /// Islands, on `vcan0..vcan{islands-1}`.
    pub islands: usize,
    /// Static elements per island.
    pub nodes: u16,
    /// Report frames per second per island.
    pub report_rate: f64,
    /// LED commands per second per island.
    pub command_rate: f64,
    /// Length of the measurement, s.
    pub secs: f64,
}

/// The island file's first static element (`fw::island`: 101, 102, …).
const FIRST: u16 = 0x101;
/// The first fault code no protocol version defines (1..=8 are named).
const FIRST_CODE: u8 = 9;
/// Fault codes the reports cycle through (`other_9` .. `other_255`).
const CODES: u32 = 256 - FIRST_CODE as u32;
/// Mosquitto's counters of PUBLISH packets (published every `sys_interval`, 1 s here).
const SYS_RECEIVED: &str = "$SYS/broker/publish/messages/received";
const SYS_SENT: &str = "$SYS/broker/publish/messages/sent";
/// How long the idle islands' cost is measured before the load.
const IDLE: Duration = Duration::from_secs(5);
/// How long after the load the answers still count.
const GRACE: Duration = Duration::from_secs(10);

fn name(i: usize) -> String {
    format!("lab{i:02}")
}

/// The `k`th report of an island of `nodes` elements: a `Fault` of element `k % nodes` with the
/// code `other_{9 + (k / nodes) % 247}` and `k` as its detail.
fn report(nodes: u16, k: u32) -> Result<Packet> {
    let n = u32::from(nodes);
    let id = NodeId::new(FIRST + (k % n) as u16).ok_or_else(|| anyhow!("node {k} out of range"))?;
    Ok(Packet::report(
        id,
        Message::Fault {
            code: FaultCode::from_raw(FIRST_CODE + ((k / n) % CODES) as u8),
            arg: 0,
            detail: k,
        },
    ))
}

/// The report index of a `fault` event the benchmark caused (the inverse of [`report`]).
fn report_index(nodes: u16, event: &Event) -> Option<u32> {
    let Event::Fault(f) = event else {
        return None;
    };
    let k = f.detail;
    let n = u32::from(nodes);
    let element = u32::from(f.node.0.get()).checked_sub(u32::from(FIRST))?;
    let FaultCode::Other(code) = FaultCode::from_text(&f.code)? else {
        return None;
    };
    let code = u32::from(code);
    (element == k % n && code == u32::from(FIRST_CODE) + (k / n) % CODES).then_some(k)
}

/// What the load threads did, for the reader to match.
enum Sent {
    /// Report `index` written on island `island`'s bus.
    Report {
        island: usize,
        index: u32,
        at: Instant,
    },
    /// A command with this `request_id` published.
    Command { id: String, at: Instant },
}

/// Samples of one kind of probe, matched in whichever order sending and receiving are seen.
#[derive(Default)]
struct Matcher<K> {
    /// Sent, not answered yet.
    sent: HashMap<K, Instant>,
    /// Answered before the sender's record came (the reader is a thread of its own).
    arrived: HashMap<K, Instant>,
    /// Answered and matched.
    matched: HashSet<K>,
    latencies: Vec<f64>,
}

impl<K: std::hash::Hash + Eq + Clone> Matcher<K> {
    fn sent(&mut self, key: K, at: Instant) {
        match self.arrived.remove(&key) {
            Some(got) => {
                self.latencies.push(micros(at, got));
                self.matched.insert(key);
            }
            None => {
                self.sent.insert(key, at);
            }
        }
    }

    /// An answer for `key`; true if it is its first (a duplicate is ignored).
    fn arrived(&mut self, key: K, at: Instant) -> bool {
        if self.matched.contains(&key) {
            return false;
        }
        match self.sent.remove(&key) {
            Some(sent) => {
                self.latencies.push(micros(sent, at));
                self.matched.insert(key);
                true
            }
            None => self.arrived.insert(key, at).is_none(),
        }
    }

    fn done(&self) -> bool {
        self.sent.is_empty()
    }
}

fn micros(from: Instant, to: Instant) -> f64 {
    to.saturating_duration_since(from).as_secs_f64() * 1e6
}

/// `/proc/stat`'s busy and total jiffies of all CPUs.
fn cpu_jiffies() -> (u64, u64) {
    let stat = std::fs::read_to_string("/proc/stat").unwrap_or_default();
    let v: Vec<u64> = stat
        .lines()
        .next()
        .unwrap_or_default()
        .split_whitespace()
        .skip(1)
        .filter_map(|f| f.parse().ok())
        .collect();
    let total: u64 = v.iter().sum();
    // idle and iowait
    let idle = v.get(3).copied().unwrap_or(0) + v.get(4).copied().unwrap_or(0);
    (total - idle, total)
}

fn load_avg() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|l| l.split_whitespace().next()?.parse().ok())
        .unwrap_or(f64::NAN)
}

fn cpu_each(procs: &[Proc]) -> Result<Vec<f64>> {
    procs.iter().map(|p| cpu_ms(p.pid())).collect()
}

fn check_alive(procs: &mut [Proc], dir: &Path, what: &str) -> Result<()> {
    for (i, p) in procs.iter_mut().enumerate() {
        if let Err(e) = p.check_alive() {
            let log =
                std::fs::read_to_string(dir.join(format!("{what}-{i:02}.log"))).unwrap_or_default();
            bail!("{e} (island {}); its log: {log}", name(i));
        }
    }
    Ok(())
}

/// The latest value of Mosquitto's `$SYS` PUBLISH counters and when it came.
#[derive(Clone, Copy, Default)]
struct SysCount {
    received: Option<(Instant, u64)>,
    sent: Option<(Instant, u64)>,
}

/// Rate of a counter between two readings, per second.
fn rate(a: Option<(Instant, u64)>, b: Option<(Instant, u64)>) -> Option<f64> {
    let ((t0, v0), (t1, v1)) = (a?, b?);
    let secs = t1.checked_duration_since(t0)?.as_secs_f64();
    (secs > 0.5).then(|| v1.saturating_sub(v0) as f64 / secs)
}

/// CPU times and counters at one moment of the measurement.
struct Snapshot {
    at: Instant,
    gateways: Vec<f64>,
    sims: Vec<f64>,
    broker: f64,
    bench: f64,
    /// `/proc/stat`: busy and total jiffies.
    jiffies: (u64, u64),
    sys: SysCount,
}

impl Snapshot {
    /// CPU used between `start` and this snapshot.
    fn cost_since(&self, start: &Snapshot) -> Cost {
        let sum = |a: &[f64], b: &[f64]| -> f64 { b.iter().zip(a).map(|(b, a)| b - a).sum() };
        Cost {
            secs: (self.at - start.at).as_secs_f64(),
            broker_cpu_ms: self.broker - start.broker,
            gateways_cpu_ms: sum(&start.gateways, &self.gateways),
            sims_cpu_ms: sum(&start.sims, &self.sims),
            machine_busy: (self.jiffies.0 - start.jiffies.0) as f64
                / (self.jiffies.1 - start.jiffies.1).max(1) as f64,
        }
    }

    fn take(gateways: &[Proc], sims: &[Proc], broker: &Proc, sys: SysCount) -> Result<Snapshot> {
        Ok(Snapshot {
            at: Instant::now(),
            gateways: cpu_each(gateways)?,
            sims: cpu_each(sims)?,
            broker: cpu_ms(broker.pid())?,
            bench: cpu_ms(std::process::id())?,
            jiffies: cpu_jiffies(),
            sys,
        })
    }
}

/// Everything the reader learns from the broker.
struct Reader {
    nodes: u16,
    islands: usize,
    mqtt: Mqtt,
    sys: SysCount,
    online: Vec<HashSet<NodeId>>,
    available: HashSet<usize>,
    reports: Matcher<(usize, u32)>,
    commands: Matcher<String>,
    /// The commands as the broker delivers them back to the benchmark (its own subscription).
    echoes: Matcher<String>,
    commands_ok: usize,
    commands_not_ok: usize,
    other: BTreeMap<String, usize>,
    /// Count the events that are neither probes nor answers (only during the measurement).
    counting: bool,
}

/// The island of `topic` when it is `labNN/rest` for one of the `islands`.
fn island_of(topic: &str, rest: &str, islands: usize) -> Option<usize> {
    let (prefix, tail) = topic.split_once('/')?;
    let i: usize = prefix.strip_prefix("lab")?.parse().ok()?;
    (tail == rest && i < islands && topic.starts_with(&name(i))).then_some(i)
}

impl Reader {
    /// Handles one message within `timeout`; false when none came.
    fn pump(&mut self, timeout: Duration) -> bool {
        let Some((at, topic, payload)) = self.mqtt.recv(timeout) else {
            return false;
        };
        let value = || String::from_utf8_lossy(&payload).trim().parse::<u64>().ok();
        if topic == SYS_RECEIVED {
            self.sys.received = value().map(|v| (at, v));
        } else if topic == SYS_SENT {
            self.sys.sent = value().map(|v| (at, v));
        } else if let Some(i) = island_of(&topic, "ihex/gateway/availability", self.islands) {
            if payload == b"online" {
                self.available.insert(i);
            }
        } else if let Some(i) = island_of(&topic, "EventsTopic", self.islands) {
            if let Ok(event) = serde_json::from_slice::<Event>(&payload) {
                self.on_event(i, at, event);
            }
        } else if island_of(&topic, "CommandsTopic", self.islands).is_some() {
            let command: serde_json::Value = serde_json::from_slice(&payload).unwrap_or_default();
            if let Some(id) = command["request_id"].as_str() {
                self.echoes.arrived(id.to_owned(), at);
            }
        }
        true
    }

    /// What a load thread sent, to be matched with its answer.
    fn sent(&mut self, sent: Sent) {
        match sent {
            Sent::Report { island, index, at } => self.reports.sent((island, index), at),
            Sent::Command { id, at } => {
                self.echoes.sent(id.clone(), at);
                self.commands.sent(id, at);
            }
        }
    }

    fn on_event(&mut self, island: usize, at: Instant, event: Event) {
        if let Some(index) = report_index(self.nodes, &event) {
            self.reports.arrived((island, index), at);
            return;
        }
        match &event {
            Event::NodeOnline(o) => {
                self.online[island].insert(o.id.0);
            }
            Event::NodeLost(l) => {
                self.online[island].remove(&l.id.0);
            }
            Event::CommandResult(r) => {
                if let Some(id) = &r.request_id {
                    if self.commands.arrived(id.clone(), at) {
                        if r.result == Outcome::Ok {
                            self.commands_ok += 1;
                        } else {
                            self.commands_not_ok += 1;
                        }
                    }
                    return;
                }
            }
            Event::CommandRejected(r) if r.request_id.is_some() => {
                if let Some(id) = &r.request_id {
                    if self.commands.arrived(id.clone(), at) {
                        self.commands_not_ok += 1;
                    }
                }
                return;
            }
            _ => {}
        }
        if self.counting {
            *self.other.entry(event.name().to_owned()).or_default() += 1;
        }
    }
}

/// Runs the islands-per-broker benchmark.
pub fn run(s: Settings) -> Result<IslandsResults> {
    if s.islands == 0 || s.islands > 100 || s.nodes == 0 || s.nodes > 0xff {
        bail!("1..=100 islands of 1..=255 elements");
    }
    let (environment, cpus) = environment();
    println!("bench: {environment}");
    let dir = std::env::temp_dir().join(format!("ihex-bench-islands-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let file = dir.join("island.toml");
    std::fs::write(&file, island(s.nodes))?;
    let mut notes = Vec::new();

    // `$SYS` every second: the broker's own count of what it handled.
    let (broker, addr) = start_mosquitto(&s.mosquitto, &dir, false, "sys_interval 1\n")?;
    let mqtt = Mqtt::connect(
        addr,
        &[
            "+/EventsTopic",
            "+/ihex/gateway/availability",
            "+/CommandsTopic",
            SYS_RECEIVED,
            SYS_SENT,
        ],
    )?;
    let mut r = Reader {
        nodes: s.nodes,
        islands: s.islands,
        mqtt,
        sys: SysCount::default(),
        online: vec![HashSet::new(); s.islands],
        available: HashSet::new(),
        reports: Matcher::default(),
        commands: Matcher::default(),
        echoes: Matcher::default(),
        commands_ok: 0,
        commands_not_ok: 0,
        other: BTreeMap::new(),
        counting: false,
    };

    println!("bench: {} gateways on one Mosquitto", s.islands);
    let mut gateways = Vec::new();
    for i in 0..s.islands {
        let mut c = Command::new(&s.gateway);
        c.args(["--can", &format!("vcan{i}"), "--island", &name(i)])
            .args(["--broker", &addr.to_string()])
            .args(["--log-dir", "-", "--log", "warn"]);
        gateways.push(Proc::spawn(
            c,
            &dir.join(format!("gateway-{i:02}.log")),
            "mc-gateway",
        )?);
    }
    let deadline = Instant::now() + Duration::from_secs(120);
    while r.available.len() < s.islands {
        // `$SYS` comes every second: check the processes whether or not a message came.
        r.pump(Duration::from_millis(500));
        check_alive(&mut gateways, &dir, "gateway")?;
        if Instant::now() > deadline {
            bail!(
                "only {} of {} gateways came online within 120 s",
                r.available.len(),
                s.islands
            );
        }
    }

    println!(
        "bench: {} sim-node islands of {} elements",
        s.islands, s.nodes
    );
    let started = Instant::now();
    let mut sims = Vec::new();
    for i in 0..s.islands {
        let mut c = Command::new(&s.sim_node);
        c.args(["--iface", &format!("vcan{i}"), "--island"])
            .arg(&file)
            .env("RUST_LOG", "warn");
        sims.push(Proc::spawn(
            c,
            &dir.join(format!("sim-{i:02}.log")),
            "sim-node",
        )?);
    }
    let deadline = started + Duration::from_secs(180);
    let want = usize::from(s.nodes);
    while r.online.iter().any(|o| o.len() < want) {
        r.pump(Duration::from_millis(500));
        check_alive(&mut gateways, &dir, "gateway")?;
        check_alive(&mut sims, &dir, "sim")?;
        if Instant::now() > deadline {
            let counts: Vec<String> = r.online.iter().map(|o| o.len().to_string()).collect();
            bail!(
                "not every node online within 180 s (online per island: {})",
                counts.join(", ")
            );
        }
    }
    let online_s = started.elapsed().as_secs_f64();
    println!(
        "bench: all {} nodes online after {online_s:.1} s",
        s.islands * want
    );
    // Let the start-up traffic (state read-backs, discovery configs) pass, then take the cost of
    // the idle islands (health checks, the broker's housekeeping) as the floor under the load.
    let quiet_until = Instant::now() + Duration::from_secs(3);
    while let Some(left) = quiet_until.checked_duration_since(Instant::now()) {
        r.pump(left);
    }
    println!("bench: {IDLE:?} idle");
    let idle_start = Snapshot::take(&gateways, &sims, &broker, r.sys)?;
    let idle_until = idle_start.at + IDLE;
    while let Some(left) = idle_until.checked_duration_since(Instant::now()) {
        r.pump(left);
    }
    let idle = Snapshot::take(&gateways, &sims, &broker, r.sys)?.cost_since(&idle_start);

    let sockets: Vec<CanSocket> = (0..s.islands)
        .map(|i| open_can(&format!("vcan{i}"), &mut notes))
        .collect::<Result<_>>()?;
    let (tx, rx) = mpsc::sync_channel::<Sent>(1 << 16);
    let stop = Arc::new(AtomicBool::new(false));
    let islands = s.islands;
    let nodes = s.nodes;
    let reports = (s.report_rate * s.secs) as usize * islands;
    let commands = (s.command_rate * s.secs) as usize * islands;

    println!(
        "bench: {:.0} reports/s and {:.1} LED commands/s per island for {:.0} s",
        s.report_rate, s.command_rate, s.secs
    );
    let start = Snapshot::take(&gateways, &sims, &broker, r.sys)?;
    let t0 = start.at;

    let report_tx = tx.clone();
    let report_stop = stop.clone();
    let report_rate = s.report_rate * islands as f64;
    let writer = std::thread::spawn(move || -> Result<usize> {
        let (sent, _) = paced(reports, report_rate, Some(&report_stop), |k| {
            let island = k as usize % islands;
            let index = k / islands as u32;
            let f = frame(&report(nodes, index)?)?;
            let at = Instant::now();
            write(&sockets[island], &f)?;
            report_tx
                .send(Sent::Report { island, index, at })
                .map_err(|_| anyhow!("reader gone"))
        })?;
        Ok(sent)
    });
    // Commands go out through a client of their own: the reader's client takes in hundreds of
    // messages a second, and rumqttc's event loop hands out every incoming packet it has read
    // before it takes the next request from its queue; sharing it, the commands waited for
    // seconds in the 1-vCPU VM before they even reached the broker.
    let publisher = Mqtt::connect_as("ihex-bench-commands", addr, &[])?;
    let client = publisher.client.clone();
    let command_stop = stop.clone();
    let command_rate = s.command_rate * islands as f64;
    let commander = std::thread::spawn(move || -> Result<usize> {
        if commands == 0 {
            return Ok(0);
        }
        let (sent, _) = paced(commands, command_rate, Some(&command_stop), |k| {
            let island = k as usize % islands;
            let n = k / islands as u32;
            let id = format!("i{island}-{n}");
            let node = FIRST + (n % u32::from(nodes)) as u16;
            let command = format!(
                r#"{{"cmd":"led","node":"{node:x}","color":[{},{},0],"request_id":"{id}"}}"#,
                n & 0xff,
                n >> 8 & 0xff
            );
            let at = Instant::now();
            client.publish(
                format!("{}/CommandsTopic", name(island)),
                QoS::AtLeastOnce,
                false,
                command,
            )?;
            tx.send(Sent::Command { id, at })
                .map_err(|_| anyhow!("reader gone"))
        })?;
        Ok(sent)
    });

    // Read while the load runs, then until every probe is answered, for `GRACE` at most (the
    // `$SYS` counters arrive every second, so "nothing came for a while" never happens).
    r.counting = true;
    let stop_at = t0 + Duration::from_secs_f64(s.secs);
    let mut ended: Option<Snapshot> = None;
    let mut checked = t0;
    loop {
        r.pump(Duration::from_millis(50));
        while let Ok(sent) = rx.try_recv() {
            r.sent(sent);
        }
        let now = Instant::now();
        if ended.is_none() && (now >= stop_at || (writer.is_finished() && commander.is_finished()))
        {
            ended = Some(Snapshot::take(&gateways, &sims, &broker, r.sys)?);
            stop.store(true, Ordering::Relaxed);
        }
        if let Some(e) = &ended {
            if writer.is_finished() && commander.is_finished() {
                let all = r.reports.done() && r.commands.done() && r.echoes.done();
                if all || now.duration_since(e.at) > GRACE {
                    break;
                }
            }
        }
        if ended.is_none() && now.duration_since(checked) >= Duration::from_secs(1) {
            checked = now;
            check_alive(&mut gateways, &dir, "gateway")?;
            check_alive(&mut sims, &dir, "sim")?;
        }
    }
    r.counting = false;
    let reports_sent = writer
        .join()
        .map_err(|_| anyhow!("report writer panicked"))??;
    let commands_sent = commander
        .join()
        .map_err(|_| anyhow!("command writer panicked"))??;
    while let Ok(sent) = rx.try_recv() {
        r.sent(sent);
    }
    let Some(end) = ended else {
        bail!("the measurement did not end");
    };
    let secs = (end.at - t0).as_secs_f64();
    check_alive(&mut gateways, &dir, "gateway")?;
    check_alive(&mut sims, &dir, "sim")?;

    let delta =
        |a: &[f64], b: &[f64]| -> Vec<f64> { b.iter().zip(a).map(|(b, a)| b - a).collect() };
    let gw_cpu = delta(&start.gateways, &end.gateways);
    let sim_cpu = delta(&start.sims, &end.sims);
    let mut rss_max = 0;
    let mut rss_sum = 0;
    let mut hwm_max = 0;
    for g in &gateways {
        let (hwm, rss) = memory_kib(g.pid())?;
        rss_max = rss_max.max(rss);
        rss_sum += rss;
        hwm_max = hwm_max.max(hwm);
    }
    let mut sims_rss = 0;
    for p in &sims {
        sims_rss += memory_kib(p.pid())?.1;
    }
    let broker_msgs_per_s = match (
        rate(start.sys.received, end.sys.received),
        rate(start.sys.sent, end.sys.sent),
    ) {
        (Some(a), Some(b)) => Some(a + b),
        _ => {
            notes.push("Mosquitto's $SYS counters did not come: no broker message rate".into());
            None
        }
    };
    let overflows = r.mqtt.overflows();
    if overflows > 0 {
        notes.push(format!(
            "bench MQTT receive queue overflowed {overflows} times"
        ));
    }
    let busy =
        (end.jiffies.0 - start.jiffies.0) as f64 / (end.jiffies.1 - start.jiffies.1).max(1) as f64;
    let results = IslandsResults {
        environment,
        cpus,
        islands: s.islands,
        nodes_per_island: s.nodes,
        online_s,
        secs,
        report_rate: s.report_rate,
        command_rate: s.command_rate,
        reports_sent,
        events_received: r.reports.latencies.len(),
        event_latency: Summary::of(std::mem::take(&mut r.reports.latencies)),
        commands_sent,
        commands_ok: r.commands_ok,
        commands_not_ok: r.commands_not_ok,
        command_rtt: Summary::of(std::mem::take(&mut r.commands.latencies)),
        command_to_broker: Summary::of(std::mem::take(&mut r.echoes.latencies)),
        broker_cpu_ms: end.broker - start.broker,
        broker_msgs_per_s,
        gateways_cpu_ms: gw_cpu.iter().sum(),
        gateway_cpu_max_ms: gw_cpu.iter().copied().fold(0.0, f64::max),
        sims_cpu_ms: sim_cpu.iter().sum(),
        bench_cpu_ms: end.bench - start.bench,
        gateway_rss_max_kib: rss_max,
        gateway_rss_sum_kib: rss_sum,
        gateway_hwm_max_kib: hwm_max,
        sims_rss_sum_kib: sims_rss,
        machine_busy: busy,
        load_avg_1m: load_avg(),
        other_events: r.other.into_iter().collect(),
        idle,
        notes,
    };
    drop(sims);
    drop(gateways);
    drop(broker);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(results)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_report_comes_back_from_its_event_and_is_never_throttled() {
        for nodes in [1u16, 20, 255] {
            for k in [0, 1, 19, 20, 4939, 4940, 1_000_000] {
                let p = report(nodes, k).unwrap();
                let Message::Fault { code, detail, .. } = p.msg else {
                    panic!("report {k} must be a Fault")
                };
                assert_eq!(code.name(), None, "report {k}: {code} is a defined code");
                assert_eq!(detail, k);
                // The event as the gateway publishes it, read back as the bench reads it.
                let json = serde_json::json!({"event": "fault", "payload": {
                    "node": p.src.to_string(), "code": code.to_string(), "arg": 0,
                    "detail": detail, "message": "-"}});
                let ev: Event = serde_json::from_value(json).unwrap();
                assert_eq!(report_index(nodes, &ev), Some(k));
            }
            // The gateway publishes one fault per element and code a second: an element's next
            // report must have another code, the pair coming back only after nodes × 247 reports.
            let key = |k: u32| {
                let p = report(nodes, k).unwrap();
                let Message::Fault { code, .. } = p.msg else {
                    unreachable!()
                };
                (p.src, code)
            };
            let n = u32::from(nodes);
            let period = n * CODES;
            let keys: HashSet<_> = (0..period).map(key).collect();
            assert_eq!(keys.len(), period as usize);
            assert_eq!(key(period), key(0));
        }
        // A fault nobody made up (a defined code) is not one of the benchmark's.
        let real: Event = serde_json::from_value(serde_json::json!({"event": "fault", "payload": {
            "node": "101", "code": "bus_off", "arg": 0, "detail": 0, "message": "-"}}))
        .unwrap();
        assert_eq!(report_index(20, &real), None);
    }

    #[test]
    fn matcher_pairs_in_either_order_and_ignores_strays() {
        let t = Instant::now();
        let mut m = Matcher::default();
        m.sent(1, t);
        assert!(m.arrived(1, t + Duration::from_millis(2)));
        // The answer is read before the writer's record of the send.
        assert!(m.arrived(2, t + Duration::from_millis(5)));
        m.sent(2, t + Duration::from_millis(1));
        assert!(m.done());
        assert!(!m.arrived(2, t + Duration::from_millis(9)));
        // A duplicate answer counts nothing.
        assert!(!m.arrived(1, t + Duration::from_millis(9)));
        m.sent(3, t);
        assert!(!m.done());
        assert_eq!(m.latencies, vec![2000.0, 4000.0]);
    }

    #[test]
    fn topics_name_their_island() {
        assert_eq!(island_of("lab07/EventsTopic", "EventsTopic", 16), Some(7));
        assert_eq!(island_of("lab16/EventsTopic", "EventsTopic", 16), None);
        assert_eq!(island_of("lab7/EventsTopic", "EventsTopic", 16), None);
        assert_eq!(
            island_of("lab03/ihex/node/101/state", "EventsTopic", 16),
            None
        );
        assert_eq!(island_of("EventsTopic", "EventsTopic", 16), None);
    }
}
