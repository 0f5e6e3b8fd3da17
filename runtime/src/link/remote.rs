//! The one place a remote aligner is built: [`RemoteOptions`] says where the alignment server is and how to
//! use it, [`RemoteOptions::parse`] checks the text forms an app's configuration holds (the C ABI and the
//! Python package pass them on unchanged), and [`RemoteOptions::start`] connects in the background and puts
//! the local aligner behind the link as its fallback. `FaceTracker` and every command-line tool go through it.

use std::net::SocketAddr;
use std::time::Duration;

use holoface_quic::Fingerprint;

use super::{Backoff, ConnectConfig, CropCodec, LinkOptions, LinkedAligner, RemoteLink};

/// The longest per-frame deadline an app may set: past it a frame is stale long before it is answered.
pub const MAX_DEADLINE: Duration = Duration::from_secs(10);

/// Where the alignment server is and how frames go to it.
#[derive(Clone, Debug, PartialEq)]
pub struct RemoteOptions {
    /// Server UDP address.
    pub server: SocketAddr,
    /// Pinned SHA-256 of the server certificate.
    pub fingerprint: Fingerprint,
    /// Access token.
    pub token: String,
    /// Per-frame deadline: past it the local aligner answers the frame.
    pub deadline: Duration,
    /// Crop encoding on the wire.
    pub codec: CropCodec,
    /// The name this client gives in its hello (the server's logs and metrics show it).
    pub client_name: String,
    /// While the link is up, the local aligner learns each tracked person's correction towards the server's
    /// answers and applies it when the link is down ([`crate::adapt`]); `None`: off.
    pub adapt: Option<crate::adapt::AdaptOptions>,
}

/// Why remote options were refused; the message names the option.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum RemoteOptionsError {
    /// The server address is not `ip:port`.
    #[error("server {given:?}: {reason} (use ip:port)")]
    Server {
        /// What was given.
        given: String,
        /// Why it does not parse.
        reason: String,
    },
    /// A server without the certificate fingerprint to pin.
    #[error("fingerprint is required with server (holoface-server prints it at start)")]
    MissingFingerprint,
    /// The fingerprint is not 64 hex digits.
    #[error("fingerprint: {0}")]
    Fingerprint(String),
    /// The deadline is zero or longer than [`MAX_DEADLINE`].
    #[error("deadline_ms {0} must be within 1..=10000")]
    Deadline(u64),
    /// The crop encoding is not `raw`, `png`, `jpeg` or `jpeg:QUALITY`.
    #[error("crop_encoding: {0}")]
    CropEncoding(String),
}

/// Why a remote aligner could not start.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RemoteStartError {
    /// An option is out of range ([`RemoteOptions::check`]).
    #[error(transparent)]
    Options(#[from] RemoteOptionsError),
    /// The link's thread or its runtime could not be started.
    #[error("starting the link thread: {0}")]
    Thread(#[from] std::io::Error),
}

impl RemoteOptions {
    /// Options with the default deadline (one frame interval at 30 fps) and crop encoding.
    pub fn new(server: SocketAddr, fingerprint: Fingerprint, token: impl Into<String>) -> Self {
        let link = LinkOptions::default();
        Self {
            server,
            fingerprint,
            token: token.into(),
            deadline: link.deadline,
            codec: link.codec,
            client_name: ConnectConfig::new(server, fingerprint, "").client_name,
            adapt: link.adapt,
        }
    }

    /// Checks and converts the text forms of the options (`crop_encoding: None` = the default).
    pub fn parse(
        server: &str,
        fingerprint: Option<&str>,
        token: &str,
        deadline_ms: u64,
        crop_encoding: Option<&str>,
    ) -> Result<Self, RemoteOptionsError> {
        let addr = server
            .parse()
            .map_err(|e: std::net::AddrParseError| RemoteOptionsError::Server {
                given: server.to_owned(),
                reason: e.to_string(),
            })?;
        let fingerprint = fingerprint
            .ok_or(RemoteOptionsError::MissingFingerprint)?
            .parse()
            .map_err(|e: holoface_quic::TlsError| RemoteOptionsError::Fingerprint(e.to_string()))?;
        let deadline = Duration::from_millis(deadline_ms);
        if deadline.is_zero() || deadline > MAX_DEADLINE {
            return Err(RemoteOptionsError::Deadline(deadline_ms));
        }
        let mut o = Self::new(addr, fingerprint, token);
        o.deadline = deadline;
        if let Some(c) = crop_encoding {
            o.codec = c.parse().map_err(RemoteOptionsError::CropEncoding)?;
        }
        Ok(o)
    }

    /// Checks the options a caller set field by field (what [`Self::parse`] checks on text).
    pub fn check(&self) -> Result<(), RemoteOptionsError> {
        if self.deadline.is_zero() || self.deadline > MAX_DEADLINE {
            return Err(RemoteOptionsError::Deadline(
                u64::try_from(self.deadline.as_millis()).unwrap_or(u64::MAX),
            ));
        }
        Ok(())
    }
}

// Here rather than on `RemoteOptions` (which an app names) so that the aligner's type stays out of the app's API.
impl<A: crate::align::Aligner> LinkedAligner<A> {
    /// Starts connecting in the background (retrying with the default backoff) and returns the aligner that
    /// sends each frame's crops to the server and lets `local` answer what misses the deadline or arrives
    /// while the link is down. `max_faces` crops (one per tracked face) may be in flight at once. Options
    /// out of range ([`RemoteOptions::check`]) are refused.
    pub fn start(remote: &RemoteOptions, local: A, max_faces: usize) -> Result<Self, RemoteStartError> {
        remote.check()?;
        let mut cfg = ConnectConfig::new(remote.server, remote.fingerprint, remote.token.clone());
        cfg.client_name.clone_from(&remote.client_name);
        cfg.encodings = vec![crate::crop_codec::wire_encoding(remote.codec)];
        cfg.max_in_flight = u16::try_from(max_faces.max(1)).unwrap_or(u16::MAX);
        let link = RemoteLink::start(cfg, Backoff::default())?;
        let opts = LinkOptions {
            deadline: remote.deadline,
            codec: remote.codec,
            adapt: remote.adapt,
            ..LinkOptions::default()
        };
        Ok(Self::new(link, local, opts))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FP: &str = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";

    #[test]
    fn parses_what_an_app_configures() {
        let o = RemoteOptions::parse("127.0.0.1:4433", Some(FP), "t", 50, Some("jpeg:80")).unwrap();
        assert_eq!(o.server, "127.0.0.1:4433".parse().unwrap());
        assert_eq!(o.deadline, Duration::from_millis(50));
        assert_eq!(o.codec.to_string(), "jpeg:80");
        assert_eq!(o.token, "t");
        let d = RemoteOptions::parse("127.0.0.1:4433", Some(FP), "", 33, None).unwrap();
        assert_eq!(d.codec, CropCodec::default());
    }

    #[test]
    fn options_set_field_by_field_are_checked_too() {
        let mut o = RemoteOptions::new("127.0.0.1:9".parse().unwrap(), FP.parse().unwrap(), "");
        assert!(o.check().is_ok());
        o.deadline = Duration::ZERO;
        assert_eq!(o.check(), Err(RemoteOptionsError::Deadline(0)));
        o.deadline = Duration::from_secs(3600);
        assert_eq!(o.check(), Err(RemoteOptionsError::Deadline(3_600_000)));
    }

    #[test]
    fn every_bad_option_is_named() {
        let bad = |s: &str, f: Option<&str>, d: u64, c: Option<&str>| {
            RemoteOptions::parse(s, f, "", d, c).unwrap_err().to_string()
        };
        assert!(bad("localhost", Some(FP), 33, None).starts_with("server \"localhost\""));
        assert!(bad("127.0.0.1:1", None, 33, None).starts_with("fingerprint is required"));
        assert!(bad("127.0.0.1:1", Some("abc"), 33, None).starts_with("fingerprint:"));
        assert!(bad("127.0.0.1:1", Some(FP), 0, None).starts_with("deadline_ms 0"));
        assert!(bad("127.0.0.1:1", Some(FP), 10_001, None).starts_with("deadline_ms 10001"));
        assert!(bad("127.0.0.1:1", Some(FP), 10_000, Some("gif")).starts_with("crop_encoding:"));
    }
}
