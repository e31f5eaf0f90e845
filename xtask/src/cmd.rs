//! Running external programs: cargo through `$CARGO`, command lines echoed, failures as errors.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use anyhow::{bail, Context, Result};

/// The cargo that started us (`$CARGO`), so nested builds use the same toolchain.
pub fn cargo() -> Command {
    Command::new(std::env::var_os("CARGO").unwrap_or_else(|| OsString::from("cargo")))
}

/// The firmware workspace, relative to the root: its own `Cargo.lock`, profiles, target and
/// `.cargo/config.toml` (thumb target); `host-tests/` and `mcu-tests/` inside are workspaces too.
pub const FIRMWARE: &str = "crates/sc-fw";

/// `cmd` prepared to run in `dir`, a workspace of its own (the firmware's): its
/// `.cargo/config.toml` (target, target-dir), profiles and `target/` apply, whatever
/// `CARGO_TARGET_DIR` or `CARGO_BUILD_TARGET` the host build uses.
pub fn in_workspace(mut cmd: Command, dir: &Path) -> Command {
    cmd.current_dir(dir)
        .env_remove("CARGO_TARGET_DIR")
        .env_remove("CARGO_BUILD_TARGET");
    cmd
}

/// Cargo run in `dir`, a workspace of its own (see [`in_workspace`]).
pub fn cargo_in(dir: &Path) -> Command {
    in_workspace(cargo(), dir)
}

/// The workspace root (the parent of this crate's folder).
pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("xtask lives in a subfolder of the workspace")
        .to_path_buf()
}

/// The host workspace's target directory (`CARGO_TARGET_DIR` or `<root>/target`).
pub fn target_dir() -> PathBuf {
    match std::env::var_os("CARGO_TARGET_DIR") {
        Some(d) => root().join(d),
        None => root().join("target"),
    }
}

/// A command line as the user would type it, from the root: `cd crates/sc-fw && cargo ...` for a
/// command that runs in a subfolder, with the variables it sets (`RUSTDOCFLAGS='-D warnings' ...`).
pub fn display(cmd: &Command) -> String {
    let mut s = String::new();
    if let Some(rel) = cmd
        .get_current_dir()
        .and_then(|d| d.strip_prefix(root()).ok())
        .filter(|rel| !rel.as_os_str().is_empty())
    {
        s.push_str(&format!("cd {} && ", rel.display()));
    }
    for (k, v) in cmd.get_envs() {
        if let Some(v) = v {
            let v = v.to_string_lossy();
            if v.contains(' ') {
                s.push_str(&format!("{}='{v}' ", k.to_string_lossy()));
            } else {
                s.push_str(&format!("{}={v} ", k.to_string_lossy()));
            }
        }
    }
    s.push_str(&cmd.get_program().to_string_lossy());
    for a in cmd.get_args() {
        s.push(' ');
        s.push_str(&a.to_string_lossy());
    }
    s
}

/// Runs `cmd` with inherited stdio (its output streams through) and fails on a non-zero exit.
pub fn run(cmd: &mut Command) -> Result<()> {
    let line = display(cmd);
    println!("$ {line}");
    let status = cmd
        .status()
        .with_context(|| format!("cannot start `{line}`"))?;
    if !status.success() {
        bail!("`{line}` failed ({status})");
    }
    Ok(())
}

/// Runs `cmd` quietly and returns its stdout when it succeeds, `None` when it fails or is missing.
pub fn output(cmd: &mut Command) -> Option<String> {
    let out = cmd
        .stdin(Stdio::null())
        .stderr(Stdio::null())
        .output()
        .ok()?;
    out.status
        .success()
        .then(|| String::from_utf8_lossy(&out.stdout).into_owned())
}

/// True when `program` runs (searched on `PATH`).
pub fn exists(program: &str) -> bool {
    find(program).is_some()
}

/// `program`'s path, searched on `PATH` and then the sbin folders (not on a normal user's `PATH`).
pub fn find(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .chain(["/usr/sbin".into(), "/sbin".into(), "/usr/local/sbin".into()])
        .map(|d| d.join(program))
        .find(|p| p.is_file())
}

/// True when this process runs as root (read from `/proc`, no libc needed).
pub fn is_root() -> bool {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("Uid:"))
                .and_then(|l| l.split_whitespace().nth(2).map(|euid| euid == "0"))
        })
        .unwrap_or(false)
}

/// A command run as root: directly when we are root, through `sudo -n` when that works without a
/// password, `None` otherwise.
pub fn privileged(program: &str) -> Option<Command> {
    if is_root() {
        return Some(Command::new(program));
    }
    let sudo_ok = output(Command::new("sudo").args(["-n", "true"])).is_some();
    sudo_ok.then(|| {
        let mut c = Command::new("sudo");
        c.args(["-n", program]);
        c
    })
}
