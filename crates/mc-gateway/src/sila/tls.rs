//! The SiLA server's certificate, as SiLA 2 v1.1 asks of a server that encrypts by default: made
//! once (self-signed, CN `SiLA2`, the server UUID in the extension 1.3.6.1.4.1.58583) and kept in the
//! state directory, so clients can pin it; made again only when the names it must carry change (the
//! host name or the addresses clients reach the server at). Or the user's own certificate and key.

use std::{
    net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr},
    path::{Path, PathBuf},
};

use crate::error::SilaError;

/// The OID of the extension that carries the server UUID (SiLA 2 v1.1, part B).
pub const UUID_OID: [u64; 7] = [1, 3, 6, 1, 4, 1, 58583];

/// A certificate and its private key, PEM.
#[derive(Clone, Debug)]
pub struct Pem {
    /// The certificate (what a client trusts: SiLA's "CA").
    pub cert: String,
    /// The private key.
    pub key: String,
}

/// The names a certificate for a server listening on `listen` must carry: `localhost`, the host
/// name, the loopback addresses, and the listening address — or, when it listens on every
/// interface, every address of `interfaces`.
pub fn names(listen: SocketAddr, host: Option<&str>, interfaces: &[IpAddr]) -> Vec<String> {
    let mut ips = vec![
        IpAddr::V4(Ipv4Addr::LOCALHOST),
        IpAddr::V6(Ipv6Addr::LOCALHOST),
    ];
    if listen.ip().is_unspecified() {
        ips.extend(interfaces.iter().copied());
    } else {
        ips.push(listen.ip());
    }
    let mut names = vec!["localhost".to_owned()];
    names.extend(host.filter(|h| !h.is_empty()).map(str::to_owned));
    for ip in ips {
        let ip = ip.to_string();
        if !names.contains(&ip) {
            names.push(ip);
        }
    }
    names
}

/// A new self-signed certificate for the server `uuid`, naming `names` (host names or addresses).
pub fn self_signed(uuid: &str, names: &[String]) -> Result<Pem, String> {
    use rcgen::{
        CertificateParams, CustomExtension, DnType, ExtendedKeyUsagePurpose, KeyPair,
        KeyUsagePurpose,
    };
    let mut params = CertificateParams::new(names.to_vec()).map_err(|e| e.to_string())?;
    params.distinguished_name.push(DnType::CommonName, "SiLA2");
    params
        .distinguished_name
        .push(DnType::OrganizationName, "iHEX island");
    params.key_usages = vec![
        KeyUsagePurpose::DigitalSignature,
        KeyUsagePurpose::KeyEncipherment,
    ];
    params.extended_key_usages = vec![ExtendedKeyUsagePurpose::ServerAuth];
    // SiLA's reference implementation writes the UUID's text as the extension's raw value.
    params
        .custom_extensions
        .push(CustomExtension::from_oid_content(
            &UUID_OID,
            uuid.as_bytes().to_vec(),
        ));
    let key = KeyPair::generate().map_err(|e| e.to_string())?;
    let cert = params.self_signed(&key).map_err(|e| e.to_string())?;
    Ok(Pem {
        cert: cert.pem(),
        key: key.serialize_pem(),
    })
}

/// Where the self-signed certificate of a server is kept: beside its identity file (`sila.json`
/// → `sila-cert.pem`, `sila-key.pem`).
pub fn files(identity_file: &Path) -> (PathBuf, PathBuf) {
    let stem = identity_file
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or("sila");
    (
        identity_file.with_file_name(format!("{stem}-cert.pem")),
        identity_file.with_file_name(format!("{stem}-key.pem")),
    )
}

/// Reads a PEM file the user configured.
pub fn read(path: &Path) -> Result<String, SilaError> {
    std::fs::read_to_string(path).map_err(|e| SilaError::Tls(format!("{}: {e}", path.display())))
}

/// Keeps a new self-signed certificate in `files` (the key readable by the gateway's user only).
pub fn save(pem: &Pem, (cert, key): (&Path, &Path)) -> Result<(), SilaError> {
    use std::io::Write;
    let err = |p: &Path, e: std::io::Error| SilaError::Tls(format!("{}: {e}", p.display()));
    std::fs::write(cert, &pem.cert).map_err(|e| err(cert, e))?;
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut f = options.open(key).map_err(|e| err(key, e))?;
    f.write_all(pem.key.as_bytes()).map_err(|e| err(key, e))
}

/// The host's name, from the kernel (`None` where it cannot be read).
pub fn host_name() -> Option<String> {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .map(|h| h.trim().to_owned())
        .filter(|h| !h.is_empty())
}

/// The addresses of this machine's interfaces, loopback left out.
pub fn interface_addresses() -> Vec<IpAddr> {
    if_addrs::get_if_addrs()
        .unwrap_or_default()
        .into_iter()
        .filter(|i| !i.is_loopback())
        .map(|i| i.ip())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_certificate_names_where_clients_reach_the_server() {
        let lan: IpAddr = "192.168.1.20".parse().unwrap();
        let any: SocketAddr = "0.0.0.0:50052".parse().unwrap();
        assert_eq!(
            names(any, Some("ihex-pi"), &[lan]),
            ["localhost", "ihex-pi", "127.0.0.1", "::1", "192.168.1.20"]
        );
        let lo: SocketAddr = "127.0.0.1:50052".parse().unwrap();
        assert_eq!(
            names(lo, None, &[lan]),
            ["localhost", "127.0.0.1", "::1"],
            "loopback only: the LAN address is not named"
        );
    }

    #[test]
    fn a_self_signed_certificate_carries_the_uuid() {
        let uuid = "4b6ee612-6605-40a8-843a-31ee72b02d5c";
        let pem = self_signed(uuid, &["localhost".into(), "127.0.0.1".into()]).unwrap();
        assert!(pem.cert.starts_with("-----BEGIN CERTIFICATE-----"));
        assert!(pem.key.contains("PRIVATE KEY"));
        // The DER holds the UUID's text verbatim, after the extension's OID.
        let der = der_of(&pem.cert);
        // 1.3.6.1.4.1.58583, DER-encoded, then the extension's value: an OCTET STRING of the text.
        let oid = [0x06, 0x08, 0x2b, 0x06, 0x01, 0x04, 0x01, 0x83, 0xc9, 0x57];
        let mut value = vec![0x04, 36];
        value.extend_from_slice(uuid.as_bytes());
        let at = der
            .windows(oid.len())
            .position(|w| w == oid)
            .expect("the OID");
        assert_eq!(
            &der[at + oid.len()..at + oid.len() + value.len()],
            &value[..]
        );
    }

    /// The DER inside a one-certificate PEM.
    fn der_of(pem: &str) -> Vec<u8> {
        use base64::Engine as _;
        let body: String = pem.lines().filter(|l| !l.starts_with("-----")).collect();
        base64::engine::general_purpose::STANDARD
            .decode(body)
            .unwrap()
    }
}
