//! Firmware update of a simulated island (issue 12's benchmark): the demo gateway (embedded broker)
//! with a simulated island of static elements read from an island file, a test-signed image
//! uploaded over MQTT and `fw_update` to all of them at once; then to one element alone, the unit of
//! a sequential update. LED commands during the update and a docking in the middle of it are timed
//! against the same commands on the idle island. Last, five mobile elements are docked on five
//! static elements and the whole island is updated again: the time against the update without
//! dockings (issue 28's goal: at most 1.5 times as long).
//!
//! The simulated island is the gateway's in-process one, so the bus itself takes no time: the
//! transfer is paced by the gateway's bus-share cap alone (counted in bits on the wire, as on a real
//! bus), and the nodes' work is that of the simulator on this machine.

use std::collections::HashMap;
use std::net::{Ipv4Addr, SocketAddr};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use ihex_bench::results::FwResults;
use ihex_bench::stats::Summary;
use ihex_gateway_core::event::Event;
use ihex_gateway_core::fwupdate::{FwReport, UploadResult};
use ihex_proto::FirmwareVersion;
use rumqttc::QoS;
use sim_node::board::{sim_image, SimFirmware, SIM_PAYLOAD_LEN};

use crate::live::{free_port, Mqtt, Proc};
use crate::web::DEMO_QUIET;

/// The island's static elements are 101, 102, …; the mobile element 2 docks during the update.
pub(crate) fn island(n: u16) -> String {
    let statics: String = (0..n)
        .map(|i| format!("[[static]]\nid = \"{:x}\"\nports = 6\n\n", 0x101 + i))
        .collect();
    format!("{statics}[[mobile]]\nid = \"2\"\nport = 0\n")
}

/// [`island`] with the mobile elements 3… (free, unpowered until docked) that join 2 for the
/// update with docked mobile elements.
fn island_with_mobiles(n: u16) -> String {
    let more: String = (3..2 + DOCKED)
        .map(|m| format!("\n[[mobile]]\nid = \"{m}\"\nport = 0\n"))
        .collect();
    format!("{}{more}", island(n))
}

/// Mobile elements docked for the last update (on 101…105, port 3).
const DOCKED: u16 = 5;

/// The simulator's control message that docks mobile 2 on 101's port 3.
const DOCK: &str = r#"{"sim":"dock","mobile":"2","static":"101","port":3}"#;

fn led(node: &str, request_id: &str) -> String {
    format!(r#"{{"cmd":"led","node":"{node}","color":"red","request_id":"{request_id}"}}"#)
}

/// What the reader loop waits for, and what it saw while waiting.
#[derive(Default)]
struct Seen {
    /// LED probes sent and not answered yet, by `request_id`.
    probes: HashMap<String, Instant>,
    /// Answered probes' latencies, µs.
    latencies: Vec<f64>,
    /// When a `new_connection` of mobile 2 arrived.
    docked: Option<Instant>,
}

impl Seen {
    fn on(&mut self, at: Instant, event: &Event) {
        match event {
            Event::CommandResult(r) => {
                if let Some(sent) = r.request_id.as_ref().and_then(|id| self.probes.remove(id)) {
                    self.latencies.push((at - sent).as_secs_f64() * 1e6);
                }
            }
            // The first only: a static element rebooting into its new image powers its mobile
            // element off and on, and the docking is announced again.
            Event::NewConnection(c) if c.n.id.to_string() == "2" && self.docked.is_none() => {
                self.docked = Some(at)
            }
            _ => {}
        }
    }
}

struct Bench {
    mqtt: Mqtt,
    gateway: Proc,
    seen: Seen,
    probe: u64,
}

impl Bench {
    fn publish(&self, topic: &str, payload: impl Into<Vec<u8>>) -> Result<()> {
        self.mqtt
            .client
            .publish(topic, QoS::AtLeastOnce, false, payload)?;
        Ok(())
    }

    /// The next event within `wait` (recorded on the way), or `None`.
    fn pump(&mut self, wait: Duration) -> Result<Option<Event>> {
        match self.mqtt.next_event(wait) {
            Some((at, event)) => {
                self.seen.on(at, &event);
                Ok(Some(event))
            }
            None => {
                self.gateway.check_alive()?;
                Ok(None)
            }
        }
    }

    /// Reads events until `done` returns a value, for `within` at most.
    fn until<T>(
        &mut self,
        within: Duration,
        mut done: impl FnMut(&Event) -> Option<T>,
    ) -> Result<T> {
        let deadline = Instant::now() + within;
        while let Some(left) = deadline.checked_duration_since(Instant::now()) {
            if let Some(v) = self
                .pump(left.min(Duration::from_millis(200)))?
                .as_ref()
                .and_then(&mut done)
            {
                return Ok(v);
            }
        }
        bail!("not within {within:?}")
    }

    fn send_probe(&mut self, node: &str) -> Result<()> {
        self.probe += 1;
        let id = format!("fw-probe-{}", self.probe);
        self.seen.probes.insert(id.clone(), Instant::now());
        self.publish("CommandsTopic", led(node, &id))
    }

    /// `n` LED probes to `node`, one after the other, on the idle island.
    fn idle_probes(&mut self, n: usize, node: &str) -> Result<Summary> {
        self.seen.latencies.clear();
        for _ in 0..n {
            self.send_probe(node)?;
            let id = format!("fw-probe-{}", self.probe);
            self.until(Duration::from_secs(5), |e| {
                matches!(e, Event::CommandResult(r) if r.request_id.as_deref() == Some(id.as_str()))
                    .then_some(())
            })
            .context("an LED command on the idle island")?;
        }
        Ok(Summary::of(std::mem::take(&mut self.seen.latencies)))
    }

    /// Docks mobile 2 on 101 port 3 on the idle island and undocks it again; the docking's
    /// latency (the simulator's dock → `new_connection`).
    fn idle_docking(&mut self) -> Result<Duration> {
        let sent = Instant::now();
        self.publish("ihex/sim", DOCK)?;
        self.until(Duration::from_secs(30), |e| {
            matches!(e, Event::NewConnection(c) if c.n.id.to_string() == "2").then_some(())
        })
        .context("a docking on the idle island")?;
        let docked = self.seen.docked.take().map_or(sent.elapsed(), |d| d - sent);
        self.publish("ihex/sim", r#"{"sim":"undock","mobile":"2"}"#)?;
        self.until(Duration::from_secs(30), |e| {
            matches!(e, Event::ConnectionRemoved(c) if c.n.id.to_string() == "2").then_some(())
        })
        .context("undocking on the idle island")?;
        // Without power it is lost after a few health periods: until then `all` would count it.
        self.until(Duration::from_secs(60), |e| {
            matches!(e, Event::NodeLost(l) if l.id.to_string() == "2").then_some(())
        })
        .context("the undocked mobile element lost")?;
        Ok(docked)
    }

    fn upload(&mut self, name: &str, image: Vec<u8>) -> Result<()> {
        self.publish(&format!("ihex/fw/upload/{name}"), image)?;
        let (result, reason) = self
            .until(Duration::from_secs(30), |e| match e {
                Event::FwUpload(u) if u.name == name => Some((u.result, u.reason.clone())),
                _ => None,
            })
            .context("the gateway's fw_upload answer")?;
        if result != UploadResult::Stored {
            bail!("the gateway rejected the image: {reason:?}");
        }
        Ok(())
    }

    /// `fw_update` of `image` to `nodes`; while it runs, an LED probe to `probe_node` every 250 ms
    /// and mobile 2 docked on 101 once `dock_after` has passed. Returns the report, the update's
    /// wall time and the docking's latency.
    fn update(
        &mut self,
        image: &str,
        nodes: &str,
        request_id: &str,
        probe_node: Option<&str>,
        dock_after: Option<Duration>,
    ) -> Result<(FwReport, Duration, Option<Duration>)> {
        let started = Instant::now();
        self.publish(
            "CommandsTopic",
            format!(
                r#"{{"cmd":"fw_update","image":"{image}","nodes":"{nodes}","request_id":"{request_id}"}}"#
            ),
        )?;
        let probe_every = Duration::from_millis(250);
        let mut next_probe = started + probe_every;
        let mut dock_at = dock_after.map(|d| started + d);
        let mut dock_sent = None;
        self.seen.latencies.clear();
        self.seen.docked = None;
        loop {
            let now = Instant::now();
            if now - started > Duration::from_secs(900) {
                bail!("no fw_report within 900 s");
            }
            if let Some(node) = probe_node.filter(|_| now >= next_probe) {
                self.send_probe(node)?;
                next_probe = now + probe_every;
            }
            if dock_at.is_some_and(|t| now >= t) {
                dock_at = None;
                dock_sent = Some(now);
                self.publish("ihex/sim", DOCK)?;
            }
            if let Some(Event::FwReport(r)) = self.pump(Duration::from_millis(50))? {
                if r.request_id.as_deref() == Some(request_id) {
                    let docking = dock_sent.zip(self.seen.docked).map(|(s, d)| d - s);
                    return Ok((*r, started.elapsed(), docking));
                }
            }
        }
    }
}

fn outcomes(r: &FwReport) -> Vec<(String, usize)> {
    let mut counts: HashMap<String, usize> = HashMap::new();
    for n in &r.nodes {
        let name = serde_json::to_value(n.outcome)
            .ok()
            .and_then(|v| v.as_str().map(str::to_string))
            .unwrap_or_else(|| "?".into());
        *counts.entry(name).or_default() += 1;
    }
    let mut v: Vec<_> = counts.into_iter().collect();
    v.sort();
    v
}

/// Runs the demo gateway `bin` with an island of `nodes` static elements and measures the updates.
pub fn run(bin: &Path, nodes: u16) -> Result<FwResults> {
    let dir = std::env::temp_dir().join(format!("ihex-bench-fw-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let island_file = dir.join("island.toml");
    std::fs::write(&island_file, island_with_mobiles(nodes))?;
    let broker = SocketAddr::from((Ipv4Addr::LOCALHOST, free_port()?));
    let mut cmd = Command::new(bin);
    cmd.args(["--broker-listen", &broker.to_string()])
        .arg("--island-file")
        .arg(&island_file)
        .args(["--http", "off"])
        .args(DEMO_QUIET);
    let mut gateway = Proc::spawn(
        cmd,
        &dir.join("gateway.log"),
        "mc-gateway (demo, firmware update)",
    )?;
    gateway.wait_listening(broker, Duration::from_secs(30))?;
    let mqtt = Mqtt::connect(broker, &["EventsTopic"])?;
    let mut b = Bench {
        mqtt,
        gateway,
        seen: Seen::default(),
        probe: 0,
    };
    // Every static element online (the island boots with the gateway, before anyone subscribes:
    // ask with `list` until it says so; the free mobile element has no power yet).
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        b.publish(
            "CommandsTopic",
            r#"{"cmd":"list","request_id":"bench-list"}"#,
        )?;
        // The first `list` may go out before the subscription is in place: no answer is asked
        // again, like too few online.
        let online = b
            .until(Duration::from_secs(5), |e| match e {
                Event::NodeList(l) if l.request_id.as_deref() == Some("bench-list") => {
                    Some(l.nodes.iter().filter(|n| n.online).count())
                }
                _ => None,
            })
            .unwrap_or(0);
        if online >= usize::from(nodes) {
            break;
        }
        if Instant::now() > deadline {
            bail!(
                "{online} of {nodes} static elements online after 60 s (log: {})",
                dir.join("gateway.log").display()
            );
        }
        std::thread::sleep(Duration::from_millis(500));
    }

    let idle = b.idle_probes(50, "102")?;
    let idle_docking = b.idle_docking()?;
    let key = ihex_image::SigningKey::test_key();
    let image = |minor: u8| {
        sim_image(
            FirmwareVersion::new(9, minor, 0),
            SimFirmware { confirms: true },
            SIM_PAYLOAD_LEN,
            &key,
        )
    };
    b.upload("bench-all.ihex", image(1)?)?;
    let (all, all_wall, docking) = b.update(
        "bench-all.ihex",
        "all",
        "bench-all",
        Some("102"),
        Some(Duration::from_secs(2)),
    )?;
    let during = Summary::of(std::mem::take(&mut b.seen.latencies));
    b.upload("bench-one.ihex", image(2)?)?;
    let (one, one_wall, _) = b.update("bench-one.ihex", "101", "bench-one", None, None)?;
    // Five mobile elements docked, each on its own static element: 2 is still on 101 port 3 from
    // the first update, 3… join it on 102… The update to all then installs each of those statics
    // only after its mobile element has its outcome.
    let more = DOCKED.min(nodes).saturating_sub(1);
    for m in 1..=more {
        let dock = format!(
            r#"{{"sim":"dock","mobile":"{}","static":"{:x}","port":3}}"#,
            2 + m,
            0x101 + m
        );
        b.publish("ihex/sim", dock)?;
    }
    let mut docked = 0;
    b.until(Duration::from_secs(60), |e| {
        if matches!(e, Event::NewConnection(c) if c.n.id.to_string() != "2") {
            docked += 1;
        }
        (docked >= more).then_some(())
    })
    .context("the mobile elements docked")?;
    b.upload("bench-docked.ihex", image(3)?)?;
    let (docked_report, docked_wall, _) =
        b.update("bench-docked.ihex", "all", "bench-docked", None, None)?;
    b.gateway.check_alive()?;
    Ok(FwResults {
        docked_mobiles: DOCKED.min(nodes),
        docked_s: docked_wall.as_secs_f64(),
        docked_outcomes: outcomes(&docked_report),
        nodes,
        image_bytes: image(1)?.len(),
        bus_share_cap: all.bus_share,
        broadcast_s: all_wall.as_secs_f64(),
        broadcast_report_ms: all.duration_ms,
        broadcast_frames: all.frames_sent,
        broadcast_outcomes: outcomes(&all),
        one_node_s: one_wall.as_secs_f64(),
        one_node_frames: one.frames_sent,
        one_node_outcomes: outcomes(&one),
        command_idle: idle,
        command_during: during,
        docking_idle_ms: idle_docking.as_secs_f64() * 1e3,
        docking_during_ms: docking.map(|d| d.as_secs_f64() * 1e3),
    })
}
