//! End-to-end test support: start the real alignment server on loopback with
//! the real ONNX model, and a small quinn client that speaks the HoloFace
//! protocol (pinning the server's self-signed certificate).
//!
//! The client here is deliberately minimal and reusable by the load tester
//! and the headset link: [`TestClient::connect`] does the handshake,
//! [`TestClient::send_frame`] opens one stream per frame,
//! [`TestClient::next_reply`] reads replies from whichever channel the
//! server chose, [`TestClient::close_code`] reports how the server closed.
//!
//! Paths: the model is `$HOLOFACE_DAN_MODEL`, else `models/assets/dan.onnx`
//! in the workspace; ONNX Runtime is `$ORT_DYLIB_PATH`, else
//! `.cache/onnxruntime/…`, else the copy inside `.venv`'s onnxruntime wheel.
//! A missing file is a test failure with a message saying how to get it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use alignment_server::Server;
use alignment_server::config::Settings;
use alignment_server::metrics::Metrics;
use bytes::{Bytes, BytesMut};
use holoface_protocol::{
    ClientHello, CloseCode, Crop, CropEncoding, DecodeError, FrameReply, FrameRequest, Message,
    PROTOCOL_VERSION, ReplyChannel, ServerWelcome, encode_framed,
};
use holoface_quic::{Fingerprint, pinned_client_config};
use quinn::{Connection, ConnectionError, Endpoint, RecvStream, SendStream};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// The token the test servers accept.
pub const TEST_TOKEN: &str = "e2e-token";

/// Client-side failures.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// Building the TLS config failed.
    #[error("tls: {0}")]
    Tls(#[from] holoface_quic::TlsError),
    /// Creating the endpoint failed.
    #[error("endpoint: {0}")]
    Io(#[from] std::io::Error),
    /// Connecting failed.
    #[error("connect: {0}")]
    Connect(#[from] quinn::ConnectError),
    /// The connection failed or was closed.
    #[error("connection: {0}")]
    Connection(#[from] ConnectionError),
    /// Writing a stream failed.
    #[error("write: {0}")]
    Write(#[from] quinn::WriteError),
    /// Reading a stream failed.
    #[error("read: {0}")]
    Read(#[from] quinn::ReadError),
    /// The stream was already closed.
    #[error("closed stream: {0}")]
    ClosedStream(#[from] quinn::ClosedStream),
    /// The server sent something undecodable.
    #[error("decode: {0}")]
    Decode(#[from] DecodeError),
    /// Encoding failed.
    #[error("encode: {0}")]
    Encode(#[from] holoface_protocol::EncodeError),
    /// The server sent an unexpected message or ended a stream early.
    #[error("protocol: {0}")]
    Protocol(String),
    /// Reading a framed message failed (the client library's reader).
    #[error(transparent)]
    Session(#[from] holoface_client::link::session::SessionError),
}

/// The workspace root (parent of this crate).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
}

/// The DAN model for tests: `$HOLOFACE_DAN_MODEL` or `models/assets/dan.onnx`.
///
/// # Panics
/// If the file does not exist (the e2e tests must fail, not skip, without it).
pub fn model_path() -> PathBuf {
    let path = std::env::var_os("HOLOFACE_DAN_MODEL")
        .filter(|v| !v.is_empty())
        .map_or_else(|| workspace_root().join("models/assets/dan.onnx"), PathBuf::from);
    assert!(
        path.is_file(),
        "DAN model not found at {} (set HOLOFACE_DAN_MODEL, or export one with \
         `.venv/bin/python models/dan/export_onnx.py --random --out <path>`)",
        path.display()
    );
    path
}

/// The ONNX Runtime library for tests.
///
/// # Panics
/// If none of `$ORT_DYLIB_PATH`, `.cache/onnxruntime/` or the `.venv` wheel has it.
pub fn ort_dylib_path() -> PathBuf {
    let root = workspace_root();
    let mut candidates: Vec<PathBuf> = std::env::var_os("ORT_DYLIB_PATH")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .into_iter()
        .collect();
    candidates.push(root.join(holoface_inference::DEFAULT_ORT_DYLIB));
    candidates
        .push(root.join(".venv/lib/python3.11/site-packages/onnxruntime/capi/libonnxruntime.so.1.31.1"));
    match candidates.iter().find(|p| p.is_file()) {
        Some(p) => p.clone(),
        None => panic!(
            "ONNX Runtime library not found (tried {candidates:?}); run `make ort` or set ORT_DYLIB_PATH"
        ),
    }
}

/// Loopback settings with the real model and runtime, 1 intra-op thread.
pub fn loopback_settings() -> Settings {
    let mut s = match Settings::for_loopback(TEST_TOKEN, model_path(), ort_dylib_path()) {
        Ok(s) => s,
        Err(e) => panic!("loopback settings: {e}"),
    };
    s.engine.intra_threads = 1;
    s.shutdown_timeout = Duration::from_secs(5);
    s
}

/// A server running on a background task.
#[derive(Debug)]
pub struct RunningServer {
    /// UDP address.
    pub addr: SocketAddr,
    /// Certificate fingerprint to pin.
    pub fingerprint: Fingerprint,
    /// Live metrics.
    pub metrics: Arc<Metrics>,
    /// Internal HTTP listener, if enabled.
    pub metrics_addr: Option<SocketAddr>,
    shutdown: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<Result<(), alignment_server::ServerError>>>,
}

impl RunningServer {
    /// Loads the engine, binds and spawns [`Server::run`].
    pub async fn start(settings: Settings) -> Result<Self, alignment_server::ServerError> {
        let server = Server::bind(settings).await?;
        Ok(Self::spawn(server))
    }

    /// Spawns an already bound server.
    pub fn spawn(server: Server) -> Self {
        let addr = server
            .local_addr()
            .unwrap_or_else(|_| SocketAddr::from(([127, 0, 0, 1], 0)));
        let fingerprint = server.fingerprint();
        let metrics = server.metrics();
        let metrics_addr = server.metrics_addr();
        let (tx, rx) = oneshot::channel::<()>();
        let task = tokio::spawn(server.run(async move {
            let _ = rx.await;
        }));
        Self {
            addr,
            fingerprint,
            metrics,
            metrics_addr,
            shutdown: Some(tx),
            task: Some(task),
        }
    }

    /// Triggers graceful shutdown and waits for `run` to return.
    pub async fn shutdown(mut self) -> Result<(), String> {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        match self.task.take() {
            Some(task) => match task.await {
                Ok(Ok(())) => Ok(()),
                Ok(Err(e)) => Err(e.to_string()),
                Err(e) => Err(e.to_string()),
            },
            None => Ok(()),
        }
    }
}

/// A client endpoint on an ephemeral loopback port, pinning `fingerprint`.
pub fn client_endpoint(fingerprint: Fingerprint) -> Result<Endpoint, ClientError> {
    client_endpoint_with(fingerprint, None)
}

/// Like [`client_endpoint`], sending QUIC keep-alives every `keep_alive`
/// (to hold idle connections open past the server's idle timeout).
pub fn client_endpoint_with(
    fingerprint: Fingerprint,
    keep_alive: Option<Duration>,
) -> Result<Endpoint, ClientError> {
    let mut endpoint = Endpoint::client(SocketAddr::from(([127, 0, 0, 1], 0)))?;
    let mut cfg = pinned_client_config(fingerprint)?;
    let mut transport = quinn::TransportConfig::default();
    transport.max_idle_timeout(quinn::IdleTimeout::try_from(Duration::from_secs(10)).ok());
    transport.keep_alive_interval(keep_alive);
    cfg.transport_config(Arc::new(transport));
    endpoint.set_default_client_config(cfg);
    Ok(endpoint)
}

/// A QUIC connection to the server, no HoloFace handshake yet.
pub async fn connect_raw(endpoint: &Endpoint, addr: SocketAddr) -> Result<Connection, ClientError> {
    Ok(endpoint.connect(addr, "localhost")?.await?)
}

/// A well-formed hello with `token`.
pub fn hello(token: &str) -> ClientHello {
    ClientHello {
        version: PROTOCOL_VERSION,
        token: token.to_owned(),
        client_name: "e2e".to_owned(),
        encodings: vec![CropEncoding::Raw],
        max_in_flight: 2,
    }
}

/// A raw 112x112 crop request: a smooth pattern seeded by `seed`.
pub fn frame(frame_id: u64, seed: u8, deadline_ms: u16) -> FrameRequest {
    let pixels: Vec<u8> = (0..112_usize * 112)
        .map(|i| {
            let (x, y) = (i % 112, i / 112);
            let v = (x * 2 + y + usize::from(seed) * 7) % 256;
            u8::try_from(v).unwrap_or(0)
        })
        .collect();
    FrameRequest {
        frame_id,
        captured_at_us: frame_id * 33_333,
        deadline_ms,
        crop: Crop::raw(112, 112, pixels),
    }
}

/// The application close code a connection ended with, if any (the client's own helper).
pub use holoface_client::link::session::app_close_code;

/// Sends one frame on its own stream of `conn` (usable from a task that
/// does not own the [`TestClient`]).
pub async fn send_frame_on(conn: &Connection, req: &FrameRequest) -> Result<(), ClientError> {
    let bytes = Message::FrameRequest(req.clone()).to_bytes()?;
    send_stream_bytes_on(conn, &bytes).await
}

/// Sends `bytes` as one unidirectional stream of `conn`.
pub async fn send_stream_bytes_on(conn: &Connection, bytes: &[u8]) -> Result<(), ClientError> {
    let mut s = conn.open_uni().await?;
    s.write_all(bytes).await?;
    s.finish()?;
    Ok(())
}

/// A HoloFace client after a successful handshake.
#[derive(Debug)]
pub struct TestClient {
    /// The client endpoint (kept alive with the connection).
    pub endpoint: Endpoint,
    /// The QUIC connection.
    pub conn: Connection,
    /// What the server answered.
    pub welcome: ServerWelcome,
    ctl_send: SendStream,
    ctl_recv: RecvStream,
    ctl_buf: BytesMut,
    reply_stream: Option<RecvStream>,
    reply_buf: BytesMut,
}

/// Sends a framed message on a stream.
pub async fn write_framed(send: &mut SendStream, msg: &Message) -> Result<(), ClientError> {
    let mut buf = BytesMut::new();
    encode_framed(msg, &mut buf)?;
    send.write_all(&buf).await?;
    Ok(())
}

async fn read_framed(recv: &mut RecvStream, buf: &mut BytesMut) -> Result<Message, ClientError> {
    Ok(holoface_client::link::session::read_framed(recv, buf).await?)
}

impl TestClient {
    /// Connects, sends `hello` on a new control stream and waits for the
    /// welcome. A server that closes instead gives `ClientError::Connection`
    /// (see [`app_close_code`]) or `Read`.
    pub async fn connect(
        addr: SocketAddr,
        fingerprint: Fingerprint,
        hello: ClientHello,
    ) -> Result<Self, ClientError> {
        Self::connect_on(client_endpoint(fingerprint)?, addr, hello).await
    }

    /// Like [`Self::connect`] on an existing endpoint (many connections can
    /// share one endpoint and its UDP socket).
    pub async fn connect_on(
        endpoint: Endpoint,
        addr: SocketAddr,
        hello: ClientHello,
    ) -> Result<Self, ClientError> {
        let conn = connect_raw(&endpoint, addr).await?;
        let (mut ctl_send, mut ctl_recv) = conn.open_bi().await?;
        write_framed(&mut ctl_send, &Message::ClientHello(hello)).await?;
        let mut ctl_buf = BytesMut::new();
        let welcome = match read_framed(&mut ctl_recv, &mut ctl_buf).await? {
            Message::ServerWelcome(w) => w,
            other => {
                return Err(ClientError::Protocol(format!(
                    "expected ServerWelcome, got {other:?}"
                )));
            }
        };
        Ok(Self {
            endpoint,
            conn,
            welcome,
            ctl_send,
            ctl_recv,
            ctl_buf,
            reply_stream: None,
            reply_buf: BytesMut::new(),
        })
    }

    /// Sends one frame on its own unidirectional stream.
    pub async fn send_frame(&self, req: &FrameRequest) -> Result<(), ClientError> {
        let bytes = Message::FrameRequest(req.clone()).to_bytes()?;
        self.send_stream_bytes(&bytes).await
    }

    /// Sends arbitrary bytes as one frame stream (for misbehaviour tests).
    pub async fn send_stream_bytes(&self, bytes: &[u8]) -> Result<(), ClientError> {
        send_stream_bytes_on(&self.conn, bytes).await
    }

    /// The next reply, from the channel the welcome announced.
    pub async fn next_reply(&mut self) -> Result<FrameReply, ClientError> {
        let msg = match self.welcome.reply_channel {
            ReplyChannel::Datagram => Message::decode(self.conn.read_datagram().await?)?,
            ReplyChannel::Stream => {
                if self.reply_stream.is_none() {
                    self.reply_stream = Some(self.conn.accept_uni().await?);
                }
                match self.reply_stream.as_mut() {
                    Some(s) => read_framed(s, &mut self.reply_buf).await?,
                    None => return Err(ClientError::Protocol("no reply stream".into())),
                }
            }
        };
        match msg {
            Message::FrameReply(r) => Ok(r),
            other => Err(ClientError::Protocol(format!(
                "expected FrameReply, got {other:?}"
            ))),
        }
    }

    /// Sends one frame and waits for its reply (skipping replies to older frames).
    pub async fn request(&mut self, req: &FrameRequest) -> Result<FrameReply, ClientError> {
        self.send_frame(req).await?;
        loop {
            let r = self.next_reply().await?;
            if r.frame_id == req.frame_id {
                return Ok(r);
            }
        }
    }

    /// The next framed message on the control stream (e.g. `Goaway`).
    pub async fn next_control(&mut self) -> Result<Message, ClientError> {
        read_framed(&mut self.ctl_recv, &mut self.ctl_buf).await
    }

    /// Writes raw bytes on the control stream (for misbehaviour tests).
    pub async fn send_control_bytes(&mut self, bytes: &[u8]) -> Result<(), ClientError> {
        self.ctl_send.write_all(bytes).await?;
        Ok(())
    }

    /// Sends a datagram to the server (clients must not; for tests).
    pub fn send_datagram(&self, bytes: Bytes) -> Result<(), quinn::SendDatagramError> {
        self.conn.send_datagram(bytes)
    }

    /// Waits until the connection closes; the server's close code, if any.
    pub async fn close_code(&self) -> Option<CloseCode> {
        app_close_code(&self.conn.closed().await)
    }
}

/// Connects with `hello` and returns the close code the server used to refuse
/// it, or `None` if it was welcomed (or closed without a code).
pub async fn refused_with(
    addr: SocketAddr,
    fingerprint: Fingerprint,
    hello: ClientHello,
) -> Option<CloseCode> {
    let endpoint = client_endpoint(fingerprint).ok()?;
    let conn = match endpoint.connect(addr, "localhost").ok()?.await {
        Ok(c) => c,
        // Closed during the handshake (e.g. the client cap).
        Err(e) => return app_close_code(&e),
    };
    let (mut send, mut recv) = match conn.open_bi().await {
        Ok(s) => s,
        Err(e) => return app_close_code(&e),
    };
    let _ = write_framed(&mut send, &Message::ClientHello(hello)).await;
    let mut buf = BytesMut::new();
    if let Ok(Message::ServerWelcome(_)) = read_framed(&mut recv, &mut buf).await {
        return None;
    }
    app_close_code(&conn.closed().await)
}
