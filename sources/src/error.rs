//! How this crate fails: [`SourceError`], a typed cause inside the file and frame it happened in, and
//! [`ImageError`], why an image could not be decoded.

use std::fmt::Display;
use std::path::PathBuf;

/// Why a source, a pose sidecar or an output file could not be opened, read or written: the one error of this
/// crate's API. [`SourceError::Context`] says where (the file, the frame); [`SourceError::root`] is what went
/// wrong. Its `Display` is the whole chain ("cam.y4m: frame 2: frame 2 has 100 of 4800 luma bytes").
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
    /// A source of one's own failed (a [`crate::FrameSource`] implemented outside this crate).
    #[error(transparent)]
    Other(Box<dyn std::error::Error + Send + Sync>),
    /// Where an error happened (a file, a frame, a step) around what went wrong.
    #[error("{context}: {error}")]
    Context {
        /// Where: "reading image faces/a.png", "cam.y4m: frame 2".
        context: String,
        /// What went wrong.
        error: Box<Self>,
    },
    /// An operating-system error reading or writing (the context around it names the file).
    #[error(transparent)]
    Os(#[from] std::io::Error),
    /// A file the user named is missing, not a regular file, or larger than its kind can be.
    #[error(transparent)]
    File(#[from] holoface_files::FileError),
    /// An image that is not a whole PNG or JPEG, or is over the image-size limit.
    #[error(transparent)]
    Image(#[from] ImageError),
    /// A recorded stream (`.hfrec`) is damaged or of an unknown version.
    #[error(transparent)]
    Recording(#[from] holoface_protocol::RecordingError),
    /// A JSON document (a pose sidecar's line) could not be read or written.
    #[error(transparent)]
    Json(#[from] serde_json::Error),
    /// The input's bytes are not what its format says (a YUV4MPEG2 header, an MP4 box, a pose sidecar's line,
    /// a recording's frame).
    #[error("{0}")]
    Malformed(String),
    /// Nothing to read where something was expected (no images in a folder, no video stream, no poses).
    #[error("{0}")]
    Empty(String),
    /// A well-formed input this build does not read (a codec without FFmpeg, a file kind, a colour format).
    #[error("{0}")]
    Unsupported(String),
    /// An argument out of its range (a frame rate, an output path that names no file).
    #[error("{0}")]
    Usage(String),
    /// The video codec library (OpenH264, FFmpeg) failed.
    #[error("{0}")]
    Codec(String),
}

impl From<holoface_models::image::ImageError> for SourceError {
    fn from(e: holoface_models::image::ImageError) -> Self {
        Self::Image(e.into())
    }
}

/// A number or text field that does not parse is malformed input (the context names the field).
impl From<std::num::ParseIntError> for SourceError {
    fn from(e: std::num::ParseIntError) -> Self {
        Self::Malformed(e.to_string())
    }
}

impl From<std::str::Utf8Error> for SourceError {
    fn from(e: std::str::Utf8Error) -> Self {
        Self::Malformed(e.to_string())
    }
}

impl SourceError {
    /// What went wrong, under every [`SourceError::Context`].
    pub fn root(&self) -> &Self {
        match self {
            Self::Context { error, .. } => error.root(),
            e => e,
        }
    }

    /// This error inside `context` (where it happened).
    pub fn context(self, context: impl Display) -> Self {
        Self::Context {
            context: context.to_string(),
            error: Box::new(self),
        }
    }
}

/// `.context(...)` and `.with_context(|| ...)` on results and options, as anyhow has them, giving a
/// [`SourceError`] (an absent option is [`SourceError::Malformed`]).
pub(crate) trait Context<T> {
    /// The error inside `context`.
    fn context(self, context: impl Display) -> Result<T, SourceError>;
    /// The error inside the context `f` makes (only on failure).
    fn with_context<C: Display>(self, f: impl FnOnce() -> C) -> Result<T, SourceError>;
}

impl<T, E: Into<SourceError>> Context<T> for Result<T, E> {
    fn context(self, context: impl Display) -> Result<T, SourceError> {
        self.map_err(|e| e.into().context(context))
    }

    fn with_context<C: Display>(self, f: impl FnOnce() -> C) -> Result<T, SourceError> {
        self.map_err(|e| e.into().context(f()))
    }
}

impl<T> Context<T> for Option<T> {
    fn context(self, context: impl Display) -> Result<T, SourceError> {
        self.ok_or_else(|| SourceError::Malformed(context.to_string()))
    }

    fn with_context<C: Display>(self, f: impl FnOnce() -> C) -> Result<T, SourceError> {
        self.ok_or_else(|| SourceError::Malformed(f().to_string()))
    }
}

/// `return Err(SourceError::Kind(format!(...)))`.
macro_rules! fail {
    ($kind:ident, $($arg:tt)+) => {
        return Err($crate::SourceError::$kind(format!($($arg)+)))
    };
}

/// `SourceError::Kind(format!(...))` (the video readers' and writer's; a build without them has no use for it).
#[allow(unused_macros)]
macro_rules! err {
    ($kind:ident, $($arg:tt)+) => {
        $crate::SourceError::$kind(format!($($arg)+))
    };
}

/// `if !cond { fail!(Kind, ...) }`.
macro_rules! ensure {
    ($cond:expr, $kind:ident, $($arg:tt)+) => {
        if !$cond {
            $crate::error::fail!($kind, $($arg)+);
        }
    };
}

#[allow(unused_imports)]
pub(crate) use {ensure, err, fail};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_chain_reads_as_one_message_and_the_root_is_typed() {
        let e: Result<(), _> = Err(SourceError::Malformed(
            "frame 2 has 100 of 4800 luma bytes".into(),
        ));
        let e = e.context("frame 2").context("cam.y4m").unwrap_err();
        assert_eq!(
            e.to_string(),
            "cam.y4m: frame 2: frame 2 has 100 of 4800 luma bytes"
        );
        assert!(matches!(e.root(), SourceError::Malformed(_)));
        let missing: Option<u8> = None;
        assert!(matches!(missing.context("no width"), Err(SourceError::Malformed(m)) if m == "no width"));
    }
}

/// Why an image could not be decoded.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ImageError {
    /// Neither PNG nor JPEG.
    #[error("not a PNG or JPEG image")]
    NotAnImage,
    /// A JPEG cut short (decoders would fill the rest with grey and report success).
    #[error("truncated or corrupt JPEG: no end-of-image marker after the scan data ({len} bytes)")]
    TruncatedJpeg {
        /// Bytes the file holds.
        len: usize,
    },
    /// Over the image-size limit (`images::max_image_pixels`).
    #[error(
        "{width} x {height} pixels ({:.1} megapixels) is over the image-size limit of {:.1} megapixels \
         (set {MAX_IMAGE_PIXELS_ENV} to change it)",
        *width as f64 * *height as f64 / 1e6,
        *limit as f64 / 1e6
    )]
    TooLarge {
        /// Width in pixels.
        width: u64,
        /// Height in pixels.
        height: u64,
        /// The limit in pixels.
        limit: u64,
    },
    /// A file larger than any image within the limit can be.
    #[error(
        "image {path} is {len} bytes, more than any image within the image-size limit can need ({most} bytes; \
         {MAX_IMAGE_PIXELS_ENV})"
    )]
    FileTooLarge {
        /// The file.
        path: PathBuf,
        /// Its size.
        len: u64,
        /// The most an image within the limit needs.
        most: u64,
    },
    /// The decoder refused the data.
    #[error(transparent)]
    Decode(#[from] image::ImageError),
    /// The decoded pixels do not make an image of the stated size.
    #[error(transparent)]
    Pixels(#[from] holoface_models::image::ImageError),
}

/// Environment variable that sets another image-size limit (pixels; `images::max_image_pixels`).
pub const MAX_IMAGE_PIXELS_ENV: &str = "HOLOFACE_MAX_IMAGE_PIXELS";
