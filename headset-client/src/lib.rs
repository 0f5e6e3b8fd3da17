//! The HoloFace headset runtime, the library a headset app embeds: face detection, tracking with an
//! interchangeable aligner (remote DAN over QUIC with KRFWS fallback, or KRFWS alone), CANDIDE-3 fitting,
//! world pose and prediction. The command-line tools live in `holoface-tools` and the readers of image
//! folders, videos and recordings in `holoface-sources`; neither the alignment server nor a video decoder is
//! ever compiled into a headset app.
//!
//! **The app-facing API is this page**: everything an app needs is re-exported here, so an app depends on
//! this one crate. Start with [`FaceTracker`] (or [`LiveTracker`] for a live camera) and [`TrackerOptions`];
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
#![deny(unreachable_pub)]

/// The defaults of every binding, defined once ([`TrackerOptions::default`], the C ABI, Python, the CLI).
#[doc(inline)]
pub use holoface_runtime::defaults;

// The app-facing API.
#[doc(inline)]
pub use holoface_runtime::{
    AlignerChoice, AnsweredBy, Asset, AssetError, AssetPaths, Blendshape, BlendshapeParams, Blendshapes,
    CANDIDE_ENV, Confidence, CropCodec, DETECTOR_ENV, DetectorOptions, FaceResult, FaceTracker, FaceUpdate,
    FailureKind, FilterParams, Frame, FrameResult, FrameSource, HOME_ENV, InitSource, KRFWS_ENV, LandmarkSet,
    LinkFailure, LinkInfo, LinkState, LiveTracker, MAX_DEADLINE, MAX_DETECT_TILES, MAX_LOOKAHEAD_S,
    MAX_TRACKED_FACES, MissingAsset, NoFaceReason, ORT_DYLIB_ENV, OneEuroParams, OwnedFrame, RemoteOptions,
    RemoteOptionsError, RemoteStartError, RunningMode, SessionOptions, SessionOptionsError, SourceError,
    SteadyParams, SteadySettings, Timings, TrackedFace, TrackerError, TrackerOptions, default_intrinsics,
    home, parse_face_model,
};

// The types the API takes and returns, from the algorithms crate (through the runtime).
#[doc(inline)]
pub use holoface_runtime::{
    Attributes, ExpressionWeights, Fingerprint, FitResult, GrayImage, GrayView, Intrinsics, Point2, Pose,
    Quat, Unit, Vec3, WorldPose,
};
