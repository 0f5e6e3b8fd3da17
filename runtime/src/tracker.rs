//! The embedding API: one [`FaceTracker`], an options struct with defaults, three running modes and one
//! [`FrameResult`] per frame.
//!
//! ```no_run
//! use holoface_runtime::tracker::{FaceTracker, RunningMode, TrackerOptions};
//! use holoface_runtime::frame::Frame;
//! use holoface_models::camera::Intrinsics;
//! use holoface_models::image::GrayView;
//! use holoface_models::math3::Pose;
//!
//! # fn main() -> Result<(), holoface_runtime::tracker::TrackerError> {
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

use std::sync::{Arc, Condvar, Mutex, PoisonError};

use holoface_models::shape::dan_mean_shape;

use crate::align::{AlignError, Aligner, AnsweredBy};
pub use crate::assets::AssetPaths;
use crate::detect::DetectError;
use crate::frame::{Frame, OwnedFrame};
use crate::frame_step::StepError;
pub use crate::frame_step::Timings;
use crate::link::{LinkInfo, LinkState, LinkWatch, RemoteOptions};
use crate::session::{FaceResult, NoFaceReason, SessionOptions, TrackerSession};

/// How frames relate to each other.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum RunningMode {
    /// Independent still images: every frame is detected afresh, no temporal filtering.
    Image,
    /// Frames of one video in order (timestamps must increase): detect once, then track.
    #[default]
    Video,
    /// A live camera: like `Video`, but frames are pushed to [`LiveTracker`] and processed on its thread;
    /// a frame that arrives while one is being processed replaces the waiting one (newest wins).
    LiveStream,
}

/// Which aligner answers.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum AlignerChoice {
    /// KRFWS on this device only.
    #[default]
    Local,
    /// DAN (and the server's refinement) on an alignment server, KRFWS when the server misses the deadline
    /// or the link is down.
    Remote(RemoteOptions),
}

/// Everything a [`FaceTracker`] needs; `Default` is local tracking of a video.
#[derive(Clone, Debug, Default)]
pub struct TrackerOptions {
    /// Running mode.
    pub mode: RunningMode,
    /// Asset paths.
    pub assets: AssetPaths,
    /// Aligner.
    pub aligner: AlignerChoice,
    /// Tracker settings (fit, Kalman, look-ahead, attributes, motion compensation).
    pub session: SessionOptions,
    /// Face detector settings.
    pub detector: DetectorOptions,
}

impl TrackerError {
    /// Names the front end's setting of a missing asset in the message (`options`: each asset with the name
    /// the front end gives its path: `--krfws-model`, `HfOptions.krfws_model`, ...). Each front end names its
    /// own; the runtime names none.
    #[must_use]
    pub fn given_by(self, options: &[(crate::assets::Asset, &str)]) -> Self {
        match self {
            Self::Asset(e) => Self::Asset(e.given_by(options)),
            Self::Detect(DetectError::Missing(m)) => Self::Detect(DetectError::Missing(m.given_by(options))),
            other => other,
        }
    }
}

impl TrackerError {
    /// A step's error as the API reports it (a plain function, not `From`, so that the step's own error type
    /// stays out of the facade's API).
    fn from_step(e: StepError) -> Self {
        match e {
            StepError::Detect(e) => Self::Detect(e),
            StepError::Align(e) => Self::Align(e),
        }
    }
}

/// Errors of the embedding API.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TrackerError {
    /// An asset could not be loaded (path and cause in the message).
    #[error(transparent)]
    Asset(#[from] crate::assets::AssetError),
    /// A setting is out of its range.
    #[error(transparent)]
    Options(#[from] crate::session::SessionOptionsError),
    /// The remote aligner could not start (an option out of range, or its thread).
    #[error("starting the link: {0}")]
    Link(#[from] crate::link::RemoteStartError),
    /// [`LiveTracker`]'s worker thread could not be started.
    #[error("starting the live tracker's thread: {0}")]
    Worker(std::io::Error),
    /// Face detection failed.
    #[error(transparent)]
    Detect(#[from] DetectError),
    /// Alignment failed.
    #[error(transparent)]
    Align(#[from] AlignError),
    /// A frame's timestamp is not after the previous one (video and live modes).
    #[error("frame timestamp {got} µs is not after the previous {previous} µs")]
    Timestamp {
        /// The previous timestamp.
        previous: u64,
        /// This frame's.
        got: u64,
    },
    /// A frame's timestamp is more than [`crate::frame::MAX_TIMESTAMP_STEP_US`] after the previous one and
    /// the frame before did not lead up to it (video and live modes): refused, the tracker's clock unchanged.
    #[error(
        "frame timestamp {got} µs is {} s after the previous {previous} µs (at most {} s between frames; a \
         clock in nanoseconds, or a corrupt one?)",
        got.saturating_sub(*previous) / 1_000_000,
        crate::frame::MAX_TIMESTAMP_STEP_US / 1_000_000
    )]
    TimestampJump {
        /// The previous accepted timestamp.
        previous: u64,
        /// This frame's.
        got: u64,
    },
    /// The frame's camera-to-world pose puts the camera beyond [`crate::frame::MAX_CAMERA_DISTANCE_M`].
    #[error(
        "world_from_camera puts the camera {distance:.1e} m from the world origin (at most {} m)",
        crate::frame::MAX_CAMERA_DISTANCE_M
    )]
    CameraDistance {
        /// The camera's distance from the world origin, metres.
        distance: f64,
    },
}

/// The answer for one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameResult {
    /// The frame's timestamp.
    pub timestamp_us: u64,
    /// Every face tracked in this frame with its stable id, oldest track first (at most
    /// [`SessionOptions::max_faces`]); empty when there is none (`no_face` says why).
    pub faces: Vec<FaceResult>,
    /// Why the frame has no face (`None` when `faces` is not empty).
    pub no_face: Option<NoFaceReason>,
    /// Which aligner answered the first candidate (`None` when nothing was aligned); per face in
    /// [`FaceResult::answered_by`].
    pub answered_by: Option<AnsweredBy>,
    /// Whether the face detector ran on this frame.
    pub detected: bool,
    /// Time per step.
    pub timings: Timings,
    /// With [`AlignerChoice::Remote`]: the link's state after this frame (`Retrying`/`Failed` say why
    /// frames are answered locally). `None` with the local aligner.
    pub link: Option<LinkState>,
}

impl FrameResult {
    /// The oldest tracked face, if any (a one-face view of `faces`).
    pub fn face(&self) -> Option<&FaceResult> {
        self.faces.first()
    }
}

/// The face detector's settings.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DetectorOptions {
    /// Tiles per side the detector looks at besides the whole frame (1 = the whole frame only, at most
    /// [`MAX_DETECT_TILES`]). `None`: 1 for one face, 3 with the several-face settings. BlazeFace sees
    /// 128 px: a face narrower than about a tenth of a tile's side is missed.
    pub tiles: Option<usize>,
    /// The several-face settings (3 x 3 tiles, score threshold 0.5) whatever `max_faces` is. `None`: when
    /// [`SessionOptions::max_faces`] is above 1.
    pub several_faces: Option<bool>,
}

/// The most detector tiles per side ([`DetectorOptions::tiles`]).
pub const MAX_DETECT_TILES: usize = 32;

impl DetectorOptions {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), crate::session::SessionOptionsError> {
        match self.tiles {
            Some(t) if !(1..=MAX_DETECT_TILES).contains(&t) => {
                Err(crate::session::SessionOptionsError::DetectTiles(t))
            }
            _ => Ok(()),
        }
    }
}

/// Detects, aligns, fits and filters faces frame by frame (see the module docs).
///
/// Every tracker of the workspace, whatever its aligner, is assembled here ([`FaceTracker::new`]; the
/// tools' own aligners through `with_aligner`): the detector with its settings, CANDIDE-3, the mean shape
/// and the several-face session. An app holds the facade's `FaceTracker`, which wraps this one.
pub struct FaceTracker<A: ?Sized = dyn Aligner + Send> {
    mode: RunningMode,
    session: TrackerSession,
    link: Option<LinkWatch>,
    last_timestamp: Option<u64>,
    /// A timestamp refused as a jump: a next frame that follows it shows the stream really resumed there.
    jumped_to: Option<u64>,
    aligner: Box<A>,
}

impl<A: ?Sized> std::fmt::Debug for FaceTracker<A> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FaceTracker")
            .field("mode", &self.mode)
            .finish_non_exhaustive()
    }
}

/// What every tracker loads before its aligner: the detector with its settings and CANDIDE-3.
struct Parts {
    detector: crate::detect::BlazeFace,
    model: holoface_models::candide::FaceModel,
}

impl Parts {
    fn load(opts: &TrackerOptions) -> Result<Self, TrackerError> {
        opts.session.validate()?;
        opts.detector.validate()?;
        let a = &opts.assets;
        let mut detector = crate::detect::BlazeFace::load(&a.detector, &a.ort_dylib, 1)?;
        if opts.detector.several_faces.unwrap_or(opts.session.max_faces > 1) {
            // Several people in view are smaller in the frame: look at tiles too (see `BlazeFace::tiles`).
            detector.for_several_faces();
        }
        if let Some(tiles) = opts.detector.tiles {
            detector.tiles = tiles;
        }
        let model = crate::assets::load_face_model(&a.candide)?;
        Ok(Self { detector, model })
    }

    /// The one place a [`TrackerSession`] is made.
    fn assemble<A: ?Sized>(
        self,
        opts: &TrackerOptions,
        aligner: Box<A>,
        link: Option<LinkWatch>,
    ) -> FaceTracker<A> {
        FaceTracker {
            mode: opts.mode,
            session: TrackerSession::new(
                Box::new(self.detector),
                self.model,
                dan_mean_shape(),
                opts.session,
            ),
            link,
            last_timestamp: None,
            jumped_to: None,
            aligner,
        }
    }
}

impl FaceTracker {
    /// Loads the assets and, for [`AlignerChoice::Remote`], starts connecting in the background.
    pub fn new(opts: TrackerOptions) -> Result<Self, TrackerError> {
        let parts = Parts::load(&opts)?;
        let local = crate::align::KrfwsAligner::new(crate::assets::load_krfws(&opts.assets.krfws)?);
        let (aligner, link): (Box<dyn Aligner + Send>, _) = match &opts.aligner {
            AlignerChoice::Local => (Box::new(local), None),
            AlignerChoice::Remote(remote) => {
                let linked = crate::link::LinkedAligner::start(remote, local, opts.session.max_faces)?;
                let watch = linked.link().watch();
                (Box::new(linked), Some(watch))
            }
        };
        Ok(parts.assemble(&opts, aligner, link))
    }
}

impl<A: Aligner + ?Sized> FaceTracker<A> {
    /// A tracker around an aligner of the caller's (`opts.aligner` is not used); `link` reports the state
    /// of a remote aligner's link in each result. For the tools, which also run DAN in-process.
    pub fn with_aligner(
        opts: &TrackerOptions,
        aligner: Box<A>,
        link: Option<LinkWatch>,
    ) -> Result<Self, TrackerError> {
        Ok(Parts::load(opts)?.assemble(opts, aligner, link))
    }

    /// The aligner (tools read a remote aligner's counters through it).
    pub fn aligner(&self) -> &A {
        &self.aligner
    }

    /// The aligner back, for a tracker of another sequence (the tools keep a warmed-up remote link).
    pub fn into_aligner(self) -> Box<A> {
        self.aligner
    }

    /// The CANDIDE-3 model the faces are fitted with.
    pub fn face_model(&self) -> &holoface_models::candide::FaceModel {
        self.session.face_model()
    }

    /// Forgets every tracked face and the last timestamp: the next frame starts from a detection, at any
    /// timestamp.
    pub fn reset(&mut self) {
        self.session.reset();
        self.last_timestamp = None;
        self.jumped_to = None;
    }

    /// Every tracked face calibrates its neutral expression again on its next frames (the blendshape
    /// coefficients then read 0 for the face as it is during those frames; ask the person to rest).
    pub fn recalibrate_blendshapes(&mut self) {
        self.session.recalibrate_blendshapes();
    }

    /// With [`AlignerChoice::Remote`]: the link's full status (the failure message included); `None` with
    /// the local aligner.
    pub fn link_status(&self) -> Option<LinkInfo> {
        self.link.as_ref().map(LinkWatch::status)
    }

    /// Processes one frame. In `Image` mode every frame starts from a detection.
    pub fn process(&mut self, frame: &Frame<'_>) -> Result<FrameResult, TrackerError> {
        let step = self.step(frame)?;
        Ok(FrameResult {
            timestamp_us: frame.timestamp_us,
            no_face: step.faces.no_face_reason(),
            answered_by: step.first_alignment().map(|a| a.answered_by),
            detected: step.detected,
            faces: step.faces.faces,
            timings: step.timings,
            link: self.link.as_ref().map(|w| w.status().state()),
        })
    }

    /// [`FaceTracker::process`] with every candidate and alignment of the frame (the tools report them).
    pub fn process_step(&mut self, frame: &Frame<'_>) -> Result<crate::frame_step::StepFrame, TrackerError> {
        self.step(frame)
    }

    /// Accepts a video or live frame's timestamp, or refuses it leaving the clock as it was: one not after the
    /// previous, or one more than an hour after it, unless the frame before was refused as that same jump and
    /// this one follows it (the stream resumed after a pause: tracking starts again from a detection).
    fn check_timestamp(&mut self, got: u64) -> Result<(), TrackerError> {
        let max = crate::frame::MAX_TIMESTAMP_STEP_US;
        if let Some(previous) = self.last_timestamp {
            if got <= previous {
                return Err(TrackerError::Timestamp { previous, got });
            }
            if got - previous > max {
                let resumed = self.jumped_to.is_some_and(|j| got > j && got - j <= max);
                if !resumed {
                    self.jumped_to = Some(got);
                    return Err(TrackerError::TimestampJump { previous, got });
                }
                self.session.reset();
            }
        }
        self.jumped_to = None;
        self.last_timestamp = Some(got);
        Ok(())
    }

    fn step(&mut self, frame: &Frame<'_>) -> Result<crate::frame_step::StepFrame, TrackerError> {
        if let Some(distance) = crate::frame::camera_too_far(&frame.world_from_camera) {
            return Err(TrackerError::CameraDistance { distance });
        }
        if self.mode == RunningMode::Image {
            self.session.reset();
        } else {
            self.check_timestamp(frame.timestamp_us)?;
        }
        crate::frame_step::step_faces(&mut self.session, &mut *self.aligner, frame)
            .map_err(TrackerError::from_step)
    }
}

struct LiveSlot {
    frame: Option<OwnedFrame>,
    closed: bool,
    replaced: u64,
}

/// Live-stream mode: frames are processed on a worker thread and results delivered to a callback.
pub struct LiveTracker {
    slot: Arc<(Mutex<LiveSlot>, Condvar)>,
    worker: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for LiveTracker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveTracker").finish_non_exhaustive()
    }
}

impl LiveTracker {
    /// Starts the worker; `on_result` receives every processed frame's result (or error) on that thread.
    pub fn start(
        opts: TrackerOptions,
        mut on_result: impl FnMut(Result<FrameResult, TrackerError>) + Send + 'static,
    ) -> Result<Self, TrackerError> {
        let mut tracker = FaceTracker::new(TrackerOptions {
            mode: RunningMode::LiveStream,
            ..opts
        })?;
        let slot = Arc::new((
            Mutex::new(LiveSlot {
                frame: None,
                closed: false,
                replaced: 0,
            }),
            Condvar::new(),
        ));
        let worker_slot = Arc::clone(&slot);
        let worker = std::thread::Builder::new()
            .name("holoface-live".into())
            .spawn(move || {
                let (lock, cv) = &*worker_slot;
                loop {
                    let frame = {
                        let mut s = lock.lock().unwrap_or_else(PoisonError::into_inner);
                        while s.frame.is_none() && !s.closed {
                            s = cv.wait(s).unwrap_or_else(PoisonError::into_inner);
                        }
                        match s.frame.take() {
                            Some(f) => f,
                            None => return,
                        }
                    };
                    on_result(tracker.process(&frame.view()));
                }
            })
            .map_err(TrackerError::Worker)?;
        Ok(Self {
            slot,
            worker: Some(worker),
        })
    }

    /// Hands a frame to the worker without waiting; a frame still waiting is replaced (newest wins).
    pub fn push(&self, frame: OwnedFrame) {
        let (lock, cv) = &*self.slot;
        let mut s = lock.lock().unwrap_or_else(PoisonError::into_inner);
        if s.frame.replace(frame).is_some() {
            s.replaced += 1;
        }
        cv.notify_one();
    }

    /// Frames replaced before the worker got to them.
    pub fn replaced(&self) -> u64 {
        self.slot
            .0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .replaced
    }
}

impl Drop for LiveTracker {
    /// Processes the frame still waiting, then stops the worker.
    fn drop(&mut self) {
        let (lock, cv) = &*self.slot;
        lock.lock().unwrap_or_else(PoisonError::into_inner).closed = true;
        cv.notify_one();
        if let Some(w) = self.worker.take() {
            let _ = w.join();
        }
    }
}
