//! HoloFace wire protocol and recorded-stream format.
//!
//! A headset client streams 112x112 gray face crops over QUIC to an alignment
//! server, which answers with landmarks and a face probability. This crate is
//! only the data and its codec: it has no async runtime, no QUIC stack and no
//! I/O except the `std::io::Read`/`Write` the recording reader and writer are
//! handed. Its normal dependencies are `bytes`, `thiserror` and `crc32fast`.
//!
//! * [`message`]: the wire messages ([`Message`], [`ClientHello`],
//!   [`ServerWelcome`], [`FrameRequest`], [`FrameReply`], [`Goaway`],
//!   [`ErrorMsg`]), whole-buffer [`Message::encode`] / [`Message::decode`] and
//!   length-prefixed [`encode_framed`] / [`decode_framed`] for streams.
//! * [`codec`]: the [`Encode`] / [`Decode`] traits and primitive layout.
//! * [`limits`]: the limit of every variable-length field.
//! * [`error`]: [`DecodeError`], [`EncodeError`], [`RecordingError`] and the
//!   QUIC application close-code table [`CloseCode`].
//! * [`recording`]: the recorded-stream file format ([`RecordingWriter`],
//!   [`RecordingReader`]).
//! * [`framing`]: the one framing (magic, version, length, payload, CRC) of
//!   our other binary files: models, teacher labels, the training cache.
//!
//! # Why a hand-written codec and not serde + bincode/postcard
//!
//! * **Limits before allocation.** Every length prefix is compared with its
//!   [`limits`] constant before a byte is buffered or allocated, with a typed
//!   error naming the field. A generic serde format cannot know that a token
//!   is at most 256 bytes but a crop 32 KiB.
//! * **Zero-copy pixels.** Decoding from [`bytes::Bytes`] slices the crop
//!   payload out of the received buffer (a reference-count bump, no memcpy),
//!   which serde's owned `Vec<u8>` cannot do and borrowed `&[u8]` can only do
//!   with a lifetime tied to the receive buffer.
//! * **No tombstoned or unmaintained dependency.** bincode 3.0.0 is a
//!   tombstone release; the protocol should not hinge on a format crate's
//!   maintenance or on serde attribute semantics.
//! * **A stable byte layout we document ourselves.** The layout is written
//!   down in [`message`] and [`recording`] and pinned by byte-vector unit tests,
//!   so a non-Rust peer (the Unity/C# headset app) can implement it from the
//!   docs, and a dependency upgrade cannot silently change it.
//!
//! `protocol/benches/codec.rs` measures this codec against postcard +
//! serde_bytes on equivalent structs; see `BENCHMARKS.md`.
//!
//! # Decoding guarantees
//!
//! Decoders never panic on any input, allocate at most a field's limit, and
//! return typed errors. [`DecodeError::Short`] means "need more bytes".
#![deny(missing_docs)]

pub mod codec;
pub mod error;
pub mod framing;
pub mod limits;
pub mod message;
pub mod recording;
pub mod text;

pub use codec::{Decode, Encode};
pub use error::{CloseCode, DecodeError, EncodeError, RecordingError};
pub use message::{
    ClientHello, Crop, CropEncoding, DropReason, ErrorMsg, FRAME_PREFIX_LEN, FrameReply, FrameRequest,
    Goaway, Message, ReplyChannel, ReplyOutcome, ServerWelcome, decode_framed, encode_framed, framed_len,
};
pub use recording::{
    CameraIntrinsics, FormatVersion, FramePayload, FrameRecord, RecordingHeader, RecordingReader,
    RecordingWriter,
};
pub use text::untrusted;

/// The newest protocol version, carried in [`ClientHello::version`]. The
/// server serves every version in [`MIN_PROTOCOL_VERSION`]`..=`this one at the
/// client's version and says which in [`ServerWelcome::version`]; any other
/// version is closed with [`CloseCode::BadVersion`].
///
/// History: 1, the first; 2 adds [`DropReason::ModelOutput`] (a version-1
/// client is sent [`DropReason::Overloaded`] instead, see
/// [`DropReason::for_version`]); 3 adds the track id of a frame
/// ([`FrameRequest::track_id`], echoed in [`FrameReply::track_id`]): a
/// non-zero track travels under its own message tags (the track id, then the
/// unchanged body), so every version-1/2 message is a version-3 message of
/// track 0; a client sends a non-zero track only to a server whose welcome
/// says 3 or more (a version-1/2 client that does is closed ProtocolViolation).
pub const PROTOCOL_VERSION: u16 = 3;

/// The oldest protocol version a server still serves.
pub const MIN_PROTOCOL_VERSION: u16 = 1;

/// QUIC ALPN protocol identifier.
pub const ALPN: &[u8] = b"holoface/1";

/// Side of the square face crop the model consumes, in pixels.
pub const CROP_SIZE: usize = 112;

/// Pixels in one crop (`CROP_SIZE * CROP_SIZE` = 12,544 bytes raw gray8).
pub const CROP_PIXELS: usize = CROP_SIZE * CROP_SIZE;
