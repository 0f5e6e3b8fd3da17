//! Where the tools' and the Python package's frames come from: folders of images or one photograph
//! ([`images`], [`source::ImageSequence`]), MP4/H.264 videos in and out ([`video`], feature `h264`),
//! YUV4MPEG2 streams and files ([`y4m`]: a live camera piped through ffmpeg), recorded streams (`.hfrec`,
//! [`source::RecordedStream`]) and pose sidecars that give frames their camera-to-world poses ([`poses`]).
//! [`open_source`] picks the reader from the path. [`output`] makes every file the tools write appear whole
//! or not at all.
//!
//! Every source implements this crate's [`FrameSource`] trait and hands over
//! [`OwnedFrame`]s; the headset runtime (`holoface-runtime`) knows only that trait, so a headset app never
//! compiles a video decoder. Every function and reader returns [`SourceError`]: what went wrong as a typed
//! variant ([`SourceError::root`]), inside the file and the frame it happened in ([`SourceError::Context`]).
#![deny(missing_docs)]

pub mod error;
#[cfg(feature = "ffmpeg")]
pub mod ffmpeg;
pub mod images;
pub mod output;
pub mod poses;
pub mod source;
#[cfg(feature = "h264")]
pub mod video;
#[cfg(not(feature = "h264"))]
#[path = "video_absent.rs"]
pub mod video;
pub mod y4m;

pub mod frame_source;
pub use error::{ImageError, SourceError};
pub use frame_source::FrameSource;
pub use holoface_runtime::OwnedFrame;

/// A decoded video frame as the runtime takes it: no pose (the identity until a sidecar gives one), the given
/// intrinsics or a 60° horizontal field of view.
#[cfg(any(feature = "h264", feature = "ffmpeg"))]
pub(crate) fn video_frame(
    index: usize,
    timestamp_us: u64,
    image: holoface_models::image::GrayImage,
    intrinsics: Option<holoface_models::camera::Intrinsics>,
) -> OwnedFrame {
    let intrinsics =
        intrinsics.unwrap_or_else(|| holoface_runtime::default_intrinsics(image.width(), image.height()));
    OwnedFrame {
        index,
        timestamp_us,
        image,
        intrinsics,
        world_from_camera: holoface_models::math3::Pose::IDENTITY,
        ground_truth: None,
    }
}

/// Limited-range luma (16–235, what almost every video encoder writes) → full range (0–255), rounded and
/// clamped: video frames get the contrast the aligners were trained on (JPEG/PNG grey levels).
#[cfg_attr(not(any(feature = "h264", feature = "ffmpeg")), allow(dead_code))]
pub(crate) fn full_range_lut() -> [u8; 256] {
    std::array::from_fn(|y| {
        let v = ((y as f64 - 16.0) * 255.0 / 219.0).round();
        v.clamp(0.0, 255.0) as u8
    })
}
pub use source::open_source;
