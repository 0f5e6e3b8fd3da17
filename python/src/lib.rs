//! Python bindings of the headset client's task API ([`holoface_headset_client::FaceTracker`]): `FaceTracker(options)`,
//! `process(image, timestamp_us, camera_to_world=None, intrinsics=None) -> FaceResult`, numpy in and out.
//!
//! Images are borrowed, not copied: a C-contiguous `uint8` array of shape `(height, width)` becomes the
//! frame's pixels directly, and the GIL is released while the frame is processed (another Python thread can
//! run meanwhile; calls on one tracker from two threads are serialised by its lock, never raced). Every error is a
//! Python exception carrying the Rust message; nothing here panics on bad input.
// PyO3's macros expand to unsafe code (the CPython ABI); this crate writes none of its own.
#![allow(unsafe_code)]

mod installed;
mod sources;
use sources::{PyFrameSource, PySourceFrame};

use std::path::PathBuf;
use std::sync::{Mutex, PoisonError};

use holoface_headset_client::geometry::default_intrinsics;
use holoface_headset_client::geometry::{Quat, Vec3};
use holoface_headset_client::link::LinkState;
use holoface_headset_client::options::{AdaptOptions, SteadySettings};
use holoface_headset_client::results::AnsweredBy;
use holoface_headset_client::{self as tracker, AlignerChoice, RunningMode, TrackerError};
use holoface_headset_client::{Frame, OwnedFrame};
use holoface_headset_client::{GrayView, Intrinsics, Pose};
use holoface_headset_client::{RemoteOptions, defaults};
use holoface_sources::FrameSource;
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArrayDescrMethods, PyArrayMethods, PyUntypedArray};
use numpy::{PyUntypedArrayMethods, ToPyArray};
use pyo3::exceptions::{PyException, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;

pyo3::create_exception!(
    _holoface,
    HoloFaceError,
    PyException,
    "Base class of holoface's errors."
);
pyo3::create_exception!(
    _holoface,
    AssetError,
    HoloFaceError,
    "A model file or the ONNX Runtime library could not be loaded (the message names it)."
);
pyo3::create_exception!(
    _holoface,
    ProcessingError,
    HoloFaceError,
    "Processing a frame failed (detector or aligner error, or a timestamp out of order)."
);
pyo3::create_exception!(
    _holoface,
    SourceError,
    HoloFaceError,
    "A frame source could not be opened or read (corrupt, truncated or missing file)."
);

/// Largest image side accepted (the C API's bound too).
const MAX_SIDE: usize = 16_384;

/// Tracker options; every field has the Rust API's default.
#[pyclass(
    module = "holoface",
    name = "TrackerOptions",
    get_all,
    set_all,
    from_py_object
)]
#[derive(Clone, Debug)]
struct PyTrackerOptions {
    /// "video" (track between frames; timestamps must increase) or "image" (detect every frame).
    mode: String,
    /// Alignment server "ip:port"; None = local KRFWS only.
    server: Option<String>,
    /// SHA-256 of the server certificate (64 hex digits, printed by holoface-server); required with server.
    fingerprint: Option<String>,
    /// Access token for the server.
    token: String,
    /// Per-frame deadline for the server's answer, milliseconds.
    deadline_ms: u64,
    /// Crop encoding on the wire: "raw", "png", "jpeg" or "jpeg:Q".
    crop_encoding: String,
    /// With a server: while the link is up, the local aligner learns each tracked person's correction towards
    /// the server's answers and applies it when the link is down.
    adapt: bool,
    /// Prediction horizon, milliseconds.
    lookahead_ms: f64,
    /// Compensate headset motion when initialising from the previous frame.
    motion_compensation: bool,
    /// Most faces tracked at once (1..=64), each with a stable id.
    max_faces: usize,
    /// While some but fewer than max_faces faces are tracked, run the detector every this many frames (>= 1).
    detect_every: u32,
    /// Detector tiles per side besides the whole frame (1..=32); None: 1 for one face, 3 for several.
    detect_tiles: Option<usize>,
    /// Steady the landmarks over time (One-Euro in the face's frame); False: landmarks == raw_landmarks.
    steady: bool,
    /// Local aligner's answers: shape cut-off at rest, Hz.
    steady_shape_cutoff_hz: f64,
    /// Local aligner's answers: shape speed coefficient.
    steady_shape_beta: f64,
    /// Local aligner's answers: placement cut-off at rest, Hz.
    steady_rigid_cutoff_hz: f64,
    /// Local aligner's answers: placement speed coefficient.
    steady_rigid_beta: f64,
    /// The server's answers: shape cut-off at rest, Hz.
    steady_precise_shape_cutoff_hz: f64,
    /// The server's answers: shape speed coefficient.
    steady_precise_shape_beta: f64,
    /// The server's answers: placement cut-off at rest, Hz.
    steady_precise_rigid_cutoff_hz: f64,
    /// The server's answers: placement speed coefficient.
    steady_precise_rigid_beta: f64,
    /// ONNX Runtime shared library (default: $ORT_DYLIB_PATH, then the `onnxruntime` package's).
    ort_dylib: Option<PathBuf>,
    /// BlazeFace ONNX model (default: $HOLOFACE_DETECTOR_MODEL, then the wheel's own copy).
    detector_model: Option<PathBuf>,
    /// KRFWS model (default: $HOLOFACE_KRFWS_MODEL, then the wheel's own copy).
    krfws_model: Option<PathBuf>,
    /// CANDIDE-3 .wfm (default: $HOLOFACE_CANDIDE, then candide3.wfm in `holoface.data_dir()`).
    candide: Option<PathBuf>,
}

#[pymethods]
impl PyTrackerOptions {
    // The defaults are the runtime's (`holoface_headset_client::defaults`, `SteadySettings::default`), as in
    // C's `hf_options_default`/`hf_settings_default` and the CLI's flags.
    #[new]
    #[pyo3(signature = (*, mode = mode_name(tracker::TrackerOptions::default().mode).to_owned(), server = None, fingerprint = None, token = String::new(),
        deadline_ms = defaults::DEADLINE_MS, crop_encoding = defaults::CROP_ENCODING.to_owned(),
        adapt = defaults::ADAPT, lookahead_ms = defaults::LOOKAHEAD_MS, motion_compensation = defaults::MOTION_COMPENSATION,
        max_faces = defaults::MAX_FACES, detect_every = defaults::DETECT_EVERY, detect_tiles = None,
        steady = defaults::STEADY, steady_shape_cutoff_hz = SteadySettings::default().shape_cutoff_hz,
        steady_shape_beta = SteadySettings::default().shape_beta,
        steady_rigid_cutoff_hz = SteadySettings::default().rigid_cutoff_hz,
        steady_rigid_beta = SteadySettings::default().rigid_beta,
        steady_precise_shape_cutoff_hz = SteadySettings::default().precise_shape_cutoff_hz,
        steady_precise_shape_beta = SteadySettings::default().precise_shape_beta,
        steady_precise_rigid_cutoff_hz = SteadySettings::default().precise_rigid_cutoff_hz,
        steady_precise_rigid_beta = SteadySettings::default().precise_rigid_beta,
        ort_dylib = None, detector_model = None, krfws_model = None, candide = None))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        mode: String,
        server: Option<String>,
        fingerprint: Option<String>,
        token: String,
        deadline_ms: u64,
        crop_encoding: String,
        adapt: bool,
        lookahead_ms: f64,
        motion_compensation: bool,
        max_faces: usize,
        detect_every: u32,
        detect_tiles: Option<usize>,
        steady: bool,
        steady_shape_cutoff_hz: f64,
        steady_shape_beta: f64,
        steady_rigid_cutoff_hz: f64,
        steady_rigid_beta: f64,
        steady_precise_shape_cutoff_hz: f64,
        steady_precise_shape_beta: f64,
        steady_precise_rigid_cutoff_hz: f64,
        steady_precise_rigid_beta: f64,
        ort_dylib: Option<PathBuf>,
        detector_model: Option<PathBuf>,
        krfws_model: Option<PathBuf>,
        candide: Option<PathBuf>,
    ) -> Self {
        Self {
            mode,
            server,
            fingerprint,
            token,
            deadline_ms,
            crop_encoding,
            adapt,
            lookahead_ms,
            motion_compensation,
            max_faces,
            detect_every,
            detect_tiles,
            steady,
            steady_shape_cutoff_hz,
            steady_shape_beta,
            steady_rigid_cutoff_hz,
            steady_rigid_beta,
            steady_precise_shape_cutoff_hz,
            steady_precise_shape_beta,
            steady_precise_rigid_cutoff_hz,
            steady_precise_rigid_beta,
            ort_dylib,
            detector_model,
            krfws_model,
            candide,
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "TrackerOptions(mode={:?}, server={:?}, deadline_ms={}, lookahead_ms={}, motion_compensation={}, \
             max_faces={}, detect_every={}, detect_tiles={:?}, steady={})",
            self.mode,
            self.server,
            self.deadline_ms,
            self.lookahead_ms,
            self.motion_compensation,
            self.max_faces,
            self.detect_every,
            self.detect_tiles,
            self.steady
        )
    }
}

impl Default for PyTrackerOptions {
    fn default() -> Self {
        let st = SteadySettings::default();
        Self::new(
            "video".to_owned(),
            None,
            None,
            String::new(),
            defaults::DEADLINE_MS,
            defaults::CROP_ENCODING.to_owned(),
            defaults::ADAPT,
            defaults::LOOKAHEAD_MS,
            defaults::MOTION_COMPENSATION,
            defaults::MAX_FACES,
            defaults::DETECT_EVERY,
            None,
            st.enabled,
            st.shape_cutoff_hz,
            st.shape_beta,
            st.rigid_cutoff_hz,
            st.rigid_beta,
            st.precise_shape_cutoff_hz,
            st.precise_shape_beta,
            st.precise_rigid_cutoff_hz,
            st.precise_rigid_beta,
            None,
            None,
            None,
            None,
        )
    }
}

/// This module's name of a running mode (a live stream is tracked as a video).
fn mode_name(mode: RunningMode) -> &'static str {
    match mode {
        RunningMode::Image => "image",
        RunningMode::Video | RunningMode::LiveStream => "video",
    }
}

impl PyTrackerOptions {
    fn to_rust(&self, py: Python<'_>) -> PyResult<tracker::TrackerOptions> {
        let mode = match self.mode.as_str() {
            "video" => RunningMode::Video,
            "image" => RunningMode::Image,
            m => {
                return Err(PyValueError::new_err(format!(
                    "mode {m:?}: use \"video\" (track between frames) or \"image\" (detect every frame)"
                )));
            }
        };
        let mut o = tracker::TrackerOptions {
            mode,
            ..tracker::TrackerOptions::default()
        };
        o.session.lookahead_s = self.lookahead_ms / 1e3;
        o.session.motion_compensation = self.motion_compensation;
        o.session.max_faces = self.max_faces;
        o.session.detect_every = self.detect_every;
        o.session.steady = SteadySettings {
            enabled: self.steady,
            shape_cutoff_hz: self.steady_shape_cutoff_hz,
            shape_beta: self.steady_shape_beta,
            rigid_cutoff_hz: self.steady_rigid_cutoff_hz,
            rigid_beta: self.steady_rigid_beta,
            precise_shape_cutoff_hz: self.steady_precise_shape_cutoff_hz,
            precise_shape_beta: self.steady_precise_shape_beta,
            precise_rigid_cutoff_hz: self.steady_precise_rigid_cutoff_hz,
            precise_rigid_beta: self.steady_precise_rigid_beta,
        };
        o.detector.tiles = self.detect_tiles;
        o.detector
            .validate()
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        o.session
            .validate()
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let paths = [
            (&self.ort_dylib, &mut o.assets.ort_dylib),
            (&self.detector_model, &mut o.assets.detector),
            (&self.krfws_model, &mut o.assets.krfws),
            (&self.candide, &mut o.assets.candide),
        ];
        for (given, slot) in paths {
            if let Some(p) = given {
                slot.clone_from(p);
            }
        }
        installed::resolve(py, self, &mut o.assets)?;
        if let Some(server) = &self.server {
            let remote = RemoteOptions::parse(
                server,
                self.fingerprint.as_deref(),
                &self.token,
                self.deadline_ms,
                Some(&self.crop_encoding),
            )
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
            o.aligner = AlignerChoice::Remote(RemoteOptions {
                adapt: self.adapt.then(AdaptOptions::default),
                ..remote
            });
        }
        Ok(o)
    }
}

/// One tracked face. Landmarks are image pixels; `camera_pose` is head-to-camera (x right, y down, z forward,
/// metres); `world_pose`, `predicted_position` and `display_pose` are in the world frame of the
/// `camera_to_world` poses passed to `process`.
#[pyclass(module = "holoface", name = "Face", frozen, get_all)]
#[derive(Debug)]
struct PyFace {
    /// The face's track id: the same for as long as it is tracked, never reused by this tracker.
    id: u32,
    /// float32 array [68, 2]: the iBUG-68 landmarks in image pixels, steadied over time (what to draw).
    landmarks: Py<PyArray2<f32>>,
    /// float32 array [68, 2]: the aligner's own landmarks for this frame, unfiltered.
    raw_landmarks: Py<PyArray2<f32>>,
    /// "ibug68" (all 68 aligned) or "inner51" (KRFWS: the jaw slots hold the initial shape).
    landmark_set: String,
    /// "remote_dan", "krfws" or "local_dan".
    answered_by: String,
    /// "detection" or "tracking": where this frame's initial shape came from.
    init: String,
    /// The remote DAN's face probability (higher is better), else None.
    face_probability: Option<f32>,
    /// KRFWS's predicted landmark error (lower is better), else None.
    predicted_error: Option<f32>,
    /// float64 [4, 4]: head-to-camera transform (CANDIDE-3 fit).
    camera_pose: Py<PyArray2<f64>>,
    /// Reprojection error of the CANDIDE-3 fit, pixels.
    fit_rmse_px: f64,
    /// float64 [4, 4]: head-to-world transform.
    world_pose: Py<PyArray2<f64>>,
    /// float64 [3]: world position predicted `lookahead_ms` ahead (Kalman), metres.
    predicted_position: Py<PyArray1<f64>>,
    /// float64 [4, 4]: the pose to render (prediction after two-frame denoising).
    display_pose: Py<PyArray2<f64>>,
    /// CANDIDE-3 expression weights by unit name (jaw_drop, lip_stretcher, brow_lowerer, ...).
    expression_weights: Py<PyDict>,
    /// Smiling (lip stretcher above its threshold, with hysteresis).
    smile: bool,
    /// Brows raised.
    brows_raised: bool,
    /// Mouth open.
    mouth_open: bool,
    /// float32 [39]: ARKit-named blendshape coefficients in [0, 1], in `holoface.BLENDSHAPE_NAMES` order
    /// (against this person's neutral, calibrated on the first second of tracking).
    blendshapes: Py<PyArray1<f32>>,
    /// With a server and `adapt`: pairs of local and server answers learnt for this face (0 otherwise).
    adapt_pairs: u32,
    /// These landmarks are the local aligner's answer corrected by what it learnt from the server.
    adapt_corrected: bool,
    /// The size of this face's correction: its mean length over the 51 inner points, in eye distances.
    adapt_correction: f32,
}

#[pymethods]
impl PyFace {
    fn __repr__(&self) -> String {
        format!(
            "Face(id={}, answered_by={:?}, init={:?}, smile={}, brows_raised={}, mouth_open={})",
            self.id, self.answered_by, self.init, self.smile, self.brows_raised, self.mouth_open
        )
    }
}

/// One frame's answer: the faces (empty when there is none) or why there is none.
#[pyclass(module = "holoface", name = "FaceResult", frozen, get_all)]
#[derive(Debug)]
struct PyFaceResult {
    /// The frame's timestamp, microseconds.
    timestamp_us: u64,
    /// Every face of the frame, oldest track first (at most `TrackerOptions.max_faces`).
    faces: Vec<Py<PyFace>>,
    /// Without a face: "not_detected", "rejected", "no_answer" or "fit_failed"; None with a face.
    no_face_reason: Option<String>,
    /// Which aligner answered ("remote_dan", "krfws", "local_dan"), None when nothing was aligned.
    answered_by: Option<String>,
    /// With a server: "connecting", "up", "retrying", "failed" or "stopped"; None without one.
    link_state: Option<String>,
    /// Why the link is not up ("unreachable", "unauthorized", "certificate_mismatch", ...), else None.
    link_failure: Option<String>,
    /// Milliseconds per step: prepare (detection or motion-compensated init), align, complete (fit, pose,
    /// filters).
    timings: Py<PyDict>,
}

#[pymethods]
impl PyFaceResult {
    /// The first face, or None.
    #[getter]
    fn face(&self, py: Python<'_>) -> Option<Py<PyFace>> {
        self.faces.first().map(|f| f.clone_ref(py))
    }

    /// True when the frame has a face.
    #[getter]
    fn has_face(&self) -> bool {
        !self.faces.is_empty()
    }

    fn __repr__(&self) -> String {
        match &self.no_face_reason {
            None => format!(
                "FaceResult(timestamp_us={}, faces={}, answered_by={:?})",
                self.timestamp_us,
                self.faces.len(),
                self.answered_by
            ),
            Some(r) => format!(
                "FaceResult(timestamp_us={}, faces=0, no_face_reason={r:?})",
                self.timestamp_us
            ),
        }
    }
}

fn link_names(state: LinkState) -> (String, Option<String>) {
    match state {
        LinkState::Connecting => ("connecting".to_owned(), None),
        LinkState::Up => ("up".to_owned(), None),
        LinkState::Retrying(k) => ("retrying".to_owned(), Some(k.name().to_owned())),
        LinkState::Failed(k) => ("failed".to_owned(), Some(k.name().to_owned())),
        LinkState::Stopped => ("stopped".to_owned(), None),
    }
}

fn matrix4(py: Python<'_>, rotation: Quat, translation: Vec3) -> Py<PyArray2<f64>> {
    let r = rotation.to_mat3().0;
    let t = translation.to_array();
    let mut m = Array2::<f64>::eye(4);
    for i in 0..3 {
        for j in 0..3 {
            m[[i, j]] = r[i][j];
        }
        m[[i, 3]] = t[i];
    }
    m.into_pyarray(py).unbind()
}

fn face_to_py(py: Python<'_>, u: &tracker::FaceResult) -> PyResult<PyFace> {
    let mut lm = Array2::<f32>::zeros((68, 2));
    let mut raw = Array2::<f32>::zeros((68, 2));
    for (i, (p, r)) in u.landmarks.iter().zip(&u.raw_landmarks).enumerate() {
        lm[[i, 0]] = p.x;
        lm[[i, 1]] = p.y;
        raw[[i, 0]] = r.x;
        raw[[i, 1]] = r.y;
    }
    let weights = PyDict::new(py);
    for (unit, w) in u.expression.iter() {
        weights.set_item(unit.name(), w)?;
    }
    let (face_probability, predicted_error) = match u.confidence {
        holoface_headset_client::results::Confidence::FaceProbability(p) => (Some(p), None),
        holoface_headset_client::results::Confidence::PredictedError(e) => (None, Some(e)),
    };
    Ok(PyFace {
        id: u.id,
        landmarks: lm.into_pyarray(py).unbind(),
        raw_landmarks: raw.into_pyarray(py).unbind(),
        landmark_set: match u.landmark_set {
            holoface_headset_client::results::LandmarkSet::Ibug68 => "ibug68",
            holoface_headset_client::results::LandmarkSet::Inner51 => "inner51",
        }
        .to_owned(),
        answered_by: u.answered_by.name().to_owned(),
        init: u.init.name().to_owned(),
        face_probability,
        predicted_error,
        camera_pose: matrix4(py, u.fit.rotation, u.fit.translation),
        fit_rmse_px: u.fit.rmse_px,
        world_pose: matrix4(py, u.world.rotation, u.world.position),
        predicted_position: u.predicted_position.to_array().to_pyarray(py).unbind(),
        display_pose: matrix4(py, u.display.1, u.display.0),
        blendshapes: u.blendshapes.0.to_pyarray(py).unbind(),
        expression_weights: weights.unbind(),
        smile: u.attributes.smile,
        brows_raised: u.attributes.brows_raised,
        mouth_open: u.attributes.mouth_open,
        adapt_pairs: u.adaptation.map_or(0, |a| a.pairs),
        adapt_corrected: u.adaptation.is_some_and(|a| a.corrected),
        adapt_correction: u.adaptation.map_or(0.0, |a| a.correction),
    })
}

fn result_to_py(py: Python<'_>, r: &tracker::FrameResult) -> PyResult<PyFaceResult> {
    let faces = r
        .faces
        .iter()
        .map(|f| Py::new(py, face_to_py(py, f)?))
        .collect::<PyResult<Vec<_>>>()?;
    let no_face_reason = r.no_face.map(|reason| reason.name().to_owned());
    let (link_state, link_failure) = match r.link.map(link_names) {
        Some((s, f)) => (Some(s), f),
        None => (None, None),
    };
    let timings = PyDict::new(py);
    timings.set_item("prepare_ms", r.timings.prepare.as_secs_f64() * 1e3)?;
    timings.set_item("align_ms", r.timings.align.as_secs_f64() * 1e3)?;
    timings.set_item("complete_ms", r.timings.complete.as_secs_f64() * 1e3)?;
    Ok(PyFaceResult {
        timestamp_us: r.timestamp_us,
        faces,
        no_face_reason,
        answered_by: r.answered_by.map(|a: AnsweredBy| a.name().to_owned()),
        link_state,
        link_failure,
        timings: timings.unbind(),
    })
}

/// `camera_to_world`: any 4x4 nested sequence or array of numbers (row-major, last row ignored).
fn pose_from_py(m: &Bound<'_, PyAny>) -> PyResult<Pose> {
    let rows: Vec<Vec<f64>> = m
        .extract()
        .map_err(|_| PyTypeError::new_err("camera_to_world must be a 4x4 array of numbers"))?;
    if rows.len() != 4 || rows.iter().any(|r| r.len() != 4) {
        return Err(PyValueError::new_err(format!(
            "camera_to_world must be 4x4, got {} rows of lengths {:?}",
            rows.len(),
            rows.iter().map(Vec::len).collect::<Vec<_>>()
        )));
    }
    let mut flat = [0f32; 16];
    for (o, v) in flat.iter_mut().zip(rows.iter().flatten()) {
        *o = *v as f32;
    }
    Pose::from_row_major_4x4(&flat).ok_or_else(|| {
        PyValueError::new_err(
            "camera_to_world is not a rigid transform (finite, rotation block orthonormal, determinant +1)",
        )
    })
}

fn intrinsics_from_py(v: Option<(f64, f64, f64, f64)>, width: usize, height: usize) -> PyResult<Intrinsics> {
    let Some((fx, fy, cx, cy)) = v else {
        return Ok(default_intrinsics(width, height));
    };
    if ![fx, fy, cx, cy].iter().all(|v| v.is_finite()) || fx <= 0.0 || fy <= 0.0 {
        return Err(PyValueError::new_err(
            "intrinsics (fx, fy, cx, cy) must be finite with fx, fy > 0",
        ));
    }
    Ok(Intrinsics::new(fx, fy, cx, cy))
}

/// Checks an image argument: a C-contiguous uint8 numpy array of shape (height, width).
fn gray_array<'a, 'py>(image: &'a Bound<'py, PyAny>) -> PyResult<&'a Bound<'py, PyArray2<u8>>> {
    let untyped = image.cast::<PyUntypedArray>().map_err(|_| {
        PyTypeError::new_err(format!(
            "image must be a numpy array (uint8, shape (height, width)), got {}",
            image
                .get_type()
                .name()
                .map_or_else(|_| "?".to_owned(), |n| n.to_string())
        ))
    })?;
    let dtype = untyped.dtype();
    if !dtype.is_equiv_to(&numpy::dtype::<u8>(image.py())) {
        return Err(PyTypeError::new_err(format!(
            "image must be uint8 grayscale, got dtype {}",
            dtype.str().map_or_else(|_| "?".to_owned(), |s| s.to_string())
        )));
    }
    if untyped.ndim() != 2 {
        return Err(PyValueError::new_err(format!(
            "image must have shape (height, width) (grayscale), got shape {:?}",
            untyped.shape()
        )));
    }
    let (h, w) = (untyped.shape()[0], untyped.shape()[1]);
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE {
        return Err(PyValueError::new_err(format!(
            "image {w}x{h}: each side must be within 1..={MAX_SIDE}"
        )));
    }
    if !untyped.is_c_contiguous() {
        return Err(PyValueError::new_err(
            "image must be C-contiguous (pass numpy.ascontiguousarray(image))",
        ));
    }
    image
        .cast::<PyArray2<u8>>()
        .map_err(|_| PyTypeError::new_err("image must be a uint8 array"))
}

/// This module's names for the files a tracker loads, in its messages.
const PY_OPTIONS: &[(holoface_headset_client::assets::Asset, &str)] = &[
    (
        holoface_headset_client::assets::home::ORT_LIBRARY,
        "TrackerOptions.ort_dylib",
    ),
    (
        holoface_headset_client::assets::home::DETECTOR,
        "TrackerOptions.detector_model",
    ),
    (
        holoface_headset_client::assets::home::KRFWS,
        "TrackerOptions.krfws_model",
    ),
    (
        holoface_headset_client::assets::home::CANDIDE,
        "TrackerOptions.candide",
    ),
];

fn tracker_error(e: TrackerError) -> PyErr {
    match e {
        TrackerError::Asset(_) => AssetError::new_err(e.to_string()),
        TrackerError::Timestamp { .. }
        | TrackerError::TimestampJump { .. }
        | TrackerError::CameraDistance { .. }
        | TrackerError::Options(_) => PyValueError::new_err(e.to_string()),
        _ => ProcessingError::new_err(e.to_string()),
    }
}

/// Detects, aligns, fits and filters a face frame by frame. Calls from several threads are serialised (one
/// frame at a time, without the GIL); create one tracker per stream.
#[pyclass(module = "holoface", name = "FaceTracker")]
#[derive(Debug)]
struct PyFaceTracker {
    inner: Mutex<Option<tracker::FaceTracker>>,
}

/// (state, failure kind, failure message) of the server link.
type LinkStatusTuple = (String, Option<String>, Option<String>);

const CLOSED: &str = "the tracker is closed";

#[pymethods]
impl PyFaceTracker {
    /// Loads the models and, with a server, starts connecting in the background.
    #[new]
    #[pyo3(signature = (options = None))]
    fn new(py: Python<'_>, options: Option<PyTrackerOptions>) -> PyResult<Self> {
        let opts = options.unwrap_or_default().to_rust(py)?;
        let inner = py
            .detach(|| tracker::FaceTracker::new(opts))
            .map_err(|e| e.given_by(PY_OPTIONS))
            .map_err(|e| match e {
                TrackerError::Detect(_) | TrackerError::Asset(_) => AssetError::new_err(e.to_string()),
                other => tracker_error(other),
            })?;
        Ok(Self {
            inner: Mutex::new(Some(inner)),
        })
    }

    /// Processes one frame: `image` a C-contiguous uint8 array (height, width); `timestamp_us` increasing
    /// in video mode; `camera_to_world` the headset camera's 4x4 pose (None = identity, a fixed camera);
    /// `intrinsics` (fx, fy, cx, cy) in pixels (None = 60 degree horizontal field of view, centred).
    #[pyo3(signature = (image, timestamp_us, camera_to_world = None, intrinsics = None))]
    fn process(
        &self,
        py: Python<'_>,
        image: &Bound<'_, PyAny>,
        timestamp_us: u64,
        camera_to_world: Option<&Bound<'_, PyAny>>,
        intrinsics: Option<(f64, f64, f64, f64)>,
    ) -> PyResult<PyFaceResult> {
        let array = gray_array(image)?;
        let readonly = array
            .try_readonly()
            .map_err(|e| PyValueError::new_err(format!("image: {e}")))?;
        let pixels = readonly
            .as_slice()
            .map_err(|e| PyValueError::new_err(format!("image: {e}")))?;
        let (h, w) = (readonly.shape()[0], readonly.shape()[1]);
        let view =
            GrayView::new(pixels, w, h, w).map_err(|e| PyValueError::new_err(format!("image: {e}")))?;
        let pose = camera_to_world
            .map(pose_from_py)
            .transpose()?
            .unwrap_or(Pose::IDENTITY);
        let frame = Frame {
            timestamp_us,
            image: view,
            intrinsics: intrinsics_from_py(intrinsics, w, h)?,
            world_from_camera: pose,
        };
        let result = py.detach(|| {
            let mut guard = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
            guard.as_mut().map(|t| t.process(&frame))
        });
        let result = result
            .ok_or_else(|| PyValueError::new_err(CLOSED))?
            .map_err(tracker_error)?;
        result_to_py(py, &result)
    }

    /// With a server: (state, failure, message) of the link, e.g. ("up", None, None) or
    /// ("failed", "unauthorized", "the server rejected the token ..."); None without a server.
    fn link_status(&self) -> PyResult<Option<LinkStatusTuple>> {
        let guard = self.inner.lock().unwrap_or_else(PoisonError::into_inner);
        let tracker = guard.as_ref().ok_or_else(|| PyValueError::new_err(CLOSED))?;
        Ok(tracker.link_status().map(|s| {
            let (state, failure) = link_names(s.state());
            (state, failure, s.failure().map(ToString::to_string))
        }))
    }

    /// Releases the models and closes the server link; further calls raise.
    fn close(&self, py: Python<'_>) {
        py.detach(|| {
            let taken = self.inner.lock().unwrap_or_else(PoisonError::into_inner).take();
            drop(taken);
        });
    }

    fn __enter__(slf: Py<Self>) -> Py<Self> {
        slf
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, py: Python<'_>, _args: &Bound<'_, pyo3::types::PyTuple>) {
        self.close(py);
    }
}

/// The extension module; the `holoface` package re-exports it.
#[pymodule]
fn _holoface(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add_class::<PyTrackerOptions>()?;
    m.add_class::<PyFaceTracker>()?;
    m.add_class::<PyFaceResult>()?;
    m.add_class::<PyFace>()?;
    m.add_class::<PyFrameSource>()?;
    m.add_class::<PySourceFrame>()?;
    m.add_function(wrap_pyfunction!(sources::read_gray, m)?)?;
    m.add_function(wrap_pyfunction!(installed::install_candide, m)?)?;
    m.add_function(wrap_pyfunction!(installed::data_dir, m)?)?;
    m.add(
        "BLENDSHAPE_NAMES",
        holoface_headset_client::results::Blendshape::ALL
            .iter()
            .map(|b| b.arkit_name())
            .collect::<Vec<_>>(),
    )?;
    // The runtime's defaults, defined once (`holoface_headset_client::defaults`): the tests compare
    // `TrackerOptions()` and the type stub with them.
    let d = PyDict::new(py);
    d.set_item("deadline_ms", defaults::DEADLINE_MS)?;
    d.set_item("crop_encoding", defaults::CROP_ENCODING)?;
    d.set_item("adapt", defaults::ADAPT)?;
    d.set_item("lookahead_ms", defaults::LOOKAHEAD_MS)?;
    d.set_item("motion_compensation", defaults::MOTION_COMPENSATION)?;
    d.set_item("max_faces", defaults::MAX_FACES)?;
    d.set_item("detect_every", defaults::DETECT_EVERY)?;
    d.set_item("steady", defaults::STEADY)?;
    d.set_item("mode", mode_name(tracker::TrackerOptions::default().mode))?;
    let s = SteadySettings::default();
    for (name, value) in [
        ("steady_shape_cutoff_hz", s.shape_cutoff_hz),
        ("steady_shape_beta", s.shape_beta),
        ("steady_rigid_cutoff_hz", s.rigid_cutoff_hz),
        ("steady_rigid_beta", s.rigid_beta),
        ("steady_precise_shape_cutoff_hz", s.precise_shape_cutoff_hz),
        ("steady_precise_shape_beta", s.precise_shape_beta),
        ("steady_precise_rigid_cutoff_hz", s.precise_rigid_cutoff_hz),
        ("steady_precise_rigid_beta", s.precise_rigid_beta),
    ] {
        d.set_item(name, value)?;
    }
    m.add("DEFAULTS", d)?;
    m.add("HoloFaceError", py.get_type::<HoloFaceError>())?;
    m.add("AssetError", py.get_type::<AssetError>())?;
    m.add("ProcessingError", py.get_type::<ProcessingError>())?;
    m.add("SourceError", py.get_type::<SourceError>())?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
