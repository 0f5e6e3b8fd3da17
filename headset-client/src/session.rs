//! The tracker session: an IO-free state machine that turns frames into per-frame face results.
//!
//! Call order per frame (the aligner runs in between, locally or over the network):
//!
//! 1. [`TrackerSession::prepare`] decides between detection and tracking and returns the initial shape:
//!    the previous landmarks moved with the headset (motion compensation), or the mean shape placed on a
//!    fresh detection; or "no face" when nothing is tracked and the detector finds nothing.
//! 2. The caller aligns the frame from that shape with any [`crate::align::Aligner`] (KRFWS on the
//!    headset, DAN over QUIC) or gives up (`None`, e.g. the link missed its deadline and no local aligner).
//! 3. [`TrackerSession::complete`] verifies the alignment with the aligner's own signal, fits CANDIDE-3,
//!    converts to a world pose, predicts it ahead with the Kalman filters, denoises, derives attributes,
//!    and updates the tracking state. Every frame gets a [`FrameResult`]: a face or an explicit "no face".
//!
//! The session never reads a clock: time comes from the frames' timestamps. The three steps are driven in one
//! place, [`crate::frame_loop::step`]; call that rather than writing the sequence out again.

use holoface_models::camera::Intrinsics;
use holoface_models::candide::{FaceModel, FitOptions, FitResult, fit};
use holoface_models::geometry::Point2;
use holoface_models::kalman::{Denoiser, KalmanParams, PositionPredictor};
use holoface_models::math3::{Pose, Quat, Vec3};
use holoface_models::pose::{
    AttributeThresholds, Attributes, WorldPose, compensate_headset_motion, world_pose,
};
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
}

impl Default for SessionOptions {
    fn default() -> Self {
        Self {
            fit: FitOptions {
                max_iterations: 3,
                ..FitOptions::default()
            },
            kalman: KalmanParams::default(),
            lookahead_s: 0.12,
            attributes: AttributeThresholds::default(),
            motion_compensation: true,
        }
    }
}

/// What `prepare` decided.
// One value per frame, moved once: boxing the large variant would only add an allocation per frame.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Prepared {
    /// Align from this shape (image pixels).
    Align {
        /// Initial 68-point shape.
        init: [Point2; 68],
        /// Where it came from.
        source: InitSource,
    },
    /// Nothing tracked and nothing detected: the frame's answer is "no face".
    NoFace,
}

/// A tracked face in one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceUpdate {
    /// Landmarks in image pixels.
    pub landmarks: [Point2; 68],
    /// Which landmarks the aligner produced.
    pub landmark_set: LandmarkSet,
    /// The aligner's confidence.
    pub confidence: Confidence,
    /// CANDIDE-3 fit in the camera frame (head → camera).
    pub fit: FitResult,
    /// Head pose in the world.
    pub world: WorldPose,
    /// World position predicted `lookahead_s` ahead (Kalman), metres.
    pub predicted_position: Vec3,
    /// Position and rotation to display (prediction after two-frame denoising).
    pub display: (Vec3, Quat),
    /// Attributes from the expression weights.
    pub attributes: Attributes,
    /// Where the frame's initial shape came from.
    pub init: InitSource,
    /// Which aligner answered this frame.
    pub answered_by: crate::align::AnsweredBy,
}

/// The answer for one frame: a face, or an explicit absence with the reason.
// One value per frame, moved once: boxing the large variant would only add an allocation per frame.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum FrameResult {
    /// A face was tracked.
    Face(FaceUpdate),
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

struct Track {
    landmarks: [Point2; 68],
    fit: FitResult,
    intrinsics: Intrinsics,
    world_from_camera: Pose,
    timestamp_us: u64,
    predictor: PositionPredictor,
    attributes: Attributes,
}

/// The tracker state machine. See the module documentation for the call order.
pub struct TrackerSession {
    detector: Box<dyn FaceDetector>,
    model: FaceModel,
    mean: [Point2; 68],
    opts: SessionOptions,
    track: Option<Track>,
    denoiser: Denoiser,
    pending: Option<InitSource>,
}

impl std::fmt::Debug for TrackerSession {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TrackerSession")
            .field("tracking", &self.track.is_some())
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
        Self {
            detector,
            model,
            mean,
            opts,
            track: None,
            denoiser: Denoiser::default(),
            pending: None,
        }
    }

    /// The CANDIDE-3 model the session fits.
    pub fn face_model(&self) -> &FaceModel {
        &self.model
    }

    /// Whether a face is currently tracked.
    pub fn is_tracking(&self) -> bool {
        self.track.is_some()
    }

    /// Forgets the tracked face (the next frame runs detection).
    pub fn reset(&mut self) {
        self.track = None;
        self.denoiser.reset();
    }

    /// Step 1: the initial shape for `frame`, from tracking or detection.
    pub fn prepare(&mut self, frame: &Frame<'_>) -> Result<Prepared, DetectError> {
        if let Some(t) = &self.track {
            let mut init = t.landmarks;
            if self.opts.motion_compensation {
                let distance = t.fit.translation.norm();
                compensate_headset_motion(
                    &t.landmarks,
                    &t.intrinsics,
                    &t.world_from_camera,
                    &frame.intrinsics,
                    &frame.world_from_camera,
                    distance,
                    &mut init,
                );
            }
            self.pending = Some(InitSource::Tracking);
            return Ok(Prepared::Align {
                init,
                source: InitSource::Tracking,
            });
        }
        let dets = self.detector.detect(&frame.image)?;
        let mut init = [Point2::default(); 68];
        match dets.first() {
            Some(d) if shape_from_detection(&self.mean, d, &mut init) => {
                self.pending = Some(InitSource::Detection);
                Ok(Prepared::Align {
                    init,
                    source: InitSource::Detection,
                })
            }
            _ => {
                self.pending = None;
                Ok(Prepared::NoFace)
            }
        }
    }

    /// Step 3: verify, fit, pose, predict. `alignment` is `None` when no aligner answered.
    pub fn complete(&mut self, frame: &Frame<'_>, alignment: Option<Alignment>) -> FrameResult {
        let Some(source) = self.pending.take() else {
            return FrameResult::NoFace(NoFaceReason::NotDetected);
        };
        let Some(a) = alignment else {
            // Keep the track: a late answer is not evidence that the face is gone.
            return FrameResult::NoFace(NoFaceReason::NoAnswer);
        };
        if !a.accepted {
            self.reset();
            return FrameResult::NoFace(NoFaceReason::Rejected);
        }
        let warm = self.track.as_ref().map(|t| t.fit);
        let opts = if warm.is_some() {
            self.opts.fit
        } else {
            FitOptions {
                max_iterations: 10,
                ..self.opts.fit
            }
        };
        let Ok(fitted) = fit(&self.model, &frame.intrinsics, &a.landmarks, warm.as_ref(), &opts) else {
            self.reset();
            return FrameResult::NoFace(NoFaceReason::FitFailed);
        };
        let world = world_pose(&fitted, &frame.world_from_camera);
        let (predictor, prev_attr) = match self.track.take() {
            Some(mut t) => {
                let dt = frame.timestamp_us.saturating_sub(t.timestamp_us) as f64 * 1e-6;
                t.predictor.step(dt, world.position);
                (t.predictor, t.attributes)
            }
            None => {
                self.denoiser.reset();
                (
                    PositionPredictor::new(world.position, self.opts.kalman),
                    Attributes::default(),
                )
            }
        };
        let predicted_position = predictor.predict(self.opts.lookahead_s);
        let display = self.denoiser.apply(predicted_position, world.rotation);
        let attributes = self.opts.attributes.update(&fitted.weights, prev_attr);
        self.track = Some(Track {
            landmarks: a.landmarks,
            fit: fitted,
            intrinsics: frame.intrinsics,
            world_from_camera: frame.world_from_camera,
            timestamp_us: frame.timestamp_us,
            predictor,
            attributes,
        });
        FrameResult::Face(FaceUpdate {
            landmarks: a.landmarks,
            landmark_set: a.set,
            confidence: a.confidence,
            fit: fitted,
            world,
            predicted_position,
            display,
            attributes,
            init: source,
            answered_by: a.answered_by,
        })
    }
}

#[cfg(test)]
mod tests {
    use holoface_models::image::GrayView;

    use super::*;
    use crate::detect::Detection;
    use holoface_models::candide::{Wfm, project_landmarks};
    use holoface_models::geometry::Rect;

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
            weights: holoface_models::expression::ExpressionWeights::NEUTRAL,
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
        };
        // Frame 1: detection.
        let f1 = frame(0);
        assert!(matches!(
            s.prepare(&f1).unwrap(),
            Prepared::Align {
                source: InitSource::Detection,
                ..
            }
        ));
        let FrameResult::Face(u) = s.complete(&f1, Some(answer(true))) else {
            panic!("expected a face")
        };
        assert!(
            (u.fit.translation.z - 0.6).abs() < 0.02,
            "{:?}",
            u.fit.translation
        );
        // Frame 2: tracking from the previous landmarks, no detector call.
        let f2 = frame(33_000);
        match s.prepare(&f2).unwrap() {
            Prepared::Align {
                init,
                source: InitSource::Tracking,
            } => assert!(init[30].dist(lm[30]) < 1e-3),
            other => panic!("{other:?}"),
        }
        assert!(matches!(
            s.complete(&f2, Some(answer(true))),
            FrameResult::Face(_)
        ));
        // Frame 3: no answer in time keeps the track; frame 4: rejection loses it.
        let f3 = frame(66_000);
        s.prepare(&f3).unwrap();
        assert_eq!(s.complete(&f3, None), FrameResult::NoFace(NoFaceReason::NoAnswer));
        assert!(s.is_tracking());
        s.prepare(&f3).unwrap();
        assert_eq!(
            s.complete(&f3, Some(answer(false))),
            FrameResult::NoFace(NoFaceReason::Rejected)
        );
        assert!(!s.is_tracking());
    }
}
