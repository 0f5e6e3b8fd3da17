//! HoloFace alignment server: headsets stream 112x112 gray face crops over
//! QUIC; the server batches them across clients, runs the DAN model in ONNX
//! Runtime and answers each frame with 68 landmarks and a face probability.
//!
//! * [`batcher`]: the sans-IO [`DynamicBatcher`] (takes `now`, unit-tested on
//!   a fake clock).
//! * The engine ([`InferenceEngine`], [`OnnxEngine`]) lives in
//!   `holoface-inference`, shared with the headset client.
//! * [`server`]: the quinn driver: [`AlignmentServer::bind`], [`AlignmentServer::run`] with an
//!   injected shutdown future, [`run`], [`shutdown_signal`]. Split by
//!   responsibility: `server/mod.rs` (the server, its shared state, transport
//!   settings and the accept loop), `lifecycle.rs` (systemd readiness,
//!   signals), `auth.rs` (hello, version and token checks), `client.rs`
//!   (the per-connection task), `reply.rs` (the reply sink), `frame_stream.rs` (one
//!   frame stream), `rate_limit.rs`, `scheduler.rs` (the batcher's task) and
//!   `engine_thread.rs` (the inference thread).
//! * [`config`]: [`ServerConfig`] (TOML + CLI + env, CLI cannot clobber the
//!   file) resolved into [`Settings`].
//! * [`tls`]: the server's certificate (PEM files or self-signed); the
//!   fingerprint clients pin is `holoface-quic`'s [`Fingerprint`].
//! * [`metrics`], [`metrics_http`]: Prometheus `/metrics` and `/health` on a
//!   loopback/private listener.
//!
//! The library emits `tracing` events and never installs a subscriber.
#![deny(missing_docs)]

pub mod batcher;
pub mod config;
pub mod metrics;
pub mod metrics_http;
pub mod server;
pub mod tls;

pub use batcher::{BatchPolicy, BatcherConfig, DynamicBatcher};
pub use config::{ServerConfig, Settings};
pub use holoface_inference::{InferenceEngine, ModelInfo, OnnxEngine};
pub use holoface_quic::Fingerprint;
pub use server::{AlignmentServer, ServerError, run, shutdown_signal};
