//! The gateway's configuration: every option declared once in the table below (flag, `IHEX_*`
//! environment variable, TOML key, default, range, help — see [`options`] for how), merged with
//! the precedence command line > environment > `--config` TOML file > defaults, and resolved into a
//! validated [`Config`].
//!
//! When neither a broker nor a CAN interface is configured anywhere, the result is the embedded demo:
//! an embedded broker on `broker_listen` and a simulated island.

pub mod check;
pub mod options;
pub mod sila;
pub mod web;

use std::{
    fmt,
    net::SocketAddr,
    path::{Path, PathBuf},
    time::Duration,
};

use ihex_gateway_core::{bridge, fwupdate, ha, topic, BridgeConfig};

use crate::error::ConfigError;
pub use options::Origin;
use options::{default_text, ms, options, setting_type, setting_value};

/// The lab broker of the seed.
pub const DEFAULT_BROKER: &str = "192.168.1.101:1883";
/// The Pi's CAN interface (MCP2515 HAT).
pub const DEFAULT_CAN: &str = "can0";
/// MQTT port when an address gives none.
pub const MQTT_PORT: u16 = 1883;

options! {
    /// TOML configuration file (keys as the long flags, with `_` for `-`).
    config: PathBuf = none, env "IHEX_CONFIG", value "FILE", [cli_only];
    /// Check the whole configuration (files and certificates included), print every option with
    /// its value and where it came from, and exit: 0 when it is valid, 1 when not.
    check_config: bool = false, env "IHEX_CHECK_CONFIG", value "BOOL", [cli_only];
    /// MQTT broker to connect to (`[v6]:port` for IPv6). Unset together with `can`: the embedded
    /// demo broker.
    broker: String = (text format!("lab: `{DEFAULT_BROKER}`")), env "IHEX_BROKER",
        value "HOST[:PORT]";
    /// SocketCAN interface of the island bus. Unset together with `broker`: the simulated island.
    can: String = (text format!("lab: `{DEFAULT_CAN}`")), env "IHEX_CAN", value "IFACE";
    /// Run the simulated island instead of a CAN interface (implied by the demo).
    sim: bool = false, env "IHEX_SIM", value "BOOL";
    /// Island description for the simulated island (`docs/sim-node.md`, e.g.
    /// `examples/islands/demo.toml`).
    island_file: PathBuf = (text "the built-in island"), env "IHEX_ISLAND_FILE", value "FILE";
    /// Bit rate the interface is expected to run at, bit/s (the system's link configuration sets
    /// it; a warning if it differs); the simulated island's bus runs at it.
    bitrate: u32 = {ihex_proto::BITRATE}, env "IHEX_BITRATE", value "BIT/S",
        range 10000..=1000000;
    /// Island name: every topic goes under `NAME/`, so several gateways can share one broker.
    island: String = none, env "IHEX_ISLAND", value "NAME";
    /// Where the embedded demo broker listens.
    broker_listen: SocketAddr = {SocketAddr::from(([127, 0, 0, 1], MQTT_PORT))},
        env "IHEX_BROKER_LISTEN", value "ADDR:PORT";
    /// Where the island view (web page and JSON API, `docs/web.md`) listens; `off` switches it off.
    http: String = (text "`127.0.0.1:8080`"), env "IHEX_HTTP", value "ADDR:PORT";
    /// Where the SiLA 2 server (`docs/sila.md`) listens; `off` switches it off.
    sila: String = (text "`127.0.0.1:50052`"), env "IHEX_SILA", value "ADDR:PORT";
    /// The SiLA server's TLS certificate (PEM; what clients verify it with) instead of the
    /// self-signed one it makes and keeps in the state directory. Needs `sila_key`.
    sila_cert: PathBuf = (text "self-signed, made once"), env "IHEX_SILA_CERT", value "FILE";
    /// The private key of `sila_cert` (PEM).
    sila_key: PathBuf = none, env "IHEX_SILA_KEY", value "FILE";
    /// Serve SiLA without TLS (plaintext gRPC): only on a loopback address, unless
    /// `sila_insecure_anywhere` is given too.
    sila_insecure: bool = false, env "IHEX_SILA_INSECURE", value "BOOL";
    /// Allow `sila_insecure` on a non-loopback address: anyone on the network can then read and
    /// drive the island unencrypted.
    sila_insecure_anywhere: bool = false, env "IHEX_SILA_INSECURE_ANYWHERE", value "BOOL";
    /// Announce the SiLA server over mDNS/DNS-SD (`_sila._tcp`), so orchestrators find it.
    sila_announce: String = "on", env "IHEX_SILA_ANNOUNCE", value "on|off", one_of ["on", "off"];
    /// Bearer token for the island view's controls; without one they work only when the view
    /// listens on a loopback address (elsewhere it is read-only).
    http_token: String = none, env "IHEX_HTTP_TOKEN", value "TOKEN", [secret];
    /// Positions of static elements in the island view, `ID=Q,R` (axial hex coordinates) separated
    /// by spaces, e.g. `111=0,0 112=1,0`; the others are arranged around them.
    layout: String = none, env "IHEX_LAYOUT", value "ID=Q,R ...";
    /// MQTT client id.
    client_id: String = (text "`ihex-gateway`, or `ihex-gateway-ISLAND`"), env "IHEX_CLIENT_ID",
        value "ID";
    /// MQTT user name.
    username: String = none, env "IHEX_MQTT_USERNAME", value "USER";
    /// MQTT password (prefer the environment variable or the file to the command line).
    password: String = none, env "IHEX_MQTT_PASSWORD", value "PASSWORD", [secret];
    /// Connect to the broker over TLS (needs the `tls` build feature).
    tls: bool = false, env "IHEX_MQTT_TLS", value "BOOL";
    /// PEM CA certificate for TLS.
    tls_ca: PathBuf = (text "the system's roots"), env "IHEX_MQTT_TLS_CA", value "FILE";
    /// MQTT keep-alive, seconds: the gateway pings the broker this often, and the broker takes a
    /// silent gateway for gone (last will `offline`) after 1.5 times this.
    keep_alive: u64 = {crate::mqtt::DEFAULT_KEEP_ALIVE.as_secs()}, env "IHEX_KEEP_ALIVE",
        value "SECS", range 5..=3600;
    /// How long a PUBACK or PINGRESP the gateway waits for may stay missing before it takes the
    /// broker link for dead and reconnects, ms.
    broker_ack_timeout_ms: u64 = {ms(crate::mqtt::DEFAULT_ACK_TIMEOUT)},
        env "IHEX_BROKER_ACK_TIMEOUT_MS", value "MS", range 500..=600000;
    /// Command topic (before the island prefix).
    commands_topic: String = {topic::COMMANDS}, env "IHEX_COMMANDS_TOPIC", value "TOPIC";
    /// Event topic (before the island prefix).
    events_topic: String = {topic::EVENTS}, env "IHEX_EVENTS_TOPIC", value "TOPIC";
    /// Retained availability topic: `online` while running, `offline` on shutdown and as the last
    /// will.
    availability_topic: String = {topic::AVAILABILITY}, env "IHEX_AVAILABILITY_TOPIC",
        value "TOPIC";
    /// Root of the retained per-node state topics `ROOT/<id>/state`.
    node_state_root: String = {topic::NODE_STATE_ROOT}, env "IHEX_NODE_STATE_ROOT",
        value "TOPIC";
    /// Home Assistant MQTT discovery: one device per element, commands from Home Assistant
    /// (`docs/integrations.md`). `false`: nothing Home Assistant's is published or subscribed.
    ha_discovery: bool = true, env "IHEX_HA_DISCOVERY", value "BOOL";
    /// Home Assistant's discovery prefix (not under the island prefix).
    ha_discovery_prefix: String = {ha::topic::DISCOVERY_PREFIX}, env "IHEX_HA_DISCOVERY_PREFIX",
        value "TOPIC";
    /// Home Assistant's status topic: its `online` birth message makes the gateway publish every
    /// discovery config again.
    ha_status_topic: String = {ha::topic::STATUS}, env "IHEX_HA_STATUS_TOPIC", value "TOPIC";
    /// The gateway's web page as people reach it (`http://…` or `https://…`): every Home Assistant
    /// device links to it.
    public_url: String = none, env "IHEX_PUBLIC_URL", value "URL";
    /// Period of the broadcast health check, ms.
    health_period_ms: u64 = {ms(bridge::DEFAULT_HEALTH_PERIOD)}, env "IHEX_HEALTH_PERIOD_MS",
        value "MS", range 10..=3600000;
    /// Missed health replies after which a node is reported lost.
    lost_after: u32 = {bridge::DEFAULT_LOST_AFTER}, env "IHEX_LOST_AFTER", value "N",
        range 1..=1000;
    /// How long to wait for a mobile element's handshake after confirming a docking, ms.
    dock_timeout_ms: u64 = {ms(bridge::DEFAULT_DOCK_TIMEOUT)}, env "IHEX_DOCK_TIMEOUT_MS",
        value "MS", range 10..=600000;
    /// How long a command may wait for the bus, and then for the node's acknowledgement, ms.
    command_timeout_ms: u64 = {ms(bridge::DEFAULT_COMMAND_TIMEOUT)},
        env "IHEX_COMMAND_TIMEOUT_MS", value "MS", range 1..=600000;
    /// Largest accepted command payload, bytes (larger ones are `command_rejected`).
    max_command_bytes: usize = {bridge::DEFAULT_MAX_COMMAND_BYTES}, env "IHEX_MAX_COMMAND_BYTES",
        value "BYTES", range 64..=1048576;
    /// Guided procedures running at once at most; a `procedure` command beyond them is refused
    /// (`docs/procedures.md`).
    max_procedures: usize = {ihex_gateway_core::procedure::DEFAULT_MAX_PROCEDURES},
        env "IHEX_MAX_PROCEDURES", value "N", range 1..=64;
    /// Directory of signed firmware images an `fw_update` command may name by file name, besides
    /// the images uploaded over MQTT (`docs/firmware-update.md`).
    fw_dir: PathBuf = (text "none: only uploaded images"), env "IHEX_FW_DIR", value "DIR";
    /// The lab's public key file (`lab.pub`): an image uploaded over MQTT must be signed with it
    /// (`docs/firmware-update.md`). Without it the gateway checks everything of an upload but its
    /// signature, which each node checks anyway.
    fw_key: PathBuf = (text "none: uploads' signatures unchecked"), env "IHEX_FW_KEY",
        value "FILE";
    /// Largest share of the bus a firmware update's frames take, % (counted in bits on the wire).
    fw_bus_share: u8 = {fwupdate::DEFAULT_BUS_SHARE}, env "IHEX_FW_BUS_SHARE", value "PERCENT",
        range 1..=100;
    /// Receive buffer asked for on the CAN socket (`SO_RCVBUFFORCE` as root, else `SO_RCVBUF`),
    /// bytes.
    rx_buffer: usize = 4194304, env "IHEX_RX_BUFFER", value "BYTES", range 4096..=268435456;
    /// Frames the CAN transmit queue holds before further frames fail (`not sent: CAN transmit
    /// queue full`).
    tx_queue: usize = {bridge::DEFAULT_TX_QUEUE}, env "IHEX_TX_QUEUE", value "FRAMES",
        range 1..=65536;
    /// Events held while the broker is slow or unreachable before the oldest are dropped (counted,
    /// reported as `publications_dropped`); answers and state documents are never dropped.
    mqtt_queue: usize = {bridge::DEFAULT_EVENT_QUEUE}, env "IHEX_MQTT_QUEUE", value "N",
        range 1..=1048576;
    /// Directory of the JSON-lines log (`mc-gateway.<date>.jsonl`, rotated); `-` = no file (the
    /// Pi's service uses `/var/log/ihex`).
    log_dir: String = (text "`$XDG_STATE_HOME/ihex`, else `~/.local/state/ihex`"),
        env "IHEX_LOG_DIR", value "DIR";
    /// When the log file rotates.
    log_rotation: String = "daily", env "IHEX_LOG_ROTATION", value "WHEN",
        one_of ["minutely", "hourly", "daily", "never"];
    /// Log filter: a default level and `target=level` directives, e.g. `info,mc_gateway=debug`.
    log: String = "info", env "IHEX_LOG", value "FILTER";
    /// Directory of the audit trail (`docs/audit.md`): every command with who sent it, through
    /// which interface and what came of it, lease changes, firmware outcomes, start and stop, in
    /// hash-chained JSON lines. `off`: no trail.
    audit_dir: String = (text "`audit/` in the log directory; none with `--log-dir -`"),
        env "IHEX_AUDIT_DIR", value "DIR";
    /// Period of the retained anchor of the audit chain's head (`ihex/audit/head` under the
    /// island prefix), seconds; 0: no anchor.
    audit_anchor_s: u64 = 60, env "IHEX_AUDIT_ANCHOR_S", value "SECS", range 0..=86400;
    /// Size of the audit directory beyond which nothing more is recorded (as with a full disk:
    /// an `audit_error` event and the health flag; commands are still answered), bytes.
    audit_max_bytes: u64 = (text "none: until the disk is full"), env "IHEX_AUDIT_MAX_BYTES",
        value "BYTES";
    /// Refuse commands (`command_rejected`; `list` aside) without an identity something vouches
    /// for: on the shared command topic, only the per-user topics `ihex/cmd/<user>` (under the
    /// island prefix) and interfaces that establish who sends are taken.
    require_identity: bool = false, env "IHEX_REQUIRE_IDENTITY", value "BOOL";
}

/// The command line: every option of the table, with its environment variable.
pub fn command() -> clap::Command {
    clap::Command::new("mc-gateway")
        .version(env!("CARGO_PKG_VERSION"))
        .about("iHEX main controller: MQTT JSON commands and events <-> the island's CAN bus")
        .long_about(
            "iHEX main controller: MQTT JSON commands and events <-> the island's CAN bus.\n\n\
             Precedence: command line > environment > --config file > defaults.\n\
             With no broker and no CAN interface configured anywhere, it runs the embedded demo: an \
             MQTT broker on --broker-listen and a simulated island. In the lab (Raspberry Pi) use \
             --broker 192.168.1.101:1883 --can can0 (the seed's values) or a config file such as \
             config/gateway.example.toml.",
        )
        .args(Options::args())
}

/// The options table of `docs/gateway.md`, as the table declares it.
pub fn docs_table() -> String {
    let mut t = String::from(
        "| flag | TOML key | environment | default | accepted | meaning |\n|---|---|---|---|---|---|\n",
    );
    for spec in specs() {
        t.push_str(&spec.docs_row());
        t.push('\n');
    }
    t
}

impl Options {
    /// The options on a command line (`args[0]` is the program name) and in the environment.
    pub fn from_args<I, T>(args: I) -> Result<Options, clap::Error>
    where
        I: IntoIterator<Item = T>,
        T: Into<std::ffi::OsString> + Clone,
    {
        command()
            .try_get_matches_from(args)
            .map(|m| Options::from_matches(&m))
    }

    /// Reads and parses a config file.
    pub fn load(path: &Path) -> Result<Options, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        Options::parse_toml(path, &text)
    }

    /// Parses config text (`path` only names it in errors). Unknown keys are errors, and a value
    /// of the wrong type is named by its key with what it must be.
    pub fn parse_toml(path: &Path, text: &str) -> Result<Options, ConfigError> {
        let table: toml::Table = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_owned(),
            source: Box::new(e),
        })?;
        let specs = specs();
        for (key, value) in &table {
            let Some(spec) = specs.iter().find(|s| s.key == key && !s.cli_only) else {
                let hint = if key == "config" {
                    "a config file cannot name another one".to_owned()
                } else {
                    "not an option (the keys are the long flags with `_` for `-`, listed in \
                     docs/gateway.md)"
                        .to_owned()
                };
                return Err(ConfigError::At {
                    origin: Origin::File(path.to_owned(), key.clone()),
                    reason: format!("unknown key `{key}`: {hint}"),
                });
            };
            let mut one = toml::Table::new();
            one.insert(key.clone(), value.clone());
            if let Err(e) = toml::Value::Table(one).try_into::<Options>() {
                tracing::debug!(error = %e, "config file value");
                return Err(ConfigError::At {
                    origin: Origin::File(path.to_owned(), spec.key.to_owned()),
                    reason: format!("{value} is not {}", spec.expected()),
                });
            }
        }
        let o: Options = toml::Value::Table(table)
            .try_into()
            .map_err(|e| ConfigError::Parse {
                path: path.to_owned(),
                source: Box::new(e),
            })?;
        if o.config.is_some() {
            return Err(ConfigError::invalid(
                "config",
                format!("{}: a config file cannot name another one", path.display()),
            ));
        }
        Ok(o)
    }
}

/// Where the MQTT broker is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Broker {
    /// An existing broker.
    External {
        /// Host name or address.
        host: String,
        /// TCP port.
        port: u16,
    },
    /// The embedded demo broker, listening here (the gateway connects to it).
    Embedded {
        /// Listen address.
        listen: SocketAddr,
    },
}

impl fmt::Display for Broker {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Broker::External { host, port } if host.contains(':') => write!(f, "[{host}]:{port}"),
            Broker::External { host, port } => write!(f, "{host}:{port}"),
            Broker::Embedded { listen } => write!(f, "embedded broker on {listen}"),
        }
    }
}

/// What carries the island's CAN frames.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Link {
    /// A SocketCAN interface (`can0`, `vcan0`).
    SocketCan(String),
    /// The in-memory simulated island (demo).
    Simulated {
        /// Island description file; `None` = the built-in island.
        island_file: Option<PathBuf>,
    },
}

impl fmt::Display for Link {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Link::SocketCan(iface) => write!(f, "SocketCAN {iface}"),
            Link::Simulated { island_file: None } => f.write_str("simulated island (built in)"),
            Link::Simulated {
                island_file: Some(p),
            } => write!(f, "simulated island from {}", p.display()),
        }
    }
}

/// MQTT connection settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MqttConfig {
    /// The broker.
    pub broker: Broker,
    /// Client id.
    pub client_id: String,
    /// Optional user name and password.
    pub credentials: Option<(String, String)>,
    /// TLS on, with an optional CA file.
    pub tls: Option<Option<PathBuf>>,
    /// Keep-alive interval.
    pub keep_alive: Duration,
    /// How long a PUBACK or PINGRESP may stay missing before the link is taken for dead.
    pub ack_timeout: Duration,
}

/// CAN side settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CanConfig {
    /// The link.
    pub link: Link,
    /// Expected bitrate (informational: the link's configuration sets it).
    pub bitrate: u32,
    /// Receive buffer asked for, bytes.
    pub rx_buffer: usize,
}

/// When the log file rotates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rotation {
    /// Every minute (tests).
    Minutely,
    /// Every hour.
    Hourly,
    /// Every day.
    Daily,
    /// Never.
    Never,
}

/// Logging settings (used by the binary's tracing set-up).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LogConfig {
    /// Directory of the JSON-lines file; `None` = no file.
    pub dir: Option<PathBuf>,
    /// Rotation of the file.
    pub rotation: Rotation,
    /// `--log`: a default level and `target=level` directives.
    pub filter: String,
}

/// The resolved, validated configuration [`crate::run()`] takes.
#[derive(Clone, Debug)]
pub struct Config {
    /// MQTT.
    pub mqtt: MqttConfig,
    /// CAN.
    pub can: CanConfig,
    /// Island name, if any (already applied to `topics`).
    pub island: Option<String>,
    /// Concrete topic names.
    pub topics: topic::Topics,
    /// The core's tunables.
    pub bridge: BridgeConfig,
    /// Home Assistant discovery, `None` when switched off.
    pub ha: Option<ha::HaConfig>,
    /// Logging.
    pub log: LogConfig,
    /// The audit trail.
    pub audit: AuditConfig,
    /// The island view.
    pub web: web::WebConfig,
    /// The SiLA 2 server.
    pub sila: sila::SilaConfig,
    /// Every option as resolved (defaults applied, ranges checked), for options that need no more
    /// than that.
    pub settings: Settings,
    /// What a person should know about how the configuration was completed (a lab default used
    /// because only half of broker/CAN was given); logged at start-up.
    pub warnings: Vec<String>,
    /// Where each option came from (all [`Origin::Default`] unless read by
    /// [`Config::from_env_and_args`]).
    pub origins: Origins,
}

/// The audit trail's settings (`docs/audit.md`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AuditConfig {
    /// Its directory; `None`: no trail.
    pub dir: Option<PathBuf>,
    /// How often the chain's head is published as a retained message; `None`: never.
    pub anchor: Option<Duration>,
    /// Size of the directory beyond which nothing more is recorded.
    pub max_bytes: Option<u64>,
}

/// Where each option's value came from (what `--check-config` prints, and what errors name).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Origins(Vec<(&'static str, Origin)>);

impl Origins {
    /// The origins of a parsed command line (with its environment) over `file` (read from
    /// `path`).
    pub fn new(m: &clap::ArgMatches, file: &Options, path: Option<&Path>) -> Origins {
        let in_file = file.set_keys();
        Origins(
            specs()
                .iter()
                .map(|spec| {
                    let origin = match m.value_source(spec.key) {
                        Some(clap::parser::ValueSource::CommandLine) => Origin::Flag(spec.flag()),
                        Some(clap::parser::ValueSource::EnvVariable) => Origin::Env(spec.env),
                        _ => match path {
                            Some(p) if in_file.contains(&spec.key) => {
                                Origin::File(p.to_owned(), spec.key.to_owned())
                            }
                            _ => Origin::Default,
                        },
                    };
                    (spec.key, origin)
                })
                .collect(),
        )
    }

    /// Where the option `key` (TOML key or flag name) came from.
    pub fn of(&self, key: &str) -> Origin {
        let key = key.replace('-', "_");
        self.0
            .iter()
            .find(|(k, _)| *k == key)
            .map_or(Origin::Default, |(_, o)| o.clone())
    }
}

/// A command-line or environment value clap could not read, as a [`ConfigError::At`] naming the
/// flag or the variable and what the value must be; `None` for any other clap error (`--help`).
/// Parses `args` with `cmd`; a bad value is the error in words ([`ConfigError`]), while `--help`,
/// `--version` and other usage errors end the process the way clap does.
pub(crate) fn matches(
    cmd: clap::Command,
    args: &[std::ffi::OsString],
) -> Result<clap::ArgMatches, ConfigError> {
    cmd.try_get_matches_from(args)
        .or_else(|e| value_error(&e, args).map_or_else(|| e.exit(), Err))
}

fn value_error(e: &clap::Error, args: &[std::ffi::OsString]) -> Option<ConfigError> {
    use clap::error::{ContextKind, ContextValue, ErrorKind};
    if !matches!(
        e.kind(),
        ErrorKind::ValueValidation | ErrorKind::InvalidValue
    ) {
        return None;
    }
    let text = |kind| match e.get(kind) {
        Some(ContextValue::String(s)) => Some(s.clone()),
        _ => None,
    };
    let arg = text(ContextKind::InvalidArg)?;
    let value = text(ContextKind::InvalidValue).unwrap_or_default();
    let flag = arg
        .trim_start_matches('-')
        .split([' ', '=', '['])
        .next()
        .unwrap_or_default()
        .to_owned();
    let spec = specs().into_iter().find(|s| s.flag() == flag)?;
    let long = format!("--{flag}");
    let on_command_line = args.iter().any(|a| {
        let a = a.to_string_lossy();
        a == long || a.starts_with(&format!("{long}="))
    });
    let origin = if on_command_line {
        Origin::Flag(flag)
    } else {
        Origin::Env(spec.env)
    };
    Some(ConfigError::At {
        origin,
        reason: format!("{value:?} is not {}", spec.expected()),
    })
}

impl Config {
    /// Parses the process's command line and environment, reads `--config` if given, and resolves;
    /// errors name where the bad value came from (flag, environment variable, file and key).
    /// `--help` and `--version` end the process the way clap does.
    pub fn from_env_and_args() -> Result<Config, ConfigError> {
        Config::from_args_and_env(std::env::args_os())
    }

    /// [`Config::from_env_and_args`] with the command line `args` (`args[0]` is the program).
    pub fn from_args_and_env(
        args: impl IntoIterator<Item = std::ffi::OsString>,
    ) -> Result<Config, ConfigError> {
        let args: Vec<_> = args.into_iter().collect();
        Config::from_matches(&matches(command(), &args)?)
    }

    /// Resolves a parsed command line (with its environment) over its `--config` file, recording
    /// where each value came from; errors name it.
    pub(crate) fn from_matches(m: &clap::ArgMatches) -> Result<Config, ConfigError> {
        let cli = Options::from_matches(m);
        let file = match &cli.config {
            Some(path) => Options::load(path)?,
            None => Options::default(),
        };
        let origins = Origins::new(m, &file, cli.config.as_deref());
        let mut config = Config::resolve(cli, file).map_err(|e| e.located(&origins))?;
        config.origins = origins;
        Ok(config)
    }

    /// Resolves command-line options (reading their `--config` file, if any).
    pub fn from_cli(cli: Options) -> Result<Config, ConfigError> {
        let file = match &cli.config {
            Some(path) => Options::load(path)?,
            None => Options::default(),
        };
        Config::resolve(cli, file)
    }

    /// A lab configuration with defaults everywhere else: `broker` (`HOST[:PORT]`) and a CAN interface
    /// (tests and benchmarks build gateways this way).
    pub fn lab(broker: &str, can: &str) -> Result<Config, ConfigError> {
        let cli = Options {
            broker: Some(broker.into()),
            can: Some(can.into()),
            ..Options::default()
        };
        Config::resolve(cli, Options::default())
    }

    /// True for the embedded demo (embedded broker and simulated island).
    pub fn is_demo(&self) -> bool {
        matches!(self.mqtt.broker, Broker::Embedded { .. })
            && matches!(self.can.link, Link::Simulated { .. })
    }

    /// Merges `cli` (which already carries the environment) over `file` over the defaults, and
    /// validates every value.
    pub fn resolve(cli: Options, file: Options) -> Result<Config, ConfigError> {
        let s = cli.or(file).settings()?;
        let mut warnings = Vec::new();
        let demo = s.broker.is_none() && s.can.is_none();

        if let Some(name) = &s.island {
            topic::validate_island(name)
                .map_err(|e| ConfigError::invalid("island", e.to_string()))?;
        }

        let broker = match &s.broker {
            Some(addr) => {
                let (host, port) = parse_host_port(addr)?;
                Broker::External { host, port }
            }
            None if demo => Broker::Embedded {
                listen: s.broker_listen,
            },
            None => {
                warnings.push(format!(
                    "no broker configured (--broker): using the lab broker {DEFAULT_BROKER}"
                ));
                let (host, port) = parse_host_port(DEFAULT_BROKER)?;
                Broker::External { host, port }
            }
        };

        let link = if s.sim || demo {
            if s.can.is_some() && s.sim {
                return Err(ConfigError::invalid(
                    "sim",
                    "--sim and --can exclude each other",
                ));
            }
            Link::Simulated {
                island_file: s.island_file.clone(),
            }
        } else {
            let iface = match &s.can {
                Some(iface) => iface.clone(),
                None => {
                    warnings.push(format!(
                        "no CAN interface configured (--can): using {DEFAULT_CAN}"
                    ));
                    DEFAULT_CAN.into()
                }
            };
            // IFNAMSIZ is 16 including the NUL.
            if iface.is_empty() || iface.len() > 15 || iface.contains(['/', ' ', '\0']) {
                return Err(ConfigError::invalid(
                    "can",
                    format!("{iface:?} is not an interface name"),
                ));
            }
            Link::SocketCan(iface)
        };

        let client_id = s.client_id.clone().unwrap_or_else(|| match &s.island {
            Some(name) => format!("ihex-gateway-{}", name.replace('/', "-")),
            None => "ihex-gateway".into(),
        });
        if client_id.is_empty() || client_id.len() > 128 {
            return Err(ConfigError::invalid("client-id", "must be 1 to 128 bytes"));
        }
        let credentials = match (&s.username, &s.password) {
            (Some(u), p) => Some((u.clone(), p.clone().unwrap_or_default())),
            (None, Some(_)) => {
                return Err(ConfigError::invalid(
                    "password",
                    "a password needs a --username",
                ))
            }
            (None, None) => None,
        };
        let tls = s.tls.then(|| s.tls_ca.clone());
        if tls.is_none() && s.tls_ca.is_some() {
            return Err(ConfigError::invalid("tls-ca", "given without --tls"));
        }

        let topic_of = |field: &'static str, v: &str| {
            topic::validate_topic(v)
                .map(|()| v.to_owned())
                .map_err(|e| ConfigError::invalid(field, e.to_string()))
        };
        let commands = topic_of("commands-topic", &s.commands_topic)?;
        let events = topic_of("events-topic", &s.events_topic)?;
        let availability = topic_of("availability-topic", &s.availability_topic)?;
        let node_root = topic_of("node-state-root", &s.node_state_root)?;
        let ha_prefix = topic_of("ha-discovery-prefix", &s.ha_discovery_prefix)?;
        let ha_status = topic_of("ha-status-topic", &s.ha_status_topic)?;
        let topics = topic::Topics::new(
            s.island.as_deref(),
            &commands,
            &events,
            &availability,
            &node_root,
        )
        .with_ha(s.island.as_deref(), &ha_prefix, &ha_status);
        if let Some(url) = &s.public_url {
            check_url(url)?;
        }
        let ha = s.ha_discovery.then(|| ha::HaConfig {
            topics: topics.clone(),
            island: s.island.clone(),
            configuration_url: s.public_url.clone(),
            sw_version: env!("CARGO_PKG_VERSION").to_owned(),
        });
        let distinct = [&topics.commands, &topics.events, &topics.availability];
        if distinct
            .iter()
            .enumerate()
            .any(|(i, a)| distinct[i + 1..].contains(a))
        {
            return Err(ConfigError::invalid(
                "commands-topic",
                "command, event and availability topics must differ",
            ));
        }

        let trusted_key = s
            .fw_key
            .as_deref()
            .map(ihex_image::load_public)
            .transpose()
            .map_err(|e| ConfigError::invalid("fw-key", e.to_string()))?;
        let bridge = BridgeConfig {
            health_period: Duration::from_millis(s.health_period_ms),
            lost_after_misses: s.lost_after,
            dock_timeout: Duration::from_millis(s.dock_timeout_ms),
            command_timeout: Duration::from_millis(s.command_timeout_ms),
            max_command_bytes: s.max_command_bytes,
            max_procedures: s.max_procedures,
            tx_queue: s.tx_queue,
            event_queue: s.mqtt_queue,
            fw: fwupdate::FwConfig {
                bitrate: s.bitrate,
                bus_share: s.fw_bus_share,
                // A node answers an update's requests as it acks a command.
                reply_timeout: Duration::from_millis(s.command_timeout_ms),
                trusted_key,
                ..fwupdate::FwConfig::default()
            },
            require_identity: s.require_identity.then(|| topics.user_commands.clone()),
        };

        let dir = match s.log_dir.as_deref() {
            Some("-") | Some("") => None,
            Some(dir) => Some(PathBuf::from(dir)),
            None => {
                let dir = state_dir(std::env::var_os("XDG_STATE_HOME"), std::env::var_os("HOME"));
                if dir.is_none() {
                    warnings.push(
                        "no log file: neither XDG_STATE_HOME nor HOME is set (give --log-dir)"
                            .into(),
                    );
                }
                dir
            }
        };
        let rotation = match s.log_rotation.as_str() {
            "minutely" => Rotation::Minutely,
            "hourly" => Rotation::Hourly,
            "never" => Rotation::Never,
            _ => Rotation::Daily,
        };
        let audit_dir = match s.audit_dir.as_deref() {
            Some("off") => None,
            Some(d) => Some(PathBuf::from(d)),
            None => match &dir {
                Some(log_dir) => Some(log_dir.join("audit")),
                None => {
                    warnings.push(
                        "no audit trail: no log directory (--log-dir -) and no --audit-dir".into(),
                    );
                    None
                }
            },
        };
        if s.audit_max_bytes.is_some_and(|b| b < 4096) {
            let why = "at least 4096 bytes (a few records)";
            return Err(ConfigError::invalid("audit-max-bytes", why));
        }
        let audit = AuditConfig {
            dir: audit_dir,
            anchor: (s.audit_anchor_s > 0).then(|| Duration::from_secs(s.audit_anchor_s)),
            max_bytes: s.audit_max_bytes,
        };
        let log = LogConfig {
            dir,
            rotation,
            filter: s.log.clone(),
        };

        Ok(Config {
            mqtt: MqttConfig {
                broker,
                client_id,
                credentials,
                tls,
                keep_alive: Duration::from_secs(s.keep_alive),
                ack_timeout: Duration::from_millis(s.broker_ack_timeout_ms),
            },
            can: CanConfig {
                link,
                bitrate: s.bitrate,
                rx_buffer: s.rx_buffer,
            },
            island: s.island.clone(),
            topics,
            bridge,
            ha,
            log,
            audit,
            web: web::WebConfig::from_settings(&s)?,
            sila: sila::SilaConfig::from_settings(&s)?,
            settings: s,
            warnings,
            origins: Origins::default(),
        })
    }
}

/// Where the log goes by default (the XDG base directory spec's state directory): `$XDG_STATE_HOME/ihex`
/// when that is an absolute path, else `$HOME/.local/state/ihex`; `None` without either. Never the
/// working directory, so a run from a source tree leaves it clean.
pub fn state_dir(
    xdg_state_home: Option<std::ffi::OsString>,
    home: Option<std::ffi::OsString>,
) -> Option<PathBuf> {
    let xdg = xdg_state_home
        .map(PathBuf::from)
        .filter(|p| p.is_absolute());
    let home = home
        .map(PathBuf::from)
        .filter(|p| p.is_absolute())
        .map(|h| h.join(".local").join("state"));
    xdg.or(home).map(|d| d.join("ihex"))
}

/// Checks the public URL: `http://` or `https://` and a host, as Home Assistant accepts a device's
/// `configuration_url` (it refuses the whole device otherwise).
fn check_url(url: &str) -> Result<(), ConfigError> {
    let host = url
        .strip_prefix("http://")
        .or_else(|| url.strip_prefix("https://"))
        .map(|rest| rest.split(['/', '?', '#']).next().unwrap_or(""));
    match host {
        Some(h) if !h.is_empty() && !h.contains(char::is_whitespace) => Ok(()),
        _ => Err(ConfigError::invalid(
            "public-url",
            format!("{url:?}: expected http://HOST[:PORT][/PATH] or https://…"),
        )),
    }
}

/// Parses `HOST`, `HOST:PORT`, `[V6]:PORT` or `V6` (port 1883 when absent).
pub fn parse_host_port(s: &str) -> Result<(String, u16), ConfigError> {
    let bad = |why: &str| ConfigError::invalid("broker", format!("{s:?}: {why}"));
    if let Ok(sa) = s.parse::<SocketAddr>() {
        return Ok((sa.ip().to_string(), sa.port()));
    }
    let (host, port) = match s.rsplit_once(':') {
        Some((h, p)) if !h.contains(':') => (
            h,
            p.parse::<u16>()
                .map_err(|_| bad("the port is not a number from 1 to 65535"))?,
        ),
        _ if s.parse::<std::net::Ipv6Addr>().is_ok() => (s, MQTT_PORT),
        Some(_) => return Err(bad("expected HOST[:PORT] (IPv6 as [ADDR]:PORT)")),
        None => (s, MQTT_PORT),
    };
    if port == 0 {
        return Err(bad("port 0"));
    }
    if host.is_empty() || host.contains(['/', ' ', '[', ']']) {
        return Err(bad("expected HOST[:PORT]"));
    }
    Ok((host.to_owned(), port))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Held while arguments are parsed: parsing reads the `IHEX_*` environment, which
    /// `environment_sits_between_cli_and_file` sets for a moment (tests run in parallel threads).
    static ENV: std::sync::Mutex<()> = std::sync::Mutex::new(());

    fn env_lock() -> std::sync::MutexGuard<'static, ()> {
        ENV.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn cli(args: &[&str]) -> Options {
        let _env = env_lock();
        parse(args)
    }

    fn parse(args: &[&str]) -> Options {
        let mut argv = vec!["mc-gateway"];
        argv.extend_from_slice(args);
        Options::from_args(argv).expect("valid arguments")
    }

    fn file(text: &str) -> Options {
        Options::parse_toml(Path::new("test.toml"), text).expect("valid file")
    }

    #[test]
    fn nothing_configured_is_the_demo() {
        let c = Config::resolve(Options::default(), Options::default()).unwrap();
        assert!(c.is_demo());
        assert_eq!(
            c.mqtt.broker,
            Broker::Embedded {
                listen: "127.0.0.1:1883".parse().unwrap()
            }
        );
        assert_eq!(c.can.link, Link::Simulated { island_file: None });
        assert_eq!(c.topics, topic::Topics::seed());
        assert_eq!(c.mqtt.keep_alive, Duration::from_secs(10));
        assert_eq!(c.can.bitrate, 500_000);
    }

    #[test]
    fn a_broker_alone_leaves_the_demo_and_uses_can0() {
        let c = Config::resolve(cli(&["--broker", "10.0.0.5"]), Options::default()).unwrap();
        assert!(!c.is_demo());
        assert_eq!(
            c.mqtt.broker,
            Broker::External {
                host: "10.0.0.5".into(),
                port: 1883
            }
        );
        assert_eq!(c.can.link, Link::SocketCan("can0".into()));
    }

    #[test]
    fn a_can_interface_alone_uses_the_lab_broker() {
        let c = Config::resolve(Options::default(), file("can = \"vcan3\"")).unwrap();
        assert_eq!(
            c.mqtt.broker,
            Broker::External {
                host: "192.168.1.101".into(),
                port: 1883
            }
        );
        assert_eq!(c.can.link, Link::SocketCan("vcan3".into()));
    }

    #[test]
    fn cli_beats_file_beats_default() {
        let f = file(
            "broker = \"file-host:1884\"\ncan = \"vcan1\"\nisland = \"from-file\"\nhealth_period_ms = 250\nlost_after = 5\n",
        );
        let c = Config::resolve(cli(&["--can", "vcan9", "--lost-after", "7"]), f).unwrap();
        assert_eq!(c.can.link, Link::SocketCan("vcan9".into()), "CLI over file");
        assert_eq!(c.bridge.lost_after_misses, 7, "CLI over file");
        assert_eq!(
            c.mqtt.broker,
            Broker::External {
                host: "file-host".into(),
                port: 1884
            },
            "file over default"
        );
        assert_eq!(
            c.bridge.health_period,
            Duration::from_millis(250),
            "file over default"
        );
        assert_eq!(c.island.as_deref(), Some("from-file"));
        assert_eq!(c.topics.commands, "from-file/CommandsTopic");
        assert_eq!(c.mqtt.client_id, "ihex-gateway-from-file");
        assert_eq!(
            c.bridge.dock_timeout,
            BridgeConfig::default().dock_timeout,
            "default"
        );
    }

    #[test]
    fn environment_sits_between_cli_and_file() {
        // Under the lock every parse takes, so parallel tests never see these variables.
        let env = env_lock();
        std::env::set_var("IHEX_DOCK_TIMEOUT_MS", "1234");
        std::env::set_var("IHEX_COMMAND_TIMEOUT_MS", "77");
        let parsed = parse(&["--command-timeout-ms", "88"]);
        std::env::remove_var("IHEX_DOCK_TIMEOUT_MS");
        std::env::remove_var("IHEX_COMMAND_TIMEOUT_MS");
        drop(env);
        let f = file("dock_timeout_ms = 999\ncommand_timeout_ms = 999\n");
        let c = Config::resolve(parsed, f).unwrap();
        assert_eq!(
            c.bridge.dock_timeout,
            Duration::from_millis(1234),
            "env over file"
        );
        assert_eq!(
            c.bridge.command_timeout,
            Duration::from_millis(88),
            "CLI over env"
        );
    }

    #[test]
    fn booleans_can_be_switched_off_on_the_command_line() {
        let f = file("tls = true\nbroker = \"h\"\n");
        let c = Config::resolve(cli(&["--tls=false"]), f.clone()).unwrap();
        assert_eq!(c.mqtt.tls, None);
        let c = Config::resolve(Options::default(), f).unwrap();
        assert_eq!(c.mqtt.tls, Some(None));
        let c = Config::resolve(cli(&["--sim", "--broker", "h"]), Options::default()).unwrap();
        assert!(matches!(c.can.link, Link::Simulated { .. }));
        assert!(!c.is_demo(), "simulated island on an external broker");
    }

    #[test]
    fn invalid_values_are_refused_with_their_field() {
        let cases: &[(&[&str], &str)] = &[
            (&["--broker", "h:0"], "broker"),
            (&["--broker", "h:99999"], "broker"),
            (&["--broker", "a:b:c"], "broker"),
            (&["--broker", ""], "broker"),
            (&["--island", "a/+"], "island"),
            (&["--can", "this-name-is-far-too-long"], "can"),
            (&["--health-period-ms", "0"], "health-period-ms"),
            (&["--lost-after", "0"], "lost-after"),
            (&["--tx-queue", "0"], "tx-queue"),
            (&["--keep-alive", "1"], "keep-alive"),
            (&["--log-rotation", "weekly"], "log-rotation"),
            (&["--password", "x", "--broker", "h"], "password"),
            (&["--tls-ca", "/ca.pem", "--broker", "h"], "tls-ca"),
            (&["--sim", "--can", "vcan0"], "sim"),
            (
                &["--events-topic", "CommandsTopic", "--broker", "h"],
                "commands-topic",
            ),
        ];
        for (args, field) in cases {
            match Config::resolve(cli(args), Options::default()) {
                Err(ConfigError::Invalid { field: f, .. }) => assert_eq!(f, *field, "{args:?}"),
                other => panic!("{args:?}: expected invalid {field}, got {other:?}"),
            }
        }
    }

    #[test]
    fn home_assistant_discovery_is_on_by_default_and_configurable() {
        let c = Config::resolve(
            cli(&["--broker", "h", "--island", "lab1"]),
            Options::default(),
        )
        .unwrap();
        let ha = c.ha.expect("discovery is on by default");
        assert_eq!(ha.topics, c.topics);
        assert_eq!(ha.topics.ha.discovery_prefix, "homeassistant");
        assert_eq!(ha.topics.ha.status, "homeassistant/status");
        assert_eq!(ha.topics.ha.command_filter(), "lab1/ihex/ha/+/+/set");
        assert_eq!(ha.island.as_deref(), Some("lab1"));
        assert_eq!(ha.configuration_url, None);
        assert_eq!(ha.sw_version, env!("CARGO_PKG_VERSION"));

        let c = Config::resolve(cli(&["--ha-discovery=false"]), file("broker = \"h\"\n")).unwrap();
        assert!(c.ha.is_none());

        let f = file(
            "broker = \"h\"\nha_discovery_prefix = \"ha\"\nha_status_topic = \"ha/status\"\n\
             public_url = \"http://pi.local:8080/\"\n",
        );
        let ha = Config::resolve(Options::default(), f).unwrap().ha.unwrap();
        assert_eq!(ha.topics.ha.discovery_prefix, "ha");
        assert_eq!(ha.topics.ha.status, "ha/status");
        assert_eq!(
            ha.configuration_url.as_deref(),
            Some("http://pi.local:8080/")
        );

        let cases: &[(&[&str], &str)] = &[
            (&["--public-url", "pi.local:8080"], "public-url"),
            (&["--public-url", "ftp://pi.local/"], "public-url"),
            (&["--public-url", "http:///x"], "public-url"),
            (&["--ha-discovery-prefix", "a/#"], "ha-discovery-prefix"),
            (&["--ha-status-topic", ""], "ha-status-topic"),
        ];
        for (args, field) in cases {
            let mut args = args.to_vec();
            args.extend(["--broker", "h"]);
            match Config::resolve(cli(&args), Options::default()) {
                Err(ConfigError::Invalid { field: f, .. }) => assert_eq!(f, *field, "{args:?}"),
                other => panic!("{args:?}: expected invalid {field}, got {other:?}"),
            }
        }
    }

    #[test]
    fn unknown_and_mistyped_file_keys_are_refused() {
        let p = Path::new("x.toml");
        let at = |text: &str| match Options::parse_toml(p, text) {
            Err(ConfigError::At {
                origin: Origin::File(path, key),
                reason,
            }) => {
                assert_eq!(path, p);
                (key, reason)
            }
            other => panic!("{text}: {other:?}"),
        };
        assert_eq!(at("brokr = \"h\"").0, "brokr");
        assert_eq!(
            at("lost_after = \"three\""),
            (
                "lost_after".into(),
                "\"three\" is not a whole number from 1 to 1000".into()
            )
        );
        assert_eq!(
            at("config = \"other.toml\""),
            (
                "config".into(),
                "unknown key `config`: a config file cannot name another one".into()
            )
        );
        assert_eq!(at("check_config = true").0, "check_config");
        assert!(matches!(
            Options::parse_toml(p, "lost_after = "),
            Err(ConfigError::Parse { .. })
        ));
        assert!(matches!(
            Options::load(Path::new("/nonexistent/gw.toml")),
            Err(ConfigError::Read { .. })
        ));
    }

    #[test]
    fn malformed_command_line_values_name_their_flag() {
        let _env = env_lock();
        for (args, flag) in [
            (&["--broker-listen", "nowhere"][..], "--broker-listen"),
            (&["--lost-after", "three"][..], "--lost-after"),
            (&["--tls=maybe"][..], "--tls"),
        ] {
            let mut argv = vec!["mc-gateway"];
            argv.extend_from_slice(args);
            let e = Options::from_args(argv).unwrap_err().to_string();
            assert!(e.contains(flag), "{args:?}: {e}");
        }
    }

    #[test]
    fn half_a_lab_configuration_says_which_default_it_used() {
        let c = Config::resolve(cli(&["--can", "vcan3"]), Options::default()).unwrap();
        assert_eq!(
            c.warnings,
            ["no broker configured (--broker): using the lab broker 192.168.1.101:1883"]
        );
        let c = Config::resolve(cli(&["--broker", "h"]), Options::default()).unwrap();
        assert_eq!(
            c.warnings,
            ["no CAN interface configured (--can): using can0"]
        );
        for args in [
            &[][..],
            &["--broker", "h", "--can", "vcan0"],
            &["--broker", "h", "--sim"],
        ] {
            let c = Config::resolve(cli(args), Options::default()).unwrap();
            assert!(c.warnings.is_empty(), "{args:?}: {:?}", c.warnings);
        }
    }

    #[test]
    fn start_up_descriptions_read_as_text() {
        let c = Config::resolve(Options::default(), Options::default()).unwrap();
        assert_eq!(
            c.mqtt.broker.to_string(),
            "embedded broker on 127.0.0.1:1883"
        );
        assert_eq!(c.can.link.to_string(), "simulated island (built in)");
        let c = Config::lab("[::1]:1884", "vcan0").unwrap();
        assert_eq!(c.mqtt.broker.to_string(), "[::1]:1884");
        assert_eq!(c.can.link.to_string(), "SocketCAN vcan0");
    }

    #[test]
    fn every_option_has_its_own_flag_variable_and_key() {
        let specs = specs();
        for (i, s) in specs.iter().enumerate() {
            assert!(s.env.starts_with("IHEX_"), "{}", s.key);
            assert!(!s.help.trim().is_empty(), "{}", s.key);
            for other in &specs[..i] {
                assert_ne!(s.key, other.key);
                assert_ne!(s.env, other.env);
            }
        }
        // The defaults the table shows are the ones that apply.
        let s = Options::default().settings().unwrap();
        assert_eq!(s.health_period_ms, 1000);
        assert_eq!(s.commands_topic, "CommandsTopic");
        assert_eq!(s.bitrate, 500_000);
        assert_eq!(s.log_rotation, "daily");
    }

    /// `docs/gateway.md`'s options table is the one the declaration generates (rust-analyzer's
    /// tidy style: run with `UPDATE_DOCS=1` to rewrite it).
    #[test]
    fn the_docs_options_table_is_generated_from_the_declaration() {
        const BEGIN: &str =
            "<!-- options table: generated from crates/mc-gateway/src/config/mod.rs -->\n";
        const END: &str = "<!-- end of options table -->";
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs/gateway.md");
        let doc = std::fs::read_to_string(&path).unwrap();
        let start = doc
            .find(BEGIN)
            .expect("docs/gateway.md has the table's begin marker")
            + BEGIN.len();
        let end = start
            + doc[start..]
                .find(END)
                .expect("docs/gateway.md has the end marker");
        let want = docs_table();
        if doc[start..end] != want {
            if std::env::var_os("UPDATE_DOCS").is_some() {
                let updated = format!("{}{want}{}", &doc[..start], &doc[end..]);
                std::fs::write(&path, updated).unwrap();
                eprintln!("updated {}", path.display());
            } else {
                panic!(
                    "docs/gateway.md's options table differs from the declaration; \
                     UPDATE_DOCS=1 cargo test -p mc-gateway docs_options_table rewrites it. Expected:\n{want}"
                );
            }
        }
    }

    #[test]
    fn the_log_goes_to_the_state_directory_by_default() {
        let d = |xdg: Option<&str>, home: Option<&str>| {
            state_dir(xdg.map(Into::into), home.map(Into::into))
        };
        assert_eq!(
            d(Some("/x/state"), Some("/home/u")),
            Some(PathBuf::from("/x/state/ihex"))
        );
        assert_eq!(
            d(None, Some("/home/u")),
            Some(PathBuf::from("/home/u/.local/state/ihex"))
        );
        // The spec ignores a relative XDG_STATE_HOME; a relative path would land in the cwd.
        assert_eq!(
            d(Some("rel"), Some("/home/u")),
            Some(PathBuf::from("/home/u/.local/state/ihex"))
        );
        assert_eq!(d(Some(""), None), None);
        let c = Config::resolve(cli(&["--log-dir", "-"]), Options::default()).unwrap();
        assert_eq!(c.log.dir, None);
        let c = Config::resolve(cli(&["--log-dir", "/var/log/ihex"]), Options::default()).unwrap();
        assert_eq!(c.log.dir, Some(PathBuf::from("/var/log/ihex")));
    }

    #[test]
    fn host_port_forms() {
        assert_eq!(
            parse_host_port("broker.lan").unwrap(),
            ("broker.lan".into(), 1883)
        );
        assert_eq!(
            parse_host_port("1.2.3.4:8883").unwrap(),
            ("1.2.3.4".into(), 8883)
        );
        assert_eq!(parse_host_port("[::1]:1884").unwrap(), ("::1".into(), 1884));
        assert_eq!(parse_host_port("::1").unwrap(), ("::1".into(), 1883));
    }

    #[test]
    fn the_example_config_file_parses_to_the_lab_values() {
        let text = include_str!("../../../../config/gateway.example.toml");
        let c = Config::resolve(Options::default(), file(text)).unwrap();
        assert_eq!(
            c.mqtt.broker,
            Broker::External {
                host: "192.168.1.101".into(),
                port: 1883
            }
        );
        assert_eq!(c.can.link, Link::SocketCan("can0".into()));
        assert_eq!(c.can.bitrate, 500_000);
        assert_eq!(c.mqtt.keep_alive, Duration::from_secs(10));
    }

    #[test]
    fn help_mentions_every_lab_default() {
        let help = command().render_long_help().to_string();
        for needle in [
            "192.168.1.101:1883",
            "can0",
            "500000",
            "--island",
            "IHEX_BROKER",
            "--config",
        ] {
            assert!(help.contains(needle), "--help lacks {needle}");
        }
    }
}
