//! The HoloFace headset runtime, the library a headset app embeds: face detection, tracking with an
//! interchangeable aligner (remote DAN over QUIC with KRFWS fallback, or KRFWS alone), CANDIDE-3 fitting,
//! world pose and prediction. The command-line tools live in `holoface-tools` and the readers of image
//! folders, videos and recordings in `holoface-sources`; neither the alignment server nor a video decoder is
//! ever compiled into a headset app.
//!
//! **The app-facing API is this crate**: what most apps name is at this root, every other type of the API in
//! a module named for what it holds ([`options`], [`results`], [`errors`], ...), so an app depends on this one
//! crate. Start with [`FaceTracker`] (or [`LiveTracker`] for a live camera) and [`TrackerOptions`];
//! each [`Frame`] gets a [`FrameResult`] with one [`FaceResult`] per tracked face, or the reason there is
//! none.
//!
//! ```no_run
//! use holoface_headset_client::{FaceTracker, Frame, GrayView, Intrinsics, Pose, RunningMode, TrackerOptions};
//!
//! # fn main() -> Result<(), holoface_headset_client::TrackerError> {
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
//!
//! **Coordinate frames.** Landmarks are in image pixels (origin top-left, x right, y down). `fit` is the head
//! in the *camera* frame (OpenCV axes: x right, y down, z forward; metres). `world`, `predicted_position` and
//! `display` are in the *world* frame of the `world_from_camera` poses the caller supplies.
//!
//! This crate is the facade over `holoface-runtime`, whose modules (the aligners, the detector, the session,
//! the link's connection) the workspace's tools, load tester and tests use; an app needs only the names here.
#![deny(missing_docs)]
#![deny(unreachable_pub, unnameable_types)]

/// The defaults of every binding, defined once ([`TrackerOptions::default`], the C ABI, Python, the CLI).
#[doc(inline)]
pub use holoface_runtime::defaults;

// The tracker, its options, a frame and what it gives back: what most apps name.
mod tracker;
#[doc(inline)]
pub use holoface_runtime::{
    AlignerChoice, DetectorOptions, FaceResult, Frame, FrameResult, GrayImage, GrayView, Intrinsics,
    LiveTracker, NoFaceReason, OwnedFrame, Pose, RemoteOptions, RunningMode, SessionOptions, TrackerError,
    TrackerOptions,
};
pub use tracker::FaceTracker;

/// Every setting of [`SessionOptions`] and [`DetectorOptions`] and their limits.
pub mod options {
    #[doc(inline)]
    pub use holoface_runtime::{
        AdaptOptions, AdaptParams, BlendshapeParams, CropCodec, MAX_DEADLINE, MAX_DETECT_TILES,
        MAX_LOOKAHEAD_S, MAX_TRACKED_FACES, SteadySettings,
    };
    #[doc(inline)]
    pub use holoface_runtime::{AttributeThresholds, FitOptions, KalmanParams};
}

/// The parts of a [`FrameResult`] and a [`FaceResult`].
pub mod results {
    #[doc(inline)]
    pub use holoface_runtime::{
        AdaptState, AnsweredBy, Attributes, Blendshape, Blendshapes, Confidence, ExpressionWeights,
        FaceModel, FitResult, InitSource, LandmarkSet, Timings, Unit, WorldPose,
    };
}

/// The parts of a [`TrackerError`] and the other errors of the API, each one an app can match.
pub mod errors {
    #[doc(inline)]
    pub use holoface_runtime::{
        AlignError, AssetError, CandideError, CropError, DetectError, EngineError, ImageError, MissingAsset,
        RemoteOptionsError, RemoteStartError, SessionOptionsError, TlsError,
    };
}

/// The remote aligner's link, as each [`FrameResult`] reports it.
pub mod link {
    #[doc(inline)]
    pub use holoface_runtime::{FailureKind, Fingerprint, LinkFailure, LinkInfo, LinkState, ServerInfo};
}

/// The models and libraries the tracker loads, and where it looks for them.
pub mod assets {
    #[doc(inline)]
    pub use holoface_runtime::{
        Asset, AssetPaths, CANDIDE_ENV, DETECTOR_ENV, HOME_ENV, KRFWS_ENV, ORT_DYLIB_ENV, Wfm, home,
        parse_face_model,
    };
}

/// Objects anchored on a face: where a virtual object (glasses, a hat) sits in the world for a face, from its
/// display pose ([`FaceResult::display`]) and a point of the fitted head ([`FaceModel`](results::FaceModel),
/// [`FaceTracker::face_model`]). `Anchor::world_from_object(model, &display_pose(face))` is what the tools'
/// renderer (`holoface track --augment`), the C ABI (`hf_tracker_anchor`) and the Unity sample place.
pub mod anchor {
    #[doc(inline)]
    pub use holoface_runtime::{Anchor, AnchorPoint};

    /// A face's display pose (predicted for display, head → world) as a transform.
    pub fn display_pose(face: &holoface_runtime::FaceResult) -> holoface_runtime::Pose {
        crate::geometry::head_pose(face.display.0, face.display.1)
    }
}

/// Points, rotations and the camera, as the API takes and returns them.
pub mod geometry {
    #[doc(inline)]
    pub use holoface_runtime::{Mat3, Point2, Quat, Similarity2, Vec3, default_intrinsics, head_pose};
}
