//! The KRFWS local aligner: HoloFace's simplified K-cluster Regression Forests with Weighted Splitting
//! (algorithms.md 2.2–2.4), trained by [`train`], loaded with [`Krfws::from_bytes`].
//!
//! **Inference** ([`Krfws::align`]), per face:
//! 1. the start shape is the model's 51-point mean shape similarity-fitted to the caller's `init`
//!    (HoloFace's `fitWithAffine`: the init supplies location, scale and in-plane rotation, never shape);
//! 2. for each of the 3 stages (scales 0.35 / 0.55 / 0.8): `T` = least-squares similarity from the current
//!    shape onto the stage's destination shape `(meanS − min(meanS) + 0.5·range(meanS))·scale`; each
//!    landmark's 16×16 HOG window is sampled **directly** from the full frame through `T⁻¹` (bilinear,
//!    zero fill, rounded to 8 bits: exactly the pixels `warp_bilinear` would write into an unbounded
//!    normalised-frame canvas, without warping the whole window); per landmark, its forest's trees route
//!    the landmark's own 144-d HOG row with oblique tests `proj·hog ≤ threshold`; the reached leaves
//!    select rows of the stage's global matrix `W` whose sum (102 values, x/y interleaved) times the stage
//!    scale is added to the shape in the normalised frame, which is then mapped back through `T⁻¹`;
//! 3. the failure score is `w·hog + b` over the last stage's 51×144 HOG taken **before** its update
//!    (HoloFace's ranking); it regresses the expected NME49 of the result (see [`FailureModel`]).
//!
//! All per-call buffers live in [`KrfwsScratch`]; `align` does not allocate.

pub mod format;
pub mod train;

use crate::crop::BilinearSampler;
use crate::geometry::{Point2, Rect, Similarity2};
use crate::hog::{HOG_DIM, PATCH, PATCH_PIXELS, hog_patch, round_coord};
use crate::image::GrayView;
use crate::shape::{INNER51, dan_mean_shape};

pub use format::ModelError;

/// Landmarks tracked (iBUG 17..=67).
pub const N_POINTS: usize = 51;
/// Length of the shape update (x/y interleaved).
pub const DELTA_DIM: usize = 2 * N_POINTS;
/// Length of the failure detector's input (51 HOG rows).
pub const FAILURE_DIM: usize = N_POINTS * HOG_DIM;
/// HoloFace's stage scales.
pub const DEFAULT_SCALES: [f32; 3] = [0.35, 0.55, 0.80];
/// Horizontal extent of the mean shape, in HoloFace's mean-shape units (`meanS.bin` spans ±61.07).
pub const MEAN_SHAPE_WIDTH: f32 = 122.14;

/// One internal node of a tree: `proj·hog ≤ threshold` goes `left`, else `right`.
///
/// A child `c ≥ 0` is the index of an internal node of the same tree (always greater than the parent's
/// index, which the loader checks, so routing terminates); `c < 0` is the leaf `−c − 1`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Node {
    /// Left child (see the type docs).
    pub left: i32,
    /// Right child.
    pub right: i32,
    /// Split threshold on the projection.
    pub threshold: f32,
}

/// One oblique regression tree.
#[derive(Clone, Debug, PartialEq)]
pub struct Tree {
    /// Internal nodes, root first.
    pub nodes: Vec<Node>,
    /// One 144-d projection per internal node, node-major.
    pub projections: Vec<f32>,
    /// Number of leaves (leaf ids are `0..n_leaves`).
    pub n_leaves: u32,
}

impl Tree {
    /// The leaf `hog` reaches. The tree must be valid (the loader and the trainer guarantee it); an
    /// out-of-range child stops at leaf 0 instead of panicking.
    #[inline]
    pub fn leaf(&self, hog: &[f32; HOG_DIM]) -> u32 {
        let mut idx = 0usize;
        loop {
            let Some(node) = self.nodes.get(idx) else { return 0 };
            let Some(proj) = self.projections.get(idx * HOG_DIM..(idx + 1) * HOG_DIM) else {
                return 0;
            };
            let next = if dot144(proj, hog) <= node.threshold {
                node.left
            } else {
                node.right
            };
            if next < 0 {
                return (-(next + 1)) as u32;
            }
            idx = next as usize;
        }
    }
}

/// One cascade stage: 51 forests of `trees_per_forest` trees and the global regression matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct Stage {
    /// Normalised-frame scale of the stage.
    pub scale: f32,
    /// Trees per landmark forest.
    pub trees_per_forest: usize,
    /// `N_POINTS · trees_per_forest` trees, landmark-major.
    pub trees: Vec<Tree>,
    /// `n_leaves × 102` row-major regression matrix, in mean-shape units (multiplied by `scale` at use).
    pub weights: Vec<f32>,
    /// Global index of each tree's leaf 0 (prefix sums of `n_leaves`); derived.
    leaf_offsets: Vec<u32>,
    /// The stage's destination shape in the normalised frame; derived from the mean shape and scale.
    dest: [Point2; N_POINTS],
}

impl Stage {
    /// Builds a stage; `weights` must hold `Σ n_leaves · 102` values (checked by the loader/trainer).
    pub fn new(
        mean: &[Point2; N_POINTS],
        scale: f32,
        trees_per_forest: usize,
        trees: Vec<Tree>,
        weights: Vec<f32>,
    ) -> Self {
        let mut leaf_offsets = Vec::with_capacity(trees.len());
        let mut acc = 0u32;
        for t in &trees {
            leaf_offsets.push(acc);
            acc = acc.saturating_add(t.n_leaves);
        }
        Self {
            scale,
            trees_per_forest,
            trees,
            weights,
            leaf_offsets,
            dest: stage_dest(mean, scale),
        }
    }

    /// Total leaves over all trees.
    pub fn n_leaves(&self) -> usize {
        self.trees.iter().map(|t| t.n_leaves as usize).sum()
    }

    /// The destination shape of this stage's normalised frame.
    pub fn dest(&self) -> &[Point2; N_POINTS] {
        &self.dest
    }

    /// Global leaf indices reached by the 51 HOG rows, one per tree, into `leaves`
    /// (`trees.len()` entries).
    ///
    /// Level-synchronous: every tree advances one level per pass, so the projection loads of different
    /// trees are independent and overlap in memory (the stage's projections do not fit in cache).
    pub fn leaves(&self, hog: &[f32], leaves: &mut [u32]) {
        const DONE: u32 = 1 << 31;
        let t = self.trees_per_forest.max(1);
        leaves.fill(0);
        loop {
            let mut active = false;
            for (k, (tree, state)) in self.trees.iter().zip(leaves.iter_mut()).enumerate() {
                if *state & DONE != 0 {
                    continue;
                }
                let l = k / t;
                let idx = *state as usize;
                let (Some(node), Some(proj), Some(row)) = (
                    tree.nodes.get(idx),
                    tree.projections.get(idx * HOG_DIM..(idx + 1) * HOG_DIM),
                    hog.get(l * HOG_DIM..(l + 1) * HOG_DIM)
                        .and_then(|r| <&[f32; HOG_DIM]>::try_from(r).ok()),
                ) else {
                    *state = DONE;
                    continue;
                };
                let next = if dot144(proj, row) <= node.threshold {
                    node.left
                } else {
                    node.right
                };
                *state = if next < 0 {
                    DONE | (-(next + 1)) as u32
                } else {
                    active = true;
                    next as u32
                };
            }
            if !active {
                break;
            }
        }
        for (state, off) in leaves.iter_mut().zip(&self.leaf_offsets) {
            *state = off + (*state & !DONE);
        }
    }

    /// Adds the `W` rows of `leaves` into `delta` (102 values).
    pub fn accumulate(&self, leaves: &[u32], delta: &mut [f32; DELTA_DIM]) {
        delta.fill(0.0);
        for &leaf in leaves {
            let s = leaf as usize * DELTA_DIM;
            if let Some(row) = self.weights.get(s..s + DELTA_DIM) {
                for (d, w) in delta.iter_mut().zip(row) {
                    *d += w;
                }
            }
        }
    }
}

/// The failure detector: `score = weights·hog + intercept`, a ridge regression of the fit's NME49
/// (clipped at [`train::FAILURE_TARGET_CAP`]) on the last stage's HOG. The fit is accepted when
/// `score < threshold`.
#[derive(Clone, Debug, PartialEq)]
pub struct FailureModel {
    /// 51·144 weights, landmark-major like the HOG.
    pub weights: Vec<f32>,
    /// Intercept.
    pub intercept: f32,
    /// Acceptance threshold chosen on validation data.
    pub threshold: f32,
}

impl FailureModel {
    /// Score of a 51×144 HOG.
    pub fn score(&self, hog: &[f32]) -> f32 {
        let mut acc = [0.0f32; 8];
        for (w, h) in self.weights.chunks_exact(8).zip(hog.chunks_exact(8)) {
            for k in 0..8 {
                acc[k] += w[k] * h[k];
            }
        }
        acc.iter().sum::<f32>() + self.intercept
    }
}

/// A trained KRFWS model. Build with [`Krfws::from_bytes`] or the trainer.
#[derive(Clone, Debug, PartialEq)]
pub struct Krfws {
    mean: [Point2; N_POINTS],
    stages: Vec<Stage>,
    failure: FailureModel,
    /// Inner 51 points of DAN's 68-point mean, relative to the 68-point extent centre, and that extent.
    box_template: ([Point2; N_POINTS], f32, f32),
}

/// Per-call buffers of [`Krfws::align`]; create once per thread with [`KrfwsScratch::new`].
#[derive(Clone, Debug)]
pub struct KrfwsScratch {
    patch: Box<[u8; PATCH_PIXELS]>,
    hog: Vec<f32>,
    last_hog: Vec<f32>,
    leaves: Vec<u32>,
    delta: [f32; DELTA_DIM],
    shape: [Point2; N_POINTS],
    norm: [Point2; N_POINTS],
}

impl Default for KrfwsScratch {
    fn default() -> Self {
        Self::new()
    }
}

impl KrfwsScratch {
    /// Fresh buffers (about 60 KB).
    pub fn new() -> Self {
        Self {
            patch: Box::new([0; PATCH_PIXELS]),
            hog: vec![0.0; FAILURE_DIM],
            last_hog: vec![0.0; FAILURE_DIM],
            leaves: Vec::with_capacity(N_POINTS * 64),
            delta: [0.0; DELTA_DIM],
            shape: [Point2::default(); N_POINTS],
            norm: [Point2::default(); N_POINTS],
        }
    }

    /// The last stage's 51×144 HOG of the previous `align` call (the failure detector's input).
    pub fn last_hog(&self) -> &[f32] {
        &self.last_hog
    }
}

/// HoloFace's normalised-frame destination: `(meanS − min(meanS) + 0.5·range(meanS))·scale`.
pub fn stage_dest(mean: &[Point2; N_POINTS], scale: f32) -> [Point2; N_POINTS] {
    let r = Rect::bounding(mean).unwrap_or_default();
    let (w, h) = (r.width(), r.height());
    std::array::from_fn(|i| {
        Point2::new(
            (mean[i].x - r.x0 + 0.5 * w) * scale,
            (mean[i].y - r.y0 + 0.5 * h) * scale,
        )
    })
}

/// The 51-point mean shape in HoloFace's units: DAN's committed mean (inner 51 points), centred on its
/// centroid and scaled to [`MEAN_SHAPE_WIDTH`].
pub fn default_mean_shape() -> [Point2; N_POINTS] {
    let m = dan_mean_shape();
    let inner = &m[INNER51];
    let c = crate::geometry::centroid(inner);
    let r = Rect::bounding(inner).unwrap_or_default();
    let s = if r.width() > 0.0 {
        MEAN_SHAPE_WIDTH / r.width()
    } else {
        1.0
    };
    std::array::from_fn(|i| Point2::new((inner[i].x - c.x) * s, (inner[i].y - c.y) * s))
}

fn box_template() -> ([Point2; N_POINTS], f32, f32) {
    let m = dan_mean_shape();
    let r = Rect::bounding(&m).unwrap_or_default();
    let c = r.centre();
    let inner = &m[INNER51];
    (
        std::array::from_fn(|i| Point2::new(inner[i].x - c.x, inner[i].y - c.y)),
        r.width().max(1e-6),
        r.height().max(1e-6),
    )
}

/// Dot product of two 144-vectors with 8 independent accumulators (vectorises).
#[inline(always)]
pub(crate) fn dot144(a: &[f32], b: &[f32; HOG_DIM]) -> f32 {
    let mut acc = [0.0f32; 8];
    for (x, y) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    (acc[0] + acc[4]) + (acc[1] + acc[5]) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// Samples the 16×16 window at the rounded normalised-frame point `p` from the image through the
/// sampler (`image_from_norm`): exactly the pixels `crop::warp_bilinear` would write into an unbounded
/// normalised-frame canvas, without warping the whole window.
#[inline]
pub fn sample_window(sampler: &BilinearSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
    let (u0, v0) = (round_coord(p.x) - 8, round_coord(p.y) - 8);
    for (dv, row) in out.chunks_exact_mut(PATCH).enumerate() {
        sampler.row(u0, v0 + dv as i64, row);
    }
}

/// Normalised-frame features of one stage: fits `norm_from_image` (current shape → `dest`), writes the
/// shape in the normalised frame into `norm` and the 51×144 HOG into `hog`. Returns the similarity, or
/// `None` for a degenerate shape.
pub fn stage_features(
    image: &GrayView<'_>,
    shape: &[Point2; N_POINTS],
    dest: &[Point2; N_POINTS],
    patch: &mut [u8; PATCH_PIXELS],
    norm: &mut [Point2; N_POINTS],
    hog: &mut [f32],
) -> Option<Similarity2> {
    let t = Similarity2::fit(shape, dest)?;
    let inv = t.inverse()?;
    let inv32 = inv.to_f32_array();
    if !inv32.iter().all(|v| v.is_finite()) {
        return None;
    }
    t.apply_all(shape, norm);
    let sampler = BilinearSampler::new(image, inv32);
    for (p, row) in norm.iter().zip(hog.chunks_exact_mut(HOG_DIM)) {
        sample_window(&sampler, *p, patch);
        if let Ok(r) = <&mut [f32; HOG_DIM]>::try_from(row) {
            hog_patch(patch, r);
        }
    }
    Some(t)
}

impl Krfws {
    /// Assembles a model (used by the trainer and the loader; the loader validates first).
    pub fn new(mean: [Point2; N_POINTS], stages: Vec<Stage>, failure: FailureModel) -> Self {
        Self {
            mean,
            stages,
            failure,
            box_template: box_template(),
        }
    }

    /// The 51-point mean shape (mean-shape units, centred).
    pub fn mean_shape(&self) -> &[Point2; N_POINTS] {
        &self.mean
    }

    /// The cascade stages.
    pub fn stages(&self) -> &[Stage] {
        &self.stages
    }

    /// The failure detector.
    pub fn failure(&self) -> &FailureModel {
        &self.failure
    }

    /// Replaces the failure detector (trainer use).
    pub fn set_failure(&mut self, failure: FailureModel) {
        self.failure = failure;
    }

    /// Acceptance threshold on the failure score: the fit is good when `score < threshold()`.
    pub fn threshold(&self) -> f32 {
        self.failure.threshold
    }

    /// Sets the acceptance threshold.
    pub fn set_threshold(&mut self, t: f32) {
        self.failure.threshold = t;
    }

    /// Initial shape from a face box, DAN's `bestFitRect` rule: DAN's 68-point mean shape is placed
    /// with its extent centre on the box centre, scaled by the mean of the width and height ratios,
    /// without rotation; its inner 51 points are returned. The box is the 68-point face extent (the
    /// 300-W ground-truth box convention); a detector with another box convention must be calibrated to
    /// it by the caller.
    pub fn init_from_box(&self, bbox: &Rect) -> [Point2; N_POINTS] {
        let (tpl, w, h) = &self.box_template;
        let s = 0.5 * (bbox.width() / w + bbox.height() / h);
        let c = bbox.centre();
        std::array::from_fn(|i| Point2::new(tpl[i].x * s + c.x, tpl[i].y * s + c.y))
    }

    /// Initial shape from the previous frame's landmarks: the mean shape similarity-fitted to them
    /// (HoloFace's tracking rule). A degenerate input is returned unchanged.
    pub fn init_from_previous(&self, previous: &[Point2; N_POINTS]) -> [Point2; N_POINTS] {
        match Similarity2::fit(&self.mean, previous) {
            Some(s) => std::array::from_fn(|i| s.apply(self.mean[i])),
            None => *previous,
        }
    }

    /// Aligns the 51 inner landmarks starting from `init` (full-frame pixels), writing the result to
    /// `out` (full-frame pixels) and returning the failure score (lower is better; compare with
    /// [`Krfws::threshold`]). A degenerate init or transform returns `f32::INFINITY` with `out` = the
    /// start shape. Does not allocate.
    pub fn align(
        &self,
        image: &GrayView<'_>,
        init: &[Point2; N_POINTS],
        scratch: &mut KrfwsScratch,
        out: &mut [Point2; N_POINTS],
    ) -> f32 {
        scratch.shape = self.init_from_previous(init);
        let n = self.stages.len();
        let score = self.run_stages(image, scratch, 0..n, true);
        *out = scratch.shape;
        score.unwrap_or(f32::INFINITY)
    }

    /// Runs `stages` on `scratch.shape` in place. With `score`, returns the failure score of the last
    /// stage run (else 0).
    fn run_stages(
        &self,
        image: &GrayView<'_>,
        scratch: &mut KrfwsScratch,
        stages: std::ops::Range<usize>,
        score: bool,
    ) -> Option<f32> {
        let mut result = 0.0;
        let last = stages.end.saturating_sub(1);
        for k in stages {
            let stage = self.stages.get(k)?;
            let t = stage_features(
                image,
                &scratch.shape,
                &stage.dest,
                &mut scratch.patch,
                &mut scratch.norm,
                &mut scratch.hog,
            )?;
            if k == last && score {
                result = self.failure.score(&scratch.hog);
                scratch.last_hog.copy_from_slice(&scratch.hog);
            }
            scratch.leaves.resize(stage.trees.len(), 0);
            stage.leaves(&scratch.hog, &mut scratch.leaves);
            stage.accumulate(&scratch.leaves, &mut scratch.delta);
            let inv = t.inverse()?;
            for (i, p) in scratch.norm.iter().enumerate() {
                let q = Point2::new(
                    p.x + scratch.delta[2 * i] * stage.scale,
                    p.y + scratch.delta[2 * i + 1] * stage.scale,
                );
                scratch.shape[i] = inv.apply(q);
            }
        }
        Some(result)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::crop::warp_bilinear;

    #[test]
    fn direct_window_sampling_equals_a_warped_canvas() {
        let (w, h) = (64usize, 48usize);
        let img: Vec<u8> = (0..w * h).map(|i| ((i * 37) % 251) as u8).collect();
        let v = GrayView::new(&img, w, h, w).unwrap();
        let t = Similarity2::from_parts(0.8, 0.3, 5.0, -2.0);
        let (cw, ch) = (60usize, 60usize);
        let mut canvas = vec![0u8; cw * ch];
        warp_bilinear(&v, &t, cw, ch, &mut canvas).unwrap();
        let inv = t.inverse().unwrap().to_f32_array();
        let mut win = [0u8; PATCH_PIXELS];
        let p = Point2::new(20.3, 30.6);
        sample_window(&BilinearSampler::new(&v, inv), p, &mut win);
        for dv in 0..16 {
            for du in 0..16 {
                let (x, y) = (20 - 8 + du, 31 - 8 + dv);
                assert_eq!(win[dv * 16 + du], canvas[y * cw + x], "({du}, {dv})");
            }
        }
    }

    #[test]
    fn stage_destination_matches_holoface_window_rule() {
        let m = default_mean_shape();
        let r = Rect::bounding(&m).unwrap();
        assert!((r.width() - MEAN_SHAPE_WIDTH).abs() < 1e-3);
        let d = stage_dest(&m, 0.35);
        let rd = Rect::bounding(&d).unwrap();
        // The shape sits in the middle of a window twice its size.
        assert!((rd.x0 - 0.5 * r.width() * 0.35).abs() < 1e-3);
        assert!((rd.width() - r.width() * 0.35).abs() < 1e-3);
    }
}
