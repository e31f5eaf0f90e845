//! The gateway's configuration: CLI flags (clap) with environment variables, an optional TOML file, and
//! defaults, merged with the precedence CLI > environment > file > defaults into a validated [`Config`].
//!
//! When neither a broker nor a CAN interface is configured anywhere, the result is the embedded demo:
//! an embedded broker on `--broker-listen` and a simulated island.

use std::{
    net::SocketAddr,
    path::{Path, PathBuf},
    time::Duration,
};

use clap::Parser;
use serde::Deserialize;

use ihex_gateway_core::{topic, BridgeConfig};

use crate::error::ConfigError;

/// The lab broker of the seed.
pub const DEFAULT_BROKER: &str = "192.168.1.101:1883";
/// The Pi's CAN interface (MCP2515 HAT).
pub const DEFAULT_CAN: &str = "can0";
/// Where the embedded demo broker listens.
pub const DEFAULT_BROKER_LISTEN: &str = "127.0.0.1:1883";
/// MQTT port when an address gives none.
pub const MQTT_PORT: u16 = 1883;

/// Command line of `mc-gateway`; every flag can also come from the environment variable shown, or from
/// the TOML file given with `--config` (key = flag name with `_` for `-`).
#[derive(Parser, Debug, Default, Clone)]
#[command(
    name = "mc-gateway",
    version,
    about = "iHEX main controller: MQTT JSON commands and events <-> the island's CAN bus",
    long_about = "iHEX main controller: MQTT JSON commands and events <-> the island's CAN bus.\n\n\
        Precedence: command line > environment > --config file > defaults.\n\
        With no broker and no CAN interface configured anywhere, it runs the embedded demo: an MQTT \
        broker on --broker-listen and a simulated island. In the lab (Raspberry Pi) use \
        --broker 192.168.1.101:1883 --can can0 (the seed's values) or a config file such as \
        config/gateway.example.toml."
)]
pub struct Cli {
    /// TOML configuration file (keys as the long flags, `-` written `_`).
    #[arg(long, env = "IHEX_CONFIG", value_name = "FILE")]
    pub config: Option<PathBuf>,

    /// MQTT broker to connect to, HOST[:PORT] [lab: 192.168.1.101:1883]. Unset together with --can:
    /// embedded demo broker.
    #[arg(long, env = "IHEX_BROKER", value_name = "HOST[:PORT]")]
    pub broker: Option<String>,

    /// SocketCAN interface of the island bus [lab: can0]. Unset together with --broker: simulated island.
    #[arg(long, env = "IHEX_CAN", value_name = "IFACE")]
    pub can: Option<String>,

    /// Run the simulated island instead of a CAN interface (implied by the demo).
    #[arg(long, env = "IHEX_SIM", num_args = 0..=1, require_equals = true, default_missing_value = "true", value_name = "BOOL")]
    pub sim: Option<bool>,

    /// Island description file for the simulated island (sim-node format) [default: its built-in island].
    #[arg(long, env = "IHEX_ISLAND_FILE", value_name = "FILE")]
    pub island_file: Option<PathBuf>,

    /// Bus bitrate the interface is expected to run at, bit/s (set by the system's link configuration,
    /// not by the gateway) [default: 500000].
    #[arg(long, env = "IHEX_BITRATE", value_name = "BIT/S")]
    pub bitrate: Option<u32>,

    /// Island name: every topic goes under `NAME/`, so several gateways can share one broker.
    #[arg(long, env = "IHEX_ISLAND", value_name = "NAME")]
    pub island: Option<String>,

    /// Where the embedded demo broker listens [default: 127.0.0.1:1883].
    #[arg(long, env = "IHEX_BROKER_LISTEN", value_name = "ADDR:PORT")]
    pub broker_listen: Option<String>,

    /// MQTT client id [default: ihex-gateway, or ihex-gateway-ISLAND].
    #[arg(long, env = "IHEX_CLIENT_ID", value_name = "ID")]
    pub client_id: Option<String>,

    /// MQTT user name.
    #[arg(long, env = "IHEX_MQTT_USERNAME", value_name = "USER")]
    pub username: Option<String>,

    /// MQTT password (prefer the environment variable or the file to the command line).
    #[arg(
        long,
        env = "IHEX_MQTT_PASSWORD",
        hide_env_values = true,
        value_name = "PASSWORD"
    )]
    pub password: Option<String>,

    /// Connect to the broker over TLS (needs the `tls` build feature) [default: false].
    #[arg(long, env = "IHEX_MQTT_TLS", num_args = 0..=1, require_equals = true, default_missing_value = "true", value_name = "BOOL")]
    pub tls: Option<bool>,

    /// PEM CA certificate for TLS [default: the system's roots].
    #[arg(long, env = "IHEX_MQTT_TLS_CA", value_name = "FILE")]
    pub tls_ca: Option<PathBuf>,

    /// MQTT keep-alive in seconds [default: 20].
    #[arg(long, env = "IHEX_KEEP_ALIVE", value_name = "SECS")]
    pub keep_alive: Option<u64>,

    /// Command topic (before the island prefix) [default: CommandsTopic].
    #[arg(long, env = "IHEX_COMMANDS_TOPIC", value_name = "TOPIC")]
    pub commands_topic: Option<String>,

    /// Event topic (before the island prefix) [default: EventsTopic].
    #[arg(long, env = "IHEX_EVENTS_TOPIC", value_name = "TOPIC")]
    pub events_topic: Option<String>,

    /// Retained availability topic, `online`/`offline` [default: ihex/gateway/availability].
    #[arg(long, env = "IHEX_AVAILABILITY_TOPIC", value_name = "TOPIC")]
    pub availability_topic: Option<String>,

    /// Root of the retained per-node state topics `ROOT/<id>/state` [default: ihex/node].
    #[arg(long, env = "IHEX_NODE_STATE_ROOT", value_name = "TOPIC")]
    pub node_state_root: Option<String>,

    /// Period of the broadcast health check, ms [default: 1000].
    #[arg(long, env = "IHEX_HEALTH_PERIOD_MS", value_name = "MS")]
    pub health_period_ms: Option<u64>,

    /// Missed health replies after which a node is reported lost [default: 3].
    #[arg(long, env = "IHEX_LOST_AFTER", value_name = "N")]
    pub lost_after: Option<u32>,

    /// How long to wait for a mobile element's handshake after confirming a docking, ms [default: 5000].
    #[arg(long, env = "IHEX_DOCK_TIMEOUT_MS", value_name = "MS")]
    pub dock_timeout_ms: Option<u64>,

    /// How long to wait for a node's acknowledgement of a command, ms [default: 500].
    #[arg(long, env = "IHEX_COMMAND_TIMEOUT_MS", value_name = "MS")]
    pub command_timeout_ms: Option<u64>,

    /// Largest accepted command payload in bytes [default: 4096].
    #[arg(long, env = "IHEX_MAX_COMMAND_BYTES", value_name = "BYTES")]
    pub max_command_bytes: Option<usize>,

    /// Receive buffer asked for on the CAN socket (SO_RCVBUF; SO_RCVBUFFORCE as root), bytes
    /// [default: 4194304].
    #[arg(long, env = "IHEX_RX_BUFFER", value_name = "BYTES")]
    pub rx_buffer: Option<usize>,

    /// Frames the CAN transmit queue holds before sends fail [default: 256].
    #[arg(long, env = "IHEX_TX_QUEUE", value_name = "FRAMES")]
    pub tx_queue: Option<usize>,

    /// Publications held while the broker is unreachable before the oldest are dropped (and counted)
    /// [default: 1024].
    #[arg(long, env = "IHEX_MQTT_QUEUE", value_name = "MESSAGES")]
    pub mqtt_queue: Option<usize>,

    /// Directory of the JSON-lines log file (rotated); `-` disables the file [default: logs].
    #[arg(long, env = "IHEX_LOG_DIR", value_name = "DIR")]
    pub log_dir: Option<String>,

    /// Log file rotation: minutely, hourly, daily or never [default: daily].
    #[arg(long, env = "IHEX_LOG_ROTATION", value_name = "WHEN")]
    pub log_rotation: Option<String>,

    /// Log filter (tracing env-filter syntax, e.g. `info,mc_gateway=debug`) [default: info].
    #[arg(long, env = "IHEX_LOG", value_name = "FILTER")]
    pub log: Option<String>,
}

/// The `--config` TOML file: the same settings as [`Cli`] (except `config`), every one optional.
#[derive(Deserialize, Debug, Default, Clone)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct FileConfig {
    pub broker: Option<String>,
    pub can: Option<String>,
    pub sim: Option<bool>,
    pub island_file: Option<PathBuf>,
    pub bitrate: Option<u32>,
    pub island: Option<String>,
    pub broker_listen: Option<String>,
    pub client_id: Option<String>,
    pub username: Option<String>,
    pub password: Option<String>,
    pub tls: Option<bool>,
    pub tls_ca: Option<PathBuf>,
    pub keep_alive: Option<u64>,
    pub commands_topic: Option<String>,
    pub events_topic: Option<String>,
    pub availability_topic: Option<String>,
    pub node_state_root: Option<String>,
    pub health_period_ms: Option<u64>,
    pub lost_after: Option<u32>,
    pub dock_timeout_ms: Option<u64>,
    pub command_timeout_ms: Option<u64>,
    pub max_command_bytes: Option<usize>,
    pub rx_buffer: Option<usize>,
    pub tx_queue: Option<usize>,
    pub mqtt_queue: Option<usize>,
    pub log_dir: Option<String>,
    pub log_rotation: Option<String>,
    pub log: Option<String>,
}

impl FileConfig {
    /// Reads and parses a config file.
    pub fn load(path: &Path) -> Result<FileConfig, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_owned(),
            source,
        })?;
        FileConfig::parse(path, &text)
    }

    /// Parses config text (`path` only names it in errors).
    pub fn parse(path: &Path, text: &str) -> Result<FileConfig, ConfigError> {
        toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_owned(),
            source: Box::new(e),
        })
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

/// What carries the island's CAN frames.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Link {
    /// A SocketCAN interface (`can0`, `vcan0`).
    SocketCan(String),
    /// The in-memory simulated island (demo).
    Simulated {
        /// Island description file; `None` = sim-node's built-in island.
        island_file: Option<PathBuf>,
    },
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
    /// Publications held while disconnected.
    pub queue: usize,
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
    /// Transmit queue length, frames.
    pub tx_queue: usize,
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
    /// env-filter directive.
    pub filter: String,
}

/// The resolved, validated configuration [`crate::run`] takes.
#[derive(Clone, Debug)]
pub struct Config {
    /// MQTT.
    pub mqtt: MqttConfig,
    /// CAN.
    pub can: CanConfig,
    /// Island name, if any (already applied to `topics`).
    pub island: Option<String>,
    /// Concrete topic names.
    pub topics: crate::topic::Topics,
    /// The bridge's tunables.
    pub bridge: BridgeConfig,
    /// Logging.
    pub log: LogConfig,
}

impl Config {
    /// Parses the process's command line and environment, reads `--config` if given, and resolves.
    pub fn from_env_and_args() -> Result<Config, ConfigError> {
        Config::from_cli(Cli::parse())
    }

    /// Resolves a parsed command line (reading its `--config` file, if any).
    pub fn from_cli(cli: Cli) -> Result<Config, ConfigError> {
        let file = match &cli.config {
            Some(path) => FileConfig::load(path)?,
            None => FileConfig::default(),
        };
        Config::resolve(cli, file)
    }

    /// A lab configuration with defaults everywhere else: `broker` HOST[:PORT] and a CAN interface
    /// (tests and benchmarks build gateways this way).
    pub fn lab(broker: &str, can: &str) -> Result<Config, ConfigError> {
        let cli = Cli {
            broker: Some(broker.into()),
            can: Some(can.into()),
            ..Cli::default()
        };
        Config::resolve(cli, FileConfig::default())
    }

    /// True for the embedded demo (embedded broker and simulated island).
    pub fn is_demo(&self) -> bool {
        matches!(self.mqtt.broker, Broker::Embedded { .. })
            && matches!(self.can.link, Link::Simulated { .. })
    }

    /// Merges CLI (which already carries the environment) over the file over the defaults, and
    /// validates every value.
    pub fn resolve(cli: Cli, file: FileConfig) -> Result<Config, ConfigError> {
        // CLI/env wins over the file field by field.
        macro_rules! pick {
            ($f:ident) => {
                cli.$f.clone().or_else(|| file.$f.clone())
            };
        }
        let broker = pick!(broker);
        let can = pick!(can);
        let sim = pick!(sim).unwrap_or(false);
        let demo = broker.is_none() && can.is_none();

        let island = pick!(island);
        if let Some(name) = &island {
            topic::validate_island(name)
                .map_err(|e| ConfigError::invalid("island", e.to_string()))?;
        }

        let broker = match broker {
            Some(addr) => {
                let (host, port) = parse_host_port(&addr)?;
                Broker::External { host, port }
            }
            None if demo => {
                let listen = pick!(broker_listen).unwrap_or_else(|| DEFAULT_BROKER_LISTEN.into());
                let listen = listen.parse().map_err(|_| {
                    ConfigError::invalid("broker-listen", format!("{listen:?} is not ADDR:PORT"))
                })?;
                Broker::Embedded { listen }
            }
            None => {
                let (host, port) = parse_host_port(DEFAULT_BROKER)?;
                Broker::External { host, port }
            }
        };

        let link = if sim || demo {
            if can.is_some() && sim {
                return Err(ConfigError::invalid(
                    "sim",
                    "--sim and --can exclude each other",
                ));
            }
            Link::Simulated {
                island_file: pick!(island_file),
            }
        } else {
            let iface = can.unwrap_or_else(|| DEFAULT_CAN.into());
            // IFNAMSIZ is 16 including the NUL.
            if iface.is_empty() || iface.len() > 15 || iface.contains(['/', ' ', '\0']) {
                return Err(ConfigError::invalid(
                    "can",
                    format!("{iface:?} is not an interface name"),
                ));
            }
            Link::SocketCan(iface)
        };

        let bitrate = pick!(bitrate).unwrap_or(ihex_proto::BITRATE);
        if !(10_000..=1_000_000).contains(&bitrate) {
            return Err(ConfigError::invalid(
                "bitrate",
                format!("{bitrate} not in 10000..=1000000"),
            ));
        }
        let rx_buffer = pick!(rx_buffer).unwrap_or(4 << 20);
        if !(4096..=(256 << 20)).contains(&rx_buffer) {
            return Err(ConfigError::invalid(
                "rx-buffer",
                format!("{rx_buffer} not in 4096..=268435456"),
            ));
        }
        let tx_queue = in_range("tx-queue", pick!(tx_queue).unwrap_or(256), 1, 65_536)?;
        let mqtt_queue = in_range("mqtt-queue", pick!(mqtt_queue).unwrap_or(1024), 1, 1 << 20)?;

        let client_id = pick!(client_id).unwrap_or_else(|| match &island {
            Some(name) => format!("ihex-gateway-{}", name.replace('/', "-")),
            None => "ihex-gateway".into(),
        });
        if client_id.is_empty() || client_id.len() > 128 {
            return Err(ConfigError::invalid("client-id", "must be 1 to 128 bytes"));
        }
        let credentials = match (pick!(username), pick!(password)) {
            (Some(u), p) => Some((u, p.unwrap_or_default())),
            (None, Some(_)) => {
                return Err(ConfigError::invalid(
                    "password",
                    "a password needs a --username",
                ))
            }
            (None, None) => None,
        };
        let tls = pick!(tls).unwrap_or(false).then(|| pick!(tls_ca));
        if tls.is_none() && pick!(tls_ca).is_some() {
            return Err(ConfigError::invalid("tls-ca", "given without --tls"));
        }
        let keep_alive = in_range("keep-alive", pick!(keep_alive).unwrap_or(20), 5, 3600)?;

        let topic_of = |field: &'static str, v: Option<String>, default: &str| {
            let v = v.unwrap_or_else(|| default.into());
            topic::validate_topic(&v)
                .map(|()| v)
                .map_err(|e| ConfigError::invalid(field, e.to_string()))
        };
        let commands = topic_of("commands-topic", pick!(commands_topic), topic::COMMANDS)?;
        let events = topic_of("events-topic", pick!(events_topic), topic::EVENTS)?;
        let availability = topic_of(
            "availability-topic",
            pick!(availability_topic),
            topic::AVAILABILITY,
        )?;
        let node_root = topic_of(
            "node-state-root",
            pick!(node_state_root),
            topic::NODE_STATE_ROOT,
        )?;
        let topics = topic::Topics::new(
            island.as_deref(),
            &commands,
            &events,
            &availability,
            &node_root,
        );
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

        let d = BridgeConfig::default();
        let ms = |field, v: Option<u64>, default: Duration, lo: u64, hi: u64| {
            let v = v.unwrap_or(default.as_millis() as u64);
            in_range(field, v, lo, hi).map(Duration::from_millis)
        };
        let bridge = BridgeConfig {
            health_period: ms(
                "health-period-ms",
                pick!(health_period_ms),
                d.health_period,
                10,
                3_600_000,
            )?,
            lost_after_misses: in_range(
                "lost-after",
                pick!(lost_after).unwrap_or(d.lost_after_misses),
                1,
                1000,
            )?,
            dock_timeout: ms(
                "dock-timeout-ms",
                pick!(dock_timeout_ms),
                d.dock_timeout,
                10,
                600_000,
            )?,
            command_timeout: ms(
                "command-timeout-ms",
                pick!(command_timeout_ms),
                d.command_timeout,
                1,
                600_000,
            )?,
            max_command_bytes: in_range(
                "max-command-bytes",
                pick!(max_command_bytes).unwrap_or(d.max_command_bytes),
                64,
                1 << 20,
            )?,
        };

        let dir = pick!(log_dir).unwrap_or_else(|| "logs".into());
        let rotation = match pick!(log_rotation).as_deref().unwrap_or("daily") {
            "minutely" => Rotation::Minutely,
            "hourly" => Rotation::Hourly,
            "daily" => Rotation::Daily,
            "never" => Rotation::Never,
            other => {
                return Err(ConfigError::invalid(
                    "log-rotation",
                    format!("{other:?} is not minutely, hourly, daily or never"),
                ))
            }
        };
        let log = LogConfig {
            dir: (dir != "-" && !dir.is_empty()).then(|| PathBuf::from(dir)),
            rotation,
            filter: pick!(log).unwrap_or_else(|| "info".into()),
        };

        Ok(Config {
            mqtt: MqttConfig {
                broker,
                client_id,
                credentials,
                tls,
                keep_alive: Duration::from_secs(keep_alive),
                queue: mqtt_queue,
            },
            can: CanConfig {
                link,
                bitrate,
                rx_buffer,
                tx_queue,
            },
            island,
            topics,
            bridge,
            log,
        })
    }
}

fn in_range<T: PartialOrd + std::fmt::Display + Copy>(
    field: &'static str,
    v: T,
    lo: T,
    hi: T,
) -> Result<T, ConfigError> {
    if v < lo || v > hi {
        return Err(ConfigError::invalid(
            field,
            format!("{v} not in {lo}..={hi}"),
        ));
    }
    Ok(v)
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
                .map_err(|_| bad("port is not a number 1..=65535"))?,
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

    fn cli(args: &[&str]) -> Cli {
        let mut argv = vec!["mc-gateway"];
        argv.extend_from_slice(args);
        Cli::try_parse_from(argv).expect("valid arguments")
    }

    fn file(text: &str) -> FileConfig {
        FileConfig::parse(Path::new("test.toml"), text).expect("valid file")
    }

    #[test]
    fn nothing_configured_is_the_demo() {
        let c = Config::resolve(Cli::default(), FileConfig::default()).unwrap();
        assert!(c.is_demo());
        assert_eq!(
            c.mqtt.broker,
            Broker::Embedded {
                listen: "127.0.0.1:1883".parse().unwrap()
            }
        );
        assert_eq!(c.can.link, Link::Simulated { island_file: None });
        assert_eq!(c.topics, topic::Topics::seed());
        assert_eq!(c.mqtt.keep_alive, Duration::from_secs(20));
        assert_eq!(c.can.bitrate, 500_000);
    }

    #[test]
    fn a_broker_alone_leaves_the_demo_and_uses_can0() {
        let c = Config::resolve(cli(&["--broker", "10.0.0.5"]), FileConfig::default()).unwrap();
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
        let c = Config::resolve(Cli::default(), file("can = \"vcan3\"")).unwrap();
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
        // Variables unique to this test, so parallel tests do not see them.
        std::env::set_var("IHEX_DOCK_TIMEOUT_MS", "1234");
        std::env::set_var("IHEX_COMMAND_TIMEOUT_MS", "77");
        let parsed = cli(&["--command-timeout-ms", "88"]);
        std::env::remove_var("IHEX_DOCK_TIMEOUT_MS");
        std::env::remove_var("IHEX_COMMAND_TIMEOUT_MS");
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
        let c = Config::resolve(Cli::default(), f).unwrap();
        assert_eq!(c.mqtt.tls, Some(None));
        let c = Config::resolve(cli(&["--sim", "--broker", "h"]), FileConfig::default()).unwrap();
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
            (&["--broker-listen", "nowhere"], "broker-listen"),
            (&["--sim", "--can", "vcan0"], "sim"),
            (
                &["--events-topic", "CommandsTopic", "--broker", "h"],
                "commands-topic",
            ),
        ];
        for (args, field) in cases {
            match Config::resolve(cli(args), FileConfig::default()) {
                Err(ConfigError::Invalid { field: f, .. }) => assert_eq!(f, *field, "{args:?}"),
                other => panic!("{args:?}: expected invalid {field}, got {other:?}"),
            }
        }
    }

    #[test]
    fn unknown_and_mistyped_file_keys_are_refused() {
        let p = Path::new("x.toml");
        assert!(matches!(
            FileConfig::parse(p, "brokr = \"h\""),
            Err(ConfigError::Parse { .. })
        ));
        assert!(matches!(
            FileConfig::parse(p, "lost_after = \"three\""),
            Err(ConfigError::Parse { .. })
        ));
        assert!(matches!(
            FileConfig::load(Path::new("/nonexistent/gw.toml")),
            Err(ConfigError::Read { .. })
        ));
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
        let text = include_str!("../../../config/gateway.example.toml");
        let c = Config::resolve(Cli::default(), file(text)).unwrap();
        assert_eq!(
            c.mqtt.broker,
            Broker::External {
                host: "192.168.1.101".into(),
                port: 1883
            }
        );
        assert_eq!(c.can.link, Link::SocketCan("can0".into()));
        assert_eq!(c.can.bitrate, 500_000);
        assert_eq!(c.mqtt.keep_alive, Duration::from_secs(20));
    }

    #[test]
    fn help_mentions_every_lab_default() {
        use clap::CommandFactory;
        let help = Cli::command().render_long_help().to_string();
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
