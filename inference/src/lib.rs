//! HoloFace inference: what the alignment server and the headset client share to run ONNX models.
//!
//! * [`crop`]: the one decoder of a crop's PNG/JPEG payload ([`decode_crop`]), hardened for network bytes.
//! * [`engine`]: the [`InferenceEngine`] trait (the DAN model contract), [`OnnxEngine`] (ort,
//!   `load-dynamic`), model-contract validation; `FakeEngine` under `cfg(test)` / the `test-util` feature.
//! * [`refine`]: [`RefinedEngine`], DAN followed by the refinement cascade (the server's pipeline).
//! * [`files`]: bounded reads of the files front ends name (kind and size checked before reading).
//! * [`integrity`]: model files checked before use (sidecar checksums, the shipped releases' checksums, a
//!   start-up self-test of the engine on a fixed crop).
//! * [`home`]: the holoface data folder and the assets in it (where installed binaries find them, and the
//!   messages when they are missing).
//! * [`runtime`]: where the ONNX Runtime library is found ([`runtime::default_ort_dylib`]) and the one
//!   process-wide ONNX Runtime environment ([`runtime::load_runtime`]) that every session in a process shares
//!   (the server's engines, the client's face detector).
//!
//! No IO besides loading the library, the model files and the bounded reads of [`files`]; no async runtime, no network.
#![deny(missing_docs)]

pub mod crop;
pub mod engine;
pub mod error;
pub mod files;
pub mod home;
pub mod integrity;
pub mod refine;
pub mod runtime;

pub use crop::{CropDecodeError, decode_crop};
pub use engine::{
    BatchTensor, CPU_PROVIDER, CUDA_PROVIDER, Execution, InferenceEngine, LandmarkOut, ModelInfo, OnnxEngine,
    OnnxOptions, Provider,
};
pub use error::EngineError;
pub use refine::{RefinedEngine, Refinement, RefinerModel};
pub use runtime::{ORT_DYLIB_ENV, default_ort_dylib, load_runtime};
