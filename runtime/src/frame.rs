//! The one frame type: [`Frame`] is a cheap view (borrowed pixels) that the tracker processes, and
//! [`OwnedFrame`] owns its pixels, as frame sources and [`crate::tracker::LiveTracker`] hand them over;
//! [`OwnedFrame::view`] turns one into the other without copying. `holoface_sources::FrameSource` is what every source
//! implements (an app's camera, or the readers of `holoface-sources`: image folders, recordings, MP4 files,
//! pose sidecars), and `holoface_sources::SourceError` is how it fails.

use holoface_models::camera::Intrinsics;
use holoface_models::geometry::Point2;
use holoface_models::image::{GrayImage, GrayView};
use holoface_models::math3::Pose;

/// One camera frame as the tracker sees it: borrowed pixels, timestamp, camera.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    /// Capture time, microseconds on the frame source's clock.
    pub timestamp_us: u64,
    /// Grayscale pixels.
    pub image: GrayView<'a>,
    /// Camera intrinsics in pixels.
    pub intrinsics: Intrinsics,
    /// Camera-to-world transform at capture (identity when unknown).
    pub world_from_camera: Pose,
}

/// The farthest a camera may be from its world's origin, metres: a headset's world is a room, a building or
/// a site, never beyond 10 km (a pose with 1e30 m is corrupt, not a pose). The tracker refuses such a frame, and
/// the pose sidecars of `holoface-sources` refuse such a line, with this one limit.
pub const MAX_CAMERA_DISTANCE_M: f64 = 1e4;

/// The longest a video or live stream's clock may move forward between two frames, microseconds: an hour. A
/// larger step is a corrupt or mis-scaled timestamp (nanoseconds passed as microseconds, `UINT64_MAX`), refused
/// for that frame; a stream that really resumes after a longer pause shows it with a second frame that follows
/// the first (the tracker then starts again from a detection).
pub const MAX_TIMESTAMP_STEP_US: u64 = 3_600_000_000;

/// How far `world_from_camera` puts the camera from its world's origin, when that is beyond
/// [`MAX_CAMERA_DISTANCE_M`] (or not finite): the distance, for the message.
pub fn camera_too_far(world_from_camera: &Pose) -> Option<f64> {
    let t = world_from_camera.translation;
    let distance = t.x.hypot(t.y).hypot(t.z);
    (!distance.is_finite() || distance > MAX_CAMERA_DISTANCE_M).then_some(distance)
}

/// A frame that owns its pixels.
#[derive(Clone, Debug)]
pub struct OwnedFrame {
    /// Index in its source (0 for frames pushed by an app).
    pub index: usize,
    /// Capture time in microseconds.
    pub timestamp_us: u64,
    /// Grayscale pixels.
    pub image: GrayImage,
    /// Camera intrinsics.
    pub intrinsics: Intrinsics,
    /// Camera-to-world pose.
    pub world_from_camera: Pose,
    /// Ground-truth landmarks when the source has them.
    pub ground_truth: Option<Vec<Point2>>,
}

impl OwnedFrame {
    /// A frame from an app's camera: index 0, no ground truth.
    pub fn new(timestamp_us: u64, image: GrayImage, intrinsics: Intrinsics, world_from_camera: Pose) -> Self {
        Self {
            index: 0,
            timestamp_us,
            image,
            intrinsics,
            world_from_camera,
            ground_truth: None,
        }
    }

    /// The borrowed view the tracker processes.
    pub fn view(&self) -> Frame<'_> {
        Frame {
            timestamp_us: self.timestamp_us,
            image: self.image.view(),
            intrinsics: self.intrinsics,
            world_from_camera: self.world_from_camera,
        }
    }
}

/// Intrinsics for a camera with a 60° horizontal field of view and the principal point at the centre, used
/// when a source does not state its own.
pub fn default_intrinsics(width: usize, height: usize) -> Intrinsics {
    let f = 0.5 * width as f64 / (30f64.to_radians()).tan();
    Intrinsics {
        fx: f,
        fy: f,
        cx: 0.5 * (width as f64 - 1.0),
        cy: 0.5 * (height as f64 - 1.0),
    }
}
