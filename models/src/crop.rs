//! Similarity-warped crops: the 112×112 DAN crop and the KRFWS stage windows.
//!
//! The arithmetic is `f32` in exactly the order of `models/dan/geometry.py::warp_crop`, so the Rust crop
//! and the crops DAN was trained on agree to the last grey level (the golden test bounds the difference).

use thiserror::Error;

use crate::geometry::{Point2, Rect, Similarity2};
use crate::image::GrayView;

/// Side of the DAN crop in pixels and the pixels in one: the wire's contract, defined once in the protocol.
pub use holoface_protocol::{CROP_PIXELS, CROP_SIZE};
/// [`CROP_SIZE`] as the wire's crop encoders and the protocol's `u16` fields take it.
pub const CROP_SIDE: u16 = CROP_SIZE as u16;

/// Errors of the crop functions.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum CropError {
    /// The similarity has zero or non-finite scale.
    #[error("crop transform is singular or not finite: {0:?}")]
    SingularTransform(Similarity2),
    /// `dst` does not hold `width · height` bytes.
    #[error("crop buffer holds {actual} bytes, {width}x{height} needs {}", width * height)]
    BadBuffer {
        /// Requested width.
        width: usize,
        /// Requested height.
        height: usize,
        /// Buffer length.
        actual: usize,
    },
}

/// One 112×112 grayscale crop, row-major.
#[derive(Clone, PartialEq, Eq)]
pub struct Crop112(pub Box<[u8; CROP_PIXELS]>);

impl Default for Crop112 {
    fn default() -> Self {
        Self(Box::new([0; CROP_PIXELS]))
    }
}

impl std::fmt::Debug for Crop112 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let sum: u64 = self.0.iter().map(|&p| u64::from(p)).sum();
        write!(f, "Crop112 {{ mean: {:.1} }}", sum as f64 / CROP_PIXELS as f64)
    }
}

impl Crop112 {
    /// The pixels.
    pub fn as_slice(&self) -> &[u8] {
        &self.0[..]
    }
}

/// Writes the 112×112 crop whose pixel `(u, v)` shows image point `crop_from_image⁻¹(u, v)`.
pub fn crop_bilinear(
    src: &GrayView<'_>,
    crop_from_image: &Similarity2,
    dst: &mut Crop112,
) -> Result<(), CropError> {
    warp_bilinear(src, crop_from_image, CROP_SIZE, CROP_SIZE, &mut dst.0[..])
}

/// Blanks the other faces out of one face's crop: every crop pixel whose image point lies in one of
/// `others` and not in `keep` becomes 0, the value a crop reads outside the image, which is how DAN saw
/// "nothing here" in training (crops running off the photo). With several faces close together, a
/// neighbour's face inside a crop pulls DAN's landmarks toward it (measured in docs/experiments/tracking.md,
/// "Several faces at once"); the face itself (`keep`) is never blanked, even where a neighbour's box
/// overlaps it.
pub fn blank_outside(crop: &mut Crop112, crop_from_image: &Similarity2, keep: &Rect, others: &[Rect]) {
    let Some(image_from_crop) = crop_from_image.inverse() else {
        return;
    };
    if others.is_empty() {
        return;
    }
    for v in 0..CROP_SIZE {
        for u in 0..CROP_SIZE {
            let p = image_from_crop.apply(Point2::new(u as f32, v as f32));
            if !keep.contains(p) && others.iter().any(|r| r.contains(p)) {
                crop.0[v * CROP_SIZE + u] = 0;
            }
        }
    }
}

/// Bilinear, zero-filled warp of `src` into a `width`×`height` buffer through `dst_from_src`.
///
/// Neighbours outside the source count as 0; values are rounded half up.
pub fn warp_bilinear(
    src: &GrayView<'_>,
    dst_from_src: &Similarity2,
    width: usize,
    height: usize,
    dst: &mut [u8],
) -> Result<(), CropError> {
    if dst.len() != width * height {
        return Err(CropError::BadBuffer {
            width,
            height,
            actual: dst.len(),
        });
    }
    let inv = dst_from_src
        .inverse()
        .ok_or(CropError::SingularTransform(*dst_from_src))?;
    let (a, b, tx, ty) = (inv.a as f32, inv.b as f32, inv.tx as f32, inv.ty as f32);
    if !(a.is_finite() && b.is_finite() && tx.is_finite() && ty.is_finite()) {
        return Err(CropError::SingularTransform(*dst_from_src));
    }
    let sampler = BilinearSampler::new(src, [a, b, tx, ty]);
    for (v, row) in dst.chunks_exact_mut(width).enumerate() {
        sampler.row(0, v as i64, row);
    }
    Ok(())
}

/// Bilinear sampling of a grey image through `image_from_dst = (a, b, tx, ty)`:
/// `x = a·u − b·v + tx`, `y = b·u + a·v + ty`; taps outside the image read 0; values rounded half up.
///
/// The sampling of [`warp_bilinear`] (the DAN crop, whose pixels the Python trainer reproduces). KRFWS
/// samples its windows with its own fixed-point sampler (`krfws::WindowSampler`).
#[derive(Clone, Copy, Debug)]
pub struct BilinearSampler<'a> {
    data: &'a [u8],
    stride: usize,
    w: i64,
    h: i64,
    t: [f32; 4],
}

impl<'a> BilinearSampler<'a> {
    /// A sampler of `src` through `image_from_dst` (f32 `a, b, tx, ty`).
    pub fn new(src: &GrayView<'a>, image_from_dst: [f32; 4]) -> Self {
        Self {
            data: src.data(),
            stride: src.stride(),
            w: src.width() as i64,
            h: src.height() as i64,
            t: image_from_dst,
        }
    }

    /// Destination pixels `(u0 + i, v)` for `i` in `0..out.len()`.
    #[inline(always)]
    pub fn row(&self, u0: i64, v: i64, out: &mut [u8]) {
        let [a, b, tx, ty] = self.t;
        let (w, h, stride, data) = (self.w, self.h, self.stride, self.data);
        let vf = v as f32;
        // Hoisted per-row products; the same f32 values as evaluating `a·u − b·v + tx` per pixel.
        let (bv, av) = (b * vf, a * vf);
        let (wm1, hm1) = ((w - 1).max(0) as u64, (h - 1).max(0) as u64);
        for (du, o) in out.iter_mut().enumerate() {
            let uf = (u0 + du as i64) as f32;
            let sx = a * uf - bv + tx;
            let sy = b * uf + av + ty;
            let (x0f, y0f) = (fast_floor(sx), fast_floor(sy));
            let (fx, fy) = (sx - x0f, sy - y0f);
            let (x0, y0) = (x0f as i64, y0f as i64);
            // Both taps of both rows inside: one unsigned compare per axis.
            let quad = if (x0 as u64) < wm1 && (y0 as u64) < hm1 {
                let i = y0 as usize * stride + x0 as usize;
                data.get(i..i + stride + 2).map(|q| {
                    (
                        f32::from(q[0]),
                        f32::from(q[1]),
                        f32::from(q[stride]),
                        f32::from(q[stride + 1]),
                    )
                })
            } else {
                None
            };
            let (p00, p01, p10, p11) = quad.unwrap_or_else(|| {
                (
                    self.tap(x0, y0),
                    self.tap(x0 + 1, y0),
                    self.tap(x0, y0 + 1),
                    self.tap(x0 + 1, y0 + 1),
                )
            });
            let top = p00 * (1.0 - fx) + p01 * fx;
            let bot = p10 * (1.0 - fx) + p11 * fx;
            let val = top * (1.0 - fy) + bot * fy;
            // val ∈ [0, 255]: truncation is the floor, and `as u8` saturates (NaN → 0).
            *o = (val + 0.5) as u8;
        }
    }

    /// One tap, 0 outside the image.
    #[inline]
    fn tap(&self, x: i64, y: i64) -> f32 {
        if x >= 0 && x < self.w && y >= 0 && y < self.h {
            self.data
                .get(y as usize * self.stride + x as usize)
                .map_or(0.0, |&p| f32::from(p))
        } else {
            0.0
        }
    }
}

/// `floor` without a libm call (baseline x86-64 has no rounding instruction): exact for |x| < 2³¹;
/// beyond, the taps are outside any image either way.
#[inline(always)]
fn fast_floor(x: f32) -> f32 {
    let t = (x as i32) as f32;
    if t > x { t - 1.0 } else { t }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: usize, h: usize) -> Vec<u8> {
        (0..w * h).map(|i| ((i % w) * 2 + (i / w)) as u8).collect()
    }

    #[test]
    fn identity_warp_copies_pixels() {
        let img = ramp(20, 10);
        let v = GrayView::new(&img, 20, 10, 20).unwrap();
        let mut out = vec![0; 200];
        warp_bilinear(&v, &Similarity2::IDENTITY, 20, 10, &mut out).unwrap();
        assert_eq!(out, img);
    }

    #[test]
    fn translation_by_half_pixel_averages_neighbours() {
        let img = vec![0, 100, 0, 100, 0, 100, 0, 100];
        let v = GrayView::new(&img, 4, 2, 4).unwrap();
        // dst(u, v) = src(u + 0.5, v): crop_from_image shifts by -0.5.
        let s = Similarity2 {
            a: 1.0,
            b: 0.0,
            tx: -0.5,
            ty: 0.0,
        };
        let mut out = vec![0; 4];
        warp_bilinear(&v, &s, 2, 2, &mut out).unwrap();
        assert_eq!(out, vec![50, 50, 50, 50]);
    }

    #[test]
    fn blanking_zeroes_the_other_faces_and_never_the_face_itself() {
        // Crop = image scaled by 2 (image point (x, y) is crop pixel (2x, 2y)).
        let img = vec![200u8; 100 * 100];
        let v = GrayView::new(&img, 100, 100, 100).unwrap();
        let sim = Similarity2::from_parts(2.0, 0.0, 0.0, 0.0);
        let mut crop = Crop112::default();
        crop_bilinear(&v, &sim, &mut crop).unwrap();
        let at = |c: &Crop112, x: usize, y: usize| c.0[2 * y * CROP_SIZE + 2 * x];
        let keep = Rect {
            x0: 0.0,
            y0: 0.0,
            x1: 30.0,
            y1: 55.0,
        };
        let other = Rect {
            x0: 20.0,
            y0: 0.0,
            x1: 55.0,
            y1: 55.0,
        };
        let mut none = crop.clone();
        blank_outside(&mut none, &sim, &keep, &[]);
        assert_eq!(none, crop, "nothing to blank without other faces");
        blank_outside(&mut crop, &sim, &keep, &[other]);
        assert_eq!(at(&crop, 10, 10), 200, "the face itself");
        assert_eq!(at(&crop, 25, 10), 200, "where the boxes overlap, the face wins");
        assert_eq!(at(&crop, 40, 10), 0, "the other face");
        assert_eq!(at(&crop, 10, 54), 200);
    }

    #[test]
    fn outside_is_zero_and_bad_inputs_are_errors() {
        let img = vec![200u8; 16];
        let v = GrayView::new(&img, 4, 4, 4).unwrap();
        let far = Similarity2 {
            a: 1.0,
            b: 0.0,
            tx: 100.0,
            ty: 100.0,
        };
        let mut out = vec![7; 4];
        warp_bilinear(&v, &far, 2, 2, &mut out).unwrap();
        assert_eq!(out, vec![0; 4]);
        let singular = Similarity2 {
            a: 0.0,
            b: 0.0,
            tx: 0.0,
            ty: 0.0,
        };
        assert!(matches!(
            warp_bilinear(&v, &singular, 2, 2, &mut out),
            Err(CropError::SingularTransform(_))
        ));
        assert!(matches!(
            warp_bilinear(&v, &far, 3, 2, &mut out),
            Err(CropError::BadBuffer { .. })
        ));
    }
}
