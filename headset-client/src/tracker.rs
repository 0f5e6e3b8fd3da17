//! The embedding API: one [`FaceTracker`], an options struct with defaults, three running modes and one
//! [`FaceResult`] per frame.
//!
//! ```no_run
//! use holoface_headset_client::tracker::{FaceTracker, RunningMode, TrackerOptions};
//! use holoface_headset_client::frame::Frame;
//! use holoface_models::camera::Intrinsics;
//! use holoface_models::image::GrayView;
//! use holoface_models::math3::Pose;
//!
//! # fn main() -> Result<(), holoface_headset_client::tracker::TrackerError> {
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
use crate::link::{LinkState, LinkStatus, LinkWatch, RemoteOptions};
use crate::session::{FaceUpdate, FrameResult, NoFaceReason, SessionOptions, TrackedFace, TrackerSession};

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
#[derive(Clone, Debug, Default, PartialEq, Eq)]
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
}

impl From<StepError> for TrackerError {
    fn from(e: StepError) -> Self {
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
    /// The link thread could not start.
    #[error("starting the link: {0}")]
    Link(#[from] std::io::Error),
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
}

/// The answer for one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct FaceResult {
    /// The frame's timestamp.
    pub timestamp_us: u64,
    /// Every face tracked in this frame with its stable id, oldest track first (at most
    /// [`SessionOptions::max_faces`]); empty when there is none (`no_face` says why).
    pub faces: Vec<TrackedFace>,
    /// Why the frame has no face (`None` when `faces` is not empty).
    pub no_face: Option<NoFaceReason>,
    /// Which aligner answered the first candidate (`None` when nothing was aligned); per face in
    /// [`FaceUpdate::answered_by`].
    pub answered_by: Option<AnsweredBy>,
    /// Whether the face detector ran on this frame.
    pub detected: bool,
    /// Time per step.
    pub timings: Timings,
    /// With [`AlignerChoice::Remote`]: the link's state after this frame (`Retrying`/`Failed` say why
    /// frames are answered locally). `None` with the local aligner.
    pub link: Option<LinkState>,
}

impl FaceResult {
    /// The oldest tracked face, if any (a one-face view of `faces`).
    pub fn face(&self) -> Option<&FaceUpdate> {
        self.faces.first().map(|f| &f.update)
    }

    /// The one-face view: the oldest face, or "no face" with the reason.
    pub fn first(&self) -> FrameResult {
        match (self.face(), self.no_face) {
            (Some(u), _) => FrameResult::Face(*u),
            (None, reason) => FrameResult::NoFace(reason.unwrap_or(NoFaceReason::NotDetected)),
        }
    }
}

/// Detects, aligns, fits and filters faces frame by frame (see the module docs).
pub struct FaceTracker {
    mode: RunningMode,
    session: TrackerSession,
    aligner: Box<dyn Aligner + Send>,
    link: Option<LinkWatch>,
    last_timestamp: Option<u64>,
}

impl std::fmt::Debug for FaceTracker {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FaceTracker")
            .field("mode", &self.mode)
            .finish_non_exhaustive()
    }
}

impl FaceTracker {
    /// Loads the assets and, for [`AlignerChoice::Remote`], starts connecting in the background.
    pub fn new(opts: TrackerOptions) -> Result<Self, TrackerError> {
        opts.session.validate()?;
        let a = &opts.assets;
        let mut detector = crate::detect::BlazeFace::load(&a.detector, &a.ort_dylib, 1)?;
        if opts.session.max_faces > 1 {
            // Several people in view are smaller in the frame: look at tiles too (see `BlazeFace::tiles`).
            detector.for_several_faces();
        }
        let model = crate::assets::load_face_model(&a.candide)?;
        let krfws = crate::assets::load_krfws(&a.krfws)?;
        let local = crate::align::KrfwsAligner::new(krfws);
        let mut watch = None;
        let aligner: Box<dyn Aligner + Send> = match &opts.aligner {
            AlignerChoice::Local => Box::new(local),
            AlignerChoice::Remote(remote) => {
                let linked = remote.start(local, opts.session.max_faces)?;
                watch = Some(linked.link().watch());
                Box::new(linked)
            }
        };
        let session = TrackerSession::new(Box::new(detector), model, dan_mean_shape(), opts.session);
        Ok(Self {
            mode: opts.mode,
            session,
            aligner,
            link: watch,
            last_timestamp: None,
        })
    }

    /// With [`AlignerChoice::Remote`]: the link's full status (the failure message included); `None` with
    /// the local aligner.
    pub fn link_status(&self) -> Option<LinkStatus> {
        self.link.as_ref().map(LinkWatch::status)
    }

    /// Processes one frame. In `Image` mode every frame starts from a detection.
    pub fn process(&mut self, frame: &Frame<'_>) -> Result<FaceResult, TrackerError> {
        if self.mode == RunningMode::Image {
            self.session.reset();
        } else {
            if let Some(previous) = self.last_timestamp.filter(|&p| frame.timestamp_us <= p) {
                return Err(TrackerError::Timestamp {
                    previous,
                    got: frame.timestamp_us,
                });
            }
            self.last_timestamp = Some(frame.timestamp_us);
        }
        let step = crate::frame_step::step_faces(&mut self.session, &mut *self.aligner, frame)?;
        Ok(FaceResult {
            timestamp_us: frame.timestamp_us,
            no_face: step.faces.no_face_reason(),
            answered_by: step.alignments.first().copied().flatten().map(|a| a.answered_by),
            detected: step.detected,
            faces: step.faces.faces,
            timings: step.timings,
            link: self.link.as_ref().map(|w| w.status().state()),
        })
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
        mut on_result: impl FnMut(Result<FaceResult, TrackerError>) + Send + 'static,
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
            })?;
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
