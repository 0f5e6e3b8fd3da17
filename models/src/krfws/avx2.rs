//! The AVX2 (+ F16C) kernels: the AVX-512 ones on 8-lane vectors, for the many x86-64 CPUs without
//! AVX-512. The same operations in the same order as the portable code, hence the same bits (tested in
//! `tests/krfws_golden.rs` and below).
#![allow(unsafe_code)] // SAFETY (every block in this file): see each comment; the kernels run only
// behind an `Avx2` token, which exists only on a CPU with AVX2 and F16C.

use std::arch::x86_64::*;

use super::{DELTA_DIM, HALF_ROW, Kernels, PackedNode, Portable, Stage, WindowSampler};
use crate::geometry::Point2;
use crate::hog::{HOG_DIM, PATCH, PATCH_PIXELS, round_coord};

/// Proof that the CPU has AVX2 and F16C: the AVX2 kernels.
#[derive(Clone, Copy, Debug)]
pub struct Avx2(());

impl Avx2 {
    /// The token, when the CPU has AVX2 and F16C.
    pub fn detect() -> Option<Self> {
        (std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("f16c")).then_some(Self(()))
    }
}

impl Kernels for Avx2 {
    #[inline(always)]
    fn window(self, sampler: &WindowSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
        // SAFETY: the token proves AVX2.
        unsafe { window_avx2(sampler, p, out) }
    }
    #[inline(always)]
    fn hog(self, patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
        // SAFETY: the token proves AVX2.
        unsafe { crate::hog::hog_patch_avx2(patch, out) }
    }
    #[inline(always)]
    fn descend(self, stage: &Stage, k: usize, node: usize, row: &[f32; HOG_DIM]) -> Option<i32> {
        let Some(n) = stage.packed_node(k, node) else {
            return Portable.descend(stage, k, node, row);
        };
        // SAFETY: the token proves AVX2 and F16C.
        let d = unsafe { dot144_half_avx2(n, row) };
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
        // SAFETY: the token proves AVX2 and F16C.
        unsafe { accumulate_half_avx2(&stage.half_weights, leaves, delta) }
    }
}

/// `dot144` of a packed node's f16 projection: lanes 0–7 and 8–15 of the portable 16 lane sums in two
/// vectors, then the same halving tree.
///
/// # Safety
/// The CPU must support AVX2 and F16C.
#[target_feature(enable = "avx2,f16c")]
#[inline]
unsafe fn dot144_half_avx2(n: &PackedNode, b: &[f32; HOG_DIM]) -> f32 {
    let (mut lo, mut hi) = (_mm256_setzero_ps(), _mm256_setzero_ps());
    for j in 0..HOG_DIM / 16 {
        // SAFETY: 16·j + 16 ≤ 144 values of each array.
        let (x0, x1, y0, y1) = unsafe {
            let h = n.proj.as_ptr().add(16 * j);
            let y = b.as_ptr().add(16 * j);
            (
                _mm256_cvtph_ps(_mm_loadu_si128(h.cast())),
                _mm256_cvtph_ps(_mm_loadu_si128(h.add(8).cast())),
                _mm256_loadu_ps(y),
                _mm256_loadu_ps(y.add(8)),
            )
        };
        lo = _mm256_add_ps(lo, _mm256_mul_ps(x0, y0));
        hi = _mm256_add_ps(hi, _mm256_mul_ps(x1, y1));
    }
    let s8 = _mm256_add_ps(lo, hi);
    let s4 = _mm_add_ps(_mm256_castps256_ps128(s8), _mm256_extractf128_ps::<1>(s8));
    let s2 = _mm_add_ps(s4, _mm_movehl_ps(s4, s4));
    _mm_cvtss_f32(_mm_add_ss(s2, _mm_shuffle_ps::<1>(s2, s2)))
}

/// `Stage::accumulate` from the f16 copy of `W` (rows of `HALF_ROW`): the same values added in the
/// same order per output.
///
/// # Safety
/// The CPU must support AVX2 and F16C.
#[target_feature(enable = "avx2,f16c")]
#[inline]
unsafe fn accumulate_half_avx2(half: &[u16], leaves: &[u32], delta: &mut [f32; DELTA_DIM]) {
    const VECS: usize = DELTA_DIM.div_ceil(8); // 13: the last holds 6 outputs and 2 pads
    let mut acc = [_mm256_setzero_ps(); VECS];
    for &leaf in leaves {
        let s = leaf as usize * HALF_ROW;
        let Some(row) = half.get(s..s + HALF_ROW) else {
            continue;
        };
        for (j, a) in acc.iter_mut().enumerate() {
            // SAFETY: 8·j + 8 ≤ 104 ≤ 112 values of the row.
            let w = unsafe { _mm_loadu_si128(row.as_ptr().add(8 * j).cast()) };
            *a = _mm256_add_ps(*a, _mm256_cvtph_ps(w));
        }
    }
    let tail = _mm256_setr_epi32(-1, -1, -1, -1, -1, -1, 0, 0);
    for (j, a) in acc.iter().enumerate() {
        // SAFETY: whole vectors end at 96 ≤ 102; the last store writes only its 6 lanes.
        unsafe {
            if j + 1 < VECS {
                _mm256_storeu_ps(delta.as_mut_ptr().add(8 * j), *a);
            } else {
                _mm256_maskstore_ps(delta.as_mut_ptr().add(8 * j), tail, *a);
            }
        }
    }
}

/// `WindowSampler::window` with AVX2: each window row as two 8-lane halves, the four taps of each lane
/// fetched by two gathers, the same integer arithmetic, so the same bytes. Windows touching the image
/// border (and huge images) take the scalar path.
///
/// # Safety
/// The CPU must support AVX2.
#[target_feature(enable = "avx2")]
unsafe fn window_avx2(s: &WindowSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
    let (u0, v0) = (round_coord(p.x) - 8, round_coord(p.y) - 8);
    let (sa, sb) = s.step;
    let len = s.data.len();
    let small = s.w < 32_768 && s.h < 32_768 && len < (1 << 30) && len >= s.stride + 4;
    if !(small && s.inside(u0, v0, 4)) {
        return s.window(p, out);
    }
    let stride = s.stride as i32;
    let k_max = _mm256_set1_epi32((len - s.stride - 4) as i32);
    let zero = _mm256_setzero_si256();
    let byte = _mm256_set1_epi32(0xff);
    let vstride = _mm256_set1_epi32(stride);
    let base = s.data.as_ptr().cast::<i32>();
    let halves = [
        _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7),
        _mm256_setr_epi32(8, 9, 10, 11, 12, 13, 14, 15),
    ];
    let (sa32, sb32) = (_mm256_set1_epi32(sa as i32), _mm256_set1_epi32(sb as i32));
    let ox = halves.map(|i| _mm256_mullo_epi32(i, sa32));
    let oy = halves.map(|i| _mm256_mullo_epi32(i, sb32));
    for (dv, row) in out.chunks_exact_mut(PATCH).enumerate() {
        let (x0, y0) = s.at(u0, v0 + dv as i64);
        let v: [__m256i; 2] = std::array::from_fn(|h| {
            let x = _mm256_add_epi32(_mm256_set1_epi32(x0 as i32), ox[h]);
            let y = _mm256_add_epi32(_mm256_set1_epi32(y0 as i32), oy[h]);
            let (xi, yi) = (_mm256_srai_epi32::<16>(x), _mm256_srai_epi32::<16>(y));
            let fx = _mm256_and_si256(_mm256_srai_epi32::<8>(x), byte);
            let fy = _mm256_and_si256(_mm256_srai_epi32::<8>(y), byte);
            let k = _mm256_add_epi32(_mm256_mullo_epi32(yi, vstride), xi);
            let k = _mm256_min_epi32(_mm256_max_epi32(k, zero), k_max);
            // SAFETY: 0 ≤ k ≤ len − stride − 4, so the 4 bytes at k and at k + stride are in `data`.
            let (g0, g1) = unsafe {
                (
                    _mm256_i32gather_epi32::<1>(base, k),
                    _mm256_i32gather_epi32::<1>(base, _mm256_add_epi32(k, vstride)),
                )
            };
            let p00 = _mm256_and_si256(g0, byte);
            let p01 = _mm256_and_si256(_mm256_srli_epi32::<8>(g0), byte);
            let p10 = _mm256_and_si256(g1, byte);
            let p11 = _mm256_and_si256(_mm256_srli_epi32::<8>(g1), byte);
            let top = _mm256_add_epi32(
                _mm256_slli_epi32::<8>(p00),
                _mm256_mullo_epi32(_mm256_sub_epi32(p01, p00), fx),
            );
            let bot = _mm256_add_epi32(
                _mm256_slli_epi32::<8>(p10),
                _mm256_mullo_epi32(_mm256_sub_epi32(p11, p10), fx),
            );
            let v = _mm256_add_epi32(
                _mm256_slli_epi32::<8>(top),
                _mm256_mullo_epi32(_mm256_sub_epi32(bot, top), fy),
            );
            _mm256_srli_epi32::<16>(_mm256_add_epi32(v, _mm256_set1_epi32(1 << 15)))
        });
        // 16 values in 0..=255 → 16 bytes in order (packs work per 128-bit lane, hence the permutes).
        let w = _mm256_permute4x64_epi64::<0xD8>(_mm256_packus_epi32(v[0], v[1]));
        let b = _mm256_permute4x64_epi64::<0x08>(_mm256_packus_epi16(w, zero));
        // SAFETY: `row` is 16 bytes.
        unsafe { _mm_storeu_si128(row.as_mut_ptr().cast(), _mm256_castsi256_si128(b)) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::GrayView;

    #[test]
    fn avx2_windows_equal_the_scalar_ones() {
        let Some(k) = Avx2::detect() else {
            eprintln!("no AVX2 on this CPU: nothing to compare");
            return;
        };
        let (w, h) = (97usize, 61usize);
        let stride = w + 5;
        let padded: Vec<u8> = (0..stride * h)
            .map(|i| {
                if i % stride < w {
                    (i * 7919 % 251) as u8
                } else {
                    255
                }
            })
            .collect();
        let v = GrayView::new(&padded, w, h, stride).unwrap();
        let (mut a, mut b) = ([0u8; PATCH_PIXELS], [0u8; PATCH_PIXELS]);
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
                }
            }
        }
    }
}
