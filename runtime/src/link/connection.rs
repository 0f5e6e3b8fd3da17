//! One QUIC connection to the alignment server speaking the HoloFace protocol (async, tokio + quinn).
//!
//! Used by the headset link ([`super::RemoteLink`]) and by the load tester: [`connect`] does the TLS 1.3
//! handshake (pinned server certificate), sends the [`ClientHello`] on the control stream and waits for the
//! [`ServerWelcome`]; [`send_frame`] writes one frame on its own unidirectional stream; [`ReplyReader`]
//! reads replies from whichever channel the welcome announced.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use bytes::BytesMut;
use holoface_protocol::{
    ClientHello, CloseCode, CropEncoding, DecodeError, FrameReply, FrameRequest, MIN_PROTOCOL_VERSION,
    Message, PROTOCOL_VERSION, ReplyChannel, ServerWelcome, decode_framed, encode_framed,
};
use holoface_quic::{Fingerprint, pinned_client_config};
use quinn::{Connection, ConnectionError, Endpoint, RecvStream, SendStream};

/// Where and how to connect.
#[derive(Clone, Debug)]
pub struct ConnectConfig {
    /// The server's UDP address.
    pub server: SocketAddr,
    /// TLS server name (the dev certificate is issued for `localhost`).
    pub server_name: String,
    /// SHA-256 of the server's certificate (printed by the server at start).
    pub fingerprint: Fingerprint,
    /// Access token.
    pub token: String,
    /// Name for the server's logs.
    pub client_name: String,
    /// Crop encodings we can send, preferred first.
    pub encodings: Vec<CropEncoding>,
    /// Frames we want in flight at most.
    pub max_in_flight: u16,
    /// Give up a connection attempt after this long.
    pub connect_timeout: Duration,
    /// QUIC idle timeout: a silent server is declared gone after this long.
    pub idle_timeout: Duration,
    /// QUIC keep-alive interval (well below `idle_timeout`); `None` sends none (the server's idle timeout
    /// then closes a silent connection).
    pub keep_alive: Option<Duration>,
}

impl ConnectConfig {
    /// Defaults for a server at `server` pinned by `fingerprint`.
    pub fn new(server: SocketAddr, fingerprint: Fingerprint, token: impl Into<String>) -> Self {
        Self {
            server,
            server_name: "localhost".to_owned(),
            fingerprint,
            token: token.into(),
            client_name: "holoface-client".to_owned(),
            encodings: vec![CropEncoding::Jpeg, CropEncoding::Png, CropEncoding::Raw],
            max_in_flight: 1,
            connect_timeout: Duration::from_secs(2),
            idle_timeout: Duration::from_secs(3),
            keep_alive: Some(Duration::from_millis(500)),
        }
    }
}

/// Why a connection could not be made or ended.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum LinkError {
    /// TLS configuration failed.
    #[error("tls: {0}")]
    Tls(#[from] holoface_quic::TlsError),
    /// The UDP socket could not be opened.
    #[error("udp socket: {0}")]
    Io(#[from] std::io::Error),
    /// The connection could not be started.
    #[error("connect: {0}")]
    Connect(#[from] quinn::ConnectError),
    /// The connection failed or was closed (by the server: see the close code).
    #[error("connection: {0}{hint}", hint = close_hint(.0))]
    Connection(#[from] ConnectionError),
    /// A stream write failed.
    #[error("write: {0}")]
    Write(#[from] quinn::WriteError),
    /// A stream read failed.
    #[error("read: {0}")]
    Read(#[from] quinn::ReadError),
    /// The stream was already closed.
    #[error("stream closed: {0}")]
    ClosedStream(#[from] quinn::ClosedStream),
    /// The server sent bytes that do not decode.
    #[error("decode: {0}")]
    Decode(#[from] DecodeError),
    /// We could not encode a message (e.g. an oversize crop).
    #[error("encode: {0}")]
    Encode(#[from] holoface_protocol::EncodeError),
    /// The server broke the protocol (unexpected message, early end of stream).
    #[error("protocol: {0}")]
    Protocol(String),
    /// The server speaks another protocol version.
    #[error("server speaks protocol version {server}, we speak {MIN_PROTOCOL_VERSION} to {PROTOCOL_VERSION}")]
    Version {
        /// The server's version.
        server: u16,
    },
    /// The attempt took longer than the configured timeout.
    #[error("timed out after {0:?}")]
    Timeout(Duration),
    /// The server announced it is going away.
    #[error("server going away: {0}")]
    Goaway(String),
}

/// What a link failure means for the user; the kind decides whether retrying can help.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum FailureKind {
    /// No answer from the server's address (nothing listening, no route, or the attempt timed out).
    Unreachable,
    /// The server rejected our token.
    Unauthorized,
    /// The server's certificate does not match the pinned fingerprint.
    CertificateMismatch,
    /// The server speaks another protocol version.
    BadVersion,
    /// The server is at its client limit (or refused work).
    ServerFull,
    /// The server is shutting down or going away.
    ShuttingDown,
    /// An established connection broke (idle timeout, reset, closed by the server).
    ConnectionLost,
    /// The server broke the protocol or sent bytes that do not decode.
    Protocol,
    /// A failure on this device (socket, TLS set-up, encoding).
    Local,
}

impl FailureKind {
    /// Every kind, for tests that go through them all.
    #[cfg(test)]
    pub(crate) const ALL: [Self; 9] = [
        Self::Unreachable,
        Self::Unauthorized,
        Self::CertificateMismatch,
        Self::BadVersion,
        Self::ServerFull,
        Self::ShuttingDown,
        Self::ConnectionLost,
        Self::Protocol,
        Self::Local,
    ];

    /// True when retrying cannot help until someone changes the configuration (token, fingerprint,
    /// client or server version): the link stops instead of retrying.
    pub const fn is_permanent(self) -> bool {
        matches!(
            self,
            Self::Unauthorized | Self::CertificateMismatch | Self::BadVersion
        )
    }

    /// The snake_case name used in logs and per-frame output.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Unreachable => "unreachable",
            Self::Unauthorized => "unauthorized",
            Self::CertificateMismatch => "certificate_mismatch",
            Self::BadVersion => "bad_version",
            Self::ServerFull => "server_full",
            Self::ShuttingDown => "shutting_down",
            Self::ConnectionLost => "connection_lost",
            Self::Protocol => "protocol",
            Self::Local => "local",
        }
    }
}

impl std::fmt::Display for FailureKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A link failure as the frame loop and the APIs see it: the kind, and the full message for people.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{kind}: {message}")]
pub struct LinkFailure {
    /// What it means.
    pub kind: FailureKind,
    /// The underlying error, for logs.
    pub message: String,
}

impl LinkFailure {
    /// A failure of `kind` with `message`.
    pub fn new(kind: FailureKind, message: impl Into<String>) -> Self {
        Self {
            kind,
            message: message.into(),
        }
    }
}

impl LinkError {
    /// This error as the link's status reports it (a method rather than `From`, so that `LinkError`, the
    /// connection's own type, stays out of the app's API through `LinkFailure`).
    pub fn failure(&self) -> LinkFailure {
        LinkFailure::new(self.kind(), self.to_string())
    }
}

/// TLS alerts our pinned-certificate verifier causes: `access_denied` (rustls' application verification
/// failure) and `bad_certificate`.
const CERT_ALERTS: [u8; 2] = [49, 42];

fn connection_kind(e: &ConnectionError) -> FailureKind {
    match e {
        ConnectionError::ApplicationClosed(_) => match app_close_code(e) {
            Some(CloseCode::Unauthorized) => FailureKind::Unauthorized,
            Some(CloseCode::BadVersion) => FailureKind::BadVersion,
            Some(CloseCode::Overloaded) => FailureKind::ServerFull,
            Some(CloseCode::ShuttingDown) => FailureKind::ShuttingDown,
            Some(CloseCode::Malformed | CloseCode::TooLarge | CloseCode::ProtocolViolation) => {
                FailureKind::Protocol
            }
            _ => FailureKind::ConnectionLost,
        },
        ConnectionError::TransportError(t)
            if CERT_ALERTS
                .iter()
                .any(|&a| t.code == quinn::TransportErrorCode::crypto(a))
                || t.reason.contains("invalid peer certificate") =>
        {
            FailureKind::CertificateMismatch
        }
        ConnectionError::TransportError(_) | ConnectionError::VersionMismatch => FailureKind::Protocol,
        ConnectionError::TimedOut => FailureKind::Unreachable,
        ConnectionError::LocallyClosed | ConnectionError::CidsExhausted => FailureKind::Local,
        ConnectionError::ConnectionClosed(_) | ConnectionError::Reset => FailureKind::ConnectionLost,
    }
}

impl LinkError {
    /// What this error means for the user (and whether retrying can help).
    pub fn kind(&self) -> FailureKind {
        use quinn::{ReadError, WriteError};
        match self {
            Self::Tls(_) | Self::Io(_) | Self::Connect(_) | Self::Encode(_) | Self::ClosedStream(_) => {
                FailureKind::Local
            }
            Self::Connection(c)
            | Self::Write(WriteError::ConnectionLost(c))
            | Self::Read(ReadError::ConnectionLost(c)) => connection_kind(c),
            Self::Write(_) | Self::Read(_) => FailureKind::ConnectionLost,
            Self::Decode(_) | Self::Protocol(_) => FailureKind::Protocol,
            Self::Version { .. } => FailureKind::BadVersion,
            Self::Timeout(_) => FailureKind::Unreachable,
            Self::Goaway(_) => FailureKind::ShuttingDown,
        }
    }
}

fn close_hint(e: &ConnectionError) -> String {
    if connection_kind(e) == FailureKind::CertificateMismatch {
        return " (the server's certificate is not the pinned one: its SHA-256 differs from the fingerprint given)"
            .to_owned();
    }
    match app_close_code(e) {
        Some(CloseCode::Unauthorized) => " (the server rejected our token)".to_owned(),
        Some(CloseCode::BadVersion) => " (protocol version mismatch)".to_owned(),
        Some(CloseCode::Overloaded) => " (server at its client limit)".to_owned(),
        Some(code) => format!(" ({code:?})"),
        None => String::new(),
    }
}

/// The application close code a connection ended with, if any.
pub fn app_close_code(err: &ConnectionError) -> Option<CloseCode> {
    match err {
        ConnectionError::ApplicationClosed(close) => u32::try_from(close.error_code.into_inner())
            .ok()
            .and_then(CloseCode::from_u32),
        _ => None,
    }
}

/// A client endpoint (one UDP socket; many connections may share it) with our transport settings.
pub fn client_endpoint(cfg: &ConnectConfig) -> Result<Endpoint, LinkError> {
    let bind = if cfg.server.is_ipv4() {
        SocketAddr::from(([0, 0, 0, 0], 0))
    } else {
        SocketAddr::from(([0u16; 8], 0))
    };
    let mut endpoint = Endpoint::client(bind)?;
    let mut client = pinned_client_config(cfg.fingerprint)?;
    let mut transport = quinn::TransportConfig::default();
    transport.max_idle_timeout(quinn::IdleTimeout::try_from(cfg.idle_timeout).ok());
    transport.keep_alive_interval(cfg.keep_alive);
    client.transport_config(Arc::new(transport));
    endpoint.set_default_client_config(client);
    Ok(endpoint)
}

/// A connection after a successful handshake.
#[derive(Debug)]
pub struct Established {
    /// The QUIC connection (cheap to clone; send frames with [`send_frame`]).
    pub conn: Connection,
    /// What the server answered.
    pub welcome: ServerWelcome,
    control: Control,
}

/// The control stream: the server sends `Goaway`/`Error` on it.
#[derive(Debug)]
pub struct Control {
    /// The sending half, held for as long as the link lives: dropping it would finish the stream. Only tests
    /// write on it after the hello (`test-util`).
    #[cfg_attr(
        not(feature = "test-util"),
        expect(dead_code, reason = "held open, written by tests only")
    )]
    send: SendStream,
    recv: RecvStream,
    buf: BytesMut,
}

impl Control {
    /// The next control message; `Goaway` and `Error` come back as errors with the server's text.
    pub async fn next(&mut self) -> Result<Message, LinkError> {
        match read_framed(&mut self.recv, &mut self.buf).await? {
            // The server's texts go into errors and logs: escaped and bounded.
            Message::Goaway(g) => Err(LinkError::Goaway(format!(
                "{:?}: {}",
                g.reason,
                holoface_protocol::untrusted(&g.text)
            ))),
            Message::Error(e) => Err(LinkError::Protocol(format!(
                "server error {:?}: {}",
                e.code,
                holoface_protocol::untrusted(&e.text)
            ))),
            other => Ok(other),
        }
    }

    /// The next framed message as it came (`Goaway` and `Error` included).
    pub async fn next_message(&mut self) -> Result<Message, LinkError> {
        read_framed(&mut self.recv, &mut self.buf).await
    }

    /// Writes raw bytes on the control stream (clients send nothing after the hello; for tests that
    /// misbehave on purpose, with the `test-util` feature: never in a headset app's build).
    #[cfg(feature = "test-util")]
    pub async fn write_bytes(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.send.write_all(bytes).await?;
        Ok(())
    }
}

/// Connects and performs the HoloFace handshake, all within `cfg.connect_timeout`.
pub async fn connect(endpoint: &Endpoint, cfg: &ConnectConfig) -> Result<Established, LinkError> {
    tokio::time::timeout(cfg.connect_timeout, connect_inner(endpoint, cfg))
        .await
        .map_err(|_| LinkError::Timeout(cfg.connect_timeout))?
}

async fn connect_inner(endpoint: &Endpoint, cfg: &ConnectConfig) -> Result<Established, LinkError> {
    let conn = endpoint.connect(cfg.server, &cfg.server_name)?.await?;
    let hello = ClientHello {
        version: PROTOCOL_VERSION,
        token: cfg.token.clone(),
        client_name: cfg.client_name.clone(),
        encodings: cfg.encodings.clone(),
        max_in_flight: cfg.max_in_flight,
    };
    let established = handshake(conn, &hello).await?;
    // The server answers with the version it serves us at: ours, or an older one we still decode.
    if !(MIN_PROTOCOL_VERSION..=PROTOCOL_VERSION).contains(&established.welcome.version) {
        established
            .conn
            .close(CloseCode::BadVersion.as_u32().into(), b"version");
        return Err(LinkError::Version {
            server: established.welcome.version,
        });
    }
    Ok(established)
}

/// How long a handshake whose stream ended waits for the server's close code.
const REFUSAL_GRACE: Duration = Duration::from_millis(500);

/// The HoloFace handshake on a QUIC connection: `hello` on a new control stream, then the server's welcome.
/// A server that refuses closes the connection: the error is then [`LinkError::Connection`] with its close
/// code (see [`app_close_code`]). The welcome's version is not checked here (see [`connect`]).
pub async fn handshake(conn: Connection, hello: &ClientHello) -> Result<Established, LinkError> {
    let (mut send, mut recv) = conn.open_bi().await?;
    let mut buf = BytesMut::new();
    encode_framed(&Message::ClientHello(hello.clone()), &mut buf)?;
    send.write_all(&buf).await?;
    let mut rbuf = BytesMut::new();
    let welcome = match read_framed(&mut recv, &mut rbuf).await {
        Ok(Message::ServerWelcome(w)) => w,
        Ok(other) => {
            return Err(LinkError::Protocol(format!(
                "expected ServerWelcome, got {other:?}"
            )));
        }
        // A refusal closes the connection with a code; report that rather than the stream error. The
        // stream can end a moment before the close arrives (a server that drops the stream first), so wait
        // briefly for it: a wrong token must read "unauthorized" (permanent), not a retryable stream end.
        Err(e) => {
            let reason = match conn.close_reason() {
                Some(reason) => Some(reason),
                None => tokio::time::timeout(REFUSAL_GRACE, conn.closed()).await.ok(),
            };
            return Err(reason.map_or(e, LinkError::Connection));
        }
    };
    Ok(Established {
        conn,
        welcome,
        control: Control {
            send,
            recv,
            buf: rbuf,
        },
    })
}

impl Established {
    /// Splits into the connection, the welcome, the control stream and a reply reader.
    pub fn split(self) -> (Connection, ServerWelcome, Control, ReplyReader) {
        let reader = ReplyReader {
            conn: self.conn.clone(),
            channel: self.welcome.reply_channel,
            stream: None,
            buf: BytesMut::new(),
        };
        (self.conn, self.welcome, self.control, reader)
    }
}

/// Sends one frame on its own unidirectional stream; returns the message size in bytes.
pub async fn send_frame(conn: &Connection, req: &FrameRequest) -> Result<usize, LinkError> {
    let bytes = Message::FrameRequest(req.clone()).to_bytes()?;
    let mut s = conn.open_uni().await?;
    s.write_all(&bytes).await?;
    s.finish()?;
    Ok(bytes.len())
}

/// Reads replies from the channel the server announced (datagrams or one reply stream).
#[derive(Debug)]
pub struct ReplyReader {
    conn: Connection,
    channel: ReplyChannel,
    stream: Option<RecvStream>,
    buf: BytesMut,
}

impl ReplyReader {
    /// The next reply.
    pub async fn next(&mut self) -> Result<FrameReply, LinkError> {
        let msg = match self.channel {
            ReplyChannel::Datagram => Message::decode(self.conn.read_datagram().await?)?,
            ReplyChannel::Stream => {
                let stream = match &mut self.stream {
                    Some(s) => s,
                    None => self.stream.insert(self.conn.accept_uni().await?),
                };
                read_framed(stream, &mut self.buf).await?
            }
        };
        match msg {
            Message::FrameReply(r) => Ok(r),
            other => Err(LinkError::Protocol(format!("expected FrameReply, got {other:?}"))),
        }
    }
}

/// Reads the next length-framed message from `recv`, buffering partial input in `buf`.
pub async fn read_framed(recv: &mut RecvStream, buf: &mut BytesMut) -> Result<Message, LinkError> {
    loop {
        if let Some(m) = decode_framed(buf)? {
            return Ok(m);
        }
        match recv.read_chunk(64 * 1024, true).await? {
            Some(chunk) => buf.extend_from_slice(&chunk.bytes),
            None => return Err(LinkError::Protocol("stream ended".into())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn closed_with(code: CloseCode) -> LinkError {
        LinkError::Connection(ConnectionError::ApplicationClosed(quinn::ApplicationClose {
            error_code: quinn::VarInt::from_u32(code.as_u32()),
            reason: bytes::Bytes::from_static(b"test"),
        }))
    }

    #[test]
    fn server_close_codes_map_to_failure_kinds() {
        let cases = [
            (CloseCode::Unauthorized, FailureKind::Unauthorized),
            (CloseCode::BadVersion, FailureKind::BadVersion),
            (CloseCode::Overloaded, FailureKind::ServerFull),
            (CloseCode::ShuttingDown, FailureKind::ShuttingDown),
            (CloseCode::Malformed, FailureKind::Protocol),
            (CloseCode::NoError, FailureKind::ConnectionLost),
        ];
        for (code, kind) in cases {
            assert_eq!(closed_with(code).kind(), kind, "{code:?}");
        }
    }

    #[test]
    fn timeouts_are_unreachable_and_only_configuration_errors_are_permanent() {
        assert_eq!(
            LinkError::Timeout(Duration::from_secs(2)).kind(),
            FailureKind::Unreachable
        );
        assert_eq!(
            LinkError::Connection(ConnectionError::TimedOut).kind(),
            FailureKind::Unreachable
        );
        assert_eq!(LinkError::Version { server: 99 }.kind(), FailureKind::BadVersion);
        let permanent: Vec<_> = FailureKind::ALL
            .into_iter()
            .filter(|k| k.is_permanent())
            .collect();
        assert_eq!(
            permanent,
            [
                FailureKind::Unauthorized,
                FailureKind::CertificateMismatch,
                FailureKind::BadVersion
            ]
        );
        let f = closed_with(CloseCode::Unauthorized).failure();
        assert!(f.to_string().starts_with("unauthorized: "), "{f}");
    }

    /// A certificate that is not the pinned one says so in words, not only as a TLS alert number.
    #[test]
    fn a_certificate_mismatch_says_which_pin_failed() {
        let e = LinkError::Connection(ConnectionError::TransportError(
            quinn::TransportErrorCode::crypto(49).into(),
        ));
        assert_eq!(e.kind(), FailureKind::CertificateMismatch);
        assert!(e.to_string().contains("not the pinned one"), "{e}");
    }
}
