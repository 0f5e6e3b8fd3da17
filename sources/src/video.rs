//! MP4/H.264 video: a [`FrameSource`] that demuxes with the `mp4` crate and decodes with OpenH264 (built
//! from its bundled source), and a writer for grey sequences (used to export synthetic headset sequences).
//!
//! Only the luma plane is used: it is the grey image the tracker needs, without a colour conversion. Luma
//! is stored in "limited range" (16–235) by almost every encoder; it is expanded to 0–255 so that video
//! frames have the contrast the aligners were trained on (JPEG/PNG grey levels).
//!
//! OpenH264 decodes H.264 of the constrained-baseline, main and high profiles, B-frames included: pictures
//! are fed in decode order and come out in display order from its reorder buffer, which is emptied only at
//! the end of the track (the `openh264` crate's default flushes a picture after every packet that returned
//! none, which breaks the reorder buffer of a stream with B-frames: "Native:16384", openh264-rs issue 50).
//! Presentation times are handed out smallest first, matching the display order. Other codecs (HEVC, VP8/VP9,
//! AV1) are refused with the codec's name and the ffmpeg pipe that reads them (`-f yuv4mpegpipe`).
//!
//! The `mp4` crate can panic or allocate a sample's claimed size on a malformed file. The source checks
//! every sample size against the file before reading, and parses inside `catch_unwind` so that a corrupt
//! file is an error, never a crash of the tracker.

use std::collections::VecDeque;
use std::fs::File;
use std::io::BufReader;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};

use crate::error::{Context as _, err, fail};
use holoface_models::camera::Intrinsics;
use holoface_models::image::GrayImage;

use crate::output::Output;
use crate::{FrameSource, SourceError};
use holoface_runtime::OwnedFrame;

/// Largest sample (one encoded frame) the source accepts; a larger claim is a corrupt file.
const MAX_SAMPLE_BYTES: u32 = 64 << 20;

/// Runs a call into the `mp4` crate, turning its errors and panics into one error type.
fn mp4_call<T>(what: &str, f: impl FnOnce() -> mp4::Result<T>) -> Result<T, SourceError> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(err!(Malformed, "{what}: {e}")),
        Err(_) => Err(err!(Malformed, "{what}: malformed MP4 structure")),
    }
}

/// An MP4 file's first H.264 track as frames.
pub struct Mp4Source {
    path: PathBuf,
    reader: mp4::Mp4Reader<BufReader<File>>,
    track_id: u32,
    timescale: u64,
    sample_count: u32,
    next_sample: u32,
    length_size: usize,
    parameter_sets: Vec<u8>,
    decoder: openh264::decoder::Decoder,
    annexb: Vec<u8>,
    /// Presentation times (µs) of samples fed to the decoder whose picture has not come out yet; pictures
    /// come out in display order, so each takes the smallest.
    pending_times: std::collections::BinaryHeap<std::cmp::Reverse<u64>>,
    /// Pictures decoded but not yet returned.
    ready: VecDeque<GrayImage>,
    flushed: bool,
    index: usize,
    intrinsics: Option<Intrinsics>,
    lut: [u8; 256],
}

impl std::fmt::Debug for Mp4Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mp4Source")
            .field("path", &self.path)
            .field("track_id", &self.track_id)
            .field("sample_count", &self.sample_count)
            .field("next_sample", &self.next_sample)
            .finish_non_exhaustive()
    }
}

/// What codec a track's sample description names, in words.
fn codec_name(track: &mp4::Mp4Track) -> &'static str {
    let stsd = &track.trak.mdia.minf.stbl.stsd;
    if stsd.avc1.is_some() {
        "H.264"
    } else if stsd.hev1.is_some() {
        "HEVC (H.265)"
    } else if stsd.vp09.is_some() {
        "VP9"
    } else if stsd.mp4a.is_some() {
        "AAC audio"
    } else if stsd.tx3g.is_some() {
        "timed text"
    } else {
        "an unsupported codec"
    }
}

impl Mp4Source {
    /// Opens `path` and finds its H.264 track; `intrinsics` default to a 60° horizontal field of view.
    pub fn open(path: &Path, intrinsics: Option<Intrinsics>) -> Result<Self, SourceError> {
        let file = File::open(path).with_context(|| format!("opening video {}", path.display()))?;
        let size = file
            .metadata()
            .with_context(|| format!("reading the size of {}", path.display()))?
            .len();
        let what = format!("{} is not a readable MP4 file", path.display());
        let reader = mp4_call(&what, || mp4::Mp4Reader::read_header(BufReader::new(file), size))?;
        let (track_id, track) = reader
            .tracks()
            .iter()
            .filter(|(_, t)| matches!(t.media_type(), Ok(mp4::MediaType::H264)))
            .min_by_key(|(id, _)| **id)
            .ok_or_else(|| {
                let found: Vec<&str> = reader.tracks().values().map(codec_name).collect();
                err!(
                    Unsupported,
                    "{} has no H.264 video track (its tracks: {}); holoface decodes H.264 itself, other codecs \
                     through ffmpeg: `ffmpeg -i {} -f yuv4mpegpipe - | holoface track --source -`",
                    path.display(),
                    if found.is_empty() { "none".to_owned() } else { found.join(", ") },
                    path.display()
                )
            })?;
        let track_id = *track_id;
        let avc = track.trak.mdia.minf.stbl.stsd.avc1.as_ref().ok_or_else(|| {
            err!(
                Malformed,
                "{}: the H.264 track has no avc1 description",
                path.display()
            )
        })?;
        crate::images::check_image_size(u64::from(avc.width), u64::from(avc.height))
            .with_context(|| format!("{}: the H.264 track's frame size", path.display()))?;
        let length_size = usize::from(avc.avcc.length_size_minus_one & 3) + 1;
        let mut parameter_sets = Vec::new();
        for nal in avc
            .avcc
            .sequence_parameter_sets
            .iter()
            .chain(&avc.avcc.picture_parameter_sets)
        {
            parameter_sets.extend_from_slice(&[0, 0, 0, 1]);
            parameter_sets.extend_from_slice(&nal.bytes);
        }
        if avc.avcc.sequence_parameter_sets.is_empty() || avc.avcc.picture_parameter_sets.is_empty() {
            fail!(Malformed, "{}: the H.264 track has no SPS/PPS", path.display());
        }
        let stsz = &track.trak.mdia.minf.stbl.stsz;
        let sample_count = track.sample_count();
        let too_big = |s: u32| s > MAX_SAMPLE_BYTES || u64::from(s) > size;
        if too_big(stsz.sample_size) || stsz.sample_sizes.iter().any(|&s| too_big(s)) {
            fail!(
                Malformed,
                "{}: a sample claims more bytes than the file holds (corrupt sample table)",
                path.display()
            );
        }
        let timescale = u64::from(track.timescale());
        if timescale == 0 {
            fail!(
                Malformed,
                "{}: the video track has a zero timescale",
                path.display()
            );
        }
        // No flush after a packet that returned no picture: the reorder buffer of B-frames must fill.
        let config =
            openh264::decoder::DecoderConfig::new().flush_after_decode(openh264::decoder::Flush::NoFlush);
        let decoder =
            openh264::decoder::Decoder::with_api_config(openh264::OpenH264API::from_source(), config)
                .map_err(|e| err!(Codec, "starting the H.264 decoder: {e}"))?;
        Ok(Self {
            path: path.to_path_buf(),
            reader,
            track_id,
            timescale,
            sample_count,
            next_sample: 1,
            length_size,
            parameter_sets,
            decoder,
            annexb: Vec::new(),
            pending_times: std::collections::BinaryHeap::new(),
            ready: VecDeque::new(),
            flushed: false,
            index: 0,
            intrinsics,
            lut: crate::full_range_lut(),
        })
    }

    /// Number of encoded frames in the track.
    pub fn frame_count(&self) -> u32 {
        self.sample_count
    }

    /// Length-prefixed NAL units (MP4) → Annex-B start codes (OpenH264), parameter sets first on sync
    /// samples so that decoding can start at any key frame.
    fn annexb_from(&mut self, sample: &[u8], sync: bool) -> Result<(), SourceError> {
        self.annexb.clear();
        if sync {
            self.annexb.extend_from_slice(&self.parameter_sets);
        }
        let mut rest = sample;
        while !rest.is_empty() {
            let (len_bytes, tail) = rest
                .split_at_checked(self.length_size)
                .ok_or_else(|| err!(Malformed, "truncated NAL length"))?;
            let len = len_bytes
                .iter()
                .fold(0usize, |acc, &b| (acc << 8) | usize::from(b));
            let (nal, tail) = tail
                .split_at_checked(len)
                .ok_or_else(|| err!(Malformed, "NAL unit of {len} bytes overruns its sample"))?;
            self.annexb.extend_from_slice(&[0, 0, 0, 1]);
            self.annexb.extend_from_slice(nal);
            rest = tail;
        }
        Ok(())
    }

    fn grey_from(lut: &[u8; 256], yuv: &openh264::decoder::DecodedYUV<'_>) -> Result<GrayImage, SourceError> {
        use openh264::formats::YUVSource;
        let (w, h) = yuv.dimensions();
        crate::images::check_image_size(w as u64, h as u64).context("a decoded picture")?;
        let (stride, _, _) = yuv.strides();
        let y = yuv.y();
        let mut out = Vec::with_capacity(w * h);
        for row in 0..h {
            let line = y
                .get(row * stride..row * stride + w)
                .ok_or_else(|| err!(Codec, "decoded picture smaller than its stated size"))?;
            out.extend(line.iter().map(|&v| lut[usize::from(v)]));
        }
        Ok(GrayImage::from_vec(out, w, h)?)
    }

    /// Feeds samples until a picture is ready or the track ends.
    fn fill(&mut self) -> Result<(), SourceError> {
        while self.ready.is_empty() && self.next_sample <= self.sample_count {
            let id = self.next_sample;
            self.next_sample += 1;
            let what = format!("reading frame {id} of {}", self.path.display());
            let track_id = self.track_id;
            let reader = &mut self.reader;
            let Some(sample) = mp4_call(&what, || reader.read_sample(track_id, id))? else {
                continue;
            };
            let pts = sample
                .start_time
                .saturating_add_signed(i64::from(sample.rendering_offset));
            self.pending_times
                .push(std::cmp::Reverse(pts.saturating_mul(1_000_000) / self.timescale));
            self.annexb_from(&sample.bytes, sample.is_sync)
                .with_context(|| format!("frame {id} of {}", self.path.display()))?;
            let picture = self
                .decoder
                .decode(&self.annexb)
                .map_err(|e| err!(Codec, "decoding frame {id} of {}: {e}", self.path.display()))?;
            if let Some(p) = picture {
                let img = Self::grey_from(&self.lut, &p)?;
                self.ready.push_back(img);
            }
        }
        if self.ready.is_empty() && !self.flushed {
            self.flushed = true;
            let rest = self
                .decoder
                .flush_remaining()
                .map_err(|e| err!(Codec, "flushing the decoder of {}: {e}", self.path.display()))?;
            let imgs: Result<Vec<_>, SourceError> =
                rest.iter().map(|p| Self::grey_from(&self.lut, p)).collect();
            self.ready.extend(imgs?);
        }
        Ok(())
    }
}

impl Mp4Source {
    fn read_next(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.fill()?;
        let Some(image) = self.ready.pop_front() else {
            return Ok(None);
        };
        let timestamp_us = self
            .pending_times
            .pop()
            .map_or_else(|| self.index as u64 * 33_333, |std::cmp::Reverse(t)| t);
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

impl FrameSource for Mp4Source {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.read_next()
    }
}

/// Writes grey frames as an H.264 (constrained baseline) track in an MP4 file.
pub struct Mp4Writer {
    path: PathBuf,
    width: usize,
    height: usize,
    fps: u32,
    encoder: openh264::encoder::Encoder,
    mux: Option<mp4::Mp4Writer<Output>>,
    /// The file until the first frame starts the muxer; it appears at `path` only when `finish` succeeds.
    file: Option<Output>,
    frames: u64,
    yuv: Vec<u8>,
}

impl std::fmt::Debug for Mp4Writer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mp4Writer")
            .field("path", &self.path)
            .field("frames", &self.frames)
            .finish_non_exhaustive()
    }
}

impl Mp4Writer {
    /// Creates `path` for `width`×`height` frames (even sizes) at `fps`, at a bitrate that keeps a
    /// 640×480 face sequence visually lossless for the aligners (about 4 Mbit/s).
    pub fn create(
        path: &Path,
        width: usize,
        height: usize,
        fps: u32,
        temporaries: &crate::output::Temporaries,
    ) -> Result<Self, SourceError> {
        use openh264::encoder::{BitRate, EncoderConfig, FrameRate, RateControlMode};
        if !width.is_multiple_of(2) || !height.is_multiple_of(2) || width == 0 || height == 0 {
            fail!(
                Usage,
                "video frames must have even, non-zero sizes, got {width}x{height}"
            );
        }
        if fps == 0 {
            fail!(Usage, "frame rate must be positive");
        }
        let cfg = EncoderConfig::new()
            .bitrate(BitRate::from_bps(4_000_000))
            .max_frame_rate(FrameRate::from_hz(fps as f32))
            .rate_control_mode(RateControlMode::Quality);
        let encoder = openh264::encoder::Encoder::with_api_config(openh264::OpenH264API::from_source(), cfg)
            .map_err(|e| err!(Codec, "starting the H.264 encoder: {e}"))?;
        let file = Output::create(path, temporaries)?;
        Ok(Self {
            path: path.to_path_buf(),
            width,
            height,
            fps,
            encoder,
            mux: None,
            file: Some(file),
            frames: 0,
            yuv: vec![128; width * height * 3 / 2],
        })
    }

    /// Encodes one frame (full-range grey, stored as limited-range luma with neutral chroma).
    pub fn push(&mut self, image: &GrayImage) -> Result<(), SourceError> {
        if (image.width(), image.height()) != (self.width, self.height) {
            fail!(
                Usage,
                "frame is {}x{}, the video is {}x{}",
                image.width(),
                image.height(),
                self.width,
                self.height
            );
        }
        let (luma, chroma) = self.yuv.split_at_mut(self.width * self.height);
        for (d, &s) in luma.iter_mut().zip(image.as_bytes()) {
            *d = (16.0 + f64::from(s) * 219.0 / 255.0).round() as u8;
        }
        chroma.fill(128);
        self.encode_current()
    }

    /// Encodes one colour frame: `rgb` holds rows of `stride` RGB pixels (`stride` ≥ the video's width, at
    /// least the video's height rows); the top-left `width`×`height` is encoded (BT.601, limited range,
    /// 4:2:0), so an odd-sized picture fits a video one pixel smaller.
    pub fn push_rgb(&mut self, rgb: &[u8], stride: usize) -> Result<(), SourceError> {
        let (w, h) = (self.width, self.height);
        if stride < w || rgb.len() < stride * 3 * h {
            fail!(
                Usage,
                "RGB frame of {} bytes with stride {stride} is smaller than the {w}x{h} video",
                rgb.len()
            );
        }
        let px = |x: usize, y: usize| {
            let i = (y * stride + x) * 3;
            (f64::from(rgb[i]), f64::from(rgb[i + 1]), f64::from(rgb[i + 2]))
        };
        let (luma, chroma) = self.yuv.split_at_mut(w * h);
        let (cb, cr) = chroma.split_at_mut(w * h / 4);
        for y in 0..h {
            for x in 0..w {
                let (r, g, b) = px(x, y);
                luma[y * w + x] = (16.0 + (65.481 * r + 128.553 * g + 24.966 * b) / 255.0).round() as u8;
            }
        }
        for cy in 0..h / 2 {
            for cx in 0..w / 2 {
                let (mut r, mut g, mut b) = (0.0, 0.0, 0.0);
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    let p = px(2 * cx + dx, 2 * cy + dy);
                    (r, g, b) = (r + p.0 / 4.0, g + p.1 / 4.0, b + p.2 / 4.0);
                }
                cb[cy * (w / 2) + cx] =
                    (128.0 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255.0).round() as u8;
                cr[cy * (w / 2) + cx] = (128.0 + (112.0 * r - 93.786 * g - 18.214 * b) / 255.0).round() as u8;
            }
        }
        self.encode_current()
    }

    /// Encodes the frame in `self.yuv` (I420) and appends it to the track.
    fn encode_current(&mut self) -> Result<(), SourceError> {
        use openh264::formats::YUVBuffer;
        let yuv = YUVBuffer::from_vec(self.yuv.clone(), self.width, self.height);
        let stream = self
            .encoder
            .encode(&yuv)
            .map_err(|e| err!(Codec, "encoding frame {}: {e}", self.frames))?;
        let sync = matches!(stream.frame_type(), openh264::encoder::FrameType::IDR);
        let (mut sps, mut pps, mut sample) = (Vec::new(), Vec::new(), Vec::new());
        for l in 0..stream.num_layers() {
            let Some(layer) = stream.layer(l) else { continue };
            for n in 0..layer.nal_count() {
                let Some(unit) = layer.nal_unit(n) else { continue };
                let nal = strip_start_code(unit);
                match nal.first().map(|b| b & 0x1f) {
                    Some(7) => sps = nal.to_vec(),
                    Some(8) => pps = nal.to_vec(),
                    Some(_) => {
                        let len = u32::try_from(nal.len()).map_err(|_| err!(Codec, "NAL unit too large"))?;
                        sample.extend_from_slice(&len.to_be_bytes());
                        sample.extend_from_slice(nal);
                    }
                    None => {}
                }
            }
        }
        if self.mux.is_none() {
            if sps.is_empty() || pps.is_empty() {
                fail!(Codec, "the encoder's first frame carries no SPS/PPS");
            }
            let file = self
                .file
                .take()
                .ok_or_else(|| err!(Usage, "writer already finished"))?;
            let mut mux = mp4::Mp4Writer::write_start(
                file,
                &mp4::Mp4Config {
                    major_brand: str::parse("isom").map_err(|e| err!(Codec, "{e}"))?,
                    minor_version: 512,
                    compatible_brands: vec![
                        str::parse("isom").map_err(|e| err!(Codec, "{e}"))?,
                        str::parse("avc1").map_err(|e| err!(Codec, "{e}"))?,
                    ],
                    timescale: 1000,
                },
            )
            .map_err(|e| err!(Codec, "writing {}: {e}", self.path.display()))?;
            mux.add_track(&mp4::TrackConfig {
                track_type: mp4::TrackType::Video,
                timescale: self.fps * 1000,
                language: "und".into(),
                media_conf: mp4::MediaConfig::AvcConfig(mp4::AvcConfig {
                    width: u16::try_from(self.width).map_err(|_| err!(Usage, "video too wide"))?,
                    height: u16::try_from(self.height).map_err(|_| err!(Usage, "video too tall"))?,
                    seq_param_set: sps,
                    pic_param_set: pps,
                }),
            })
            .map_err(|e| err!(Codec, "writing {}: {e}", self.path.display()))?;
            self.mux = Some(mux);
        }
        let mux = self
            .mux
            .as_mut()
            .ok_or_else(|| err!(Usage, "writer already finished"))?;
        mux.write_sample(
            1,
            &mp4::Mp4Sample {
                start_time: self.frames * 1000,
                duration: 1000,
                rendering_offset: 0,
                is_sync: sync,
                bytes: sample.into(),
            },
        )
        .map_err(|e| err!(Codec, "writing {}: {e}", self.path.display()))?;
        self.frames += 1;
        Ok(())
    }

    /// Writes the index (`moov`) and closes the file; returns the number of frames.
    pub fn finish(mut self) -> Result<u64, SourceError> {
        let mut mux = self
            .mux
            .take()
            .ok_or_else(|| err!(Empty, "{}: no frames were written", self.path.display()))?;
        mux.write_end()
            .map_err(|e| err!(Codec, "writing {}: {e}", self.path.display()))?;
        mux.into_writer().commit()?;
        Ok(self.frames)
    }
}

fn strip_start_code(unit: &[u8]) -> &[u8] {
    unit.strip_prefix(&[0, 0, 0, 1])
        .or_else(|| unit.strip_prefix(&[0, 0, 1]))
        .unwrap_or(unit)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn luma_range_expansion_is_monotone_and_saturates() {
        let lut = crate::full_range_lut();
        assert_eq!(lut[16], 0);
        assert_eq!(lut[235], 255);
        assert_eq!(lut[0], 0);
        assert_eq!(lut[255], 255);
        assert!(lut.windows(2).all(|w| w[0] <= w[1]));
    }

    #[test]
    fn start_codes_are_stripped() {
        assert_eq!(strip_start_code(&[0, 0, 0, 1, 0x65, 1]), &[0x65, 1]);
        assert_eq!(strip_start_code(&[0, 0, 1, 0x41]), &[0x41]);
        assert_eq!(strip_start_code(&[0x41]), &[0x41]);
    }
}
