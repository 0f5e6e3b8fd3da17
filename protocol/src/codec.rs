//! The hand-written little-endian codec: [`Encode`] / [`Decode`] traits and the
//! primitive readers and writers every message is built from.
//!
//! Primitive encodings (all little-endian, no padding, no varints):
//!
//! | type | bytes |
//! |---|---|
//! | `u8` / `u16` / `u32` / `u64` | 1 / 2 / 4 / 8, little-endian |
//! | `f32` | 4, IEEE-754 bits little-endian; NaN and ±inf are rejected |
//! | `bool` | never used bare; see the field docs |
//! | string | `u16` byte length, then that many UTF-8 bytes |
//! | point list | `u16` count, then `count` × (`f32` x, `f32` y) |
//! | byte payload | `u32` byte length, then the bytes (sliced zero-copy on decode) |
//!
//! Decoders read from a `&mut Bytes` cursor: every read first checks
//! `remaining()`, returning [`DecodeError::Short`] instead of panicking, and
//! every length prefix is checked against its limit *before* the bytes are
//! waited for or allocated, so an oversize prefix fails with
//! [`DecodeError::TooLarge`] even when only the prefix has arrived.

use bytes::{Buf, BufMut, Bytes, BytesMut};

use crate::error::{DecodeError, EncodeError, InvalidError};

/// A value with a fixed, documented little-endian wire layout.
///
/// `encode` appends the value's bytes to `buf`. It validates every limit
/// first, so on error it has written nothing.
pub trait Encode {
    /// Appends the encoding of `self` to `buf`, or returns why it cannot be
    /// encoded (leaving `buf` unchanged).
    fn encode(&self, buf: &mut BytesMut) -> Result<(), EncodeError>;

    /// The exact number of bytes `encode` appends on success.
    fn encoded_len(&self) -> usize;
}

/// A value that can be decoded from the front of a byte buffer.
pub trait Decode: Sized {
    /// Decodes one value from the front of `buf`, advancing it past the
    /// value. Byte payloads are sliced out of `buf` without copying.
    ///
    /// [`DecodeError::Short`] means `buf` ended before the value did; `buf`
    /// may then have been partly consumed, so retry on a fresh view of the
    /// whole input.
    fn decode(buf: &mut Bytes) -> Result<Self, DecodeError>;
}

/// Fails with `Short` unless `buf` holds at least `n` more bytes.
#[inline]
pub(crate) fn need(buf: &Bytes, n: usize) -> Result<(), DecodeError> {
    let have = buf.remaining();
    if have < n {
        Err(DecodeError::Short { needed: n - have })
    } else {
        Ok(())
    }
}

#[inline]
pub(crate) fn get_u8(buf: &mut Bytes) -> Result<u8, DecodeError> {
    need(buf, 1)?;
    Ok(buf.get_u8())
}

#[inline]
pub(crate) fn get_u16(buf: &mut Bytes) -> Result<u16, DecodeError> {
    need(buf, 2)?;
    Ok(buf.get_u16_le())
}

#[inline]
pub(crate) fn get_u32(buf: &mut Bytes) -> Result<u32, DecodeError> {
    need(buf, 4)?;
    Ok(buf.get_u32_le())
}

#[inline]
pub(crate) fn get_u64(buf: &mut Bytes) -> Result<u64, DecodeError> {
    need(buf, 8)?;
    Ok(buf.get_u64_le())
}

/// Reads a finite `f32`.
#[inline]
pub(crate) fn get_f32(buf: &mut Bytes, field: &'static str) -> Result<f32, DecodeError> {
    need(buf, 4)?;
    let v = buf.get_f32_le();
    check_finite(v, field)?;
    Ok(v)
}

/// Reads `N` finite `f32`s.
pub(crate) fn get_f32_array<const N: usize>(
    buf: &mut Bytes,
    field: &'static str,
) -> Result<[f32; N], DecodeError> {
    need(buf, 4 * N)?;
    let mut out = [0.0_f32; N];
    let (words, _) = buf.get(..4 * N).unwrap_or_default().as_chunks::<4>();
    for (v, w) in out.iter_mut().zip(words) {
        *v = f32::from_le_bytes(*w);
        check_finite(*v, field)?;
    }
    buf.advance(4 * N);
    Ok(out)
}

/// Reads a `u16`-length-prefixed UTF-8 string of at most `max` bytes.
pub(crate) fn get_string(buf: &mut Bytes, field: &'static str, max: usize) -> Result<String, DecodeError> {
    let len = usize::from(get_u16(buf)?);
    check_len(field, len, max)?;
    need(buf, len)?;
    let raw = buf.split_to(len);
    match std::str::from_utf8(&raw) {
        Ok(s) => Ok(s.to_owned()),
        Err(_) => Err(DecodeError::InvalidUtf8 { field }),
    }
}

/// Reads a `u16`-count-prefixed list of at most `max` finite points.
pub(crate) fn get_points(
    buf: &mut Bytes,
    field: &'static str,
    max: usize,
) -> Result<Vec<[f32; 2]>, DecodeError> {
    let count = usize::from(get_u16(buf)?);
    check_len(field, count, max)?;
    let len = count * 8;
    need(buf, len)?;
    // One bounds check for the whole list, then plain array reads into an
    // exactly-sized Vec (at most `max` points: the count was checked above).
    let (pairs, _) = buf.get(..len).unwrap_or_default().as_chunks::<8>();
    let out: Vec<[f32; 2]> = pairs
        .iter()
        .map(|&[x0, x1, x2, x3, y0, y1, y2, y3]| {
            [
                f32::from_le_bytes([x0, x1, x2, x3]),
                f32::from_le_bytes([y0, y1, y2, y3]),
            ]
        })
        .collect();
    if !all_finite(out.as_flattened()) {
        return Err(DecodeError::NonFinite { field });
    }
    buf.advance(len);
    Ok(out)
}

/// Reads a `u32`-length-prefixed payload of at most `max` bytes, zero-copy.
pub(crate) fn get_payload(buf: &mut Bytes, field: &'static str, max: usize) -> Result<Bytes, DecodeError> {
    let len = usize::try_from(get_u32(buf)?).unwrap_or(usize::MAX);
    check_len(field, len, max)?;
    need(buf, len)?;
    Ok(buf.split_to(len))
}

#[inline]
pub(crate) fn check_len<E: InvalidError>(field: &'static str, len: usize, max: usize) -> Result<(), E> {
    if len > max {
        Err(E::too_large(field, len, max))
    } else {
        Ok(())
    }
}

#[inline]
pub(crate) fn check_finite<E: InvalidError>(v: f32, field: &'static str) -> Result<(), E> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(E::non_finite(field))
    }
}

pub(crate) fn check_all_finite<E: InvalidError>(vs: &[f32], field: &'static str) -> Result<(), E> {
    vs.iter().try_for_each(|&v| check_finite(v, field))
}

pub(crate) fn check_points<E: InvalidError>(
    field: &'static str,
    points: &[[f32; 2]],
    max: usize,
) -> Result<(), E> {
    check_len(field, points.len(), max)?;
    if all_finite(points.as_flattened()) {
        Ok(())
    } else {
        Err(E::non_finite(field))
    }
}

/// Branch-free (vectorisable) "no NaN or infinity in `vs`".
fn all_finite(vs: &[f32]) -> bool {
    vs.iter().fold(true, |ok, v| ok & v.is_finite())
}

/// Writes a string whose length was already checked against a limit that
/// fits in `u16`.
pub(crate) fn put_string(buf: &mut BytesMut, s: &str) {
    put_len_u16(buf, s.len());
    buf.put_slice(s.as_bytes());
}

pub(crate) fn put_points(buf: &mut BytesMut, points: &[[f32; 2]]) {
    put_len_u16(buf, points.len());
    // Size once, then fill: per-float `put_f32_le` calls are several times slower.
    let start = buf.len();
    buf.resize(start + 8 * points.len(), 0);
    let (dst, _) = buf.get_mut(start..).unwrap_or_default().as_chunks_mut::<8>();
    for (d, [x, y]) in dst.iter_mut().zip(points) {
        let [x0, x1, x2, x3] = x.to_le_bytes();
        let [y0, y1, y2, y3] = y.to_le_bytes();
        *d = [x0, x1, x2, x3, y0, y1, y2, y3];
    }
}

pub(crate) fn put_payload(buf: &mut BytesMut, data: &[u8]) {
    // Callers check the length against a limit far below u32::MAX first.
    buf.put_u32_le(u32::try_from(data.len()).unwrap_or(u32::MAX));
    buf.put_slice(data);
}

fn put_len_u16(buf: &mut BytesMut, len: usize) {
    // Callers check the length against a limit far below u16::MAX first.
    buf.put_u16_le(u16::try_from(len).unwrap_or(u16::MAX));
}

/// Wire size of a `u16`-prefixed string.
pub(crate) const fn string_len(s: &str) -> usize {
    2 + s.len()
}

/// Wire size of a `u16`-prefixed point list.
pub(crate) const fn points_len(points: &[[f32; 2]]) -> usize {
    2 + 8 * points.len()
}

// Limits that use u16 prefixes must fit.
const _: () = {
    use crate::limits::*;
    assert!(MAX_TOKEN_LEN <= u16::MAX as usize);
    assert!(MAX_NAME_LEN <= u16::MAX as usize);
    assert!(MAX_LANDMARKS <= u16::MAX as usize);
    assert!(MAX_ERROR_TEXT_LEN <= u16::MAX as usize);
    assert!(MAX_SOURCE_LEN <= u16::MAX as usize);
    assert!(MAX_RECORD_LEN <= u32::MAX as usize);
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_reports_missing_bytes() {
        let mut b = Bytes::from_static(&[1, 2, 3]);
        assert_eq!(get_u64(&mut b), Err(DecodeError::Short { needed: 5 }));
        assert_eq!(get_u16(&mut b), Ok(0x0201));
    }

    #[test]
    fn oversize_prefix_rejected_before_payload_arrives() {
        // Length 300 for a 256-byte field, with no payload at all.
        let mut b = Bytes::from_static(&[0x2c, 0x01]);
        assert_eq!(
            get_string(&mut b, "token", 256),
            Err(DecodeError::TooLarge {
                field: "token",
                len: 300,
                max: 256
            })
        );
        let mut b = Bytes::from_static(&[0xff, 0xff, 0xff, 0xff]);
        assert_eq!(
            get_payload(&mut b, "crop.data", 10),
            Err(DecodeError::TooLarge {
                field: "crop.data",
                len: u32::MAX as usize,
                max: 10
            })
        );
    }

    #[test]
    fn strings_and_points() {
        let mut b = Bytes::from_static(&[2, 0, b'h', b'i', 1, 0, 0, 0, 0x80, 0x3f, 0, 0, 0, 0x40]);
        assert_eq!(get_string(&mut b, "s", 8).as_deref(), Ok("hi"));
        assert_eq!(get_points(&mut b, "p", 8), Ok(vec![[1.0, 2.0]]));
        assert!(b.is_empty());

        let mut b = Bytes::from_static(&[2, 0, 0xff, 0xfe]);
        assert_eq!(
            get_string(&mut b, "s", 8),
            Err(DecodeError::InvalidUtf8 { field: "s" })
        );

        let nan = f32::NAN.to_le_bytes();
        let mut v = vec![1, 0, 0, 0, 0, 0];
        v.extend_from_slice(&nan);
        assert_eq!(
            get_points(&mut Bytes::from(v), "p", 8),
            Err(DecodeError::NonFinite { field: "p" })
        );
    }
}
