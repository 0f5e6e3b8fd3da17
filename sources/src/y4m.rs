//! YUV4MPEG2 (`.y4m`): the uncompressed stream format ffmpeg writes with `-f yuv4mpegpipe`, so a live camera
//! can be piped into `holoface track --source -`. [`Y4mSource`] reads the luma plane of every frame (8-bit
//! `mono`, `420` (jpeg, paldv, mpeg2 siting), `411`, `422`, `444` and `444alpha`; the chroma planes are skipped); [`Y4mWriter`] writes gray
//! (`Cmono`) streams, for tests and tools. Frames are timed by the header's frame rate; the camera is taken
//! as fixed (identity pose) unless a pose sidecar is given.
//!
//! A stream that ends inside a frame, a header that is not YUV4MPEG2 or a frame without its `FRAME` marker is
//! an error naming the frame, never a silently short or shifted image.

use std::io::{BufRead, Read, Write};

use crate::error::{Context as _, ensure, fail};
use holoface_models::camera::Intrinsics;
use holoface_models::image::GrayImage;
use holoface_models::math3::Pose;

use crate::{FrameSource, SourceError};
use holoface_runtime::{OwnedFrame, default_intrinsics};

/// The stream's first bytes.
pub const MAGIC: &[u8] = b"YUV4MPEG2";
/// Longest stream or frame header accepted, bytes (real ones are well under 100).
const MAX_HEADER: usize = 4096;
/// Largest frame side accepted.
const MAX_SIDE: usize = 16_384;

/// The stream header's fields that matter here.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Y4mHeader {
    /// Frame width, pixels.
    pub width: usize,
    /// Frame height, pixels.
    pub height: usize,
    /// Frame rate as a fraction (numerator, denominator); `None` when the header has no `F` field.
    pub fps: Option<(u64, u64)>,
    /// Bytes of chroma (and alpha) after each luma plane.
    pub extra_plane_bytes: usize,
}

/// Reads one `\n`-terminated line of at most [`MAX_HEADER`] bytes; `Ok(None)` at a clean end of the stream.
fn read_line(r: &mut impl BufRead, what: &str) -> Result<Option<Vec<u8>>, SourceError> {
    let mut line = Vec::new();
    let n = Read::take(&mut *r, MAX_HEADER as u64 + 1)
        .read_until(b'\n', &mut line)
        .with_context(|| format!("reading the {what}"))?;
    if n == 0 {
        return Ok(None);
    }
    if line.last() != Some(&b'\n') {
        if line.len() > MAX_HEADER {
            fail!(Malformed, "{what} longer than {MAX_HEADER} bytes");
        }
        fail!(Malformed, "{what} truncated (the stream ends before its newline)");
    }
    line.pop();
    Ok(Some(line))
}

impl Y4mHeader {
    /// Parses the stream header line (without its newline).
    pub fn parse(line: &[u8]) -> Result<Self, SourceError> {
        let text = std::str::from_utf8(line).context("the YUV4MPEG2 header is not ASCII")?;
        let mut fields = text.split(' ').filter(|f| !f.is_empty());
        ensure!(
            fields.next().map(str::as_bytes) == Some(MAGIC),
            Malformed,
            "not a YUV4MPEG2 stream (the header starts {:?}, expected \"YUV4MPEG2 \")",
            text.chars().take(16).collect::<String>()
        );
        let (mut width, mut height, mut fps, mut colour) = (None, None, None, "420jpeg");
        for f in fields {
            let (tag, value) = f.split_at(1);
            match tag {
                "W" => {
                    width = Some(
                        value
                            .parse::<usize>()
                            .with_context(|| format!("width {value:?}"))?,
                    )
                }
                "H" => {
                    height = Some(
                        value
                            .parse::<usize>()
                            .with_context(|| format!("height {value:?}"))?,
                    )
                }
                "F" => {
                    let (n, d) = value
                        .split_once(':')
                        .with_context(|| format!("frame rate {value:?} (expected N:D)"))?;
                    let (n, d): (u64, u64) = (
                        n.parse().with_context(|| format!("frame rate {value:?}"))?,
                        d.parse().with_context(|| format!("frame rate {value:?}"))?,
                    );
                    ensure!(n > 0 && d > 0, Malformed, "frame rate {value} must be positive");
                    fps = Some((n, d));
                }
                "C" => colour = value,
                // Interlacing, aspect ratio and extensions do not change the planes' sizes.
                _ => {}
            }
        }
        let width = width.context("the YUV4MPEG2 header has no width (W)")?;
        let height = height.context("the YUV4MPEG2 header has no height (H)")?;
        ensure!(
            (1..=MAX_SIDE).contains(&width) && (1..=MAX_SIDE).contains(&height),
            Malformed,
            "frame size {width}x{height}: each side must be within 1..={MAX_SIDE}"
        );
        crate::images::check_image_size(width as u64, height as u64).context("the YUV4MPEG2 frame size")?;
        let (cw, ch) = (width.div_ceil(2), height.div_ceil(2));
        let extra_plane_bytes = match colour {
            "mono" => 0,
            "420" | "420jpeg" | "420paldv" | "420mpeg2" => 2 * cw * ch,
            "411" => 2 * width.div_ceil(4) * height,
            "422" => 2 * cw * height,
            "444" => 2 * width * height,
            "444alpha" => 3 * width * height,
            c => fail!(
                Unsupported,
                "colour space C{c} is not supported (8-bit mono, 420, 411, 422 or 444; ffmpeg: -pix_fmt gray)"
            ),
        };
        Ok(Self {
            width,
            height,
            fps,
            extra_plane_bytes,
        })
    }
}

/// Reads exactly `buf.len()` bytes; returns how many arrived when the stream ends first.
fn read_full(r: &mut impl BufRead, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

/// Frames of a YUV4MPEG2 stream (a file or a pipe).
pub struct Y4mSource<R> {
    reader: R,
    name: String,
    header: Y4mHeader,
    frame_interval_us: (u64, u64),
    intrinsics: Intrinsics,
    index: usize,
    skip: Vec<u8>,
    done: bool,
}

impl<R> std::fmt::Debug for Y4mSource<R> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Y4mSource")
            .field("name", &self.name)
            .field("header", &self.header)
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl<R: BufRead> Y4mSource<R> {
    /// Reads the stream header. `name` is used in errors ("stdin" or the file's path); `default_fps` times
    /// the frames when the header has no frame rate; `intrinsics` default to a 60° horizontal field of view.
    pub fn new(
        mut reader: R,
        name: &str,
        default_fps: f64,
        intrinsics: Option<Intrinsics>,
    ) -> Result<Self, SourceError> {
        let line = read_line(&mut reader, "YUV4MPEG2 header")
            .and_then(|l| l.context("the stream is empty (no YUV4MPEG2 header)"))
            .and_then(|l| Y4mHeader::parse(&l))
            .with_context(|| format!("{name}: YUV4MPEG2 stream header"))?;
        ensure!(
            default_fps.is_finite() && default_fps > 0.0,
            Usage,
            "frame rate {default_fps} must be positive"
        );
        // Microseconds per frame as a fraction, so long streams do not drift.
        let frame_interval_us = match line.fps {
            Some((n, d)) => (d * 1_000_000, n),
            None => ((1e6 / default_fps * 1000.0).round() as u64, 1000),
        };
        Ok(Self {
            reader,
            name: name.to_owned(),
            intrinsics: intrinsics.unwrap_or_else(|| default_intrinsics(line.width, line.height)),
            header: line,
            frame_interval_us,
            index: 0,
            skip: Vec::new(),
            done: false,
        })
    }

    /// The stream header.
    pub fn header(&self) -> Y4mHeader {
        self.header
    }

    fn read_frame(&mut self) -> Result<Option<GrayImage>, SourceError> {
        let Some(marker) = read_line(&mut self.reader, "frame header")? else {
            return Ok(None);
        };
        ensure!(
            marker.starts_with(b"FRAME") && matches!(marker.get(5), None | Some(b' ')),
            Malformed,
            "expected a FRAME marker, got {:?}",
            String::from_utf8_lossy(&marker[..marker.len().min(16)])
        );
        let (w, h) = (self.header.width, self.header.height);
        let mut luma = vec![0u8; w * h];
        let got = read_full(&mut self.reader, &mut luma)?;
        ensure!(
            got == luma.len(),
            Malformed,
            "truncated: the stream ends after {got} of the {} luma bytes",
            luma.len()
        );
        self.skip.resize(self.header.extra_plane_bytes, 0);
        let got = read_full(&mut self.reader, &mut self.skip)?;
        ensure!(
            got == self.skip.len(),
            Malformed,
            "truncated: the stream ends after {got} of the {} chroma bytes",
            self.skip.len()
        );
        Ok(Some(GrayImage::from_vec(luma, w, h)?))
    }
}

impl<R: BufRead> Y4mSource<R> {
    fn read_next(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        if self.done {
            return Ok(None);
        }
        let image = match self.read_frame() {
            Ok(Some(image)) => image,
            Ok(None) => {
                self.done = true;
                return Ok(None);
            }
            Err(e) => {
                self.done = true;
                return Err(e.context(format!("{}: frame {}", self.name, self.index)));
            }
        };
        let (num, den) = self.frame_interval_us;
        let timestamp_us = (self.index as u128 * u128::from(num) / u128::from(den)) as u64;
        let mut frame = OwnedFrame::new(timestamp_us, image, self.intrinsics, Pose::IDENTITY);
        frame.index = self.index;
        self.index += 1;
        Ok(Some(frame))
    }
}

impl<R: BufRead> FrameSource for Y4mSource<R> {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.read_next()
    }
}

/// Writes gray frames as a YUV4MPEG2 stream (`Cmono`).
#[derive(Debug)]
pub struct Y4mWriter<W: Write> {
    out: W,
    width: usize,
    height: usize,
}

impl<W: Write> Y4mWriter<W> {
    /// Writes the stream header: `width`x`height` at `fps_num / fps_den` frames per second.
    pub fn new(
        mut out: W,
        width: usize,
        height: usize,
        fps_num: u32,
        fps_den: u32,
    ) -> Result<Self, SourceError> {
        ensure!(
            (1..=MAX_SIDE).contains(&width) && (1..=MAX_SIDE).contains(&height),
            Usage,
            "frame size {width}x{height}"
        );
        ensure!(
            fps_num > 0 && fps_den > 0,
            Usage,
            "frame rate {fps_num}:{fps_den}"
        );
        writeln!(
            out,
            "YUV4MPEG2 W{width} H{height} F{fps_num}:{fps_den} Ip A1:1 Cmono"
        )?;
        Ok(Self { out, width, height })
    }

    /// Appends one frame; it must have the stream's size.
    pub fn push(&mut self, image: &GrayImage) -> Result<(), SourceError> {
        ensure!(
            (image.width(), image.height()) == (self.width, self.height),
            Usage,
            "frame {}x{} in a {}x{} stream",
            image.width(),
            image.height(),
            self.width,
            self.height
        );
        self.out.write_all(b"FRAME\n")?;
        let v = image.view();
        for y in 0..self.height {
            self.out.write_all(v.row(y).context("row out of range")?)?;
        }
        Ok(())
    }

    /// Flushes and returns the writer.
    pub fn finish(mut self) -> Result<W, SourceError> {
        self.out.flush()?;
        Ok(self.out)
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use std::io::Cursor;

    use super::*;

    fn image(w: usize, h: usize, seed: u8) -> GrayImage {
        let data = (0..w * h)
            .map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed))
            .collect();
        GrayImage::from_vec(data, w, h).unwrap()
    }

    fn stream(frames: &[GrayImage]) -> Vec<u8> {
        let (w, h) = (frames[0].width(), frames[0].height());
        let mut wr = Y4mWriter::new(Vec::new(), w, h, 30, 1).unwrap();
        for f in frames {
            wr.push(f).unwrap();
        }
        wr.finish().unwrap()
    }

    fn read_all(bytes: Vec<u8>) -> Result<Vec<OwnedFrame>, SourceError> {
        let mut src = Y4mSource::new(Cursor::new(bytes), "test.y4m", 30.0, None)?;
        let mut out = Vec::new();
        while let Some(f) = src.next_frame()? {
            out.push(f);
        }
        Ok(out)
    }

    #[test]
    fn written_frames_read_back_identically_with_their_times() {
        let frames: Vec<_> = (0..4).map(|k| image(7, 5, k)).collect();
        let got = read_all(stream(&frames)).unwrap();
        assert_eq!(got.len(), 4);
        for (k, (g, want)) in got.iter().zip(&frames).enumerate() {
            assert_eq!(g.index, k);
            assert_eq!(g.image.view().data(), want.view().data());
            assert_eq!(g.timestamp_us, [0, 33_333, 66_666, 100_000][k]);
            assert_eq!(g.world_from_camera, Pose::IDENTITY);
        }
    }

    #[test]
    fn colour_streams_give_their_luma_plane() {
        // 5x3 4:2:0: chroma planes are 3x2 each.
        let luma = image(5, 3, 9);
        let mut bytes = b"YUV4MPEG2 W5 H3 F25:1 Ip A0:0 C420jpeg XYSCSS=420JPEG\n".to_vec();
        for _ in 0..2 {
            bytes.extend_from_slice(b"FRAME\n");
            bytes.extend_from_slice(luma.view().data());
            bytes.extend_from_slice(&[128; 12]);
        }
        let got = read_all(bytes).unwrap();
        assert_eq!(got.len(), 2);
        assert_eq!(got[1].image.view().data(), luma.view().data());
        assert_eq!(got[1].timestamp_us, 40_000);
    }

    #[test]
    fn a_truncated_stream_is_an_error_naming_the_frame() {
        let frames: Vec<_> = (0..3).map(|k| image(8, 8, k)).collect();
        let mut bytes = stream(&frames);
        bytes.truncate(bytes.len() - 10);
        let mut src = Y4mSource::new(Cursor::new(bytes), "cam.y4m", 30.0, None).unwrap();
        assert!(src.next_frame().unwrap().is_some());
        assert!(src.next_frame().unwrap().is_some());
        let err = format!("{:#}", src.next_frame().unwrap_err());
        assert!(
            err.contains("cam.y4m: frame 2") && err.contains("54 of the 64 luma bytes"),
            "{err}"
        );
        assert!(src.next_frame().unwrap().is_none(), "no frames after the error");
        // Cut inside the FRAME marker.
        let mut bytes = stream(&frames[..1]);
        bytes.extend_from_slice(b"FRA");
        let err = format!("{:#}", read_all(bytes).unwrap_err());
        assert!(err.contains("frame 1") && err.contains("truncated"), "{err}");
    }

    #[test]
    fn bad_headers_and_markers_are_errors() {
        let cases: [(&[u8], &str); 8] = [
            (b"", "empty"),
            (b"P5 640 480 255\n", "not a YUV4MPEG2 stream"),
            (b"YUV4MPEG2 H4\n", "no width"),
            (b"YUV4MPEG2 W4 H0\n", "within 1..="),
            (b"YUV4MPEG2 W4 H4 Cmono16\n", "not supported"),
            (b"YUV4MPEG2 W4 H4 C420p10\n", "not supported"),
            (b"YUV4MPEG2 W4 H4 F30:0\n", "positive"),
            (b"YUV4MPEG2 W4 H4", "truncated"),
        ];
        for (bytes, words) in cases {
            let err = format!("{:#}", read_all(bytes.to_vec()).unwrap_err());
            assert!(err.contains(words), "{bytes:?}: {err}");
        }
        let mut bytes = b"YUV4MPEG2 W2 H2 Cmono\nFRAME\n\x01\x02\x03\x04".to_vec();
        bytes.extend_from_slice(b"FRAMES\n\x01\x02\x03\x04");
        let err = format!("{:#}", read_all(bytes).unwrap_err());
        assert!(
            err.contains("frame 1") && err.contains("expected a FRAME marker"),
            "{err}"
        );
        let long = [b"YUV4MPEG2 W2 H2 X".as_slice(), &[b'a'; 5000]].concat();
        let err = format!("{:#}", read_all(long).unwrap_err());
        assert!(err.contains("longer than"), "{err}");
    }

    #[test]
    fn the_writer_refuses_a_frame_of_another_size() {
        let mut wr = Y4mWriter::new(Vec::new(), 4, 4, 30, 1).unwrap();
        assert!(wr.push(&image(4, 5, 0)).is_err());
    }
}
