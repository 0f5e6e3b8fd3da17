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
//!
//! Layout:
//!
//! * this module: [`AlignmentServer`], [`ServerError`], [`run`], the state shared by
//!   every connection, the QUIC transport configuration and the accept loop;
//! * `lifecycle`: systemd readiness notification and [`shutdown_signal`];
//! * `auth`: reading the `ClientHello`, the version and token checks;
//! * `fault`: how a connection ends (close code and reason), shared by the
//!   modules below;
//! * `client`: the per-connection task (the hello's timeout, handshake, welcome,
//!   frame loop, graceful drain) and how a connection ends;
//! * `reply`: the reply sink (datagrams or the reply stream);
//! * `frame_stream`: the per-connection state its frame streams share, and one
//!   frame stream: ordering, crop decoding, submission;
//! * `rate_limit`: the per-connection frame-rate token bucket;
//! * `scheduler`: the task that owns the [`DynamicBatcher`];
//! * `engine_thread`: the thread that runs the [`InferenceEngine`].

mod admission;
mod auth;
mod client;
mod engine_thread;
mod fault;
mod frame_stream;
pub(crate) mod lifecycle;
mod log_throttle;
mod rate_limit;
mod reply;
mod scheduler;

pub use lifecycle::shutdown_signal;

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use holoface_protocol::CloseCode;
use holoface_protocol::limits::MAX_MESSAGE_LEN;
use quinn::VarInt;
use tokio::sync::{mpsc, watch};
use tokio::task::JoinSet;
use tracing::{debug, info, warn};

use crate::batcher::{Batch, DynamicBatcher};
use crate::config::{ServerConfig, Settings, TlsSource};
use crate::metrics::Metrics;
use crate::tls::{Fingerprint, ServerIdentity, TlsError};
use crate::{config::ConfigError, metrics_http};
use holoface_inference::{
    CascadeEngine, CpuInt8, EngineError, InferenceEngine, LoadedCascade, ModelInfo, OnnxEngine,
};

use admission::{Admission, Admit};
use client::connection;
use engine_thread::engine_loop;
use lifecycle::notify_systemd_ready;
use scheduler::{FrameJob, SchedMsg, scheduler_loop};

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

/// State shared by every connection task.
#[derive(Debug)]
struct Shared {
    settings: Settings,
    model: ModelInfo,
    metrics: Arc<Metrics>,
    sched: mpsc::Sender<SchedMsg>,
    stop: watch::Receiver<bool>,
    next_client: AtomicU64,
    admission: Arc<Admission>,
    /// Which misbehaving clients' closes get a log line of their own.
    log_throttle: Arc<std::sync::Mutex<log_throttle::LogThrottle>>,
}

impl Shared {
    /// Logs a misbehaving client's close, unless its code has had its burst of lines in this window; logs
    /// the previous window's summary when it ended with closes left out.
    fn log_fault(&self, client: crate::batcher::ClientId, remote: SocketAddr, fault: &fault::Fault) {
        let (log, ended) = self
            .log_throttle
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .admit(fault.code, std::time::Instant::now());
        if let Some(s) = ended {
            log_suppressed(s);
        }
        if log {
            warn!(client, %remote, code = %fault.code, detail = %fault.detail, "closing misbehaving client");
        }
    }
}

/// One line for the closes of a window that were not logged one by one.
fn log_suppressed(s: log_throttle::Suppressed) {
    warn!(
        code = %s.code,
        closes = s.count,
        window_s = log_throttle::WINDOW.as_secs(),
        "closed more misbehaving clients than logged one by one (the metrics count every close)"
    );
}

/// A bound, not yet running, alignment server.
#[derive(Debug)]
pub struct AlignmentServer {
    endpoint: quinn::Endpoint,
    fingerprint: Fingerprint,
    metrics: Arc<Metrics>,
    metrics_listener: Option<tokio::net::TcpListener>,
    /// One or more instances of the same model (`engine.instances`), never empty.
    engines: Vec<Box<dyn InferenceEngine>>,
    settings: Settings,
}

/// Loads the engine and binds; then [`AlignmentServer::run`] until `shutdown`.
pub async fn run(config: ServerConfig, shutdown: impl Future<Output = ()>) -> Result<(), ServerError> {
    AlignmentServer::bind(config.resolve()?)
        .await?
        .run(shutdown)
        .await
}

impl AlignmentServer {
    /// Loads the ONNX engine (validating the model) and binds the endpoint.
    pub async fn bind(settings: Settings) -> Result<Self, ServerError> {
        // Which file serves: int8 on a CPU with VNNI, else engine.model (holoface_inference::precision).
        let cpu = CpuInt8::detect();
        let decision = holoface_inference::precision::decide(
            settings.precision,
            &settings.engine.model,
            &settings.int8_model,
            settings.int8_model.is_file(),
            settings.engine.provider,
            cpu,
        );
        let base = settings.engine.clone();
        let auto = settings.precision == holoface_inference::PrecisionChoice::Auto;
        let instances = settings.engine_instances.max(1);
        let refine_path = settings.refine_model.clone();
        // The server's own names for the files it loads, in its messages.
        const OPTIONS: &[(holoface_files::home::Asset, &str)] = &[
            (holoface_files::home::DAN, "engine.model / --model"),
            (holoface_files::home::DAN_INT8, "engine.int8_model / --int8-model"),
            (
                holoface_files::home::ORT_LIBRARY,
                "engine.ort_dylib / --ort-dylib",
            ),
            (holoface_files::home::REFINER, "refine.model / --refine-model"),
        ];
        let (decision, engines) = tokio::task::spawn_blocking(move || {
            let mut decision = decision;
            // Auto serves the int8 file only as the same release as engine.model: an operator who points
            // engine.model at another DAN must not be served an older int8 one from the data folder.
            if auto && decision.expect == Some("int8") {
                let of = |model: &std::path::Path| {
                    let mut o = base.clone();
                    o.model = model.to_path_buf();
                    OnnxEngine::load(&o).map(|e| e.info().clone())
                };
                let (fp, q) = (of(&base.model), of(&decision.model));
                let (fp, q) = (fp.map_err(|e| e.given_by(OPTIONS))?, q.map_err(|e| e.given_by(OPTIONS))?);
                if (&fp.name, &fp.version) != (&q.name, &q.version) {
                    decision = holoface_inference::Decision {
                        reason: format!(
                            "auto: the int8 model {} is {} {}, engine.model is {} {}: engine.model serves \
                             (install the matching int8 file with `holoface setup`, or set engine.int8_model)",
                            decision.model.display(),
                            q.name,
                            q.version,
                            fp.name,
                            fp.version
                        ),
                        model: base.model.clone(),
                        expect: None,
                    };
                }
            }
            let mut opts = base;
            opts.model = decision.model.clone();
            // One refiner, shared by every instance; a missing or damaged file stops the start here.
            let refiner = refine_path
                .as_deref()
                .map(LoadedCascade::load)
                .transpose()
                .map_err(|e| e.given_by(OPTIONS))?;
            (0..instances)
                .map(|_| {
                    let dan = OnnxEngine::load(&opts)?;
                    decision.check(dan.info())?;
                    Ok(match &refiner {
                        Some(r) => {
                            Box::new(CascadeEngine::new(dan, r.clone())?.with_threads(opts.intra_threads))
                                as Box<dyn InferenceEngine>
                        }
                        None => Box::new(dan) as Box<dyn InferenceEngine>,
                    })
                })
                .collect::<Result<Vec<_>, EngineError>>()
                .map_err(|e| e.given_by(OPTIONS))
                .map(|engines| (decision, engines))
        })
        .await
        .map_err(|e| ServerError::EngineThread(e.to_string()))??;
        let info = engines[0].info();
        let execution = engines[0].execution();
        info!(
            model = %decision.model.display(),
            name = %info.name,
            version = %info.version,
            precision = %info.precision,
            why = %decision.reason,
            cpu_int8 = cpu.label(),
            refiner = engines[0].refiner().unwrap_or("off"),
            refiner_model = %settings.refine_model.as_deref().map_or_else(|| "-".into(), |p| p.display().to_string()),
            untrained = info.untrained,
            provider = %execution.provider,
            device = ?execution.device,
            intra_threads = settings.engine.intra_threads,
            engine_instances = instances,
            "model loaded"
        );
        if info.precision == "int8" && !cpu.has_vnni() {
            warn!("{}", decision.reason);
        }
        if let Some(why) = &execution.fallback {
            warn!(
                "the CUDA execution provider was requested but cannot run, so the CPU runs the model \
                 (set engine.cuda_required = true to refuse to start instead): {why}"
            );
        }
        if info.untrained {
            warn!("the model is marked untrained (random weights): landmarks are meaningless");
        }
        Self::bind_with_engines(settings, engines).await
    }

    /// Binds with a given engine (tests and benchmarks use this with a fake
    /// or preloaded engine).
    pub async fn bind_with_engine(
        settings: Settings,
        engine: Box<dyn InferenceEngine>,
    ) -> Result<Self, ServerError> {
        Self::bind_with_engines(settings, vec![engine]).await
    }

    /// Binds with several instances of one model, each run on its own thread; the batcher hands each batch
    /// to an idle one. Instances must describe the same model.
    pub async fn bind_with_engines(
        settings: Settings,
        engines: Vec<Box<dyn InferenceEngine>>,
    ) -> Result<Self, ServerError> {
        let Some(first) = engines.first() else {
            return Err(ServerError::EngineThread("no engine instance".into()));
        };
        if engines.iter().any(|e| e.info() != first.info()) {
            return Err(ServerError::EngineThread(
                "engine instances describe different models".into(),
            ));
        }
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
        metrics.set_engine_info(first.info(), &first.execution(), engines.len(), first.refiner());
        Ok(Self {
            endpoint,
            fingerprint,
            metrics,
            metrics_listener,
            engines,
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
        self.engines[0].info()
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
            engines,
            settings,
        } = self;
        let model = engines[0].info().clone();
        let (stop_tx, stop_rx) = watch::channel(false);

        let EngineThreads {
            jobs: job_txs,
            threads: engine_threads,
            done: done_rx,
        } = start_engines(engines, &metrics)?;

        let sched_capacity = settings
            .max_clients
            .saturating_mul(usize::from(settings.max_in_flight))
            .clamp(16, 1 << 16);
        let (sched_tx, sched_rx) = mpsc::channel(sched_capacity);
        let scheduler = tokio::spawn(scheduler_loop(
            DynamicBatcher::new(settings.batch),
            sched_rx,
            job_txs,
            done_rx,
            stop_rx.clone(),
            Arc::clone(&metrics),
        ));
        let internal_task = metrics_listener.map(|l| {
            if let Ok(addr) = l.local_addr() {
                info!(%addr, "metrics and health on http://{addr}/metrics, /health");
            }
            tokio::spawn(metrics_http::serve(l, Arc::clone(&metrics), stop_rx.clone()))
        });

        let admission = Admission::new(settings.max_clients, settings.max_pending, Arc::clone(&metrics));
        let shutdown_timeout = settings.shutdown_timeout;
        let shared = Arc::new(Shared {
            settings,
            model,
            metrics: Arc::clone(&metrics),
            sched: sched_tx,
            stop: stop_rx,
            next_client: AtomicU64::new(1),
            admission,
            log_throttle: Arc::default(),
        });
        let log_flush = spawn_log_flush(&shared);
        metrics.ready.store(true, Ordering::Relaxed);
        notify_systemd_ready();
        info!(
            addr = %endpoint.local_addr().map_err(io_err("reading the local address"))?,
            %fingerprint,
            "alignment server ready; clients pin this certificate SHA-256 fingerprint"
        );

        let mut conns = accept_until(&endpoint, &shared, shutdown).await;

        info!(
            clients = conns.len(),
            "shutting down: refusing new clients, draining"
        );
        metrics.draining.store(true, Ordering::Relaxed);
        endpoint.set_server_config(None);
        let _ = stop_tx.send(true);
        // One deadline for the whole drain (deploy/README promises the bound): connections finish their
        // in-flight frames and close themselves with ShuttingDown well before it.
        let deadline = tokio::time::Instant::now() + shutdown_timeout;
        let drained =
            tokio::time::timeout_at(deadline, async { while conns.join_next().await.is_some() {} }).await;
        // Close what is left with ShuttingDown *before* dropping the tasks: dropping a connection's last
        // handle would close it with code 0 instead.
        endpoint.close(
            code(CloseCode::ShuttingDown),
            CloseCode::ShuttingDown.reason().as_bytes(),
        );
        if drained.is_err() {
            warn!(
                left = conns.len(),
                "shutdown timeout: closing the remaining connections with ShuttingDown"
            );
            conns.abort_all();
        }
        // Let the close frames go out; bounded by the deadline (and at least a moment after a timeout).
        let close_until = deadline.max(tokio::time::Instant::now() + std::time::Duration::from_millis(100));
        if tokio::time::timeout_at(close_until, endpoint.wait_idle())
            .await
            .is_err()
        {
            debug!("endpoint did not go idle before the shutdown deadline");
        }
        drop(shared);
        if tokio::time::timeout_at(close_until, scheduler).await.is_err() {
            warn!("scheduler did not stop before the shutdown deadline");
        }
        if let Some(task) = internal_task {
            task.abort();
        }
        join_engine_threads(engine_threads).await?;
        let _ = log_flush.await;
        info!("shutdown complete");
        Ok(())
    }
}

/// The engine threads, one per instance, fed by the scheduler through their job senders; each reports its
/// index on `done` when it is done with a batch.
struct EngineThreads {
    jobs: Vec<std::sync::mpsc::SyncSender<Batch<FrameJob>>>,
    threads: Vec<std::thread::JoinHandle<()>>,
    done: mpsc::UnboundedReceiver<usize>,
}

fn start_engines(
    engines: Vec<Box<dyn InferenceEngine>>,
    metrics: &Arc<Metrics>,
) -> Result<EngineThreads, ServerError> {
    let (done_tx, done) = mpsc::unbounded_channel::<usize>();
    let mut jobs = Vec::with_capacity(engines.len());
    let mut threads = Vec::with_capacity(engines.len());
    for (index, engine) in engines.into_iter().enumerate() {
        let (job_tx, job_rx) = std::sync::mpsc::sync_channel::<Batch<FrameJob>>(1);
        let (done_tx, engine_metrics) = (done_tx.clone(), Arc::clone(metrics));
        let thread = std::thread::Builder::new()
            .name(format!("holoface-engine-{index}"))
            .spawn(move || engine_loop(engine, index, &job_rx, &done_tx, &engine_metrics))
            .map_err(io_err("starting an engine thread"))?;
        jobs.push(job_tx);
        threads.push(thread);
    }
    Ok(EngineThreads { jobs, threads, done })
}

/// The tail of a flood of bad clients is summed up every window even when no close follows it, and at
/// shutdown.
fn spawn_log_flush(shared: &Shared) -> tokio::task::JoinHandle<()> {
    let (throttle, mut stop) = (Arc::clone(&shared.log_throttle), shared.stop.clone());
    tokio::spawn(async move {
        let mut tick = tokio::time::interval(log_throttle::WINDOW);
        loop {
            let stopping = tokio::select! {
                _ = tick.tick() => false,
                _ = stop.changed() => true,
            };
            let mut throttle = throttle.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            let ended = if stopping {
                throttle.drain()
            } else {
                throttle.flush(std::time::Instant::now())
            };
            ended.into_iter().for_each(log_suppressed);
            if stopping {
                break;
            }
        }
    })
}

/// Accepts clients (or asks them to retry, as admission says) until `shutdown` resolves or the endpoint
/// closes; returns the connections still running.
async fn accept_until(
    endpoint: &quinn::Endpoint,
    shared: &Arc<Shared>,
    shutdown: impl Future<Output = ()>,
) -> JoinSet<()> {
    let mut conns = JoinSet::new();
    tokio::pin!(shutdown);
    loop {
        tokio::select! {
            () = &mut shutdown => break,
            incoming = endpoint.accept() => match incoming {
                Some(incoming) => {
                    let admit = shared
                        .admission
                        .on_incoming(incoming.remote_address_validated(), incoming.may_retry());
                    match admit {
                        Admit::Retry => {
                            if let Err(e) = incoming.retry() {
                                debug!(error = %e, "retry failed; dropping the attempt");
                            }
                        }
                        Admit::Accept => {
                            let slot = shared.admission.enter();
                            conns.spawn(connection(incoming, slot, Arc::clone(shared)));
                        }
                    }
                }
                None => break,
            },
            Some(_) = conns.join_next(), if !conns.is_empty() => {}
        }
    }
    conns
}

/// Waits for the engine threads (the scheduler owned their job senders; they end with them); a panicked one
/// is an error.
async fn join_engine_threads(threads: Vec<std::thread::JoinHandle<()>>) -> Result<(), ServerError> {
    let joined = tokio::task::spawn_blocking(move || {
        threads
            .into_iter()
            .map(std::thread::JoinHandle::join)
            .filter(Result::is_err)
            .count()
    })
    .await;
    match joined {
        Ok(0) => Ok(()),
        Ok(n) => Err(ServerError::EngineThread(format!("{n} engine threads panicked"))),
        Err(e) => Err(ServerError::EngineThread(e.to_string())),
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
