//! `holoface multi-face`: several faces at once, measured against the truth on rendered scenes.
//!
//! A scene holds N validation faces (never trained on), each cut out of its photo and hung as a flat,
//! life-size picture (`render.rs`) at its own place, depth and motion (a head's slow turns and sway), all
//! seen by the wearer's headset camera, which turns and sways too. Pictures are drawn far to near, so a
//! nearer one covers a farther one where they overlap; every frame is the exact homography of each photo,
//! so every face's true landmarks are known in every frame.
//!
//! One tracker session (`max_faces = N`) runs over the scene. Per frame, its faces are matched to the true
//! faces (smallest NME49 first, each truth at most once, a match only below NME49 0.25). Per true face:
//! * **NME49** over the frames it is matched, against the **same face tracked alone**: the same frames
//!   rendered with only that picture, one single-face session;
//! * **id switches**: the face, matched to track a in the previous frame, is now matched to track b != a, or
//!   to a track last matched to another face (a swap);
//! * **losses**: matched in the previous frame, not in this one (its track was rejected or wandered off);
//! * **reacquisitions**: back after a loss under a new track id (ids are never reused);
//!
//! and per scene the most tracks at once, the distinct track ids and the detector runs.

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args as ClapArgs;
use holoface_models::accuracy::nme49;
use holoface_models::geometry::Point2;
use holoface_models::image::GrayImage;
use holoface_models::math3::{Mat3, Pose, Vec3};
use holoface_models::shape::dan_mean_shape;
use serde_json::json;

use super::tracking_losses::{FRAME_H, FRAME_W};
use super::tracking_losses::{SequenceExport, cut_face_with_margin};
use crate::args::{AlignerKind, RuntimeArgs};
use crate::render::{PlanarScene, SCENE_CAMERA};
use holoface_harness::data::{Split, faces68_or, load_folder};
use holoface_runtime::align::Aligner;
use holoface_runtime::frame::Frame;
use holoface_runtime::{FaceResult, SessionOptions};

/// Arguments of `holoface multi-face`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// Annotated faces (`NAME.jpg` + `NAME.pts`); the validation split is used.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Scenes to run: the number of faces in each.
    #[arg(long, value_delimiter = ',', default_value = "1,2,3,5")]
    pub counts: Vec<usize>,
    /// Frames per scene.
    #[arg(long, default_value_t = 300)]
    pub frames: usize,
    /// Frame rate.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Headset yaw amplitude, degrees.
    #[arg(long, default_value_t = 4.0)]
    pub headset_yaw_deg: f64,
    /// While fewer than N faces are tracked, run the detector every this many frames.
    #[arg(long, default_value_t = holoface_runtime::defaults::DETECT_EVERY)]
    pub detect_every: u32,
    /// Horizontal spacing of the pictures' rest positions, centimetres. At the default the pictures touch
    /// and their motion makes them cover each other at times; five fill the 640-px view.
    #[arg(long, default_value_t = 17.0)]
    pub spacing_cm: f64,
    /// Aligner.
    #[arg(long, value_enum, default_value = "krfws")]
    pub aligner: AlignerKind,
    /// CANDIDE-3 model.
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
    /// JSON report.
    #[arg(long, default_value = "runs/multi-face.json")]
    pub out: PathBuf,
    /// Also write the first scene as `sequence.mp4` (H.264), `poses.jsonl` (the sidecar `holoface track
    /// --poses` reads) and `truth.jsonl` (every face's true landmarks per frame) into this folder.
    #[arg(long)]
    pub write_sequence: Option<PathBuf>,
    /// Also draw each scene's first frame with the tracked faces and their ids (`scene_N.png`) here.
    #[arg(long)]
    pub snapshots: Option<PathBuf>,
    /// With `--aligner remote`: how long a frame waits for the server's replies before KRFWS answers the
    /// faces it missed, ms.
    #[arg(long, default_value_t = holoface_runtime::defaults::DEADLINE_MS)]
    pub deadline_ms: u64,
    /// Deliver frames at `--fps`, as a live camera does (otherwise as fast as they are processed).
    #[arg(long)]
    pub realtime: bool,
    /// With `--aligner remote`: ONNX Runtime threads of the in-process server.
    #[arg(long, default_value_t = 2)]
    pub server_threads: usize,
    /// Runtime assets.
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

/// Largest scene: five pictures side by side fill the 640-px view at the default spacing and this depth. The depth
/// keeps every face about 95 px wide, which the detector (BlazeFace short range, the frame letterboxed into
/// 128 px) still finds; farther faces are below its smallest anchor.
const MAX_FACES: usize = 5;
/// Depth of the nearest picture, metres; the others step back by `DEPTH_STEP_M` each.
const NEAR_M: f64 = 0.74;
const DEPTH_STEP_M: f64 = 0.03;
/// Each picture is the face's landmark box grown by this fraction of its size on every side.
const PICTURE_MARGIN: f32 = 0.15;
/// Faces used: near-frontal (the nose tip within this fraction of the eye distance from the eyes'
/// midpoint, horizontally) and sharp enough (at least `MIN_EYE_PX` between the eye centres in the photo).
const MAX_NOSE_OFFSET: f32 = 0.12;
const MIN_EYE_PX: f32 = 40.0;
/// A tracked face further than this (NME49) from every unmatched true face matches none.
const MATCH_NME: f64 = 0.25;

/// One picture of a scene and its motion.
struct Person {
    name: String,
    scene: PlanarScene,
    rest: Vec3,
    phase: f64,
}

impl Person {
    fn pose(&self, t: f64) -> Pose {
        let tau = std::f64::consts::TAU;
        let s = t + self.phase;
        Pose {
            rotation: Mat3::rot_y(12f64.to_radians() * (tau * s / 5.0).sin())
                * Mat3::rot_x(6f64.to_radians() * (tau * s / 4.0 + 0.5).sin())
                * Mat3::rot_z(6f64.to_radians() * (tau * s / 4.5).sin()),
            translation: self.rest
                + Vec3::new(
                    0.03 * (tau * s / 6.0).sin(),
                    0.02 * (tau * s / 5.0).sin(),
                    0.03 * (tau * s / 7.0).sin(),
                ),
        }
    }
}

fn headset(yaw_deg: f64, t: f64) -> Pose {
    let w = std::f64::consts::TAU / 3.0;
    Pose {
        rotation: Mat3::rot_y(yaw_deg.to_radians() * (w * t).sin())
            * Mat3::rot_x((0.5 * yaw_deg).to_radians() * (0.7 * w * t + 1.0).sin()),
        translation: Vec3::new(0.02 * (0.5 * w * t).sin(), 0.015 * (0.6 * w * t).sin(), 0.0),
    }
}

/// Per true face.
#[derive(Debug, Default, Clone)]
struct FaceTally {
    frames: usize,
    matched: usize,
    nme_sum: f64,
    losses: usize,
    id_switches: usize,
    reacquisitions: usize,
    last_id: Option<u32>,
    matched_before: bool,
    /// Per frame: NME49 of the face's match (none when unmatched) and the share of its 68 true landmarks
    /// that a nearer picture covers.
    per_frame: Vec<(Option<f64>, f64)>,
}

impl FaceTally {
    /// One frame: `matched` is the track id and NME49 of the face's match, `owner` says which true face a
    /// track id was last matched to (to tell a swap from a new track).
    fn record(
        &mut self,
        me: usize,
        matched: Option<(u32, f64)>,
        covered: f64,
        owner: &mut std::collections::HashMap<u32, usize>,
    ) {
        self.frames += 1;
        self.per_frame.push((matched.map(|m| m.1), covered));
        match matched {
            Some((id, e)) => {
                self.matched += 1;
                self.nme_sum += e;
                let other_face = owner.get(&id).is_some_and(|&f| f != me);
                if self.last_id.is_some_and(|last| last != id) {
                    if self.matched_before || other_face {
                        self.id_switches += 1;
                    } else {
                        self.reacquisitions += 1;
                    }
                } else if other_face {
                    self.id_switches += 1;
                }
                owner.insert(id, me);
                self.last_id = Some(id);
            }
            None if self.matched_before => self.losses += 1,
            None => {}
        }
        self.matched_before = matched.is_some();
    }

    fn nme_pct(&self) -> f64 {
        100.0 * self.nme_sum / self.matched.max(1) as f64
    }

    /// Mean share of the face's landmarks covered by nearer pictures, percent.
    fn covered_pct(&self) -> f64 {
        100.0 * self.per_frame.iter().map(|f| f.1).sum::<f64>() / self.frames.max(1) as f64
    }

    /// NME49 (percent) here and in `alone` over the frames where nothing covers the face here and it is
    /// matched in both runs, and how many such frames there are: the several-face tracker against the
    /// single-face one with occlusion, which no tracker undoes, taken out.
    fn uncovered_vs(&self, alone: &Self) -> (f64, f64, usize) {
        let (mut here, mut there, mut n) = (0.0, 0.0, 0usize);
        for (&(a, covered), &(b, _)) in self.per_frame.iter().zip(&alone.per_frame) {
            if let (Some(a), Some(b), true) = (a, b, covered == 0.0) {
                here += a;
                there += b;
                n += 1;
            }
        }
        let pct = |sum: f64| 100.0 * sum / n.max(1) as f64;
        (pct(here), pct(there), n)
    }
}

/// Greedy matching of tracked faces to true faces (smallest NME49 first, each at most once).
fn match_faces(faces: &[FaceResult], truths: &[[Point2; 68]]) -> Vec<Option<(u32, f64)>> {
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (i, f) in faces.iter().enumerate() {
        for (j, t) in truths.iter().enumerate() {
            if let Some(e) = nme49(&f.landmarks, t).filter(|e| e.is_finite() && *e < MATCH_NME) {
                pairs.push((e, i, j));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut out = vec![None; truths.len()];
    let mut used = vec![false; faces.len()];
    for (e, i, j) in pairs {
        if !used[i] && out[j].is_none() {
            used[i] = true;
            out[j] = Some((faces[i].id, e));
        }
    }
    out
}

/// Renders frame `i` of a scene with the pictures `which` (far to near) and returns, for every person,
/// the true landmarks and the share of them that nearer pictures cover (0 for those not in `which`).
fn render(
    people: &[Person],
    which: &[usize],
    cam: &Pose,
    t: f64,
    image: &mut GrayImage,
) -> anyhow::Result<Vec<([Point2; 68], f64)>> {
    image.as_bytes_mut().fill(90);
    let mut order: Vec<usize> = which.to_vec();
    order.sort_by(|&a, &b| people[b].rest.z.total_cmp(&people[a].rest.z));
    let mut truths = vec![([Point2::default(); 68], 0.0); people.len()];
    let mut drawn = Vec::with_capacity(order.len());
    for &k in &order {
        let p = &people[k];
        let h = p.scene.homography(&SCENE_CAMERA, cam, &p.pose(t));
        p.scene.render_over(&h, image)?;
        truths[k].0 = p.scene.landmarks_in(&h);
        drawn.push((k, h));
    }
    for (i, (k, _)) in drawn.iter().enumerate() {
        let nearer = &drawn[i + 1..];
        let covered = truths[*k]
            .0
            .iter()
            .filter(|&&q| nearer.iter().any(|(j, h)| people[*j].scene.covers(h, q)))
            .count();
        truths[*k].1 = covered as f64 / 68.0;
    }
    Ok(truths)
}

struct Run {
    tallies: Vec<FaceTally>,
    ids: std::collections::BTreeSet<u32>,
    most_at_once: usize,
    detector_runs: usize,
    /// Per frame: time from the frame's arrival to its answer (prepare + align + complete), ms.
    frame_ms: Vec<f64>,
    /// Faces aligned, and how many of them the server answered.
    aligned: usize,
    remote: usize,
}

impl Run {
    /// The frame-time and remote-share summary of this run.
    fn timing_json(&self) -> serde_json::Value {
        json!({
            "frames_answered": self.frame_ms.len(),
            "frame_ms_p50": crate::stats::percentile(&self.frame_ms, 0.5),
            "frame_ms_p99": crate::stats::percentile(&self.frame_ms, 0.99),
            "frame_ms_max": crate::stats::percentile(&self.frame_ms, 1.0),
            "faces_aligned": self.aligned,
            "faces_answered_remote_pct": 100.0 * self.remote as f64 / self.aligned.max(1) as f64,
        })
    }
}

/// Tracks one rendered sequence of `which` (with `max_faces` = its size) and tallies the faces in it; hands the
/// aligner back for the next sequence.
fn track(
    args: &Args,
    aligner: Box<dyn Aligner + Send>,
    people: &[Person],
    which: &[usize],
    mut export: Option<&mut SequenceExport>,
) -> anyhow::Result<(Run, Box<dyn Aligner + Send>)> {
    let session = SessionOptions {
        max_faces: which.len(),
        detect_every: args.detect_every,
        ..SessionOptions::default()
    };
    let mut opts = args.runtime.tracker_options(&args.candide, session);
    // The same detector for the scene and for each face alone: the several-face settings.
    opts.detector.several_faces = Some(true);
    let mut tracker = crate::args::tracker_with(&opts, aligner, None)?;
    let mut image = GrayImage::zeros(FRAME_W, FRAME_H);
    let mut run = Run {
        tallies: vec![FaceTally::default(); which.len()],
        ids: std::collections::BTreeSet::new(),
        most_at_once: 0,
        detector_runs: 0,
        frame_ms: Vec::with_capacity(args.frames),
        aligned: 0,
        remote: 0,
    };
    let mut owner = std::collections::HashMap::new();
    let start = std::time::Instant::now();
    for i in 0..args.frames {
        let t = i as f64 / args.fps;
        if args.realtime
            && let Some(wait) = (start + std::time::Duration::from_secs_f64(t))
                .checked_duration_since(std::time::Instant::now())
        {
            std::thread::sleep(wait);
        }
        let cam = headset(args.headset_yaw_deg, t);
        let all = render(people, which, &cam, t, &mut image)?;
        let truths: Vec<[Point2; 68]> = which.iter().map(|&k| all[k].0).collect();
        let frame = Frame {
            timestamp_us: (t * 1e6).round() as u64,
            image: image.view(),
            intrinsics: SCENE_CAMERA,
            world_from_camera: cam,
        };
        if let Some(e) = export.as_deref_mut() {
            let faces: Vec<Vec<[f32; 2]>> = truths
                .iter()
                .map(|lm| lm.iter().map(|p| [p.x, p.y]).collect())
                .collect();
            e.push(
                i,
                frame.timestamp_us,
                &image,
                &cam,
                &json!({"frame": i, "faces_landmarks_px": faces}),
            )?;
        }
        let step = tracker.process_step(&frame)?;
        let timings = &step.timings;
        run.frame_ms
            .push((timings.prepare + timings.align + timings.complete).as_secs_f64() * 1e3);
        for a in step.alignments.iter().flatten() {
            run.aligned += 1;
            run.remote += usize::from(a.answered_by == holoface_runtime::align::AnsweredBy::RemoteDan);
        }
        if let Some(dir) = args
            .snapshots
            .as_ref()
            .filter(|_| i + 1 == args.frames.min(30) && which.len() > 1)
        {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            let canvas = crate::annotate::annotate(
                &image,
                i,
                &step.faces.faces,
                step.faces.no_face_reason(),
                tracker.face_model(),
                &SCENE_CAMERA,
            );
            let path = dir.join(format!("scene_{}.png", which.len()));
            crate::cli::write_atomic(&path, canvas.to_png())?;
        }
        run.detector_runs += usize::from(step.detected);
        run.ids.extend(step.faces.faces.iter().map(|f| f.id));
        run.most_at_once = run.most_at_once.max(step.faces.faces.len());
        let matches = match_faces(&step.faces.faces, &truths);
        for (k, (tally, m)) in run.tallies.iter_mut().zip(matches).enumerate() {
            tally.record(k, m, all[which[k]].1, &mut owner);
        }
    }
    Ok((run, tracker.into_aligner()))
}

/// Runs `holoface multi-face`.
pub fn run(args: Args) -> anyhow::Result<()> {
    if args.counts.is_empty() || args.counts.iter().any(|&n| n == 0 || n > MAX_FACES) {
        bail!("--counts: each scene holds 1..={MAX_FACES} faces");
    }
    if args.frames == 0 || !(args.fps.is_finite() && args.fps > 0.0) {
        bail!("--frames and --fps must be positive");
    }
    if !(args.spacing_cm.is_finite() && (0.0..=100.0).contains(&args.spacing_cm)) {
        bail!("--spacing-cm must be within 0..=100");
    }
    let root = faces68_or(args.data.as_deref());
    let samples = load_folder(&root, Split::Validation, true)?;
    let mut server = None;
    let mut aligner: Box<dyn Aligner + Send> = match args.aligner {
        AlignerKind::Krfws => Box::new(args.runtime.krfws_aligner()?),
        AlignerKind::Dan => Box::new(args.runtime.dan_aligner()?),
        AlignerKind::Remote => {
            let (s, a) = remote_aligner(&args)?;
            server = Some(s);
            Box::new(a)
        }
    };
    let mut scenes = Vec::new();
    crate::say!(
        "{:>5} {:>9} {:>8} {:>11} {:>9} {:>6} {:>10}   per face: NME49 % together / alone (relative)",
        "faces",
        "at once",
        "ids",
        "id switches",
        "detector",
        "losses",
        "reacquired"
    );
    for &n in &args.counts {
        let people = scene_people(&samples, n, args.spacing_cm)?;
        let all: Vec<usize> = (0..n).collect();
        let mut export = match args.write_sequence.as_deref() {
            Some(dir) if scenes.is_empty() => Some(SequenceExport::create(dir, args.fps)?),
            _ => None,
        };
        let (together, back) = track(&args, aligner, &people, &all, export.as_mut())?;
        aligner = back;
        if let (Some(e), Some(dir)) = (export, args.write_sequence.as_deref()) {
            crate::say!(
                "wrote {} frames of the {n}-face scene to {}",
                e.finish()?,
                dir.display()
            );
        }
        let (back, alone) = each_face_alone(&args, aligner, &people, &together)?;
        aligner = back;
        let AloneVsTogether {
            per_face,
            line,
            covered_line,
        } = alone;
        let sum = |f: fn(&FaceTally) -> usize| together.tallies.iter().map(f).sum::<usize>();
        let (switches, losses, reacquired) = (
            sum(|t| t.id_switches),
            sum(|t| t.losses),
            sum(|t| t.reacquisitions),
        );
        crate::say!(
            "{n:>5} {:>9} {:>8} {switches:>11} {:>9} {losses:>6} {reacquired:>10} {line}",
            together.most_at_once,
            together.ids.len(),
            together.detector_runs
        );
        crate::say!("      per face:{covered_line}");
        let timing = together.timing_json();
        crate::say!(
            "      frames answered {}/{}, frame time p50 {:.1} ms, p99 {:.1} ms, faces answered by the server {:.1} %",
            together.frame_ms.len(),
            args.frames,
            timing["frame_ms_p50"].as_f64().unwrap_or(f64::NAN),
            timing["frame_ms_p99"].as_f64().unwrap_or(f64::NAN),
            timing["faces_answered_remote_pct"].as_f64().unwrap_or(f64::NAN),
        );
        scenes.push(json!({
            "faces": n,
            "frames": args.frames,
            "tracks_at_once": together.most_at_once,
            "track_ids": together.ids.len(),
            "id_switches": switches,
            "detector_runs": together.detector_runs,
            "losses": losses,
            "reacquisitions": reacquired,
            "timing": timing,
            "per_face": per_face,
        }));
    }
    drop(aligner);
    if let Some(server) = server {
        server.stop();
    }
    let report = json!({
        "aligner": format!("{:?}", args.aligner).to_lowercase(),
        "fps": args.fps,
        "headset_yaw_deg": args.headset_yaw_deg,
        "detect_every": args.detect_every,
        "spacing_cm": args.spacing_cm,
        "realtime": args.realtime,
        "deadline_ms": (args.aligner == AlignerKind::Remote).then_some(args.deadline_ms),
        "scenes": scenes,
    });
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    crate::cli::write_atomic(&args.out, &serde_json::to_vec_pretty(&report)?)?;
    crate::say!("wrote {}", args.out.display());
    Ok(())
}

/// The first `n` near-frontal validation faces as life-size pictures, `spacing_cm` apart side by side and
/// staggered in depth.
fn scene_people(
    samples: &[holoface_harness::data::Sample],
    n: usize,
    spacing_cm: f64,
) -> anyhow::Result<Vec<Person>> {
    let mut people = Vec::with_capacity(n);
    let usable = samples
        .iter()
        .filter(|s| s.landmarks.as_ref().is_some_and(near_frontal));
    for (k, sample) in usable.take(n).enumerate() {
        let Some(lm) = sample.landmarks else { continue };
        let (photo, lm) =
            cut_face_with_margin(&sample.image, &lm, PICTURE_MARGIN).with_context(|| sample.name.clone())?;
        let x = (k as f64 - (n as f64 - 1.0) / 2.0) * spacing_cm / 100.0;
        people.push(Person {
            name: sample.name.clone(),
            scene: PlanarScene::life_size(photo, lm).with_context(|| sample.name.clone())?,
            rest: Vec3::new(x, 0.0, NEAR_M + DEPTH_STEP_M * k as f64),
            phase: 1.3 * k as f64,
        });
    }
    if people.len() < n {
        bail!(
            "{} near-frontal validation faces, the scene needs {n}",
            people.len()
        );
    }
    Ok(people)
}

/// Each face of a scene tracked alone, against how it fared together: per face, the JSON report, and the two
/// printed lines (NME together / alone, landmarks covered).
struct AloneVsTogether {
    per_face: Vec<serde_json::Value>,
    line: String,
    covered_line: String,
}

/// Each face of the scene tracked alone, against how it fared `together`; hands the aligner back.
fn each_face_alone(
    args: &Args,
    mut aligner: Box<dyn Aligner + Send>,
    people: &[Person],
    together: &Run,
) -> anyhow::Result<(Box<dyn Aligner + Send>, AloneVsTogether)> {
    let mut per_face = Vec::new();
    let mut line = String::new();
    let mut covered_line = String::new();
    for (k, tally) in together.tallies.iter().enumerate() {
        let (alone, back) = track(args, aligner, people, &[k], None)?;
        aligner = back;
        let solo = &alone.tallies[0];
        let rel = together_vs_alone(tally.nme_pct(), solo.nme_pct());
        let (clear, clear_alone, clear_frames) = tally.uncovered_vs(solo);
        line.push_str(&format!(
            "  {:.2}/{:.2} ({:+.1} %)",
            tally.nme_pct(),
            solo.nme_pct(),
            rel
        ));
        covered_line.push_str(&format!(
            "  {:.0} % covered, uncovered {clear_frames} frames {clear:.2}/{clear_alone:.2} ({:+.1} %)",
            tally.covered_pct(),
            together_vs_alone(clear, clear_alone)
        ));
        per_face.push(json!({
            "face": people[k].name,
            "nme49_pct": tally.nme_pct(),
            "nme49_alone_pct": solo.nme_pct(),
            "nme49_relative_change_pct": rel,
            "tracked_frames_pct": 100.0 * tally.matched as f64 / tally.frames.max(1) as f64,
            "covered_landmarks_pct": tally.covered_pct(),
            "uncovered_frames_matched_both": clear_frames,
            "nme49_uncovered_pct": clear,
            "nme49_uncovered_alone_pct": clear_alone,
            "nme49_uncovered_relative_change_pct": together_vs_alone(clear, clear_alone),
            "tracked_frames_alone_pct": 100.0 * solo.matched as f64 / solo.frames.max(1) as f64,
            "id_switches": tally.id_switches,
            "losses": tally.losses,
            "losses_alone": solo.losses,
            "reacquisitions": tally.reacquisitions,
        }));
    }
    Ok((
        aligner,
        AloneVsTogether {
            per_face,
            line,
            covered_line,
        },
    ))
}

/// The in-process server and the headset's remote aligner (KRFWS for what the server misses), connected
/// and past its start-up hold-off (probes must answer for a second before frames go remote), so the scenes
/// measure the remote path from their first frame.
fn remote_aligner(
    args: &Args,
) -> anyhow::Result<(
    crate::loopback::LoopbackServer,
    holoface_runtime::link::LinkedAligner<holoface_runtime::align::KrfwsAligner>,
)> {
    use holoface_runtime::link::{Mode, RemoteOptions};
    let server = crate::loopback::LoopbackServer::start(&args.runtime, args.server_threads, |_| {})?;
    let mut remote = RemoteOptions::new(server.addr, server.fingerprint, server.token.clone());
    remote.client_name = "holoface-multi-face".into();
    remote.deadline = std::time::Duration::from_millis(args.deadline_ms);
    // One crop per face per frame in flight.
    let max_faces = args.counts.iter().copied().max().unwrap_or(1);
    let mut aligner =
        holoface_runtime::link::LinkedAligner::start(&remote, args.runtime.krfws_aligner()?, max_faces)?;
    let blank = GrayImage::zeros(FRAME_W, FRAME_H);
    let init = dan_mean_shape().map(|p| Point2::new(p.x + 260.0, p.y + 180.0));
    let give_up = std::time::Instant::now() + std::time::Duration::from_secs(10);
    while aligner.policy().mode() != Mode::Remote {
        if std::time::Instant::now() > give_up {
            bail!(
                "the loopback server did not answer in time: {:?}",
                aligner.link().status()
            );
        }
        aligner.align(&blank.view(), &init)?;
        std::thread::sleep(std::time::Duration::from_millis(33));
    }
    Ok((server, aligner))
}

/// See [`MAX_NOSE_OFFSET`] and [`MIN_EYE_PX`].
fn near_frontal(lm: &[Point2; 68]) -> bool {
    let c = |r: std::ops::Range<usize>| holoface_models::geometry::centroid(&lm[r]);
    let (l, r) = (c(36..42), c(42..48));
    let eyes = l.dist(r);
    eyes >= MIN_EYE_PX && (lm[30].x - 0.5 * (l.x + r.x)).abs() <= MAX_NOSE_OFFSET * eyes
}

/// NME49 together relative to alone, percent (0 when both are 0).
fn together_vs_alone(together: f64, alone: f64) -> f64 {
    if alone > 0.0 {
        100.0 * (together / alone - 1.0)
    } else {
        0.0
    }
}
