//! The one trait every reader of frames implements. It lives here, with the readers, and not in the runtime: the
//! runtime takes frames, it never pulls them.

use holoface_runtime::OwnedFrame;

use crate::SourceError;

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
