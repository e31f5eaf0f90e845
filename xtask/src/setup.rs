//! `cargo xtask setup`: the rustup targets and the system packages the test stages need.
//!
//! On Debian/Ubuntu as root (or with password-less sudo) missing packages are installed with
//! apt-get; a machine that has everything never touches apt. Elsewhere it lists what is missing
//! and how to get it.

use std::process::Command;

use anyhow::{bail, Result};

use crate::cmd;

/// Cross targets of the project (firmware, static test binaries for the VM, the Pi).
pub const TARGETS: [&str; 3] = [
    "thumbv7em-none-eabihf",
    "x86_64-unknown-linux-musl",
    "aarch64-unknown-linux-gnu",
];

/// Debian packages for the microVM and the MQTT tests.
const VM_PACKAGES: [&str; 4] = [
    "qemu-system-x86",
    "linux-image-amd64",
    "busybox-static",
    "cpio",
];
const BROKER_PACKAGE: &str = "mosquitto";
/// Runs the SC core's tests on Cortex-M4 instructions (the firmware stage).
const MCU_EMULATOR_PACKAGE: &str = "qemu-system-arm";

/// Installs what is missing; fails with instructions when it cannot.
pub fn run() -> Result<()> {
    let mut problems = Vec::new();
    if let Err(e) = targets() {
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

fn targets() -> Result<()> {
    let Some(installed) =
        cmd::output(Command::new("rustup").args(["target", "list", "--installed"]))
    else {
        bail!(
            "rustup not found: install it from https://rustup.rs, then run `rustup target add {}`",
            TARGETS.join(" ")
        );
    };
    let missing: Vec<&str> = TARGETS
        .iter()
        .copied()
        .filter(|t| !installed.lines().any(|l| l.trim() == *t))
        .collect();
    if missing.is_empty() {
        println!("setup: rust targets present ({})", TARGETS.join(", "));
        return Ok(());
    }
    cmd::run(
        Command::new("rustup")
            .args(["target", "add"])
            .args(&missing),
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
    v.extend(crate::browser::PACKAGES);
    v
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
            "chromium" => (crate::browser::present(), "Chromium and chromedriver (or set IHEX_CHROMIUM and IHEX_CHROMEDRIVER)"),
            "chromium-driver" => (true, ""),
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
