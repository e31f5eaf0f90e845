//! The SiLA 2 server's settings (`sila` of the options table), checked at start-up whether or not
//! this build has the `sila` feature.

use std::net::{IpAddr, Ipv4Addr, SocketAddr};

use super::Settings;
use crate::error::ConfigError;

/// Where the SiLA server listens unless told otherwise (50052: the port SiLA's examples use).
pub const DEFAULT_SILA: SocketAddr = SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), 50052);

/// The value of `--sila` that switches the server off.
pub const SILA_OFF: &str = "off";

/// The SiLA server's checked settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SilaConfig {
    /// Where it listens; `None` when it is off.
    pub listen: Option<SocketAddr>,
    /// The address was configured rather than defaulted: then failing to listen there stops the
    /// gateway; a taken default port only switches the server off.
    pub configured: bool,
}

impl SilaConfig {
    /// The server's part of the resolved options.
    pub fn from_settings(s: &Settings) -> Result<SilaConfig, ConfigError> {
        let listen = match s.sila.as_deref().map(str::trim) {
            None => Some(DEFAULT_SILA),
            Some(SILA_OFF) => None,
            Some(addr) => Some(addr.parse::<SocketAddr>().map_err(|_| {
                ConfigError::invalid(
                    "sila",
                    format!(
                        "{addr:?} is not ADDR:PORT (e.g. 127.0.0.1:50052, [::]:50052) or \
                         {SILA_OFF}"
                    ),
                )
            })?),
        };
        Ok(SilaConfig {
            listen,
            configured: s.sila.is_some(),
        })
    }
}
