//! Video files through FFmpeg's own libraries (libavformat, libavcodec; the `ffmpeg-next` crate over the
//! system's FFmpeg, Debian's `libav*-dev`): MP4/MOV, WebM/Matroska and whatever else the installed FFmpeg
//! demuxes, with H.264 of every profile (B-frames, temporal direct, weighted prediction), HEVC, VP8, VP9 and
//! AV1 where the installed FFmpeg has a decoder. Decoding is FFmpeg's, so every frame is bit-exact with what
//! `ffmpeg -i CLIP` decodes (the tests compare them).
//!
//! Only the luma plane is used: the grey image the tracker needs, without a colour conversion. Limited-range
//! luma (16–235, what almost every encoder writes) is expanded to 0–255 as in [`crate::video`]; full-range
//! (`yuvj*`, JPEG range) is taken as it is; 10- and 12-bit luma is rounded to 8 bits first.
//!
//! Bounds: the file must be a regular file opened through the `file` protocol only (no playlist or concat
//! demuxer can make it open other files or URLs); the frame size is checked against [`MAX_SIDE`] and
//! [`MAX_PIXELS`] before any frame is decoded, and the decoder itself refuses larger frames later in the stream
//! (`max_pixels`). A packet the decoder refuses is an error naming the file and the packet, and so is a file
//! that ends well before the length it declares (cut short: FFmpeg itself only logs it); frames come out in
//! display order with increasing times.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::Once;

use crate::error::{Context as _, err, fail};
use crate::{FrameSource, SourceError};
use ff::format::Pixel;
use ffmpeg_next as ff;
use holoface_models::camera::Intrinsics;
use holoface_models::image::GrayImage;
use holoface_runtime::OwnedFrame;

/// Largest frame side accepted (the same bound as the y4m reader's).
pub const MAX_SIDE: usize = 16_384;
/// Largest frame accepted, in pixels (8K x 8K): above it a video is refused before decoding.
pub const MAX_PIXELS: usize = 8192 * 8192;
/// Decoder threads (frame threading is bit-exact; the tools' video is read ahead of the tracker).
const THREADS: usize = 2;

/// FFmpeg's global set-up: the error strings and a quiet log (errors reach the user through our messages).
fn init() {
    static INIT: Once = Once::new();
    INIT.call_once(|| {
        // `init` fails only on FFmpeg older than 4.0, which the build's version probe already refuses.
        let _ = ff::init();
        ff::util::log::set_level(ff::util::log::Level::Quiet);
    });
}

/// The pipe that reads any video FFmpeg's command line reads, for messages.
fn pipe_hint(path: &Path) -> String {
    format!(
        "`ffmpeg -i {} -f yuv4mpegpipe - | holoface track --source -`",
        path.display()
    )
}

/// How a frame's luma plane is laid out.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Luma {
    /// 8 bits per sample; `full` when already 0–255.
    Eight { full: bool },
    /// `bits` (9–16) per sample in little-endian u16; `full` as above.
    Wide { bits: u32, full: bool },
}

/// The luma layout of a pixel format, or `None` when plane 0 is not a luma plane (RGB, palettes, ...).
fn luma_of(format: Pixel, full_range: bool) -> Option<Luma> {
    use Pixel as P;
    match format {
        P::YUVJ420P | P::YUVJ422P | P::YUVJ444P | P::YUVJ440P | P::YUVJ411P => {
            Some(Luma::Eight { full: true })
        }
        P::YUV420P
        | P::YUV422P
        | P::YUV444P
        | P::YUV440P
        | P::YUV411P
        | P::YUV410P
        | P::NV12
        | P::NV21
        | P::NV16
        | P::YUVA420P
        | P::YUVA422P
        | P::YUVA444P => Some(Luma::Eight { full: full_range }),
        P::GRAY8 => Some(Luma::Eight { full: true }),
        P::YUV420P10LE | P::YUV422P10LE | P::YUV444P10LE | P::P010LE => Some(Luma::Wide {
            bits: 10,
            full: full_range,
        }),
        P::YUV420P12LE | P::YUV422P12LE | P::YUV444P12LE => Some(Luma::Wide {
            bits: 12,
            full: full_range,
        }),
        _ => None,
    }
}

/// A video file's best video stream as frames, decoded by FFmpeg.
pub struct FfmpegSource {
    path: PathBuf,
    input: ff::format::context::Input,
    decoder: ff::decoder::Video,
    stream: usize,
    /// The stream's time base: seconds per tick as a fraction (numerator, denominator).
    time_base: (i128, i128),
    /// Frame spacing (µs) when timestamps are missing or do not increase: from the stream's average rate.
    frame_us: u64,
    codec: &'static str,
    frame: ff::frame::Video,
    packet: ff::Packet,
    packets_read: u64,
    ready: VecDeque<(Option<i64>, GrayImage)>,
    /// The end of the file was reached and the decoder told so.
    drained: bool,
    /// The decoder has given its last frame.
    finished: bool,
    first_ts: Option<i64>,
    last_us: Option<u64>,
    /// The video's length the container declares (µs), when it declares one: a file that ends well before it
    /// was cut short (an interrupted download or copy).
    declared_us: Option<u64>,
    index: usize,
    intrinsics: Option<Intrinsics>,
    lut: [u8; 256],
}

impl std::fmt::Debug for FfmpegSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FfmpegSource")
            .field("path", &self.path)
            .field("codec", &self.codec)
            .field("index", &self.index)
            .finish_non_exhaustive()
    }
}

impl FfmpegSource {
    /// Opens `path` and its best video stream; `intrinsics` default to a 60° horizontal field of view.
    pub fn open(path: &Path, intrinsics: Option<Intrinsics>) -> Result<Self, SourceError> {
        init();
        let shown = path.display();
        // The file itself, so that a missing file or a device is said as such, not as FFmpeg's "I/O error".
        holoface_files::regular_file(path, "video")?;
        let name = path.to_str().ok_or_else(|| {
            err!(
                Usage,
                "{shown}: the video's path is not UTF-8 (FFmpeg takes UTF-8 paths); rename it"
            )
        })?;
        // `file:` + the path: a name with a colon is not taken for another protocol.
        let url = if path.is_absolute() {
            format!("file:{name}")
        } else {
            format!("file:./{name}")
        };
        let mut options = ff::Dictionary::new();
        options.set("protocol_whitelist", "file");
        let input = ff::format::input_with_dictionary(&url, options)
            .map_err(|e| err!(Malformed, "{shown} is not a readable video ({e})"))?;
        let stream = input
            .streams()
            .best(ff::media::Type::Video)
            .ok_or_else(|| err!(Empty, "{shown} has no video stream"))?;
        // The video stream's own length, else the container's (AV_TIME_BASE = µs); absent = not declared.
        let declared_us = {
            let own = stream.duration();
            let tb = stream.time_base();
            if own > 0 && tb.denominator() > 0 {
                u64::try_from(
                    i128::from(own) * i128::from(tb.numerator()) * 1_000_000 / i128::from(tb.denominator()),
                )
                .ok()
            } else {
                u64::try_from(input.duration()).ok().filter(|&d| d > 0)
            }
        };
        let (index, time_base, rate, params) = (
            stream.index(),
            stream.time_base(),
            stream.avg_frame_rate(),
            stream.parameters(),
        );
        let id = params.id();
        let codec = id.name();
        let found = ff::decoder::find(id).ok_or_else(|| {
            err!(
                Unsupported,
                "{shown}: its video is {codec}, which this build's FFmpeg cannot decode; convert it with ffmpeg \
                 (for example {})",
                pipe_hint(path)
            )
        })?;
        let mut context = ff::codec::context::Context::from_parameters(params)
            .map_err(|e| err!(Codec, "{shown}: reading the {codec} stream's parameters: {e}"))?;
        let mut threading = ff::codec::threading::Config::default();
        threading.kind = ff::codec::threading::Type::Frame;
        threading.count = THREADS;
        context.set_threading(threading);
        let mut decoder = context.decoder();
        decoder.set_packet_time_base(time_base);
        let mut options = ff::Dictionary::new();
        options.set("max_pixels", &MAX_PIXELS.to_string());
        let decoder = decoder
            .open_as_with(found, options)
            .and_then(|d| d.video())
            .map_err(|e| err!(Codec, "{shown}: opening FFmpeg's {codec} decoder: {e}"))?;
        // The size the container declares, before any frame is decoded (every frame is checked again).
        check_size(path, decoder.width() as usize, decoder.height() as usize)?;
        let frame_us = if rate.numerator() > 0 && rate.denominator() > 0 {
            (1e6 * f64::from(rate.denominator()) / f64::from(rate.numerator()))
                .round()
                .max(1.0) as u64
        } else {
            33_333
        };
        Ok(Self {
            path: path.to_path_buf(),
            input,
            decoder,
            stream: index,
            time_base: (
                i128::from(time_base.numerator()),
                i128::from(time_base.denominator()),
            ),
            frame_us,
            codec,
            frame: ff::frame::Video::empty(),
            packet: ff::Packet::empty(),
            packets_read: 0,
            ready: VecDeque::new(),
            drained: false,
            finished: false,
            first_ts: None,
            last_us: None,
            declared_us,
            index: 0,
            intrinsics,
            lut: crate::full_range_lut(),
        })
    }

    /// The name FFmpeg gives the video's codec (`h264`, `hevc`, `vp9`, ...).
    pub fn codec(&self) -> &'static str {
        self.codec
    }

    /// Takes every frame the decoder has ready.
    fn receive(&mut self) -> Result<(), SourceError> {
        loop {
            match self.decoder.receive_frame(&mut self.frame) {
                Ok(()) => {
                    let image = self.grey().with_context(|| {
                        format!(
                            "frame {} of {}",
                            self.index + self.ready.len(),
                            self.path.display()
                        )
                    })?;
                    self.ready.push_back((self.frame.timestamp(), image));
                }
                Err(ff::Error::Other { errno }) if errno == ff::error::EAGAIN => return Ok(()),
                Err(ff::Error::Eof) => {
                    self.finished = true;
                    return Ok(());
                }
                Err(e) => fail!(
                    Malformed,
                    "decoding frame {} of {} ({}): {e}",
                    self.index + self.ready.len(),
                    self.path.display(),
                    self.codec
                ),
            }
        }
    }

    /// Feeds packets until a frame is ready or the stream ends.
    fn fill(&mut self) -> Result<(), SourceError> {
        while self.ready.is_empty() && !self.finished {
            if self.drained {
                self.receive()?;
                if self.ready.is_empty() {
                    // The decoder is empty after the end of input but did not say so: it is done.
                    self.finished = true;
                }
                continue;
            }
            match self.packet.read(&mut self.input) {
                Ok(()) => {}
                Err(ff::Error::Eof) => {
                    self.drained = true;
                    self.decoder.send_eof().map_err(|e| {
                        err!(
                            Malformed,
                            "ending the decode of {}: {e}; the file is damaged or cut short",
                            self.path.display()
                        )
                    })?;
                    continue;
                }
                Err(e) => fail!(
                    Malformed,
                    "{}: reading packet {} failed ({e}); the file is damaged or cut short",
                    self.path.display(),
                    self.packets_read
                ),
            }
            self.packets_read += 1;
            if self.packet.stream() != self.stream {
                continue;
            }
            self.decoder.send_packet(&self.packet).map_err(|e| {
                err!(
                    Malformed,
                    "{}: the {} decoder refused packet {} ({e}); the file is damaged",
                    self.path.display(),
                    self.codec,
                    self.packets_read - 1
                )
            })?;
            self.receive()?;
        }
        Ok(())
    }

    /// The decoded frame's luma as a full-range grey image.
    fn grey(&self) -> Result<GrayImage, SourceError> {
        let f = &self.frame;
        let (w, h) = (f.width() as usize, f.height() as usize);
        check_size(&self.path, w, h)?;
        let full = f.color_range() == ff::util::color::Range::JPEG;
        let luma = luma_of(f.format(), full).ok_or_else(|| {
            err!(
                Unsupported,
                "pixel format {:?} has no luma plane holoface reads; convert it with {}",
                f.format(),
                pipe_hint(&self.path)
            )
        })?;
        let (data, stride) = (f.data(0), f.stride(0));
        let mut px = Vec::with_capacity(w * h);
        for y in 0..h {
            let row = &data[y * stride..];
            match luma {
                Luma::Eight { full } => {
                    let row = &row[..w];
                    if full {
                        px.extend_from_slice(row);
                    } else {
                        px.extend(row.iter().map(|&v| self.lut[usize::from(v)]));
                    }
                }
                Luma::Wide { bits, full } => {
                    let shift = bits - 8;
                    let half = 1u32 << (shift - 1);
                    px.extend(row[..2 * w].chunks_exact(2).map(|b| {
                        let v = u32::from(u16::from_le_bytes([b[0], b[1]]));
                        let v8 = ((v + half) >> shift).min(255) as u8;
                        if full { v8 } else { self.lut[usize::from(v8)] }
                    }));
                }
            }
        }
        GrayImage::from_vec(px, w, h).context(format!("a {w}x{h} frame"))
    }

    /// At the end: refuses a video that stops well before the length its container declares (more than half a
    /// second and three frames short), which is what a cut file looks like to the demuxer (it just ends).
    fn check_complete(&self) -> Result<(), SourceError> {
        let (Some(declared), Some(last)) = (self.declared_us, self.last_us) else {
            return Ok(());
        };
        let got = last.saturating_add(self.frame_us);
        let slack = self.frame_us.saturating_mul(3).max(500_000);
        if got.saturating_add(slack) < declared {
            fail!(
                Malformed,
                "{}: the video ends at {:.2} s ({} frames) but its container declares {:.2} s: the file is cut short \
                 (an interrupted download or copy?)",
                self.path.display(),
                got as f64 / 1e6,
                self.index,
                declared as f64 / 1e6
            );
        }
        Ok(())
    }

    /// A frame's time in µs from the first frame: the stream's own time when it increases, else the previous
    /// time plus one frame.
    fn time_of(&mut self, ts: Option<i64>) -> u64 {
        let (num, den) = self.time_base;
        let from_stream = ts.and_then(|t| {
            let first = *self.first_ts.get_or_insert(t);
            // Whole microseconds, rounded down (as the OpenH264 reader does).
            let us = (i128::from(t) - i128::from(first)) * num * 1_000_000;
            (den > 0)
                .then(|| us.div_euclid(den))
                .and_then(|us| u64::try_from(us).ok())
        });
        let t = match (from_stream, self.last_us) {
            (Some(t), Some(last)) if t > last => t,
            (Some(t), None) => t,
            (_, Some(last)) => last.saturating_add(self.frame_us),
            (None, None) => 0,
        };
        self.last_us = Some(t);
        t
    }

    fn read_next(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.fill()?;
        let Some((ts, image)) = self.ready.pop_front() else {
            self.check_complete()?;
            return Ok(None);
        };
        let timestamp_us = self.time_of(ts);
        let index = self.index;
        self.index += 1;
        Ok(Some(crate::video_frame(
            index,
            timestamp_us,
            image,
            self.intrinsics,
        )))
    }
}

impl FrameSource for FfmpegSource {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.read_next()
    }
}

/// Refuses a frame size outside [`MAX_SIDE`] and [`MAX_PIXELS`].
fn check_size(path: &Path, w: usize, h: usize) -> Result<(), SourceError> {
    if w == 0 || h == 0 || w > MAX_SIDE || h > MAX_SIDE || w * h > MAX_PIXELS {
        fail!(
            Unsupported,
            "{}: frame size {w}x{h} is outside what holoface reads (each side 1..={MAX_SIDE}, at most {MAX_PIXELS} \
             pixels); scale it down with ffmpeg's `-vf scale=...`",
            path.display()
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn luma_layouts_cover_the_common_formats_and_refuse_rgb() {
        assert_eq!(luma_of(Pixel::YUV420P, false), Some(Luma::Eight { full: false }));
        assert_eq!(luma_of(Pixel::YUVJ420P, false), Some(Luma::Eight { full: true }));
        assert_eq!(
            luma_of(Pixel::YUV420P10LE, false),
            Some(Luma::Wide {
                bits: 10,
                full: false
            })
        );
        assert_eq!(luma_of(Pixel::RGB24, false), None);
    }

    #[test]
    fn frame_sizes_outside_the_bounds_are_refused_naming_the_file() {
        let p = Path::new("big.mkv");
        assert!(check_size(p, 1920, 1080).is_ok());
        assert!(check_size(p, MAX_SIDE, 16).is_ok());
        for (w, h) in [
            (0, 10),
            (10, 0),
            (MAX_SIDE + 1, 2),
            (2, MAX_SIDE + 1),
            (MAX_SIDE, MAX_SIDE),
        ] {
            let e = check_size(p, w, h).unwrap_err().to_string();
            assert!(e.contains("big.mkv") && e.contains(&format!("{w}x{h}")), "{e}");
        }
    }
}
