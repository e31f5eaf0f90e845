//! Runs a fault plan against the real parts and records the [`Trace`]: a Mosquitto broker, the
//! [`Proxy`] between it and the `mc-gateway` binary (a child process, so it can be killed with
//! SIGKILL), a simulated island on a leased vcan interface, and four observers — the commander
//! (publishes commands), the recorder (everything under the island's prefix, straight from the
//! broker), a bus listener (every frame) and the island's truth after each change.
//!
//! After each fault the harness waits until the system is seen back (the fault's recovery: the
//! gateway `online` again, the bus `recovered`, the node back), keeps still for two health periods
//! and takes a checkpoint: the island's truth and the broker's retained documents, as a fresh
//! client sees them. The [checker](super::check) does the judging.

use std::collections::BTreeMap;
use std::io;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::{Child, Command as Process, Stdio};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use ihex_proto::{BootRole, NodeId};
use ihex_sc_core::BuzzerOutput;
use mc_gateway::topic::Topics;
use rumqttc::{AsyncClient, Event, Incoming, QoS};
use sim_node::{link::Link, Island as SimIsland, IslandDesc, IslandHandle, NodeView};
use socketcan::tokio::CanSocket;
use tokio::task::JoinHandle;
use tokio::time::Instant;

use super::plan::{Island, Plan, Timing};
use super::trace::{Element, Entry, Fault, IslandAction, Ms, Params, Record, Sent, Trace};
use crate::broker::Mosquitto;
use crate::mqtt;
use crate::proxy::{Direction, Mode, Proxy};

/// Environment variable naming the `mc-gateway` binary (default: `mc-gateway` beside the test
/// binary's `deps/` folder, where `cargo build -p mc-gateway` puts it).
pub const GATEWAY_BIN_ENV: &str = "IHEX_GATEWAY_BIN";

/// The island of every run: the demo's (static 111 and 112, mobile 2 docked on 111 port 3 by its
/// port 0, mobile 3 free with port 1).
pub const ISLAND: &str = mc_gateway::demo::BUILTIN_ISLAND;

/// The island name (topic prefix) of the gateway under test.
const PREFIX: &str = "faults";

/// The `mc-gateway` binary to run.
pub fn gateway_binary() -> Result<PathBuf, String> {
    if let Some(p) = std::env::var_os(GATEWAY_BIN_ENV) {
        return Ok(p.into());
    }
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let beside = exe
        .parent()
        .and_then(Path::parent)
        .map(|d| d.join("mc-gateway"));
    match beside {
        Some(p) if p.is_file() => Ok(p),
        _ => Err(format!(
            "no mc-gateway binary: build it (`cargo build -p mc-gateway`, next to this test's \
             target folder) or set {GATEWAY_BIN_ENV}; `cargo xtask test --stage vcan` and \
             `cargo xtask soak` do both"
        )),
    }
}

/// The shared record of a run.
#[derive(Clone)]
struct Recorder {
    start: Instant,
    records: Arc<Mutex<Vec<Record>>>,
}

impl Recorder {
    fn now(&self) -> Ms {
        self.start.elapsed().as_millis() as Ms
    }

    fn record(&self, entry: Entry) -> Ms {
        let mut records = self.records.lock().unwrap_or_else(|p| p.into_inner());
        // Stamped under the lock, so the records stay in time order.
        let at = self.now();
        records.push(Record { at, entry });
        at
    }

    fn len(&self) -> usize {
        self.records.lock().unwrap_or_else(|p| p.into_inner()).len()
    }

    /// The first record from index `from` on that `pred` accepts.
    fn find(&self, from: usize, pred: &dyn Fn(&Record) -> bool) -> Option<Record> {
        let records = self.records.lock().unwrap_or_else(|p| p.into_inner());
        records.iter().skip(from).find(|r| pred(r)).cloned()
    }

    /// Waits until a record from index `from` on passes `pred`, for at most `within`.
    async fn wait(
        &self,
        from: usize,
        within: Duration,
        pred: &dyn Fn(&Record) -> bool,
    ) -> Option<Record> {
        let deadline = Instant::now() + within;
        loop {
            if let Some(r) = self.find(from, pred) {
                return Some(r);
            }
            if Instant::now() >= deadline {
                return None;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

/// The gateway as a child process.
struct Gateway {
    bin: PathBuf,
    args: Vec<String>,
    child: Option<Child>,
    logs: Vec<PathBuf>,
    dir: PathBuf,
}

impl Gateway {
    fn start(&mut self) -> io::Result<()> {
        let log = self.dir.join(format!("gateway-{}.log", self.logs.len()));
        let file = std::fs::File::create(&log)?;
        let child = Process::new(&self.bin)
            .args(&self.args)
            .env("NO_COLOR", "1")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(file)
            .spawn()?;
        self.logs.push(log);
        self.child = Some(child);
        Ok(())
    }

    /// SIGKILL, like `kill -9`: no `offline`, no flushing; the broker publishes the last will.
    fn kill(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// The last `lines` lines of every run's log.
    fn tail(&self, lines: usize) -> String {
        self.logs
            .iter()
            .map(|p| {
                let text = std::fs::read_to_string(p).unwrap_or_default();
                let all: Vec<&str> = text.lines().collect();
                let from = all.len().saturating_sub(lines);
                format!("--- {} ---\n{}", p.display(), all[from..].join("\n"))
            })
            .collect::<Vec<_>>()
            .join("\n")
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Everything a run needs, running.
pub struct Rig {
    rec: Recorder,
    timing: Timing,
    plan: Plan,
    island: Island,
    broker: Mosquitto,
    proxy: Proxy,
    iface: String,
    sim: IslandHandle,
    own_ports: BTreeMap<NodeId, u8>,
    gateway: Gateway,
    topics: Topics,
    commander: AsyncClient,
    docked: Vec<Option<(String, u8)>>,
    faults: u32,
    sent: u32,
    tasks: Vec<JoinHandle<()>>,
}

fn hex(id: NodeId) -> String {
    id.to_string()
}

fn node(hex_id: &str) -> NodeId {
    sim_node::desc::parse_node_id(hex_id).unwrap_or(NodeId::BROADCAST)
}

fn is_availability(r: &Record, topics: &Topics, what: &str) -> bool {
    matches!(&r.entry, Entry::Received { topic, payload, .. }
        if *topic == topics.availability && payload == what)
}

fn is_bus_error(r: &Record, topics: &Topics, error: &str) -> bool {
    matches!(&r.entry, Entry::Received { topic, payload, .. }
        if *topic == topics.events
            && serde_json::from_str::<serde_json::Value>(payload)
                .is_ok_and(|v| v["event"] == "bus_error" && v["payload"]["error"] == error))
}

fn buzzer_text(b: BuzzerOutput) -> String {
    match b {
        BuzzerOutput::Off => "off".into(),
        BuzzerOutput::Tone { freq_hz } => format!("on {freq_hz}"),
        BuzzerOutput::Pattern {
            freq_hz,
            on_ms,
            off_ms,
            count,
        } => format!("pattern {freq_hz} {on_ms} {off_ms} {count}"),
    }
}

fn element(v: &NodeView, own_ports: &BTreeMap<NodeId, u8>) -> Element {
    let d = v.actuators.led.duty;
    Element {
        id: hex(v.node_id.unwrap_or(v.name)),
        mobile: v.role == BootRole::Mobile,
        own_port: own_ports.get(&v.name).copied().unwrap_or(0),
        powered: v.powered,
        on_bus: v.on_bus,
        led: [d.r, d.g, d.b],
        blink: v.actuators.led.blink,
        buzzer: buzzer_text(v.actuators.buzzer),
        relay: v.actuators.relay,
        docked: v.docked.map(|(s, p)| (hex(s), p.get())),
    }
}

async fn truth(sim: &IslandHandle, own_ports: &BTreeMap<NodeId, u8>) -> Vec<Element> {
    sim.snapshot()
        .await
        .map(|all| all.iter().map(|v| element(v, own_ports)).collect())
        .unwrap_or_default()
}

impl Rig {
    /// Starts broker, proxy, island, observers and the gateway, and waits until the gateway is
    /// online and has published a state document for every node on the bus.
    pub async fn start(seed: u64) -> Result<Rig, String> {
        let timing = Timing::for_this_machine();
        let rec = Recorder {
            start: Instant::now(),
            records: Arc::default(),
        };
        rec.record(Entry::Note(format!(
            "seed {seed} ({}={seed} repeats this plan); timing {timing:?}",
            super::plan::SEED_ENV
        )));
        let broker = Mosquitto::start().map_err(|e| e.to_string())?;
        let proxy = Proxy::start(broker.addr())
            .await
            .map_err(|e| format!("proxy: {e}"))?;
        let iface = crate::can::lease();
        let desc = IslandDesc::parse(ISLAND).map_err(|e| e.to_string())?;
        let own_ports: BTreeMap<NodeId, u8> =
            desc.mobiles.iter().map(|m| (m.id, m.port.get())).collect();
        let island = Island {
            statics: desc.statics.iter().map(|s| hex(s.id)).collect(),
            mobiles: desc
                .mobiles
                .iter()
                .map(|m| (hex(m.id), m.port.get()))
                .collect(),
            dock_ports: vec![("111".into(), 3), ("112".into(), 2)],
        };
        let docked = desc
            .mobiles
            .iter()
            .map(|m| m.dock.map(|(s, p)| (hex(s), p.get())))
            .collect();
        let topics = Topics::new(
            Some(PREFIX),
            mc_gateway::topic::COMMANDS,
            mc_gateway::topic::EVENTS,
            mc_gateway::topic::AVAILABILITY,
            mc_gateway::topic::NODE_STATE_ROOT,
        );

        let mut tasks = Vec::new();
        tasks.push(tokio::spawn(record_mqtt(rec.clone(), broker.addr())));
        tasks.push(tokio::spawn(listen_bus(rec.clone(), iface.clone())));
        let sim = SimIsland::start(&desc, Link::socketcan(iface.clone()))
            .map_err(|e| format!("island: {e}"))?;
        tasks.push(tokio::spawn(watch_island(
            rec.clone(),
            sim.clone(),
            own_ports.clone(),
        )));
        let (commander, mut el) =
            AsyncClient::new(mqtt::options(broker.addr(), "faults-commander"), 256);
        tasks.push(tokio::spawn(async move {
            loop {
                if el.poll().await.is_err() {
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }));

        let dir = std::env::temp_dir().join(format!("ihex-faults-{}-{seed}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
        let args: Vec<String> = [
            "--broker",
            &proxy.addr().to_string(),
            "--can",
            &iface,
            "--island",
            PREFIX,
            "--health-period-ms",
            &timing.health_period_ms.to_string(),
            "--lost-after",
            &timing.lost_after.to_string(),
            "--command-timeout-ms",
            &timing.command_timeout_ms.to_string(),
            "--dock-timeout-ms",
            &timing.dock_timeout_ms.to_string(),
            "--keep-alive",
            &timing.keep_alive_s.to_string(),
            "--broker-ack-timeout-ms",
            &timing.broker_ack_timeout_ms.to_string(),
            "--log-dir",
            "-",
        ]
        .map(String::from)
        .to_vec();
        let mut gateway = Gateway {
            bin: gateway_binary()?,
            args,
            child: None,
            logs: Vec::new(),
            dir,
        };
        gateway
            .start()
            .map_err(|e| format!("starting {}: {e}", gateway.bin.display()))?;

        let mut rig = Rig {
            rec,
            timing,
            plan: Plan::new(seed),
            island,
            broker,
            proxy,
            iface,
            sim,
            own_ports,
            gateway,
            topics,
            commander,
            docked,
            faults: 0,
            sent: 0,
            tasks,
        };
        let t = rig.topics.clone();
        let up = rig
            .rec
            .wait(0, rig.settle_limit(), &|r| is_availability(r, &t, "online"))
            .await;
        if up.is_none() {
            return Err(format!(
                "the gateway did not come online\n{}",
                rig.gateway.tail(40)
            ));
        }
        // Let it learn the island, then the first checkpoint: the start is a recovery too.
        rig.quiet(2 * rig.timing.health_period_ms).await;
        rig.checkpoint(None).await;
        Ok(rig)
    }

    /// How long a recovery may take before the run calls it failed.
    fn settle_limit(&self) -> Duration {
        Duration::from_millis(20_000 + 4 * self.timing.slack_ms)
    }

    fn params(&self) -> Params {
        Params {
            health_period_ms: self.timing.health_period_ms,
            lost_after: self.timing.lost_after,
            command_timeout_ms: self.timing.command_timeout_ms,
            slack_ms: self.timing.slack_ms,
            dock_timeout_ms: self.timing.dock_timeout_ms,
        }
    }

    async fn quiet(&self, ms: u64) {
        tokio::time::sleep(Duration::from_millis(ms)).await;
    }

    /// Random commands and island activity for `ms`.
    async fn activity(&mut self, ms: u64) {
        let until = Instant::now() + Duration::from_millis(ms);
        while Instant::now() < until {
            self.send_command().await;
            let docked = self.docked.clone();
            if let Some(a) = self.plan.island_action(&self.island, &docked) {
                self.island_action(a).await;
            }
            let pause = self.plan.pause_ms(&self.timing);
            tokio::time::sleep(Duration::from_millis(pause)).await;
        }
    }

    async fn send_command(&mut self) {
        let c = self.plan.command(&self.island, &self.timing);
        self.publish(&c, false).await;
    }

    async fn publish(&mut self, c: &super::plan::Command, retained: bool) {
        self.sent += 1;
        let n = self.sent;
        let payload = c.payload();
        self.rec.record(Entry::Sent(Sent {
            n,
            payload: payload.clone(),
            request_id: c.request_id.clone(),
            retained,
            ttl_ms: c.ttl_ms,
            action: c.action.clone(),
        }));
        let r = self
            .commander
            .publish(&self.topics.commands, QoS::AtLeastOnce, retained, payload)
            .await;
        if let Err(e) = r {
            self.rec
                .record(Entry::Note(format!("command #{n} not queued: {e}")));
        }
    }

    async fn island_action(&mut self, a: IslandAction) {
        let r = match &a {
            IslandAction::Dock { mobile, at, port } => {
                self.sim.dock(node(mobile), node(at), *port).await
            }
            IslandAction::Undock { mobile } => self.sim.undock(node(mobile)).await,
        };
        match r {
            Ok(()) => {
                if let Some(i) = self.mobile_index(&a) {
                    self.docked[i] = match &a {
                        IslandAction::Dock { at, port, .. } => Some((at.clone(), *port)),
                        IslandAction::Undock { .. } => None,
                    };
                }
                self.rec.record(Entry::Island(a));
            }
            Err(e) => {
                self.rec
                    .record(Entry::Note(format!("island refused {a:?}: {e}")));
            }
        }
    }

    fn mobile_index(&self, a: &IslandAction) -> Option<usize> {
        let m = match a {
            IslandAction::Dock { mobile, .. } | IslandAction::Undock { mobile } => mobile,
        };
        self.island.mobiles.iter().position(|(id, _)| id == m)
    }

    /// Injects one fault with activity around it, waits for the recovery, keeps still for two
    /// health periods and takes a checkpoint.
    pub async fn fault(&mut self, what: Fault) {
        let lead = self.timing.ms(500 + u64::from(self.faults % 3) * 500);
        self.activity(lead).await;
        self.faults += 1;
        let n = self.faults;
        let from = self.rec.len();
        self.rec.record(Entry::FaultBegin {
            fault: n,
            what: what.clone(),
        });
        let t = self.topics.clone();
        let limit = self.settle_limit();
        let recovered: Option<String> = match &what {
            Fault::BrokerKill { down_ms } => {
                self.broker.stop();
                self.activity(*down_ms).await;
                if let Err(e) = self.broker.restart() {
                    self.rec.record(Entry::Note(format!("broker restart: {e}")));
                }
                self.rec.record(Entry::FaultEnd { fault: n });
                let since = self.rec.len();
                self.rec
                    .wait(since, limit, &|r| is_availability(r, &t, "online"))
                    .await
                    .map(|_| "availability online".into())
            }
            Fault::GatewayKill { down_ms } => {
                self.gateway.kill();
                // Once the broker published the last will, the gateway's session is gone: a
                // retained command now can only ever reach it as a replay.
                let offline = self
                    .rec
                    .wait(from, limit, &|r| is_availability(r, &t, "offline"))
                    .await;
                if offline.is_some() {
                    let c = self.plan.retained_command(&self.island);
                    self.publish(&c, true).await;
                }
                self.activity(*down_ms).await;
                if let Err(e) = self.gateway.start() {
                    self.rec
                        .record(Entry::Note(format!("gateway restart: {e}")));
                }
                self.rec.record(Entry::FaultEnd { fault: n });
                let since = self.rec.len();
                self.rec
                    .wait(since, limit, &|r| is_availability(r, &t, "online"))
                    .await
                    .map(|_| "availability online".into())
            }
            Fault::ProxyCut { ms } => {
                self.proxy.set(Mode::Cut);
                let offline = self
                    .rec
                    .wait(from, limit, &|r| is_availability(r, &t, "offline"))
                    .await;
                if offline.is_some() {
                    let c = self.plan.retained_command(&self.island);
                    self.publish(&c, true).await;
                }
                self.activity(*ms).await;
                self.proxy.set(Mode::Pass);
                self.rec.record(Entry::FaultEnd { fault: n });
                let since = self.rec.len();
                self.rec
                    .wait(since, limit, &|r| is_availability(r, &t, "online"))
                    .await
                    .map(|_| "availability online".into())
            }
            Fault::ProxyDelay { delay_ms, ms } => {
                self.proxy
                    .set(Mode::Delay(Duration::from_millis(*delay_ms)));
                self.activity(*ms).await;
                self.proxy.set(Mode::Pass);
                self.rec.record(Entry::FaultEnd { fault: n });
                Some("proxy passing again".into())
            }
            Fault::ProxyHalfOpen { ms, noticed } => {
                self.proxy.set(Mode::HalfOpen(Direction::Both));
                self.activity(*ms).await;
                self.proxy.set(Mode::Pass);
                self.rec.record(Entry::FaultEnd { fault: n });
                if *noticed {
                    let since = self.rec.len();
                    self.rec
                        .wait(since, limit, &|r| is_availability(r, &t, "online"))
                        .await
                        .map(|_| "availability online".into())
                } else {
                    Some("proxy passing again".into())
                }
            }
            Fault::CanDown { ms } => {
                let down = ip_link(&self.iface, "down");
                self.activity(*ms).await;
                let up = ip_link(&self.iface, "up");
                if let Err(e) = down.and(up) {
                    self.rec.record(Entry::Note(e));
                }
                self.rec.record(Entry::FaultEnd { fault: n });
                let since = self.rec.len();
                let noticed = self
                    .rec
                    .find(from, &|r| is_bus_error(r, &t, "interface_down"))
                    .is_some();
                if noticed {
                    self.rec
                        .wait(since, limit, &|r| is_bus_error(r, &t, "recovered"))
                        .await
                        .map(|_| "bus_error recovered".into())
                } else {
                    self.rec.record(Entry::Note(
                        "the gateway did not report the interface down".into(),
                    ));
                    Some("interface up".into())
                }
            }
            Fault::NodeReset { node: id } => {
                if let Err(e) = self.sim.power_cycle(node(id)).await {
                    self.rec.record(Entry::Note(format!("power cycle: {e}")));
                }
                self.rec.record(Entry::FaultEnd { fault: n });
                Some("power restored".into())
            }
            Fault::OffBus { node: id, ms } => {
                let off = self.sim.set_on_bus(node(id), false).await;
                self.activity(*ms).await;
                let on = self.sim.set_on_bus(node(id), true).await;
                if let Err(e) = off.and(on) {
                    self.rec.record(Entry::Note(format!("off bus: {e}")));
                }
                self.rec.record(Entry::FaultEnd { fault: n });
                Some("node back on the bus".into())
            }
        };
        let Some(how) = recovered else {
            self.rec.record(Entry::Note(format!(
                "fault {n} ({}): no recovery within {limit:?}",
                what.name()
            )));
            return;
        };
        self.rec.record(Entry::Recovered { fault: n, how });
        self.quiet(2 * self.timing.health_period_ms).await;
        self.checkpoint(Some(n)).await;
    }

    /// The truth and the broker's retained documents, now.
    async fn checkpoint(&mut self, fault: Option<u32>) {
        let truth = truth(&self.sim, &self.own_ports).await;
        let retained = match retained(self.broker.addr()).await {
            Ok(r) => r,
            Err(e) => {
                self.rec
                    .record(Entry::Note(format!("retained snapshot failed: {e}")));
                Vec::new()
            }
        };
        self.rec.record(Entry::Checkpoint {
            fault,
            truth,
            retained,
        });
    }

    /// Random activity for `ms`, then time for the last answers, a final checkpoint and the trace.
    pub async fn finish(mut self, ms: u64) -> (Trace, String) {
        self.activity(ms).await;
        self.quiet(self.timing.command_timeout_ms + self.timing.slack_ms)
            .await;
        self.checkpoint(None).await;
        let logs = self.gateway.tail(60);
        self.gateway.kill();
        for t in &self.tasks {
            t.abort();
        }
        self.sim.shutdown().await;
        let records = self
            .rec
            .records
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        (
            Trace {
                params: self.params(),
                records,
            },
            logs,
        )
    }

    /// The seed of this run.
    pub fn seed(&self) -> u64 {
        self.plan.seed
    }

    /// Every kind of fault once, in the seed's order.
    pub fn every_fault_once(&mut self) -> Vec<Fault> {
        self.plan.every_fault_once(&self.timing, &self.island)
    }

    /// A random fault.
    pub fn any_fault(&mut self) -> Fault {
        self.plan.any_fault(&self.timing, &self.island)
    }

    /// The run's timing.
    pub fn timing(&self) -> Timing {
        self.timing
    }
}

fn ip_link(iface: &str, state: &str) -> Result<(), String> {
    let st = Process::new("ip")
        .args(["link", "set", iface, state])
        .status()
        .map_err(|e| format!("ip link set {iface} {state}: {e}"))?;
    if st.success() {
        Ok(())
    } else {
        Err(format!("ip link set {iface} {state}: {st}"))
    }
}

/// The recorder: everything under the island's prefix, straight from the broker.
async fn record_mqtt(rec: Recorder, broker: SocketAddr) {
    let (client, mut el) = AsyncClient::new(mqtt::options(broker, "faults-recorder"), 64);
    let filter = format!("{PREFIX}/#");
    loop {
        match el.poll().await {
            Ok(Event::Incoming(Incoming::ConnAck(_))) => {
                rec.record(Entry::RecorderConnected);
                let _ = client.try_subscribe(filter.clone(), QoS::AtLeastOnce);
            }
            Ok(Event::Incoming(Incoming::Publish(p))) => {
                rec.record(Entry::Received {
                    topic: p.topic,
                    payload: String::from_utf8_lossy(&p.payload).into_owned(),
                    retain: p.retain,
                });
            }
            Ok(_) => {}
            Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
        }
    }
}

/// The bus listener: every data frame on the interface; reopens after the interface went away.
async fn listen_bus(rec: Recorder, iface: String) {
    use embedded_can::Frame as _;
    loop {
        let sock = match CanSocket::open(&iface) {
            Ok(s) => s,
            Err(_) => {
                tokio::time::sleep(Duration::from_millis(10)).await;
                continue;
            }
        };
        rec.record(Entry::Listening(true));
        loop {
            match sock.read_frame().await {
                Ok(socketcan::CanFrame::Data(f)) => {
                    let id = match f.id() {
                        embedded_can::Id::Extended(e) => e.as_raw(),
                        embedded_can::Id::Standard(s) => u32::from(s.as_raw()),
                    };
                    rec.record(Entry::Frame {
                        id,
                        data: f.data().to_vec(),
                    });
                }
                Ok(_) => {}
                Err(_) => break,
            }
        }
        rec.record(Entry::Listening(false));
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// The island's truth after every change.
async fn watch_island(rec: Recorder, sim: IslandHandle, own_ports: BTreeMap<NodeId, u8>) {
    let mut events = sim.subscribe();
    rec.record(Entry::Truth(truth(&sim, &own_ports).await));
    loop {
        match events.recv().await {
            Ok(_) | Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {
                rec.record(Entry::Truth(truth(&sim, &own_ports).await));
            }
            Err(tokio::sync::broadcast::error::RecvError::Closed) => return,
        }
    }
}

/// Every retained message under the island's prefix, as a client connecting now sees it.
async fn retained(broker: SocketAddr) -> Result<Vec<(String, String)>, String> {
    let mut c = mqtt::Client::connect(mqtt::options(broker, "faults-checkpoint"));
    let code = crate::within(Duration::from_secs(10), "checkpoint CONNACK", c.connack())
        .await
        .map_err(|e| e.to_string())?;
    if code != rumqttc::ConnectReturnCode::Success {
        return Err(format!("checkpoint client refused: {code:?}"));
    }
    c.subscribe(&format!("{PREFIX}/ihex/#")).await;
    // The broker sends a subscription's retained messages before it handles the next SUBSCRIBE:
    // the second SUBACK closes the burst.
    c.subscribe(&format!("{PREFIX}/checkpoint-end")).await;
    let mut latest: BTreeMap<String, String> = BTreeMap::new();
    for s in c.drain() {
        if let mqtt::Seen::Message { topic, payload, .. } = s {
            latest.insert(topic.clone(), String::from_utf8_lossy(payload).into_owned());
        }
    }
    Ok(latest.into_iter().collect())
}
