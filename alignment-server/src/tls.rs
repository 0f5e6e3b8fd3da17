//! The server's TLS 1.3 certificate for the QUIC endpoint: from PEM files or a self-signed development
//! certificate. Clients pin its SHA-256 ([`Fingerprint`], `holoface-quic`).

use std::path::Path;
use std::sync::Arc;

use holoface_protocol::ALPN;
pub use holoface_quic::Fingerprint;
use holoface_quic::provider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer};

/// TLS set-up failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TlsError {
    /// A PEM file could not be read or parsed.
    #[error("reading {what} from {path}: {detail}")]
    Pem {
        /// "certificate chain" or "private key".
        what: &'static str,
        /// The file.
        path: String,
        /// What went wrong.
        detail: String,
    },
    /// The certificate file holds no certificate.
    #[error("{path} contains no certificate")]
    NoCertificate {
        /// The file.
        path: String,
    },
    /// Generating the self-signed certificate failed.
    #[error("generating the self-signed certificate: {0}")]
    Generate(#[from] rcgen::Error),
    /// rustls refused the configuration (e.g. the key does not match).
    #[error("TLS configuration: {0}")]
    Rustls(#[from] rustls::Error),
    /// The rustls config is not usable for QUIC.
    #[error("TLS configuration is not usable for QUIC: {0}")]
    Quic(String),
}

/// The server's certificate chain and key.
#[derive(Debug)]
pub struct ServerIdentity {
    /// Leaf first.
    pub chain: Vec<CertificateDer<'static>>,
    /// The leaf's private key.
    pub key: PrivateKeyDer<'static>,
    /// SHA-256 of the leaf certificate.
    pub fingerprint: Fingerprint,
    /// The leaf in PEM (for writing next to the fingerprint).
    pub self_signed_pem: Option<String>,
}

impl ServerIdentity {
    /// Loads a PEM certificate chain and PEM private key.
    pub fn from_pem_files(cert: &Path, key: &Path) -> Result<Self, TlsError> {
        let chain = CertificateDer::pem_file_iter(cert)
            .and_then(|it| it.collect::<Result<Vec<_>, _>>())
            .map_err(|e| TlsError::Pem {
                what: "certificate chain",
                path: cert.display().to_string(),
                detail: e.to_string(),
            })?;
        let leaf = chain.first().ok_or_else(|| TlsError::NoCertificate {
            path: cert.display().to_string(),
        })?;
        let fingerprint = Fingerprint::of_der(leaf);
        let key = PrivateKeyDer::from_pem_file(key).map_err(|e| TlsError::Pem {
            what: "private key",
            path: key.display().to_string(),
            detail: e.to_string(),
        })?;
        Ok(Self {
            chain,
            key,
            fingerprint,
            self_signed_pem: None,
        })
    }

    /// Generates a self-signed development certificate for `names`.
    pub fn self_signed(names: &[String]) -> Result<Self, TlsError> {
        let certified = rcgen::generate_simple_self_signed(names.to_vec())?;
        let der = certified.cert.der().clone();
        let fingerprint = Fingerprint::of_der(&der);
        let key = PrivateKeyDer::Pkcs8(PrivatePkcs8KeyDer::from(certified.signing_key.serialize_der()));
        Ok(Self {
            chain: vec![der],
            key,
            fingerprint,
            self_signed_pem: Some(certified.cert.pem()),
        })
    }

    /// The quinn server crypto: TLS 1.3 only, ring, the HoloFace ALPN.
    pub fn quic_server_config(&self) -> Result<Arc<quinn::crypto::rustls::QuicServerConfig>, TlsError> {
        let mut cfg = rustls::ServerConfig::builder_with_provider(provider())
            .with_protocol_versions(&[&rustls::version::TLS13])?
            .with_no_client_auth()
            .with_single_cert(self.chain.clone(), self.key.clone_key())?;
        cfg.alpn_protocols = vec![ALPN.to_vec()];
        let quic = quinn::crypto::rustls::QuicServerConfig::try_from(cfg)
            .map_err(|e| TlsError::Quic(e.to_string()))?;
        Ok(Arc::new(quic))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use holoface_quic::{PinnedCertVerifier, pinned_client_config};
    use rustls::client::danger::ServerCertVerifier;
    use rustls::pki_types::{ServerName, UnixTime};

    #[test]
    fn self_signed_identity_builds_a_quic_config() {
        let id = ServerIdentity::self_signed(&["localhost".to_owned()]).unwrap();
        assert_eq!(id.fingerprint, Fingerprint::of_der(&id.chain[0]));
        assert!(id.quic_server_config().is_ok());
        assert!(pinned_client_config(id.fingerprint).is_ok());
    }

    #[test]
    fn verifier_rejects_other_certificates() {
        let a = ServerIdentity::self_signed(&["localhost".to_owned()]).unwrap();
        let b = ServerIdentity::self_signed(&["localhost".to_owned()]).unwrap();
        let v = PinnedCertVerifier::new(a.fingerprint);
        let name = ServerName::try_from("localhost").unwrap();
        assert!(
            v.verify_server_cert(&a.chain[0], &[], &name, &[], UnixTime::now())
                .is_ok()
        );
        assert!(
            v.verify_server_cert(&b.chain[0], &[], &name, &[], UnixTime::now())
                .is_err()
        );
    }

    #[test]
    fn missing_pem_is_a_clear_error() {
        let err =
            ServerIdentity::from_pem_files(Path::new("/nonexistent/c.pem"), Path::new("/nonexistent/k.pem"))
                .unwrap_err();
        assert!(err.to_string().contains("/nonexistent/c.pem"), "{err}");
    }
}
