//! The SiLA 2 server's settings (`sila` of the options table), checked at start-up whether or not
//! this build has the `sila` feature.

use std::{
    net::{IpAddr, Ipv4Addr, SocketAddr},
    path::PathBuf,
};

use super::Settings;
use crate::error::ConfigError;

/// Where the SiLA server listens unless told otherwise (50052: the port SiLA's examples use).
pub const DEFAULT_SILA: SocketAddr = SocketAddr::new(IpAddr::V4(Ipv4Addr::LOCALHOST), 50052);

/// The value of `--sila` that switches the server off.
pub const SILA_OFF: &str = "off";

/// How the SiLA server secures its connections.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Security {
    /// TLS with a self-signed certificate the gateway makes once and keeps (the default).
    SelfSigned,
    /// TLS with the user's certificate and key.
    Files {
        /// The certificate (PEM).
        cert: PathBuf,
        /// Its private key (PEM).
        key: PathBuf,
    },
    /// Plaintext (`sila_insecure`).
    Insecure,
}

/// The SiLA server's checked settings.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SilaConfig {
    /// Where it listens; `None` when it is off.
    pub listen: Option<SocketAddr>,
    /// The address was configured rather than defaulted: then failing to listen there stops the
    /// gateway; a taken default port only switches the server off.
    pub configured: bool,
    /// TLS or not.
    pub security: Security,
    /// Announced over mDNS.
    pub announce: bool,
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
        let security = match (&s.sila_cert, &s.sila_key, s.sila_insecure) {
            (None, None, false) => Security::SelfSigned,
            (Some(cert), Some(key), false) => Security::Files {
                cert: cert.clone(),
                key: key.clone(),
            },
            (None, None, true) => Security::Insecure,
            (_, _, true) => {
                return Err(ConfigError::invalid(
                    "sila-insecure",
                    "given with --sila-cert/--sila-key: choose TLS or plaintext",
                ))
            }
            (Some(_), None, _) => {
                return Err(ConfigError::invalid("sila-cert", "needs --sila-key"))
            }
            (None, Some(_), _) => {
                return Err(ConfigError::invalid("sila-key", "needs --sila-cert"))
            }
        };
        if let (Security::Insecure, Some(addr)) = (&security, listen) {
            if !addr.ip().is_loopback() && !s.sila_insecure_anywhere {
                return Err(ConfigError::invalid(
                    "sila-insecure",
                    format!(
                        "plaintext on {addr} would let anyone on the network read and drive the \
                         island unencrypted: keep TLS (the default), listen on a loopback address, \
                         or add --sila-insecure-anywhere"
                    ),
                ));
            }
        }
        Ok(SilaConfig {
            listen,
            configured: s.sila.is_some(),
            security,
            announce: s.sila_announce != "off",
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::{Config, Options};

    fn resolve(args: &[&str]) -> Result<SilaConfig, String> {
        let mut argv = vec!["mc-gateway"];
        argv.extend_from_slice(args);
        let cli = Options::from_args(argv).map_err(|e| e.to_string())?;
        Config::resolve(cli, Options::default())
            .map(|c| c.sila)
            .map_err(|e| e.to_string())
    }

    #[test]
    fn tls_unless_plaintext_is_asked_for_and_plaintext_stays_on_loopback() {
        let c = resolve(&[]).unwrap();
        assert_eq!(c.listen, Some(DEFAULT_SILA));
        assert_eq!(c.security, Security::SelfSigned);
        assert_eq!(resolve(&["--sila", "off"]).unwrap().listen, None);
        assert_eq!(
            resolve(&["--sila-insecure"]).unwrap().security,
            Security::Insecure
        );
        let e = resolve(&["--sila", "0.0.0.0:50052", "--sila-insecure"]).unwrap_err();
        assert!(e.contains("--sila-insecure-anywhere"), "{e}");
        let c = resolve(&[
            "--sila",
            "0.0.0.0:50052",
            "--sila-insecure",
            "--sila-insecure-anywhere",
        ])
        .unwrap();
        assert_eq!(c.security, Security::Insecure);
        assert!(resolve(&["--sila-cert", "c.pem"])
            .unwrap_err()
            .contains("needs --sila-key"));
        assert!(resolve(&["--sila", "nowhere"]).is_err());
    }
}
