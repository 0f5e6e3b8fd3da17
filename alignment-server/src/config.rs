//! Server configuration: one clap + serde struct, a TOML file the CLI cannot
//! silently clobber, and the resolved [`Settings`] the server runs with.
//!
//! Precedence, highest first: command-line flag, `HOLOFACE_*` environment
//! variable, TOML file (`--config`), built-in default. Every field the TOML
//! can set is an `Option`, so a flag that was not given is `None` and cannot
//! overwrite the file ([`ServerConfig::merge`]); the `cli_does_not_clobber_toml_*`
//! tests guard this. The ONNX Runtime path additionally falls back to the
//! conventional `ORT_DYLIB_PATH` variable, below the TOML file.
//!
//! [`ServerConfig::parse_and_merge`] is pure (it is handed the file reader);
//! [`ServerConfig::load`] is the binary's entry point.

use std::ffi::OsString;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use clap::{Args, Parser, ValueEnum};
use holoface_protocol::ReplyChannel;
use serde::{Deserialize, Serialize};

use holoface_files::{FileError, read_text_bounded};
use holoface_inference::PrecisionChoice;

mod settings;
pub use settings::{Settings, TlsSource};

/// Default QUIC listen address.
pub const DEFAULT_LISTEN: &str = "0.0.0.0:4433";
/// The DAN model when `engine.model` is not set: `$HOLOFACE_DAN_MODEL`, else `dan.onnx` in the holoface data
/// folder (`holoface setup` installs it; [`holoface_files::home`]).
pub fn default_model() -> PathBuf {
    holoface_files::home::DAN.default_path()
}

/// The int8 DAN when `engine.int8_model` is not set: `$HOLOFACE_DAN_INT8_MODEL`, else `dan.int8.onnx` in the data
/// folder.
pub fn default_int8_model() -> PathBuf {
    holoface_files::home::DAN_INT8.default_path()
}

/// The refinement cascade when `refine.model` is not set: `$HOLOFACE_REFINE_MODEL`, else `refiner.bin` in the
/// data folder.
pub fn default_refine_model() -> PathBuf {
    holoface_files::home::REFINER.default_path()
}

/// The shortest idle timeout the server accepts, ms (QUIC keep-alives from clients come every 500 ms).
pub const MIN_IDLE_TIMEOUT_MS: u64 = 100;

/// The most clients (and pending handshakes) one server admits: far beyond what one engine answers, far
/// below what its admission semaphore can count (tokio's limit is `usize::MAX >> 3`, a panic beyond).
pub const MAX_CLIENTS: usize = 1_000_000;

/// The largest config file read.
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// The largest tokens file read (a token per line: tens of thousands of headsets).
pub const MAX_TOKENS_FILE_BYTES: u64 = 4 << 20;

/// The config file read whole, refused before reading when it is not a regular file or larger than
/// [`MAX_CONFIG_BYTES`] (a device, a pipe or a huge file named by mistake must not hang the start or fill the
/// memory); the error keeps what went wrong, for the caller to match.
pub fn read_config_file(path: &Path) -> Result<String, FileError> {
    read_text_bounded(path, MAX_CONFIG_BYTES, "config file")
}

/// The longest idle, hello and shutdown timeout accepted, ms (an hour).
pub const MAX_TIMEOUT_MS: u64 = 3_600_000;

/// The oldest a frame may be allowed to get, ms.
pub const MAX_FRAME_AGE_MS: u64 = 60_000;

/// The most ONNX Runtime threads per engine instance.
pub const MAX_INTRA_THREADS: usize = 1024;

/// The longest per-client queue of crops.
pub const MAX_PER_CLIENT_QUEUE: usize = 256;

/// Configuration errors.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigError {
    /// Command-line parsing failed (or `--help` / `--version` was asked for).
    #[error(transparent)]
    Cli(#[from] clap::Error),
    /// The config file could not be read: missing, not a regular file, too large or unreadable (the
    /// `FileError` names it as "config file").
    #[error(transparent)]
    Read(FileError),
    /// The access-tokens file could not be read (named as "tokens file").
    #[error(transparent)]
    TokensFile(FileError),
    /// The config file is not valid TOML for this schema.
    #[error("parsing config file {path}: {source}")]
    Toml {
        /// The file.
        path: PathBuf,
        /// The parse error.
        source: Box<toml::de::Error>,
    },
    /// A value is out of range or inconsistent.
    #[error("invalid configuration: {0}")]
    Invalid(String),
}

/// How replies travel back (the TOML/CLI spelling of [`ReplyChannel`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ReplyMode {
    /// One QUIC datagram per reply (default; see BENCHMARKS.md).
    Datagram,
    /// Framed replies on one server-to-client unidirectional stream.
    Stream,
}

impl From<ReplyMode> for ReplyChannel {
    fn from(m: ReplyMode) -> Self {
        match m {
            ReplyMode::Datagram => Self::Datagram,
            ReplyMode::Stream => Self::Stream,
        }
    }
}

/// When a partial batch goes to an idle engine (the TOML/CLI spelling of [`BatchPolicy`](crate::batcher::BatchPolicy)).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum BatchPolicyName {
    /// At once: no batching delay for an idle engine; batches fill while it is busy (default).
    WorkConserving,
    /// After the oldest frame has waited `max_wait_us` (throughput over latency).
    MaxWait,
}

/// Which DAN precision serves (the TOML/CLI spelling of [`PrecisionChoice`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum PrecisionName {
    /// int8 (`engine.int8_model`) where the CPU has AVX-512 VNNI or AVX-VNNI, else `engine.model` (default).
    Auto,
    /// `engine.model` as it is, whatever its precision.
    Model,
    /// `engine.model`, which must be fp32.
    Fp32,
    /// `engine.model`, which must be fp16 (GPUs).
    Fp16,
    /// `engine.int8_model`, even without VNNI.
    Int8,
}

impl From<PrecisionName> for PrecisionChoice {
    fn from(p: PrecisionName) -> Self {
        match p {
            PrecisionName::Auto => Self::Auto,
            PrecisionName::Model => Self::Model,
            PrecisionName::Fp32 => Self::Fp32,
            PrecisionName::Fp16 => Self::Fp16,
            PrecisionName::Int8 => Self::Int8,
        }
    }
}

/// `[quic]`: endpoint, TLS and handshake.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct QuicConfig {
    /// UDP address to listen on [default: 0.0.0.0:4433].
    #[arg(long, env = "HOLOFACE_LISTEN")]
    pub listen: Option<SocketAddr>,
    /// PEM certificate chain; without it a self-signed certificate is generated.
    #[arg(long, env = "HOLOFACE_CERT")]
    pub cert: Option<PathBuf>,
    /// PEM private key for `cert`.
    #[arg(long, env = "HOLOFACE_KEY")]
    pub key: Option<PathBuf>,
    /// Subject names of the self-signed certificate [default: localhost].
    #[arg(long = "self-signed-name", value_delimiter = ',')]
    pub self_signed_names: Option<Vec<String>>,
    /// Also write the certificate's SHA-256 fingerprint to this file.
    #[arg(long, env = "HOLOFACE_FINGERPRINT_FILE")]
    pub fingerprint_file: Option<PathBuf>,
    /// Close connections idle this long, ms [default: 10000; at least 100].
    #[arg(long)]
    pub idle_timeout_ms: Option<u64>,
    /// A client must send its ClientHello within this, ms [default: 5000; at least 1].
    #[arg(long)]
    pub hello_timeout_ms: Option<u64>,
    /// Reply transport offered to clients [default: datagram].
    #[arg(long, value_enum)]
    pub reply_channel: Option<ReplyMode>,
}

/// `[auth]`: access tokens.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AuthConfig {
    /// Accepted tokens (comma-separated on the command line).
    #[arg(
        long = "token",
        env = "HOLOFACE_TOKENS",
        value_delimiter = ',',
        hide_env_values = true
    )]
    pub tokens: Option<Vec<String>>,
    /// File with one accepted token per line (added to `tokens`).
    #[arg(long)]
    pub tokens_file: Option<PathBuf>,
    /// Accept clients without a valid token (development only) [default: false].
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub allow_anonymous: Option<bool>,
}

/// `[limits]`: what one client, and all of them, may use.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LimitsConfig {
    /// Concurrent authenticated clients; more are closed with Overloaded [default: 64].
    #[arg(long, env = "HOLOFACE_MAX_CLIENTS")]
    pub max_clients: Option<usize>,
    /// Connections without an authenticated hello yet; at the limit the oldest is evicted, from half of it
    /// unvalidated peers get a QUIC Retry [default: max(max_clients, 16)].
    #[arg(long)]
    pub max_pending: Option<usize>,
    /// Crops one client may have in flight (open frame streams; a headset sends one per tracked face per
    /// frame), so the most faces one client is served for; announced in the welcome as its
    /// `max_in_flight` [default: 8].
    #[arg(long)]
    pub max_in_flight: Option<u16>,
    /// Frames older than this (or their own deadline) are dropped, ms [default: 100; at least 1].
    #[arg(long)]
    pub max_frame_age_ms: Option<u32>,
    /// Bound on graceful shutdown, ms [default: 5000].
    #[arg(long)]
    pub shutdown_timeout_ms: Option<u64>,
    /// Crops (frame streams) per second one client may send, 1 s burst; a frame with three faces counts
    /// three. Above it the client is closed with Overloaded; 0 = unlimited [default: what one headset
    /// needs: max_in_flight faces x 30 fps, 240 with the defaults].
    #[arg(long)]
    pub max_frame_rate: Option<u32>,
}

/// The frame rate a headset's camera runs at; with `limits.max_in_flight` it sets the default crop rate.
pub const HEADSET_FPS: u32 = 30;

/// `[batch]`: the dynamic batcher.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BatchConfig {
    /// Largest inference batch [default: 8].
    #[arg(long, env = "HOLOFACE_MAX_BATCH")]
    pub max_batch: Option<usize>,
    /// When a partial batch goes to an idle engine [default: work-conserving].
    #[arg(long = "batch-policy", value_enum)]
    pub policy: Option<BatchPolicyName>,
    /// With `policy = "max-wait"`: longest wait for a fuller batch, µs [default: 2000].
    #[arg(long)]
    pub max_wait_us: Option<u64>,
    /// Queued frames kept per client; newer ones supersede older [default: 1].
    #[arg(long)]
    pub per_client_queue: Option<usize>,
}

/// `[engine]`: ONNX Runtime.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EngineConfig {
    /// The DAN ONNX model [default: dan.onnx in the holoface data folder].
    #[arg(long, env = "HOLOFACE_DAN_MODEL")]
    pub model: Option<PathBuf>,
    /// The DAN quantised to int8 [default: $HOLOFACE_DAN_INT8_MODEL, else dan.int8.onnx in the data folder].
    #[arg(long)]
    pub int8_model: Option<PathBuf>,
    /// Which precision serves: `auto` runs the int8 model where the CPU has VNNI (about 3x the crops per core)
    /// and `model` otherwise; the log says which and why [default: auto].
    #[arg(long, value_enum, env = "HOLOFACE_PRECISION")]
    pub precision: Option<PrecisionName>,
    /// libonnxruntime.so [default: $ORT_DYLIB_PATH, else libonnxruntime.so.1.31.1 in the holoface data folder].
    #[arg(long)]
    pub ort_dylib: Option<PathBuf>,
    /// ONNX Runtime intra-op threads [default: available cores].
    #[arg(long, env = "HOLOFACE_INTRA_THREADS")]
    pub intra_threads: Option<usize>,
    /// Run the model on ONNX Runtime's CUDA execution provider; needs `ort_dylib` to be the onnxruntime-gpu
    /// build (`make ort-gpu`), CUDA 13, cuDNN 9 and a GPU. Without them the CPU runs it and the log and
    /// `holoface_engine_info` say why [default: false].
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub cuda: Option<bool>,
    /// The CUDA device ordinal [default: 0].
    #[arg(long)]
    pub cuda_device: Option<i32>,
    /// With `cuda`: refuse to start instead of falling back to the CPU [default: false].
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub cuda_required: Option<bool>,
    /// Let ONNX Runtime's intra-op threads spin between ops [default: false].
    #[arg(long, num_args = 0..=1, default_missing_value = "true")]
    pub spin: Option<bool>,
    /// Engine instances (ONNX Runtime sessions, each on its own thread with `intra_threads` threads) fed
    /// by the one batcher; a batch goes to whichever is idle [default: 1].
    #[arg(long = "engine-instances", env = "HOLOFACE_ENGINE_INSTANCES")]
    pub instances: Option<usize>,
}

/// `[refine]`: the refinement cascade after DAN.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RefineConfig {
    /// Refine DAN's landmarks with the cascade (more precise answers; every client version benefits)
    /// [default: true].
    #[arg(
        id = "refine",
        long = "refine",
        num_args = 0..=1,
        default_missing_value = "true",
        env = "HOLOFACE_REFINE"
    )]
    pub enabled: Option<bool>,
    /// The refinement cascade's model file [default: refiner.bin in the holoface data folder].
    #[arg(id = "refine_model", long = "refine-model", env = "HOLOFACE_REFINE_MODEL")]
    pub model: Option<PathBuf>,
}

/// `[internal]`: the metrics/health listener.
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InternalConfig {
    /// Serve /metrics and /health here (loopback or private address only) [default: off].
    #[arg(long, env = "HOLOFACE_METRICS_LISTEN")]
    pub metrics_listen: Option<SocketAddr>,
}

/// `[log]`: logging (installed by the binary).
#[derive(Debug, Clone, Default, PartialEq, Eq, Args, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LogConfig {
    /// Log filter, e.g. `info` or `holoface_alignment_server=debug`; RUST_LOG overrides [default: info].
    #[arg(long = "log-level", env = "HOLOFACE_LOG")]
    pub level: Option<String>,
}

/// The log filter without `[log] level` or RUST_LOG.
pub const DEFAULT_LOG_LEVEL: &str = "info";

impl LogConfig {
    /// The `tracing_subscriber::EnvFilter` directive: `RUST_LOG` if set, else
    /// the configured level, with quinn and rustls capped at `info`.
    pub fn filter_directive(&self) -> String {
        if let Ok(env) = std::env::var("RUST_LOG")
            && !env.trim().is_empty()
        {
            return env;
        }
        let level = self.level.as_deref().unwrap_or(DEFAULT_LOG_LEVEL);
        format!("{level},quinn=info,quinn_proto=info,rustls=info")
    }
}

/// Everything the server can be configured with, as parsed (all optional).
#[derive(Debug, Clone, Default, PartialEq, Eq, Parser, Serialize, Deserialize)]
#[command(
    name = "holoface-server",
    version,
    about = "HoloFace alignment server (QUIC + ONNX Runtime)"
)]
#[serde(deny_unknown_fields, default)]
pub struct ServerConfig {
    /// TOML config file (see deploy/server.example.toml).
    #[arg(long, short = 'c', env = "HOLOFACE_CONFIG")]
    #[serde(skip)]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub quic: QuicConfig,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub auth: AuthConfig,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub limits: LimitsConfig,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub batch: BatchConfig,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub engine: EngineConfig,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub refine: RefineConfig,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub internal: InternalConfig,
    #[command(flatten)]
    #[allow(missing_docs)]
    pub log: LogConfig,
}

macro_rules! merge_fields {
    ($hi:expr, $lo:expr, $($f:ident),+) => {
        Self { $($f: $hi.$f.or($lo.$f)),+ }
    };
}

impl QuicConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(
            self,
            lo,
            listen,
            cert,
            key,
            self_signed_names,
            fingerprint_file,
            idle_timeout_ms,
            hello_timeout_ms,
            reply_channel
        )
    }
}
impl AuthConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(self, lo, tokens, tokens_file, allow_anonymous)
    }
}
impl LimitsConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(
            self,
            lo,
            max_clients,
            max_pending,
            max_in_flight,
            max_frame_age_ms,
            shutdown_timeout_ms,
            max_frame_rate
        )
    }
}
impl BatchConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(self, lo, max_batch, policy, max_wait_us, per_client_queue)
    }
}
impl EngineConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(
            self,
            lo,
            model,
            int8_model,
            precision,
            ort_dylib,
            intra_threads,
            cuda,
            cuda_device,
            cuda_required,
            spin,
            instances
        )
    }
}
impl RefineConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(self, lo, enabled, model)
    }
}
impl InternalConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(self, lo, metrics_listen)
    }
}
impl LogConfig {
    fn merge(self, lo: Self) -> Self {
        merge_fields!(self, lo, level)
    }
}

impl ServerConfig {
    /// Field-by-field: values set in `self` win, unset ones come from `lower`.
    pub fn merge(self, lower: Self) -> Self {
        Self {
            config: self.config.or(lower.config),
            quic: self.quic.merge(lower.quic),
            auth: self.auth.merge(lower.auth),
            limits: self.limits.merge(lower.limits),
            batch: self.batch.merge(lower.batch),
            engine: self.engine.merge(lower.engine),
            refine: self.refine.merge(lower.refine),
            internal: self.internal.merge(lower.internal),
            log: self.log.merge(lower.log),
        }
    }

    /// Parses a TOML config file's text.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, ConfigError> {
        toml::from_str(text).map_err(|e| ConfigError::Toml {
            path: path.to_path_buf(),
            source: Box::new(e),
        })
    }

    /// Parses `args` (program name first), reads the `--config` file through
    /// `read_file` if one is named, and merges: CLI/env over file. Pure apart
    /// from `read_file` and clap's environment look-ups.
    pub fn parse_and_merge<I, T>(
        args: I,
        read_file: impl FnOnce(&Path) -> Result<String, FileError>,
    ) -> Result<Self, ConfigError>
    where
        I: IntoIterator<Item = T>,
        T: Into<OsString> + Clone,
    {
        let cli = Self::try_parse_from(args)?;
        let Some(path) = cli.config.clone() else {
            return Ok(cli);
        };
        let text = read_file(&path).map_err(ConfigError::Read)?;
        let file = Self::from_toml(&text, &path)?;
        Ok(cli.merge(file))
    }

    /// The binary's entry point: process arguments, the config file, then
    /// [`Self::resolve`].
    pub fn load() -> Result<(Settings, LogConfig), ConfigError> {
        let cfg = Self::parse_and_merge(std::env::args_os(), read_config_file)?;
        let log = cfg.log.clone();
        Ok((cfg.resolve()?, log))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::batcher::BatchPolicy;
    use holoface_inference::Provider;
    use proptest::prelude::*;
    use std::time::Duration;

    fn resolve_toml(text: &str) -> Result<Settings, ConfigError> {
        ServerConfig::from_toml(text, Path::new("server.toml"))?.resolve()
    }

    #[test]
    fn a_batch_wait_as_long_as_the_frame_age_is_refused() {
        let err = resolve_toml("[auth]\ntokens=[\"t\"]\n[batch]\npolicy=\"max-wait\"\nmax_wait_us=150000\n")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("max_wait_us = 150000") && err.contains("max_frame_age_ms = 100"),
            "{err}"
        );
        // Shorter than the frame age: accepted.
        let toml = "[auth]\ntokens=[\"t\"]\n[batch]\npolicy=\"max-wait\"\nmax_wait_us=5000\n";
        assert!(resolve_toml(toml).is_ok());
    }

    #[test]
    fn absurd_limits_are_refused_naming_the_setting() {
        // As an operator types them: the largest value each flag's type takes.
        for (flag, setting) in [
            ("--max-clients", "max_clients"),
            ("--max-pending", "max_pending"),
            ("--shutdown-timeout-ms", "shutdown_timeout_ms"),
            ("--idle-timeout-ms", "idle_timeout_ms"),
            ("--per-client-queue", "per_client_queue"),
            ("--intra-threads", "intra_threads"),
        ] {
            let argv = ["holoface-server", "--token", "t", flag, "18446744073709551615"];
            let cfg = ServerConfig::parse_and_merge(argv, |_| Ok(String::new())).unwrap();
            let err = cfg.resolve().unwrap_err().to_string();
            assert!(err.contains(setting), "{flag}: {err}");
        }
        let argv = [
            "holoface-server",
            "--token",
            "t",
            "--max-frame-age-ms",
            "4294967295",
        ];
        let err = ServerConfig::parse_and_merge(argv, |_| Ok(String::new()))
            .unwrap()
            .resolve()
            .unwrap_err();
        assert!(err.to_string().contains("max_frame_age_ms"), "{err}");
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]
        /// No value of any numeric option panics; whatever is accepted can answer frames (a batch wait
        /// shorter than the frame age) and fits the admission semaphore.
        #[test]
        fn no_value_of_any_limit_panics(
            max_clients in prop::option::of(any::<u64>()),
            max_pending in prop::option::of(any::<u64>()),
            max_in_flight in prop::option::of(any::<u16>()),
            max_frame_age_ms in prop::option::of(any::<u32>()),
            shutdown_timeout_ms in prop::option::of(any::<u64>()),
            max_frame_rate in prop::option::of(any::<u32>()),
            max_batch in prop::option::of(any::<u64>()),
            max_wait_us in prop::option::of(any::<u64>()),
            per_client_queue in prop::option::of(any::<u64>()),
            idle_timeout_ms in prop::option::of(any::<u64>()),
            hello_timeout_ms in prop::option::of(any::<u64>()),
            instances in prop::option::of(any::<u64>()),
            intra_threads in prop::option::of(any::<u64>()),
        ) {
            // TOML integers are i64: larger values are a parse error, which is fine too.
            let line = |k: &str, v: Option<String>| v.map(|v| format!("{k} = {v}\n")).unwrap_or_default();
            let s = |v: Option<u64>| v.map(|v| v.to_string());
            let mut toml = String::from("[auth]\ntokens = [\"t\"]\n[quic]\n");
            toml += &line("idle_timeout_ms", s(idle_timeout_ms));
            toml += &line("hello_timeout_ms", s(hello_timeout_ms));
            toml += "[limits]\n";
            toml += &line("max_clients", s(max_clients));
            toml += &line("max_pending", s(max_pending));
            toml += &line("max_in_flight", max_in_flight.map(|v| v.to_string()));
            toml += &line("max_frame_age_ms", max_frame_age_ms.map(|v| v.to_string()));
            toml += &line("shutdown_timeout_ms", s(shutdown_timeout_ms));
            toml += &line("max_frame_rate", max_frame_rate.map(|v| v.to_string()));
            toml += "[batch]\n";
            toml += &line("max_batch", s(max_batch));
            if max_wait_us.is_some() {
                toml += "policy = \"max-wait\"\n";
            }
            toml += &line("max_wait_us", s(max_wait_us));
            toml += &line("per_client_queue", s(per_client_queue));
            toml += "[engine]\n";
            toml += &line("instances", s(instances));
            toml += &line("intra_threads", s(intra_threads));
            if let Ok(settings) = resolve_toml(&toml) {
                prop_assert!((1..=MAX_CLIENTS).contains(&settings.max_clients));
                prop_assert!((1..=MAX_CLIENTS).contains(&settings.max_pending));
                prop_assert!(!settings.max_frame_age.is_zero());
                if let BatchPolicy::MaxWait(w) = settings.batch.policy {
                    prop_assert!(w < settings.max_frame_age);
                }
                // What the server builds from them without IO must not panic either.
                let _ = tokio::sync::Semaphore::new(settings.max_clients);
                let _ = crate::batcher::DynamicBatcher::<u8>::new(settings.batch);
                let _ = std::time::Instant::now().checked_add(settings.shutdown_timeout).is_some();
            }
        }
    }

    const TOML: &str = r#"
        [quic]
        listen = "127.0.0.1:5000"
        reply_channel = "stream"
        [auth]
        tokens = ["from-file"]
        [batch]
        max_batch = 16
        policy = "max-wait"
        max_wait_us = 500
        [engine]
        model = "/srv/dan.onnx"
        intra_threads = 3
        [limits]
        max_clients = 7
    "#;

    fn parse(args: &[&str]) -> ServerConfig {
        let mut argv = vec!["holoface-server", "--config", "server.toml"];
        argv.extend_from_slice(args);
        ServerConfig::parse_and_merge(argv, |p| {
            assert_eq!(p, Path::new("server.toml"));
            Ok(TOML.to_owned())
        })
        .unwrap()
    }

    #[test]
    fn cli_does_not_clobber_toml_when_flags_absent() {
        let cfg = parse(&[]);
        assert_eq!(cfg.batch.max_batch, Some(16));
        assert_eq!(cfg.batch.max_wait_us, Some(500));
        assert_eq!(cfg.quic.reply_channel, Some(ReplyMode::Stream));
        assert_eq!(cfg.engine.intra_threads, Some(3));
        assert_eq!(cfg.limits.max_clients, Some(7));
        let s = cfg.resolve().unwrap();
        assert_eq!(s.batch.max_batch, 16);
        assert_eq!(s.batch.policy, BatchPolicy::MaxWait(Duration::from_micros(500)));
        assert_eq!(s.reply_channel, ReplyChannel::Stream);
        assert_eq!(s.listen, "127.0.0.1:5000".parse().unwrap());
        assert_eq!(s.tokens, vec!["from-file".to_owned()]);
    }

    #[test]
    fn batching_is_work_conserving_unless_max_wait_is_chosen() {
        let resolve = |toml: &str| {
            ServerConfig::parse_and_merge(
                ["holoface-server", "--config", "s.toml", "--allow-anonymous"],
                |_| Ok(toml.to_owned()),
            )
            .unwrap()
            .resolve()
        };
        assert_eq!(resolve("").unwrap().batch.policy, BatchPolicy::WorkConserving);
        assert_eq!(
            resolve("[batch]\npolicy = \"max-wait\"").unwrap().batch.policy,
            BatchPolicy::MaxWait(Duration::from_millis(2))
        );
        let err = resolve("[batch]\nmax_wait_us = 2000").unwrap_err().to_string();
        assert!(err.contains("max_wait_us") && err.contains("max-wait"), "{err}");
        let cli = ServerConfig::parse_and_merge(
            [
                "holoface-server",
                "--allow-anonymous",
                "--batch-policy",
                "max-wait",
                "--max-wait-us",
                "700",
            ],
            |_| unreachable!("no config file"),
        )
        .unwrap()
        .resolve()
        .unwrap();
        assert_eq!(cli.batch.policy, BatchPolicy::MaxWait(Duration::from_micros(700)));
    }

    #[test]
    fn cli_does_not_clobber_toml_other_fields_of_a_section() {
        // Setting one batch flag must not reset the other batch fields.
        let cfg = parse(&["--max-batch", "4"]);
        assert_eq!(cfg.batch.max_batch, Some(4));
        assert_eq!(cfg.batch.max_wait_us, Some(500));
        assert_eq!(cfg.engine.model, Some(PathBuf::from("/srv/dan.onnx")));
    }

    #[test]
    fn cli_does_not_clobber_toml_but_explicit_flags_win() {
        let cfg = parse(&[
            "--listen",
            "127.0.0.1:6000",
            "--reply-channel",
            "datagram",
            "--token",
            "a,b",
        ]);
        assert_eq!(cfg.quic.listen, Some("127.0.0.1:6000".parse().unwrap()));
        assert_eq!(cfg.quic.reply_channel, Some(ReplyMode::Datagram));
        assert_eq!(cfg.auth.tokens, Some(vec!["a".to_owned(), "b".to_owned()]));
        assert_eq!(cfg.limits.max_clients, Some(7));
    }

    #[test]
    fn defaults_without_a_file() {
        let cfg =
            ServerConfig::parse_and_merge(["holoface-server", "--token", "t"], |_| panic!("no file named"))
                .unwrap();
        let s = cfg.resolve().unwrap();
        assert_eq!(s.listen, DEFAULT_LISTEN.parse().unwrap());
        assert_eq!(s.batch.max_batch, 8);
        assert_eq!(s.batch.per_client_queue, 1);
        assert_eq!(s.max_in_flight, 8);
        assert_eq!(s.reply_channel, ReplyChannel::Datagram);
        assert_eq!(s.engine.model, default_model());
        assert_eq!(
            s.refine_model,
            Some(default_refine_model()),
            "refinement is on by default"
        );
        assert_eq!(s.metrics_listen, None);
        assert!(matches!(s.tls, TlsSource::SelfSigned { ref names } if names == &["localhost"]));
    }

    #[test]
    fn cuda_settings_resolve_to_a_provider() {
        let parse = |toml: &'static str| {
            ServerConfig::parse_and_merge(["x", "-c", "f.toml", "--token", "t"], move |_| Ok(toml.into()))
                .and_then(ServerConfig::resolve)
                .map(|s| s.engine.provider)
        };
        assert_eq!(parse("").unwrap(), Provider::Cpu);
        assert_eq!(
            parse("[engine]\ncuda = true\n").unwrap(),
            Provider::Cuda {
                device: 0,
                required: false
            }
        );
        assert_eq!(
            parse("[engine]\ncuda = true\ncuda_device = 1\ncuda_required = true\n").unwrap(),
            Provider::Cuda {
                device: 1,
                required: true
            }
        );
        for bad in ["[engine]\ncuda_device = 1\n", "[engine]\ncuda_required = true\n"] {
            let e = parse(bad).unwrap_err().to_string();
            assert!(e.contains("need engine.cuda = true"), "{bad}: {e}");
        }
        let e = parse("[engine]\ncuda = true\ncuda_device = -1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("cuda_device -1"), "{e}");
    }

    #[test]
    fn unknown_toml_keys_are_rejected() {
        let err =
            ServerConfig::parse_and_merge(["x", "-c", "f.toml"], |_| Ok("[batch]\nmax_bach = 3\n".into()))
                .unwrap_err();
        assert!(err.to_string().contains("max_bach"), "{err}");
    }

    #[test]
    fn invalid_values_are_refused() {
        let no_tokens = ServerConfig::default().resolve().unwrap_err().to_string();
        assert!(no_tokens.contains("no access tokens"), "{no_tokens}");
        let mut cfg = ServerConfig::default();
        cfg.auth.allow_anonymous = Some(true);
        cfg.internal.metrics_listen = Some("0.0.0.0:9000".parse().unwrap());
        assert!(
            cfg.clone()
                .resolve()
                .unwrap_err()
                .to_string()
                .contains("loopback or private")
        );
        cfg.internal.metrics_listen = None;
        cfg.quic.cert = Some("c.pem".into());
        assert!(
            cfg.clone()
                .resolve()
                .unwrap_err()
                .to_string()
                .contains("together")
        );
        cfg.quic.cert = None;
        cfg.batch.max_batch = Some(0);
        assert!(
            cfg.clone()
                .resolve()
                .unwrap_err()
                .to_string()
                .contains("max_batch")
        );
        cfg.batch.max_batch = None;
        assert_eq!(
            cfg.clone().resolve().unwrap().engine_instances,
            1,
            "one instance by default"
        );
        for bad in [0, 65] {
            cfg.engine.instances = Some(bad);
            let e = cfg.clone().resolve().unwrap_err().to_string();
            assert!(e.contains("engine.instances"), "{e}");
        }
        cfg.engine.instances = Some(2);
        assert_eq!(cfg.resolve().unwrap().engine_instances, 2);
    }

    #[test]
    fn zero_durations_are_refused_not_raised() {
        let base = || {
            let mut cfg = ServerConfig::default();
            cfg.auth.allow_anonymous = Some(true);
            cfg
        };
        let mut cfg = base();
        cfg.quic.idle_timeout_ms = Some(0);
        let e = cfg.resolve().unwrap_err().to_string();
        assert!(
            e.contains("idle_timeout_ms = 0") && e.contains("at least 100"),
            "{e}"
        );
        let mut cfg = base();
        cfg.quic.idle_timeout_ms = Some(99);
        assert!(cfg.resolve().is_err());
        let mut cfg = base();
        cfg.quic.idle_timeout_ms = Some(100);
        assert_eq!(cfg.resolve().unwrap().idle_timeout, Duration::from_millis(100));
        let mut cfg = base();
        cfg.limits.max_frame_age_ms = Some(0);
        let e = cfg.resolve().unwrap_err().to_string();
        assert!(e.contains("max_frame_age_ms = 0"), "{e}");
        let mut cfg = base();
        cfg.quic.hello_timeout_ms = Some(0);
        assert!(
            cfg.resolve()
                .unwrap_err()
                .to_string()
                .contains("hello_timeout_ms")
        );
    }

    #[test]
    fn a_missing_tokens_file_is_named_as_such() {
        let mut cfg = ServerConfig::default();
        cfg.auth.tokens_file = Some("/nonexistent/holoface-tokens".into());
        let e = cfg.resolve().unwrap_err().to_string();
        assert_eq!(e, "tokens file /nonexistent/holoface-tokens does not exist");
    }

    /// What `resolve` makes of a config with nothing but a token, changed by `edit`.
    fn resolved(edit: impl FnOnce(&mut ServerConfig)) -> Settings {
        let mut cfg = ServerConfig::default();
        cfg.auth.tokens = Some(vec!["t".into()]);
        edit(&mut cfg);
        cfg.resolve().unwrap()
    }

    /// The defaults as `resolve` applies them, spelled as the field docs spell them, by argument id: the one
    /// table that the docs' "[default: ...]" and deploy/server.example.toml are checked against.
    fn resolved_defaults() -> Vec<(&'static str, String)> {
        let s = resolved(|_| {});
        let wait = match resolved(|c| c.batch.policy = Some(BatchPolicyName::MaxWait))
            .batch
            .policy
        {
            BatchPolicy::MaxWait(d) => d.as_micros().to_string(),
            BatchPolicy::WorkConserving => "work-conserving".into(),
        };
        let (device, required) = match resolved(|c| c.engine.cuda = Some(true)).engine.provider {
            Provider::Cuda { device, required } => (device.to_string(), required.to_string()),
            other => (format!("{other:?}"), String::new()),
        };
        let names = match &s.tls {
            TlsSource::SelfSigned { names } => names.join(","),
            TlsSource::Files { .. } => "files".into(),
        };
        let ms = |d: Duration| d.as_millis().to_string();
        vec![
            ("listen", s.listen.to_string()),
            ("self_signed_names", names),
            ("idle_timeout_ms", ms(s.idle_timeout)),
            ("hello_timeout_ms", ms(s.hello_timeout)),
            ("reply_channel", format!("{:?}", s.reply_channel).to_lowercase()),
            ("allow_anonymous", s.allow_anonymous.to_string()),
            ("max_clients", s.max_clients.to_string()),
            ("max_in_flight", s.max_in_flight.to_string()),
            ("max_frame_age_ms", ms(s.max_frame_age)),
            ("shutdown_timeout_ms", ms(s.shutdown_timeout)),
            ("max_batch", s.batch.max_batch.to_string()),
            (
                "policy",
                match s.batch.policy {
                    BatchPolicy::WorkConserving => "work-conserving".into(),
                    BatchPolicy::MaxWait(_) => "max-wait".into(),
                },
            ),
            ("max_wait_us", wait),
            ("per_client_queue", s.batch.per_client_queue.to_string()),
            ("precision", format!("{:?}", s.precision).to_lowercase()),
            ("cuda", (s.engine.provider != Provider::Cpu).to_string()),
            ("cuda_device", device),
            ("cuda_required", required),
            ("spin", s.engine.spin.to_string()),
            ("instances", s.engine_instances.to_string()),
            ("refine", s.refine_model.is_some().to_string()),
            (
                "metrics_listen",
                s.metrics_listen.map_or("off".into(), |a| a.to_string()),
            ),
            // Applied by `LogConfig::filter_directive` (RUST_LOG overrides it), not by `resolve`.
            ("level", DEFAULT_LOG_LEVEL.into()),
        ]
    }

    #[test]
    fn the_documented_defaults_are_the_ones_resolve_applies() {
        // Defaults the docs give in words, not as one value: derived from another setting, a path in the data
        // folder, the machine's cores.
        const IN_WORDS: [&str; 7] = [
            "max_pending",
            "max_frame_rate",
            "model",
            "int8_model",
            "ort_dylib",
            "intra_threads",
            "refine_model",
        ];
        let table = resolved_defaults();
        let cmd = <ServerConfig as clap::CommandFactory>::command();
        let mut checked = Vec::new();
        for arg in cmd.get_arguments() {
            let id = arg.get_id().as_str();
            let help = arg
                .get_long_help()
                .or(arg.get_help())
                .map(ToString::to_string)
                .unwrap_or_default();
            let Some(at) = help.find("[default: ") else {
                continue;
            };
            let documented = help[at + 10..]
                .split([';', ']'])
                .next()
                .unwrap_or_default()
                .trim();
            match table.iter().find(|(k, _)| *k == id) {
                Some((_, value)) => {
                    assert_eq!(
                        documented, value,
                        "--{id}: the docs say {documented}, resolve applies {value}"
                    );
                    checked.push(id.to_owned());
                }
                None => assert!(
                    IN_WORDS.contains(&id),
                    "--{id} documents [default: {documented}], which nothing compares with resolve"
                ),
            }
        }
        let missing: Vec<_> = table
            .iter()
            .filter(|(k, _)| !checked.iter().any(|c| c == k))
            .collect();
        assert!(missing.is_empty(), "defaults the docs do not give: {missing:?}");
    }

    #[test]
    fn the_example_file_spells_the_defaults_it_does_not_change() {
        let text = include_str!("../../deploy/server.example.toml");
        let example = ServerConfig::from_toml(text, Path::new("deploy/server.example.toml")).unwrap();
        let file: toml::Table = toml::from_str(text).unwrap();
        // What the example sets on purpose: a token to replace, a fingerprint file, two ONNX Runtime threads, a
        // metrics listener on loopback.
        let on_purpose = ["tokens", "fingerprint_file", "intra_threads", "metrics_listen"];
        let mut defaults = ServerConfig::default();
        defaults.auth.tokens = example.auth.tokens.clone();
        let defaults = defaults.resolve().unwrap();
        let table = resolved_defaults();
        let mut compared = 0;
        for (section, keys) in &file {
            for (key, value) in keys.as_table().unwrap() {
                if on_purpose.contains(&key.as_str()) {
                    continue;
                }
                // The file's spelling of the key, as the table's argument id.
                let id = match (section.as_str(), key.as_str()) {
                    ("refine", "enabled") => "refine",
                    (_, k) => k,
                };
                let spelled = match value {
                    toml::Value::String(v) => v.clone(),
                    toml::Value::Array(a) => {
                        a.iter().filter_map(|v| v.as_str()).collect::<Vec<_>>().join(",")
                    }
                    v => v.to_string(),
                };
                match table.iter().find(|(k, _)| *k == id) {
                    Some((_, d)) => assert_eq!(&spelled, d, "[{section}] {key}"),
                    // Values the docs give in words: compared as resolved.
                    None if id == "max_frame_rate" => {
                        assert_eq!(
                            spelled,
                            defaults.max_frame_rate.to_string(),
                            "[limits] max_frame_rate"
                        );
                    }
                    None => panic!("[{section}] {key} = {spelled}: not a default the table knows"),
                }
                compared += 1;
            }
        }
        assert!(
            compared >= 15,
            "only {compared} values compared: the file lost its sections?"
        );
    }

    #[test]
    fn a_config_file_that_is_not_a_file_is_refused_with_its_kind() {
        let dir = std::env::temp_dir();
        let e =
            ServerConfig::parse_and_merge(["x", "-c", dir.to_str().unwrap()], read_config_file).unwrap_err();
        // The structure is kept: a caller can match the kind, and the words name the file and its role.
        assert!(
            matches!(&e, ConfigError::Read(FileError::NotAFile { path, .. }) if *path == dir),
            "{e:?}"
        );
        assert_eq!(
            e.to_string(),
            format!("config file {} is a directory, not a regular file", dir.display())
        );
    }

    #[test]
    fn refinement_is_configured_by_file_flag_and_environment() {
        let from = |args: &[&str], toml: &'static str| {
            ServerConfig::parse_and_merge(args.iter().copied(), |_| Ok(toml.to_owned()))
                .and_then(ServerConfig::resolve)
        };
        let off = from(&["s", "--token", "t", "-c", "f"], "[refine]\nenabled = false\n").unwrap();
        assert_eq!(off.refine_model, None);
        let other = from(
            &["s", "--token", "t", "-c", "f"],
            "[refine]\nmodel = \"/srv/r.bin\"\n",
        )
        .unwrap();
        assert_eq!(other.refine_model, Some(PathBuf::from("/srv/r.bin")));
        // The flag turns it back on over the file.
        let on = from(
            &["s", "--token", "t", "--refine", "-c", "f"],
            "[refine]\nenabled = false\n",
        )
        .unwrap();
        assert_eq!(on.refine_model, Some(default_refine_model()));
        let both = from(
            &["s", "--token", "t", "-c", "f"],
            "[refine]\nenabled = false\nmodel = \"/srv/r.bin\"\n",
        )
        .unwrap_err()
        .to_string();
        assert!(both.contains("refine.enabled = false"), "{both}");
    }

    #[test]
    fn example_config_parses() {
        let text = include_str!("../../deploy/server.example.toml");
        let cfg = ServerConfig::from_toml(text, Path::new("deploy/server.example.toml")).unwrap();
        let s = cfg.resolve().unwrap();
        // Its asset paths are commented out: an installed server finds them in the data folder.
        assert_eq!(s.engine.model, default_model());
        assert_eq!(s.refine_model, Some(default_refine_model()));
    }
}
