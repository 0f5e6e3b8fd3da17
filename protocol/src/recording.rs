//! The recorded-stream file format (`*.hfrec`): what the headset saw, frame by
//! frame, for replay by the load tester and for offline evaluation.
//!
//! The reader streams: it holds one record at a time and never loads the
//! whole file. All integers and floats are little-endian; floats must be
//! finite. Primitive encodings (`str`, `points`, `payload`) are those of
//! [`crate::codec`].
//!
//! # File layout
//!
//! ```text
//! offset       size  field
//! 0            8     magic b"HFREC\0\r\n"   (the \0 and \r\n catch text-mode mangling)
//! 8            2     major version u16       (current 1)
//! 10           2     minor version u16       (current 0)
//! 12           4     header body length u32  (<= MAX_HEADER_LEN, 64 KiB)
//! 16           n     header body
//! 16+n         4     CRC-32 of the header body (IEEE / ISO-HDLC, as crc32fast)
//! 20+n         ...   records, back to back, until end of file
//! ```
//!
//! Header body (version 1.0):
//!
//! ```text
//! fx f32 | fy f32 | cx f32 | cy f32 | width u32 | height u32     camera intrinsics (pixels)
//! source str (<= MAX_SOURCE_LEN, 1024 B)                          free-form description
//! created_unix_ms u64
//! ```
//!
//! Record:
//!
//! ```text
//! body length u32 (<= MAX_RECORD_LEN, 32 MiB) | CRC-32 of body u32 | body
//! ```
//!
//! Record body:
//!
//! ```text
//! kind u8
//! kind 1 (frame record):
//!   timestamp_us u64
//!   camera_to_world 16 x f32               row-major 4x4, camera frame -> world frame
//!   payload tag u8
//!     0 Crop:      image_from_crop 4 x f32 (a, b, tx, ty) | crop (as on the wire:
//!                  encoding u8 | width u16 | height u16 | data payload <= 32 KiB)
//!     1 FullFrame: width u32 | height u32 | encoding u8 | data payload
//!                  (gray8; raw data is exactly width*height bytes; 1..=8192 px a side)
//!   ground truth present u8 (0 or 1); if 1: points (u16 count <= 128, f32 x, y pairs),
//!                  in image pixels
//!   face_present u8: 0 = unknown, 1 = no face, 2 = face
//! ```
//!
//! The crop similarity maps crop pixels to image pixels:
//! `x' = a*x - b*y + tx`, `y' = b*x + a*y + ty`.
//!
//! # Compatibility rules
//!
//! * A different **major** version is refused with
//!   [`RecordingError::UnsupportedVersion`].
//! * Same major, **newer minor** (written by a newer writer): new fields may be
//!   appended at the end of the header body or of a record body; this reader
//!   ignores bytes after the fields it knows. For the current or an older
//!   minor, trailing bytes are an error.
//! * Records of a **kind** this reader does not know are skipped silently
//!   (their CRC is still checked); [`RecordingReader::unknown_records_skipped`]
//!   counts them. Writers add new kinds only together with a minor bump.
//!
//! # Errors
//!
//! End of file exactly at a record boundary is the normal end
//! (`Ok(None)`); end of file inside a record is
//! [`RecordingError::Truncated`]; a CRC mismatch is
//! [`RecordingError::Corrupt`]; an oversize length prefix is
//! [`RecordingError::TooLarge`], reported before anything is allocated. The
//! reader allocates a record's buffer as its bytes arrive, so a lying length
//! prefix in a short file costs no more memory than the file holds.

use std::io::{self, Read, Write};

use bytes::{Buf, BufMut, Bytes, BytesMut};

use crate::codec::{
    Decode, Encode, check_all_finite, check_len, check_points, get_f32_array, get_payload, get_points,
    get_string, get_u8, get_u32, get_u64, points_len, put_payload, put_points, put_string, string_len,
};
use crate::error::{DecodeError, EncodeError, InvalidError, RecordingError};
use crate::limits::{MAX_FULL_FRAME_DIM, MAX_HEADER_LEN, MAX_LANDMARKS, MAX_RECORD_LEN, MAX_SOURCE_LEN};
use crate::message::{Crop, CropEncoding, check_dims, check_raw_len};

/// The 8-byte file magic.
pub const MAGIC: [u8; 8] = *b"HFREC\0\r\n";

/// Record kind of a [`FrameRecord`].
pub const KIND_FRAME: u8 = 1;

const PAYLOAD_CROP: u8 = 0;
const PAYLOAD_FULL_FRAME: u8 = 1;

/// A file format version.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct FormatVersion {
    /// Incompatible changes bump this.
    pub major: u16,
    /// Compatible additions (appended fields, new record kinds) bump this.
    pub minor: u16,
}

impl FormatVersion {
    /// The version this crate writes (1.0).
    pub const CURRENT: Self = Self { major: 1, minor: 0 };
}

/// Pinhole intrinsics of the camera the frames come from, in pixels.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraIntrinsics {
    /// Focal length along x.
    pub fx: f32,
    /// Focal length along y.
    pub fy: f32,
    /// Principal point x.
    pub cx: f32,
    /// Principal point y.
    pub cy: f32,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
}

/// The file header: what is constant for the whole recording.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingHeader {
    /// Camera intrinsics.
    pub intrinsics: CameraIntrinsics,
    /// Free-form description of the source (device, session, ...), at most
    /// [`MAX_SOURCE_LEN`] bytes.
    pub source: String,
    /// When the recording started, Unix time in milliseconds.
    pub created_unix_ms: u64,
}

impl RecordingHeader {
    fn validate<E: InvalidError>(&self) -> Result<(), E> {
        let i = &self.intrinsics;
        check_all_finite(&[i.fx, i.fy, i.cx, i.cy], "intrinsics")?;
        check_len("source", self.source.len(), MAX_SOURCE_LEN)
    }

    fn body_len(&self) -> usize {
        4 * 4 + 4 + 4 + string_len(&self.source) + 8
    }

    fn encode_body(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        self.validate::<EncodeError>()?;
        let i = &self.intrinsics;
        for v in [i.fx, i.fy, i.cx, i.cy] {
            buf.put_f32_le(v);
        }
        buf.put_u32_le(i.width);
        buf.put_u32_le(i.height);
        put_string(buf, &self.source);
        buf.put_u64_le(self.created_unix_ms);
        Ok(())
    }

    fn decode_body(mut body: Bytes, minor: u16) -> Result<Self, DecodeError> {
        let [fx, fy, cx, cy] = get_f32_array::<4>(&mut body, "intrinsics")?;
        let header = Self {
            intrinsics: CameraIntrinsics {
                fx,
                fy,
                cx,
                cy,
                width: get_u32(&mut body)?,
                height: get_u32(&mut body)?,
            },
            source: get_string(&mut body, "source", MAX_SOURCE_LEN)?,
            created_unix_ms: get_u64(&mut body)?,
        };
        check_trailing(&body, minor)?;
        Ok(header)
    }

    /// The complete file header (magic, version 1.0, length, body, CRC) as
    /// [`RecordingWriter::new`] writes it.
    pub fn encode(&self) -> Result<Bytes, EncodeError> {
        let body_len = self.body_len();
        let mut buf = BytesMut::with_capacity(8 + 2 + 2 + 4 + body_len + 4);
        buf.put_slice(&MAGIC);
        buf.put_u16_le(FormatVersion::CURRENT.major);
        buf.put_u16_le(FormatVersion::CURRENT.minor);
        buf.put_u32_le(u32::try_from(body_len).unwrap_or(u32::MAX));
        let start = buf.len();
        self.encode_body(&mut buf)?;
        let crc = crc32fast::hash(buf.get(start..).unwrap_or_default());
        buf.put_u32_le(crc);
        Ok(buf.freeze())
    }

    /// Decodes the file header at the start of `bytes` (what follows it is
    /// ignored). Same checks as [`RecordingReader::new`].
    pub fn decode(bytes: &[u8]) -> Result<Self, RecordingError> {
        let mut r = bytes;
        read_file_header(&mut r).map(|(header, _, _)| header)
    }
}

/// What a frame record carries.
#[derive(Debug, Clone, PartialEq)]
pub enum FramePayload {
    /// The crop the client cut (and would have sent), plus where it came from.
    Crop {
        /// Similarity `(a, b, tx, ty)` mapping crop pixels to image pixels:
        /// `x' = a*x - b*y + tx`, `y' = b*x + a*y + ty`.
        image_from_crop: [f32; 4],
        /// The crop, as on the wire.
        crop: Crop,
    },
    /// The whole gray8 camera frame.
    FullFrame {
        /// Width in pixels (1..=[`MAX_FULL_FRAME_DIM`]).
        width: u32,
        /// Height in pixels (1..=[`MAX_FULL_FRAME_DIM`]).
        height: u32,
        /// How `data` is encoded; raw means exactly `width * height` bytes.
        encoding: CropEncoding,
        /// The pixels (zero-copy slice of the record buffer after decoding).
        data: Bytes,
    },
}

/// One recorded frame (record kind 1).
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRecord {
    /// Capture time, microseconds on the recording device's clock.
    pub timestamp_us: u64,
    /// Camera pose: row-major 4x4 matrix mapping camera coordinates to world
    /// coordinates.
    pub camera_to_world: [f32; 16],
    /// The pixels.
    pub payload: FramePayload,
    /// Ground-truth landmarks in image pixels, if known (at most
    /// [`MAX_LANDMARKS`]).
    pub ground_truth: Option<Vec<[f32; 2]>>,
    /// Whether a face is present, if known.
    pub face_present: Option<bool>,
}

impl FrameRecord {
    fn validate<E: InvalidError>(&self) -> Result<(), E> {
        check_all_finite(&self.camera_to_world, "camera_to_world")?;
        match &self.payload {
            FramePayload::Crop {
                image_from_crop,
                crop,
            } => {
                check_all_finite(image_from_crop, "image_from_crop")?;
                crop.validate()?;
            }
            FramePayload::FullFrame {
                width,
                height,
                encoding,
                data,
            } => {
                check_dims(*width, *height, MAX_FULL_FRAME_DIM)?;
                check_len("full_frame.data", data.len(), MAX_RECORD_LEN)?;
                if *encoding == CropEncoding::Raw {
                    check_raw_len(*width, *height, data.len())?;
                }
            }
        }
        if let Some(gt) = &self.ground_truth {
            check_points("ground_truth", gt, MAX_LANDMARKS)?;
        }
        Ok(())
    }

    /// The exact length of the record body [`FrameRecord::encode_body`] writes.
    pub fn encoded_body_len(&self) -> usize {
        let payload = match &self.payload {
            FramePayload::Crop { crop, .. } => 16 + crop.encoded_len(),
            FramePayload::FullFrame { data, .. } => 4 + 4 + 1 + 4 + data.len(),
        };
        1 + 8 + 64 + 1 + payload + 1 + self.ground_truth.as_deref().map_or(0, points_len) + 1
    }

    /// Appends the record body (kind byte included, no length or CRC).
    /// On error `buf` is left as it was.
    pub fn encode_body(&self, buf: &mut BytesMut) -> Result<(), EncodeError> {
        self.validate::<EncodeError>()?;
        let start = buf.len();
        buf.reserve(self.encoded_body_len());
        buf.put_u8(KIND_FRAME);
        buf.put_u64_le(self.timestamp_us);
        for v in self.camera_to_world {
            buf.put_f32_le(v);
        }
        match &self.payload {
            FramePayload::Crop {
                image_from_crop,
                crop,
            } => {
                buf.put_u8(PAYLOAD_CROP);
                for v in image_from_crop {
                    buf.put_f32_le(*v);
                }
                if let Err(e) = crop.encode(buf) {
                    buf.truncate(start);
                    return Err(e);
                }
            }
            FramePayload::FullFrame {
                width,
                height,
                encoding,
                data,
            } => {
                buf.put_u8(PAYLOAD_FULL_FRAME);
                buf.put_u32_le(*width);
                buf.put_u32_le(*height);
                buf.put_u8(encoding.as_u8());
                put_payload(buf, data);
            }
        }
        match &self.ground_truth {
            None => buf.put_u8(0),
            Some(points) => {
                buf.put_u8(1);
                put_points(buf, points);
            }
        }
        buf.put_u8(match self.face_present {
            None => 0,
            Some(false) => 1,
            Some(true) => 2,
        });
        Ok(())
    }

    /// Decodes a complete frame-record body (kind byte included) written by
    /// this version: the kind must be [`KIND_FRAME`] and no bytes may follow.
    /// Pixel data is a zero-copy slice of `body`.
    pub fn decode_body(body: Bytes) -> Result<Self, DecodeError> {
        let mut b = body;
        match get_u8(&mut b)? {
            KIND_FRAME => {}
            other => {
                return Err(DecodeError::UnknownValue {
                    field: "record kind",
                    value: u64::from(other),
                });
            }
        }
        let rec = Self::decode_fields(&mut b)?;
        check_trailing(&b, FormatVersion::CURRENT.minor)?;
        Ok(rec)
    }

    fn decode_fields(b: &mut Bytes) -> Result<Self, DecodeError> {
        let timestamp_us = get_u64(b)?;
        let camera_to_world = get_f32_array::<16>(b, "camera_to_world")?;
        let payload = match get_u8(b)? {
            PAYLOAD_CROP => FramePayload::Crop {
                image_from_crop: get_f32_array::<4>(b, "image_from_crop")?,
                crop: Crop::decode(b)?,
            },
            PAYLOAD_FULL_FRAME => {
                let width = get_u32(b)?;
                let height = get_u32(b)?;
                check_dims::<DecodeError>(width, height, MAX_FULL_FRAME_DIM)?;
                let encoding = CropEncoding::decode(b)?;
                let data = get_payload(b, "full_frame.data", MAX_RECORD_LEN)?;
                if encoding == CropEncoding::Raw {
                    check_raw_len::<DecodeError>(width, height, data.len())?;
                }
                FramePayload::FullFrame {
                    width,
                    height,
                    encoding,
                    data,
                }
            }
            other => {
                return Err(DecodeError::UnknownValue {
                    field: "payload",
                    value: u64::from(other),
                });
            }
        };
        let ground_truth = match get_u8(b)? {
            0 => None,
            1 => Some(get_points(b, "ground_truth", MAX_LANDMARKS)?),
            other => {
                return Err(DecodeError::UnknownValue {
                    field: "ground_truth",
                    value: u64::from(other),
                });
            }
        };
        let face_present = match get_u8(b)? {
            0 => None,
            1 => Some(false),
            2 => Some(true),
            other => {
                return Err(DecodeError::UnknownValue {
                    field: "face_present",
                    value: u64::from(other),
                });
            }
        };
        Ok(Self {
            timestamp_us,
            camera_to_world,
            payload,
            ground_truth,
            face_present,
        })
    }
}

/// Trailing bytes are allowed only when the file is from a newer minor version.
fn check_trailing(rest: &Bytes, file_minor: u16) -> Result<(), DecodeError> {
    let newer_minor = file_minor > FormatVersion::CURRENT.minor;
    if rest.has_remaining() && !newer_minor {
        Err(DecodeError::TrailingBytes {
            len: rest.remaining(),
        })
    } else {
        Ok(())
    }
}

/// Decodes a record body of a file with minor version `file_minor`:
/// `Ok(None)` for a kind this version does not know.
fn decode_record_body(body: Bytes, file_minor: u16) -> Result<Option<FrameRecord>, DecodeError> {
    let mut b = body;
    if get_u8(&mut b)? != KIND_FRAME {
        return Ok(None);
    }
    let rec = FrameRecord::decode_fields(&mut b)?;
    check_trailing(&b, file_minor)?;
    Ok(Some(rec))
}

/// Reads until `buf` is full or EOF; returns how many bytes were read.
fn read_full<R: Read + ?Sized>(r: &mut R, buf: &mut [u8]) -> io::Result<usize> {
    let mut filled = 0;
    while let Some(rest) = buf.get_mut(filled..) {
        if rest.is_empty() {
            break;
        }
        match r.read(rest) {
            Ok(0) => break,
            Ok(n) => filled += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(filled)
}

/// Reads up to `len` bytes, growing the buffer only as data arrives (at most
/// doubling), so a lying length prefix cannot make us allocate `len` up front.
fn read_growing<R: Read + ?Sized>(r: &mut R, len: usize) -> io::Result<Vec<u8>> {
    const FIRST_CHUNK: usize = 64 * 1024;
    let mut out = Vec::new();
    while out.len() < len {
        let start = out.len();
        let want = (len - start).min(start.max(FIRST_CHUNK));
        out.resize(start + want, 0);
        let n = match out.get_mut(start..) {
            Some(dst) => read_full(r, dst)?,
            None => 0,
        };
        out.truncate(start + n);
        if n < want {
            break;
        }
    }
    Ok(out)
}

fn split_record_prefix(raw: &[u8; 8]) -> (u32, u32) {
    let [a0, a1, a2, a3, b0, b1, b2, b3] = *raw;
    (
        u32::from_le_bytes([a0, a1, a2, a3]),
        u32::from_le_bytes([b0, b1, b2, b3]),
    )
}

/// Reads and checks the file header; returns it, its version and the number
/// of bytes it took.
fn read_file_header<R: Read + ?Sized>(
    r: &mut R,
) -> Result<(RecordingHeader, FormatVersion, u64), RecordingError> {
    let mut magic = [0_u8; 8];
    let n = read_full(r, &mut magic)?;
    if n < magic.len() {
        return Err(RecordingError::HeaderTruncated { offset: n as u64 });
    }
    if magic != MAGIC {
        return Err(RecordingError::BadMagic { found: magic });
    }
    let mut fixed = [0_u8; 8];
    let n = read_full(r, &mut fixed)?;
    let [ma0, ma1, mi0, mi1, l0, l1, l2, l3] = fixed;
    let version = FormatVersion {
        major: u16::from_le_bytes([ma0, ma1]),
        minor: u16::from_le_bytes([mi0, mi1]),
    };
    if n >= 2 && version.major != FormatVersion::CURRENT.major {
        return Err(RecordingError::UnsupportedVersion {
            major: version.major,
            minor: version.minor,
            supported_major: FormatVersion::CURRENT.major,
        });
    }
    if n < fixed.len() {
        return Err(RecordingError::HeaderTruncated { offset: 8 + n as u64 });
    }
    let len = usize::try_from(u32::from_le_bytes([l0, l1, l2, l3])).unwrap_or(usize::MAX);
    if len > MAX_HEADER_LEN {
        return Err(RecordingError::TooLarge {
            field: "header",
            len,
            max: MAX_HEADER_LEN,
        });
    }
    let body = read_growing(r, len)?;
    if body.len() < len {
        return Err(RecordingError::HeaderTruncated {
            offset: 16 + body.len() as u64,
        });
    }
    let mut crc = [0_u8; 4];
    let n = read_full(r, &mut crc)?;
    if n < crc.len() {
        return Err(RecordingError::HeaderTruncated {
            offset: (16 + len + n) as u64,
        });
    }
    if crc32fast::hash(&body) != u32::from_le_bytes(crc) {
        return Err(RecordingError::HeaderCorrupt);
    }
    let header = RecordingHeader::decode_body(Bytes::from(body), version.minor)
        .map_err(RecordingError::HeaderMalformed)?;
    Ok((header, version, (16 + len + 4) as u64))
}

/// Writes a recording: the header on creation, then one record per
/// [`RecordingWriter::write_record`]. Wrap files in a `BufWriter`.
#[derive(Debug)]
pub struct RecordingWriter<W: Write> {
    inner: W,
    scratch: BytesMut,
    records: u64,
}

impl<W: Write> RecordingWriter<W> {
    /// Writes the file header (format version 1.0) to `inner`.
    pub fn new(mut inner: W, header: &RecordingHeader) -> Result<Self, RecordingError> {
        let bytes = header.encode()?;
        inner.write_all(&bytes)?;
        Ok(Self {
            inner,
            scratch: BytesMut::new(),
            records: 0,
        })
    }

    /// Appends one frame record (length, CRC, body).
    pub fn write_record(&mut self, record: &FrameRecord) -> Result<(), RecordingError> {
        self.scratch.clear();
        self.scratch.reserve(8 + record.encoded_body_len());
        self.scratch.put_u64_le(0);
        record.encode_body(&mut self.scratch)?;
        let body = self.scratch.get(8..).unwrap_or_default();
        let len = body.len();
        if len > MAX_RECORD_LEN {
            return Err(RecordingError::TooLarge {
                field: "record",
                len,
                max: MAX_RECORD_LEN,
            });
        }
        let crc = crc32fast::hash(body);
        let mut prefix = [0_u8; 8];
        let (l, c) = prefix.split_at_mut(4);
        l.copy_from_slice(&u32::try_from(len).unwrap_or(u32::MAX).to_le_bytes());
        c.copy_from_slice(&crc.to_le_bytes());
        if let Some(slot) = self.scratch.get_mut(..8) {
            slot.copy_from_slice(&prefix);
        }
        self.inner.write_all(&self.scratch)?;
        self.records += 1;
        Ok(())
    }

    /// Flushes the records written so far to the underlying writer (a live recording flushes after each
    /// record, so that a killed writer leaves every whole record on disk).
    pub fn flush(&mut self) -> Result<(), RecordingError> {
        self.inner.flush()?;
        Ok(())
    }

    /// Number of records written so far.
    pub fn records_written(&self) -> u64 {
        self.records
    }

    /// Flushes and returns the underlying writer.
    pub fn finish(mut self) -> Result<W, RecordingError> {
        self.inner.flush()?;
        Ok(self.inner)
    }
}

/// Streams a recording record by record. Opening reads and checks the header; a file cut inside a record is an
/// error unless [`RecordingReader::tolerate_cut`] forgives a missing tail.
///
/// After the end of the file or the first error, [`RecordingReader::next_record`]
/// keeps returning `Ok(None)` (and the iterator `None`).
#[derive(Debug)]
pub struct RecordingReader<R: Read> {
    inner: R,
    header: RecordingHeader,
    version: FormatVersion,
    offset: u64,
    record_index: u64,
    frames: u64,
    skipped: u64,
    done: bool,
    /// Whether a file that ends inside a record ends the reading instead of failing it.
    tolerate_cut: bool,
    cut: Option<Cut>,
}

/// Where a recording cut short ends: inside record `record_index`, which starts at byte `offset` (every record
/// before it is whole). What a writer killed part-way leaves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Cut {
    /// The record the file ends inside (0-based, counting every kind).
    pub record_index: u64,
    /// The byte at which that record starts: the length of the file's whole part.
    pub offset: u64,
}

impl<R: Read> RecordingReader<R> {
    /// Reads and validates the file header from `inner`. Wrap files in a
    /// `BufReader`.
    pub fn new(mut inner: R) -> Result<Self, RecordingError> {
        let (header, version, offset) = read_file_header(&mut inner)?;
        Ok(Self {
            inner,
            header,
            version,
            offset,
            record_index: 0,
            frames: 0,
            skipped: 0,
            done: false,
            tolerate_cut: false,
            cut: None,
        })
    }

    /// Reads a file that may have been cut short (a recording whose writer was killed): one that ends inside a
    /// record then ends after its last whole record, as at a clean end, and [`RecordingReader::cut`] says
    /// where. A damaged record (checksum, content) is still an error: only a missing tail is forgiven.
    #[must_use]
    pub fn tolerate_cut(mut self) -> Self {
        self.tolerate_cut = true;
        self
    }

    /// Where the file was cut, once the reading has reached it ([`RecordingReader::tolerate_cut`]).
    pub fn cut(&self) -> Option<Cut> {
        self.cut
    }

    /// The file header.
    pub fn header(&self) -> &RecordingHeader {
        &self.header
    }

    /// The file's format version (major is always the supported one).
    pub fn version(&self) -> FormatVersion {
        self.version
    }

    /// Frame records returned so far.
    pub fn frames_read(&self) -> u64 {
        self.frames
    }

    /// Records of unknown kinds skipped so far.
    pub fn unknown_records_skipped(&self) -> u64 {
        self.skipped
    }

    /// Byte offset of the next record.
    pub fn offset(&self) -> u64 {
        self.offset
    }

    /// Returns the underlying reader.
    pub fn into_inner(self) -> R {
        self.inner
    }

    /// The next frame record, `Ok(None)` at a clean end of file. Records of
    /// unknown kinds are skipped.
    pub fn next_record(&mut self) -> Result<Option<FrameRecord>, RecordingError> {
        if self.done {
            return Ok(None);
        }
        let res = self.read_next();
        if !matches!(res, Ok(Some(_))) {
            self.done = true;
        }
        match res {
            Err(RecordingError::Truncated { record_index, offset }) if self.tolerate_cut => {
                self.cut = Some(Cut { record_index, offset });
                Ok(None)
            }
            res => res,
        }
    }

    fn read_next(&mut self) -> Result<Option<FrameRecord>, RecordingError> {
        loop {
            let record_index = self.record_index;
            let offset = self.offset;
            let mut prefix = [0_u8; 8];
            let n = read_full(&mut self.inner, &mut prefix)?;
            if n == 0 {
                return Ok(None);
            }
            if n < prefix.len() {
                return Err(RecordingError::Truncated { record_index, offset });
            }
            let (len, crc) = split_record_prefix(&prefix);
            let len = usize::try_from(len).unwrap_or(usize::MAX);
            if len > MAX_RECORD_LEN {
                return Err(RecordingError::TooLarge {
                    field: "record",
                    len,
                    max: MAX_RECORD_LEN,
                });
            }
            let body = read_growing(&mut self.inner, len)?;
            if body.len() < len {
                return Err(RecordingError::Truncated { record_index, offset });
            }
            if crc32fast::hash(&body) != crc {
                return Err(RecordingError::Corrupt { record_index, offset });
            }
            self.record_index += 1;
            self.offset += 8 + len as u64;
            match decode_record_body(Bytes::from(body), self.version.minor) {
                Ok(Some(rec)) => {
                    self.frames += 1;
                    return Ok(Some(rec));
                }
                Ok(None) => self.skipped += 1,
                Err(source) => {
                    return Err(RecordingError::Malformed {
                        record_index,
                        offset,
                        source,
                    });
                }
            }
        }
    }
}

impl<R: Read> Iterator for RecordingReader<R> {
    type Item = Result<FrameRecord, RecordingError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_record().transpose()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header() -> RecordingHeader {
        RecordingHeader {
            intrinsics: CameraIntrinsics {
                fx: 1.0,
                fy: 2.0,
                cx: 3.0,
                cy: 4.0,
                width: 640,
                height: 480,
            },
            source: "ab".into(),
            created_unix_ms: 5,
        }
    }

    fn crop_record(ts: u64) -> FrameRecord {
        FrameRecord {
            timestamp_us: ts,
            camera_to_world: [0.0; 16],
            payload: FramePayload::Crop {
                image_from_crop: [1.0, 0.0, 10.0, 20.0],
                crop: Crop::raw(2, 2, vec![1, 2, 3, 4]),
            },
            ground_truth: Some(vec![[1.5, 2.5]]),
            face_present: Some(true),
        }
    }

    fn full_record() -> FrameRecord {
        FrameRecord {
            timestamp_us: 1,
            camera_to_world: [1.0; 16],
            payload: FramePayload::FullFrame {
                width: 3,
                height: 1,
                encoding: CropEncoding::Raw,
                data: Bytes::from_static(&[9, 8, 7]),
            },
            ground_truth: None,
            face_present: None,
        }
    }

    fn write(records: &[FrameRecord]) -> Vec<u8> {
        let mut w = RecordingWriter::new(Vec::new(), &header()).unwrap();
        for r in records {
            w.write_record(r).unwrap();
        }
        assert_eq!(w.records_written(), records.len() as u64);
        w.finish().unwrap()
    }

    /// Appends a raw record (length, CRC, body) to a file image.
    fn push_raw(file: &mut Vec<u8>, body: &[u8]) {
        file.extend_from_slice(&(body.len() as u32).to_le_bytes());
        file.extend_from_slice(&crc32fast::hash(body).to_le_bytes());
        file.extend_from_slice(body);
    }

    #[test]
    fn header_layout() {
        let bytes = header().encode().unwrap();
        #[rustfmt::skip]
        let body: &[u8] = &[
            0x00, 0x00, 0x80, 0x3f, 0x00, 0x00, 0x00, 0x40, // fx 1.0, fy 2.0
            0x00, 0x00, 0x40, 0x40, 0x00, 0x00, 0x80, 0x40, // cx 3.0, cy 4.0
            0x80, 0x02, 0x00, 0x00, 0xe0, 0x01, 0x00, 0x00, // 640, 480
            0x02, 0x00, b'a', b'b',                         // source "ab"
            0x05, 0, 0, 0, 0, 0, 0, 0,                      // created_unix_ms 5
        ];
        let mut expected = b"HFREC\0\r\n".to_vec();
        expected.extend_from_slice(&[1, 0, 0, 0, body.len() as u8, 0, 0, 0]);
        expected.extend_from_slice(body);
        expected.extend_from_slice(&crc32fast::hash(body).to_le_bytes());
        assert_eq!(&bytes[..], &expected[..]);
        assert_eq!(RecordingHeader::decode(&bytes).unwrap(), header());
    }

    #[test]
    fn record_body_layout() {
        let mut buf = BytesMut::new();
        full_record().encode_body(&mut buf).unwrap();
        let mut expected = vec![KIND_FRAME, 1, 0, 0, 0, 0, 0, 0, 0];
        for _ in 0..16 {
            expected.extend_from_slice(&1.0_f32.to_le_bytes());
        }
        expected.extend_from_slice(&[1, 3, 0, 0, 0, 1, 0, 0, 0, 0, 3, 0, 0, 0, 9, 8, 7]);
        expected.extend_from_slice(&[0, 0]); // no ground truth, face unknown
        assert_eq!(&buf[..], &expected[..]);
        assert_eq!(buf.len(), full_record().encoded_body_len());
        assert_eq!(FrameRecord::decode_body(buf.freeze()).unwrap(), full_record());
    }

    #[test]
    fn round_trip_and_clean_eof() {
        let records = vec![crop_record(1), full_record(), crop_record(3)];
        let file = write(&records);
        let mut reader = RecordingReader::new(&file[..]).unwrap();
        assert_eq!(reader.header(), &header());
        assert_eq!(reader.version(), FormatVersion::CURRENT);
        let got: Vec<_> = reader.by_ref().collect::<Result<_, _>>().unwrap();
        assert_eq!(got, records);
        assert_eq!(reader.frames_read(), 3);
        assert_eq!(reader.offset(), file.len() as u64);
        assert!(reader.next_record().unwrap().is_none());
    }

    #[test]
    fn truncation_corruption_and_size_errors() {
        let file = write(&[crop_record(1), crop_record(2)]);
        let header_len = header().encode().unwrap().len();
        let first_len = 8 + crop_record(1).encoded_body_len();

        // EOF inside the second record.
        let cut = &file[..file.len() - 1];
        let mut r = RecordingReader::new(cut).unwrap();
        assert!(r.next_record().unwrap().is_some());
        match r.next_record() {
            Err(RecordingError::Truncated {
                record_index: 1,
                offset,
            }) => {
                assert_eq!(offset, (header_len + first_len) as u64);
            }
            other => panic!("{other:?}"),
        }
        assert!(r.next_record().unwrap().is_none(), "fused after an error");

        // A flipped bit in the first body.
        let mut bad = file.clone();
        bad[header_len + 8 + 3] ^= 0x10;
        let mut r = RecordingReader::new(&bad[..]).unwrap();
        assert!(matches!(
            r.next_record(),
            Err(RecordingError::Corrupt { record_index: 0, offset }) if offset == header_len as u64
        ));

        // A huge length prefix followed by a few bytes: rejected before allocating.
        let mut huge = file[..header_len].to_vec();
        huge.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0, 0, 0, 0, 1, 2, 3]);
        let mut r = RecordingReader::new(&huge[..]).unwrap();
        assert!(matches!(
            r.next_record(),
            Err(RecordingError::TooLarge {
                field: "record",
                len: 0xffff_ffff,
                max: MAX_RECORD_LEN
            })
        ));

        // A 32 MiB claim (allowed) over 3 bytes: Truncated, without a 32 MiB buffer.
        let mut lying = file[..header_len].to_vec();
        lying.extend_from_slice(&(MAX_RECORD_LEN as u32).to_le_bytes());
        lying.extend_from_slice(&[0, 0, 0, 0, 1, 2, 3]);
        let mut r = RecordingReader::new(&lying[..]).unwrap();
        assert!(matches!(
            r.next_record(),
            Err(RecordingError::Truncated { record_index: 0, .. })
        ));
    }

    #[test]
    fn header_errors() {
        let good = header().encode().unwrap().to_vec();
        assert!(matches!(
            RecordingHeader::decode(&good[..5]),
            Err(RecordingError::HeaderTruncated { offset: 5 })
        ));
        let mut text_mode = good.clone();
        text_mode.splice(6..8, [b'\n']);
        assert!(matches!(
            RecordingHeader::decode(&text_mode),
            Err(RecordingError::BadMagic { .. })
        ));
        let mut v2 = good.clone();
        v2[8] = 2;
        assert!(matches!(
            RecordingHeader::decode(&v2),
            Err(RecordingError::UnsupportedVersion {
                major: 2,
                minor: 0,
                supported_major: 1
            })
        ));
        let mut big = good.clone();
        big[12..16].copy_from_slice(&(MAX_HEADER_LEN as u32 + 1).to_le_bytes());
        assert!(matches!(
            RecordingHeader::decode(&big),
            Err(RecordingError::TooLarge { field: "header", .. })
        ));
        let mut flipped = good.clone();
        flipped[20] ^= 1;
        assert!(matches!(
            RecordingHeader::decode(&flipped),
            Err(RecordingError::HeaderCorrupt)
        ));
        // Non-finite intrinsics are refused on both sides.
        let mut h = header();
        h.intrinsics.fx = f32::INFINITY;
        assert_eq!(h.encode(), Err(EncodeError::NonFinite { field: "intrinsics" }));
    }

    /// A file from a newer minor version: appended header fields, an appended
    /// record field and an unknown record kind.
    fn newer_minor_file() -> Vec<u8> {
        let mut hbody = BytesMut::new();
        header().encode_body(&mut hbody).unwrap();
        hbody.extend_from_slice(&[0xde, 0xad]); // field added in 1.1
        let mut file = MAGIC.to_vec();
        file.extend_from_slice(&[1, 0, 1, 0]);
        file.extend_from_slice(&(hbody.len() as u32).to_le_bytes());
        file.extend_from_slice(&hbody);
        file.extend_from_slice(&crc32fast::hash(&hbody).to_le_bytes());

        let mut body = BytesMut::new();
        crop_record(1).encode_body(&mut body).unwrap();
        body.extend_from_slice(&[7, 7, 7]); // field added in 1.1
        push_raw(&mut file, &body);
        push_raw(&mut file, &[42, 1, 2, 3]); // kind 42, unknown
        let mut body = BytesMut::new();
        full_record().encode_body(&mut body).unwrap();
        push_raw(&mut file, &body);
        file
    }

    #[test]
    fn newer_minor_is_read_forward_compatibly() {
        let file = newer_minor_file();
        let mut r = RecordingReader::new(&file[..]).unwrap();
        assert_eq!(r.version(), FormatVersion { major: 1, minor: 1 });
        assert_eq!(r.header(), &header());
        assert_eq!(r.next_record().unwrap(), Some(crop_record(1)));
        assert_eq!(r.next_record().unwrap(), Some(full_record()));
        assert_eq!(r.unknown_records_skipped(), 1);
        assert!(r.next_record().unwrap().is_none());
    }

    #[test]
    fn same_minor_trailing_bytes_are_malformed() {
        let mut file = header().encode().unwrap().to_vec();
        let mut body = BytesMut::new();
        crop_record(1).encode_body(&mut body).unwrap();
        body.put_u8(0);
        push_raw(&mut file, &body);
        let mut r = RecordingReader::new(&file[..]).unwrap();
        assert!(matches!(
            r.next_record(),
            Err(RecordingError::Malformed {
                record_index: 0,
                source: DecodeError::TrailingBytes { len: 1 },
                ..
            })
        ));
        assert_eq!(
            FrameRecord::decode_body(Bytes::from_static(&[42])),
            Err(DecodeError::UnknownValue {
                field: "record kind",
                value: 42
            })
        );
    }

    #[test]
    fn invalid_records_are_refused_by_the_writer() {
        let mut w = RecordingWriter::new(Vec::new(), &header()).unwrap();
        let mut rec = full_record();
        rec.payload = FramePayload::FullFrame {
            width: 4,
            height: 4,
            encoding: CropEncoding::Raw,
            data: Bytes::from_static(&[0; 3]),
        };
        assert!(matches!(
            w.write_record(&rec),
            Err(RecordingError::Encode(EncodeError::RawSizeMismatch {
                expected: 16,
                len: 3,
                ..
            }))
        ));
        let mut rec = crop_record(0);
        rec.ground_truth = Some(vec![[f32::NAN, 0.0]]);
        assert!(matches!(
            w.write_record(&rec),
            Err(RecordingError::Encode(EncodeError::NonFinite { .. }))
        ));
        assert_eq!(w.records_written(), 0);
        assert_eq!(w.finish().unwrap(), header().encode().unwrap().to_vec());
    }
}
