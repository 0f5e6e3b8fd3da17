//! HoloFace alignment server: headsets stream 112x112 gray face crops over
//! QUIC; the server batches them across clients, runs the DAN model in ONNX
//! Runtime and answers each frame with 68 landmarks and a face probability.
//!
//! * [`batcher`]: the sans-IO [`DynamicBatcher`] (takes `now`, unit-tested on
//!   a fake clock).
//! * [`engine`]: the [`InferenceEngine`] trait, [`OnnxEngine`] (ort,
//!   `load-dynamic`), model-contract validation; `FakeEngine` under
//!   `cfg(test)` / the `test-util` feature.
//! * [`server`]: the quinn driver: [`Server::bind`], [`Server::run`] with an
//!   injected shutdown future, [`run`].
//! * [`config`]: [`ServerConfig`] (TOML + CLI + env, CLI cannot clobber the
//!   file) resolved into [`Settings`].
//! * [`tls`]: server certificates and the client-side pinned-fingerprint
//!   verifier ([`tls::pinned_client_config`]) the headset client reuses.
//! * [`metrics`], [`internal`]: Prometheus `/metrics` and `/health` on a
//!   loopback/private listener.
//!
//! The library emits `tracing` events and never installs a subscriber.
#![deny(missing_docs)]

pub mod batcher;
pub mod config;
pub mod engine;
pub mod internal;
pub mod metrics;
pub mod server;
pub mod tls;

pub use batcher::{BatcherConfig, DynamicBatcher};
pub use config::{ServerConfig, Settings};
pub use engine::{InferenceEngine, ModelInfo, OnnxEngine};
pub use server::{Server, ServerError, run, shutdown_signal};
pub use tls::{Fingerprint, pinned_client_config};
