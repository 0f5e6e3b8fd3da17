//! What the trainers do to their training data, written once for both (KRFWS and the refiner): a random
//! similarity of a start shape about its centroid ([`perturb`]) and appearance changes of a crop ([`augment`]).

use crate::geometry::{Point2, Rect, Similarity2, centroid};
use crate::rng::Rng;

/// A random similarity's spread: σ of translation (fraction of the shape's width/height), rotation (degrees)
/// and scale (relative), and the range the scale is clamped to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Perturbation {
    /// Translation σ as a fraction of the shape's extent.
    pub translation: f64,
    /// Rotation σ in degrees.
    pub rotation_deg: f64,
    /// Scale σ.
    pub scale: f64,
    /// Smallest and largest scale drawn (the draw is clamped).
    pub scale_range: (f64, f64),
}

impl Perturbation {
    /// σ `translation`, `rotation_deg` and `scale`, the scale clamped to 0.4..=2.5 (KRFWS's trainer).
    pub const fn new(translation: f64, rotation_deg: f64, scale: f64) -> Self {
        Self {
            translation,
            rotation_deg,
            scale,
            scale_range: (0.4, 2.5),
        }
    }

    /// The same spread with the scale clamped to `min..=max`.
    #[must_use]
    pub const fn clamp_scale(self, min: f64, max: f64) -> Self {
        Self {
            scale_range: (min, max),
            ..self
        }
    }
}

/// `shape` moved by a random similarity about its centroid: translation, rotation and scale drawn (in this
/// order) from normal distributions of `p`'s σ.
pub fn perturb<const N: usize>(shape: &[Point2; N], p: Perturbation, rng: &mut Rng) -> [Point2; N] {
    let r = Rect::bounding(shape).unwrap_or_default();
    let c = centroid(shape);
    let tx = rng.normal() * p.translation * f64::from(r.width());
    let ty = rng.normal() * p.translation * f64::from(r.height());
    let ang = (rng.normal() * p.rotation_deg).to_radians();
    let s = (1.0 + rng.normal() * p.scale).clamp(p.scale_range.0, p.scale_range.1);
    let sim = Similarity2::from_parts(s, ang, 0.0, 0.0);
    std::array::from_fn(|i| {
        let q = sim.apply(Point2::new(shape[i].x - c.x, shape[i].y - c.y));
        Point2::new(q.x + c.x + tx as f32, q.y + c.y + ty as f32)
    })
}

/// In-place box blur of a square `size`² crop (`radius` 1 or 2), `passes` times.
pub fn blur(px: &mut [u8], size: usize, radius: usize, passes: usize) {
    let mut tmp = vec![0u8; px.len()];
    for _ in 0..passes {
        for horizontal in [true, false] {
            for y in 0..size {
                for x in 0..size {
                    let (mut sum, mut n) = (0u32, 0u32);
                    for k in x.saturating_sub(radius)..=(x + radius).min(size - 1) {
                        let (xx, yy) = if horizontal { (k, y) } else { (y, k) };
                        sum += u32::from(px[yy * size + xx]);
                        n += 1;
                    }
                    let (ox, oy) = if horizontal { (x, y) } else { (y, x) };
                    tmp[oy * size + ox] = ((sum + n / 2) / n) as u8;
                }
            }
            px.copy_from_slice(&tmp);
        }
    }
}

/// The appearance changes a square `size`² crop may get: brightness/contrast (30 %), a blur (25 %), an
/// occluding block, flat or noise (20 %).
pub fn augment(px: &mut [u8], size: usize, rng: &mut Rng) {
    if rng.uniform() < 0.3 {
        let gain = 0.7 + 0.6 * rng.uniform();
        let bias = (rng.uniform() - 0.5) * 50.0;
        for p in px.iter_mut() {
            *p = (f64::from(*p) * gain + bias).clamp(0.0, 255.0) as u8;
        }
    }
    if rng.uniform() < 0.25 {
        blur(px, size, 1 + rng.below(2), 1 + rng.below(2));
    }
    if rng.uniform() < 0.2 {
        let w = size * (15 + rng.below(25)) / 100;
        let h = size * (15 + rng.below(25)) / 100;
        let x0 = rng.below(size - w);
        let y0 = rng.below(size - h);
        let level = rng.below(256) as u8;
        let noisy = rng.uniform() < 0.5;
        for y in y0..y0 + h {
            for x in x0..x0 + w {
                px[y * size + x] = if noisy { rng.below(256) as u8 } else { level };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_perturbation_moves_the_shape_rigidly_within_its_scale_range() {
        let shape: [Point2; 4] = [
            Point2::new(0.0, 0.0),
            Point2::new(10.0, 0.0),
            Point2::new(10.0, 10.0),
            Point2::new(0.0, 10.0),
        ];
        let p = Perturbation::new(0.1, 10.0, 0.5).clamp_scale(0.9, 1.1);
        let mut rng = Rng::new(3);
        for _ in 0..200 {
            let q = perturb(&shape, p, &mut rng);
            let scale = f64::from(q[0].dist(q[1])) / 10.0;
            assert!((0.9 - 1e-4..=1.1 + 1e-4).contains(&scale), "{scale}");
            // A similarity keeps the square a square.
            assert!((q[0].dist(q[1]) - q[1].dist(q[2])).abs() < 1e-3);
        }
        assert_eq!(perturb(&shape, Perturbation::new(0.0, 0.0, 0.0), &mut rng), shape);
    }

    #[test]
    fn augmentation_keeps_the_crop_and_changes_some() {
        let mut rng = Rng::new(5);
        let mut changed = 0;
        for _ in 0..50 {
            let mut px: Vec<u8> = (0..32 * 32).map(|i| (i % 251) as u8).collect();
            let before = px.clone();
            augment(&mut px, 32, &mut rng);
            assert_eq!(px.len(), before.len());
            changed += usize::from(px != before);
        }
        // 1 - 0.7 x 0.75 x 0.8 = 58 % of the crops are changed.
        assert!((15..=45).contains(&changed), "{changed}");
    }
}
