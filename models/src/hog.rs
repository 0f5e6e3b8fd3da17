//! Per-landmark HOG of HoloFace's simplified KRFWS (algorithms.md 2.2).
//!
//! One descriptor per landmark:
//! * the landmark is rounded to the nearest pixel `p` (`floor(x + 0.5)`); the window is `[p − 8, p + 8)` in
//!   x and y, 16×16 pixels = 4×4 cells of 4×4 pixels;
//! * gradients are central differences divided by 2 on the 8-bit grey levels of the window; the window's
//!   own border pixels (first and last row and column) have no central difference and are skipped, so
//!   the 14×14 interior pixels vote (window pixels outside the image read as 0);
//! * orientation is unsigned (0–180°), 9 bins of 20° centred at 10°, 30°, …, 170°; each vote is split
//!   linearly between the two nearest bin centres, wrapping at 0/180°; the vote's weight is the gradient
//!   magnitude;
//! * each vote is spread bilinearly over the 4 nearest cell centres (cell centres at window coordinates
//!   1.5, 5.5, 9.5, 13.5; a share that would fall on a cell outside the 4×4 grid is dropped);
//! * the 144 values (cell-major: `(cell_y · 4 + cell_x) · 9 + bin`) are L2-normalised once,
//!   `v / (‖v‖ + 1e-8)`.
//!
//! [`hog_patch`] is the fast path (no `atan2`: a branch-free polynomial arctangent, max error 1e-5 rad,
//! and a padded cell grid so every pixel makes exactly 8 unconditional votes). [`hog_patch_naive`] is the
//! readable specification the tests and benches compare it with.

use thiserror::Error;

#[cfg(target_arch = "aarch64")]
pub(crate) mod neon;
#[cfg(target_arch = "aarch64")]
pub(crate) use neon::hog_patch_neon;

use crate::geometry::Point2;
use crate::image::GrayView;

/// Window side in pixels.
pub const PATCH: usize = 16;
/// Pixels in one window.
pub const PATCH_PIXELS: usize = PATCH * PATCH;
/// Cells per window side.
pub const CELLS: usize = 4;
/// Cell side in pixels.
pub const CELL_PIXELS: usize = 4;
/// Orientation bins.
pub const BINS: usize = 9;
/// Descriptor length per landmark (4·4·9).
pub const HOG_DIM: usize = CELLS * CELLS * BINS;

/// Errors of the HOG entry points.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum HogError {
    /// The output buffer does not hold `points · 144` values.
    #[error("HOG output holds {actual} values, {points} points need {}", points * HOG_DIM)]
    BadOutput {
        /// Number of points.
        points: usize,
        /// Output length.
        actual: usize,
    },
}

/// Tent weight of window coordinate `u` (0..16) for cell `c` (0..4): the bilinear share of a vote at
/// `u` for the cell centred at `1.5 + 4c`; zero for the border coordinates 0 and 15, which have no
/// central difference and do not vote.
const fn tent(c: usize, u: usize) -> f32 {
    if u == 0 || u == PATCH - 1 {
        return 0.0;
    }
    let d = u as f32 - 1.5 - (CELL_PIXELS * c) as f32;
    let d = if d < 0.0 { -d } else { d };
    let w = 1.0 - d / CELL_PIXELS as f32;
    if w > 0.0 { w } else { 0.0 }
}

const fn tent_table() -> [[f32; PATCH]; CELLS] {
    let mut t = [[0.0f32; PATCH]; CELLS];
    let mut c = 0;
    while c < CELLS {
        let mut u = 0;
        while u < PATCH {
            t[c][u] = tent(c, u);
            u += 1;
        }
        c += 1;
    }
    t
}

/// Adding and subtracting 1.5·2²³ rounds an f32 of magnitude < 2²² to the nearest integer.
pub(crate) const ROUND_MAGIC: f32 = 12_582_912.0;

/// `TENT[c][u]`: share of a vote at window coordinate `u` (x or y) for cell `c`.
pub(crate) static TENT: [[f32; PATCH]; CELLS] = tent_table();

/// Unsigned gradient orientation in radians, `[0, π]`, without `atan2`.
#[inline(always)]
fn unsigned_angle(dx: f32, dy: f32) -> f32 {
    let (ax, ay) = (dx.abs(), dy.abs());
    let mx = ax.max(ay);
    let mn = ax.min(ay);
    let t = mn / (mx + 1e-30);
    let t2 = t * t;
    // atan(t) on [0, 1], minimax polynomial (Abramowitz–Stegun 4.4.49 style), |error| < 1e-5 rad.
    let p = 0.020_835_1f32;
    let p = p * t2 - 0.085_133f32;
    let p = p * t2 + 0.180_141f32;
    let p = p * t2 - 0.330_299_5f32;
    let p = p * t2 + 0.999_866f32;
    let a = p * t;
    let a = if ay > ax {
        std::f32::consts::FRAC_PI_2 - a
    } else {
        a
    };
    // atan2 mod π: the same angle when dx and dy share a sign, its supplement otherwise.
    if (dx < 0.0) != (dy < 0.0) {
        std::f32::consts::PI - a
    } else {
        a
    }
}

/// HOG of one 16×16 window (row-major grey levels) into `out` (144 values).
///
/// Portable fast path, written as fixed-width lane loops that vectorise (the specification the vector
/// kernels [`hog_patch_avx512`] and [`hog_patch_avx2`] reproduce bit for bit): per window row, the 16 gradients, magnitudes and bin positions;
/// each pixel's two bin shares become 9 orientation planes (a lane holds its share of the bin or 0),
/// which are pooled vertically into the 4 cell rows with the tent weights; at the end each cell row
/// is pooled horizontally into the 4 cells. No scattered read-modify-write (the old per-pixel vote loop
/// stalled on store-to-load forwarding when neighbours hit the same bin), no data-dependent branch.
#[inline(always)]
pub fn hog_patch(patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
    const L: usize = PATCH;
    let scale = BINS as f32 / std::f32::consts::PI;
    let mut f = [0.0f32; PATCH_PIXELS + 2];
    for (d, s) in f[1..=PATCH_PIXELS].iter_mut().zip(patch) {
        *d = f32::from(*s);
    }
    // Pass 1, all 14 interior rows (independent, so their long arctangent chains overlap): each pixel's
    // two bin shares and bins. Columns 0 and 15 get meaningless (finite) values: their tent weight is 0.
    const R: usize = PATCH - 2;
    let (mut lo_share, mut hi_share) = ([[0.0f32; L]; R], [[0.0f32; L]; R]);
    let (mut lo_bin, mut hi_bin) = ([[0.0f32; L]; R], [[0.0f32; L]; R]);
    for j in 0..R {
        // Window row j + 1 starts at f[1 + 16(j + 1)]; f[16(j + 1) + x] is its left neighbour of x.
        let row = 1 + (j + 1) * PATCH;
        let run = |start: usize| <&[f32; L]>::try_from(&f[start..start + L]);
        let (Ok(left), Ok(right), Ok(up), Ok(down)) =
            (run(row - 1), run(row + 1), run(row - PATCH), run(row + PATCH))
        else {
            continue;
        };
        for x in 0..L {
            let dx = 0.5 * (right[x] - left[x]);
            let dy = 0.5 * (down[x] - up[x]);
            let mag = (dx * dx + dy * dy).sqrt();
            // Bin coordinate + 1: θ·9/π − 0.5 + 1 ∈ [0.5, 9.5]; lower bin floor − 1 (wrapping to 8).
            let pos = unsigned_angle(dx, dy) * scale + 0.5;
            // floor(pos) by the 1.5·2²³ rounding trick on pos − 0.5 (vectorises on any x86-64, unlike
            // `floor` or a saturating cast). At an exact integer it may answer pos − 1 with frac = 1,
            // which gives the same two shares: the bin interpolation is continuous there.
            let b = (((pos - 0.5) + ROUND_MAGIC) - ROUND_MAGIC).clamp(0.0, 9.0);
            let frac = pos - b;
            lo_share[j][x] = mag * (1.0 - frac);
            hi_share[j][x] = mag * frac;
            lo_bin[j][x] = if b == 0.0 { 8.0 } else { b - 1.0 };
            hi_bin[j][x] = if b == 9.0 { 0.0 } else { b };
        }
    }
    // Pass 2, per row: 9 orientation planes pooled into the cell rows.
    // cols[bin][cell_y][x]: the votes of column x pooled over the rows, per cell row.
    let mut cols = [[[0.0f32; L]; CELLS]; BINS];
    for j in 0..R {
        let (lo_s, hi_s, lo_b, hi_b) = (&lo_share[j], &hi_share[j], &lo_bin[j], &hi_bin[j]);
        for (k, planes) in cols.iter_mut().enumerate() {
            let kf = k as f32;
            let mut plane = [0.0f32; L];
            for x in 0..L {
                // Multiplying by 0 or 1 (the shares are finite and ≥ 0): a select the compiler keeps
                // vectorised.
                plane[x] = lo_s[x] * f32::from(lo_b[x] == kf) + hi_s[x] * f32::from(hi_b[x] == kf);
            }
            for (cell_row, w) in planes.iter_mut().zip(&TENT) {
                let wy = w[j + 1];
                if wy != 0.0 {
                    for x in 0..L {
                        cell_row[x] += plane[x] * wy;
                    }
                }
            }
        }
    }
    // Horizontal pooling: out[(cy·4 + cx)·9 + k] = Σ_x cols[k][cy][x]·TENT[cx][x], in a fixed tree.
    let mut sq = [0.0f32; 8];
    for (k, planes) in cols.iter().enumerate() {
        for (cy, r) in planes.iter().enumerate() {
            for (cx, w) in TENT.iter().enumerate() {
                let mut p = [0.0f32; 8];
                for i in 0..8 {
                    p[i] = r[i] * w[i] + r[i + 8] * w[i + 8];
                }
                let v = ((p[0] + p[4]) + (p[2] + p[6])) + ((p[1] + p[5]) + (p[3] + p[7]));
                out[(cy * CELLS + cx) * BINS + k] = v;
            }
        }
    }
    for c in out.chunks_exact(8) {
        for i in 0..8 {
            sq[i] += c[i] * c[i];
        }
    }
    let ss = ((sq[0] + sq[4]) + (sq[2] + sq[6])) + ((sq[1] + sq[5]) + (sq[3] + sq[7]));
    let inv = 1.0 / (ss.sqrt() + 1e-8);
    for v in out.iter_mut() {
        *v *= inv;
    }
}

/// [`hog_patch`] with AVX-512F intrinsics, operation for operation (one 16-lane vector per window
/// row), hence the same bits. Differences that cannot change a bit: the orientation planes are
/// masked adds (the portable build adds `share·1` or `share·0`: the same sums, as one pixel's two
/// bins always differ), and the border lanes 0 and 15, whose tent weight is 0, are not replicated.
///
/// # Safety
/// The CPU must support AVX-512F.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
#[allow(unsafe_code)]
pub unsafe fn hog_patch_avx512(patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
    use std::arch::x86_64::*;
    let ps = |v: f32| _mm512_set1_ps(v);
    // Grey levels of 16 consecutive window pixels from `start` (in bounds for 0 ≤ start ≤ 240).
    let load = |start: usize| -> __m512 {
        debug_assert!(start + 16 <= PATCH_PIXELS);
        // SAFETY: start + 16 ≤ 256 at every call below.
        let b = unsafe { _mm_loadu_si128(patch.as_ptr().add(start).cast()) };
        _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(b))
    };
    let scale = ps(BINS as f32 / std::f32::consts::PI);
    let mut cols = [[_mm512_setzero_ps(); CELLS]; BINS];
    let tent: [__m512; CELLS] = std::array::from_fn(|c| {
        // SAFETY: TENT rows are 16 values.
        unsafe { _mm512_loadu_ps(TENT[c].as_ptr()) }
    });
    for y in 1..PATCH - 1 {
        let c = y * PATCH;
        let dx = _mm512_mul_ps(ps(0.5), _mm512_sub_ps(load(c + 1), load(c - 1)));
        let dy = _mm512_mul_ps(ps(0.5), _mm512_sub_ps(load(c + PATCH), load(c - PATCH)));
        let mag = _mm512_sqrt_ps(_mm512_add_ps(_mm512_mul_ps(dx, dx), _mm512_mul_ps(dy, dy)));
        // unsigned_angle, step by step.
        let (ax, ay) = (_mm512_abs_ps(dx), _mm512_abs_ps(dy));
        let (mx, mn) = (_mm512_max_ps(ax, ay), _mm512_min_ps(ax, ay));
        let t = _mm512_div_ps(mn, _mm512_add_ps(mx, ps(1e-30)));
        let t2 = _mm512_mul_ps(t, t);
        let mut p = ps(0.020_835_1);
        p = _mm512_sub_ps(_mm512_mul_ps(p, t2), ps(0.085_133));
        p = _mm512_add_ps(_mm512_mul_ps(p, t2), ps(0.180_141));
        p = _mm512_sub_ps(_mm512_mul_ps(p, t2), ps(0.330_299_5));
        p = _mm512_add_ps(_mm512_mul_ps(p, t2), ps(0.999_866));
        let a = _mm512_mul_ps(p, t);
        let steep = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(ay, ax);
        let a = _mm512_mask_sub_ps(a, steep, ps(std::f32::consts::FRAC_PI_2), a);
        let zero = _mm512_setzero_ps();
        let opposite =
            _mm512_cmp_ps_mask::<_CMP_LT_OQ>(dx, zero) ^ _mm512_cmp_ps_mask::<_CMP_LT_OQ>(dy, zero);
        let a = _mm512_mask_sub_ps(a, opposite, ps(std::f32::consts::PI), a);
        let pos = _mm512_add_ps(_mm512_mul_ps(a, scale), ps(0.5));
        let b = _mm512_sub_ps(
            _mm512_add_ps(_mm512_sub_ps(pos, ps(0.5)), ps(ROUND_MAGIC)),
            ps(ROUND_MAGIC),
        );
        let b = _mm512_min_ps(_mm512_max_ps(b, zero), ps(9.0));
        let frac = _mm512_sub_ps(pos, b);
        let lo_share = _mm512_mul_ps(mag, _mm512_sub_ps(ps(1.0), frac));
        let hi_share = _mm512_mul_ps(mag, frac);
        // Lower bin b − 1 (b = 0 → 8), upper bin b (b = 9 → 0): pixel in bin k's lower share iff
        // b = k + 1 (or k = 8 and b = 0); in its upper share iff b = k (or k = 0 and b = 9).
        let at = |v: f32| _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(b, ps(v));
        let eq: [__mmask16; 10] = std::array::from_fn(|v| at(v as f32));
        for (cy, w) in TENT.iter().enumerate() {
            let wy = w[y];
            if wy == 0.0 {
                continue;
            }
            let lo_w = _mm512_mul_ps(lo_share, ps(wy));
            let hi_w = _mm512_mul_ps(hi_share, ps(wy));
            for (k, planes) in cols.iter_mut().enumerate() {
                let lo_m = if k == 8 { eq[9] | eq[0] } else { eq[k + 1] };
                let hi_m = if k == 0 { eq[0] | eq[9] } else { eq[k] };
                let v = planes[cy];
                let v = _mm512_mask_add_ps(v, lo_m, v, lo_w);
                planes[cy] = _mm512_mask_add_ps(v, hi_m, v, hi_w);
            }
        }
    }
    // Horizontal pooling in the portable tree order, 16 outputs at a time: the 16 products of one
    // bin (4 cell rows × 4 cells) are reduced together by shuffles (lane i + lane i+8, then +4, +2, +1
    // within each product: exactly the portable tree), landing in lane 4·cx + cy.
    let mut pooled = [0.0f32; HOG_DIM];
    // Output position of lane 4·cx + cy, without the bin.
    let slot = _mm512_setr_epi32(0, 36, 72, 108, 9, 45, 81, 117, 18, 54, 90, 126, 27, 63, 99, 135);
    for (k, planes) in cols.iter().enumerate() {
        let p: [__m512; 16] = std::array::from_fn(|i| _mm512_mul_ps(planes[i / 4], tent[i % 4]));
        let s8: [__m512; 8] = std::array::from_fn(|j| {
            let (a, b) = (p[2 * j], p[2 * j + 1]);
            _mm512_add_ps(
                _mm512_shuffle_f32x4::<0x44>(a, b),
                _mm512_shuffle_f32x4::<0xEE>(a, b),
            )
        });
        let s4: [__m512; 4] = std::array::from_fn(|m| {
            let (a, b) = (s8[2 * m], s8[2 * m + 1]);
            _mm512_add_ps(
                _mm512_shuffle_f32x4::<0x88>(a, b),
                _mm512_shuffle_f32x4::<0xDD>(a, b),
            )
        });
        let s2: [__m512; 2] = std::array::from_fn(|u| {
            let (a, b) = (s4[2 * u], s4[2 * u + 1]);
            _mm512_add_ps(_mm512_shuffle_ps::<0x44>(a, b), _mm512_shuffle_ps::<0xEE>(a, b))
        });
        let (a, b) = (s2[0], s2[1]);
        let v = _mm512_add_ps(_mm512_shuffle_ps::<0x88>(a, b), _mm512_shuffle_ps::<0xDD>(a, b));
        let idx = _mm512_add_epi32(slot, _mm512_set1_epi32(k as i32));
        // SAFETY: every index is below 144 = pooled.len().
        unsafe { _mm512_i32scatter_ps::<4>(pooled.as_mut_ptr(), idx, v) };
    }
    // SAFETY: AVX-512F implies AVX2.
    unsafe { l2_normalise_avx2(&pooled, out) }
}

/// [`hog_patch_avx512`] on 8-lane vectors (each window row as two halves), for CPUs with AVX2 but not
/// AVX-512: the same operations, hence the same bits as [`hog_patch`]. The orientation planes add
/// `share & mask` (the share or +0: adding +0 to a non-negative sum changes no bit).
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(unsafe_code)]
pub unsafe fn hog_patch_avx2(patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
    use std::arch::x86_64::*;
    let ps = |v: f32| _mm256_set1_ps(v);
    // Grey levels of 8 consecutive window pixels from `start` (in bounds for 0 ≤ start ≤ 248).
    let load = |start: usize| -> __m256 {
        debug_assert!(start + 8 <= PATCH_PIXELS);
        // SAFETY: start + 8 ≤ 256 at every call below.
        let b = unsafe { _mm_loadl_epi64(patch.as_ptr().add(start).cast()) };
        _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(b))
    };
    let scale = ps(BINS as f32 / std::f32::consts::PI);
    let abs = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
    let zero = _mm256_setzero_ps();
    let mut cols = [[[zero; 2]; CELLS]; BINS];
    let tent: [[__m256; 2]; CELLS] = std::array::from_fn(|c| {
        // SAFETY: TENT rows are 16 values.
        std::array::from_fn(|h| unsafe { _mm256_loadu_ps(TENT[c].as_ptr().add(8 * h)) })
    });
    for y in 1..PATCH - 1 {
        for h in 0..2 {
            let c = y * PATCH + 8 * h;
            let dx = _mm256_mul_ps(ps(0.5), _mm256_sub_ps(load(c + 1), load(c - 1)));
            let dy = _mm256_mul_ps(ps(0.5), _mm256_sub_ps(load(c + PATCH), load(c - PATCH)));
            let mag = _mm256_sqrt_ps(_mm256_add_ps(_mm256_mul_ps(dx, dx), _mm256_mul_ps(dy, dy)));
            let (ax, ay) = (_mm256_and_ps(dx, abs), _mm256_and_ps(dy, abs));
            let (mx, mn) = (_mm256_max_ps(ax, ay), _mm256_min_ps(ax, ay));
            let t = _mm256_div_ps(mn, _mm256_add_ps(mx, ps(1e-30)));
            let t2 = _mm256_mul_ps(t, t);
            let mut p = ps(0.020_835_1);
            p = _mm256_sub_ps(_mm256_mul_ps(p, t2), ps(0.085_133));
            p = _mm256_add_ps(_mm256_mul_ps(p, t2), ps(0.180_141));
            p = _mm256_sub_ps(_mm256_mul_ps(p, t2), ps(0.330_299_5));
            p = _mm256_add_ps(_mm256_mul_ps(p, t2), ps(0.999_866));
            let a = _mm256_mul_ps(p, t);
            let steep = _mm256_cmp_ps::<_CMP_GT_OQ>(ay, ax);
            let a = _mm256_blendv_ps(a, _mm256_sub_ps(ps(std::f32::consts::FRAC_PI_2), a), steep);
            let opposite = _mm256_xor_ps(
                _mm256_cmp_ps::<_CMP_LT_OQ>(dx, zero),
                _mm256_cmp_ps::<_CMP_LT_OQ>(dy, zero),
            );
            let a = _mm256_blendv_ps(a, _mm256_sub_ps(ps(std::f32::consts::PI), a), opposite);
            let pos = _mm256_add_ps(_mm256_mul_ps(a, scale), ps(0.5));
            let b = _mm256_sub_ps(
                _mm256_add_ps(_mm256_sub_ps(pos, ps(0.5)), ps(ROUND_MAGIC)),
                ps(ROUND_MAGIC),
            );
            let b = _mm256_min_ps(_mm256_max_ps(b, zero), ps(9.0));
            let frac = _mm256_sub_ps(pos, b);
            let lo_share = _mm256_mul_ps(mag, _mm256_sub_ps(ps(1.0), frac));
            let hi_share = _mm256_mul_ps(mag, frac);
            let eq: [__m256; 10] = std::array::from_fn(|v| _mm256_cmp_ps::<_CMP_EQ_OQ>(b, ps(v as f32)));
            for (cy, w) in TENT.iter().enumerate() {
                let wy = w[y];
                if wy == 0.0 {
                    continue;
                }
                let lo_w = _mm256_mul_ps(lo_share, ps(wy));
                let hi_w = _mm256_mul_ps(hi_share, ps(wy));
                for (k, planes) in cols.iter_mut().enumerate() {
                    let lo_m = if k == 8 {
                        _mm256_or_ps(eq[9], eq[0])
                    } else {
                        eq[k + 1]
                    };
                    let hi_m = if k == 0 { _mm256_or_ps(eq[0], eq[9]) } else { eq[k] };
                    let v = _mm256_add_ps(planes[cy][h], _mm256_and_ps(lo_m, lo_w));
                    planes[cy][h] = _mm256_add_ps(v, _mm256_and_ps(hi_m, hi_w));
                }
            }
        }
    }
    // Horizontal pooling in the portable tree: lane i + lane i+8 (the two halves), then +4, +2, +1 by
    // shuffles, 8 outputs at a time; output i·9 + k of bin k for product i = 4·cy + cx.
    let mut pooled = [0.0f32; HOG_DIM];
    for (k, planes) in cols.iter().enumerate() {
        let s8: [__m256; 16] = std::array::from_fn(|i| {
            let (r, w) = (&planes[i / 4], &tent[i % 4]);
            _mm256_add_ps(_mm256_mul_ps(r[0], w[0]), _mm256_mul_ps(r[1], w[1]))
        });
        let s4: [__m256; 8] = std::array::from_fn(|j| {
            let (a, b) = (s8[2 * j], s8[2 * j + 1]);
            _mm256_add_ps(
                _mm256_permute2f128_ps::<0x20>(a, b),
                _mm256_permute2f128_ps::<0x31>(a, b),
            )
        });
        let s2: [__m256; 4] = std::array::from_fn(|m| {
            let (a, b) = (s4[2 * m], s4[2 * m + 1]);
            _mm256_add_ps(_mm256_shuffle_ps::<0x44>(a, b), _mm256_shuffle_ps::<0xEE>(a, b))
        });
        for n in 0..2 {
            let (a, b) = (s2[2 * n], s2[2 * n + 1]);
            let v = _mm256_add_ps(_mm256_shuffle_ps::<0x88>(a, b), _mm256_shuffle_ps::<0xDD>(a, b));
            let mut lanes = [0.0f32; 8];
            // SAFETY: 8 values.
            unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), v) };
            // Lane L holds product 8n + 2·(L mod 4) + L div 4.
            for (l, v) in lanes.into_iter().enumerate() {
                pooled[(8 * n + 2 * (l % 4) + l / 4) * BINS + k] = v;
            }
        }
    }
    // SAFETY: the caller guarantees AVX2.
    unsafe { l2_normalise_avx2(&pooled, out) }
}

/// The vector kernels' last step: `out = pooled / (‖pooled‖ + 1e-8)` with [`hog_patch`]'s summation
/// order for the norm (8 lane sums, then a fixed tree).
///
/// # Safety
/// The CPU must support AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[allow(unsafe_code)]
#[inline]
unsafe fn l2_normalise_avx2(pooled: &[f32; HOG_DIM], out: &mut [f32; HOG_DIM]) {
    use std::arch::x86_64::*;
    let mut acc = _mm256_setzero_ps();
    for c in pooled.chunks_exact(8) {
        // SAFETY: chunks of 8 values.
        let v = unsafe { _mm256_loadu_ps(c.as_ptr()) };
        acc = _mm256_add_ps(acc, _mm256_mul_ps(v, v));
    }
    let mut lanes = [0.0f32; 8];
    // SAFETY: 8 values.
    unsafe { _mm256_storeu_ps(lanes.as_mut_ptr(), acc) };
    let ss =
        ((lanes[0] + lanes[4]) + (lanes[2] + lanes[6])) + ((lanes[1] + lanes[5]) + (lanes[3] + lanes[7]));
    let inv = _mm256_set1_ps(1.0 / (ss.sqrt() + 1e-8));
    for (o, c) in out.chunks_exact_mut(8).zip(pooled.chunks_exact(8)) {
        // SAFETY: chunks of 8 values.
        unsafe { _mm256_storeu_ps(o.as_mut_ptr(), _mm256_mul_ps(_mm256_loadu_ps(c.as_ptr()), inv)) };
    }
}

/// The fastest HOG this CPU runs: [`hog_patch_avx512`], else [`hog_patch_avx2`] (x86-64), the NEON kernel
/// (aarch64), else the baseline build (the same bits on every path); for callers outside [`crate::krfws::Krfws::align`],
/// which dispatches once per face.
pub fn hog_patch_dispatch(patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx512f") {
        #[allow(unsafe_code)]
        // SAFETY: the CPU has AVX-512F (checked just above).
        return unsafe { hog_patch_avx512(patch, out) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("avx2") {
        #[allow(unsafe_code)]
        // SAFETY: the CPU has AVX2 (checked just above).
        return unsafe { hog_patch_avx2(patch, out) };
    }
    #[cfg(target_arch = "aarch64")]
    if std::arch::is_aarch64_feature_detected!("neon") {
        #[allow(unsafe_code)]
        // SAFETY: the CPU has NEON (checked just above).
        return unsafe { hog_patch_neon(patch, out) };
    }
    hog_patch(patch, out)
}

/// The readable specification of [`hog_patch`]: `atan2` in `f64`, explicit range checks, no tables.
/// Used by tests and the benchmark as the reference (agreement within 1e-4 per value).
pub fn hog_patch_naive(patch: &[u8; PATCH_PIXELS], out: &mut [f32; HOG_DIM]) {
    let mut hist = [0.0f64; HOG_DIM];
    let px = |x: usize, y: usize| f64::from(patch[y * PATCH + x]);
    for y in 1..PATCH - 1 {
        for x in 1..PATCH - 1 {
            let dx = (px(x + 1, y) - px(x - 1, y)) / 2.0;
            let dy = (px(x, y + 1) - px(x, y - 1)) / 2.0;
            let mag = dx.hypot(dy);
            let mut deg = dy.atan2(dx).to_degrees();
            if deg < 0.0 {
                deg += 180.0;
            }
            if deg >= 180.0 {
                deg -= 180.0;
            }
            let fb = deg / 20.0 - 0.5;
            let b0 = fb.floor();
            let fr = fb - b0;
            let lo = (b0 as i64).rem_euclid(9) as usize;
            let hi = (b0 as i64 + 1).rem_euclid(9) as usize;
            let fx = (x as f64 - 1.5) / 4.0;
            let fy = (y as f64 - 1.5) / 4.0;
            let (cx0, cy0) = (fx.floor(), fy.floor());
            let (ax, ay) = (fx - cx0, fy - cy0);
            for (cy, wy) in [(cy0 as i64, 1.0 - ay), (cy0 as i64 + 1, ay)] {
                for (cx, wx) in [(cx0 as i64, 1.0 - ax), (cx0 as i64 + 1, ax)] {
                    if (0..4).contains(&cx) && (0..4).contains(&cy) {
                        let base = (cy as usize * 4 + cx as usize) * 9;
                        hist[base + lo] += wy * wx * mag * (1.0 - fr);
                        hist[base + hi] += wy * wx * mag * fr;
                    }
                }
            }
        }
    }
    let norm = hist.iter().map(|v| v * v).sum::<f64>().sqrt() + 1e-8;
    for (o, h) in out.iter_mut().zip(hist) {
        *o = (h / norm) as f32;
    }
}

/// Copies the 16×16 window at the rounded `p` out of `image` (pixels outside the image are 0).
pub fn window_at(image: &GrayView<'_>, p: Point2, out: &mut [u8; PATCH_PIXELS]) {
    let (cx, cy) = (round_coord(p.x), round_coord(p.y));
    let (x0, y0) = (cx - 8, cy - 8);
    let (w, h) = (image.width() as i64, image.height() as i64);
    let inside = x0 >= 0 && y0 >= 0 && x0 + PATCH as i64 <= w && y0 + PATCH as i64 <= h;
    for (v, dst) in out.chunks_exact_mut(PATCH).enumerate() {
        let y = y0 + v as i64;
        let row = if y >= 0 { image.row(y as usize) } else { None };
        match row {
            Some(r) if inside => {
                let s = x0 as usize;
                dst.copy_from_slice(&r[s..s + PATCH]);
            }
            Some(r) => {
                for (u, d) in dst.iter_mut().enumerate() {
                    let x = x0 + u as i64;
                    *d = if x >= 0 && x < w { r[x as usize] } else { 0 };
                }
            }
            None => dst.fill(0),
        }
    }
}

/// `floor(v + 0.5)` as an integer, saturating for huge or non-finite input (NaN → 0).
#[inline]
pub fn round_coord(v: f32) -> i64 {
    let r = (v + 0.5).floor();
    if r.is_finite() {
        r.clamp(-1.0e9, 1.0e9) as i64
    } else {
        0
    }
}

/// HOG of the windows at `points` (rounded) in `image`, written row by row into `out`
/// (`points.len() · 144` values; row `i` belongs to `points[i]`). Allocation-free.
pub fn hog_points(image: &GrayView<'_>, points: &[Point2], out: &mut [f32]) -> Result<(), HogError> {
    if out.len() != points.len() * HOG_DIM {
        return Err(HogError::BadOutput {
            points: points.len(),
            actual: out.len(),
        });
    }
    let mut patch = [0u8; PATCH_PIXELS];
    for (p, row) in points.iter().zip(out.chunks_exact_mut(HOG_DIM)) {
        window_at(image, *p, &mut patch);
        if let Ok(dst) = <&mut [f32; HOG_DIM]>::try_from(row) {
            hog_patch_dispatch(&patch, dst);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn patch_from(f: impl Fn(usize, usize) -> u8) -> [u8; PATCH_PIXELS] {
        std::array::from_fn(|i| f(i % PATCH, i / PATCH))
    }

    fn bin_energy(h: &[f32; HOG_DIM]) -> [f32; BINS] {
        let mut e = [0.0; BINS];
        for (i, v) in h.iter().enumerate() {
            e[i % BINS] += v;
        }
        e
    }

    #[test]
    fn horizontal_ramp_votes_at_zero_degrees() {
        // Intensity grows with x: gradient angle 0°, halfway between bin 8 (170°) and bin 0 (10°).
        let p = patch_from(|x, _| (x * 10) as u8);
        let mut h = [0.0; HOG_DIM];
        hog_patch(&p, &mut h);
        let e = bin_energy(&h);
        assert!((e[0] - e[8]).abs() < 1e-4, "{e:?}");
        assert!(e[0] > 0.4 && e[1..8].iter().all(|v| v.abs() < 1e-6), "{e:?}");
    }

    #[test]
    fn vertical_ramp_votes_at_ninety_degrees() {
        // Intensity grows with y: 90° is the centre of bin 4.
        let p = patch_from(|_, y| (y * 12) as u8);
        let mut h = [0.0; HOG_DIM];
        hog_patch(&p, &mut h);
        let e = bin_energy(&h);
        let total: f32 = e.iter().sum();
        assert!(e[4] / total > 0.999, "{e:?}");
    }

    #[test]
    fn diagonal_edge_and_its_negation_share_bins() {
        // Unsigned: a dark-to-bright edge and a bright-to-dark edge give the same histogram.
        let a = patch_from(|x, y| if x + y > 15 { 200 } else { 20 });
        let b = patch_from(|x, y| if x + y > 15 { 20 } else { 200 });
        let (mut ha, mut hb) = ([0.0; HOG_DIM], [0.0; HOG_DIM]);
        hog_patch(&a, &mut ha);
        hog_patch(&b, &mut hb);
        for (x, y) in ha.iter().zip(&hb) {
            assert!((x - y).abs() < 1e-6);
        }
        // Gradient along (1, 1): 45°, a quarter of the way from bin 2 (50°) to bin 1 (30°): shares 3 : 1.
        let e = bin_energy(&ha);
        assert!((e[2] - 3.0 * e[1]).abs() < 1e-3 && e[1] > 0.3, "{e:?}");
        assert!(
            e.iter()
                .enumerate()
                .all(|(i, v)| i == 1 || i == 2 || v.abs() < 1e-6)
        );
    }

    #[test]
    fn fast_matches_naive_on_noise_and_is_unit_norm() {
        let mut s = 0x1234_5678_u32;
        for _ in 0..50 {
            let p: [u8; PATCH_PIXELS] = std::array::from_fn(|_| {
                s ^= s << 13;
                s ^= s >> 17;
                s ^= s << 5;
                (s >> 24) as u8
            });
            let (mut f, mut n) = ([0.0; HOG_DIM], [0.0; HOG_DIM]);
            hog_patch(&p, &mut f);
            hog_patch_naive(&p, &mut n);
            for (a, b) in f.iter().zip(&n) {
                assert!((a - b).abs() < 1e-4, "{a} vs {b}");
            }
            let norm: f32 = f.iter().map(|v| v * v).sum::<f32>().sqrt();
            assert!((norm - 1.0).abs() < 1e-4);
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[test]
    fn vector_kernels_give_the_portable_bits() {
        let has512 = std::is_x86_feature_detected!("avx512f");
        let has2 = std::is_x86_feature_detected!("avx2");
        if !has2 {
            eprintln!("no AVX2 on this CPU: nothing to compare");
            return;
        }
        let mut s = 0x9e37_79b9_u32;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 17;
            s ^= s << 5;
            s
        };
        for case in 0..300 {
            // Noise, smooth ramps at every angle (bin boundaries), flat and saturated patches.
            let (a, b) = ((next() % 9) as f32 - 4.0, (next() % 9) as f32 - 4.0);
            let p: [u8; PATCH_PIXELS] = std::array::from_fn(|i| match case % 4 {
                0 => (next() >> 24) as u8,
                1 => (128.0 + a * (i % PATCH) as f32 + b * (i / PATCH) as f32) as u8,
                2 => {
                    if (i % PATCH) * 3 > (i / PATCH) * 2 + 7 {
                        255
                    } else {
                        0
                    }
                }
                _ => 77,
            });
            let (mut want, mut got, mut got2) = ([0.0; HOG_DIM], [1.0; HOG_DIM], [1.0; HOG_DIM]);
            hog_patch(&p, &mut want);
            #[allow(unsafe_code)]
            // SAFETY: each kernel runs only if the CPU has its features (checked above).
            unsafe {
                if has512 {
                    hog_patch_avx512(&p, &mut got);
                    assert_eq!(
                        want.map(f32::to_bits),
                        got.map(f32::to_bits),
                        "AVX-512, case {case}"
                    );
                }
                hog_patch_avx2(&p, &mut got2);
            }
            assert_eq!(
                want.map(f32::to_bits),
                got2.map(f32::to_bits),
                "AVX2, case {case}"
            );
        }
    }

    #[test]
    fn spatial_votes_land_in_the_cell_of_the_edge() {
        // A vertical edge only in the top-left cell region.
        let p = patch_from(|x, y| if y < 4 && x >= 2 { 255 } else { 0 });
        let mut h = [0.0; HOG_DIM];
        hog_patch(&p, &mut h);
        let cell = |cx: usize, cy: usize| h[(cy * 4 + cx) * 9..(cy * 4 + cx + 1) * 9].iter().sum::<f32>();
        assert!(cell(0, 0) > cell(3, 3) + 0.1 && cell(3, 3).abs() < 1e-6);
    }

    #[test]
    fn flat_patch_is_all_zero_and_windows_clip_to_zero() {
        let p = [77u8; PATCH_PIXELS];
        let mut h = [1.0; HOG_DIM];
        hog_patch(&p, &mut h);
        assert!(h.iter().all(|v| *v == 0.0));
        let img = vec![9u8; 20 * 20];
        let v = GrayView::new(&img, 20, 20, 20).unwrap();
        let mut w = [1u8; PATCH_PIXELS];
        window_at(&v, Point2::new(0.2, 0.4), &mut w);
        assert_eq!(w[0], 0);
        assert_eq!(w[8 * PATCH + 8], 9);
        let mut out = vec![0.0; 2 * HOG_DIM];
        assert!(
            hog_points(
                &v,
                &[Point2::new(3.0, 3.0), Point2::new(f32::NAN, 1e30)],
                &mut out
            )
            .is_ok()
        );
        assert!(matches!(
            hog_points(&v, &[Point2::new(3.0, 3.0)], &mut out),
            Err(HogError::BadOutput {
                points: 1,
                actual: 288
            })
        ));
    }
}
