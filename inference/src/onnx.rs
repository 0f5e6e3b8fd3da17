//! [`OnnxEngine`]: the DAN model in ONNX Runtime (`ort`, `load-dynamic`), on the CPU or on CUDA with fail-over
//! to the CPU (or a refusal when CUDA is required), the model file checked before use
//! ([`crate::integrity`]).

use std::path::PathBuf;

use crate::contract::{
    BatchTensor, ElemType, Execution, InferenceEngine, LandmarkOut, ModelInfo, OUTPUT_FACE_PROB,
    OUTPUT_LANDMARKS, TensorSpec, validate_io,
};
pub use crate::contract::{CPU_PROVIDER, CUDA_PROVIDER};
use crate::error::EngineError;
use crate::runtime::load_runtime;

/// The ONNX Runtime execution provider an [`OnnxEngine`] is asked to run the model on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Provider {
    /// ONNX Runtime's CPU execution provider (any `libonnxruntime`).
    #[default]
    Cpu,
    /// The CUDA execution provider on GPU `device`; needs the CUDA build of ONNX Runtime (the
    /// `onnxruntime-gpu` wheel's library, `make ort-gpu`), CUDA 13 and cuDNN 9. When it cannot run, the
    /// engine falls back to the CPU and says why ([`Execution::fallback`]), unless `required`.
    Cuda {
        /// The CUDA device ordinal.
        device: i32,
        /// Fail to load instead of falling back to the CPU.
        required: bool,
    },
}

/// ONNX Runtime engine settings.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OnnxOptions {
    /// The `.onnx` model.
    pub model: PathBuf,
    /// `libonnxruntime.so`.
    pub ort_dylib: PathBuf,
    /// Intra-op threads.
    pub intra_threads: usize,
    /// Largest batch.
    pub max_batch: usize,
    /// The execution provider to run on.
    pub provider: Provider,
    /// Let ONNX Runtime's intra-op threads spin between ops. Off by default:
    /// the engine shares the cores with the QUIC driver, and spinning threads
    /// starve it (and each other) on a small or loaded machine.
    pub spin: bool,
}

/// The DAN model in ONNX Runtime: one session, reused for every batch.
#[derive(Debug)]
pub struct OnnxEngine {
    session: ort::session::Session,
    info: ModelInfo,
    max_batch: usize,
    execution: Execution,
    _env: ort::environment::Environment,
}

fn spec_of(outlet: &ort::value::Outlet) -> TensorSpec {
    use ort::value::{TensorElementType, ValueType};
    let (elem, shape) = match outlet.dtype() {
        ValueType::Tensor { ty, shape, .. } => {
            let elem = match ty {
                TensorElementType::Uint8 => ElemType::U8,
                TensorElementType::Float32 => ElemType::F32,
                other => ElemType::Other(format!("{other:?}")),
            };
            (Some(elem), shape.to_vec())
        }
        _ => (None, Vec::new()),
    };
    TensorSpec {
        name: outlet.name().to_owned(),
        elem,
        shape,
    }
}

impl OnnxEngine {
    /// Loads the runtime and the model, and validates the model contract.
    pub fn load(opts: &OnnxOptions) -> Result<Self, EngineError> {
        if opts.model.is_dir() {
            return Err(EngineError::ModelIsDirectory {
                path: opts.model.clone(),
            });
        }
        if !opts.model.is_file() {
            return Err(holoface_files::home::DAN.missing(&opts.model).into());
        }
        // The file is read once, checked, and the session made from those very bytes.
        let bytes = read_model(&opts.model)?;
        crate::integrity::verify_sidecar(&opts.model, &bytes)?;
        let env = load_runtime(&opts.ort_dylib)?;
        let (session, execution) = match opts.provider {
            Provider::Cpu => (cpu_session(&env, opts, &bytes)?, Execution::cpu()),
            Provider::Cuda { device, required } => match cuda_session(&env, opts, device, &bytes) {
                Ok(session) => (
                    session,
                    Execution {
                        provider: CUDA_PROVIDER.into(),
                        device: Some(device),
                        fallback: None,
                    },
                ),
                Err(why) if required => {
                    return Err(EngineError::ProviderUnavailable {
                        provider: CUDA_PROVIDER,
                        detail: why,
                    });
                }
                Err(why) => (
                    cpu_session(&env, opts, &bytes)?,
                    Execution {
                        fallback: Some(why),
                        ..Execution::cpu()
                    },
                ),
            },
        };
        let info = {
            let meta = session.metadata()?;
            ModelInfo::from_metadata(|k| meta.custom(k))?
        };
        let inputs: Vec<TensorSpec> = session.inputs().iter().map(spec_of).collect();
        let outputs: Vec<TensorSpec> = session.outputs().iter().map(spec_of).collect();
        validate_io(&inputs, &outputs, &info)?;
        let known = crate::integrity::known(&info.name, &info.version, &info.precision);
        if let Some(k) = known {
            crate::integrity::verify_known(&opts.model, k, &bytes)?;
        }
        let mut engine = Self {
            session,
            info,
            max_batch: opts.max_batch.max(1),
            execution,
            _env: env,
        };
        crate::integrity::self_test(&mut engine, &opts.model, known)?;
        Ok(engine)
    }
}

/// Reads a model file whole, refusing one too large to be a model (or not a file at all) before reading it.
fn read_model(path: &std::path::Path) -> Result<Vec<u8>, EngineError> {
    holoface_files::read_bounded(
        path,
        holoface_files::home::DAN.max_bytes,
        holoface_files::home::DAN.name,
    )
    .map_err(|e| match e {
        holoface_files::FileError::Missing { .. } => holoface_files::home::DAN.missing(path).into(),
        other => EngineError::Damaged {
            path: path.to_path_buf(),
            detail: other.to_string(),
        },
    })
}

/// A session builder with the options every provider shares.
fn session_builder(
    env: &ort::environment::Environment,
    opts: &OnnxOptions,
) -> Result<ort::session::builder::SessionBuilder, EngineError> {
    Ok(ort::session::Session::builder(env)?
        .with_intra_threads(opts.intra_threads.max(1))
        .map_err(ort::Error::from)?
        .with_inter_threads(1)
        .map_err(ort::Error::from)?
        .with_intra_op_spinning(opts.spin)
        .map_err(ort::Error::from)?)
}

fn cpu_session(
    env: &ort::environment::Environment,
    opts: &OnnxOptions,
    model: &[u8],
) -> Result<ort::session::Session, EngineError> {
    Ok(session_builder(env, opts)?.commit_from_memory(model)?)
}

/// A CUDA session, or why there is none: the library is the CPU build, the provider or the CUDA/cuDNN
/// libraries it links cannot be loaded, or there is no usable GPU.
#[cfg(feature = "cuda")]
fn cuda_session(
    env: &ort::environment::Environment,
    opts: &OnnxOptions,
    device: i32,
    model: &[u8],
) -> Result<ort::session::Session, String> {
    use ort::ep::ExecutionProvider as _;
    match ort::ep::CUDA::is_available() {
        Ok(true) => {}
        Ok(false) => {
            return Err(format!(
                "{} is a build of ONNX Runtime without the CUDA execution provider (use the onnxruntime-gpu \
                 wheel's library: `make ort-gpu`, then engine.ort_dylib = .cache/onnxruntime-gpu/…)",
                opts.ort_dylib.display()
            ));
        }
        Err(e) => return Err(format!("asking ONNX Runtime for its providers: {e}")),
    }
    let builder = session_builder(env, opts).map_err(|e| e.to_string())?;
    let mut builder = builder
        .with_execution_providers([ort::ep::CUDA::default()
            .with_device_id(device)
            .build()
            .error_on_failure()])
        .map_err(|e| {
            format!(
                "registering the CUDA execution provider on device {device}: {}",
                e.to_string().trim_end()
            )
        })?;
    builder.commit_from_memory(model).map_err(|e| {
        format!(
            "creating a CUDA session on device {device}: {}",
            e.to_string().trim_end()
        )
    })
}

#[cfg(not(feature = "cuda"))]
fn cuda_session(
    _env: &ort::environment::Environment,
    _opts: &OnnxOptions,
    _device: i32,
    _model: &[u8],
) -> Result<ort::session::Session, String> {
    Err("this build of holoface has no `cuda` feature".into())
}

impl InferenceEngine for OnnxEngine {
    fn info(&self) -> &ModelInfo {
        &self.info
    }

    fn execution(&self) -> Execution {
        self.execution.clone()
    }

    fn max_batch(&self) -> usize {
        self.max_batch
    }

    fn infer(&mut self, input: &BatchTensor, out: &mut [LandmarkOut]) -> Result<(), EngineError> {
        let n = input.len();
        if n == 0 {
            return Ok(());
        }
        if n > self.max_batch || out.len() < n {
            return Err(EngineError::BatchTooLarge {
                len: n,
                max: self.max_batch.min(out.len()),
            });
        }
        let s = self.info.crop_size;
        let l = self.info.landmark_count;
        let tensor = ort::value::TensorRef::from_array_view(([n, 1, s, s], input.as_slice()))?;
        let outputs = self.session.run(ort::inputs![tensor])?;
        let bad = |what: &str| EngineError::BadOutput(what.to_owned());
        let (lm_shape, lm) = outputs
            .get(OUTPUT_LANDMARKS)
            .ok_or_else(|| bad("no landmarks"))?
            .try_extract_tensor::<f32>()?;
        let (_, prob) = outputs
            .get(OUTPUT_FACE_PROB)
            .ok_or_else(|| bad("no face_prob"))?
            .try_extract_tensor::<f32>()?;
        if lm.len() != n * l * 2 || prob.len() != n {
            return Err(bad(&format!(
                "landmarks shape {:?}, {} face_prob",
                &**lm_shape,
                prob.len()
            )));
        }
        for ((slot, pts), p) in out.iter_mut().zip(lm.chunks_exact(l * 2)).zip(prob) {
            slot.landmarks.clear();
            slot.landmarks.extend(pts.chunks_exact(2).map(|xy| {
                [
                    xy.first().copied().unwrap_or(0.0),
                    xy.get(1).copied().unwrap_or(0.0),
                ]
            }));
            slot.face_prob = *p;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn directories_are_not_called_missing_files() {
        let dir = std::env::temp_dir();
        let opts = OnnxOptions {
            model: dir.clone(),
            ort_dylib: "/nonexistent/libonnxruntime.so".into(),
            intra_threads: 1,
            max_batch: 1,
            provider: Provider::Cpu,
            spin: false,
        };
        let e = OnnxEngine::load(&opts).unwrap_err().to_string();
        assert!(e.contains("is a directory") && !e.contains("not found"), "{e}");
        let e = load_runtime(&dir).unwrap_err().to_string();
        assert!(e.contains("is a directory") && !e.contains("not found"), "{e}");
    }

    #[test]
    fn missing_runtime_and_model_are_clear_errors() {
        let opts = OnnxOptions {
            model: "/nonexistent/dan.onnx".into(),
            ort_dylib: "/nonexistent/libonnxruntime.so".into(),
            intra_threads: 1,
            max_batch: 1,
            provider: Provider::Cpu,
            spin: false,
        };
        let e = OnnxEngine::load(&opts).unwrap_err().to_string();
        assert!(
            e.contains("DAN model not found at /nonexistent/dan.onnx (the path given)"),
            "{e}"
        );
        let e = load_runtime(Path::new("/nonexistent/libonnxruntime.so"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("ONNX Runtime library not found") && e.contains("ORT_DYLIB_PATH"),
            "{e}"
        );
    }
}
