//! Issuing the deployment's certificates: one CA, and for each process a
//! certificate it serves and presents as a client (ECDSA P-256).

use crate::tokens::is_plain_name;
use rcgen::{
    BasicConstraints, CertificateParams, DnType, ExtendedKeyUsagePurpose, IsCa, Issuer, KeyPair,
    KeyUsagePurpose,
};
use time::{Duration, OffsetDateTime};

/// A certificate and its private key, both PEM.
#[derive(Clone)]
pub struct Issued {
    /// The certificate.
    pub cert_pem: String,
    /// The private key.
    pub key_pem: String,
}

impl std::fmt::Debug for Issued {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Issued").finish_non_exhaustive()
    }
}

/// What went wrong issuing a certificate.
#[derive(Debug, thiserror::Error)]
pub enum CertError {
    /// A host name that cannot go in a certificate.
    #[error("host `{0}` is neither a DNS name nor an IP address")]
    Host(String),
    /// The CA files do not read as a CA certificate and its key.
    #[error("the CA: {0}")]
    Ca(String),
    /// A name that cannot name the certificate's files.
    #[error(
        "certificate name `{0}`: use 1 to 64 letters, digits, `.`, `_` or `-` (it names the files NAME.crt and NAME.key)"
    )]
    Name(String),
    /// The validity period.
    #[error("--days must be 1 to 36500, got {0}")]
    Days(u32),
    /// rcgen refused.
    #[error("cannot issue the certificate: {0}")]
    Issue(#[from] rcgen::Error),
}

/// Checks that the certificate in `cert_pem` (a leaf, then any
/// intermediates) is valid now for serving TLS and chains to a CA in
/// `ca_pem`: the check a client that trusts that CA makes.
pub fn check_issued_by(cert_pem: &[u8], ca_pem: &[u8]) -> Result<(), String> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, UnixTime};
    let chain = CertificateDer::pem_slice_iter(cert_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("the certificate does not load: {e}"))?;
    let (leaf, intermediates) = chain
        .split_first()
        .ok_or("the certificate file holds no certificate")?;
    let cas = CertificateDer::pem_slice_iter(ca_pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("the CA does not load: {e}"))?;
    let anchors = cas
        .iter()
        .map(|ca| webpki::anchor_from_trusted_cert(ca).map(|a| a.to_owned()))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| format!("the CA does not load: {e}"))?;
    let leaf = webpki::EndEntityCert::try_from(leaf)
        .map_err(|e| format!("the certificate does not parse: {e}"))?;
    let algorithms = rustls::crypto::ring::default_provider()
        .signature_verification_algorithms
        .all;
    leaf.verify_for_usage(
        algorithms,
        &anchors,
        intermediates,
        UnixTime::now(),
        webpki::KeyUsage::server_auth(),
        None,
        None,
    )
    .map(|_| ())
    .map_err(|e| {
        format!(
            "the certificate does not chain to the CA in `ca` ({e}): clients that trust that CA would refuse it"
        )
    })
}

/// A new CA named `name`, valid for `days`.
pub fn new_ca(name: &str, days: u32) -> Result<Issued, CertError> {
    let mut params = CertificateParams::new(Vec::<String>::new())?;
    params.distinguished_name.push(DnType::CommonName, name);
    params.is_ca = IsCa::Ca(BasicConstraints::Constrained(0));
    params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    validity(&mut params, days)?;
    let key = KeyPair::generate()?;
    let cert = params.self_signed(&key)?;
    Ok(Issued {
        cert_pem: cert.pem(),
        key_pem: key.serialize_pem(),
    })
}

/// A certificate for `name`, valid for `hosts` (DNS names or IP
/// addresses) for `days`, for serving and for client authentication,
/// signed by the CA in `ca`.
pub fn issue(ca: &Issued, name: &str, hosts: &[String], days: u32) -> Result<Issued, CertError> {
    if !is_plain_name(name) {
        return Err(CertError::Name(name.into()));
    }
    for host in hosts {
        let ok = host.parse::<std::net::IpAddr>().is_ok()
            || (!host.is_empty()
                && host
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b"-.*".contains(&b)));
        if !ok {
            return Err(CertError::Host(host.clone()));
        }
    }
    let ca_key = KeyPair::from_pem(&ca.key_pem).map_err(|e| CertError::Ca(e.to_string()))?;
    let issuer =
        Issuer::from_ca_cert_pem(&ca.cert_pem, ca_key).map_err(|e| CertError::Ca(e.to_string()))?;
    let mut params = CertificateParams::new(hosts.to_vec())?;
    params.distinguished_name.push(DnType::CommonName, name);
    params.key_usages = vec![
        KeyUsagePurpose::DigitalSignature,
        KeyUsagePurpose::KeyEncipherment,
    ];
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    validity(&mut params, days)?;
    let key = KeyPair::generate()?;
    let cert = params.signed_by(&key, &issuer)?;
    Ok(Issued {
        cert_pem: cert.pem(),
        key_pem: key.serialize_pem(),
    })
}

fn validity(params: &mut CertificateParams, days: u32) -> Result<(), CertError> {
    if !(1..=36_500).contains(&days) {
        return Err(CertError::Days(days));
    }
    let now = OffsetDateTime::now_utc();
    // An hour's slack for clocks a little behind.
    params.not_before = now - Duration::hours(1);
    params.not_after = now + Duration::days(i64::from(days));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn issues_a_ca_and_a_leaf_it_signs() {
        let ca = new_ca("tweezer test CA", 30).unwrap();
        assert!(ca.cert_pem.starts_with("-----BEGIN CERTIFICATE-----"));
        assert!(ca.key_pem.contains("PRIVATE KEY"));
        let leaf = issue(
            &ca,
            "learner",
            &["localhost".into(), "127.0.0.1".into()],
            30,
        )
        .unwrap();
        assert_ne!(leaf.cert_pem, ca.cert_pem);
        assert!(!format!("{leaf:?}").contains("PRIVATE"));
        let err = issue(&ca, "x", &["bad host".into()], 30).unwrap_err();
        assert!(err.to_string().contains("bad host"));
        assert!(new_ca("x", 0).is_err());
        let garbled = Issued {
            cert_pem: ca.cert_pem.clone(),
            key_pem: "not a key".into(),
        };
        assert!(matches!(
            issue(&garbled, "x", &["a".into()], 1),
            Err(CertError::Ca(_))
        ));
        for name in ["../evil", "a/b", "", "/etc/x"] {
            assert!(
                matches!(issue(&ca, name, &["a".into()], 1), Err(CertError::Name(_))),
                "{name:?}"
            );
        }
    }

    #[test]
    fn a_certificate_is_checked_against_its_ca() {
        let ca = new_ca("ours", 30).unwrap();
        let other = new_ca("theirs", 30).unwrap();
        let leaf = issue(&ca, "learner", &["localhost".into()], 30).unwrap();
        let foreign = issue(&other, "learner", &["localhost".into()], 30).unwrap();
        let (leaf, foreign) = (leaf.cert_pem.as_bytes(), foreign.cert_pem.as_bytes());
        check_issued_by(leaf, ca.cert_pem.as_bytes()).unwrap();
        let err = check_issued_by(foreign, ca.cert_pem.as_bytes()).unwrap_err();
        assert!(err.contains("does not chain to the CA"), "{err}");
        assert!(check_issued_by(b"", ca.cert_pem.as_bytes()).is_err());
    }
}
