//! HoloFace inference: what the alignment server and the headset client share to run ONNX models.
//!
//! * [`crop_decode`]: the one decoder of a crop's PNG/JPEG payload ([`decode_crop`]), hardened for network bytes.
//! * [`contract`]: the [`InferenceEngine`] trait and the DAN model contract (batch, outputs, metadata,
//!   input/output validation), which every engine below meets.
//! * [`onnx`]: [`OnnxEngine`] (ort, `load-dynamic`; CUDA with fail-over to the CPU).
//! * [`precision`]: which DAN file serves (int8 on a CPU with VNNI, else fp32), as a pure rule.
//! * [`cascade`]: [`CascadeEngine`], an engine followed by the refinement cascade (the server's pipeline).
//! * `fake`: `FakeEngine` under `cfg(test)` / the `test-util` feature.
//! * [`integrity`]: model files checked before use (sidecar checksums, the shipped releases' checksums, a
//!   start-up self-test of the engine on a fixed crop).
//! * [`runtime`]: where the ONNX Runtime library is found ([`runtime::default_ort_dylib`]) and the one
//!   process-wide ONNX Runtime environment ([`runtime::load_runtime`]) that every session in a process shares
//!   (the server's engines, the client's face detector).
//!
//! No IO besides loading the library and the model files (read through `holoface-files`' bounded reads); no
//! async runtime, no network. The data folder and its assets are `holoface-files`' `home`.
#![deny(missing_docs)]

pub mod cascade;
pub mod contract;
pub mod cpu;
pub mod crop_decode;
pub mod error;
#[cfg(any(test, feature = "test-util"))]
pub mod fake;
pub mod integrity;
pub mod onnx;
pub mod precision;
pub mod runtime;

pub use cascade::{CascadeEngine, LoadedCascade};
pub use contract::{
    BatchTensor, CPU_PROVIDER, CUDA_PROVIDER, CascadeStats, Execution, InferenceEngine, LandmarkOut,
    ModelInfo,
};
pub use cpu::CpuInt8;
pub use crop_decode::{CropDecodeError, decode_crop};
pub use error::EngineError;
#[cfg(any(test, feature = "test-util"))]
pub use fake::FakeEngine;
pub use onnx::{OnnxEngine, OnnxOptions, Provider};
pub use precision::{Decision, PrecisionChoice};
pub use runtime::{ORT_DYLIB_ENV, default_ort_dylib, load_runtime};
