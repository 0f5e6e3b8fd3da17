//! Frame sources: image sequences, MP4/H.264 videos (`video.rs`), YUV4MPEG2 streams (`y4m.rs`, files or
//! standard input) and recorded streams. Each frame carries a timestamp, intrinsics and a
//! camera-to-world pose (identity when the source does not know it).
//!
//! This module and `data.rs` are the only places the client reads frames from files.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use crate::error::{Context as _, fail};
use holoface_models::camera::Intrinsics;
use holoface_models::image::GrayImage;
use holoface_models::math3::Pose;
use holoface_protocol::CropEncoding;
use holoface_protocol::recording::{FramePayload, RecordingReader};

use crate::images::{list_images, read_gray};
use crate::{FrameSource, SourceError};
use holoface_runtime::{OwnedFrame, default_intrinsics};

/// A folder of PNG/JPEG images in name order, at a fixed frame rate, identity pose.
#[derive(Debug)]
pub struct ImageSequence {
    paths: Vec<PathBuf>,
    next: usize,
    fps: f64,
    intrinsics: Option<Intrinsics>,
}

impl ImageSequence {
    /// One image file as a one-frame sequence (a photograph).
    pub fn single(path: &Path, fps: f64) -> Result<Self, SourceError> {
        if !(fps.is_finite() && fps > 0.0) {
            fail!(Usage, "frame rate must be positive, got {fps}");
        }
        Ok(Self {
            paths: vec![path.to_path_buf()],
            next: 0,
            fps,
            intrinsics: None,
        })
    }

    /// Lists the images of `dir`.
    pub fn open(dir: &Path, fps: f64, intrinsics: Option<Intrinsics>) -> Result<Self, SourceError> {
        let paths: Vec<PathBuf> = list_images(dir)?.into_iter().map(|(_, p)| p).collect();
        if paths.is_empty() {
            fail!(Empty, "no PNG or JPEG images in {}", dir.display());
        }
        if !(fps.is_finite() && fps > 0.0) {
            fail!(Usage, "frame rate must be positive, got {fps}");
        }
        Ok(Self {
            paths,
            next: 0,
            fps,
            intrinsics,
        })
    }
}

impl ImageSequence {
    fn read_next(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        let Some(path) = self.paths.get(self.next) else {
            return Ok(None);
        };
        let index = self.next;
        self.next += 1;
        let image = read_gray(path)?;
        let intrinsics = self
            .intrinsics
            .unwrap_or_else(|| default_intrinsics(image.width(), image.height()));
        Ok(Some(OwnedFrame {
            index,
            timestamp_us: (index as f64 * 1e6 / self.fps) as u64,
            image,
            intrinsics,
            world_from_camera: Pose::IDENTITY,
            ground_truth: None,
        }))
    }
}

impl FrameSource for ImageSequence {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.read_next()
    }
}

/// A recorded stream (`.hfrec`) of full frames. Crop records are skipped (they carry no full frame).
#[derive(Debug)]
pub struct RecordedStream {
    reader: RecordingReader<BufReader<File>>,
    intrinsics: Intrinsics,
    path: PathBuf,
    index: usize,
    /// Crop records passed over (they are for the load tester, not for tracking).
    crops: u64,
}

impl RecordedStream {
    /// Opens a recording and reads its header.
    pub fn open(path: &Path) -> Result<Self, SourceError> {
        let file = File::open(path).with_context(|| format!("opening recording {}", path.display()))?;
        // A recording whose writer was killed ends inside a record: its whole records are read (and the cut named).
        let reader = RecordingReader::new(BufReader::new(file))
            .with_context(|| format!("reading the header of {}", path.display()))?
            .tolerate_cut();
        let c = reader.header().intrinsics;
        let intrinsics = Intrinsics {
            fx: f64::from(c.fx),
            fy: f64::from(c.fy),
            cx: f64::from(c.cx),
            cy: f64::from(c.cy),
        };
        if let Err(why) = intrinsics.check() {
            fail!(Malformed, "{}: the header's intrinsics: {why}", path.display());
        }
        Ok(Self {
            reader,
            intrinsics,
            path: path.to_path_buf(),
            index: 0,
            crops: 0,
        })
    }
}

/// What a reader of a recording cut short says: where it ends and that its whole records were used.
pub fn cut_note(path: &Path, cut: holoface_protocol::recording::Cut) -> String {
    format!(
        "note: {} ends inside record {} (byte {}): a recording cut short, as a killed run leaves it; its {} \
         whole records were read",
        path.display(),
        cut.record_index,
        cut.offset,
        cut.record_index
    )
}

impl RecordedStream {
    fn read_next(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        loop {
            let rec = self
                .reader
                .next_record()
                .with_context(|| format!("reading {}", self.path.display()))?;
            let Some(rec) = rec else {
                if self.index == 0 && self.crops > 0 {
                    fail!(
                        Unsupported,
                        "{} holds {} face crops and no full frames (a `holoface record --crops` recording, made \
                         for the load tester `holoface-load`); tracking needs full frames: record without --crops",
                        self.path.display(),
                        self.crops
                    );
                }
                if let Some(cut) = self.reader.cut() {
                    eprintln!("{}", cut_note(&self.path, cut));
                }
                return Ok(None);
            };
            let FramePayload::FullFrame {
                width,
                height,
                encoding,
                data,
            } = rec.payload
            else {
                self.crops += 1;
                continue;
            };
            let (w, h) = (width as usize, height as usize);
            let image = match encoding {
                CropEncoding::Raw => GrayImage::from_vec(data.to_vec(), w, h)?,
                CropEncoding::Png | CropEncoding::Jpeg => {
                    let img = crate::images::decode_gray(&data).with_context(|| {
                        format!("decoding frame {} of {}", self.index, self.path.display())
                    })?;
                    if (img.width(), img.height()) != (w, h) {
                        fail!(
                            Malformed,
                            "frame {} of {}: encoded image size differs from the record",
                            self.index,
                            self.path.display()
                        );
                    }
                    img
                }
            };
            let world_from_camera = Pose::from_row_major_4x4(&rec.camera_to_world).with_context(|| {
                format!(
                    "frame {} of {}: camera-to-world is not a rigid transform",
                    self.index,
                    self.path.display()
                )
            })?;
            if let Err(why) = crate::poses::check_distance(&world_from_camera) {
                fail!(
                    Malformed,
                    "frame {} of {}: {why}",
                    self.index,
                    self.path.display()
                );
            }
            let index = self.index;
            self.index += 1;
            return Ok(Some(OwnedFrame {
                index,
                timestamp_us: rec.timestamp_us,
                image,
                intrinsics: self.intrinsics,
                world_from_camera,
                ground_truth: rec.ground_truth.map(|g| {
                    g.iter()
                        .map(|p| holoface_models::geometry::Point2::new(p[0], p[1]))
                        .collect()
                }),
            }));
        }
    }
}

impl FrameSource for RecordedStream {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.read_next()
    }
}

/// Whether `path` looks like an MP4/QuickTime file: by extension, else by the `ftyp` box at offset 4.
fn is_mp4(path: &Path) -> bool {
    let by_ext = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["mp4", "m4v", "mov"].contains(&e.to_ascii_lowercase().as_str()));
    by_ext || {
        use std::io::Read;
        let mut head = [0u8; 8];
        File::open(path)
            .and_then(|mut f| f.read_exact(&mut head))
            .is_ok_and(|()| &head[4..8] == b"ftyp")
    }
}

/// Whether `path` is a WebM/Matroska file: by extension, else by its EBML magic.
fn is_matroska(path: &Path) -> bool {
    let by_ext = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["webm", "mkv"].contains(&e.to_ascii_lowercase().as_str()));
    by_ext || {
        use std::io::Read;
        let mut head = [0u8; 4];
        File::open(path)
            .and_then(|mut f| f.read_exact(&mut head))
            .is_ok_and(|()| head == [0x1a, 0x45, 0xdf, 0xa3])
    }
}

/// Whether `path` names a video container FFmpeg reads other than MP4 and Matroska, by extension.
fn is_other_video(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| {
        [
            "avi", "ts", "mts", "m2ts", "3gp", "flv", "ogv", "hevc", "h264", "264", "265",
        ]
        .contains(&e.to_ascii_lowercase().as_str())
    })
}

/// A video file through FFmpeg's libraries (feature `ffmpeg`).
#[cfg(feature = "ffmpeg")]
fn open_video(path: &Path) -> Result<Box<dyn FrameSource>, SourceError> {
    Ok(Box::new(crate::ffmpeg::FfmpegSource::open(path, None)?))
}

/// Never called without the `ffmpeg` feature (the caller checks it first).
#[cfg(not(feature = "ffmpeg"))]
fn open_video(path: &Path) -> Result<Box<dyn FrameSource>, SourceError> {
    fail!(
        Unsupported,
        "{}: this build reads videos without FFmpeg",
        path.display()
    )
}

/// Whether `path` is a PNG or JPEG image, by extension.
fn is_image(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["png", "jpg", "jpeg"].contains(&e.to_ascii_lowercase().as_str()))
}

/// Whether `path` is a YUV4MPEG2 stream: by extension, else by its magic bytes.
fn is_y4m(path: &Path) -> bool {
    use std::io::Read;
    let by_ext = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("y4m"));
    by_ext || {
        let mut head = [0u8; 9];
        File::open(path)
            .and_then(|mut f| f.read_exact(&mut head))
            .is_ok_and(|()| head == *crate::y4m::MAGIC)
    }
}

/// Opens a frame source: a folder of images, one image (a photograph: one frame), a video file (with the `ffmpeg`
/// feature whatever the system's FFmpeg decodes: MP4, MOV, WebM, MKV, ... with H.264, HEVC, VP8/VP9, AV1; without
/// it MP4/H.264 through OpenH264), a YUV4MPEG2 stream (`.y4m`, or `-` for
/// standard input: a live camera piped through ffmpeg), or a recorded stream (`.hfrec`); with a pose sidecar
/// (see [`crate::poses`]) the frames take their camera-to-world poses from it. `fps` times the frames of an
/// image folder and of a `.y4m` whose header has no frame rate.
pub fn open_source(path: &Path, fps: f64, poses: Option<&Path>) -> Result<Box<dyn FrameSource>, SourceError> {
    let inner: Box<dyn FrameSource> = if path.as_os_str() == "-" {
        let stdin = BufReader::new(std::io::stdin());
        Box::new(crate::y4m::Y4mSource::new(stdin, "stdin", fps, None)?)
    } else if path.is_dir() {
        Box::new(ImageSequence::open(path, fps, None)?)
    } else if path.is_file() {
        if is_image(path) {
            Box::new(ImageSequence::single(path, fps)?)
        } else if cfg!(feature = "ffmpeg") && (is_mp4(path) || is_matroska(path) || is_other_video(path)) {
            open_video(path)?
        } else if is_matroska(path) {
            fail!(
                Unsupported,
                "{} is a WebM/Matroska video (VP8, VP9 or AV1): this build decodes H.264 MP4 and y4m itself \
                 (the `ffmpeg` feature reads the rest); pipe other videos through ffmpeg: `ffmpeg -i {} -f yuv4mpegpipe - | holoface track --source -`",
                path.display(),
                path.display()
            )
        } else if is_mp4(path) {
            Box::new(crate::video::Mp4Source::open(path, None)?)
        } else if is_y4m(path) {
            let file = File::open(path).with_context(|| format!("opening {}", path.display()))?;
            let name = path.display().to_string();
            Box::new(crate::y4m::Y4mSource::new(
                BufReader::new(file),
                &name,
                fps,
                None,
            )?)
        } else {
            Box::new(RecordedStream::open(path)?)
        }
    } else {
        // Not a folder, not a file: say what it is (a pipe, a device, a link loop) rather than "missing".
        match holoface_files::regular_file(path, "frame source") {
            Err(holoface_files::FileError::NotAFile {
                kind: holoface_files::FileKind::NamedPipe,
                ..
            }) => {
                fail!(
                    Unsupported,
                    "frame source {} is a named pipe (FIFO): stream a y4m video through standard input instead \
                 (`--source - < {}`, or `ffmpeg -i VIDEO -f yuv4mpegpipe - | holoface track --source -`)",
                    path.display(),
                    path.display()
                )
            }
            Err(e) => return Err(e.into()),
            Ok(_) => fail!(Unsupported, "frame source {} cannot be read", path.display()),
        }
    };
    Ok(match poses {
        Some(p) => Box::new(crate::poses::WithPoses::new(
            inner,
            crate::poses::PoseSidecar::load(p)?,
        )),
        None => inner,
    })
}

#[cfg(test)]
mod tests {
    use holoface_protocol::recording::{CameraIntrinsics, FrameRecord, RecordingHeader, RecordingWriter};

    use super::*;

    fn recording(name: &str, payloads: Vec<FramePayload>) -> PathBuf {
        let identity = [
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ];
        recording_at(name, payloads, identity)
    }

    fn recording_at(name: &str, payloads: Vec<FramePayload>, camera_to_world: [f32; 16]) -> PathBuf {
        let path = std::env::temp_dir().join(format!("holoface-source-{name}-{}.hfrec", std::process::id()));
        let header = RecordingHeader {
            intrinsics: CameraIntrinsics {
                fx: 100.0,
                fy: 100.0,
                cx: 8.0,
                cy: 8.0,
                width: 16,
                height: 16,
            },
            source: "test".into(),
            created_unix_ms: 0,
        };
        let mut w = RecordingWriter::new(File::create(&path).unwrap(), &header).unwrap();
        for (k, payload) in payloads.into_iter().enumerate() {
            w.write_record(&FrameRecord {
                timestamp_us: k as u64 * 33_333,
                camera_to_world,
                payload,
                ground_truth: None,
                face_present: None,
            })
            .unwrap();
        }
        w.finish().unwrap();
        path
    }

    fn crop() -> FramePayload {
        FramePayload::Crop {
            image_from_crop: [1.0, 0.0, 0.0, 0.0],
            crop: holoface_protocol::Crop::raw(112, 112, vec![7; 112 * 112]),
        }
    }

    #[test]
    fn a_crops_only_recording_is_an_error_not_zero_frames() {
        let path = recording("crops", vec![crop(), crop()]);
        let mut src = RecordedStream::open(&path).unwrap();
        let err = src.next_frame().unwrap_err().to_string();
        assert!(
            err.contains("2 face crops and no full frames") && err.contains("--crops"),
            "{err}"
        );
        std::fs::remove_file(path).ok();
    }

    #[test]
    fn one_image_file_is_a_one_frame_source_and_a_corrupt_one_an_error() {
        let dir = std::env::temp_dir().join(format!("holoface-source-photo-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let photo = dir.join("group.PNG");
        image::GrayImage::from_pixel(20, 10, image::Luma([77]))
            .save_with_format(&photo, image::ImageFormat::Png)
            .unwrap();
        let mut src = open_source(&photo, 30.0, None).unwrap();
        let f = src.next_frame().unwrap().expect("the photo");
        assert_eq!((f.index, f.image.width(), f.image.height()), (0, 20, 10));
        assert_eq!(f.image.as_bytes()[0], 77);
        assert!(src.next_frame().unwrap().is_none(), "one frame");

        let bad = dir.join("bad.jpg");
        std::fs::write(&bad, b"not a jpeg").unwrap();
        let mut src = open_source(&bad, 30.0, None).unwrap();
        let err = format!("{:#}", src.next_frame().unwrap_err());
        assert!(err.contains("bad.jpg"), "the error names the file: {err}");
        std::fs::remove_dir_all(dir).ok();
    }

    /// A recorded pose 3e38 m from the world origin is refused like the same pose in a sidecar (issue 30).
    #[test]
    fn a_recorded_pose_far_outside_any_world_is_an_error_naming_the_frame() {
        let full = FramePayload::FullFrame {
            width: 16,
            height: 16,
            encoding: CropEncoding::Raw,
            data: vec![9; 256].into(),
        };
        let far = [
            1.0, 0.0, 0.0, 3e38, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ];
        let path = recording_at("far", vec![full], far);
        let mut src = RecordedStream::open(&path).unwrap();
        let err = src.next_frame().unwrap_err().to_string();
        assert!(err.contains("frame 0 of") && err.contains("3.0e38 m"), "{err}");
        std::fs::remove_file(path).ok();
    }

    #[test]
    fn crops_between_full_frames_are_passed_over() {
        let full = FramePayload::FullFrame {
            width: 16,
            height: 16,
            encoding: CropEncoding::Raw,
            data: vec![9; 256].into(),
        };
        let path = recording("mixed", vec![crop(), full, crop()]);
        let mut src = RecordedStream::open(&path).unwrap();
        let f = src.next_frame().unwrap().expect("the full frame");
        assert_eq!((f.index, f.image.width(), f.timestamp_us), (0, 16, 33_333));
        assert!(
            src.next_frame().unwrap().is_none(),
            "a clean end after a full frame"
        );
        std::fs::remove_file(path).ok();
    }
}
