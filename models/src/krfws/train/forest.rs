//! The stage data and the weighted K-cluster regression forests of one cascade stage (see the module docs of
//! [`super`]: "Weighted K-cluster splits").

use super::*;

pub(super) struct StageData {
    pub(super) hog: Vec<f32>,
    pub(super) targets: Vec<f32>,
    pub(super) sims: Vec<Option<Similarity2>>,
    pub(super) norms: Vec<[Point2; N_POINTS]>,
}

pub(super) fn stage_data(
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

pub(super) struct TreeBuilder<'a> {
    pub(super) hog: &'a [f32],
    pub(super) targets: &'a [f32],
    pub(super) landmark: usize,
    pub(super) cfg: &'a TrainConfig,
    pub(super) rng: Rng,
    pub(super) nodes: Vec<Node>,
    pub(super) projections: Vec<f32>,
    pub(super) n_leaves: u32,
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
        let ys: Vec<[f64; 2]> = idx.iter().map(|&i| self.y(i)).collect();
        let (label, c) = two_means(&ys)?;
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
        let k = best_cut(&ys, &proj, min_leaf)?;
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
        crate::krfws::format::round_f16(&mut v);
        Some(v)
    }
}

/// Trains the forests of one landmark; returns the trees and each sample's local leaf per tree
/// (`n · trees`, sample-major).
pub(super) fn train_forest(
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

/// 2-means on the 2-D targets `ys`, initialised on their principal axis: each sample's cluster and the two
/// centres; `None` when a cluster empties.
fn two_means(ys: &[[f64; 2]]) -> Option<(Vec<bool>, [[f64; 2]; 2])> {
    let n = ys.len();
    let mean = ys.iter().fold([0.0; 2], |a, y| [a[0] + y[0], a[1] + y[1]]);
    let mean = [mean[0] / n as f64, mean[1] / n as f64];
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for y in ys {
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
    Some((label, c))
}

/// Where to cut the samples sorted by projection (`proj`: value, sample, index into `ys`): the count on the
/// left minimising the children's squared error, each child keeping `min_leaf` samples and the cut falling
/// between two different values.
fn best_cut(ys: &[[f64; 2]], proj: &[(f32, u32, usize)], min_leaf: usize) -> Option<usize> {
    let n = ys.len();
    let (mut tx, mut ty, mut tq) = (0.0f64, 0.0f64, 0.0f64);
    for y in ys {
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
    best.map(|(_, k)| k)
}
