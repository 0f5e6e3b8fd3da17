//! Training the refinement cascade, pure: in-memory crops with DAN's start shapes and the ground truth
//! in, a [`RefineCascade`] out; no IO, no clock. Deterministic for a given seed whatever the thread count
//! (every random stream is seeded from the seed and the stage/tree it serves; sums are merged in chunk
//! order).
//!
//! Gradient boosting as in Kazemi & Sullivan (2014) and dlib's `shape_predictor_trainer`:
//! - each stage draws a pool of feature points uniformly in the mean shape's box (grown by
//!   [`RefineConfig::padding`]), each anchored to its nearest landmark, and reads their grey levels on
//!   every sample at its current shape;
//! - each tree is grown level by level on the residuals `target − current` (mean-shape frame): at every
//!   node [`RefineConfig::split_tests`] random tests `I(u) − I(v) > τ` are scored (pairs drawn with a
//!   prior `exp(−‖u − v‖ / (λ · extent))` favouring nearby points, `τ` uniform in ±64 grey levels) and the
//!   one maximising `‖Σ_left‖²/n_left + ‖Σ_right‖²/n_right` (the sum-of-squares reduction) is kept;
//! - a leaf holds the mean residual of its samples times the learning rate, and the residuals are
//!   reduced by it before the next tree;
//! - at the end of a stage every shape moves by the sum of its leaves, turned back into crop pixels.

use super::{
    REFINE_LANDMARKS, RefineCascade, RefineStage, RegressionTree, SHAPE_DIM, Sampling, SplitTest, frame_of,
    read_features,
};
use crate::accuracy::nme68;
use crate::geometry::{Point2, Rect};
use crate::rng::Rng;
use thiserror::Error;

/// One training sample: a crop as the server receives it, DAN's answer on it and the ground truth, both
/// in crop pixels.
#[derive(Clone, Copy, Debug)]
pub struct RefineSample<'a> {
    /// `crop_size²` gray8 bytes.
    pub crop: &'a [u8],
    /// Where the cascade starts (DAN's landmarks on this crop).
    pub start: [Point2; REFINE_LANDMARKS],
    /// The annotated landmarks mapped into the crop.
    pub target: [Point2; REFINE_LANDMARKS],
}

/// Training settings.
#[derive(Clone, Debug, PartialEq)]
pub struct RefineConfig {
    /// Cascade stages.
    pub stages: usize,
    /// Trees per stage.
    pub trees: usize,
    /// Depth of every tree.
    pub depth: usize,
    /// Feature points per stage.
    pub features: usize,
    /// Random tests scored per node.
    pub split_tests: usize,
    /// Shrinkage applied to every leaf.
    pub learning_rate: f32,
    /// Locality prior of the test pairs, as a fraction of the mean shape's extent.
    pub lambda: f32,
    /// Growth of the mean shape's box the feature points are drawn in (fraction of its extent).
    pub padding: f32,
    /// Feature points drawn around the landmarks instead of over the whole face box: each point is a
    /// random landmark plus an offset uniform in a disc whose radius (mean-shape frame, crop pixels)
    /// shrinks geometrically from the first value at the first stage to the second at the last
    /// (coarse to fine, as in LBF's local features). `None`: dlib's face-box pool.
    pub local_radius: Option<(f32, f32)>,
    /// How the feature points read the crop.
    pub sampling: Sampling,
    /// Seed of every random stream.
    pub seed: u64,
    /// Worker threads.
    pub threads: usize,
    /// Identity written into the model (`name version`).
    pub name: String,
}

impl Default for RefineConfig {
    /// dlib's shape-predictor defaults (10 stages, 500 trees of depth 4, 400 features, 20 tests, ν 0.1,
    /// λ 0.1).
    fn default() -> Self {
        Self {
            stages: 10,
            trees: 500,
            depth: 4,
            features: 400,
            split_tests: 20,
            learning_rate: 0.1,
            lambda: 0.1,
            padding: 0.1,
            local_radius: None,
            sampling: Sampling::Nearest,
            seed: 1,
            threads: 2,
            name: "holoface-ert".into(),
        }
    }
}

/// Why training cannot run.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum RefineTrainError {
    /// No samples.
    #[error("no training samples")]
    NoSamples,
    /// A sample's crop is not `crop_size²` bytes.
    #[error("sample {index}: crop of {len} bytes, expected {expected}")]
    CropSize {
        /// Sample index.
        index: usize,
        /// Its length.
        len: usize,
        /// `crop_size²`.
        expected: usize,
    },
    /// Bad configuration.
    #[error("bad configuration: {0}")]
    Config(&'static str),
}

/// Progress after one stage.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StageReport {
    /// Stage index (0-based).
    pub stage: usize,
    /// Mean NME68 (outer eye corners) of the training shapes before the stage.
    pub nme_before: f64,
    /// The same after it.
    pub nme_after: f64,
}

fn mean_nme(cur: &[[Point2; REFINE_LANDMARKS]], samples: &[RefineSample<'_>]) -> f64 {
    let sum: f64 = cur
        .iter()
        .zip(samples)
        .filter_map(|(c, s)| nme68(c, &s.target))
        .sum();
    sum / cur.len().max(1) as f64
}

/// Samples per block of work: sums are formed per block and merged in block order, so results do not
/// depend on the thread count.
const BLOCK: usize = 2048;

/// Runs `f` over `0..n` in blocks of [`BLOCK`], the blocks spread over `threads` threads; results in
/// block order.
fn blocked<T: Send>(n: usize, threads: usize, f: impl Fn(std::ops::Range<usize>) -> T + Sync) -> Vec<T> {
    let blocks = n.div_ceil(BLOCK).max(1);
    let run = |bs: std::ops::Range<usize>| -> Vec<T> {
        bs.map(|b| f((b * BLOCK).min(n)..((b + 1) * BLOCK).min(n)))
            .collect()
    };
    let threads = threads.clamp(1, blocks);
    if threads == 1 {
        return run(0..blocks);
    }
    let per = blocks.div_ceil(threads);
    std::thread::scope(|sc| {
        let run = &run;
        let handles: Vec<_> = (0..threads)
            .map(|t| sc.spawn(move || run((t * per).min(blocks)..((t + 1) * per).min(blocks))))
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().unwrap_or_else(|e| std::panic::resume_unwind(e)))
            .collect()
    })
}

/// A stage's feature pool: with [`RefineConfig::local_radius`], points in a disc of this stage's radius
/// around random landmarks; else points uniform in the grown mean-shape box, each anchored to its nearest
/// landmark. Returns (anchors, offsets, positions in the mean frame).
fn feature_pool(
    mean: &[Point2; REFINE_LANDMARKS],
    cfg: &RefineConfig,
    stage: usize,
    rng: &mut Rng,
) -> (Vec<u8>, Vec<[f32; 2]>, Vec<Point2>) {
    if let Some((first, last)) = cfg.local_radius {
        let t = if cfg.stages > 1 {
            stage as f32 / (cfg.stages - 1) as f32
        } else {
            0.0
        };
        let radius = first * (last / first).powf(t);
        let mut out = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..cfg.features {
            let k = rng.below(REFINE_LANDMARKS);
            let r = radius * (rng.uniform() as f32).sqrt();
            let a = std::f32::consts::TAU * rng.uniform() as f32;
            let off = [r * a.cos(), r * a.sin()];
            out.0.push(k as u8);
            out.1.push(off);
            out.2.push(Point2::new(mean[k].x + off[0], mean[k].y + off[1]));
        }
        return out;
    }
    let b = Rect::bounding(mean).unwrap_or_default();
    let pad = cfg.padding * b.width().max(b.height());
    let (x0, y0, x1, y1) = (b.x0 - pad, b.y0 - pad, b.x1 + pad, b.y1 + pad);
    let mut anchors = Vec::with_capacity(cfg.features);
    let mut offsets = Vec::with_capacity(cfg.features);
    let mut pos = Vec::with_capacity(cfg.features);
    for _ in 0..cfg.features {
        let p = Point2::new(
            x0 + (x1 - x0) * rng.uniform() as f32,
            y0 + (y1 - y0) * rng.uniform() as f32,
        );
        let (k, _) = mean
            .iter()
            .enumerate()
            .map(|(k, m)| (k, m.dist(p)))
            .fold((0, f32::MAX), |best, c| if c.1 < best.1 { c } else { best });
        anchors.push(k as u8);
        offsets.push([p.x - mean[k].x, p.y - mean[k].y]);
        pos.push(p);
    }
    (anchors, offsets, pos)
}

/// A random node test: a pair drawn with the locality prior, a threshold in ±64 grey levels.
fn random_test(pos: &[Point2], scale: f32, rng: &mut Rng) -> SplitTest {
    let n = pos.len();
    let u = rng.below(n);
    let mut v = (u + 1) % n;
    for _ in 0..1000 {
        let c = rng.below(n);
        if c != u && rng.uniform() < f64::from((-pos[u].dist(pos[c]) / scale).exp()) {
            v = c;
            break;
        }
    }
    SplitTest {
        u: u as u16,
        v: v as u16,
        threshold: (rng.uniform() as f32 * 256.0 - 128.0) / 2.0,
    }
}

#[inline]
fn goes_right(f: &[i16], s: &SplitTest) -> bool {
    f32::from(f[usize::from(s.u)] - f[usize::from(s.v)]) > s.threshold
}

/// Of a node's candidate tests (each with the sum of the residuals it sends right, `right_sums`, and how many,
/// `right_counts`), the one whose children's summed squared means are largest (the least squared error left);
/// `parent` is the node's residual sum over its `n_node` samples.
fn best_test(parent: &[f64], n_node: usize, right_sums: &[f64], right_counts: &[usize]) -> usize {
    let mut best = (f64::MIN, 0usize);
    for (c, (right, &nr)) in right_sums.chunks_exact(SHAPE_DIM).zip(right_counts).enumerate() {
        let nl = n_node - nr;
        let score = if nr == 0 || nl == 0 {
            f64::MIN / 2.0
        } else {
            let (mut sr, mut sl) = (0.0, 0.0);
            for (p, r) in parent.iter().zip(right) {
                sr += r * r;
                sl += (p - r) * (p - r);
            }
            sr / nr as f64 + sl / nl as f64
        };
        if score > best.0 {
            best = (score, c);
        }
    }
    best.1
}

/// The leaves of a tree of `depth` from its nodes' residual sums and counts: each leaf's mean residual times
/// the learning rate (0 for an empty leaf).
fn leaf_means(sums: &[f64], counts: &[usize], depth: usize, learning_rate: f32) -> Vec<f32> {
    let first_leaf = (1usize << depth) - 1;
    let mut leaves = vec![0f32; (1 << depth) * SHAPE_DIM];
    for (l, leaf) in leaves.chunks_exact_mut(SHAPE_DIM).enumerate() {
        let node = first_leaf + l;
        if counts[node] > 0 {
            let k = f64::from(learning_rate) / counts[node] as f64;
            for (v, s) in leaf
                .iter_mut()
                .zip(&sums[node * SHAPE_DIM..(node + 1) * SHAPE_DIM])
            {
                *v = (s * k) as f32;
            }
        }
    }
    leaves
}

/// Grows one tree on `resid` (n × [`SHAPE_DIM`]) and subtracts its leaves from the residuals.
fn grow_tree(
    feats: &[i16],
    n_feat: usize,
    resid: &mut [f32],
    pos: &[Point2],
    scale: f32,
    cfg: &RefineConfig,
    rng: &mut Rng,
) -> RegressionTree {
    let n = resid.len() / SHAPE_DIM;
    let depth = cfg.depth;
    let total = (1usize << (depth + 1)) - 1;
    let c_tests = cfg.split_tests;
    let mut node_of = vec![0u32; n];
    let mut sums = vec![0f64; total * SHAPE_DIM];
    let mut counts = vec![0usize; total];
    for r in resid.chunks_exact(SHAPE_DIM) {
        for (s, v) in sums[..SHAPE_DIM].iter_mut().zip(r) {
            *s += f64::from(*v);
        }
    }
    counts[0] = n;
    let mut splits = Vec::with_capacity((1 << depth) - 1);
    for level in 0..depth {
        let first = (1usize << level) - 1;
        let width = 1usize << level;
        let cands: Vec<SplitTest> = (0..width * c_tests)
            .map(|_| random_test(pos, scale, rng))
            .collect();
        let slots = width * c_tests;
        let resid_ro: &[f32] = resid;
        let node_ro = &node_of;
        let partial = blocked(n, cfg.threads, |range| {
            let mut acc = vec![0f32; slots * SHAPE_DIM];
            let mut cnt = vec![0usize; slots];
            for i in range {
                let j = node_ro[i] as usize - first;
                let f = &feats[i * n_feat..(i + 1) * n_feat];
                let r = &resid_ro[i * SHAPE_DIM..(i + 1) * SHAPE_DIM];
                for c in 0..c_tests {
                    let slot = j * c_tests + c;
                    if goes_right(f, &cands[slot]) {
                        cnt[slot] += 1;
                        for (a, v) in acc[slot * SHAPE_DIM..(slot + 1) * SHAPE_DIM].iter_mut().zip(r) {
                            *a += *v;
                        }
                    }
                }
            }
            (acc, cnt)
        });
        let mut acc = vec![0f64; slots * SHAPE_DIM];
        let mut cnt = vec![0usize; slots];
        for (pa, pc) in &partial {
            for (a, v) in acc.iter_mut().zip(pa) {
                *a += f64::from(*v);
            }
            for (a, v) in cnt.iter_mut().zip(pc) {
                *a += *v;
            }
        }
        for j in 0..width {
            let node = first + j;
            let n_node = counts[node];
            let parent = &sums[node * SHAPE_DIM..(node + 1) * SHAPE_DIM];
            let tests = j * c_tests..(j + 1) * c_tests;
            let slot = j * c_tests
                + best_test(
                    parent,
                    n_node,
                    &acc[tests.start * SHAPE_DIM..tests.end * SHAPE_DIM],
                    &cnt[tests],
                );
            splits.push(cands[slot]);
            let (l, r) = (2 * node + 1, 2 * node + 2);
            counts[r] = cnt[slot];
            counts[l] = n_node - cnt[slot];
            for k in 0..SHAPE_DIM {
                let right = acc[slot * SHAPE_DIM + k];
                sums[r * SHAPE_DIM + k] = right;
                sums[l * SHAPE_DIM + k] = sums[node * SHAPE_DIM + k] - right;
            }
        }
        for (i, nd) in node_of.iter_mut().enumerate() {
            let node = *nd as usize;
            let s = &splits[node];
            let right = goes_right(&feats[i * n_feat..(i + 1) * n_feat], s);
            *nd = (2 * node + 1 + usize::from(right)) as u32;
        }
    }
    let first_leaf = (1usize << depth) - 1;
    let leaves = leaf_means(&sums, &counts, depth, cfg.learning_rate);
    // Quantised as the file stores it; training subtracts exactly what inference will add.
    let tree = RegressionTree::new(splits, &leaves);
    let mut step = vec![0f32; SHAPE_DIM];
    for (r, nd) in resid.chunks_exact_mut(SHAPE_DIM).zip(&node_of) {
        step.fill(0.0);
        tree.add_leaf(*nd as usize - first_leaf, &mut step);
        for (a, v) in r.iter_mut().zip(&step) {
            *a -= *v;
        }
    }
    tree
}

/// Trains a cascade on `samples` (crops of `crop_size²` bytes) with `mean` as its reference frame;
/// `on_stage` hears the training error after every stage, with the stage (to follow held-out error).
pub fn train(
    samples: &[RefineSample<'_>],
    mean: &[Point2; REFINE_LANDMARKS],
    crop_size: usize,
    cfg: &RefineConfig,
    on_stage: &mut dyn FnMut(&StageReport, &RefineStage),
) -> Result<RefineCascade, RefineTrainError> {
    if samples.is_empty() {
        return Err(RefineTrainError::NoSamples);
    }
    if cfg.stages == 0 || cfg.trees == 0 || !(1..=8).contains(&cfg.depth) {
        return Err(RefineTrainError::Config("stages, trees >= 1 and depth 1..=8"));
    }
    if !(2..=4096).contains(&cfg.features) || cfg.split_tests == 0 {
        return Err(RefineTrainError::Config("features 2..=4096 and split_tests >= 1"));
    }
    let expected = crop_size * crop_size;
    if let Some((index, s)) = samples.iter().enumerate().find(|(_, s)| s.crop.len() != expected) {
        return Err(RefineTrainError::CropSize {
            index,
            len: s.crop.len(),
            expected,
        });
    }
    let n = samples.len();
    let extent = Rect::bounding(mean).map_or(1.0, |b| b.width().max(b.height()));
    let scale = cfg.lambda * extent;
    let mut cur: Vec<[Point2; REFINE_LANDMARKS]> = samples.iter().map(|s| s.start).collect();
    let mut stages = Vec::with_capacity(cfg.stages);
    for st in 0..cfg.stages {
        let nme_before = mean_nme(&cur, samples);
        let frames: Vec<(f32, f32)> = cur
            .iter()
            .map(|c| frame_of(mean, c).unwrap_or((1.0, 0.0)))
            .collect();
        let mut resid = vec![0f32; n * SHAPE_DIM];
        for (i, r) in resid.chunks_exact_mut(SHAPE_DIM).enumerate() {
            let (a, b) = frames[i];
            let inv = 1.0 / (a * a + b * b);
            for k in 0..REFINE_LANDMARKS {
                let dx = samples[i].target[k].x - cur[i][k].x;
                let dy = samples[i].target[k].y - cur[i][k].y;
                r[2 * k] = (a * dx + b * dy) * inv;
                r[2 * k + 1] = (-b * dx + a * dy) * inv;
            }
        }
        let mut pool_rng = Rng::stream(cfg.seed, &[st as u64, u64::MAX]);
        let (anchors, offsets, pos) = feature_pool(mean, cfg, st, &mut pool_rng);
        let nf = anchors.len();
        let chunks = blocked(n, cfg.threads, |range| {
            let mut out = vec![0i16; range.len() * nf];
            for (o, i) in out.chunks_exact_mut(nf).zip(range) {
                read_features(
                    samples[i].crop,
                    (crop_size, cfg.sampling),
                    &cur[i],
                    frames[i],
                    &anchors,
                    &offsets,
                    o,
                );
            }
            out
        });
        let feats: Vec<i16> = chunks.concat();
        let start_resid = resid.clone();
        let mut trees = Vec::with_capacity(cfg.trees);
        for t in 0..cfg.trees {
            let mut rng = Rng::stream(cfg.seed, &[st as u64, t as u64]);
            trees.push(grow_tree(&feats, nf, &mut resid, &pos, scale, cfg, &mut rng));
        }
        for (i, c) in cur.iter_mut().enumerate() {
            let (a, b) = frames[i];
            let r0 = &start_resid[i * SHAPE_DIM..(i + 1) * SHAPE_DIM];
            let r1 = &resid[i * SHAPE_DIM..(i + 1) * SHAPE_DIM];
            for k in 0..REFINE_LANDMARKS {
                let (dx, dy) = (r0[2 * k] - r1[2 * k], r0[2 * k + 1] - r1[2 * k + 1]);
                c[k] = Point2::new(c[k].x + a * dx - b * dy, c[k].y + b * dx + a * dy);
            }
        }
        let stage = RefineStage {
            anchors,
            offsets,
            trees,
        };
        on_stage(
            &StageReport {
                stage: st,
                nme_before,
                nme_after: mean_nme(&cur, samples),
            },
            &stage,
        );
        stages.push(stage);
    }
    Ok(RefineCascade {
        crop_size,
        depth: cfg.depth,
        mean: *mean,
        stages,
        name: cfg.name.clone(),
        starts: 1,
        mirror: false,
        sampling: cfg.sampling,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::refine::RefineScratch;
    use crate::shape::dan_mean_shape;

    /// Synthetic crops whose landmark positions are written into the pixels: a bright dot at every
    /// true landmark on a dark background; starts are the truth shifted by a per-sample offset. A cascade
    /// must learn to move the shape onto the dots, on the training samples and on new ones.
    /// Crops, start shapes and target shapes.
    type Dots = (Vec<Vec<u8>>, Vec<[Point2; 68]>, Vec<[Point2; 68]>);

    fn dots(n: usize, seed: u64) -> Dots {
        let mean = dan_mean_shape();
        let mut rng = Rng::new(seed);
        let (mut crops, mut starts, mut targets) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..n {
            let (tx, ty) = (
                (rng.uniform() * 6.0 - 3.0) as f32,
                (rng.uniform() * 6.0 - 3.0) as f32,
            );
            let target: [Point2; 68] = std::array::from_fn(|k| Point2::new(mean[k].x + tx, mean[k].y + ty));
            let mut crop = vec![20u8; 112 * 112];
            for p in &target {
                for dy in -1i32..=1 {
                    for dx in -1i32..=1 {
                        let (x, y) = (p.x.round() as i32 + dx, p.y.round() as i32 + dy);
                        if (0..112).contains(&x) && (0..112).contains(&y) {
                            crop[y as usize * 112 + x as usize] = 230;
                        }
                    }
                }
            }
            crops.push(crop);
            starts.push(mean);
            targets.push(target);
        }
        (crops, starts, targets)
    }

    #[test]
    fn training_reduces_the_error_and_generalises_on_a_synthetic_task() {
        let mean = dan_mean_shape();
        let (crops, starts, targets) = dots(300, 1);
        let samples: Vec<RefineSample<'_>> = crops
            .iter()
            .zip(&starts)
            .zip(&targets)
            .map(|((c, s), t)| RefineSample {
                crop: c,
                start: *s,
                target: *t,
            })
            .collect();
        let cfg = RefineConfig {
            stages: 4,
            trees: 40,
            features: 200,
            ..RefineConfig::default()
        };
        let mut reports = Vec::new();
        let model = train(&samples, &mean, 112, &cfg, &mut |r, _| reports.push(*r)).unwrap();
        assert_eq!(reports.len(), 4);
        let first = reports[0].nme_before;
        let last = reports[3].nme_after;
        assert!(last < 0.5 * first, "training error {first} -> {last}");
        // Same seed, other thread count: the same model.
        let again = train(
            &samples,
            &mean,
            112,
            &RefineConfig {
                threads: 1,
                ..cfg.clone()
            },
            &mut |_, _| {},
        )
        .unwrap();
        assert_eq!(again, model);
        // New samples.
        let (crops, starts, targets) = dots(50, 99);
        let mut scratch = RefineScratch::default();
        let (mut before, mut after) = (0.0, 0.0);
        for ((c, s), t) in crops.iter().zip(&starts).zip(&targets) {
            let mut shape = *s;
            model.refine(c, &mut shape, &mut scratch).unwrap();
            before += nme68(s, t).unwrap();
            after += nme68(&shape, t).unwrap();
        }
        assert!(after < 0.6 * before, "held-out error {before} -> {after}");
        // The file round trip gives the same answers.
        let back = RefineCascade::from_bytes(&model.to_bytes().unwrap()).unwrap();
        let mut a = starts[0];
        let mut b = starts[0];
        model.refine(&crops[0], &mut a, &mut scratch).unwrap();
        back.refine(&crops[0], &mut b, &mut scratch).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn bad_training_input_is_an_error() {
        let mean = dan_mean_shape();
        let cfg = RefineConfig::default();
        assert_eq!(
            train(&[], &mean, 112, &cfg, &mut |_, _| {}),
            Err(RefineTrainError::NoSamples)
        );
        let crop = [0u8; 5];
        let s = RefineSample {
            crop: &crop,
            start: mean,
            target: mean,
        };
        assert!(matches!(
            train(&[s], &mean, 112, &cfg, &mut |_, _| {}),
            Err(RefineTrainError::CropSize { index: 0, len: 5, .. })
        ));
        let bad = RefineConfig { depth: 0, ..cfg };
        assert!(matches!(
            train(&[s], &mean, 112, &bad, &mut |_, _| {}),
            Err(RefineTrainError::Config(_))
        ));
    }
}
