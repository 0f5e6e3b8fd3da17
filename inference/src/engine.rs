//! The inference engine: a trait, the ONNX Runtime implementation and (for
//! tests only) a deterministic fake.
//!
//! The engine is synchronous and owned by one dedicated thread (the
//! server's engine thread); the server copies each batch's crops into a preallocated
//! [`BatchTensor`] (`[max_batch, 1, S, S]` u8) and the engine writes into
//! caller-allocated [`LandmarkOut`]s.
//!
//! # Model contract (models/dan/export_onnx.py)
//!
//! * input `pixels`: uint8 `[N, 1, S, S]`, dynamic `N`;
//! * outputs `landmarks`: float32 `[N, L, 2]` in crop pixels, and
//!   `face_prob`: float32 `[N]`;
//! * metadata `holoface.name`, `holoface.version`, `holoface.landmarks` (L),
//!   `holoface.crop_size` (S), `holoface.mean_shape` (JSON list of L `[x, y]`),
//!   `holoface.face_threshold`; optional `holoface.licence`,
//!   `holoface.untrained`, `holoface.precision` (`fp32` when absent; `fp16` for
//!   `models/dan/to_fp16.py`'s half-precision graph, same inputs and outputs).
//!
//! Everything is checked at load ([`validate_io`], [`ModelInfo::from_metadata`])
//! with an error that names the offending tensor, dimension or key.

use std::path::PathBuf;

use holoface_protocol::limits::{MAX_LANDMARKS, MAX_NAME_LEN};

pub use crate::error::EngineError;
use crate::runtime::load_runtime;

/// Name of the model's input tensor.
pub const INPUT_PIXELS: &str = "pixels";
/// Name of the landmark output.
pub const OUTPUT_LANDMARKS: &str = "landmarks";
/// Name of the face-probability output.
pub const OUTPUT_FACE_PROB: &str = "face_prob";

/// What the model is, from its metadata; the server sends most of it to
/// clients in `ServerWelcome`.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelInfo {
    /// `holoface.name`.
    pub name: String,
    /// `holoface.version`.
    pub version: String,
    /// `holoface.landmarks` (L).
    pub landmark_count: usize,
    /// `holoface.crop_size` (S).
    pub crop_size: usize,
    /// `holoface.mean_shape`: L points in crop pixels.
    pub mean_shape: Vec<[f32; 2]>,
    /// `holoface.face_threshold`.
    pub face_threshold: f32,
    /// `holoface.licence`, if present.
    pub licence: Option<String>,
    /// `holoface.untrained == "true"` (a random-weights development model).
    pub untrained: bool,
    /// `holoface.precision`: the arithmetic inside the graph (`fp32` when absent, `fp16`); the inputs and
    /// outputs are the contract's either way.
    pub precision: String,
}

impl ModelInfo {
    /// Parses and checks the `holoface.*` metadata; `get` returns a key's value.
    pub fn from_metadata(get: impl Fn(&str) -> Option<String>) -> Result<Self, EngineError> {
        let req = |key: &'static str| {
            get(key).ok_or(EngineError::BadMetadata {
                key,
                problem: "missing".into(),
            })
        };
        let parse_usize = |key: &'static str| -> Result<usize, EngineError> {
            let v = req(key)?;
            v.trim().parse().map_err(|_| EngineError::BadMetadata {
                key,
                problem: format!("{v:?} is not a positive integer"),
            })
        };
        let name = req("holoface.name")?;
        let version = req("holoface.version")?;
        for (key, v) in [("holoface.name", &name), ("holoface.version", &version)] {
            if v.is_empty() || v.len() > MAX_NAME_LEN {
                return Err(EngineError::BadMetadata {
                    key,
                    problem: format!("length {} outside 1..={MAX_NAME_LEN}", v.len()),
                });
            }
        }
        let landmark_count = parse_usize("holoface.landmarks")?;
        if landmark_count == 0 || landmark_count > MAX_LANDMARKS {
            return Err(EngineError::BadMetadata {
                key: "holoface.landmarks",
                problem: format!("{landmark_count} outside 1..={MAX_LANDMARKS}"),
            });
        }
        let crop_size = parse_usize("holoface.crop_size")?;
        if crop_size == 0 || crop_size > usize::from(holoface_protocol::limits::MAX_CROP_DIM) {
            return Err(EngineError::BadMetadata {
                key: "holoface.crop_size",
                problem: format!("{crop_size} is not a usable crop size"),
            });
        }
        let shape_text = req("holoface.mean_shape")?;
        let mean_shape: Vec<[f32; 2]> =
            serde_json::from_str(&shape_text).map_err(|e| EngineError::BadMetadata {
                key: "holoface.mean_shape",
                problem: format!("not a JSON list of [x, y] pairs: {e}"),
            })?;
        if mean_shape.len() != landmark_count {
            return Err(EngineError::BadMetadata {
                key: "holoface.mean_shape",
                problem: format!(
                    "{} points, but holoface.landmarks says {landmark_count}",
                    mean_shape.len()
                ),
            });
        }
        if mean_shape.iter().flatten().any(|v| !v.is_finite()) {
            return Err(EngineError::BadMetadata {
                key: "holoface.mean_shape",
                problem: "non-finite coordinate".into(),
            });
        }
        let thr = req("holoface.face_threshold")?;
        let face_threshold: f32 =
            thr.trim()
                .parse()
                .ok()
                .filter(|t: &f32| t.is_finite())
                .ok_or(EngineError::BadMetadata {
                    key: "holoface.face_threshold",
                    problem: format!("{thr:?} is not a finite number"),
                })?;
        let precision = get("holoface.precision").map_or_else(|| "fp32".to_owned(), |v| v.trim().to_owned());
        if !matches!(precision.as_str(), "fp32" | "fp16") {
            return Err(EngineError::BadMetadata {
                key: "holoface.precision",
                problem: format!("{precision:?} is neither \"fp32\" nor \"fp16\""),
            });
        }
        Ok(Self {
            name,
            version,
            landmark_count,
            crop_size,
            mean_shape,
            face_threshold,
            licence: get("holoface.licence"),
            untrained: get("holoface.untrained").is_some_and(|v| v.trim() == "true"),
            precision,
        })
    }

    /// Bytes in one crop (S * S).
    pub const fn crop_pixels(&self) -> usize {
        self.crop_size * self.crop_size
    }
}

/// Element type of a model tensor, as far as the contract cares.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ElemType {
    /// uint8.
    U8,
    /// float32.
    F32,
    /// Anything else (its name, for the error message).
    Other(String),
}

/// A model input or output as declared in the graph (`-1` = dynamic).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TensorSpec {
    /// Tensor name.
    pub name: String,
    /// Element type; `None` for a non-tensor value.
    pub elem: Option<ElemType>,
    /// Declared dimensions.
    pub shape: Vec<i64>,
}

/// Checks the model's inputs and outputs against the contract and `info`.
pub fn validate_io(
    inputs: &[TensorSpec],
    outputs: &[TensorSpec],
    info: &ModelInfo,
) -> Result<(), EngineError> {
    let s = i64::try_from(info.crop_size).unwrap_or(i64::MAX);
    let l = i64::try_from(info.landmark_count).unwrap_or(i64::MAX);
    let bad = |tensor: &str, problem: String| EngineError::BadModelIo {
        tensor: tensor.to_owned(),
        problem,
    };
    if inputs.len() != 1 {
        let names: Vec<&str> = inputs.iter().map(|t| t.name.as_str()).collect();
        return Err(bad(
            "inputs",
            format!("expected exactly one input `{INPUT_PIXELS}`, found {names:?}"),
        ));
    }
    check_tensor(inputs, INPUT_PIXELS, &ElemType::U8, &[-1, 1, s, s], "input", &bad)?;
    check_tensor(
        outputs,
        OUTPUT_LANDMARKS,
        &ElemType::F32,
        &[-1, l, 2],
        "output",
        &bad,
    )?;
    check_tensor(outputs, OUTPUT_FACE_PROB, &ElemType::F32, &[-1], "output", &bad)?;
    Ok(())
}

fn check_tensor(
    list: &[TensorSpec],
    name: &str,
    elem: &ElemType,
    want: &[i64],
    kind: &str,
    bad: &impl Fn(&str, String) -> EngineError,
) -> Result<(), EngineError> {
    let Some(t) = list.iter().find(|t| t.name == name) else {
        let names: Vec<&str> = list.iter().map(|t| t.name.as_str()).collect();
        return Err(bad(name, format!("missing {kind} (the model has {names:?})")));
    };
    match &t.elem {
        Some(e) if e == elem => {}
        other => return Err(bad(name, format!("element type {other:?}, expected {elem:?}"))),
    }
    if t.shape.len() != want.len() {
        return Err(bad(
            name,
            format!(
                "shape {:?} has rank {}, expected {want:?}",
                t.shape,
                t.shape.len()
            ),
        ));
    }
    for (i, (got, exp)) in t.shape.iter().zip(want).enumerate() {
        // Dimension 0 is the batch: dynamic (-1) is required for batching.
        let ok = if i == 0 { *got < 0 } else { got == exp || *got < 0 };
        if !ok {
            let what = if i == 0 {
                "the batch dimension must be dynamic".to_owned()
            } else {
                format!("expected {exp}")
            };
            return Err(bad(
                name,
                format!(
                    "dimension {i} is {got} in {:?}: {what} (wanted {want:?})",
                    t.shape
                ),
            ));
        }
    }
    Ok(())
}

/// A preallocated `[max_batch, 1, S, S]` u8 input batch.
#[derive(Debug, Clone)]
pub struct BatchTensor {
    crop_pixels: usize,
    max_batch: usize,
    data: Vec<u8>,
    len: usize,
}

impl BatchTensor {
    /// Room for `max_batch` crops of `crop_pixels` bytes, allocated once.
    pub fn new(max_batch: usize, crop_pixels: usize) -> Self {
        Self {
            crop_pixels,
            max_batch,
            data: vec![0; max_batch * crop_pixels],
            len: 0,
        }
    }

    /// Empties the batch (keeps the allocation).
    pub const fn clear(&mut self) {
        self.len = 0;
    }

    /// Crops in the batch.
    pub const fn len(&self) -> usize {
        self.len
    }

    /// `true` when empty.
    pub const fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Bytes per crop.
    pub const fn crop_pixels(&self) -> usize {
        self.crop_pixels
    }

    /// Copies one gray8 crop (S * S bytes) into the next slot.
    pub fn push(&mut self, crop: &[u8]) -> Result<(), EngineError> {
        if crop.len() != self.crop_pixels {
            return Err(EngineError::CropSize {
                len: crop.len(),
                expected: self.crop_pixels,
            });
        }
        let start = self.len * self.crop_pixels;
        let slot = self
            .data
            .get_mut(start..start + self.crop_pixels)
            .ok_or(EngineError::BatchTooLarge {
                len: self.len + 1,
                max: self.max_batch,
            })?;
        slot.copy_from_slice(crop);
        self.len += 1;
        Ok(())
    }

    /// The filled part: `len * S * S` bytes, crop after crop.
    pub fn as_slice(&self) -> &[u8] {
        self.data.get(..self.len * self.crop_pixels).unwrap_or_default()
    }
}

/// One frame's result, written by the engine into a caller-owned slot.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LandmarkOut {
    /// L points in crop pixels.
    pub landmarks: Vec<[f32; 2]>,
    /// Face probability.
    pub face_prob: f32,
}

impl LandmarkOut {
    /// Why this result cannot be sent as landmarks, if it cannot: a landmark count other than the model
    /// declares, a non-finite coordinate, or a face probability that is not a probability.
    pub fn problem(&self, landmark_count: usize) -> Option<String> {
        if self.landmarks.len() != landmark_count {
            return Some(format!(
                "{} landmarks, the model declares {landmark_count}",
                self.landmarks.len()
            ));
        }
        if let Some(i) = self
            .landmarks
            .iter()
            .position(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Some(format!("landmark {i} is {:?}", self.landmarks[i]));
        }
        // A softmax output, allowing for its rounding.
        if !(-1e-4..=1.0 + 1e-4).contains(&self.face_prob) {
            return Some(format!("face probability {}", self.face_prob));
        }
        None
    }
}

/// A synchronous batch inference engine.
pub trait InferenceEngine: Send {
    /// The model's description.
    fn info(&self) -> &ModelInfo;
    /// Largest batch `infer` accepts.
    fn max_batch(&self) -> usize;
    /// Runs `input` (`input.len()` crops) and fills `out[..input.len()]`.
    fn infer(&mut self, input: &BatchTensor, out: &mut [LandmarkOut]) -> Result<(), EngineError>;
    /// The refinement cascade that follows the model, if any (its identity, for logs and metrics).
    fn refiner(&self) -> Option<&str> {
        None
    }
    /// What the refinement cascade did on the last batch (`None` without one).
    fn last_refinement(&self) -> Option<crate::refine::Refinement> {
        None
    }
    /// What runs the model (the execution provider, and why it is not the requested one if it is not).
    fn execution(&self) -> Execution {
        Execution {
            provider: "in-process engine".into(),
            device: None,
            fallback: None,
        }
    }
}

impl std::fmt::Debug for dyn InferenceEngine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "InferenceEngine({} {})", self.info().name, self.info().version)
    }
}

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

/// What actually runs a loaded engine's model.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Execution {
    /// The execution provider's ONNX Runtime name (`CPUExecutionProvider`, `CUDAExecutionProvider`), or the
    /// test engine's name.
    pub provider: String,
    /// The GPU ordinal, when the provider is a GPU's.
    pub device: Option<i32>,
    /// Why the requested provider is not the one running (the CPU took over), if it is not.
    pub fallback: Option<String>,
}

impl Execution {
    /// The CPU execution provider, as asked.
    pub fn cpu() -> Self {
        Self {
            provider: CPU_PROVIDER.into(),
            device: None,
            fallback: None,
        }
    }
}

impl std::fmt::Display for Execution {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.provider)?;
        if let Some(d) = self.device {
            write!(f, " (device {d})")?;
        }
        if let Some(why) = &self.fallback {
            write!(f, ", falling back from the requested provider: {why}")?;
        }
        Ok(())
    }
}

/// ONNX Runtime's name of its CPU execution provider.
pub const CPU_PROVIDER: &str = "CPUExecutionProvider";
/// ONNX Runtime's name of its CUDA execution provider.
pub const CUDA_PROVIDER: &str = "CUDAExecutionProvider";

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
            return Err(EngineError::ModelMissing {
                path: opts.model.clone(),
            });
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
    crate::files::read_bounded(path, crate::home::DAN.max_bytes, crate::home::DAN.name).map_err(|e| match e {
        crate::files::FileError::Missing { .. } => EngineError::ModelMissing {
            path: path.to_path_buf(),
        },
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

/// A deterministic stand-in for unit tests: landmarks are the mean shape
/// shifted by the crop's first pixel / 16, face probability is the mean
/// pixel / 255.
#[cfg(any(test, feature = "test-util"))]
#[derive(Debug)]
pub struct FakeEngine {
    info: ModelInfo,
    max_batch: usize,
    /// Batches run so far (length of each).
    pub batches: Vec<usize>,
}

#[cfg(any(test, feature = "test-util"))]
impl FakeEngine {
    /// A fake 68-point, 112-pixel model.
    pub fn new(max_batch: usize) -> Self {
        let mean_shape = (0..68)
            .map(|i| [20.0 + (i % 17) as f32 * 4.0, 30.0 + (i / 17) as f32 * 15.0])
            .collect();
        Self {
            info: ModelInfo {
                name: "fake".into(),
                version: "0".into(),
                landmark_count: 68,
                crop_size: 112,
                mean_shape,
                face_threshold: 0.5,
                licence: None,
                untrained: true,
                precision: "fp32".into(),
            },
            max_batch,
            batches: Vec::new(),
        }
    }
}

#[cfg(any(test, feature = "test-util"))]
impl InferenceEngine for FakeEngine {
    fn info(&self) -> &ModelInfo {
        &self.info
    }

    fn max_batch(&self) -> usize {
        self.max_batch
    }

    fn infer(&mut self, input: &BatchTensor, out: &mut [LandmarkOut]) -> Result<(), EngineError> {
        let n = input.len();
        if n > self.max_batch || out.len() < n {
            return Err(EngineError::BatchTooLarge {
                len: n,
                max: self.max_batch,
            });
        }
        self.batches.push(n);
        for (crop, slot) in input
            .as_slice()
            .chunks_exact(input.crop_pixels())
            .zip(out.iter_mut())
        {
            let shift = f32::from(crop.first().copied().unwrap_or(0)) / 16.0;
            let mean = crop.iter().map(|p| f32::from(*p)).sum::<f32>() / crop.len() as f32;
            slot.landmarks.clear();
            slot.landmarks
                .extend(self.info.mean_shape.iter().map(|[x, y]| [x + shift, y + shift]));
            slot.face_prob = mean / 255.0;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;
    use std::path::Path;

    fn meta() -> HashMap<&'static str, String> {
        let shape: Vec<[f32; 2]> = (0..68).map(|i| [i as f32, 1.0]).collect();
        HashMap::from([
            ("holoface.name", "dan".to_owned()),
            ("holoface.version", "1".to_owned()),
            ("holoface.landmarks", "68".to_owned()),
            ("holoface.crop_size", "112".to_owned()),
            ("holoface.mean_shape", serde_json::to_string(&shape).unwrap()),
            ("holoface.face_threshold", "0.5".to_owned()),
            ("holoface.untrained", "true".to_owned()),
        ])
    }

    fn info_of(m: &HashMap<&'static str, String>) -> Result<ModelInfo, EngineError> {
        ModelInfo::from_metadata(|k| m.get(k).cloned())
    }

    fn good_io() -> (Vec<TensorSpec>, Vec<TensorSpec>) {
        let t = |name: &str, elem, shape: &[i64]| TensorSpec {
            name: name.into(),
            elem: Some(elem),
            shape: shape.to_vec(),
        };
        (
            vec![t("pixels", ElemType::U8, &[-1, 1, 112, 112])],
            vec![
                t("landmarks", ElemType::F32, &[-1, 68, 2]),
                t("face_prob", ElemType::F32, &[-1]),
            ],
        )
    }

    #[test]
    fn metadata_parses() {
        let info = info_of(&meta()).unwrap();
        assert_eq!(info.landmark_count, 68);
        assert_eq!(info.crop_size, 112);
        assert_eq!(info.mean_shape[3], [3.0, 1.0]);
        assert_eq!(info.face_threshold, 0.5);
        assert!(info.untrained);
        assert_eq!(info.licence, None);
        assert_eq!(info.precision, "fp32", "absent means fp32");
        let mut m = meta();
        m.insert("holoface.precision", "fp16".into());
        assert_eq!(info_of(&m).unwrap().precision, "fp16");
    }

    #[test]
    fn metadata_errors_name_the_key() {
        let mut m = meta();
        m.remove("holoface.mean_shape");
        assert!(
            info_of(&m)
                .unwrap_err()
                .to_string()
                .contains("holoface.mean_shape: missing")
        );
        let mut m = meta();
        m.insert("holoface.mean_shape", "[[1,2]]".into());
        let e = info_of(&m).unwrap_err().to_string();
        assert!(e.contains("1 points, but holoface.landmarks says 68"), "{e}");
        let mut m = meta();
        m.insert("holoface.face_threshold", "NaN".into());
        assert!(info_of(&m).unwrap_err().to_string().contains("face_threshold"));
        let mut m = meta();
        m.insert("holoface.precision", "int4".into());
        let e = info_of(&m).unwrap_err().to_string();
        assert!(e.contains("holoface.precision") && e.contains("int4"), "{e}");
        let mut m = meta();
        m.insert("holoface.landmarks", "500".into());
        assert!(
            info_of(&m)
                .unwrap_err()
                .to_string()
                .contains("holoface.landmarks")
        );
    }

    #[test]
    fn io_contract_accepts_the_dan_export() {
        let info = info_of(&meta()).unwrap();
        let (i, o) = good_io();
        validate_io(&i, &o, &info).unwrap();
    }

    #[test]
    fn io_contract_errors_say_what_is_wrong() {
        let info = info_of(&meta()).unwrap();
        let (mut i, o) = good_io();
        i[0].shape = vec![-1, 3, 112, 112];
        let e = validate_io(&i, &o, &info).unwrap_err().to_string();
        assert!(e.contains("pixels") && e.contains("dimension 1 is 3"), "{e}");

        let (mut i, o) = good_io();
        i[0].shape = vec![1, 1, 112, 112];
        let e = validate_io(&i, &o, &info).unwrap_err().to_string();
        assert!(e.contains("batch dimension must be dynamic"), "{e}");

        let (mut i, o) = good_io();
        i[0].elem = Some(ElemType::F32);
        let e = validate_io(&i, &o, &info).unwrap_err().to_string();
        assert!(e.contains("pixels") && e.contains("element type"), "{e}");

        let (i, mut o) = good_io();
        o[0].shape = vec![-1, 51, 2];
        let e = validate_io(&i, &o, &info).unwrap_err().to_string();
        assert!(e.contains("landmarks") && e.contains("expected 68"), "{e}");

        let (i, mut o) = good_io();
        o.pop();
        let e = validate_io(&i, &o, &info).unwrap_err().to_string();
        assert!(e.contains("face_prob: missing output"), "{e}");

        let (mut i, o) = good_io();
        i[0].name = "input".into();
        let e = validate_io(&i, &o, &info).unwrap_err().to_string();
        assert!(e.contains("pixels: missing input"), "{e}");
    }

    #[test]
    fn batch_tensor_is_reused() {
        let mut b = BatchTensor::new(2, 4);
        b.push(&[1, 2, 3, 4]).unwrap();
        b.push(&[5, 6, 7, 8]).unwrap();
        assert!(matches!(b.push(&[0; 4]), Err(EngineError::BatchTooLarge { .. })));
        assert!(matches!(b.push(&[0; 3]), Err(EngineError::CropSize { .. })));
        assert_eq!(b.as_slice(), &[1, 2, 3, 4, 5, 6, 7, 8]);
        b.clear();
        assert!(b.is_empty());
        b.push(&[9; 4]).unwrap();
        assert_eq!(b.as_slice(), &[9; 4]);
    }

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
            e.contains("DAN model not found at /nonexistent/dan.onnx") && e.contains("engine.model"),
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

    #[test]
    fn fake_engine_is_deterministic() {
        let mut e = FakeEngine::new(4);
        let mut b = BatchTensor::new(4, 112 * 112);
        b.push(&[32; 112 * 112]).unwrap();
        let mut out = vec![LandmarkOut::default(); 4];
        e.infer(&b, &mut out).unwrap();
        assert_eq!(out[0].landmarks[0], [22.0, 32.0]);
        assert!((out[0].face_prob - 32.0 / 255.0).abs() < 1e-6);
        assert_eq!(e.batches, vec![1]);
    }
}
