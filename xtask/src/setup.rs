//! `cargo xtask setup`: the rustup targets and toolchains and the system packages the test stages
//! need.
//!
//! On Debian/Ubuntu as root (or with password-less sudo) missing packages are installed with
//! apt-get; a machine that has everything never touches apt. Elsewhere it lists what is missing
//! and how to get it.

use std::process::Command;

use anyhow::{bail, Context, Result};

use crate::cmd;

/// Debian packages for the microVM and the MQTT tests.
const VM_PACKAGES: [&str; 4] = [
    "qemu-system-x86",
    "linux-image-amd64",
    "busybox-static",
    "cpio",
];
const BROKER_PACKAGE: &str = "mosquitto";
/// Runs the SC core's tests on Cortex-M4 instructions (the firmware stage) and, as
/// qemu-system-aarch64, the arm64 stage's VM.
const MCU_EMULATOR_PACKAGE: &str = "qemu-system-arm";
/// The arm64 stage unpacks Debian's compressed kernel modules.
const XZ_PACKAGE: &str = "xz-utils";

/// Installs what is missing; fails with instructions when it cannot.
pub fn run() -> Result<()> {
    let mut problems = Vec::new();
    if let Err(e) = targets() {
        problems.push(format!("{e:#}"));
    }
    // A second toolchain only when the declared MSRV is older than the pinned one.
    match crate::lint::msrv_below_pinned() {
        Ok(None) => {}
        Ok(Some(v)) => {
            if let Err(e) = toolchain(&v, &crate::lint::MSRV_TARGETS) {
                problems.push(format!("{e:#}"));
            }
        }
        Err(e) => problems.push(format!("{e:#}")),
    }
    // The fuzz targets (the lint stage builds them and runs their seeds).
    if let Err(e) = toolchain(crate::fuzz::TOOLCHAIN, &[]).and_then(|()| cargo_fuzz()) {
        problems.push(format!("{e:#}"));
    }
    if let Err(e) = packages() {
        problems.push(format!("{e:#}"));
    }
    if !problems.is_empty() {
        bail!("setup incomplete:\n  {}", problems.join("\n  "));
    }
    Ok(())
}

/// The cross targets of the project (firmware, static binaries for the VMs, the Pi): the
/// `targets` of `rust-toolchain.toml`, the one place that lists them.
pub fn toolchain_targets() -> Result<Vec<String>> {
    let path = cmd::root().join("rust-toolchain.toml");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
    let list = text
        .lines()
        .find_map(|l| l.trim().strip_prefix("targets"))
        .and_then(|rest| rest.trim_start().strip_prefix('='))
        .and_then(|rest| rest.trim().strip_prefix('['))
        .and_then(|rest| rest.split_once(']'))
        .map(|(inner, _)| inner)
        .with_context(|| format!("no `targets = [...]` line in {}", path.display()))?;
    Ok(list
        .split(',')
        .map(|t| t.trim().trim_matches('"').to_string())
        .filter(|t| !t.is_empty())
        .collect())
}

fn targets() -> Result<()> {
    let targets = toolchain_targets()?;
    let Some(installed) =
        cmd::output(Command::new("rustup").args(["target", "list", "--installed"]))
    else {
        bail!(
            "rustup not found: install it from https://rustup.rs, then run `rustup target add {}`",
            targets.join(" ")
        );
    };
    let missing: Vec<&str> = targets
        .iter()
        .map(String::as_str)
        .filter(|t| !installed.lines().any(|l| l.trim() == *t))
        .collect();
    if missing.is_empty() {
        println!("setup: rust targets present ({})", targets.join(", "));
        return Ok(());
    }
    cmd::run(
        Command::new("rustup")
            .args(["target", "add"])
            .args(&missing),
    )
}

/// Installs the rustup toolchain `version` (the lint's MSRV check) with the minimal profile and
/// `targets` when they are missing; a machine that has them never asks the network.
pub fn toolchain(version: &str, targets: &[&str]) -> Result<()> {
    let list = cmd::output(Command::new("rustup").args(["toolchain", "list"])).context(
        "rustup not found: install it from https://rustup.rs (the MSRV check needs a second toolchain)",
    )?;
    // `rustup toolchain install 1.89` names it `1.89-<host triple>`.
    if !list.lines().any(|l| l.starts_with(&format!("{version}-"))) {
        return cmd::run(
            Command::new("rustup")
                .args(["toolchain", "install", version, "--profile", "minimal"])
                .args(targets.iter().flat_map(|t| ["--target", t])),
        );
    }
    let installed = cmd::output(Command::new("rustup").args([
        "target",
        "list",
        "--installed",
        "--toolchain",
        version,
    ]))
    .unwrap_or_default();
    let missing: Vec<&str> = targets
        .iter()
        .copied()
        .filter(|t| !installed.lines().any(|l| l.trim() == *t))
        .collect();
    if missing.is_empty() {
        println!(
            "setup: toolchain {version} present ({})",
            targets.join(", ")
        );
        return Ok(());
    }
    cmd::run(
        Command::new("rustup")
            .args(["target", "add", "--toolchain", version])
            .args(&missing),
    )
}

/// Installs cargo-fuzz [`crate::fuzz::CARGO_FUZZ_VERSION`] from crates.io unless that version is
/// there (about 1.5 min of CPU, once).
fn cargo_fuzz() -> Result<()> {
    let version = crate::fuzz::CARGO_FUZZ_VERSION;
    let installed = cmd::output(Command::new("cargo").args(["fuzz", "--version"]));
    // `cargo-fuzz 0.13.2`
    if installed.is_some_and(|v| v.split_whitespace().nth(1) == Some(version)) {
        println!("setup: cargo-fuzz {version} present");
        return Ok(());
    }
    cmd::run(
        cmd::cargo()
            .args(["install", "--locked", "cargo-fuzz", "--version", version])
            // Its own build, not with the flags of whatever cargo started us.
            .env_remove("CARGO_TARGET_DIR")
            .env_remove("CARGO_BUILD_TARGET"),
    )
}

/// The packages this machine needs: the VM ones only where SocketCAN cannot run natively.
fn wanted() -> Vec<&'static str> {
    let mut v = Vec::new();
    if crate::vcan::native_interfaces(false).is_none() {
        v.extend(VM_PACKAGES);
    }
    v.push(BROKER_PACKAGE);
    v.push(MCU_EMULATOR_PACKAGE);
    v.push(XZ_PACKAGE);
    v.extend(crate::browser::PACKAGES);
    v.extend(crate::prometheus::PACKAGES);
    v
}

/// True when deploy/check-arm64.sh will need Debian's arm64 package lists (its kernel and busybox
/// are not cached yet) and apt does not have them.
fn arm64_lists_wanted() -> bool {
    let root = cmd::root();
    root.join("deploy/check-arm64.sh").exists()
        && !root.join("target/arm64-vm/rootfs/.complete").exists()
        && !cmd::output(Command::new("dpkg").arg("--print-foreign-architectures"))
            .is_some_and(|a| a.lines().any(|l| l.trim() == "arm64"))
}

fn dpkg_installed(pkg: &str) -> bool {
    cmd::output(Command::new("dpkg-query").args(["-W", "-f=${Status}", pkg]))
        .is_some_and(|s| s.trim() == "install ok installed")
}

fn packages() -> Result<()> {
    let wanted = wanted();
    if !cmd::exists("dpkg-query") || !cmd::exists("apt-get") {
        return check_without_apt(&wanted);
    }
    let missing: Vec<&str> = wanted
        .iter()
        .copied()
        .filter(|p| !dpkg_installed(p))
        .collect();
    if missing.is_empty() {
        println!("setup: packages present ({})", wanted.join(", "));
        return Ok(());
    }
    let Some(mut update) = cmd::privileged("apt-get") else {
        bail!(
            "missing packages: {m}; install them with `sudo apt-get install {m}` (no root and no \
             password-less sudo here)",
            m = missing.join(" ")
        );
    };
    // With the architecture added first, this one update also fetches the arm64 lists the arm64
    // stage downloads its kernel from, and that stage needs no update of its own.
    if arm64_lists_wanted() {
        if let Some(mut dpkg) = cmd::privileged("dpkg") {
            cmd::run(dpkg.args(["--add-architecture", "arm64"]))?;
        }
    }
    cmd::run(
        update
            .env("DEBIAN_FRONTEND", "noninteractive")
            .args(["-q", "update"]),
    )?;
    let mut install = cmd::privileged("apt-get").expect("checked above");
    cmd::run(
        install
            .env("DEBIAN_FRONTEND", "noninteractive")
            .args(["-q", "-y", "--no-install-recommends", "install"])
            .args(&missing),
    )
}

/// Not Debian: look for the programs and files themselves.
fn check_without_apt(wanted: &[&str]) -> Result<()> {
    let mut missing = Vec::new();
    for pkg in wanted {
        let (ok, hint) = match *pkg {
            "qemu-system-x86" => (cmd::exists("qemu-system-x86_64"), "qemu-system-x86_64 (package qemu / qemu-system-x86)"),
            "linux-image-amd64" => (
                crate::vm::host_kernel().is_ok(),
                "a kernel with CAN modules: /boot/vmlinuz-<v> and /lib/modules/<v>/ with can, can-raw, can-dev, vcan (or set IHEX_VM_KERNEL and IHEX_VM_MODULES)",
            ),
            "busybox-static" => (crate::vm::static_busybox().is_some(), "a statically linked busybox (package busybox-static / busybox; or set IHEX_VM_BUSYBOX)"),
            "cpio" => (true, ""),
            "qemu-system-arm" => (cmd::exists("qemu-system-arm"), "qemu-system-arm (package qemu-system-arm / qemu)"),
            "xz-utils" => (cmd::exists("xz"), "xz (package xz-utils / xz)"),
            "chromium" => (crate::browser::present(), "Chromium and chromedriver (or set IHEX_CHROMIUM and IHEX_CHROMEDRIVER)"),
            "chromium-driver" => (true, ""),
            "prometheus" => (crate::prometheus::present(), "Prometheus and promtool (or set IHEX_PROMETHEUS and IHEX_PROMTOOL)"),
            _ => (cmd::exists("mosquitto"), "mosquitto (package mosquitto)"),
        };
        if !ok {
            missing.push(hint);
        }
    }
    if missing.is_empty() {
        println!("setup: no apt here; the needed programs are present");
        return Ok(());
    }
    bail!(
        "no apt-get on this system; install these yourself:\n    - {}",
        missing.join("\n    - ")
    )
}
