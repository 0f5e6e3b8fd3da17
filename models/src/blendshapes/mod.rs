//! Named blendshape coefficients in [0, 1], as ARKit, MediaPipe's Face Landmarker and avatar rigs (Unity,
//! Unreal, VRM) take them, from 68 landmarks: every movement 68 landmarks can observe.
//!
//! **How.** Each frame's landmarks are brought into the face's own frame: the affine map that takes the
//! face's rigid points (eye corners, nasion, nose wings) onto a fixed template, which removes the head's
//! position, size, roll and, to first order, the foreshortening of yaw and pitch (a flat patch seen from
//! any direction is an affine image of itself). The face is not flat, so what a turn still moves there (the
//! lips, the chin, the brows) is undone with [`PoseTerms`], learnt from annotated faces in every pose, given
//! the head's turn from the runtime's CANDIDE-3 fit ([`HeadTurn`]). There each coefficient is one
//! displacement (a lid, a brow, a lip corner, the lip gap, ...) against the same person's **neutral**, in
//! eye distances, divided by its
//! full movement. The neutral is the per-feature median over the frames of the first
//! [`BlendshapeParams::calibration_s`] of tracking (the quarter of them with the lips closest: a person may talk meanwhile), so a resting face
//! reads near 0 whoever it is; each aligner calibrates its own (see [`BlendshapeEstimator`]). Until then it is
//! another aligner's, else the median of the frames so far (from the fifth), else (the first frames, still
//! images) a mean face's (the 300-W mean shape). Once calibrated, the neutral follows the face as it settles:
//! a frame that already reads near rest (every coefficient at most 0.25, the lips closed as in the neutral)
//! moves it by an exponential mean over 150 frames (5 s at 30 fps), so a first second that was not quite at
//! rest (brows raised to start talking) wears off, while a held expression or speech never moves it.
//! The lids (`eyeBlink*`, `eyeWide*`) have no dead zone: a hard clamp at the neutral would drop every small
//! lid movement on the open side of it, so within 0.3 of the neutral they follow a soft knee and a resting lid
//! reads 0.075 (`soft_knee`); further out they read like the others.
//! [`BlendshapeEstimator::recalibrate`] starts over (a new person, or a calibration prompt). Without a jaw
//! line (KRFWS's 51 points) the coefficients that read the chin (`jawLeft`, `jawRight`, `mouthClose`) are 0.
//!
//! The full movements of the five that CANDIDE-3 animates (jaw drop, lip stretcher, brow lowerer, lip-corner
//! depressor, eyes closed) are CANDIDE's at weight 1, projected frontally; the others are set in eye distances
//! (see [`Blendshape::full_movement`]). Names and sides follow ARKit: `Left` is the **subject's** left, which
//! is the image's right for a face looking at the camera (iBUG points 42-47, 22-26, 54).
//!
//! Not covered (68 landmarks do not see them): the eight eye-look directions (no iris), `cheekPuff` (no cheek
//! contour in depth), `jawForward` (depth) and `tongueOut`. Pure: no IO, no clock.

use crate::geometry::Point2;

mod features;
mod head_turn;
use features::*;
pub use head_turn::{HeadTurn, PoseTerms};

/// The committed pose terms (`holoface train-blendshapes`; see [`PoseTerms`]).
const POSE_TERMS_TXT: &str = include_str!("../../assets/blendshape_pose.txt");

/// The committed pose terms, parsed once; `None` only in a build whose asset is broken, which its own test
/// (`committed_pose_terms_parse_and_undo_turns`) fails.
fn pose_terms() -> Option<&'static PoseTerms> {
    static TERMS: std::sync::OnceLock<Option<PoseTerms>> = std::sync::OnceLock::new();
    TERMS
        .get_or_init(|| PoseTerms::parse(POSE_TERMS_TXT).ok())
        .as_ref()
}

/// Fits the pose terms to annotated shapes (image pixels) and their heads' turns, every pose (pass their
/// mirror images too so that the terms are symmetric). `None` with fewer than 20 usable shapes.
pub fn fit_pose_terms(shapes: &[([Point2; 68], HeadTurn)]) -> Option<PoseTerms> {
    let frames: Vec<([P; 68], HeadTurn)> = shapes
        .iter()
        .filter_map(|(lm, t)| Some((face_frame(lm)?, *t)))
        .collect();
    PoseTerms::fit(&frames)
}

/// The landmarks in the face's frame, with the head's turn undone when it is known
/// ([`PoseTerms::frontalise`]).
fn frame(lm: &[Point2; 68], turn: Option<HeadTurn>) -> Option<[P; 68]> {
    let mut n = face_frame(lm)?;
    if let (Some(terms), Some(turn)) = (pose_terms(), turn) {
        terms.frontalise(&mut n, turn);
    }
    Some(n)
}

/// One ARKit blendshape this module estimates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[allow(missing_docs)] // ARKit's own names say what each is
pub enum Blendshape {
    EyeBlinkLeft,
    EyeBlinkRight,
    EyeSquintLeft,
    EyeSquintRight,
    EyeWideLeft,
    EyeWideRight,
    BrowDownLeft,
    BrowDownRight,
    BrowInnerUp,
    BrowOuterUpLeft,
    BrowOuterUpRight,
    CheekSquintLeft,
    CheekSquintRight,
    NoseSneerLeft,
    NoseSneerRight,
    JawOpen,
    JawLeft,
    JawRight,
    MouthClose,
    MouthFunnel,
    MouthPucker,
    MouthLeft,
    MouthRight,
    MouthSmileLeft,
    MouthSmileRight,
    MouthFrownLeft,
    MouthFrownRight,
    MouthStretchLeft,
    MouthStretchRight,
    MouthPressLeft,
    MouthPressRight,
    MouthRollUpper,
    MouthRollLower,
    MouthShrugUpper,
    MouthShrugLower,
    MouthUpperUpLeft,
    MouthUpperUpRight,
    MouthLowerDownLeft,
    MouthLowerDownRight,
}

/// How many blendshapes are estimated.
pub const N_BLENDSHAPES: usize = 39;

/// ARKit's names of the blendshapes 68 landmarks cannot observe, and why.
pub const NOT_COVERED: [(&str, &str); 13] = [
    ("eyeLookDownLeft", "no iris landmarks"),
    ("eyeLookDownRight", "no iris landmarks"),
    ("eyeLookInLeft", "no iris landmarks"),
    ("eyeLookInRight", "no iris landmarks"),
    ("eyeLookOutLeft", "no iris landmarks"),
    ("eyeLookOutRight", "no iris landmarks"),
    ("eyeLookUpLeft", "no iris landmarks"),
    ("eyeLookUpRight", "no iris landmarks"),
    ("cheekPuff", "no cheek contour in depth"),
    ("jawForward", "a movement in depth"),
    ("tongueOut", "no tongue landmarks"),
    (
        "mouthDimpleLeft",
        "no landmark on the cheek beside the lip corner",
    ),
    (
        "mouthDimpleRight",
        "no landmark on the cheek beside the lip corner",
    ),
];

impl Blendshape {
    /// Every estimated blendshape, in output order (the C ABI's and Python's array order).
    pub const ALL: [Self; N_BLENDSHAPES] = [
        Self::EyeBlinkLeft,
        Self::EyeBlinkRight,
        Self::EyeSquintLeft,
        Self::EyeSquintRight,
        Self::EyeWideLeft,
        Self::EyeWideRight,
        Self::BrowDownLeft,
        Self::BrowDownRight,
        Self::BrowInnerUp,
        Self::BrowOuterUpLeft,
        Self::BrowOuterUpRight,
        Self::CheekSquintLeft,
        Self::CheekSquintRight,
        Self::NoseSneerLeft,
        Self::NoseSneerRight,
        Self::JawOpen,
        Self::JawLeft,
        Self::JawRight,
        Self::MouthClose,
        Self::MouthFunnel,
        Self::MouthPucker,
        Self::MouthLeft,
        Self::MouthRight,
        Self::MouthSmileLeft,
        Self::MouthSmileRight,
        Self::MouthFrownLeft,
        Self::MouthFrownRight,
        Self::MouthStretchLeft,
        Self::MouthStretchRight,
        Self::MouthPressLeft,
        Self::MouthPressRight,
        Self::MouthRollUpper,
        Self::MouthRollLower,
        Self::MouthShrugUpper,
        Self::MouthShrugLower,
        Self::MouthUpperUpLeft,
        Self::MouthUpperUpRight,
        Self::MouthLowerDownLeft,
        Self::MouthLowerDownRight,
    ];

    /// ARKit's name (`ARFaceAnchor.BlendShapeLocation`, as MediaPipe spells it too).
    pub const fn arkit_name(self) -> &'static str {
        match self {
            Self::EyeBlinkLeft => "eyeBlinkLeft",
            Self::EyeBlinkRight => "eyeBlinkRight",
            Self::EyeSquintLeft => "eyeSquintLeft",
            Self::EyeSquintRight => "eyeSquintRight",
            Self::EyeWideLeft => "eyeWideLeft",
            Self::EyeWideRight => "eyeWideRight",
            Self::BrowDownLeft => "browDownLeft",
            Self::BrowDownRight => "browDownRight",
            Self::BrowInnerUp => "browInnerUp",
            Self::BrowOuterUpLeft => "browOuterUpLeft",
            Self::BrowOuterUpRight => "browOuterUpRight",
            Self::CheekSquintLeft => "cheekSquintLeft",
            Self::CheekSquintRight => "cheekSquintRight",
            Self::NoseSneerLeft => "noseSneerLeft",
            Self::NoseSneerRight => "noseSneerRight",
            Self::JawOpen => "jawOpen",
            Self::JawLeft => "jawLeft",
            Self::JawRight => "jawRight",
            Self::MouthClose => "mouthClose",
            Self::MouthFunnel => "mouthFunnel",
            Self::MouthPucker => "mouthPucker",
            Self::MouthLeft => "mouthLeft",
            Self::MouthRight => "mouthRight",
            Self::MouthSmileLeft => "mouthSmileLeft",
            Self::MouthSmileRight => "mouthSmileRight",
            Self::MouthFrownLeft => "mouthFrownLeft",
            Self::MouthFrownRight => "mouthFrownRight",
            Self::MouthStretchLeft => "mouthStretchLeft",
            Self::MouthStretchRight => "mouthStretchRight",
            Self::MouthPressLeft => "mouthPressLeft",
            Self::MouthPressRight => "mouthPressRight",
            Self::MouthRollUpper => "mouthRollUpper",
            Self::MouthRollLower => "mouthRollLower",
            Self::MouthShrugUpper => "mouthShrugUpper",
            Self::MouthShrugLower => "mouthShrugLower",
            Self::MouthUpperUpLeft => "mouthUpperUpLeft",
            Self::MouthUpperUpRight => "mouthUpperUpRight",
            Self::MouthLowerDownLeft => "mouthLowerDownLeft",
            Self::MouthLowerDownRight => "mouthLowerDownRight",
        }
    }

    /// The feature it reads and the feature's change (eye distances, in the face's frame; the sign says
    /// which way is "more") at the full movement, coefficient 1.
    const fn reading(self) -> (Feature, f64) {
        use Feature as F;
        match self {
            // Eyes closed: CANDIDE-3's AUV6 at weight 1 closes the lids by about this much.
            Self::EyeBlinkLeft => (F::LidGap(Side::Left), -EYE_CLOSE),
            Self::EyeBlinkRight => (F::LidGap(Side::Right), -EYE_CLOSE),
            Self::EyeSquintLeft => (F::LowerLid(Side::Left), -0.035),
            Self::EyeSquintRight => (F::LowerLid(Side::Right), -0.035),
            Self::EyeWideLeft => (F::LidGap(Side::Left), 0.06),
            Self::EyeWideRight => (F::LidGap(Side::Right), 0.06),
            // Brow lowerer: CANDIDE-3's AUV3 at weight 1.
            Self::BrowDownLeft => (F::Brow(Side::Left), BROW_DOWN),
            Self::BrowDownRight => (F::Brow(Side::Right), BROW_DOWN),
            Self::BrowInnerUp => (F::InnerBrows, -0.12),
            Self::BrowOuterUpLeft => (F::OuterBrow(Side::Left), -0.12),
            Self::BrowOuterUpRight => (F::OuterBrow(Side::Right), -0.12),
            Self::CheekSquintLeft => (F::LowerLid(Side::Left), -0.05),
            Self::CheekSquintRight => (F::LowerLid(Side::Right), -0.05),
            Self::NoseSneerLeft => (F::NoseWing(Side::Left), -0.05),
            Self::NoseSneerRight => (F::NoseWing(Side::Right), -0.05),
            // Jaw drop: CANDIDE-3's AUV11 at weight 1.
            Self::JawOpen => (F::LipGap, JAW_OPEN),
            Self::JawLeft => (F::ChinX, 0.12),
            Self::JawRight => (F::ChinX, -0.12),
            // The lips closed over a jaw dropped as far as at `jawOpen` 1 (the chin's drop less the lips' gap).
            Self::MouthClose => (F::ClosedJawDrop, JAW_OPEN),
            // The mouth narrowed, while open (funnel) or closed (pucker): see `BlendshapeEstimator::update`.
            Self::MouthFunnel => (F::MouthWidth, -0.15),
            Self::MouthPucker => (F::MouthWidth, -0.15),
            Self::MouthLeft => (F::MouthX, 0.15),
            Self::MouthRight => (F::MouthX, -0.15),
            Self::MouthSmileLeft => (F::CornerY(Side::Left), -0.10),
            Self::MouthSmileRight => (F::CornerY(Side::Right), -0.10),
            // Lip-corner depressor: CANDIDE-3's AUV14 at weight 1.
            Self::MouthFrownLeft => (F::CornerY(Side::Left), FROWN),
            Self::MouthFrownRight => (F::CornerY(Side::Right), FROWN),
            // Lip stretcher: CANDIDE-3's AUV2 at weight 1.
            Self::MouthStretchLeft => (F::CornerOut(Side::Left), STRETCH),
            Self::MouthStretchRight => (F::CornerOut(Side::Right), STRETCH),
            Self::MouthPressLeft => (F::LipThickness(Side::Left), -0.05),
            Self::MouthPressRight => (F::LipThickness(Side::Right), -0.05),
            Self::MouthRollUpper => (F::UpperLipThickness, -0.07),
            Self::MouthRollLower => (F::LowerLipThickness, -0.08),
            Self::MouthShrugUpper => (F::UpperLipY, -0.06),
            Self::MouthShrugLower => (F::LowerLipY, -0.08),
            Self::MouthUpperUpLeft => (F::UpperLipSideY(Side::Left), -0.12),
            Self::MouthUpperUpRight => (F::UpperLipSideY(Side::Right), -0.12),
            Self::MouthLowerDownLeft => (F::LowerLipSideY(Side::Left), 0.20),
            Self::MouthLowerDownRight => (F::LowerLipSideY(Side::Right), 0.20),
        }
    }

    /// The feature change (eye distances) at coefficient 1, signed.
    pub const fn full_movement(self) -> f64 {
        self.reading().1
    }
}

// Full movements measured on CANDIDE-3 (its animation units at weight 1, frontal, in eye distances of the
// face's frame): `models/tests/blendshapes.rs` checks they read their weight.
const EYE_CLOSE: f64 = 0.0601;
const BROW_DOWN: f64 = 0.1096;
const JAW_OPEN: f64 = 0.219;
const FROWN: f64 = 0.140;
const STRETCH: f64 = 0.0918;

/// The coefficients of one face, in [`Blendshape::ALL`] order, each in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Blendshapes(pub [f32; N_BLENDSHAPES]);

impl Default for Blendshapes {
    fn default() -> Self {
        Self([0.0; N_BLENDSHAPES])
    }
}

impl Blendshapes {
    /// One coefficient.
    pub fn get(&self, b: Blendshape) -> f32 {
        Blendshape::ALL
            .iter()
            .position(|&a| a == b)
            .map_or(0.0, |i| self.0[i])
    }

    /// `(name, value)` pairs in output order.
    pub fn iter(&self) -> impl Iterator<Item = (Blendshape, f32)> + '_ {
        Blendshape::ALL.iter().copied().zip(self.0.iter().copied())
    }
}

/// Settings of the estimator.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BlendshapeParams {
    /// Seconds of a track's first frames whose median is the person's neutral (time enters as each frame's
    /// `dt`, so a 25-fps and a 60-fps camera calibrate over the same second).
    pub calibration_s: f64,
}

impl Default for BlendshapeParams {
    fn default() -> Self {
        Self { calibration_s: 1.0 }
    }
}

/// One source's neutral: being calibrated, or done.
#[derive(Clone, Debug, Default)]
struct Calibration {
    /// The calibration frames' features (kept until calibrated).
    seen: Vec<Features>,
    /// The lip-side features' calibration, like `seen`.
    seen_sides: Vec<[f64; 4]>,
    neutral: Option<(Features, [f64; 4])>,
    /// The chin's two features and the lips' gap, calibrated on frames with a jaw line only.
    seen_jaw: Vec<[f64; 3]>,
    neutral_jaw: Option<[f64; 2]>,
    /// Time spanned by `seen` and by `seen_jaw` (the sum of their frames' `dt`), seconds.
    seen_s: f64,
    seen_jaw_s: f64,
}

/// How far apart (eye distances) the inner lips of a closed mouth may read: a few pixels of landmark noise.
const CLOSED_LIPS: f64 = 0.02;

/// The largest inner-lip gap of the calibration frames counted as closed lips: within [`CLOSED_LIPS`] of the
/// gaps' 10th percentile, and at least their lower quartile (infinite without frames).
fn closed_lips(gaps: impl Iterator<Item = f64>) -> f64 {
    let mut gaps: Vec<f64> = gaps.collect();
    gaps.sort_by(f64::total_cmp);
    let at = |q: usize| gaps.get(gaps.len().saturating_sub(1) * q / 100).copied();
    match (at(10), at(25)) {
        (Some(least), Some(quarter)) => quarter.max(least + CLOSED_LIPS),
        _ => f64::INFINITY,
    }
}

/// Half the width of the lids' soft knee ([`soft_knee`]), in coefficient units.
const LID_KNEE: f64 = 0.3;

/// The lids' reading without a dead zone: a lid is never still (a half blink, a squint against the light,
/// the lid following the gaze), and a hard clamp at the neutral drops every movement on the open side of it,
/// so a rig's lid would sit dead still and then jump. Within [`LID_KNEE`] of the neutral the reading follows
/// a parabola that meets 0 and the straight line with their slopes; the neutral itself reads a quarter of
/// the knee (0.075), further out the reading is the plain one.
fn soft_knee(c: f64) -> f64 {
    if c <= -LID_KNEE {
        0.0
    } else if c >= LID_KNEE {
        c
    } else {
        (c + LID_KNEE) * (c + LID_KNEE) / (4.0 * LID_KNEE)
    }
}

/// A frame counts as at rest for the neutral's drift when every coefficient reads at most this and the lips
/// are closed as in the neutral (within [`CLOSED_LIPS`]).
const DRIFT_BELOW: f32 = 0.25;

/// Time constant with which a calibrated neutral follows the resting face (an exponential mean over the frames
/// at rest, each weighing its `dt`), seconds.
const DRIFT_S: f64 = 5.0;

/// Frames after which a calibrating neutral is used provisionally (their median) instead of a mean face's.
const PROVISIONAL_FRAMES: usize = 5;

impl Calibration {
    /// The median of the frames seen so far, once there are [`PROVISIONAL_FRAMES`]: a person's face is closer
    /// to its own first frames than to a mean face.
    fn provisional(&self) -> Option<(Features, [f64; 4])> {
        (self.seen.len() >= PROVISIONAL_FRAMES).then(|| self.resting())
    }

    /// The neutral of the frames seen: the per-feature median over those whose lips are closed
    /// ([`closed_lips`]), so that a person who talks while it calibrates still gets a neutral with the mouth
    /// at rest.
    fn resting(&self) -> (Features, [f64; 4]) {
        let gap = slot(Feature::LipGap);
        let cut = closed_lips(self.seen.iter().map(|f| f[gap]));
        let (mut f, mut s) = (Vec::new(), Vec::new());
        for (a, b) in self.seen.iter().zip(&self.seen_sides) {
            if a[gap] <= cut {
                f.push(*a);
                s.push(*b);
            }
        }
        (median(&f), median(&s))
    }

    /// The chin's neutral, from the jaw frames with closed lips as [`Self::resting`].
    fn resting_jaw(&self) -> [f64; 2] {
        let cut = closed_lips(self.seen_jaw.iter().map(|r| r[2]));
        let kept: Vec<[f64; 2]> = self
            .seen_jaw
            .iter()
            .filter(|r| r[2] <= cut)
            .map(|r| [r[0], r[1]])
            .collect();
        median(&kept)
    }

    fn provisional_jaw(&self) -> Option<[f64; 2]> {
        (self.seen_jaw.len() >= PROVISIONAL_FRAMES).then(|| self.resting_jaw())
    }

    /// Moves the calibrated neutral `dt / DRIFT_S` of the way to a frame at rest ([`DRIFT_S`]): the first second of
    /// tracking is not always at rest (brows raised to speak, eyes narrowed against the light), and a face
    /// settles; only frames that already read near rest move it, so a held expression is never absorbed.
    fn drift(&mut self, f: &Features, s: [f64; 4], jaw_line: bool, dt: f64) {
        let w = (dt / DRIFT_S).clamp(0.0, 1.0);
        let step = |n: &mut f64, v: f64| *n += (v - *n) * w;
        if let Some((n, ns)) = &mut self.neutral {
            n.iter_mut().zip(f).for_each(|(n, &v)| step(n, v));
            ns.iter_mut().zip(s).for_each(|(n, v)| step(n, v));
        }
        if let (true, Some([chin_x, jaw_drop])) = (jaw_line, &mut self.neutral_jaw) {
            step(chin_x, f[slot(Feature::ChinX)]);
            step(jaw_drop, f[slot(Feature::ClosedJawDrop)]);
        }
    }

    /// Takes one frame's features into the calibration while it lasts: until the frames seen span
    /// `calibration_s` (the time between them, and the last one's own `dt`: 30 frames at 30 fps make a
    /// second).
    fn observe(&mut self, f: &Features, s: [f64; 4], jaw_line: bool, dt: f64, calibration_s: f64) {
        let dt = if dt.is_finite() { dt.max(0.0) } else { 0.0 };
        let spans = |seen_s: f64| seen_s + dt >= calibration_s - 1e-9;
        if jaw_line && self.neutral_jaw.is_none() {
            self.seen_jaw.push([
                f[slot(Feature::ChinX)],
                f[slot(Feature::ClosedJawDrop)],
                f[slot(Feature::LipGap)],
            ]);
            if self.seen_jaw.len() > 1 {
                self.seen_jaw_s += dt;
            }
            if spans(self.seen_jaw_s) {
                self.neutral_jaw = Some(self.resting_jaw());
                self.seen_jaw = Vec::new();
            }
        }
        if self.neutral.is_none() {
            self.seen.push(*f);
            self.seen_sides.push(s);
            if self.seen.len() > 1 {
                self.seen_s += dt;
            }
            if spans(self.seen_s) {
                self.neutral = Some(self.resting());
                self.seen = Vec::new();
                self.seen_sides = Vec::new();
            }
        }
    }
}

/// One face's estimator: a neutral per source of landmarks (being calibrated or done).
///
/// Aligners differ systematically (the server's DAN and the headset's KRFWS place a resting mouth a little
/// differently), so each source ([`Self::update_from`]) calibrates its own neutral on its own frames; until
/// it has, it reads against another source's calibrated neutral, else the median of its own first frames
/// (from the fifth), else a mean face's.
#[derive(Clone, Debug)]
pub struct BlendshapeEstimator {
    params: BlendshapeParams,
    /// Per source id, in the order first seen.
    sources: Vec<(u8, Calibration)>,
}

impl BlendshapeEstimator {
    /// An estimator that calibrates on the first frames it sees.
    pub fn new(params: BlendshapeParams) -> Self {
        Self {
            params,
            sources: Vec::new(),
        }
    }

    /// Whether a neutral is calibrated (for any source).
    pub fn is_calibrated(&self) -> bool {
        self.sources.iter().any(|(_, c)| c.neutral.is_some())
    }

    /// Forgets every neutral: the next frames calibrate them again.
    pub fn recalibrate(&mut self) {
        self.sources.clear();
    }

    /// Sets the neutral from landmarks of the person at rest (instead of the first frames), with the head's
    /// turn as for [`Self::update`]; for every source (each calibrated on its own frames afterwards is
    /// replaced).
    pub fn set_neutral(&mut self, lm: &[Point2; 68], turn: Option<HeadTurn>) -> bool {
        let Some(n) = frame(lm, turn) else {
            return false;
        };
        let f = features(&n);
        self.sources = vec![(
            0,
            Calibration {
                neutral_jaw: Some([f[slot(Feature::ChinX)], f[slot(Feature::ClosedJawDrop)]]),
                neutral: Some((f, sides(&n))),
                ..Calibration::default()
            },
        )];
        true
    }

    /// [`Self::update_from`] for one source of landmarks (source 0).
    pub fn update(
        &mut self,
        lm: &[Point2; 68],
        jaw_line: bool,
        turn: Option<HeadTurn>,
        dt: f64,
    ) -> Blendshapes {
        self.update_from(0, lm, jaw_line, turn, dt)
    }

    /// The coefficients of one frame's landmarks (image pixels) from `source` (an aligner's id: each has
    /// its own neutral); all 0 for a degenerate shape. `jaw_line`: whether the jaw points (0-16) were
    /// aligned (not with KRFWS's 51 points). `turn`: the head's turn (from the frame's CANDIDE-3 fit), whose
    /// shift of the landmarks is undone first ([`PoseTerms`]); `None` reads the landmarks as they are (a
    /// still image without a fit). Give it on every frame or on none: the neutral is read the same way.
    /// `dt`: seconds since the face's previous frame (0 for its first, and for a still image): the neutral
    /// calibrates over [`BlendshapeParams::calibration_s`] and follows a resting face with a time constant
    /// of seconds, whatever the frame rate.
    pub fn update_from(
        &mut self,
        source: u8,
        lm: &[Point2; 68],
        jaw_line: bool,
        turn: Option<HeadTurn>,
        dt: f64,
    ) -> Blendshapes {
        let Some(n) = frame(lm, turn) else {
            return Blendshapes::default();
        };
        let f = features(&n);
        let s = sides(&n);
        let k = match self.sources.iter().position(|(id, _)| *id == source) {
            Some(k) => k,
            None => {
                self.sources.push((source, Calibration::default()));
                self.sources.len() - 1
            }
        };
        // This frame's neutral: the source's own once calibrated, else another's, else its own first frames',
        // else a mean face's.
        let own = &self.sources[k].1;
        let pick = |get: fn(&Calibration) -> bool| {
            Some(own)
                .filter(|c| get(c))
                .or_else(|| self.sources.iter().map(|(_, c)| c).find(|c| get(c)))
        };
        let calibrated = own.neutral.is_some();
        let neutral = pick(|c| c.neutral.is_some())
            .and_then(|c| c.neutral)
            .or_else(|| own.provisional());
        let neutral_jaw = pick(|c| c.neutral_jaw.is_some())
            .and_then(|c| c.neutral_jaw)
            .or_else(|| own.provisional_jaw());
        self.sources[k]
            .1
            .observe(&f, s, jaw_line, dt, self.params.calibration_s);
        let (mut f0, s0) = neutral.unwrap_or_else(mean_face);
        // The chin's features from frames that aligned the jaw only (KRFWS's jaw slots hold its start).
        let [chin_x, jaw_drop] = neutral_jaw.unwrap_or_else(|| {
            let m = mean_face().0;
            [m[slot(Feature::ChinX)], m[slot(Feature::ClosedJawDrop)]]
        });
        f0[slot(Feature::ChinX)] = chin_x;
        f0[slot(Feature::ClosedJawDrop)] = jaw_drop;
        let mut out = [0.0f32; N_BLENDSHAPES];
        for (o, b) in out.iter_mut().zip(Blendshape::ALL) {
            let (feat, full) = b.reading();
            if !jaw_line && matches!(feat, Feature::ChinX | Feature::ClosedJawDrop) {
                continue;
            }
            let (now, rest) = match side_slot(feat) {
                Some(k) => (s[k], s0[k]),
                None => (value(&f, &n, feat), f0[slot(feat)]),
            };
            let mut c = (now - rest) / full;
            if matches!(feat, Feature::LidGap(_)) {
                c = soft_knee(c);
            }
            // `+ 0.0`: a movement of exactly 0 reads 0, never -0.
            *o = if c.is_finite() {
                (c.clamp(0.0, 1.0) + 0.0) as f32
            } else {
                0.0
            };
        }
        // A narrowed mouth is a funnel as far as the jaw is open, a pucker as far as it is closed.
        let open = out[index(Blendshape::JawOpen)];
        out[index(Blendshape::MouthFunnel)] *= open;
        out[index(Blendshape::MouthPucker)] *= 1.0 - open;
        let gap = slot(Feature::LipGap);
        if calibrated && (f[gap] - f0[gap]).abs() <= CLOSED_LIPS && out.iter().all(|&v| v <= DRIFT_BELOW) {
            self.sources[k].1.drift(&f, s, jaw_line, dt);
        }
        Blendshapes(out)
    }
}

impl Blendshapes {
    /// The mean of a left/right pair (or the one value).
    fn both(&self, left: Blendshape, right: Blendshape) -> f64 {
        0.5 * (f64::from(self.get(left)) + f64::from(self.get(right)))
    }

    /// HoloFace's five expression weights (CANDIDE-3's units), derived from the coefficients, each in
    /// [-1, 1] with the old signs: jaw drop `jawOpen`; lip stretcher `mouthStretch`; brow lowerer `browDown`
    /// less the brows' raise (negative: raised); lip-corner depressor `mouthFrown` less `mouthSmile`
    /// (negative: a smile); eyes closed `eyeBlink` less `eyeWide`.
    pub fn expression_weights(&self) -> crate::expression::ExpressionWeights {
        use Blendshape as B;
        crate::expression::ExpressionWeights([
            f64::from(self.get(B::JawOpen)),
            self.both(B::MouthStretchLeft, B::MouthStretchRight),
            self.both(B::BrowDownLeft, B::BrowDownRight) - self.brows_raised(),
            self.both(B::MouthFrownLeft, B::MouthFrownRight) - self.smile(),
            self.both(B::EyeBlinkLeft, B::EyeBlinkRight) - self.both(B::EyeWideLeft, B::EyeWideRight),
        ])
    }

    /// A smile: the mean of `mouthSmileLeft/Right`.
    pub fn smile(&self) -> f64 {
        self.both(Blendshape::MouthSmileLeft, Blendshape::MouthSmileRight)
    }

    /// The brows' raise: `browInnerUp` or the outer brows' mean, the larger.
    pub fn brows_raised(&self) -> f64 {
        f64::from(self.get(Blendshape::BrowInnerUp))
            .max(self.both(Blendshape::BrowOuterUpLeft, Blendshape::BrowOuterUpRight))
    }
}

/// Where `b` is in [`Blendshape::ALL`].
fn index(b: Blendshape) -> usize {
    Blendshape::ALL.iter().position(|&a| a == b).unwrap_or(0)
}

/// The neutral of a mean face (the 300-W mean shape), before a person's is calibrated.
fn mean_face() -> (Features, [f64; 4]) {
    static MEAN: std::sync::OnceLock<(Features, [f64; 4])> = std::sync::OnceLock::new();
    *MEAN.get_or_init(|| {
        let n = frame(&crate::shape::dan_mean_shape(), None).unwrap_or([(0.0, 0.0); 68]);
        (features(&n), sides(&n))
    })
}

/// The lip-side features, calibrated like the others.
fn sides(n: &[P; 68]) -> [f64; 4] {
    [n[52].1, n[50].1, n[56].1, n[58].1]
}

fn side_slot(f: Feature) -> Option<usize> {
    match f {
        Feature::UpperLipSideY(Side::Left) => Some(0),
        Feature::UpperLipSideY(Side::Right) => Some(1),
        Feature::LowerLipSideY(Side::Left) => Some(2),
        Feature::LowerLipSideY(Side::Right) => Some(3),
        _ => None,
    }
}

/// The per-element median of `rows`.
fn median<const N: usize>(rows: &[[f64; N]]) -> [f64; N] {
    let mut out = [0.0; N];
    let mut col = Vec::with_capacity(rows.len());
    for (k, o) in out.iter_mut().enumerate() {
        col.clear();
        col.extend(rows.iter().map(|r| r[k]));
        col.sort_by(f64::total_cmp);
        *o = match col.len() {
            0 => 0.0,
            n if n % 2 == 1 => col[n / 2],
            n => 0.5 * (col[n / 2 - 1] + col[n / 2]),
        };
    }
    out
}

#[cfg(test)]
mod tests {
    /// A 30-fps camera.
    const DT: f64 = 1.0 / 30.0;
    use super::*;

    /// A face read against its own neutral: the lids at their knee's foot, everything else 0.
    fn at_neutral(b: &Blendshapes) -> bool {
        Blendshape::ALL.iter().zip(b.0).all(|(k, v)| {
            let lid = matches!(k.reading().0, Feature::LidGap(_));
            let expected = if lid { soft_knee(0.0) as f32 } else { 0.0 };
            (v - expected).abs() < 1e-4
        })
    }

    #[test]
    fn the_lids_read_small_moves_on_both_sides_of_the_neutral() {
        let rest = crate::shape::dan_mean_shape();
        let mut e = BlendshapeEstimator::new(BlendshapeParams {
            calibration_s: 5.0 * DT,
        });
        for _ in 0..5 {
            e.update(&rest, true, None, DT);
        }
        // The subject's left upper lid (iBUG 43, 44) moved by `dy` pixels (positive: down, closing).
        let mut lid = |dy: f32| {
            let mut p = rest;
            p[43].y += dy;
            p[44].y += dy;
            let b = e.update(&p, true, None, DT);
            (b.get(Blendshape::EyeBlinkLeft), b.get(Blendshape::EyeWideLeft))
        };
        let neutral = soft_knee(0.0) as f32;
        assert!(neutral < 0.1);
        assert_eq!(lid(0.0), (neutral, neutral));
        let readings: Vec<(f32, f32)> = [-0.3, -0.1, 0.0, 0.1, 0.3].map(&mut lid).to_vec();
        // Each step of the lid moves both readings, the right way: no dead zone at the neutral.
        for w in readings.windows(2) {
            assert!(w[1].0 > w[0].0 && w[1].1 < w[0].1, "{readings:?}");
        }
        // A closed lid still reads the full movement.
        let closed = lid(100.0);
        assert_eq!(closed, (1.0, 0.0));
    }

    #[test]
    fn soft_knee_meets_zero_and_the_line_smoothly() {
        let d = 1e-7;
        for edge in [-LID_KNEE, LID_KNEE] {
            let (below, above) = (soft_knee(edge - d), soft_knee(edge + d));
            assert!((above - below).abs() < 1e-6, "{edge}: {below} {above}");
        }
        assert_eq!(soft_knee(-1.0), 0.0);
        assert_eq!(soft_knee(0.7), 0.7);
        let slope = |c: f64| (soft_knee(c + d) - soft_knee(c - d)) / (2.0 * d);
        assert!((slope(LID_KNEE - 1e-4) - 1.0).abs() < 1e-3);
        assert!(slope(-LID_KNEE + 1e-4).abs() < 1e-3);
    }

    #[test]
    fn each_source_reads_against_its_own_neutral_once_calibrated() {
        let params = BlendshapeParams {
            calibration_s: 5.0 * DT,
        };
        let remote = crate::shape::dan_mean_shape();
        // The local aligner places the resting mouth corners systematically higher.
        let mut local = remote;
        local[48].y -= 1.0;
        local[54].y -= 1.0;
        let smile = |b: &Blendshapes| b.get(Blendshape::MouthSmileLeft);
        let mut e = BlendshapeEstimator::new(params);
        for _ in 0..5 {
            e.update_from(1, &remote, true, None, DT);
        }
        assert!(e.is_calibrated());
        // Before its own neutral, the local source reads against the remote one: the offset shows.
        let first = e.update_from(2, &local, false, None, DT);
        assert!(smile(&first) > 0.2, "{first:?}");
        for _ in 0..5 {
            e.update_from(2, &local, false, None, DT);
        }
        let local_now = e.update_from(2, &local, false, None, DT);
        let remote_now = e.update_from(1, &remote, true, None, DT);
        assert!(
            [local_now, remote_now].iter().all(at_neutral),
            "{local_now:?} {remote_now:?}"
        );
        // Recalibration forgets both.
        e.recalibrate();
        assert!(!e.is_calibrated());
    }

    #[test]
    fn the_neutral_drifts_to_a_settled_face_but_never_absorbs_a_held_expression() {
        let rest = crate::shape::dan_mean_shape();
        // Calibrated while the brows were raised a little (people raise them to start talking).
        let mut raised = rest;
        for p in &mut raised[17..27] {
            p.y -= 1.0;
        }
        let params = BlendshapeParams {
            calibration_s: 5.0 * DT,
        };
        let mut e = BlendshapeEstimator::new(params);
        for _ in 0..5 {
            e.update(&raised, true, None, DT);
        }
        let brow_down = |b: &Blendshapes| b.get(Blendshape::BrowDownLeft);
        let first = e.update(&rest, true, None, DT);
        assert!(brow_down(&first) > 0.05, "{first:?}");
        for _ in 0..(4.0 * DRIFT_S / DT) as usize {
            e.update(&rest, true, None, DT);
        }
        let settled = e.update(&rest, true, None, DT);
        assert!(
            brow_down(&settled) < 0.03 * brow_down(&first),
            "{first:?} {settled:?}"
        );
        // A smile held for 20 s reads the same at its end: frames with a movement are not rest.
        let mut smile = rest;
        smile[48].y -= 2.0;
        smile[54].y -= 2.0;
        let smiling = |b: &Blendshapes| b.get(Blendshape::MouthSmileLeft);
        let start = e.update(&smile, true, None, DT);
        assert!(smiling(&start) > DRIFT_BELOW, "{start:?}");
        for _ in 0..600 {
            e.update(&smile, true, None, DT);
        }
        let end = e.update(&smile, true, None, DT);
        assert_eq!(smiling(&end), smiling(&start));
        // Talking (lips apart) does not move it either.
        let mut open = rest;
        for p in &mut open[65..68] {
            p.y += 1.5;
        }
        let mut before = e.clone();
        for _ in 0..600 {
            e.update(&open, true, None, DT);
        }
        assert_eq!(
            e.update(&rest, true, None, DT),
            before.update(&rest, true, None, DT)
        );
    }

    #[test]
    fn while_calibrating_a_face_reads_against_its_own_first_frames() {
        // A person whose resting mouth corners sit higher than the mean face's.
        let mut face = crate::shape::dan_mean_shape();
        face[48].y -= 1.0;
        face[54].y -= 1.0;
        let mut e = BlendshapeEstimator::new(BlendshapeParams::default());
        let first = e.update(&face, true, None, DT);
        assert!(first.get(Blendshape::MouthSmileLeft) > 0.2, "{first:?}");
        for _ in 1..PROVISIONAL_FRAMES {
            e.update(&face, true, None, DT);
        }
        let sixth = e.update(&face, true, None, DT);
        assert!(!e.is_calibrated() && at_neutral(&sixth), "{sixth:?}");
    }

    #[test]
    fn talking_while_calibrating_still_gives_a_resting_mouth() {
        let closed = crate::shape::dan_mean_shape();
        // The mouth open: the lower lip and the jaw dropped.
        let mut open = closed;
        for i in [5, 6, 7, 8, 9, 10, 11, 55, 56, 57, 58, 59, 65, 66, 67] {
            open[i].y += 6.0;
        }
        let mut e = BlendshapeEstimator::new(BlendshapeParams::default());
        // Talking: open on three frames of every five.
        for k in 0..30 {
            e.update(if k % 5 < 3 { &open } else { &closed }, true, None, DT);
        }
        assert!(e.is_calibrated());
        let rest = e.update(&closed, true, None, DT);
        assert!(at_neutral(&rest), "{rest:?}");
        assert!(e.update(&open, true, None, DT).get(Blendshape::JawOpen) > 0.2);
    }

    #[test]
    fn the_old_weights_come_from_the_coefficients_with_their_old_signs() {
        let mut b = Blendshapes::default();
        let set = |b: &mut Blendshapes, s: Blendshape, v: f32| b.0[index(s)] = v;
        set(&mut b, Blendshape::JawOpen, 0.6);
        set(&mut b, Blendshape::MouthSmileLeft, 0.8);
        set(&mut b, Blendshape::MouthSmileRight, 0.6);
        set(&mut b, Blendshape::BrowInnerUp, 0.5);
        set(&mut b, Blendshape::EyeBlinkLeft, 1.0);
        let w = b.expression_weights();
        use crate::expression::Unit;
        assert!((w[Unit::JawDrop] - 0.6).abs() < 1e-6);
        assert!(
            (w[Unit::LipCornerDepressor] + 0.7).abs() < 1e-6,
            "a smile is negative"
        );
        assert!(
            (w[Unit::BrowLowerer] + 0.5).abs() < 1e-6,
            "raised brows are negative"
        );
        assert!((w[Unit::EyesClosed] - 0.5).abs() < 1e-6);
        assert_eq!(w[Unit::LipStretcher], 0.0);
        assert!((b.smile() - 0.7).abs() < 1e-6 && (b.brows_raised() - 0.5).abs() < 1e-6);
    }

    #[test]
    fn committed_pose_terms_parse_and_undo_turns() {
        let terms = pose_terms().expect("models/assets/blendshape_pose.txt parses");
        // Facing the camera nothing moves; turned, the landmarks move (the chin most of all).
        let mean = face_frame(&crate::shape::dan_mean_shape()).unwrap();
        let mut ahead = mean;
        terms.frontalise(&mut ahead, HeadTurn::default());
        assert_eq!(ahead, mean);
        let mut turned = mean;
        terms.frontalise(
            &mut turned,
            HeadTurn {
                across: 0.4,
                down: 0.0,
            },
        );
        assert!(
            (turned[8].0 - mean[8].0).abs() > 0.05,
            "{:?} {:?}",
            turned[8],
            mean[8]
        );
    }

    #[test]
    fn names_are_arkits_and_cover_what_68_landmarks_see() {
        let names: std::collections::HashSet<&str> = Blendshape::ALL.iter().map(|b| b.arkit_name()).collect();
        assert_eq!(names.len(), N_BLENDSHAPES, "one name each");
        assert_eq!(N_BLENDSHAPES + NOT_COVERED.len(), 52, "ARKit has 52");
        for (n, _) in NOT_COVERED {
            assert!(!names.contains(n), "{n}");
        }
        assert!(
            names.contains("jawOpen") && names.contains("eyeBlinkLeft") && names.contains("mouthSmileRight")
        );
    }

    #[test]
    fn a_resting_face_reads_zero_and_degenerate_shapes_never_give_nan() {
        let rest = crate::shape::dan_mean_shape().map(|p| Point2::new(200.0 + 2.0 * p.x, 150.0 + 2.0 * p.y));
        let mut e = BlendshapeEstimator::new(BlendshapeParams::default());
        for _ in 0..40 {
            let b = e.update(&rest, true, None, DT);
            assert!(at_neutral(&b), "{b:?}");
        }
        assert!(e.is_calibrated());
        let flat = [Point2::new(5.0, 5.0); 68];
        assert_eq!(e.update(&flat, true, None, DT), Blendshapes::default());
        let mut nan = rest;
        nan[10] = Point2::new(f32::NAN, 1.0);
        let b = e.update(&nan, true, None, DT);
        assert!(b.0.iter().all(|v| (0.0..=1.0).contains(v)), "{b:?}");
        e.recalibrate();
        assert!(!e.is_calibrated());
    }

    #[test]
    fn the_chin_is_calibrated_only_on_frames_that_aligned_it() {
        let rest = crate::shape::dan_mean_shape().map(|p| Point2::new(200.0 + 2.0 * p.x, 150.0 + 2.0 * p.y));
        // KRFWS's frames: the jaw slots hold its start, here a chin 20 px off to one side.
        let mut off = rest;
        off[8].x += 20.0;
        let mut e = BlendshapeEstimator::new(BlendshapeParams::default());
        for _ in 0..30 {
            e.update(&off, false, None, DT);
        }
        assert!(e.is_calibrated());
        for _ in 0..30 {
            e.update(&rest, true, None, DT);
        }
        let b = e.update(&rest, true, None, DT);
        assert!(
            b.get(Blendshape::JawLeft) < 1e-4 && b.get(Blendshape::JawRight) < 1e-4,
            "{b:?}"
        );
        // Without a jaw line the chin's coefficients are 0 whatever the slots hold.
        let b = e.update(&off, false, None, DT);
        assert_eq!(
            (b.get(Blendshape::JawLeft), b.get(Blendshape::JawRight)),
            (0.0, 0.0)
        );
    }

    #[test]
    fn the_face_frame_undoes_position_size_and_roll() {
        let base = crate::shape::dan_mean_shape();
        let a = face_frame(&base.map(|p| Point2::new(100.0 + p.x, 80.0 + p.y))).unwrap();
        let (c, s) = (0.3f32.cos(), 0.3f32.sin());
        let moved = base.map(|p| {
            Point2::new(
                400.0 + 3.0 * (c * p.x - s * p.y),
                50.0 + 3.0 * (s * p.x + c * p.y),
            )
        });
        let b = face_frame(&moved).unwrap();
        for (p, q) in a.iter().zip(&b) {
            assert!(
                (p.0 - q.0).abs() < 1e-4 && (p.1 - q.1).abs() < 1e-4,
                "{p:?} {q:?}"
            );
        }
    }
}
