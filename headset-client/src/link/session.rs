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
    ClientHello, CloseCode, CropEncoding, DecodeError, FrameReply, FrameRequest, Message, PROTOCOL_VERSION,
    ReplyChannel, ServerWelcome, decode_framed, encode_framed,
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
    /// QUIC keep-alive interval (well below `idle_timeout`).
    pub keep_alive: Duration,
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
            keep_alive: Duration::from_millis(500),
        }
    }
}

/// Why a connection could not be made or ended.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SessionError {
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
    #[error("server speaks protocol version {server}, we speak {PROTOCOL_VERSION}")]
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

fn close_hint(e: &ConnectionError) -> String {
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
pub fn client_endpoint(cfg: &ConnectConfig) -> Result<Endpoint, SessionError> {
    let bind = if cfg.server.is_ipv4() {
        SocketAddr::from(([0, 0, 0, 0], 0))
    } else {
        SocketAddr::from(([0u16; 8], 0))
    };
    let mut endpoint = Endpoint::client(bind)?;
    let mut client = pinned_client_config(cfg.fingerprint)?;
    let mut transport = quinn::TransportConfig::default();
    transport.max_idle_timeout(quinn::IdleTimeout::try_from(cfg.idle_timeout).ok());
    transport.keep_alive_interval(Some(cfg.keep_alive));
    client.transport_config(Arc::new(transport));
    endpoint.set_default_client_config(client);
    Ok(endpoint)
}

/// A connection after a successful handshake.
#[derive(Debug)]
pub struct Session {
    /// The QUIC connection (cheap to clone; send frames with [`send_frame`]).
    pub conn: Connection,
    /// What the server answered.
    pub welcome: ServerWelcome,
    control: Control,
}

/// The control stream: the server sends `Goaway`/`Error` on it.
#[derive(Debug)]
pub struct Control {
    _send: SendStream,
    recv: RecvStream,
    buf: BytesMut,
}

impl Control {
    /// The next control message; `Goaway` and `Error` come back as errors with the server's text.
    pub async fn next(&mut self) -> Result<Message, SessionError> {
        match read_framed(&mut self.recv, &mut self.buf).await? {
            Message::Goaway(g) => Err(SessionError::Goaway(format!("{:?}: {}", g.reason, g.text))),
            Message::Error(e) => Err(SessionError::Protocol(format!(
                "server error {:?}: {}",
                e.code, e.text
            ))),
            other => Ok(other),
        }
    }
}

/// Connects and performs the HoloFace handshake, all within `cfg.connect_timeout`.
pub async fn connect(endpoint: &Endpoint, cfg: &ConnectConfig) -> Result<Session, SessionError> {
    tokio::time::timeout(cfg.connect_timeout, connect_inner(endpoint, cfg))
        .await
        .map_err(|_| SessionError::Timeout(cfg.connect_timeout))?
}

async fn connect_inner(endpoint: &Endpoint, cfg: &ConnectConfig) -> Result<Session, SessionError> {
    let conn = endpoint.connect(cfg.server, &cfg.server_name)?.await?;
    let (mut send, mut recv) = conn.open_bi().await?;
    let hello = ClientHello {
        version: PROTOCOL_VERSION,
        token: cfg.token.clone(),
        client_name: cfg.client_name.clone(),
        encodings: cfg.encodings.clone(),
        max_in_flight: cfg.max_in_flight,
    };
    let mut buf = BytesMut::new();
    encode_framed(&Message::ClientHello(hello), &mut buf)?;
    send.write_all(&buf).await?;
    let mut rbuf = BytesMut::new();
    let welcome = match read_framed(&mut recv, &mut rbuf).await {
        Ok(Message::ServerWelcome(w)) => w,
        Ok(other) => {
            return Err(SessionError::Protocol(format!(
                "expected ServerWelcome, got {other:?}"
            )));
        }
        // A refusal closes the connection with a code; report that rather than the stream error.
        Err(e) => {
            return Err(match conn.close_reason() {
                Some(reason) => SessionError::Connection(reason),
                None => e,
            });
        }
    };
    if welcome.version != PROTOCOL_VERSION {
        conn.close(CloseCode::BadVersion.as_u32().into(), b"version");
        return Err(SessionError::Version {
            server: welcome.version,
        });
    }
    Ok(Session {
        conn,
        welcome,
        control: Control {
            _send: send,
            recv,
            buf: rbuf,
        },
    })
}

impl Session {
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
pub async fn send_frame(conn: &Connection, req: &FrameRequest) -> Result<usize, SessionError> {
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
    pub async fn next(&mut self) -> Result<FrameReply, SessionError> {
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
            other => Err(SessionError::Protocol(format!(
                "expected FrameReply, got {other:?}"
            ))),
        }
    }
}

/// Reads the next length-framed message from `recv`, buffering partial input in `buf`.
pub async fn read_framed(recv: &mut RecvStream, buf: &mut BytesMut) -> Result<Message, SessionError> {
    loop {
        if let Some(m) = decode_framed(buf)? {
            return Ok(m);
        }
        match recv.read_chunk(64 * 1024, true).await? {
            Some(chunk) => buf.extend_from_slice(&chunk.bytes),
            None => return Err(SessionError::Protocol("stream ended".into())),
        }
    }
}
