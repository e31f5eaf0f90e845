//! One error enum per layer of the gateway (configuration, CAN, MQTT, embedded broker, island view),
//! gathered by [`GatewayError`] for [`crate::run()`].

use std::{io, net::SocketAddr, path::PathBuf};

/// The configuration (CLI, environment, TOML file) is unusable.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The `--config` file could not be read.
    #[error("cannot read config file {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: io::Error,
    },
    /// The `--config` file is not valid TOML for the gateway (unknown keys are refused too).
    #[error("invalid config file {path}: {source}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// What the TOML parser said.
        source: Box<toml::de::Error>,
    },
    /// A value is out of range or malformed (`field` names the option by its flag).
    #[error("invalid {field}: {reason}")]
    Invalid {
        /// The option's flag without dashes (`lost-after`).
        field: String,
        /// What is wrong, with the offending value.
        reason: String,
    },
    /// A value is out of range or malformed, named where it was given: the flag, the environment
    /// variable, or the file and key.
    #[error("invalid {origin}: {reason}")]
    At {
        /// Where the value came from.
        origin: crate::config::Origin,
        /// What is wrong, with the offending value and what is accepted.
        reason: String,
    },
}

impl ConfigError {
    /// An [`ConfigError::Invalid`] of an option given somewhere (not its default) as
    /// [`ConfigError::At`] that place.
    pub fn located(self, origins: &crate::config::Origins) -> ConfigError {
        match self {
            ConfigError::Invalid { field, reason } => match origins.of(&field) {
                crate::config::Origin::Default => ConfigError::Invalid { field, reason },
                origin => ConfigError::At { origin, reason },
            },
            other => other,
        }
    }

    pub(crate) fn invalid(field: impl Into<String>, reason: impl Into<String>) -> Self {
        ConfigError::Invalid {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

/// The CAN side failed in a way the gateway cannot retry.
#[derive(Debug, thiserror::Error)]
pub enum CanError {
    /// The protocol's gateway filters cannot be expressed as kernel filters.
    #[error("gateway filters cannot be installed: {0}")]
    Filter(#[from] ihex_proto::filter::FilterError),
    /// A socket option could not be set.
    #[error("cannot set {option} on the CAN socket: {source}")]
    SocketOption {
        /// The option (`CAN_RAW_FILTER`, `SO_RCVBUF`, ...).
        option: &'static str,
        /// The kernel's answer.
        source: io::Error,
    },
    /// The interface could not be opened at start-up.
    #[error("cannot open CAN interface {iface}: {source}")]
    Open {
        /// Interface name.
        iface: String,
        /// The kernel's answer.
        source: io::Error,
    },
}

/// The MQTT side is misconfigured (connection problems are retried, never returned).
#[derive(Debug, thiserror::Error)]
pub enum MqttError {
    /// TLS was asked for but the binary was built without the `tls` feature.
    #[error("TLS requested but this gateway was built without the `tls` cargo feature")]
    TlsUnavailable,
    /// The TLS CA file could not be read.
    #[error("cannot read TLS CA file {path}: {source}")]
    TlsCa {
        /// The file.
        path: PathBuf,
        /// Why.
        source: io::Error,
    },
}

/// The embedded broker could not be started.
#[derive(Debug, thiserror::Error)]
pub enum BrokerError {
    /// The listen address is taken (another broker is probably running).
    #[error(
        "cannot listen on {addr} for the embedded broker: {source} (is another MQTT broker running? \
         pick another address with --broker-listen, or use it with --broker)"
    )]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The OS's answer.
        source: io::Error,
    },
    /// The broker thread did not accept connections in time.
    #[error("the embedded broker on {0} did not start accepting connections")]
    NotReady(SocketAddr),
}

/// The island view could not be started.
#[derive(Debug, thiserror::Error)]
pub enum WebError {
    /// The configured address cannot be listened on.
    #[error(
        "cannot listen on {addr} for the island view: {source} (choose another address with \
         --http ADDR:PORT, or --http off)"
    )]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The OS's answer.
        source: io::Error,
    },
}

/// Why the SiLA 2 server could not start.
#[derive(Debug, thiserror::Error)]
pub enum SilaError {
    /// The configured address cannot be listened on.
    #[error(
        "cannot listen on {addr} for the SiLA server: {source} (choose another address with \
         --sila ADDR:PORT, or --sila off)"
    )]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// The OS's answer.
        source: io::Error,
    },
    /// The TLS certificate cannot be made, read, kept or used.
    #[error("SiLA server TLS: {0}")]
    Tls(String),
    /// The server's identity (its UUID and name) cannot be read or kept.
    #[error("SiLA server identity in {path}: {why} (fix or remove the file)")]
    Identity {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong.
        why: String,
    },
}

/// Everything [`crate::run()`] can fail with.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// Bad configuration.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// CAN set-up failure.
    #[error(transparent)]
    Can(#[from] CanError),
    /// MQTT set-up failure.
    #[error(transparent)]
    Mqtt(#[from] MqttError),
    /// Embedded broker failure.
    #[error(transparent)]
    Broker(#[from] BrokerError),
    /// The island view could not be started.
    #[error(transparent)]
    Web(#[from] WebError),
    /// The SiLA server could not be started.
    #[error(transparent)]
    Sila(#[from] SilaError),
    /// The simulated island could not be built.
    #[error("simulated island: {0}")]
    Sim(String),
    /// The configuration asks for the embedded broker or the simulated island, and this build has
    /// no `demo` feature.
    #[error(
        "this gateway was built without the `demo` cargo feature (embedded broker, simulated island): \
         pass --broker HOST[:PORT] and --can IFACE"
    )]
    DemoUnavailable,
    /// `--http` names an address, and this build has no `web` feature.
    #[error(
        "this gateway was built without the `web` cargo feature (island view): pass --http off"
    )]
    WebUnavailable,
    /// `--sila` names an address, and this build has no `sila` feature.
    #[error(
        "this gateway was built without the `sila` cargo feature (SiLA 2 server): pass --sila off"
    )]
    SilaUnavailable,
    /// A gateway task panicked.
    #[error("gateway task failed: {0}")]
    Task(String),
}
