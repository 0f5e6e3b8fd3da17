//! `holoface train-refiner`: trains the server's refinement cascade (`holoface_models::refine`) on DAN's
//! real answers.
//!
//! For every training face (never the validation split) and its mirror image it builds several crops the
//! way a headset does (the similarity that maps an initial shape onto the mean shape, bilinear, 112 px),
//! from the starts a headset has: the detector's placement, the tracker's previous landmarks (the truth
//! with alignment noise and a small motion), and larger misplacements; some crops are blurred, some
//! partly occluded, some change brightness and contrast. Each crop then takes the server's path: JPEG q75
//! encode and decode, DAN through ONNX Runtime. DAN's landmarks on the decoded crop are where the cascade
//! starts, the annotation mapped into the crop is where it must go. Crops DAN rejects (face probability
//! below the model's threshold) are left out, as the server does not refine them.
//!
//! DAN's answers are cached (`--cache`, keyed by the DAN model's checksum and the sampling settings), so
//! the cascade can be retrained without running DAN again. The trained model is checked on the validation
//! split with the detector's start (`holoface eval`'s protocol) and a JSON report goes beside it.

use std::io::{BufReader, BufWriter, Read, Write as _};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail};
use holoface_inference::{BatchTensor, InferenceEngine, LandmarkOut, OnnxEngine, OnnxOptions};
use holoface_models::GrayView;
use holoface_models::accuracy::{nme49, nme68, summarise};
use holoface_models::crop::{CROP_SIZE, warp_bilinear};
use holoface_models::geometry::{Point2, Rect, Similarity2, centroid};
use holoface_models::refine::train::{RefineConfig, RefineSample, borrowed_error_starts, train};
use holoface_models::refine::{RefineCascade, RefineScratch, Sampling};
use holoface_models::rng::Rng;
use holoface_models::shape::{dan_mean_shape, fit_to_box, mirror68};
use holoface_runtime::align::crop_from_image;
use holoface_runtime::link::CropCodec;
use serde::Serialize;

use crate::args::RuntimeArgs;
use crate::cli::eval::initial_shape;
use crate::data::{Sample, Split, faces68_or, load_folder};

/// Arguments of `holoface train-refiner`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Annotated face folder; default `$HOLOFACE_DATA/faces68/train`.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Model output; the JSON report goes beside it (`.json`).
    #[arg(long, default_value = "models/assets/refiner.bin")]
    pub out: PathBuf,
    /// DAN's answers on the training crops (reused when the DAN model and the sampling settings match).
    #[arg(long, default_value = "runs/refiner/dan-answers.bin")]
    pub cache: PathBuf,
    /// Crops per face and per mirror image.
    #[arg(long, default_value_t = 6)]
    pub crops: usize,
    /// Side of the refiner's crop as a multiple of the 112-px crop DAN sees (1 or 2): with 2 the refiner
    /// works on a 224-px crop built with the same similarity scaled by 2.
    #[arg(long, default_value_t = 1)]
    pub crop_scale: usize,
    /// Cascade stages.
    #[arg(long, default_value_t = 10)]
    pub stages: usize,
    /// Trees per stage.
    #[arg(long, default_value_t = 500)]
    pub trees: usize,
    /// Tree depth.
    #[arg(long, default_value_t = 4)]
    pub depth: usize,
    /// Feature points per stage.
    #[arg(long, default_value_t = 400)]
    pub features: usize,
    /// Random tests per node.
    #[arg(long, default_value_t = 20)]
    pub split_tests: usize,
    /// Learning rate (shrinkage of every leaf).
    #[arg(long, default_value_t = 0.1)]
    pub learning_rate: f32,
    /// Draw each stage's feature points around the landmarks, in a disc whose radius (crop pixels of the
    /// mean shape) shrinks from the first value to the second over the stages (`--local-radius 8,2`);
    /// default: dlib's pool over the whole face box.
    #[arg(long, value_delimiter = ',')]
    pub local_radius: Option<Vec<f32>>,
    /// The model also refines the mirror image and answers the mean of the two (validation is reported
    /// without and with it).
    #[arg(long)]
    pub mirror: bool,
    /// Bilinear feature reads (sub-pixel: a format v2 model) instead of the nearest pixel.
    #[arg(long)]
    pub bilinear: bool,
    /// Locality prior of the node tests' point pairs (fraction of the mean shape's extent).
    #[arg(long, default_value_t = 0.1)]
    pub lambda: f32,
    /// Starts per crop the model asks for (1..=9; the per-coordinate median of their answers). The
    /// validation is reported for 1 and for this many.
    #[arg(long, default_value_t = 1)]
    pub starts: usize,
    /// Seed of every random choice.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Worker threads for training (the result does not depend on it); `--threads` sets ONNX Runtime's.
    #[arg(long, default_value_t = 2)]
    pub train_threads: usize,
    /// Train on the first N training faces only (smoke runs).
    #[arg(long)]
    pub limit: Option<usize>,
    /// Teacher-label files (`holoface teacher-labels`) whose faces are trained on beside the annotated ones.
    #[arg(long, value_delimiter = ',')]
    pub teacher_labels: Vec<PathBuf>,
    /// Crops per teacher-labelled face and per mirror image (the annotated faces get `--crops`: this ratio
    /// weighs the two kinds of label).
    #[arg(long, default_value_t = 2)]
    pub teacher_crops: usize,
    /// More training starts per crop, each DAN's error on another crop carried over into this face's frame
    /// (`borrowed_error_starts`): the same crops met from several DAN-like starts, against memorising one
    /// correction per crop. 0 = DAN's own start only.
    #[arg(long, default_value_t = 0)]
    pub borrowed_starts: usize,
    /// At most this many faces from each teacher-label file (evenly spaced over it).
    #[arg(long)]
    pub teacher_limit: Option<usize>,
    /// Give each teacher-labelled face `--teacher-crops` times (its pose's share among the annotated faces /
    /// its share among the teacher faces) crops, rounded at random, at most 5 times `--teacher-crops`:
    /// the teacher faces then spread over head turn and tilt as the annotated ones (`pose_bin`), not as
    /// the mostly frontal photo collections.
    #[arg(long)]
    pub teacher_pose_match: bool,
    /// Skip training: validate the model already at `--out` with 1 and with `--starts` starts.
    #[arg(long)]
    pub evaluate: bool,
    /// Version written into the model's name.
    #[arg(long, default_value = "0.1.0")]
    pub version: String,
    #[command(flatten)]
    /// Runtime assets (DAN, detector, ONNX Runtime).
    pub runtime: RuntimeArgs,
}

/// The wire encoding every crop goes through (the client's default).
const WIRE: CropCodec = CropCodec::Jpeg { quality: 75 };
const CACHE_MAGIC: &[u8; 8] = b"HFRDATA2";
const BATCH: usize = 16;

/// One crop with DAN's answer on it.
struct Answered {
    /// The refiner's crop after the JPEG round trip (`(112·scale)²` bytes).
    crop: Vec<u8>,
    /// DAN's landmarks, in the refiner's crop pixels.
    start: [Point2; 68],
    /// Ground truth in the refiner's crop pixels.
    target: [Point2; 68],
}

/// Perturbs `shape` by a random similarity about its centroid: translation σ `t` of its extent,
/// rotation σ `r_deg`, scale σ `s`.
fn perturb(shape: &[Point2; 68], rng: &mut Rng, t: f64, r_deg: f64, s: f64) -> [Point2; 68] {
    let c = centroid(shape);
    let b = Rect::bounding(shape).unwrap_or_default();
    let angle = (rng.normal() * r_deg).to_radians();
    let scale = (1.0 + rng.normal() * s).clamp(0.5, 1.6);
    let (dx, dy) = (
        rng.normal() * t * f64::from(b.width()),
        rng.normal() * t * f64::from(b.height()),
    );
    let (cx, cy) = (f64::from(c.x), f64::from(c.y));
    let rot = Similarity2::from_parts(scale, angle, 0.0, 0.0);
    let m = Similarity2 {
        tx: cx + dx - (rot.a * cx - rot.b * cy),
        ty: cy + dy - (rot.b * cx + rot.a * cy),
        ..rot
    };
    std::array::from_fn(|i| m.apply(shape[i]))
}

/// A tracker's start: the truth with per-point alignment noise (σ 2.5 % of the eye-corner distance,
/// about a good tracker's error), then moved by a small similarity (the headset and head motion that
/// motion compensation leaves).
fn tracker_start(gt: &[Point2; 68], rng: &mut Rng) -> [Point2; 68] {
    let iod = f64::from(gt[36].dist(gt[45])).max(1.0);
    let noisy: [Point2; 68] = std::array::from_fn(|i| {
        Point2::new(
            gt[i].x + (rng.normal() * 0.025 * iod) as f32,
            gt[i].y + (rng.normal() * 0.025 * iod) as f32,
        )
    });
    perturb(&noisy, rng, 0.03, 3.0, 0.03)
}

/// In-place box blur of a square crop (radius 1 or 2), `passes` times.
fn blur(px: &mut [u8], size: usize, radius: usize, passes: usize) {
    let mut tmp = vec![0u8; px.len()];
    for _ in 0..passes {
        for horizontal in [true, false] {
            for y in 0..size {
                for x in 0..size {
                    let (mut sum, mut n) = (0u32, 0u32);
                    for k in x.saturating_sub(radius)..=(x + radius).min(size - 1) {
                        let (xx, yy) = if horizontal { (k, y) } else { (y, k) };
                        sum += u32::from(px[yy * size + xx]);
                        n += 1;
                    }
                    let (ox, oy) = if horizontal { (x, y) } else { (y, x) };
                    tmp[oy * size + ox] = ((sum + n / 2) / n) as u8;
                }
            }
            px.copy_from_slice(&tmp);
        }
    }
}

/// The appearance changes a crop may get: blur, an occluding block, brightness/contrast.
fn augment(px: &mut [u8], size: usize, rng: &mut Rng) {
    if rng.uniform() < 0.3 {
        let gain = 0.7 + 0.6 * rng.uniform();
        let bias = (rng.uniform() - 0.5) * 50.0;
        for p in px.iter_mut() {
            *p = (f64::from(*p) * gain + bias).clamp(0.0, 255.0) as u8;
        }
    }
    if rng.uniform() < 0.25 {
        blur(px, size, 1 + rng.below(2), 1 + rng.below(2));
    }
    if rng.uniform() < 0.2 {
        let w = size * (15 + rng.below(25)) / 100;
        let h = size * (15 + rng.below(25)) / 100;
        let x0 = rng.below(size - w);
        let y0 = rng.below(size - h);
        let level = rng.below(256) as u8;
        let noisy = rng.uniform() < 0.5;
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                px[y * size + x] = if noisy { rng.below(256) as u8 } else { level };
            }
        }
    }
}

/// The JPEG q75 round trip of the wire.
fn wire_round_trip(px: &[u8], size: usize) -> anyhow::Result<Vec<u8>> {
    let side = u16::try_from(size).context("crop too large")?;
    let crop = holoface_runtime::crop_codec::encode(WIRE, px, side, side)?;
    Ok(holoface_inference::decode_crop(&crop)?.to_vec())
}

/// Builds a start's crops: DAN's 112-px crop and the refiner's (the same similarity scaled), both after
/// the wire round trip, with the same appearance change applied to both.
struct CropJob {
    dan_crop: Vec<u8>,
    refiner_crop: Vec<u8>,
    target: [Point2; 68],
}

fn make_crops(
    image: &GrayView<'_>,
    mean: &[Point2; 68],
    init: &[Point2; 68],
    gt: &[Point2; 68],
    scale: usize,
    rng: Option<&mut Rng>,
) -> anyhow::Result<CropJob> {
    let sim = crop_from_image(init, mean)?;
    let big = Similarity2 {
        a: sim.a * scale as f64,
        b: sim.b * scale as f64,
        tx: sim.tx * scale as f64,
        ty: sim.ty * scale as f64,
    };
    let size = CROP_SIZE * scale;
    let mut px = vec![0u8; size * size];
    warp_bilinear(image, &big, size, size, &mut px)?;
    let mut dan = if scale == 1 {
        Vec::new()
    } else {
        let mut d = vec![0u8; CROP_SIZE * CROP_SIZE];
        warp_bilinear(image, &sim, CROP_SIZE, CROP_SIZE, &mut d)?;
        d
    };
    if let Some(rng) = rng {
        // The same change on both crops: one seed, replayed.
        let seed = rng.next_u64();
        augment(&mut px, size, &mut Rng::new(seed));
        if scale != 1 {
            augment(&mut dan, CROP_SIZE, &mut Rng::new(seed));
        }
    }
    let refiner_crop = wire_round_trip(&px, size)?;
    let dan_crop = if scale == 1 {
        refiner_crop.clone()
    } else {
        wire_round_trip(&dan, CROP_SIZE)?
    };
    Ok(CropJob {
        dan_crop,
        refiner_crop,
        target: std::array::from_fn(|i| big.apply(gt[i])),
    })
}

/// Runs DAN on queued crops in batches; keeps the accepted answers.
struct DanRunner {
    engine: OnnxEngine,
    batch: BatchTensor,
    outs: Vec<LandmarkOut>,
    queued: Vec<CropJob>,
    scale: f32,
    threshold: f32,
    answered: Vec<Answered>,
    rejected: usize,
}

impl DanRunner {
    fn push(&mut self, job: CropJob) -> anyhow::Result<()> {
        self.queued.push(job);
        if self.queued.len() == BATCH {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> anyhow::Result<()> {
        self.batch.clear();
        for j in &self.queued {
            self.batch.push(&j.dan_crop)?;
        }
        self.engine.infer(&self.batch, &mut self.outs)?;
        for (j, o) in self.queued.drain(..).zip(&self.outs) {
            if o.problem(68).is_some() || o.face_prob < self.threshold {
                self.rejected += 1;
                continue;
            }
            let s = self.scale;
            self.answered.push(Answered {
                crop: j.refiner_crop,
                start: std::array::from_fn(|i| Point2::new(o.landmarks[i][0] * s, o.landmarks[i][1] * s)),
                target: j.target,
            });
        }
        Ok(())
    }
}

/// The key the cache is valid for.
fn cache_key(dan_model: &Path, args: &Args, faces: usize) -> anyhow::Result<Vec<u8>> {
    let model = std::fs::read(dan_model).with_context(|| format!("reading {}", dan_model.display()))?;
    let mut key = Vec::new();
    key.extend_from_slice(&crc32fast::hash(&model).to_le_bytes());
    for v in [args.crops, args.crop_scale, faces, args.seed as usize] {
        key.extend_from_slice(&(v as u64).to_le_bytes());
    }
    Ok(key)
}

/// What the teacher-labelled crops' cache is valid for: which labels, how many faces, how many crops each.
fn teacher_cache_key(args: &Args, teacher_faces: usize) -> anyhow::Result<Vec<u8>> {
    let mut labels = crc32fast::Hasher::new();
    for path in &args.teacher_labels {
        labels.update(&std::fs::read(path).with_context(|| format!("reading {}", path.display()))?);
    }
    let mut key = Vec::new();
    for v in [
        u64::from(labels.finalize()),
        teacher_faces as u64,
        args.teacher_crops as u64,
        u64::from(args.teacher_pose_match),
    ] {
        key.extend_from_slice(&v.to_le_bytes());
    }
    Ok(key)
}

/// DAN's answers from the cache at `path` when its key matches, else from `make` (then cached).
fn cached_answers(
    path: &Path,
    key: &[u8],
    size: usize,
    runner: &mut DanRunner,
    make: impl FnOnce(&mut DanRunner) -> anyhow::Result<()>,
) -> anyhow::Result<Vec<Answered>> {
    if let Some(a) = read_cache(path, key, size)? {
        tracing::info!(crops = a.len(), cache = %path.display(), "DAN's answers from the cache");
        return Ok(a);
    }
    runner.answered.clear();
    make(runner)?;
    let a = std::mem::take(&mut runner.answered);
    write_cache(path, key, size, &a)?;
    Ok(a)
}

fn write_cache(path: &Path, key: &[u8], size: usize, data: &[Answered]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension("tmp");
    let mut w = BufWriter::new(std::fs::File::create(&tmp)?);
    w.write_all(CACHE_MAGIC)?;
    w.write_all(key)?;
    w.write_all(&(data.len() as u64).to_le_bytes())?;
    for a in data {
        debug_assert_eq!(a.crop.len(), size * size);
        w.write_all(&a.crop)?;
        for p in a.start.iter().chain(&a.target) {
            w.write_all(&p.x.to_le_bytes())?;
            w.write_all(&p.y.to_le_bytes())?;
        }
    }
    w.flush()?;
    drop(w);
    std::fs::rename(&tmp, path)?;
    Ok(())
}

fn read_cache(path: &Path, key: &[u8], size: usize) -> anyhow::Result<Option<Vec<Answered>>> {
    let Ok(f) = std::fs::File::open(path) else {
        return Ok(None);
    };
    let len = f.metadata()?.len();
    let mut r = BufReader::new(f);
    let mut head = vec![0u8; CACHE_MAGIC.len() + key.len() + 8];
    if r.read_exact(&mut head).is_err() || &head[..8] != CACHE_MAGIC || &head[8..8 + key.len()] != key {
        return Ok(None);
    }
    let n = u64::from_le_bytes(head[head.len() - 8..].try_into()?) as usize;
    let rec = size * size + 2 * 68 * 8;
    if (len as usize).saturating_sub(head.len()) != n * rec {
        bail!("{} is truncated; delete it to regenerate", path.display());
    }
    let mut out = Vec::with_capacity(n);
    let mut pts = vec![0u8; 2 * 68 * 8];
    for _ in 0..n {
        let mut crop = vec![0u8; size * size];
        r.read_exact(&mut crop)?;
        r.read_exact(&mut pts)?;
        let f = |i: usize| f32::from_le_bytes([pts[4 * i], pts[4 * i + 1], pts[4 * i + 2], pts[4 * i + 3]]);
        out.push(Answered {
            crop,
            start: std::array::from_fn(|i| Point2::new(f(2 * i), f(2 * i + 1))),
            target: std::array::from_fn(|i| Point2::new(f(136 + 2 * i), f(136 + 2 * i + 1))),
        });
    }
    Ok(Some(out))
}

/// DAN's answers on the augmented crops of `faces` (each face and its mirror, `crops` starts each); the
/// random streams are numbered from `first` (the teacher-labelled faces follow the annotated ones).
/// A face's pose bin: its head turn (the nose tip's offset from the jaw's middle, in jaw widths, 10 bins of
/// 0.05 up to 0.5, either side alike) times its tilt (the eyes' line: under 5, 5-15, over 15 degrees).
fn pose_bin(lm: &[Point2; 68]) -> usize {
    let width = (lm[16].x - lm[0].x).abs().max(1e-3);
    let turn = ((lm[30].x - 0.5 * (lm[0].x + lm[16].x)).abs() / width).min(0.499);
    let eye = |r: std::ops::Range<usize>| centroid(&lm[r]);
    let (l, r) = (eye(36..42), eye(42..48));
    let tilt = (r.y - l.y).atan2(r.x - l.x).abs().to_degrees();
    let tilt = if tilt < 5.0 {
        0
    } else if tilt < 15.0 {
        1
    } else {
        2
    };
    (turn / 0.05) as usize * 3 + tilt
}

/// Crops per teacher face (`--teacher-pose-match`, else `--teacher-crops` each).
fn teacher_crops_per_face(args: &Args, train: &[Sample], teacher: &[Sample]) -> Vec<usize> {
    if args.teacher_pose_match {
        pose_matched_crops(args.teacher_crops, args.seed, train, teacher)
    } else {
        vec![args.teacher_crops; teacher.len()]
    }
}

/// `per_face` crops per teacher face on average, each face's scaled by how much more common its pose bin is
/// among the `train` faces than among the `teacher` ones (at most 5 times), rounded at random.
fn pose_matched_crops(per_face: usize, seed: u64, train: &[Sample], teacher: &[Sample]) -> Vec<usize> {
    let share = |faces: &[Sample]| {
        let mut n = [1.0f64; 30];
        for f in faces.iter().filter_map(|f| f.landmarks.as_ref()) {
            n[pose_bin(f)] += 1.0;
        }
        let total: f64 = n.iter().sum();
        n.map(|v| v / total)
    };
    let (want, have) = (share(train), share(teacher));
    let cap = 5.0 * per_face as f64;
    teacher
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let Some(lm) = f.landmarks.as_ref() else {
                return 0;
            };
            let b = pose_bin(lm);
            let r = (per_face as f64 * want[b] / have[b]).min(cap);
            let mut rng = Rng::stream(seed, &[i as u64, 0x9053]);
            r.floor() as usize + usize::from(rng.uniform() < r.fract())
        })
        .collect()
}

fn answer_training_crops(
    faces: &[Sample],
    crops_per_face: &[usize],
    first: usize,
    args: &Args,
    runner: &mut DanRunner,
    detector: &mut holoface_runtime::detect::BlazeFace,
) -> anyhow::Result<()> {
    let mean = dan_mean_shape();
    for (fi, (face, &crops)) in faces.iter().zip(crops_per_face).enumerate() {
        let fi = first + fi;
        if crops == 0 {
            continue;
        }
        let gt0 = face.landmarks.context("annotation missing")?;
        let mirrored = face.image.mirrored();
        for (side, (img, gt)) in [
            (&face.image, gt0),
            (&mirrored, mirror68(&gt0, face.image.width())),
        ]
        .into_iter()
        .enumerate()
        {
            let view = img.view();
            let detected = initial_shape(Some(detector), &mean, &view, &gt)?;
            let boxed = {
                let mut out = [Point2::default(); 68];
                fit_to_box(&mean, &Rect::bounding(&gt).context("empty annotation")?, &mut out);
                out
            };
            let placed = detected.unwrap_or(boxed);
            for k in 0..crops {
                let mut rng = Rng::stream(args.seed, &[fi as u64, side as u64, k as u64]);
                // Starts cycle through what a headset sends: the detector's placement, a tracker's
                // previous landmarks (twice as often: most frames are tracked), a moved detection, a
                // badly placed box.
                let init = match k % 5 {
                    0 => placed,
                    1 | 3 => tracker_start(&gt, &mut rng),
                    2 => perturb(&placed, &mut rng, 0.05, 5.0, 0.05),
                    _ => perturb(&boxed, &mut rng, 0.1, 10.0, 0.1),
                };
                let augmented = k > 0;
                let job = make_crops(
                    &view,
                    &mean,
                    &init,
                    &gt,
                    args.crop_scale,
                    augmented.then_some(&mut rng),
                )
                .with_context(|| format!("cropping {}", face.name))?;
                runner.push(job)?;
            }
        }
        if (fi + 1).is_multiple_of(200) {
            tracing::info!(
                faces = fi + 1,
                of = first + faces.len(),
                crops = runner.answered.len(),
                "DAN answered"
            );
        }
    }
    runner.flush()
}

#[derive(Debug, Serialize)]
struct ValReport {
    faces: usize,
    detected: usize,
    dan_nme68: f64,
    refined_nme68: f64,
    dan_nme49: f64,
    refined_nme49: f64,
    dan_failure68: f64,
    refined_failure68: f64,
    refine_us_per_crop: f64,
    starts: usize,
    mirror: bool,
}

/// Mean NME68 before and after one stage, on the training samples and on the validation faces.
#[derive(Debug, Serialize)]
struct StageNme {
    train_before: f64,
    train_after: f64,
    validation_before: f64,
    validation_after: f64,
}

#[derive(Debug, Serialize)]
struct Report {
    model: String,
    dan_model: String,
    data: String,
    training_faces: usize,
    teacher_labels: Vec<PathBuf>,
    teacher_faces: usize,
    teacher_crops_per_face: usize,
    teacher_pose_match: bool,
    training_crops: usize,
    /// Starts per crop borrowed from other crops' errors (`--borrowed-starts`).
    borrowed_starts_per_crop: usize,
    /// Crops times starts: what the cascade is trained on.
    training_samples: usize,
    rejected_crops: usize,
    crop_size: usize,
    crops_per_face: usize,
    stages: usize,
    trees: usize,
    depth: usize,
    features: usize,
    split_tests: usize,
    learning_rate: f32,
    lambda: f32,
    /// Bilinear feature reads (format v2) instead of the nearest pixel.
    bilinear: bool,
    local_radius: Option<Vec<f32>>,
    seed: u64,
    dan_seconds: f64,
    train_seconds: f64,
    stage_nme68: Vec<StageNme>,
    validation_detector_init: ValReport,
    file_bytes: usize,
}

/// The refiner on the validation faces, detector start, the server's path (crop, JPEG, DAN, refine).
/// DAN's answers on the validation faces, detector start (`holoface eval`'s protocol), and how many the
/// detector found.
struct ValAnswers {
    faces: usize,
    detected: usize,
    answered: Vec<Answered>,
}

fn val_answers(
    faces: &[Sample],
    args: &Args,
    runner: &mut DanRunner,
    detector: &mut holoface_runtime::detect::BlazeFace,
) -> anyhow::Result<ValAnswers> {
    runner.answered.clear();
    let mean = dan_mean_shape();
    let mut detected = 0;
    for face in faces {
        let gt = face.landmarks.context("annotation missing")?;
        let Some(init) = initial_shape(Some(detector), &mean, &face.image.view(), &gt)? else {
            continue;
        };
        detected += 1;
        runner.push(make_crops(
            &face.image.view(),
            &mean,
            &init,
            &gt,
            args.crop_scale,
            None,
        )?)?;
    }
    runner.flush()?;
    Ok(ValAnswers {
        faces: faces.len(),
        detected,
        answered: std::mem::take(&mut runner.answered),
    })
}

/// Mean NME68 over the validation faces of `shapes` (faces without an answer count as failures in
/// [`validate`]; this running figure is over the answered ones).
fn mean_nme68(val: &ValAnswers, shapes: &[[Point2; 68]]) -> f64 {
    let sum: f64 = val
        .answered
        .iter()
        .zip(shapes)
        .filter_map(|(a, s)| nme68(s, &a.target))
        .sum();
    sum / val.answered.len().max(1) as f64
}

fn validate(refiner: &RefineCascade, val: &ValAnswers) -> anyhow::Result<ValReport> {
    let runner = val;
    let (faces, detected) = (val.faces, val.detected);
    // The figures below are over every validation face: missing answers are failures.
    let mut scratch = RefineScratch::default();
    let (mut d68, mut r68, mut d49, mut r49) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let t0 = Instant::now();
    let mut refined = Vec::with_capacity(runner.answered.len());
    for a in &runner.answered {
        let mut shape = a.start;
        refiner.refine(&a.crop, &mut shape, &mut scratch)?;
        refined.push(shape);
    }
    let us = t0.elapsed().as_secs_f64() * 1e6 / runner.answered.len().max(1) as f64;
    for (a, r) in runner.answered.iter().zip(&refined) {
        d68.push(nme68(&a.start, &a.target).unwrap_or(f64::INFINITY));
        r68.push(nme68(r, &a.target).unwrap_or(f64::INFINITY));
        d49.push(nme49(&a.start, &a.target).unwrap_or(f64::INFINITY));
        r49.push(nme49(r, &a.target).unwrap_or(f64::INFINITY));
    }
    // Faces the detector missed or DAN rejected count as failures, as in `holoface eval`.
    let missing = faces - runner.answered.len();
    for v in [&mut d68, &mut r68, &mut d49, &mut r49] {
        v.extend(std::iter::repeat_n(f64::INFINITY, missing));
    }
    let (sd68, sr68) = (summarise(&d68), summarise(&r68));
    Ok(ValReport {
        faces,
        detected,
        dan_nme68: sd68.mean,
        refined_nme68: sr68.mean,
        dan_nme49: summarise(&d49).mean,
        refined_nme49: summarise(&r49).mean,
        dan_failure68: sd68.failure_rate,
        refined_failure68: sr68.failure_rate,
        refine_us_per_crop: us,
        starts: refiner.starts,
        mirror: refiner.mirror,
    })
}

/// Runs `holoface train-refiner`.
pub fn run(args: Args) -> anyhow::Result<()> {
    check(&args)?;
    let data = faces68_or(args.data.as_deref());
    let mut train_faces = load_folder(&data, Split::Train, true)?;
    if let Some(n) = args.limit {
        train_faces.truncate(n);
    }
    let val_faces = load_folder(&data, Split::Validation, true)?;
    let mut teacher_faces = Vec::new();
    for path in &args.teacher_labels {
        let faces = crate::labels::load_samples(path, args.teacher_limit)?;
        tracing::info!(faces = faces.len(), labels = %path.display(), "teacher-labelled faces");
        teacher_faces.extend(faces);
    }
    let (mut runner, dan_name) = dan_runner(&args)?;
    let mut detector = args.runtime.detector()?;
    if args.evaluate {
        return evaluate(&args, &val_faces, &mut runner, &mut detector);
    }
    let size = CROP_SIZE * args.crop_scale;
    let t0 = Instant::now();
    let faces = (&train_faces[..], &teacher_faces[..]);
    let answered = training_answers(&args, faces, size, &mut runner, &mut detector)?;
    let dan_seconds = t0.elapsed().as_secs_f64();
    let mut samples: Vec<RefineSample<'_>> = answered
        .iter()
        .map(|a| RefineSample {
            crop: &a.crop,
            start: a.start,
            target: a.target,
        })
        .collect();
    let mean: [Point2; 68] = {
        let m = dan_mean_shape();
        std::array::from_fn(|i| {
            Point2::new(
                m[i].x * size as f32 / CROP_SIZE as f32,
                m[i].y * size as f32 / CROP_SIZE as f32,
            )
        })
    };
    let borrowed = borrowed_error_starts(&samples, &mean, args.borrowed_starts, args.seed);
    samples.extend(borrowed);
    let cfg = refine_config(&args);
    let val_set = val_answers(&val_faces, &args, &mut runner, &mut detector)?;
    let t1 = Instant::now();
    let (mut refiner, stage_nme) = train_watched(&samples, &mean, size, &cfg, &val_set)?;
    let train_seconds = t1.elapsed().as_secs_f64();
    let val = final_validation(&mut refiner, &args, &val_set)?;
    let bytes = refiner.to_bytes();
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let report = Report {
        model: refiner.name.clone(),
        dan_model: dan_name,
        data: data.display().to_string(),
        training_faces: train_faces.len(),
        teacher_labels: args.teacher_labels.clone(),
        teacher_faces: teacher_faces.len(),
        teacher_crops_per_face: 2 * args.teacher_crops,
        teacher_pose_match: args.teacher_pose_match,
        training_crops: answered.len(),
        borrowed_starts_per_crop: args.borrowed_starts,
        training_samples: samples.len(),
        rejected_crops: runner.rejected,
        crop_size: size,
        crops_per_face: 2 * args.crops,
        stages: args.stages,
        trees: args.trees,
        depth: args.depth,
        features: args.features,
        split_tests: args.split_tests,
        learning_rate: args.learning_rate,
        lambda: args.lambda,
        bilinear: args.bilinear,
        local_radius: args.local_radius.clone(),
        seed: args.seed,
        dan_seconds,
        train_seconds,
        stage_nme68: stage_nme,
        validation_detector_init: val,
        file_bytes: bytes.len(),
    };
    holoface_sources::output::write_atomic(&args.out, &bytes)?;
    let json = args.out.with_extension("json");
    holoface_sources::output::write_atomic(&json, serde_json::to_string_pretty(&report)? + "\n")?;
    crate::say!(
        "wrote {} ({} bytes) and {}",
        args.out.display(),
        bytes.len(),
        json.display()
    );
    Ok(())
}

/// The settings' ranges.
fn check(args: &Args) -> anyhow::Result<()> {
    if !(1..=holoface_models::refine::START_OFFSETS.len()).contains(&args.starts) {
        bail!(
            "--starts must be within 1..={}",
            holoface_models::refine::START_OFFSETS.len()
        );
    }
    if !(1..=2).contains(&args.crop_scale) {
        bail!("--crop-scale must be 1 or 2");
    }
    if args
        .local_radius
        .as_ref()
        .is_some_and(|v| v.len() != 2 || v.iter().any(|r| !r.is_finite() || *r <= 0.0))
    {
        bail!("--local-radius takes two positive radii: FIRST,LAST");
    }
    Ok(())
}

/// DAN through ONNX Runtime in batches, and its name and version.
fn dan_runner(args: &Args) -> anyhow::Result<(DanRunner, String)> {
    let engine = OnnxEngine::load(&OnnxOptions {
        model: args.runtime.dan_model.clone(),
        ort_dylib: args.runtime.ort_dylib(),
        intra_threads: args.runtime.threads,
        max_batch: BATCH,
        provider: holoface_inference::Provider::Cpu,
        spin: false,
    })
    .with_context(|| format!("loading DAN model {}", args.runtime.dan_model.display()))?;
    let threshold = engine.info().face_threshold;
    let dan_name = format!("{} {}", engine.info().name, engine.info().version);
    let runner = DanRunner {
        engine,
        batch: BatchTensor::new(BATCH, CROP_SIZE * CROP_SIZE),
        outs: vec![LandmarkOut::default(); BATCH],
        queued: Vec::new(),
        scale: args.crop_scale as f32,
        threshold,
        answered: Vec::new(),
        rejected: 0,
    };
    Ok((runner, dan_name))
}

/// `--evaluate`: the cascade at `--out` on the validation faces, 1 and `--starts` starts, with and without
/// the mirror pass.
fn evaluate(
    args: &Args,
    val_faces: &[Sample],
    runner: &mut DanRunner,
    detector: &mut holoface_runtime::detect::BlazeFace,
) -> anyhow::Result<()> {
    let val = val_answers(val_faces, args, runner, detector)?;
    let bytes = std::fs::read(&args.out).with_context(|| format!("reading {}", args.out.display()))?;
    let mut refiner = RefineCascade::from_bytes(&bytes)?;
    for (starts, mirror) in [(1, false), (args.starts, false), (1, true), (args.starts, true)] {
        refiner.starts = starts;
        refiner.mirror = mirror;
        let v = validate(&refiner, &val)?;
        crate::say!("{}", serde_json::to_string(&v)?);
    }
    Ok(())
}

/// DAN's answers on the annotated faces' training crops and on the teacher-labelled ones (`faces`), each from
/// its cache when it matches. The two are cached apart, so that the ablation (the same recipe without teacher
/// labels) and retrains reuse both.
fn training_answers(
    args: &Args,
    (train_faces, teacher_faces): (&[Sample], &[Sample]),
    size: usize,
    runner: &mut DanRunner,
    detector: &mut holoface_runtime::detect::BlazeFace,
) -> anyhow::Result<Vec<Answered>> {
    let key = cache_key(&args.runtime.dan_model, args, train_faces.len())?;
    let mut answered = cached_answers(&args.cache, &key, size, runner, |runner| {
        tracing::info!(
            faces = train_faces.len(),
            crops = args.crops,
            "running DAN on the training crops"
        );
        answer_training_crops(
            train_faces,
            &vec![args.crops; train_faces.len()],
            0,
            args,
            runner,
            detector,
        )
    })?;
    if !teacher_faces.is_empty() {
        let mut key = teacher_cache_key(args, teacher_faces.len())?;
        key.extend_from_slice(&cache_key(&args.runtime.dan_model, args, train_faces.len())?);
        let path = args.cache.with_extension("teacher.bin");
        answered.extend(cached_answers(&path, &key, size, runner, |runner| {
            tracing::info!(
                faces = teacher_faces.len(),
                crops = args.teacher_crops,
                "running DAN on the teacher-labelled crops"
            );
            let first = train_faces.len();
            let crops = teacher_crops_per_face(args, train_faces, teacher_faces);
            tracing::info!(crops = crops.iter().sum::<usize>(), "teacher crops per side");
            answer_training_crops(teacher_faces, &crops, first, args, runner, detector)
        })?);
    }
    Ok(answered)
}

/// The cascade's settings from the command line.
fn refine_config(args: &Args) -> RefineConfig {
    RefineConfig {
        stages: args.stages,
        trees: args.trees,
        depth: args.depth,
        features: args.features,
        split_tests: args.split_tests,
        learning_rate: args.learning_rate,
        seed: args.seed,
        threads: args.train_threads,
        lambda: args.lambda,
        sampling: if args.bilinear {
            Sampling::Bilinear
        } else {
            Sampling::Nearest
        },
        local_radius: args
            .local_radius
            .as_ref()
            .and_then(|v| Some((*v.first()?, *v.get(1)?))),
        name: format!("holoface-ert {}", args.version),
        ..RefineConfig::default()
    }
}

/// Trains the cascade; the validation shapes follow it stage by stage (held-out error per stage, printed
/// and returned).
fn train_watched(
    samples: &[RefineSample<'_>],
    mean: &[Point2; 68],
    size: usize,
    cfg: &RefineConfig,
    val_set: &ValAnswers,
) -> anyhow::Result<(RefineCascade, Vec<StageNme>)> {
    let mut val_shapes: Vec<[Point2; 68]> = val_set.answered.iter().map(|a| a.start).collect();
    let mut scratch = RefineScratch::default();
    let mut stage_nme = Vec::new();
    let t1 = Instant::now();
    let refiner = train(samples, mean, size, cfg, &mut |r, stage| {
        let before = mean_nme68(val_set, &val_shapes);
        for (shape, a) in val_shapes.iter_mut().zip(&val_set.answered) {
            stage.apply(
                mean,
                cfg.depth,
                (size, cfg.sampling),
                &a.crop,
                shape,
                &mut scratch,
            );
        }
        let after = mean_nme68(val_set, &val_shapes);
        crate::say!(
            "stage {:>2}: training NME68 {:.3} % -> {:.3} %, validation {:.3} % -> {:.3} % ({:.0} s)",
            r.stage,
            100.0 * r.nme_before,
            100.0 * r.nme_after,
            100.0 * before,
            100.0 * after,
            t1.elapsed().as_secs_f64()
        );
        stage_nme.push(StageNme {
            train_before: r.nme_before,
            train_after: r.nme_after,
            validation_before: before,
            validation_after: after,
        });
    })?;
    Ok((refiner, stage_nme))
}

/// The trained cascade on the validation faces, with `--starts` and `--mirror` set on it (and, when those
/// differ from one plain pass, the plain pass printed first).
fn final_validation(
    refiner: &mut RefineCascade,
    args: &Args,
    val_set: &ValAnswers,
) -> anyhow::Result<ValReport> {
    let mut val = validate(refiner, val_set)?;
    if args.starts > 1 || args.mirror {
        crate::say!(
            "validation, 1 start, no mirror: NME68 {:.2} % NME49 {:.2} % ({:.0} us per crop)",
            100.0 * val.refined_nme68,
            100.0 * val.refined_nme49,
            val.refine_us_per_crop
        );
        refiner.starts = args.starts;
        refiner.mirror = args.mirror;
        val = validate(refiner, val_set)?;
    }
    crate::say!(
        "validation (detector init, {} faces, {} detected): NME68 DAN {:.2} % -> refined {:.2} %; NME49 {:.2} % -> {:.2} %; failures68 {:.2} % -> {:.2} %; {:.0} us per crop",
        val.faces,
        val.detected,
        100.0 * val.dan_nme68,
        100.0 * val.refined_nme68,
        100.0 * val.dan_nme49,
        100.0 * val.refined_nme49,
        100.0 * val.dan_failure68,
        100.0 * val.refined_failure68,
        val.refine_us_per_crop
    );
    Ok(val)
}

#[cfg(test)]
mod tests {
    use super::*;
    use holoface_models::image::GrayImage;

    /// A face whose nose tip sits `turn` jaw widths off the jaw's middle, eyes level.
    fn face(turn: f32) -> Sample {
        let mut lm = dan_mean_shape();
        let (l, r) = (lm[0].x, lm[16].x);
        lm[30].x = 0.5 * (l + r) + turn * (r - l);
        Sample {
            name: format!("turn {turn}"),
            image: GrayImage::zeros(1, 1),
            landmarks: Some(lm),
        }
    }

    #[test]
    fn pose_bins_follow_the_turn_either_side_and_the_tilt() {
        let frontal = face(0.0).landmarks.unwrap();
        assert_eq!(pose_bin(&frontal), 0);
        let turned = face(0.22).landmarks.unwrap();
        assert_eq!(pose_bin(&turned), 4 * 3);
        assert_eq!(
            pose_bin(&face(-0.22).landmarks.unwrap()),
            4 * 3,
            "either side alike"
        );
        let tilted = Similarity2::from_parts(1.0, 10f64.to_radians(), 0.0, 0.0);
        let mut t = frontal;
        tilted.apply_all(&frontal, &mut t);
        assert_eq!(pose_bin(&t), 1);
    }

    #[test]
    fn teacher_crops_go_where_the_annotated_poses_are() {
        // Annotated: half frontal, half turned; teachers: nine frontal to one turned.
        let train: Vec<Sample> = (0..200)
            .map(|i| face(if i % 2 == 0 { 0.0 } else { 0.22 }))
            .collect();
        let teacher: Vec<Sample> = (0..1000)
            .map(|i| face(if i % 10 == 0 { 0.22 } else { 0.0 }))
            .collect();
        let crops = pose_matched_crops(2, 7, &train, &teacher);
        let mean = |turned: bool| {
            let v: Vec<f64> = (0..crops.len())
                .filter(|i| (i % 10 == 0) == turned)
                .map(|i| crops[i] as f64)
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        // Turned: about 2 x 0.5 / 0.1 = 10 (each share counts one face more per bin); frontal: 2 x 0.5 / 0.9.
        assert!((8.5..=10.0).contains(&mean(true)), "{}", mean(true));
        assert!((0.95..1.2).contains(&mean(false)), "{}", mean(false));
        assert_eq!(
            crops,
            pose_matched_crops(2, 7, &train, &teacher),
            "the seed fixes the rounding"
        );
        // A pose the teachers almost never show gets at most 5 times the crops.
        let rare: Vec<Sample> = (0..1000).map(|i| face(if i == 0 { 0.22 } else { 0.0 })).collect();
        assert_eq!(pose_matched_crops(2, 7, &train, &rare)[0], 10);
    }
}
