//! `cargo xtask fuzz` and the lint stage's fuzz step: every cargo-fuzz target of the repository
//! built with nightly, then run for a bounded time (`--seconds 0`: only its seeds, once each).
//!
//! Each fuzz workspace is a folder `fuzz/` beside the crate it fuzzes, excluded from the host
//! workspace (nightly, sanitizer flags); its targets are the `[[bin]]`s of its `Cargo.toml`, its
//! tracked seeds `seeds/<target>/`. What libFuzzer finds goes to `target/fuzz/<crate>/<target>/`,
//! never into the tracked seeds.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

use crate::cmd;

/// The fuzz workspaces, relative to the root.
pub const WORKSPACES: [&str; 3] = [
    "crates/ihex-proto/fuzz",
    "crates/ihex-image/fuzz",
    "crates/ihex-gateway-core/fuzz",
];

/// The toolchain cargo-fuzz builds with (`-Zsanitizer` is nightly only).
pub const TOOLCHAIN: &str = "nightly";

/// The cargo-fuzz that `cargo xtask setup` installs (`cargo install --locked`).
pub const CARGO_FUZZ_VERSION: &str = "0.13.2";

/// A fuzz target: its workspace (relative to the root) and name.
pub struct Target {
    /// The fuzz workspace, e.g. `crates/ihex-proto/fuzz`.
    pub workspace: &'static str,
    /// The `[[bin]]` name, e.g. `decode`.
    pub name: String,
}

/// Every target of every fuzz workspace, in [`WORKSPACES`] order.
pub fn targets() -> Result<Vec<Target>> {
    let mut out = Vec::new();
    for ws in WORKSPACES {
        let path = cmd::root().join(ws).join("Cargo.toml");
        let text = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
        let names = bin_names(&text);
        if names.is_empty() {
            bail!("{} declares no [[bin]] fuzz target", path.display());
        }
        out.extend(names.into_iter().map(|name| Target {
            workspace: ws,
            name,
        }));
    }
    Ok(out)
}

/// The `name`s of the `[[bin]]` tables of a manifest.
fn bin_names(manifest: &str) -> Vec<String> {
    let mut names = Vec::new();
    let mut in_bin = false;
    for line in manifest.lines().map(str::trim) {
        if line.starts_with('[') {
            in_bin = line == "[[bin]]";
        } else if let Some(v) = line.strip_prefix("name").filter(|_| in_bin) {
            if let Some(v) = v.trim_start().strip_prefix('=') {
                names.push(v.trim().trim_matches('"').to_string());
            }
        }
    }
    names
}

/// `cargo fuzz` under [`TOOLCHAIN`], run from the crate that holds `workspace` (cargo-fuzz finds
/// its `fuzz/` there).
fn cargo_fuzz(workspace: &str) -> Command {
    let krate = cmd::root().join(workspace);
    let krate = krate.parent().unwrap_or(Path::new("."));
    let mut c = cmd::in_workspace(Command::new("rustup"), krate);
    c.args(["run", TOOLCHAIN, "cargo", "fuzz"])
        // Set by the outer (stable) cargo for its own compiler; nightly's cargo must find its own.
        .env_remove("RUSTC")
        .env_remove("RUSTDOC")
        .env_remove("CARGO");
    c
}

/// Fails with what to do when nightly or cargo-fuzz is missing.
fn check_tools() -> Result<()> {
    let list = cmd::output(Command::new("rustup").args(["toolchain", "list"]))
        .context("rustup not found: install it from https://rustup.rs")?;
    if !list
        .lines()
        .any(|l| l.starts_with(&format!("{TOOLCHAIN}-")))
    {
        bail!("no {TOOLCHAIN} toolchain: run `cargo xtask setup`");
    }
    if cmd::output(Command::new("cargo").args(["fuzz", "--version"])).is_none() {
        bail!("cargo-fuzz is not installed: run `cargo xtask setup`");
    }
    Ok(())
}

/// Builds every target, then runs each for `seconds` (0: its seeds once each); every failure is
/// collected and reported at the end.
pub fn run(seconds: u64) -> Result<()> {
    check_tools()?;
    let targets = targets()?;
    let mut failed = Vec::new();
    for ws in WORKSPACES {
        println!("==> xtask: fuzz: build {ws}");
        if let Err(e) = cmd::run(cargo_fuzz(ws).args(["build", "--dev"])) {
            failed.push(format!("build {ws}: {e:#}"));
        }
    }
    for t in &targets {
        if failed
            .iter()
            .any(|f| f.starts_with(&format!("build {}:", t.workspace)))
        {
            continue;
        }
        println!(
            "==> xtask: fuzz: run {} ({}) for {seconds} s",
            t.name, t.workspace
        );
        if let Err(e) = run_one(t, seconds) {
            failed.push(format!("{} ({}): {e:#}", t.name, t.workspace));
        }
    }
    if !failed.is_empty() {
        bail!("{}", failed.join("; "));
    }
    Ok(())
}

/// The scratch corpus of a target, where libFuzzer writes what it finds.
fn scratch(t: &Target) -> PathBuf {
    let krate = Path::new(t.workspace)
        .parent()
        .and_then(Path::file_name)
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    cmd::target_dir().join("fuzz").join(krate).join(&t.name)
}

fn run_one(t: &Target, seconds: u64) -> Result<()> {
    let corpus = scratch(t);
    std::fs::create_dir_all(&corpus).with_context(|| format!("{}", corpus.display()))?;
    let seeds = cmd::root().join(t.workspace).join("seeds").join(&t.name);
    let mut c = cargo_fuzz(t.workspace);
    // The same (unoptimised, debug-assertions) build as `build --dev` above: nothing compiles again.
    c.args(["run", "--dev", &t.name]).arg(&corpus);
    if seeds.is_dir() {
        c.arg(&seeds);
    }
    c.arg("--");
    if seconds == 0 {
        c.arg("-runs=0");
    } else {
        c.arg(format!("-max_total_time={seconds}"));
    }
    cmd::run(&mut c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bin_names_reads_only_bin_tables() {
        let manifest =
            "[package]\nname = \"x-fuzz\"\n[[bin]]\nname = \"decode\"\npath = \"a.rs\"\n\
                        [dependencies]\nname = 1\n[[bin]]\nname=\"check\"\n";
        assert_eq!(bin_names(manifest), ["decode", "check"]);
    }

    #[test]
    fn every_fuzz_workspace_is_excluded_from_the_host_workspace_and_has_targets() {
        let root = std::fs::read_to_string(cmd::root().join("Cargo.toml")).expect("Cargo.toml");
        let exclude = root
            .lines()
            .find(|l| l.starts_with("exclude"))
            .expect("an exclude line in Cargo.toml");
        for ws in WORKSPACES {
            assert!(
                exclude.contains(&format!("\"{ws}\"")),
                "{ws} not in {exclude}"
            );
        }
        let targets = targets().expect("fuzz targets");
        assert!(targets.iter().any(|t| t.name == "command"));
    }
}
