//! Hard limits for every variable-length field on the wire and in recordings.
//!
//! Every length prefix or element count the decoders read is compared against
//! one of these constants *before* anything is allocated or buffered, so a
//! hostile peer or a corrupt file can make the decoder allocate at most the
//! limit of the field it is decoding. The encoders enforce the same limits, so
//! a message that encodes successfully always decodes on the other side.
//!
//! | field | limit | constant |
//! |---|---|---|
//! | `ClientHello::token` | 256 B | [`MAX_TOKEN_LEN`] |
//! | `ClientHello::client_name`, `ServerWelcome::model_id`, `ServerWelcome::model_version` | 128 B | [`MAX_NAME_LEN`] |
//! | `ClientHello::encodings` | 8 entries | [`MAX_ENCODINGS`] |
//! | landmark lists (`mean_shape`, reply landmarks, ground truth) | 128 points | [`MAX_LANDMARKS`] |
//! | `Crop::data` | 32 KiB | [`MAX_ENCODED_CROP_LEN`] |
//! | `Crop::width`, `Crop::height` | 1024 px | [`MAX_CROP_DIM`] |
//! | `Goaway::text`, `ErrorMsg::text` | 512 B | [`MAX_ERROR_TEXT_LEN`] |
//! | one message (the u32 frame length prefix) | 40 KiB | [`MAX_MESSAGE_LEN`] |
//! | recording header body | 64 KiB | [`MAX_HEADER_LEN`] |
//! | recording source description | 1024 B | [`MAX_SOURCE_LEN`] |
//! | recording record body | 32 MiB | [`MAX_RECORD_LEN`] |
//! | recording full-frame width / height | 8192 px | [`MAX_FULL_FRAME_DIM`] |
//!
//! String limits are in bytes of UTF-8, not characters.

/// Maximum length in bytes of `ClientHello::token`.
pub const MAX_TOKEN_LEN: usize = 256;

/// Maximum length in bytes of a name: `ClientHello::client_name`,
/// `ServerWelcome::model_id` and `ServerWelcome::model_version`.
pub const MAX_NAME_LEN: usize = 128;

/// Maximum number of entries in `ClientHello::encodings`.
pub const MAX_ENCODINGS: usize = 8;

/// Maximum number of landmarks in any landmark list (`ServerWelcome::mean_shape`,
/// `ReplyOutcome::Landmarks::landmarks`, recorded ground truth).
pub const MAX_LANDMARKS: usize = 128;

/// Maximum length in bytes of `Crop::data`, whatever the encoding (32 KiB).
///
/// A raw 112x112 crop is 12,544 B; the limit leaves room for raw crops up to
/// about 181x181 and for badly compressing PNGs.
pub const MAX_ENCODED_CROP_LEN: usize = 32 * 1024;

/// Maximum `Crop::width` and `Crop::height` in pixels.
pub const MAX_CROP_DIM: u16 = 1024;

/// Maximum length in bytes of the human-readable text in `Goaway` and `ErrorMsg`.
pub const MAX_ERROR_TEXT_LEN: usize = 512;

/// Maximum length of one encoded message (tag + body), i.e. the largest value
/// the u32 length prefix of [`crate::encode_framed`] may carry (40 KiB).
///
/// It is larger than the biggest valid message (a `FrameRequest` with a
/// [`MAX_ENCODED_CROP_LEN`] crop), so every valid message fits in one frame.
pub const MAX_MESSAGE_LEN: usize = 40 * 1024;

/// Maximum length of the recording file header body (64 KiB).
pub const MAX_HEADER_LEN: usize = 64 * 1024;

/// Maximum length in bytes of the recording source description.
pub const MAX_SOURCE_LEN: usize = 1024;

/// Maximum length of one recording record body (32 MiB).
pub const MAX_RECORD_LEN: usize = 32 * 1024 * 1024;

/// Maximum width and height in pixels of a recorded full frame.
pub const MAX_FULL_FRAME_DIM: u32 = 8192;

// The biggest FrameRequest must fit in one frame.
const _: () = assert!(MAX_ENCODED_CROP_LEN + 64 <= MAX_MESSAGE_LEN);
