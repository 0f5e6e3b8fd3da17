//! The server's refinement cascade: an ensemble of regression trees (ERT, Kazemi & Sullivan 2014) over
//! shape-indexed pixel differences, run on the crop DAN aligned, starting from DAN's 68 landmarks.
//!
//! DAN is the robust part of the remote pipeline (it rarely fails and its face head is excellent); a
//! tree cascade is precise, cheap to train on a CPU and cheap to run, but needs a good start. The server
//! has that start, so it runs DAN, then this cascade (`holoface-inference`'s `CascadeEngine`).
//!
//! # Model
//! Landmarks are in crop pixels (the client's crop, mean shape 56 px in 112). Each stage has a pool of
//! feature points, each anchored to a landmark with an offset in the mean-shape frame; at run time the
//! offset is turned and scaled by the similarity from the mean shape to the current shape (rotation and
//! scale only), the crop is read there (0 outside the crop, as the crop reads outside the image): the nearest
//! pixel, or, in models trained so ([`Sampling::Bilinear`]), the bilinear interpolation of the four around
//! it rounded to a grey level, so that a feature changes with sub-pixel moves of the shape.
//! Each tree of the stage tests `I(u) − I(v) > threshold` at every node (depth `d`, heap order) and its
//! leaf holds a 136-d shape increment in the mean-shape frame (the learning rate already applied); the
//! stage sums its trees' leaves and moves the shape by that sum turned back into crop pixels.
//!
//! Training (`train`, feature `train`) is gradient boosting of those trees on the residuals `ground truth − current`
//! (in the mean-shape frame), stage after stage, from DAN's real outputs on augmented training crops.
//! The file format is in [`mod@format`].

pub mod format;
#[cfg(feature = "train")]
pub mod train;

use crate::geometry::{Point2, Similarity2};
use thiserror::Error;

/// Landmarks the refiner works on (the iBUG 68).
pub const REFINE_LANDMARKS: usize = 68;
/// Values of one shape increment (x and y of every landmark).
pub const SHAPE_DIM: usize = 2 * REFINE_LANDMARKS;

/// Errors of loading or running a refiner.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum RefineError {
    /// The model file is not a refiner model or is damaged.
    #[error(transparent)]
    Format(#[from] holoface_protocol::framing::FormatError),
    /// The crop is not `crop_size²` bytes.
    #[error("crop holds {len} bytes, the refiner needs {expected}")]
    CropSize {
        /// Bytes given.
        len: usize,
        /// `crop_size²`.
        expected: usize,
    },
    /// The start shape is not 68 finite points.
    #[error("start shape: {0}")]
    BadStart(String),
}

/// How a feature point reads the crop.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Sampling {
    /// The nearest pixel (format v1 models).
    #[default]
    Nearest,
    /// The four pixels around the point, interpolated and rounded to a grey level.
    Bilinear,
}

/// One node test: `I(u) − I(v) > threshold` goes right.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SplitTest {
    /// First feature point (index into the stage's pool).
    pub u: u16,
    /// Second feature point.
    pub v: u16,
    /// Threshold on the grey-level difference.
    pub threshold: f32,
}

/// One regression tree of depth `d`: `2^d − 1` tests in heap order and `2^d` leaves, each leaf
/// [`SHAPE_DIM`] values quantised to `i8` with one `f32` scale (value = scale · q). Quantised leaves are a
/// quarter of `f32` ones: the cascade's cost is reading its reached leaves, so this is most of its speed;
/// the rounding (under 0.4 % of a leaf's largest value) is applied in training too.
#[derive(Clone, Debug, PartialEq)]
pub struct RegressionTree {
    /// Node tests, heap order (children of `i` are `2i + 1`, `2i + 2`).
    pub splits: Vec<SplitTest>,
    /// One scale per leaf.
    pub scales: Vec<f32>,
    /// Quantised leaf increments, leaf after leaf, in the mean-shape frame.
    pub values: Vec<i8>,
}

/// One cascade stage: its feature pool and its trees.
#[derive(Clone, Debug, PartialEq)]
pub struct RefineStage {
    /// Landmark each feature point is anchored to.
    pub anchors: Vec<u8>,
    /// Offset of each feature point from its anchor, in the mean-shape frame (crop pixels).
    pub offsets: Vec<[f32; 2]>,
    /// The stage's trees.
    pub trees: Vec<RegressionTree>,
}

impl RefineStage {
    /// Moves `shape` by this stage on `crop` (`crop_size²` pixels); `false` when the shape is degenerate
    /// and the stage could not run.
    ///
    /// On a CPU with AVX2 the same code is compiled for AVX2 and runs there (the leaves' `i8` → `f32`
    /// sums are 8 lanes wide instead of the baseline's 4); the arithmetic is the same, in the same order,
    /// so the answers are bit-identical either way.
    pub fn apply(
        &self,
        mean: &[Point2; REFINE_LANDMARKS],
        depth: usize,
        (crop_size, sampling): (usize, Sampling),
        crop: &[u8],
        shape: &mut [Point2; REFINE_LANDMARKS],
        scratch: &mut RefineScratch,
    ) -> bool {
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bw") {
            #[allow(unsafe_code)]
            // SAFETY: `apply_avx512` only asks for AVX-512F and BW, which this CPU has (checked just above).
            return unsafe { self.apply_avx512(mean, depth, (crop_size, sampling), crop, shape, scratch) };
        }
        #[cfg(target_arch = "x86_64")]
        if std::is_x86_feature_detected!("avx2") {
            #[allow(unsafe_code)]
            // SAFETY: `apply_avx2` only asks for AVX2, which this CPU has (checked just above).
            return unsafe { self.apply_avx2(mean, depth, (crop_size, sampling), crop, shape, scratch) };
        }
        self.apply_portable(mean, depth, (crop_size, sampling), crop, shape, scratch)
    }

    /// [`RefineStage::apply`] compiled for AVX-512 (16 lanes).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f,avx512bw")]
    fn apply_avx512(
        &self,
        mean: &[Point2; REFINE_LANDMARKS],
        depth: usize,
        (crop_size, sampling): (usize, Sampling),
        crop: &[u8],
        shape: &mut [Point2; REFINE_LANDMARKS],
        scratch: &mut RefineScratch,
    ) -> bool {
        self.apply_portable(mean, depth, (crop_size, sampling), crop, shape, scratch)
    }

    /// [`RefineStage::apply`] compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn apply_avx2(
        &self,
        mean: &[Point2; REFINE_LANDMARKS],
        depth: usize,
        (crop_size, sampling): (usize, Sampling),
        crop: &[u8],
        shape: &mut [Point2; REFINE_LANDMARKS],
        scratch: &mut RefineScratch,
    ) -> bool {
        self.apply_portable(mean, depth, (crop_size, sampling), crop, shape, scratch)
    }

    #[inline(always)]
    fn apply_portable(
        &self,
        mean: &[Point2; REFINE_LANDMARKS],
        depth: usize,
        (crop_size, sampling): (usize, Sampling),
        crop: &[u8],
        shape: &mut [Point2; REFINE_LANDMARKS],
        scratch: &mut RefineScratch,
    ) -> bool {
        let Some((a, b)) = frame_of(mean, shape) else {
            return false;
        };
        scratch.delta.resize(SHAPE_DIM, 0.0);
        scratch.features.resize(self.anchors.len(), 0);
        read_features(
            crop,
            (crop_size, sampling),
            shape,
            (a, b),
            &self.anchors,
            &self.offsets,
            &mut scratch.features,
        );
        // Route every tree first, then add the reached leaves: the routes are independent chains of
        // loads the core can overlap, and once every leaf is known its values can stream in.
        scratch.leaves.clear();
        scratch.leaves.extend(
            self.trees
                .iter()
                .map(|t| t.leaf_of(&scratch.features, depth) as u16),
        );
        let delta = &mut scratch.delta;
        delta.fill(0.0);
        for (tree, &leaf) in self.trees.iter().zip(&scratch.leaves) {
            tree.add_leaf(usize::from(leaf), delta);
        }
        let moved: [Point2; REFINE_LANDMARKS] = std::array::from_fn(|i| {
            let (dx, dy) = (delta[2 * i], delta[2 * i + 1]);
            Point2::new(shape[i].x + a * dx - b * dy, shape[i].y + b * dx + a * dy)
        });
        if moved.iter().all(|p| p.x.is_finite() && p.y.is_finite()) {
            *shape = moved;
        }
        true
    }
}

/// A trained refinement cascade.
#[derive(Clone, Debug, PartialEq)]
pub struct RefineCascade {
    /// Side of the square crop it works on.
    pub crop_size: usize,
    /// Tree depth (every tree of every stage).
    pub depth: usize,
    /// The mean shape in crop pixels: the frame the feature offsets and the leaves are expressed in.
    pub mean: [Point2; REFINE_LANDMARKS],
    /// The stages, first to last.
    pub stages: Vec<RefineStage>,
    /// Free-form identity written by the trainer (`name version`), shown in logs and metrics.
    pub name: String,
    /// Starts per crop (1..=9, the first of [`START_OFFSETS`]); the answer is their per-coordinate median.
    pub starts: usize,
    /// Also refine the mirror image (the crop flipped left to right, the start mirrored with the iBUG
    /// left/right swap) and answer the mean of the two.
    pub mirror: bool,
    /// How the feature points read the crop (the model was trained with it).
    pub sampling: Sampling,
}

/// The starts [`RefineCascade::refine`] runs when the model asks for several ([`RefineCascade::starts`]): the given
/// shape, then shifted by `(dx, dy)` in the mean-shape frame (crop pixels of the mean shape: ±1.5 px is
/// about 4 % of the eye-corner distance), scaled about its centroid and turned by degrees. Fixed, so the
/// answer is a function of the crop and the start alone.
pub const START_OFFSETS: [(f32, f32, f32, f32); 9] = [
    (0.0, 0.0, 1.0, 0.0),
    (1.5, 0.0, 1.0, 0.0),
    (-1.5, 0.0, 1.0, 0.0),
    (0.0, 1.5, 1.0, 0.0),
    (0.0, -1.5, 1.0, 0.0),
    (0.0, 0.0, 1.04, 0.0),
    (0.0, 0.0, 0.96, 0.0),
    (0.0, 0.0, 1.0, 4.0),
    (0.0, 0.0, 1.0, -4.0),
];

/// The median of `v` (the mean of the middle two for an even count); `v` is reordered.
fn median(v: &mut [f32]) -> f32 {
    v.sort_unstable_by(f32::total_cmp);
    let n = v.len();
    match n {
        0 => 0.0,
        _ if n % 2 == 1 => v[n / 2],
        _ => 0.5 * (v[n / 2 - 1] + v[n / 2]),
    }
}

/// Buffers reused across calls (one per thread).
#[derive(Debug, Default, Clone)]
pub struct RefineScratch {
    features: Vec<i16>,
    delta: Vec<f32>,
    flipped: Vec<u8>,
    leaves: Vec<u16>,
}

/// The rotation-and-scale part `(a, b)` of the similarity mapping the mean shape onto `shape`, or `None`
/// when `shape` is degenerate.
pub(crate) fn frame_of(mean: &[Point2], shape: &[Point2]) -> Option<(f32, f32)> {
    let s = Similarity2::fit(mean, shape)?;
    let (a, b) = (s.a as f32, s.b as f32);
    (a.is_finite() && b.is_finite() && (a * a + b * b) > 1e-12).then_some((a, b))
}

/// The grey levels of a stage's feature points on `crop` (nearest pixel or bilinear, 0 outside), into `out`.
#[inline(always)]
pub(crate) fn read_features(
    crop: &[u8],
    (size, sampling): (usize, Sampling),
    shape: &[Point2],
    (a, b): (f32, f32),
    anchors: &[u8],
    offsets: &[[f32; 2]],
    out: &mut [i16],
) {
    let lim = size as f32 - 0.5;
    for ((o, &k), off) in out.iter_mut().zip(anchors).zip(offsets) {
        let p = shape[usize::from(k)];
        let x = p.x + a * off[0] - b * off[1];
        let y = p.y + b * off[0] + a * off[1];
        *o = if !(x >= -0.5 && y >= -0.5 && x < lim && y < lim) {
            0
        } else if sampling == Sampling::Bilinear && size >= 2 {
            bilinear(crop, size, x, y)
        } else {
            // In range, so the rounded coordinates are valid indices.
            let (xi, yi) = ((x + 0.5) as usize, (y + 0.5) as usize);
            crop.get(yi * size + xi).map_or(0, |&v| i16::from(v))
        };
    }
}

/// The crop at `(x, y)` (inside `[-0.5, size - 0.5)`; clamped to the pixel centres), interpolated
/// between the four pixels around it and rounded to a grey level.
#[inline(always)]
fn bilinear(crop: &[u8], size: usize, x: f32, y: f32) -> i16 {
    let top = (size - 1) as f32;
    let (x, y) = (x.clamp(0.0, top), y.clamp(0.0, top));
    // Clamped, so these are valid indices with a right and a lower neighbour.
    let (x0, y0) = ((x as usize).min(size - 2), (y as usize).min(size - 2));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let px = |xi: usize, yi: usize| crop.get(yi * size + xi).map_or(0.0, |&v| f32::from(v));
    let upper = px(x0, y0) + fx * (px(x0 + 1, y0) - px(x0, y0));
    let lower = px(x0, y0 + 1) + fx * (px(x0 + 1, y0 + 1) - px(x0, y0 + 1));
    (upper + fy * (lower - upper) + 0.5) as i16
}

impl RegressionTree {
    /// A tree from its tests and its leaves' `f32` increments (`2^d · SHAPE_DIM` values), quantised.
    pub fn new(splits: Vec<SplitTest>, leaves: &[f32]) -> Self {
        let mut scales = Vec::with_capacity(leaves.len() / SHAPE_DIM);
        let mut values = Vec::with_capacity(leaves.len());
        for leaf in leaves.chunks_exact(SHAPE_DIM) {
            let max = leaf.iter().fold(0f32, |m, v| m.max(v.abs()));
            let scale = if max > 0.0 && max.is_finite() {
                max / 127.0
            } else {
                0.0
            };
            scales.push(scale);
            values.extend(leaf.iter().map(|v| {
                if scale > 0.0 {
                    (v / scale).round().clamp(-127.0, 127.0) as i8
                } else {
                    0
                }
            }));
        }
        Self {
            splits,
            scales,
            values,
        }
    }

    /// Adds leaf `leaf`'s increment to `delta` ([`SHAPE_DIM`] values).
    #[inline(always)]
    pub fn add_leaf(&self, leaf: usize, delta: &mut [f32]) {
        let scale = self.scales.get(leaf).copied().unwrap_or(0.0);
        if let Some(q) = self.values.get(leaf * SHAPE_DIM..(leaf + 1) * SHAPE_DIM) {
            for (d, v) in delta.iter_mut().zip(q) {
                *d += scale * f32::from(*v);
            }
        }
    }

    /// The leaf a sample with these feature values reaches.
    #[inline(always)]
    pub fn leaf_of(&self, features: &[i16], depth: usize) -> usize {
        let mut node = 0usize;
        for _ in 0..depth {
            let go_right = self.splits.get(node).is_some_and(|s| {
                let fu = features.get(usize::from(s.u)).copied().unwrap_or(0);
                let fv = features.get(usize::from(s.v)).copied().unwrap_or(0);
                f32::from(fu - fv) > s.threshold
            });
            node = 2 * node + 1 + usize::from(go_right);
        }
        node + 1 - (1 << depth)
    }
}

impl RefineCascade {
    /// Number of trees over all stages.
    pub fn tree_count(&self) -> usize {
        self.stages.iter().map(|s| s.trees.len()).sum()
    }

    /// Refines `shape` (68 points in crop pixels, DAN's answer) in place on `crop` (`crop_size²` gray8
    /// bytes, row-major).
    ///
    /// A stage whose shape has become degenerate is skipped; the result is always 68 finite points (the
    /// start is kept if a stage would produce anything else).
    pub fn refine(
        &self,
        crop: &[u8],
        shape: &mut [Point2; REFINE_LANDMARKS],
        scratch: &mut RefineScratch,
    ) -> Result<(), RefineError> {
        let expected = self.crop_size * self.crop_size;
        if crop.len() != expected {
            return Err(RefineError::CropSize {
                len: crop.len(),
                expected,
            });
        }
        if let Some(i) = shape.iter().position(|p| !(p.x.is_finite() && p.y.is_finite())) {
            return Err(RefineError::BadStart(format!("landmark {i} is not finite")));
        }
        if !self.mirror {
            self.refine_starts(crop, shape, scratch);
            return Ok(());
        }
        let size = self.crop_size;
        let mut flipped = std::mem::take(&mut scratch.flipped);
        flipped.clear();
        for row in crop.chunks_exact(size) {
            flipped.extend(row.iter().rev());
        }
        let mut other = crate::shape::mirror68(shape, size);
        self.refine_starts(&flipped, &mut other, scratch);
        scratch.flipped = flipped;
        let back = crate::shape::mirror68(&other, size);
        self.refine_starts(crop, shape, scratch);
        for (p, q) in shape.iter_mut().zip(&back) {
            *p = Point2::new(0.5 * (p.x + q.x), 0.5 * (p.y + q.y));
        }
        Ok(())
    }

    /// The cascade from [`RefineCascade::starts`] starts around `shape` (their per-coordinate median), in place.
    fn refine_starts(
        &self,
        crop: &[u8],
        shape: &mut [Point2; REFINE_LANDMARKS],
        scratch: &mut RefineScratch,
    ) {
        let starts = self.starts.clamp(1, START_OFFSETS.len());
        if starts == 1 {
            self.cascade(crop, shape, scratch);
            return;
        }
        // Several starts around the given shape, each refined, then the per-coordinate median.
        let frame = frame_of(&self.mean, shape);
        let centre = crate::geometry::centroid(shape);
        let mut results = Vec::with_capacity(starts);
        for &(dx, dy, scale, angle_deg) in &START_OFFSETS[..starts] {
            let mut s = *shape;
            if let Some((a, b)) = frame {
                let (sin, cos) = angle_deg.to_radians().sin_cos();
                let (tx, ty) = (a * dx - b * dy, b * dx + a * dy);
                for p in &mut s {
                    let (x, y) = (p.x - centre.x, p.y - centre.y);
                    *p = Point2::new(
                        centre.x + tx + scale * (cos * x - sin * y),
                        centre.y + ty + scale * (sin * x + cos * y),
                    );
                }
            }
            self.cascade(crop, &mut s, scratch);
            results.push(s);
        }
        let mut column = Vec::with_capacity(starts);
        for (i, p) in shape.iter_mut().enumerate() {
            column.clear();
            column.extend(results.iter().map(|r| r[i].x));
            let x = median(&mut column);
            column.clear();
            column.extend(results.iter().map(|r| r[i].y));
            *p = Point2::new(x, median(&mut column));
        }
    }

    /// One run of the stages from `shape`, in place.
    fn cascade(&self, crop: &[u8], shape: &mut [Point2; REFINE_LANDMARKS], scratch: &mut RefineScratch) {
        for stage in &self.stages {
            if !stage.apply(
                &self.mean,
                self.depth,
                (self.crop_size, self.sampling),
                crop,
                shape,
                scratch,
            ) {
                break;
            }
        }
    }

    /// [`RefineCascade::refine`] on `[x, y]` pairs (the engine's output layout), in place.
    pub fn refine_pairs(
        &self,
        crop: &[u8],
        landmarks: &mut [[f32; 2]],
        scratch: &mut RefineScratch,
    ) -> Result<(), RefineError> {
        if landmarks.len() != REFINE_LANDMARKS {
            return Err(RefineError::BadStart(format!(
                "{} landmarks, the refiner needs {REFINE_LANDMARKS}",
                landmarks.len()
            )));
        }
        let mut shape: [Point2; REFINE_LANDMARKS] =
            std::array::from_fn(|i| Point2::new(landmarks[i][0], landmarks[i][1]));
        self.refine(crop, &mut shape, scratch)?;
        for (l, p) in landmarks.iter_mut().zip(&shape) {
            *l = [p.x, p.y];
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::shape::dan_mean_shape;

    /// A one-stage, one-tree refiner of depth 1 whose test reads two fixed pixels.
    pub(crate) fn tiny(left: f32, right: f32) -> RefineCascade {
        let mut leaves = vec![left; SHAPE_DIM];
        leaves.extend(std::iter::repeat_n(right, SHAPE_DIM));
        RefineCascade {
            crop_size: 112,
            depth: 1,
            mean: dan_mean_shape(),
            stages: vec![RefineStage {
                anchors: vec![30, 30],
                offsets: vec![[0.0, 0.0], [10.0, 0.0]],
                trees: vec![RegressionTree::new(
                    vec![SplitTest {
                        u: 0,
                        v: 1,
                        threshold: 20.0,
                    }],
                    &leaves,
                )],
            }],
            name: "tiny".into(),
            starts: 1,
            mirror: false,
            sampling: Sampling::Nearest,
        }
    }

    #[test]
    fn a_tree_moves_the_shape_by_its_leaf_in_the_shapes_frame() {
        let r = tiny(1.0, -2.0);
        let mut crop = vec![0u8; 112 * 112];
        let mut shape = dan_mean_shape();
        let mut scratch = RefineScratch::default();
        // Both pixels 0: difference 0 <= 20, left leaf (+1 in x and y, identity frame).
        r.refine(&crop, &mut shape, &mut scratch).unwrap();
        let m = dan_mean_shape();
        assert!((shape[0].x - m[0].x - 1.0).abs() < 1e-4 && (shape[0].y - m[0].y - 1.0).abs() < 1e-4);
        // The anchor pixel bright: right leaf.
        let p = m[30];
        crop[(p.y.round() as usize) * 112 + p.x.round() as usize] = 200;
        let mut shape = m;
        r.refine(&crop, &mut shape, &mut scratch).unwrap();
        assert!((shape[5].x - m[5].x + 2.0).abs() < 1e-4);
        // A shape twice the size rotated by 90 degrees: the increment turns and scales with it.
        let rot = Similarity2::from_parts(2.0, std::f64::consts::FRAC_PI_2, 300.0, 0.0);
        let mut shape = [Point2::default(); 68];
        rot.apply_all(&m, &mut shape);
        let start = shape;
        r.refine(&vec![0u8; 112 * 112], &mut shape, &mut scratch).unwrap();
        // (1, 1) in the mean frame is (-2, 2) after a 90 degree turn and a scale of 2.
        assert!((shape[3].x - start[3].x + 2.0).abs() < 1e-3, "{:?}", shape[3]);
        assert!((shape[3].y - start[3].y - 2.0).abs() < 1e-3, "{:?}", shape[3]);
    }

    #[test]
    fn several_starts_give_the_median_of_their_answers() {
        let crop = vec![0u8; 112 * 112];
        let mut scratch = RefineScratch::default();
        let single = {
            let mut s = dan_mean_shape();
            tiny(1.0, -2.0).refine(&crop, &mut s, &mut scratch).unwrap();
            s
        };
        // The starts are symmetric about the given shape and this cascade moves every start alike, so the
        // median is the single start's answer.
        for starts in [3, 5, 7, 9] {
            let mut r = tiny(1.0, -2.0);
            r.starts = starts;
            let mut s = dan_mean_shape();
            r.refine(&crop, &mut s, &mut scratch).unwrap();
            for (a, b) in s.iter().zip(&single) {
                assert!(a.dist(*b) < 1e-3, "{starts} starts: {a:?} vs {b:?}");
            }
        }
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0]), 2.5);
    }

    #[test]
    fn bad_inputs_are_errors_not_panics() {
        let r = tiny(0.0, 0.0);
        let mut scratch = RefineScratch::default();
        let mut shape = dan_mean_shape();
        assert!(matches!(
            r.refine(&[0u8; 10], &mut shape, &mut scratch),
            Err(RefineError::CropSize { len: 10, .. })
        ));
        shape[7].x = f32::NAN;
        assert!(matches!(
            r.refine(&vec![0u8; 112 * 112], &mut shape, &mut scratch),
            Err(RefineError::BadStart(_))
        ));
        let mut pairs = vec![[0.0f32; 2]; 67];
        assert!(
            r.refine_pairs(&vec![0u8; 112 * 112], &mut pairs, &mut scratch)
                .is_err()
        );
        // A degenerate start (all points equal) is left as it is.
        let mut same = [Point2::new(5.0, 5.0); 68];
        r.refine(&vec![0u8; 112 * 112], &mut same, &mut scratch).unwrap();
        assert_eq!(same, [Point2::new(5.0, 5.0); 68]);
    }

    #[test]
    fn the_mirrored_answer_is_averaged_in() {
        // A cascade that moves every point right by 1 (in its frame) moves a mirrored start right too, that
        // is left once mirrored back: the two cancel.
        let crop = vec![0u8; 112 * 112];
        let mut scratch = RefineScratch::default();
        let mut r = tiny(1.0, 1.0);
        let start = dan_mean_shape();
        let mut plain = start;
        r.refine(&crop, &mut plain, &mut scratch).unwrap();
        r.mirror = true;
        let mut both = start;
        r.refine(&crop, &mut both, &mut scratch).unwrap();
        let mean_dx = |s: &[Point2; 68]| s.iter().zip(&start).map(|(a, b)| a.x - b.x).sum::<f32>() / 68.0;
        assert!((mean_dx(&plain) - 1.0).abs() < 1e-3, "{}", mean_dx(&plain));
        assert!(mean_dx(&both).abs() < 0.05, "{}", mean_dx(&both));
    }

    /// Whichever instruction set runs the stage, the answer is bit-identical to the portable code's.
    #[test]
    fn the_vector_paths_agree_bit_for_bit_with_the_portable_one() {
        let mut rng = crate::rng::Rng::new(7);
        let mean = dan_mean_shape();
        let trees = (0..60)
            .map(|_| {
                let splits = (0..15)
                    .map(|_| SplitTest {
                        u: rng.below(50) as u16,
                        v: rng.below(50) as u16,
                        threshold: (rng.uniform() as f32 - 0.5) * 100.0,
                    })
                    .collect();
                let leaves: Vec<f32> = (0..16 * SHAPE_DIM)
                    .map(|_| (rng.uniform() as f32 - 0.5) * 0.7)
                    .collect();
                RegressionTree::new(splits, &leaves)
            })
            .collect();
        let stage = RefineStage {
            anchors: (0..50).map(|_| rng.below(68) as u8).collect(),
            offsets: (0..50)
                .map(|_| {
                    [
                        (rng.uniform() as f32 - 0.5) * 8.0,
                        (rng.uniform() as f32 - 0.5) * 8.0,
                    ]
                })
                .collect(),
            trees,
        };
        let crop: Vec<u8> = (0..112 * 112).map(|_| rng.below(256) as u8).collect();
        let start = mean.map(|p| Point2::new(p.x + 0.7, p.y - 1.3));
        let (mut a, mut b) = (start, start);
        let mut scratch = RefineScratch::default();
        assert!(stage.apply(&mean, 4, (112, Sampling::Bilinear), &crop, &mut a, &mut scratch));
        assert!(stage.apply_portable(&mean, 4, (112, Sampling::Bilinear), &crop, &mut b, &mut scratch));
        assert_ne!(a, start, "the stage moved the shape");
        for (p, q) in a.iter().zip(&b) {
            assert_eq!((p.x.to_bits(), p.y.to_bits()), (q.x.to_bits(), q.y.to_bits()));
        }
    }

    #[test]
    fn bilinear_features_follow_sub_pixel_moves() {
        // A horizontal ramp, 10 grey levels per pixel: bilinear reads 10 per pixel moved, in tenths too;
        // the nearest pixel jumps.
        let crop: Vec<u8> = (0..8 * 8).map(|i| (i % 8 * 10) as u8).collect();
        let read = |x: f32, sampling| {
            let mut out = [0i16; 1];
            read_features(
                &crop,
                (8, sampling),
                &[Point2::new(x, 3.0)],
                (1.0, 0.0),
                &[0],
                &[[0.0, 0.0]],
                &mut out,
            );
            out[0]
        };
        assert_eq!(read(2.0, Sampling::Bilinear), 20);
        assert_eq!(read(2.3, Sampling::Bilinear), 23);
        assert_eq!(read(2.75, Sampling::Bilinear), 28);
        assert_eq!(read(2.3, Sampling::Nearest), 20);
        assert_eq!(read(2.75, Sampling::Nearest), 30);
        // The border: clamped to the last pixel inside, 0 outside, as nearest.
        assert_eq!(read(7.2, Sampling::Bilinear), 70);
        assert_eq!(read(-0.4, Sampling::Bilinear), 0);
        assert_eq!(read(7.6, Sampling::Bilinear), 0);
        assert_eq!(read(-0.6, Sampling::Bilinear), 0);
    }

    #[test]
    fn features_outside_the_crop_read_zero() {
        let crop = vec![255u8; 4 * 4];
        let shape = [Point2::new(1.0, 1.0); 1];
        let mut out = [7i16; 3];
        read_features(
            &crop,
            (4, Sampling::Nearest),
            &shape,
            (1.0, 0.0),
            &[0, 0, 0],
            &[[0.0, 0.0], [5.0, 0.0], [-1.6, 0.0]],
            &mut out,
        );
        assert_eq!(out, [255, 0, 0]);
    }
}
