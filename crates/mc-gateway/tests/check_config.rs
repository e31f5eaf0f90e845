//! `mc-gateway --check-config` as a person runs it: a good file prints every option with its value
//! and where it came from (flag, environment variable, file and key, default) and exits 0; a bad
//! value, whether from the file, the environment or a flag, is named by where it was given and
//! what is accepted, and exits 1; files the configuration names are checked too.

use std::process::{Command, Output};

const BIN: &str = env!("CARGO_BIN_EXE_mc-gateway");

/// Runs the binary with `args` and exactly the `IHEX_*` variables of `env`.
fn run(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut cmd = Command::new(BIN);
    cmd.args(args);
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("IHEX_") {
            cmd.env_remove(k);
        }
    }
    cmd.envs(env.iter().copied());
    cmd.output().unwrap()
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// The report's row of `flag`: its value and origin columns, whitespace collapsed.
fn row(report: &str, flag: &str) -> String {
    report
        .lines()
        .find(|l| l.split_whitespace().next() == Some(flag))
        .unwrap_or_else(|| panic!("no row for {flag}:\n{report}"))
        .split_whitespace()
        .skip(1)
        .collect::<Vec<_>>()
        .join(" ")
}

#[test]
fn a_good_configuration_is_reported_with_every_origin() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("gw.toml");
    std::fs::write(
        &file,
        "broker = \"lab-broker:1884\"\nlost_after = 5\nkeep_alive = 60\npassword = \"s3cret\"\nusername = \"gw\"\n",
    )
    .unwrap();
    let f = file.to_str().unwrap();
    let out = run(
        &[
            "--check-config",
            "--config",
            f,
            "--can",
            "vcan0",
            "--log-dir",
            "-",
        ],
        &[("IHEX_KEEP_ALIVE", "30")],
    );
    let report = text(&out.stdout);
    assert!(out.status.success(), "{report}{}", text(&out.stderr));
    assert_eq!(row(&report, "--can"), "vcan0 flag --can");
    assert_eq!(
        row(&report, "--broker"),
        format!("lab-broker:1884 file {f}, key broker")
    );
    assert_eq!(
        row(&report, "--lost-after"),
        format!("5 file {f}, key lost_after")
    );
    // The environment is above the file.
    assert_eq!(
        row(&report, "--keep-alive"),
        "30 environment variable IHEX_KEEP_ALIVE"
    );
    assert_eq!(row(&report, "--bitrate"), "500000 default");
    assert_eq!(
        row(&report, "--password"),
        format!("(set, hidden) file {f}, key password")
    );
    assert!(!report.contains("s3cret"), "{report}");
    assert!(
        report.contains("resolved: broker lab-broker:1884; CAN SocketCAN vcan0;"),
        "{report}"
    );
    assert!(report.ends_with("configuration OK\n"), "{report}");
}

/// Runs `--check-config` expecting exit status 1 and exactly `error` as stderr's last line.
fn refused(args: &[&str], env: &[(&str, &str)], error: &str) {
    let mut all = vec!["--check-config"];
    all.extend_from_slice(args);
    let out = run(&all, env);
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{args:?} {env:?}: {err}");
    assert_eq!(err.trim_end(), error, "{args:?} {env:?}");
}

#[test]
fn bad_values_are_named_by_where_they_were_given_and_what_is_accepted() {
    let dir = tempfile::tempdir().unwrap();
    let file = |name: &str, body: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, body).unwrap();
        p.to_str().unwrap().to_owned()
    };
    let range = file("range.toml", "lost_after = 0\n");
    refused(
        &["--config", &range],
        &[],
        &format!(
            "mc-gateway: invalid file {range}, key lost_after: 0 is not in the range 1 to 1000"
        ),
    );
    let typed = file("typed.toml", "lost_after = \"three\"\n");
    refused(
        &["--config", &typed],
        &[],
        &format!(
            "mc-gateway: invalid file {typed}, key lost_after: \"three\" is not a whole number from 1 to 1000"
        ),
    );
    let unknown = file("unknown.toml", "brokr = \"h\"\n");
    refused(
        &["--config", &unknown],
        &[],
        &format!(
            "mc-gateway: invalid file {unknown}, key brokr: unknown key `brokr`: not an option (the keys are the long flags with `_` for `-`, listed in docs/gateway.md)"
        ),
    );
    let choice = file("choice.toml", "log_rotation = \"weekly\"\n");
    refused(
        &["--config", &choice],
        &[],
        &format!(
            "mc-gateway: invalid file {choice}, key log_rotation: \"weekly\" is not minutely, hourly, daily or never"
        ),
    );
    refused(
        &[],
        &[("IHEX_LOST_AFTER", "abc")],
        "mc-gateway: invalid environment variable IHEX_LOST_AFTER: \"abc\" is not a whole number from 1 to 1000",
    );
    refused(
        &[],
        &[("IHEX_KEEP_ALIVE", "4")],
        "mc-gateway: invalid environment variable IHEX_KEEP_ALIVE: 4 is not in the range 5 to 3600",
    );
    refused(
        &["--keep-alive", "1"],
        &[("IHEX_KEEP_ALIVE", "30")],
        "mc-gateway: invalid flag --keep-alive: 1 is not in the range 5 to 3600",
    );
    refused(
        &["--broker-listen", "nowhere"],
        &[],
        "mc-gateway: invalid flag --broker-listen: \"nowhere\" is not an address ADDR:PORT (e.g. 127.0.0.1:1883 or [::1]:1883)",
    );
    refused(
        &["--tls=maybe"],
        &[],
        "mc-gateway: invalid flag --tls: \"maybe\" is not true or false",
    );
}

#[test]
fn files_the_configuration_names_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let not_a_dir = dir.path().join("file");
    std::fs::write(&not_a_dir, "x").unwrap();
    let missing = dir.path().join("missing");
    let out = run(
        &[
            "--check-config",
            "--broker",
            "h",
            "--can",
            "vcan0",
            "--fw-dir",
            missing.to_str().unwrap(),
            "--log-dir",
            not_a_dir.join("logs").to_str().unwrap(),
        ],
        &[],
    );
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains(&format!(
            "flag --fw-dir: {} is not a directory",
            missing.display()
        )),
        "{err}"
    );
    assert!(
        err.contains(&format!(
            "flag --log-dir: {} cannot be created: {} is not a directory",
            not_a_dir.join("logs").display(),
            not_a_dir.display()
        )),
        "{err}"
    );
    let out = run(
        &["--check-config", "--island-file", missing.to_str().unwrap()],
        &[],
    );
    let err = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("flag --island-file: "), "{err}");
    assert!(err.contains(&missing.display().to_string()), "{err}");
}
