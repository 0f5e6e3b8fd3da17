//! A small z-buffered triangle rasteriser: what draws the anchored objects into a camera frame.
//!
//! Perspective projection with the camera's own intrinsics (the same pinhole as [`Intrinsics::project`]),
//! depth as 1/z interpolated linearly in screen space (exact for planar triangles), per-vertex Lambert and
//! Blinn-Phong shading under a light fixed to the camera, interpolated perspective-correctly, two-sided.
//! Occluders write depth only (the fitted head hides what is behind it); see-through parts are drawn last,
//! depth-tested but not depth-written, blended over what is behind them. Triangles with a vertex nearer than
//! [`NEAR_M`] are left out rather than clipped: anchored objects are half a metre to metres away.
//! Everything is in f64 and deterministic: the golden-image test compares pixels.

use holoface_models::camera::Intrinsics;
use holoface_models::math3::{Pose, Vec3};

/// Nearest depth drawn, metres.
pub const NEAR_M: f64 = 0.05;

/// Light fixed to the camera: from above, left and in front (camera frame, pointing to the light).
const LIGHT: Vec3 = Vec3::new(-0.38, -0.62, -0.69);
/// Share of the colour lit without the light.
const AMBIENT: f64 = 0.38;
/// Blinn-Phong exponent of the highlights.
const SHININESS_EXP: i32 = 24;

/// Triangles with per-vertex normals, in the frame they were made or moved into.
#[derive(Clone, Debug, Default)]
pub struct Mesh {
    /// Vertex positions, metres.
    pub positions: Vec<Vec3>,
    /// Unit normals, one per vertex.
    pub normals: Vec<Vec3>,
    /// Vertex indices, three per triangle.
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// Adds `other`, moved by `pose`.
    pub fn append(&mut self, other: &Self, pose: &Pose) {
        let base = self.positions.len() as u32;
        self.positions
            .extend(other.positions.iter().map(|&p| pose.apply(p)));
        self.normals
            .extend(other.normals.iter().map(|&n| pose.rotation * n));
        self.triangles
            .extend(other.triangles.iter().map(|t| t.map(|v| v + base)));
    }

    /// A copy moved by `pose`.
    pub fn moved(&self, pose: &Pose) -> Self {
        let mut m = Self::default();
        m.append(self, pose);
        m
    }

    /// A copy scaled by `s` about the frame's origin (normals unchanged).
    pub fn scaled(&self, s: f64) -> Self {
        Self {
            positions: self.positions.iter().map(|p| p.scale(s)).collect(),
            ..self.clone()
        }
    }
}

/// How a part looks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    /// Base colour, 0-1 per channel.
    pub colour: [f64; 3],
    /// 1 opaque, less for see-through parts (lenses).
    pub opacity: f64,
    /// Strength of the highlights, 0-1.
    pub gloss: f64,
}

impl Material {
    /// An opaque material of an 8-bit colour.
    pub fn opaque(rgb: [u8; 3], gloss: f64) -> Self {
        Self {
            colour: rgb.map(|c| f64::from(c) / 255.0),
            opacity: 1.0,
            gloss,
        }
    }
}

/// A camera frame being drawn into: its RGB pixels and a depth buffer (1/z, 0 where nothing was drawn).
#[derive(Debug)]
pub struct Target<'a> {
    rgb: &'a mut [u8],
    w: usize,
    h: usize,
    inv_depth: Vec<f64>,
    k: Intrinsics,
}

/// A vertex on screen: pixel position, 1/z, and its shaded colour.
#[derive(Clone, Copy)]
struct Screen {
    x: f64,
    y: f64,
    iz: f64,
    colour: [f64; 3],
}

impl<'a> Target<'a> {
    /// A target over `rgb` (`w` x `h` RGB triples) seen through `k`, with an empty depth buffer.
    pub fn new(rgb: &'a mut [u8], w: usize, h: usize, k: Intrinsics) -> Self {
        assert_eq!(rgb.len(), w * h * 3, "the pixels are not w x h RGB triples");
        Self {
            rgb,
            w,
            h,
            inv_depth: vec![0.0; w * h],
            k,
        }
    }

    /// Writes the depth of `mesh` (camera frame) and no colour: what it hides stays hidden.
    pub fn occlude(&mut self, mesh: &Mesh) {
        self.draw_mesh(mesh, None);
    }

    /// Draws `mesh` (camera frame) in `m`: opaque parts write depth, see-through parts blend without it.
    pub fn draw(&mut self, mesh: &Mesh, m: &Material) {
        self.draw_mesh(mesh, Some(m));
    }

    /// A disc of radius `radius_m` facing the camera at `centre` (camera frame), depth-tested against what
    /// was drawn, in `colour` at `opacity`: a particle.
    pub fn splat(&mut self, centre: Vec3, radius_m: f64, colour: [f64; 3], opacity: f64) {
        if !(centre.z >= NEAR_M && radius_m > 0.0 && centre.x.is_finite() && centre.y.is_finite()) {
            return;
        }
        let Some(c) = self.k.project(centre) else {
            return;
        };
        let (cx, cy) = (f64::from(c.x), f64::from(c.y));
        let r = (self.k.fx * radius_m / centre.z).min(self.w.max(self.h) as f64);
        let iz = 1.0 / centre.z;
        let (x0, x1) = (clamp_px(cx - r, self.w), clamp_px(cx + r, self.w));
        let (y0, y1) = (clamp_px(cy - r, self.h), clamp_px(cy + r, self.h));
        for y in y0..=y1 {
            for x in x0..=x1 {
                let d2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
                let i = y * self.w + x;
                if d2 <= r * r && iz > self.inv_depth[i] {
                    // Brighter in the middle: a soft round sprite.
                    let lit = 1.0 - 0.45 * (d2 / (r * r).max(1e-9));
                    self.blend(i, colour.map(|c| c * lit), opacity);
                }
            }
        }
    }

    fn draw_mesh(&mut self, mesh: &Mesh, m: Option<&Material>) {
        let light = LIGHT.normalized().unwrap_or(Vec3::new(0.0, 0.0, -1.0));
        let verts: Vec<Option<Screen>> = mesh
            .positions
            .iter()
            .zip(&mesh.normals)
            .map(|(&p, &n)| {
                if !(p.z >= NEAR_M && p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
                    return None;
                }
                let q = self.k.project(p)?;
                let colour = m.map_or([0.0; 3], |m| shade(p, n, light, m));
                Some(Screen {
                    x: f64::from(q.x),
                    y: f64::from(q.y),
                    iz: 1.0 / p.z,
                    colour,
                })
            })
            .collect();
        for t in &mesh.triangles {
            let get = |v: u32| verts.get(v as usize).copied().flatten();
            if let (Some(a), Some(b), Some(c)) = (get(t[0]), get(t[1]), get(t[2])) {
                self.triangle([a, b, c], m);
            }
        }
    }

    fn triangle(&mut self, v: [Screen; 3], m: Option<&Material>) {
        let edge = |a: &Screen, b: &Screen, x: f64, y: f64| (b.x - a.x) * (y - a.y) - (b.y - a.y) * (x - a.x);
        // One winding for all, so that an edge two triangles share runs one way in one and the other way in
        // the other.
        let v = if edge(&v[0], &v[1], v[2].x, v[2].y) < 0.0 {
            [v[0], v[2], v[1]]
        } else {
            v
        };
        let area = edge(&v[0], &v[1], v[2].x, v[2].y);
        if !area.is_finite() || area < 1e-9 {
            return;
        }
        // A pixel centre on an edge belongs to one triangle only (else a see-through part would be blended
        // twice there): to the one whose edge points down, or left when level.
        let owns = |a: &Screen, b: &Screen| b.y > a.y || (b.y == a.y && b.x < a.x);
        let own = [owns(&v[1], &v[2]), owns(&v[2], &v[0]), owns(&v[0], &v[1])];
        let min = |f: fn(&Screen) -> f64| v.iter().map(f).fold(f64::INFINITY, f64::min);
        let max = |f: fn(&Screen) -> f64| v.iter().map(f).fold(f64::NEG_INFINITY, f64::max);
        let (x0, x1) = (min(|s| s.x), max(|s| s.x));
        let (y0, y1) = (min(|s| s.y), max(|s| s.y));
        if x1 < 0.0 || y1 < 0.0 || x0 > (self.w - 1) as f64 || y0 > (self.h - 1) as f64 {
            return;
        }
        let (x0, x1) = (clamp_px(x0, self.w), clamp_px(x1, self.w));
        let (y0, y1) = (clamp_px(y0, self.h), clamp_px(y1, self.h));
        for y in y0..=y1 {
            let fy = y as f64;
            for x in x0..=x1 {
                let fx = x as f64;
                let l = [
                    edge(&v[1], &v[2], fx, fy) / area,
                    edge(&v[2], &v[0], fx, fy) / area,
                    edge(&v[0], &v[1], fx, fy) / area,
                ];
                if l.iter().zip(own).any(|(&w, own)| w < 0.0 || (w == 0.0 && !own)) {
                    continue;
                }
                let iz = l[0] * v[0].iz + l[1] * v[1].iz + l[2] * v[2].iz;
                let i = y * self.w + x;
                if iz <= self.inv_depth[i] {
                    continue;
                }
                let Some(m) = m else {
                    self.inv_depth[i] = iz;
                    continue;
                };
                // Perspective-correct weights of the vertex colours.
                let q = [0, 1, 2].map(|k| l[k] * v[k].iz / iz);
                let colour =
                    [0, 1, 2].map(|c| q[0] * v[0].colour[c] + q[1] * v[1].colour[c] + q[2] * v[2].colour[c]);
                if m.opacity >= 1.0 {
                    self.inv_depth[i] = iz;
                }
                self.blend(i, colour, m.opacity);
            }
        }
    }

    /// Blends `colour` (0-1) over pixel `i` at `opacity`.
    fn blend(&mut self, i: usize, colour: [f64; 3], opacity: f64) {
        let a = opacity.clamp(0.0, 1.0);
        for (c, &v) in colour.iter().enumerate() {
            let old = f64::from(self.rgb[i * 3 + c]);
            let new = (v.clamp(0.0, 1.0) * 255.0 * a + old * (1.0 - a)).round();
            self.rgb[i * 3 + c] = new as u8;
        }
    }
}

/// A pixel coordinate clamped into `0..n`.
fn clamp_px(v: f64, n: usize) -> usize {
    if v.is_nan() || v <= 0.0 {
        0
    } else {
        (v.ceil() as usize).min(n - 1)
    }
}

/// Lit colour of a vertex at `p` with normal `n` (camera frame), two-sided.
fn shade(p: Vec3, n: Vec3, light: Vec3, m: &Material) -> [f64; 3] {
    let view = (-p).normalized().unwrap_or(Vec3::new(0.0, 0.0, -1.0));
    let n = n.normalized().unwrap_or(view);
    let n = if n.dot(view) < 0.0 { -n } else { n };
    let diffuse = n.dot(light).max(0.0);
    let half = (light + view).normalized().unwrap_or(view);
    let spec = m.gloss * n.dot(half).max(0.0).powi(SHININESS_EXP);
    m.colour.map(|c| c * (AMBIENT + (1.0 - AMBIENT) * diffuse) + spec)
}

#[cfg(test)]
mod tests {
    use super::*;

    const K: Intrinsics = Intrinsics::new(100.0, 100.0, 32.0, 24.0);

    /// A square of side `s` at depth `z`, facing the camera, centred on the optical axis.
    fn square(s: f64, z: f64) -> Mesh {
        let h = s / 2.0;
        Mesh {
            positions: vec![
                Vec3::new(-h, -h, z),
                Vec3::new(h, -h, z),
                Vec3::new(h, h, z),
                Vec3::new(-h, h, z),
            ],
            normals: vec![Vec3::new(0.0, 0.0, -1.0); 4],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        }
    }

    #[test]
    fn a_square_covers_its_projection_and_the_nearer_one_wins() {
        let mut px = vec![0u8; 64 * 48 * 3];
        let mut t = Target::new(&mut px, 64, 48, K);
        // 0.2 m at 1 m: 20 px wide, centred on (32, 24).
        t.draw(&square(0.2, 1.0), &Material::opaque([255, 0, 0], 0.0));
        // A smaller green square behind it is hidden; a blue one in front shows.
        t.draw(&square(0.1, 2.0), &Material::opaque([0, 255, 0], 0.0));
        t.draw(&square(0.05, 0.5), &Material::opaque([0, 0, 255], 0.0));
        let at = |x: usize, y: usize| {
            [
                px[(y * 64 + x) * 3],
                px[(y * 64 + x) * 3 + 1],
                px[(y * 64 + x) * 3 + 2],
            ]
        };
        assert_eq!(at(0, 0), [0, 0, 0], "outside");
        assert!(
            at(24, 24)[0] > 100 && at(24, 24)[1] == 0,
            "red at the square's left: {:?}",
            at(24, 24)
        );
        assert!(
            at(32, 24)[2] > 100 && at(32, 24)[0] == 0,
            "blue in the middle: {:?}",
            at(32, 24)
        );
        // Coverage: the 20-px square spans 21 pixel centres each way, edges on them; a pixel centre on an edge
        // goes to one side only, so 20 x 20.
        let red_or_blue = (0..48)
            .flat_map(|y| (0..64).map(move |x| (x, y)))
            .filter(|&(x, y)| at(x, y) != [0, 0, 0])
            .count();
        assert_eq!(red_or_blue, 20 * 20);
    }

    #[test]
    fn an_occluder_hides_without_drawing_and_glass_blends() {
        let mut px = vec![100u8; 64 * 48 * 3];
        let mut t = Target::new(&mut px, 64, 48, K);
        t.occlude(&square(0.2, 1.0));
        t.draw(&square(0.6, 1.5), &Material::opaque([255, 255, 255], 0.0));
        let glass = Material {
            colour: [0.0; 3],
            opacity: 0.5,
            gloss: 0.0,
        };
        t.draw(&square(0.1, 0.8), &glass);
        let at = |x: usize, y: usize| px[(y * 64 + x) * 3];
        assert_eq!(
            at(24, 24),
            100,
            "the occluder hides the far square and draws nothing"
        );
        assert!(at(32 + 13, 24) > 100, "the far square shows around the occluder");
        assert_eq!(at(32, 24), 50, "half-transparent black over the background");
    }

    #[test]
    fn what_is_behind_or_too_near_the_camera_is_left_out() {
        let mut px = vec![0u8; 64 * 48 * 3];
        let mut t = Target::new(&mut px, 64, 48, K);
        t.draw(&square(0.2, -1.0), &Material::opaque([255, 0, 0], 0.0));
        t.draw(&square(0.2, 0.01), &Material::opaque([255, 0, 0], 0.0));
        t.splat(Vec3::new(0.0, 0.0, 0.01), 0.1, [1.0; 3], 1.0);
        t.splat(Vec3::new(f64::NAN, 0.0, 1.0), 0.1, [1.0; 3], 1.0);
        assert!(px.iter().all(|&v| v == 0));
    }

    #[test]
    fn a_particle_is_a_disc_of_its_projected_radius() {
        let mut px = vec![0u8; 64 * 48 * 3];
        let mut t = Target::new(&mut px, 64, 48, K);
        // 5 cm at 1 m: 5 px.
        t.splat(Vec3::new(0.0, 0.0, 1.0), 0.05, [1.0; 3], 1.0);
        let lit = px.chunks(3).filter(|p| p[0] > 0).count();
        // Pixel centres within 5 px of (32, 24): 81.
        assert_eq!(lit, 81);
    }
}
