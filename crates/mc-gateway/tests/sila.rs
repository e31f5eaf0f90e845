//! The SiLA 2 server as the reference client sees it: PyPI's `sila2` (tests/sila/reference_client.py)
//! checks the feature definitions (valid against `FeatureDefinition.xsd`, the protos what SiLA's own
//! transform makes of them), then drives the `mc-gateway` demo binary (embedded broker, simulated
//! island): discovery over mDNS (on loopback), `SiLAService`, its dynamic client built from the served definitions, `SetLight` with the
//! `command_result` it gives on MQTT, the documented errors, the `Dockings` stream over a dock and an
//! undock through `ihex/sim`, a `LockController` lock that SiLA and MQTT commands honour, and after a restart the same UUID and the name it set — all over TLS,
//! trusting the self-signed certificate the gateway made at its first start (a plaintext client is
//! refused).
//!
//! Ignored by `cargo test` (it needs the Python environment); the host stage of `cargo xtask test`
//! makes `target/venv` with `tests/sila/requirements.txt` and runs it with `--ignored`
//! (`IHEX_SILA_PYTHON` names another Python). When it ran to its end it writes
//! `target/sila/passed`, which the host stage checks.
#![cfg(all(feature = "demo", feature = "sila"))]

use std::{
    io::{BufRead, BufReader},
    path::{Path, PathBuf},
    process::{Child, Command, Output, Stdio},
    time::{Duration, Instant},
};

use ihex_tests::net::free_port;

const BIN: &str = env!("CARGO_BIN_EXE_mc-gateway");

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// `target/` (or `CARGO_TARGET_DIR`).
fn target_dir() -> PathBuf {
    std::env::var_os("CARGO_TARGET_DIR")
        .map(|d| root().join(d))
        .unwrap_or_else(|| root().join("target"))
}

/// The Python with `sila2`: `IHEX_SILA_PYTHON`, else the environment `cargo xtask test` makes.
fn python() -> PathBuf {
    let p = std::env::var_os("IHEX_SILA_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| target_dir().join("venv/bin/python"));
    assert!(
        p.is_file(),
        "{} not found: `cargo xtask test` makes it (or set IHEX_SILA_PYTHON to a Python with \
         crates/mc-gateway/tests/sila/requirements.txt installed)",
        p.display()
    );
    p
}

/// A child process killed on drop.
struct Process(Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The demo gateway with its SiLA server on `sila`, its state in `state`; returned once it runs.
fn gateway(state: &Path, broker: u16, sila: u16) -> Process {
    let mut cmd = Command::new(BIN);
    cmd.args(["--broker-listen", &format!("127.0.0.1:{broker}")])
        .args(["--sila", &format!("127.0.0.1:{sila}")])
        .args([
            "--http",
            "off",
            "--log-dir",
            "-",
            "--health-period-ms",
            "250",
        ])
        .env("XDG_STATE_HOME", state)
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("IHEX_") {
            cmd.env_remove(k);
        }
    }
    let mut gw = Process(cmd.spawn().unwrap());
    for line in BufReader::new(gw.0.stdout.take().unwrap()).lines() {
        if line.unwrap().contains("Ctrl-C stops the gateway") {
            break;
        }
    }
    gw
}

/// How long one run of the reference client may take (each takes seconds): a client that hangs
/// is killed, and the test fails with what it printed so far instead of holding CI up.
const CLIENT_LIMIT: Duration = Duration::from_secs(300);

/// Runs the reference client script with `args`; its output, after it succeeded.
fn client(args: &[&str]) -> String {
    let script = root().join("crates/mc-gateway/tests/sila/reference_client.py");
    // Unbuffered (-u), so that a killed client's output so far is in the pipes.
    let mut child = Command::new(python())
        .arg("-u")
        .arg(script)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + CLIENT_LIMIT;
    let mut killed = false;
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            killed = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let Output {
        status,
        stdout,
        stderr,
    } = child.wait_with_output().unwrap();
    let out = String::from_utf8_lossy(&stdout).into_owned();
    println!("{out}");
    assert!(
        !killed,
        "reference client {args:?} still running after {CLIENT_LIMIT:?}, killed; its output:\n{out}\n{}",
        String::from_utf8_lossy(&stderr)
    );
    assert!(
        status.success(),
        "reference client {args:?} failed:\n{out}\n{}",
        String::from_utf8_lossy(&stderr)
    );
    out
}

/// Two images of the simulated firmware, written to `dir`: a small one (updated to its end) and
/// a large one (cancelled); the reference client uploads them over MQTT and updates 111 and 112.
fn firmware(dir: &Path, ca: &str, broker: u16, sila: u16) {
    let key = ihex_image::SigningKey::test_key();
    let write = |name: &str, version, len| {
        let firmware = ihex_image::sim::SimFirmware { confirms: true };
        let image = ihex_image::sim::sim_image(version, firmware, len, &key).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, image).unwrap();
        path.to_str().unwrap().to_owned()
    };
    let small = write(
        "sila-9.0.0.img",
        ihex_image::FirmwareVersion::new(9, 0, 0),
        4 * 1024,
    );
    let big = write(
        "sila-9.1.0.img",
        ihex_image::FirmwareVersion::new(9, 1, 0),
        120 * 1024,
    );
    client(&[
        "firmware",
        "127.0.0.1",
        &sila.to_string(),
        ca,
        &broker.to_string(),
        &small,
        &big,
    ]);
}

#[test]
#[ignore = "needs the Python environment with sila2 (cargo xtask test makes it)"]
fn the_reference_client_drives_the_island() {
    let sila_dir = root().join("crates/mc-gateway/sila");
    let sila_dir = sila_dir.to_str().unwrap();
    client(&["definitions", sila_dir]);

    let state = tempfile::tempdir().unwrap();
    let (broker, sila) = (free_port(), free_port());
    let name = "Bench A (SiLA test)";
    let gw = gateway(state.path(), broker, sila);
    // The self-signed certificate the gateway made at its first start: what clients trust.
    let ca = state.path().join("ihex/sila-cert.pem");
    let ca = ca.to_str().unwrap();
    let identity: serde_json::Value =
        serde_json::from_slice(&std::fs::read(state.path().join("ihex/sila.json")).unwrap())
            .unwrap();
    let uuid = identity["uuid"].as_str().unwrap();
    client(&[
        "first",
        "127.0.0.1",
        &sila.to_string(),
        ca,
        &broker.to_string(),
        sila_dir,
        name,
        uuid,
    ]);
    firmware(state.path(), ca, broker, sila);
    drop(gw);

    let cert = std::fs::read(ca).unwrap();
    let _gw = gateway(state.path(), broker, sila);
    assert_eq!(
        std::fs::read(ca).unwrap(),
        cert,
        "the certificate is kept, so clients that trust it keep trusting the server"
    );
    client(&["again", "127.0.0.1", &sila.to_string(), ca, uuid, name]);

    let passed = target_dir().join("sila/passed");
    std::fs::create_dir_all(passed.parent().unwrap()).unwrap();
    std::fs::write(passed, "ok\n").unwrap();
}
