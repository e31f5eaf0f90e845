//! `cargo xtask bench` (issue 8; not part of `cargo xtask test`): builds the gateway and the
//! benchmark for the static musl target, counts instructions per bridged frame under callgrind,
//! reads the release firmware's size, runs the live benchmark over real SocketCAN (native vcan, or
//! the microVM of [`crate::vcan::test_vm`]) with a real Mosquitto, then islands per broker (16
//! gateways with `sim-node` islands on one Mosquitto) in the same place, and has `ihex-bench report`
//! write `target/bench/results.json`, the SVG plots and the table. A baseline commit's gateway
//! (issue 15: "today's figures next to the new ones") is built from the cargo cache and measured in
//! the same run by the same harness. See docs/benchmarks.md.

use std::fs;
use std::io::Read;
use std::net::{Ipv4Addr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::mpsc;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use clap::{Args, ValueEnum};

use crate::cmd;
use crate::fwsize;
use crate::vcan::{self, Mode, VmSettings, MUSL};
use crate::vm::{NetDevice, Payload, Program};

/// Options of `cargo xtask bench`.
#[derive(Args, Clone, Debug)]
pub struct BenchArgs {
    /// Run the live part in the microVM even where native vcan exists (IHEX_VCAN=vm).
    #[arg(long)]
    vm: bool,
    /// Virtual CPUs of the microVM. With 2 the nodes' side (the benchmark's responder) and the
    /// kernel's work for it run beside the gateway, whose tasks share one thread; with 1 they take
    /// the gateway's CPU, which then bounds the rates before the bus does.
    #[arg(long, env = "IHEX_BENCH_SMP", default_value_t = 2)]
    smp: u32,
    /// Leave every process where the kernels put it. By default, with 2 or more vCPUs on a host
    /// with 2 or more cores, the live part pins vCPU 0's thread alone on the first host CPU this
    /// process may use (everything else it starts on the others) and, in the VM, the gateway and the plain forwarder
    /// alone on vCPU 0: their CPU figures then hold only their own work.
    #[arg(long)]
    no_pin: bool,
    /// Kill the VM after this many seconds (both gateways' live runs and islands per broker together).
    #[arg(long, default_value_t = 2400)]
    vm_timeout: u64,
    /// Latency probes per series.
    #[arg(long, default_value_t = 300)]
    probes: usize,
    /// Seconds of traffic per rate trial.
    #[arg(long, default_value_t = 2.0)]
    trial_secs: f64,
    /// Messages per second of the MQTT -> CAN cost rounds, one series of rounds per rate (repeat
    /// the option or separate rates by commas; the first is the headline), the same for this
    /// build and the baseline (default: 1,000/s, then each at 80 % of its own sustained command
    /// rate)
    #[arg(long, value_delimiter = ',')]
    cost_rate: Vec<f64>,
    /// Iterations of the short callgrind run (the long one is twice that).
    #[arg(long, default_value_t = 2000)]
    callgrind_n: u64,
    /// Build the firmware (crates/sc-fw, release) when no release ELF exists yet.
    #[arg(long)]
    build_firmware: bool,
    /// Skip the live part (callgrind, firmware and the report only).
    #[arg(long)]
    no_live: bool,
    /// Keep Mosquitto's default Nagle algorithm on its sockets (to compare; see docs/benchmarks.md).
    #[arg(long)]
    mosquitto_nagle: bool,
    /// Take the kernel's trace (ftrace) of five idle commands after each idle latency series,
    /// and count the system calls of one command trial at each cost rate (gateway, forwarder).
    /// Off by default: starting it has twice hung the microVM's kernel (a soft lockup in the
    /// benchmark's system call, TCG with two vCPUs), which loses the whole run.
    #[arg(long)]
    trace: bool,
    /// Skip the island view's latency (the demo gateway on the host).
    #[arg(long)]
    no_web: bool,
    /// Skip the SiLA server's round trip and memory (the demo gateway on the host).
    #[arg(long)]
    no_sila: bool,
    /// Skip the firmware update of a simulated island (the demo gateway on the host).
    #[arg(long)]
    no_fw: bool,
    /// Skip the instructions per command of the whole demo gateway process (callgrind on the
    /// host).
    #[arg(long)]
    no_process: bool,
    /// Skip islands per broker (16 gateways with sim-node islands on one Mosquitto, after the
    /// live part in the same VM boot).
    #[arg(long, conflicts_with = "only_islands")]
    no_islands: bool,
    /// Run islands per broker alone (no baseline, callgrind, firmware, live, web, sila, fw or
    /// process part).
    #[arg(long)]
    only_islands: bool,
    /// Islands per broker: gateway + sim-node pairs, on vcan0.. (at most 16).
    #[arg(long, default_value_t = 16)]
    island_count: usize,
    /// Islands per broker: seconds of measurement.
    #[arg(long, default_value_t = 30.0)]
    islands_secs: f64,
    /// Islands per broker: report frames per second per island.
    #[arg(long, default_value_t = 10.0)]
    islands_rate: f64,
    /// Measure the gateway of this commit beside this one, in the same run with the same harness
    /// (its tree exported with `git archive` and built under target/bench/ from its own
    /// Cargo.lock, fetching from the registry what the cargo cache lacks). The default
    /// is the state issue 15 measured.
    #[arg(long, env = "IHEX_BENCH_BASELINE", default_value = BASELINE)]
    baseline: String,
    /// Measure this gateway only.
    #[arg(long)]
    no_baseline: bool,
    /// Measure this already built static gateway binary as the baseline instead of building
    /// `--baseline` (the live part only; its file name labels it).
    #[arg(long, conflicts_with = "no_baseline")]
    baseline_gateway: Option<PathBuf>,
    /// Run the live part alone (no callgrind, procedure, audit, firmware, islands, web, sila, fw or
    /// process part).
    #[arg(long, conflicts_with_all = ["no_live", "only_islands"])]
    only_live: bool,
    /// Where the live part's Mosquitto runs when the live part runs in the microVM: on the host
    /// (reached from the VM at 10.0.2.2, so it does not share the gateway's vCPU; one fresh broker
    /// per gateway measured) or in the VM beside the gateway. `both` measures this gateway in both
    /// layouts (the second into `live-vm.json`). With native vcan the broker is always beside it.
    #[arg(long, value_enum, default_value_t = BrokerPlace::Host)]
    broker: BrokerPlace,
    /// With the broker on the host: publish the MQTT -> CAN trials' commands (and the bare ingress
    /// messages) from the benchmark in the VM, sharing the gateway's vCPU, instead of from a load
    /// generator beside the host's broker.
    #[arg(long)]
    load_in_vm: bool,
    /// The microVM's network card, which every MQTT packet to and from the host's broker crosses.
    #[arg(long, value_enum, default_value_t = NetDevice::Virtio)]
    vm_net: NetDevice,
}

/// Where the live part's broker runs (`--broker`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum BrokerPlace {
    /// On the host, reached from the microVM over its user-mode network.
    Host,
    /// In the microVM, sharing its vCPU with the gateway and the benchmark.
    Vm,
    /// This gateway in both layouts.
    Both,
}

/// The commit whose figures issue 15 quotes ("today's"): the gateway before its core split.
const BASELINE: &str = "baf77e8";

/// A built baseline: its gateway and its own benchmark binary (for its callgrind workload).
struct BaselineBuild {
    commit: String,
    gateway: PathBuf,
    bench: PathBuf,
}

/// Exports `commit`'s tree under target/bench/baseline-COMMIT/src (once) and builds its gateway
/// and benchmark as [`build`] does, with its own Cargo.lock (`--locked`) into a target directory of
/// its own. Not offline: resolving an older lock needs index entries a cache filled for this tree
/// lacks (even of crates its features leave out, such as `aws-lc-rs`).
fn build_baseline(commit: &str) -> Result<BaselineBuild> {
    let dir = cmd::target_dir()
        .join("bench")
        .join(format!("baseline-{commit}"));
    let src = dir.join("src");
    if !src.join("Cargo.toml").exists() {
        fs::create_dir_all(&src)?;
        let tar = dir.join("src.tar");
        cmd::run(
            Command::new("git")
                .current_dir(cmd::root())
                .args(["archive", "--format=tar", "-o"])
                .arg(&tar)
                .arg(commit),
        )?;
        cmd::run(Command::new("tar").arg("-xf").arg(&tar).arg("-C").arg(&src))?;
        fs::remove_file(&tar)?;
    }
    let target = dir.join("target");
    cmd::run(
        cmd::cargo()
            .current_dir(&src)
            .env("CARGO_TARGET_DIR", &target)
            .args(["build", "--locked"])
            .args(BUILD),
    )?;
    let bin = |name: &str| target.join(MUSL).join("release").join(name);
    Ok(BaselineBuild {
        commit: commit.to_owned(),
        gateway: bin("mc-gateway"),
        bench: bin("ihex-bench"),
    })
}

/// What `cargo build` builds for the benchmark, this tree's and the baseline's alike: the gateway
/// as deployed (no embedded broker) and the benchmark, optimised (timing a debug build means
/// nothing), static musl (they run in the microVM too).
const BUILD: [&str; 8] = [
    "--release",
    "--target",
    MUSL,
    "-p",
    "mc-gateway",
    "-p",
    "ihex-bench",
    "--no-default-features",
];

fn musl_release(name: &str) -> PathBuf {
    cmd::target_dir().join(MUSL).join("release").join(name)
}

/// This tree's build: [`BUILD`] and the simulator the islands-per-broker part runs (not needed
/// from the baseline).
fn build() -> Result<(PathBuf, PathBuf, PathBuf)> {
    cmd::run(
        cmd::cargo()
            .current_dir(cmd::root())
            .arg("build")
            .args(BUILD)
            .args(["-p", "sim-node"]),
    )?;
    Ok((
        musl_release("mc-gateway"),
        musl_release("ihex-bench"),
        musl_release("sim-node"),
    ))
}

fn firmware(dir: &Path, build: bool, out: &Path) -> Result<()> {
    let mut bins = fwsize::binaries(dir).unwrap_or_default();
    if bins.is_empty() && build {
        let fw = cmd::root().join("crates/sc-fw");
        cmd::run(
            cmd::cargo()
                .current_dir(&fw)
                .env_remove("CARGO_TARGET_DIR")
                .env_remove("CARGO_BUILD_TARGET")
                .args(["build", "--release"]),
        )?;
        bins = fwsize::binaries(dir)?;
    }
    if bins.is_empty() {
        bail!(
            "no release firmware ELF in {} (build it: cd crates/sc-fw && cargo build --release, \
             or pass --build-firmware)",
            dir.display()
        );
    }
    let list: Vec<serde_json::Value> = bins
        .iter()
        .map(|(p, s)| {
            let name = p.file_name().unwrap_or_default().to_string_lossy();
            let (flash_budget, ram_budget) = fwsize::budget(&name);
            serde_json::json!({
                "name": name,
                "flash": s.flash(),
                "ram": s.ram(),
                "flash_budget": flash_budget,
                "ram_budget": ram_budget,
            })
        })
        .collect();
    fs::write(out, serde_json::to_vec_pretty(&list)?)?;
    Ok(())
}

fn host_cpu() -> String {
    let info = fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let model = info
        .lines()
        .find_map(|l| l.strip_prefix("model name"))
        .map(|m| m.trim_start_matches([' ', '\t', ':']).to_string())
        .unwrap_or_else(|| "unknown CPU".into());
    let n = std::thread::available_parallelism().map_or(1, |n| n.get());
    // Other work on the host shows in TCG figures: record how busy it was.
    let load = fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let load = load.split_whitespace().next().unwrap_or("?");
    format!("{n}-core {model}, host load average {load} at the start")
}

/// One `ihex-bench` run of the SocketCAN part: what it is, its arguments (without `--mosquitto`,
/// `--out` and `--report`, added where it runs) and the file its results go to.
struct CanRun {
    name: &'static str,
    args: Vec<String>,
    out: PathBuf,
    /// In the microVM, give it a fresh Mosquitto on the host (`--broker 10.0.2.2:PORT`).
    host_broker: bool,
    /// In a pinned microVM (see `--no-pin`), pass `--pin`: a live run, whose CPU figures compare
    /// the gateway with the plain forwarder.
    pin: bool,
}

/// A Mosquitto on the host for one run in the microVM: on a free loopback port, which the VM's
/// user-mode network reaches at 10.0.2.2; the live part's configuration (unlimited queues,
/// `set_tcp_nodelay` unless `nagle`). With it, when asked, the run's MQTT load generator
/// (`ihex-bench loadgen`). Both stopped when dropped.
struct HostBroker {
    child: std::process::Child,
    port: u16,
    /// Its configuration file, removed with it.
    conf: PathBuf,
    loadgen: Option<std::process::Child>,
}

impl HostBroker {
    fn start(bin: &Path, dir: &Path, nagle: bool) -> Result<HostBroker> {
        let port = TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?
            .local_addr()?
            .port();
        let conf = dir.join(format!("mosquitto-host-{port}.conf"));
        fs::write(
            &conf,
            format!(
                "listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nuser root\n\
                 max_queued_messages 0\nmax_inflight_messages 0\nset_tcp_nodelay {}\n\
                 log_dest stderr\nlog_type error\n",
                !nagle
            ),
        )?;
        let child = Command::new(bin)
            .arg("-c")
            .arg(&conf)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .spawn()
            .with_context(|| format!("starting {}", bin.display()))?;
        let broker = HostBroker {
            child,
            port,
            conf,
            loadgen: None,
        };
        for _ in 0..100 {
            if std::net::TcpStream::connect((Ipv4Addr::LOCALHOST, port)).is_ok() {
                return Ok(broker);
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        bail!("the host's mosquitto did not listen on port {port} within 5 s")
    }

    /// Starts `bench loadgen` at this broker (the run finds it with `live --remote-load`).
    fn start_loadgen(&mut self, bench: &Path) -> Result<()> {
        let child = Command::new(bench)
            .args(["loadgen", "--broker", &format!("127.0.0.1:{}", self.port)])
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .spawn()
            .with_context(|| format!("starting {} loadgen", bench.display()))?;
        self.loadgen = Some(child);
        Ok(())
    }
}

impl Drop for HostBroker {
    fn drop(&mut self) {
        for child in self.loadgen.iter_mut().chain([&mut self.child]) {
            let _ = child.kill();
            let _ = child.wait();
        }
        let _ = fs::remove_file(&self.conf);
    }
}

fn islands_args(gateway: &Path, sim_node: &Path, args: &BenchArgs) -> Vec<String> {
    vec![
        "islands".into(),
        "--gateway".into(),
        gateway.to_string_lossy().into_owned(),
        "--sim-node".into(),
        sim_node.to_string_lossy().into_owned(),
        "--islands".into(),
        args.island_count.to_string(),
        "--secs".into(),
        args.islands_secs.to_string(),
        "--rate".into(),
        args.islands_rate.to_string(),
    ]
}

fn live_args(gateway: &Path, args: &BenchArgs) -> Vec<String> {
    let mut v = vec![
        "live".into(),
        "--iface".into(),
        "vcan0".into(),
        "--forward-iface".into(),
        "vcan1".into(),
        "--gateway".into(),
        gateway.to_string_lossy().into_owned(),
        "--probes".into(),
        args.probes.to_string(),
        "--trial-secs".into(),
        args.trial_secs.to_string(),
    ];
    if args.mosquitto_nagle {
        v.push("--mosquitto-nagle".into());
    }
    for r in &args.cost_rate {
        v.extend(["--cost-rate".into(), r.to_string()]);
    }
    if args.trace {
        v.push("--trace".into());
    }
    v
}

/// Accepts one connection on `listener` in the background and hands over what it sent.
fn receive(listener: TcpListener) -> mpsc::Receiver<std::io::Result<Vec<u8>>> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        if let Ok((mut s, _)) = listener.accept() {
            let mut buf = Vec::new();
            let _ = tx.send(s.read_to_end(&mut buf).map(|_| buf));
        }
    });
    rx
}

/// Runs the SocketCAN part's `runs` one after the other (natively, or all in one microVM boot,
/// `files` copied in at their host paths) and writes each one's results to its `out`; returns the
/// machine description. A run that fails does not stop the others: the error names every one
/// that failed.
fn live(runs: &[CanRun], files: &[PathBuf], bench: &Path, args: &BenchArgs) -> Result<String> {
    let mosquitto = cmd::find("mosquitto")
        .ok_or_else(|| anyhow!("mosquitto not installed (Debian: apt-get install mosquitto)"))?;
    let mode = Mode::from_env(args.vm)?;
    let native = match mode {
        Mode::Vm => None,
        _ => vcan::native_interfaces(true),
    };
    let mut failed = Vec::new();
    if native.is_some() {
        let machine = format!("native vcan on the host ({})", host_cpu());
        for run in runs {
            let mut c = Command::new(bench);
            c.args(&run.args)
                .arg("--mosquitto")
                .arg(&mosquitto)
                .arg("--out")
                .arg(&run.out);
            if let Err(e) = cmd::run(&mut c) {
                failed.push(format!("{}: {e:#}", run.name));
            }
        }
        if !failed.is_empty() {
            bail!("{}", failed.join("; "));
        }
        return Ok(machine);
    }
    if mode == Mode::Native {
        bail!("IHEX_VCAN=native but this kernel cannot create vcan interfaces");
    }
    let settings = VmSettings {
        timeout: Duration::from_secs(args.vm_timeout),
        smp: args.smp.max(1),
        memory_mb: 1024,
    };
    let mut vm = vcan::test_vm(settings)?;
    vm.net_device = Some(args.vm_net);
    // The CPUs this process may use (a container or `taskset` may have narrowed them).
    let allowed = if !args.no_pin && settings.smp >= 2 {
        allowed_cpus()?
    } else {
        Vec::new()
    };
    let machine = format!(
        "QEMU TCG microVM, {} vCPU, {:?} network card, Debian kernel, on a {}",
        settings.smp,
        args.vm_net,
        host_cpu()
    );
    let pinned = allowed.len() >= 2;
    // Everything this process starts from here (the host's brokers and load generators, QEMU)
    // inherits the other CPUs; QEMU's vCPU 0 thread then moves to the first one alone.
    let off_first = if pinned {
        vm.pin_vcpu0 = Some(allowed[0]);
        Some(HostAffinity::leave_first(&allowed)?)
    } else {
        None
    };
    // Each run sends its results back over the user-mode network (10.0.2.2 is our loopback).
    let mut programs = Vec::new();
    let mut results = Vec::new();
    // Stopped when the VM is done (dropped at the end of this function).
    let mut brokers = Vec::new();
    let conf_dir = cmd::target_dir().join("bench");
    for run in runs {
        let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?;
        let port = listener.local_addr()?.port();
        results.push((run.name, receive(listener), &run.out));
        let mut program_args = run.args.clone();
        if pinned && run.pin {
            program_args.push("--pin".into());
        }
        program_args.extend([
            "--mosquitto".into(),
            mosquitto.to_string_lossy().into_owned(),
            "--report".into(),
            format!("10.0.2.2:{port}"),
        ]);
        if run.host_broker {
            // A fresh broker per run: the retained state documents of one gateway's run would
            // be read back by the next gateway.
            let mut b = HostBroker::start(&mosquitto, &conf_dir, args.mosquitto_nagle)?;
            program_args.extend(["--broker".into(), format!("10.0.2.2:{}", b.port)]);
            if !args.load_in_vm {
                b.start_loadgen(bench)?;
                program_args.push("--remote-load".into());
            }
            brokers.push(b);
        }
        programs.push(Program {
            name: run.name.into(),
            path: bench.to_path_buf(),
            args: program_args,
        });
    }
    let payload = Payload {
        programs,
        env: vec![("RUST_BACKTRACE".into(), "1".into())],
        cwd: None,
        // The gateways (and the simulator) go in at their host paths; the program itself is
        // copied by the VM runner.
        files: files.to_vec(),
    };
    let outcomes = vm.run(&payload)?;
    drop(brokers);
    drop(off_first);
    for ((name, rx, out), o) in results.into_iter().zip(&outcomes) {
        if o.code != 0 {
            failed.push(format!("{name} failed in the VM (exit {})", o.code));
            continue;
        }
        match rx.recv_timeout(Duration::from_secs(10)) {
            Ok(Ok(bytes)) => fs::write(out, bytes)?,
            Ok(Err(e)) => failed.push(format!("{name}: reading its results from the VM: {e}")),
            Err(_) => failed.push(format!("{name}: the VM finished without sending results")),
        }
    }
    if !failed.is_empty() {
        bail!("{}", failed.join("; "));
    }
    Ok(if pinned {
        format!(
            "{machine}; vCPU 0 alone on host CPU {}, the other vCPU and the host's broker and load \
             generator on the other cores",
            allowed[0]
        )
    } else {
        machine
    })
}

/// This process's threads (and so what it starts while this lives) kept off the first of its
/// CPUs, which the microVM's vCPU 0 gets to itself; its CPUs as before when dropped. Uses
/// util-linux's `taskset`.
struct HostAffinity {
    before: String,
}

impl HostAffinity {
    fn leave_first(allowed: &[usize]) -> Result<HostAffinity> {
        let list = |cpus: &[usize]| {
            cpus.iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(",")
        };
        set_affinity(&list(&allowed[1..]))?;
        Ok(HostAffinity {
            before: list(allowed),
        })
    }
}

impl Drop for HostAffinity {
    fn drop(&mut self) {
        if let Err(e) = set_affinity(&self.before) {
            eprintln!("xtask bench: giving this process its CPUs again: {e:#}");
        }
    }
}

/// The CPUs this process may run on (`Cpus_allowed_list` of `/proc/self/status`), ascending.
fn allowed_cpus() -> Result<Vec<usize>> {
    let status = fs::read_to_string("/proc/self/status").context("reading /proc/self/status")?;
    let list = status
        .lines()
        .find_map(|l| l.strip_prefix("Cpus_allowed_list:"))
        .ok_or_else(|| anyhow!("/proc/self/status has no Cpus_allowed_list"))?;
    cpu_list(list.trim())
}

/// A kernel CPU list (`0-3,8,10-11`), expanded.
fn cpu_list(list: &str) -> Result<Vec<usize>> {
    let mut cpus = Vec::new();
    for part in list.split(',').filter(|p| !p.is_empty()) {
        let (first, last) = part.split_once('-').unwrap_or((part, part));
        let (first, last): (usize, usize) = (first.parse()?, last.parse()?);
        cpus.extend(first..=last);
    }
    if cpus.is_empty() {
        bail!("empty CPU list {list:?}");
    }
    Ok(cpus)
}

fn set_affinity(cpus: &str) -> Result<()> {
    cmd::run(
        Command::new("taskset")
            .args(["-a", "-p", "-c", cpus, &std::process::id().to_string()])
            .stdout(std::process::Stdio::null()),
    )
    .with_context(|| format!("taskset -c {cpus} (util-linux; `--no-pin` runs without)"))
}

/// The gateway as the README's first command runs it (default features: embedded broker,
/// simulated island, web view), optimised, for the parts that run on this machine: the island
/// view's event stream and a firmware update of the simulated island have nothing to do with CAN,
/// so no VM is needed.
///
/// With it, the host's `ihex-bench` with its default features (the SiLA client), which the musl
/// build for the VM leaves out; built in the same run, so the gateway's features do not change.
fn demo_gateway() -> Result<(PathBuf, PathBuf)> {
    cmd::run(cmd::cargo().current_dir(cmd::root()).args([
        "build",
        "--release",
        "-p",
        "mc-gateway",
        "-p",
        "ihex-bench",
    ]))?;
    let release = cmd::target_dir().join("release");
    Ok((release.join("mc-gateway"), release.join("ihex-bench")))
}

/// `ihex-bench VERB --gateway GATEWAY --out OUT` (the island view: `web`; the firmware update: `fw`).
fn on_demo(bench: &Path, verb: &str, gateway: &Path, out: &Path) -> Result<()> {
    cmd::run(
        Command::new(bench)
            .args([verb, "--gateway"])
            .arg(gateway)
            .arg("--out")
            .arg(out),
    )
}

/// `cargo xtask bench`.
pub fn run(args: BenchArgs, firmware_dir: &Path) -> Result<()> {
    let dir = cmd::target_dir().join("bench");
    fs::create_dir_all(&dir)?;
    for f in [
        "live.json",
        "live-vm.json",
        "callgrind.json",
        "firmware.json",
        "missing.json",
        "baseline-commit.txt",
        "baseline-live.json",
        "baseline-callgrind.json",
        "islands.json",
        "web.json",
        "sila.json",
        "fw.json",
        "procedure.json",
        "audit.json",
        "process.json",
    ] {
        let _ = fs::remove_file(dir.join(f));
    }
    let (gateway, bench, sim_node) = build()?;
    let mut missing = Vec::new();
    let only = args.only_islands;
    let baseline = if let Some(path) = &args.baseline_gateway {
        let label = path
            .file_name()
            .map_or_else(|| "prebuilt".into(), |n| n.to_string_lossy().into_owned());
        fs::write(dir.join("baseline-commit.txt"), &label)?;
        // Copied in at its host path like this build's gateway; no benchmark of its own.
        Some(BaselineBuild {
            commit: label,
            gateway: fs::canonicalize(path)
                .with_context(|| format!("--baseline-gateway {}", path.display()))?,
            bench: PathBuf::new(),
        })
    } else if args.no_baseline || only || args.only_live {
        None
    } else {
        println!("\n==> xtask bench: build the baseline {}", args.baseline);
        match build_baseline(&args.baseline) {
            Ok(b) => {
                fs::write(dir.join("baseline-commit.txt"), &b.commit)?;
                Some(b)
            }
            Err(e) => {
                missing.push(format!("baseline {}: {e:#}", args.baseline));
                None
            }
        }
    };

    if only {
        missing.push("instruction counts, firmware sizes, live: --only-islands".into());
    } else if args.only_live {
        missing.push("instruction counts, procedure, audit, firmware sizes: --only-live".into());
    } else {
        measure_host(
            &args,
            &bench,
            baseline.as_ref(),
            firmware_dir,
            &dir,
            &mut missing,
        )?;
    }

    let mut runs = Vec::new();
    if args.no_live {
        missing.push("live benchmark: --no-live".into());
    } else if !only {
        let on_host = args.broker != BrokerPlace::Vm;
        runs.push(CanRun {
            name: "ihex-bench live",
            args: live_args(&gateway, &args),
            out: dir.join("live.json"),
            host_broker: on_host,
            pin: true,
        });
        if let Some(b) = &baseline {
            runs.push(CanRun {
                name: "ihex-bench live (baseline)",
                args: live_args(&b.gateway, &args),
                out: dir.join("baseline-live.json"),
                host_broker: on_host,
                pin: true,
            });
        }
        if args.broker == BrokerPlace::Both {
            runs.push(CanRun {
                name: "ihex-bench live (broker in the VM)",
                args: live_args(&gateway, &args),
                out: dir.join("live-vm.json"),
                host_broker: false,
                pin: true,
            });
        }
    }
    if args.no_islands || args.only_live {
        missing.push("islands per broker: --no-islands or --only-live".into());
    } else if args.island_count > vcan::COUNT {
        missing.push(format!(
            "islands per broker: --island-count {} (the VM has vcan0..{})",
            args.island_count,
            vcan::COUNT - 1
        ));
    } else {
        runs.push(CanRun {
            name: "ihex-bench islands",
            args: islands_args(&gateway, &sim_node, &args),
            out: dir.join("islands.json"),
            host_broker: false,
            pin: false,
        });
    }
    let mut machine = "SocketCAN part not run".to_string();
    if !runs.is_empty() {
        println!(
            "\n==> xtask bench: SocketCAN + Mosquitto + mc-gateway (live, islands per broker)"
        );
        let files: Vec<PathBuf> = std::iter::once(gateway.clone())
            .chain(baseline.as_ref().map(|b| b.gateway.clone()))
            .chain(std::iter::once(sim_node.clone()))
            .collect();
        match live(&runs, &files, &bench, &args) {
            Ok(m) => machine = m,
            Err(e) => missing.push(format!("SocketCAN part: {e:#}")),
        }
    }
    if only || args.only_live {
        missing.push(
            "island view latency, SiLA server, firmware update and whole-process instructions: \
             --only-islands or --only-live"
                .into(),
        );
    } else {
        on_host_demo(&args, &bench, &dir, &mut missing);
    }
    fs::write(dir.join("missing.json"), serde_json::to_vec(&missing)?)?;

    println!("\n==> xtask bench: report");
    cmd::run(
        Command::new(&bench)
            .args(["report", "--dir"])
            .arg(&dir)
            .args(["--machine", &machine]),
    )?;
    println!(
        "xtask bench: wrote {} (+ latency.svg, rate.svg, table.txt)",
        dir.join("results.json").display()
    );
    Ok(())
}

/// The parts measured on the host before the SocketCAN part: instructions per bridged frame
/// (this build's and the baseline's) and the firmware's size.
fn measure_host(
    args: &BenchArgs,
    bench: &Path,
    baseline: Option<&BaselineBuild>,
    firmware_dir: &Path,
    dir: &Path,
    missing: &mut Vec<String>,
) -> Result<()> {
    println!("\n==> xtask bench: instructions per bridged frame (callgrind)");
    if cmd::exists("valgrind") {
        let mut c = Command::new(bench);
        c.args(["callgrind", "--n", &args.callgrind_n.to_string(), "--out"])
            .arg(dir.join("callgrind.json"));
        if let Err(e) = cmd::run(&mut c) {
            missing.push(format!("callgrind: {e:#}"));
        }
        if let Some(b) = baseline.filter(|b| !b.bench.as_os_str().is_empty()) {
            // Its own workload: the same definition of a bridged frame, on its own bridge API.
            let mut c = Command::new(&b.bench);
            c.args(["callgrind", "--n", &args.callgrind_n.to_string(), "--out"])
                .arg(dir.join("baseline-callgrind.json"));
            if let Err(e) = cmd::run(&mut c) {
                missing.push(format!("baseline callgrind: {e:#}"));
            }
        }
    } else {
        missing.push("callgrind: valgrind not installed (apt-get install valgrind)".into());
    }

    println!("\n==> xtask bench: docking -> procedure step done (the core)");
    let mut c = Command::new(bench);
    c.args(["procedure", "--out"])
        .arg(dir.join("procedure.json"));
    if let Err(e) = cmd::run(&mut c) {
        missing.push(format!("procedure: {e:#}"));
    }

    println!("\n==> xtask bench: audit trail, one million records verified");
    let mut c = Command::new(bench);
    c.args(["audit-verify", "--records", "1000000", "--out"])
        .arg(dir.join("audit.json"));
    if let Err(e) = cmd::run(&mut c) {
        missing.push(format!("audit verification: {e:#}"));
    }

    println!("\n==> xtask bench: firmware size");
    if let Err(e) = firmware(
        firmware_dir,
        args.build_firmware,
        &dir.join("firmware.json"),
    ) {
        missing.push(format!("firmware: {e:#}"));
    }
    Ok(())
}

/// The parts that run the demo gateway on the host: the island view, the SiLA server, the
/// firmware update and the whole process's instructions per command.
fn on_host_demo(args: &BenchArgs, bench: &Path, dir: &Path, missing: &mut Vec<String>) {
    let parts = [
        (
            args.no_web,
            "web",
            "island view latency",
            "web.json",
            "--no-web",
        ),
        (
            args.no_sila,
            "sila",
            "SiLA round trip and memory",
            "sila.json",
            "--no-sila",
        ),
        (args.no_fw, "fw", "firmware update", "fw.json", "--no-fw"),
        (
            args.no_process,
            "process",
            "instructions per command, whole process",
            "process.json",
            "--no-process",
        ),
    ];
    if parts.iter().any(|(skip, ..)| !skip) {
        match demo_gateway() {
            Ok((gateway, host_bench)) => {
                for (skip, verb, what, file, flag) in parts {
                    if skip {
                        missing.push(format!("{what}: {flag}"));
                        continue;
                    }
                    println!("\n==> xtask bench: {what} (the demo gateway on this machine)");
                    let bench = if verb == "sila" { &host_bench } else { bench };
                    if let Err(e) = on_demo(bench, verb, &gateway, &dir.join(file)) {
                        missing.push(format!("{what}: {e:#}"));
                    }
                }
            }
            Err(e) => missing.push(format!(
                "island view, SiLA server, firmware update and whole-process instructions: {e:#}"
            )),
        }
    } else {
        missing.push(
            "island view latency, SiLA server, firmware update and whole-process instructions: \
             --no-web --no-sila --no-fw --no-process"
                .into(),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_lists_expand_as_the_kernel_writes_them() {
        assert_eq!(cpu_list("0-1").unwrap(), vec![0, 1]);
        assert_eq!(cpu_list("0-2,5,8-9").unwrap(), vec![0, 1, 2, 5, 8, 9]);
        assert_eq!(cpu_list("3").unwrap(), vec![3]);
        assert!(cpu_list("").is_err());
        assert!(cpu_list("x-1").is_err());
    }

    #[test]
    fn this_process_may_run_somewhere() {
        assert!(!allowed_cpus().unwrap().is_empty());
    }
}
