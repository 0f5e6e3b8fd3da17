//! MP4/H.264 in a build without the `h264` feature: the same types as the real module, but neither can be
//! made. Opening or creating a video is an error that says why, so a tool built lean (`make demo`) fails
//! clearly on a video instead of lacking the command or the option.

use std::convert::Infallible;
use std::path::Path;

use crate::error::fail;
use crate::{FrameSource, SourceError};
use holoface_models::camera::Intrinsics;
use holoface_models::image::GrayImage;
use holoface_runtime::OwnedFrame;

fn absent<T>(path: &Path) -> Result<T, SourceError> {
    fail!(
        Unsupported,
        "{}: this build has no MP4/H.264 support (holoface-sources without its `h264` feature; \
         build the tools with their default features)",
        path.display()
    )
}

/// An MP4/H.264 reader; this build has none, so [`Mp4Source::open`] always fails.
#[derive(Debug)]
pub struct Mp4Source {
    never: Infallible,
}

impl Mp4Source {
    /// Fails: this build reads no MP4.
    pub fn open(path: &Path, _intrinsics: Option<Intrinsics>) -> Result<Self, SourceError> {
        absent(path)
    }

    /// Frames in the video (never called: no value of this type exists).
    pub fn frame_count(&self) -> u32 {
        match self.never {}
    }
}

impl FrameSource for Mp4Source {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        match self.never {}
    }
}

/// An MP4/H.264 writer; this build has none, so [`Mp4Writer::create`] always fails.
#[derive(Debug)]
pub struct Mp4Writer {
    never: Infallible,
}

impl Mp4Writer {
    /// Fails: this build writes no MP4.
    pub fn create(
        path: &Path,
        _width: usize,
        _height: usize,
        _fps: u32,
        _temporaries: &crate::output::Temporaries,
    ) -> Result<Self, SourceError> {
        absent(path)
    }

    /// Never called: no value of this type exists.
    pub fn push(&mut self, _image: &GrayImage) -> Result<(), SourceError> {
        match self.never {}
    }

    /// Never called: no value of this type exists.
    pub fn push_rgb(&mut self, _rgb: &[u8], _stride: usize) -> Result<(), SourceError> {
        match self.never {}
    }

    /// Never called: no value of this type exists.
    pub fn finish(self) -> Result<u64, SourceError> {
        match self.never {}
    }
}
