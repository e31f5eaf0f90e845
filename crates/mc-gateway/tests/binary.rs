//! The `mc-gateway` binary itself: `--help`, a bad option, and a demo run stopped with SIGTERM that
//! exits 0, announces `offline` and leaves a JSON-lines log file.
#![cfg(feature = "demo")]

use std::{
    ffi::OsStr,
    io::{BufRead, BufReader},
    net::TcpListener,
    path::Path,
    process::{Command, Stdio},
    time::{Duration, Instant},
};

const BIN: &str = env!("CARGO_BIN_EXE_mc-gateway");

#[test]
fn help_explains_the_options_and_lab_defaults() {
    let out = Command::new(BIN).arg("--help").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    for needle in [
        "--broker",
        "192.168.1.101:1883",
        "--can",
        "can0",
        "--island",
        "IHEX_BROKER",
    ] {
        assert!(text.contains(needle), "--help lacks {needle}");
    }
}

#[test]
fn a_bad_option_value_fails_with_its_name() {
    let out = Command::new(BIN)
        .args(["--lost-after", "0", "--log-dir", "-"])
        .env_remove("IHEX_CONFIG")
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("lost-after"), "{err}");
}

/// A demo run of the binary: started on a free port, stopped with SIGTERM.
struct DemoRun {
    child: std::process::Child,
    port: u16,
    /// Everything printed on stdout up to the end of the banner.
    banner: String,
}

impl DemoRun {
    /// Starts `mc-gateway` with `args`, in `dir` (when given), with `env` set and every `IHEX_*`
    /// variable of this process removed; returns once the banner is printed.
    fn start(args: &[&str], dir: Option<&Path>, env: &[(&str, &OsStr)]) -> DemoRun {
        DemoRun::start_with_stderr(args, dir, env, Stdio::null())
    }

    /// [`DemoRun::start`] with stderr going to `stderr`.
    fn start_with_stderr(
        args: &[&str],
        dir: Option<&Path>,
        env: &[(&str, &OsStr)],
        stderr: Stdio,
    ) -> DemoRun {
        let port = TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let mut cmd = Command::new(BIN);
        cmd.args(["--broker-listen", &format!("127.0.0.1:{port}")])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(stderr);
        for (k, _) in std::env::vars_os() {
            if k.to_string_lossy().starts_with("IHEX_") {
                cmd.env_remove(k);
            }
        }
        for (k, v) in env {
            cmd.env(k, v);
        }
        if let Some(dir) = dir {
            cmd.current_dir(dir);
        }
        let mut child = cmd.spawn().unwrap();
        // The banner is printed once broker, island and tasks run.
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let deadline = Instant::now() + Duration::from_secs(30);
        let mut banner = String::new();
        for line in lines.by_ref() {
            let line = line.unwrap();
            banner.push_str(&line);
            banner.push('\n');
            if line.contains("Ctrl-C stops the gateway") || Instant::now() > deadline {
                break;
            }
        }
        DemoRun {
            child,
            port,
            banner,
        }
    }

    /// SIGTERM, and the exit status.
    fn stop(mut self) -> std::process::ExitStatus {
        // SAFETY: plain kill(2) on our own child's pid.
        assert_eq!(
            unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) },
            0
        );
        self.child.wait().unwrap()
    }
}

/// The JSON-lines records of the one log file in `dir` (the state directory also holds the SiLA
/// server's identity and certificate).
fn log_records(dir: &Path) -> (String, Vec<serde_json::Value>) {
    let files: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "jsonl"))
        .collect();
    assert_eq!(files.len(), 1, "{files:?}");
    let text = std::fs::read_to_string(&files[0]).unwrap();
    let records = text
        .lines()
        .map(|l| serde_json::from_str(l).expect("every line is JSON"))
        .collect();
    (text, records)
}

/// A failure is said once, on one line: no `Error:` then `Caused by:` repeating it.
#[test]
fn an_error_is_printed_once() {
    let out = Command::new(BIN)
        .args(["--config", "/nonexistent/gateway.toml"])
        .env_remove("IHEX_CONFIG")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        err,
        "mc-gateway: cannot read config file /nonexistent/gateway.toml: \
         No such file or directory (os error 2)\n"
    );
}

#[test]
fn sigterm_stops_the_demo_cleanly_and_flushes_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let log_dir = dir.path().to_str().unwrap();
    let demo = DemoRun::start(&["--log-dir", log_dir], None, &[]);
    let port = demo.port;
    let demo_banner = demo.banner.clone();
    assert!(
        demo.banner
            .contains(&format!("mosquitto_pub -h 127.0.0.1 -p {}", demo.port)),
        "{}",
        demo.banner
    );
    let pid = demo.child.id();
    // Let the MQTT task connect before asking it to say goodbye.
    std::thread::sleep(Duration::from_millis(500));
    let status = demo.stop();
    assert!(status.success(), "exit status {status}");
    let (text, records) = log_records(dir.path());
    // Where the log is, said in the banner and in the log itself; whose lines they are, in each.
    let file = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e == "jsonl"))
        .expect("the log file");
    assert!(
        demo_banner.contains(&format!(
            "The JSON log: {} (this gateway's lines have \"pid\":{pid}).",
            file.display()
        )),
        "{demo_banner}"
    );
    assert_eq!(
        records[0]["fields"]["file"],
        file.display().to_string(),
        "the first line names the file: {text}"
    );
    assert!(
        records.iter().all(|r| r["pid"] == pid),
        "a line without pid {pid}: {text}"
    );
    let said = |m: &str| records.iter().any(|r| r["fields"]["message"] == m);
    // Start-up lines say what a person reads, not Rust's Debug of the configuration.
    let running = records
        .iter()
        .find(|r| r["fields"]["message"] == "gateway running")
        .unwrap_or_else(|| panic!("{text}"));
    assert_eq!(running["fields"]["link"], "simulated island (built in)");
    assert_eq!(
        running["fields"]["broker"],
        format!("embedded broker on 127.0.0.1:{port}")
    );
    assert_eq!(running["fields"]["island"], "none");
    for debug in ["None", "Some(", "Simulated {", "Embedded {"] {
        assert!(!text.contains(debug), "{debug} in the log:\n{text}");
    }
    assert!(said("published offline and disconnected"), "{text}");
    assert!(said("gateway stopped"), "the last line was flushed: {text}");
}

/// A fatal start-up error (the embedded broker's port is taken) is the first thing the gateway says
/// and the JSON log's last line: the island does not boot and nothing else is started before it.
#[test]
fn a_fatal_start_up_error_comes_first_and_is_logged() {
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = taken.local_addr().unwrap().to_string();
    let dir = tempfile::tempdir().unwrap();
    let mut cmd = Command::new(BIN);
    cmd.args(["--broker-listen", &addr, "--http", "off", "--log-dir"])
        .arg(dir.path());
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("IHEX_") {
            cmd.env_remove(k);
        }
    }
    let out = cmd.output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    let why = format!("cannot listen on {addr} for the embedded broker");
    // Said once on stderr, as the one line main prints (not a second time by the log).
    assert_eq!(stderr.matches(&why).count(), 1, "{stderr}");
    assert!(
        stderr.lines().last().unwrap().starts_with("mc-gateway: "),
        "{stderr}"
    );
    let (text, records) = log_records(dir.path());
    let last = records.last().unwrap();
    assert_eq!(last["level"], "ERROR", "{text}");
    assert_eq!(last["fields"]["message"], "the gateway stopped on an error");
    assert!(
        last["fields"]["error"].as_str().unwrap().contains(&why),
        "{text}"
    );
    // Nothing but the log's own first line before it: no island boot, no warning.
    assert_eq!(records.len(), 2, "{text}");
    assert!(!text.contains("simulated island started"), "{text}");
}

fn git(dir: &Path, args: &[&str]) -> String {
    let out = Command::new("git")
        .args([
            "-c",
            "user.name=ihex-test",
            "-c",
            "user.email=test@ihex.invalid",
        ])
        .args(args)
        .current_dir(dir)
        .output()
        .expect("git is installed");
    assert!(
        out.status.success(),
        "git {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The demo started from inside a work tree (a copy of the repository's top files) writes nothing
/// there: `git status` stays clean, and the JSON log is in the state directory under `$HOME`.
#[test]
fn a_demo_run_leaves_the_work_tree_clean() {
    let tree = tempfile::tempdir().unwrap();
    let home = tempfile::tempdir().unwrap();
    let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    for f in ["Cargo.toml", "README.md"] {
        std::fs::copy(repo.join(f), tree.path().join(f)).unwrap();
    }
    git(tree.path(), &["init", "-q"]);
    git(tree.path(), &["add", "."]);
    git(
        tree.path(),
        &["commit", "-q", "-m", "a copy of the repository"],
    );
    let demo = DemoRun::start(
        &[],
        Some(tree.path()),
        &[
            ("HOME", home.path().as_os_str()),
            ("XDG_STATE_HOME", OsStr::new("")),
        ],
    );
    std::thread::sleep(Duration::from_millis(500));
    assert!(demo.stop().success());
    assert_eq!(
        git(tree.path(), &["status", "--porcelain", "--ignored"]),
        ""
    );
    let (_, records) = log_records(&home.path().join(".local/state/ihex"));
    assert!(records
        .iter()
        .any(|r| r["fields"]["message"] == "gateway stopped"));
}

/// Redirected to a file, stderr carries no terminal escape codes (colour is for terminals only).
#[test]
fn a_redirected_run_has_no_escape_codes() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("stderr.txt");
    let file = std::fs::File::create(&path).unwrap();
    let demo = DemoRun::start_with_stderr(&["--log-dir", "-"], None, &[], Stdio::from(file));
    std::thread::sleep(Duration::from_millis(300));
    assert!(demo.stop().success());
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains("gateway running"), "{text}");
    assert!(
        !text.contains('\x1b'),
        "escape codes in a redirected log:\n{text:?}"
    );
}

/// Half a lab configuration works, and says which lab default it used.
#[test]
fn a_can_interface_alone_warns_that_the_lab_broker_is_used() {
    let mut child = Command::new(BIN)
        .args(["--can", "ihexnone0", "--log-dir", "-"])
        .env_remove("IHEX_CONFIG")
        .env_remove("IHEX_BROKER")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = BufReader::new(child.stderr.take().unwrap());
    let warned = stderr.lines().map_while(Result::ok).find(|l| {
        l.contains("WARN")
            && l.contains(
                "no broker configured (--broker): using the lab broker 192.168.1.101:1883",
            )
    });
    // SAFETY: plain kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    child.wait().unwrap();
    assert!(warned.is_some(), "no warning naming the lab broker");
}

/// A broker nobody listens on is a warning at the default log level that names it and what to
/// check (it was a debug line: the gateway said "running" and then nothing).
#[test]
fn an_unreachable_broker_is_a_warning_at_the_default_level() {
    // A port that was free a moment ago: nothing accepts connections there.
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let broker = format!("127.0.0.1:{port}");
    let mut child = Command::new(BIN)
        .args(["--can", "ihexnone0", "--broker", &broker, "--log-dir", "-"])
        .env_remove("IHEX_CONFIG")
        .env_remove("RUST_LOG")
        .env_remove("IHEX_LOG")
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stderr = BufReader::new(child.stderr.take().unwrap());
    let want = format!("nothing accepts connections at {broker}");
    let warned = stderr
        .lines()
        .map_while(Result::ok)
        .find(|l| l.contains("WARN") && l.contains(&want) && l.contains("--broker"));
    // SAFETY: plain kill(2) on our own child's pid.
    assert_eq!(unsafe { libc::kill(child.id() as i32, libc::SIGTERM) }, 0);
    child.wait().unwrap();
    assert!(warned.is_some(), "no warning naming the unreachable broker");
}

/// Every event the gateway publishes is also a line of its JSON log, at info, with the payload as
/// published: command answers, rejections, the node list and the simulator's answers included.
#[test]
fn every_published_event_is_in_the_json_log() {
    use rumqttc::{Client, Event, Incoming, MqttOptions, QoS};
    let dir = tempfile::tempdir().unwrap();
    let demo = DemoRun::start(&["--log-dir", dir.path().to_str().unwrap()], None, &[]);
    let mut o = MqttOptions::new("log-test", "127.0.0.1", demo.port);
    o.set_keep_alive(Duration::from_secs(5));
    let (client, mut connection) = Client::new(o, 16);
    let (tx, rx) = std::sync::mpsc::channel();
    let sub = client.clone();
    std::thread::spawn(move || {
        for ev in connection.iter() {
            match ev {
                Ok(Event::Incoming(Incoming::ConnAck(_))) => {
                    let _ = sub.try_subscribe("EventsTopic", QoS::AtLeastOnce);
                    // The gateway publishes `online` after subscribing the command topic.
                    let _ = sub.try_subscribe("ihex/gateway/availability", QoS::AtLeastOnce);
                }
                Ok(Event::Incoming(Incoming::SubAck(_))) => {
                    let _ = tx.send(None);
                }
                Ok(Event::Incoming(Incoming::Publish(p))) => {
                    let payload = String::from_utf8_lossy(&p.payload).into_owned();
                    if tx.send(Some((p.topic, payload))).is_err() {
                        return;
                    }
                }
                Ok(_) => {}
                Err(_) => std::thread::sleep(Duration::from_millis(50)),
            }
        }
    });
    assert_eq!(
        rx.recv_timeout(Duration::from_secs(20)),
        Ok(None),
        "subscribed"
    );
    // Commands published before the gateway subscribed would be lost: wait for its `online`.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let left = deadline
            .checked_duration_since(Instant::now())
            .expect("the gateway online in time");
        if let Ok(Some((_, p))) = rx.recv_timeout(left) {
            if p == "online" {
                break;
            }
        }
    }
    let sends = [
        (
            "CommandsTopic",
            r#"{"cmd":"led","node":"111","color":"red","request_id":"a"}"#,
        ),
        (
            "CommandsTopic",
            r#"{"cmd":"led","node":"111","colour":"red","request_id":"b"}"#,
        ),
        ("CommandsTopic", r#"{"cmd":"list","request_id":"c"}"#),
        (
            "ihex/sim",
            r#"{"sim":"dock","mobile":"3","static":"112","port":2}"#,
        ),
        (
            "ihex/sim",
            r#"{"sim":"dock","mobile":"9","static":"112","port":2}"#,
        ),
    ];
    for (topic, payload) in sends {
        client
            .publish(topic, QoS::AtLeastOnce, false, payload)
            .unwrap();
    }
    // command_result, command_rejected, node_list, new_connection, two sim_results at least.
    let mut seen = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(20);
    let wanted = [
        "command_result",
        "command_rejected",
        "node_list",
        "new_connection",
        "sim_result",
    ];
    while !wanted.iter().all(|w| {
        seen.iter()
            .any(|e: &String| e.contains(&format!("\"event\":\"{w}\"")))
    }) {
        let left = deadline
            .checked_duration_since(Instant::now())
            .expect("the answers in time");
        if let Ok(Some((topic, e))) = rx.recv_timeout(left) {
            if topic == "EventsTopic" {
                seen.push(e);
            }
        }
    }
    // A quiet moment for whatever else is on its way, then stop: the log is flushed at exit.
    std::thread::sleep(Duration::from_millis(300));
    while let Ok(Some((topic, e))) = rx.try_recv() {
        // The availability topic is not an event (the broker may deliver `online` twice: retained
        // on subscription and live, when the two cross).
        if topic == "EventsTopic" {
            seen.push(e);
        }
    }
    assert!(demo.stop().success());
    let (text, records) = log_records(dir.path());
    let logged: Vec<&str> = records
        .iter()
        .filter(|r| r["level"] == "INFO" && r["fields"]["message"] == "event published")
        .filter_map(|r| r["fields"]["payload"].as_str())
        .collect();
    for e in &seen {
        assert!(
            logged.contains(&e.as_str()),
            "published but not logged: {e}\nlog:\n{text}"
        );
    }
}
