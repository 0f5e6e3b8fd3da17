//! The pinhole camera every crate shares: intrinsics in pixels, projection and back-projection.

use crate::geometry::Point2;
use crate::math3::Vec3;

/// Pinhole intrinsics in pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x.
    pub fx: f64,
    /// Focal length along y.
    pub fy: f64,
    /// Principal point x.
    pub cx: f64,
    /// Principal point y.
    pub cy: f64,
}

/// The shortest focal length a camera may have, pixels (below it a pixel spans more than 45°).
pub const MIN_FOCAL_PX: f64 = 1.0;
/// The longest focal length, pixels (a 100 000-px focal length is a 0.04° field of view on a 64-px sensor
/// row: beyond any headset or phone camera).
pub const MAX_FOCAL_PX: f64 = 1e5;
/// How far the principal point may lie from the image origin, pixels.
pub const MAX_PRINCIPAL_PX: f64 = 1e5;

/// A number as a message shows it: plainly, or in exponent form when huge or tiny (1e308, not 309 digits).
fn short(v: f64) -> String {
    if v != 0.0 && !(1e-3..1e6).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

impl Intrinsics {
    /// Checks the intrinsics against physical bounds: finite, focal lengths within
    /// [`MIN_FOCAL_PX`]..=[`MAX_FOCAL_PX`], principal point within [`MAX_PRINCIPAL_PX`] of the origin. The
    /// message says which value is out of which bound.
    pub fn check(&self) -> Result<(), String> {
        for (name, f) in [("fx", self.fx), ("fy", self.fy)] {
            if !(f.is_finite() && (MIN_FOCAL_PX..=MAX_FOCAL_PX).contains(&f)) {
                return Err(format!(
                    "focal length {name} = {} px is outside {MIN_FOCAL_PX}..={MAX_FOCAL_PX} px",
                    short(f)
                ));
            }
        }
        for (name, c) in [("cx", self.cx), ("cy", self.cy)] {
            if !(c.is_finite() && c.abs() <= MAX_PRINCIPAL_PX) {
                return Err(format!(
                    "principal point {name} = {} px is more than {MAX_PRINCIPAL_PX} px from the origin",
                    short(c)
                ));
            }
        }
        Ok(())
    }

    /// Focal lengths and principal point, in pixels.
    pub const fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Self {
        Self { fx, fy, cx, cy }
    }

    /// Projects a camera-frame point; `None` behind the camera.
    #[inline]
    pub fn project(&self, p: Vec3) -> Option<Point2> {
        if p.z <= 1e-6 {
            return None;
        }
        Some(Point2::new(
            (self.fx * p.x / p.z + self.cx) as f32,
            (self.fy * p.y / p.z + self.cy) as f32,
        ))
    }
    /// Unit ray through a pixel.
    pub fn ray(&self, p: Point2) -> Vec3 {
        let v = Vec3::new(
            (f64::from(p.x) - self.cx) / self.fx,
            (f64::from(p.y) - self.cy) / self.fy,
            1.0,
        );
        v.normalized().unwrap_or(Vec3::new(0.0, 0.0, 1.0))
    }
    pub(crate) fn valid(&self) -> bool {
        [self.fx, self.fy, self.cx, self.cy].iter().all(|v| v.is_finite()) && self.fx > 0.0 && self.fy > 0.0
    }
}
