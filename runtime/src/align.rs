//! Interchangeable landmark aligners: the tracker, the evaluation tool and the demo all call [`Aligner`].
//!
//! * [`KrfwsAligner`], the headset's own (51 points, with its failure detector).
//! * The remote aligner (`crate::link::LinkedAligner`) sends the crop cut by [`crop_from_image`] over QUIC
//!   and maps the answer back with [`landmarks_from_crop`]; the tools' in-process DAN does the same locally.

use holoface_inference::EngineError;
use holoface_models::adapt::Appearance;
use holoface_models::crop::{Crop112, blank_outside};
use holoface_models::geometry::{Point2, Rect, Similarity2};
use holoface_models::image::GrayView;
use serde::Serialize;
use thiserror::Error;

/// Which landmarks an alignment fills.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LandmarkSet {
    /// All 68 iBUG points.
    Ibug68,
    /// The 51 inner points (iBUG 17..=67); the jaw slots hold the initial shape.
    Inner51,
}

/// The aligner's own verdict on its result.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Confidence {
    /// DAN's face/no-face head: probability that the crop holds an aligned face (higher is better).
    FaceProbability(f32),
    /// KRFWS failure detector: predicted landmark error (lower is better).
    PredictedError(f32),
}

/// Which aligner produced an alignment.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AnsweredBy {
    /// DAN in this process (evaluation, `holoface track --aligner dan`).
    LocalDan,
    /// DAN on the alignment server, over QUIC.
    RemoteDan,
    /// KRFWS on the headset.
    Krfws,
}

impl AnsweredBy {
    /// The snake_case name, as serde writes it (per-frame JSON, the Python module).
    pub const fn name(self) -> &'static str {
        match self {
            Self::LocalDan => "local_dan",
            Self::RemoteDan => "remote_dan",
            Self::Krfws => "krfws",
        }
    }
}

/// The per-person adaptation's state for one face in one frame ([`crate::adapt`]; here, with the alignment
/// that carries it).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct AdaptState {
    /// Pairs (local and remote answer of one frame) learnt for this face so far.
    pub pairs: u32,
    /// Whether this frame's landmarks are a corrected local answer.
    pub corrected: bool,
    /// The size of the face's correction: its mean length over the 51 inner points, in eye distances, the
    /// last time it was computed (0 before enough pairs).
    pub correction: f32,
}

/// Result of one alignment, in image pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Alignment {
    /// Landmarks in image pixels.
    pub landmarks: [Point2; 68],
    /// Which of them the aligner produced.
    pub set: LandmarkSet,
    /// The aligner's confidence signal.
    pub confidence: Confidence,
    /// Whether the confidence passes the aligner's threshold (a face is tracked).
    pub accepted: bool,
    /// Which aligner answered.
    pub answered_by: AnsweredBy,
    /// The per-person adaptation's state for this face ([`crate::adapt`]); `None` when it is off or the
    /// face has no id yet.
    pub adaptation: Option<AdaptState>,
}

/// Errors of an aligner.
#[derive(Debug, Error)]
#[non_exhaustive]
pub enum AlignError {
    /// The initial shape is degenerate (all points equal or not finite).
    #[error("initial shape is degenerate")]
    DegenerateInit,
    /// The crop could not be cut.
    #[error("crop: {0}")]
    Crop(#[from] holoface_models::crop::CropError),
    /// The inference engine failed.
    #[error("inference: {0}")]
    Engine(#[from] EngineError),
    /// The model's output is unusable.
    #[error("model output: {0}")]
    BadOutput(String),
}

/// Aligns landmarks in a frame starting from an initial 68-point shape (image pixels).
pub trait Aligner {
    /// Short name for reports (`dan`, `krfws`).
    fn name(&self) -> &'static str;
    /// Aligns one face.
    fn align(&mut self, image: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError>;

    /// Aligns a face whose initial shape was placed on a detector's box rather than carried over from
    /// the previous frame. A coarser start: an aligner may spend more work here (KRFWS runs several
    /// starts). Default: [`Aligner::align`].
    fn align_detection(
        &mut self,
        image: &GrayView<'_>,
        init: &[Point2; 68],
    ) -> Result<Alignment, AlignError> {
        self.align(image, init)
    }

    /// What the aligner sees around the 51 inner points of `landmarks` (image pixels), for the per-person
    /// adaptation ([`crate::adapt`]: KRFWS's HOG there, pooled); `None` when it has no such description (the
    /// default) or the shape is degenerate.
    fn appearance(&mut self, image: &GrayView<'_>, landmarks: &[Point2; 68]) -> Option<Box<Appearance>> {
        let _ = (image, landmarks);
        None
    }

    /// Aligns every face of one frame: one answer per candidate, in order. Default: one after another
    /// ([`align_from`]); the remote aligner sends every face's crop at once and waits once.
    fn align_faces(
        &mut self,
        image: &GrayView<'_>,
        faces: &[Candidate],
    ) -> Result<Vec<Alignment>, AlignError> {
        faces
            .iter()
            .map(|c| align_from(self, image, &c.init, c.source))
            .collect()
    }
}

/// Where the initial shape of a frame came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum InitSource {
    /// A fresh detection.
    Detection,
    /// The previous frame's landmarks (motion-compensated when enabled).
    Tracking,
}

impl InitSource {
    /// The snake_case name, as serde writes it.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Detection => "detection",
            Self::Tracking => "tracking",
        }
    }
}

/// One face to align in a frame: a tracked face (its id) or a new detection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// The tracked face's id; `None` for a new detection (it gets an id when its alignment is accepted).
    pub track: Option<u32>,
    /// Initial 68-point shape (image pixels).
    pub init: [Point2; 68],
    /// Where it came from.
    pub source: InitSource,
}

/// Aligns from a prepared initial shape: [`Aligner::align_detection`] after a detection,
/// [`Aligner::align`] when tracking.
pub fn align_from(
    aligner: &mut (impl Aligner + ?Sized),
    image: &GrayView<'_>,
    init: &[Point2; 68],
    source: InitSource,
) -> Result<Alignment, AlignError> {
    match source {
        InitSource::Detection => aligner.align_detection(image, init),
        InitSource::Tracking => aligner.align(image, init),
    }
}

/// Each face's own region in a frame with several: its initial landmarks' box grown by this fraction on
/// every side (the start may sit a little off the face).
const OWN_MARGIN: f32 = 0.10;
/// Each other face's region: its initial landmarks' box grown by this fraction on every side (cheeks and
/// forehead beyond the landmarks; hair and ears farther out are left).
const OTHER_MARGIN: f32 = 0.15;

/// What to blank out of one face's DAN crop when the frame has several: the other faces' regions, minus
/// the face's own ([`blank_outside`]). DAN, trained on one face per crop, otherwise drifts toward a
/// neighbour inside its crop.
#[derive(Clone, Debug, PartialEq)]
pub struct Neighbours {
    keep: Rect,
    others: Vec<Rect>,
}

impl Neighbours {
    /// For face `i` of `faces`; `None` when it is alone (or its start has no extent).
    pub fn of(faces: &[Candidate], i: usize) -> Option<Self> {
        let keep = Rect::bounding(&faces.get(i)?.init)?.grown(OWN_MARGIN);
        let others: Vec<Rect> = faces
            .iter()
            .enumerate()
            .filter(|&(j, _)| j != i)
            .filter_map(|(_, f)| Rect::bounding(&f.init).map(|r| r.grown(OTHER_MARGIN)))
            .collect();
        (!others.is_empty()).then_some(Self { keep, others })
    }

    /// Blanks the other faces out of `crop` (made through `crop_from_image`).
    pub fn blank(&self, crop: &mut Crop112, crop_from_image: &Similarity2) {
        blank_outside(crop, crop_from_image, &self.keep, &self.others);
    }
}

/// The similarity that maps `init` onto the canonical crop shape.
pub fn crop_from_image(init: &[Point2; 68], canonical: &[Point2; 68]) -> Result<Similarity2, AlignError> {
    if init.iter().any(|p| !p.x.is_finite() || !p.y.is_finite()) {
        return Err(AlignError::DegenerateInit);
    }
    Similarity2::fit(init, canonical).ok_or(AlignError::DegenerateInit)
}

/// Maps DAN's crop-pixel landmarks back to the image and applies the face threshold.
pub fn landmarks_from_crop(
    crop_landmarks: &[[f32; 2]],
    face_prob: f32,
    crop_from_image: &Similarity2,
    threshold: f32,
) -> Result<Alignment, AlignError> {
    if crop_landmarks.len() != 68 {
        return Err(AlignError::BadOutput(format!(
            "{} landmarks, expected 68",
            crop_landmarks.len()
        )));
    }
    let image_from_crop = crop_from_image.inverse().ok_or(AlignError::DegenerateInit)?;
    let landmarks = std::array::from_fn(|i| {
        image_from_crop.apply(Point2::new(crop_landmarks[i][0], crop_landmarks[i][1]))
    });
    Ok(Alignment {
        landmarks,
        set: LandmarkSet::Ibug68,
        confidence: Confidence::FaceProbability(face_prob),
        accepted: face_prob >= threshold,
        answered_by: AnsweredBy::LocalDan,
        adaptation: None,
    })
}

/// KRFWS on the headset: 51 inner landmarks plus the failure detector's predicted error.
#[derive(Debug)]
pub struct KrfwsAligner {
    model: holoface_models::krfws::Krfws,
    scratch: holoface_models::krfws::KrfwsScratch,
    restarts: usize,
}

/// Starts KRFWS runs on a detection frame (see [`holoface_models::krfws::Krfws::align_restarts`]).
pub const KRFWS_DETECTION_STARTS: usize = 13;

impl KrfwsAligner {
    /// Wraps a loaded model.
    pub fn new(model: holoface_models::krfws::Krfws) -> Self {
        Self {
            model,
            scratch: holoface_models::krfws::KrfwsScratch::new(),
            restarts: KRFWS_DETECTION_STARTS,
        }
    }

    /// Sets the number of starts on detection frames (1 = a single alignment).
    pub fn set_detection_starts(&mut self, starts: usize) {
        self.restarts = starts.max(1);
    }

    fn run(
        &mut self,
        image: &GrayView<'_>,
        init: &[Point2; 68],
        starts: usize,
    ) -> Result<Alignment, AlignError> {
        if init.iter().any(|p| !p.x.is_finite() || !p.y.is_finite()) {
            return Err(AlignError::DegenerateInit);
        }
        let start: [Point2; 51] = std::array::from_fn(|i| init[17 + i]);
        let mut out = start;
        let score = self
            .model
            .align_restarts(image, &start, starts, &mut self.scratch, &mut out);
        let mut landmarks = *init;
        landmarks[17..].copy_from_slice(&out);
        Ok(Alignment {
            landmarks,
            set: LandmarkSet::Inner51,
            confidence: Confidence::PredictedError(score),
            accepted: score < self.model.threshold(),
            answered_by: AnsweredBy::Krfws,
            adaptation: None,
        })
    }
}

impl Aligner for KrfwsAligner {
    fn name(&self) -> &'static str {
        "krfws"
    }

    fn align(&mut self, image: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
        self.run(image, init, 1)
    }

    fn appearance(&mut self, image: &GrayView<'_>, landmarks: &[Point2; 68]) -> Option<Box<Appearance>> {
        let inner: [Point2; 51] = std::array::from_fn(|i| landmarks[17 + i]);
        if inner.iter().any(|p| !p.x.is_finite() || !p.y.is_finite()) {
            return None;
        }
        self.model
            .hog_at(image, &inner, &mut self.scratch)
            .then(|| holoface_models::adapt::pool_hog(self.scratch.last_hog()))
            .flatten()
    }

    fn align_detection(
        &mut self,
        image: &GrayView<'_>,
        init: &[Point2; 68],
    ) -> Result<Alignment, AlignError> {
        self.run(image, init, self.restarts)
    }
}
