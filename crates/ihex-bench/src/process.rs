//! Instructions per command of the whole gateway process, a deterministic unit beside the VM's CPU
//! figures: the demo gateway on this machine (`--sim`, no web view), run under callgrind against a
//! Mosquitto of its own, answers LED commands one at a time. Everything the process executes
//! counts — tokio, the MQTT connection, the tasks' channels, the core, the simulated island — the
//! kernel does not. The idle cost of as long a pause is measured after the commands and subtracted.
//!
//! Measured twice: with the SiLA server off (the part of the README's gateway that is also the
//! deployed one, but for the island) and on (the README's gateway, without the web view).

use std::net::{Ipv4Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use ihex_bench::results::{ProcessCost, ProcessPhase, ProcessResults};
use ihex_gateway_core::event::{Event, Outcome};

use crate::callgrind::{inclusive, total_instructions};
use crate::live::{answers, free_port, start_mosquitto, Mqtt, Proc};

/// The static element every command colours (the built-in demo island has it).
pub(crate) const NODE: &str = "111";
/// How long one command may take under callgrind before it counts as lost.
const PROBE_TIMEOUT: Duration = Duration::from_secs(10);
/// How long the gateway may take to start under callgrind and its island to answer.
const START: Duration = Duration::from_secs(120);
/// Commands before the counted ones (the first turns of every path allocate what later ones reuse).
const WARM_UP: usize = 20;
/// Pause after each answer, so that every command is a turn of its own, as at idle.
const GAP: Duration = Duration::from_millis(5);
/// Commands published back to back in the second count, where they share the process's turns as
/// at a high rate: below the 256 unanswered LED commands a node may have.
const BURST: usize = 200;

/// Where the instructions go: each task of the process by the function tokio polls it through,
/// and the parts of the core and MQTT tasks a command meets (callgrind's names; a part is
/// indented under its task). The simulated link and island are the demo's: a deployed gateway
/// reads a CAN socket instead. What no line names is tokio's scheduler and I/O driver, and with
/// the SiLA server on, the server.
const PHASES: [(&str, &[&str]); 9] = [
    ("core task", &["mc_gateway::run::Core::run::{{closure}}"]),
    (
        "  command in (read, checked, its frame written)",
        &["mc_gateway::run::on_mqtt"],
    ),
    ("  the node's answer", &["mc_gateway::run::on_can"]),
    (
        "  answers and frames out (publications taken, JSON)",
        &["mc_gateway::run::Core::carry_out"],
    ),
    (
        "MQTT task",
        &["mc_gateway::mqtt::MqttTask::run::{{closure}}"],
    ),
    (
        "  socket reads and writes, packets parsed",
        &["mc_gateway::mqtt::conn::Connection::poll::{{closure}}"],
    ),
    (
        "  publications and PUBACKs encoded",
        &["mc_gateway::mqtt::carry_out"],
    ),
    (
        "CAN receive task (simulated link)",
        &["mc_gateway::can::receive_link::{{closure}}"],
    ),
    (
        "simulated island",
        &[
            "sim_node::island::Island::run::{{closure}}",
            "sim_node::island::Island::boot::{{closure}}",
        ],
    ),
];

/// [`PHASES`] per command: the commands' dump less the pause's scaled by `idle_scale` (the
/// commands' time over the pause's), over `n`.
fn phases(commands: &str, idle: &str, idle_scale: f64, n: usize) -> Vec<ProcessPhase> {
    let names: Vec<&str> = PHASES.iter().flat_map(|(_, f)| f.iter().copied()).collect();
    let (busy, quiet) = (inclusive(commands, &names), inclusive(idle, &names));
    let of = |f: &str| {
        let i = names.iter().position(|n| *n == f)?;
        Some(busy[i]? as f64 - quiet[i].unwrap_or(0) as f64 * idle_scale)
    };
    PHASES
        .iter()
        .map(|(phase, functions)| ProcessPhase {
            name: (*phase).to_owned(),
            per_command: functions
                .iter()
                .filter_map(|f| of(f))
                .reduce(|a, b| a + b)
                .map(|s| s / n as f64),
        })
        .collect()
}

/// An LED command with colour `colour` published on `CommandsTopic` as `request_id`: its round
/// trip when its `command_result` said `ok` within `timeout`.
pub(crate) fn led_probe(
    mqtt: &Mqtt,
    request_id: &str,
    colour: &str,
    timeout: Duration,
) -> Result<Option<Duration>> {
    let sent = Instant::now();
    publish_led(mqtt, request_id, colour)?;
    let deadline = sent + timeout;
    loop {
        let Some(left) = deadline.checked_duration_since(Instant::now()) else {
            return Ok(None);
        };
        match mqtt.next_event(left) {
            Some((t, Event::CommandResult(r))) if r.request_id.as_deref() == Some(request_id) => {
                return Ok(matches!(r.result, Outcome::Ok).then(|| t - sent));
            }
            Some(_) => {}
            None => return Ok(None),
        }
    }
}

/// Publishes an LED command with colour `colour` on `CommandsTopic` as `request_id` (QoS 1).
fn publish_led(mqtt: &Mqtt, request_id: &str, colour: &str) -> Result<()> {
    let command = format!(
        r#"{{"cmd":"led","node":"{NODE}","color":"{colour}","brightness":255,"request_id":"{request_id}"}}"#
    );
    mqtt.client
        .publish("CommandsTopic", rumqttc::QoS::AtLeastOnce, false, command)?;
    Ok(())
}

/// A colour of its own per command, so that every command changes the element's state.
pub(crate) fn colour(i: usize) -> String {
    let c = (i % 200) as u8;
    format!("#{c:02x}{:02x}28", 255 - c)
}

/// Both runs: `n` counted commands each, the gateway `gateway` (default features), Mosquitto
/// `mosquitto`; callgrind's files and the logs kept in `keep` when given.
pub fn run(
    gateway: &Path,
    mosquitto: &Path,
    n: usize,
    keep: Option<&Path>,
) -> Result<ProcessResults> {
    if n == 0 {
        bail!("--n must be at least 1");
    }
    let dir = match keep {
        Some(d) => d.to_owned(),
        None => std::env::temp_dir().join(format!("ihex-bench-process-{}", std::process::id())),
    };
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let (_broker, addr) = start_mosquitto(mosquitto, &dir, false, "")?;
    let mut runs = Vec::new();
    for sila in [false, true] {
        runs.extend(measure(gateway, addr, sila, n, &dir)?);
    }
    if keep.is_none() {
        let _ = std::fs::remove_dir_all(&dir);
    }
    Ok(ProcessResults {
        gateway: gateway.display().to_string(),
        runs,
    })
}

/// One gateway run: `n` commands one at a time, then (SiLA server off) `n` rounded up to
/// [`BURST`]s in bursts.
fn measure(
    gateway: &Path,
    broker: SocketAddr,
    sila: bool,
    n: usize,
    dir: &Path,
) -> Result<Vec<ProcessCost>> {
    let out = dir.join(format!("callgrind.sila-{sila}"));
    // A kept directory may hold an earlier run's dumps, which `dump` would take for this one's.
    for k in 1..=3 {
        let _ = std::fs::remove_file(format!("{}.{k}", out.display()));
    }
    let mut cmd = Command::new("valgrind");
    cmd.args(["--tool=callgrind", "--quiet"])
        .arg(format!("--callgrind-out-file={}", out.display()))
        .arg(gateway)
        .args(["--broker", &broker.to_string(), "--sim", "--http", "off"])
        .args([
            "--health-period-ms",
            "3600000",
            "--log-dir",
            "-",
            "--log",
            "warn",
        ]);
    if sila {
        let a = SocketAddr::from((Ipv4Addr::LOCALHOST, free_port()?));
        cmd.args([
            "--sila",
            &a.to_string(),
            "--sila-insecure",
            "--sila-announce",
            "off",
        ]);
    } else {
        cmd.args(["--sila", "off"]);
    }
    let log = dir.join(format!("gateway.sila-{sila}.log"));
    let mut gateway = Proc::spawn(cmd, &log, "mc-gateway (demo, under callgrind)")?;
    let name = format!("ihex-bench-process-{sila}");
    let mqtt = Mqtt::connect_as(&name, broker, &["EventsTopic"])?;
    let ready = Instant::now() + START;
    let mut sent = 0;
    let mut probe = |mqtt: &Mqtt| {
        sent += 1;
        led_probe(
            mqtt,
            &format!("process-{sent}"),
            &colour(sent),
            PROBE_TIMEOUT,
        )
    };
    while probe(&mqtt)?.is_none() {
        gateway.check_alive()?;
        if Instant::now() > ready {
            bail!(
                "the demo island never acknowledged an LED command within {START:?} (log: {})",
                log.display()
            );
        }
    }
    for _ in 0..WARM_UP {
        probe(&mqtt)?;
        std::thread::sleep(GAP);
    }
    let pid = gateway.pid().to_string();
    control(&pid, "-z")?;
    let start = Instant::now();
    for i in 0..n {
        if probe(&mqtt)?.is_none() {
            bail!("command {i} of {n} was not answered `ok` within {PROBE_TIMEOUT:?}: the count would mix in a timeout");
        }
        std::thread::sleep(GAP);
    }
    let took = start.elapsed();
    let (commands, busy) = dump(&pid, &out, 1)?;
    std::thread::sleep(took);
    let (idle, quiet) = dump(&pid, &out, 2)?;
    gateway.check_alive()?;
    let mut costs = vec![ProcessCost {
        sila,
        burst: None,
        commands: n,
        seconds: took.as_secs_f64(),
        instructions_commands: commands,
        instructions_idle: idle,
        per_command: (commands as f64 - idle as f64) / n as f64,
        phases: phases(&busy, &quiet, 1.0, n),
    }];
    if !sila {
        let bursts = n.div_ceil(BURST);
        let start = Instant::now();
        for b in 0..bursts {
            for k in 0..BURST {
                let i = sent + b * BURST + k;
                publish_led(&mqtt, &format!("burst-{i}"), &colour(i))?;
            }
            let (ok, note) = answers(&mqtt, BURST, PROBE_TIMEOUT);
            if ok < BURST {
                bail!(
                    "burst {b} of {bursts}: {ok} of {BURST} commands answered `ok`{}",
                    note.map_or(String::new(), |n| format!(" ({n})"))
                );
            }
        }
        let took_bursts = start.elapsed();
        let (commands, busy) = dump(&pid, &out, 3)?;
        gateway.check_alive()?;
        let counted = bursts * BURST;
        // The pause's count, scaled to the bursts' time.
        let idle_scale = took_bursts.as_secs_f64() / took.as_secs_f64();
        let idle_share = idle as f64 * idle_scale;
        costs.push(ProcessCost {
            sila,
            burst: Some(BURST),
            commands: counted,
            seconds: took_bursts.as_secs_f64(),
            instructions_commands: commands,
            instructions_idle: idle_share as u64,
            per_command: (commands as f64 - idle_share) / counted as f64,
            phases: phases(&busy, &quiet, idle_scale, counted),
        });
    }
    Ok(costs)
}

/// `callgrind_control FLAG PID`.
fn control(pid: &str, flag: &str) -> Result<()> {
    let status = Command::new("callgrind_control")
        .args([flag, pid])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .context("running callgrind_control (Debian: apt-get install valgrind)")?;
    if !status.success() {
        bail!("callgrind_control {flag} {pid} failed: {status}");
    }
    Ok(())
}

/// Asks callgrind for dump number `k` of `out` and reads its instruction total (the counts since
/// the previous dump or zeroing), with the dump itself.
fn dump(pid: &str, out: &Path, k: u32) -> Result<(u64, String)> {
    control(pid, "-d")?;
    let file = PathBuf::from(format!("{}.{k}", out.display()));
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        // The `totals:` line ends the file: before it, the dump may be half written.
        let text = std::fs::read_to_string(&file).unwrap_or_default();
        if text.contains("\ntotals:") {
            let total = total_instructions(&text)
                .with_context(|| format!("no instruction total in {}", file.display()))?;
            return Ok((total, text));
        }
        if Instant::now() > deadline {
            bail!("no instruction total in {} within 30 s", file.display());
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}
