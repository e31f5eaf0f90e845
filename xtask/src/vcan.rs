//! The SocketCAN stage: `ihex-tests --features vcan` on native vcan interfaces when the host has
//! them, otherwise inside the x86_64 microVM; and `vm-run`, the cargo runner of the musl target.
//!
//! The VM runs the host-target test binaries the way the host stage built them (one workspace
//! build, the `vcan` feature only adds ihex-tests itself), with the glibc libraries they link
//! copied in: no second build of every dependency for another target.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};

use crate::cmd;
use crate::vm::{shared_libraries, Payload, Program, Vm};

/// Number of vcan interfaces the tests get.
pub const COUNT: usize = 16;

/// The static target `vm-run` serves as cargo runner (and the benchmark builds for the VM).
pub const MUSL: &str = "x86_64-unknown-linux-musl";

/// Modules the VM loads (dependencies are resolved with modinfo).
const MODULES: [&str; 4] = ["can", "can-raw", "can-dev", "vcan"];

/// How the user wants the SocketCAN tests run (`IHEX_VCAN` or `--vm`).
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Mode {
    /// Native vcan when possible, else the VM.
    Auto,
    /// Always the VM.
    Vm,
    /// Native vcan or fail.
    Native,
}

impl Mode {
    /// From `IHEX_VCAN` (`auto`, `vm`, `native`), overridden by `force_vm`.
    pub fn from_env(force_vm: bool) -> Result<Mode> {
        if force_vm {
            return Ok(Mode::Vm);
        }
        match std::env::var("IHEX_VCAN").ok().as_deref().map(str::trim) {
            None | Some("") | Some("auto") => Ok(Mode::Auto),
            Some("vm") => Ok(Mode::Vm),
            Some("native") => Ok(Mode::Native),
            Some(other) => bail!("IHEX_VCAN={other}: expected auto, vm or native"),
        }
    }
}

/// VM knobs from the command line.
#[derive(Clone, Copy, Debug)]
pub struct VmSettings {
    /// Kill the VM after this long.
    pub timeout: Duration,
    /// Virtual CPUs.
    pub smp: u32,
    /// Guest memory floor in MiB.
    pub memory_mb: u64,
}

fn vcan_names() -> Vec<String> {
    let mut names: Vec<String> = fs::read_dir("/sys/class/net")
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .filter(|n| n.starts_with("vcan"))
                .collect()
        })
        .unwrap_or_default();
    names.sort_by_key(|n| (n.len(), n.clone()));
    names
}

fn quiet(mut c: Command) -> bool {
    c.stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    c.status().is_ok_and(|s| s.success())
}

/// The host's vcan interfaces, creating `vcan0..vcan15` (with sudo when not root) where the kernel
/// allows; `None` when SocketCAN cannot run natively here.
pub fn native_interfaces(create: bool) -> Option<Vec<String>> {
    let existing = vcan_names();
    if !create && !existing.is_empty() {
        return Some(existing);
    }
    if existing.len() < COUNT {
        if let Some(mut c) = cmd::privileged("modprobe") {
            c.arg("vcan");
            let _ = quiet(c);
        }
        for i in 0..COUNT {
            let name = format!("vcan{i}");
            if Path::new("/sys/class/net").join(&name).exists() {
                continue;
            }
            let Some(mut c) = cmd::privileged("ip") else {
                break;
            };
            c.args(["link", "add", "dev", &name, "type", "vcan"]);
            if !quiet(c) {
                break;
            }
        }
    }
    let names = vcan_names();
    for n in &names {
        if let Some(mut c) = cmd::privileged("ip") {
            c.args(["link", "set", "up", n]);
            let _ = quiet(c);
        }
    }
    (!names.is_empty()).then_some(names)
}

/// The `vcan` stage: every SocketCAN test binary, or only the integration test `only`.
pub fn stage(mode: Mode, vm: VmSettings, only: Option<&str>) -> Result<()> {
    let native = match mode {
        Mode::Vm => None,
        _ => native_interfaces(true),
    };
    match (native, mode) {
        (Some(ifaces), _) => run_native(&ifaces, only),
        (None, Mode::Native) => bail!(
            "IHEX_VCAN=native but this kernel cannot create vcan interfaces \
             (try `sudo modprobe vcan`, or unset IHEX_VCAN to use the microVM)"
        ),
        (None, _) => {
            println!(
                "xtask: no vcan on this kernel: running the SocketCAN tests in a QEMU microVM"
            );
            run_in_vm(vm, only)
        }
    }
}

fn run_native(ifaces: &[String], only: Option<&str>) -> Result<()> {
    println!("xtask: native SocketCAN on {}", ifaces.join(","));
    // The fault suite runs the gateway binary; the tests find it beside their `deps/` folder.
    cmd::run(
        cmd::cargo()
            .current_dir(cmd::root())
            .args(["build", "-p", "mc-gateway"]),
    )?;
    let mut c = cmd::cargo();
    c.current_dir(cmd::root())
        .args(["test", "-p", "ihex-tests", "--features", "vcan"])
        .env("IHEX_TEST_CAN", ifaces.join(","));
    if let Some(test) = only {
        c.args(["--test", test]);
    }
    cmd::run(&mut c)
}

/// The x86_64 VM set up for the SocketCAN tests: CAN modules, `vcan0..15` up, big socket buffers,
/// mosquitto and its libraries inside.
pub fn test_vm(settings: VmSettings) -> Result<Vm> {
    let mut vm = Vm::x86_64(&cmd::target_dir().join("vm"))?;
    vm.modules = MODULES.map(String::from).to_vec();
    let names: Vec<String> = (0..COUNT).map(|i| format!("vcan{i}")).collect();
    vm.boot_script = format!(
        "for i in {seq}; do ip link add dev vcan$i type vcan && ip link set up vcan$i; done\n\
         echo 16777216 > /proc/sys/net/core/rmem_max\n\
         echo 16777216 > /proc/sys/net/core/wmem_max\n\
         export IHEX_TEST_CAN={list}",
        seq = (0..COUNT)
            .map(|i| i.to_string())
            .collect::<Vec<_>>()
            .join(" "),
        list = names.join(",")
    );
    if let Some(m) = cmd::find("mosquitto") {
        vm.host_programs.push(m);
    }
    vm.timeout = settings.timeout;
    vm.smp = settings.smp;
    vm.memory_mb = settings.memory_mb;
    Ok(vm)
}

/// Repository files (tracked by git, under 1 MiB) so tests find fixtures at their host paths.
fn repo_files() -> Vec<PathBuf> {
    let root = cmd::root();
    let Some(out) = cmd::output(
        Command::new("git")
            .arg("-C")
            .arg(&root)
            .args(["ls-files", "-z"]),
    ) else {
        return Vec::new();
    };
    out.split('\0')
        .filter(|s| !s.is_empty())
        .map(|s| root.join(s))
        .filter(|p| fs::metadata(p).is_ok_and(|m| m.is_file() && m.len() < (1 << 20)))
        .collect()
}

/// Variables the programs in the VM see: the test settings plus what cargo and the user set for
/// tests (`RUST_*`, `IHEX_*`, `CARGO_PKG_*`, `CARGO_MANIFEST_DIR`...).
fn guest_env() -> Vec<(String, String)> {
    let mut env: Vec<(String, String)> = std::env::vars()
        .filter(|(k, _)| {
            (k.starts_with("RUST_") && k != "RUSTUP_HOME")
                || k.starts_with("IHEX_")
                || k.starts_with("CARGO_PKG_")
                || k == "CARGO_MANIFEST_DIR"
                || k == "CARGO_CRATE_NAME"
        })
        .filter(|(k, _)| k != "IHEX_TEST_CAN")
        .collect();
    // TCG emulation is many times slower than the host: stretch the tests' deadlines.
    if !env.iter().any(|(k, _)| k == "IHEX_TEST_TIME_SCALE") {
        env.push(("IHEX_TEST_TIME_SCALE".into(), "5".into()));
    }
    env
}

/// Builds the SocketCAN test binaries for the host and returns them (name, path). `--workspace`
/// and `ihex-tests/tls` resolve features as the host stage does, so after it only ihex-tests
/// compiles again, and the `mc-gateway` binary the fault suite runs is the host stage's.
fn build_tests() -> Result<Vec<(String, PathBuf)>> {
    let mut c = cmd::cargo();
    c.current_dir(cmd::root())
        .args([
            "test",
            "--workspace",
            "--features",
            "ihex-tests/vcan,ihex-tests/tls",
            "--no-run",
        ])
        .arg("--message-format=json-render-diagnostics")
        .stdout(Stdio::piped());
    println!("$ {}", cmd::display(&c));
    let out = c.output().context("running cargo")?;
    if !out.status.success() {
        bail!(
            "building the SocketCAN test binaries failed ({})",
            out.status
        );
    }
    let manifest = cmd::root().join("tests/Cargo.toml");
    let mut bins = Vec::new();
    for line in String::from_utf8_lossy(&out.stdout).lines() {
        let Ok(msg) = serde_json::from_str::<serde_json::Value>(line) else {
            continue;
        };
        // Only ihex-tests' test binaries: the workspace build lists every package's.
        if msg["reason"] != "compiler-artifact"
            || msg["profile"]["test"] != true
            || msg["manifest_path"].as_str().map(Path::new) != Some(&manifest)
        {
            continue;
        }
        let Some(exe) = msg["executable"].as_str() else {
            continue;
        };
        let target = &msg["target"];
        let kind = target["kind"][0].as_str().unwrap_or("?");
        let name = target["name"].as_str().unwrap_or("?");
        bins.push((format!("{name} ({kind})"), PathBuf::from(exe)));
    }
    if bins.is_empty() {
        bail!("cargo built no test executables for ihex-tests");
    }
    Ok(bins)
}

/// The integration test (a file of `tests/tests/`) a [`build_tests`] label names, if it names one.
fn integration_test(label: &str) -> Option<&str> {
    label.strip_suffix(" (test)")
}

/// Test binaries of `ihex-tests` the stage leaves out: `security` and `bridge` need no CAN (the
/// host stage runs them). The fault suite (`faults`) runs its bounded run here (every kind of
/// fault once; `cargo xtask soak` makes it a soak).
const NOT_IN_STAGE: [&str; 2] = ["security (test)", "bridge (test)"];
/// The workspace programs tests run as child processes, and the variable that tells them where
/// the program is (`IHEX_GATEWAY_BIN`: the fault suite; `IHEX_PROVISION_BIN`:
/// `gateway_fw_update`).
const CARRIED_PROGRAMS: [(&str, &str); 2] = [
    ("mc-gateway", "IHEX_GATEWAY_BIN"),
    ("ihex-provision", "IHEX_PROVISION_BIN"),
];

fn run_in_vm(settings: VmSettings, only: Option<&str>) -> Result<()> {
    let built = build_tests()?;
    let bins: Vec<(String, PathBuf)> = built
        .iter()
        .filter(|(name, _)| match only {
            Some(t) => integration_test(name) == Some(t),
            None => !NOT_IN_STAGE.contains(&name.as_str()),
        })
        .cloned()
        .collect();
    if let (Some(t), true) = (only, bins.is_empty()) {
        let tests: Vec<&str> = built
            .iter()
            .filter_map(|(name, _)| integration_test(name))
            .collect();
        bail!(
            "no integration test \"{t}\"; there are: {}",
            tests.join(", ")
        );
    }
    // Tests run the workspace's programs as users do (the fault suite the gateway, the firmware
    // update test ihex-provision): built with the tests (each has tests of its own binary),
    // found beside the test binaries' `deps/` folder.
    let mut programs = Vec::new();
    for (name, env) in CARRIED_PROGRAMS {
        let path = cmd::target_dir().join("debug").join(name);
        if !path.is_file() {
            bail!("no {} after building the tests", path.display());
        }
        programs.push((env, stripped_copy(&path)));
    }
    let vm = test_vm(settings)?;
    // The binaries are dynamically linked: their libraries (glibc) go in at the host's paths.
    let mut files = repo_files();
    files.extend(programs.iter().map(|(_, p)| p.clone()));
    for path in bins
        .iter()
        .map(|(_, p)| p)
        .chain(programs.iter().map(|(_, p)| p))
    {
        for lib in shared_libraries(path)? {
            if !files.contains(&lib) {
                files.push(lib);
            }
        }
    }
    let payload = Payload {
        programs: bins
            .into_iter()
            .map(|(name, path)| Program {
                name,
                path,
                args: Vec::new(),
            })
            .collect(),
        env: {
            let mut env = guest_env();
            for (var, path) in &programs {
                env.push((var.to_string(), path.display().to_string()));
            }
            env
        },
        cwd: Some(cmd::root().join("tests")),
        files,
    };
    let outcomes = vm.run(&payload)?;
    let failed: Vec<String> = outcomes
        .iter()
        .filter(|o| o.code != 0)
        .map(|o| format!("{} (exit {})", o.name, o.code))
        .collect();
    for o in &outcomes {
        println!(
            "vm: {:<32} {}",
            o.name,
            if o.code == 0 {
                "ok".into()
            } else {
                format!("FAILED (exit {})", o.code)
            }
        );
    }
    if !failed.is_empty() {
        bail!("failed in the VM: {}", failed.join(", "));
    }
    Ok(())
}

/// A copy of `program` without debug info in `target/vm/` (the VM strips the programs it runs,
/// not the files it carries; a debug `mc-gateway` would add 100 MB to the initrd), or `program`
/// itself when `strip` is missing, fails, or `IHEX_VM_KEEP_DEBUG` is set.
fn stripped_copy(program: &Path) -> PathBuf {
    let Some(strip) =
        cmd::find("strip").filter(|_| std::env::var_os("IHEX_VM_KEEP_DEBUG").is_none())
    else {
        return program.to_path_buf();
    };
    let out = cmd::target_dir()
        .join("vm")
        .join(program.file_name().unwrap_or_default());
    let ok = fs::create_dir_all(cmd::target_dir().join("vm")).is_ok()
        && Command::new(strip)
            .arg("--strip-debug")
            .arg("-o")
            .arg(&out)
            .arg(program)
            .status()
            .is_ok_and(|s| s.success());
    if ok {
        out
    } else {
        program.to_path_buf()
    }
}

/// `vm-run`: runs one program (a musl test binary) in the VM and returns its exit code. Meant as
/// `CARGO_TARGET_X86_64_UNKNOWN_LINUX_MUSL_RUNNER`, so `cargo test --target x86_64-unknown-linux-musl`
/// works unchanged.
pub fn vm_run(settings: VmSettings, binary: &Path, args: &[String]) -> Result<i32> {
    let path = fs::canonicalize(binary).with_context(|| format!("{}", binary.display()))?;
    let vm = test_vm(settings)?;
    let name = path
        .file_name()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    let mut files = repo_files();
    // Programs the tests run as child processes must be in the VM too.
    for (_, var) in CARRIED_PROGRAMS {
        if let Some(program) = std::env::var_os(var) {
            let program = PathBuf::from(program);
            files.extend(shared_libraries(&program)?);
            files.push(program);
        }
    }
    let payload = Payload {
        programs: vec![Program {
            name,
            path,
            args: args.to_vec(),
        }],
        env: guest_env(),
        cwd: std::env::current_dir().ok(),
        files,
    };
    let outcome = vm.run(&payload)?;
    outcome
        .first()
        .map(|o| o.code)
        .ok_or_else(|| anyhow!("the VM reported no exit code"))
}

/// `vm-shell`: the test VM with an interactive shell.
pub fn vm_shell(settings: VmSettings) -> Result<()> {
    let mut s = settings;
    s.timeout = Duration::MAX;
    test_vm(s)?.shell()
}
