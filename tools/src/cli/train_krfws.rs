//! `holoface train-krfws`: trains the KRFWS local aligner on an annotated face folder, evaluates it on
//! the fixed validation split (never trained on), chooses the failure threshold there, and writes the
//! model plus a JSON report next to it.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{Context, bail};
use holoface_models::accuracy::{FAILURE_THRESHOLD, summarise};
use holoface_models::accuracy::{roc_auc, youden_threshold};
use holoface_models::geometry::{Point2, Rect};
use holoface_models::krfws::train::{self, FitKind, Progress, TrainConfig, TrainFace, gt_box};
use holoface_models::krfws::{Krfws, KrfwsScratch, N_POINTS, nme49_inner};
use holoface_models::rng::Rng;
use serde::Serialize;

use holoface_harness::data::{Split, faces68_or, load_folder};

/// Arguments of `holoface train-krfws`. The defaults are the shipped model's recipe (`models/assets/krfws.json`
/// records it; a test keeps the two equal).
#[derive(Debug, clap::Args)]
pub struct Args {
    /// Annotated face folder (`NAME.jpg` + `NAME.pts`); default `$HOLOFACE_DATA/faces68/train`.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Model output; the JSON report goes beside it (`.json`).
    #[arg(long, default_value = "models/assets/krfws.bin")]
    pub out: PathBuf,
    /// Seed of every random choice (training is deterministic given it).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Trees per landmark forest.
    #[arg(long, default_value_t = 6)]
    pub trees: usize,
    /// Tree depth.
    #[arg(long, default_value_t = 5)]
    pub depth: usize,
    /// Stage-1 start shapes per face and mirror image.
    #[arg(long, default_value_t = 10)]
    pub perturbations: usize,
    /// Every `full_period`-th stage-1 start shape gets the full DAN perturbation (others small/medium).
    #[arg(long, default_value_t = 5)]
    pub full_period: usize,
    /// Smallest child size of a split.
    #[arg(long, default_value_t = 8)]
    pub min_leaf: usize,
    /// Samples entering each node's Fisher discriminant.
    #[arg(long, default_value_t = 500)]
    pub lda_samples: usize,
    /// Shrinkage of the pooled scatter.
    #[arg(long, default_value_t = 0.2)]
    pub shrinkage: f64,
    /// Candidate ridge factors of the global regression (times the mean leaf population), comma
    /// separated; with several, each stage picks one on held-out training faces.
    #[arg(long, value_delimiter = ',', default_value = "0.5,1,2,4")]
    pub ridge: Vec<f64>,
    /// Plain (unweighted) K-cluster splits instead of weighted splitting.
    #[arg(long)]
    pub plain: bool,
    /// Worker threads (results do not depend on it).
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Perturbed fits per training face (and mirror) for the failure detector.
    #[arg(long, default_value_t = 8)]
    pub failure_fits: usize,
    /// Ridge factor of the failure detector.
    #[arg(long, default_value_t = 0.05)]
    pub failure_ridge: f64,
    /// Jittered boxes per validation face.
    #[arg(long, default_value_t = 5)]
    pub jitter_boxes: usize,
    /// Perturbed fits per validation face for the detector's AUC and threshold.
    #[arg(long, default_value_t = 16)]
    pub val_fits: usize,
    /// Skip training: evaluate the model already at `--out` on the validation split (same fits and
    /// threshold rule); writes `<out>.eval.json` and leaves the model file untouched.
    #[arg(long)]
    pub evaluate: bool,
    /// Train on the first N training faces only (smoke runs).
    #[arg(long)]
    pub limit: Option<usize>,
    /// Teacher-label files (`make teacher-labels` writes them) whose faces are trained on beside the
    /// annotated ones.
    #[arg(
        long,
        value_delimiter = ',',
        default_values = [".data/labels/lfw.hflabels", ".data/labels/nomask.hflabels"]
    )]
    pub teacher_labels: Vec<PathBuf>,
    /// Stage-1 start shapes per teacher-labelled face and mirror image (the annotated faces get
    /// `--perturbations`: this ratio weighs the two kinds of label); 0 trains on the annotated faces only and
    /// reads no teacher labels.
    #[arg(long, default_value_t = 3)]
    pub teacher_starts: usize,
    /// At most this many faces from each teacher-label file (evenly spaced over it).
    #[arg(long)]
    pub teacher_limit: Option<usize>,
}

/// A plain stderr progress bar (redrawn at most 5 times a second).
struct Bar {
    state: Mutex<BarState>,
}

struct BarState {
    phase: String,
    total: u64,
    done: u64,
    started: Instant,
    drawn: Instant,
}

impl Bar {
    fn new() -> Self {
        let now = Instant::now();
        Self {
            state: Mutex::new(BarState {
                phase: String::new(),
                total: 0,
                done: 0,
                started: now,
                drawn: now,
            }),
        }
    }
    fn draw(s: &BarState) {
        let frac = if s.total > 0 {
            (s.done as f64 / s.total as f64).min(1.0)
        } else {
            0.0
        };
        let filled = (frac * 30.0) as usize;
        let el = s.started.elapsed().as_secs_f64();
        let eta = if frac > 0.0 { el / frac - el } else { 0.0 };
        eprint!(
            "\r{:<22} [{}{}] {:>6}/{:<6} {:>6.1}s eta {:>6.1}s",
            s.phase,
            "#".repeat(filled),
            "-".repeat(30 - filled),
            s.done.min(s.total),
            s.total,
            el,
            eta
        );
        let _ = std::io::stderr().flush();
    }
}

impl Progress for Bar {
    fn begin(&self, phase: &str, total: u64) {
        if let Ok(mut s) = self.state.lock() {
            s.phase = phase.to_owned();
            s.total = total;
            s.done = 0;
            s.started = Instant::now();
            Self::draw(&s);
        }
    }
    fn inc(&self, n: u64) {
        if let Ok(mut s) = self.state.lock() {
            s.done += n;
            if s.drawn.elapsed().as_millis() >= 200 {
                s.drawn = Instant::now();
                Self::draw(&s);
            }
        }
    }
    fn end(&self, summary: &str) {
        if let Ok(mut s) = self.state.lock() {
            s.done = s.total;
            Self::draw(&s);
            eprintln!(" {summary}");
        }
    }
}

/// Validation summary of one initialisation.
#[derive(Debug, Serialize)]
struct ValSummary {
    faces: usize,
    fits: usize,
    nme49_mean: f64,
    nme49_median: f64,
    auc_0_08: f64,
    failure_rate: f64,
    accepted_rate: f64,
}

/// The JSON report written beside the model.
#[derive(Debug, Serialize)]
struct Report {
    model: String,
    model_bytes: usize,
    data: String,
    train_faces: usize,
    val_faces: usize,
    config: ConfigJson,
    training_seconds: f64,
    train_samples: usize,
    train_stage_nme49: Vec<f64>,
    leaves_per_stage: Vec<usize>,
    cg_iterations: Vec<usize>,
    ridge_chosen: Vec<f64>,
    ridge_holdout_mse: Vec<Vec<f64>>,
    failure_train_fits: usize,
    val_box_init: ValSummary,
    val_jittered_box_init: ValSummary,
    detector_auc_nme_gt_0_08: f64,
    detector_threshold: f32,
    detector_tpr: f64,
    detector_fpr: f64,
    detector_val_fits: usize,
    detector_val_failures: usize,
}

#[derive(Debug, Serialize)]
struct ConfigJson {
    seed: u64,
    trees: usize,
    depth: usize,
    perturbations: usize,
    full_period: usize,
    min_leaf: usize,
    lda_samples: usize,
    shrinkage: f64,
    ridge: Vec<f64>,
    weighted: bool,
    scales: Vec<f32>,
    failure_fits: usize,
    failure_ridge: f64,
    teacher_labels: Vec<PathBuf>,
    teacher_faces: usize,
    teacher_starts: usize,
}

fn to_train_faces(root: &Path, split: Split) -> anyhow::Result<Vec<TrainFace>> {
    let samples = load_folder(root, split, true)?;
    Ok(samples
        .into_iter()
        .filter_map(|s| {
            s.landmarks.map(|landmarks| TrainFace {
                image: s.image,
                landmarks,
                starts: None,
                lid_weight: 1.0,
            })
        })
        .collect())
}

fn median(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.iter().copied().filter(|e| e.is_finite()).collect();
    s.sort_by(f64::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(f64::NAN)
}

fn summary(faces: usize, errs: &[f64], scores: &[f32], thr: f32) -> ValSummary {
    let s = summarise(errs);
    ValSummary {
        faces,
        fits: errs.len(),
        nme49_mean: s.mean,
        nme49_median: median(errs),
        auc_0_08: s.auc,
        failure_rate: s.failure_rate,
        accepted_rate: scores.iter().filter(|&&x| x < thr).count() as f64 / scores.len().max(1) as f64,
    }
}

/// Box-initialised validation fits: `(nme, score)` per fit; `jitter` = 0 is the exact ground-truth box.
fn box_fits(model: &Krfws, faces: &[TrainFace], jitter: usize, seed: u64) -> (Vec<f64>, Vec<f32>) {
    let mut scratch = KrfwsScratch::new();
    let mut errs = Vec::new();
    let mut scores = Vec::new();
    let mut out = [Point2::default(); N_POINTS];
    for (f, face) in faces.iter().enumerate() {
        let b = gt_box(&face.landmarks);
        let boxes: Vec<Rect> = if jitter == 0 {
            vec![b]
        } else {
            let mut rng = Rng::stream(seed, &[11, f as u64]);
            (0..jitter)
                .map(|_| {
                    let (w, h) = (b.width(), b.height());
                    let c = b.centre();
                    let cx = c.x + (rng.normal() * 0.05) as f32 * w;
                    let cy = c.y + (rng.normal() * 0.05) as f32 * h;
                    let s = (1.0 + rng.normal() * 0.05) as f32;
                    Rect {
                        x0: cx - 0.5 * w * s,
                        y0: cy - 0.5 * h * s,
                        x1: cx + 0.5 * w * s,
                        y1: cy + 0.5 * h * s,
                    }
                })
                .collect()
        };
        for bx in boxes {
            let init = model.init_from_box(&bx);
            let score = model.align(&face.image.view(), &init, &mut scratch, &mut out);
            errs.push(nme49_inner(&out, &face.landmarks));
            scores.push(score);
        }
    }
    (errs, scores)
}

/// Runs `holoface train-krfws`.
pub fn run(args: Args) -> anyhow::Result<()> {
    let root = faces68_or(args.data.as_deref());
    crate::say!("loading faces from {}", root.display());
    let mut train_faces = to_train_faces(&root, Split::Train)?;
    if let Some(n) = args.limit {
        train_faces.truncate(n);
    }
    add_teacher_faces(&args, &mut train_faces)?;
    let val_faces = to_train_faces(&root, Split::Validation)?;
    if train_faces.is_empty() || val_faces.is_empty() {
        bail!("need training and validation faces in {}", root.display());
    }
    crate::say!(
        "{} training faces (x2 mirrored), {} validation faces",
        train_faces.len(),
        val_faces.len()
    );
    let cfg = train_config(&args);
    let bar = Bar::new();
    let t0 = Instant::now();
    let (mut model, report) = if args.evaluate {
        let bytes = std::fs::read(&args.out).with_context(|| format!("reading {}", args.out.display()))?;
        let model = Krfws::from_bytes(&bytes).with_context(|| format!("loading {}", args.out.display()))?;
        (model, train::TrainReport::default())
    } else {
        train::train(&train_faces, &cfg, &bar)?
    };
    let training_seconds = t0.elapsed().as_secs_f64();
    model.round_to_storage();
    let detector = failure_detector(&mut model, &val_faces, &args, cfg.threads, &bar);
    let thr = detector.threshold;
    let (box_errs, box_scores) = box_fits(&model, &val_faces, 0, args.seed);
    let (jit_errs, jit_scores) = box_fits(&model, &val_faces, args.jitter_boxes.max(1), args.seed);
    let val_box = summary(val_faces.len(), &box_errs, &box_scores, thr);
    let val_jit = summary(val_faces.len(), &jit_errs, &jit_scores, thr);

    let bytes = model.to_bytes()?;
    let back = Krfws::from_bytes(&bytes).context("re-reading the model just written")?;
    if back != model {
        bail!("model changed through to_bytes/from_bytes");
    }
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    if !args.evaluate {
        crate::cli::write_atomic(&args.out, &bytes)?;
    }
    let rep = Report {
        model: args.out.display().to_string(),
        model_bytes: bytes.len(),
        data: root.display().to_string(),
        train_faces: train_faces.len(),
        val_faces: val_faces.len(),
        config: config_json(&args, &cfg, &train_faces),
        training_seconds,
        train_samples: report.samples,
        train_stage_nme49: report.stage_nme.clone(),
        leaves_per_stage: report.leaves.clone(),
        cg_iterations: report.cg_iterations.clone(),
        ridge_chosen: report.ridge.clone(),
        ridge_holdout_mse: report.ridge_holdout_mse.clone(),
        failure_train_fits: report.failure_samples,
        val_box_init: val_box,
        val_jittered_box_init: val_jit,
        detector_auc_nme_gt_0_08: detector.auc,
        detector_threshold: thr,
        detector_tpr: detector.tpr,
        detector_fpr: detector.fpr,
        detector_val_fits: detector.fits,
        detector_val_failures: detector.failures,
    };
    let json_path = args
        .out
        .with_extension(if args.evaluate { "eval.json" } else { "json" });
    crate::cli::write_atomic(
        &json_path,
        (serde_json::to_string_pretty(&rep)? + "\n").as_bytes(),
    )?;
    say_report(&rep, &report, (&args.out, bytes.len(), &json_path));
    Ok(())
}

/// The teacher-labelled faces of `--teacher-labels`, each with `--teacher-starts` starts.
fn add_teacher_faces(args: &Args, train_faces: &mut Vec<TrainFace>) -> anyhow::Result<()> {
    for path in args.teacher_labels.iter().filter(|_| args.teacher_starts > 0) {
        let faces = crate::labels::load_samples(path, args.teacher_limit)?;
        crate::say!("{} teacher-labelled faces from {}", faces.len(), path.display());
        train_faces.extend(faces.into_iter().filter_map(|s| {
            s.landmarks.map(|landmarks| TrainFace {
                image: s.image,
                landmarks,
                starts: Some(args.teacher_starts),
                lid_weight: 1.0,
            })
        }));
    }
    Ok(())
}

/// The trainer's settings from the command line.
fn train_config(args: &Args) -> TrainConfig {
    TrainConfig {
        seed: args.seed,
        trees: args.trees,
        depth: args.depth,
        perturbations: args.perturbations,
        full_period: args.full_period,
        min_leaf: args.min_leaf,
        lda_samples: args.lda_samples,
        shrinkage: args.shrinkage,
        ridge: args.ridge.clone(),
        weighted: !args.plain,
        threads: args.threads.max(1),
        failure_fits: args.failure_fits,
        failure_ridge: args.failure_ridge,
        ..TrainConfig::default()
    }
}

/// The failure detector, measured on perturbed validation fits.
struct Detector {
    auc: f64,
    threshold: f32,
    tpr: f64,
    fpr: f64,
    fits: usize,
    failures: usize,
}

/// Failure detector: AUC and threshold on perturbed validation fits; sets the threshold on `model`.
fn failure_detector(
    model: &mut Krfws,
    val_faces: &[TrainFace],
    args: &Args,
    threads: usize,
    bar: &Bar,
) -> Detector {
    let (fits, _) = train::perturbed_fits(
        model,
        val_faces,
        args.val_fits.max(4),
        args.seed ^ 0x7A1,
        threads,
        false,
        bar,
    );
    let scores: Vec<f32> = fits.iter().map(|f| f.score).collect();
    let labels: Vec<bool> = fits.iter().map(|f| f.nme > FAILURE_THRESHOLD).collect();
    let auc = roc_auc(&scores, &labels).unwrap_or(f64::NAN);
    let (thr, tpr, fpr) = youden_threshold(&scores, &labels).unwrap_or((f32::INFINITY, f64::NAN, f64::NAN));
    model.set_threshold(thr);
    for kind in [FitKind::Small, FitKind::Full, FitKind::Gross, FitKind::NonFace] {
        let k: Vec<&train::PerturbedFit> = fits.iter().filter(|f| f.kind == kind).collect();
        let fail = k.iter().filter(|f| f.nme > FAILURE_THRESHOLD).count();
        let flagged = k.iter().filter(|f| f.score >= thr).count();
        crate::say!(
            "  val {kind:?}: {} fits, {fail} with NME > 0.08, {flagged} flagged",
            k.len()
        );
    }

    Detector {
        auc,
        threshold: thr,
        tpr,
        fpr,
        fits: fits.len(),
        failures: labels.iter().filter(|l| **l).count(),
    }
}

/// The report's copy of the settings.
fn config_json(args: &Args, cfg: &TrainConfig, train_faces: &[TrainFace]) -> ConfigJson {
    ConfigJson {
        seed: cfg.seed,
        trees: cfg.trees,
        depth: cfg.depth,
        perturbations: cfg.perturbations,
        full_period: cfg.full_period,
        min_leaf: cfg.min_leaf,
        lda_samples: cfg.lda_samples,
        shrinkage: cfg.shrinkage,
        ridge: cfg.ridge.clone(),
        weighted: cfg.weighted,
        scales: cfg.scales.clone(),
        failure_fits: cfg.failure_fits,
        failure_ridge: cfg.failure_ridge,
        teacher_labels: if args.teacher_starts > 0 {
            args.teacher_labels.clone()
        } else {
            Vec::new()
        },
        teacher_faces: train_faces.iter().filter(|f| f.starts.is_some()).count(),
        teacher_starts: args.teacher_starts,
    }
}

/// The run in words.
fn say_report(rep: &Report, report: &train::TrainReport, (out, bytes, json_path): (&Path, usize, &Path)) {
    let (training_seconds, thr, auc, tpr, fpr) = (
        rep.training_seconds,
        rep.detector_threshold,
        rep.detector_auc_nme_gt_0_08,
        rep.detector_tpr,
        rep.detector_fpr,
    );
    crate::say!(
        "training time        {:.1} s ({} samples/stage)",
        training_seconds,
        report.samples
    );
    crate::say!("train NME49 by stage {:?}", report.stage_nme);
    crate::say!(
        "ridge chosen         {:?} (held-out MSE {:?})",
        report.ridge,
        report.ridge_holdout_mse
    );
    crate::say!(
        "val NME49 (GT box)   {:.4} mean, {:.4} median, AUC@0.08 {:.4}, failure rate {:.2} %",
        rep.val_box_init.nme49_mean,
        rep.val_box_init.nme49_median,
        rep.val_box_init.auc_0_08,
        100.0 * rep.val_box_init.failure_rate
    );
    crate::say!(
        "val NME49 (jittered) {:.4} mean, {:.4} median, AUC@0.08 {:.4}, failure rate {:.2} %",
        rep.val_jittered_box_init.nme49_mean,
        rep.val_jittered_box_init.nme49_median,
        rep.val_jittered_box_init.auc_0_08,
        100.0 * rep.val_jittered_box_init.failure_rate
    );
    crate::say!(
        "failure detector     AUC {:.4} (NME > 0.08, {} perturbed val fits, {} failures), threshold {:.4} (TPR {:.3}, FPR {:.3})",
        auc,
        rep.detector_val_fits,
        rep.detector_val_failures,
        thr,
        tpr,
        fpr
    );
    crate::say!(
        "model                {} ({} bytes), report {}",
        out.display(),
        bytes,
        json_path.display()
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::trainer_tests::{parse, shipped_report};

    /// `holoface train-krfws` with no options trains the shipped model's recipe: every setting its training
    /// report (`models/assets/krfws.json`, written by this command) records.
    #[test]
    fn the_defaults_are_the_shipped_models_recipe() {
        let args = parse::<Args>(&["train-krfws"]).unwrap();
        let shipped = shipped_report("krfws.json");
        let cfg = train_config(&args);
        let mut ours = serde_json::to_value(config_json(&args, &cfg, &[])).unwrap();
        // Counted from the faces it loads, not a setting.
        ours.as_object_mut().unwrap().remove("teacher_faces");
        for (key, want) in ours.as_object().unwrap() {
            let have = &shipped["config"][key];
            if let (Some(a), Some(b)) = (have.as_array(), want.as_array()) {
                // f32 lists (the scales) are written as f32: compare them so.
                let f = |v: &Vec<serde_json::Value>| -> Vec<String> {
                    v.iter()
                        .map(|x| x.as_f64().map_or(x.to_string(), |f| (f as f32).to_string()))
                        .collect()
                };
                assert_eq!(f(a), f(b), "{key}: the default differs from the shipped model's");
            } else {
                assert_eq!(have, want, "{key}: the default differs from the shipped model's");
            }
        }
    }

    #[test]
    fn the_rejected_levers_are_not_options() {
        for gone in [
            "--teacher-turned",
            "--turned-min-yaw",
            "--turned-starts",
            "--teacher-lid-weight",
            "--turned-lid-weight",
        ] {
            assert!(parse::<Args>(&["train-krfws", gone, "1"]).is_err(), "{gone}");
        }
    }
}
