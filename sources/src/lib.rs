//! Where the tools' and the Python package's frames come from: folders of images or one photograph
//! ([`images`], [`source::ImageSequence`]), MP4/H.264 videos in and out ([`video`], feature `h264`),
//! YUV4MPEG2 streams and files ([`y4m`]: a live camera piped through ffmpeg), recorded streams (`.hfrec`,
//! [`source::RecordedStream`]) and pose sidecars that give frames their camera-to-world poses ([`poses`]).
//! [`open_source`] picks the reader from the path. [`output`] makes every file the tools write appear whole
//! or not at all.
//!
//! Every source implements the runtime's [`FrameSource`] trait and hands over
//! [`OwnedFrame`]s; the headset runtime (`holoface-headset-client`) knows only that trait, so a headset app never
//! compiles a video decoder. Constructors report errors with `anyhow` (this is a tools crate: messages name
//! the file and the frame); [`FrameSource::next_frame`] wraps them in [`SourceError::Other`], whole chain in its
//! message.
#![deny(missing_docs)]

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

pub use holoface_headset_client::{FrameSource, OwnedFrame, SourceError};
pub use source::open_source;

/// A source's failure as the runtime's error type. The message is the whole context chain ("cam.y4m: frame 2:
/// ..."), so that `{}` already names the file and the frame.
fn source_error(e: anyhow::Error) -> SourceError {
    SourceError::Other(format!("{e:#}").into())
}
