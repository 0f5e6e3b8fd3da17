//! Error types and the QUIC application close-code table.
//!
//! * [`CloseCode`]: the one table of QUIC application error codes used in
//!   `CONNECTION_CLOSE`, `RESET_STREAM` / `STOP_SENDING`, [`crate::Goaway`] and
//!   [`crate::ErrorMsg`].
//! * [`DecodeError`]: everything that can go wrong turning bytes into a message.
//!   [`DecodeError::Short`] is not a failure on a stream: it means "need more
//!   bytes". It never boxes or allocates.
//! * [`EncodeError`]: a message violates a limit or invariant and was not
//!   encoded (nothing is left in the output buffer).
//! * [`RecordingError`]: reading or writing a recorded-stream file.

use std::fmt;

/// QUIC application close codes of the HoloFace protocol.
///
/// This is the single table of application error codes: it is what a peer
/// puts in a QUIC `CONNECTION_CLOSE` (application variant), in
/// `RESET_STREAM` / `STOP_SENDING` for a frame stream, and in the `reason` /
/// `code` of [`crate::Goaway`] and [`crate::ErrorMsg`]. On the wire in those
/// messages it is a u32 little-endian; QUIC itself carries it as a varint.
///
/// | code | name | meaning |
/// |---:|---|---|
/// | 0 | `NoError` | graceful close, nothing went wrong |
/// | 1 | `BadVersion` | no common protocol version (`ClientHello::version`) |
/// | 2 | `Unauthorized` | token missing or rejected |
/// | 3 | `Malformed` | a message failed to decode ([`DecodeError`]) |
/// | 4 | `TooLarge` | a length exceeded a [`crate::limits`] constant |
/// | 5 | `Overloaded` | the server refuses work (too many clients / frames) |
/// | 6 | `ShuttingDown` | the server is draining; reconnect elsewhere or later |
/// | 7 | `Internal` | a bug or internal failure on the sender's side |
/// | 8 | `ProtocolViolation` | a valid message at the wrong time (out of order, unexpected, duplicate hello) |
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum CloseCode {
    /// Graceful close, nothing went wrong.
    NoError = 0,
    /// No common protocol version.
    BadVersion = 1,
    /// Token missing or rejected.
    Unauthorized = 2,
    /// A message failed to decode.
    Malformed = 3,
    /// A length exceeded its limit.
    TooLarge = 4,
    /// The server refuses work because it is overloaded.
    Overloaded = 5,
    /// The server is shutting down.
    ShuttingDown = 6,
    /// Internal failure on the sender's side.
    Internal = 7,
    /// A well-formed message arrived when it was not allowed.
    ProtocolViolation = 8,
}

impl CloseCode {
    /// Every code, in numeric order.
    pub const ALL: [Self; 9] = [
        Self::NoError,
        Self::BadVersion,
        Self::Unauthorized,
        Self::Malformed,
        Self::TooLarge,
        Self::Overloaded,
        Self::ShuttingDown,
        Self::Internal,
        Self::ProtocolViolation,
    ];

    /// The snake_case name logs, metric labels and tools use for this code.
    pub const fn name(self) -> &'static str {
        match self {
            Self::NoError => "no_error",
            Self::BadVersion => "bad_version",
            Self::Unauthorized => "unauthorized",
            Self::Malformed => "malformed",
            Self::TooLarge => "too_large",
            Self::Overloaded => "overloaded",
            Self::ShuttingDown => "shutting_down",
            Self::Internal => "internal",
            Self::ProtocolViolation => "protocol_violation",
        }
    }

    /// The numeric code (what goes into QUIC and onto the wire).
    pub const fn as_u32(self) -> u32 {
        self as u32
    }

    /// The code for a number, or `None` if the number is not in the table.
    pub const fn from_u32(code: u32) -> Option<Self> {
        Some(match code {
            0 => Self::NoError,
            1 => Self::BadVersion,
            2 => Self::Unauthorized,
            3 => Self::Malformed,
            4 => Self::TooLarge,
            5 => Self::Overloaded,
            6 => Self::ShuttingDown,
            7 => Self::Internal,
            8 => Self::ProtocolViolation,
            _ => return None,
        })
    }

    /// A short, static, human-readable reason (also usable as the QUIC
    /// close reason bytes).
    pub const fn reason(self) -> &'static str {
        match self {
            Self::NoError => "no error",
            Self::BadVersion => "unsupported protocol version",
            Self::Unauthorized => "unauthorized",
            Self::Malformed => "malformed message",
            Self::TooLarge => "message or field too large",
            Self::Overloaded => "server overloaded",
            Self::ShuttingDown => "server shutting down",
            Self::Internal => "internal error",
            Self::ProtocolViolation => "protocol violation",
        }
    }
}

impl fmt::Display for CloseCode {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.reason(), self.as_u32())
    }
}

impl From<CloseCode> for u32 {
    fn from(code: CloseCode) -> Self {
        code.as_u32()
    }
}

/// Decoding a message (or a recording body) failed.
///
/// Cheap to construct: no variant allocates or boxes.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum DecodeError {
    /// The input ended early: at least `needed` more bytes are required.
    ///
    /// On a stream this means "read more and try again"; for a complete
    /// buffer (a datagram, a whole message) it means the input was truncated.
    #[error("need at least {needed} more bytes")]
    Short {
        /// Minimum number of additional bytes required to make progress.
        needed: usize,
    },
    /// A length prefix or count exceeds its limit (checked before allocating).
    #[error("{field}: length {len} exceeds the limit {max}")]
    TooLarge {
        /// The field whose length was too large.
        field: &'static str,
        /// The length read from the input.
        len: usize,
        /// The limit for that field.
        max: usize,
    },
    /// An enum field holds a value this version does not know.
    #[error("{field}: unknown value {value}")]
    UnknownValue {
        /// The field (message tag, encoding, drop reason, ...).
        field: &'static str,
        /// The value read from the input.
        value: u64,
    },
    /// A string field is not valid UTF-8.
    #[error("{field}: invalid UTF-8")]
    InvalidUtf8 {
        /// The string field.
        field: &'static str,
    },
    /// A float field is NaN or infinite.
    #[error("{field}: non-finite float")]
    NonFinite {
        /// The float field.
        field: &'static str,
    },
    /// Two fields that must agree do not (e.g. `mean_shape` length vs
    /// `landmark_count`).
    #[error("{field}: expected {expected} entries, got {actual}")]
    LengthMismatch {
        /// The field whose length is wrong.
        field: &'static str,
        /// The length required by the other field.
        expected: usize,
        /// The length found.
        actual: usize,
    },
    /// Image dimensions are zero or above the limit.
    #[error("image dimensions {width}x{height} outside 1..={max}")]
    BadDimensions {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Largest allowed width and height.
        max: u32,
    },
    /// A raw (gray8) image payload does not hold exactly `width * height` bytes.
    #[error("raw image {width}x{height} needs {expected} bytes, got {len}")]
    RawSizeMismatch {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// `width * height`.
        expected: usize,
        /// Payload length found.
        len: usize,
    },
    /// Bytes were left over after a complete message or body.
    #[error("{len} trailing bytes after the message")]
    TrailingBytes {
        /// Number of bytes left over.
        len: usize,
    },
    /// A complete length-prefixed frame ended before the message inside it did.
    #[error("frame of {frame_len} bytes ends {needed} bytes before its message")]
    ShortFrame {
        /// The frame length from the prefix.
        frame_len: usize,
        /// How many more bytes the message needed.
        needed: usize,
    },
}

impl DecodeError {
    /// `true` for [`DecodeError::Short`], i.e. "need more bytes".
    pub const fn is_short(&self) -> bool {
        matches!(self, Self::Short { .. })
    }

    /// The close code to send to the peer that sent the undecodable bytes.
    pub const fn close_code(&self) -> CloseCode {
        match self {
            Self::TooLarge { .. } => CloseCode::TooLarge,
            _ => CloseCode::Malformed,
        }
    }
}

/// Encoding a message failed because it violates a limit or an invariant.
///
/// The encoders refuse anything the decoders would reject, so a successful
/// encode always decodes on the other side. On error nothing is left behind
/// in the output buffer.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[non_exhaustive]
pub enum EncodeError {
    /// A field is longer than its limit.
    #[error("{field}: length {len} exceeds the limit {max}")]
    TooLarge {
        /// The field.
        field: &'static str,
        /// Its length.
        len: usize,
        /// The limit for that field.
        max: usize,
    },
    /// A float field is NaN or infinite.
    #[error("{field}: non-finite float")]
    NonFinite {
        /// The float field.
        field: &'static str,
    },
    /// Two fields that must agree do not.
    #[error("{field}: expected {expected} entries, got {actual}")]
    LengthMismatch {
        /// The field whose length is wrong.
        field: &'static str,
        /// The length required by the other field.
        expected: usize,
        /// The length found.
        actual: usize,
    },
    /// Image dimensions are zero or above the limit.
    #[error("image dimensions {width}x{height} outside 1..={max}")]
    BadDimensions {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// Largest allowed width and height.
        max: u32,
    },
    /// A raw (gray8) image payload does not hold exactly `width * height` bytes.
    #[error("raw image {width}x{height} needs {expected} bytes, got {len}")]
    RawSizeMismatch {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// `width * height`.
        expected: usize,
        /// Payload length found.
        len: usize,
    },
}

/// Reading or writing a recorded-stream file failed.
///
/// Offsets are byte offsets from the start of the file; for record errors the
/// offset is where the record (its length prefix) starts, and `record_index`
/// counts records from 0, unknown (skipped) kinds included.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RecordingError {
    /// An I/O error other than an unexpected end of file.
    #[error("I/O error: {0}")]
    Io(#[from] std::io::Error),
    /// The file does not start with the recording magic.
    #[error("not a HoloFace recording (magic {found:02x?})")]
    BadMagic {
        /// The first eight bytes found.
        found: [u8; 8],
    },
    /// The file's major version differs from the one this reader supports.
    #[error("unsupported recording version {major}.{minor} (this reader supports {supported_major}.x)")]
    UnsupportedVersion {
        /// Major version in the file.
        major: u16,
        /// Minor version in the file.
        minor: u16,
        /// Major version this reader supports.
        supported_major: u16,
    },
    /// The file ended inside the file header.
    #[error("file ends inside the header at offset {offset}")]
    HeaderTruncated {
        /// Where the file ended.
        offset: u64,
    },
    /// The header body failed its CRC32 check.
    #[error("header CRC mismatch")]
    HeaderCorrupt,
    /// The header body passed its CRC but does not decode.
    #[error("malformed header: {0}")]
    HeaderMalformed(#[source] DecodeError),
    /// The file ended inside a record.
    #[error("file ends inside record {record_index} (record starts at offset {offset})")]
    Truncated {
        /// Index of the incomplete record.
        record_index: u64,
        /// Offset where that record starts.
        offset: u64,
    },
    /// A record body failed its CRC32 check.
    #[error("record {record_index} at offset {offset} fails its CRC check")]
    Corrupt {
        /// Index of the corrupt record.
        record_index: u64,
        /// Offset where that record starts.
        offset: u64,
    },
    /// A record body passed its CRC but does not decode.
    #[error("record {record_index} at offset {offset} is malformed: {source}")]
    Malformed {
        /// Index of the malformed record.
        record_index: u64,
        /// Offset where that record starts.
        offset: u64,
        /// What was wrong with it.
        #[source]
        source: DecodeError,
    },
    /// A length prefix exceeds its limit (checked before allocating).
    #[error("{field}: length {len} exceeds the limit {max}")]
    TooLarge {
        /// The field (`"header"`, `"record"`).
        field: &'static str,
        /// The length found (or to be written).
        len: usize,
        /// The limit.
        max: usize,
    },
    /// A record or header to be written violates a limit or invariant.
    #[error("cannot encode: {0}")]
    Encode(#[from] EncodeError),
}

/// Constructors for the validation errors shared by [`DecodeError`] and
/// [`EncodeError`], so each invariant is checked by one function for both
/// directions.
pub(crate) trait InvalidError: Sized {
    fn too_large(field: &'static str, len: usize, max: usize) -> Self;
    fn non_finite(field: &'static str) -> Self;
    fn length_mismatch(field: &'static str, expected: usize, actual: usize) -> Self;
    fn bad_dimensions(width: u32, height: u32, max: u32) -> Self;
    fn raw_size_mismatch(width: u32, height: u32, expected: usize, len: usize) -> Self;
}

macro_rules! impl_invalid_error {
    ($t:ty) => {
        impl InvalidError for $t {
            fn too_large(field: &'static str, len: usize, max: usize) -> Self {
                Self::TooLarge { field, len, max }
            }
            fn non_finite(field: &'static str) -> Self {
                Self::NonFinite { field }
            }
            fn length_mismatch(field: &'static str, expected: usize, actual: usize) -> Self {
                Self::LengthMismatch {
                    field,
                    expected,
                    actual,
                }
            }
            fn bad_dimensions(width: u32, height: u32, max: u32) -> Self {
                Self::BadDimensions { width, height, max }
            }
            fn raw_size_mismatch(width: u32, height: u32, expected: usize, len: usize) -> Self {
                Self::RawSizeMismatch {
                    width,
                    height,
                    expected,
                    len,
                }
            }
        }
    };
}

impl_invalid_error!(DecodeError);
impl_invalid_error!(EncodeError);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn close_code_table_round_trips() {
        for (i, code) in CloseCode::ALL.iter().enumerate() {
            assert_eq!(code.as_u32() as usize, i);
            assert_eq!(CloseCode::from_u32(code.as_u32()), Some(*code));
            assert!(!code.reason().is_empty());
        }
        assert_eq!(CloseCode::from_u32(9), None);
        assert_eq!(CloseCode::from_u32(u32::MAX), None);
        assert_eq!(CloseCode::ShuttingDown.to_string(), "server shutting down (6)");
    }

    #[test]
    fn decode_errors_map_to_close_codes() {
        assert_eq!(
            DecodeError::Short { needed: 1 }.close_code(),
            CloseCode::Malformed
        );
        let big = DecodeError::TooLarge {
            field: "token",
            len: 300,
            max: 256,
        };
        assert_eq!(big.close_code(), CloseCode::TooLarge);
        assert_eq!(big.to_string(), "token: length 300 exceeds the limit 256");
    }
}
