//! Shared rig of the lab-topology tests (feature `tls`): the central broker exactly as
//! `deploy/mosquitto/central.conf` and `acl` configure it (TLS with fresh test certificates,
//! passwords, the per-island ACL), in-process gateways running the simulated island, and MQTT
//! clients that log in like lab software does.
#![allow(dead_code)]

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use ihex_tests::broker::{self, Mosquitto, Setup};
use ihex_tests::mqtt;
use ihex_tests::tls::Pki;
use mc_gateway::{config::Options, CancellationToken, Config};
use tokio::task::JoinHandle;

/// Users of the central broker and their passwords (the ACL file names the users).
pub const USERS: [(&str, &str); 3] = [
    ("gw-bench-a", "pass-a"),
    ("gw-bench-b", "pass-b"),
    ("lab", "pass-lab"),
];

/// The password of a user of [`USERS`].
pub fn password(user: &str) -> &'static str {
    USERS
        .iter()
        .find(|(u, _)| *u == user)
        .map(|(_, p)| *p)
        .expect("a user of USERS")
}

/// A file of `deploy/mosquitto/`.
pub fn deploy_file(name: &str) -> String {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../deploy/mosquitto")
        .join(name);
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The lab's central broker as documented, on a free loopback port, with a fresh CA.
pub struct Central {
    pub broker: Mosquitto,
    pub pki: Pki,
}

impl Central {
    pub fn start(log_types: &[&str]) -> Central {
        let pki = Pki::new("iHEX test CA", &["localhost", "127.0.0.1"]).expect("certificates");
        let conf = broker::rewrite(
            &deploy_file("central.conf"),
            &[
                ("listener", "{port} 127.0.0.1"),
                ("password_file", "{dir}/passwd"),
                ("acl_file", "{dir}/acl"),
                ("cafile", "{dir}/ca.crt"),
                ("certfile", "{dir}/server.crt"),
                ("keyfile", "{dir}/server.key"),
            ],
        )
        .expect("central.conf has the lines the test replaces");
        let setup = Setup {
            conf: Some(conf),
            files: vec![
                (
                    "passwd".into(),
                    broker::password_file(&USERS).expect("mosquitto_passwd"),
                ),
                ("acl".into(), deploy_file("acl").into_bytes()),
                ("ca.crt".into(), pki.ca.clone().into_bytes()),
                ("server.crt".into(), pki.server_cert.clone().into_bytes()),
                ("server.key".into(), pki.server_key.clone().into_bytes()),
            ],
            log_types: log_types.iter().map(|t| t.to_string()).collect(),
            ..Setup::default()
        };
        let broker = Mosquitto::start_with(&setup).expect("start the central broker");
        Central { broker, pki }
    }

    pub fn addr(&self) -> SocketAddr {
        self.broker.addr()
    }

    pub fn ca_file(&self) -> PathBuf {
        self.broker.dir().join("ca.crt")
    }
}

/// A gateway configuration for `island` on `broker` with the simulated island; TLS with `ca` when
/// given; user and password when given.
pub fn gateway_config(
    broker: SocketAddr,
    island: &str,
    login: Option<(&str, &str)>,
    ca: Option<&Path>,
) -> Config {
    let cli = Options {
        broker: Some(broker.to_string()),
        sim: Some(true),
        island: Some(island.into()),
        username: login.map(|(u, _)| u.to_string()),
        password: login.map(|(_, p)| p.to_string()),
        tls: Some(ca.is_some()),
        tls_ca: ca.map(Path::to_path_buf),
        health_period_ms: Some(200),
        keep_alive: Some(5),
        log_dir: Some("-".into()),
        ..Options::default()
    };
    Config::resolve(cli, Options::default()).expect("valid gateway configuration")
}

/// A gateway running in-process.
pub struct Gateway {
    pub config: Config,
    stop: CancellationToken,
    task: JoinHandle<Result<(), mc_gateway::GatewayError>>,
}

impl Gateway {
    pub fn start(config: Config) -> Gateway {
        let stop = CancellationToken::new();
        let task = tokio::spawn(mc_gateway::run(config.clone(), stop.clone()));
        Gateway { config, stop, task }
    }

    pub async fn shutdown(self) {
        self.stop.cancel();
        let r = ihex_tests::within_or_panic(Duration::from_secs(10), "gateway shutdown", self.task)
            .await;
        r.expect("gateway task panicked")
            .expect("gateway returned an error");
    }
}

/// A client of `broker` with the options the gateway's own client would use for this login and
/// CA (TLS when `ca` is given), subscribed to `filters` on every connect.
pub fn client(
    broker: SocketAddr,
    id: &str,
    login: Option<(&str, &str)>,
    ca: Option<&Path>,
    filters: &[&str],
) -> mqtt::Client {
    let config = gateway_config(broker, "x", login, ca);
    let mut o = mc_gateway::mqtt::client_options(&config.mqtt, id.into()).expect("client options");
    o.set_keep_alive(Duration::from_secs(5))
        .set_max_packet_size(1 << 21, 1 << 21);
    mqtt::Client::subscribe_on_connect(o, filters)
}

/// The payload of an event named `name` on `topic`, if `s` is one.
pub fn event(s: &mqtt::Seen, topic: &str, name: &str) -> Option<serde_json::Value> {
    if !s.is_on(topic) {
        return None;
    }
    let v = s.json()?;
    (v["event"] == name).then(|| v["payload"].clone())
}
