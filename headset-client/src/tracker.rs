//! The tracker an app holds: the runtime's tracker with its remote or local aligner behind it, and only the
//! calls an app makes (the runtime's generic tracker, its aligners and per-step reports stay the tools').

use holoface_runtime::{Frame, FrameResult, LinkInfo, TrackerError, TrackerOptions};

use crate::results::FaceModel;

/// Detects, aligns, fits and filters faces frame by frame: one call per camera frame, in timestamp order.
///
/// [`TrackerOptions::aligner`] picks the remote aligner (the alignment server over QUIC, the local KRFWS
/// answering while the link is down) or the local one alone.
#[derive(Debug)]
pub struct FaceTracker(holoface_runtime::FaceTracker);

impl FaceTracker {
    /// Loads the assets and, for [`AlignerChoice::Remote`](crate::AlignerChoice::Remote), starts
    /// connecting in the background (the first frames are answered locally until the link is up).
    pub fn new(opts: TrackerOptions) -> Result<Self, TrackerError> {
        holoface_runtime::FaceTracker::new(opts).map(Self)
    }

    /// Processes one frame: every tracked face's result, or why there is none. In
    /// [`RunningMode::Image`](crate::RunningMode::Image) every frame starts from a detection; otherwise a
    /// timestamp not after the previous one ([`TrackerError::Timestamp`]) or an hour past it
    /// ([`TrackerError::TimestampJump`]) is refused, leaving the tracker as it was. A camera pose beyond 10 km
    /// from the world origin is refused in every mode ([`TrackerError::CameraDistance`]).
    pub fn process(&mut self, frame: &Frame<'_>) -> Result<FrameResult, TrackerError> {
        self.0.process(frame)
    }

    /// Forgets every tracked face and the last timestamp: the next frame starts from a detection, at any
    /// timestamp.
    pub fn reset(&mut self) {
        self.0.reset();
    }

    /// Every tracked face calibrates its neutral expression again on its next frames (the blendshape
    /// coefficients then read 0 for the face as it is during those frames; ask the person to rest).
    pub fn recalibrate_blendshapes(&mut self) {
        self.0.recalibrate_blendshapes();
    }

    /// With the remote aligner: the link's full status (the failure message included); `None` with the
    /// local aligner.
    pub fn link_status(&self) -> Option<LinkInfo> {
        self.0.link_status()
    }

    /// The CANDIDE-3 model the faces are fitted with.
    pub fn face_model(&self) -> &FaceModel {
        self.0.face_model()
    }
}
