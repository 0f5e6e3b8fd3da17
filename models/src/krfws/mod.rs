//! The KRFWS local aligner: HoloFace's simplified K-cluster Regression Forests with Weighted Splitting
//! (algorithms.md 2.2–2.4), trained by `train` (feature `train`), loaded with [`Krfws::from_bytes`].
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
//! **Speed** (ARCHITECTURE.md, "KRFWS inference cost"): sampling, HOG and routing of a stage run
//! software-pipelined ([`Stage::features_and_leaves`]) through the [`Kernels`] of the CPU ([`Portable`],
//! the AVX-512 or AVX2 ones on x86-64, the NEON ones on aarch64; all bit-identical), with the nodes and `W` streamed as the stored f16 values.
//!
//! All per-call buffers live in [`KrfwsScratch`]; `align` does not allocate.

#[cfg(target_arch = "x86_64")]
mod avx2;
#[cfg(target_arch = "x86_64")]
mod avx512;
pub mod format;
#[cfg(target_arch = "aarch64")]
pub(crate) mod neon;
mod stage;
#[cfg(feature = "train")]
pub mod train;

#[cfg(target_arch = "x86_64")]
pub use avx2::Avx2;
#[cfg(target_arch = "x86_64")]
pub use avx512::Avx512;
#[cfg(target_arch = "aarch64")]
pub use neon::Neon;

use crate::geometry::{Point2, Rect, Similarity2};
use crate::hog::{HOG_DIM, PATCH, PATCH_PIXELS, hog_patch, round_coord};
use crate::image::GrayView;
use crate::isa::Isa;
use crate::shape::{INNER51, dan_mean_shape};

pub use format::ModelError;
use stage::{HALF_ROW, PackedNode, prefetch};
pub use stage::{Node, Stage, Tree};

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

/// Start perturbations of [`Krfws::align_restarts`]: scale and rotation (radians) about the centroid,
/// then a shift in units of the start shape's width. The first is the start itself; then shifts of 7 %,
/// ±10 % scale, ±11.5° roll, shifts of 14 %.
pub const RESTARTS: [(f32, f32, f32, f32); 13] = [
    (1.0, 0.0, 0.0, 0.0),
    (1.0, 0.0, 0.0, 0.07),
    (1.0, 0.0, -0.07, 0.0),
    (1.0, 0.0, 0.07, 0.0),
    (1.0, 0.0, 0.0, -0.07),
    (0.9, 0.0, 0.0, 0.0),
    (1.1, 0.0, 0.0, 0.0),
    (1.0, 0.2, 0.0, 0.0),
    (1.0, -0.2, 0.0, 0.0),
    (1.0, 0.0, 0.0, 0.14),
    (1.0, 0.0, -0.14, 0.0),
    (1.0, 0.0, 0.14, 0.0),
    (1.0, 0.0, 0.0, -0.14),
];

/// The failure detector: `score = weights·hog + intercept`, a ridge regression of the fit's NME49
/// (clipped at the trainer's `FAILURE_TARGET_CAP`) on the last stage's HOG. The fit is accepted when
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
    #[inline(always)]
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
    best_hog: Vec<f32>,
    restarts: Vec<(f32, [Point2; N_POINTS])>,
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
            best_hog: Vec::new(),
            restarts: Vec::new(),
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

/// Dot product of a 144-d projection and a HOG row, in the one summation order every build uses:
/// 16 lane sums over the 9 blocks of 16, then a halving tree (lane i + lane i+8, then +4, +2, +1).
/// The order is the AVX-512 kernel's; the portable build vectorises it too. A shorter `a` counts its
/// missing values as 0 (the loader guarantees 144).
#[inline(always)]
pub(crate) fn dot144(a: &[f32], b: &[f32; HOG_DIM]) -> f32 {
    let mut acc = [0.0f32; 16];
    for (x, y) in a.chunks_exact(16).zip(b.chunks_exact(16)) {
        for i in 0..16 {
            acc[i] += x[i] * y[i];
        }
    }
    let s8: [f32; 8] = std::array::from_fn(|i| acc[i] + acc[i + 8]);
    let s4: [f32; 4] = std::array::from_fn(|i| s8[i] + s8[i + 4]);
    (s4[0] + s4[2]) + (s4[1] + s4[3])
}

/// KRFWS's window sampler: bilinear, zero fill, in fixed point. Image coordinates are tracked in 16.16
/// fixed point along each window row (one add per pixel instead of two products), the bilinear weights
/// have 8 bits, and the value is rounded half up: within one grey level of the float sampler
/// ([`crate::crop::BilinearSampler`]) and several times cheaper. Training and inference both sample
/// through here, so the model sees the same pixels in both.
#[derive(Clone, Copy, Debug)]
pub struct WindowSampler<'a> {
    data: &'a [u8],
    stride: usize,
    w: i64,
    h: i64,
    /// `image_from_norm` as `a, b, tx, ty` (f64 for the per-row starting points).
    t: [f64; 4],
    /// `a` and `b` in 16.16 fixed point: the per-pixel step along a window row.
    step: (i64, i64),
}

const FIX_ONE: f64 = 65536.0;

impl<'a> WindowSampler<'a> {
    /// A sampler of `image` through `image_from_norm` (`a, b, tx, ty`: `x = a·u − b·v + tx`,
    /// `y = b·u + a·v + ty`).
    pub fn new(image: &GrayView<'a>, image_from_norm: [f32; 4]) -> Self {
        let t = image_from_norm.map(f64::from);
        Self {
            data: image.data(),
            stride: image.stride(),
            w: image.width() as i64,
            h: image.height() as i64,
            t,
            step: (Self::fix(t[0]), Self::fix(t[1])),
        }
    }

    /// Fixed point of a coordinate, clamped far outside any image (so no overflow in the row walk).
    #[inline(always)]
    fn fix(x: f64) -> i64 {
        (x.clamp(-1e9, 1e9) * FIX_ONE).round() as i64
    }

    /// Fixed-point image position of normalised-frame pixel `(u, v)`.
    #[inline(always)]
    fn at(&self, u: i64, v: i64) -> (i64, i64) {
        let [a, b, tx, ty] = self.t;
        let (uf, vf) = (u as f64, v as f64);
        (Self::fix(a * uf - b * vf + tx), Self::fix(b * uf + a * vf + ty))
    }

    /// Whether every tap of the window at `(u0, v0)` is inside the image with a pixel of margin for the
    /// row walk's rounding on the top/left and `right` pixels on the right (the taps of a row of the
    /// window lie between its end points, the end points of the middle rows between the corners').
    #[inline(always)]
    fn inside(&self, u0: i64, v0: i64, right: i64) -> bool {
        let (sa, sb) = self.step;
        let last = PATCH as i64 - 1;
        [(0, 0), (last, 0), (0, last), (last, last)]
            .iter()
            .all(|&(du, dv)| {
                let (x, y) = self.at(u0, v0 + dv);
                let (x, y) = ((x + du * sa) >> 16, (y + du * sb) >> 16);
                x >= 1 && y >= 1 && x < self.w - right && y < self.h - 2
            })
    }

    /// The 16×16 window centred on the rounded normalised-frame point `p` (`[p − 8, p + 8)`).
    #[inline(always)]
    pub fn window(&self, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
        let (u0, v0) = (round_coord(p.x) - 8, round_coord(p.y) - 8);
        let (sa, sb) = self.step;
        let inside = self.inside(u0, v0, 2);
        let stride = self.stride;
        for (dv, row) in out.chunks_exact_mut(PATCH).enumerate() {
            let (mut x, mut y) = self.at(u0, v0 + dv as i64);
            for o in row.iter_mut() {
                let (xi, yi) = (x >> 16, y >> 16);
                let (fx, fy) = (((x >> 8) & 0xff) as u32, ((y >> 8) & 0xff) as u32);
                let taps = if inside {
                    let k = yi as usize * stride + xi as usize;
                    self.data
                        .get(k..k + stride + 2)
                        .map(|q| [q[0], q[1], q[stride], q[stride + 1]])
                } else {
                    None
                };
                let [p00, p01, p10, p11] = taps
                    .unwrap_or_else(|| {
                        [
                            self.tap(xi, yi),
                            self.tap(xi + 1, yi),
                            self.tap(xi, yi + 1),
                            self.tap(xi + 1, yi + 1),
                        ]
                    })
                    .map(u32::from);
                let top = p00 * (256 - fx) + p01 * fx;
                let bot = p10 * (256 - fx) + p11 * fx;
                *o = ((top * (256 - fy) + bot * fy + (1 << 15)) >> 16) as u8;
                x += sa;
                y += sb;
            }
        }
    }

    #[inline(always)]
    fn tap(&self, x: i64, y: i64) -> u8 {
        if x >= 0 && x < self.w && y >= 0 && y < self.h {
            self.data
                .get(y as usize * self.stride + x as usize)
                .copied()
                .unwrap_or(0)
        } else {
            0
        }
    }
}

/// The kernels one compiled copy of [`Krfws::align`] inlines: the portable ones, or hand-vectorised
/// ones for an instruction set the running CPU was checked to have (the token types can only be made
/// by that check). Every implementation gives the same bits.
pub trait Kernels: Copy {
    /// [`WindowSampler::window`].
    fn window(self, sampler: &WindowSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]);
    /// [`hog_patch`].
    fn hog(self, patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]);
    /// The child internal node `node` of tree `k` sends `row` to (the [`Node`] convention), using
    /// `dot144`'s summation order; `None` for a node the tree does not have.
    fn descend(self, stage: &Stage, k: usize, node: usize, row: &[f32; HOG_DIM]) -> Option<i32>;
    /// Asks the caches for what [`Kernels::descend`] will read for node `node` of tree `k`.
    fn prefetch_node(self, stage: &Stage, k: usize, node: usize);
    /// Asks the caches for row `row` of `W` as [`Kernels::accumulate`] will read it.
    fn prefetch_row(self, stage: &Stage, row: usize);
    /// [`Stage::accumulate`].
    fn accumulate(self, stage: &Stage, leaves: &[u32], delta: &mut [f32; DELTA_DIM]);
}

/// The portable kernels.
#[derive(Clone, Copy, Debug, Default)]
pub struct Portable;

impl Kernels for Portable {
    #[inline(always)]
    fn window(self, sampler: &WindowSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
        sampler.window(p, out)
    }
    #[inline(always)]
    fn hog(self, patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
        hog_patch(patch, out)
    }
    #[inline(always)]
    fn descend(self, stage: &Stage, k: usize, node: usize, row: &[f32; HOG_DIM]) -> Option<i32> {
        let tree = stage.trees.get(k)?;
        let n = tree.nodes.get(node)?;
        let d = dot144(tree.projection(node)?, row);
        Some(if d <= n.threshold { n.left } else { n.right })
    }
    #[inline(always)]
    fn prefetch_node(self, stage: &Stage, k: usize, node: usize) {
        prefetch(
            stage
                .trees
                .get(k)
                .and_then(|t| t.projection(node))
                .map(|p| &p[..]),
        );
    }
    #[inline(always)]
    fn prefetch_row(self, stage: &Stage, row: usize) {
        prefetch(stage.weights.get(row * DELTA_DIM..(row + 1) * DELTA_DIM));
    }
    #[inline(always)]
    fn accumulate(self, stage: &Stage, leaves: &[u32], delta: &mut [f32; DELTA_DIM]) {
        stage.accumulate(leaves, delta)
    }
}

/// The stage's normalised frame: `norm_from_image` (current shape → `dest`), the shape in that frame
/// (into `norm`) and the window sampler through its inverse; `None` for a degenerate shape.
#[inline(always)]
fn stage_frame<'a>(
    image: &GrayView<'a>,
    shape: &[Point2; N_POINTS],
    dest: &[Point2; N_POINTS],
    norm: &mut [Point2; N_POINTS],
) -> Option<(Similarity2, WindowSampler<'a>)> {
    let t = Similarity2::fit(shape, dest)?;
    let inv32 = t.inverse()?.to_f32_array();
    if !inv32.iter().all(|v| v.is_finite()) {
        return None;
    }
    t.apply_all(shape, norm);
    Some((t, WindowSampler::new(image, inv32)))
}

/// Normalised-frame features of one stage: fits `norm_from_image` (current shape → `dest`), writes the
/// shape in the normalised frame into `norm` and the 51×144 HOG into `hog`. Returns the similarity, or
/// `None` for a degenerate shape.
#[inline(always)]
pub fn stage_features(
    image: &GrayView<'_>,
    shape: &[Point2; N_POINTS],
    dest: &[Point2; N_POINTS],
    patch: &mut [u8; PATCH_PIXELS],
    norm: &mut [Point2; N_POINTS],
    hog: &mut [f32],
) -> Option<Similarity2> {
    stage_features_with(Portable, image, shape, dest, patch, norm, hog)
}

/// [`stage_features`] with the given kernels.
#[inline(always)]
pub fn stage_features_with<K: Kernels>(
    kernels: K,
    image: &GrayView<'_>,
    shape: &[Point2; N_POINTS],
    dest: &[Point2; N_POINTS],
    patch: &mut [u8; PATCH_PIXELS],
    norm: &mut [Point2; N_POINTS],
    hog: &mut [f32],
) -> Option<Similarity2> {
    let (t, sampler) = stage_frame(image, shape, dest, norm)?;
    for (p, row) in norm.iter().zip(hog.chunks_exact_mut(HOG_DIM)) {
        kernels.window(&sampler, *p, patch);
        if let Ok(r) = <&mut [f32; HOG_DIM]>::try_from(row) {
            kernels.hog(patch, r);
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

    /// The 51×144 HOG around `shape` (full-frame pixels) as the last stage samples it (its normalised frame,
    /// fitted to `shape`), written to [`KrfwsScratch::last_hog`]: what the aligner sees at a given answer,
    /// for the per-person adaptation (`crate::adapt`). `false` (the HOG untouched) for a degenerate shape or a
    /// model without stages.
    pub fn hog_at(
        &self,
        image: &GrayView<'_>,
        shape: &[Point2; N_POINTS],
        scratch: &mut KrfwsScratch,
    ) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            if let Some(k) = Avx512::detect() {
                #[target_feature(enable = "avx512f")]
                fn avx512(
                    m: &Krfws,
                    k: Avx512,
                    i: &GrayView<'_>,
                    s: &[Point2; N_POINTS],
                    x: &mut KrfwsScratch,
                ) -> bool {
                    m.hog_at_with(k, i, s, x)
                }
                #[allow(unsafe_code)]
                // SAFETY: the token proves the CPU has AVX-512F.
                return unsafe { avx512(self, k, image, shape, scratch) };
            }
            if let Some(k) = Avx2::detect() {
                #[target_feature(enable = "avx2,f16c")]
                fn avx2(
                    m: &Krfws,
                    k: Avx2,
                    i: &GrayView<'_>,
                    s: &[Point2; N_POINTS],
                    x: &mut KrfwsScratch,
                ) -> bool {
                    m.hog_at_with(k, i, s, x)
                }
                #[allow(unsafe_code)]
                // SAFETY: the token proves the CPU has AVX2 and F16C.
                return unsafe { avx2(self, k, image, shape, scratch) };
            }
        }
        #[cfg(target_arch = "aarch64")]
        if let Some(k) = Neon::detect() {
            return self.hog_at_with(k, image, shape, scratch);
        }
        self.hog_at_with(Portable, image, shape, scratch)
    }

    #[inline(always)]
    fn hog_at_with<K: Kernels>(
        &self,
        kernels: K,
        image: &GrayView<'_>,
        shape: &[Point2; N_POINTS],
        scratch: &mut KrfwsScratch,
    ) -> bool {
        let Some(stage) = self.stages.last() else {
            return false;
        };
        let KrfwsScratch {
            patch,
            norm,
            last_hog,
            ..
        } = scratch;
        stage_features_with(kernels, image, shape, &stage.dest, patch, norm, last_hog).is_some()
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
        self.align_on(crate::isa::detected(), image, init, scratch, out)
    }

    /// [`Krfws::align`] on the code path compiled for `isa` when this CPU has it (else the baseline
    /// path). Every path gives the same bits; tests compare them.
    pub fn align_on(
        &self,
        isa: Isa,
        image: &GrayView<'_>,
        init: &[Point2; N_POINTS],
        scratch: &mut KrfwsScratch,
        out: &mut [Point2; N_POINTS],
    ) -> f32 {
        #[cfg(target_arch = "x86_64")]
        match isa {
            Isa::Avx512 => {
                if let Some(k) = Avx512::detect() {
                    #[allow(unsafe_code)]
                    // SAFETY: the token proves the CPU has AVX-512F.
                    return unsafe { self.align_avx512(k, image, init, scratch, out) };
                }
            }
            Isa::Avx2 => {
                if let Some(k) = Avx2::detect() {
                    #[allow(unsafe_code)]
                    // SAFETY: the token proves the CPU has AVX2 and F16C.
                    return unsafe { self.align_avx2(k, image, init, scratch, out) };
                }
            }
            Isa::Neon | Isa::Baseline => {}
        }
        #[cfg(target_arch = "aarch64")]
        if isa == Isa::Neon
            && let Some(k) = Neon::detect()
        {
            return self.align_with(k, image, init, scratch, out);
        }
        self.align_with(Portable, image, init, scratch, out)
    }

    /// [`Krfws::align`] compiled for AVX2 and F16C with the AVX2 kernels: 8-lane vectors, the same IEEE
    /// operations in the same order, so the same bits (Rust never fuses a multiply and an add on its
    /// own, so enabling AVX2 cannot change a rounding).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,f16c")]
    fn align_avx2(
        &self,
        kernels: Avx2,
        image: &GrayView<'_>,
        init: &[Point2; N_POINTS],
        scratch: &mut KrfwsScratch,
        out: &mut [Point2; N_POINTS],
    ) -> f32 {
        self.align_with(kernels, image, init, scratch, out)
    }

    /// [`Krfws::align`] compiled for AVX-512F: 16-lane vector code and the AVX-512 kernels (same bits).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn align_avx512(
        &self,
        kernels: Avx512,
        image: &GrayView<'_>,
        init: &[Point2; N_POINTS],
        scratch: &mut KrfwsScratch,
        out: &mut [Point2; N_POINTS],
    ) -> f32 {
        self.align_with(kernels, image, init, scratch, out)
    }

    #[inline(always)]
    fn align_with<K: Kernels>(
        &self,
        kernels: K,
        image: &GrayView<'_>,
        init: &[Point2; N_POINTS],
        scratch: &mut KrfwsScratch,
        out: &mut [Point2; N_POINTS],
    ) -> f32 {
        scratch.shape = self.init_from_previous(init);
        let n = self.stages.len();
        let score = self.run_stages(kernels, image, scratch, 0..n, true);
        *out = scratch.shape;
        score.unwrap_or(f32::INFINITY)
    }

    /// Aligns from the first `starts` of [`RESTARTS`] (perturbations of `init` about its centroid) and
    /// returns the per-coordinate median of the results whose failure score is within
    /// `max(0.5·|best|, 0.005)` of the best one (an ensemble over starts, as in explicit shape regression;
    /// the failure detector drops the starts that did not converge). The returned score and
    /// [`KrfwsScratch::last_hog`] are the best start's. For a detector's box, a coarser start than the
    /// previous frame's landmarks; costs `starts` alignments. `starts ≤ 1` is [`Krfws::align`].
    pub fn align_restarts(
        &self,
        image: &GrayView<'_>,
        init: &[Point2; N_POINTS],
        starts: usize,
        scratch: &mut KrfwsScratch,
        out: &mut [Point2; N_POINTS],
    ) -> f32 {
        if starts <= 1 {
            return self.align(image, init, scratch, out);
        }
        let starts = starts.min(RESTARTS.len());
        let c = crate::geometry::centroid(init);
        let width = Rect::bounding(init).map_or(0.0, |r| r.width());
        let mut results = std::mem::take(&mut scratch.restarts);
        results.clear();
        let mut best_hog = std::mem::take(&mut scratch.best_hog);
        best_hog.resize(FAILURE_DIM, 0.0);
        let mut best = f32::INFINITY;
        let mut shape = [Point2::default(); N_POINTS];
        for &(scale, rot, dx, dy) in &RESTARTS[..starts] {
            let (sn, cs) = rot.sin_cos();
            let start: [Point2; N_POINTS] = std::array::from_fn(|i| {
                let (x, y) = (init[i].x - c.x, init[i].y - c.y);
                Point2::new(
                    c.x + scale * (cs * x - sn * y) + dx * width,
                    c.y + scale * (sn * x + cs * y) + dy * width,
                )
            });
            let score = self.align(image, &start, scratch, &mut shape);
            if results.is_empty() || score < best {
                best = score;
                best_hog.copy_from_slice(&scratch.last_hog);
            }
            results.push((score, shape));
        }
        let gate = best + (0.5 * best.abs()).max(0.005);
        let mut xs = Vec::with_capacity(starts);
        let mut ys = Vec::with_capacity(starts);
        for (i, o) in out.iter_mut().enumerate() {
            xs.clear();
            ys.clear();
            for (_, r) in results.iter().filter(|(sc, _)| *sc <= gate) {
                xs.push(r[i].x);
                ys.push(r[i].y);
            }
            if xs.is_empty() {
                // Every score is NaN or infinite: keep the first start's answer.
                *o = results.first().map_or(init[i], |(_, r)| r[i]);
                continue;
            }
            xs.sort_by(f32::total_cmp);
            ys.sort_by(f32::total_cmp);
            *o = Point2::new(xs[xs.len() / 2], ys[ys.len() / 2]);
        }
        scratch.last_hog.copy_from_slice(&best_hog);
        scratch.best_hog = best_hog;
        scratch.restarts = results;
        best
    }

    /// Runs `stages` on `scratch.shape` in place. With `score`, returns the failure score of the last
    /// stage run (else 0).
    #[inline(always)]
    fn run_stages<K: Kernels>(
        &self,
        kernels: K,
        image: &GrayView<'_>,
        scratch: &mut KrfwsScratch,
        stages: std::ops::Range<usize>,
        score: bool,
    ) -> Option<f32> {
        let mut result = 0.0;
        let last = stages.end.saturating_sub(1);
        for k in stages {
            let stage = self.stages.get(k)?;
            scratch.leaves.resize(stage.trees.len(), 0);
            let t = stage.features_and_leaves(
                kernels,
                image,
                &scratch.shape,
                &mut scratch.patch,
                &mut scratch.norm,
                &mut scratch.hog,
                &mut scratch.leaves,
            )?;
            if k == last && score {
                result = self.failure.score(&scratch.hog);
                scratch.last_hog.copy_from_slice(&scratch.hog);
            }
            kernels.accumulate(stage, &scratch.leaves, &mut scratch.delta);
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

/// NME49 of 51 predicted inner points against 68 ground-truth points.
pub fn nme49_inner(pred: &[Point2; N_POINTS], gt: &[Point2; 68]) -> f64 {
    let mut full = *gt;
    full[INNER51].copy_from_slice(pred);
    crate::accuracy::nme49(&full, gt).unwrap_or(f64::INFINITY)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::crop::warp_bilinear;

    #[test]
    fn window_sampling_is_within_one_grey_level_of_a_warped_canvas() {
        let (w, h) = (64usize, 48usize);
        let img: Vec<u8> = (0..w * h)
            .map(|i| (128.0 + 100.0 * ((i % w) as f32 / 5.0).sin() * ((i / w) as f32 / 7.0).cos()) as u8)
            .collect();
        let v = GrayView::new(&img, w, h, w).unwrap();
        let t = Similarity2::from_parts(0.8, 0.3, 5.0, -2.0);
        let (cw, ch) = (60usize, 60usize);
        let mut canvas = vec![0u8; cw * ch];
        warp_bilinear(&v, &t, cw, ch, &mut canvas).unwrap();
        let inv = t.inverse().unwrap().to_f32_array();
        let mut win = [0u8; PATCH_PIXELS];
        // Inside the image, and overlapping its border (zero fill).
        for p in [
            Point2::new(20.3, 30.6),
            Point2::new(40.0, 9.0),
            Point2::new(3.0, 3.0),
        ] {
            WindowSampler::new(&v, inv).window(p, &mut win);
            let (cx, cy) = (round_coord(p.x) - 8, round_coord(p.y) - 8);
            for dv in 0..16 {
                for du in 0..16 {
                    let (x, y) = (cx + du, cy + dv);
                    let want = if x >= 0 && y >= 0 && (x as usize) < cw && (y as usize) < ch {
                        canvas[y as usize * cw + x as usize]
                    } else {
                        continue;
                    };
                    let got = win[(dv * 16 + du) as usize];
                    assert!(got.abs_diff(want) <= 1, "{p:?} ({du}, {dv}): {got} vs {want}");
                }
            }
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx512_windows_equal_the_scalar_ones() {
        let Some(k) = Avx512::detect() else {
            eprintln!("no AVX-512F on this CPU: nothing to compare");
            return;
        };
        let (w, h) = (97usize, 61usize);
        let img: Vec<u8> = (0..w * h).map(|i| (i * 7919 % 251) as u8).collect();
        // A stride wider than the image: the padding must never be read as pixels.
        let stride = w + 5;
        let mut padded = vec![255u8; stride * h];
        for y in 0..h {
            padded[y * stride..y * stride + w].copy_from_slice(&img[y * w..(y + 1) * w]);
        }
        let v = GrayView::new(&padded, w, h, stride).unwrap();
        let (mut a, mut b) = ([0u8; PATCH_PIXELS], [0u8; PATCH_PIXELS]);
        let mut inside = 0;
        for (i, (scale, angle)) in [(1.0f32, 0.0f32), (0.7, 0.4), (1.9, -1.2), (0.3, 3.0)]
            .into_iter()
            .enumerate()
        {
            let t = [scale * angle.cos(), scale * angle.sin(), 3.0 + i as f32, -2.5];
            let sampler = WindowSampler::new(&v, t);
            for py in (-12..80).step_by(3) {
                for px in (-12..110).step_by(3) {
                    let p = Point2::new(px as f32 + 0.3, py as f32 - 0.2);
                    sampler.window(p, &mut a);
                    k.window(&sampler, p, &mut b);
                    assert_eq!(a, b, "{p:?} {t:?}");
                    inside += usize::from(a.iter().all(|&x| x != 0));
                }
            }
        }
        assert!(inside > 100, "the vector path ran on only {inside} windows");
    }

    #[test]
    fn hog_at_is_the_last_stages_view_of_a_shape() {
        let (w, h) = (160usize, 140usize);
        let img: Vec<u8> = (0..w * h).map(|i| (i * 7919 % 251) as u8).collect();
        let v = GrayView::new(&img, w, h, w).unwrap();
        let mean = default_mean_shape();
        let failure = FailureModel {
            weights: vec![0.0; FAILURE_DIM],
            intercept: 0.0,
            threshold: 1.0,
        };
        let mut scratch = KrfwsScratch::new();
        let shape: [Point2; N_POINTS] =
            std::array::from_fn(|i| Point2::new(80.0 + mean[i].x * 0.6, 70.0 + mean[i].y * 0.6));
        // No stage: nothing to see with.
        assert!(!Krfws::new(mean, Vec::new(), failure.clone()).hog_at(&v, &shape, &mut scratch));
        let stages = [0.5, 0.3]
            .map(|s| Stage::new(&mean, s, 1, Vec::new(), Vec::new()))
            .to_vec();
        let model = Krfws::new(mean, stages, failure);
        assert!(model.hog_at(&v, &shape, &mut scratch));
        // The last stage's frame (scale 0.3), through the portable kernels: the same bits.
        let (mut patch, mut norm, mut want) = (
            [0u8; PATCH_PIXELS],
            [Point2::default(); N_POINTS],
            vec![0.0; FAILURE_DIM],
        );
        stage_features(
            &v,
            &shape,
            &stage_dest(&mean, 0.3),
            &mut patch,
            &mut norm,
            &mut want,
        )
        .unwrap();
        assert_eq!(scratch.last_hog(), &want[..]);
        assert!(want.iter().any(|&x| x != 0.0));
        // A degenerate shape leaves the HOG as it was.
        assert!(!model.hog_at(&v, &[Point2::new(5.0, 5.0); N_POINTS], &mut scratch));
        assert_eq!(scratch.last_hog(), &want[..]);
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
