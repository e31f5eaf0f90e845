//! `cargo xtask lint` and the `lint` stage: formatting, clippy and rustdoc warnings of the host and
//! firmware workspaces, every fuzz target built and run on its seeds, and the declared MSRV (nothing to do while it is the pinned toolchain's
//! version). Every step runs; their failures are reported together.
//!
//! Cheap by construction: clippy and rustdoc build dependencies as metadata only and share it
//! (rustdoc `--no-deps` documents only our crates), and the firmware is linted in the `release`
//! profile its stage builds, so embassy's build scripts run once for both.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::{bail, Context, Result};

use crate::{cmd, fuzz, setup};

/// One cargo invocation of the lint.
pub struct Step {
    /// Its name in the log and in failures.
    pub what: &'static str,
    /// The workspace it runs in, relative to the root (`.` is the host workspace; any other is a
    /// workspace of its own, see [`cmd::in_workspace`]).
    pub dir: &'static str,
    /// Cargo's arguments.
    pub args: &'static [&'static str],
    /// Extra environment.
    pub env: &'static [(&'static str, &'static str)],
}

const DENY: [&str; 3] = ["--", "-D", "warnings"];

/// Every step but the MSRV check, in run order (formatting first: it costs nothing).
pub const STEPS: &[Step] = &[
    Step {
        what: "fmt: host workspace",
        dir: ".",
        args: &["fmt", "--all", "--check"],
        env: &[],
    },
    Step {
        what: "fmt: firmware",
        dir: "crates/sc-fw",
        args: &["fmt", "--check"],
        env: &[],
    },
    Step {
        what: "fmt: firmware host tests",
        dir: "crates/sc-fw/host-tests",
        args: &["fmt", "--check"],
        env: &[],
    },
    Step {
        what: "fmt: Cortex-M4 tests",
        dir: "crates/sc-fw/mcu-tests",
        args: &["fmt", "--check"],
        env: &[],
    },
    Step {
        what: "fmt: protocol fuzz targets",
        dir: "crates/ihex-proto/fuzz",
        args: &["fmt", "--check"],
        env: &[],
    },
    Step {
        what: "fmt: image fuzz targets",
        dir: "crates/ihex-image/fuzz",
        args: &["fmt", "--check"],
        env: &[],
    },
    Step {
        what: "fmt: gateway core fuzz targets",
        dir: "crates/ihex-gateway-core/fuzz",
        args: &["fmt", "--check"],
        env: &[],
    },
    // The SocketCAN tests of ihex-tests are compiled only with its `vcan` feature, the TLS and
    // bridge tests only with `tls`.
    Step {
        what: "clippy: host workspace",
        dir: ".",
        args: &[
            "clippy",
            "--keep-going",
            "--workspace",
            "--all-targets",
            "--features",
            "ihex-tests/vcan,ihex-tests/tls",
            DENY[0],
            DENY[1],
            DENY[2],
        ],
        env: &[],
    },
    Step {
        what: "rustdoc: host workspace",
        dir: ".",
        args: &["doc", "--keep-going", "--workspace", "--no-deps"],
        env: &[("RUSTDOCFLAGS", "-D warnings")],
    },
    Step {
        what: "clippy: firmware",
        dir: "crates/sc-fw",
        args: &[
            "clippy",
            "--keep-going",
            "--release",
            "--all-targets",
            DENY[0],
            DENY[1],
            DENY[2],
        ],
        env: &[],
    },
    Step {
        what: "clippy: firmware host tests",
        dir: "crates/sc-fw/host-tests",
        args: &[
            "clippy",
            "--keep-going",
            "--all-targets",
            DENY[0],
            DENY[1],
            DENY[2],
        ],
        env: &[],
    },
    Step {
        what: "clippy: Cortex-M4 tests",
        dir: "crates/sc-fw/mcu-tests",
        args: &[
            "clippy",
            "--keep-going",
            "--release",
            "--all-targets",
            DENY[0],
            DENY[1],
            DENY[2],
        ],
        env: &[],
    },
];

/// Runs every step and the MSRV check; fails naming each step that failed.
pub fn run() -> Result<()> {
    let root = cmd::root();
    let mut failed = Vec::new();
    for step in STEPS {
        let dir = root.join(step.dir);
        if !dir.join("Cargo.toml").exists() {
            println!(
                "==> xtask: lint: {}: skipped (no {}/Cargo.toml)",
                step.what, step.dir
            );
            continue;
        }
        println!("==> xtask: lint: {}", step.what);
        let mut c = if step.dir == "." {
            let mut c = cmd::cargo();
            c.current_dir(&dir);
            c
        } else {
            cmd::cargo_in(&dir)
        };
        c.args(step.args).envs(step.env.iter().copied());
        if let Err(e) = cmd::run(&mut c) {
            println!("==> xtask: lint: {} FAILED: {e:#}", step.what);
            failed.push(step.what.to_string());
        }
    }
    println!("==> xtask: lint: fuzz targets (built with nightly, each run on its seeds)");
    if let Err(e) = fuzz::run(0) {
        println!("==> xtask: lint: fuzz targets FAILED: {e:#}");
        failed.push("fuzz targets".to_string());
    }
    println!("==> xtask: lint: MSRV");
    if let Err(e) = msrv() {
        println!("==> xtask: lint: MSRV FAILED: {e:#}");
        failed.push("MSRV".to_string());
    }
    if !failed.is_empty() {
        bail!("{}", failed.join(", "));
    }
    Ok(())
}

/// Targets the MSRV toolchain needs besides the host: the firmware's.
pub const MSRV_TARGETS: [&str; 1] = ["thumbv7em-none-eabihf"];

/// The declared `rust-version` when it is older than the pinned toolchain (rust-toolchain.toml),
/// so that it needs a check of its own; `None` when they are the same version, which every stage
/// already builds with.
pub fn msrv_below_pinned() -> Result<Option<String>> {
    let declared = declared_msrv()?;
    let rustc = cmd::output(
        Command::new("rustc")
            .arg("--version")
            .current_dir(cmd::root()),
    )
    .context("`rustc --version` failed")?;
    // `rustc 1.95.0 (59807616e 2026-04-14)` against `1.95` or `1.95.0`.
    let pinned = rustc.split_whitespace().nth(1).unwrap_or_default();
    let same = pinned == declared || pinned.strip_prefix(&format!("{declared}.")).is_some();
    Ok((!same).then_some(declared))
}

/// `cargo check` with the toolchain of the declared `rust-version` (installed when missing) of the
/// host workspace's libraries and binaries (what its users build; tests and dev-dependencies are
/// ours) and of the firmware, which declares the same version — when that version is not the
/// pinned toolchain every stage builds with anyway. In `target/msrv` of each: nothing built by
/// another compiler can be reused.
fn msrv() -> Result<()> {
    let Some(version) = msrv_below_pinned()? else {
        println!(
            "xtask: lint: the declared MSRV is the pinned toolchain (rust-toolchain.toml): every \
             stage builds with it, nothing more to check"
        );
        return Ok(());
    };
    setup::toolchain(&version, &MSRV_TARGETS)?;
    let check = |dir: &Path, target: PathBuf, args: &[&str]| {
        let mut c = cmd::in_workspace(Command::new("rustup"), dir);
        c.args([
            "run",
            &version,
            "cargo",
            "check",
            "--locked",
            "--keep-going",
        ])
        .args(args)
        .env("CARGO_TARGET_DIR", target)
        // Set by the outer cargo for its own compiler; the MSRV cargo must find its own.
        .env_remove("RUSTC")
        .env_remove("RUSTDOC");
        cmd::run(&mut c)
    };
    let root = cmd::root();
    let mut failed = Vec::new();
    if let Err(e) = check(&root, cmd::target_dir().join("msrv"), &["--workspace"]) {
        failed.push(format!("host workspace: {e:#}"));
    }
    // The release profile the firmware stage builds (its build scripts' settings).
    let fw = root.join(cmd::FIRMWARE);
    if let Err(e) = check(&fw, fw.join("target/msrv"), &["--release"]) {
        failed.push(format!("firmware: {e:#}"));
    }
    if !failed.is_empty() {
        bail!(
            "does not build with the declared MSRV {version}: {}",
            failed.join("; ")
        );
    }
    Ok(())
}

/// The host workspace's `rust-version`: the one every member declares (a tidy test checks they
/// all inherit the workspace's).
pub fn declared_msrv() -> Result<String> {
    let out = cmd::output(cmd::cargo().current_dir(cmd::root()).args([
        "metadata",
        "--no-deps",
        "--format-version",
        "1",
    ]))
    .context("`cargo metadata` failed")?;
    let meta: serde_json::Value = serde_json::from_str(&out).context("parsing cargo metadata")?;
    let mut versions: Vec<&str> = meta["packages"]
        .as_array()
        .map(|ps| {
            ps.iter()
                .filter_map(|p| p["rust_version"].as_str())
                .collect()
        })
        .unwrap_or_default();
    versions.sort_unstable();
    versions.dedup();
    match versions.as_slice() {
        [one] => Ok((*one).to_string()),
        [] => bail!("no package of the workspace declares a rust-version"),
        many => bail!(
            "the workspace's packages declare different rust-versions: {}",
            many.join(", ")
        ),
    }
}
