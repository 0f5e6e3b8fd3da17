//! Rendering annotated stills as a moving headset would see them: the photo is a flat, life-size picture
//! (63 mm between the eye centres) with a pose in the world, the camera has a pose in the world, and each
//! frame is the exact homography of the photo, so the landmarks' true positions in every frame are known.
//!
//! Used by `holoface demo` (the bundled sample) and `holoface tracking-losses` (the validation faces).
//! A flat face is not a head: out-of-plane turns foreshorten it instead of revealing its side. That is
//! enough to exercise tracking under headset and head motion with exact ground truth.

use anyhow::Context;
use holoface_models::camera::Intrinsics;
use holoface_models::geometry::Point2;
use holoface_models::image::GrayImage;
use holoface_models::math3::{Pose, Vec3};

/// Distance between the eye centres of a life-size face, metres.
const EYE_DISTANCE_M: f64 = 0.063;

/// The synthetic headset camera of the demo, the tracking-losses scenes and the frame benchmark: 640x480,
/// 500 px focal length, principal point at (320, 240).
pub const SCENE_CAMERA: Intrinsics = Intrinsics::new(500.0, 500.0, 320.0, 240.0);

/// A 3×3 homography (row-major) mapping photo pixels to image pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Homography(pub [[f64; 3]; 3]);

impl Homography {
    /// Maps a point.
    pub fn apply(&self, p: Point2) -> Point2 {
        let h = &self.0;
        let (u, v) = (f64::from(p.x), f64::from(p.y));
        let w = h[2][0] * u + h[2][1] * v + h[2][2];
        Point2::new(
            ((h[0][0] * u + h[0][1] * v + h[0][2]) / w) as f32,
            ((h[1][0] * u + h[1][1] * v + h[1][2]) / w) as f32,
        )
    }

    /// The inverse, `None` when singular.
    pub fn inverse(&self) -> Option<Self> {
        let m = &self.0;
        let c = |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
        let cof = [
            [c(1, 2, 1, 2), -c(1, 2, 0, 2), c(1, 2, 0, 1)],
            [-c(0, 2, 1, 2), c(0, 2, 0, 2), -c(0, 2, 0, 1)],
            [c(0, 1, 1, 2), -c(0, 1, 0, 2), c(0, 1, 0, 1)],
        ];
        let det = m[0][0] * cof[0][0] + m[0][1] * cof[0][1] + m[0][2] * cof[0][2];
        (det.abs() > 1e-12).then(|| Self(std::array::from_fn(|i| std::array::from_fn(|j| cof[j][i] / det))))
    }
}

/// An annotated photo hung in the world as a flat, life-size picture.
#[derive(Clone, Debug)]
pub struct PlanarScene {
    photo: GrayImage,
    landmarks: [Point2; 68],
    /// Photo pixel that sits at the plane's origin (the landmarks' centroid).
    origin: (f64, f64),
    /// Metres per photo pixel.
    scale: f64,
}

impl PlanarScene {
    /// Scales the photo so that its face has 63 mm between the eye centres (landmarks 36–41 and 42–47)
    /// and puts the plane's origin at the landmarks' centroid.
    pub fn life_size(photo: GrayImage, landmarks: [Point2; 68]) -> anyhow::Result<Self> {
        let mean = |r: std::ops::Range<usize>| {
            let n = r.len() as f64;
            r.fold((0.0, 0.0), |(x, y), i| {
                (
                    x + f64::from(landmarks[i].x) / n,
                    y + f64::from(landmarks[i].y) / n,
                )
            })
        };
        let (l, r) = (mean(36..42), mean(42..48));
        let ipd_px = ((l.0 - r.0).powi(2) + (l.1 - r.1).powi(2)).sqrt();
        if !(ipd_px.is_finite() && ipd_px > 1.0) {
            anyhow::bail!("the landmarks' eyes are {ipd_px} px apart: not a usable face");
        }
        Ok(Self {
            photo,
            landmarks,
            origin: mean(0..68),
            scale: EYE_DISTANCE_M / ipd_px,
        })
    }

    /// The photo's landmarks (photo pixels).
    pub fn landmarks(&self) -> &[Point2; 68] {
        &self.landmarks
    }

    /// Image ← photo homography for a camera with intrinsics `k` at `world_from_camera`, the picture at
    /// `world_from_plane` (plane axes: x right, y down in the photo, z out of its back; metres).
    pub fn homography(
        &self,
        k: &Intrinsics,
        world_from_camera: &Pose,
        world_from_plane: &Pose,
    ) -> Homography {
        let cam_from_plane = world_from_camera.inverse().after(world_from_plane);
        let r = cam_from_plane.rotation;
        let m1 = r * Vec3::new(self.scale, 0.0, 0.0);
        let m2 = r * Vec3::new(0.0, self.scale, 0.0);
        let origin = Vec3::new(-self.scale * self.origin.0, -self.scale * self.origin.1, 0.0);
        let m3 = r * origin + cam_from_plane.translation;
        let kk = [[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]];
        let cols = [m1.to_array(), m2.to_array(), m3.to_array()];
        Homography(std::array::from_fn(|i| {
            std::array::from_fn(|j| (0..3).map(|l| kk[i][l] * cols[j][l]).sum())
        }))
    }

    /// The landmarks' true image positions under `h`.
    pub fn landmarks_in(&self, h: &Homography) -> [Point2; 68] {
        std::array::from_fn(|i| h.apply(self.landmarks[i]))
    }

    /// Whether image point `p` falls on the picture under `h` (in front of the camera): what a picture
    /// drawn nearer covers of the ones behind it.
    pub fn covers(&self, h: &Homography, p: Point2) -> bool {
        let Some(hi) = h.inverse() else { return false };
        let (x, y) = (f64::from(p.x), f64::from(p.y));
        let m = hi.0;
        let w = m[2][0] * x + m[2][1] * y + m[2][2];
        let u = (m[0][0] * x + m[0][1] * y + m[0][2]) / w;
        let v = (m[1][0] * x + m[1][1] * y + m[1][2]) / w;
        let (pw, ph) = (self.photo.width() as f64, self.photo.height() as f64);
        w > 0.0 && (0.0..pw - 1.0).contains(&u) && (0.0..ph - 1.0).contains(&v)
    }

    /// Renders the photo through `h` into `out` (bilinear; `background` outside the picture or behind
    /// the camera).
    pub fn render(&self, h: &Homography, out: &mut GrayImage, background: u8) -> anyhow::Result<()> {
        out.as_bytes_mut().fill(background);
        self.render_over(h, out)
    }

    /// Renders the photo through `h` over what `out` already holds: pixels outside the picture (or behind
    /// the camera) are left alone, so pictures drawn far to near occlude each other.
    pub fn render_over(&self, h: &Homography, out: &mut GrayImage) -> anyhow::Result<()> {
        let hi = h.inverse().context("degenerate camera pose")?.0;
        let (pw, ph) = (self.photo.width(), self.photo.height());
        let (fw, fh) = (out.width(), out.height());
        let src = self.photo.as_bytes();
        let dst = out.as_bytes_mut();
        for y in 0..fh {
            let yf = y as f64;
            for x in 0..fw {
                let xf = x as f64;
                let w = hi[2][0] * xf + hi[2][1] * yf + hi[2][2];
                let u = (hi[0][0] * xf + hi[0][1] * yf + hi[0][2]) / w;
                let v = (hi[1][0] * xf + hi[1][1] * yf + hi[1][2]) / w;
                if w > 0.0 && u >= 0.0 && v >= 0.0 && u < (pw - 1) as f64 && v < (ph - 1) as f64 {
                    let (iu, iv) = (u as usize, v as usize);
                    let (fu, fv) = (u - iu as f64, v - iv as f64);
                    let p = |dx: usize, dy: usize| f64::from(src[(iv + dy) * pw + iu + dx]);
                    let top = p(0, 0) * (1.0 - fu) + p(1, 0) * fu;
                    let bottom = p(0, 1) * (1.0 - fu) + p(1, 1) * fu;
                    dst[y * fw + x] = (top * (1.0 - fv) + bottom * fv).round() as u8;
                }
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use holoface_models::math3::Mat3;

    use super::*;

    fn scene() -> PlanarScene {
        let (w, h) = (200usize, 200usize);
        let photo = GrayImage::from_vec((0..w * h).map(|i| (i % 251) as u8).collect(), w, h).unwrap();
        let lm: [Point2; 68] = std::array::from_fn(|i| {
            let a = i as f32 * 0.37;
            Point2::new(100.0 + 40.0 * a.cos(), 100.0 + 40.0 * a.sin())
        });
        let mut lm = lm;
        lm[36..42].fill(Point2::new(70.0, 90.0));
        lm[42..48].fill(Point2::new(130.0, 90.0));
        PlanarScene::life_size(photo, lm).unwrap()
    }

    const K: Intrinsics = SCENE_CAMERA;

    #[test]
    fn homography_projects_plane_points_like_the_pinhole_camera() {
        let s = scene();
        let cam = Pose {
            rotation: Mat3::rot_y(0.2) * Mat3::rot_x(-0.1),
            translation: Vec3::new(0.05, -0.02, 0.01),
        };
        let plane = Pose {
            rotation: Mat3::rot_y(-0.3),
            translation: Vec3::new(0.0, 0.0, 0.6),
        };
        let h = s.homography(&K, &cam, &plane);
        for &p in &s.landmarks()[..10] {
            // The plane point in the world, then through the camera.
            let local = Vec3::new(
                (f64::from(p.x) - s.origin.0) * s.scale,
                (f64::from(p.y) - s.origin.1) * s.scale,
                0.0,
            );
            let world = plane.apply(local);
            let want = K.project(cam.inverse().apply(world)).unwrap();
            let got = h.apply(p);
            assert!(
                (got.x - want.x).abs() < 1e-3 && (got.y - want.y).abs() < 1e-3,
                "{got:?} vs {want:?}"
            );
        }
        let hi = h.inverse().unwrap();
        let q = hi.apply(h.apply(Point2::new(10.0, 20.0)));
        assert!((q.x - 10.0).abs() < 1e-3 && (q.y - 20.0).abs() < 1e-3);
    }

    #[test]
    fn a_picture_covers_its_own_pixels_and_nothing_beside_or_behind_the_camera() {
        let s = scene();
        let plane = Pose {
            rotation: Mat3::IDENTITY,
            translation: Vec3::new(0.0, 0.0, 0.6),
        };
        let h = s.homography(&K, &Pose::IDENTITY, &plane);
        let centre = h.apply(Point2::new(100.0, 100.0));
        assert!(s.covers(&h, centre));
        let corner = h.apply(Point2::new(1.0, 1.0));
        assert!(s.covers(&h, corner));
        for p in [
            h.apply(Point2::new(-5.0, 100.0)),
            h.apply(Point2::new(100.0, 205.0)),
        ] {
            assert!(!s.covers(&h, p), "{p:?} is off the picture");
        }
        // A picture behind the camera covers nothing.
        let behind = Pose {
            rotation: Mat3::IDENTITY,
            translation: Vec3::new(0.0, 0.0, -0.6),
        };
        let hb = s.homography(&K, &Pose::IDENTITY, &behind);
        assert!(!s.covers(&hb, centre));
    }

    #[test]
    fn life_size_puts_63_mm_between_the_eyes() {
        let s = scene();
        assert!((s.scale * 60.0 - 0.063).abs() < 1e-9);
        let bad = PlanarScene::life_size(GrayImage::zeros(4, 4), [Point2::default(); 68]);
        assert!(bad.is_err());
    }
}
