//! The NEON kernels (aarch64, 4-lane vectors): what a headset's ARM CPU runs where x86-64 runs `avx2.rs` or
//! `avx512.rs`. The same operations in the same order as the portable code, hence the same bits (tested below
//! and in `tests/krfws_golden.rs`, under `qemu-aarch64` on an x86-64 machine: `make arm64-test`).
//!
//! * HOG (`crate::hog::hog_patch_neon`, beside the x86 HOG kernels): each 16-pixel window row as four vectors,
//!   the orientation planes as masked adds (the share or +0), the pooling tree of [`crate::hog::hog_patch`].
//! * Tree routing: `dot144` of a packed node's f16 projection. Stable Rust has no NEON half-precision type
//!   yet, so the f16 → f32 conversion is integer shifts and one multiply by 2¹¹²: exact for every finite half
//!   (normal, subnormal, zero), which is all a model holds (`Stage::refresh` copies only exact halves of
//!   finite values).
//! * `W` sums from the f16 copy, 26 vectors per row, each output's values added in the portable order.
//! * The window sampler: the 16.16 positions, fractions and offsets of a window row in vectors, the taps
//!   read lane by lane (NEON has no gather), the bilinear weighting in vectors; the same integers.
//!
//! NEON is part of the aarch64 baseline, so the portable code is compiled with NEON too (the compiler
//! vectorises its lane loops); these are the hand-written kernels, chosen through the [`Neon`] token exactly
//! as the x86 ones are through theirs ([`crate::isa::detected`]).
#![allow(unsafe_code)] // SAFETY (every block in this file): see each comment; the kernels run only behind a
// `Neon` token, which exists only on a CPU with NEON.

use std::arch::aarch64::*;

use super::{DELTA_DIM, HALF_ROW, Kernels, PackedNode, Portable, Stage, WindowSampler};
use crate::geometry::Point2;
use crate::hog::neon::tree8;
use crate::hog::{HOG_DIM, PATCH, PATCH_PIXELS, round_coord};

/// Proof that the CPU has NEON (Advanced SIMD): the NEON kernels.
#[derive(Clone, Copy, Debug)]
pub struct Neon(());

impl Neon {
    /// The token, when the CPU has NEON (every aarch64 CPU that runs Linux, Android or Windows does).
    pub fn detect() -> Option<Self> {
        std::arch::is_aarch64_feature_detected!("neon").then_some(Self(()))
    }
}

impl Kernels for Neon {
    #[inline(always)]
    fn window(self, sampler: &WindowSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
        // SAFETY: the token proves NEON.
        unsafe { window_neon(sampler, p, out) }
    }
    #[inline(always)]
    fn hog(self, patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
        // SAFETY: the token proves NEON.
        unsafe { crate::hog::hog_patch_neon(patch, out) }
    }
    #[inline(always)]
    fn descend(self, stage: &Stage, k: usize, node: usize, row: &[f32; HOG_DIM]) -> Option<i32> {
        let Some(n) = stage.packed_node(k, node) else {
            return Portable.descend(stage, k, node, row);
        };
        // SAFETY: the token proves NEON.
        let d = unsafe { dot144_half_neon(n, row) };
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
        // SAFETY: the token proves NEON.
        unsafe { accumulate_half_neon(&stage.half_weights, leaves, delta) }
    }
}

/// Four f16 bit patterns as f32, exactly for every finite half: the magnitude's bits moved to the f32
/// positions (`<< 13`) read as an f32 are the half's value times 2⁻¹¹², which one multiply by 2¹¹² undoes
/// without rounding (subnormal halves come out normal); the sign is put back last.
#[target_feature(enable = "neon")]
#[inline]
pub(crate) fn f16x4_to_f32(h: uint16x4_t) -> float32x4_t {
    let w = vmovl_u16(h);
    let sign = vshlq_n_u32::<16>(vandq_u32(w, vdupq_n_u32(0x8000)));
    let mag = vshlq_n_u32::<13>(vandq_u32(w, vdupq_n_u32(0x7fff)));
    let v = vmulq_f32(
        vreinterpretq_f32_u32(mag),
        vdupq_n_f32(f32::from_bits(0x7780_0000)),
    ); // 2¹¹²
    vreinterpretq_f32_u32(vorrq_u32(vreinterpretq_u32_f32(v), sign))
}

/// `dot144` of a packed node's f16 projection: the portable 16 lane sums in four vectors, then its tree.
#[target_feature(enable = "neon")]
#[inline]
fn dot144_half_neon(n: &PackedNode, b: &[f32; HOG_DIM]) -> f32 {
    let z = vdupq_n_f32(0.0);
    let mut acc = [z; 4];
    for (h, y) in n.proj.chunks_exact(16).zip(b.chunks_exact(16)) {
        for (q, a) in acc.iter_mut().enumerate() {
            // SAFETY: 4·q + 4 ≤ 16 values of each chunk.
            let (x, y) = unsafe {
                (
                    f16x4_to_f32(vld1_u16(h.as_ptr().add(4 * q))),
                    vld1q_f32(y.as_ptr().add(4 * q)),
                )
            };
            *a = vaddq_f32(*a, vmulq_f32(x, y));
        }
    }
    // s8[i] = acc[i] + acc[i + 8]: lanes 0–3 and 4–7.
    tree8(vaddq_f32(acc[0], acc[2]), vaddq_f32(acc[1], acc[3]))
}

/// `Stage::accumulate` from the f16 copy of `W` (rows of `HALF_ROW`): the same values added in the same
/// order per output.
#[target_feature(enable = "neon")]
#[inline]
fn accumulate_half_neon(half: &[u16], leaves: &[u32], delta: &mut [f32; DELTA_DIM]) {
    const VECS: usize = DELTA_DIM.div_ceil(4); // 26: the last holds 2 outputs and 2 pads
    let z = vdupq_n_f32(0.0);
    let mut acc = [z; VECS];
    for &leaf in leaves {
        let s = leaf as usize * HALF_ROW;
        let Some(row) = half.get(s..s + HALF_ROW) else {
            continue;
        };
        for (j, a) in acc.iter_mut().enumerate() {
            // SAFETY: 4·j + 4 ≤ 104 ≤ 112 values of the row.
            let w = unsafe { vld1_u16(row.as_ptr().add(4 * j)) };
            *a = vaddq_f32(*a, f16x4_to_f32(w));
        }
    }
    for (d, a) in delta.chunks_exact_mut(4).zip(&acc) {
        // SAFETY: a chunk is 4 values.
        unsafe { vst1q_f32(d.as_mut_ptr(), *a) };
    }
    let last = acc[VECS - 1];
    delta[DELTA_DIM - 2] = vgetq_lane_f32::<0>(last);
    delta[DELTA_DIM - 1] = vgetq_lane_f32::<1>(last);
}

/// `WindowSampler::window` with NEON: per window row, the 16 lanes' 16.16 positions, bilinear fractions and
/// byte offsets as four 4-lane vectors, the four taps of each lane read as two neighbouring bytes at the
/// offset and one row below, the same integer arithmetic, so the same bytes. Windows touching the image
/// border (and huge images) take the scalar path.
#[target_feature(enable = "neon")]
#[inline]
fn window_neon(s: &WindowSampler<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
    let (u0, v0) = (round_coord(p.x) - 8, round_coord(p.y) - 8);
    let (sa, sb) = s.step;
    let len = s.data.len();
    let small = s.w < 32_768 && s.h < 32_768 && len < (1 << 30) && len >= s.stride + 2;
    if !(small && s.inside(u0, v0, 2)) {
        return s.window(p, out);
    }
    let stride = s.stride as i32;
    let k_max = vdupq_n_s32((len - s.stride - 2) as i32);
    let zero = vdupq_n_s32(0);
    let byte = vdupq_n_s32(0xff);
    let (mut ox, mut oy) = ([zero; 4], [zero; 4]);
    for q in 0..4 {
        let i = 4 * q as i32;
        // SAFETY: 4 values.
        let lanes = unsafe { vld1q_s32([i, i + 1, i + 2, i + 3].as_ptr()) };
        ox[q] = vmulq_s32(lanes, vdupq_n_s32(sa as i32));
        oy[q] = vmulq_s32(lanes, vdupq_n_s32(sb as i32));
    }
    let mut offsets = [0i32; PATCH];
    let (mut top_row, mut bottom_row) = ([0u16; PATCH], [0u16; PATCH]);
    for (dv, row) in out.chunks_exact_mut(PATCH).enumerate() {
        let (x0, y0) = s.at(u0, v0 + dv as i64);
        let (x0, y0) = (vdupq_n_s32(x0 as i32), vdupq_n_s32(y0 as i32));
        let mut fx = [zero; 4];
        let mut fy = [zero; 4];
        for q in 0..4 {
            let (x, y) = (vaddq_s32(x0, ox[q]), vaddq_s32(y0, oy[q]));
            fx[q] = vandq_s32(vshrq_n_s32::<8>(x), byte);
            fy[q] = vandq_s32(vshrq_n_s32::<8>(y), byte);
            let k = vmlaq_s32(vshrq_n_s32::<16>(x), vshrq_n_s32::<16>(y), vdupq_n_s32(stride));
            let k = vminq_s32(vmaxq_s32(k, zero), k_max);
            // SAFETY: 4·q + 4 ≤ 16 values.
            unsafe { vst1q_s32(offsets.as_mut_ptr().add(4 * q), k) };
        }
        for ((&k, t), b) in offsets.iter().zip(&mut top_row).zip(&mut bottom_row) {
            // 0 ≤ k ≤ len − stride − 2: both pairs are in `data`.
            let k = k as usize;
            if let (Some(a), Some(c)) = (s.data.get(k..k + 2), s.data.get(k + s.stride..k + s.stride + 2)) {
                *t = u16::from_le_bytes([a[0], a[1]]);
                *b = u16::from_le_bytes([c[0], c[1]]);
            }
        }
        let u0 = vdupq_n_u32(0);
        let mut v = [u0; 4];
        for q in 0..4 {
            // SAFETY: 4·q + 4 ≤ 16 values.
            let (t, b) = unsafe {
                (
                    vreinterpretq_s32_u32(vmovl_u16(vld1_u16(top_row.as_ptr().add(4 * q)))),
                    vreinterpretq_s32_u32(vmovl_u16(vld1_u16(bottom_row.as_ptr().add(4 * q)))),
                )
            };
            let (p00, p01) = (vandq_s32(t, byte), vshrq_n_s32::<8>(t));
            let (p10, p11) = (vandq_s32(b, byte), vshrq_n_s32::<8>(b));
            // p00·(256 − fx) + p01·fx = 256·p00 + (p01 − p00)·fx: the same integer.
            let top = vmlaq_s32(vshlq_n_s32::<8>(p00), vsubq_s32(p01, p00), fx[q]);
            let bot = vmlaq_s32(vshlq_n_s32::<8>(p10), vsubq_s32(p11, p10), fx[q]);
            let w = vmlaq_s32(vshlq_n_s32::<8>(top), vsubq_s32(bot, top), fy[q]);
            v[q] = vshrq_n_u32::<16>(vaddq_u32(vreinterpretq_u32_s32(w), vdupq_n_u32(1 << 15)));
        }
        let lo = vcombine_u16(vmovn_u32(v[0]), vmovn_u32(v[1]));
        let hi = vcombine_u16(vmovn_u32(v[2]), vmovn_u32(v[3]));
        // SAFETY: `row` is 16 bytes.
        unsafe { vst1q_u8(row.as_mut_ptr(), vcombine_u8(vmovn_u16(lo), vmovn_u16(hi))) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::GrayView;

    #[test]
    fn every_finite_half_converts_exactly() {
        for bits in 0..=u16::MAX {
            if bits & 0x7c00 == 0x7c00 {
                continue; // inf and NaN: never in a model
            }
            // SAFETY: 4 values.
            let v = unsafe { f16x4_to_f32(vld1_u16([bits; 4].as_ptr())) };
            let want = half::f16::from_bits(bits).to_f32();
            let mut lanes = [0f32; 4];
            // SAFETY: 4 values.
            unsafe { vst1q_f32(lanes.as_mut_ptr(), v) };
            assert_eq!(lanes.map(f32::to_bits), [want.to_bits(); 4], "{bits:#06x}");
        }
    }

    #[test]
    fn neon_windows_equal_the_scalar_ones() {
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
                    // SAFETY: as above.
                    unsafe { window_neon(&sampler, p, &mut b) };
                    assert_eq!(a, b, "{p:?} {t:?}");
                }
            }
        }
    }

    #[test]
    fn the_token_exists_on_every_aarch64_linux_cpu() {
        assert!(Neon::detect().is_some());
        assert_eq!(crate::isa::detected(), crate::isa::Isa::Neon);
    }
}
