//! The AVX-512F kernels (16-lane vectors), the fastest of KRFWS's code paths: the tree projections' dot
//! products, the f16 weight accumulation, the window sampler and the token that proves the CPU has AVX-512F.
//! The same operations in the same order as the portable code, hence the same bits (tested in
//! `tests/krfws_golden.rs` and in `mod.rs`); the AVX2 ones, for CPUs without AVX-512, are `avx2.rs`.
#![allow(unsafe_code)] // SAFETY (every block in this file): see each comment; the kernels run only behind an
// `Avx512` token, which exists only on a CPU with AVX-512F.

use super::{DELTA_DIM, HALF_ROW, Kernels, Stage, WindowSampler};
use crate::geometry::Point2;
use crate::hog::{HOG_DIM, PATCH, PATCH_PIXELS, round_coord};

/// A node's projection in either storage (f16 → f32 is exact: the same products).
#[derive(Clone, Copy)]
enum Proj<'a> {
    Full(&'a [f32; HOG_DIM]),
    Half(&'a [u16; HOG_DIM]),
}

/// [`dot144`] with AVX-512F, operation for operation.
///
/// # Safety
/// The CPU must support AVX-512F.
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn dot144_avx512(a: Proj<'_>, b: &[f32; HOG_DIM]) -> f32 {
    use std::arch::x86_64::*;
    let mut acc = _mm512_setzero_ps();
    for j in 0..HOG_DIM / 16 {
        // SAFETY: 16·j + 16 ≤ 144 values of each array.
        let (x, y) = unsafe {
            (
                match a {
                    Proj::Full(p) => _mm512_loadu_ps(p.as_ptr().add(16 * j)),
                    Proj::Half(h) => _mm512_cvtph_ps(_mm256_loadu_si256(h.as_ptr().add(16 * j).cast())),
                },
                _mm512_loadu_ps(b.as_ptr().add(16 * j)),
            )
        };
        acc = _mm512_add_ps(acc, _mm512_mul_ps(x, y));
    }
    let lo = _mm512_castps512_ps256(acc);
    let hi = _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(acc)));
    let s8 = _mm256_add_ps(lo, hi);
    let s4 = _mm_add_ps(_mm256_castps256_ps128(s8), _mm256_extractf128_ps::<1>(s8));
    let s2 = _mm_add_ps(s4, _mm_movehl_ps(s4, s4));
    let s1 = _mm_add_ss(s2, _mm_shuffle_ps::<1>(s2, s2));
    _mm_cvtss_f32(s1)
}

/// [`Stage::accumulate`] from the f16 copy of `W` (rows of [`HALF_ROW`]) with AVX-512F: the same
/// values added in the same order per output, so the same bits.
///
/// # Safety
/// The CPU must support AVX-512F.
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn accumulate_half_avx512(half: &[u16], leaves: &[u32], delta: &mut [f32; DELTA_DIM]) {
    use std::arch::x86_64::*;
    const VECS: usize = HALF_ROW / 16;
    const FULL: usize = DELTA_DIM / 16; // 6 whole output vectors, then 6 values
    const TAIL: __mmask16 = (1 << (DELTA_DIM - 16 * FULL)) - 1;
    let mut acc = [_mm512_setzero_ps(); VECS];
    for &leaf in leaves {
        let s = leaf as usize * HALF_ROW;
        let Some(row) = half.get(s..s + HALF_ROW) else {
            continue;
        };
        for (j, a) in acc.iter_mut().enumerate() {
            // SAFETY: 16·j + 16 ≤ 112 values of the row.
            let w = unsafe { _mm256_loadu_si256(row.as_ptr().add(16 * j).cast()) };
            *a = _mm512_add_ps(*a, _mm512_cvtph_ps(w));
        }
    }
    for (j, a) in acc.iter().enumerate() {
        // SAFETY: whole vectors end at 96 ≤ 102; the last store writes only its 6 lanes.
        unsafe {
            if j < FULL {
                _mm512_storeu_ps(delta.as_mut_ptr().add(16 * j), *a);
            } else {
                _mm512_mask_storeu_ps(delta.as_mut_ptr().add(16 * j), TAIL, *a);
            }
        }
    }
}

impl WindowSampler<'_> {
    /// [`WindowSampler::window`] with AVX-512F: one 16-lane row at a time, the four taps of each
    /// lane fetched by two gathers (two neighbouring bytes each), the same integer arithmetic, so the
    /// same bytes. Windows that touch the image border, and images too large for 32-bit fixed point,
    /// take the scalar path.
    ///
    /// # Safety
    /// The CPU must support AVX-512F.
    #[target_feature(enable = "avx512f")]
    pub unsafe fn window_avx512(&self, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
        use std::arch::x86_64::*;
        let (u0, v0) = (round_coord(p.x) - 8, round_coord(p.y) - 8);
        let (sa, sb) = self.step;
        let len = self.data.len();
        // 16.16 positions and byte offsets fit in i32; every 4-byte read stays inside `data`.
        let small = self.w < 32_768 && self.h < 32_768 && len < (1 << 30) && len >= self.stride + 4;
        if !(small && self.inside(u0, v0, 4)) {
            return self.window(p, out);
        }
        let stride = self.stride as i32;
        // Offsets are clamped to the readable range: a no-op given `inside`, and what makes the
        // gathers memory-safe whatever the arithmetic above concluded.
        let k_max = _mm512_set1_epi32((len - self.stride - 4) as i32);
        let zero = _mm512_setzero_si512();
        let iota = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        // |15·step| < image size < 2¹⁵ pixels, so the lane offsets fit in i32.
        let ox = _mm512_mullo_epi32(iota, _mm512_set1_epi32(sa as i32));
        let oy = _mm512_mullo_epi32(iota, _mm512_set1_epi32(sb as i32));
        let byte = _mm512_set1_epi32(0xff);
        let vstride = _mm512_set1_epi32(stride);
        let base = self.data.as_ptr().cast::<i32>();
        for (dv, row) in out.chunks_exact_mut(PATCH).enumerate() {
            let (x0, y0) = self.at(u0, v0 + dv as i64);
            let x = _mm512_add_epi32(_mm512_set1_epi32(x0 as i32), ox);
            let y = _mm512_add_epi32(_mm512_set1_epi32(y0 as i32), oy);
            let (xi, yi) = (_mm512_srai_epi32::<16>(x), _mm512_srai_epi32::<16>(y));
            let fx = _mm512_and_si512(_mm512_srai_epi32::<8>(x), byte);
            let fy = _mm512_and_si512(_mm512_srai_epi32::<8>(y), byte);
            let k = _mm512_add_epi32(_mm512_mullo_epi32(yi, vstride), xi);
            let k = _mm512_min_epi32(_mm512_max_epi32(k, zero), k_max);
            // SAFETY: 0 ≤ k ≤ len − stride − 4, so the 4 bytes at k and at k + stride are in `data`.
            let (g0, g1) = unsafe {
                (
                    _mm512_i32gather_epi32::<1>(k, base),
                    _mm512_i32gather_epi32::<1>(_mm512_add_epi32(k, vstride), base),
                )
            };
            let p00 = _mm512_and_si512(g0, byte);
            let p01 = _mm512_and_si512(_mm512_srli_epi32::<8>(g0), byte);
            let p10 = _mm512_and_si512(g1, byte);
            let p11 = _mm512_and_si512(_mm512_srli_epi32::<8>(g1), byte);
            // p00·(256 − fx) + p01·fx = 256·p00 + (p01 − p00)·fx: the same integer, no overflow.
            let top = _mm512_add_epi32(
                _mm512_slli_epi32::<8>(p00),
                _mm512_mullo_epi32(_mm512_sub_epi32(p01, p00), fx),
            );
            let bot = _mm512_add_epi32(
                _mm512_slli_epi32::<8>(p10),
                _mm512_mullo_epi32(_mm512_sub_epi32(p11, p10), fx),
            );
            let v = _mm512_add_epi32(
                _mm512_slli_epi32::<8>(top),
                _mm512_mullo_epi32(_mm512_sub_epi32(bot, top), fy),
            );
            let v = _mm512_srli_epi32::<16>(_mm512_add_epi32(v, _mm512_set1_epi32(1 << 15)));
            let bytes = _mm512_cvtepi32_epi8(v);
            // SAFETY: `row` is 16 bytes.
            unsafe { _mm_storeu_si128(row.as_mut_ptr().cast(), bytes) };
        }
    }
}

/// Proof that the CPU has AVX-512F: the AVX-512 kernels (and the f16 copies of the model).
#[derive(Clone, Copy, Debug)]
pub struct Avx512(());

impl Avx512 {
    /// The token, when the CPU has AVX-512F.
    pub fn detect() -> Option<Self> {
        std::is_x86_feature_detected!("avx512f").then_some(Self(()))
    }
}

// SAFETY (every block below): an `Avx512` token exists only on a CPU with AVX-512F.
impl Kernels for Avx512 {
    #[inline(always)]
    fn window(self, sampler: &WindowSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
        unsafe { sampler.window_avx512(p, out) }
    }
    #[inline(always)]
    fn hog(self, patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
        unsafe { crate::hog::hog_patch_avx512(patch, out) }
    }
    #[inline(always)]
    fn descend(self, stage: &Stage, k: usize, node: usize, row: &[f32; HOG_DIM]) -> Option<i32> {
        if let Some(n) = stage.packed_node(k, node) {
            let d = unsafe { dot144_avx512(Proj::Half(&n.proj), row) };
            return Some(if d <= n.threshold { n.left } else { n.right });
        }
        let tree = stage.trees.get(k)?;
        let n = tree.nodes.get(node)?;
        let d = unsafe { dot144_avx512(Proj::Full(tree.projection(node)?), row) };
        Some(if d <= n.threshold { n.left } else { n.right })
    }
    #[inline(always)]
    fn prefetch_node(self, stage: &Stage, k: usize, node: usize) {
        stage.prefetch_node_f16(k, node)
    }
    #[inline(always)]
    fn prefetch_row(self, stage: &Stage, row: usize) {
        stage.prefetch_row_f16(row)
    }
    #[inline(always)]
    fn accumulate(self, stage: &Stage, leaves: &[u32], delta: &mut [f32; DELTA_DIM]) {
        if stage.half_weights.is_empty() {
            return stage.accumulate(leaves, delta);
        }
        unsafe { accumulate_half_avx512(&stage.half_weights, leaves, delta) }
    }
}
