//! A cascade stage: the landmarks' forests of oblique trees, the global regression matrix `W`, and their
//! vector-kernel layouts (f16 nodes in cache-line blocks, f16 rows of `W`), with the software-pipelined
//! sampling, HOG and routing of [`Stage::features_and_leaves`].

use super::*;

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
    /// The projection of internal node `node`.
    #[inline(always)]
    pub fn projection(&self, node: usize) -> Option<&[f32; HOG_DIM]> {
        self.projections
            .get(node * HOG_DIM..(node + 1) * HOG_DIM)?
            .try_into()
            .ok()
    }

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
    /// `N_POINTS · trees_per_forest` trees, landmark-major (call [`Stage::refresh`] after changing them).
    pub trees: Vec<Tree>,
    /// `n_leaves × 102` row-major regression matrix, in mean-shape units (multiplied by `scale` at use;
    /// call [`Stage::refresh`] after changing it).
    pub weights: Vec<f32>,
    /// Global index of each tree's leaf 0 (prefix sums of `n_leaves`); derived.
    pub(super) leaf_offsets: Vec<u32>,
    /// Every tree's nodes in the vector kernels' layout, tree after tree (empty unless every
    /// projection is exactly an f16); derived.
    pub(super) packed: Vec<PackedNode>,
    /// Index of each tree's root in `packed`.
    pub(super) packed_offsets: Vec<u32>,
    /// `W` as f16 bit patterns, rows padded to [`HALF_ROW`] values (empty unless every value is
    /// exactly an f16); derived.
    pub(super) half_weights: Vec<u16>,
    /// The stage's destination shape in the normalised frame; derived from the mean shape and scale.
    pub(super) dest: [Point2; N_POINTS],
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
        let mut stage = Self {
            scale,
            trees_per_forest,
            trees,
            weights,
            leaf_offsets: Vec::new(),
            packed: Vec::new(),
            packed_offsets: Vec::new(),
            half_weights: Vec::new(),
            dest: stage_dest(mean, scale),
        };
        stage.refresh();
        stage
    }

    /// Rebuilds what is derived from `trees` and `weights`: the leaf offsets and the f16 copies the
    /// vector kernels stream (every node as a `PackedNode`, `W` as f16 rows). Each copy is made only
    /// if every value is exactly an f16 (a stored model is: see `Krfws::round_to_storage`), so it holds
    /// the same numbers as the f32 fields and every path decides alike. [`Stage::new`] calls it; call it
    /// again after changing `trees` or `weights` in place.
    pub fn refresh(&mut self) {
        fn exact_f16(v: f32) -> Option<u16> {
            let h = half::f16::from_f32(v);
            (h.to_f32().to_bits() == v.to_bits()).then_some(h.to_bits())
        }
        self.leaf_offsets.clear();
        let mut acc = 0u32;
        for t in &self.trees {
            self.leaf_offsets.push(acc);
            acc = acc.saturating_add(t.n_leaves);
        }
        self.packed.clear();
        self.packed_offsets.clear();
        let packed = 'trees: {
            for t in &self.trees {
                self.packed_offsets.push(self.packed.len() as u32);
                for (i, n) in t.nodes.iter().enumerate() {
                    let Some(p) = t.projection(i) else {
                        break 'trees false;
                    };
                    let mut proj = [0u16; HOG_DIM];
                    for (h, &v) in proj.iter_mut().zip(p) {
                        let Some(b) = exact_f16(v) else { break 'trees false };
                        *h = b;
                    }
                    self.packed.push(PackedNode {
                        proj,
                        threshold: n.threshold,
                        left: n.left,
                        right: n.right,
                    });
                }
            }
            true
        };
        if !packed {
            self.packed.clear();
            self.packed_offsets.clear();
        }
        // Rows padded to HALF_ROW values, so the kernel loads whole vectors.
        self.half_weights.clear();
        for row in self.weights.chunks_exact(DELTA_DIM) {
            for &v in row {
                let Some(b) = exact_f16(v) else {
                    self.half_weights.clear();
                    return;
                };
                self.half_weights.push(b);
            }
            self.half_weights
                .resize(self.half_weights.len() + HALF_ROW - DELTA_DIM, 0);
        }
    }

    /// [`Kernels::prefetch_node`] for the vector kernels: the packed node, else the f32 projection.
    #[inline(always)]
    pub(super) fn prefetch_node_f16(&self, k: usize, node: usize) {
        match self.packed_node(k, node) {
            Some(n) => prefetch(Some(std::slice::from_ref(n))),
            None => Portable.prefetch_node(self, k, node),
        }
    }

    /// [`Kernels::prefetch_row`] for the vector kernels: the f16 row of `W`, else the f32 one.
    #[inline(always)]
    pub(super) fn prefetch_row_f16(&self, row: usize) {
        match self.half_weights.get(row * HALF_ROW..row * HALF_ROW + DELTA_DIM) {
            Some(h) => prefetch(Some(h)),
            None => Portable.prefetch_row(self, row),
        }
    }

    /// Internal node `node` of tree `k` in the packed layout, if the stage has it.
    #[inline(always)]
    pub(super) fn packed_node(&self, k: usize, node: usize) -> Option<&PackedNode> {
        let first = *self.packed_offsets.get(k)? as usize;
        let n = self.trees.get(k)?.nodes.len();
        if node >= n {
            return None;
        }
        self.packed.get(first + node)
    }

    /// Total leaves over all trees.
    pub fn n_leaves(&self) -> usize {
        self.trees.iter().map(|t| t.n_leaves as usize).sum()
    }

    /// The destination shape of this stage's normalised frame.
    pub fn dest(&self) -> &[Point2; N_POINTS] {
        &self.dest
    }

    /// Whether the vector kernels stream the f16 copies (true for any stored model).
    pub fn streams_f16(&self) -> bool {
        !self.packed.is_empty() && !self.half_weights.is_empty()
    }

    /// Global leaf indices reached by the 51 HOG rows, one per tree, into `leaves`
    /// (`trees.len()` entries).
    ///
    /// Level-synchronous: every tree advances one level per pass, so the projection loads of different
    /// trees are independent and overlap in memory (the stage's projections do not fit in cache).
    #[inline(always)]
    pub fn leaves(&self, hog: &[f32], leaves: &mut [u32]) {
        self.leaves_with(Portable, hog, leaves)
    }

    /// [`Stage::leaves`] with the given kernels.
    #[inline(always)]
    pub fn leaves_with<K: Kernels>(&self, kernels: K, hog: &[f32], leaves: &mut [u32]) {
        leaves.fill(0);
        for k in 0..self.trees.len() {
            kernels.prefetch_node(self, k, 0);
        }
        self.drain(kernels, hog, leaves);
    }

    /// Advances every unfinished tree a level at a time until all reached their leaves, then turns
    /// the per-tree leaves into global leaf indices.
    #[inline(always)]
    pub(super) fn drain<K: Kernels>(&self, kernels: K, hog: &[f32], leaves: &mut [u32]) {
        let t = self.trees_per_forest.max(1);
        loop {
            let mut active = false;
            for (k, state) in leaves.iter_mut().enumerate() {
                active |= self.step(kernels, k, hog_row(hog, k / t), state);
            }
            if !active {
                break;
            }
        }
        for (state, off) in leaves.iter_mut().zip(&self.leaf_offsets) {
            *state = off + (*state & !ROUTE_DONE);
        }
    }

    /// Moves tree `k` one node down on `row`. `state` is the current internal node, or
    /// [`ROUTE_DONE`] `|` the reached leaf. Returns whether the tree has further to go. Asks the
    /// caches for the next node, or for the leaf's `W` row, as soon as it is known.
    #[inline(always)]
    pub(super) fn step<K: Kernels>(
        &self,
        kernels: K,
        k: usize,
        row: Option<&[f32; HOG_DIM]>,
        state: &mut u32,
    ) -> bool {
        if *state & ROUTE_DONE != 0 {
            return false;
        }
        let Some(next) = row.and_then(|r| kernels.descend(self, k, *state as usize, r)) else {
            *state = ROUTE_DONE;
            return false;
        };
        if next < 0 {
            let leaf = (-(next + 1)) as u32;
            kernels.prefetch_row(
                self,
                (self.leaf_offsets.get(k).copied().unwrap_or(0) + leaf) as usize,
            );
            *state = ROUTE_DONE | leaf;
            false
        } else {
            kernels.prefetch_node(self, k, next as usize);
            *state = next as u32;
            true
        }
    }

    /// [`stage_features_with`] and [`Stage::leaves_with`] in one pass, software-pipelined: after each
    /// landmark's window and HOG, the trees of the last `ROUTE_LAG` (5) landmarks go one level down, so
    /// each next node is asked for a whole HOG computation before it is needed and the node traffic
    /// (the stage's nodes do not fit in L2) overlaps the arithmetic. The same leaves as the two calls
    /// in sequence (each tree takes the same path; only the order of the trees' steps differs).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    pub fn features_and_leaves<K: Kernels>(
        &self,
        kernels: K,
        image: &GrayView<'_>,
        shape: &[Point2; N_POINTS],
        patch: &mut [u8; PATCH_PIXELS],
        norm: &mut [Point2; N_POINTS],
        hog: &mut [f32],
        leaves: &mut [u32],
    ) -> Option<Similarity2> {
        let (t, sampler) = stage_frame(image, shape, &self.dest, norm)?;
        let tpf = self.trees_per_forest.max(1);
        leaves.fill(0);
        let roots = |l: usize| {
            for k in l * tpf..((l + 1) * tpf).min(self.trees.len()) {
                kernels.prefetch_node(self, k, 0);
            }
        };
        roots(0);
        for (l, p) in norm.iter().enumerate() {
            roots(l + 1);
            kernels.window(&sampler, *p, patch);
            if let Some(row) = hog
                .get_mut(l * HOG_DIM..(l + 1) * HOG_DIM)
                .and_then(|r| <&mut [f32; HOG_DIM]>::try_from(r).ok())
            {
                kernels.hog(patch, row);
            }
            for m in (l + 1).saturating_sub(ROUTE_LAG)..=l {
                let row = hog_row(hog, m);
                for k in m * tpf..(m + 1) * tpf {
                    if let Some(state) = leaves.get_mut(k) {
                        self.step(kernels, k, row, state);
                    }
                }
            }
        }
        self.drain(kernels, hog, leaves);
        Some(t)
    }

    /// Adds the `W` rows of `leaves` into `delta` (102 values).
    #[inline(always)]
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

/// A node laid out for the vector kernels: its projection as f16 and its test, in one 64-byte-aligned
/// block of five cache lines (one prefetch stream per node visit, no separate miss on the test).
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C, align(64))]
pub(super) struct PackedNode {
    pub(super) proj: [u16; HOG_DIM],
    pub(super) threshold: f32,
    pub(super) left: i32,
    pub(super) right: i32,
}

/// Row stride of the f16 copy of `W`: 102 values padded to 7 vectors of 16.
pub(super) const HALF_ROW: usize = 112;

/// Marks a finished tree in the routing state (the low bits hold its leaf).
pub(super) const ROUTE_DONE: u32 = 1 << 31;

/// Landmarks whose trees advance after each HOG in [`Stage::features_and_leaves`]: the trees' depth,
/// so a tree usually finishes inside the pipeline.
pub(super) const ROUTE_LAG: usize = 5;

/// Row `l` of a 51×144 HOG.
#[inline(always)]
pub(super) fn hog_row(hog: &[f32], l: usize) -> Option<&[f32; HOG_DIM]> {
    hog.get(l * HOG_DIM..(l + 1) * HOG_DIM)?.try_into().ok()
}

/// Asks for every line of `data` to be brought into L2 (a hint: it never faults and never changes a
/// result). Into L2 rather than L1: the prefetches then do not wait for L1's few fill buffers, and
/// measured faster.
#[inline(always)]
pub(super) fn prefetch<T>(data: Option<&[T]>) {
    let Some(d) = data else { return };
    let p = d.as_ptr().cast::<u8>();
    let skew = p as usize % 64;
    let first = p.wrapping_sub(skew);
    for o in (0..size_of_val(d) + skew).step_by(64) {
        prefetch_line(first.wrapping_add(o));
    }
}

/// One cache line towards L2: `prefetcht1` on x86-64, `prfm pldl2keep` on aarch64, nothing elsewhere.
#[inline(always)]
#[allow(unsafe_code)]
pub(super) fn prefetch_line(line: *const u8) {
    // SAFETY (both): a prefetch is a hint; it reads nothing, writes nothing and never faults, whatever the address.
    #[cfg(target_arch = "x86_64")]
    unsafe {
        std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T1 }>(line.cast::<i8>())
    };
    #[cfg(target_arch = "aarch64")]
    unsafe {
        std::arch::asm!("prfm pldl2keep, [{0}]", in(reg) line, options(nostack, preserves_flags, readonly))
    };
    #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
    let _ = line;
}
