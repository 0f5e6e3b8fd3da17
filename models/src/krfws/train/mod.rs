//! KRFWS training (algorithms.md 2.4), pure: in-memory faces in, a [`Krfws`] out; no IO, no clock.
//! Deterministic for a given [`TrainConfig::seed`] whatever the thread count (every random stream is
//! seeded from the seed and the stage/landmark/sample it serves, and results are assembled in index
//! order).
//!
//! # Cascade
//! Stage-1 start shapes are the box initialisation ([`Krfws::init_from_box`] on the ground-truth 68-point
//! extent) of every face and of its mirror image (`MIRROR68`), perturbed by random similarities about the
//! shape centroid: sample 0 unperturbed; sample `k > 0` gets the full DAN σ (20 % of the shape's
//! width/height translation, 20° rotation, 25 % scale) when `k % full_period == 0`, else small noise
//! (σ 5 % translation, 5°, 5 % scale: the jitter of a detector box or of the previous frame) for an odd
//! remainder or medium noise (10 %, 10°, 10 %) for an even one ([`TrainConfig::full_period`]). Later stages start from the previous
//! stage's outputs. Targets are the per-landmark displacements ground truth − current in the stage's
//! normalised frame divided by the stage scale (mean-shape units).
//!
//! # Weighted K-cluster splits
//! At a node with samples `S`, the landmark's 2-D targets `d_i` are clustered by 2-means (initialised by
//! the sign of the projection on their principal axis; 10 Lloyd iterations), giving centres `c₀, c₁`.
//! Routing sample `i` into the child of the *other* cluster raises the node's squared error by exactly
//!
//! ```text
//!     Δᵢ = ‖dᵢ − c_other‖² − ‖dᵢ − c_own‖² = 2·|⟨dᵢ − m, c₁ − c₀⟩|,   m = (c₀ + c₁)/2,
//! ```
//!
//! so the **weighted splitting** rule gives each sample the weight `wᵢ = Δᵢ + 0.1·mean(Δ)` (its
//! misrouting cost, floored so samples on the cluster boundary still count) in a weighted Fisher
//! discriminant on the 144-d HOG: class means `μ_k = Σ wᵢxᵢ / Σ wᵢ` over cluster `k`, pooled scatter
//! `S_w = Σ wᵢ (xᵢ − μ_{k(i)})(xᵢ − μ_{k(i)})ᵀ / Σ wᵢ`, shrunk to `S = (1−γ)S_w + γ·tr(S_w)/144·I`
//! (γ = [`TrainConfig::shrinkage`]), direction `v = S⁻¹(μ₁ − μ₀)` (Cholesky; at most
//! [`TrainConfig::lda_samples`] samples, drawn at random, enter `S_w` and the means). The threshold on
//! `⟨v, x⟩` is then chosen over all node samples to minimise the children's summed squared target error
//! (the regression objective itself), each child keeping at least [`TrainConfig::min_leaf`] samples.
//! The *plain* K-cluster split ([`TrainConfig::weighted`] = false) is the same with `wᵢ = 1`.
//!
//! # Global regression
//! `W = argmin ‖XW − Y‖² + λ‖W‖²` with `X` the binary leaf code (one 1 per tree) and `Y` the 102-d
//! targets, solved by Jacobi-preconditioned conjugate gradients on the normal equations with sparse
//! matrix–vector products (`X·P` gathers leaf rows, `Xᵀ·R` scatters them): `XᵀX` (leaves × leaves) is
//! never formed. `λ = ridge · n · trees / leaves`, i.e. [`TrainConfig::ridge`] times the mean leaf
//! population. A face's [`TrainFace::lid_weight`] ≠ 1 makes each lid output column its own weighted
//! problem (`XᵀDX + λI`, `D` the samples' lid weights; the preconditioner stays unweighted).
//!
//! # Failure detector
//! Perturbed fits of every training face (small, full-σ and 2×σ gross perturbations, and boxes moved off
//! the face onto background = non-face patches) are run through the trained cascade; the last stage's
//! 51×144 HOG is regressed on `min(NME49, FAILURE_TARGET_CAP)` by ridge regression (dense CG, centred
//! features, intercept = mean target). The acceptance threshold is chosen by the caller on validation
//! data ([`crate::accuracy::youden_threshold`]).

use std::sync::atomic::{AtomicUsize, Ordering};

mod failure;
mod forest;
mod ridge;

use failure::empty_failure;
pub use failure::{FitKind, PerturbedFit, perturbed_fits, perturbed_init, train_failure};
use forest::{stage_data, train_forest};
use ridge::{Solve, ridge_sparse};

use super::{
    DELTA_DIM, FAILURE_DIM, FailureModel, Krfws, KrfwsScratch, N_POINTS, Node, Stage, Tree, dot144,
    nme49_inner, stage_features,
};
use crate::augment::{Perturbation, perturb};
use crate::geometry::{Point2, Rect, Similarity2};
use crate::hog::{HOG_DIM, PATCH_PIXELS};
use crate::image::GrayImage;
use crate::rng::Rng;
use crate::shape::{INNER51, mirror68};

/// Failure-detector targets are NME49 clipped at this value (gross failures and non-faces).
pub const FAILURE_TARGET_CAP: f32 = 0.25;

/// One annotated training face.
#[derive(Clone, Debug)]
pub struct TrainFace {
    /// Grayscale image.
    pub image: GrayImage,
    /// 68 ground-truth landmarks in image pixels.
    pub landmarks: [Point2; 68],
    /// Stage-1 start shapes of this face (and of its mirror image); `None`: [`TrainConfig::perturbations`].
    /// Fewer starts weigh a face less: the teacher-labelled faces get fewer than the annotated ones. Faces
    /// with `Some` follow the annotated ones in [`train`]'s list; the failure detector learns from the
    /// annotated faces only.
    pub starts: Option<usize>,
    /// Weight of this face's eyelid targets (the 8 lid points of the 51, [`LID_POINTS`]) in the global
    /// regression, relative to its other points: 1 for annotated faces. Below 1, this face's labels shape
    /// the lids less than the rest of the face (a lever for teacher labels, measured in
    /// docs/experiments/krfws.md, "The teacher lids weighed down"); the trees are unchanged.
    pub lid_weight: f32,
}

/// The eyelid points (upper and lower lid, not the corners) as indices into the 51 inner points.
pub const LID_POINTS: [usize; 8] = [20, 21, 23, 24, 26, 27, 29, 30];

/// Which of the 102 regression outputs belong to the lid points.
fn lid_columns() -> [bool; DELTA_DIM] {
    let mut c = [false; DELTA_DIM];
    for p in LID_POINTS {
        c[2 * p] = true;
        c[2 * p + 1] = true;
    }
    c
}

/// Training hyper-parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainConfig {
    /// Seed of every random choice.
    pub seed: u64,
    /// Trees per landmark forest.
    pub trees: usize,
    /// Tree depth (leaves per tree ≤ 2^depth).
    pub depth: usize,
    /// Stage-1 start shapes per face and per mirror image.
    pub perturbations: usize,
    /// Stage-1 start shape `k > 0` gets the DAN σ when `k % full_period == 0`, else small (odd
    /// remainder) or medium (even remainder) noise; 3 gives the cycle small, medium, DAN.
    pub full_period: usize,
    /// Smallest number of samples a child may receive.
    pub min_leaf: usize,
    /// Largest number of samples entering the Fisher discriminant at a node.
    pub lda_samples: usize,
    /// Shrinkage γ of the pooled scatter towards a scaled identity.
    pub shrinkage: f64,
    /// Candidate ridge factors of the global regression, relative to the mean leaf population. With
    /// more than one, every 10th training face (with its mirror) is held out of the forests and the
    /// factor with the lowest held-out error is chosen per stage, then `W` is refitted on all samples.
    pub ridge: Vec<f64>,
    /// Weighted splitting (true) or plain K-cluster splits (false).
    pub weighted: bool,
    /// Stage scales.
    pub scales: Vec<f32>,
    /// Worker threads (results do not depend on it).
    pub threads: usize,
    /// Perturbed fits per training face for the failure detector.
    pub failure_fits: usize,
    /// Ridge factor of the failure detector, relative to the mean diagonal of `XᵀX`.
    pub failure_ridge: f64,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            trees: 6,
            depth: 5,
            perturbations: 10,
            full_period: 3,
            min_leaf: 8,
            lda_samples: 500,
            shrinkage: 0.2,
            ridge: vec![0.5, 1.0, 2.0, 4.0],
            weighted: true,
            scales: super::DEFAULT_SCALES.to_vec(),
            threads: 2,
            failure_fits: 8,
            failure_ridge: 0.05,
        }
    }
}

/// Progress sink; the CLI draws bars with it. Called from worker threads.
pub trait Progress: Sync {
    /// A phase starts with `total` units of work.
    fn begin(&self, phase: &str, total: u64);
    /// `n` more units are done.
    fn inc(&self, n: u64);
    /// The phase ended; `summary` is a one-line result.
    fn end(&self, summary: &str);
}

/// A [`Progress`] that ignores everything.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoProgress;

impl Progress for NoProgress {
    fn begin(&self, _: &str, _: u64) {}
    fn inc(&self, _: u64) {}
    fn end(&self, _: &str) {}
}

/// What training measured on the training samples.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TrainReport {
    /// Training samples per stage.
    pub samples: usize,
    /// Mean NME49 of the training start shapes and after each stage.
    pub stage_nme: Vec<f64>,
    /// Leaves per stage.
    pub leaves: Vec<usize>,
    /// Conjugate-gradient iterations of each stage's final regression.
    pub cg_iterations: Vec<usize>,
    /// Ridge factor chosen per stage.
    pub ridge: Vec<f64>,
    /// Held-out mean squared target error per stage and candidate ridge factor.
    pub ridge_holdout_mse: Vec<Vec<f64>>,
    /// Samples the failure detector was fitted on.
    pub failure_samples: usize,
}

/// Errors of training.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum TrainError {
    /// No usable faces.
    #[error("no training faces")]
    NoFaces,
    /// Bad configuration.
    #[error("bad configuration: {0}")]
    Config(&'static str),
}

/// Horizontally mirrored copy of a face.
pub fn mirror_face(face: &TrainFace) -> TrainFace {
    TrainFace {
        image: face.image.mirrored(),
        landmarks: mirror68(&face.landmarks, face.image.width()),
        starts: face.starts,
        lid_weight: face.lid_weight,
    }
}

/// DAN's stage-1 perturbation (algorithms.md 1.7).
pub const DAN_PERTURBATION: Perturbation = Perturbation::new(0.2, 20.0, 0.25);

/// Small perturbation: detector-box or previous-frame jitter.
pub const SMALL_PERTURBATION: Perturbation = Perturbation::new(0.05, 5.0, 0.05);

/// Medium perturbation, between the small and the DAN one.
pub const MEDIUM_PERTURBATION: Perturbation = Perturbation::new(0.1, 10.0, 0.1);

/// The ground-truth box: the extent of the 68 points.
pub fn gt_box(gt: &[Point2; 68]) -> Rect {
    Rect::bounding(gt).unwrap_or_default()
}

struct Sample {
    face: usize,
    shape: [Point2; N_POINTS],
}

/// Runs `f(index, item)` over `items` on `threads` threads, each with its own state from `init`.
fn par_for_each<T: Send, S>(
    items: &mut [T],
    threads: usize,
    init: impl Fn() -> S + Sync,
    f: impl Fn(&mut S, usize, &mut T) + Sync,
) {
    let threads = threads.clamp(1, 64);
    let chunk = items.len().div_ceil(threads).max(1);
    std::thread::scope(|sc| {
        for (c, part) in items.chunks_mut(chunk).enumerate() {
            let (f, init) = (&f, &init);
            sc.spawn(move || {
                let mut state = init();
                for (k, it) in part.iter_mut().enumerate() {
                    f(&mut state, c * chunk + k, it);
                }
            });
        }
    });
}

/// Refuses a training run that cannot work: no faces, or settings out of range.
fn validate(faces: &[TrainFace], cfg: &TrainConfig) -> Result<(), TrainError> {
    if faces.is_empty() {
        return Err(TrainError::NoFaces);
    }
    if cfg.ridge.is_empty() || cfg.ridge.iter().any(|r| r.is_nan() || *r <= 0.0) {
        return Err(TrainError::Config("ridge factors must be positive"));
    }
    if cfg.trees == 0 || cfg.trees > 64 || cfg.depth == 0 || cfg.depth > 11 || cfg.perturbations == 0 {
        return Err(TrainError::Config(
            "trees 1..=64, depth 1..=11, perturbations ≥ 1",
        ));
    }
    if cfg.scales.is_empty() || cfg.scales.len() > 8 || cfg.scales.iter().any(|s| !(0.01..=100.0).contains(s))
    {
        return Err(TrainError::Config("1..=8 stage scales in 0.01..=100"));
    }
    if faces.iter().any(|f| !(0.0..=1e3).contains(&f.lid_weight)) {
        return Err(TrainError::Config("lid weights must be in 0..=1000"));
    }
    Ok(())
}

/// Every training face's starting shapes: the mean shape on its box, then perturbations of it (the seed's
/// streams per face and start).
fn starting_shapes(all: &[TrainFace], proto: &Krfws, cfg: &TrainConfig) -> Vec<Sample> {
    let mut samples = Vec::with_capacity(all.len() * cfg.perturbations);
    for (fi, f) in all.iter().enumerate() {
        let base = proto.init_from_box(&gt_box(&f.landmarks));
        for k in 0..f.starts.unwrap_or(cfg.perturbations).max(1) {
            let mut rng = Rng::stream(cfg.seed, &[0, fi as u64, k as u64]);
            let r = k % cfg.full_period.max(2);
            let shape = if k == 0 {
                base
            } else if r == 0 {
                perturb(&base, DAN_PERTURBATION, &mut rng)
            } else if r % 2 == 1 {
                perturb(&base, SMALL_PERTURBATION, &mut rng)
            } else {
                perturb(&base, MEDIUM_PERTURBATION, &mut rng)
            };
            samples.push(Sample { face: fi, shape });
        }
    }
    samples
}

/// One stage's forests (landmarks distributed over threads, assembled in landmark order) trained on `pool`:
/// the trees, every sample's leaf codes (`N_POINTS * trees` per sample) and the number of leaves; `None` when
/// a worker failed.
fn stage_forests(
    data: &forest::StageData,
    pool: &[u32],
    si: usize,
    cfg: &TrainConfig,
    progress: &dyn Progress,
) -> Option<(Vec<Tree>, Vec<u32>, u32)> {
    // Forests, landmarks distributed over threads, assembled in landmark order.
    progress.begin(&format!("stage {} forests", si + 1), N_POINTS as u64);
    let next = AtomicUsize::new(0);
    let mut results: Vec<(usize, Vec<Tree>, Vec<u32>)> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..cfg.threads.clamp(1, 64))
            .map(|_| {
                sc.spawn(|| {
                    let mut out = Vec::new();
                    loop {
                        let l = next.fetch_add(1, Ordering::Relaxed);
                        if l >= N_POINTS {
                            break;
                        }
                        let (t, lv) = train_forest(data, pool, l, si, cfg);
                        out.push((l, t, lv));
                        progress.inc(1);
                    }
                    out
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap_or_default())
            .collect()
    });
    results.sort_by_key(|r| r.0);
    if results.len() != N_POINTS {
        return None;
    }
    let mut trees = Vec::with_capacity(N_POINTS * cfg.trees);
    let mut offsets = Vec::with_capacity(N_POINTS * cfg.trees);
    let mut total = 0u32;
    for (_, ts, _) in &results {
        for t in ts {
            offsets.push(total);
            total += t.n_leaves;
        }
    }
    let per = N_POINTS * cfg.trees;
    let n = data.sims.len();
    let mut codes = vec![0u32; n * per];
    for (l, ts, lv) in &mut results {
        for i in 0..n {
            for t in 0..cfg.trees {
                codes[i * per + *l * cfg.trees + t] = offsets[*l * cfg.trees + t] + lv[i * cfg.trees + t];
            }
        }
        trees.append(ts);
    }
    Some((trees, codes, total))
}

/// A stage's sparse regression problem: every sample's `per` leaf codes into `leaves` leaves, and its targets.
struct RidgeFit<'a> {
    codes: &'a [u32],
    per: usize,
    leaves: usize,
    targets: &'a [f32],
}

/// The ridge factor of `cfg.ridge` whose regression, fitted without the `held` samples, predicts them best
/// (squared error, the lid coordinates weighed by each sample's `weights` when `weighted`), and each factor's
/// held-out error.
fn choose_ridge(
    fit: &RidgeFit<'_>,
    held: &[bool],
    weights: &[f32],
    weighted: bool,
    population: f64,
    cfg: &TrainConfig,
) -> (f64, Vec<f64>) {
    let per = fit.per;
    let lids = lid_columns();
    let mut mses = Vec::new();
    let mut chosen = cfg.ridge[0];
    let (mut tc, mut ty, mut tw, mut hc, mut hy, mut hw) = (
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
        Vec::new(),
    );
    for (i, (&w, &held)) in weights.iter().zip(held).enumerate() {
        let (c, y) = (
            &fit.codes[i * per..(i + 1) * per],
            &fit.targets[i * DELTA_DIM..(i + 1) * DELTA_DIM],
        );
        if held {
            hc.extend_from_slice(c);
            hy.extend_from_slice(y);
            hw.push(w);
        } else {
            tc.extend_from_slice(c);
            ty.extend_from_slice(y);
            tw.push(w);
        }
    }
    let tw = weighted.then_some(tw.as_slice());
    let mut best = f64::INFINITY;
    for &r in &cfg.ridge {
        let (w, _) = ridge_sparse(
            &tc,
            per,
            fit.leaves,
            &ty,
            tw,
            Solve {
                lambda: r * population,
                tol: 1e-6,
                threads: cfg.threads,
            },
        );
        let mut err = 0.0f64;
        for ((c, y), &wi) in hc.chunks_exact(per).zip(hy.chunks_exact(DELTA_DIM)).zip(&hw) {
            let mut pred = [0.0f64; DELTA_DIM];
            for &leaf in c {
                for (p, v) in pred.iter_mut().zip(&w[leaf as usize * DELTA_DIM..]) {
                    *p += f64::from(*v);
                }
            }
            err += pred
                .iter()
                .zip(y)
                .zip(&lids)
                .map(|((p, t), &lid)| {
                    let w = if lid { f64::from(wi) } else { 1.0 };
                    w * (p - f64::from(*t)).powi(2)
                })
                .sum::<f64>();
        }
        let mse = err / (hy.len().max(1)) as f64;
        mses.push(mse);
        if mse < best {
            best = mse;
            chosen = r;
        }
    }
    (chosen, mses)
}

/// Trains the cascade (no failure detector yet: call [`train_failure`]). `faces` are the training faces
/// (mirrors are added here).
pub fn train_cascade(
    faces: &[TrainFace],
    cfg: &TrainConfig,
    progress: &dyn Progress,
) -> Result<(Krfws, TrainReport), TrainError> {
    validate(faces, cfg)?;
    let mut all: Vec<TrainFace> = Vec::with_capacity(faces.len() * 2);
    for f in faces {
        all.push(f.clone());
        all.push(mirror_face(f));
    }
    let mean = super::default_mean_shape();
    let proto = Krfws::new(mean, Vec::new(), empty_failure());
    let mut samples = starting_shapes(&all, &proto, cfg);
    let n = samples.len();
    // Per-sample lid weights, only when some face weighs its lids differently (else the plain solve).
    let lid_weights: Option<Vec<f32>> = all
        .iter()
        .any(|f| f.lid_weight != 1.0)
        .then(|| samples.iter().map(|s| all[s.face].lid_weight).collect());
    let mut report = TrainReport {
        samples: n,
        ..TrainReport::default()
    };
    let mean_nme = |samples: &[Sample]| {
        samples
            .iter()
            .map(|s| nme49_inner(&s.shape, &all[s.face].landmarks))
            .filter(|e| e.is_finite())
            .sum::<f64>()
            / samples.len() as f64
    };
    report.stage_nme.push(mean_nme(&samples));
    let mut stages = Vec::new();
    for (si, &scale) in cfg.scales.iter().enumerate() {
        let dest = super::stage_dest(&mean, scale);
        let data = stage_data(&all, &samples, &dest, scale, cfg.threads, progress);
        // Every 10th original face (and its mirror) is held out of the forests to choose the ridge.
        let select = cfg.ridge.len() > 1;
        let held = |i: usize| select && (samples[i].face / 2) % 10 == 9;
        let pool: Vec<u32> = (0..n).filter(|&i| !held(i)).map(|i| i as u32).collect();
        let Some((trees, codes, total)) = stage_forests(&data, &pool, si, cfg, progress) else {
            return Err(TrainError::Config("a forest worker failed"));
        };
        let per = N_POINTS * cfg.trees;
        progress.end(&format!("{total} leaves"));
        progress.begin(&format!("stage {} regression", si + 1), 1);
        let population = (n * per) as f64 / f64::from(total.max(1));
        let (chosen, mses) = if select {
            let held: Vec<bool> = (0..n).map(held).collect();
            let weights: Vec<f32> = samples.iter().map(|s| all[s.face].lid_weight).collect();
            let fit = RidgeFit {
                codes: &codes,
                per,
                leaves: total as usize,
                targets: &data.targets,
            };
            choose_ridge(&fit, &held, &weights, lid_weights.is_some(), population, cfg)
        } else {
            (cfg.ridge[0], Vec::new())
        };
        let lambda = chosen * population;
        let (mut w, iters) = ridge_sparse(
            &codes,
            per,
            total as usize,
            &data.targets,
            lid_weights.as_deref(),
            Solve {
                lambda,
                tol: 1e-8,
                threads: cfg.threads,
            },
        );
        super::format::round_f16(&mut w);
        progress.inc(1);
        progress.end(&format!("{iters} CG iterations"));
        let stage = Stage::new(&mean, scale, cfg.trees, trees, w);
        // Update the training shapes with the stored (rounded) model.
        let mut delta = [0.0f32; DELTA_DIM];
        for (i, s) in samples.iter_mut().enumerate() {
            let (Some(t), norm) = (data.sims[i], &data.norms[i]) else {
                continue;
            };
            let Some(inv) = t.inverse() else { continue };
            stage.accumulate(&codes[i * per..(i + 1) * per], &mut delta);
            for (k, p) in s.shape.iter_mut().enumerate() {
                *p = inv.apply(Point2::new(
                    norm[k].x + delta[2 * k] * scale,
                    norm[k].y + delta[2 * k + 1] * scale,
                ));
            }
        }
        report.stage_nme.push(mean_nme(&samples));
        report.leaves.push(total as usize);
        report.cg_iterations.push(iters);
        report.ridge.push(chosen);
        report.ridge_holdout_mse.push(mses);
        stages.push(stage);
    }
    Ok((Krfws::new(mean, stages, empty_failure()), report))
}

/// Trains the cascade and the failure detector (threshold left at +∞).
pub fn train(
    faces: &[TrainFace],
    cfg: &TrainConfig,
    progress: &dyn Progress,
) -> Result<(Krfws, TrainReport), TrainError> {
    let (mut model, mut report) = train_cascade(faces, cfg, progress)?;
    // The failure detector regresses the true error of a fit: it learns from annotated faces only (those
    // with `starts: None`, which lead the list), never from teacher labels' own errors.
    let annotated = faces
        .iter()
        .position(|f| f.starts.is_some())
        .unwrap_or(faces.len())
        .max(1);
    report.failure_samples = train_failure(&mut model, &faces[..annotated.min(faces.len())], cfg, progress);
    Ok((model, report))
}

#[cfg(test)]
mod tests {
    use super::ridge::ridge_dense;
    use super::*;
    use crate::accuracy::{roc_auc, youden_threshold};

    #[test]
    fn rng_is_deterministic_and_roughly_normal() {
        let mut a = Rng::new(3);
        let mut b = Rng::new(3);
        assert_eq!(a.next_u64(), b.next_u64());
        let xs: Vec<f64> = (0..20000).map(|_| a.normal()).collect();
        let m = xs.iter().sum::<f64>() / xs.len() as f64;
        let v = xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / xs.len() as f64;
        assert!(m.abs() < 0.03 && (v - 1.0).abs() < 0.05, "{m} {v}");
        assert!((0..1000).all(|_| a.below(7) < 7));
    }

    /// λ = 1, solved to round-off, on `threads` threads.
    fn exact(threads: usize) -> Solve {
        Solve {
            lambda: 1.0,
            tol: 1e-12,
            threads,
        }
    }

    #[test]
    fn sparse_ridge_matches_closed_form_on_one_tree() {
        // One tree with 2 leaves: the ridge solution of each leaf is Σy / (count + λ).
        let codes = vec![0u32, 0, 1, 1, 1];
        let mut y = vec![0.0f32; 5 * DELTA_DIM];
        for (i, v) in [1.0f32, 3.0, -2.0, -2.0, -5.0].iter().enumerate() {
            y[i * DELTA_DIM] = *v;
        }
        let (w, _) = ridge_sparse(&codes, 1, 2, &y, None, exact(1));
        assert!((w[0] - 4.0 / 3.0).abs() < 1e-4, "{}", w[0]);
        assert!((w[DELTA_DIM] + 9.0 / 4.0).abs() < 1e-4, "{}", w[DELTA_DIM]);
    }

    #[test]
    fn lid_weights_drop_a_sample_from_the_lid_outputs_only() {
        // One leaf, three samples; the third weighs 0 on the lids: a lid output averages the first two,
        // every other output all three (ridge λ = 1: Σ w·y / (Σ w + 1)).
        let codes = vec![0u32; 3];
        let lid = 2 * LID_POINTS[0];
        let other = 0;
        let mut y = vec![0.0f32; 3 * DELTA_DIM];
        for (i, v) in [2.0f32, 4.0, 30.0].iter().enumerate() {
            y[i * DELTA_DIM + lid] = *v;
            y[i * DELTA_DIM + other] = *v;
        }
        let (w, _) = ridge_sparse(&codes, 1, 1, &y, Some(&[1.0, 1.0, 0.0]), exact(3));
        assert!((w[lid] - 6.0 / 3.0).abs() < 1e-4, "{}", w[lid]);
        assert!((w[other] - 36.0 / 4.0).abs() < 1e-4, "{}", w[other]);
        let (plain, _) = ridge_sparse(&codes, 1, 1, &y, None, exact(2));
        assert!((plain[lid] - 36.0 / 4.0).abs() < 1e-4, "{}", plain[lid]);
    }

    #[test]
    fn dense_ridge_recovers_a_linear_map() {
        let d = 5;
        let mut rng = Rng::new(9);
        let truth = [0.5, -1.0, 0.0, 2.0, 0.25];
        let mut x = Vec::new();
        let mut y = Vec::new();
        for _ in 0..200 {
            let row: Vec<f32> = (0..d).map(|_| rng.normal() as f32).collect();
            y.push(
                3.0 + row
                    .iter()
                    .zip(&truth)
                    .map(|(a, b)| f64::from(*a) * b)
                    .sum::<f64>(),
            );
            x.extend(row);
        }
        let (w, b) = ridge_dense(&x, &y, d, 1e-6);
        for (a, t) in w.iter().zip(&truth) {
            assert!((f64::from(*a) - t).abs() < 1e-3, "{w:?}");
        }
        assert!((b - 3.0).abs() < 1e-3);
    }

    #[test]
    fn auc_and_youden_on_separable_scores() {
        let s = [0.1, 0.2, 0.3, 0.8, 0.9];
        let l = [false, false, false, true, true];
        assert_eq!(roc_auc(&s, &l), Some(1.0));
        let (t, tpr, fpr) = youden_threshold(&s, &l).unwrap();
        assert!(t > 0.3 && t < 0.8 && tpr == 1.0 && fpr == 0.0);
        assert_eq!(roc_auc(&[0.5, 0.5], &[true, false]), Some(0.5));
        assert_eq!(roc_auc(&s, &[false; 5]), None);
    }
}
