//! The one framing of holoface's binary files: the KRFWS and refiner models, teacher-label files and the
//! refiner's training cache. One writer ([`encode`], [`FramedWriter`]), one reader ([`decode`],
//! [`FramedReader`]) and one error ([`FormatError`]: which kind of file, what is damaged, where).
//!
//! ```text
//! offset  size  field
//! 0       8     magic, one per kind of file (Format::magic)
//! 8       4     version u32 (Format::oldest ..= Format::newest)
//! 12      4     payload length P u32 (versions >= Format::sized_from)
//! 16      P     payload, the kind's own layout
//! 16+P    4     CRC-32 (IEEE) of bytes 0 .. 16+P
//! ```
//!
//! Everything is little-endian. A version older than [`Format::sized_from`] (files written before the
//! framing was shared: refiner models v1 and v2) has no length field: its payload runs from offset 12 to the
//! CRC. The recorded stream (`.hfrec`, [`crate::recording`]) keeps its own framing: it is written frame by
//! frame while a headset streams, so it cannot know its length up front, and a recording cut short by a
//! crash must keep every whole frame before the cut; each of its records carries its own length and CRC.
//!
//! The reader checks the magic, the version, the length against the file's size (a truncated file is
//! [`Damage::Truncated`], not a checksum error) and the CRC before the payload is parsed; [`PayloadReader`]
//! then reads the payload's fields with every count checked against the bytes left before anything is
//! allocated, so a damaged file is an error naming the field and its file offset, never a panic.

use std::io::{self, Read, Write};

use thiserror::Error;

/// Header bytes before a sized payload: magic, version, length.
pub const HEADER_LEN: usize = 16;
/// Bytes of the CRC after the payload.
pub const CRC_LEN: usize = 4;

/// One kind of framed file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Format {
    /// What the file is, for errors ("KRFWS model").
    pub name: &'static str,
    /// Its first eight bytes.
    pub magic: [u8; 8],
    /// Oldest version this build reads.
    pub oldest: u32,
    /// Newest version, the one [`encode`] writes.
    pub newest: u32,
    /// First version whose header carries the payload length (older ones run to the CRC).
    pub sized_from: u32,
    /// Largest payload accepted, checked before anything is read.
    pub max_payload: u64,
}

/// A damaged or foreign file: which kind of file, and what is wrong with it.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[error("{file}: {damage}")]
pub struct FormatError {
    /// The kind of file ([`Format::name`]).
    pub file: &'static str,
    /// What is wrong.
    pub damage: Damage,
}

/// What is wrong with a file.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum Damage {
    /// The file ends before a field.
    #[error("truncated: {needed} bytes needed at offset {offset}, the file has {len}")]
    Truncated {
        /// File offset of the field.
        offset: u64,
        /// Bytes the field needs.
        needed: u64,
        /// File length.
        len: u64,
    },
    /// Another kind of file.
    #[error("not this kind of file (magic {found:02x?}, expected {expected:02x?})")]
    BadMagic {
        /// The file's first eight bytes.
        found: [u8; 8],
        /// The kind's magic.
        expected: [u8; 8],
    },
    /// Written by a format version this build does not read.
    #[error("format version {found}, this build reads {oldest}..={newest}")]
    UnsupportedVersion {
        /// Version in the file.
        found: u32,
        /// Oldest version read.
        oldest: u32,
        /// Newest version read.
        newest: u32,
    },
    /// The header declares a payload over the kind's limit.
    #[error("header declares a {declared}-byte payload, at most {max} are accepted")]
    TooLarge {
        /// Declared payload length.
        declared: u64,
        /// The kind's limit.
        max: u64,
    },
    /// The checksum does not match: the file was changed or damaged after it was written.
    #[error("checksum mismatch: stored {stored:#010x}, computed {computed:#010x}")]
    Checksum {
        /// CRC in the file.
        stored: u32,
        /// CRC of the bytes.
        computed: u32,
    },
    /// A count or value is outside its allowed range.
    #[error("{field} = {value} is outside {min}..={max}")]
    OutOfRange {
        /// Which field.
        field: &'static str,
        /// Its value.
        value: u64,
        /// Smallest allowed.
        min: u64,
        /// Largest allowed.
        max: u64,
    },
    /// A float is NaN or infinite.
    #[error("non-finite value in {field} at index {index}")]
    NotFinite {
        /// Which field.
        field: &'static str,
        /// Index of the value.
        index: usize,
    },
    /// A field's content is invalid (not UTF-8, an index out of order, ...).
    #[error("{field} at offset {offset}: {reason}")]
    Invalid {
        /// Which field.
        field: &'static str,
        /// File offset just after the field.
        offset: u64,
        /// What is wrong.
        reason: String,
    },
    /// Bytes after the payload's last field, or after the CRC.
    #[error("{count} bytes after the last field")]
    TrailingBytes {
        /// How many.
        count: u64,
    },
}

impl Format {
    /// An error about a file of this kind.
    pub fn error(&self, damage: Damage) -> FormatError {
        FormatError {
            file: self.name,
            damage,
        }
    }

    /// Reads the header from the file's first bytes (`head`, up to [`HEADER_LEN`]) of a file of `file_len`
    /// bytes: the version, where the payload starts and how long it is.
    fn header(&self, head: &[u8], file_len: u64) -> Result<Header, FormatError> {
        let truncated = |offset: u64, needed: u64| {
            self.error(Damage::Truncated {
                offset,
                needed,
                len: file_len,
            })
        };
        let field = |at: usize| -> Result<u32, FormatError> {
            head.get(at..at + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .ok_or_else(|| truncated(at as u64, 4))
        };
        let magic: [u8; 8] = head
            .get(..8)
            .and_then(|m| m.try_into().ok())
            .ok_or_else(|| truncated(0, 8))?;
        if magic != self.magic {
            return Err(self.error(Damage::BadMagic {
                found: magic,
                expected: self.magic,
            }));
        }
        let version = field(8)?;
        if !(self.oldest..=self.newest).contains(&version) {
            return Err(self.error(Damage::UnsupportedVersion {
                found: version,
                oldest: self.oldest,
                newest: self.newest,
            }));
        }
        let (start, payload_len) = if version >= self.sized_from {
            (HEADER_LEN as u64, u64::from(field(12)?))
        } else {
            let start = 12u64;
            let min = start + CRC_LEN as u64;
            if file_len < min {
                return Err(truncated(file_len, min - file_len));
            }
            (start, file_len - min)
        };
        if payload_len > self.max_payload {
            return Err(self.error(Damage::TooLarge {
                declared: payload_len,
                max: self.max_payload,
            }));
        }
        let expected = start + payload_len + CRC_LEN as u64;
        if file_len < expected {
            return Err(truncated(file_len, expected - file_len));
        }
        if file_len > expected {
            return Err(self.error(Damage::TrailingBytes {
                count: file_len - expected,
            }));
        }
        Ok(Header {
            version,
            start,
            payload_len,
        })
    }

    /// The header of the newest version for a payload of `payload_len` bytes.
    fn write_header(&self, payload_len: u64) -> Result<[u8; HEADER_LEN], FormatError> {
        let len = u32::try_from(payload_len)
            .ok()
            .filter(|_| payload_len <= self.max_payload)
            .ok_or_else(|| {
                self.error(Damage::TooLarge {
                    declared: payload_len,
                    max: self.max_payload,
                })
            })?;
        let mut h = [0u8; HEADER_LEN];
        h[..8].copy_from_slice(&self.magic);
        h[8..12].copy_from_slice(&self.newest.to_le_bytes());
        h[12..].copy_from_slice(&len.to_le_bytes());
        Ok(h)
    }
}

struct Header {
    version: u32,
    start: u64,
    payload_len: u64,
}

/// A whole file of `kind` around `payload`, in the newest version.
///
/// # Errors
/// [`Damage::TooLarge`]: the payload is over the kind's limit (the reader would refuse the file).
pub fn encode(kind: &Format, payload: &[u8]) -> Result<Vec<u8>, FormatError> {
    let header = kind.write_header(payload.len() as u64)?;
    let mut out = Vec::with_capacity(HEADER_LEN + payload.len() + CRC_LEN);
    out.extend_from_slice(&header);
    out.extend_from_slice(payload);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    Ok(out)
}

/// Checks a whole file of `kind` (magic, version, length, CRC) and hands its payload to a reader.
///
/// # Errors
/// [`FormatError`] for a foreign, truncated, over-long, future-version or damaged file.
pub fn decode<'a>(kind: &Format, bytes: &'a [u8]) -> Result<Framed<'a>, FormatError> {
    let file_len = bytes.len() as u64;
    let header = kind.header(&bytes[..bytes.len().min(HEADER_LEN)], file_len)?;
    let end = (header.start + header.payload_len) as usize;
    let (body, crc) = bytes.split_at(end);
    let stored = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
    let computed = crc32fast::hash(body);
    if stored != computed {
        return Err(kind.error(Damage::Checksum { stored, computed }));
    }
    Ok(Framed {
        version: header.version,
        payload: PayloadReader {
            file: kind.name,
            data: &body[header.start as usize..],
            pos: 0,
            base: header.start,
            file_len,
        },
    })
}

/// A checked file: its version and a reader over its payload.
#[derive(Debug)]
pub struct Framed<'a> {
    /// The file's format version.
    pub version: u32,
    /// The payload.
    pub payload: PayloadReader<'a>,
}

/// Reads a payload's fields; every error names the kind of file and the field's file offset.
#[derive(Debug)]
pub struct PayloadReader<'a> {
    file: &'static str,
    data: &'a [u8],
    pos: usize,
    /// File offset of `data[0]`.
    base: u64,
    file_len: u64,
}

impl<'a> PayloadReader<'a> {
    /// An error about this file.
    pub fn error(&self, damage: Damage) -> FormatError {
        FormatError {
            file: self.file,
            damage,
        }
    }

    /// [`Damage::OutOfRange`].
    pub fn out_of_range(&self, field: &'static str, value: u64, min: u64, max: u64) -> FormatError {
        self.error(Damage::OutOfRange {
            field,
            value,
            min,
            max,
        })
    }

    /// [`Damage::Invalid`] at the current offset.
    pub fn invalid(&self, field: &'static str, reason: impl Into<String>) -> FormatError {
        self.error(Damage::Invalid {
            field,
            offset: self.offset(),
            reason: reason.into(),
        })
    }

    /// File offset of the next byte.
    pub fn offset(&self) -> u64 {
        self.base + self.pos as u64
    }

    /// Payload bytes not yet read.
    pub fn left(&self) -> usize {
        self.data.len() - self.pos
    }

    /// Fails unless `n` more bytes are left (checked before allocating for them).
    pub fn need(&self, n: u64) -> Result<(), FormatError> {
        if n > self.left() as u64 {
            return Err(self.error(Damage::Truncated {
                offset: self.offset(),
                needed: n,
                len: self.file_len,
            }));
        }
        Ok(())
    }

    /// The next `n` bytes.
    pub fn take(&mut self, n: usize) -> Result<&'a [u8], FormatError> {
        self.need(n as u64)?;
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    /// The next `N` bytes as an array.
    pub fn array<const N: usize>(&mut self) -> Result<[u8; N], FormatError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N)?);
        Ok(a)
    }

    /// A `u8`.
    pub fn u8(&mut self) -> Result<u8, FormatError> {
        Ok(self.take(1)?[0])
    }

    /// A little-endian `u16`.
    pub fn u16(&mut self) -> Result<u16, FormatError> {
        Ok(u16::from_le_bytes(self.array()?))
    }

    /// A little-endian `u32`.
    pub fn u32(&mut self) -> Result<u32, FormatError> {
        Ok(u32::from_le_bytes(self.array()?))
    }

    /// A little-endian `i32`.
    pub fn i32(&mut self) -> Result<i32, FormatError> {
        Ok(i32::from_le_bytes(self.array()?))
    }

    /// A little-endian `f32` that must be finite (`field` and `index` name it in the error).
    pub fn f32(&mut self, field: &'static str, index: usize) -> Result<f32, FormatError> {
        let v = f32::from_le_bytes(self.array()?);
        if !v.is_finite() {
            return Err(self.error(Damage::NotFinite { field, index }));
        }
        Ok(v)
    }

    /// `v` when it is in `min..=max`, else [`Damage::OutOfRange`] naming `field`.
    fn bounded<T: Copy + PartialOrd + Into<u64>>(
        &self,
        field: &'static str,
        v: T,
        min: T,
        max: T,
    ) -> Result<T, FormatError> {
        if v < min || v > max {
            return Err(self.out_of_range(field, v.into(), min.into(), max.into()));
        }
        Ok(v)
    }

    /// A little-endian `u32` count in `min..=max`.
    pub fn count(&mut self, field: &'static str, min: u32, max: u32) -> Result<u32, FormatError> {
        let v = self.u32()?;
        self.bounded(field, v, min, max)
    }

    /// A `u8` in `min..=max`.
    pub fn u8_in(&mut self, field: &'static str, min: u8, max: u8) -> Result<u8, FormatError> {
        let v = self.u8()?;
        self.bounded(field, v, min, max)
    }

    /// A little-endian `u16` in `min..=max`.
    pub fn u16_in(&mut self, field: &'static str, min: u16, max: u16) -> Result<u16, FormatError> {
        let v = self.u16()?;
        self.bounded(field, v, min, max)
    }

    /// `u16` length + UTF-8 text of at most `max` bytes.
    pub fn text(&mut self, field: &'static str, max: usize) -> Result<&'a str, FormatError> {
        let n = usize::from(self.u16()?);
        if n > max {
            return Err(self.out_of_range(field, n as u64, 0, max as u64));
        }
        let b = self.take(n)?;
        std::str::from_utf8(b).map_err(|_| self.invalid(field, "not UTF-8"))
    }

    /// Fails if any payload byte is left unread.
    pub fn finish(self) -> Result<(), FormatError> {
        match self.left() {
            0 => Ok(()),
            n => Err(self.error(Damage::TrailingBytes { count: n as u64 })),
        }
    }
}

/// Writes a framed file as a stream: the header, then the payload through [`Write`], then the CRC at
/// [`FramedWriter::finish`], which fails unless exactly the declared payload was written.
#[derive(Debug)]
pub struct FramedWriter<W: Write> {
    inner: W,
    crc: crc32fast::Hasher,
    declared: u64,
    written: u64,
    file: &'static str,
}

impl<W: Write> FramedWriter<W> {
    /// Writes the newest version's header for a payload of `payload_len` bytes.
    ///
    /// # Errors
    /// The payload is over the kind's limit ([`io::ErrorKind::InvalidInput`] around a [`FormatError`]), or
    /// the write fails.
    pub fn new(mut inner: W, kind: &Format, payload_len: u64) -> io::Result<Self> {
        let header = kind
            .write_header(payload_len)
            .map_err(|e| io::Error::new(io::ErrorKind::InvalidInput, e))?;
        inner.write_all(&header)?;
        let mut crc = crc32fast::Hasher::new();
        crc.update(&header);
        Ok(Self {
            inner,
            crc,
            declared: payload_len,
            written: 0,
            file: kind.name,
        })
    }

    /// Writes the CRC and hands back the writer.
    ///
    /// # Errors
    /// Fewer or more payload bytes were written than declared, or the write fails.
    pub fn finish(mut self) -> io::Result<W> {
        if self.written != self.declared {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!(
                    "{}: {} payload bytes written, {} declared",
                    self.file, self.written, self.declared
                ),
            ));
        }
        let crc = self.crc.clone().finalize();
        self.inner.write_all(&crc.to_le_bytes())?;
        self.inner.flush()?;
        Ok(self.inner)
    }
}

impl<W: Write> Write for FramedWriter<W> {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.crc.update(&buf[..n]);
        self.written += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }
}

/// Reading a framed file as a stream failed.
#[derive(Debug, Error)]
pub enum StreamError {
    /// The underlying read failed.
    #[error(transparent)]
    Io(#[from] io::Error),
    /// The file is foreign or damaged.
    #[error(transparent)]
    Format(#[from] FormatError),
}

/// Reads a framed file as a stream, for files too large to hold at once (the training cache): the header
/// is checked against the file's length at [`FramedReader::new`], the CRC at [`FramedReader::finish`].
#[derive(Debug)]
pub struct FramedReader<R: Read> {
    inner: R,
    crc: crc32fast::Hasher,
    kind: Format,
    version: u32,
    left: u64,
}

impl<R: Read> FramedReader<R> {
    /// Reads and checks the header of a file of `file_len` bytes.
    ///
    /// # Errors
    /// [`StreamError::Format`] for a foreign, truncated or future-version file; [`StreamError::Io`] if the
    /// read fails.
    pub fn new(mut inner: R, kind: &Format, file_len: u64) -> Result<Self, StreamError> {
        let mut head = [0u8; HEADER_LEN];
        let n = (file_len.min(HEADER_LEN as u64)) as usize;
        inner.read_exact(&mut head[..n])?;
        let header = kind.header(&head[..n], file_len)?;
        if header.start != HEADER_LEN as u64 {
            // Only the refiner's models predate the length field, and they are read whole.
            return Err(io::Error::new(
                io::ErrorKind::Unsupported,
                format!("{}: version {} cannot be streamed", kind.name, header.version),
            )
            .into());
        }
        let mut crc = crc32fast::Hasher::new();
        crc.update(&head);
        Ok(Self {
            inner,
            crc,
            kind: *kind,
            version: header.version,
            left: header.payload_len,
        })
    }

    /// The file's format version.
    pub fn version(&self) -> u32 {
        self.version
    }

    /// Payload bytes not yet read.
    pub fn left(&self) -> u64 {
        self.left
    }

    /// Fills `buf` from the payload.
    ///
    /// # Errors
    /// [`StreamError::Format`] if the payload has fewer bytes left; [`StreamError::Io`] if the read fails.
    pub fn read_exact(&mut self, buf: &mut [u8]) -> Result<(), StreamError> {
        if buf.len() as u64 > self.left {
            return Err(self
                .kind
                .error(Damage::OutOfRange {
                    field: "payload read",
                    value: buf.len() as u64,
                    min: 0,
                    max: self.left,
                })
                .into());
        }
        self.inner.read_exact(buf)?;
        self.crc.update(buf);
        self.left -= buf.len() as u64;
        Ok(())
    }

    /// Checks that the payload was read to its end and that the CRC matches.
    ///
    /// # Errors
    /// [`Damage::TrailingBytes`] if payload is left, [`Damage::Checksum`] if the file is damaged.
    pub fn finish(mut self) -> Result<(), StreamError> {
        if self.left != 0 {
            return Err(self.kind.error(Damage::TrailingBytes { count: self.left }).into());
        }
        let mut stored = [0u8; CRC_LEN];
        self.inner.read_exact(&mut stored)?;
        let stored = u32::from_le_bytes(stored);
        let computed = self.crc.finalize();
        if stored != computed {
            return Err(self.kind.error(Damage::Checksum { stored, computed }).into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    const KIND: Format = Format {
        name: "test file",
        magic: *b"HFTEST\0\0",
        oldest: 1,
        newest: 3,
        sized_from: 3,
        max_payload: 1 << 20,
    };

    fn damage(bytes: &[u8]) -> Damage {
        match decode(&KIND, bytes) {
            Err(e) => {
                assert_eq!(e.file, "test file");
                e.damage
            }
            Ok(_) => panic!("accepted"),
        }
    }

    fn reseal(mut b: Vec<u8>) -> Vec<u8> {
        b.truncate(b.len() - CRC_LEN);
        let c = crc32fast::hash(&b);
        b.extend_from_slice(&c.to_le_bytes());
        b
    }

    #[test]
    fn the_layout_is_pinned_and_round_trips() {
        let file = encode(&KIND, b"payload").unwrap();
        assert_eq!(&file[..8], b"HFTEST\0\0");
        assert_eq!(&file[8..12], &3u32.to_le_bytes());
        assert_eq!(&file[12..16], &7u32.to_le_bytes());
        assert_eq!(&file[16..23], b"payload");
        assert_eq!(&file[23..], &crc32fast::hash(&file[..23]).to_le_bytes());
        let mut f = decode(&KIND, &file).unwrap();
        assert_eq!(f.version, 3);
        assert_eq!(f.payload.offset(), 16);
        assert_eq!(f.payload.take(7).unwrap(), b"payload");
        f.payload.finish().unwrap();
    }

    #[test]
    fn each_damage_is_named() {
        let good = encode(&KIND, b"payload").unwrap();
        assert!(matches!(
            damage(&good[..5]),
            Damage::Truncated {
                offset: 0,
                needed: 8,
                len: 5
            }
        ));
        assert!(matches!(
            damage(&good[..good.len() - 3]),
            Damage::Truncated {
                offset: 24,
                needed: 3,
                len: 24
            }
        ));
        let mut magic = good.clone();
        magic[0] = b'X';
        assert!(matches!(damage(&magic), Damage::BadMagic { .. }));
        let mut future = good.clone();
        future[8] = 4;
        assert!(matches!(
            damage(&reseal(future)),
            Damage::UnsupportedVersion {
                found: 4,
                oldest: 1,
                newest: 3
            }
        ));
        let mut flipped = good.clone();
        flipped[17] ^= 1;
        assert!(matches!(damage(&flipped), Damage::Checksum { .. }));
        let mut long = good.clone();
        long.push(0);
        assert!(matches!(damage(&long), Damage::TrailingBytes { count: 1 }));
        let mut huge = good.clone();
        huge[12..16].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(damage(&huge), Damage::TooLarge { .. }));
        let text = decode(&KIND, &flipped).unwrap_err().to_string();
        assert!(text.starts_with("test file: checksum mismatch"), "{text}");
    }

    #[test]
    fn an_unsized_legacy_version_runs_to_the_crc() {
        let mut old = b"HFTEST\0\0".to_vec();
        old.extend_from_slice(&2u32.to_le_bytes());
        old.extend_from_slice(b"old payload");
        old.extend_from_slice(&[0; 4]);
        let old = reseal(old);
        let mut f = decode(&KIND, &old).unwrap();
        assert_eq!((f.version, f.payload.offset(), f.payload.left()), (2, 12, 11));
        assert_eq!(f.payload.take(11).unwrap(), b"old payload");
        assert!(matches!(damage(&old[..14]), Damage::Truncated { .. }));
    }

    #[test]
    fn payload_fields_are_bounded_and_located() {
        let mut p = Vec::new();
        p.extend_from_slice(&5u32.to_le_bytes());
        p.extend_from_slice(&f32::NAN.to_le_bytes());
        p.extend_from_slice(&2u16.to_le_bytes());
        p.extend_from_slice(&[0xff, 0xfe]);
        let file = encode(&KIND, &p).unwrap();
        let mut r = decode(&KIND, &file).unwrap().payload;
        let e = r.count("n", 1, 4).unwrap_err();
        assert_eq!(
            e.damage,
            Damage::OutOfRange {
                field: "n",
                value: 5,
                min: 1,
                max: 4
            }
        );
        assert!(matches!(
            r.f32("x", 3).unwrap_err().damage,
            Damage::NotFinite { field: "x", index: 3 }
        ));
        assert!(matches!(
            r.text("name", 8).unwrap_err().damage,
            Damage::Invalid { offset: 28, .. }
        ));
        assert!(matches!(
            r.u32().unwrap_err().damage,
            Damage::Truncated {
                offset: 28,
                needed: 4,
                ..
            }
        ));
        assert!(r.need(1).is_err());
    }

    #[test]
    fn streams_read_what_encode_writes_and_check_the_crc() {
        let payload: Vec<u8> = (0..1000u32).map(|i| (i * 7) as u8).collect();
        let file = encode(&KIND, &payload).unwrap();
        let mut r = FramedReader::new(&file[..], &KIND, file.len() as u64).unwrap();
        let mut back = vec![0u8; 1000];
        r.read_exact(&mut back[..400]).unwrap();
        r.read_exact(&mut back[400..]).unwrap();
        assert_eq!(back, payload);
        r.finish().unwrap();

        let mut bad = file.clone();
        bad[500] ^= 0x10;
        let mut r = FramedReader::new(&bad[..], &KIND, bad.len() as u64).unwrap();
        r.read_exact(&mut back).unwrap();
        assert!(matches!(
            r.finish(),
            Err(StreamError::Format(FormatError {
                damage: Damage::Checksum { .. },
                ..
            }))
        ));
        let cut = &file[..600];
        assert!(matches!(
            FramedReader::new(cut, &KIND, cut.len() as u64),
            Err(StreamError::Format(FormatError {
                damage: Damage::Truncated { .. },
                ..
            }))
        ));
        let mut short = FramedWriter::new(Vec::new(), &KIND, 10).unwrap();
        short.write_all(b"abc").unwrap();
        assert!(short.finish().is_err());
        assert!(encode(&KIND, &vec![0; (1 << 20) + 1]).is_err());
    }
}
