//! The island view in a real browser: Debian's headless Chromium driven through chromedriver
//! (fantoccini), against the `mc-gateway` demo binary (embedded broker, simulated island), while the
//! island is changed over MQTT like a person at the bench would.
//!
//! Ignored in the host stage (it needs `chromium` and `chromedriver`); the `browser` stage of
//! `cargo xtask test` installs them and runs it with `--ignored`. Screenshots go to
//! `target/web-screenshots/`. Deadlines are scaled by `IHEX_TEST_TIME_SCALE`: they bound how long
//! a change may take to show, they do not measure it.
#![cfg(all(feature = "demo", feature = "web"))]

use std::{
    io::{BufRead, BufReader},
    net::TcpListener,
    path::{Path, PathBuf},
    process::{Child, Command, Stdio},
    time::Duration,
};

use fantoccini::{Client, ClientBuilder, Locator};
use ihex_tests::time::scaled;
use rumqttc::{AsyncClient, Event, Incoming, MqttOptions, QoS};
use serde_json::{json, Value};
use tokio::sync::mpsc;

const BIN: &str = env!("CARGO_BIN_EXE_mc-gateway");

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A program on `PATH` (or named by the environment variable `var`).
fn program(var: &str, names: &[&str]) -> PathBuf {
    if let Some(p) = std::env::var_os(var) {
        return PathBuf::from(p);
    }
    let path = std::env::var_os("PATH").unwrap_or_default();
    names
        .iter()
        .flat_map(|n| std::env::split_paths(&path).map(move |d| d.join(n)))
        .find(|p| p.is_file())
        .unwrap_or_else(|| {
            panic!(
                "none of {names:?} found on PATH (set {var}); `cargo xtask setup` installs Debian's chromium and chromium-driver"
            )
        })
}

/// The screenshot folder, `target/web-screenshots/`.
fn screenshot_dir() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../../target"));
    let dir = target.join("web-screenshots");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The demo gateway as a process, started and stopped like a person would.
struct Gateway {
    child: Child,
}

impl Gateway {
    fn start(broker: u16, http: u16) -> Gateway {
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
        let mut child = cmd.spawn().unwrap();
        // The banner is printed once broker, island, view and tasks run; it names the view.
        let mut banner = String::new();
        for line in BufReader::new(child.stdout.take().unwrap()).lines() {
            let line = line.unwrap();
            banner.push_str(&line);
            banner.push('\n');
            if line.contains("Ctrl-C stops the gateway") {
                break;
            }
        }
        let url = format!("See the island live in a browser: http://127.0.0.1:{http}/");
        assert!(
            banner.contains(&url),
            "the banner does not name the view:\n{banner}"
        );
        Gateway { child }
    }

    /// SIGTERM, and the exit status must be a success.
    fn stop(mut self) {
        // SAFETY: plain kill(2) on our own child's pid.
        assert_eq!(
            unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) },
            0
        );
        assert!(self.child.wait().unwrap().success());
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// chromedriver on a free port, killed on drop.
struct Driver(Child, u16);

impl Driver {
    fn start() -> Driver {
        let port = free_port();
        let child = Command::new(program("IHEX_CHROMEDRIVER", &["chromedriver"]))
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start chromedriver");
        Driver(child, port)
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A headless Chromium session with the flags that work on machines without a network or a GPU.
async fn browser(driver: &Driver, profile: &Path) -> Client {
    let chromium = program(
        "IHEX_CHROMIUM",
        &["chromium", "chromium-browser", "google-chrome"],
    );
    let caps = json!({
        "goog:chromeOptions": {
            "binary": chromium,
            "args": [
                "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--window-size=1400,1100",
                format!("--user-data-dir={}", profile.display()),
            ],
        }
    });
    let caps = caps.as_object().unwrap().clone();
    let url = format!("http://127.0.0.1:{}", driver.1);
    let deadline = tokio::time::Instant::now() + scaled(Duration::from_secs(20));
    loop {
        let connector = hyper_util::client::legacy::connect::HttpConnector::new();
        match ClientBuilder::new(connector)
            .capabilities(caps.clone())
            .connect(&url)
            .await
        {
            Ok(c) => return c,
            Err(e) if tokio::time::Instant::now() < deadline => {
                let _ = e;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("no browser session through chromedriver: {e}"),
        }
    }
}

/// An MQTT client of the demo broker seeing every message; reconnects on its own.
fn mqtt(port: u16) -> (AsyncClient, mpsc::UnboundedReceiver<(String, Value)>) {
    let mut o = MqttOptions::new("browser-test", "127.0.0.1", port);
    o.set_keep_alive(Duration::from_secs(5));
    let (c, mut el) = AsyncClient::new(o, 32);
    let (tx, rx) = mpsc::unbounded_channel();
    let sub = c.clone();
    tokio::spawn(async move {
        loop {
            match el.poll().await {
                Ok(Event::Incoming(Incoming::ConnAck(_))) => {
                    let _ = sub.try_subscribe("#", QoS::AtLeastOnce);
                }
                Ok(Event::Incoming(Incoming::Publish(p))) => {
                    let v = serde_json::from_slice(&p.payload).unwrap_or(Value::Null);
                    if tx.send((p.topic, v)).is_err() {
                        return;
                    }
                }
                Ok(_) => {}
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    });
    (c, rx)
}

async fn expect_mqtt(
    rx: &mut mpsc::UnboundedReceiver<(String, Value)>,
    what: &str,
    pred: impl Fn(&str, &Value) -> bool,
) -> Value {
    let wait = async {
        while let Some((t, v)) = rx.recv().await {
            if pred(&t, &v) {
                return v;
            }
        }
        panic!("MQTT client stopped");
    };
    tokio::time::timeout(scaled(Duration::from_secs(10)), wait)
        .await
        .unwrap_or_else(|_| panic!("no {what} on MQTT"))
}

/// Evaluates `expr` in the page until it is `true`; fails after `within` (scaled) with `what`, the
/// last value and a screenshot.
async fn until(c: &Client, within: Duration, what: &str, expr: &str) {
    let deadline = tokio::time::Instant::now() + scaled(within);
    let script = format!("try {{ return ({expr}); }} catch (e) {{ return String(e); }}");
    loop {
        let v = c.execute(&script, vec![]).await.unwrap();
        if v == Value::Bool(true) {
            return;
        }
        if tokio::time::Instant::now() > deadline {
            let name = format!(
                "failed-{}.png",
                what.replace(|ch: char| !ch.is_alphanumeric(), "-")
            );
            shoot(c, &name).await;
            panic!(
                "the page did not show {what} within {:?} (last value {v}); see {name}",
                scaled(within)
            );
        }
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

async fn shoot(c: &Client, name: &str) {
    if let Ok(png) = c.screenshot().await {
        std::fs::write(screenshot_dir().join(name), png).unwrap();
    }
}

/// Clicks what `css` selects, as a person would (a WebDriver click); the page redraws the map when
/// the island changes, so an element found just before a redraw is looked up again.
async fn click(c: &Client, css: &str) {
    for _ in 0..20 {
        match c.find(Locator::Css(css)).await.unwrap().click().await {
            Ok(()) => return,
            Err(e) if e.to_string().contains("stale element") => continue,
            Err(e) => panic!("cannot click {css}: {e}"),
        }
    }
    panic!("{css} kept being redrawn under the click");
}

/// The map's element `id`: a CSS selector.
fn on_map(id: &str) -> String {
    format!("#map g.element[data-node='{id}']")
}

/// JavaScript reading one data attribute of the map's element `id` (`null` when it is not drawn).
fn attr(id: &str, name: &str) -> String {
    format!(
        "(document.querySelector(\"{}\") || {{dataset: {{}}}}).dataset.{name}",
        on_map(id)
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs chromium and chromedriver: cargo xtask test --stage browser"]
async fn the_island_view_follows_the_bench() {
    let (broker, http) = (free_port(), free_port());
    let gateway = Gateway::start(broker, http);
    let (bus, mut rx) = mqtt(broker);
    let driver = Driver::start();
    let profile = tempfile::tempdir().unwrap();
    let c = browser(&driver, profile.path()).await;
    c.goto(&format!("http://127.0.0.1:{http}/")).await.unwrap();

    // Every element of the demo island on the bus, in its state: 111 and 112 static, 2 docked on
    // 111 port 3 by its port 0, all online, 111's relay on (it powers 2). Mobile 3 is not docked,
    // so it has no power and the gateway has never heard of it: it is not drawn.
    let one_second = Duration::from_secs(1);
    until(
        &c,
        Duration::from_secs(10),
        "the island",
        "document.querySelectorAll('#map g.element').length === 3",
    )
    .await;
    until(
        &c,
        one_second,
        "no 3",
        &format!("document.querySelector(\"{}\") === null", on_map("3")),
    )
    .await;
    for (id, role) in [("111", "static"), ("112", "static"), ("2", "mobile")] {
        until(
            &c,
            one_second,
            &format!("{id} as {role}"),
            &format!("{} === '{role}'", attr(id, "role")),
        )
        .await;
        until(
            &c,
            one_second,
            &format!("{id} online"),
            &format!("{} === 'online'", attr(id, "status")),
        )
        .await;
        until(
            &c,
            one_second,
            &format!("{id} listed online"),
            &format!("document.querySelector(\"#elements tr[data-node='{id}']\").dataset.status === 'online'"),
        )
        .await;
    }
    until(
        &c,
        one_second,
        "2 docked on 111 port 3",
        &format!(
            "{} === '111' && {} === '3' && {} === '0'",
            attr("2", "dockedTo"),
            attr("2", "dockPort"),
            attr("2", "ownPort")
        ),
    )
    .await;
    until(
        &c,
        one_second,
        "111's relay on",
        &format!("{} === 'on'", attr("111", "relay")),
    )
    .await;
    until(&c, one_second, "111's closed loop on port 3",
        &format!("document.querySelector(\"{} circle.port[data-port='3']\").classList.contains('closed')", on_map("111"))).await;
    until(
        &c,
        one_second,
        "the gateway's health",
        "document.getElementById('mqtt-state').textContent === 'connected'",
    )
    .await;
    until(
        &c,
        one_second,
        "no stale banner",
        "document.getElementById('stale').hidden",
    )
    .await;
    shoot(&c, "island.png").await;

    // Docking in the simulator redraws 3 against 112's port 2; undocking puts it back in the tray.
    bus.publish(
        "ihex/sim",
        QoS::AtLeastOnce,
        false,
        r#"{"sim":"dock","mobile":"3","static":"112","port":2}"#,
    )
    .await
    .unwrap();
    until(
        &c,
        one_second,
        "3 docked on 112 port 2",
        &format!(
            "{} === '112' && {} === '2' && {} === 'online'",
            attr("3", "dockedTo"),
            attr("3", "dockPort"),
            attr("3", "status")
        ),
    )
    .await;
    until(&c, one_second, "the docking in the timeline",
        "[...document.querySelectorAll('#timeline li')].some(li => li.dataset.event === 'new_connection' && li.dataset.nodes.split(' ').includes('3'))").await;
    shoot(&c, "docked.png").await;
    bus.publish(
        "ihex/sim",
        QoS::AtLeastOnce,
        false,
        r#"{"sim":"undock","mobile":"3"}"#,
    )
    .await
    .unwrap();
    until(
        &c,
        one_second,
        "3 undocked",
        &format!("{} === 'true'", attr("3", "free")),
    )
    .await;
    // Without power it stops answering: lost after three missed health checks of 250 ms.
    until(
        &c,
        Duration::from_secs(3),
        "3 lost",
        &format!("{} === 'lost'", attr("3", "status")),
    )
    .await;

    // An LED command over MQTT changes 111's colour on the page.
    bus.publish(
        "CommandsTopic",
        QoS::AtLeastOnce,
        false,
        r##"{"cmd":"led","node":"111","color":"#00ff00"}"##,
    )
    .await
    .unwrap();
    until(&c, one_second, "111 green", &format!(
        "{} === '#00ff00' && document.querySelector(\"{} polygon.body\").getAttribute('fill') === '#00ff00'",
        attr("111", "led"), on_map("111"))).await;
    shoot(&c, "led.png").await;

    // A command given on the page reaches the simulated node and its result shows beside it.
    click(&c, &on_map("112")).await;
    until(
        &c,
        one_second,
        "112's details",
        "document.getElementById('details-body').dataset.node === '112'",
    )
    .await;
    c.execute(
        "document.getElementById('led-color').value = '#0000ff'",
        vec![],
    )
    .await
    .unwrap();
    click(&c, "#led-set").await;
    until(
        &c,
        Duration::from_secs(2),
        "the command's result",
        "document.getElementById('details-result').textContent === 'led: ok'",
    )
    .await;
    let state = expect_mqtt(&mut rx, "112's state turning blue", |t, v| {
        t == "ihex/node/112/state" && v["led"]["color"] == "#0000ff"
    })
    .await;
    assert_eq!(state["led"]["mode"], "steady", "{state}");
    until(
        &c,
        one_second,
        "112 blue on the map",
        &format!("{} === '#0000ff'", attr("112", "led")),
    )
    .await;
    until(&c, one_second, "the result in the list",
        "document.querySelector(\"#elements tr[data-node='112'] td.result\").textContent === 'led: ok'").await;
    // The relay of 111 switched off from the page; the node acknowledges (its state says so).
    click(&c, &on_map("111")).await;
    click(&c, "#relay-off").await;
    until(
        &c,
        Duration::from_secs(2),
        "power: ok",
        "document.getElementById('details-result').textContent === 'power: ok'",
    )
    .await;
    expect_mqtt(&mut rx, "111's relay off", |t, v| {
        t == "ihex/node/111/state" && v["relay"] == false
    })
    .await;
    until(
        &c,
        one_second,
        "111's relay off on the map",
        &format!("{} === 'off'", attr("111", "relay")),
    )
    .await;
    shoot(&c, "command.png").await;

    // Stopping the gateway shows the stale banner; a new gateway on the same ports clears it.
    gateway.stop();
    until(
        &c,
        Duration::from_secs(3),
        "the stale banner",
        "!document.getElementById('stale').hidden",
    )
    .await;
    shoot(&c, "stale.png").await;
    let gateway = Gateway::start(broker, http);
    until(
        &c,
        Duration::from_secs(10),
        "the banner cleared",
        "document.getElementById('stale').hidden",
    )
    .await;
    until(
        &c,
        one_second,
        "the new gateway's island",
        "document.querySelectorAll('#map g.element').length === 3",
    )
    .await;
    // The new gateway's island starts afresh: 111 is dark again.
    until(
        &c,
        one_second,
        "111 as the new island has it",
        &format!("{} !== '#00ff00'", attr("111", "led")),
    )
    .await;
    shoot(&c, "recovered.png").await;

    c.close().await.unwrap();
    gateway.stop();
}
