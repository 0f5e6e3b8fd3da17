//! [`super::hog_patch`] with NEON (aarch64): each 16-pixel window row as four 4-lane vectors, the same
//! operations in the same order, hence the same bits (tested below under `qemu-aarch64`, `make arm64-test`).
//! The x86 kernels, `hog_patch_avx512` and `hog_patch_avx2`, are in `hog.rs` itself.
#![allow(unsafe_code)] // SAFETY (every block in this file): loads and stores of whole arrays, see each comment;
// the kernel runs only on a CPU with NEON (the caller checks).

use std::arch::aarch64::*;

use super::{BINS, CELLS, HOG_DIM, PATCH, PATCH_PIXELS, ROUND_MAGIC, TENT};

/// The portable 8-lane tail of `dot144`, the HOG's pooling and its norm: lanes `lo` = 0–3 and `hi` = 4–7,
/// then `((p0 + p4) + (p2 + p6)) + ((p1 + p5) + (p3 + p7))`.
#[target_feature(enable = "neon")]
#[inline]
pub(crate) fn tree8(lo: float32x4_t, hi: float32x4_t) -> f32 {
    let q = vaddq_f32(lo, hi);
    let r = vaddq_f32(q, vextq_f32::<2>(q, q));
    vgetq_lane_f32::<0>(r) + vgetq_lane_f32::<1>(r)
}

/// [`super::hog_patch`] with NEON, operation for operation (each window row as four 4-lane vectors),
/// hence the same bits. The orientation planes add `share & mask` (the share or +0: adding +0 to a
/// non-negative sum changes no bit), as the AVX2 kernel does.
///
/// # Safety
/// The CPU must support NEON.
#[target_feature(enable = "neon")]
pub(crate) unsafe fn hog_patch_neon(patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
    /// Grey levels of 4 consecutive window pixels from `start` (0 ≤ start ≤ 252).
    #[target_feature(enable = "neon")]
    #[inline]
    fn load(patch: &[u8; PATCH_PIXELS], start: usize) -> float32x4_t {
        let b = patch
            .get(start..start + 4)
            .map_or([0; 4], |b| [b[0], b[1], b[2], b[3]]);
        // SAFETY: 4 values.
        let w = unsafe { vld1q_u32(b.map(u32::from).as_ptr()) };
        vcvtq_f32_u32(w)
    }
    #[target_feature(enable = "neon")]
    #[inline]
    fn ps(v: f32) -> float32x4_t {
        vdupq_n_f32(v)
    }
    let scale = ps(BINS as f32 / std::f32::consts::PI);
    let zero = ps(0.0);
    let mut cols = [[[zero; 4]; CELLS]; BINS];
    let mut tent = [[zero; 4]; CELLS];
    for (t, w) in tent.iter_mut().zip(&TENT) {
        for (q, v) in t.iter_mut().enumerate() {
            // SAFETY: TENT rows are 16 values.
            *v = unsafe { vld1q_f32(w.as_ptr().add(4 * q)) };
        }
    }
    for y in 1..PATCH - 1 {
        for q in 0..4 {
            let c = y * PATCH + 4 * q;
            let dx = vmulq_f32(ps(0.5), vsubq_f32(load(patch, c + 1), load(patch, c - 1)));
            let dy = vmulq_f32(ps(0.5), vsubq_f32(load(patch, c + PATCH), load(patch, c - PATCH)));
            let mag = vsqrtq_f32(vaddq_f32(vmulq_f32(dx, dx), vmulq_f32(dy, dy)));
            let (ax, ay) = (vabsq_f32(dx), vabsq_f32(dy));
            let (mx, mn) = (vmaxq_f32(ax, ay), vminq_f32(ax, ay));
            let t = vdivq_f32(mn, vaddq_f32(mx, ps(1e-30)));
            let t2 = vmulq_f32(t, t);
            let mut p = ps(0.020_835_1);
            p = vsubq_f32(vmulq_f32(p, t2), ps(0.085_133));
            p = vaddq_f32(vmulq_f32(p, t2), ps(0.180_141));
            p = vsubq_f32(vmulq_f32(p, t2), ps(0.330_299_5));
            p = vaddq_f32(vmulq_f32(p, t2), ps(0.999_866));
            let a = vmulq_f32(p, t);
            let steep = vcgtq_f32(ay, ax);
            let a = vbslq_f32(steep, vsubq_f32(ps(std::f32::consts::FRAC_PI_2), a), a);
            let opposite = veorq_u32(vcltq_f32(dx, zero), vcltq_f32(dy, zero));
            let a = vbslq_f32(opposite, vsubq_f32(ps(std::f32::consts::PI), a), a);
            let pos = vaddq_f32(vmulq_f32(a, scale), ps(0.5));
            let b = vsubq_f32(
                vaddq_f32(vsubq_f32(pos, ps(0.5)), ps(ROUND_MAGIC)),
                ps(ROUND_MAGIC),
            );
            let b = vminq_f32(vmaxq_f32(b, zero), ps(9.0));
            let frac = vsubq_f32(pos, b);
            let lo_share = vmulq_f32(mag, vsubq_f32(ps(1.0), frac));
            let hi_share = vmulq_f32(mag, frac);
            let mut eq = [vceqq_f32(b, zero); 10];
            for (v, e) in eq.iter_mut().enumerate().skip(1) {
                *e = vceqq_f32(b, ps(v as f32));
            }
            for (cy, w) in TENT.iter().enumerate() {
                let wy = w[y];
                if wy == 0.0 {
                    continue;
                }
                let lo_w = vreinterpretq_u32_f32(vmulq_f32(lo_share, ps(wy)));
                let hi_w = vreinterpretq_u32_f32(vmulq_f32(hi_share, ps(wy)));
                for (k, planes) in cols.iter_mut().enumerate() {
                    let lo_m = if k == 8 {
                        vorrq_u32(eq[9], eq[0])
                    } else {
                        eq[k + 1]
                    };
                    let hi_m = if k == 0 { vorrq_u32(eq[0], eq[9]) } else { eq[k] };
                    let v = vaddq_f32(planes[cy][q], vreinterpretq_f32_u32(vandq_u32(lo_m, lo_w)));
                    planes[cy][q] = vaddq_f32(v, vreinterpretq_f32_u32(vandq_u32(hi_m, hi_w)));
                }
            }
        }
    }
    // Horizontal pooling in the portable tree: p[i] = r[i]·w[i] + r[i + 8]·w[i + 8] for lanes 0–3 and 4–7.
    let mut pooled = [0.0f32; HOG_DIM];
    for (k, planes) in cols.iter().enumerate() {
        for (cy, r) in planes.iter().enumerate() {
            for (cx, w) in tent.iter().enumerate() {
                let lo = vaddq_f32(vmulq_f32(r[0], w[0]), vmulq_f32(r[2], w[2]));
                let hi = vaddq_f32(vmulq_f32(r[1], w[1]), vmulq_f32(r[3], w[3]));
                pooled[(cy * CELLS + cx) * BINS + k] = tree8(lo, hi);
            }
        }
    }
    // `v / (‖v‖ + 1e-8)` with the portable 8 lane sums of squares.
    let (mut sq_lo, mut sq_hi) = (zero, zero);
    for c in pooled.chunks_exact(8) {
        // SAFETY: chunks of 8 values.
        let (lo, hi) = unsafe { (vld1q_f32(c.as_ptr()), vld1q_f32(c.as_ptr().add(4))) };
        sq_lo = vaddq_f32(sq_lo, vmulq_f32(lo, lo));
        sq_hi = vaddq_f32(sq_hi, vmulq_f32(hi, hi));
    }
    let inv = ps(1.0 / (tree8(sq_lo, sq_hi).sqrt() + 1e-8));
    for (o, c) in out.chunks_exact_mut(4).zip(pooled.chunks_exact(4)) {
        // SAFETY: chunks of 4 values.
        unsafe { vst1q_f32(o.as_mut_ptr(), vmulq_f32(vld1q_f32(c.as_ptr()), inv)) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hog::hog_patch;

    #[test]
    fn neon_hog_equals_the_portable_one_bit_for_bit() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let (mut a, mut b) = ([0.0f32; HOG_DIM], [0.0f32; HOG_DIM]);
        for case in 0..300 {
            let mut patch = [0u8; PATCH_PIXELS];
            for (i, p) in patch.iter_mut().enumerate() {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                // Noise, flat patches, and ramps whose gradients land on bin edges.
                *p = match case % 3 {
                    0 => state as u8,
                    1 => 128,
                    _ => ((i % PATCH) * 16 + (i / PATCH) * (case % 7)) as u8,
                };
            }
            hog_patch(&patch, &mut a);
            // SAFETY: NEON is in every aarch64 Linux CPU (the token test checks it).
            unsafe { hog_patch_neon(&patch, &mut b) };
            assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "case {case}");
        }
    }
}
