//! The HoloFace headset runtime: face detection, tracking with an interchangeable aligner (remote DAN over
//! QUIC with KRFWS fallback, or KRFWS alone), CANDIDE-3 fitting, world pose and prediction, with every module
//! public for the workspace's tools, load tester and tests (the aligners, the detector, the session, the
//! link's connection). Not a stable API: **an app embeds `holoface-headset-client`**, the facade over this
//! crate, which re-exports the app-facing names of this crate's root.
//!
//! ```no_run
//! use holoface_runtime::{FaceTracker, Frame, GrayView, Intrinsics, Pose, RunningMode, TrackerOptions};
//!
//! # fn main() -> Result<(), holoface_runtime::TrackerError> {
//! let mut tracker = FaceTracker::new(TrackerOptions { mode: RunningMode::Video, ..TrackerOptions::default() })?;
//! let pixels = vec![0u8; 640 * 480];
//! let frame = Frame {
//!     timestamp_us: 0,
//!     image: GrayView::new(&pixels, 640, 480, 640).expect("640x480"),
//!     intrinsics: Intrinsics { fx: 500.0, fy: 500.0, cx: 320.0, cy: 240.0 },
//!     world_from_camera: Pose::IDENTITY,
//! };
//! let result = tracker.process(&frame)?;
//! if let Some(face) = result.face() {
//!     println!("head at {:?} m in the world", face.world.position.to_array());
//! }
//! # Ok(())
//! # }
//! ```
#![deny(missing_docs)]

pub mod adapt;
pub mod align;
pub mod assets;
pub mod crop_codec;
pub mod detect;
pub mod frame;
pub mod frame_step;
pub mod link;
pub mod session;
pub mod tracker;

/// The defaults of every binding, defined once: [`TrackerOptions::default`], the C ABI's
/// `hf_options_default`/`hf_settings_default`, Python's `TrackerOptions()` and the `holoface` CLI's flags all
/// take them from here. The landmark filter's defaults are [`SteadySettings::default`].
pub mod defaults {
    /// Per-frame deadline for the alignment server, ms: one frame interval at 30 fps, so a missed frame is
    /// still answered (deadline + the local aligner) well within two intervals.
    pub const DEADLINE_MS: u64 = 33;
    /// How far ahead the displayed position is predicted, ms (HoloFace: 120).
    pub const LOOKAHEAD_MS: f64 = 120.0;
    /// Crop encoding on the wire: JPEG q75, within 3.3 KB per frame at +1 % relative NME (BENCHMARKS.md).
    pub const CROP_ENCODING: &str = "jpeg:75";
    /// The quality of [`CROP_ENCODING`] (`CropCodec::default()`; a test keeps the two equal).
    pub const CROP_JPEG_QUALITY: u8 = 75;
    /// Faces tracked at once.
    pub const MAX_FACES: usize = 1;
    /// While some but fewer than `max_faces` faces are tracked, the detector runs every this many frames.
    pub const DETECT_EVERY: u32 = 10;
    /// Headset-motion compensation of each frame's initial shape.
    pub const MOTION_COMPENSATION: bool = true;
    /// The landmark filter is on.
    pub const STEADY: bool = true;
    /// With the remote aligner, the local aligner adapts to each tracked person while the link is up
    /// ([`crate::adapt`]).
    pub const ADAPT: bool = true;
    /// The local aligner learns beside every this many remote answers of a face.
    pub const ADAPT_LEARN_EVERY: u32 = 20;
}

// The app-facing API.
pub use adapt::AdaptOptions;
pub use align::AdaptState;
pub use align::AlignError;
pub use align::{AnsweredBy, Confidence, InitSource, LandmarkSet};
pub use assets::{
    Asset, AssetError, AssetPaths, CANDIDE_ENV, DETECTOR_ENV, HOME_ENV, KRFWS_ENV, MissingAsset,
    ORT_DYLIB_ENV, home, parse_face_model,
};
pub use crop_codec::CropCodec;
pub use detect::DetectError;
pub use frame::{Frame, OwnedFrame, default_intrinsics};
pub use frame_step::Timings;
pub use holoface_inference::EngineError;
pub use holoface_models::adapt::AdaptParams;
pub use holoface_models::anchor::{Anchor, AnchorPoint, head_pose};
pub use holoface_models::crop::CropError;
pub use link::{
    FailureKind, LinkFailure, LinkInfo, LinkState, MAX_DEADLINE, RemoteOptions, RemoteOptionsError,
    RemoteStartError, ServerInfo,
};
pub use session::{
    Blendshape, BlendshapeParams, Blendshapes, FaceOutcome, FaceResult, MAX_LOOKAHEAD_S, MAX_TRACKED_FACES,
    NoFaceReason, SessionOptions, SessionOptionsError, SteadySettings,
};
pub use tracker::{
    AlignerChoice, DetectorOptions, FaceTracker, FrameResult, LiveTracker, MAX_DETECT_TILES, RunningMode,
    TrackerError, TrackerOptions,
};

// The types the API takes and returns, from the algorithms crate.
pub use holoface_models::camera::Intrinsics;
pub use holoface_models::candide::{FaceModel, FitOptions, FitResult};
pub use holoface_models::expression::{ExpressionWeights, Unit};
pub use holoface_models::geometry::Point2;
pub use holoface_models::image::{GrayImage, GrayView};
pub use holoface_models::kalman::KalmanParams;
pub use holoface_models::math3::{Pose, Quat, Vec3};
pub use holoface_models::pose::AttributeThresholds;
pub use holoface_models::pose::{Attributes, WorldPose};
pub use holoface_quic::{Fingerprint, TlsError};

// The types those types carry (an error's source, a link's welcome), so that every type of the API can be named.
pub use holoface_models::candide::{CandideError, Wfm};
pub use holoface_models::geometry::Similarity2;
pub use holoface_models::image::ImageError;
pub use holoface_models::math3::Mat3;
