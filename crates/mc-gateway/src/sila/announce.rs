//! SiLA server discovery (SiLA 2 v1.1, part B): the server announced over mDNS/DNS-SD as
//! `UUID._sila._tcp.local.` with its version, name and description in TXT records, and with TLS its
//! certificate, one PEM line per record `ca0`, `ca1`, … (what clients verify an untrusted server
//! with). A server on a loopback address is announced on the loopback interface only, with
//! `127.0.0.1`: only clients on the same machine can reach it anyway.

use std::net::SocketAddr;

use mdns_sd::{IfKind, ServiceDaemon, ServiceInfo};
use tracing::{info, warn};

/// The DNS-SD service type of SiLA servers.
pub const SERVICE_TYPE: &str = "_sila._tcp.local.";

/// A TXT record's `key=value` is at most 255 bytes.
const TXT_MAX: usize = 255;

/// What the announcement says.
#[derive(Clone, Debug)]
pub struct Announcement {
    /// The server UUID (the instance name).
    pub uuid: String,
    /// `version`.
    pub version: String,
    /// `server_name`.
    pub server_name: String,
    /// `description`.
    pub description: String,
    /// The certificate clients verify the server with (PEM), when it serves TLS.
    pub ca: Option<String>,
}

/// `value` cut so that `key=value` fits a TXT record (at a character boundary).
fn fit(key: &str, value: &str) -> String {
    let room = TXT_MAX - key.len() - 1;
    let mut end = value.len().min(room);
    while !value.is_char_boundary(end) {
        end -= 1;
    }
    value[..end].to_owned()
}

impl Announcement {
    /// The TXT records, in order.
    pub fn txt(&self) -> Vec<(String, String)> {
        let mut txt = vec![
            ("version".to_owned(), fit("version", &self.version)),
            (
                "server_name".to_owned(),
                fit("server_name", &self.server_name),
            ),
            (
                "description".to_owned(),
                fit("description", &self.description),
            ),
        ];
        if let Some(ca) = &self.ca {
            for (i, line) in ca.lines().enumerate() {
                let key = format!("ca{i}");
                let value = fit(&key, line);
                txt.push((key, value));
            }
        }
        txt
    }
}

/// The running announcement; withdrawn when dropped.
pub struct Announcer {
    daemon: ServiceDaemon,
    fullname: String,
}

impl Announcer {
    /// Announces a server listening on `addr`; `None` (with a warning) when mDNS cannot run here.
    pub fn start(addr: SocketAddr, host: &str, what: &Announcement) -> Option<Announcer> {
        let started = (|| {
            let daemon = ServiceDaemon::new()?;
            let host_name = format!("{host}.local.");
            let txt = what.txt();
            let info = if addr.ip().is_loopback() {
                daemon.disable_interface(IfKind::All)?;
                daemon.enable_interface(IfKind::LoopbackV4)?;
                ServiceInfo::new(
                    SERVICE_TYPE,
                    &what.uuid,
                    &host_name,
                    "127.0.0.1",
                    addr.port(),
                    &txt[..],
                )?
            } else if addr.ip().is_unspecified() {
                ServiceInfo::new(
                    SERVICE_TYPE,
                    &what.uuid,
                    &host_name,
                    "",
                    addr.port(),
                    &txt[..],
                )?
                .enable_addr_auto()
            } else {
                ServiceInfo::new(
                    SERVICE_TYPE,
                    &what.uuid,
                    &host_name,
                    addr.ip(),
                    addr.port(),
                    &txt[..],
                )?
            };
            let fullname = info.get_fullname().to_owned();
            daemon.register(info)?;
            Ok::<_, mdns_sd::Error>(Announcer { daemon, fullname })
        })();
        match started {
            Ok(a) => {
                info!(name = %a.fullname, "SiLA server announced (mDNS)");
                Some(a)
            }
            Err(e) => {
                warn!(error = %e, "SiLA server not announced: mDNS unavailable (clients need its address)");
                None
            }
        }
    }
}

impl Drop for Announcer {
    fn drop(&mut self) {
        // Goodbye packets, so browsers forget the server at once; best effort.
        let _ = self.daemon.unregister(&self.fullname);
        let _ = self.daemon.shutdown();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_txt_records_fit_and_carry_the_certificate_line_by_line() {
        let a = Announcement {
            uuid: "u".into(),
            version: "0.1.0".into(),
            server_name: "ä".repeat(200),
            description: "d".into(),
            ca: Some("-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n".into()),
        };
        let txt = a.txt();
        let keys: Vec<&str> = txt.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(
            keys,
            ["version", "server_name", "description", "ca0", "ca1", "ca2"]
        );
        assert!(txt.iter().all(|(k, v)| k.len() + 1 + v.len() <= TXT_MAX));
        assert_eq!(txt[4].1, "MIIB");
    }
}
