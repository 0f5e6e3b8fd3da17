//! The wire messages and their byte layout.
//!
//! A message is a one-byte tag followed by the body of that message type. On
//! a QUIC datagram, or a unidirectional stream carrying exactly one message,
//! the whole buffer is one message ([`Message::encode`] / [`Message::decode`]).
//! On a stream carrying several messages each one is preceded by a `u32`
//! little-endian length ([`encode_framed`] / [`decode_framed`]), capped at
//! [`MAX_MESSAGE_LEN`].
//!
//! Primitive encodings are described in [`crate::codec`]: integers and `f32`
//! are little-endian, `str` is a `u16` byte length + UTF-8, `points` is a
//! `u16` count + `count` × (`f32` x, `f32` y), `payload` is a `u32` byte
//! length + bytes. Floats must be finite.
//!
//! | tag | message | direction |
//! |---:|---|---|
//! | `0x01` | [`ClientHello`] | client → server, first message on the control stream |
//! | `0x02` | [`ServerWelcome`] | server → client, answer to the hello |
//! | `0x03` | [`FrameRequest`] | client → server, one per frame stream |
//! | `0x04` | [`FrameReply`] | server → client, datagram or stream (see [`ReplyChannel`]) |
//! | `0x05` | [`Goaway`] | server → client, graceful shutdown |
//! | `0x06` | [`ErrorMsg`] | either way, just before closing |
//! | `0x07` | [`FrameRequest`] with a non-zero `track_id` (version 3) | client → server |
//! | `0x08` | [`FrameReply`] with a non-zero `track_id` (version 3) | server → client |
//!
//! Body layouts (offsets are relative to the start of the body, after the tag):
//!
//! ```text
//! ClientHello    version u16 | token str(<=256) | client_name str(<=128)
//!                | encodings: u8 count(<=8), count x u8 | max_in_flight u16
//! ServerWelcome  version u16 | model_id str(<=128) | model_version str(<=128)
//!                | landmark_count u16 | crop_size u16 | mean_shape points(<=128, == landmark_count)
//!                | face_threshold f32 | encoding u8 | reply_channel u8
//!                | max_in_flight u16 | max_frame_age_ms u32
//! FrameRequest   frame_id u64 | captured_at_us u64 | deadline_ms u16 | crop
//! Crop           encoding u8 | width u16 | height u16 | data payload(<=32 KiB)
//! FrameReply     frame_id u64 | outcome u8
//!                outcome 0 (Landmarks): landmarks points(<=128) | face_prob f32
//!                                       | queue_us u32 | infer_us u32
//!                outcome 1 (Dropped):   reason u8
//! Goaway         reason u32 (CloseCode) | text str(<=512)
//! ErrorMsg       code u32 (CloseCode)   | text str(<=512)
//! Tracked*       track_id u16 (non-zero) | the FrameRequest or FrameReply body above
//! ```
//!
//! A request's `track_id` says which of the client's faces the crop is; the reply echoes it. Track 0 is sent
//! under tags 0x03/0x04, byte for byte the version-1/2 layout, so a single-face client never pays for it.
//!
//! A raw 112x112 [`FrameRequest`] is therefore 1 + 8 + 8 + 2 + 1 + 2 + 2 + 4 +
//! 12,544 = 12,572 bytes, and a 68-landmark [`FrameReply`] is 1 + 8 + 1 + 2 +
//! 544 + 4 + 4 + 4 = 568 bytes (one datagram).
//!
//! The crop-to-image mapping deliberately stays on the client: the server is
//! stateless per frame (it sees a crop, answers in crop pixels) and the
//! request stays a few bytes smaller. The client maps the reply's crop-pixel
//! landmarks back to image pixels with the similarity it used to cut the crop.

use bytes::{Buf, BufMut, Bytes, BytesMut};

use crate::codec::{
    Decode, Encode, check_finite, check_len, check_points, get_f32, get_payload, get_points, get_string,
    get_u8, get_u16, get_u32, get_u64, points_len, put_payload, put_points, put_string, string_len,
};
use crate::error::{CloseCode, DecodeError, EncodeError, InvalidError};
use crate::limits::{
    MAX_CROP_DIM, MAX_ENCODED_CROP_LEN, MAX_ENCODINGS, MAX_ERROR_TEXT_LEN, MAX_LANDMARKS, MAX_MESSAGE_LEN,
    MAX_NAME_LEN, MAX_TOKEN_LEN,
};

macro_rules! wire_enum_u8 {
    ($(#[$meta:meta])* $name:ident, $field:literal { $($(#[$vmeta:meta])* $variant:ident = $value:literal,)+ }) => {
        $(#[$meta])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
        #[repr(u8)]
        pub enum $name {
            $($(#[$vmeta])* $variant = $value,)+
        }

        impl $name {
            /// Every value, in wire order.
            pub const ALL: &'static [Self] = &[$(Self::$variant,)+];

            /// The wire byte.
            pub const fn as_u8(self) -> u8 {
                self as u8
            }

            /// The value for a wire byte, or `None` if unknown.
            pub const fn from_u8(value: u8) -> Option<Self> {
                match value {
                    $($value => Some(Self::$variant),)+
                    _ => None,
                }
            }
        }

        impl TryFrom<u8> for $name {
            type Error = DecodeError;

            fn try_from(value: u8) -> Result<Self, DecodeError> {
                Self::from_u8(value).ok_or(DecodeError::UnknownValue { field: $field, value: value as u64 })
            }
        }

        impl Decode for $name {
            fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
                Self::try_from(get_u8(buf)?)
            }
        }
    };
}

wire_enum_u8!(
    /// How a crop's pixels are encoded (`u8` on the wire).
    CropEncoding, "encoding" {
        /// Uncompressed gray8, row-major, `width * height` bytes.
        Raw = 0,
        /// A PNG file (8-bit grayscale).
        Png = 1,
        /// A baseline JPEG file (8-bit grayscale).
        Jpeg = 2,
    }
);

wire_enum_u8!(
    /// Where the server sends [`FrameReply`]s (`u8` on the wire).
    ReplyChannel, "reply_channel" {
        /// One QUIC datagram per reply (preferred: no head-of-line blocking).
        Datagram = 0,
        /// A unidirectional stream carrying framed replies (when the
        /// connection does not support datagrams).
        Stream = 1,
    }
);

wire_enum_u8!(
    /// Why the server did not align a frame (`u8` on the wire).
    DropReason, "drop_reason" {
        /// A newer frame from the same client replaced this one in the queue.
        Superseded = 0,
        /// The frame was older than its deadline when its turn came.
        Expired = 1,
        /// The server shed load.
        Overloaded = 2,
        /// The crop could not be decoded or has the wrong size.
        BadCrop = 3,
        /// The server is draining.
        ShuttingDown = 4,
        /// The model's output for this frame was unusable (non-finite values, or a
        /// shape that contradicts the model's declaration). Protocol version 2.
        ModelOutput = 5,
    }
);

impl DropReason {
    /// The snake_case name logs, metric labels and tools use for this reason.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Superseded => "superseded",
            Self::Expired => "expired",
            Self::Overloaded => "overloaded",
            Self::BadCrop => "bad_crop",
            Self::ShuttingDown => "shutting_down",
            Self::ModelOutput => "model_output",
        }
    }

    /// The reason as a client of protocol `version` understands it: a reason
    /// newer than its version becomes [`Self::Overloaded`], which a client
    /// handles the same way (it answers the frame locally).
    pub const fn for_version(self, version: u16) -> Self {
        match self {
            Self::ModelOutput if version < 2 => Self::Overloaded,
            other => other,
        }
    }
}

mod hello;
pub use hello::{ClientHello, ServerWelcome};

/// An image patch: `width` x `height` gray8 pixels in some [`CropEncoding`].
///
/// Invariants (checked by both encoder and decoder): `1 <= width, height <=`
/// [`MAX_CROP_DIM`], `data.len() <=` [`MAX_ENCODED_CROP_LEN`], and for
/// [`CropEncoding::Raw`] `data.len() == width * height`. Compressed payloads
/// are not decoded here; the server answers [`DropReason::BadCrop`] if they
/// do not decode to `width` x `height`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Crop {
    /// How `data` is encoded.
    pub encoding: CropEncoding,
    /// Width in pixels.
    pub width: u16,
    /// Height in pixels.
    pub height: u16,
    /// The pixels (zero-copy slice of the received buffer after decoding).
    pub data: Bytes,
}

impl Crop {
    /// A raw gray8 crop (row-major, `width * height` bytes).
    pub fn raw(width: u16, height: u16, data: impl Into<Bytes>) -> Self {
        Self {
            encoding: CropEncoding::Raw,
            width,
            height,
            data: data.into(),
        }
    }

    pub(crate) fn validate<E: InvalidError>(&self) -> Result<(), E> {
        check_dims(
            u32::from(self.width),
            u32::from(self.height),
            u32::from(MAX_CROP_DIM),
        )?;
        check_len("crop.data", self.data.len(), MAX_ENCODED_CROP_LEN)?;
        if self.encoding == CropEncoding::Raw {
            check_raw_len(u32::from(self.width), u32::from(self.height), self.data.len())?;
        }
        Ok(())
    }
}

/// `1 <= width, height <= max`.
pub(crate) fn check_dims<E: InvalidError>(width: u32, height: u32, max: u32) -> Result<(), E> {
    if width == 0 || height == 0 || width > max || height > max {
        Err(E::bad_dimensions(width, height, max))
    } else {
        Ok(())
    }
}

/// `len == width * height` (without overflow).
pub(crate) fn check_raw_len<E: InvalidError>(width: u32, height: u32, len: usize) -> Result<(), E> {
    let expected = u64::from(width) * u64::from(height);
    if u64::try_from(len).ok() == Some(expected) {
        Ok(())
    } else {
        Err(E::raw_size_mismatch(
            width,
            height,
            usize::try_from(expected).unwrap_or(usize::MAX),
            len,
        ))
    }
}

impl Encode for Crop {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        self.validate::<EncodeError>()?;
        buf.reserve(self.encoded_len());
        buf.put_u8(self.encoding.as_u8());
        buf.put_u16_le(self.width);
        buf.put_u16_le(self.height);
        put_payload(buf, &self.data);
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        1 + 2 + 2 + 4 + self.data.len()
    }
}

impl Decode for Crop {
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
        let encoding = CropEncoding::decode(buf)?;
        let width = get_u16(buf)?;
        let height = get_u16(buf)?;
        check_dims::<DecodeError>(u32::from(width), u32::from(height), u32::from(MAX_CROP_DIM))?;
        let data = get_payload(buf, "crop.data", MAX_ENCODED_CROP_LEN)?;
        let crop = Self {
            encoding,
            width,
            height,
            data,
        };
        crop.validate::<DecodeError>()?;
        Ok(crop)
    }
}

/// One frame to align: a crop cut by the client around the tracked face.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FrameRequest {
    /// Client-chosen, strictly increasing frame number; echoed in the reply.
    pub frame_id: u64,
    /// Capture time on the client's clock, in microseconds (echo only; the
    /// server never compares it with its own clock).
    pub captured_at_us: u64,
    /// Age budget set by the client: the server drops the frame
    /// ([`DropReason::Expired`]) if it has waited longer than this since arrival.
    pub deadline_ms: u16,
    /// The pixels. Landmarks in the reply are in this crop's pixel frame.
    pub crop: Crop,
    /// Which of the client's tracked faces this crop is (protocol version 3; echoed in the reply). The
    /// server's batcher keys supersede and expiry by (client, track), so a newer crop of one face never
    /// drops another face's. A non-zero track travels as [`Message::TAG_TRACKED_FRAME_REQUEST`] (the track
    /// id, then this layout); track 0 is the version-1/2 message, byte for byte.
    pub track_id: u16,
}

impl Encode for FrameRequest {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        self.crop.validate::<EncodeError>()?;
        buf.reserve(self.encoded_len());
        buf.put_u64_le(self.frame_id);
        buf.put_u64_le(self.captured_at_us);
        buf.put_u16_le(self.deadline_ms);
        self.crop.encode(buf)
    }

    fn encoded_len(&self) -> usize {
        8 + 8 + 2 + self.crop.encoded_len()
    }
}

impl Decode for FrameRequest {
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
        Ok(Self {
            frame_id: get_u64(buf)?,
            captured_at_us: get_u64(buf)?,
            deadline_ms: get_u16(buf)?,
            crop: Crop::decode(buf)?,
            track_id: 0,
        })
    }
}

/// What happened to a frame.
#[derive(Debug, Clone, PartialEq)]
pub enum ReplyOutcome {
    /// The frame was aligned (outcome byte 0).
    Landmarks {
        /// Landmarks in crop pixels (`landmark_count` of them, at most
        /// [`MAX_LANDMARKS`]; finite).
        landmarks: Vec<[f32; 2]>,
        /// Probability that the crop contains a face (finite; compare with
        /// `ServerWelcome::face_threshold`).
        face_prob: f32,
        /// Time the frame waited in the server's queue, in microseconds.
        queue_us: u32,
        /// Time spent in inference, in microseconds.
        infer_us: u32,
    },
    /// The frame was not aligned (outcome byte 1).
    Dropped {
        /// Why.
        reason: DropReason,
    },
}

/// The server's answer to one [`FrameRequest`].
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReply {
    /// The request's `frame_id`.
    pub frame_id: u64,
    /// Landmarks or the reason the frame was dropped.
    pub outcome: ReplyOutcome,
    /// The request's `track_id` (version 3; non-zero ones travel as [`Message::TAG_TRACKED_FRAME_REPLY`]).
    pub track_id: u16,
}

const OUTCOME_LANDMARKS: u8 = 0;
const OUTCOME_DROPPED: u8 = 1;

impl FrameReply {
    fn validate<E: InvalidError>(&self) -> Result<(), E> {
        match &self.outcome {
            ReplyOutcome::Landmarks {
                landmarks, face_prob, ..
            } => {
                check_points("landmarks", landmarks, MAX_LANDMARKS)?;
                check_finite(*face_prob, "face_prob")
            }
            ReplyOutcome::Dropped { .. } => Ok(()),
        }
    }
}

impl Encode for FrameReply {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        self.validate::<EncodeError>()?;
        buf.reserve(self.encoded_len());
        buf.put_u64_le(self.frame_id);
        match &self.outcome {
            ReplyOutcome::Landmarks {
                landmarks,
                face_prob,
                queue_us,
                infer_us,
            } => {
                buf.put_u8(OUTCOME_LANDMARKS);
                put_points(buf, landmarks);
                buf.put_f32_le(*face_prob);
                buf.put_u32_le(*queue_us);
                buf.put_u32_le(*infer_us);
            }
            ReplyOutcome::Dropped { reason } => {
                buf.put_u8(OUTCOME_DROPPED);
                buf.put_u8(reason.as_u8());
            }
        }
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        8 + 1
            + match &self.outcome {
                ReplyOutcome::Landmarks { landmarks, .. } => points_len(landmarks) + 4 + 4 + 4,
                ReplyOutcome::Dropped { .. } => 1,
            }
    }
}

impl Decode for FrameReply {
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
        let frame_id = get_u64(buf)?;
        let outcome = match get_u8(buf)? {
            OUTCOME_LANDMARKS => ReplyOutcome::Landmarks {
                landmarks: get_points(buf, "landmarks", MAX_LANDMARKS)?,
                face_prob: get_f32(buf, "face_prob")?,
                queue_us: get_u32(buf)?,
                infer_us: get_u32(buf)?,
            },
            OUTCOME_DROPPED => ReplyOutcome::Dropped {
                reason: DropReason::decode(buf)?,
            },
            other => {
                return Err(DecodeError::UnknownValue {
                    field: "outcome",
                    value: u64::from(other),
                });
            }
        };
        Ok(Self {
            frame_id,
            outcome,
            track_id: 0,
        })
    }
}

/// The track id of a tracked frame message: never 0 (track 0 has its own, untracked tag).
fn get_track(buf: &mut Bytes) -> Result<u16, DecodeError> {
    match get_u16(buf)? {
        0 => Err(DecodeError::UnknownValue {
            field: "track_id (0 is sent untracked)",
            value: 0,
        }),
        t => Ok(t),
    }
}

fn get_close_code(buf: &mut Bytes, field: &'static str) -> Result<CloseCode, DecodeError> {
    let v = get_u32(buf)?;
    CloseCode::from_u32(v).ok_or(DecodeError::UnknownValue {
        field,
        value: u64::from(v),
    })
}

/// Server → client: stop sending new frames; the connection will close with
/// `reason` once in-flight frames are answered.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Goaway {
    /// Why (usually [`CloseCode::ShuttingDown`]).
    pub reason: CloseCode,
    /// Human-readable detail (at most [`MAX_ERROR_TEXT_LEN`] bytes).
    pub text: String,
}

impl Encode for Goaway {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        check_len::<EncodeError>("text", self.text.len(), MAX_ERROR_TEXT_LEN)?;
        buf.reserve(self.encoded_len());
        buf.put_u32_le(self.reason.as_u32());
        put_string(buf, &self.text);
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        4 + string_len(&self.text)
    }
}

impl Decode for Goaway {
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
        Ok(Self {
            reason: get_close_code(buf, "reason")?,
            text: get_string(buf, "text", MAX_ERROR_TEXT_LEN)?,
        })
    }
}

/// Either direction: a fatal error, sent just before closing the connection
/// with the same `code`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ErrorMsg {
    /// The close code that follows.
    pub code: CloseCode,
    /// Human-readable detail (at most [`MAX_ERROR_TEXT_LEN`] bytes).
    pub text: String,
}

impl Encode for ErrorMsg {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        check_len::<EncodeError>("text", self.text.len(), MAX_ERROR_TEXT_LEN)?;
        buf.reserve(self.encoded_len());
        buf.put_u32_le(self.code.as_u32());
        put_string(buf, &self.text);
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        4 + string_len(&self.text)
    }
}

impl Decode for ErrorMsg {
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
        Ok(Self {
            code: get_close_code(buf, "code")?,
            text: get_string(buf, "text", MAX_ERROR_TEXT_LEN)?,
        })
    }
}

/// Any protocol message; on the wire a one-byte tag then the body.
#[derive(Debug, Clone, PartialEq)]
pub enum Message {
    /// Tag `0x01`.
    ClientHello(ClientHello),
    /// Tag `0x02`.
    ServerWelcome(ServerWelcome),
    /// Tag `0x03`.
    FrameRequest(FrameRequest),
    /// Tag `0x04`.
    FrameReply(FrameReply),
    /// Tag `0x05`.
    Goaway(Goaway),
    /// Tag `0x06`.
    Error(ErrorMsg),
}

impl Message {
    /// Tag of [`Message::ClientHello`].
    pub const TAG_CLIENT_HELLO: u8 = 0x01;
    /// Tag of [`Message::ServerWelcome`].
    pub const TAG_SERVER_WELCOME: u8 = 0x02;
    /// Tag of [`Message::FrameRequest`].
    pub const TAG_FRAME_REQUEST: u8 = 0x03;
    /// Tag of [`Message::FrameReply`].
    pub const TAG_FRAME_REPLY: u8 = 0x04;
    /// Tag of [`Message::Goaway`].
    pub const TAG_GOAWAY: u8 = 0x05;
    /// Tag of [`Message::Error`].
    pub const TAG_ERROR: u8 = 0x06;
    /// Tag of a [`Message::FrameRequest`] with a non-zero track id (version 3): `u16` track id, then the
    /// [`Self::TAG_FRAME_REQUEST`] body.
    pub const TAG_TRACKED_FRAME_REQUEST: u8 = 0x07;
    /// Tag of a [`Message::FrameReply`] with a non-zero track id (version 3): `u16` track id, then the
    /// [`Self::TAG_FRAME_REPLY`] body.
    pub const TAG_TRACKED_FRAME_REPLY: u8 = 0x08;

    /// The message's tag byte.
    pub const fn tag(&self) -> u8 {
        match self {
            Self::ClientHello(_) => Self::TAG_CLIENT_HELLO,
            Self::ServerWelcome(_) => Self::TAG_SERVER_WELCOME,
            Self::FrameRequest(m) if m.track_id != 0 => Self::TAG_TRACKED_FRAME_REQUEST,
            Self::FrameRequest(_) => Self::TAG_FRAME_REQUEST,
            Self::FrameReply(m) if m.track_id != 0 => Self::TAG_TRACKED_FRAME_REPLY,
            Self::FrameReply(_) => Self::TAG_FRAME_REPLY,
            Self::Goaway(_) => Self::TAG_GOAWAY,
            Self::Error(_) => Self::TAG_ERROR,
        }
    }

    /// The exact number of bytes [`Message::encode`] appends (tag included).
    pub fn encoded_len(&self) -> usize {
        1 + self.track().map_or(0, |_| 2)
            + match self {
                Self::ClientHello(m) => m.encoded_len(),
                Self::ServerWelcome(m) => m.encoded_len(),
                Self::FrameRequest(m) => m.encoded_len(),
                Self::FrameReply(m) => m.encoded_len(),
                Self::Goaway(m) => m.encoded_len(),
                Self::Error(m) => m.encoded_len(),
            }
    }

    /// A frame request's or reply's non-zero track id (it selects the tracked tag).
    const fn track(&self) -> Option<u16> {
        match self {
            Self::FrameRequest(FrameRequest { track_id, .. })
            | Self::FrameReply(FrameReply { track_id, .. })
                if *track_id != 0 =>
            {
                Some(*track_id)
            }
            _ => None,
        }
    }

    /// Appends tag + body to `buf`.
    ///
    /// Fails, leaving `buf` as it was, if a field breaks a limit in
    /// [`crate::limits`] or an invariant the decoder checks, so a message
    /// that encodes always decodes on the other side.
    pub fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        let start = buf.len();
        buf.reserve(self.encoded_len());
        buf.put_u8(self.tag());
        if let Some(track) = self.track() {
            buf.put_u16_le(track);
        }
        let res = match self {
            Self::ClientHello(m) => m.encode(buf),
            Self::ServerWelcome(m) => m.encode(buf),
            Self::FrameRequest(m) => m.encode(buf),
            Self::FrameReply(m) => m.encode(buf),
            Self::Goaway(m) => m.encode(buf),
            Self::Error(m) => m.encode(buf),
        };
        if res.is_err() {
            buf.truncate(start);
        }
        res
    }

    /// Encodes into a fresh buffer.
    pub fn to_bytes(&self) -> Result<Bytes, EncodeError> {
        let mut buf = BytesMut::with_capacity(self.encoded_len());
        self.encode(&mut buf)?;
        Ok(buf.freeze())
    }

    /// Decodes exactly one message from the whole of `buf` (a datagram or a
    /// complete single-message stream). Trailing bytes are an error
    /// ([`DecodeError::TrailingBytes`]); a truncated buffer gives
    /// [`DecodeError::Short`] or another typed error. Crop pixels in the
    /// result are a zero-copy slice of `buf`.
    pub fn decode(mut buf: Bytes) -> Result<Self, DecodeError> {
        let tag = get_u8(&mut buf)?;
        let msg = match tag {
            Self::TAG_CLIENT_HELLO => Self::ClientHello(ClientHello::decode(&mut buf)?),
            Self::TAG_SERVER_WELCOME => Self::ServerWelcome(ServerWelcome::decode(&mut buf)?),
            Self::TAG_FRAME_REQUEST => Self::FrameRequest(FrameRequest::decode(&mut buf)?),
            Self::TAG_FRAME_REPLY => Self::FrameReply(FrameReply::decode(&mut buf)?),
            Self::TAG_TRACKED_FRAME_REQUEST => {
                let track_id = get_track(&mut buf)?;
                Self::FrameRequest(FrameRequest {
                    track_id,
                    ..FrameRequest::decode(&mut buf)?
                })
            }
            Self::TAG_TRACKED_FRAME_REPLY => {
                let track_id = get_track(&mut buf)?;
                Self::FrameReply(FrameReply {
                    track_id,
                    ..FrameReply::decode(&mut buf)?
                })
            }
            Self::TAG_GOAWAY => Self::Goaway(Goaway::decode(&mut buf)?),
            Self::TAG_ERROR => Self::Error(ErrorMsg::decode(&mut buf)?),
            other => {
                return Err(DecodeError::UnknownValue {
                    field: "message tag",
                    value: u64::from(other),
                });
            }
        };
        if buf.has_remaining() {
            return Err(DecodeError::TrailingBytes { len: buf.remaining() });
        }
        Ok(msg)
    }
}

macro_rules! impl_from_for_message {
    ($($t:ident => $v:ident),+) => {
        $(impl From<$t> for Message {
            fn from(m: $t) -> Self {
                Self::$v(m)
            }
        })+
    };
}

impl_from_for_message!(
    ClientHello => ClientHello,
    ServerWelcome => ServerWelcome,
    FrameRequest => FrameRequest,
    FrameReply => FrameReply,
    Goaway => Goaway,
    ErrorMsg => Error
);

/// Size of the length prefix written by [`encode_framed`].
pub const FRAME_PREFIX_LEN: usize = 4;

/// The exact number of bytes [`encode_framed`] appends for `msg`.
pub fn framed_len(msg: &Message) -> usize {
    FRAME_PREFIX_LEN + msg.encoded_len()
}

/// Appends `msg` to `buf` as a frame: `u32` little-endian length of the
/// message, then the message (tag + body). On error `buf` is left as it was.
pub fn encode_framed(msg: &Message, buf: &mut BytesMut) -> Result<(), EncodeError> {
    let start = buf.len();
    buf.reserve(framed_len(msg));
    buf.put_u32_le(0);
    if let Err(e) = msg.encode(buf) {
        buf.truncate(start);
        return Err(e);
    }
    let len = buf.len() - start - FRAME_PREFIX_LEN;
    let prefix = match u32::try_from(len) {
        Ok(l) if len <= MAX_MESSAGE_LEN => l,
        _ => {
            buf.truncate(start);
            return Err(EncodeError::TooLarge {
                field: "message",
                len,
                max: MAX_MESSAGE_LEN,
            });
        }
    };
    if let Some(slot) = buf.get_mut(start..start + FRAME_PREFIX_LEN) {
        slot.copy_from_slice(&prefix.to_le_bytes());
    }
    Ok(())
}

/// Takes one complete frame off the front of `buf` and decodes it.
///
/// * `Ok(None)`: `buf` does not yet hold a whole frame; read more and call
///   again. Nothing is consumed.
/// * `Ok(Some(msg))`: the frame was removed from `buf`. Crop pixels in `msg`
///   share `buf`'s allocation (no copy).
/// * `Err(TooLarge { field: "message", .. })`: the length prefix exceeds
///   [`MAX_MESSAGE_LEN`]; returned as soon as the 4 prefix bytes are there,
///   before any of the frame is buffered.
/// * `Err(ShortFrame { .. })`: the frame was complete but the message inside
///   was cut short.
/// * Any other `Err`: the frame was removed and was malformed.
///
/// After an error the stream is out of sync; close it with
/// [`DecodeError::close_code`].
pub fn decode_framed(buf: &mut BytesMut) -> Result<Option<Message>, DecodeError> {
    let Some(prefix) = buf.get(..FRAME_PREFIX_LEN) else {
        return Ok(None);
    };
    let mut raw = [0_u8; FRAME_PREFIX_LEN];
    raw.copy_from_slice(prefix);
    let len = usize::try_from(u32::from_le_bytes(raw)).unwrap_or(usize::MAX);
    check_len::<DecodeError>("message", len, MAX_MESSAGE_LEN)?;
    let total = FRAME_PREFIX_LEN + len;
    if buf.len() < total {
        return Ok(None);
    }
    let mut frame = buf.split_to(total).freeze();
    frame.advance(FRAME_PREFIX_LEN);
    match Message::decode(frame) {
        Ok(msg) => Ok(Some(msg)),
        Err(DecodeError::Short { needed }) => Err(DecodeError::ShortFrame {
            frame_len: len,
            needed,
        }),
        Err(e) => Err(e),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn enc(msg: &Message) -> Vec<u8> {
        let mut buf = BytesMut::new();
        msg.encode(&mut buf).unwrap();
        assert_eq!(buf.len(), msg.encoded_len());
        buf.to_vec()
    }

    fn round_trip(msg: Message, expected: &[u8]) {
        let bytes = enc(&msg);
        assert_eq!(bytes, expected, "layout of {msg:?}");
        assert_eq!(Message::decode(Bytes::from(bytes)).unwrap(), msg);
    }

    #[test]
    fn client_hello_layout() {
        let msg = Message::ClientHello(ClientHello {
            version: 1,
            token: "tk".into(),
            client_name: "hs".into(),
            encodings: vec![CropEncoding::Raw, CropEncoding::Png],
            max_in_flight: 2,
        });
        #[rustfmt::skip]
        let expected = [
            0x01,                   // tag
            0x01, 0x00,             // version 1
            0x02, 0x00, b't', b'k', // token "tk"
            0x02, 0x00, b'h', b's', // client_name "hs"
            0x02, 0x00, 0x01,       // 2 encodings: Raw, Png
            0x02, 0x00,             // max_in_flight 2
        ];
        round_trip(msg, &expected);
    }

    #[test]
    fn server_welcome_layout() {
        let msg = Message::ServerWelcome(ServerWelcome {
            version: 1,
            model_id: "d".into(),
            model_version: "1".into(),
            landmark_count: 1,
            crop_size: 112,
            mean_shape: vec![[1.0, -2.0]],
            face_threshold: 0.5,
            encoding: CropEncoding::Jpeg,
            reply_channel: ReplyChannel::Stream,
            max_in_flight: 2,
            max_frame_age_ms: 66,
        });
        #[rustfmt::skip]
        let expected = [
            0x02,
            0x01, 0x00,                 // version
            0x01, 0x00, b'd',           // model_id
            0x01, 0x00, b'1',           // model_version
            0x01, 0x00,                 // landmark_count 1
            0x70, 0x00,                 // crop_size 112
            0x01, 0x00,                 // mean_shape count 1
            0x00, 0x00, 0x80, 0x3f,     // 1.0
            0x00, 0x00, 0x00, 0xc0,     // -2.0
            0x00, 0x00, 0x00, 0x3f,     // face_threshold 0.5
            0x02,                       // Jpeg
            0x01,                       // Stream
            0x02, 0x00,                 // max_in_flight
            0x42, 0x00, 0x00, 0x00,     // max_frame_age_ms 66
        ];
        round_trip(msg, &expected);
    }

    #[test]
    fn frame_request_layout() {
        let msg = Message::FrameRequest(FrameRequest {
            track_id: 0,
            frame_id: 0x0102,
            captured_at_us: 7,
            deadline_ms: 33,
            crop: Crop::raw(2, 1, vec![0xaa, 0xbb]),
        });
        #[rustfmt::skip]
        let expected = [
            0x03,
            0x02, 0x01, 0, 0, 0, 0, 0, 0,   // frame_id
            0x07, 0, 0, 0, 0, 0, 0, 0,      // captured_at_us
            0x21, 0x00,                     // deadline_ms 33
            0x00,                           // Raw
            0x02, 0x00, 0x01, 0x00,         // 2x1
            0x02, 0x00, 0x00, 0x00,         // 2 bytes
            0xaa, 0xbb,
        ];
        round_trip(msg, &expected);
    }

    #[test]
    fn a_track_id_travels_under_its_own_tag_and_track_0_is_the_version_2_layout() {
        let req = |track_id| {
            Message::FrameRequest(FrameRequest {
                frame_id: 0x0102,
                captured_at_us: 7,
                deadline_ms: 33,
                crop: Crop::raw(2, 1, vec![0xaa, 0xbb]),
                track_id,
            })
        };
        let v2 = req(0).to_bytes().unwrap();
        let v3 = req(0x0304).to_bytes().unwrap();
        assert_eq!(
            v2[0],
            Message::TAG_FRAME_REQUEST,
            "track 0: the version-2 message"
        );
        assert_eq!(&v3[..3], &[Message::TAG_TRACKED_FRAME_REQUEST, 0x04, 0x03]);
        assert_eq!(&v3[3..], &v2[1..], "then the same body");
        assert_eq!(Message::decode(v3).unwrap(), req(0x0304));
        // Track 0 under the tracked tag is not canonical.
        let mut zero = vec![Message::TAG_TRACKED_FRAME_REQUEST, 0, 0];
        zero.extend_from_slice(&v2[1..]);
        let e = Message::decode(Bytes::from(zero)).unwrap_err().to_string();
        assert!(e.contains("track_id"), "{e}");
        let reply = Message::FrameReply(FrameReply {
            frame_id: 9,
            outcome: ReplyOutcome::Dropped {
                reason: DropReason::Superseded,
            },
            track_id: 2,
        });
        let b = reply.to_bytes().unwrap();
        assert_eq!(&b[..3], &[Message::TAG_TRACKED_FRAME_REPLY, 2, 0]);
        assert_eq!(Message::decode(b).unwrap(), reply);
    }

    #[test]
    fn frame_reply_layouts() {
        let msg = Message::FrameReply(FrameReply {
            track_id: 0,
            frame_id: 9,
            outcome: ReplyOutcome::Landmarks {
                landmarks: vec![[0.5, 2.0]],
                face_prob: 1.0,
                queue_us: 0x0100,
                infer_us: 3,
            },
        });
        #[rustfmt::skip]
        let expected = [
            0x04,
            0x09, 0, 0, 0, 0, 0, 0, 0,
            0x00,                       // Landmarks
            0x01, 0x00,                 // 1 point
            0x00, 0x00, 0x00, 0x3f,     // 0.5
            0x00, 0x00, 0x00, 0x40,     // 2.0
            0x00, 0x00, 0x80, 0x3f,     // face_prob 1.0
            0x00, 0x01, 0x00, 0x00,     // queue_us 256
            0x03, 0x00, 0x00, 0x00,     // infer_us 3
        ];
        round_trip(msg, &expected);

        let msg = Message::FrameReply(FrameReply {
            track_id: 0,
            frame_id: 1,
            outcome: ReplyOutcome::Dropped {
                reason: DropReason::Expired,
            },
        });
        round_trip(msg, &[0x04, 1, 0, 0, 0, 0, 0, 0, 0, 0x01, 0x01]);
    }

    #[test]
    fn goaway_and_error_layouts() {
        let msg = Message::Goaway(Goaway {
            reason: CloseCode::ShuttingDown,
            text: "bye".into(),
        });
        round_trip(msg, &[0x05, 6, 0, 0, 0, 3, 0, b'b', b'y', b'e']);
        let msg = Message::Error(ErrorMsg {
            code: CloseCode::ProtocolViolation,
            text: String::new(),
        });
        round_trip(msg, &[0x06, 8, 0, 0, 0, 0, 0]);
    }

    #[test]
    fn raw_112_request_size() {
        let msg = Message::FrameRequest(FrameRequest {
            track_id: 0,
            frame_id: 1,
            captured_at_us: 2,
            deadline_ms: 66,
            crop: Crop::raw(112, 112, vec![0_u8; crate::CROP_PIXELS]),
        });
        assert_eq!(msg.encoded_len(), 12_572);
        let reply = Message::FrameReply(FrameReply {
            track_id: 0,
            frame_id: 1,
            outcome: ReplyOutcome::Landmarks {
                landmarks: vec![[0.0; 2]; 68],
                face_prob: 0.9,
                queue_us: 0,
                infer_us: 0,
            },
        });
        assert_eq!(reply.encoded_len(), 568);
        assert_eq!(enc(&reply).len(), 568);
    }

    #[test]
    fn decode_slices_pixels_without_copying() {
        let msg = Message::FrameRequest(FrameRequest {
            track_id: 0,
            frame_id: 1,
            captured_at_us: 2,
            deadline_ms: 3,
            crop: Crop::raw(4, 4, vec![7_u8; 16]),
        });
        let wire = Bytes::from(enc(&msg));
        let range = wire.as_ptr_range();
        let Message::FrameRequest(req) = Message::decode(wire.clone()).unwrap() else {
            panic!("wrong variant")
        };
        let data = req.crop.data.as_ptr_range();
        assert!(range.start <= data.start && data.end <= range.end);
    }

    #[test]
    fn typed_errors() {
        let err = |v: &[u8]| Message::decode(Bytes::copy_from_slice(v)).unwrap_err();
        assert_eq!(err(&[]), DecodeError::Short { needed: 1 });
        assert_eq!(
            err(&[0x00]),
            DecodeError::UnknownValue {
                field: "message tag",
                value: 0
            }
        );
        assert_eq!(
            err(&[0x06, 8, 0, 0, 0, 0, 0, 0xff]),
            DecodeError::TrailingBytes { len: 1 }
        );
        assert_eq!(
            err(&[0x06, 99, 0, 0, 0, 0, 0]),
            DecodeError::UnknownValue {
                field: "code",
                value: 99
            }
        );
        // Unknown crop encoding.
        let mut v = vec![0x03];
        v.extend_from_slice(&[0; 18]);
        v.push(9);
        assert_eq!(
            err(&v),
            DecodeError::UnknownValue {
                field: "encoding",
                value: 9
            }
        );
        // Raw crop whose payload does not match width*height.
        let mut v = vec![0x03];
        v.extend_from_slice(&[0; 18]);
        v.extend_from_slice(&[0, 2, 0, 2, 0, 3, 0, 0, 0, 1, 2, 3]);
        assert_eq!(
            err(&v),
            DecodeError::RawSizeMismatch {
                width: 2,
                height: 2,
                expected: 4,
                len: 3
            }
        );
        // Crop wider than MAX_CROP_DIM.
        let mut v = vec![0x03];
        v.extend_from_slice(&[0; 18]);
        v.extend_from_slice(&[1, 0x01, 0x04, 1, 0]);
        assert_eq!(
            err(&v),
            DecodeError::BadDimensions {
                width: 1025,
                height: 1,
                max: 1024
            }
        );
        // NaN face probability.
        let mut v = vec![0x04, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0];
        v.extend_from_slice(&f32::NAN.to_le_bytes());
        v.extend_from_slice(&[0; 8]);
        assert_eq!(err(&v), DecodeError::NonFinite { field: "face_prob" });
    }

    #[test]
    fn encode_refuses_invalid_and_leaves_buffer_alone() {
        let mut buf = BytesMut::from(&b"keep"[..]);
        let hello = Message::ClientHello(ClientHello {
            version: 1,
            token: "x".repeat(MAX_TOKEN_LEN + 1),
            client_name: String::new(),
            encodings: vec![],
            max_in_flight: 1,
        });
        assert_eq!(
            hello.encode(&mut buf),
            Err(EncodeError::TooLarge {
                field: "token",
                len: 257,
                max: 256
            })
        );
        assert_eq!(
            encode_framed(&hello, &mut buf).unwrap_err().to_string(),
            "token: length 257 exceeds the limit 256"
        );
        assert_eq!(&buf[..], b"keep");

        let welcome = Message::ServerWelcome(ServerWelcome {
            version: 1,
            model_id: String::new(),
            model_version: String::new(),
            landmark_count: 68,
            crop_size: 112,
            mean_shape: vec![[0.0; 2]; 67],
            face_threshold: 0.1,
            encoding: CropEncoding::Raw,
            reply_channel: ReplyChannel::Datagram,
            max_in_flight: 1,
            max_frame_age_ms: 100,
        });
        assert_eq!(
            welcome.encode(&mut buf),
            Err(EncodeError::LengthMismatch {
                field: "mean_shape",
                expected: 68,
                actual: 67
            })
        );
        let req = Message::FrameRequest(FrameRequest {
            track_id: 0,
            frame_id: 0,
            captured_at_us: 0,
            deadline_ms: 0,
            crop: Crop::raw(112, 112, vec![0_u8; 100]),
        });
        assert!(matches!(
            req.encode(&mut buf),
            Err(EncodeError::RawSizeMismatch { .. })
        ));
        assert_eq!(&buf[..], b"keep");
    }

    #[test]
    fn framed_stream() {
        let a = Message::Goaway(Goaway {
            reason: CloseCode::NoError,
            text: "a".into(),
        });
        let b = Message::FrameReply(FrameReply {
            track_id: 0,
            frame_id: 2,
            outcome: ReplyOutcome::Dropped {
                reason: DropReason::Overloaded,
            },
        });
        let mut wire = BytesMut::new();
        encode_framed(&a, &mut wire).unwrap();
        encode_framed(&b, &mut wire).unwrap();
        assert_eq!(wire.len(), framed_len(&a) + framed_len(&b));
        assert_eq!(&wire[..4], &[8, 0, 0, 0]);

        // Feed one byte at a time.
        let mut rx = BytesMut::new();
        let mut out = Vec::new();
        for byte in wire.iter() {
            rx.put_u8(*byte);
            while let Some(m) = decode_framed(&mut rx).unwrap() {
                out.push(m);
            }
        }
        assert_eq!(out, vec![a, b]);
        assert!(rx.is_empty());
    }

    #[test]
    fn framed_rejects_huge_prefix_immediately() {
        let mut rx = BytesMut::from(&[0xff, 0xff, 0xff, 0x7f, 1][..]);
        assert_eq!(
            decode_framed(&mut rx),
            Err(DecodeError::TooLarge {
                field: "message",
                len: 0x7fff_ffff,
                max: MAX_MESSAGE_LEN
            })
        );
        // A frame whose message ends after the frame does.
        let mut rx = BytesMut::from(&[2, 0, 0, 0, 0x06, 0][..]);
        assert_eq!(
            decode_framed(&mut rx),
            Err(DecodeError::ShortFrame {
                frame_len: 2,
                needed: 3
            })
        );
    }

    #[test]
    fn enum_bytes() {
        for (i, e) in DropReason::ALL.iter().enumerate() {
            assert_eq!(usize::from(e.as_u8()), i);
        }
        assert_eq!(
            CropEncoding::try_from(3),
            Err(DecodeError::UnknownValue {
                field: "encoding",
                value: 3
            })
        );
        assert_eq!(ReplyChannel::from_u8(1), Some(ReplyChannel::Stream));
    }
}
