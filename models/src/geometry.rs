//! Points and 2-D similarities.
//!
//! Conventions shared with `models/dan/geometry.py` (the training side):
//! * points are `(x, y)` pixels, 0-based, pixel centres at integer coordinates;
//! * a [`Similarity2`] `(a, b, tx, ty)` maps `(x, y)` to `(a·x − b·y + tx, b·x + a·y + ty)`.
//!
//! Transforms are named output-first: a `crop_from_image` similarity maps image pixels to crop pixels.

/// A 2-D point in pixels. Which frame it lives in is named by the variable or field that holds it.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C)]
pub struct Point2 {
    /// Horizontal coordinate, pixels, growing to the right.
    pub x: f32,
    /// Vertical coordinate, pixels, growing downwards.
    pub y: f32,
}

impl Point2 {
    /// A point from its coordinates.
    pub const fn new(x: f32, y: f32) -> Self {
        Self { x, y }
    }

    /// Euclidean distance to `other`.
    pub fn dist(self, other: Self) -> f32 {
        (self.x - other.x).hypot(self.y - other.y)
    }
}

/// A similarity transform (rotation, uniform scale, translation).
///
/// Maps `(x, y)` to `(a·x − b·y + tx, b·x + a·y + ty)`; the scale is `hypot(a, b)` and the rotation
/// `atan2(b, a)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Similarity2 {
    /// `scale · cos(angle)`.
    pub a: f64,
    /// `scale · sin(angle)`.
    pub b: f64,
    /// Translation along x.
    pub tx: f64,
    /// Translation along y.
    pub ty: f64,
}

impl Default for Similarity2 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Similarity2 {
    /// The identity map.
    pub const IDENTITY: Self = Self {
        a: 1.0,
        b: 0.0,
        tx: 0.0,
        ty: 0.0,
    };

    /// Rotation by `angle` radians about the origin, scaling by `scale`, then translating.
    pub fn from_parts(scale: f64, angle: f64, tx: f64, ty: f64) -> Self {
        Self {
            a: scale * angle.cos(),
            b: scale * angle.sin(),
            tx,
            ty,
        }
    }

    /// Least-squares similarity mapping `src` onto `dst` (DAN's `bestFit`).
    ///
    /// Returns `None` when the point sets differ in length, are empty, or `src` is degenerate (all
    /// points equal).
    pub fn fit(src: &[Point2], dst: &[Point2]) -> Option<Self> {
        if src.len() != dst.len() || src.is_empty() {
            return None;
        }
        let n = src.len() as f64;
        let (mut msx, mut msy, mut mdx, mut mdy) = (0.0, 0.0, 0.0, 0.0);
        for (s, d) in src.iter().zip(dst) {
            msx += f64::from(s.x);
            msy += f64::from(s.y);
            mdx += f64::from(d.x);
            mdy += f64::from(d.y);
        }
        msx /= n;
        msy /= n;
        mdx /= n;
        mdy /= n;
        let (mut ss, mut sd, mut cross) = (0.0, 0.0, 0.0);
        for (s, d) in src.iter().zip(dst) {
            let (sx, sy) = (f64::from(s.x) - msx, f64::from(s.y) - msy);
            let (dx, dy) = (f64::from(d.x) - mdx, f64::from(d.y) - mdy);
            ss += sx * sx + sy * sy;
            sd += sx * dx + sy * dy;
            cross += sx * dy - sy * dx;
        }
        if ss <= f64::EPSILON {
            return None;
        }
        let a = sd / ss;
        let b = cross / ss;
        Some(Self {
            a,
            b,
            tx: mdx - (a * msx - b * msy),
            ty: mdy - (b * msx + a * msy),
        })
    }

    /// Maps one point.
    #[inline]
    pub fn apply(&self, p: Point2) -> Point2 {
        let (x, y) = (f64::from(p.x), f64::from(p.y));
        Point2::new(
            (self.a * x - self.b * y + self.tx) as f32,
            (self.b * x + self.a * y + self.ty) as f32,
        )
    }

    /// Maps every point of `src` into `dst` (same length; extra entries are left untouched).
    pub fn apply_all(&self, src: &[Point2], dst: &mut [Point2]) {
        for (d, s) in dst.iter_mut().zip(src) {
            *d = self.apply(*s);
        }
    }

    /// The inverse map, or `None` when the similarity is singular (zero scale).
    pub fn inverse(&self) -> Option<Self> {
        let n = self.a * self.a + self.b * self.b;
        if n <= f64::MIN_POSITIVE || !n.is_finite() {
            return None;
        }
        let (ia, ib) = (self.a / n, -self.b / n);
        Some(Self {
            a: ia,
            b: ib,
            tx: -(ia * self.tx - ib * self.ty),
            ty: -(ib * self.tx + ia * self.ty),
        })
    }

    /// `self ∘ first`: apply `first`, then `self`.
    pub fn after(&self, first: &Self) -> Self {
        Self {
            a: self.a * first.a - self.b * first.b,
            b: self.a * first.b + self.b * first.a,
            tx: self.a * first.tx - self.b * first.ty + self.tx,
            ty: self.b * first.tx + self.a * first.ty + self.ty,
        }
    }

    /// Uniform scale factor.
    pub fn scale(&self) -> f64 {
        self.a.hypot(self.b)
    }

    /// Rotation angle in radians.
    pub fn angle(&self) -> f64 {
        self.b.atan2(self.a)
    }

    /// `[a, b, tx, ty]` as `f32`, the wire and file representation.
    pub fn to_f32_array(&self) -> [f32; 4] {
        [self.a as f32, self.b as f32, self.tx as f32, self.ty as f32]
    }

    /// From `[a, b, tx, ty]`.
    pub fn from_f32_array(v: [f32; 4]) -> Self {
        Self {
            a: f64::from(v[0]),
            b: f64::from(v[1]),
            tx: f64::from(v[2]),
            ty: f64::from(v[3]),
        }
    }
}

/// Centroid of a point set (`(0, 0)` for an empty set).
pub fn centroid(pts: &[Point2]) -> Point2 {
    if pts.is_empty() {
        return Point2::default();
    }
    let (mut x, mut y) = (0.0f64, 0.0f64);
    for p in pts {
        x += f64::from(p.x);
        y += f64::from(p.y);
    }
    let n = pts.len() as f64;
    Point2::new((x / n) as f32, (y / n) as f32)
}

/// Axis-aligned box `(x0, y0, x1, y1)` in pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Rect {
    /// Left edge.
    pub x0: f32,
    /// Top edge.
    pub y0: f32,
    /// Right edge.
    pub x1: f32,
    /// Bottom edge.
    pub y1: f32,
}

impl Rect {
    /// Width.
    pub fn width(&self) -> f32 {
        self.x1 - self.x0
    }
    /// Height.
    pub fn height(&self) -> f32 {
        self.y1 - self.y0
    }
    /// Centre point.
    pub fn centre(&self) -> Point2 {
        Point2::new(0.5 * (self.x0 + self.x1), 0.5 * (self.y0 + self.y1))
    }
    /// Bounding box of a point set (`None` when empty).
    pub fn bounding(pts: &[Point2]) -> Option<Self> {
        let first = pts.first()?;
        let mut r = Self {
            x0: first.x,
            y0: first.y,
            x1: first.x,
            y1: first.y,
        };
        for p in pts {
            r.x0 = r.x0.min(p.x);
            r.y0 = r.y0.min(p.y);
            r.x1 = r.x1.max(p.x);
            r.y1 = r.y1.max(p.y);
        }
        Some(r)
    }
    /// The box grown by `frac` of its width (left and right) and of its height (top and bottom).
    pub fn grown(&self, frac: f32) -> Self {
        let (dx, dy) = (frac * self.width(), frac * self.height());
        Self {
            x0: self.x0 - dx,
            y0: self.y0 - dy,
            x1: self.x1 + dx,
            y1: self.y1 + dy,
        }
    }
    /// Whether `p` lies in the box (edges included).
    pub fn contains(&self, p: Point2) -> bool {
        (self.x0..=self.x1).contains(&p.x) && (self.y0..=self.y1).contains(&p.y)
    }
    /// Intersection over union with `other` (0 when either is empty).
    pub fn iou(&self, other: &Self) -> f32 {
        let ix = (self.x1.min(other.x1) - self.x0.max(other.x0)).max(0.0);
        let iy = (self.y1.min(other.y1) - self.y0.max(other.y0)).max(0.0);
        let inter = ix * iy;
        let union = self.width() * self.height() + other.width() * other.height() - inter;
        if union > 0.0 { inter / union } else { 0.0 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn square() -> Vec<Point2> {
        vec![
            Point2::new(0.0, 0.0),
            Point2::new(1.0, 0.0),
            Point2::new(1.0, 1.0),
            Point2::new(0.0, 1.0),
        ]
    }

    #[test]
    fn fit_recovers_a_known_similarity() {
        let s = Similarity2::from_parts(2.5, 0.3, 10.0, -4.0);
        let src = square();
        let dst: Vec<_> = src.iter().map(|p| s.apply(*p)).collect();
        let f = Similarity2::fit(&src, &dst).unwrap();
        assert!((f.a - s.a).abs() < 1e-6 && (f.b - s.b).abs() < 1e-6);
        assert!((f.tx - s.tx).abs() < 1e-5 && (f.ty - s.ty).abs() < 1e-5);
    }

    #[test]
    fn fit_rejects_degenerate_input() {
        let p = vec![Point2::new(1.0, 1.0); 3];
        assert!(Similarity2::fit(&p, &p).is_none());
        assert!(Similarity2::fit(&[], &[]).is_none());
        assert!(Similarity2::fit(&square(), &square()[..3]).is_none());
        assert!(
            Similarity2 {
                a: 0.0,
                b: 0.0,
                tx: 1.0,
                ty: 1.0
            }
            .inverse()
            .is_none()
        );
    }

    proptest! {
        #[test]
        fn inverse_round_trips(scale in 0.05f64..20.0, angle in -3.2f64..3.2, tx in -500.0f64..500.0,
                               ty in -500.0f64..500.0, x in -300.0f32..300.0, y in -300.0f32..300.0) {
            let s = Similarity2::from_parts(scale, angle, tx, ty);
            let inv = s.inverse().unwrap();
            let p = Point2::new(x, y);
            let q = inv.apply(s.apply(p));
            prop_assert!(p.dist(q) < 1e-2, "{p:?} -> {q:?}");
            let id = inv.after(&s);
            prop_assert!((id.a - 1.0).abs() < 1e-9 && id.b.abs() < 1e-9);
        }
    }
}
