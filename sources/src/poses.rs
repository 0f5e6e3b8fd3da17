//! Pose sidecar files: the headset's camera-to-world pose (and optionally intrinsics) per frame of a video
//! or image folder, which carry none themselves.
//!
//! Format: JSON lines, one object per frame; blank lines and lines starting with `#` are ignored.
//!
//! ```text
//! {"frame": 0, "camera_to_world": [r00, r01, r02, tx, r10, r11, r12, ty, r20, r21, r22, tz, 0, 0, 0, 1]}
//! {"frame": 1, "camera_to_world": [...], "intrinsics": [fx, fy, cx, cy], "timestamp_us": 33333}
//! ```
//!
//! * `frame`: 0-based index in the source (each at most once);
//! * `camera_to_world`: row-major 4×4 rigid transform, metres, camera axes x right / y down / z forward;
//! * `intrinsics` (optional): pixels, overrides the source's;
//! * `timestamp_us` (optional): overrides the source's capture time.
//!
//! A sidecar must cover every frame the source yields: a frame without a pose is an error naming the
//! frame, not a silent identity pose (motion compensation would be wrong without notice).

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::{Context as _, fail};
use holoface_models::camera::Intrinsics;
use holoface_models::math3::Pose;
use serde::Deserialize;

use crate::{FrameSource, SourceError};
use holoface_runtime::OwnedFrame;
use holoface_runtime::frame::{MAX_CAMERA_DISTANCE_M, camera_too_far};

/// Refuses a camera farther than [`MAX_CAMERA_DISTANCE_M`] from its world's origin (the message continues
/// "camera_to_world of frame N ..."): the tracker's own limit.
pub(crate) fn check_distance(world_from_camera: &Pose) -> Result<(), String> {
    match camera_too_far(world_from_camera) {
        Some(distance) => Err(format!(
            "puts the camera {distance:.1e} m from the world origin (at most {MAX_CAMERA_DISTANCE_M} m)"
        )),
        None => Ok(()),
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Line {
    frame: usize,
    camera_to_world: [f32; 16],
    #[serde(default)]
    intrinsics: Option<[f64; 4]>,
    #[serde(default)]
    timestamp_us: Option<u64>,
}

/// One frame's entry.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PoseEntry {
    /// Camera-to-world pose.
    pub world_from_camera: Pose,
    /// Intrinsics override.
    pub intrinsics: Option<Intrinsics>,
    /// Capture-time override, microseconds.
    pub timestamp_us: Option<u64>,
}

/// A parsed pose sidecar.
#[derive(Clone, Debug)]
pub struct PoseSidecar {
    path: PathBuf,
    entries: BTreeMap<usize, PoseEntry>,
}

/// The largest pose sidecar read: a line of about 200 bytes per frame, a day of 30-fps video.
pub const MAX_SIDECAR_BYTES: u64 = 512 << 20;

impl PoseSidecar {
    /// Parses sidecar text; `path` only names the file in errors.
    pub fn parse(text: &str, path: &Path) -> Result<Self, SourceError> {
        let mut entries = BTreeMap::new();
        for (i, raw) in text.lines().enumerate() {
            let line_no = i + 1;
            let line = raw.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let at = || format!("{} line {line_no}", path.display());
            let l: Line = serde_json::from_str(line).with_context(at)?;
            let world_from_camera = Pose::from_row_major_4x4(&l.camera_to_world).with_context(|| {
                format!(
                    "{}: camera_to_world of frame {} is not a rigid transform (its 3x3 block must be a rotation)",
                    at(),
                    l.frame
                )
            })?;
            if let Err(why) = check_distance(&world_from_camera) {
                fail!(Malformed, "{}: camera_to_world of frame {} {why}", at(), l.frame);
            }
            let intrinsics = match l.intrinsics {
                Some([fx, fy, cx, cy]) => {
                    let k = Intrinsics { fx, fy, cx, cy };
                    if let Err(why) = k.check() {
                        fail!(Malformed, "{}: intrinsics of frame {}: {why}", at(), l.frame);
                    }
                    Some(k)
                }
                None => None,
            };
            let entry = PoseEntry {
                world_from_camera,
                intrinsics,
                timestamp_us: l.timestamp_us,
            };
            if entries.insert(l.frame, entry).is_some() {
                fail!(Malformed, "{}: frame {} appears twice", at(), l.frame);
            }
        }
        if entries.is_empty() {
            fail!(Empty, "{} holds no poses", path.display());
        }
        Ok(Self {
            path: path.to_path_buf(),
            entries,
        })
    }

    /// Reads and parses a sidecar file.
    pub fn load(path: &Path) -> Result<Self, SourceError> {
        let text = holoface_files::read_text_bounded(path, MAX_SIDECAR_BYTES, "pose sidecar")?;
        Self::parse(&text, path)
    }

    /// The entry of frame `index`.
    pub fn get(&self, index: usize) -> Option<&PoseEntry> {
        self.entries.get(&index)
    }

    /// Number of frames covered.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no frame is covered (never true for a parsed sidecar).
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }
}

/// Writes one sidecar line for `frame`.
pub fn write_line(
    out: &mut impl Write,
    frame: usize,
    world_from_camera: &Pose,
    intrinsics: Option<&Intrinsics>,
    timestamp_us: Option<u64>,
) -> std::io::Result<()> {
    let mut obj = serde_json::json!({
        "frame": frame,
        "camera_to_world": world_from_camera.to_row_major_4x4(),
    });
    if let Some(k) = intrinsics {
        obj["intrinsics"] = serde_json::json!([k.fx, k.fy, k.cx, k.cy]);
    }
    if let Some(t) = timestamp_us {
        obj["timestamp_us"] = serde_json::json!(t);
    }
    serde_json::to_writer(&mut *out, &obj)?;
    out.write_all(b"\n")
}

/// A source whose poses (and optional intrinsics and times) come from a sidecar.
#[derive(Debug)]
pub struct WithPoses<S> {
    inner: S,
    sidecar: PoseSidecar,
}

impl<S: FrameSource> WithPoses<S> {
    /// Wraps `inner`.
    pub fn new(inner: S, sidecar: PoseSidecar) -> Self {
        Self { inner, sidecar }
    }
}

impl<S: FrameSource> WithPoses<S> {
    fn read_next(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        let Some(mut f) = self.inner.next_frame()? else {
            return Ok(None);
        };
        let e = self.sidecar.get(f.index).with_context(|| {
            format!(
                "pose sidecar {} has no pose for frame {} (it covers {} frames)",
                self.sidecar.path.display(),
                f.index,
                self.sidecar.len()
            )
        })?;
        f.world_from_camera = e.world_from_camera;
        if let Some(k) = e.intrinsics {
            f.intrinsics = k;
        }
        if let Some(t) = e.timestamp_us {
            f.timestamp_us = t;
        }
        Ok(Some(f))
    }
}

impl<S: FrameSource> FrameSource for WithPoses<S> {
    fn next_frame(&mut self) -> Result<Option<OwnedFrame>, SourceError> {
        self.read_next()
    }
}

#[cfg(test)]
mod tests {
    use holoface_models::math3::{Mat3, Vec3};

    use super::*;

    fn p() -> &'static Path {
        Path::new("poses.jsonl")
    }

    #[test]
    fn round_trips_written_lines() {
        let pose = Pose {
            rotation: Mat3::rot_y(0.3) * Mat3::rot_x(-0.1),
            translation: Vec3::new(0.1, -0.2, 0.3),
        };
        let k = Intrinsics {
            fx: 500.0,
            fy: 510.0,
            cx: 320.0,
            cy: 240.0,
        };
        let mut buf = Vec::new();
        write_line(&mut buf, 0, &pose, Some(&k), Some(5)).unwrap();
        write_line(&mut buf, 1, &Pose::IDENTITY, None, None).unwrap();
        let s = PoseSidecar::parse(std::str::from_utf8(&buf).unwrap(), p()).unwrap();
        assert_eq!(s.len(), 2);
        let e = s.get(0).unwrap();
        assert!((e.world_from_camera.translation - pose.translation).norm() < 1e-6);
        assert_eq!(e.intrinsics, Some(k));
        assert_eq!(e.timestamp_us, Some(5));
        assert!(s.get(1).unwrap().intrinsics.is_none());
        assert!(s.get(2).is_none());
    }

    #[test]
    fn bad_sidecars_name_the_line_and_the_problem() {
        let ident = "[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]";
        let cases = [
            ("{\"frame\": 0}".to_string(), "line 1"),
            (
                format!("{{\"frame\": 0, \"camera_to_world\": {ident}}}\nnot json"),
                "line 2",
            ),
            (
                "{\"frame\": 0, \"camera_to_world\": [2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]}".to_string(),
                "not a rigid transform",
            ),
            (
                format!(
                    "{{\"frame\": 3, \"camera_to_world\": {ident}}}\n{{\"frame\": 3, \"camera_to_world\": {ident}}}"
                ),
                "appears twice",
            ),
            (
                format!("{{\"frame\": 0, \"camera_to_world\": {ident}, \"intrinsics\": [0, 1, 2, 3]}}"),
                "focal length fx = 0 px",
            ),
            // Physically absurd values (issue 30): a 1e308-px focal length, a principal point 1e9 px away, a
            // camera 3e38 m from the world origin; each names the line and the frame.
            (
                format!(
                    "{{\"frame\": 0, \"camera_to_world\": {ident}}}\n{{\"frame\": 1, \"camera_to_world\": {ident}, \"intrinsics\": [1e308, 1e308, 320, 240]}}"
                ),
                "line 2: intrinsics of frame 1: focal length fx = 1e308 px",
            ),
            (
                format!(
                    "{{\"frame\": 0, \"camera_to_world\": {ident}, \"intrinsics\": [500, 500, 1e9, 240]}}"
                ),
                "line 1: intrinsics of frame 0: principal point cx",
            ),
            (
                "{\"frame\": 4, \"camera_to_world\": [1,0,0,3e38, 0,1,0,0, 0,0,1,0, 0,0,0,1]}".to_string(),
                "line 1: camera_to_world of frame 4 puts the camera 3.0e38 m",
            ),
            (
                format!("{{\"frame\": 0, \"camera_to_world\": {ident}, \"extra\": 1}}"),
                "line 1",
            ),
            ("# only a comment\n\n".to_string(), "holds no poses"),
        ];
        for (text, want) in cases {
            let err = format!("{:#}", PoseSidecar::parse(&text, p()).unwrap_err());
            assert!(err.contains(want), "{text:?}: {err}");
            assert!(err.contains("poses.jsonl"), "{err}");
        }
    }
}
