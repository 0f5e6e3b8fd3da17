//! TLS 1.3 for the QUIC endpoint: the server's certificate (from PEM files or
//! a self-signed development certificate) and, for clients, a rustls
//! verifier that pins the server certificate's SHA-256 fingerprint.
//!
//! Clients (the headset's remote link, the load tester, the e2e tests) use
//! [`pinned_client_config`] with the fingerprint the server prints at start.

use std::fmt;
use std::path::Path;
use std::str::FromStr;
use std::sync::Arc;

use holoface_protocol::ALPN;
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer, ServerName, UnixTime};
use rustls::{DigitallySignedStruct, SignatureScheme};

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
    /// A fingerprint string is not 64 hex digits.
    #[error("certificate fingerprint must be 64 hex digits (SHA-256), optionally with ':' separators")]
    BadFingerprint,
}

/// SHA-256 of a DER certificate: what clients pin.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Fingerprint(pub [u8; 32]);

impl Fingerprint {
    /// Fingerprint of a DER-encoded certificate.
    pub fn of_der(der: &[u8]) -> Self {
        let digest = ring::digest::digest(&ring::digest::SHA256, der);
        let mut out = [0_u8; 32];
        out.copy_from_slice(digest.as_ref());
        Self(out)
    }
}

impl fmt::Display for Fingerprint {
    /// Lowercase hex, no separators (64 characters).
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.iter().try_for_each(|b| write!(f, "{b:02x}"))
    }
}

impl fmt::Debug for Fingerprint {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Fingerprint({self})")
    }
}

impl FromStr for Fingerprint {
    type Err = TlsError;

    /// Accepts 64 hex digits, upper or lower case, with optional `:`
    /// separators and surrounding whitespace.
    fn from_str(s: &str) -> Result<Self, TlsError> {
        let hex: Vec<u8> = s.trim().bytes().filter(|b| *b != b':').collect();
        if hex.len() != 64 {
            return Err(TlsError::BadFingerprint);
        }
        let nibble = |c: u8| (c as char).to_digit(16).ok_or(TlsError::BadFingerprint);
        let mut out = [0_u8; 32];
        for (o, pair) in out.iter_mut().zip(hex.chunks_exact(2)) {
            let (hi, lo) = match pair {
                [h, l] => (nibble(*h)?, nibble(*l)?),
                _ => return Err(TlsError::BadFingerprint),
            };
            *o = u8::try_from(hi * 16 + lo).map_err(|_| TlsError::BadFingerprint)?;
        }
        Ok(Self(out))
    }
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

fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// A rustls verifier that accepts exactly one server certificate, identified
/// by the SHA-256 of its DER encoding, and checks handshake signatures with
/// that certificate's key. Names and validity dates are not checked: the pin
/// is the trust anchor (as with SSH host keys).
#[derive(Debug)]
pub struct PinnedCertVerifier {
    fingerprint: Fingerprint,
    provider: Arc<CryptoProvider>,
}

impl PinnedCertVerifier {
    /// Pins `fingerprint`.
    pub fn new(fingerprint: Fingerprint) -> Self {
        Self {
            fingerprint,
            provider: provider(),
        }
    }
}

impl ServerCertVerifier for PinnedCertVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        let got = Fingerprint::of_der(end_entity);
        // Not secret: constant-time comparison is not needed for a public pin.
        if got == self.fingerprint {
            Ok(ServerCertVerified::assertion())
        } else {
            Err(rustls::Error::InvalidCertificate(
                rustls::CertificateError::ApplicationVerificationFailure,
            ))
        }
    }

    fn verify_tls12_signature(
        &self,
        _message: &[u8],
        _cert: &CertificateDer<'_>,
        _dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        // The client config only enables TLS 1.3.
        Err(rustls::Error::PeerIncompatible(
            rustls::PeerIncompatible::Tls12NotOffered,
        ))
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(
            message,
            cert,
            dss,
            &self.provider.signature_verification_algorithms,
        )
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.provider
            .signature_verification_algorithms
            .supported_schemes()
    }
}

/// A rustls client config (TLS 1.3, ring, HoloFace ALPN) that trusts only the
/// server certificate with `fingerprint`.
pub fn pinned_rustls_config(fingerprint: Fingerprint) -> Result<rustls::ClientConfig, TlsError> {
    let mut cfg = rustls::ClientConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(PinnedCertVerifier::new(fingerprint)))
        .with_no_client_auth();
    cfg.alpn_protocols = vec![ALPN.to_vec()];
    Ok(cfg)
}

/// A quinn client config that pins the server certificate's SHA-256
/// `fingerprint` (see [`PinnedCertVerifier`]); use with
/// `quinn::Endpoint::connect_with(config, addr, "localhost")`.
pub fn pinned_client_config(fingerprint: Fingerprint) -> Result<quinn::ClientConfig, TlsError> {
    let quic = quinn::crypto::rustls::QuicClientConfig::try_from(pinned_rustls_config(fingerprint)?)
        .map_err(|e| TlsError::Quic(e.to_string()))?;
    Ok(quinn::ClientConfig::new(Arc::new(quic)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_round_trips_through_text() {
        let fp = Fingerprint::of_der(b"not really a certificate");
        let text = fp.to_string();
        assert_eq!(text.len(), 64);
        assert_eq!(text.parse::<Fingerprint>().unwrap(), fp);
        let colons: String = text
            .as_bytes()
            .chunks(2)
            .map(|c| std::str::from_utf8(c).unwrap().to_uppercase())
            .collect::<Vec<_>>()
            .join(":");
        assert_eq!(colons.parse::<Fingerprint>().unwrap(), fp);
        assert!("abc".parse::<Fingerprint>().is_err());
        assert!("zz".repeat(32).parse::<Fingerprint>().is_err());
    }

    #[test]
    fn known_sha256() {
        // SHA-256("abc"), FIPS 180-2 test vector.
        assert_eq!(
            Fingerprint::of_der(b"abc").to_string(),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
    }

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
