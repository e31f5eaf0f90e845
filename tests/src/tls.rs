//! Test certificates, made fresh for each test: a private CA and a server certificate it signed
//! (feature `tls`). Nothing is written to disk here; the broker's [`crate::broker::Setup`] files
//! take the PEM texts.

use rcgen::{
    BasicConstraints, CertificateParams, CertifiedIssuer, DnType, IsCa, KeyPair, KeyUsagePurpose,
};

/// A CA and one server certificate, as PEM texts.
pub struct Pki {
    /// The CA's certificate (what clients trust).
    pub ca: String,
    /// The server's certificate, signed by the CA.
    pub server_cert: String,
    /// The server's private key.
    pub server_key: String,
}

/// Why certificates could not be made.
#[derive(Debug, thiserror::Error)]
#[error("test certificates: {0}")]
pub struct Error(#[from] rcgen::Error);

impl Pki {
    /// A new CA (common name `name`) and a certificate for `hosts` (DNS names or IP addresses)
    /// signed by it.
    pub fn new(name: &str, hosts: &[&str]) -> Result<Pki, Error> {
        let mut ca = CertificateParams::new(Vec::<String>::new())?;
        ca.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
        ca.distinguished_name.push(DnType::CommonName, name);
        ca.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
        let ca = CertifiedIssuer::self_signed(ca, KeyPair::generate()?)?;

        let key = KeyPair::generate()?;
        let mut server =
            CertificateParams::new(hosts.iter().map(|h| h.to_string()).collect::<Vec<_>>())?;
        server.distinguished_name.push(
            DnType::CommonName,
            hosts.first().copied().unwrap_or("localhost"),
        );
        let cert = server.signed_by(&key, &ca)?;
        Ok(Pki {
            ca: ca.pem(),
            server_cert: cert.pem(),
            server_key: key.serialize_pem(),
        })
    }
}
