//! The configuration as the server runs with it: [`Settings`], from [`ServerConfig::resolve`], the one place
//! the defaults are applied and the ranges checked.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use holoface_files::read_text_bounded;
use holoface_inference::{OnnxOptions, PrecisionChoice, Provider};
use holoface_protocol::ReplyChannel;

use super::{
    AuthConfig, BatchConfig, BatchPolicyName, ConfigError, DEFAULT_LISTEN, EngineConfig, HEADSET_FPS,
    LimitsConfig, MAX_CLIENTS, MAX_FRAME_AGE_MS, MAX_INTRA_THREADS, MAX_PER_CLIENT_QUEUE, MAX_TIMEOUT_MS,
    MAX_TOKENS_FILE_BYTES, MIN_IDLE_TIMEOUT_MS, PrecisionName, QuicConfig, RefineConfig, ReplyMode,
    ServerConfig, default_int8_model, default_model, default_refine_model,
};
use crate::batcher::{BatchPolicy, BatcherConfig};
use crate::metrics_http::is_internal_addr;

impl ServerConfig {
    /// Applies defaults and checks ranges (the one place the defaults are written: the field docs and
    /// `deploy/server.example.toml` are tested against it). Reads `auth.tokens_file` if set.
    pub fn resolve(self) -> Result<Settings, ConfigError> {
        let quic = resolve_quic(self.quic)?;
        let (tokens, allow_anonymous) = resolve_tokens(self.auth)?;
        let limits = resolve_limits(&self.limits)?;
        let (max_batch, policy, per_client_queue) = resolve_batch(&self.batch, limits.max_frame_age)?;
        if let Some(addr) = self.internal.metrics_listen
            && !is_internal_addr(addr.ip())
        {
            return Err(ConfigError::Invalid(format!(
                "internal.metrics_listen {addr} must be a loopback or private address"
            )));
        }
        let engine = self.engine;
        let provider = resolve_provider(&engine)?;
        let engine_instances = engine.instances.unwrap_or(1);
        if !(1..=64).contains(&engine_instances) {
            return Err(ConfigError::Invalid(format!(
                "engine.instances {engine_instances} must be within 1..=64"
            )));
        }
        let intra_threads = engine
            .intra_threads
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, usize::from))
            .max(1);
        if intra_threads > MAX_INTRA_THREADS {
            return Err(ConfigError::Invalid(format!(
                "engine.intra_threads = {intra_threads}: at most {MAX_INTRA_THREADS}"
            )));
        }
        Ok(Settings {
            listen: quic.listen,
            tls: quic.tls,
            fingerprint_file: quic.fingerprint_file,
            idle_timeout: quic.idle_timeout,
            hello_timeout: quic.hello_timeout,
            reply_channel: quic.reply_channel,
            tokens,
            allow_anonymous,
            max_clients: limits.max_clients,
            max_pending: limits.max_pending,
            max_in_flight: limits.max_in_flight,
            max_frame_age: limits.max_frame_age,
            shutdown_timeout: limits.shutdown_timeout,
            max_frame_rate: limits.max_frame_rate,
            batch: BatcherConfig {
                max_batch,
                policy,
                per_client_queue,
                max_queued: limits
                    .max_clients
                    .saturating_mul(usize::from(limits.max_in_flight))
                    .max(1),
            },
            engine: OnnxOptions {
                model: engine.model.unwrap_or_else(default_model),
                ort_dylib: engine
                    .ort_dylib
                    .unwrap_or_else(holoface_inference::default_ort_dylib),
                intra_threads,
                max_batch,
                provider,
                spin: engine.spin.unwrap_or(false),
            },
            engine_instances,
            precision: engine.precision.unwrap_or(PrecisionName::Auto).into(),
            int8_model: engine.int8_model.unwrap_or_else(default_int8_model),
            refine_model: match (self.refine.enabled.unwrap_or(true), self.refine.model) {
                (true, model) => Some(model.unwrap_or_else(default_refine_model)),
                (false, None) => None,
                (false, Some(m)) => {
                    return Err(ConfigError::Invalid(format!(
                        "refine.model = {} is set but refine.enabled = false: drop one of them",
                        m.display()
                    )));
                }
            },
            metrics_listen: self.internal.metrics_listen,
        })
    }
}

/// `[quic]` resolved.
struct QuicSettings {
    listen: SocketAddr,
    tls: TlsSource,
    fingerprint_file: Option<PathBuf>,
    idle_timeout: Duration,
    hello_timeout: Duration,
    reply_channel: ReplyChannel,
}

fn resolve_quic(q: QuicConfig) -> Result<QuicSettings, ConfigError> {
    let invalid = |m: String| ConfigError::Invalid(m);
    let tls = match (q.cert, q.key) {
        (Some(cert), Some(key)) => TlsSource::Files { cert, key },
        (None, None) => TlsSource::SelfSigned {
            names: q
                .self_signed_names
                .unwrap_or_else(|| vec!["localhost".to_owned()]),
        },
        _ => return Err(invalid("quic.cert and quic.key must be given together".into())),
    };
    let listen = match q.listen {
        Some(a) => a,
        None => DEFAULT_LISTEN
            .parse()
            .map_err(|e| invalid(format!("default listen address: {e}")))?,
    };
    // Zero and too-small durations are refused, not silently raised: an operator who wrote 0 meant
    // something (off? immediate?) that the server cannot do.
    let idle_timeout_ms = q.idle_timeout_ms.unwrap_or(10_000);
    if idle_timeout_ms < MIN_IDLE_TIMEOUT_MS {
        return Err(invalid(format!(
            "quic.idle_timeout_ms = {idle_timeout_ms}: must be at least {MIN_IDLE_TIMEOUT_MS} (a shorter idle \
             timeout closes healthy connections between keep-alives)"
        )));
    }
    if idle_timeout_ms > MAX_TIMEOUT_MS {
        return Err(invalid(format!(
            "quic.idle_timeout_ms = {idle_timeout_ms}: at most {MAX_TIMEOUT_MS} (an hour; a dead headset \
             would hold its place that long)"
        )));
    }
    let hello_timeout_ms = q.hello_timeout_ms.unwrap_or(5_000);
    if !(1..=MAX_TIMEOUT_MS).contains(&hello_timeout_ms) {
        return Err(invalid(format!(
            "quic.hello_timeout_ms = {hello_timeout_ms}: allowed 1..={MAX_TIMEOUT_MS}"
        )));
    }
    Ok(QuicSettings {
        listen,
        tls,
        fingerprint_file: q.fingerprint_file,
        idle_timeout: Duration::from_millis(idle_timeout_ms),
        hello_timeout: Duration::from_millis(hello_timeout_ms),
        reply_channel: q.reply_channel.unwrap_or(ReplyMode::Datagram).into(),
    })
}

/// `[limits]` resolved.
struct Limits {
    max_clients: usize,
    max_pending: usize,
    max_in_flight: u16,
    max_frame_age: Duration,
    shutdown_timeout: Duration,
    max_frame_rate: u32,
}

fn resolve_limits(l: &LimitsConfig) -> Result<Limits, ConfigError> {
    let invalid = |m: String| ConfigError::Invalid(m);
    let max_frame_age_ms = l.max_frame_age_ms.unwrap_or(100);
    if max_frame_age_ms == 0 {
        return Err(invalid(
            "limits.max_frame_age_ms = 0: must be at least 1 (0 would expire every frame)".into(),
        ));
    }
    if u64::from(max_frame_age_ms) > MAX_FRAME_AGE_MS {
        return Err(invalid(format!(
            "limits.max_frame_age_ms = {max_frame_age_ms}: at most {MAX_FRAME_AGE_MS} (an answer that late \
             is of no use to a headset)"
        )));
    }
    let shutdown_timeout_ms = l.shutdown_timeout_ms.unwrap_or(5_000);
    if shutdown_timeout_ms > MAX_TIMEOUT_MS {
        return Err(invalid(format!(
            "limits.shutdown_timeout_ms = {shutdown_timeout_ms}: at most {MAX_TIMEOUT_MS}"
        )));
    }
    let max_clients = l.max_clients.unwrap_or(64);
    if !(1..=MAX_CLIENTS).contains(&max_clients) {
        return Err(invalid(format!(
            "limits.max_clients = {max_clients}: allowed 1..={MAX_CLIENTS} (one server answers far fewer \
             headsets; each holds a QUIC connection and a share of the engine)"
        )));
    }
    if let Some(p) = l.max_pending
        && !(1..=MAX_CLIENTS).contains(&p)
    {
        return Err(invalid(format!(
            "limits.max_pending = {p}: allowed 1..={MAX_CLIENTS}"
        )));
    }
    let max_in_flight = l.max_in_flight.unwrap_or(8).max(1);
    Ok(Limits {
        max_clients,
        max_pending: l.max_pending.unwrap_or(max_clients.max(16)),
        max_in_flight,
        max_frame_age: Duration::from_millis(u64::from(max_frame_age_ms)),
        shutdown_timeout: Duration::from_millis(shutdown_timeout_ms),
        // What one headset needs at most: every face it may have in flight, at 30 fps.
        max_frame_rate: l.max_frame_rate.unwrap_or(u32::from(max_in_flight) * HEADSET_FPS),
    })
}

/// `[batch]` resolved: the largest batch, the policy and the per-client queue. A batch may not wait as long as
/// a frame may live (`max_frame_age`).
fn resolve_batch(
    b: &BatchConfig,
    max_frame_age: Duration,
) -> Result<(usize, BatchPolicy, usize), ConfigError> {
    let invalid = |m: String| ConfigError::Invalid(m);
    let per_client_queue = b.per_client_queue.unwrap_or(1).max(1);
    if per_client_queue > MAX_PER_CLIENT_QUEUE {
        return Err(invalid(format!(
            "batch.per_client_queue = {per_client_queue}: at most {MAX_PER_CLIENT_QUEUE} (a newer crop \
             supersedes an older one; a long queue only holds stale frames)"
        )));
    }
    let max_batch = b.max_batch.unwrap_or(8);
    if !(1..=256).contains(&max_batch) {
        return Err(invalid(format!("batch.max_batch = {max_batch}, allowed 1..=256")));
    }
    let age_us = max_frame_age.as_micros() as u64;
    let policy = match (b.policy.unwrap_or(BatchPolicyName::WorkConserving), b.max_wait_us) {
        (BatchPolicyName::WorkConserving, None) => BatchPolicy::WorkConserving,
        (BatchPolicyName::WorkConserving, Some(us)) => {
            return Err(invalid(format!(
                "batch.max_wait_us = {us} applies only to batch.policy = \"max-wait\" \
                 (the default policy, work-conserving, never waits)"
            )));
        }
        (BatchPolicyName::MaxWait, us) => {
            let us = us.unwrap_or(2_000);
            // A batch that waits as long as a frame may live answers nothing: every frame expires first.
            if us >= age_us {
                return Err(invalid(format!(
                    "batch.max_wait_us = {us} is not shorter than limits.max_frame_age_ms = {} ({age_us} us): \
                     every frame would expire waiting for its batch and none would be answered; choose a \
                     max_wait_us well under the frame age",
                    age_us / 1_000
                )));
            }
            BatchPolicy::MaxWait(Duration::from_micros(us))
        }
    };
    Ok((max_batch, policy, per_client_queue))
}

/// The access tokens (inline and from `auth.tokens_file`) and whether anonymous clients are allowed.
fn resolve_tokens(auth: AuthConfig) -> Result<(Vec<String>, bool), ConfigError> {
    let invalid = |m: String| ConfigError::Invalid(m);
    let mut tokens = auth.tokens.unwrap_or_default();
    if let Some(path) = &auth.tokens_file {
        let text =
            read_text_bounded(path, MAX_TOKENS_FILE_BYTES, "tokens file").map_err(ConfigError::TokensFile)?;
        tokens.extend(
            text.lines()
                .map(str::trim)
                .filter(|l| !l.is_empty() && !l.starts_with('#'))
                .map(str::to_owned),
        );
    }
    tokens.retain(|t| !t.is_empty());
    let allow_anonymous = auth.allow_anonymous.unwrap_or(false);
    if tokens.is_empty() && !allow_anonymous {
        return Err(invalid(
            "no access tokens: set auth.tokens / --token / HOLOFACE_TOKENS (or auth.allow_anonymous for development)"
                .into(),
        ));
    }
    if let Some(t) = tokens
        .iter()
        .find(|t| t.len() > holoface_protocol::limits::MAX_TOKEN_LEN)
    {
        return Err(invalid(format!(
            "a token is {} bytes; the protocol allows at most {}",
            t.len(),
            holoface_protocol::limits::MAX_TOKEN_LEN
        )));
    }
    Ok((tokens, allow_anonymous))
}

/// The execution provider: the CPU, or CUDA with its device and whether it is required.
fn resolve_provider(engine: &EngineConfig) -> Result<Provider, ConfigError> {
    let provider = match (
        engine.cuda.unwrap_or(false),
        engine.cuda_device,
        engine.cuda_required,
    ) {
        (true, device, required) => {
            let device = device.unwrap_or(0);
            if device < 0 {
                return Err(ConfigError::Invalid(format!(
                    "engine.cuda_device {device} must be 0 or more"
                )));
            }
            Provider::Cuda {
                device,
                required: required.unwrap_or(false),
            }
        }
        (false, Some(_), _) | (false, _, Some(true)) => {
            return Err(ConfigError::Invalid(
                "engine.cuda_device and engine.cuda_required need engine.cuda = true".into(),
            ));
        }
        (false, _, _) => Provider::Cpu,
    };
    Ok(provider)
}

/// Where the server's certificate comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TlsSource {
    /// PEM files.
    Files {
        /// Certificate chain.
        cert: PathBuf,
        /// Private key.
        key: PathBuf,
    },
    /// A self-signed certificate generated at start for these names.
    SelfSigned {
        /// Subject alternative names.
        names: Vec<String>,
    },
}

/// The resolved configuration the server runs with.
#[derive(Debug, Clone, PartialEq)]
pub struct Settings {
    /// UDP listen address.
    pub listen: SocketAddr,
    /// Certificate source.
    pub tls: TlsSource,
    /// Where to write the certificate fingerprint, if anywhere.
    pub fingerprint_file: Option<PathBuf>,
    /// QUIC idle timeout.
    pub idle_timeout: Duration,
    /// Time allowed for the ClientHello.
    pub hello_timeout: Duration,
    /// Reply transport offered to clients.
    pub reply_channel: ReplyChannel,
    /// Accepted tokens.
    pub tokens: Vec<String>,
    /// Accept any token.
    pub allow_anonymous: bool,
    /// Concurrent client cap (authenticated clients).
    pub max_clients: usize,
    /// Budget of connections without an authenticated hello.
    pub max_pending: usize,
    /// Per-client frames in flight.
    pub max_in_flight: u16,
    /// Server-side cap on a frame's age.
    pub max_frame_age: Duration,
    /// Bound on graceful shutdown.
    pub shutdown_timeout: Duration,
    /// Frames per second per client (token bucket, 1 s burst); 0 = unlimited.
    pub max_frame_rate: u32,
    /// Batcher limits.
    pub batch: BatcherConfig,
    /// ONNX Runtime engine options (each instance's); `engine.model` is the fp32 (or fp16) model, which
    /// `precision` may replace with `int8_model`.
    pub engine: OnnxOptions,
    /// Which precision serves.
    pub precision: PrecisionChoice,
    /// The int8 model.
    pub int8_model: PathBuf,
    /// Engine instances fed by the batcher.
    pub engine_instances: usize,
    /// The refinement cascade run after DAN (`None`: off).
    pub refine_model: Option<PathBuf>,
    /// Internal metrics listener.
    pub metrics_listen: Option<SocketAddr>,
}

impl Settings {
    /// Settings for tests and benchmarks: loopback on an ephemeral port,
    /// self-signed certificate, one token, the refinement cascade `refine_model` (`None`: off), `model` served as
    /// it is (`engine.precision = "model"`: a benchmark measures the file it names), everything else default.
    pub fn for_loopback(
        token: &str,
        model: PathBuf,
        refine_model: Option<PathBuf>,
        ort_dylib: PathBuf,
    ) -> Result<Self, ConfigError> {
        let cfg = ServerConfig {
            quic: QuicConfig {
                listen: Some(SocketAddr::from(([127, 0, 0, 1], 0))),
                ..QuicConfig::default()
            },
            auth: AuthConfig {
                tokens: Some(vec![token.to_owned()]),
                ..AuthConfig::default()
            },
            engine: EngineConfig {
                model: Some(model),
                ort_dylib: Some(ort_dylib),
                precision: Some(PrecisionName::Model),
                ..EngineConfig::default()
            },
            refine: RefineConfig {
                enabled: Some(refine_model.is_some()),
                model: refine_model,
            },
            ..ServerConfig::default()
        };
        cfg.resolve()
    }
}
