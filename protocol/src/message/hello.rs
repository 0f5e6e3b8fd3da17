//! The handshake: the client's hello and the server's welcome, the first message each way on the control
//! stream.

use super::*;

/// First message from the client on the control stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ClientHello {
    /// The client's [`crate::PROTOCOL_VERSION`].
    pub version: u16,
    /// Opaque access token (at most [`MAX_TOKEN_LEN`] bytes).
    pub token: String,
    /// Free-form client name for logs (at most [`MAX_NAME_LEN`] bytes).
    pub client_name: String,
    /// Crop encodings the client can send, most preferred first (at most
    /// [`MAX_ENCODINGS`]).
    pub encodings: Vec<CropEncoding>,
    /// How many frames the client wants to have in flight at most.
    pub max_in_flight: u16,
}

impl ClientHello {
    fn validate<E: InvalidError>(&self) -> Result<(), E> {
        check_len("token", self.token.len(), MAX_TOKEN_LEN)?;
        check_len("client_name", self.client_name.len(), MAX_NAME_LEN)?;
        check_len("encodings", self.encodings.len(), MAX_ENCODINGS)
    }
}

impl Encode for ClientHello {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        self.validate::<EncodeError>()?;
        buf.reserve(self.encoded_len());
        buf.put_u16_le(self.version);
        put_string(buf, &self.token);
        put_string(buf, &self.client_name);
        // Checked above: at most MAX_ENCODINGS (8) entries.
        buf.put_u8(u8::try_from(self.encodings.len()).unwrap_or(u8::MAX));
        for e in &self.encodings {
            buf.put_u8(e.as_u8());
        }
        buf.put_u16_le(self.max_in_flight);
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        2 + string_len(&self.token) + string_len(&self.client_name) + 1 + self.encodings.len() + 2
    }
}

impl Decode for ClientHello {
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
        let version = get_u16(buf)?;
        let token = get_string(buf, "token", MAX_TOKEN_LEN)?;
        let client_name = get_string(buf, "client_name", MAX_NAME_LEN)?;
        let count = usize::from(get_u8(buf)?);
        check_len::<DecodeError>("encodings", count, MAX_ENCODINGS)?;
        let mut encodings = Vec::with_capacity(count);
        for _ in 0..count {
            encodings.push(CropEncoding::decode(buf)?);
        }
        let max_in_flight = get_u16(buf)?;
        Ok(Self {
            version,
            token,
            client_name,
            encodings,
            max_in_flight,
        })
    }
}

/// The server's answer to a [`ClientHello`]: what it runs and how to talk to it.
#[derive(Debug, Clone, PartialEq)]
pub struct ServerWelcome {
    /// The server's [`crate::PROTOCOL_VERSION`].
    pub version: u16,
    /// Identifier of the alignment model (at most [`MAX_NAME_LEN`] bytes).
    pub model_id: String,
    /// Version of the alignment model (at most [`MAX_NAME_LEN`] bytes).
    pub model_version: String,
    /// Number of landmarks in every reply (68 for the DAN model).
    pub landmark_count: u16,
    /// Side of the square crop the model expects, in pixels (112).
    pub crop_size: u16,
    /// Canonical landmark positions in crop pixels: the shape the client warps
    /// the previous landmarks onto when it cuts the next crop. Its length must
    /// equal `landmark_count` (at most [`MAX_LANDMARKS`]).
    pub mean_shape: Vec<[f32; 2]>,
    /// Replies with `face_prob` below this are "no face".
    pub face_threshold: f32,
    /// The crop encoding the server chose from the client's list.
    pub encoding: CropEncoding,
    /// Where replies will arrive.
    pub reply_channel: ReplyChannel,
    /// Frames the client may have in flight (at most what it asked for).
    pub max_in_flight: u16,
    /// The server drops frames older than this on arrival at inference.
    pub max_frame_age_ms: u32,
}

impl ServerWelcome {
    fn validate<E: InvalidError>(&self) -> Result<(), E> {
        check_len("model_id", self.model_id.len(), MAX_NAME_LEN)?;
        check_len("model_version", self.model_version.len(), MAX_NAME_LEN)?;
        check_points("mean_shape", &self.mean_shape, MAX_LANDMARKS)?;
        if self.mean_shape.len() != usize::from(self.landmark_count) {
            return Err(E::length_mismatch(
                "mean_shape",
                usize::from(self.landmark_count),
                self.mean_shape.len(),
            ));
        }
        check_finite(self.face_threshold, "face_threshold")
    }
}

impl Encode for ServerWelcome {
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        self.validate::<EncodeError>()?;
        buf.reserve(self.encoded_len());
        buf.put_u16_le(self.version);
        put_string(buf, &self.model_id);
        put_string(buf, &self.model_version);
        buf.put_u16_le(self.landmark_count);
        buf.put_u16_le(self.crop_size);
        put_points(buf, &self.mean_shape);
        buf.put_f32_le(self.face_threshold);
        buf.put_u8(self.encoding.as_u8());
        buf.put_u8(self.reply_channel.as_u8());
        buf.put_u16_le(self.max_in_flight);
        buf.put_u32_le(self.max_frame_age_ms);
        Ok(())
    }

    fn encoded_len(&self) -> usize {
        2 + string_len(&self.model_id)
            + string_len(&self.model_version)
            + 2
            + 2
            + points_len(&self.mean_shape)
            + 4
            + 1
            + 1
            + 2
            + 4
    }
}

impl Decode for ServerWelcome {
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError> {
        let msg = Self {
            version: get_u16(buf)?,
            model_id: get_string(buf, "model_id", MAX_NAME_LEN)?,
            model_version: get_string(buf, "model_version", MAX_NAME_LEN)?,
            landmark_count: get_u16(buf)?,
            crop_size: get_u16(buf)?,
            mean_shape: get_points(buf, "mean_shape", MAX_LANDMARKS)?,
            face_threshold: get_f32(buf, "face_threshold")?,
            encoding: CropEncoding::decode(buf)?,
            reply_channel: ReplyChannel::decode(buf)?,
            max_in_flight: get_u16(buf)?,
            max_frame_age_ms: get_u32(buf)?,
        };
        msg.validate::<DecodeError>()?;
        Ok(msg)
    }
}
