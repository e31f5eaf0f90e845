//! `cargo xtask`: the project's automation. `cargo xtask test` is THE test command: it runs every
//! stage, streams their output, collects all failures and ends with `xtask: N passed, M failed`.
#![forbid(unsafe_code)]

mod bench;
mod browser;
mod cantools;
mod cmd;
mod cpio;
mod dbc;
mod fuzz;
mod fwsize;
mod ignored_test;
mod lint;
mod prometheus;
mod setup;
mod sila;
#[cfg(test)]
mod tidy;
mod vcan;
mod vm;

use std::path::PathBuf;
use std::process::{Command, ExitCode};
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand, ValueEnum};

#[derive(Parser)]
#[command(name = "cargo xtask", about = "iHEX project automation")]
struct Cli {
    #[command(subcommand)]
    command: Task,
}

#[derive(Subcommand)]
enum Task {
    /// Run every test stage in order, or those picked with --stage / --skip (docs/testing.md).
    Test(TestArgs),
    /// Formatting, clippy and rustdoc warnings of the host and firmware workspaces, and the MSRV
    /// (the `lint` stage alone).
    Lint,
    /// Install the rust targets, toolchains and system packages the tests need (apt on
    /// Debian/Ubuntu).
    Setup,
    /// Print flash/RAM use of the release firmware (bootloader, application) against the budgets:
    /// 96 KiB flash per application, 24 KiB for the bootloader, 16 KiB static RAM each.
    FwSize {
        /// Folder with the firmware ELFs.
        #[arg(long)]
        dir: Option<PathBuf>,
    },
    /// Run a static x86_64 (musl) program in the SocketCAN microVM; usable as the musl target's
    /// cargo runner: CARGO_TARGET_X86_64_UNKNOWN_LINUX_MUSL_RUNNER="cargo xtask vm-run".
    VmRun {
        #[command(flatten)]
        vm: VmArgs,
        /// The program (a test binary built for x86_64-unknown-linux-musl).
        binary: PathBuf,
        /// Its arguments.
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Write docs/ihex.dbc (the CAN protocol for cantools, SavvyCAN, ...) from ihex-proto's schema.
    Dbc {
        /// Only check that docs/ihex.dbc is what the generator writes (the host stage does).
        #[arg(long, conflicts_with = "island")]
        check: bool,
        /// Print instead a DBC with exact IDs for these sub-controllers (hex IDs: 111,112,2), for
        /// tools that cannot mask IDs (SavvyCAN).
        #[arg(long, value_delimiter = ',', num_args = 1..)]
        island: Vec<ihex_proto::NodeId>,
    },
    /// Benchmarks (not a test): gateway rates, latency, CPU, RSS, instructions per frame, firmware
    /// size; writes target/bench/results.json (docs/benchmarks.md).
    Bench(bench::BenchArgs),
    /// The fault suite as a soak: random faults for M minutes against the real gateway (in the
    /// microVM where vcan is missing), then the contract checker's verdict (docs/testing.md).
    Soak(SoakArgs),
    /// Build every cargo-fuzz target (nightly) and run each for a bounded time, its seeds first
    /// (docs/testing.md, "Fuzzing").
    Fuzz {
        /// How long each target runs (0: only its seeds, once each).
        #[arg(long, default_value_t = 60)]
        seconds: u64,
    },
    /// Boot the SocketCAN microVM to an interactive shell (vcan0..15 up).
    VmShell {
        #[command(flatten)]
        vm: VmArgs,
    },
}

#[derive(Args, Clone, Copy)]
struct VmArgs {
    /// Kill a VM still running after this many seconds.
    #[arg(long, env = "IHEX_VM_TIMEOUT", default_value_t = 900)]
    vm_timeout: u64,
    /// Virtual CPUs (1 for latency measurements).
    #[arg(long, env = "IHEX_VM_SMP", default_value_t = 2)]
    smp: u32,
    /// Guest memory floor in MiB (raised automatically for big initrds).
    #[arg(long, env = "IHEX_VM_MEMORY", default_value_t = 1024)]
    memory: u64,
}

impl VmArgs {
    fn settings(self) -> vcan::VmSettings {
        vcan::VmSettings {
            timeout: Duration::from_secs(self.vm_timeout),
            smp: self.smp.max(1),
            memory_mb: self.memory,
        }
    }
}

#[derive(Args)]
struct SoakArgs {
    /// Repeat the plan of this seed (printed by every run; default: a fresh one).
    #[arg(long, env = "IHEX_FAULT_SEED")]
    seed: Option<u64>,
    /// How long to inject random faults (0: every kind of fault once, the bounded run).
    #[arg(long, default_value_t = 10)]
    minutes: u64,
    /// Instead of the fault suite: the firmware power-cut suite on the host
    /// (`crates/sim-node/tests/power_cut.rs`) with this many seeded cuts (the test command runs
    /// 100 of one fixed seed); --seed repeats a plan.
    #[arg(long, value_name = "N")]
    fw_power_cuts: Option<u64>,
    /// Run in the microVM even where native vcan exists (IHEX_VCAN=vm).
    #[arg(long)]
    vm: bool,
    #[command(flatten)]
    vm_args: VmArgs,
}

#[derive(Args)]
struct TestArgs {
    /// Run only these stages (`--stage host vcan`, `--stage host,vcan` or repeated).
    #[arg(long = "stage", value_enum, num_args = 1.., value_delimiter = ',')]
    stages: Vec<Stage>,
    /// Skip these stages (same forms as --stage).
    #[arg(long, value_enum, num_args = 1.., value_delimiter = ',')]
    skip: Vec<Stage>,
    /// Run the SocketCAN tests in the microVM even where native vcan exists (IHEX_VCAN=vm).
    #[arg(long)]
    vm: bool,
    /// In the vcan stage, run only this integration test (`--vcan-test gateway_fw_update`: one
    /// file of tests/tests/, to chase a failure without the whole stage).
    #[arg(long, value_name = "TEST")]
    vcan_test: Option<String>,
    #[command(flatten)]
    vm_args: VmArgs,
}

/// The stages of `cargo xtask test`, in the order they run; the one list of them. A new stage is a
/// variant here (its doc line is its `--stage` help), an arm in [`run_stage`] and a row in
/// docs/testing.md (the tidy tests check the docs).
#[derive(Clone, Copy, PartialEq, Eq, Debug, ValueEnum)]
enum Stage {
    /// Rust targets (an MSRV toolchain if one is needed) and system packages.
    Setup,
    /// `cargo test --workspace`.
    Host,
    /// fmt, clippy, rustdoc and the MSRV check (after `host`: it reuses its build scripts and proc macros).
    Lint,
    /// The protocol crate builds for the MCU (no_std).
    ProtoMcu,
    /// Firmware build, size budget, pin-map check, host and Cortex-M4 tests.
    Firmware,
    /// SocketCAN tests on vcan (natively or in the x86_64 microVM).
    Vcan,
    /// The aarch64 binaries on a real arm64 kernel (deploy/check-arm64.sh).
    Arm64,
}

impl Stage {
    /// Every stage, in run order.
    fn all() -> &'static [Stage] {
        Stage::value_variants()
    }

    /// The name used by `--stage`, `--skip`, the log and docs/testing.md.
    fn name(self) -> String {
        self.to_possible_value()
            .map(|v| v.get_name().to_owned())
            .unwrap_or_default()
    }
}

/// A stage that ran to the end or decided it had nothing to do.
enum Done {
    Ran,
    Skipped(String),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Task::Test(args) => return test(args),
        Task::Lint => lint::run(),
        Task::Setup => setup::run(),
        Task::FwSize { dir } => fwsize::report(&dir.unwrap_or_else(firmware_release_dir)),
        Task::VmRun { vm, binary, args } => match vcan::vm_run(vm.settings(), &binary, &args) {
            Ok(code) => return ExitCode::from(u8::try_from(code).unwrap_or(1)),
            Err(e) => Err(e),
        },
        Task::VmShell { vm } => vcan::vm_shell(vm.settings()),
        Task::Fuzz { seconds } => fuzz::run(seconds),
        Task::Soak(args) => soak(args),
        Task::Bench(args) => bench::run(args, &firmware_release_dir()),
        Task::Dbc { check: true, .. } => dbc::check(),
        Task::Dbc { island, .. } if !island.is_empty() => dbc::island(&island),
        Task::Dbc { .. } => dbc::write(),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("xtask: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// `cargo xtask soak`: the fault suite's test binary with `IHEX_FAULT_MINUTES` (and the seed),
/// which the VM passes on like every `IHEX_*` variable.
fn soak(args: SoakArgs) -> Result<()> {
    if let Some(cuts) = args.fw_power_cuts {
        return fw_power_cuts(cuts, args.seed);
    }
    // Read by the child processes started below (the VM passes `IHEX_*` on).
    std::env::set_var(FAULT_MINUTES_ENV, args.minutes.to_string());
    if let Some(seed) = args.seed {
        std::env::set_var(FAULT_SEED_ENV, seed.to_string());
    }
    let mut vm = args.vm_args.settings();
    // The soak, then the wait for recovery and the checker, well inside the VM's lifetime.
    vm.timeout = vm
        .timeout
        .max(Duration::from_secs(args.minutes * 60 * 2 + 600));
    vcan::stage(vcan::Mode::from_env(args.vm)?, vm, Some("faults"))
}

/// `cargo xtask soak --fw-power-cuts N`: the power-cut suite with N cuts and a fresh seed (or
/// the one given), printed first so that a failing plan can be run again.
fn fw_power_cuts(cuts: u64, seed: Option<u64>) -> Result<()> {
    let seed = seed.unwrap_or_else(|| {
        let t = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        t.as_nanos() as u64 ^ u64::from(std::process::id())
    });
    println!("firmware power-cut soak: {cuts} cuts, seed {seed} (again: --seed {seed})");
    cmd::run(
        cmd::cargo()
            .current_dir(cmd::root())
            .args(["test", "--release", "-p", "sim-node", "--test", "power_cut"])
            .args(["--", "--nocapture"])
            .env("IHEX_FW_CUTS", cuts.to_string())
            .env("IHEX_FW_CUT_SEED", seed.to_string()),
    )
}

/// Turns the fault suite into a soak of that many minutes (read by `tests/tests/faults.rs`).
const FAULT_MINUTES_ENV: &str = "IHEX_FAULT_MINUTES";
/// The fault suite's seed.
const FAULT_SEED_ENV: &str = "IHEX_FAULT_SEED";

/// The fault suite's plan in the vcan stage unless `IHEX_FAULT_SEED` names another: a plan that
/// puts every kind of fault once, found green in the runs listed in docs/testing.md. A fresh seed
/// per test run would make the test command a lottery over plans nobody has looked at; the soak
/// (`cargo xtask soak`) is where new plans are drawn.
const CI_FAULT_SEED: &str = "7100433354494382628";

/// How long the host stage cuts the bridge in `tests/tests/bridge.rs` unless `IHEX_BRIDGE_CUT_S`
/// says otherwise: long enough for the bridge's keep-alive to notice, short enough for CI; the
/// 60 s of the reference scenario is the test's own default (docs/testing.md).
const CI_BRIDGE_CUT_S: &str = "8";

fn test(args: TestArgs) -> ExitCode {
    let selected: Vec<Stage> = Stage::all()
        .iter()
        .copied()
        .filter(|s| args.stages.is_empty() || args.stages.contains(s))
        .filter(|s| !args.skip.contains(s))
        .collect();
    let start_all = Instant::now();
    let mut results = Vec::new();
    for stage in selected {
        let name = stage.name();
        println!("\n==> xtask: stage {name}");
        let start = Instant::now();
        let r = run_stage(stage, &args);
        let secs = start.elapsed().as_secs_f64();
        match &r {
            Ok(Done::Ran) => println!("==> xtask: stage {name} passed ({secs:.1} s)"),
            Ok(Done::Skipped(why)) => {
                println!("==> xtask: stage {name} skipped ({secs:.1} s): {why}")
            }
            Err(e) => println!("==> xtask: stage {name} FAILED ({secs:.1} s): {e:#}"),
        }
        results.push((name, r, secs));
    }
    let total = start_all.elapsed().as_secs_f64();
    println!("\nxtask: summary");
    let (mut passed, mut failed) = (0, 0);
    for (name, r, secs) in &results {
        let what = match r {
            Ok(Done::Ran) => {
                passed += 1;
                "passed".to_string()
            }
            Ok(Done::Skipped(why)) => format!("skipped ({why})"),
            Err(e) => {
                failed += 1;
                format!(
                    "FAILED: {}",
                    format!("{e:#}").lines().next().unwrap_or_default()
                )
            }
        };
        println!("  {name:<10} {secs:>7.1} s  {what}");
    }
    println!("  {:<10} {total:>7.1} s  ({})", "total", minutes(total));
    println!("xtask: {passed} passed, {failed} failed");
    if failed == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}

/// `754.2` -> `12 min 34 s`.
fn minutes(secs: f64) -> String {
    let whole = secs.round() as u64;
    format!("{} min {:02} s", whole / 60, whole % 60)
}

/// The firmware's own checks after its build: the pin map cannot disagree with the code (broken
/// copies must fail the build), its pure modules on the host, and the SC core on Cortex-M4
/// instructions in QEMU mps2-an386. Each is its own workspace, run from its folder under
/// `crates/sc-fw`: (what, folder, program, arguments).
const FIRMWARE_CHECKS: [(&str, &str, &str, &[&str]); 3] = [
    ("pin map check", ".", "./check-pinmap.sh", &[]),
    ("host tests", "host-tests", "cargo", &["test"]),
    ("Cortex-M4 tests", "mcu-tests", "./run.sh", &[]),
];

fn run_stage(stage: Stage, args: &TestArgs) -> Result<Done> {
    let root = cmd::root();
    match stage {
        Stage::Setup => setup::run().map(|()| Done::Ran),
        Stage::Host => {
            // golden.rs appends every vector it checks here; cantools then decodes them all.
            let vectors = cmd::target_dir().join("dbc/golden-vectors.txt");
            if let Some(dir) = vectors.parent() {
                std::fs::create_dir_all(dir)?;
            }
            if vectors.exists() {
                std::fs::remove_file(&vectors)?;
            }
            let mut failures = Vec::new();
            if let Err(e) = cmd::run(
                cmd::cargo()
                    .current_dir(&root)
                    .env("IHEX_GOLDEN_VECTORS", &vectors)
                    .env(
                        "IHEX_BRIDGE_CUT_S",
                        std::env::var("IHEX_BRIDGE_CUT_S")
                            .unwrap_or_else(|_| CI_BRIDGE_CUT_S.to_string()),
                    )
                    // The vcan stage builds with the same features and leaves the TLS tests to
                    // this one.
                    .args(["test", "--workspace", "--no-fail-fast"])
                    .args(["--features", cmd::HOST_FEATURES]),
            ) {
                failures.push(format!("{e:#}"));
            }
            println!("==> xtask: host: DBC round trip through cantools");
            if let Err(e) = cantools::round_trip(&vectors) {
                failures.push(format!("cantools round trip: {e:#}"));
            }
            println!("==> xtask: host: the island view in headless Chromium");
            if let Err(e) = browser::run() {
                failures.push(format!("browser test: {e:#}"));
            }
            println!("==> xtask: host: Prometheus scraping the demo gateway");
            if let Err(e) = prometheus::run() {
                failures.push(format!("Prometheus test: {e:#}"));
            }
            println!("==> xtask: host: the reference SiLA 2 client driving the demo gateway");
            if let Err(e) = sila::run() {
                failures.push(format!("SiLA test: {e:#}"));
            }
            if !failures.is_empty() {
                anyhow::bail!("{}", failures.join("; "));
            }
            Ok(Done::Ran)
        }
        Stage::Lint => lint::run().map(|()| Done::Ran),
        Stage::ProtoMcu => {
            let base = [
                "build",
                "-p",
                "ihex-proto",
                "--target",
                "thumbv7em-none-eabihf",
            ];
            cmd::run(cmd::cargo().current_dir(&root).args(base))?;
            cmd::run(
                cmd::cargo()
                    .current_dir(&root)
                    .args(base)
                    .args(["--features", "defmt"]),
            )?;
            Ok(Done::Ran)
        }
        Stage::Firmware => {
            let fw = root.join(cmd::FIRMWARE);
            if !fw.join("Cargo.toml").exists() {
                return Ok(Done::Skipped(format!("no {}/Cargo.toml", cmd::FIRMWARE)));
            }
            cmd::run(cmd::cargo_in(&fw).args(["build", "--release"]))?;
            fwsize::report(&firmware_release_dir())?;
            fwsize::pack_check(&firmware_release_dir())?;
            let mut failures = Vec::new();
            for (what, dir, prog, args) in FIRMWARE_CHECKS {
                println!("==> xtask: firmware: {what}");
                let dir = fw.join(dir);
                let mut c = if prog == "cargo" {
                    cmd::cargo_in(&dir)
                } else {
                    cmd::in_workspace(Command::new(prog), &dir)
                };
                if let Err(e) = cmd::run(c.args(args)) {
                    failures.push(format!("{what}: {e:#}"));
                }
            }
            if !failures.is_empty() {
                anyhow::bail!("{}", failures.join("; "));
            }
            Ok(Done::Ran)
        }
        Stage::Vcan => {
            // The test command repeats one plan of the fault suite; the soak explores fresh ones.
            if std::env::var_os(FAULT_SEED_ENV).is_none() {
                std::env::set_var(FAULT_SEED_ENV, CI_FAULT_SEED);
            }
            vcan::stage(
                vcan::Mode::from_env(args.vm)?,
                args.vm_args.settings(),
                args.vcan_test.as_deref(),
            )?;
            Ok(Done::Ran)
        }
        Stage::Arm64 => {
            let script = root.join("deploy/check-arm64.sh");
            if !script.exists() {
                return Ok(Done::Skipped("no deploy/check-arm64.sh".into()));
            }
            // Its shebang picks the shell; a copy that lost its execute bit still runs through sh.
            let mut c = if is_executable(&script) {
                Command::new(&script)
            } else {
                let mut c = Command::new("sh");
                c.arg(&script);
                c
            };
            cmd::run(c.current_dir(&root)).with_context(|| format!("{}", script.display()))?;
            Ok(Done::Ran)
        }
    }
}

fn is_executable(path: &std::path::Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(path).is_ok_and(|m| m.permissions().mode() & 0o111 != 0)
}

fn firmware_release_dir() -> PathBuf {
    cmd::root()
        .join(cmd::FIRMWARE)
        .join("target/thumbv7em-none-eabihf/release")
}
