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
use holoface_models::geometry::{Point2, Rect};
use holoface_models::refine::train::{RefineConfig, RefineSample, train};
use holoface_models::refine::{RefineCascade, RefineScratch, Sampling};
use holoface_models::rng::Rng;
use holoface_models::shape::{dan_mean_shape, fit_to_box, mirror68};
use holoface_runtime::align::crop_from_image;
use holoface_runtime::link::CropCodec;
use serde::Serialize;

use crate::args::RuntimeArgs;
use crate::cli::eval::initial_shape;
use holoface_harness::data::{Sample, Split, faces68_or, load_folder};

mod crops;
use crops::*;

/// Arguments of `holoface train-refiner`. The defaults are the shipped model's recipe
/// (`models/assets/refiner.json` records it; a test keeps the two equal).
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
    #[arg(long, default_value_t = 20)]
    pub crops: usize,
    /// Cascade stages.
    #[arg(long, default_value_t = 12)]
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
    /// Each stage draws its feature points around the landmarks, in a disc whose radius (crop pixels of
    /// the mean shape) shrinks from the first value to the second over the stages.
    #[arg(long, value_delimiter = ',', default_values_t = [4.0, 1.5])]
    pub local_radius: Vec<f32>,
    /// The model also refines the mirror image and answers the mean of the two (validation is reported
    /// without and with it); `--mirror false` trains a model that does not.
    #[arg(long, default_value_t = true, action = clap::ArgAction::Set)]
    pub mirror: bool,
    /// How features read the crop: bilinear (sub-pixel, a format v2 model) or the nearest pixel (v1).
    #[arg(long, value_enum, default_value_t = SamplingArg::Bilinear)]
    pub sampling: SamplingArg,
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
    /// Teacher-label files (`make teacher-labels` writes them) whose faces are trained on beside the
    /// annotated ones.
    #[arg(
        long,
        value_delimiter = ',',
        default_values = [
            ".data/labels/utkface.hflabels",
            ".data/labels/lfw.hflabels",
            ".data/labels/celeba.hflabels",
            ".data/labels/nomask.hflabels",
        ]
    )]
    pub teacher_labels: Vec<PathBuf>,
    /// Crops per teacher-labelled face and per mirror image (the annotated faces get `--crops`: this ratio
    /// weighs the two kinds of label); 0 trains on the annotated faces only and reads no teacher labels.
    #[arg(long, default_value_t = 1)]
    pub teacher_crops: usize,
    /// Skip training: validate the model already at `--out` with 1 and with `--starts` starts.
    #[arg(long)]
    pub evaluate: bool,
    /// Version written into the model's name.
    #[arg(long, default_value = "0.4.0")]
    pub version: String,
    #[command(flatten)]
    /// Runtime assets (DAN, detector, ONNX Runtime).
    pub runtime: RuntimeArgs,
}

/// `--sampling`: how the cascade's features read the crop.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SamplingArg {
    /// Sub-pixel reads (format v2).
    Bilinear,
    /// The nearest pixel (format v1).
    Nearest,
}

impl From<SamplingArg> for Sampling {
    fn from(s: SamplingArg) -> Self {
        match s {
            SamplingArg::Bilinear => Self::Bilinear,
            SamplingArg::Nearest => Self::Nearest,
        }
    }
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
    training_crops: usize,
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
    local_radius: Vec<f32>,
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
        runner.push(make_crops(&face.image.view(), &mean, &init, &gt, None)?)?;
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
    for path in args.teacher_labels.iter().filter(|_| args.teacher_crops > 0) {
        let faces = crate::labels::load_samples(path, None)?;
        tracing::info!(faces = faces.len(), labels = %path.display(), "teacher-labelled faces");
        teacher_faces.extend(faces);
    }
    let (mut runner, dan_name) = dan_runner(&args)?;
    let mut detector = args.runtime.detector()?;
    if args.evaluate {
        return evaluate(&args, &val_faces, &mut runner, &mut detector);
    }
    let size = CROP_SIZE;
    let t0 = Instant::now();
    let faces = (&train_faces[..], &teacher_faces[..]);
    let answered = training_answers(&args, faces, size, &mut runner, &mut detector)?;
    let dan_seconds = t0.elapsed().as_secs_f64();
    let samples: Vec<RefineSample<'_>> = answered
        .iter()
        .map(|a| RefineSample {
            crop: &a.crop,
            start: a.start,
            target: a.target,
        })
        .collect();
    let mean = dan_mean_shape();
    let cfg = refine_config(&args);
    let val_set = val_answers(&val_faces, &mut runner, &mut detector)?;
    let t1 = Instant::now();
    let (mut refiner, stage_nme) = train_watched(&samples, &mean, size, &cfg, &val_set)?;
    let train_seconds = t1.elapsed().as_secs_f64();
    let val = final_validation(&mut refiner, &args, &val_set)?;
    let bytes = refiner.to_bytes()?;
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let report = Report {
        model: refiner.name.clone(),
        dan_model: dan_name,
        data: data.display().to_string(),
        training_faces: train_faces.len(),
        teacher_labels: if teacher_faces.is_empty() {
            Vec::new()
        } else {
            args.teacher_labels.clone()
        },
        teacher_faces: teacher_faces.len(),
        teacher_crops_per_face: 2 * args.teacher_crops,
        training_crops: answered.len(),
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
        bilinear: args.sampling == SamplingArg::Bilinear,
        local_radius: args.local_radius.clone(),
        seed: args.seed,
        dan_seconds,
        train_seconds,
        stage_nme68: stage_nme,
        validation_detector_init: val,
        file_bytes: bytes.len(),
    };
    crate::cli::write_atomic(&args.out, &bytes)?;
    let json = args.out.with_extension("json");
    crate::cli::write_atomic(&json, serde_json::to_string_pretty(&report)? + "\n")?;
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
    if args.local_radius.len() != 2 || args.local_radius.iter().any(|r| !r.is_finite() || *r <= 0.0) {
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
    let val = val_answers(val_faces, runner, detector)?;
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
            let crops = vec![args.teacher_crops; teacher_faces.len()];
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
        sampling: args.sampling.into(),
        local_radius: Some((args.local_radius[0], args.local_radius[1])),
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
    use crate::cli::trainer_tests::{parse, shipped_report};

    /// `holoface train-refiner` with no options trains the shipped model's recipe: every setting its
    /// training report (`models/assets/refiner.json`, written by this command) records.
    #[test]
    fn the_defaults_are_the_shipped_models_recipe() {
        let args = parse::<Args>(&["train-refiner"]).unwrap();
        let shipped = shipped_report("refiner.json");
        let cfg = refine_config(&args);
        let labels: Vec<String> = args
            .teacher_labels
            .iter()
            .map(|p| p.display().to_string())
            .collect();
        let ours = serde_json::json!({
            "model": cfg.name,
            "teacher_labels": labels,
            "teacher_crops_per_face": 2 * args.teacher_crops,
            "crops_per_face": 2 * args.crops,
            "crop_size": CROP_SIZE,
            "stages": cfg.stages,
            "trees": cfg.trees,
            "depth": cfg.depth,
            "features": cfg.features,
            "split_tests": cfg.split_tests,
            "bilinear": cfg.sampling == Sampling::Bilinear,
            "seed": cfg.seed,
        });
        for (key, want) in ours.as_object().unwrap() {
            assert_eq!(
                &shipped[key], want,
                "{key}: the default differs from the shipped model's"
            );
        }
        // The report writes f32 settings as f32 (0.1, not 0.100000001).
        let f32s = |key: &str| -> Vec<f32> {
            let v = &shipped[key];
            let all = v.as_array().cloned().unwrap_or_else(|| vec![v.clone()]);
            all.iter().map(|x| x.as_f64().unwrap() as f32).collect()
        };
        assert_eq!(f32s("learning_rate"), [cfg.learning_rate]);
        assert_eq!(f32s("lambda"), [cfg.lambda]);
        assert_eq!(f32s("local_radius"), args.local_radius);
        let val = &shipped["validation_detector_init"];
        assert_eq!(val["mirror"], args.mirror);
        assert_eq!(val["starts"], args.starts);
        assert!(check(&args).is_ok());
    }

    #[test]
    fn the_rejected_levers_are_not_options() {
        for gone in [
            "--crop-scale",
            "--borrowed-starts",
            "--teacher-pose-match",
            "--teacher-limit",
        ] {
            assert!(parse::<Args>(&["train-refiner", gone, "1"]).is_err(), "{gone}");
        }
        let args = parse::<Args>(&["train-refiner", "--mirror", "false", "--sampling", "nearest"]).unwrap();
        assert!(!args.mirror);
        assert_eq!(Sampling::from(args.sampling), Sampling::Nearest);
    }
}
