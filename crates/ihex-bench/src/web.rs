//! The island view's latency: the demo gateway (embedded broker, simulated island, web view) on
//! this machine, an MQTT client and a server-sent-events reader of `/api/events` (the page's own
//! transport), and commands whose `command_result` both of them wait for.
//!
//! The gateway hands a publication to MQTT and to the view's feed at the same moment, so the time
//! from a command to its result on the event stream bounds the publication-to-page delay from
//! above (it also holds the command's trip through the island); the difference between the two
//! readers shows what the view adds next to an MQTT subscriber.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{Ipv4Addr, SocketAddr, TcpStream};
use std::path::Path;
use std::process::Command;
use std::sync::mpsc::{self, Receiver};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use ihex_bench::results::WebResults;
use ihex_bench::stats::Summary;
use ihex_gateway_core::event::{Event, Outcome};
use serde::Deserialize;

use crate::live::{free_port, Mqtt, Proc};

/// What the benchmarks' demo gateways are told besides their addresses: no Home Assistant
/// publications, warnings only, on stderr alone.
pub(crate) const DEMO_QUIET: [&str; 5] =
    ["--ha-discovery=false", "--log-dir", "-", "--log", "warn"];

/// The static element every probe colours (the built-in demo island has it).
const NODE: &str = "111";
/// How long one probe may take before it counts as lost.
const PROBE_TIMEOUT: Duration = Duration::from_secs(2);

/// The part of an event the reader needs: its payload's `request_id`.
#[derive(Deserialize)]
struct Answer {
    event: String,
    payload: AnswerPayload,
}

#[derive(Deserialize)]
struct AnswerPayload {
    request_id: Option<String>,
}

/// Reads `/api/events` and hands on each `event` message's `request_id` of a `command_result`,
/// with the moment its last line arrived.
fn sse_reader(http: SocketAddr) -> Result<Receiver<(Instant, String)>> {
    let mut stream = TcpStream::connect(http).with_context(|| format!("connecting to {http}"))?;
    // HTTP/1.0: the body ends when the connection does, so no chunked framing to take apart.
    write!(
        stream,
        "GET /api/events HTTP/1.0\r\nHost: {http}\r\nAccept: text/event-stream\r\n\r\n"
    )?;
    let mut lines = BufReader::new(stream).lines();
    let status = lines.next().context("no HTTP status line")??;
    if !status.contains(" 200") {
        bail!("GET /api/events answered {status}");
    }
    let (tx, rx) = mpsc::sync_channel(4096);
    std::thread::Builder::new()
        .name("sse".into())
        .spawn(move || {
            let (mut name, mut data) = (String::new(), String::new());
            for line in lines {
                let Ok(line) = line else { return };
                let now = Instant::now();
                if let Some(v) = line.strip_prefix("event:") {
                    name = v.trim().to_string();
                } else if let Some(v) = line.strip_prefix("data:") {
                    data.push_str(v.trim_start());
                } else if line.is_empty() {
                    if name == "event" {
                        if let Ok(a) = serde_json::from_str::<Answer>(&data) {
                            if let (true, Some(id)) =
                                (a.event == "command_result", a.payload.request_id)
                            {
                                if tx.send((now, id)).is_err() {
                                    return;
                                }
                            }
                        }
                    }
                    name.clear();
                    data.clear();
                }
            }
        })?;
    Ok(rx)
}

/// One probe: an LED command with a fresh `request_id`; when its `command_result` reached the
/// MQTT client and the event stream.
struct Probe {
    sent: Instant,
    mqtt: Option<(Instant, Outcome)>,
    page: Option<Instant>,
}

fn command(i: usize) -> String {
    // A colour of its own per probe, so that every probe changes the element's state.
    let c = i % 200;
    format!(
        r#"{{"cmd":"led","node":"{NODE}","color":[{c},{},40],"request_id":"web-{i}"}}"#,
        255 - c
    )
}

/// Sends probe `i` and waits for both readers (or [`PROBE_TIMEOUT`]).
fn probe(i: usize, mqtt: &Mqtt, sse: &Receiver<(Instant, String)>) -> Result<Probe> {
    let id = format!("web-{i}");
    let sent = Instant::now();
    mqtt.client.publish(
        "CommandsTopic",
        rumqttc::QoS::AtLeastOnce,
        false,
        command(i),
    )?;
    let deadline = sent + PROBE_TIMEOUT;
    let mut p = Probe {
        sent,
        mqtt: None,
        page: None,
    };
    while p.mqtt.is_none() {
        let Some(left) = deadline.checked_duration_since(Instant::now()) else {
            break;
        };
        match mqtt.next_event(left) {
            Some((t, Event::CommandResult(r))) if r.request_id.as_deref() == Some(&id) => {
                p.mqtt = Some((t, r.result));
            }
            Some(_) => {}
            None => break,
        }
    }
    while p.page.is_none() {
        let Some(left) = deadline.checked_duration_since(Instant::now()) else {
            break;
        };
        match sse.recv_timeout(left) {
            Ok((t, got)) if got == id => p.page = Some(t),
            Ok(_) => {}
            Err(_) => break,
        }
    }
    Ok(p)
}

fn us(d: Duration) -> f64 {
    d.as_secs_f64() * 1e6
}

/// Signed difference `a - b`, µs.
fn diff_us(a: Instant, b: Instant) -> f64 {
    match a.checked_duration_since(b) {
        Some(d) => us(d),
        None => -us(b - a),
    }
}

/// Runs the demo gateway `bin` and `probes` probes, one every `gap`: with its embedded broker, or
/// with the simulated island and the broker at `broker`.
pub fn run(
    bin: &Path,
    broker: Option<SocketAddr>,
    probes: usize,
    gap: Duration,
) -> Result<WebResults> {
    let http = SocketAddr::from((Ipv4Addr::LOCALHOST, free_port()?));
    let dir = std::env::temp_dir().join(format!("ihex-bench-web-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let mut cmd = Command::new(bin);
    let broker = match broker {
        Some(b) => {
            cmd.args(["--sim", "--broker", &b.to_string()]);
            b
        }
        None => {
            let b = SocketAddr::from((Ipv4Addr::LOCALHOST, free_port()?));
            cmd.args(["--broker-listen", &b.to_string()]);
            b
        }
    };
    cmd.args(["--http", &http.to_string()]).args(DEMO_QUIET);
    let mut gateway = Proc::spawn(cmd, &dir.join("gateway.log"), "mc-gateway (demo)")?;
    gateway.wait_listening(broker, Duration::from_secs(30))?;
    gateway.wait_listening(http, Duration::from_secs(30))?;
    let mqtt = Mqtt::connect(broker, &["EventsTopic"])?;
    let sse = sse_reader(http)?;

    // Until the simulated island answers (the demo's nodes boot when the gateway starts).
    let warm_up = Instant::now() + Duration::from_secs(30);
    let mut i = 0;
    loop {
        let p = probe(i, &mqtt, &sse)?;
        i += 1;
        if matches!(p.mqtt, Some((_, Outcome::Ok))) && p.page.is_some() {
            break;
        }
        gateway.check_alive()?;
        if Instant::now() > warm_up {
            bail!(
                "the demo island never acknowledged an LED command within 30 s (log: {})",
                dir.join("gateway.log").display()
            );
        }
        std::thread::sleep(Duration::from_millis(200));
    }

    let (mut to_page, mut to_mqtt, mut page_vs_mqtt) = (Vec::new(), Vec::new(), Vec::new());
    let mut outcomes: HashMap<String, usize> = HashMap::new();
    let mut lost = 0;
    for n in 0..probes {
        let p = probe(i + n, &mqtt, &sse)?;
        match (p.mqtt, p.page) {
            (Some((m, outcome)), Some(page)) => {
                let name = serde_json::to_value(outcome)?;
                *outcomes
                    .entry(name.as_str().unwrap_or("?").to_string())
                    .or_default() += 1;
                to_page.push(us(page - p.sent));
                to_mqtt.push(us(m - p.sent));
                page_vs_mqtt.push(diff_us(page, m));
            }
            _ => lost += 1,
        }
        std::thread::sleep(gap);
    }
    gateway.check_alive()?;
    let mut outcomes: Vec<_> = outcomes.into_iter().collect();
    outcomes.sort();
    Ok(WebResults {
        probes,
        lost,
        outcomes,
        command_to_page: Summary::of(to_page),
        command_to_mqtt: Summary::of(to_mqtt),
        page_minus_mqtt: Summary::of(page_vs_mqtt),
    })
}
