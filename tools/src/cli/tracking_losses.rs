//! `holoface tracking-losses`: tracking losses with and without headset-motion compensation, measured
//! with a real aligner on rendered headset sequences.
//!
//! Each validation face (never trained on) is cut out of its photo and hung as a flat, life-size picture
//! (`render.rs`) that moves like a head (±15° yaw, ±8° pitch and roll, ±5 cm), while the wearer's headset
//! turns quickly (default ±15° yaw every 1.5 s, ≈ 60°/s at its fastest, plus pitch and sway). Every frame
//! is the exact homography of the photo, so the annotated landmarks' true positions are known.
//!
//! Two tracker sessions see the same frames, with the same detector, aligner and thresholds; the only
//! difference is whether the previous landmarks are moved with the headset's pose before aligning.
//! Per session:
//! * **loss**: a frame initialised from tracking whose result is not a good face: the aligner's own
//!   signal rejects it (the session re-detects on the next frame), or it is accepted but NME49 against
//!   the truth exceeds 0.08 (silent drift). Counted once per episode;
//! * good / drifting / no-face frames and the detector runs they cost.
//!
//! `--write-sequence DIR` also exports the first face's sequence as `sequence.mp4` (H.264), `poses.jsonl`
//! (the pose sidecar `holoface track --poses` reads) and `truth.jsonl` (true landmarks per frame).

use std::io::Write;
use std::path::PathBuf;

use crate::render::SCENE_CAMERA;
use anyhow::{Context, bail};
use clap::Args as ClapArgs;
use holoface_models::accuracy::nme49;
use holoface_models::geometry::{Point2, Rect};
use holoface_models::image::GrayImage;
use holoface_models::math3::{Mat3, Pose, Vec3};
use serde_json::json;

use crate::args::{AlignerKind, RuntimeArgs};
use crate::render::PlanarScene;
use holoface_harness::data::{Split, faces68_or, load_folder};
use holoface_runtime::frame::Frame;
use holoface_runtime::{FaceOutcome, FaceTracker, InitSource, SessionOptions};

/// Arguments of `holoface tracking-losses`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// Annotated faces (`NAME.jpg` + `NAME.pts`); the validation split is used.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Number of validation faces (sequences).
    #[arg(long, default_value_t = 20)]
    pub faces: usize,
    /// Length of each sequence, seconds.
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Frame rate.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Headset yaw amplitude, degrees (the wearer turning their head).
    #[arg(long, default_value_t = 15.0)]
    pub headset_yaw_deg: f64,
    /// Period of the headset's yaw, seconds.
    #[arg(long, default_value_t = 1.5)]
    pub headset_period_s: f64,
    /// Aligner.
    #[arg(long, value_enum, default_value = "krfws")]
    pub aligner: AlignerKind,
    /// CANDIDE-3 model.
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
    /// JSON report.
    #[arg(long, default_value = "runs/tracking-losses.json")]
    pub out: PathBuf,
    /// The landmark filter.
    #[command(flatten)]
    pub steady: crate::args::SteadyArgs,
    /// Also export the first face's sequence (MP4 + pose sidecar + true landmarks) into this folder.
    #[arg(long)]
    pub write_sequence: Option<PathBuf>,
    /// Runtime assets.
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

pub(crate) const FRAME_W: usize = 640;
pub(crate) const FRAME_H: usize = 480;
const FACE_DISTANCE_M: f64 = 0.6;
pub(crate) const GOOD_NME: f64 = 0.08;

/// The scenario's motion; `phase` decorrelates sequences.
#[derive(Clone, Copy, Debug)]
struct Motion {
    yaw: f64,
    period: f64,
    phase: f64,
}

impl Motion {
    fn headset(&self, t: f64) -> Pose {
        let w = std::f64::consts::TAU / self.period;
        let s = t + self.phase;
        Pose {
            rotation: Mat3::rot_y(self.yaw.to_radians() * (w * s).sin())
                * Mat3::rot_x((0.4 * self.yaw).to_radians() * (0.7 * w * s + 1.0).sin()),
            translation: Vec3::new(
                0.03 * (0.5 * w * s).sin(),
                0.02 * (0.6 * w * s + 0.3).sin(),
                0.03 * (0.4 * w * s).sin(),
            ),
        }
    }

    /// The face's own motion, slower than the headset's: where the picture hangs at `t`.
    fn head(&self, t: f64) -> Pose {
        let tau = std::f64::consts::TAU;
        let s = t + 2.0 * self.phase;
        Pose {
            rotation: Mat3::rot_y(15f64.to_radians() * (tau * s / 6.0).sin())
                * Mat3::rot_x(8f64.to_radians() * (tau * s / 4.5 + 0.5).sin())
                * Mat3::rot_z(8f64.to_radians() * (tau * s / 5.0).sin()),
            translation: Vec3::new(
                0.05 * (tau * s / 7.0).sin(),
                0.03 * (tau * s / 5.5).sin(),
                FACE_DISTANCE_M + 0.05 * (tau * s / 8.0).sin(),
            ),
        }
    }
}

/// The face's photo region: the landmarks' box grown by its size on every side (other faces in group
/// photos are mostly cut away); landmarks are moved into the cut.
fn cut_face(image: &GrayImage, lm: &[Point2; 68]) -> anyhow::Result<(GrayImage, [Point2; 68])> {
    cut_face_with_margin(image, lm, 1.0)
}

/// [`cut_face`] with the box grown by `margin` times its size on every side.
pub(crate) fn cut_face_with_margin(
    image: &GrayImage,
    lm: &[Point2; 68],
    margin: f32,
) -> anyhow::Result<(GrayImage, [Point2; 68])> {
    let r = Rect::bounding(lm).context("empty landmarks")?;
    let m = margin * r.width().max(r.height());
    let x0 = (r.x0 - m).floor().max(0.0) as usize;
    let y0 = (r.y0 - m).floor().max(0.0) as usize;
    let x1 = ((r.x1 + m).ceil() as usize).min(image.width());
    let y1 = ((r.y1 + m).ceil() as usize).min(image.height());
    if x1 <= x0 + 1 || y1 <= y0 + 1 {
        bail!("face box outside the image");
    }
    let (w, h) = (x1 - x0, y1 - y0);
    let src = image.as_bytes();
    let mut data = Vec::with_capacity(w * h);
    for y in y0..y1 {
        data.extend_from_slice(&src[y * image.width() + x0..y * image.width() + x1]);
    }
    let moved = std::array::from_fn(|i| Point2::new(lm[i].x - x0 as f32, lm[i].y - y0 as f32));
    Ok((GrayImage::from_vec(data, w, h)?, moved))
}

/// Per-session counters.
#[derive(Debug, Default, Clone, serde::Serialize)]
struct Tally {
    frames: usize,
    good: usize,
    drifting: usize,
    no_face: usize,
    detections: usize,
    losses: usize,
    nme49_sum: f64,
    nme49_n: usize,
    /// NME49 of the aligner's own (unsteadied) landmarks, over the same frames.
    raw_nme49_sum: f64,
    /// Lag behind the truth, least squares over the 49 points of every frame after the first of a track:
    /// `sum <truth - shown, v> / sum |v|^2` with `v` the truth's motion since the previous frame (frames).
    lag_num: f64,
    lag_raw_num: f64,
    lag_den: f64,
    #[serde(skip)]
    was_good: bool,
    #[serde(skip)]
    prev_truth: Option<[Point2; 68]>,
}

impl Tally {
    fn record(&mut self, result: &FaceOutcome, init: Option<InitSource>, truth: &[Point2; 68]) {
        self.frames += 1;
        if init == Some(InitSource::Detection) {
            self.detections += 1;
        }
        let good = match result {
            FaceOutcome::Face(u) => {
                let e = nme49(&u.landmarks, truth).unwrap_or(f64::INFINITY);
                let raw = nme49(&u.raw_landmarks, truth).unwrap_or(f64::INFINITY);
                if e.is_finite() && raw.is_finite() {
                    self.nme49_sum += e;
                    self.raw_nme49_sum += raw;
                    self.nme49_n += 1;
                }
                if let Some(prev) = self.prev_truth.filter(|_| init == Some(InitSource::Tracking)) {
                    for &i in &holoface_models::shape::PROTOCOL49 {
                        let v = (
                            f64::from(truth[i].x - prev[i].x),
                            f64::from(truth[i].y - prev[i].y),
                        );
                        let behind =
                            |p: Point2| f64::from(truth[i].x - p.x) * v.0 + f64::from(truth[i].y - p.y) * v.1;
                        self.lag_num += behind(u.landmarks[i]);
                        self.lag_raw_num += behind(u.raw_landmarks[i]);
                        self.lag_den += v.0 * v.0 + v.1 * v.1;
                    }
                }
                if e <= GOOD_NME {
                    self.good += 1;
                    true
                } else {
                    self.drifting += 1;
                    false
                }
            }
            FaceOutcome::NoFace(_) => {
                self.no_face += 1;
                false
            }
        };
        if init == Some(InitSource::Tracking) && self.was_good && !good {
            self.losses += 1;
        }
        self.was_good = good;
        self.prev_truth = Some(*truth);
    }

    fn summary(&self, fps: f64) -> serde_json::Value {
        let n = self.frames.max(1) as f64;
        json!({
            "frames": self.frames,
            "losses": self.losses,
            "losses_per_minute": self.losses as f64 / (self.frames as f64 / fps / 60.0).max(1e-9),
            "good_frames_pct": 100.0 * self.good as f64 / n,
            "drifting_frames_pct": 100.0 * self.drifting as f64 / n,
            "no_face_frames_pct": 100.0 * self.no_face as f64 / n,
            "detector_runs": self.detections,
            "mean_nme49_pct": 100.0 * self.nme49_sum / self.nme49_n.max(1) as f64,
            "raw_mean_nme49_pct": 100.0 * self.raw_nme49_sum / self.nme49_n.max(1) as f64,
            "lag_frames": self.lag_num / self.lag_den.max(1e-12),
            "raw_lag_frames": self.lag_raw_num / self.lag_den.max(1e-12),
        })
    }
}

struct Runner {
    tracker: FaceTracker,
    tally: Tally,
}

impl Runner {
    fn step(&mut self, frame: &Frame<'_>, truth: &[Point2; 68]) -> anyhow::Result<()> {
        let step = self.tracker.process_step(frame)?;
        let init = step.first_candidate().map(|c| c.source);
        let result = step.faces.first();
        self.tally.record(&result, init, truth);
        Ok(())
    }
}

/// Writes a sequence's MP4 (`sequence.mp4`), pose sidecar (`poses.jsonl`) and truth file (`truth.jsonl`, one
/// JSON line per frame); `multi-face --write-sequence` uses it too.
pub(crate) struct SequenceExport {
    video: holoface_sources::video::Mp4Writer,
    poses: holoface_sources::output::Output,
    truth: holoface_sources::output::Output,
}

impl SequenceExport {
    pub(crate) fn create(dir: &std::path::Path, fps: f64) -> anyhow::Result<Self> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let file =
            |name: &str| holoface_sources::output::Output::create(&dir.join(name), crate::cli::temporaries());
        Ok(Self {
            video: holoface_sources::video::Mp4Writer::create(
                &dir.join("sequence.mp4"),
                FRAME_W,
                FRAME_H,
                fps.round() as u32,
                crate::cli::temporaries(),
            )?,
            poses: file("poses.jsonl")?,
            truth: file("truth.jsonl")?,
        })
    }

    /// Frame `i`: the image, the camera pose, and the frame's truth line.
    pub(crate) fn push(
        &mut self,
        i: usize,
        t_us: u64,
        image: &GrayImage,
        cam: &Pose,
        truth: &serde_json::Value,
    ) -> anyhow::Result<()> {
        self.video.push(image)?;
        holoface_sources::poses::write_line(&mut self.poses, i, cam, Some(&SCENE_CAMERA), Some(t_us))?;
        serde_json::to_writer(&mut self.truth, truth)?;
        self.truth.write_all(b"\n")?;
        Ok(())
    }

    /// The video first: when it fails, the sidecar and the truth are not committed either.
    pub(crate) fn finish(self) -> anyhow::Result<u64> {
        let frames = self.video.finish()?;
        self.poses.commit()?;
        self.truth.commit()?;
        Ok(frames)
    }
}

/// Renders `frames` frames of one face's sequence (the headset and the head moving as `motion` says) and
/// steps every runner's tracker through them, tallying against the rendered truth; `export` also writes the
/// sequence. Computes only (the tallies are the runners').
fn run_sequence(
    runners: &mut [Runner],
    scene: &PlanarScene,
    motion: &Motion,
    frames: usize,
    fps: f64,
    image: &mut GrayImage,
    mut export: Option<&mut SequenceExport>,
) -> anyhow::Result<()> {
    for i in 0..frames {
        let t = i as f64 / fps;
        let cam = motion.headset(t);
        let h = scene.homography(&SCENE_CAMERA, &cam, &motion.head(t));
        scene.render(&h, image, 90)?;
        let truth = scene.landmarks_in(&h);
        let t_us = (t * 1e6).round() as u64;
        let frame = Frame {
            timestamp_us: t_us,
            image: image.view(),
            intrinsics: SCENE_CAMERA,
            world_from_camera: cam,
        };
        for r in runners.iter_mut() {
            r.step(&frame, &truth)?;
        }
        if let Some(e) = export.as_deref_mut() {
            let lm: Vec<[f32; 2]> = truth.iter().map(|p| [p.x, p.y]).collect();
            e.push(i, t_us, image, &cam, &json!({"frame": i, "landmarks_px": lm}))?;
        }
    }
    Ok(())
}

/// Prints the compensated / uncompensated table of a report.
fn say_summary(report: &serde_json::Value) {
    crate::say!("\n{:<26} {:>10} {:>14}", "", "compensated", "uncompensated");
    for key in [
        "losses",
        "losses_per_minute",
        "good_frames_pct",
        "drifting_frames_pct",
        "no_face_frames_pct",
        "detector_runs",
        "mean_nme49_pct",
        "raw_mean_nme49_pct",
        "lag_frames",
        "raw_lag_frames",
    ] {
        let f = |v: &serde_json::Value| v[key].as_f64().unwrap_or(f64::NAN);
        crate::say!(
            "{key:<26} {:>10.2} {:>14.2}",
            f(&report["motion_compensated"]),
            f(&report["uncompensated"])
        );
    }
}

/// Runs `holoface tracking-losses`.
pub fn run(args: Args) -> anyhow::Result<()> {
    let positive = |v: f64| v.is_finite() && v > 0.0;
    if args.faces == 0 || !positive(args.seconds) || !positive(args.fps) || !positive(args.headset_period_s) {
        bail!("--faces, --seconds, --fps and --headset-period-s must be positive");
    }
    let root = faces68_or(args.data.as_deref());
    let samples = load_folder(&root, Split::Validation, true)?;
    if args.aligner == AlignerKind::Remote {
        bail!("tracking-losses measures an aligner in-process: --aligner krfws or dan")
    }
    let mut runners = Vec::new();
    for compensate in [true, false] {
        let opts = SessionOptions {
            motion_compensation: compensate,
            steady: args.steady.settings(),
            ..SessionOptions::default()
        };
        let opts = args.runtime.tracker_options(&args.candide, opts);
        let tracker = match args.aligner {
            AlignerKind::Dan => crate::args::tracker_with(&opts, args.runtime.dan_aligner()?.boxed(), None)?,
            _ => crate::args::tracker(opts)?,
        };
        runners.push(Runner {
            tracker,
            tally: Tally::default(),
        });
    }
    let frames = (args.seconds * args.fps).round() as usize;
    let mut image = GrayImage::zeros(FRAME_W, FRAME_H);
    let mut export = match &args.write_sequence {
        Some(dir) => Some(SequenceExport::create(dir, args.fps)?),
        None => None,
    };
    let mut per_face = Vec::new();
    for (n, sample) in samples.iter().take(args.faces).enumerate() {
        let Some(lm) = sample.landmarks else { continue };
        let (photo, lm) = cut_face(&sample.image, &lm).with_context(|| sample.name.clone())?;
        let scene = PlanarScene::life_size(photo, lm).with_context(|| sample.name.clone())?;
        let motion = Motion {
            yaw: args.headset_yaw_deg,
            period: args.headset_period_s,
            phase: 0.37 * n as f64,
        };
        let before: Vec<Tally> = runners.iter().map(|r| r.tally.clone()).collect();
        for r in &mut runners {
            r.tracker.reset();
            r.tally.was_good = false;
            r.tally.prev_truth = None;
        }
        let export_this = if n == 0 { export.as_mut() } else { None };
        run_sequence(
            &mut runners,
            &scene,
            &motion,
            frames,
            args.fps,
            &mut image,
            export_this,
        )?;
        if n == 0
            && let Some(e) = export.take()
        {
            let written = e.finish()?;
            if let Some(dir) = &args.write_sequence {
                crate::say!("wrote {written} frames of {} to {}", sample.name, dir.display());
            }
        }
        let losses: Vec<usize> = runners
            .iter()
            .zip(&before)
            .map(|(r, b)| r.tally.losses - b.losses)
            .collect();
        crate::say!(
            "{:>3} {:<28} losses: compensated {:>3}, uncompensated {:>3}",
            n + 1,
            sample.name,
            losses[0],
            losses[1]
        );
        per_face.push(
            json!({"face": sample.name, "losses_compensated": losses[0], "losses_uncompensated": losses[1]}),
        );
    }
    let report = json!({
        "aligner": format!("{:?}", args.aligner).to_lowercase(),
        "faces": per_face.len(),
        "seconds_per_face": args.seconds,
        "fps": args.fps,
        "headset_yaw_deg": args.headset_yaw_deg,
        "headset_period_s": args.headset_period_s,
        "motion_compensated": runners[0].tally.summary(args.fps),
        "uncompensated": runners[1].tally.summary(args.fps),
        "per_face": per_face,
    });
    say_summary(&report);
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    crate::cli::write_atomic(&args.out, &serde_json::to_vec_pretty(&report)?)?;
    crate::say!("wrote {}", args.out.display());
    Ok(())
}
