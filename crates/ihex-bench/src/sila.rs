//! The SiLA server's cost (issue 31): the demo gateway (embedded broker, simulated island) on this
//! machine, driven by a gRPC client built from the gateway's own generated protos (tonic, plaintext
//! on loopback with `--sila-insecure`).
//!
//! * Round trip: `IslandControl.SetLight` on element 111 → the node's acknowledgement → the
//!   response, alternating probe by probe with the same LED command published on MQTT → its
//!   `command_result` at an MQTT subscriber, on the same gateway in the same run.
//! * Memory (`VmHWM`, `VmRSS`): a gateway with `--sila off`, and one with the server on, each after
//!   the same MQTT commands; the latter again after the probes with [`CLIENTS`] clients, each on its
//!   own connection, first only connected, then subscribed to `ElementStates` and sent new states.

use std::net::{Ipv4Addr, SocketAddr};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use ihex_bench::results::SilaResults;
use ihex_bench::stats::Summary;
use mc_gateway::sila::proto::{
    framework,
    island_control::{self as pb, island_control_client::IslandControlClient},
};
use tokio::runtime::Runtime;
use tonic::transport::Channel;

use crate::live::{free_port, memory_kib, Mqtt, Proc};
use crate::process::{colour, led_probe, NODE};
use crate::web::DEMO_QUIET;

/// Subscribed SiLA clients in the last memory figure.
pub const CLIENTS: usize = 100;
/// How long one probe may take before it counts as lost.
const PROBE_TIMEOUT: Duration = Duration::from_secs(2);
/// How long the gateway may take to start and its island to answer.
const START: Duration = Duration::from_secs(30);
/// MQTT commands every gateway carries out before its memory is read.
const SETTLE_COMMANDS: usize = 100;

/// One demo gateway and an MQTT client of its broker.
struct Demo {
    gateway: Proc,
    mqtt: Mqtt,
    sila: Option<SocketAddr>,
    /// Probes sent so far (their `request_id`s and colours).
    sent: usize,
}

impl Demo {
    /// Starts the demo gateway `bin`, with its SiLA server on a free loopback port or off, and
    /// waits until the island answers an LED command.
    fn start(bin: &Path, sila: bool, log: &Path) -> Result<Demo> {
        let broker = SocketAddr::from((Ipv4Addr::LOCALHOST, free_port()?));
        let mut cmd = Command::new(bin);
        cmd.args(["--broker-listen", &broker.to_string(), "--http", "off"])
            .args(DEMO_QUIET);
        let sila = if sila {
            let a = SocketAddr::from((Ipv4Addr::LOCALHOST, free_port()?));
            cmd.args(["--sila", &a.to_string(), "--sila-insecure"])
                .args(["--sila-announce", "off"]);
            Some(a)
        } else {
            cmd.args(["--sila", "off"]);
            None
        };
        let mut gateway = Proc::spawn(cmd, log, "mc-gateway (demo)")?;
        gateway.wait_listening(broker, START)?;
        if let Some(a) = sila {
            gateway.wait_listening(a, START)?;
        }
        let name = if sila.is_some() {
            "ihex-bench-sila-on"
        } else {
            "ihex-bench-sila-off"
        };
        let mqtt = Mqtt::connect_as(name, broker, &["EventsTopic"])?;
        let mut demo = Demo {
            gateway,
            mqtt,
            sila,
            sent: 0,
        };
        let ready = Instant::now() + START;
        while demo.mqtt_probe()?.is_none() {
            demo.gateway.check_alive()?;
            if Instant::now() > ready {
                bail!(
                    "the demo island never acknowledged an LED command within {START:?} (log: {})",
                    log.display()
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        Ok(demo)
    }

    /// An LED command on MQTT; its round trip when its `command_result` said `ok` in time.
    fn mqtt_probe(&mut self) -> Result<Option<Duration>> {
        let i = self.next();
        led_probe(
            &self.mqtt,
            &format!("sila-bench-{i}"),
            &colour(i),
            PROBE_TIMEOUT,
        )
    }

    /// `SetLight` with the next probe's colour; its round trip when it succeeded in time.
    async fn sila_probe(&mut self, c: &mut IslandControlClient<Channel>) -> Option<Duration> {
        let i = self.next();
        let text = |v: String| Some(framework::String { value: v });
        let int = |value| Some(framework::Integer { value });
        let light = pb::SetLightParameters {
            element_id: text(NODE.into()),
            color: text(colour(i)),
            brightness: int(100),
            blink_period: int(0),
            blink_duty: int(50),
        };
        let sent = Instant::now();
        let r = tokio::time::timeout(PROBE_TIMEOUT, c.set_light(light)).await;
        matches!(r, Ok(Ok(_))).then(|| sent.elapsed())
    }

    fn next(&mut self) -> usize {
        self.sent += 1;
        self.sent
    }

    /// [`SETTLE_COMMANDS`] MQTT commands, a pause, then the gateway's memory.
    fn settled_memory(&mut self) -> Result<(u64, u64)> {
        for _ in 0..SETTLE_COMMANDS {
            self.mqtt_probe()?;
        }
        std::thread::sleep(Duration::from_millis(500));
        self.gateway.check_alive()?;
        memory_kib(self.gateway.pid())
    }

    /// A new connection to the SiLA server.
    async fn channel(&self) -> Result<Channel> {
        let addr = self.sila.context("the SiLA server is off")?;
        Channel::from_shared(format!("http://{addr}"))?
            .connect()
            .await
            .with_context(|| format!("connecting to the SiLA server on {addr}"))
    }
}

fn us(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

/// Runs the demo gateway `bin` twice (SiLA off, then on) and `probes` probes of each interface,
/// one every `gap`.
pub fn run(bin: &Path, probes: usize, gap: Duration) -> Result<SilaResults> {
    let dir = std::env::temp_dir().join(format!("ihex-bench-sila-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let rt: Runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    // Timeouts made outside `block_on` need the runtime's timer.
    let _entered = rt.enter();

    let memory_off_kib = {
        let mut off = Demo::start(bin, false, &dir.join("gateway-sila-off.log"))?;
        off.settled_memory()?
    };

    let mut on = Demo::start(bin, true, &dir.join("gateway-sila-on.log"))?;
    let memory_idle_kib = on.settled_memory()?;

    let mut client = IslandControlClient::new(rt.block_on(on.channel())?);
    // The first call opens the HTTP/2 connection: not a probe.
    rt.block_on(on.sila_probe(&mut client))
        .context("the SiLA server did not carry out SetLight")?;
    let (mut sila, mut mqtt) = (Vec::new(), Vec::new());
    let (mut sila_lost, mut mqtt_lost) = (0, 0);
    for _ in 0..probes {
        match rt.block_on(on.sila_probe(&mut client)) {
            Some(d) => sila.push(us(d)),
            None => sila_lost += 1,
        }
        std::thread::sleep(gap);
        match on.mqtt_probe()? {
            Some(d) => mqtt.push(us(d)),
            None => mqtt_lost += 1,
        }
        std::thread::sleep(gap);
    }
    on.gateway.check_alive()?;

    // Each client on its own connection (the memory of the connections alone first), then
    // subscribed, its first value read.
    let mut clients = Vec::with_capacity(CLIENTS);
    for _ in 0..CLIENTS {
        clients.push(IslandControlClient::new(rt.block_on(on.channel())?));
    }
    let memory_connected_kib = on.settled_memory()?;
    let mut streams = Vec::with_capacity(CLIENTS);
    for c in &mut clients {
        let mut s = rt.block_on(async {
            let mut s = c
                .subscribe_element_states(pb::SubscribeElementStatesParameters {})
                .await?
                .into_inner();
            tokio::time::timeout(PROBE_TIMEOUT, s.message())
                .await
                .context("no first ElementStates value within 2 s")??
                .context("the ElementStates stream ended")?;
            anyhow::Ok(s)
        })?;
        // Read again below: whatever the subscription said before the commands is not news.
        while let Ok(Ok(Some(_))) = rt.block_on(tokio::time::timeout(Duration::ZERO, s.message())) {
        }
        streams.push(s);
    }
    let memory_before = on.settled_memory()?;
    let mut clients_updated = 0;
    for s in &mut streams {
        if let Ok(Ok(Some(_))) = rt.block_on(tokio::time::timeout(PROBE_TIMEOUT, s.message())) {
            clients_updated += 1;
        }
    }
    on.gateway.check_alive()?;
    let (hwm, rss) = memory_kib(on.gateway.pid())?;
    drop(streams);
    drop(clients);
    let _ = std::fs::remove_dir_all(&dir);
    Ok(SilaResults {
        probes,
        sila_lost,
        mqtt_lost,
        sila_round_trip: Summary::of(sila),
        mqtt_round_trip: Summary::of(mqtt),
        clients: CLIENTS,
        clients_updated,
        memory_off_kib,
        memory_idle_kib,
        memory_connected_kib,
        memory_clients_kib: (hwm.max(memory_before.0), rss),
    })
}
