//! The metrics as a real Prometheus server sees them: Debian's `prometheus` scrapes the
//! `mc-gateway` demo binary (embedded broker, simulated island) once a second; after the island
//! booted and three LED commands succeeded over MQTT, the server's HTTP API must return the
//! `ihex_` series with the right values, every PromQL expression of the shipped Grafana dashboard
//! (`deploy/grafana/ihex-gateway.json`) must return data, and `promtool check metrics` must
//! accept the exposition.
//!
//! Ignored by `cargo test` (it needs `prometheus` and `promtool`); the host stage of
//! `cargo xtask test` runs it with `--ignored` and `cargo xtask setup` installs Debian's
//! `prometheus`. When it ran to its end it writes `target/prometheus/passed`, which the host stage
//! checks. Deadlines are scaled by `IHEX_TEST_TIME_SCALE`.
#![cfg(all(feature = "demo", feature = "web"))]

use std::{
    io::{BufRead, BufReader, Read, Write},
    net::{SocketAddr, TcpStream},
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    time::{Duration, Instant},
};

use ihex_tests::{
    mqtt::{options, Client, Seen},
    net::free_port,
    time::scaled,
};
use serde_json::Value;

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

/// A program on `PATH` (or named by the environment variable `var`).
fn program(var: &str, name: &str) -> PathBuf {
    if let Some(p) = std::env::var_os(var) {
        return PathBuf::from(p);
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    std::env::split_paths(&path)
        .map(|d| d.join(name))
        .find(|p| p.is_file())
        .unwrap_or_else(|| {
            panic!("{name} not found on PATH (set {var}); `cargo xtask setup` installs Debian's prometheus")
        })
}

/// A child process killed on drop.
struct Process(Child);

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// `GET path` over HTTP/1.0 (no chunking): the status and the body.
fn get(addr: SocketAddr, path: &str) -> std::io::Result<(u16, String)> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_secs(10)))?;
    write!(s, "GET {path} HTTP/1.0\r\nHost: {addr}\r\n\r\n")?;
    let mut text = String::new();
    s.read_to_string(&mut text)?;
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    Ok((status, body.to_owned()))
}

/// `POST path` with a JSON body over HTTP/1.0: the status.
fn post_json(addr: SocketAddr, path: &str, body: &str) -> u16 {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(
        s,
        "POST {path} HTTP/1.0\r\nHost: {addr}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{body}",
        body.len()
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    text.split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or(0)
}

/// A query string value, percent-encoded.
fn encode(v: &str) -> String {
    v.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// The result vector of an instant query through Prometheus's HTTP API.
fn query(prom: SocketAddr, promql: &str) -> Vec<Value> {
    let (status, body) = get(prom, &format!("/api/v1/query?query={}", encode(promql)))
        .unwrap_or_else(|e| panic!("query {promql}: {e}"));
    let v: Value = serde_json::from_str(&body).unwrap_or(Value::Null);
    assert_eq!(status, 200, "query {promql}: {body}");
    assert_eq!(v["status"], "success", "query {promql}: {body}");
    v["data"]["result"].as_array().cloned().unwrap_or_default()
}

/// The value of a one-series result.
fn value(series: &Value) -> f64 {
    series["value"][1]
        .as_str()
        .and_then(|v| v.parse().ok())
        .unwrap_or(f64::NAN)
}

/// Polls `promql` until `ok` accepts its result, or panics with the last result.
fn until(prom: SocketAddr, promql: &str, what: &str, ok: impl Fn(&[Value]) -> bool) -> Vec<Value> {
    let deadline = Instant::now() + scaled(Duration::from_secs(30));
    loop {
        // Prometheus takes a moment before it listens.
        let r = match get(prom, "/-/ready") {
            Ok((200, _)) => query(prom, promql),
            _ => Vec::new(),
        };
        if ok(&r) {
            return r;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}: {promql} = {r:?}"
        );
        std::thread::sleep(Duration::from_millis(250));
    }
}

/// Every PromQL expression of the dashboard (its panels' targets and its variables' queries), with
/// the Grafana variables it uses replaced by what Grafana would send here.
fn dashboard_expressions() -> Vec<String> {
    let path = root().join("deploy/grafana/ihex-gateway.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let dash: Value = serde_json::from_str(&text).unwrap();
    let mut exprs = Vec::new();
    for panel in dash["panels"].as_array().expect("panels") {
        for t in panel["targets"].as_array().expect("targets") {
            exprs.push(t["expr"].as_str().expect("expr").to_owned());
        }
    }
    for var in dash["templating"]["list"].as_array().expect("variables") {
        if let Some(q) = var["query"]["query"].as_str() {
            // `label_values(METRIC, LABEL)`: Grafana asks for METRIC's series.
            let inner = q
                .strip_prefix("label_values(")
                .and_then(|r| r.split_once(','))
                .map(|(m, _)| m.trim().to_owned())
                .unwrap_or_else(|| panic!("variable query {q} is not label_values(...)"));
            exprs.push(inner);
        }
    }
    assert!(exprs.len() > 10, "the dashboard lost its panels: {exprs:?}");
    exprs
        .into_iter()
        .map(|e| {
            e.replace("$__rate_interval", "15s")
                .replace("$__range", "1h")
                .replace("$instance", ".*")
        })
        .collect()
}

#[test]
#[ignore = "needs Debian's prometheus (promtool); run by `cargo xtask test` (host stage)"]
fn prometheus_scrapes_the_demo_gateway_and_the_dashboard_has_data() {
    let prometheus = program("IHEX_PROMETHEUS", "prometheus");
    let promtool = program("IHEX_PROMTOOL", "promtool");
    let broker = free_port();
    let http = free_port();
    let dir = tempfile::tempdir().unwrap();

    let mut cmd = Command::new(BIN);
    cmd.args(["--broker-listen", &format!("127.0.0.1:{broker}")])
        .args(["--http", &format!("127.0.0.1:{http}")])
        .args(["--log-dir", "-", "--health-period-ms", "250"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null());
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("IHEX_") {
            cmd.env_remove(k);
        }
    }
    let mut gateway = Process(cmd.spawn().unwrap());
    for line in BufReader::new(gateway.0.stdout.take().unwrap()).lines() {
        if line.unwrap().contains("Ctrl-C stops the gateway") {
            break;
        }
    }
    let view: SocketAddr = format!("127.0.0.1:{http}").parse().unwrap();

    // Three LED commands over MQTT, each answered `ok` (and one from the island view).
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    rt.block_on(async {
        let o = options(format!("127.0.0.1:{broker}").parse().unwrap(), "prom-test");
        let mut c = Client::subscribe_on_connect(o, &["EventsTopic", "ihex/node/+/state"]);
        c.seen("node 2's state", |s| s.is_on("ihex/node/2/state"))
            .await;
        for (i, (node, color)) in [("111", "red"), ("112", "green"), ("2", "blue")]
            .into_iter()
            .enumerate()
        {
            let id = format!("prom-{i}");
            c.publish(
                "CommandsTopic",
                format!(r#"{{"cmd":"led","node":"{node}","color":"{color}","request_id":"{id}"}}"#),
            )
            .await;
            let answer = c
                .expect(&format!("command_result of {id}"), |s: &Seen| {
                    s.json().is_some_and(|j| {
                        j["event"] == "command_result" && j["payload"]["request_id"] == id.as_str()
                    })
                })
                .await;
            assert_eq!(answer.json().unwrap()["payload"]["result"], "ok");
        }
        // And one from the island view, counted under its own interface.
        let body = r#"{"cmd":"led","node":"111","color":"white","request_id":"prom-web"}"#;
        let status = tokio::task::spawn_blocking(move || post_json(view, "/api/command", body))
            .await
            .unwrap();
        assert_eq!(status, 202);
        let answer = c
            .expect("command_result of prom-web", |s: &Seen| {
                s.json().is_some_and(|j| {
                    j["event"] == "command_result" && j["payload"]["request_id"] == "prom-web"
                })
            })
            .await;
        assert_eq!(answer.json().unwrap()["payload"]["result"], "ok");
    });

    // promtool on the exposition itself.
    let (status, exposition) = get(view, "/metrics").unwrap();
    assert_eq!(status, 200, "{exposition}");
    let mut check = Command::new(&promtool)
        .args(["check", "metrics"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    check
        .stdin
        .take()
        .unwrap()
        .write_all(exposition.as_bytes())
        .unwrap();
    let out = check.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "promtool check metrics: {}{}\n{exposition}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );

    // Prometheus scraping the gateway once a second.
    let prom: SocketAddr = format!("127.0.0.1:{}", free_port()).parse().unwrap();
    let config = dir.path().join("prometheus.yml");
    std::fs::write(
        &config,
        format!(
            "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\nscrape_configs:\n  - job_name: ihex-gateway\n    static_configs:\n      - targets: ['{view}']\n"
        ),
    )
    .unwrap();
    let check = Command::new(&promtool)
        .args(["check", "config"])
        .arg(&config)
        .output()
        .unwrap();
    assert!(check.status.success(), "{check:?}");
    let _server = Process(
        Command::new(&prometheus)
            .arg(format!("--config.file={}", config.display()))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.path().join("data").display()
            ))
            .arg(format!("--web.listen-address={prom}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );

    let up = until(
        prom,
        "up{job=\"ihex-gateway\"}",
        "a successful scrape",
        |r| r.len() == 1 && value(&r[0]) == 1.0,
    );
    let instance = up[0]["metric"]["instance"].as_str().unwrap().to_owned();
    assert_eq!(instance, view.to_string());

    let ok = until(
        prom,
        "ihex_commands_total{interface=\"mqtt\",result=\"ok\"}",
        "three commands ok",
        |r| r.len() == 1 && value(&r[0]) == 3.0,
    );
    assert_eq!(ok[0]["metric"]["job"], "ihex-gateway");
    let one = |promql: &str| {
        let r = query(prom, promql);
        assert_eq!(r.len(), 1, "{promql}: {r:?}");
        value(&r[0])
    };
    assert_eq!(
        one("ihex_command_round_trip_seconds_count{interface=\"mqtt\"}"),
        3.0
    );
    let rt_sum = one("ihex_command_round_trip_seconds_sum{interface=\"mqtt\"}");
    assert!(rt_sum > 0.0 && rt_sum < 3.0 * 5.0, "round trips {rt_sum}");
    assert_eq!(
        one("ihex_commands_total{interface=\"web\",result=\"ok\"}"),
        1.0
    );
    assert_eq!(
        one("ihex_command_round_trip_seconds_count{interface=\"web\"}"),
        1.0
    );
    assert_eq!(
        one("ihex_commands_total{interface=\"ha\",result=\"ok\"}"),
        0.0
    );
    assert_eq!(one("sum(ihex_commands_total{result!=\"ok\"})"), 0.0);
    assert_eq!(one("ihex_mqtt_connected"), 1.0);
    assert_eq!(one("ihex_mqtt_reconnects_total"), 0.0);
    assert_eq!(one("ihex_can_bus_down"), 0.0);
    assert_eq!(one("ihex_can_bus_off_total"), 0.0);
    assert_eq!(one("ihex_can_error_frames_total"), 0.0);
    assert_eq!(one("ihex_commands_in_flight"), 0.0);
    assert_eq!(one("ihex_publications_dropped_total"), 0.0);
    assert!(one("ihex_can_frames_received_total") > 0.0);
    // Four commands went out, beside the health checks and read-backs.
    assert!(one("ihex_can_frames_sent_total") >= 4.0);
    assert!(one("ihex_can_frame_bytes_total") > 0.0);
    assert_eq!(one("ihex_can_bitrate_bytes_per_second"), 500_000.0 / 8.0);
    assert_eq!(
        query(prom, "ihex_build_info")[0]["metric"]["version"],
        env!("CARGO_PKG_VERSION")
    );
    // The demo island: statics 111 and 112 and mobile 2 on the bus (mobile 3 is not docked).
    let online = query(prom, "ihex_element_online");
    let mut nodes: Vec<(String, f64)> = online
        .iter()
        .map(|s| (s["metric"]["node"].as_str().unwrap().to_owned(), value(s)))
        .collect();
    nodes.sort_by(|a, b| a.0.cmp(&b.0));
    assert_eq!(
        nodes,
        [("111".into(), 1.0), ("112".into(), 1.0), ("2".into(), 1.0)]
    );
    let heard = query(prom, "max(ihex_element_last_heard_seconds)");
    assert!(value(&heard[0]) < 5.0, "{heard:?}");
    let firmware = query(prom, "ihex_element_firmware_info");
    assert_eq!(firmware.len(), 3, "{firmware:?}");
    for s in &firmware {
        assert_eq!(value(s), 1.0);
        // The simulated elements run the workspace's version.
        assert_eq!(s["metric"]["version"], env!("CARGO_PKG_VERSION"), "{s:?}");
    }

    // Every expression of the dashboard has data. Rates need two scrapes inside their window.
    std::thread::sleep(Duration::from_secs(3));
    for expr in dashboard_expressions() {
        let r = query(prom, &expr);
        assert!(!r.is_empty(), "the dashboard's {expr} returns no data");
    }

    let passed = target_dir().join("prometheus/passed");
    std::fs::create_dir_all(passed.parent().unwrap()).unwrap();
    std::fs::write(&passed, format!("{}\n", instance)).unwrap();
}
