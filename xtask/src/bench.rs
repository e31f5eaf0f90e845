//! `cargo xtask bench` (issue 8; not part of `cargo xtask test`): builds the gateway and the
//! benchmark for the static musl target, counts instructions per bridged frame under callgrind,
//! reads the release firmware's size, runs the live benchmark over real SocketCAN (native vcan, or
//! the microVM of [`crate::vcan::test_vm`]) with a real Mosquitto, and has `ihex-bench report`
//! write `target/bench/results.json`, the SVG plots and the table. See docs/benchmarks.md.

use std::fs;
use std::io::Read;
use std::net::{Ipv4Addr, TcpListener};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::mpsc;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use clap::Args;

use crate::cmd;
use crate::fwsize;
use crate::vcan::{self, Mode, VmSettings, MUSL};
use crate::vm::{Payload, Program};

/// Options of `cargo xtask bench`.
#[derive(Args, Clone, Debug)]
pub struct BenchArgs {
    /// Run the live part in the microVM even where native vcan exists (IHEX_VCAN=vm).
    #[arg(long)]
    vm: bool,
    /// Virtual CPUs of the microVM (1 keeps latency figures meaningful under TCG).
    #[arg(long, env = "IHEX_BENCH_SMP", default_value_t = 1)]
    smp: u32,
    /// Kill the VM after this many seconds.
    #[arg(long, default_value_t = 900)]
    vm_timeout: u64,
    /// Latency probes per series.
    #[arg(long, default_value_t = 300)]
    probes: usize,
    /// Seconds of traffic per rate trial.
    #[arg(long, default_value_t = 2.0)]
    trial_secs: f64,
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
    /// Skip the island view's latency (the demo gateway on the host).
    #[arg(long)]
    no_web: bool,
}

fn musl_release(name: &str) -> PathBuf {
    cmd::target_dir().join(MUSL).join("release").join(name)
}

fn build() -> Result<(PathBuf, PathBuf)> {
    // The gateway as deployed (no embedded broker), optimised: timing a debug build means nothing.
    cmd::run(cmd::cargo().current_dir(cmd::root()).args([
        "build",
        "--release",
        "--target",
        MUSL,
        "-p",
        "mc-gateway",
        "-p",
        "ihex-bench",
        "--no-default-features",
    ]))?;
    Ok((musl_release("mc-gateway"), musl_release("ihex-bench")))
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

fn live_args(gateway: &Path, args: &BenchArgs) -> Vec<String> {
    let mut v = vec![
        "live".into(),
        "--iface".into(),
        "vcan0".into(),
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
    v
}

/// Runs the live part; returns the machine description.
fn live(gateway: &Path, bench: &Path, args: &BenchArgs, out: &Path) -> Result<String> {
    let mosquitto = cmd::find("mosquitto")
        .ok_or_else(|| anyhow!("mosquitto not installed (Debian: apt-get install mosquitto)"))?;
    let mode = Mode::from_env(args.vm)?;
    let native = match mode {
        Mode::Vm => None,
        _ => vcan::native_interfaces(true),
    };
    if native.is_some() {
        let mut c = Command::new(bench);
        c.args(live_args(gateway, args))
            .arg("--mosquitto")
            .arg(&mosquitto)
            .arg("--out")
            .arg(out);
        cmd::run(&mut c)?;
        return Ok(format!("native vcan on the host ({})", host_cpu()));
    }
    if mode == Mode::Native {
        bail!("IHEX_VCAN=native but this kernel cannot create vcan interfaces");
    }
    let settings = VmSettings {
        timeout: Duration::from_secs(args.vm_timeout),
        smp: args.smp.max(1),
        memory_mb: 1024,
    };
    let vm = vcan::test_vm(settings)?;
    // The guest sends its results back over the user-mode network (10.0.2.2 is our loopback).
    let listener = TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?;
    let port = listener.local_addr()?.port();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        if let Ok((mut s, _)) = listener.accept() {
            let mut buf = Vec::new();
            let _ = tx.send(s.read_to_end(&mut buf).map(|_| buf));
        }
    });
    let mut program_args = live_args(gateway, args);
    program_args.extend([
        "--mosquitto".into(),
        mosquitto.to_string_lossy().into_owned(),
        "--report".into(),
        format!("10.0.2.2:{port}"),
    ]);
    let payload = Payload {
        programs: vec![Program {
            name: "ihex-bench live".into(),
            path: bench.to_path_buf(),
            args: program_args,
        }],
        env: vec![("RUST_BACKTRACE".into(), "1".into())],
        cwd: None,
        // The gateway goes in at its host path; the program itself is copied by the VM runner.
        files: vec![gateway.to_path_buf()],
    };
    let outcomes = vm.run(&payload)?;
    if let Some(o) = outcomes.iter().find(|o| o.code != 0) {
        bail!("ihex-bench live failed in the VM (exit {})", o.code);
    }
    let bytes = rx
        .recv_timeout(Duration::from_secs(10))
        .map_err(|_| anyhow!("the VM finished without sending results"))?
        .context("reading the results from the VM")?;
    fs::write(out, bytes)?;
    Ok(format!(
        "QEMU TCG microVM, {} vCPU, Debian kernel, on a {}",
        settings.smp,
        host_cpu()
    ))
}

/// The island view's latency: the gateway as the README's first command runs it (default
/// features: embedded broker, simulated island, web view), optimised, on this machine — the page's
/// event stream has nothing to do with CAN, so no VM is needed.
fn web(bench: &Path, out: &Path) -> Result<()> {
    cmd::run(cmd::cargo().current_dir(cmd::root()).args([
        "build",
        "--release",
        "-p",
        "mc-gateway",
    ]))?;
    let gateway = cmd::target_dir().join("release").join("mc-gateway");
    cmd::run(
        Command::new(bench)
            .args(["web", "--gateway"])
            .arg(&gateway)
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
        "callgrind.json",
        "firmware.json",
        "missing.json",
        "web.json",
    ] {
        let _ = fs::remove_file(dir.join(f));
    }
    let (gateway, bench) = build()?;
    let mut missing = Vec::new();

    println!("\n==> xtask bench: instructions per bridged frame (callgrind)");
    if cmd::exists("valgrind") {
        let mut c = Command::new(&bench);
        c.args(["callgrind", "--n", &args.callgrind_n.to_string(), "--out"])
            .arg(dir.join("callgrind.json"));
        if let Err(e) = cmd::run(&mut c) {
            missing.push(format!("callgrind: {e:#}"));
        }
    } else {
        missing.push("callgrind: valgrind not installed (apt-get install valgrind)".into());
    }

    println!("\n==> xtask bench: firmware size");
    if let Err(e) = firmware(
        firmware_dir,
        args.build_firmware,
        &dir.join("firmware.json"),
    ) {
        missing.push(format!("firmware: {e:#}"));
    }

    let mut machine = "live part not run".to_string();
    if args.no_live {
        missing.push("live benchmark: --no-live".into());
    } else {
        println!("\n==> xtask bench: live (SocketCAN + Mosquitto + mc-gateway)");
        match live(&gateway, &bench, &args, &dir.join("live.json")) {
            Ok(m) => machine = m,
            Err(e) => missing.push(format!("live benchmark: {e:#}")),
        }
    }
    if args.no_web {
        missing.push("island view latency: --no-web".into());
    } else {
        println!("\n==> xtask bench: island view latency (the demo gateway on this machine)");
        if let Err(e) = web(&bench, &dir.join("web.json")) {
            missing.push(format!("island view latency: {e:#}"));
        }
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
