//! `ihex-bench`: the benchmark programs `cargo xtask bench` runs (live over SocketCAN + Mosquitto,
//! islands per broker, the callgrind workload) and the report it prints. See docs/benchmarks.md.
#![forbid(unsafe_code)]

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use ihex_bench::{report, workload};

mod affinity;
mod callgrind;
mod forward;
mod fw;
mod islands;
mod live;
mod loadgen;
mod process;
#[cfg(feature = "sila")]
mod sila;
mod stamp;
mod trace;
mod watchdog;
mod web;

#[derive(Parser)]
#[command(
    name = "ihex-bench",
    about = "iHEX gateway benchmarks (run through `cargo xtask bench`)"
)]
struct Cli {
    #[command(subcommand)]
    command: Cmd,
}

#[derive(Clone, Copy, ValueEnum)]
enum WorkPath {
    /// CAN report -> event JSON.
    Can,
    /// JSON command -> frame.
    Command,
    /// JSON command -> frame, with leases held (commands to leased nodes carry the token).
    CommandLeased,
    /// JSON command -> frame -> ack -> command_result, audit trail off.
    Answered,
    /// The same, audit trail on.
    Audited,
}

#[derive(Subcommand)]
enum Cmd {
    /// The live benchmark: mc-gateway between SocketCAN and a Mosquitto it starts (or the one
    /// at `--broker`).
    Live {
        /// SocketCAN interface.
        #[arg(long, default_value = "vcan0")]
        iface: String,
        /// The plain forwarder's SocketCAN interface (the yardstick of the command cost runs
        /// beside the gateway, on a bus of its own).
        #[arg(long, default_value = "vcan1")]
        forward_iface: String,
        /// The mc-gateway binary.
        #[arg(long)]
        gateway: PathBuf,
        /// The mosquitto binary.
        #[arg(long, default_value = "/usr/sbin/mosquitto")]
        mosquitto: PathBuf,
        /// Latency probes per series.
        #[arg(long, default_value_t = 300)]
        probes: usize,
        /// Seconds of traffic per rate trial.
        #[arg(long, default_value_t = 2.0)]
        trial_secs: f64,
        /// Messages per second of the MQTT -> CAN cost rounds, one series of rounds per rate
        /// (repeat the option or separate rates by commas; the first is the headline). Default:
        /// 1,000/s and 80 % of the sustained command rate. A fixed rate makes two gateways' CPU
        /// per 1,000 commands comparable: both depend on how many commands share a wake-up.
        #[arg(long, value_delimiter = ',', value_parser = rate)]
        cost_rate: Vec<f64>,
        /// Commands in the MQTT -> CAN burst.
        #[arg(long, default_value_t = 4000)]
        commands: usize,
        /// Keep Mosquitto's default Nagle algorithm (set_tcp_nodelay false) on its sockets.
        #[arg(long)]
        mosquitto_nagle: bool,
        /// Take the kernel's trace (ftrace) of five idle commands after each idle latency series,
        /// and count the system calls of one command trial at each cost rate (gateway, forwarder).
        #[arg(long)]
        trace: bool,
        /// Use the Mosquitto already running at this address (in the microVM: the host's, at
        /// 10.0.2.2:PORT) instead of starting one here; its CPU is then not counted.
        #[arg(long)]
        broker: Option<std::net::SocketAddr>,
        /// Publish the MQTT -> CAN trials' commands and the bare ingress messages from the
        /// `ihex-bench loadgen` serving at `--broker` (asked over the broker), not from here.
        #[arg(long, requires = "broker")]
        remote_load: bool,
        /// Run the gateway and the plain forwarder alone on CPU 0 and this benchmark's threads on
        /// the other CPUs (needs two or more), so that the measured processes' CPU figures do
        /// not include the benchmark's work.
        #[arg(long)]
        pin: bool,
        /// Send the results as a JSON line to this TCP address (the host's xtask).
        #[arg(long)]
        report: Option<String>,
        /// Write the results to this file.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// A plain MQTT -> CAN forwarder (the raw forward the live part measures in the gateway's
    /// place): each message `ID#DATA` on `ihex-bench/raw` written as that frame; runs until killed.
    Forward {
        /// SocketCAN interface.
        #[arg(long, default_value = "vcan0")]
        iface: String,
        /// The broker.
        #[arg(long)]
        broker: std::net::SocketAddr,
    },
    /// The live part's MQTT load generator: publishes commands or bare messages at the broker
    /// when the live part asks over it (`live --remote-load`); runs until killed.
    Loadgen {
        /// The broker both meet at.
        #[arg(long)]
        broker: std::net::SocketAddr,
    },
    /// Islands per broker: N gateways, each on its own SocketCAN interface (vcan0..) with a
    /// sim-node island, all on one Mosquitto; report frames and LED commands on every island,
    /// timed to their events at one MQTT client; CPU of the broker, gateways and simulators.
    Islands {
        /// The mc-gateway binary.
        #[arg(long)]
        gateway: PathBuf,
        /// The sim-node binary.
        #[arg(long)]
        sim_node: PathBuf,
        /// The mosquitto binary.
        #[arg(long, default_value = "/usr/sbin/mosquitto")]
        mosquitto: PathBuf,
        /// Islands (gateway + sim-node pairs) on vcan0..vcan{N-1}.
        #[arg(long, default_value_t = 16)]
        islands: usize,
        /// Static elements per island.
        #[arg(long, default_value_t = 20)]
        nodes: u16,
        /// Report frames per second per island (each one event).
        #[arg(long, default_value_t = 10.0)]
        rate: f64,
        /// LED commands per second per island (each one command_result).
        #[arg(long, default_value_t = 1.0)]
        command_rate: f64,
        /// Length of the measurement, s.
        #[arg(long, default_value_t = 30.0)]
        secs: f64,
        /// Send the results as a JSON line to this TCP address (the host's xtask).
        #[arg(long)]
        report: Option<String>,
        /// Write the results to this file.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The island view's latency: the demo gateway (embedded broker, simulated island, web view)
    /// on this machine; LED commands over MQTT, their results read from `/api/events` and by an
    /// MQTT client.
    Web {
        /// The mc-gateway binary, built with its default features (demo and web).
        #[arg(long)]
        gateway: PathBuf,
        /// Use this MQTT broker (the simulated island with it) instead of the embedded one.
        #[arg(long)]
        broker: Option<std::net::SocketAddr>,
        /// Probes (after the warm-up).
        #[arg(long, default_value_t = 300)]
        probes: usize,
        /// Pause between probes, ms.
        #[arg(long, default_value_t = 20)]
        gap_ms: u64,
        /// Write the figures (JSON) here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The SiLA server: `SetLight` against the same LED command over MQTT on the demo gateway, and
    /// the gateway's memory with the server off, idle and with 100 subscribed clients.
    Sila {
        /// The mc-gateway binary, built with its default features (demo and sila).
        #[arg(long)]
        gateway: PathBuf,
        /// Probes of each interface (after the warm-up).
        #[arg(long, default_value_t = 300)]
        probes: usize,
        /// Pause after each probe, ms.
        #[arg(long, default_value_t = 10)]
        gap_ms: u64,
        /// Write the figures (JSON) here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Instructions per LED command of the whole demo gateway process under callgrind, against a
    /// Mosquitto of its own, with the SiLA server off and on.
    Process {
        /// The mc-gateway binary, built with its default features (demo and sila).
        #[arg(long)]
        gateway: PathBuf,
        /// The Mosquitto binary.
        #[arg(long, default_value = "mosquitto")]
        mosquitto: PathBuf,
        /// Commands counted in each run.
        #[arg(long, default_value_t = 400)]
        n: usize,
        /// Keep callgrind's files in this directory (`callgrind.sila-false.1` is the commands'
        /// dump, `.2` the idle one: read them with `callgrind_annotate`); by default they are
        /// removed.
        #[arg(long)]
        keep: Option<PathBuf>,
        /// Write the figures (JSON) here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Firmware update of a simulated island: the demo gateway with N static elements, a
    /// test-signed image uploaded over MQTT, `fw_update` to all and to one; LED commands and a
    /// docking during the update.
    Fw {
        /// The mc-gateway binary, built with its default features (demo).
        #[arg(long)]
        gateway: PathBuf,
        /// Static elements in the island.
        #[arg(long, default_value_t = 20)]
        nodes: u16,
        /// Write the figures (JSON) here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Copy standard input to standard output as it comes: the far end of the live run's process
    /// round trip (the harness starts it; there is no need to run it by hand).
    #[command(hide = true)]
    Echo,
    /// Drive the sans-IO bridge over a fixed workload (run under callgrind).
    Workload {
        /// Which path.
        #[arg(long, value_enum)]
        path: WorkPath,
        /// Iterations.
        #[arg(long)]
        n: u32,
    },
    /// The audit trail: write RECORDS records into a temporary directory, time their verification.
    AuditVerify {
        /// Records in the chain.
        #[arg(long, default_value_t = 1_000_000)]
        records: u64,
        /// Write the figures (JSON) here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Instruction counts of both workload paths under valgrind: (I(2n) - I(n)) / n.
    Callgrind {
        /// Iterations of the short run.
        #[arg(long, default_value_t = 2000)]
        n: u64,
        /// Write the figures (JSON) here.
        #[arg(long)]
        out: PathBuf,
    },
    /// Docking -> a guided procedure's step `done`, timed in the gateway's sans-IO core.
    Procedure {
        /// Dockings.
        #[arg(long, default_value_t = 2000)]
        samples: usize,
        /// Write the figures (JSON) here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Combine live.json, callgrind.json, firmware.json, islands.json, web.json, sila.json and fw.json of DIR (and the baseline's
    /// baseline-commit.txt, baseline-live.json, baseline-callgrind.json when present) into
    /// results.json, the plots and the table.
    Report {
        /// Folder with the parts (target/bench).
        #[arg(long)]
        dir: PathBuf,
        /// Where the live part ran.
        #[arg(long, default_value = "unknown machine")]
        machine: String,
    },
}

/// Writes a run's results to `out`, sends them to `report` (the host's xtask) when asked, and
/// prints their table (`table` places them in the report).
fn finish<T: serde::Serialize>(
    results: T,
    out: Option<PathBuf>,
    report: Option<String>,
    table: impl FnOnce(T) -> report::Results,
) -> Result<()> {
    if let Some(out) = out {
        std::fs::write(&out, serde_json::to_vec_pretty(&results)?)?;
    }
    if let Some(addr) = report {
        live::send(&results, &addr)?;
    }
    let r = report::Results {
        machine: "this machine".into(),
        ..table(results)
    };
    println!("{}", report::table(&r));
    Ok(())
}

/// A rate of messages per second: a positive number.
fn rate(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(r) if r.is_finite() && r > 0.0 => Ok(r),
        _ => Err(format!(
            "{s:?} is not a rate: give messages per second, above 0"
        )),
    }
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Cmd::Live {
            iface,
            forward_iface,
            gateway,
            mosquitto,
            probes,
            trial_secs,
            cost_rate,
            commands,
            mosquitto_nagle,
            trace,
            broker,
            remote_load,
            pin,
            report,
            out,
        } => {
            let r = live::run(live::Settings {
                iface,
                forward_iface,
                gateway,
                mosquitto,
                probes,
                trial_secs,
                cost_rates: cost_rate,
                commands,
                mosquitto_nagle,
                trace,
                broker,
                remote_load,
                pin,
            })?;
            finish(r, out, report, |r| report::Results {
                live: Some(r),
                ..Default::default()
            })?;
        }
        Cmd::Islands {
            gateway,
            sim_node,
            mosquitto,
            islands,
            nodes,
            rate,
            command_rate,
            secs,
            report,
            out,
        } => {
            let r = islands::run(islands::Settings {
                gateway,
                sim_node,
                mosquitto,
                islands,
                nodes,
                report_rate: rate,
                command_rate,
                secs,
            })?;
            finish(r, out, report, |r| report::Results {
                islands: Some(r),
                ..Default::default()
            })?;
        }
        Cmd::Web {
            gateway,
            broker,
            probes,
            gap_ms,
            out,
        } => {
            let w = web::run(
                &gateway,
                broker,
                probes,
                std::time::Duration::from_millis(gap_ms),
            )?;
            finish(w, out, None, |w| report::Results {
                web: Some(w),
                ..Default::default()
            })?;
        }
        #[cfg(feature = "sila")]
        Cmd::Sila {
            gateway,
            probes,
            gap_ms,
            out,
        } => {
            let r = sila::run(&gateway, probes, std::time::Duration::from_millis(gap_ms))?;
            finish(r, out, None, |r| report::Results {
                sila: Some(r),
                ..Default::default()
            })?;
        }
        Cmd::Process {
            gateway,
            mosquitto,
            n,
            keep,
            out,
        } => {
            let r = process::run(&gateway, &mosquitto, n, keep.as_deref())?;
            finish(r, out, None, |r| report::Results {
                process: Some(r),
                ..Default::default()
            })?;
        }
        #[cfg(not(feature = "sila"))]
        Cmd::Sila { .. } => {
            anyhow::bail!("this ihex-bench was built without its `sila` feature")
        }
        Cmd::Fw {
            gateway,
            nodes,
            out,
        } => {
            let f = fw::run(&gateway, nodes)?;
            finish(f, out, None, |f| report::Results {
                fw: Some(f),
                ..Default::default()
            })?;
        }
        Cmd::Echo => live::echo()?,
        Cmd::Loadgen { broker } => loadgen::serve(broker)?,
        Cmd::Forward { iface, broker } => forward::serve(&iface, broker)?,
        Cmd::Workload { path, n } => {
            let p = match path {
                WorkPath::Can => workload::Path::CanToEvent,
                WorkPath::Command => workload::Path::CommandToFrame,
                WorkPath::CommandLeased => workload::Path::CommandLeased,
                WorkPath::Answered => workload::Path::CommandAnswered,
                WorkPath::Audited => workload::Path::CommandAudited,
            };
            let out = workload::run(p, n);
            println!("{out:?}");
        }
        Cmd::Procedure { samples, out } => {
            let p = ihex_bench::procedure::run(samples);
            finish(p, out, None, |p| report::Results {
                procedure: Some(p),
                ..Default::default()
            })?;
        }
        Cmd::AuditVerify { records, out } => {
            let dir =
                std::env::temp_dir().join(format!("ihex-bench-verify-{}", std::process::id()));
            let result = ihex_bench::audit::run(&dir, records, 3);
            let _ = std::fs::remove_dir_all(&dir);
            let a = result?;
            finish(a, out, None, |a| report::Results {
                audit: Some(a),
                ..Default::default()
            })?;
        }
        Cmd::Callgrind { n, out } => {
            let c = callgrind::run(n)?;
            std::fs::write(&out, serde_json::to_vec_pretty(&c)?)?;
        }
        Cmd::Report { dir, machine } => {
            let read = |name: &str| -> Option<Vec<u8>> { std::fs::read(dir.join(name)).ok() };
            let mut r = report::Results {
                machine,
                ..Default::default()
            };
            match read("live.json") {
                Some(b) => r.live = Some(serde_json::from_slice(&b).context("live.json")?),
                None => r.missing.push("live benchmark (no live.json)".into()),
            }
            if let Some(b) = read("live-vm.json") {
                r.live_broker_in_vm = Some(serde_json::from_slice(&b).context("live-vm.json")?);
            }
            match read("callgrind.json") {
                Some(b) => {
                    r.callgrind = Some(serde_json::from_slice(&b).context("callgrind.json")?)
                }
                None => r
                    .missing
                    .push("instruction counts (no callgrind.json)".into()),
            }
            match read("firmware.json") {
                Some(b) => r.firmware = Some(serde_json::from_slice(&b).context("firmware.json")?),
                None => r.missing.push("firmware sizes (no firmware.json)".into()),
            }
            if let Some(commit) = read("baseline-commit.txt") {
                let commit = String::from_utf8_lossy(&commit).trim().to_owned();
                let live = match read("baseline-live.json") {
                    Some(b) => Some(serde_json::from_slice(&b).context("baseline-live.json")?),
                    None => None,
                };
                let callgrind = match read("baseline-callgrind.json") {
                    Some(b) => Some(serde_json::from_slice(&b).context("baseline-callgrind.json")?),
                    None => None,
                };
                r.baseline = Some(report::Baseline {
                    commit,
                    live,
                    callgrind,
                });
            }
            match read("audit.json") {
                Some(b) => r.audit = Some(serde_json::from_slice(&b).context("audit.json")?),
                None => r
                    .missing
                    .push("audit trail verification (no audit.json)".into()),
            }
            match read("fw.json") {
                Some(b) => r.fw = Some(serde_json::from_slice(&b).context("fw.json")?),
                None => r.missing.push("firmware update (no fw.json)".into()),
            }
            match read("islands.json") {
                Some(b) => r.islands = Some(serde_json::from_slice(&b).context("islands.json")?),
                None => r
                    .missing
                    .push("islands per broker (no islands.json)".into()),
            }
            match read("procedure.json") {
                Some(b) => {
                    r.procedure = Some(serde_json::from_slice(&b).context("procedure.json")?)
                }
                None => r
                    .missing
                    .push("docking -> procedure step (no procedure.json)".into()),
            }
            match read("web.json") {
                Some(b) => r.web = Some(serde_json::from_slice(&b).context("web.json")?),
                None => r.missing.push("island view latency (no web.json)".into()),
            }
            match read("sila.json") {
                Some(b) => r.sila = Some(serde_json::from_slice(&b).context("sila.json")?),
                None => r
                    .missing
                    .push("SiLA round trip and memory (no sila.json)".into()),
            }
            match read("process.json") {
                Some(b) => r.process = Some(serde_json::from_slice(&b).context("process.json")?),
                None => r
                    .missing
                    .push("instructions per command, whole process (no process.json)".into()),
            }
            if let Some(b) = read("missing.json") {
                let more: Vec<String> = serde_json::from_slice(&b).context("missing.json")?;
                r.missing.extend(more);
            }
            if let Some(l) = &r.live {
                std::fs::write(dir.join("latency.svg"), report::latency_svg(l))?;
                std::fs::write(dir.join("rate.svg"), report::rate_svg(l))?;
            }
            std::fs::write(dir.join("results.json"), serde_json::to_vec_pretty(&r)?)?;
            let t = report::table(&r);
            std::fs::write(dir.join("table.txt"), &t)?;
            println!("{t}");
        }
    }
    Ok(())
}
