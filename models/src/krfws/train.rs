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
//! data ([`youden_threshold`]).

use std::sync::atomic::{AtomicUsize, Ordering};

use super::{
    DELTA_DIM, FAILURE_DIM, FailureModel, Krfws, KrfwsScratch, N_POINTS, Node, Stage, Tree, dot144,
    nme49_inner, stage_features,
};
use crate::geometry::{Point2, Rect, Similarity2, centroid};
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
    /// the lids less than the rest of the face (a lever for teacher labels, measured in BENCHMARKS.md,
    /// "The teacher lids weighed down"); the trees are unchanged.
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

/// Similarity perturbation σ: translation (fraction of the shape's width/height), rotation (degrees),
/// scale (relative).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Perturbation {
    /// Translation σ as a fraction of the shape's extent.
    pub translation: f64,
    /// Rotation σ in degrees.
    pub rotation_deg: f64,
    /// Scale σ.
    pub scale: f64,
}

/// DAN's stage-1 perturbation (algorithms.md 1.7).
pub const DAN_PERTURBATION: Perturbation = Perturbation {
    translation: 0.2,
    rotation_deg: 20.0,
    scale: 0.25,
};

/// Small perturbation: detector-box or previous-frame jitter.
pub const SMALL_PERTURBATION: Perturbation = Perturbation {
    translation: 0.05,
    rotation_deg: 5.0,
    scale: 0.05,
};

/// Medium perturbation, between the small and the DAN one.
pub const MEDIUM_PERTURBATION: Perturbation = Perturbation {
    translation: 0.1,
    rotation_deg: 10.0,
    scale: 0.1,
};

/// Applies a random similarity about the centroid (scale clamped to 0.4..2.5).
pub fn perturb(shape: &[Point2; N_POINTS], p: Perturbation, rng: &mut Rng) -> [Point2; N_POINTS] {
    let r = Rect::bounding(shape).unwrap_or_default();
    let c = centroid(shape);
    let tx = rng.normal() * p.translation * f64::from(r.width());
    let ty = rng.normal() * p.translation * f64::from(r.height());
    let ang = (rng.normal() * p.rotation_deg).to_radians();
    let s = (1.0 + rng.normal() * p.scale).clamp(0.4, 2.5);
    let sim = Similarity2::from_parts(s, ang, 0.0, 0.0);
    std::array::from_fn(|i| {
        let q = sim.apply(Point2::new(shape[i].x - c.x, shape[i].y - c.y));
        Point2::new(q.x + c.x + tx as f32, q.y + c.y + ty as f32)
    })
}

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

struct StageData {
    hog: Vec<f32>,
    targets: Vec<f32>,
    sims: Vec<Option<Similarity2>>,
    norms: Vec<[Point2; N_POINTS]>,
}

fn stage_data(
    faces: &[TrainFace],
    samples: &[Sample],
    dest: &[Point2; N_POINTS],
    scale: f32,
    threads: usize,
    progress: &dyn Progress,
) -> StageData {
    struct Row {
        hog: Vec<f32>,
        target: [f32; DELTA_DIM],
        sim: Option<Similarity2>,
        norm: [Point2; N_POINTS],
    }
    let mut rows: Vec<Row> = (0..samples.len())
        .map(|_| Row {
            hog: Vec::new(),
            target: [0.0; DELTA_DIM],
            sim: None,
            norm: [Point2::default(); N_POINTS],
        })
        .collect();
    progress.begin("features", samples.len() as u64);
    par_for_each(
        &mut rows,
        threads,
        || Box::new([0u8; PATCH_PIXELS]),
        |patch, i, row| {
            let s = &samples[i];
            let face = &faces[s.face];
            row.hog = vec![0.0; FAILURE_DIM];
            let view = face.image.view();
            row.sim = stage_features(&view, &s.shape, dest, patch, &mut row.norm, &mut row.hog);
            if let Some(t) = row.sim {
                for (k, g) in face.landmarks[INNER51].iter().enumerate() {
                    let q = t.apply(*g);
                    row.target[2 * k] = (q.x - row.norm[k].x) / scale;
                    row.target[2 * k + 1] = (q.y - row.norm[k].y) / scale;
                }
            }
            if i % 256 == 0 {
                progress.inc(256.min(samples.len() - i) as u64);
            }
        },
    );
    progress.end("");
    let mut data = StageData {
        hog: Vec::with_capacity(samples.len() * FAILURE_DIM),
        targets: Vec::with_capacity(samples.len() * DELTA_DIM),
        sims: Vec::with_capacity(samples.len()),
        norms: Vec::with_capacity(samples.len()),
    };
    for r in rows {
        data.hog.extend_from_slice(&r.hog);
        data.targets.extend_from_slice(&r.target);
        data.sims.push(r.sim);
        data.norms.push(r.norm);
    }
    data
}

struct TreeBuilder<'a> {
    hog: &'a [f32],
    targets: &'a [f32],
    landmark: usize,
    cfg: &'a TrainConfig,
    rng: Rng,
    nodes: Vec<Node>,
    projections: Vec<f32>,
    n_leaves: u32,
}

impl TreeBuilder<'_> {
    fn x(&self, i: u32) -> &[f32; HOG_DIM] {
        let s = i as usize * FAILURE_DIM + self.landmark * HOG_DIM;
        <&[f32; HOG_DIM]>::try_from(&self.hog[s..s + HOG_DIM]).unwrap_or(&[0.0; HOG_DIM])
    }
    fn y(&self, i: u32) -> [f64; 2] {
        let s = i as usize * DELTA_DIM + 2 * self.landmark;
        [f64::from(self.targets[s]), f64::from(self.targets[s + 1])]
    }

    fn leaf(&mut self) -> i32 {
        let id = self.n_leaves;
        self.n_leaves += 1;
        -(id as i32) - 1
    }

    /// Grows the subtree of `idx`; returns the child code.
    fn grow(&mut self, idx: &mut [u32], depth: usize, root: bool) -> i32 {
        let split = if depth < self.cfg.depth {
            self.split(idx)
        } else {
            None
        };
        let forced = split.is_none();
        let (proj, threshold, n_left) = match split {
            Some(s) => s,
            None if root => (vec![0.0; HOG_DIM], 0.0, idx.len()),
            None => return self.leaf(),
        };
        let me = self.nodes.len();
        self.nodes.push(Node {
            left: 0,
            right: 0,
            threshold,
        });
        self.projections.extend_from_slice(&proj);
        let (l, r) = idx.split_at_mut(n_left);
        let left = if forced {
            self.leaf()
        } else {
            self.grow(l, depth + 1, false)
        };
        let right = if forced {
            self.leaf()
        } else {
            self.grow(r, depth + 1, false)
        };
        self.nodes[me].left = left;
        self.nodes[me].right = right;
        me as i32
    }

    /// Finds the split of `idx` and reorders `idx` so the left child comes first.
    fn split(&mut self, idx: &mut [u32]) -> Option<(Vec<f32>, f32, usize)> {
        let n = idx.len();
        let min_leaf = self.cfg.min_leaf.max(1);
        if n < 2 * min_leaf {
            return None;
        }
        // 2-means on the 2-D targets, initialised on the principal axis.
        let ys: Vec<[f64; 2]> = idx.iter().map(|&i| self.y(i)).collect();
        let mean = ys.iter().fold([0.0; 2], |a, y| [a[0] + y[0], a[1] + y[1]]);
        let mean = [mean[0] / n as f64, mean[1] / n as f64];
        let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
        for y in &ys {
            let (dx, dy) = (y[0] - mean[0], y[1] - mean[1]);
            sxx += dx * dx;
            sxy += dx * dy;
            syy += dy * dy;
        }
        let ang = 0.5 * (2.0 * sxy).atan2(sxx - syy);
        let e = [ang.cos(), ang.sin()];
        let mut label: Vec<bool> = ys
            .iter()
            .map(|y| (y[0] - mean[0]) * e[0] + (y[1] - mean[1]) * e[1] > 0.0)
            .collect();
        let mut c = [[0.0f64; 2]; 2];
        for _ in 0..10 {
            let mut sum = [[0.0f64; 2]; 2];
            let mut cnt = [0usize; 2];
            for (y, &l) in ys.iter().zip(&label) {
                let k = usize::from(l);
                sum[k][0] += y[0];
                sum[k][1] += y[1];
                cnt[k] += 1;
            }
            if cnt[0] == 0 || cnt[1] == 0 {
                return None;
            }
            for k in 0..2 {
                c[k] = [sum[k][0] / cnt[k] as f64, sum[k][1] / cnt[k] as f64];
            }
            let mut changed = false;
            for (y, l) in ys.iter().zip(label.iter_mut()) {
                let d0 = (y[0] - c[0][0]).powi(2) + (y[1] - c[0][1]).powi(2);
                let d1 = (y[0] - c[1][0]).powi(2) + (y[1] - c[1][1]).powi(2);
                let nl = d1 < d0;
                changed |= nl != *l;
                *l = nl;
            }
            if !changed {
                break;
            }
        }
        // Sample weights: misrouting cost (weighted) or 1 (plain).
        let u = [c[1][0] - c[0][0], c[1][1] - c[0][1]];
        let m = [0.5 * (c[0][0] + c[1][0]), 0.5 * (c[0][1] + c[1][1])];
        let mut w: Vec<f64> = if self.cfg.weighted {
            ys.iter()
                .map(|y| 2.0 * ((y[0] - m[0]) * u[0] + (y[1] - m[1]) * u[1]).abs())
                .collect()
        } else {
            vec![1.0; n]
        };
        if self.cfg.weighted {
            let floor = 0.1 * w.iter().sum::<f64>() / n as f64 + 1e-12;
            for v in &mut w {
                *v += floor;
            }
        }
        // Samples entering the discriminant.
        let mut pick: Vec<usize> = (0..n).collect();
        let k = self.cfg.lda_samples.max(4).min(n);
        if k < n {
            for j in 0..k {
                let r = j + self.rng.below(n - j);
                pick.swap(j, r);
            }
            pick.truncate(k);
        }
        let v = self.fisher(idx, &label, &w, &pick)?;
        // Project every sample with the stored (f16) direction: training routes exactly as inference.
        let mut proj: Vec<(f32, u32, usize)> = idx
            .iter()
            .enumerate()
            .map(|(j, &i)| (dot144(&v, self.x(i)), i, j))
            .collect();
        proj.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        // Threshold minimising the children's squared error.
        let (mut tx, mut ty, mut tq) = (0.0f64, 0.0f64, 0.0f64);
        for y in &ys {
            tx += y[0];
            ty += y[1];
            tq += y[0] * y[0] + y[1] * y[1];
        }
        let (mut lx, mut ly, mut lq) = (0.0f64, 0.0f64, 0.0f64);
        let mut best: Option<(f64, usize)> = None;
        for k in 1..n {
            let y = ys[proj[k - 1].2];
            lx += y[0];
            ly += y[1];
            lq += y[0] * y[0] + y[1] * y[1];
            if k < min_leaf || n - k < min_leaf || proj[k - 1].0 >= proj[k].0 {
                continue;
            }
            let (nl, nr) = (k as f64, (n - k) as f64);
            let sse =
                (lq - (lx * lx + ly * ly) / nl) + ((tq - lq) - ((tx - lx).powi(2) + (ty - ly).powi(2)) / nr);
            if best.is_none_or(|(b, _)| sse < b) {
                best = Some((sse, k));
            }
        }
        let (_, k) = best?;
        let threshold = 0.5 * (proj[k - 1].0 + proj[k].0);
        // The midpoint may round onto the upper value; keep the routing rule `≤ threshold` exact.
        let threshold = if threshold >= proj[k].0 {
            proj[k - 1].0
        } else {
            threshold
        };
        for (slot, p) in idx.iter_mut().zip(&proj) {
            *slot = p.1;
        }
        Some((v, threshold, k))
    }

    /// Weighted, shrunk Fisher direction from `pick` (indices into `idx`), rounded to f16 and unit norm.
    fn fisher(&self, idx: &[u32], label: &[bool], w: &[f64], pick: &[usize]) -> Option<Vec<f32>> {
        const D: usize = HOG_DIM;
        let mut mu = [[0.0f64; D]; 2];
        let mut wsum = [0.0f64; 2];
        for &j in pick {
            let k = usize::from(label[j]);
            wsum[k] += w[j];
            for (m, &x) in mu[k].iter_mut().zip(self.x(idx[j])) {
                *m += w[j] * f64::from(x);
            }
        }
        if wsum[0] <= 0.0 || wsum[1] <= 0.0 {
            return None;
        }
        for k in 0..2 {
            for m in &mut mu[k] {
                *m /= wsum[k];
            }
        }
        let mut s = vec![0.0f64; D * D];
        let mut dvec = [0.0f64; D];
        for &j in pick {
            let k = usize::from(label[j]);
            let sw = w[j].sqrt();
            for ((d, &x), m) in dvec.iter_mut().zip(self.x(idx[j])).zip(&mu[k]) {
                *d = sw * (f64::from(x) - m);
            }
            for a in 0..D {
                let da = dvec[a];
                let row = &mut s[a * D..a * D + a + 1];
                for (r, db) in row.iter_mut().zip(&dvec[..=a]) {
                    *r += da * db;
                }
            }
        }
        let total = wsum[0] + wsum[1];
        let mut tr = 0.0;
        for a in 0..D {
            tr += s[a * D + a];
        }
        let g = self.cfg.shrinkage.clamp(0.0, 1.0);
        let ridge = g * tr / total / D as f64 + 1e-9;
        for a in 0..D {
            for b in 0..=a {
                s[a * D + b] *= (1.0 - g) / total;
            }
            s[a * D + a] += ridge;
        }
        let mut b: Vec<f64> = (0..D).map(|a| mu[1][a] - mu[0][a]).collect();
        if !crate::linalg::cholesky_solve(&mut s, D, &mut b) {
            return None;
        }
        let norm = b.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm <= 0.0 || !norm.is_finite() {
            return None;
        }
        let mut v: Vec<f32> = b.iter().map(|x| (x / norm) as f32).collect();
        super::format::round_f16(&mut v);
        Some(v)
    }
}

/// Trains the forests of one landmark; returns the trees and each sample's local leaf per tree
/// (`n · trees`, sample-major).
fn train_forest(
    data: &StageData,
    pool: &[u32],
    l: usize,
    stage: usize,
    cfg: &TrainConfig,
) -> (Vec<Tree>, Vec<u32>) {
    let n = data.sims.len();
    let mut trees = Vec::with_capacity(cfg.trees);
    let mut leaves = vec![0u32; n * cfg.trees];
    for t in 0..cfg.trees {
        let mut rng = Rng::stream(cfg.seed, &[1, stage as u64, l as u64, t as u64]);
        let mut idx: Vec<u32> = (0..pool.len()).map(|_| pool[rng.below(pool.len())]).collect();
        let mut b = TreeBuilder {
            hog: &data.hog,
            targets: &data.targets,
            landmark: l,
            cfg,
            rng,
            nodes: Vec::new(),
            projections: Vec::new(),
            n_leaves: 0,
        };
        b.grow(&mut idx, 0, true);
        let tree = Tree {
            nodes: b.nodes,
            projections: b.projections,
            n_leaves: b.n_leaves,
        };
        for i in 0..n {
            let s = i * FAILURE_DIM + l * HOG_DIM;
            if let Ok(x) = <&[f32; HOG_DIM]>::try_from(&data.hog[s..s + HOG_DIM]) {
                leaves[i * cfg.trees + t] = tree.leaf(x);
            }
        }
        trees.push(tree);
    }
    (trees, leaves)
}

/// How [`ridge_sparse`] solves: ridge `lambda`, relative residual `tol` per column, worker `threads`.
#[derive(Clone, Copy)]
struct Solve {
    lambda: f64,
    tol: f64,
    threads: usize,
}

/// Ridge regression from sparse binary codes (`per` global leaf ids per sample) to `y` (n × 102) by
/// Jacobi-preconditioned multi-right-hand-side conjugate gradients. Returns `W` and the iterations.
/// `lid_weights` (one per sample) weigh each sample's lid outputs ([`LID_POINTS`]): each output column is
/// its own weighted least-squares problem; `None` weighs everything 1. The products run on `threads`
/// threads with the same result bits whatever their number.
fn ridge_sparse(
    codes: &[u32],
    per: usize,
    n_leaves: usize,
    y: &[f32],
    lid_weights: Option<&[f32]>,
    solve: Solve,
) -> (Vec<f32>, usize) {
    const K: usize = DELTA_DIM;
    let Solve { lambda, tol, threads } = solve;
    let n = codes.len() / per.max(1);
    let lids = lid_columns();
    // Scales a sample-major n × K buffer by the sample weights in the lid columns.
    let weigh = |v: &mut [f64]| {
        if let Some(w) = lid_weights {
            for (row, &wi) in v.chunks_exact_mut(K).zip(w) {
                for (x, _) in row.iter_mut().zip(&lids).filter(|(_, l)| **l) {
                    *x *= f64::from(wi);
                }
            }
        }
    };
    let mut diag = vec![lambda; n_leaves];
    for &c in codes {
        diag[c as usize] += 1.0;
    }
    let threads = threads.clamp(1, 64);
    // `Xᵀr`: every thread sums its own block of output columns over all samples in sample order, so the
    // result is the same bits whatever the thread count.
    let xt = |r: &[f64], out: &mut [f64]| {
        let bw = K.div_ceil(threads);
        let parts: Vec<(usize, Vec<f64>)> = std::thread::scope(|sc| {
            let handles: Vec<_> = (0..K)
                .step_by(bw)
                .map(|k0| {
                    sc.spawn(move || {
                        let w = bw.min(K - k0);
                        let mut part = vec![0.0f64; n_leaves * w];
                        for (i, row) in codes.chunks_exact(per).enumerate() {
                            let ri = &r[i * K + k0..i * K + k0 + w];
                            for &c in row {
                                for (o, v) in part[c as usize * w..(c as usize + 1) * w].iter_mut().zip(ri) {
                                    *o += v;
                                }
                            }
                        }
                        (k0, part)
                    })
                })
                .collect();
            handles
                .into_iter()
                .map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
                .collect()
        });
        for (k0, part) in parts {
            let w = part.len() / n_leaves.max(1);
            for (o, src) in out.chunks_exact_mut(K).zip(part.chunks_exact(w.max(1))) {
                o[k0..k0 + w].copy_from_slice(src);
            }
        }
    };
    // `Xp`: rows split over the threads (each row is one sample's own sum).
    let x_mul = |p: &[f64], out: &mut [f64]| {
        let rows = n.div_ceil(threads).max(1);
        std::thread::scope(|sc| {
            for (o, cs) in out.chunks_mut(rows * K).zip(codes.chunks(rows * per)) {
                sc.spawn(move || {
                    for (oi, row) in o.chunks_exact_mut(K).zip(cs.chunks_exact(per)) {
                        oi.fill(0.0);
                        for &c in row {
                            for (o, v) in oi.iter_mut().zip(&p[c as usize * K..(c as usize + 1) * K]) {
                                *o += v;
                            }
                        }
                    }
                });
            }
        });
    };
    let mut yd: Vec<f64> = y.iter().map(|&v| f64::from(v)).collect();
    weigh(&mut yd);
    let mut b = vec![0.0; n_leaves * K];
    xt(&yd, &mut b);
    let mut x = vec![0.0f64; n_leaves * K];
    let mut r = b.clone();
    let mut z: Vec<f64> = r.iter().enumerate().map(|(j, v)| v / diag[j / K]).collect();
    let mut p = z.clone();
    let col_dot = |a: &[f64], b: &[f64]| {
        let mut s = [0.0f64; K];
        for (ra, rb) in a.chunks_exact(K).zip(b.chunks_exact(K)) {
            for k in 0..K {
                s[k] += ra[k] * rb[k];
            }
        }
        s
    };
    let bnorm = col_dot(&b, &b);
    let mut rz = col_dot(&r, &z);
    let mut tmp = vec![0.0f64; n * K];
    let mut q = vec![0.0f64; n_leaves * K];
    let mut iters = 0;
    for it in 0..200 {
        iters = it + 1;
        x_mul(&p, &mut tmp);
        weigh(&mut tmp);
        xt(&tmp, &mut q);
        for (j, qv) in q.iter_mut().enumerate() {
            *qv += lambda * p[j];
        }
        let pq = col_dot(&p, &q);
        let alpha: Vec<f64> = (0..K)
            .map(|k| if pq[k] > 0.0 { rz[k] / pq[k] } else { 0.0 })
            .collect();
        for j in 0..x.len() {
            let k = j % K;
            x[j] += alpha[k] * p[j];
            r[j] -= alpha[k] * q[j];
        }
        let rr = col_dot(&r, &r);
        if (0..K).all(|k| rr[k] <= tol * bnorm[k].max(1e-30)) {
            break;
        }
        for (j, zv) in z.iter_mut().enumerate() {
            *zv = r[j] / diag[j / K];
        }
        let rz_new = col_dot(&r, &z);
        for j in 0..p.len() {
            let k = j % K;
            let beta = if rz[k] > 0.0 { rz_new[k] / rz[k] } else { 0.0 };
            p[j] = z[j] + beta * p[j];
        }
        rz = rz_new;
    }
    (x.iter().map(|&v| v as f32).collect(), iters)
}

/// Trains the cascade (no failure detector yet: call [`train_failure`]). `faces` are the training faces
/// (mirrors are added here).
pub fn train_cascade(
    faces: &[TrainFace],
    cfg: &TrainConfig,
    progress: &dyn Progress,
) -> Result<(Krfws, TrainReport), TrainError> {
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
    let mut all: Vec<TrainFace> = Vec::with_capacity(faces.len() * 2);
    for f in faces {
        all.push(f.clone());
        all.push(mirror_face(f));
    }
    let mean = super::default_mean_shape();
    let proto = Krfws::new(mean, Vec::new(), empty_failure());
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
    let n = samples.len();
    // Per-sample lid weights, only when some face weighs its lids differently (else the plain solve).
    let lid_weights: Option<Vec<f32>> = all
        .iter()
        .any(|f| f.lid_weight != 1.0)
        .then(|| samples.iter().map(|s| all[s.face].lid_weight).collect());
    let lids = lid_columns();
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
                            let (t, lv) = train_forest(&data, &pool, l, si, cfg);
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
            return Err(TrainError::Config("a forest worker failed"));
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
        let mut codes = vec![0u32; n * per];
        for (l, ts, lv) in &mut results {
            for i in 0..n {
                for t in 0..cfg.trees {
                    codes[i * per + *l * cfg.trees + t] = offsets[*l * cfg.trees + t] + lv[i * cfg.trees + t];
                }
            }
            trees.append(ts);
        }
        progress.end(&format!("{total} leaves"));
        progress.begin(&format!("stage {} regression", si + 1), 1);
        let population = (n * per) as f64 / f64::from(total.max(1));
        let mut mses = Vec::new();
        let mut chosen = cfg.ridge[0];
        if select {
            let (mut tc, mut ty, mut tw, mut hc, mut hy, mut hw) = (
                Vec::new(),
                Vec::new(),
                Vec::new(),
                Vec::new(),
                Vec::new(),
                Vec::new(),
            );
            for i in 0..n {
                let (c, y) = (
                    &codes[i * per..(i + 1) * per],
                    &data.targets[i * DELTA_DIM..(i + 1) * DELTA_DIM],
                );
                let w = all[samples[i].face].lid_weight;
                if held(i) {
                    hc.extend_from_slice(c);
                    hy.extend_from_slice(y);
                    hw.push(w);
                } else {
                    tc.extend_from_slice(c);
                    ty.extend_from_slice(y);
                    tw.push(w);
                }
            }
            let tw = lid_weights.is_some().then_some(tw.as_slice());
            let mut best = f64::INFINITY;
            for &r in &cfg.ridge {
                let (w, _) = ridge_sparse(
                    &tc,
                    per,
                    total as usize,
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
        }
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

fn empty_failure() -> FailureModel {
    FailureModel {
        weights: vec![0.0; FAILURE_DIM],
        intercept: 0.0,
        threshold: f32::INFINITY,
    }
}

/// Kind of a perturbed fit for the failure detector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FitKind {
    /// Small jitter of the box initialisation.
    Small,
    /// DAN σ perturbation.
    Full,
    /// Twice DAN σ: mostly gross failures.
    Gross,
    /// Box moved off the face onto background: a non-face patch.
    NonFace,
}

/// One perturbed fit.
#[derive(Clone, Debug)]
pub struct PerturbedFit {
    /// Index of the face.
    pub face: usize,
    /// How the start shape was made.
    pub kind: FitKind,
    /// Failure score of the fit.
    pub score: f32,
    /// NME49 of the fit against the ground truth.
    pub nme: f64,
}

/// Start shape of fit `j` of a face (kinds cycle Small, Full, Gross, NonFace).
pub fn perturbed_init(
    model: &Krfws,
    face: &TrainFace,
    j: usize,
    rng: &mut Rng,
) -> (FitKind, [Point2; N_POINTS]) {
    let bbox = gt_box(&face.landmarks);
    let base = model.init_from_box(&bbox);
    match j % 4 {
        0 => (FitKind::Small, perturb(&base, SMALL_PERTURBATION, rng)),
        1 => (FitKind::Full, perturb(&base, DAN_PERTURBATION, rng)),
        2 => {
            let gross = Perturbation {
                translation: 0.4,
                rotation_deg: 40.0,
                scale: 0.5,
            };
            (FitKind::Gross, perturb(&base, gross, rng))
        }
        _ => {
            let ang = rng.uniform() * std::f64::consts::TAU;
            let dist = 0.8 + 0.7 * rng.uniform();
            let (dx, dy) = (
                (ang.cos() * dist * f64::from(bbox.width())) as f32,
                (ang.sin() * dist * f64::from(bbox.height())) as f32,
            );
            (FitKind::NonFace, base.map(|p| Point2::new(p.x + dx, p.y + dy)))
        }
    }
}

/// Runs `per_face` perturbed fits per face through `model`, keeping the last stage's HOG when `keep_hog`.
pub fn perturbed_fits(
    model: &Krfws,
    faces: &[TrainFace],
    per_face: usize,
    seed: u64,
    threads: usize,
    keep_hog: bool,
    progress: &dyn Progress,
) -> (Vec<PerturbedFit>, Vec<f32>) {
    let mut rows: Vec<(PerturbedFit, Vec<f32>)> = (0..faces.len() * per_face)
        .map(|i| {
            (
                PerturbedFit {
                    face: i / per_face.max(1),
                    kind: FitKind::Small,
                    score: 0.0,
                    nme: 0.0,
                },
                Vec::new(),
            )
        })
        .collect();
    progress.begin("perturbed fits", rows.len() as u64);
    par_for_each(&mut rows, threads, KrfwsScratch::new, |scratch, i, row| {
        let f = i / per_face.max(1);
        let j = i % per_face.max(1);
        let face = &faces[f];
        let mut rng = Rng::stream(seed, &[7, f as u64, j as u64]);
        let (kind, init) = perturbed_init(model, face, j, &mut rng);
        let mut out = [Point2::default(); N_POINTS];
        let score = model.align(&face.image.view(), &init, scratch, &mut out);
        row.0 = PerturbedFit {
            face: f,
            kind,
            score,
            nme: nme49_inner(&out, &face.landmarks),
        };
        if keep_hog {
            row.1 = scratch.last_hog().to_vec();
        }
        if i % 64 == 0 {
            progress.inc(64);
        }
    });
    progress.end("");
    let mut fits = Vec::with_capacity(rows.len());
    let mut hog = Vec::with_capacity(if keep_hog { rows.len() * FAILURE_DIM } else { 0 });
    for (f, h) in rows {
        fits.push(f);
        hog.extend_from_slice(&h);
    }
    (fits, hog)
}

/// Fits the failure detector on perturbed fits of `faces` (mirrors added) and installs it in `model`
/// (threshold left at +∞; choose it on validation data). Returns the number of fits used.
pub fn train_failure(
    model: &mut Krfws,
    faces: &[TrainFace],
    cfg: &TrainConfig,
    progress: &dyn Progress,
) -> usize {
    let mut all: Vec<TrainFace> = Vec::with_capacity(faces.len() * 2);
    for f in faces {
        all.push(f.clone());
        all.push(mirror_face(f));
    }
    let (fits, hog) = perturbed_fits(
        model,
        &all,
        cfg.failure_fits.max(4),
        cfg.seed ^ 0xFA11,
        cfg.threads,
        true,
        progress,
    );
    let y: Vec<f64> = fits
        .iter()
        .map(|f| f.nme.min(f64::from(FAILURE_TARGET_CAP)))
        .collect();
    progress.begin("failure detector", 1);
    let (w, b) = ridge_dense(&hog, &y, FAILURE_DIM, cfg.failure_ridge);
    progress.inc(1);
    progress.end("");
    model.set_failure(FailureModel {
        weights: w,
        intercept: b,
        threshold: f32::INFINITY,
    });
    fits.len()
}

/// Ridge regression with intercept on dense rows (`x`: n × d) by CG on the centred normal equations.
fn ridge_dense(x: &[f32], y: &[f64], d: usize, factor: f64) -> (Vec<f32>, f32) {
    let n = y.len();
    if n == 0 {
        return (vec![0.0; d], 0.0);
    }
    let mut mx = vec![0.0f64; d];
    for row in x.chunks_exact(d) {
        for (m, &v) in mx.iter_mut().zip(row) {
            *m += f64::from(v);
        }
    }
    for m in &mut mx {
        *m /= n as f64;
    }
    let my = y.iter().sum::<f64>() / n as f64;
    // A v = Xcᵀ Xc v + λ v, with Xc = X − 1 mxᵀ.
    let apply = |v: &[f64], out: &mut [f64], s: &mut [f64]| {
        let mv: f64 = mx.iter().zip(v).map(|(a, b)| a * b).sum();
        for (si, row) in s.iter_mut().zip(x.chunks_exact(d)) {
            *si = dot_f32_f64(row, v) - mv;
        }
        out.fill(0.0);
        for (&si, row) in s.iter().zip(x.chunks_exact(d)) {
            for (o, &a) in out.iter_mut().zip(row) {
                *o += si * f64::from(a);
            }
        }
        // Xcᵀ s = Xᵀ s − mx · Σ s.
        let ssum: f64 = s.iter().sum();
        for (o, m) in out.iter_mut().zip(&mx) {
            *o -= ssum * m;
        }
    };
    let mut diag_mean = 0.0;
    for row in x.chunks_exact(d) {
        for (&a, m) in row.iter().zip(&mx) {
            diag_mean += (f64::from(a) - m).powi(2);
        }
    }
    diag_mean /= d as f64;
    let lambda = factor * diag_mean + 1e-9;
    let mut b = vec![0.0f64; d];
    for (row, &t) in x.chunks_exact(d).zip(y) {
        for ((o, &a), m) in b.iter_mut().zip(row).zip(&mx) {
            *o += (f64::from(a) - m) * (t - my);
        }
    }
    let mut w = vec![0.0f64; d];
    let mut r = b.clone();
    let mut p = r.clone();
    let mut rr: f64 = r.iter().map(|v| v * v).sum();
    let bn = rr.max(1e-300);
    let mut q = vec![0.0f64; d];
    let mut sbuf = vec![0.0f64; n];
    for _ in 0..300 {
        apply(&p, &mut q, &mut sbuf);
        for (qv, pv) in q.iter_mut().zip(&p) {
            *qv += lambda * pv;
        }
        let pq: f64 = p.iter().zip(&q).map(|(a, b)| a * b).sum();
        if pq <= 0.0 {
            break;
        }
        let alpha = rr / pq;
        for j in 0..d {
            w[j] += alpha * p[j];
            r[j] -= alpha * q[j];
        }
        let rr_new: f64 = r.iter().map(|v| v * v).sum();
        if rr_new <= 1e-10 * bn {
            break;
        }
        let beta = rr_new / rr;
        for j in 0..d {
            p[j] = r[j] + beta * p[j];
        }
        rr = rr_new;
    }
    let intercept = my - w.iter().zip(&mx).map(|(a, b)| a * b).sum::<f64>();
    (w.iter().map(|&v| v as f32).collect(), intercept as f32)
}

fn dot_f32_f64(a: &[f32], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    for (x, y) in a.chunks_exact(4).zip(b.chunks_exact(4)) {
        for k in 0..4 {
            acc[k] += f64::from(x[k]) * y[k];
        }
    }
    let tail = a.len() / 4 * 4;
    let rest: f64 = a[tail..]
        .iter()
        .zip(&b[tail..])
        .map(|(x, y)| f64::from(*x) * y)
        .sum();
    acc.iter().sum::<f64>() + rest
}

/// ROC AUC of `scores` for the positive `labels` (higher score = more positive), ties counted half.
/// `None` when one class is empty.
pub fn roc_auc(scores: &[f32], labels: &[bool]) -> Option<f64> {
    let mut v: Vec<(f32, bool)> = scores.iter().copied().zip(labels.iter().copied()).collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let pos = v.iter().filter(|x| x.1).count();
    let neg = v.len() - pos;
    if pos == 0 || neg == 0 {
        return None;
    }
    let mut rank_sum = 0.0f64;
    let mut i = 0;
    while i < v.len() {
        let mut j = i;
        while j < v.len() && v[j].0 == v[i].0 {
            j += 1;
        }
        let avg = (i + j + 1) as f64 / 2.0;
        rank_sum += avg * v[i..j].iter().filter(|x| x.1).count() as f64;
        i = j;
    }
    Some((rank_sum - (pos * (pos + 1)) as f64 / 2.0) / (pos as f64 * neg as f64))
}

/// Threshold maximising Youden's J (TPR − FPR) for "score ≥ threshold ⇒ failure" on labelled scores;
/// returns `(threshold, tpr, fpr)`.
pub fn youden_threshold(scores: &[f32], labels: &[bool]) -> Option<(f32, f64, f64)> {
    let mut v: Vec<(f32, bool)> = scores.iter().copied().zip(labels.iter().copied()).collect();
    v.sort_by(|a, b| b.0.total_cmp(&a.0));
    let pos = v.iter().filter(|x| x.1).count() as f64;
    let neg = v.len() as f64 - pos;
    if pos == 0.0 || neg == 0.0 {
        return None;
    }
    let (mut tp, mut fp) = (0.0, 0.0);
    let mut best = (f64::NEG_INFINITY, f32::INFINITY, 0.0, 0.0);
    for k in 0..v.len() {
        if v[k].1 {
            tp += 1.0;
        } else {
            fp += 1.0;
        }
        if k + 1 < v.len() && v[k + 1].0 == v[k].0 {
            continue;
        }
        let j = tp / pos - fp / neg;
        if j > best.0 {
            let thr = match v.get(k + 1) {
                Some(next) => 0.5 * (v[k].0 + next.0),
                None => v[k].0,
            };
            best = (j, thr, tp / pos, fp / neg);
        }
    }
    Some((best.1, best.2, best.3))
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
    use super::*;

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
