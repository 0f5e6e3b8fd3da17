//! End-to-end test support: start the real alignment server on loopback with
//! the real ONNX model, and a test client built on the headset link's own
//! connection code (`holoface_runtime::link::connection`: pinned TLS 1.3
//! endpoint, handshake, frame streams, reply reader), with the raw access
//! misbehaviour tests need: [`TestClient::connect`] does the handshake with any
//! hello, [`TestClient::send_frame`] opens one stream per frame,
//! [`TestClient::next_reply`] reads replies from whichever channel the server
//! chose, [`TestClient::close_code`] reports how the server closed.
//!
//! Paths: the model is `$HOLOFACE_DAN_MODEL`, else `models/assets/dan.onnx`
//! in the workspace; ONNX Runtime is `$ORT_DYLIB_PATH`, else
//! `.cache/holoface/…`, else the copy inside `.venv`'s onnxruntime wheel.
//! A missing file is a test failure with a message saying how to get it.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use bytes::{Bytes, BytesMut};
use holoface_alignment_server::AlignmentServer;
use holoface_alignment_server::config::Settings;
use holoface_alignment_server::metrics::Metrics;
use holoface_protocol::{
    ClientHello, CloseCode, Crop, CropEncoding, FrameReply, FrameRequest, Message, PROTOCOL_VERSION,
    ServerWelcome, encode_framed,
};
use holoface_quic::Fingerprint;
use holoface_runtime::link::connection::{self, Control, ReplyReader};
use holoface_runtime::link::{ConnectConfig, LinkError};
use quinn::{Connection, Endpoint, SendStream};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

/// The token the test servers accept.
pub const TEST_TOKEN: &str = "e2e-token";

/// How long a test waits for something that should happen at once (a reply, a handshake, a close): a bound
/// that only a hang reaches, never a timing the test measures.
pub const WAIT: Duration = Duration::from_secs(20);

/// `fut`, or a panic naming `what` after [`WAIT`]: a test that would hang fails instead.
pub async fn within<T>(what: &str, fut: impl Future<Output = T>) -> T {
    tokio::time::timeout(WAIT, fut)
        .await
        .unwrap_or_else(|_| panic!("timed out waiting for {what}"))
}

/// Client-side failures: the headset link's own error type.
pub type ClientError = LinkError;

/// The workspace root (parent of this crate).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map_or_else(|| PathBuf::from("."), Path::to_path_buf)
}

/// `$env` when set and not empty, else `default` under the workspace root; it must be a file.
///
/// # Panics
/// If it is not (the e2e tests must fail, not skip, without their assets); `hint` says how to get it.
fn required_asset(env: &str, default: &str, what: &str, hint: &str) -> PathBuf {
    let path = std::env::var_os(env)
        .filter(|v| !v.is_empty())
        .map_or_else(|| workspace_root().join(default), PathBuf::from);
    assert!(
        path.is_file(),
        "{what} not found at {} (set {env}, or {hint})",
        path.display()
    );
    path
}

/// The shipped refinement cascade: `$HOLOFACE_REFINE_MODEL` or `models/assets/refiner.bin`.
///
/// # Panics
/// If it is not there.
pub fn refiner_path() -> PathBuf {
    required_asset(
        "HOLOFACE_REFINE_MODEL",
        "models/assets/refiner.bin",
        "refiner model",
        "train one with `make train-refiner`",
    )
}

/// The DAN model for tests: `$HOLOFACE_DAN_MODEL` or `models/assets/dan.onnx`.
///
/// # Panics
/// If the file does not exist (the e2e tests must fail, not skip, without it).
pub fn model_path() -> PathBuf {
    required_asset(
        "HOLOFACE_DAN_MODEL",
        "models/assets/dan.onnx",
        "DAN model",
        "export one with `.venv/bin/python models/dan/export_onnx.py --random --out <path>`",
    )
}

/// The ONNX Runtime library for tests.
///
/// # Panics
/// If none of `$ORT_DYLIB_PATH`, the checkout's data folder `.cache/holoface/` or the `.venv` wheel has it.
pub fn ort_dylib_path() -> PathBuf {
    let root = workspace_root();
    let mut candidates: Vec<PathBuf> = std::env::var_os("ORT_DYLIB_PATH")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .into_iter()
        .collect();
    candidates.push(
        root.join(".cache/holoface")
            .join(holoface_files::home::ORT_LIBRARY.file),
    );
    candidates
        .push(root.join(".venv/lib/python3.11/site-packages/onnxruntime/capi/libonnxruntime.so.1.31.1"));
    match candidates.iter().find(|p| p.is_file()) {
        Some(p) => p.clone(),
        None => panic!(
            "ONNX Runtime library not found (tried {candidates:?}); run `make setup` or set ORT_DYLIB_PATH"
        ),
    }
}

/// ONNX Runtime's CUDA build (the `onnxruntime-gpu` wheel's library, `make ort-gpu`):
/// `$HOLOFACE_ORT_GPU_DYLIB`, else `.cache/onnxruntime-gpu/`.
///
/// # Panics
/// If it is not there (the fail-over tests must fail, not skip, without it).
pub fn ort_gpu_dylib_path() -> PathBuf {
    let path = std::env::var_os("HOLOFACE_ORT_GPU_DYLIB")
        .filter(|v| !v.is_empty())
        .map_or_else(
            || workspace_root().join(".cache/onnxruntime-gpu/libonnxruntime.so.1.31.1"),
            PathBuf::from,
        );
    assert!(
        path.is_file(),
        "ONNX Runtime's CUDA build not found at {} (run `make ort-gpu` or set HOLOFACE_ORT_GPU_DYLIB)",
        path.display()
    );
    path
}

/// Loopback settings with the real model and runtime, 1 intra-op thread.
pub fn loopback_settings() -> Settings {
    let mut s = match Settings::for_loopback(TEST_TOKEN, model_path(), Some(refiner_path()), ort_dylib_path())
    {
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
    task: Option<JoinHandle<Result<(), holoface_alignment_server::ServerError>>>,
}

impl RunningServer {
    /// Loads the engine, binds and spawns [`AlignmentServer::run`].
    pub async fn start(settings: Settings) -> Result<Self, holoface_alignment_server::ServerError> {
        let server = AlignmentServer::bind(settings).await?;
        Ok(Self::spawn(server))
    }

    /// Spawns an already bound server.
    pub fn spawn(server: AlignmentServer) -> Self {
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

/// A client endpoint on an ephemeral port, pinning `fingerprint` (the headset link's own endpoint).
pub fn client_endpoint(fingerprint: Fingerprint) -> Result<Endpoint, ClientError> {
    client_endpoint_with(fingerprint, None)
}

/// Like [`client_endpoint`], sending QUIC keep-alives every `keep_alive`
/// (to hold idle connections open past the server's idle timeout).
pub fn client_endpoint_with(
    fingerprint: Fingerprint,
    keep_alive: Option<Duration>,
) -> Result<Endpoint, ClientError> {
    let mut cfg = ConnectConfig::new(SocketAddr::from(([127, 0, 0, 1], 0)), fingerprint, "");
    cfg.idle_timeout = Duration::from_secs(10);
    cfg.keep_alive = keep_alive;
    connection::client_endpoint(&cfg)
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
        track_id: 0,
        frame_id,
        captured_at_us: frame_id * 33_333,
        deadline_ms,
        crop: Crop::raw(112, 112, pixels),
    }
}

/// The application close code a connection ended with, if any (the client's own helper).
pub use holoface_runtime::link::connection::app_close_code;

/// Sends one frame on its own stream of `conn` (usable from a task that
/// does not own the [`TestClient`]).
pub async fn send_frame_on(conn: &Connection, req: &FrameRequest) -> Result<(), ClientError> {
    connection::send_frame(conn, req).await?;
    Ok(())
}

/// Sends `bytes` as one unidirectional stream of `conn`.
pub async fn send_stream_bytes_on(conn: &Connection, bytes: &[u8]) -> Result<(), ClientError> {
    let mut s = conn.open_uni().await?;
    s.write_all(bytes).await?;
    s.finish()?;
    Ok(())
}

/// A HoloFace client after a successful handshake: the headset link's own connection code
/// (`holoface_runtime::link::connection`), with the raw access misbehaviour tests need.
#[derive(Debug)]
pub struct TestClient {
    /// The client endpoint (kept alive with the connection).
    pub endpoint: Endpoint,
    /// The QUIC connection.
    pub conn: Connection,
    /// What the server answered.
    pub welcome: ServerWelcome,
    control: Control,
    replies: ReplyReader,
}

/// Sends a framed message on a stream.
pub async fn write_framed(send: &mut SendStream, msg: &Message) -> Result<(), ClientError> {
    let mut buf = BytesMut::new();
    encode_framed(msg, &mut buf)?;
    send.write_all(&buf).await?;
    Ok(())
}

impl TestClient {
    /// Connects, sends `hello` on a new control stream and waits for the
    /// welcome. A server that closes instead gives `ClientError::Link`
    /// with the close code (see [`app_close_code`]).
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
        let (conn, welcome, control, replies) = connection::handshake(conn, &hello).await?.split();
        Ok(Self {
            endpoint,
            conn,
            welcome,
            control,
            replies,
        })
    }

    /// Sends one frame on its own unidirectional stream.
    pub async fn send_frame(&self, req: &FrameRequest) -> Result<(), ClientError> {
        send_frame_on(&self.conn, req).await
    }

    /// Sends arbitrary bytes as one frame stream (for misbehaviour tests).
    pub async fn send_stream_bytes(&self, bytes: &[u8]) -> Result<(), ClientError> {
        send_stream_bytes_on(&self.conn, bytes).await
    }

    /// The next reply, from the channel the welcome announced.
    pub async fn next_reply(&mut self) -> Result<FrameReply, ClientError> {
        self.replies.next().await
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
        self.control.next_message().await
    }

    /// Writes raw bytes on the control stream (for misbehaviour tests).
    pub async fn send_control_bytes(&mut self, bytes: &[u8]) -> Result<(), ClientError> {
        self.control.write_bytes(bytes).await
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
    match connection::handshake(conn.clone(), &hello).await {
        Ok(_) => None,
        Err(LinkError::Connection(e)) => app_close_code(&e),
        Err(_) => app_close_code(&conn.closed().await),
    }
}

/// The shipped `holoface-server` binary of the same build as the running test (`target/<profile>/`), for tests
/// that treat the server as an operator's process (signals, exit codes, logs).
///
/// # Panics
/// If it has not been built (`cargo build --bins -p holoface-alignment-server` with the test's profile; `make
/// test` builds every binary first).
pub fn server_binary() -> PathBuf {
    let exe = std::env::current_exe().unwrap_or_default();
    // target/<profile>/deps/<test binary>
    let profile_dir = exe.parent().and_then(Path::parent).unwrap_or(Path::new("."));
    let bin = profile_dir.join(format!("holoface-server{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.is_file(),
        "{} not built (cargo build --bins -p holoface-alignment-server, same profile as the tests)",
        bin.display()
    );
    bin
}
