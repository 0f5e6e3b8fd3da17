//! CANDIDE-3 face model: `.wfm` parsing, iBUG landmark ↔ vertex correspondences, and the per-frame
//! Levenberg–Marquardt fit of head rotation, metric translation and five expression units.
//!
//! # Frames
//! * **Camera frame** (OpenCV): x right, y down, z forward along the optical axis; metres.
//! * **Head frame**: CANDIDE with y and z negated, so that the identity rotation is a frontal, upright face
//!   looking at the camera: x towards the subject's left (image right), y down, z into the head; metres,
//!   scaled so that the eye centres are [`EYE_DISTANCE_M`] apart; origin at the CANDIDE origin.
//! * [`FitResult::rotation`] and [`FitResult::translation`] map head-frame points into the camera frame.
//!
//! # Correspondences
//! Built by meaning from the CANDIDE-3.1.6 vertex list (HoloFace's index list addresses Unity's import
//! order and is unusable on the raw file). The table is [`CORRESPONDENCES`]; the eye-lid and eye-corner
//! vertices are the five evenly spaced columns x = 0.13 … 0.47 of each eye.

// Numeric kernels on small fixed arrays read best with explicit indices.
#![allow(clippy::needless_range_loop)]

use thiserror::Error;

use crate::camera::Intrinsics;
use crate::expression::ExpressionWeights;
use crate::geometry::Point2;
use crate::math3::{Mat3, Quat, Vec3};

/// Inter-pupillary distance the mesh is scaled to (metres).
pub const EYE_DISTANCE_M: f64 = 0.063;

/// Expression units fitted, in this order: AUV11 jaw drop, AUV2 lip stretcher, AUV3 brow lowerer,
/// AUV14 lip-corner depressor, AUV6 eyes closed (HoloFace's five blendshapes).
pub const FITTED_UNITS: [&str; 5] = ["AUV11", "AUV2", "AUV3", "AUV14", "AUV6"];
/// Number of fitted expression units.
pub const N_UNITS: usize = FITTED_UNITS.len();

/// iBUG 68-point index → CANDIDE-3 vertex index, by meaning.
///
/// | iBUG | meaning | vertex |
/// |---|---|---|
/// | 17, 19, 21 / 22, 24, 26 | brow outer end, top, inner end (image left / right) | 48, 49, 50 / 17, 16, 15 |
/// | 27, 28, 30 | nasion, nose bridge, nose tip | 4, 94, 5 |
/// | 31, 32, 33, 34, 35 | nose base: left alar, left nostril, subnasale, right nostril, right alar | 59, 112, 6, 111, 26 |
/// | 36–41 | image-left eye: outer corner, upper lid ×2, inner corner, lower lid ×2 | 53, 98, 106, 56, 108, 100 |
/// | 42–47 | image-right eye: inner corner, upper lid ×2, outer corner, lower lid ×2 | 23, 105, 97, 20, 99, 107 |
/// | 48, 54 | mouth corners | 64, 31 |
/// | 49, 50, 51, 52, 53 | upper lip outer contour | 80, 66, 7, 33, 79 |
/// | 56, 57, 58 | lower lip outer contour | 85, 8, 86 |
/// | 60–67 | inner lip contour | 89, 82, 87, 81, 88, 83, 40, 84 |
pub const CORRESPONDENCES: [(usize, usize); 44] = [
    (17, 48),
    (19, 49),
    (21, 50),
    (22, 17),
    (24, 16),
    (26, 15),
    (27, 4),
    (28, 94),
    (30, 5),
    (31, 59),
    (32, 112),
    (33, 6),
    (34, 111),
    (35, 26),
    (36, 53),
    (37, 98),
    (38, 106),
    (39, 56),
    (40, 108),
    (41, 100),
    (42, 23),
    (43, 105),
    (44, 97),
    (45, 20),
    (46, 99),
    (47, 107),
    (48, 64),
    (49, 80),
    (50, 66),
    (51, 7),
    (52, 33),
    (53, 79),
    (54, 31),
    (56, 85),
    (57, 8),
    (58, 86),
    (60, 89),
    (61, 82),
    (62, 87),
    (63, 81),
    (64, 88),
    (65, 83),
    (66, 40),
    (67, 84),
];
/// Number of correspondences.
pub const N_CORR: usize = CORRESPONDENCES.len();

/// Errors reading a `.wfm` file or fitting.
#[derive(Debug, Error, Clone, PartialEq)]
#[non_exhaustive]
pub enum CandideError {
    /// A section header is missing.
    #[error("wfm: section {0:?} not found")]
    MissingSection(&'static str),
    /// A line could not be parsed.
    #[error("wfm line {line}: {what}")]
    Parse {
        /// 1-based line number.
        line: usize,
        /// What was expected.
        what: String,
    },
    /// A vertex index is out of range.
    #[error("wfm: vertex index {index} out of range ({count} vertices)")]
    BadVertex {
        /// Index found.
        index: usize,
        /// Vertex count.
        count: usize,
    },
    /// A required animation unit is missing.
    #[error("wfm: animation unit {0} not found")]
    MissingUnit(&'static str),
    /// Fewer landmarks than the fit needs.
    #[error("fit needs the 68-point set, got {actual} points")]
    TooFewLandmarks {
        /// Points given.
        actual: usize,
    },
    /// Bad camera intrinsics.
    #[error("camera intrinsics must be positive and finite")]
    BadIntrinsics,
}

/// Sparse displacements of one animation unit: `(vertex, [dx, dy, dz])`.
pub type UnitDisplacements = Vec<(usize, [f64; 3])>;

/// A parsed CANDIDE-3 file (original units and axes: y up, z towards the viewer).
#[derive(Clone, Debug)]
pub struct Wfm {
    /// Neutral vertices.
    pub vertices: Vec<[f64; 3]>,
    /// Triangles.
    pub faces: Vec<[usize; 3]>,
    /// Animation units: name (first comment word, e.g. `AUV11`) and sparse vertex displacements.
    pub animation_units: Vec<(String, UnitDisplacements)>,
}

fn numbers(line: &str) -> Option<Vec<f64>> {
    line.split_whitespace()
        .map(|t| t.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect()
}

impl Wfm {
    /// Parses the text of a `.wfm` file (vertex, face and animation-unit sections; shape units ignored).
    pub fn parse(text: &str) -> Result<Self, CandideError> {
        let lines: Vec<&str> = text.lines().collect();
        let find = |name: &'static str| {
            lines
                .iter()
                .position(|l| l.trim_start().starts_with(name))
                .ok_or(CandideError::MissingSection(name))
        };
        let perr = |line: usize, what: &str| CandideError::Parse {
            line: line + 1,
            what: what.to_owned(),
        };
        // Iterator over non-empty, non-comment lines after `start`, with their indices.
        let data_after = |start: usize| {
            lines
                .iter()
                .enumerate()
                .skip(start + 1)
                .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        };
        let count_at = |start: usize| -> Result<(usize, usize), CandideError> {
            let (i, l) = data_after(start).next().ok_or_else(|| perr(start, "count"))?;
            let n = l.trim().parse::<usize>().map_err(|_| perr(i, "count"))?;
            Ok((i, n))
        };

        let vstart = find("# VERTEX LIST")?;
        let (ci, nv) = count_at(vstart)?;
        if nv > 100_000 {
            return Err(perr(ci, "vertex count too large"));
        }
        let mut vertices = Vec::with_capacity(nv);
        for (i, l) in data_after(ci).take(nv) {
            match numbers(l).as_deref() {
                Some([x, y, z]) => vertices.push([*x, *y, *z]),
                _ => return Err(perr(i, "vertex `x y z`")),
            }
        }
        if vertices.len() != nv {
            return Err(perr(ci, "vertex list truncated"));
        }

        let fstart = find("# FACE LIST")?;
        let (ci, nf) = count_at(fstart)?;
        if nf > 1_000_000 {
            return Err(perr(ci, "face count too large"));
        }
        let mut faces = Vec::with_capacity(nf);
        for (i, l) in data_after(ci).take(nf) {
            let idx: Option<Vec<usize>> = l.split_whitespace().map(|t| t.parse().ok()).collect();
            match idx.as_deref() {
                Some(&[a, b, c]) => {
                    for v in [a, b, c] {
                        if v >= nv {
                            return Err(CandideError::BadVertex { index: v, count: nv });
                        }
                    }
                    faces.push([a, b, c]);
                }
                _ => return Err(perr(i, "face `a b c`")),
            }
        }

        // Animation units: a count, then per unit a `# NAME ...` comment, a count and displacement lines.
        let astart = find("# ANIMATION UNITS LIST")?;
        let (ci, nu) = count_at(astart)?;
        let end = lines
            .iter()
            .position(|l| l.trim_start().starts_with("# SHAPE UNITS LIST"))
            .unwrap_or(lines.len());
        let mut animation_units = Vec::with_capacity(nu.min(256));
        let mut i = ci + 1;
        let mut name = String::new();
        while i < end && animation_units.len() < nu {
            let l = lines[i].trim();
            i += 1;
            if l.is_empty() {
                continue;
            }
            if let Some(c) = l.strip_prefix('#') {
                if name.is_empty() {
                    name = c.split_whitespace().next().unwrap_or("").to_owned();
                }
                continue;
            }
            let n = l
                .parse::<usize>()
                .map_err(|_| perr(i - 1, "unit displacement count"))?;
            let mut disp = Vec::with_capacity(n.min(nv));
            while disp.len() < n {
                let l = lines.get(i).ok_or_else(|| perr(i, "unit truncated"))?.trim();
                i += 1;
                if l.is_empty() || l.starts_with('#') {
                    continue;
                }
                match numbers(l).as_deref() {
                    Some([v, dx, dy, dz]) if *v >= 0.0 && v.fract() == 0.0 => {
                        let v = *v as usize;
                        if v >= nv {
                            return Err(CandideError::BadVertex { index: v, count: nv });
                        }
                        disp.push((v, [*dx, *dy, *dz]));
                    }
                    _ => return Err(perr(i - 1, "displacement `vertex dx dy dz`")),
                }
            }
            animation_units.push((std::mem::take(&mut name), disp));
        }
        Ok(Self {
            vertices,
            faces,
            animation_units,
        })
    }
}

/// The fitting model: head-frame positions (metres) of the corresponding vertices and their unit deltas.
#[derive(Clone, Debug)]
pub struct FaceModel {
    /// Neutral positions of the correspondence vertices, head frame, metres.
    pub points: [Vec3; N_CORR],
    /// Per fitted unit, the displacement of each correspondence vertex (head frame, metres per unit weight).
    pub units: [[Vec3; N_CORR]; N_UNITS],
    /// The full neutral mesh in the head frame (for drawing), metres.
    pub mesh: Vec<Vec3>,
    /// Full-mesh unit displacements (for drawing).
    pub mesh_units: Vec<[Vec3; N_UNITS]>,
    /// Triangles.
    pub faces: Vec<[usize; 3]>,
    /// Metres per CANDIDE unit.
    pub scale: f64,
}

/// CANDIDE vertices of the two eyes whose means define the eye centres (the 63 mm distance): the image-left
/// eye's six, then the image-right eye's.
pub(crate) const EYE_VERTICES: [usize; 12] = [53, 98, 106, 56, 108, 100, 23, 105, 97, 20, 99, 107];

impl FaceModel {
    /// Builds the model from a parsed `.wfm`.
    pub fn from_wfm(wfm: &Wfm) -> Result<Self, CandideError> {
        let nv = wfm.vertices.len();
        let get = |v: usize| {
            wfm.vertices
                .get(v)
                .copied()
                .ok_or(CandideError::BadVertex { index: v, count: nv })
        };
        let centre = |ids: &[usize]| -> Result<[f64; 3], CandideError> {
            let mut c = [0.0; 3];
            for &v in ids {
                let p = get(v)?;
                for k in 0..3 {
                    c[k] += p[k] / ids.len() as f64;
                }
            }
            Ok(c)
        };
        let (l, r) = (centre(&EYE_VERTICES[..6])?, centre(&EYE_VERTICES[6..])?);
        let d = ((l[0] - r[0]).powi(2) + (l[1] - r[1]).powi(2) + (l[2] - r[2]).powi(2)).sqrt();
        if d <= 0.0 {
            return Err(CandideError::Parse {
                line: 0,
                what: "eye vertices coincide".into(),
            });
        }
        let scale = EYE_DISTANCE_M / d;
        let to_head = |p: [f64; 3]| Vec3::new(p[0] * scale, -p[1] * scale, -p[2] * scale);
        let mesh: Vec<Vec3> = wfm.vertices.iter().map(|&p| to_head(p)).collect();
        let mut mesh_units = vec![[Vec3::default(); N_UNITS]; nv];
        for (u, unit_name) in FITTED_UNITS.iter().enumerate() {
            let (_, disp) = wfm
                .animation_units
                .iter()
                .find(|(n, _)| n == unit_name)
                .ok_or(CandideError::MissingUnit(unit_name))?;
            for &(v, dv) in disp {
                if let Some(slot) = mesh_units.get_mut(v) {
                    slot[u] = to_head(dv);
                }
            }
        }
        let mut points = [Vec3::default(); N_CORR];
        let mut units = [[Vec3::default(); N_CORR]; N_UNITS];
        for (k, &(_, v)) in CORRESPONDENCES.iter().enumerate() {
            points[k] = *mesh
                .get(v)
                .ok_or(CandideError::BadVertex { index: v, count: nv })?;
            for (u, unit) in units.iter_mut().enumerate() {
                unit[k] = mesh_units[v][u];
            }
        }
        Ok(Self {
            points,
            units,
            mesh,
            mesh_units,
            faces: wfm.faces.clone(),
            scale,
        })
    }

    /// Head-frame position of correspondence `k` under expression weights `w`.
    #[inline]
    pub fn point(&self, k: usize, w: &[f64; N_UNITS]) -> Vec3 {
        let mut p = self.points[k];
        for (u, wu) in w.iter().enumerate() {
            p = p + self.units[u][k].scale(*wu);
        }
        p
    }

    /// Full mesh vertices in the head frame under expression weights `w` (for drawing and occlusion).
    pub fn mesh_with(&self, w: &[f64; N_UNITS]) -> Vec<Vec3> {
        self.mesh
            .iter()
            .zip(&self.mesh_units)
            .map(|(p, du)| {
                let mut q = *p;
                for (u, d) in du.iter().enumerate() {
                    q = q + d.scale(w[u]);
                }
                q
            })
            .collect()
    }

    /// Full mesh vertices in the camera frame for a fit (for drawing).
    pub fn mesh_in_camera(&self, fit: &FitResult) -> Vec<Vec3> {
        let r = fit.rotation.to_mat3();
        self.mesh_with(&fit.weights.0)
            .into_iter()
            .map(|q| r * q + fit.translation)
            .collect()
    }
}

/// Fit settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitOptions {
    /// Maximum LM iterations.
    pub max_iterations: u32,
    /// Tikhonov prior on the expression weights, in (normalised residual)² per unit weight². Residuals are
    /// divided by the observed outer-eye-corner distance, so the prior does not depend on face size.
    pub weight_prior: f64,
    /// Stop when the relative cost decrease falls below this.
    pub tolerance: f64,
}

impl Default for FitOptions {
    fn default() -> Self {
        Self {
            max_iterations: 6,
            weight_prior: 2e-4,
            tolerance: 1e-6,
        }
    }
}

/// Result of a fit: maps head-frame points into the camera frame as `rotation · p + translation`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitResult {
    /// Head-to-camera rotation.
    pub rotation: Quat,
    /// Head origin in the camera frame, metres.
    pub translation: Vec3,
    /// Expression weights.
    pub weights: ExpressionWeights,
    /// Root-mean-square reprojection error over the correspondences, pixels.
    pub rmse_px: f64,
    /// Iterations run.
    pub iterations: u32,
    /// Whether the cost stopped decreasing before the iteration cap.
    pub converged: bool,
}

const NP: usize = 6 + N_UNITS;

/// Initial guess from the landmarks alone: frontal with the in-plane roll of the eye line, depth from the
/// eye distance, position from the landmark centroid.
pub fn initial_guess(model: &FaceModel, k: &Intrinsics, lm: &[Point2]) -> Option<FitResult> {
    if lm.len() < 68 || !k.valid() {
        return None;
    }
    let eye = |r: std::ops::Range<usize>| {
        let n = r.len() as f64;
        let (x, y) = lm[r]
            .iter()
            .fold((0.0, 0.0), |(x, y), p| (x + f64::from(p.x), y + f64::from(p.y)));
        (x / n, y / n)
    };
    let (l, r) = (eye(36..42), eye(42..48));
    let d_px = ((r.0 - l.0).powi(2) + (r.1 - l.1).powi(2)).sqrt();
    if d_px < 1.0 {
        return None;
    }
    let roll = (r.1 - l.1).atan2(r.0 - l.0);
    let z = k.fx * EYE_DISTANCE_M / d_px;
    let rot = Quat::from_axis_angle(Vec3::new(0.0, 0.0, roll));
    let rm = rot.to_mat3();
    // Centroid of the correspondence landmarks vs the model's.
    let (mut ox, mut oy) = (0.0, 0.0);
    let mut mc = Vec3::default();
    for (j, &(i, _)) in CORRESPONDENCES.iter().enumerate() {
        ox += f64::from(lm[i].x);
        oy += f64::from(lm[i].y);
        mc = mc + model.points[j];
    }
    let n = N_CORR as f64;
    let (ox, oy, mc) = (ox / n, oy / n, mc.scale(1.0 / n));
    let ray = Vec3::new((ox - k.cx) / k.fx, (oy - k.cy) / k.fy, 1.0);
    let centre = ray.scale(z);
    Some(FitResult {
        rotation: rot,
        translation: centre - rm * mc,
        weights: ExpressionWeights::NEUTRAL,
        rmse_px: f64::INFINITY,
        iterations: 0,
        converged: false,
    })
}

/// The data of one fit: model, camera, observed landmarks and the residual scaling.
struct Problem<'a> {
    model: &'a FaceModel,
    k: &'a Intrinsics,
    lm: &'a [Point2],
    inv_norm: f64,
    prior: f64,
}

impl Problem<'_> {
    /// The normal equations JᵀJ δ = −Jᵀr at `rm` (the rotation of `cur`) and `cur` (analytic Jacobian, the weight
    /// prior on the diagonal). Parameters: δω (left-multiplied rotation increment), δt, δw.
    fn normal_equations(&self, rm: &Mat3, cur: &FitResult) -> ([[f64; NP]; NP], [f64; NP]) {
        let (model, k, landmarks, inv_norm, prior) = (self.model, self.k, self.lm, self.inv_norm, self.prior);
        let rm = *rm;
        let mut jtj = [[0.0f64; NP]; NP];
        let mut jtr = [0.0f64; NP];
        for (j, &(i, _)) in CORRESPONDENCES.iter().enumerate() {
            let x = model.point(j, &cur.weights.0);
            let rx = rm * x;
            let p = rx + cur.translation;
            let iz = 1.0 / p.z;
            let u = (k.fx * p.x * iz + k.cx - f64::from(landmarks[i].x)) * inv_norm;
            let v = (k.fy * p.y * iz + k.cy - f64::from(landmarks[i].y)) * inv_norm;
            // d(u,v)/dp
            let du = Vec3::new(k.fx * iz, 0.0, -k.fx * p.x * iz * iz).scale(inv_norm);
            let dv = Vec3::new(0.0, k.fy * iz, -k.fy * p.y * iz * iz).scale(inv_norm);
            let mut ju = [0.0; NP];
            let mut jv = [0.0; NP];
            // dp/dω = −[R x]×  ⇒  row·dp/dω = (R x) × row
            let cu = rx.cross(du);
            let cv = rx.cross(dv);
            ju[..3].copy_from_slice(&cu.to_array());
            jv[..3].copy_from_slice(&cv.to_array());
            ju[3..6].copy_from_slice(&du.to_array());
            jv[3..6].copy_from_slice(&dv.to_array());
            for un in 0..N_UNITS {
                let d = rm * model.units[un][j];
                ju[6 + un] = du.dot(d);
                jv[6 + un] = dv.dot(d);
            }
            for a in 0..NP {
                jtr[a] += ju[a] * u + jv[a] * v;
                for b in a..NP {
                    jtj[a][b] += ju[a] * ju[b] + jv[a] * jv[b];
                }
            }
        }
        for un in 0..N_UNITS {
            jtj[6 + un][6 + un] += prior;
            jtr[6 + un] += prior * cur.weights.0[un];
        }
        for a in 0..NP {
            for b in 0..a {
                jtj[a][b] = jtj[b][a];
            }
        }
        (jtj, jtr)
    }

    /// Cost (normalised squared reprojection error plus the weight prior); `None` behind the camera.
    fn cost(&self, r: &Mat3, t: Vec3, w: &[f64; N_UNITS]) -> Option<f64> {
        let (k, lm, inv_norm) = (self.k, self.lm, self.inv_norm);
        let mut cost = 0.0;
        for (j, &(i, _)) in CORRESPONDENCES.iter().enumerate() {
            let p = *r * self.model.point(j, w) + t;
            if p.z <= 1e-4 {
                return None;
            }
            let u = k.fx * p.x / p.z + k.cx - f64::from(lm[i].x);
            let v = k.fy * p.y / p.z + k.cy - f64::from(lm[i].y);
            cost += (u * u + v * v) * inv_norm * inv_norm;
        }
        Some(cost + self.prior * w.iter().map(|x| x * x).sum::<f64>())
    }
}

/// Fits rotation, translation and expression weights to 68 image landmarks (pixels) by Levenberg–Marquardt
/// with an analytic Jacobian. `start` is the previous frame's result (warm start) or `None` (reset: uses
/// [`initial_guess`]).
pub fn fit(
    model: &FaceModel,
    k: &Intrinsics,
    landmarks: &[Point2],
    start: Option<&FitResult>,
    opts: &FitOptions,
) -> Result<FitResult, CandideError> {
    if landmarks.len() < 68 {
        return Err(CandideError::TooFewLandmarks {
            actual: landmarks.len(),
        });
    }
    if !k.valid() {
        return Err(CandideError::BadIntrinsics);
    }
    let mut cur = match start {
        Some(s) if s.translation.z > 0.0 && s.translation.z.is_finite() => *s,
        _ => initial_guess(model, k, landmarks).ok_or(CandideError::TooFewLandmarks {
            actual: landmarks.len(),
        })?,
    };
    let norm = f64::from(landmarks[36].dist(landmarks[45])).max(1.0);
    let inv_norm = 1.0 / norm;
    let prior = opts.weight_prior;
    let problem = Problem {
        model,
        k,
        lm: landmarks,
        inv_norm,
        prior,
    };
    let mut rm = cur.rotation.to_mat3();
    let mut cost = problem
        .cost(&rm, cur.translation, &cur.weights.0)
        .unwrap_or(f64::INFINITY);
    if !cost.is_finite() {
        cur = initial_guess(model, k, landmarks).ok_or(CandideError::TooFewLandmarks {
            actual: landmarks.len(),
        })?;
        rm = cur.rotation.to_mat3();
        cost = problem
            .cost(&rm, cur.translation, &cur.weights.0)
            .unwrap_or(f64::INFINITY);
    }
    let mut lambda = 1e-3;
    let mut converged = false;
    let mut iterations = 0;
    for _ in 0..opts.max_iterations {
        iterations += 1;
        let (jtj, jtr) = problem.normal_equations(&rm, &cur);
        let mut improved = false;
        for _ in 0..8 {
            let mut m = jtj;
            for (a, row) in m.iter_mut().enumerate() {
                row[a] += lambda * (jtj[a][a] + 1e-9);
            }
            let Some(delta) = crate::linalg::solve_spd(m, jtr.map(|x| -x)) else {
                lambda *= 10.0;
                continue;
            };
            let dq = Quat::from_axis_angle(Vec3::new(delta[0], delta[1], delta[2]));
            let rot = dq * cur.rotation.normalized();
            let rmn = rot.to_mat3();
            let t = cur.translation + Vec3::new(delta[3], delta[4], delta[5]);
            let mut w = cur.weights;
            for un in 0..N_UNITS {
                w.0[un] += delta[6 + un];
            }
            match problem.cost(&rmn, t, &w.0) {
                Some(c) if c < cost => {
                    let rel = (cost - c) / cost.max(1e-300);
                    cur.rotation = rot;
                    cur.translation = t;
                    cur.weights = w;
                    rm = rmn;
                    cost = c;
                    lambda = (lambda * 0.3).max(1e-9);
                    improved = true;
                    if rel < opts.tolerance {
                        converged = true;
                    }
                    break;
                }
                _ => lambda *= 10.0,
            }
        }
        if !improved {
            converged = true;
        }
        if converged {
            break;
        }
    }
    let data_cost = cost - prior * cur.weights.0.iter().map(|x| x * x).sum::<f64>();
    cur.rmse_px = (data_cost.max(0.0) / N_CORR as f64).sqrt() * norm;
    cur.iterations = iterations;
    cur.converged = converged;
    Ok(cur)
}

/// Projects the model's correspondence points for a fit into 68-point landmark slots (others untouched).
/// Used to synthesise ground-truth landmarks and by tests.
pub fn project_landmarks(model: &FaceModel, k: &Intrinsics, fit: &FitResult, out: &mut [Point2; 68]) -> bool {
    let rm = fit.rotation.to_mat3();
    for (j, &(i, _)) in CORRESPONDENCES.iter().enumerate() {
        match k.project(rm * model.point(j, &fit.weights.0) + fit.translation) {
            Some(p) => out[i] = p,
            None => return false,
        }
    }
    true
}
