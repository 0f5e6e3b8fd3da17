//! The one trait every reader of frames implements, and how it fails. It lives here, with the readers, and
//! not in the runtime: the runtime takes frames, it never pulls them.

use holoface_runtime::OwnedFrame;

/// A sequence of frames: what every reader of this crate is (image folders, videos, `.hfrec` recordings, y4m on
/// standard input), and what a camera of one's own implements to feed the tools' loops.
pub trait FrameSource {
    /// The next frame, `Ok(None)` at the end.
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError>;
}

impl FrameSource for Box<dyn FrameSource> {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        (**self).next_frame()
    }
}

/// Why a [`FrameSource`] could not hand over its next frame.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum SourceError {
    /// Reading the source failed (a file, a pipe, a camera device).
    #[error("reading {what}: {source}")]
    Io {
        /// What was being read (a path, `stdin`, a device name).
        what: String,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// The source's data is not a valid frame.
    #[error("{what}, frame {frame}: {reason}")]
    Invalid {
        /// The source (a path, `stdin`, a device name).
        what: String,
        /// The frame's index in the source.
        frame: usize,
        /// What is wrong with it.
        reason: String,
    },
    /// A source's own error (the readers of `holoface-sources` report through this, with the file and the
    /// frame in the message).
    #[error(transparent)]
    Other(Box<dyn std::error::Error + Send + Sync>),
}
