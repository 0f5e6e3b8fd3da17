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

impl Intrinsics {
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
