//! The tracker session: an IO-free state machine that turns frames into per-frame face results.
//!
//! Call order per frame (the aligner runs in between, locally or over the network):
//!
//! 1. [`TrackerSession::prepare_faces`] decides between detection and tracking and returns one candidate
//!    per face: its previous landmarks moved with the headset (motion compensation), or the mean shape
//!    placed on a fresh detection; none when nothing is tracked and the detector finds nothing.
//! 2. The caller aligns each candidate with any [`crate::align::Aligner`] (KRFWS on the headset, DAN over
//!    QUIC) or gives up on it (`None`, e.g. the link missed its deadline and no local aligner).
//! 3. [`TrackerSession::complete_faces`] verifies each alignment with the aligner's own signal, fits
//!    CANDIDE-3, converts to a world pose, predicts it ahead with the Kalman filters, denoises, derives
//!    attributes, and updates the tracks. Every frame gets a [`SessionFrame`]: its faces, or an explicit "no
//!    face" with the reason ([`SessionFrame::first`] is the one-face view).
//!
//! The session never reads a clock: time comes from the frames' timestamps. The three steps are driven in one
//! place, [`crate::frame_step::step_faces`]; call that rather than writing the sequence out again.

pub use holoface_models::blendshapes::{Blendshape, BlendshapeParams, Blendshapes};
use holoface_models::blendshapes::{BlendshapeEstimator, HeadTurn};
use holoface_models::camera::Intrinsics;
use holoface_models::candide::{FaceModel, FitOptions, FitResult, fit};
use holoface_models::expression::ExpressionWeights;
use holoface_models::geometry::{Point2, Rect, Similarity2};
use holoface_models::kalman::{Denoiser, KalmanParams, PositionPredictor};
use holoface_models::math3::{Pose, Quat, Vec3};
use holoface_models::pose::{
    AttributeThresholds, Attributes, WorldPose, compensate_headset_motion, world_pose,
};
use holoface_models::shape::OUTER_EYE_CORNERS;
use holoface_models::steady::SteadyParams;
use holoface_models::steady::{LandmarkFilter, Source};
use serde::Serialize;

pub use crate::align::InitSource;
use crate::align::{Alignment, Confidence, LandmarkSet};
use crate::detect::{DetectError, FaceDetector, shape_from_detection};
use crate::frame::Frame;

/// Tracker settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SessionOptions {
    /// CANDIDE fit settings for a warm-started frame.
    pub fit: FitOptions,
    /// Kalman filter parameters.
    pub kalman: KalmanParams,
    /// How far ahead the rendered position is predicted (seconds; HoloFace: 0.12).
    pub lookahead_s: f64,
    /// Attribute thresholds.
    pub attributes: AttributeThresholds,
    /// Apply headset-motion compensation to the tracking initialisation.
    pub motion_compensation: bool,
    /// Most faces tracked at once (at least 1). With 1 (the default) the tracker follows one face and
    /// detects only while it has none, as before multi-face tracking.
    pub max_faces: usize,
    /// While at least one face but fewer than `max_faces` are tracked, the detector runs every this many
    /// frames to find the others (at least 1); with no face tracked it runs on every frame.
    pub detect_every: u32,
    /// The landmark filter (One-Euro, in the face's own frame; [`holoface_models::steady`]): what
    /// [`FaceResult::landmarks`] shows, and what CANDIDE-3 is fitted to. `enabled: false` turns it off
    /// (then `landmarks` equals `raw_landmarks`). It only acts across frames, so still images are unaffected.
    pub steady: SteadySettings,
    /// Blendshape coefficients: how long a track's first frames calibrate the person's neutral.
    pub blendshapes: BlendshapeParams,
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            fit: FitOptions {
                max_iterations: 3,
                ..FitOptions::default()
            },
            kalman: KalmanParams::default(),
            lookahead_s: crate::defaults::LOOKAHEAD_MS / 1e3,
            attributes: AttributeThresholds::default(),
            motion_compensation: crate::defaults::MOTION_COMPENSATION,
            max_faces: crate::defaults::MAX_FACES,
            detect_every: crate::defaults::DETECT_EVERY,
            steady: SteadySettings::default(),
            blendshapes: BlendshapeParams::default(),
        }
    }
}

/// The landmark filter's settings, the one steadying type of the API, flat and by name as every binding offers
/// them (the CLI's `--no-steady` and `--steady-*` flags, Python's `steady*` options, C's `HfSettings.steady*`):
/// whether it runs, and the One-Euro cut-off at rest and speed coefficient of the face's shape and of its
/// placement (translation, scale, rotation), for the local aligner's noisy answers and for the server's precise
/// ones. The filter's other constants (speed cut-offs, the fade after an aligner switch, the longest gap) are
/// `holoface_models::steady::SteadyParams::default`'s, as are these defaults.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SteadySettings {
    /// The filter is on ([`crate::defaults::STEADY`]).
    pub enabled: bool,
    /// Local aligner's answers: shape cut-off at rest, Hz.
    pub shape_cutoff_hz: f64,
    /// Local aligner's answers: shape speed coefficient (per eye distance per second).
    pub shape_beta: f64,
    /// Local aligner's answers: placement cut-off at rest, Hz.
    pub rigid_cutoff_hz: f64,
    /// Local aligner's answers: placement speed coefficient.
    pub rigid_beta: f64,
    /// The server's (and DAN's) answers: shape cut-off at rest, Hz.
    pub precise_shape_cutoff_hz: f64,
    /// The server's answers: shape speed coefficient.
    pub precise_shape_beta: f64,
    /// The server's answers: placement cut-off at rest, Hz.
    pub precise_rigid_cutoff_hz: f64,
    /// The server's answers: placement speed coefficient.
    pub precise_rigid_beta: f64,
}

impl Default for SteadySettings {
    fn default() -> Self {
        let p = SteadyParams::default();
        Self {
            enabled: crate::defaults::STEADY,
            shape_cutoff_hz: p.noisy.shape.min_cutoff_hz,
            shape_beta: p.noisy.shape.beta,
            rigid_cutoff_hz: p.noisy.rigid.min_cutoff_hz,
            rigid_beta: p.noisy.rigid.beta,
            precise_shape_cutoff_hz: p.precise.shape.min_cutoff_hz,
            precise_shape_beta: p.precise.shape.beta,
            precise_rigid_cutoff_hz: p.precise.rigid.min_cutoff_hz,
            precise_rigid_beta: p.precise.rigid.beta,
        }
    }
}

impl SteadySettings {
    /// The filter's parameters: `None` when off; the other constants (speed cut-offs, fade, gap) are the
    /// defaults'. [`SessionOptions::validate`] checks the values.
    pub(crate) fn params(&self) -> Option<SteadyParams> {
        let mut p = SteadyParams::default();
        p.noisy.shape.min_cutoff_hz = self.shape_cutoff_hz;
        p.noisy.shape.beta = self.shape_beta;
        p.noisy.rigid.min_cutoff_hz = self.rigid_cutoff_hz;
        p.noisy.rigid.beta = self.rigid_beta;
        p.precise.shape.min_cutoff_hz = self.precise_shape_cutoff_hz;
        p.precise.shape.beta = self.precise_shape_beta;
        p.precise.rigid.min_cutoff_hz = self.precise_rigid_cutoff_hz;
        p.precise.rigid.beta = self.precise_rigid_beta;
        self.enabled.then_some(p)
    }
}

/// Most faces one tracker follows at once.
pub const MAX_TRACKED_FACES: usize = 64;
/// The longest look-ahead of the prediction, seconds (HoloFace predicts 0.12 s; past a second the Kalman
/// prediction is a guess).
pub const MAX_LOOKAHEAD_S: f64 = 1.0;

/// Why tracker settings were refused; the message names the setting as the front ends spell it.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum SessionOptionsError {
    /// The look-ahead is negative, not finite or longer than [`MAX_LOOKAHEAD_S`].
    #[error("lookahead_ms {} must be within 0..=1000", (.0 * 1e6).round() / 1e3)]
    Lookahead(f64),
    /// `max_faces` is 0 or more than [`MAX_TRACKED_FACES`].
    #[error("max_faces {0} must be within 1..=64")]
    MaxFaces(usize),
    /// A landmark filter parameter is not finite or out of range.
    #[error("steady: cut-offs must be > 0 Hz, beta >= 0 and times >= 0 (finite)")]
    Steady,
    /// `detect_every` is 0.
    #[error("detect_every must be at least 1")]
    DetectEvery,
    /// The detector's tiles per side are 0 or more than [`crate::tracker::MAX_DETECT_TILES`].
    #[error("detect_tiles {0} must be within 1..=32")]
    DetectTiles(usize),
}

impl SessionOptions {
    /// Checks the settings an app sets (the C ABI, Python and `FaceTracker::new` all call this).
    pub fn validate(&self) -> Result<(), SessionOptionsError> {
        if !(self.lookahead_s.is_finite() && (0.0..=MAX_LOOKAHEAD_S).contains(&self.lookahead_s)) {
            return Err(SessionOptionsError::Lookahead(self.lookahead_s));
        }
        if !(1..=MAX_TRACKED_FACES).contains(&self.max_faces) {
            return Err(SessionOptionsError::MaxFaces(self.max_faces));
        }
        if self.steady.params().is_some_and(|p| !p.is_valid()) {
            return Err(SessionOptionsError::Steady);
        }
        if self.detect_every == 0 {
            return Err(SessionOptionsError::DetectEvery);
        }
        Ok(())
    }
}

/// A new detection overlapping a tracked face's box by more than this (intersection over union) is that
/// face again, not a new one.
pub const DETECTION_OVERLAP_IOU: f32 = 0.3;
/// Two tracks whose landmark boxes overlap by more than this after alignment have converged on one face;
/// the younger one is dropped.
pub const DUPLICATE_TRACK_IOU: f32 = 0.5;

pub use crate::align::Candidate;

/// What happened to one [`Candidate`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CandidateOutcome {
    /// The face's id: the candidate's track, or the id a new detection was given; `None` for a new
    /// detection that was not accepted.
    pub id: Option<u32>,
    /// The face, or why this candidate has none.
    pub result: FaceOutcome,
}

/// The session's result for one frame: every face and what came of each candidate (one frame-result type per
/// layer: the step's [`crate::frame_step::StepFrame`] holds this one, the link's is `LinkReport`, the app's
/// [`crate::FrameResult`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SessionFrame {
    /// The faces tracked in this frame, oldest track first.
    pub faces: Vec<FaceResult>,
    /// Per candidate, in the order [`TrackerSession::prepare_faces`] returned them.
    pub outcomes: Vec<CandidateOutcome>,
}

impl SessionFrame {
    /// Why the frame has no face: `None` when it has one; else the first candidate's reason, or
    /// [`NoFaceReason::NotDetected`] when there was no candidate.
    pub fn no_face_reason(&self) -> Option<NoFaceReason> {
        if !self.faces.is_empty() {
            return None;
        }
        Some(
            self.outcomes
                .iter()
                .find_map(|o| match o.result {
                    FaceOutcome::NoFace(r) => Some(r),
                    FaceOutcome::Face(_) => None,
                })
                .unwrap_or(NoFaceReason::NotDetected),
        )
    }

    /// The first face's answer in the single-face form.
    pub fn first(&self) -> FaceOutcome {
        self.faces.first().map_or_else(
            || FaceOutcome::NoFace(self.no_face_reason().unwrap_or(NoFaceReason::NotDetected)),
            |f| FaceOutcome::Face(*f),
        )
    }
}

/// A face tracked in one frame: the one result type per face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceResult {
    /// The track's id: the same for as long as the face is tracked, never reused within a session.
    pub id: u32,
    /// Landmarks in image pixels, steadied over time ([`SessionOptions::steady`]): what an app draws.
    pub landmarks: [Point2; 68],
    /// The aligner's own landmarks for this frame, unfiltered (image pixels).
    pub raw_landmarks: [Point2; 68],
    /// Which landmarks the aligner produced.
    pub landmark_set: LandmarkSet,
    /// The aligner's confidence.
    pub confidence: Confidence,
    /// CANDIDE-3 fit in the camera frame (head → camera); its `weights` shape the fitted mesh. What an app
    /// reads as expression is [`Self::blendshapes`] (or [`Self::expression`]).
    pub fit: FitResult,
    /// Head pose in the world.
    pub world: WorldPose,
    /// World position predicted `lookahead_s` ahead (Kalman), metres.
    pub predicted_position: Vec3,
    /// Position and rotation to display (prediction after two-frame denoising).
    pub display: (Vec3, Quat),
    /// Attributes (smile, brows raised, mouth open) from the blendshape coefficients.
    pub attributes: Attributes,
    /// HoloFace's five expression weights (jaw drop, lip stretcher, brow lowerer, lip-corner depressor, eyes
    /// closed), derived from [`Self::blendshapes`], each in [-1, 1]
    /// ([`holoface_models::blendshapes::Blendshapes::expression_weights`]).
    pub expression: ExpressionWeights,
    /// ARKit-named blendshape coefficients in [0, 1] ([`holoface_models::blendshapes`]), from the steadied
    /// landmarks in the face's own frame, the head's turn undone, against this person's neutral (calibrated
    /// on the track's first [`SessionOptions::blendshapes`] frames of each aligner; see
    /// [`crate::FaceTracker::recalibrate_blendshapes`]).
    pub blendshapes: Blendshapes,
    /// Where the frame's initial shape came from.
    pub init: InitSource,
    /// Which aligner answered this frame.
    pub answered_by: crate::align::AnsweredBy,
    /// With the remote aligner and its adaptation on: pairs learnt for this face, whether these landmarks
    /// are a corrected local answer, and the correction's size ([`crate::adapt`]). `None` otherwise.
    pub adaptation: Option<crate::align::AdaptState>,
}

/// What came of one candidate: a face, or an explicit absence with the reason (the session's and the
/// tools' view; an app reads [`FaceResult`]s and [`NoFaceReason`] in its frame result).
// One value per candidate, moved once: boxing the large variant would only add an allocation per frame.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FaceOutcome {
    /// A face was tracked.
    Face(FaceResult),
    /// No face in this frame.
    NoFace(NoFaceReason),
}

/// Why a frame has no face.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NoFaceReason {
    /// The detector found nothing.
    NotDetected,
    /// The aligner's own signal rejected the result (tracking lost; detection runs on the next frame).
    Rejected,
    /// No aligner answered in time.
    NoAnswer,
    /// The 3-D fit failed.
    FitFailed,
}

impl NoFaceReason {
    /// The snake_case name, as serde writes it (per-frame JSON, the Python module).
    pub const fn name(self) -> &'static str {
        match self {
            Self::NotDetected => "not_detected",
            Self::Rejected => "rejected",
            Self::NoAnswer => "no_answer",
            Self::FitFailed => "fit_failed",
        }
    }
}

struct Track {
    id: u32,
    landmarks: [Point2; 68],
    fit: FitResult,
    intrinsics: Intrinsics,
    world_from_camera: Pose,
    timestamp_us: u64,
    predictor: PositionPredictor,
    attributes: Attributes,
    denoiser: Denoiser,
    steady: Option<LandmarkFilter<68>>,
    expressions: BlendshapeEstimator,
}

/// The tracker state machine. See the module documentation for the call order.
pub struct TrackerSession {
    detector: Box<dyn FaceDetector>,
    model: FaceModel,
    mean: [Point2; 68],
    opts: SessionOptions,
    /// Tracked faces, oldest first.
    tracks: Vec<Track>,
    next_id: u32,
    frames_since_detection: u32,
    detector_runs: u64,
    pending: Vec<Candidate>,
}

impl std::fmt::Debug for TrackerSession {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TrackerSession")
            .field("tracks", &self.tracks.len())
            .finish_non_exhaustive()
    }
}

impl TrackerSession {
    /// A session with a detector, a CANDIDE model and the canonical mean shape used to place detections.
    pub fn new(
        detector: Box<dyn FaceDetector>,
        model: FaceModel,
        mean: [Point2; 68],
        opts: SessionOptions,
    ) -> Self {
        let opts = SessionOptions {
            max_faces: opts.max_faces.max(1),
            detect_every: opts.detect_every.max(1),
            ..opts
        };
        Self {
            detector,
            model,
            mean,
            opts,
            tracks: Vec::new(),
            next_id: 0,
            frames_since_detection: 0,
            detector_runs: 0,
            pending: Vec::new(),
        }
    }

    /// The CANDIDE-3 model the session fits.
    pub fn face_model(&self) -> &FaceModel {
        &self.model
    }

    /// Whether a face is currently tracked.
    pub fn is_tracking(&self) -> bool {
        !self.tracks.is_empty()
    }

    /// The ids of the faces tracked now, oldest first.
    pub fn track_ids(&self) -> Vec<u32> {
        self.tracks.iter().map(|t| t.id).collect()
    }

    /// How often the detector has run in this session.
    pub fn detector_runs(&self) -> u64 {
        self.detector_runs
    }

    /// Every tracked face calibrates its neutral expression again on its next frames (the person should be
    /// at rest then).
    pub fn recalibrate_blendshapes(&mut self) {
        for t in &mut self.tracks {
            t.expressions.recalibrate();
        }
    }

    /// Forgets every tracked face (the next frame runs detection). Ids are not reused afterwards.
    pub fn reset(&mut self) {
        self.tracks.clear();
        self.pending.clear();
    }

    /// Step 1: one [`Candidate`] per tracked face (its previous landmarks moved with the headset) and, when
    /// fewer than `max_faces` are tracked and the detection cadence says so, one per new detection that
    /// does not overlap a tracked face. Empty means "no face" (nothing tracked, nothing detected).
    pub fn prepare_faces(&mut self, frame: &Frame<'_>) -> Result<Vec<Candidate>, DetectError> {
        let mut candidates: Vec<Candidate> = self
            .tracks
            .iter()
            .map(|t| {
                let mut init = t.landmarks;
                if self.opts.motion_compensation {
                    compensate_headset_motion(
                        &t.landmarks,
                        &t.intrinsics,
                        &t.world_from_camera,
                        &frame.intrinsics,
                        &frame.world_from_camera,
                        t.fit.translation.norm(),
                        &mut init,
                    );
                }
                Candidate {
                    track: Some(t.id),
                    init,
                    source: InitSource::Tracking,
                }
            })
            .collect();
        self.pending.clear();
        let room = self.opts.max_faces.saturating_sub(self.tracks.len());
        let due = self.tracks.is_empty() || self.frames_since_detection + 1 >= self.opts.detect_every;
        if room > 0 && due {
            self.frames_since_detection = 0;
            self.detector_runs += 1;
            let dets = self.detector.detect(&frame.image)?;
            let mut added = 0;
            for d in &dets {
                if added == room {
                    break;
                }
                let mut init = [Point2::default(); 68];
                if !shape_from_detection(&self.mean, d, &mut init) {
                    continue;
                }
                let Some(bbox) = Rect::bounding(&init) else {
                    continue;
                };
                let overlaps = candidates
                    .iter()
                    .filter_map(|c| Rect::bounding(&c.init))
                    .any(|b| b.iou(&bbox) > DETECTION_OVERLAP_IOU);
                if !overlaps {
                    candidates.push(Candidate {
                        track: None,
                        init,
                        source: InitSource::Detection,
                    });
                    added += 1;
                }
            }
        } else {
            self.frames_since_detection = self.frames_since_detection.saturating_add(1);
        }
        self.pending.clone_from(&candidates);
        Ok(candidates)
    }

    /// Step 3: per candidate of the last [`Self::prepare_faces`] (in its order; `None`: no aligner
    /// answered that one), verify, fit, pose, predict, filter; a new detection whose alignment is accepted
    /// becomes a track with a new id. Tracks that converge on one face are merged (the older one stays).
    pub fn complete_faces(&mut self, frame: &Frame<'_>, alignments: &[Option<Alignment>]) -> SessionFrame {
        let pending = std::mem::take(&mut self.pending);
        let mut outcomes = Vec::with_capacity(pending.len());
        for (i, c) in pending.iter().enumerate() {
            let alignment = alignments.get(i).copied().flatten();
            outcomes.push(self.complete_one(frame, c, alignment));
        }
        self.merge_duplicates(&mut outcomes);
        let mut faces: Vec<FaceResult> = outcomes
            .iter()
            .filter_map(|o| match (o.id, o.result) {
                (Some(_), FaceOutcome::Face(face)) => Some(face),
                _ => None,
            })
            .collect();
        faces.sort_by_key(|f| f.id);
        SessionFrame { faces, outcomes }
    }

    /// The landmarks to show for alignment `a` of candidate `c` (steadied by the track's filter, or a new
    /// filter for a new face), and the filter to keep with the track; the fit sees the steadied landmarks.
    fn steadied(
        &mut self,
        frame: &Frame<'_>,
        c: &Candidate,
        index: Option<usize>,
        a: &Alignment,
    ) -> ([Point2; 68], Option<LandmarkFilter<68>>) {
        let mut steady = index.and_then(|i| self.tracks[i].steady.take()).or_else(|| {
            self.opts
                .steady
                .params()
                .and_then(|p| LandmarkFilter::new(&self.mean, OUTER_EYE_CORNERS, p).ok())
        });
        // The headset's own motion since the track's last frame, as the image sees it: the similarity
        // between the track's landmarks and the candidate's start (those landmarks moved with the headset).
        let moved = index
            .filter(|_| c.source == InitSource::Tracking)
            .and_then(|i| Similarity2::fit(&self.tracks[i].landmarks, &c.init))
            .unwrap_or(Similarity2::IDENTITY);
        let shown = steady.as_mut().map_or(a.landmarks, |f| {
            let source = Source {
                id: a.answered_by as u8,
                precise: a.answered_by != crate::align::AnsweredBy::Krfws,
            };
            f.filter(&a.landmarks, frame.timestamp_us, source, &moved)
        });
        (shown, steady)
    }

    /// Takes track `index` out (its predictor stepped to `position` at `timestamp_us`), or starts a new
    /// face's: its id, predictor, last attributes and denoiser.
    fn take_track(
        &mut self,
        index: Option<usize>,
        timestamp_us: u64,
        position: Vec3,
    ) -> (u32, PositionPredictor, Attributes, Denoiser) {
        match index.map(|i| self.tracks.remove(i)) {
            Some(mut t) => {
                let dt = timestamp_us.saturating_sub(t.timestamp_us) as f64 * 1e-6;
                t.predictor.step(dt, position);
                (t.id, t.predictor, t.attributes, t.denoiser)
            }
            None => {
                let id = self.next_id;
                self.next_id = self.next_id.wrapping_add(1);
                (
                    id,
                    PositionPredictor::new(position, self.opts.kalman),
                    Attributes::default(),
                    Denoiser::default(),
                )
            }
        }
    }

    fn complete_one(
        &mut self,
        frame: &Frame<'_>,
        c: &Candidate,
        alignment: Option<Alignment>,
    ) -> CandidateOutcome {
        let index = c.track.and_then(|id| self.tracks.iter().position(|t| t.id == id));
        let no_face = |id, reason| CandidateOutcome {
            id,
            result: FaceOutcome::NoFace(reason),
        };
        let Some(a) = alignment else {
            // Keep the track: a late answer is not evidence that the face is gone.
            return no_face(c.track, NoFaceReason::NoAnswer);
        };
        if !a.accepted {
            if let Some(i) = index {
                self.tracks.remove(i);
            }
            return no_face(c.track, NoFaceReason::Rejected);
        }
        let warm = index.map(|i| self.tracks[i].fit);
        let (shown, steady) = self.steadied(frame, c, index, &a);
        let opts = if warm.is_some() {
            self.opts.fit
        } else {
            FitOptions {
                max_iterations: 10,
                ..self.opts.fit
            }
        };
        let Ok(fitted) = fit(&self.model, &frame.intrinsics, &shown, warm.as_ref(), &opts) else {
            if let Some(i) = index {
                self.tracks.remove(i);
            }
            return no_face(c.track, NoFaceReason::FitFailed);
        };
        let world = world_pose(&fitted, &frame.world_from_camera);
        let mut expressions = index
            .map(|i| self.tracks[i].expressions.clone())
            .unwrap_or_else(|| BlendshapeEstimator::new(self.opts.blendshapes));
        let turn = HeadTurn::from_pose(fitted.rotation, fitted.translation);
        // Each aligner calibrates its own neutral: they place a resting face a little differently.
        // Time since the track's previous frame (0 for a new face): the neutral calibrates and drifts in seconds.
        let dt = index.map_or(0.0, |i| {
            frame.timestamp_us.saturating_sub(self.tracks[i].timestamp_us) as f64 * 1e-6
        });
        let blendshapes = expressions.update_from(
            a.answered_by as u8,
            &shown,
            a.set == LandmarkSet::Ibug68,
            Some(turn),
            dt,
        );
        let (id, predictor, prev_attr, mut denoiser) =
            self.take_track(index, frame.timestamp_us, world.position);
        let predicted_position = predictor.predict(self.opts.lookahead_s);
        let display = denoiser.apply(predicted_position, world.rotation);
        let attributes = self.opts.attributes.update(&blendshapes, prev_attr);
        let track = Track {
            id,
            landmarks: a.landmarks,
            fit: fitted,
            intrinsics: frame.intrinsics,
            world_from_camera: frame.world_from_camera,
            timestamp_us: frame.timestamp_us,
            predictor,
            attributes,
            denoiser,
            steady,
            expressions,
        };
        // Oldest first: a track keeps its place, a new one goes after every older one.
        let at = self.tracks.partition_point(|t| t.id < id);
        self.tracks.insert(at, track);
        CandidateOutcome {
            id: Some(id),
            result: FaceOutcome::Face(FaceResult {
                id,
                landmarks: shown,
                raw_landmarks: a.landmarks,
                landmark_set: a.set,
                confidence: a.confidence,
                fit: fitted,
                world,
                predicted_position,
                display,
                attributes,
                expression: blendshapes.expression_weights(),
                blendshapes,
                init: c.source,
                answered_by: a.answered_by,
                adaptation: a.adaptation,
            }),
        }
    }

    /// Drops the younger of two tracks whose landmark boxes overlap by more than [`DUPLICATE_TRACK_IOU`]
    /// (faces crossing can pull two tracks onto one face); its outcome becomes "rejected".
    fn merge_duplicates(&mut self, outcomes: &mut [CandidateOutcome]) {
        let mut i = 0;
        while i < self.tracks.len() {
            let Some(a) = Rect::bounding(&self.tracks[i].landmarks) else {
                i += 1;
                continue;
            };
            let dup = (i + 1..self.tracks.len()).find(|&j| {
                Rect::bounding(&self.tracks[j].landmarks).is_some_and(|b| a.iou(&b) > DUPLICATE_TRACK_IOU)
            });
            match dup {
                Some(j) => {
                    let gone = self.tracks.remove(j).id;
                    for o in outcomes.iter_mut().filter(|o| o.id == Some(gone)) {
                        o.result = FaceOutcome::NoFace(NoFaceReason::Rejected);
                    }
                }
                None => i += 1,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use holoface_models::image::GrayView;

    use super::*;
    use crate::detect::Detection;
    use holoface_models::candide::{Wfm, project_landmarks};
    use holoface_models::geometry::Rect;

    /// The names the Python module reads are the ones the per-frame JSON (serde) writes.
    #[test]
    fn enum_names_are_serdes() {
        use crate::align::{AnsweredBy, InitSource};
        use crate::link::FailureKind;
        let pairs = [AnsweredBy::LocalDan, AnsweredBy::RemoteDan, AnsweredBy::Krfws]
            .map(|v| (serde_json::json!(v), v.name()))
            .into_iter()
            .chain([InitSource::Detection, InitSource::Tracking].map(|v| (serde_json::json!(v), v.name())))
            .chain(
                [
                    NoFaceReason::NotDetected,
                    NoFaceReason::Rejected,
                    NoFaceReason::NoAnswer,
                    NoFaceReason::FitFailed,
                ]
                .map(|v| (serde_json::json!(v), v.name())),
            )
            .chain(FailureKind::ALL.map(|v| (serde_json::json!(v), v.name())));
        for (serde, name) in pairs {
            assert_eq!(serde.as_str(), Some(name));
        }
    }

    const K: Intrinsics = Intrinsics::new(500.0, 500.0, 160.0, 120.0);

    fn model() -> FaceModel {
        let base = std::env::var_os("HOLOFACE_DATA").map_or_else(
            || std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
            std::path::PathBuf::from,
        );
        let text =
            String::from_utf8_lossy(&std::fs::read(base.join("candide3/candide3.wfm")).unwrap()).into_owned();
        FaceModel::from_wfm(&Wfm::parse(&text).unwrap()).unwrap()
    }

    /// Detector fake: reports a face at the truth's keypoints while `present`.
    struct FakeDetector {
        present: bool,
        keypoints: [Point2; 6],
    }
    impl FaceDetector for FakeDetector {
        fn detect(&mut self, _: &GrayView<'_>) -> Result<Vec<Detection>, DetectError> {
            Ok(if self.present {
                vec![Detection {
                    bbox: Rect::default(),
                    score: 0.9,
                    keypoints: self.keypoints,
                }]
            } else {
                vec![]
            })
        }
    }

    fn truth_landmarks(m: &FaceModel, z: f64) -> [Point2; 68] {
        let gt = FitResult {
            rotation: Quat::IDENTITY,
            translation: Vec3::new(0.0, 0.0, z),
            weights: ExpressionWeights::NEUTRAL,
            rmse_px: 0.0,
            iterations: 0,
            converged: true,
        };
        let mut lm = [Point2::new(160.0, 120.0); 68];
        assert!(project_landmarks(m, &K, &gt, &mut lm));
        lm
    }

    #[test]
    fn detect_then_track_then_lose() {
        let m = model();
        let lm = truth_landmarks(&m, 0.6);
        let avg = |r: std::ops::Range<usize>| {
            let n = r.len() as f32;
            let (x, y) = lm[r].iter().fold((0.0, 0.0), |(x, y), p| (x + p.x, y + p.y));
            Point2::new(x / n, y / n)
        };
        let kp = [
            avg(36..42),
            avg(42..48),
            lm[30],
            Point2::new(0.5 * (lm[62].x + lm[66].x), lm[62].y),
            lm[0],
            lm[16],
        ];
        let det = FakeDetector {
            present: true,
            keypoints: kp,
        };
        let mean = holoface_models::shape::dan_mean_shape();
        let mut s = TrackerSession::new(Box::new(det), m, mean, SessionOptions::default());
        let pixels = vec![0u8; 320 * 240];
        let frame = |t: u64| Frame {
            timestamp_us: t,
            image: GrayView::new(&pixels, 320, 240, 320).unwrap(),
            intrinsics: K,
            world_from_camera: Pose::IDENTITY,
        };
        let answer = |accepted: bool| Alignment {
            landmarks: lm,
            set: LandmarkSet::Ibug68,
            confidence: Confidence::FaceProbability(if accepted { 0.9 } else { 0.01 }),
            accepted,
            answered_by: crate::align::AnsweredBy::RemoteDan,
            adaptation: None,
        };
        // One face per frame: the first candidate, completed with `alignment`.
        let one = |s: &mut TrackerSession, f: &Frame<'_>, alignment: Option<Alignment>| {
            let candidates = s.prepare_faces(f).unwrap();
            assert!(candidates.len() <= 1, "{candidates:?}");
            let alignments = vec![alignment; candidates.len()];
            (
                candidates.first().copied(),
                s.complete_faces(f, &alignments).first(),
            )
        };
        // Frame 1: detection.
        let f1 = frame(0);
        let (c, r) = one(&mut s, &f1, Some(answer(true)));
        assert_eq!(c.map(|c| c.source), Some(InitSource::Detection));
        let FaceOutcome::Face(u) = r else {
            panic!("expected a face")
        };
        assert!(
            (u.fit.translation.z - 0.6).abs() < 0.02,
            "{:?}",
            u.fit.translation
        );
        // Frame 2: tracking from the previous landmarks, no detector call.
        let f2 = frame(33_000);
        let (c, r) = one(&mut s, &f2, Some(answer(true)));
        let c = c.expect("a tracked candidate");
        assert_eq!(c.source, InitSource::Tracking);
        assert!(c.init[30].dist(lm[30]) < 1e-3);
        assert!(matches!(r, FaceOutcome::Face(_)));
        // Frame 3: no answer in time keeps the track; frame 4: rejection loses it.
        let f3 = frame(66_000);
        assert_eq!(
            one(&mut s, &f3, None).1,
            FaceOutcome::NoFace(NoFaceReason::NoAnswer)
        );
        assert!(s.is_tracking());
        assert_eq!(
            one(&mut s, &f3, Some(answer(false))).1,
            FaceOutcome::NoFace(NoFaceReason::Rejected)
        );
        assert!(!s.is_tracking());
    }

    #[test]
    fn options_out_of_range_are_refused_by_name() {
        assert_eq!(SessionOptions::default().validate(), Ok(()));
        let with = |o: SessionOptions| o.validate();
        let lookahead = SessionOptions {
            lookahead_s: -0.1,
            ..SessionOptions::default()
        };
        assert!(with(lookahead).unwrap_err().to_string().contains("lookahead_ms"));
        let faces = SessionOptions {
            max_faces: 65,
            ..SessionOptions::default()
        };
        assert!(with(faces).unwrap_err().to_string().contains("max_faces"));
        let bad = SteadySettings {
            shape_cutoff_hz: f64::INFINITY,
            ..SteadySettings::default()
        };
        let steady = |steady| SessionOptions {
            steady,
            ..SessionOptions::default()
        };
        assert_eq!(with(steady(bad)), Err(SessionOptionsError::Steady));
        let off = SteadySettings {
            enabled: false,
            ..SteadySettings::default()
        };
        assert_eq!(with(steady(off)), Ok(()));
        let never = SessionOptions {
            detect_every: 0,
            ..SessionOptions::default()
        };
        assert_eq!(never.validate(), Err(SessionOptionsError::DetectEvery));
    }

    /// The aligner's noisy answers stay available raw; what the session shows (and fits) is steadied,
    /// and `steady: None` shows the raw answers.
    #[test]
    fn landmarks_are_steadied_and_the_raw_ones_kept() {
        let m = model();
        let lm = truth_landmarks(&m, 0.6);
        let det = || FakeDetector {
            present: true,
            keypoints: keypoints_of(&lm),
        };
        let pixels = vec![0u8; 320 * 240];
        let mut rng = holoface_models::rng::Rng::new(3);
        let noisy: Vec<[Point2; 68]> = (0..60)
            .map(|_| lm.map(|p| Point2::new(p.x + rng.normal() as f32, p.y + rng.normal() as f32)))
            .collect();
        let run = |enabled: bool| {
            let opts = SessionOptions {
                steady: SteadySettings {
                    enabled,
                    ..SteadySettings::default()
                },
                ..SessionOptions::default()
            };
            let mut s = TrackerSession::new(
                Box::new(det()),
                m.clone(),
                holoface_models::shape::dan_mean_shape(),
                opts,
            );
            let mut out = Vec::new();
            for (k, n) in noisy.iter().enumerate() {
                let f = Frame {
                    timestamp_us: k as u64 * 33_333,
                    image: GrayView::new(&pixels, 320, 240, 320).unwrap(),
                    intrinsics: K,
                    world_from_camera: Pose::IDENTITY,
                };
                let c = s.prepare_faces(&f).unwrap();
                let a = Alignment {
                    landmarks: *n,
                    set: LandmarkSet::Ibug68,
                    confidence: Confidence::PredictedError(0.02),
                    accepted: true,
                    answered_by: crate::align::AnsweredBy::Krfws,
                    adaptation: None,
                };
                let FaceOutcome::Face(u) = s.complete_faces(&f, &vec![Some(a); c.len()]).first() else {
                    panic!("frame {k}: no face")
                };
                assert_eq!(
                    u.raw_landmarks, *n,
                    "frame {k}: the raw landmarks are the aligner's"
                );
                out.push(u.landmarks);
            }
            out
        };
        let err = |shown: &[[Point2; 68]]| -> f32 {
            shown[20..]
                .iter()
                .flat_map(|s| s.iter().zip(&lm).map(|(a, b)| a.dist(*b)))
                .sum::<f32>()
                / (40.0 * 68.0)
        };
        let (steadied, raw) = (run(true), run(false));
        assert_eq!(
            raw, noisy,
            "without the filter the shown landmarks are the raw ones"
        );
        assert_eq!(steadied[0], noisy[0], "the first frame passes through");
        assert!(
            err(&steadied) < 0.75 * err(&raw),
            "steadied {} px vs raw {} px",
            err(&steadied),
            err(&raw)
        );
    }

    /// Detector fake for several faces: one detection per entry of `faces` (keypoints), counting calls.
    struct Crowd {
        faces: std::sync::Arc<std::sync::Mutex<Vec<[Point2; 6]>>>,
        calls: std::sync::Arc<std::sync::atomic::AtomicUsize>,
    }
    impl FaceDetector for Crowd {
        fn detect(&mut self, _: &GrayView<'_>) -> Result<Vec<Detection>, DetectError> {
            self.calls.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let faces = self.faces.lock().unwrap().clone();
            Ok(faces
                .into_iter()
                .map(|keypoints| Detection {
                    bbox: Rect::default(),
                    score: 0.9,
                    keypoints,
                })
                .collect())
        }
    }

    fn keypoints_of(lm: &[Point2; 68]) -> [Point2; 6] {
        let avg = |r: std::ops::Range<usize>| {
            let n = r.len() as f32;
            let (x, y) = lm[r].iter().fold((0.0, 0.0), |(x, y), p| (x + p.x, y + p.y));
            Point2::new(x / n, y / n)
        };
        [
            avg(36..42),
            avg(42..48),
            lm[30],
            Point2::new(0.5 * (lm[62].x + lm[66].x), lm[62].y),
            lm[0],
            lm[16],
        ]
    }

    fn shifted(lm: &[Point2; 68], dx: f32) -> [Point2; 68] {
        lm.map(|p| Point2::new(p.x + dx, p.y))
    }

    /// The truth face nearest to `init` (the aligner fake: it snaps onto the face it starts on).
    fn snap(truths: &[[Point2; 68]], init: &[Point2; 68], accepted: bool) -> Alignment {
        let c = holoface_models::geometry::centroid(init);
        let lm = *truths
            .iter()
            .min_by(|a, b| {
                let da = holoface_models::geometry::centroid(&a[..]).dist(c);
                let db = holoface_models::geometry::centroid(&b[..]).dist(c);
                da.total_cmp(&db)
            })
            .unwrap();
        Alignment {
            landmarks: lm,
            set: LandmarkSet::Ibug68,
            confidence: Confidence::FaceProbability(0.9),
            accepted,
            answered_by: crate::align::AnsweredBy::Krfws,
            adaptation: None,
        }
    }

    #[test]
    fn several_faces_keep_their_ids_and_detection_follows_the_cadence() {
        let m = model();
        let base = truth_landmarks(&m, 1.2);
        // Three faces side by side (a 320-px frame; the faces are about 60 px wide at 1.2 m).
        let truths = [shifted(&base, -100.0), base, shifted(&base, 100.0)];
        let faces = std::sync::Arc::new(std::sync::Mutex::new(vec![
            keypoints_of(&truths[0]),
            keypoints_of(&truths[1]),
        ]));
        let calls = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let det = Crowd {
            faces: faces.clone(),
            calls: calls.clone(),
        };
        let opts = SessionOptions {
            max_faces: 3,
            detect_every: 5,
            ..SessionOptions::default()
        };
        let mut s = TrackerSession::new(Box::new(det), m, holoface_models::shape::dan_mean_shape(), opts);
        let pixels = vec![0u8; 320 * 240];
        let frame = |i: u64| Frame {
            timestamp_us: i * 33_000,
            image: GrayView::new(&pixels, 320, 240, 320).unwrap(),
            intrinsics: K,
            world_from_camera: Pose::IDENTITY,
        };
        let run = |s: &mut TrackerSession, i: u64, reject: Option<u32>| {
            let f = frame(i);
            let cands = s.prepare_faces(&f).unwrap();
            let answers: Vec<_> = cands
                .iter()
                .map(|c| Some(snap(&truths, &c.init, c.track != reject || reject.is_none())))
                .collect();
            (cands, s.complete_faces(&f, &answers))
        };
        let ids = |r: &SessionFrame| r.faces.iter().map(|f| f.id).collect::<Vec<_>>();

        // Frame 0: two detections become tracks 0 and 1.
        let (c, r) = run(&mut s, 0, None);
        assert_eq!(
            c.iter().map(|c| c.source).collect::<Vec<_>>(),
            [InitSource::Detection; 2]
        );
        assert_eq!(ids(&r), [0, 1]);
        assert_eq!(calls.load(std::sync::atomic::Ordering::Relaxed), 1);
        // A third person steps in; the detector only looks again on frame 5 (every 5th frame while fewer
        // than 3 are tracked), and never re-adds the two tracked faces.
        faces.lock().unwrap().push(keypoints_of(&truths[2]));
        for i in 1..5 {
            let (c, r) = run(&mut s, i, None);
            assert!(
                c.iter().all(|c| c.source == InitSource::Tracking),
                "frame {i}: {c:?}"
            );
            assert_eq!(ids(&r), [0, 1], "frame {i}");
        }
        assert_eq!(calls.load(std::sync::atomic::Ordering::Relaxed), 1);
        let (c, r) = run(&mut s, 5, None);
        assert_eq!(c.len(), 3, "two tracked + one new: {c:?}");
        assert_eq!(ids(&r), [0, 1, 2]);
        assert_eq!(calls.load(std::sync::atomic::Ordering::Relaxed), 2);
        // Full: the detector no longer runs.
        for i in 6..20 {
            let (_, r) = run(&mut s, i, None);
            assert_eq!(ids(&r), [0, 1, 2]);
        }
        assert_eq!(calls.load(std::sync::atomic::Ordering::Relaxed), 2);
        // Face 1's alignment is rejected: only that track is lost, the others keep their ids and filters.
        let (_, r) = run(&mut s, 20, Some(1));
        assert_eq!(ids(&r), [0, 2]);
        let lost = r.outcomes.iter().find(|o| o.id == Some(1)).unwrap();
        assert_eq!(lost.result, FaceOutcome::NoFace(NoFaceReason::Rejected));
        // Found again at the next detection: a new id, never a reused one.
        let mut found = None;
        for i in 21..30 {
            let (_, r) = run(&mut s, i, None);
            if r.faces.len() == 3 {
                found = Some(ids(&r));
                break;
            }
        }
        assert_eq!(found, Some(vec![0, 2, 3]));
        assert_eq!(s.track_ids(), [0, 2, 3]);
    }

    #[test]
    fn tracks_that_converge_on_one_face_are_merged_into_the_older() {
        let m = model();
        let base = truth_landmarks(&m, 1.2);
        let truths = [shifted(&base, -60.0), shifted(&base, 60.0)];
        let faces = std::sync::Arc::new(std::sync::Mutex::new(vec![
            keypoints_of(&truths[0]),
            keypoints_of(&truths[1]),
        ]));
        let det = Crowd {
            faces,
            calls: std::sync::Arc::default(),
        };
        let opts = SessionOptions {
            max_faces: 2,
            ..SessionOptions::default()
        };
        let mut s = TrackerSession::new(Box::new(det), m, holoface_models::shape::dan_mean_shape(), opts);
        let pixels = vec![0u8; 320 * 240];
        let f = Frame {
            timestamp_us: 0,
            image: GrayView::new(&pixels, 320, 240, 320).unwrap(),
            intrinsics: K,
            world_from_camera: Pose::IDENTITY,
        };
        let c = s.prepare_faces(&f).unwrap();
        let answers: Vec<_> = c.iter().map(|c| Some(snap(&truths, &c.init, true))).collect();
        assert_eq!(s.complete_faces(&f, &answers).faces.len(), 2);
        // Both aligners snap onto the left face (as when two people cross): one track remains, the older.
        let f2 = Frame {
            timestamp_us: 33_000,
            ..f
        };
        let c = s.prepare_faces(&f2).unwrap();
        let answers: Vec<_> = c.iter().map(|_| Some(snap(&truths[..1], &base, true))).collect();
        let r = s.complete_faces(&f2, &answers);
        assert_eq!(r.faces.iter().map(|f| f.id).collect::<Vec<_>>(), [0]);
        assert_eq!(
            r.outcomes.iter().find(|o| o.id == Some(1)).map(|o| o.result),
            Some(FaceOutcome::NoFace(NoFaceReason::Rejected))
        );
    }
}
