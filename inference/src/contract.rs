//! The model contract every engine meets, whatever runs it: the [`InferenceEngine`] trait, the batch it
//! takes ([`BatchTensor`]), what it writes ([`LandmarkOut`]), the model's description ([`ModelInfo`]) and the
//! checks of a graph's inputs and outputs ([`validate_io`]). The ONNX Runtime engine is [`crate::onnx`], the
//! refinement cascade that follows DAN [`crate::cascade`], the tests' fake `crate::fake` (feature `test-util`).
//!
//! The engine is synchronous and owned by one dedicated thread (the server's engine thread); the server copies
//! each batch's crops into a preallocated [`BatchTensor`] (`[max_batch, 1, S, S]` u8) and the engine writes
//! into caller-allocated [`LandmarkOut`]s.
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
//!   `models/dan/to_fp16.py`'s half-precision graph, `int8` for `models/dan/to_int8.py`'s quantised one; same
//!   inputs and outputs).
//!
//! Everything is checked at load ([`validate_io`], [`ModelInfo::from_metadata`])
//! with an error that names the offending tensor, dimension or key.

use std::time::Duration;

use holoface_protocol::limits::{MAX_LANDMARKS, MAX_NAME_LEN};

use crate::error::EngineError;

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
    /// `holoface.precision`: the arithmetic inside the graph (`fp32` when absent, `fp16`, `int8`); the inputs and
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
        // The server's welcome names the release with its precision ("0.4.0+int8", within MAX_NAME_LEN).
        for (key, v, max) in [
            ("holoface.name", &name, MAX_NAME_LEN),
            ("holoface.version", &version, MAX_NAME_LEN - "+fp32".len()),
        ] {
            if v.is_empty() || v.len() > max {
                return Err(EngineError::BadMetadata {
                    key,
                    problem: format!("length {} outside 1..={max}", v.len()),
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
        if !matches!(precision.as_str(), "fp32" | "fp16" | "int8") {
            return Err(EngineError::BadMetadata {
                key: "holoface.precision",
                problem: format!("{precision:?} is none of \"fp32\", \"fp16\", \"int8\""),
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
    fn last_refinement(&self) -> Option<CascadeStats> {
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

/// What the refinement cascade did on an engine's last batch ([`InferenceEngine::last_refinement`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CascadeStats {
    /// Crops refined (the others failed the face threshold or had unusable output).
    pub crops: usize,
    /// Time spent refining them.
    pub elapsed: Duration,
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

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
        m.insert("holoface.precision", "int8".into());
        assert_eq!(info_of(&m).unwrap().precision, "int8");
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
}
