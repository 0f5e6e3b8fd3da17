//! The async driver: the quinn endpoint, one task per client connection, the
//! batcher's scheduler task and the engine thread. The only module that
//! knows about tokio and quinn.
//!
//! ```text
//!  client conn task ──frame stream task──┐ Submit (bounded mpsc)
//!  client conn task ──frame stream task──┼──────────────▶ scheduler task ──Batch──▶ engine thread
//!                                        │                (DynamicBatcher)          (InferenceEngine)
//!        ◀── reply (datagram / stream) ──┴── oneshot per frame ◀────────────────────────┘
//! ```
//!
//! Per connection: the client opens the control stream (bidirectional) and
//! sends a framed `ClientHello`; the server checks version then token
//! (closing with `BadVersion` / `Unauthorized` before any inference), answers
//! with a framed `ServerWelcome`, and from then on accepts one
//! unidirectional stream per frame carrying exactly one unframed
//! `FrameRequest`. Replies go out as one datagram each, or framed on one
//! server-opened unidirectional stream, as the welcome says. On shutdown the
//! server writes a framed `Goaway` on the control stream, answers what is in
//! flight, and closes with `ShuttingDown`.

use std::future::Future;
use std::io::Cursor;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicI64, AtomicU64, Ordering};
use std::time::{Duration, Instant};

use bytes::{Bytes, BytesMut};
use holoface_protocol::limits::MAX_MESSAGE_LEN;
use holoface_protocol::{
    ClientHello, CloseCode, Crop, CropEncoding, DecodeError, DropReason, FrameReply, FrameRequest, Goaway,
    Message, PROTOCOL_VERSION, ReplyChannel, ReplyOutcome, ServerWelcome, decode_framed, encode_framed,
};
use quinn::{Connection, Incoming, ReadToEndError, RecvStream, SendStream, VarInt};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc, oneshot, watch};
use tokio::task::JoinSet;
use tracing::{debug, info, warn};

use crate::batcher::{Batch, ClientId, DynamicBatcher, Pending};
use crate::config::{ServerConfig, Settings, TlsSource};
use crate::metrics::Metrics;
use crate::tls::{Fingerprint, ServerIdentity, TlsError};
use crate::{config::ConfigError, internal};
use holoface_inference::{BatchTensor, EngineError, InferenceEngine, LandmarkOut, ModelInfo, OnnxEngine};

/// Starting or running the server failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ServerError {
    /// Bad configuration.
    #[error(transparent)]
    Config(#[from] ConfigError),
    /// TLS set-up failed.
    #[error(transparent)]
    Tls(#[from] TlsError),
    /// The engine could not be loaded.
    #[error(transparent)]
    Engine(#[from] EngineError),
    /// An I/O operation failed.
    #[error("{context}: {source}")]
    Io {
        /// What was being done.
        context: String,
        /// The error.
        source: std::io::Error,
    },
    /// The engine thread stopped unexpectedly.
    #[error("the engine thread failed: {0}")]
    EngineThread(String),
}

fn io_err(context: impl Into<String>) -> impl FnOnce(std::io::Error) -> ServerError {
    let context = context.into();
    move |source| ServerError::Io { context, source }
}

/// Why a frame was not aligned, or its landmarks.
#[derive(Debug)]
enum FrameOutcome {
    Landmarks {
        landmarks: Vec<[f32; 2]>,
        face_prob: f32,
        queue_us: u32,
        infer_us: u32,
    },
    Dropped(DropReason),
}

/// What the batcher carries for each frame.
#[derive(Debug)]
struct FrameJob {
    pixels: Bytes,
    reply: oneshot::Sender<FrameOutcome>,
}

#[derive(Debug)]
enum SchedMsg {
    Submit(Pending<FrameJob>),
    Disconnect(ClientId),
}

/// A connection-ending problem: the close code and a log/close-reason text.
#[derive(Debug)]
struct Fault {
    code: CloseCode,
    detail: String,
}

impl Fault {
    fn new(code: CloseCode, detail: impl Into<String>) -> Self {
        Self {
            code,
            detail: detail.into(),
        }
    }

    fn decode(e: &DecodeError) -> Self {
        Self::new(e.close_code(), e.to_string())
    }
}

/// How a session ended.
#[derive(Debug)]
enum SessionEnd {
    /// The peer closed or the connection was lost.
    Gone(String),
    /// The server must close the connection with this code.
    Fault(Fault),
    /// Graceful shutdown completed; close with `ShuttingDown`.
    Shutdown,
}

impl From<Fault> for SessionEnd {
    fn from(f: Fault) -> Self {
        Self::Fault(f)
    }
}

/// State shared by every connection task.
#[derive(Debug)]
struct Shared {
    settings: Settings,
    model: ModelInfo,
    metrics: Arc<Metrics>,
    sched: mpsc::Sender<SchedMsg>,
    stop: watch::Receiver<bool>,
    next_client: AtomicU64,
}

/// A bound, not yet running, alignment server.
#[derive(Debug)]
pub struct Server {
    endpoint: quinn::Endpoint,
    fingerprint: Fingerprint,
    metrics: Arc<Metrics>,
    metrics_listener: Option<tokio::net::TcpListener>,
    engine: Box<dyn InferenceEngine>,
    settings: Settings,
}

/// Loads the engine and binds; then [`Server::run`] until `shutdown`.
pub async fn run(config: ServerConfig, shutdown: impl Future<Output = ()>) -> Result<(), ServerError> {
    Server::bind(config.resolve()?).await?.run(shutdown).await
}

/// Tells systemd (`Type=notify` units) that the server is ready: `READY=1` on `$NOTIFY_SOCKET`, if set.
/// Without systemd this does nothing; a failure is logged, never fatal.
fn notify_systemd_ready() {
    if let Some(path) = std::env::var_os("NOTIFY_SOCKET") {
        notify_ready_at(&path);
    }
}

/// Sends `READY=1` to the notify socket at `path` (`@name` = abstract namespace).
fn notify_ready_at(path: &std::ffi::OsStr) {
    let sent = std::os::unix::net::UnixDatagram::unbound().and_then(|sock| {
        let bytes = std::os::unix::ffi::OsStrExt::as_bytes(path);
        match bytes.strip_prefix(b"@") {
            // Abstract socket namespace (Linux).
            Some(name) => {
                use std::os::linux::net::SocketAddrExt;
                let addr = std::os::unix::net::SocketAddr::from_abstract_name(name)?;
                sock.send_to_addr(b"READY=1", &addr)
            }
            None => sock.send_to(b"READY=1", path),
        }
    });
    if let Err(e) = sent {
        warn!(error = %e, "could not notify systemd of readiness");
    }
}

/// Resolves on SIGINT (Ctrl-C) or SIGTERM: the production shutdown trigger.
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(e) => {
                warn!(%e, "cannot listen for SIGTERM; only Ctrl-C stops the server");
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

impl Server {
    /// Loads the ONNX engine (validating the model) and binds the endpoint.
    pub async fn bind(settings: Settings) -> Result<Self, ServerError> {
        let opts = settings.engine.clone();
        let engine = tokio::task::spawn_blocking(move || OnnxEngine::load(&opts))
            .await
            .map_err(|e| ServerError::EngineThread(e.to_string()))??;
        let info = engine.info();
        info!(
            model = %settings.engine.model.display(),
            name = %info.name,
            version = %info.version,
            untrained = info.untrained,
            intra_threads = settings.engine.intra_threads,
            "model loaded"
        );
        if info.untrained {
            warn!("the model is marked untrained (random weights): landmarks are meaningless");
        }
        Self::bind_with_engine(settings, Box::new(engine)).await
    }

    /// Binds with a given engine (tests and benchmarks use this with a fake
    /// or preloaded engine).
    pub async fn bind_with_engine(
        settings: Settings,
        engine: Box<dyn InferenceEngine>,
    ) -> Result<Self, ServerError> {
        let identity = match &settings.tls {
            TlsSource::Files { cert, key } => ServerIdentity::from_pem_files(cert, key)?,
            TlsSource::SelfSigned { names } => ServerIdentity::self_signed(names)?,
        };
        let fingerprint = identity.fingerprint;
        if let Some(path) = &settings.fingerprint_file {
            std::fs::write(path, format!("{fingerprint}\n"))
                .map_err(io_err(format!("writing the fingerprint to {}", path.display())))?;
        }
        let mut server_config = quinn::ServerConfig::with_crypto(identity.quic_server_config()?);
        server_config.transport_config(Arc::new(transport_config(&settings)));
        let endpoint = quinn::Endpoint::server(server_config, settings.listen)
            .map_err(io_err(format!("binding UDP {}", settings.listen)))?;
        let metrics_listener = match settings.metrics_listen {
            Some(addr) => Some(
                tokio::net::TcpListener::bind(addr)
                    .await
                    .map_err(io_err(format!("binding the metrics listener {addr}")))?,
            ),
            None => None,
        };
        let metrics = Arc::new(Metrics::new(settings.batch.max_batch));
        Ok(Self {
            endpoint,
            fingerprint,
            metrics,
            metrics_listener,
            engine,
            settings,
        })
    }

    /// The UDP address the endpoint is bound to.
    pub fn local_addr(&self) -> Result<SocketAddr, ServerError> {
        self.endpoint
            .local_addr()
            .map_err(io_err("reading the local address"))
    }

    /// The metrics listener's address, if enabled.
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_listener.as_ref().and_then(|l| l.local_addr().ok())
    }

    /// SHA-256 of the server certificate (what clients pin).
    pub const fn fingerprint(&self) -> Fingerprint {
        self.fingerprint
    }

    /// The live metrics.
    pub fn metrics(&self) -> Arc<Metrics> {
        Arc::clone(&self.metrics)
    }

    /// The model being served.
    pub fn model(&self) -> &ModelInfo {
        self.engine.info()
    }

    /// Serves clients until `shutdown` resolves, then drains: stop accepting,
    /// let the in-flight batch finish, send `Goaway`, close every client with
    /// `ShuttingDown`, and wait (bounded) for the endpoint to go idle.
    pub async fn run(self, shutdown: impl Future<Output = ()>) -> Result<(), ServerError> {
        let Self {
            endpoint,
            fingerprint,
            metrics,
            metrics_listener,
            engine,
            settings,
        } = self;
        let model = engine.info().clone();
        let (stop_tx, stop_rx) = watch::channel(false);

        // Engine thread, fed by the scheduler.
        let (job_tx, job_rx) = std::sync::mpsc::sync_channel::<Batch<FrameJob>>(1);
        let (done_tx, done_rx) = mpsc::unbounded_channel::<()>();
        let engine_metrics = Arc::clone(&metrics);
        let engine_thread = std::thread::Builder::new()
            .name("holoface-engine".into())
            .spawn(move || engine_loop(engine, &job_rx, &done_tx, &engine_metrics))
            .map_err(io_err("starting the engine thread"))?;

        let sched_capacity = settings
            .max_clients
            .saturating_mul(usize::from(settings.max_in_flight))
            .clamp(16, 1 << 16);
        let (sched_tx, sched_rx) = mpsc::channel(sched_capacity);
        let scheduler = tokio::spawn(scheduler_loop(
            DynamicBatcher::new(settings.batch),
            sched_rx,
            job_tx,
            done_rx,
            stop_rx.clone(),
            Arc::clone(&metrics),
        ));
        let internal_task = metrics_listener.map(|l| {
            if let Ok(addr) = l.local_addr() {
                info!(%addr, "metrics and health on http://{addr}/metrics, /health");
            }
            tokio::spawn(internal::serve(l, Arc::clone(&metrics), stop_rx.clone()))
        });

        let permits = Arc::new(Semaphore::new(settings.max_clients));
        let shutdown_timeout = settings.shutdown_timeout;
        let shared = Arc::new(Shared {
            settings,
            model,
            metrics: Arc::clone(&metrics),
            sched: sched_tx,
            stop: stop_rx,
            next_client: AtomicU64::new(1),
        });
        metrics.ready.store(true, Ordering::Relaxed);
        notify_systemd_ready();
        info!(
            addr = %endpoint.local_addr().map_err(io_err("reading the local address"))?,
            %fingerprint,
            "alignment server ready; clients pin this certificate SHA-256 fingerprint"
        );

        let mut conns = JoinSet::new();
        tokio::pin!(shutdown);
        loop {
            tokio::select! {
                () = &mut shutdown => break,
                incoming = endpoint.accept() => match incoming {
                    Some(incoming) => {
                        let permit = Arc::clone(&permits).try_acquire_owned().ok();
                        conns.spawn(connection(incoming, permit, Arc::clone(&shared)));
                    }
                    None => break,
                },
                Some(_) = conns.join_next(), if !conns.is_empty() => {}
            }
        }

        info!(
            clients = conns.len(),
            "shutting down: refusing new clients, draining"
        );
        metrics.draining.store(true, Ordering::Relaxed);
        endpoint.set_server_config(None);
        let _ = stop_tx.send(true);
        let drained = tokio::time::timeout(shutdown_timeout, async {
            while conns.join_next().await.is_some() {}
        })
        .await;
        if drained.is_err() {
            warn!(
                left = conns.len(),
                "shutdown timeout: aborting remaining connections"
            );
            conns.abort_all();
        }
        endpoint.close(
            code(CloseCode::ShuttingDown),
            CloseCode::ShuttingDown.reason().as_bytes(),
        );
        if tokio::time::timeout(shutdown_timeout, endpoint.wait_idle())
            .await
            .is_err()
        {
            warn!("endpoint did not go idle before the shutdown timeout");
        }
        drop(shared);
        if tokio::time::timeout(shutdown_timeout, scheduler).await.is_err() {
            warn!("scheduler did not stop before the shutdown timeout");
        }
        if let Some(task) = internal_task {
            task.abort();
        }
        // The scheduler owned the job sender; the engine thread ends with it.
        let joined = tokio::task::spawn_blocking(move || engine_thread.join()).await;
        match joined {
            Ok(Ok(())) => {}
            Ok(Err(_)) => return Err(ServerError::EngineThread("panicked".into())),
            Err(e) => return Err(ServerError::EngineThread(e.to_string())),
        }
        info!("shutdown complete");
        Ok(())
    }
}

/// Per-frame stream receive window: one maximal message plus slack.
const FRAME_STREAM_WINDOW: u32 = (MAX_MESSAGE_LEN + 8 * 1024) as u32;

fn transport_config(settings: &Settings) -> quinn::TransportConfig {
    let mut t = quinn::TransportConfig::default();
    t.max_concurrent_bidi_streams(VarInt::from_u32(1));
    t.max_concurrent_uni_streams(VarInt::from(u32::from(settings.max_in_flight)));
    t.stream_receive_window(VarInt::from_u32(FRAME_STREAM_WINDOW));
    t.receive_window(VarInt::from_u32(
        FRAME_STREAM_WINDOW.saturating_mul(u32::from(settings.max_in_flight) + 1),
    ));
    t.datagram_receive_buffer_size(Some(16 * 1024));
    t.datagram_send_buffer_size(64 * 1024);
    if let Ok(idle) = quinn::IdleTimeout::try_from(settings.idle_timeout) {
        t.max_idle_timeout(Some(idle));
    }
    t
}

const fn code(c: CloseCode) -> VarInt {
    VarInt::from_u32(c.as_u32())
}

fn close_conn(conn: &Connection, c: CloseCode, detail: &str) {
    // Keep the reason short: it has to fit in one packet.
    let mut end = detail.len().min(120);
    while !detail.is_char_boundary(end) {
        end -= 1;
    }
    conn.close(code(c), detail.get(..end).unwrap_or_default().as_bytes());
}

/// Decrements a gauge when dropped.
struct GaugeGuard<'a>(&'a AtomicI64);

impl<'a> GaugeGuard<'a> {
    fn new(g: &'a AtomicI64) -> Self {
        g.fetch_add(1, Ordering::Relaxed);
        Self(g)
    }
}

impl Drop for GaugeGuard<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

async fn connection(incoming: Incoming, permit: Option<OwnedSemaphorePermit>, shared: Arc<Shared>) {
    let remote = incoming.remote_address();
    let conn = match incoming.await {
        Ok(c) => c,
        Err(e) => {
            debug!(%remote, %e, "handshake failed");
            return;
        }
    };
    let metrics = &shared.metrics;
    metrics.connections_total.fetch_add(1, Ordering::Relaxed);
    let Some(_permit) = permit else {
        metrics.rejected_overloaded.fetch_add(1, Ordering::Relaxed);
        metrics.count_close(CloseCode::Overloaded);
        warn!(%remote, max_clients = shared.settings.max_clients, "client cap reached: closing with Overloaded");
        close_conn(&conn, CloseCode::Overloaded, "client cap reached");
        return;
    };
    let _gauge = GaugeGuard::new(&metrics.connected_clients);
    let client = shared.next_client.fetch_add(1, Ordering::Relaxed);
    let end = session(&conn, client, &shared).await;
    let _ = shared.sched.try_send(SchedMsg::Disconnect(client));
    match end {
        SessionEnd::Gone(why) => debug!(client, %remote, why, "client gone"),
        SessionEnd::Shutdown => {
            metrics.count_close(CloseCode::ShuttingDown);
            close_conn(&conn, CloseCode::ShuttingDown, CloseCode::ShuttingDown.reason());
            // Let the CONNECTION_CLOSE go out before the endpoint is closed.
            let _ = tokio::time::timeout(Duration::from_millis(200), conn.closed()).await;
        }
        SessionEnd::Fault(f) => {
            metrics.count_close(f.code);
            warn!(client, %remote, code = %f.code, detail = %f.detail, "closing misbehaving client");
            close_conn(&conn, f.code, &f.detail);
        }
    }
}

async fn read_hello(recv: &mut RecvStream) -> Result<ClientHello, SessionEnd> {
    let mut buf = BytesMut::new();
    loop {
        match decode_framed(&mut buf) {
            Ok(Some(Message::ClientHello(h))) => return Ok(h),
            Ok(Some(other)) => {
                return Err(Fault::new(
                    CloseCode::ProtocolViolation,
                    format!("first message must be ClientHello, got tag {}", other.tag()),
                )
                .into());
            }
            Ok(None) => {}
            Err(e) => return Err(Fault::decode(&e).into()),
        }
        match recv.read_chunk(8 * 1024, true).await {
            Ok(Some(chunk)) => buf.extend_from_slice(&chunk.bytes),
            Ok(None) => {
                return Err(Fault::new(
                    CloseCode::ProtocolViolation,
                    "control stream finished before ClientHello",
                )
                .into());
            }
            Err(e) => return Err(SessionEnd::Gone(e.to_string())),
        }
    }
}

/// Compares without an early exit on the first differing byte.
fn token_eq(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0_u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

fn authorize(hello: &ClientHello, settings: &Settings, metrics: &Metrics) -> Result<(), Fault> {
    if hello.version != PROTOCOL_VERSION {
        metrics.auth_bad_version.fetch_add(1, Ordering::Relaxed);
        return Err(Fault::new(
            CloseCode::BadVersion,
            format!(
                "protocol version {} not supported (server speaks {PROTOCOL_VERSION})",
                hello.version
            ),
        ));
    }
    let ok = settings.allow_anonymous
        || settings
            .tokens
            .iter()
            .fold(false, |found, t| found | token_eq(t, &hello.token));
    if !ok {
        metrics.auth_unauthorized.fetch_add(1, Ordering::Relaxed);
        return Err(Fault::new(CloseCode::Unauthorized, "token rejected"));
    }
    Ok(())
}

/// Per-connection state shared by its frame tasks.
#[derive(Debug)]
struct ConnCtx {
    client: ClientId,
    shared: Arc<Shared>,
    sink: ReplySink,
    /// Highest frame id seen (`None` before the first frame).
    newest: std::sync::Mutex<Option<u64>>,
    read_timeout: Duration,
}

#[derive(Debug, Clone)]
enum ReplySink {
    Datagram(Connection),
    Stream(mpsc::Sender<Bytes>),
}

impl ReplySink {
    fn send(&self, reply: FrameReply) {
        let msg = Message::FrameReply(reply);
        match self {
            Self::Datagram(conn) => match msg.to_bytes() {
                Ok(bytes) => {
                    if let Err(e) = conn.send_datagram(bytes) {
                        debug!(%e, "reply datagram not sent");
                    }
                }
                Err(e) => warn!(%e, "reply does not encode"),
            },
            Self::Stream(tx) => {
                let mut buf = BytesMut::new();
                match encode_framed(&msg, &mut buf) {
                    Ok(()) => {
                        if tx.try_send(buf.freeze()).is_err() {
                            debug!("reply stream backlog full: reply dropped");
                        }
                    }
                    Err(e) => warn!(%e, "reply does not encode"),
                }
            }
        }
    }
}

async fn reply_writer(conn: Connection, mut rx: mpsc::Receiver<Bytes>) {
    let mut stream: Option<SendStream> = None;
    while let Some(bytes) = rx.recv().await {
        if stream.is_none() {
            match conn.open_uni().await {
                Ok(s) => stream = Some(s),
                Err(e) => {
                    debug!(%e, "cannot open the reply stream");
                    return;
                }
            }
        }
        if let Some(s) = stream.as_mut()
            && let Err(e) = s.write_all(&bytes).await
        {
            debug!(%e, "reply stream write failed");
            return;
        }
    }
    if let Some(mut s) = stream
        && s.finish().is_ok()
    {
        let _ = tokio::time::timeout(CLOSE_GRACE, s.stopped()).await;
    }
}

/// How often each connection's RTT and loss are sampled into the metrics.
const STATS_PERIOD: Duration = Duration::from_secs(5);

/// A draining connection stops accepting frame streams after this long without one.
const DRAIN_QUIET: Duration = Duration::from_millis(100);

/// How long a draining connection waits for the peer to acknowledge its last data.
const CLOSE_GRACE: Duration = Duration::from_secs(1);

async fn session(conn: &Connection, client: ClientId, shared: &Arc<Shared>) -> SessionEnd {
    let settings = &shared.settings;
    let mut stop = shared.stop.clone();
    // 1. The control stream and the hello, within the hello timeout.
    let handshake = async {
        let (send, mut recv) = conn
            .accept_bi()
            .await
            .map_err(|e| SessionEnd::Gone(e.to_string()))?;
        let hello = read_hello(&mut recv).await?;
        Ok::<_, SessionEnd>((send, recv, hello))
    };
    let (mut ctl_send, mut ctl_recv, hello) = tokio::select! {
        r = tokio::time::timeout(settings.hello_timeout, handshake) => match r {
            Ok(Ok(v)) => v,
            Ok(Err(end)) => return end,
            Err(_) => return Fault::new(CloseCode::ProtocolViolation, "no ClientHello before the hello timeout").into(),
        },
        () = internal::stopped(&mut stop) => return SessionEnd::Shutdown,
    };
    if let Err(f) = authorize(&hello, settings, &shared.metrics) {
        return f.into();
    }

    // 2. Welcome.
    let encoding = hello.encodings.first().copied().unwrap_or(CropEncoding::Raw);
    let reply_channel = match (settings.reply_channel, conn.max_datagram_size()) {
        (ReplyChannel::Datagram, Some(max)) if max >= 1200.min(max_reply_len(&shared.model)) => {
            ReplyChannel::Datagram
        }
        _ => ReplyChannel::Stream,
    };
    let max_in_flight = hello.max_in_flight.clamp(1, settings.max_in_flight);
    conn.set_max_concurrent_uni_streams(VarInt::from(u32::from(max_in_flight)));
    let model = &shared.model;
    let welcome = Message::ServerWelcome(ServerWelcome {
        version: PROTOCOL_VERSION,
        model_id: model.name.clone(),
        model_version: model.version.clone(),
        landmark_count: u16::try_from(model.landmark_count).unwrap_or(u16::MAX),
        crop_size: u16::try_from(model.crop_size).unwrap_or(u16::MAX),
        mean_shape: model.mean_shape.clone(),
        face_threshold: model.face_threshold,
        encoding,
        reply_channel,
        max_in_flight,
        max_frame_age_ms: u32::try_from(settings.max_frame_age.as_millis()).unwrap_or(u32::MAX),
    });
    let mut buf = BytesMut::new();
    if let Err(e) = encode_framed(&welcome, &mut buf) {
        return Fault::new(CloseCode::Internal, format!("welcome does not encode: {e}")).into();
    }
    if let Err(e) = ctl_send.write_all(&buf).await {
        return SessionEnd::Gone(e.to_string());
    }
    info!(
        client,
        remote = %conn.remote_address(),
        name = %hello.client_name,
        ?encoding,
        ?reply_channel,
        max_in_flight,
        "client connected"
    );

    let (sink, writer) = match reply_channel {
        ReplyChannel::Datagram => (ReplySink::Datagram(conn.clone()), None),
        ReplyChannel::Stream => {
            let (tx, rx) = mpsc::channel(usize::from(max_in_flight) * 4 + 4);
            (
                ReplySink::Stream(tx),
                Some(tokio::spawn(reply_writer(conn.clone(), rx))),
            )
        }
    };
    let ctx = Arc::new(ConnCtx {
        client,
        shared: Arc::clone(shared),
        sink,
        newest: std::sync::Mutex::new(None),
        read_timeout: settings.hello_timeout.max(settings.max_frame_age),
    });

    // 3. Frames until the client leaves, misbehaves, or the server stops.
    let mut rate = RateLimit::new(settings.max_frame_rate, Instant::now());
    let mut stats_tick = tokio::time::interval(STATS_PERIOD);
    let mut lost_reported = 0_u64;
    let mut frames: JoinSet<Result<(), Fault>> = JoinSet::new();
    let mut ctl_buf = BytesMut::new();
    let mut ctl_open = true;
    let end = loop {
        tokio::select! {
            () = internal::stopped(&mut stop) => break SessionEnd::Shutdown,
            _ = stats_tick.tick() => {
                let path = conn.stats().path;
                shared.metrics.client_rtt_us.observe_duration(path.rtt);
                let lost = path.lost_packets;
                shared
                    .metrics
                    .client_lost_packets
                    .fetch_add(lost.saturating_sub(lost_reported), Ordering::Relaxed);
                lost_reported = lost;
            },
            stream = conn.accept_uni() => match stream {
                Ok(recv) => {
                    if !rate.take(Instant::now()) {
                        break Fault::new(
                            CloseCode::Overloaded,
                            format!("frame rate above {} per second", settings.max_frame_rate),
                        )
                        .into();
                    }
                    frames.spawn(frame_task(recv, Arc::clone(&ctx)));
                }
                Err(e) => break SessionEnd::Gone(e.to_string()),
            },
            datagram = conn.read_datagram() => match datagram {
                Ok(bytes) => {
                    break match Message::decode(bytes) {
                        Err(e) => Fault::decode(&e).into(),
                        Ok(m) => Fault::new(
                            CloseCode::ProtocolViolation,
                            format!("clients must not send datagrams (got tag {})", m.tag()),
                        )
                        .into(),
                    };
                }
                Err(e) => break SessionEnd::Gone(e.to_string()),
            },
            chunk = ctl_recv.read_chunk(4096, true), if ctl_open => match chunk {
                Ok(Some(c)) => {
                    ctl_buf.extend_from_slice(&c.bytes);
                    match decode_framed(&mut ctl_buf) {
                        Ok(None) => {}
                        Ok(Some(Message::Error(e))) => {
                            break SessionEnd::Gone(format!("client error {}: {}", e.code, e.text));
                        }
                        Ok(Some(m)) => {
                            break Fault::new(
                                CloseCode::ProtocolViolation,
                                format!("unexpected message (tag {}) on the control stream", m.tag()),
                            )
                            .into();
                        }
                        Err(e) => break Fault::decode(&e).into(),
                    }
                }
                Ok(None) => ctl_open = false,
                Err(e) => break SessionEnd::Gone(e.to_string()),
            },
            Some(joined) = frames.join_next(), if !frames.is_empty() => match joined {
                Ok(Ok(())) => {}
                Ok(Err(fault)) => break fault.into(),
                Err(e) => break Fault::new(CloseCode::Internal, format!("frame task failed: {e}")).into(),
            },
        }
    };

    match end {
        SessionEnd::Shutdown => {
            // Goaway, then answer what is in flight (the scheduler drains).
            let mut buf = BytesMut::new();
            let goaway = Message::Goaway(Goaway {
                reason: CloseCode::ShuttingDown,
                text: "server shutting down".into(),
            });
            if encode_framed(&goaway, &mut buf).is_ok() {
                let _ = tokio::time::timeout(Duration::from_millis(500), ctl_send.write_all(&buf)).await;
            }
            let deadline = shared.settings.shutdown_timeout;
            // Frames the client sent before it saw the Goaway still get an
            // answer (landmarks if already batched, else ShuttingDown): keep
            // accepting until in-flight work is done and the link is quiet.
            let drain = async {
                loop {
                    tokio::select! {
                        Some(_) = frames.join_next(), if !frames.is_empty() => {}
                        stream = conn.accept_uni() => match stream {
                            Ok(recv) => {
                                frames.spawn(frame_task(recv, Arc::clone(&ctx)));
                            }
                            Err(_) => break,
                        },
                        () = tokio::time::sleep(DRAIN_QUIET), if frames.is_empty() => break,
                    }
                }
            };
            let _ = tokio::time::timeout(deadline, drain).await;
            frames.abort_all();
            drop(ctx);
            if let Some(w) = writer {
                let _ = tokio::time::timeout(CLOSE_GRACE, w).await;
            }
            // Finish the control stream and wait (bounded) for the peer to
            // acknowledge it: the Goaway and the last replies, queued before
            // the FIN, are then on the client's side before the close.
            if ctl_send.finish().is_ok() {
                let _ = tokio::time::timeout(CLOSE_GRACE.min(deadline), ctl_send.stopped()).await;
            }
            SessionEnd::Shutdown
        }
        other => {
            frames.abort_all();
            if let Some(w) = writer {
                w.abort();
            }
            other
        }
    }
}

/// A token bucket over frames: `rate` per second, a burst of `rate`
/// (one second's worth). Sans-IO: the caller passes `now`.
#[derive(Debug, Clone, Copy)]
struct RateLimit {
    rate: f64,
    tokens: f64,
    last: Instant,
}

impl RateLimit {
    /// `rate == 0` means unlimited.
    fn new(rate: u32, now: Instant) -> Self {
        Self {
            rate: f64::from(rate),
            tokens: f64::from(rate),
            last: now,
        }
    }

    /// Takes one token; `false` when the client is over its rate.
    fn take(&mut self, now: Instant) -> bool {
        if self.rate <= 0.0 {
            return true;
        }
        let elapsed = now.saturating_duration_since(self.last).as_secs_f64();
        self.last = now;
        self.tokens = (self.tokens + elapsed * self.rate).min(self.rate);
        if self.tokens >= 1.0 {
            self.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

fn max_reply_len(model: &ModelInfo) -> usize {
    // tag + frame_id + outcome + count + points + prob + queue + infer
    1 + 8 + 1 + 2 + 8 * model.landmark_count + 4 + 4 + 4
}

/// Decodes a crop into `size` x `size` gray8 pixels.
fn crop_pixels(crop: &Crop, size: usize) -> Option<Bytes> {
    if usize::from(crop.width) != size || usize::from(crop.height) != size {
        return None;
    }
    let format = match crop.encoding {
        // The protocol decoder already checked len == width * height.
        CropEncoding::Raw => return Some(crop.data.clone()),
        CropEncoding::Png => image::ImageFormat::Png,
        CropEncoding::Jpeg => image::ImageFormat::Jpeg,
    };
    let mut reader = image::ImageReader::with_format(Cursor::new(&crop.data[..]), format);
    let mut limits = image::Limits::default();
    let side = u32::try_from(size).ok()?;
    limits.max_image_width = Some(side);
    limits.max_image_height = Some(side);
    limits.max_alloc = Some(4 * 1024 * 1024);
    reader.limits(limits);
    let img = reader.decode().ok()?.into_luma8();
    (img.width() == side && img.height() == side).then(|| Bytes::from(img.into_raw()))
}

async fn frame_task(mut recv: RecvStream, ctx: Arc<ConnCtx>) -> Result<(), Fault> {
    let data = match tokio::time::timeout(ctx.read_timeout, recv.read_to_end(MAX_MESSAGE_LEN)).await {
        Err(_) => {
            let _ = recv.stop(code(CloseCode::NoError));
            debug!(client = ctx.client, "frame stream not finished in time: ignored");
            return Ok(());
        }
        Ok(Err(ReadToEndError::TooLong)) => {
            return Err(Fault::new(
                CloseCode::TooLarge,
                format!("frame stream longer than {MAX_MESSAGE_LEN} bytes"),
            ));
        }
        Ok(Err(ReadToEndError::Read(e))) => {
            // Reset by the client (a stale frame it gave up on) or connection loss.
            debug!(client = ctx.client, %e, "frame stream not read");
            return Ok(());
        }
        Ok(Ok(d)) => d,
    };
    let req = match Message::decode(Bytes::from(data)) {
        Ok(Message::FrameRequest(r)) => r,
        Ok(other) => {
            return Err(Fault::new(
                CloseCode::ProtocolViolation,
                format!(
                    "a frame stream must carry a FrameRequest (got tag {})",
                    other.tag()
                ),
            ));
        }
        Err(e) => return Err(Fault::decode(&e)),
    };
    let metrics = &ctx.shared.metrics;
    metrics.frames_received.fetch_add(1, Ordering::Relaxed);
    let frame_id = req.frame_id;
    let outcome = align(&ctx, req).await?;
    let outcome = match outcome {
        FrameOutcome::Landmarks {
            landmarks,
            face_prob,
            queue_us,
            infer_us,
        } => ReplyOutcome::Landmarks {
            landmarks,
            face_prob,
            queue_us,
            infer_us,
        },
        FrameOutcome::Dropped(reason) => ReplyOutcome::Dropped { reason },
    };
    ctx.sink.send(FrameReply { frame_id, outcome });
    // The stream (and its flow-control credit) is released only now, so a
    // client cannot have more than max_in_flight frames being worked on.
    drop(recv);
    Ok(())
}

/// Where a frame's id stands against the newest id seen on its connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FrameOrder {
    /// Newer than every frame so far (now the newest).
    Newest,
    /// The newest id again: a protocol violation.
    Duplicate,
    /// Older than the newest: superseded.
    Older,
}

/// Classifies `id` and records it when it is the newest. Every `u64` is a valid id, `u64::MAX` included.
fn order_frame(newest: &std::sync::Mutex<Option<u64>>, id: u64) -> FrameOrder {
    let mut n = newest.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    match *n {
        Some(prev) if id == prev => FrameOrder::Duplicate,
        Some(prev) if id < prev => FrameOrder::Older,
        _ => {
            *n = Some(id);
            FrameOrder::Newest
        }
    }
}

async fn align(ctx: &ConnCtx, req: FrameRequest) -> Result<FrameOutcome, Fault> {
    let metrics = &ctx.shared.metrics;
    let dropped = |reason| {
        metrics.count_drop(reason);
        Ok(FrameOutcome::Dropped(reason))
    };
    match order_frame(&ctx.newest, req.frame_id) {
        FrameOrder::Newest => {}
        FrameOrder::Duplicate => {
            return Err(Fault::new(
                CloseCode::ProtocolViolation,
                format!("duplicate frame_id {}", req.frame_id),
            ));
        }
        FrameOrder::Older => return dropped(DropReason::Superseded),
    }
    let Some(pixels) = crop_pixels(&req.crop, ctx.shared.model.crop_size) else {
        debug!(client = ctx.client, frame_id = req.frame_id, "bad crop");
        return dropped(DropReason::BadCrop);
    };
    let settings = &ctx.shared.settings;
    let budget = match req.deadline_ms {
        0 => settings.max_frame_age,
        ms => Duration::from_millis(u64::from(ms)).min(settings.max_frame_age),
    };
    let arrived = tokio::time::Instant::now().into_std();
    let (tx, rx) = oneshot::channel();
    let pending = Pending {
        client: ctx.client,
        frame_id: req.frame_id,
        arrived,
        expires: arrived + budget,
        payload: FrameJob { pixels, reply: tx },
    };
    match ctx.shared.sched.try_send(SchedMsg::Submit(pending)) {
        Ok(()) => {}
        Err(mpsc::error::TrySendError::Full(_)) => return dropped(DropReason::Overloaded),
        Err(mpsc::error::TrySendError::Closed(_)) => return dropped(DropReason::ShuttingDown),
    }
    Ok(rx
        .await
        .unwrap_or(FrameOutcome::Dropped(DropReason::ShuttingDown)))
}

async fn scheduler_loop(
    mut batcher: DynamicBatcher<FrameJob>,
    mut rx: mpsc::Receiver<SchedMsg>,
    job_tx: std::sync::mpsc::SyncSender<Batch<FrameJob>>,
    mut done_rx: mpsc::UnboundedReceiver<()>,
    mut stop: watch::Receiver<bool>,
    metrics: Arc<Metrics>,
) {
    let mut busy = false;
    let mut inputs_open = true;
    let now = || tokio::time::Instant::now().into_std();
    loop {
        while let Some(d) = batcher.poll_dropped() {
            metrics.count_drop(d.reason);
            let _ = d.item.payload.reply.send(FrameOutcome::Dropped(d.reason));
        }
        let batch = if busy { None } else { batcher.poll_batch(now()) };
        metrics
            .queued_frames
            .store(batcher.len() as i64, Ordering::Relaxed);
        if let Some(batch) = batch {
            for item in &batch.items {
                metrics
                    .queue_wait_us
                    .observe_duration(batch.formed_at.saturating_duration_since(item.arrived));
            }
            if job_tx.send(batch).is_err() {
                warn!("engine thread is gone; dropping queued frames");
                batcher.start_drain();
                continue;
            }
            busy = true;
            continue;
        }
        if (batcher.is_draining() || !inputs_open) && !busy && batcher.is_empty() {
            break;
        }
        // While the engine is busy only expiries can be acted on; arming the
        // (already passed) flush time would spin this loop.
        let timeout = if busy {
            batcher.next_expiry()
        } else {
            batcher.poll_timeout()
        }
        .map(tokio::time::Instant::from_std);
        tokio::select! {
            msg = rx.recv(), if inputs_open => match msg {
                Some(SchedMsg::Submit(p)) => batcher.push(p, now()),
                Some(SchedMsg::Disconnect(client)) => {
                    batcher.remove_client(client);
                }
                None => {
                    inputs_open = false;
                    batcher.start_drain();
                }
            },
            done = done_rx.recv(), if busy => {
                busy = false;
                if done.is_none() {
                    warn!("engine thread stopped");
                    batcher.start_drain();
                    inputs_open = false;
                }
            },
            () = async {
                if let Some(t) = timeout {
                    tokio::time::sleep_until(t).await;
                }
            }, if timeout.is_some() => batcher.handle_timeout(now()),
            () = internal::stopped(&mut stop), if !batcher.is_draining() => {
                debug!(queued = batcher.len(), "scheduler draining");
                batcher.start_drain();
            },
        }
    }
    debug!("scheduler stopped");
}

fn engine_loop(
    mut engine: Box<dyn InferenceEngine>,
    jobs: &std::sync::mpsc::Receiver<Batch<FrameJob>>,
    done: &mpsc::UnboundedSender<()>,
    metrics: &Metrics,
) {
    let max_batch = engine.max_batch();
    let mut tensor = BatchTensor::new(max_batch, engine.info().crop_pixels());
    let mut outs = vec![
        LandmarkOut {
            landmarks: Vec::with_capacity(engine.info().landmark_count),
            face_prob: 0.0,
        };
        max_batch
    ];
    while let Ok(batch) = jobs.recv() {
        tensor.clear();
        let mut items = Vec::with_capacity(batch.items.len());
        for item in batch.items {
            match tensor.push(&item.payload.pixels) {
                Ok(()) => items.push(item),
                Err(e) => {
                    warn!(%e, "crop does not fit the batch");
                    metrics.count_drop(DropReason::BadCrop);
                    let _ = item
                        .payload
                        .reply
                        .send(FrameOutcome::Dropped(DropReason::BadCrop));
                }
            }
        }
        let started = Instant::now();
        let result = engine.infer(&tensor, &mut outs);
        let infer = started.elapsed();
        metrics.batch_size.observe(items.len() as u64);
        metrics.inference_us.observe_duration(infer);
        let infer_us = u32::try_from(infer.as_micros()).unwrap_or(u32::MAX);
        match result {
            Ok(()) => {
                for (item, out) in items.into_iter().zip(&outs) {
                    let queue = batch.formed_at.saturating_duration_since(item.arrived);
                    metrics.frames_aligned.fetch_add(1, Ordering::Relaxed);
                    let _ = item.payload.reply.send(FrameOutcome::Landmarks {
                        landmarks: out.landmarks.clone(),
                        face_prob: out.face_prob,
                        queue_us: u32::try_from(queue.as_micros()).unwrap_or(u32::MAX),
                        infer_us,
                    });
                }
            }
            Err(e) => {
                warn!(%e, frames = items.len(), "inference failed");
                metrics.inference_errors.fetch_add(1, Ordering::Relaxed);
                for item in items {
                    metrics.count_drop(DropReason::Overloaded);
                    let _ = item
                        .payload
                        .reply
                        .send(FrameOutcome::Dropped(DropReason::Overloaded));
                }
            }
        }
        if done.send(()).is_err() {
            break;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::batcher::BatcherConfig;
    use holoface_inference::engine::FakeEngine;

    #[test]
    fn frame_ids_order_across_the_whole_u64_range() {
        let n = std::sync::Mutex::new(None);
        assert_eq!(order_frame(&n, u64::MAX), FrameOrder::Newest);
        // MAX - 1 after MAX is an older frame, not a duplicate.
        assert_eq!(order_frame(&n, u64::MAX - 1), FrameOrder::Older);
        assert_eq!(order_frame(&n, u64::MAX), FrameOrder::Duplicate);
        let n = std::sync::Mutex::new(None);
        assert_eq!(order_frame(&n, 0), FrameOrder::Newest);
        assert_eq!(order_frame(&n, 0), FrameOrder::Duplicate);
        assert_eq!(order_frame(&n, 5), FrameOrder::Newest);
        assert_eq!(order_frame(&n, 3), FrameOrder::Older);
        assert_eq!(order_frame(&n, 6), FrameOrder::Newest);
    }

    fn submit(client: ClientId, seed: u8, at: Instant) -> (SchedMsg, oneshot::Receiver<FrameOutcome>) {
        let (tx, rx) = oneshot::channel();
        let msg = SchedMsg::Submit(Pending {
            client,
            frame_id: 1,
            arrived: at,
            expires: at + Duration::from_secs(1),
            payload: FrameJob {
                pixels: Bytes::from(vec![seed; 112 * 112]),
                reply: tx,
            },
        });
        (msg, rx)
    }

    /// The driver around the batcher and the engine thread, with the fake
    /// engine and tokio's paused clock: no sockets, no sleeps.
    #[tokio::test(start_paused = true)]
    async fn scheduler_flushes_a_partial_batch_at_max_wait_and_drains_on_stop() {
        let metrics = Arc::new(Metrics::new(4));
        let (job_tx, job_rx) = std::sync::mpsc::sync_channel(1);
        let (done_tx, done_rx) = mpsc::unbounded_channel();
        let engine_metrics = Arc::clone(&metrics);
        let engine = std::thread::spawn(move || {
            engine_loop(Box::new(FakeEngine::new(4)), &job_rx, &done_tx, &engine_metrics);
        });
        let (tx, rx) = mpsc::channel(16);
        let (stop_tx, stop_rx) = watch::channel(false);
        let batcher = DynamicBatcher::new(BatcherConfig {
            max_batch: 4,
            max_wait: Duration::from_millis(5),
            per_client_queue: 1,
            max_queued: 100,
        });
        let sched = tokio::spawn(scheduler_loop(
            batcher,
            rx,
            job_tx,
            done_rx,
            stop_rx,
            Arc::clone(&metrics),
        ));

        let t0 = tokio::time::Instant::now().into_std();
        let mut replies = Vec::new();
        for client in 0..3_u8 {
            let (msg, reply) = submit(u64::from(client), client * 50, t0);
            tx.send(msg).await.unwrap();
            replies.push(reply);
        }
        for (client, reply) in replies.into_iter().enumerate() {
            match reply.await.unwrap() {
                FrameOutcome::Landmarks {
                    face_prob, queue_us, ..
                } => {
                    assert!((face_prob - (client as f32 * 50.0) / 255.0).abs() < 1e-6);
                    assert_eq!(queue_us, 5_000, "a batch of 3 was flushed at t0 + max_wait");
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(metrics.batch_size.count(), 1);
        assert_eq!(metrics.batch_size.sum(), 3);

        // A frame still waiting for a fuller batch when shutdown starts is
        // answered ShuttingDown, and the scheduler stops.
        let (msg, reply) = submit(9, 1, tokio::time::Instant::now().into_std());
        tx.send(msg).await.unwrap();
        tokio::task::yield_now().await;
        stop_tx.send(true).unwrap();
        assert!(matches!(
            reply.await.unwrap(),
            FrameOutcome::Dropped(DropReason::ShuttingDown)
        ));
        sched.await.unwrap();
        engine.join().unwrap();
        assert_eq!(metrics.drops_for(DropReason::ShuttingDown), 1);
    }

    #[test]
    fn rate_limit_allows_a_burst_then_the_rate() {
        let t0 = Instant::now();
        let mut r = RateLimit::new(10, t0);
        assert!((0..10).all(|_| r.take(t0)), "one second of burst");
        assert!(!r.take(t0), "then empty");
        assert!(r.take(t0 + Duration::from_millis(100)), "refills at 10/s");
        assert!(!r.take(t0 + Duration::from_millis(100)));
        // 30 fps forever is fine under a 240/s limit.
        let mut r = RateLimit::new(240, t0);
        assert!((0..3000_u32).all(|i| r.take(t0 + Duration::from_millis(33) * i)));
        let mut unlimited = RateLimit::new(0, t0);
        assert!((0..10_000).all(|_| unlimited.take(t0)));
    }

    #[test]
    fn token_comparison() {
        assert!(token_eq("abc", "abc"));
        assert!(!token_eq("abc", "abd"));
        assert!(!token_eq("abc", "abcd"));
        assert!(token_eq("", ""));
    }

    fn hello(version: u16, token: &str) -> ClientHello {
        ClientHello {
            version,
            token: token.into(),
            client_name: "t".into(),
            encodings: vec![],
            max_in_flight: 1,
        }
    }

    #[test]
    fn version_is_checked_before_the_token() {
        let settings = Settings::for_loopback("good", "m.onnx".into(), "l.so".into()).unwrap();
        let m = Metrics::new(8);
        let f = authorize(&hello(99, "bad"), &settings, &m).unwrap_err();
        assert_eq!(f.code, CloseCode::BadVersion);
        let f = authorize(&hello(PROTOCOL_VERSION, "bad"), &settings, &m).unwrap_err();
        assert_eq!(f.code, CloseCode::Unauthorized);
        authorize(&hello(PROTOCOL_VERSION, "good"), &settings, &m).unwrap();
        assert_eq!(m.auth_bad_version.load(Ordering::Relaxed), 1);
        assert_eq!(m.auth_unauthorized.load(Ordering::Relaxed), 1);
    }

    #[test]
    fn crops_are_checked_and_decoded() {
        let raw = Crop::raw(4, 4, vec![9_u8; 16]);
        assert_eq!(crop_pixels(&raw, 4).unwrap().len(), 16);
        assert!(crop_pixels(&raw, 8).is_none(), "wrong size is a bad crop");
        let mut png = Vec::new();
        image::GrayImage::from_pixel(4, 4, image::Luma([7]))
            .write_to(&mut Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let crop = Crop {
            encoding: CropEncoding::Png,
            width: 4,
            height: 4,
            data: png.into(),
        };
        assert_eq!(&crop_pixels(&crop, 4).unwrap()[..], &[7_u8; 16]);
        let garbage = Crop {
            encoding: CropEncoding::Jpeg,
            width: 4,
            height: 4,
            data: Bytes::from_static(b"not a jpeg"),
        };
        assert!(crop_pixels(&garbage, 4).is_none());
    }
}

#[cfg(test)]
mod notify_tests {
    use super::notify_ready_at;

    #[test]
    fn readiness_goes_to_the_notify_socket() {
        let dir = std::env::temp_dir().join(format!("holoface-notify-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("notify.sock");
        let sock = std::os::unix::net::UnixDatagram::bind(&path).unwrap();
        notify_ready_at(path.as_os_str());
        let mut buf = [0u8; 32];
        sock.set_read_timeout(Some(std::time::Duration::from_secs(1)))
            .unwrap();
        let n = sock.recv(&mut buf).unwrap();
        assert_eq!(&buf[..n], b"READY=1");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
