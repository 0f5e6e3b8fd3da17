//! How head turns move the landmarks in the face's frame, and how to undo it.
//!
//! The face's frame (an affine map of the rigid points onto a template) removes the head's position, size and
//! roll and the foreshortening of a flat patch, but the face is not flat: the lips, the chin, the brows and
//! the nose lie off the plane of the eye corners, so a yaw or a pitch moves them in that frame as an
//! expression would (on real video, `mouthClose` and `browInnerUp` followed the head's pitch with r = -0.86
//! and -0.91, `jawRight` its yaw with r = -0.88). Each landmark's shift is modelled as a quadratic in the
//! head's turn `(a, b)` ([`HeadTurn`], from the CANDIDE-3 fit the runtime makes every frame):
//! `d_i = A_i · [a, b, a², ab, b²]`, fitted by least squares over annotated faces in every pose (and their
//! mirror images, so that the terms are symmetric), each face's turn from CANDIDE-3 fitted to its annotation.
//! [`PoseTerms::frontalise`] subtracts it: what is left is the landmark of a face looking at the camera plus
//! the expression.
//!
//! The committed terms (`models/assets/blendshape_pose.txt`) come from `holoface train-blendshapes` over the
//! training split of the annotated faces (the validation split excluded): statistics our code produced.

use super::P;
use crate::math3::{Quat, Vec3};

/// The quadratic basis of the turn.
const BASIS: usize = 5;

fn basis(t: HeadTurn) -> [f64; BASIS] {
    let (a, b) = (t.across, t.down);
    [a, b, a * a, a * b, b * b]
}

/// How far the head is turned from facing the viewer: the components across the image (x right, y down)
/// of the head's forward axis less those of the line of sight to it (unit vectors); (0, 0) facing the
/// camera, about (sin yaw, -sin pitch) for small turns.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct HeadTurn {
    /// Across the image, to its right.
    pub across: f64,
    /// Down the image.
    pub down: f64,
}

impl HeadTurn {
    /// From a head-to-camera rotation and the head's place in the camera frame (CANDIDE-3's fit: the head
    /// frame's z points into the head).
    pub fn from_pose(rotation: Quat, translation: Vec3) -> Self {
        let forward = rotation.to_mat3().col(2);
        let sight = translation.normalized().unwrap_or(Vec3::new(0.0, 0.0, 1.0));
        let t = Self {
            across: forward.x - sight.x,
            down: forward.y - sight.y,
        };
        if t.across.is_finite() && t.down.is_finite() {
            t
        } else {
            Self::default()
        }
    }
}

/// The learnt pose terms.
#[derive(Clone, Debug, PartialEq)]
pub struct PoseTerms {
    /// The range of the turn seen in training (1st to 99th percentile of each component): turns are clamped
    /// to it, so that a wild fit cannot send the quadratic off.
    range: [f64; 4],
    /// Per landmark, the x and y rows of `A_i`.
    terms: Vec<[[f64; BASIS]; 2]>,
}

impl PoseTerms {
    /// Fits the terms to face-frame shapes and their turns (`None` with fewer than 20 or a singular system).
    pub(crate) fn fit(frames: &[([P; 68], HeadTurn)]) -> Option<Self> {
        if frames.len() < 20 {
            return None;
        }
        let n = frames.len() as f64;
        let mut us: Vec<f64> = frames.iter().map(|f| f.1.across).collect();
        let mut vs: Vec<f64> = frames.iter().map(|f| f.1.down).collect();
        us.sort_by(f64::total_cmp);
        vs.sort_by(f64::total_cmp);
        let q = |v: &[f64], p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
        let range = [q(&us, 0.01), q(&us, 0.99), q(&vs, 0.01), q(&vs, 0.99)];
        // Normal equations of [1, basis] (an intercept, then the terms), one per landmark and axis; the
        // design is the same for all of them.
        const M: usize = BASIS + 1;
        let mut ata = [[0.0; M]; M];
        let mut atb = vec![[[0.0; M]; 2]; 68];
        for (f, turn) in frames {
            let mut row = [1.0; M];
            row[1..].copy_from_slice(&basis(*turn));
            for r in 0..M {
                for c in 0..M {
                    ata[r][c] += row[r] * row[c];
                }
            }
            for (acc, p) in atb.iter_mut().zip(f) {
                for r in 0..M {
                    acc[0][r] += row[r] * p.0;
                    acc[1][r] += row[r] * p.1;
                }
            }
        }
        // A light ridge on the terms (not the intercept) keeps a pose-poor set from fitting noise.
        for (k, r) in ata.iter_mut().enumerate().skip(1) {
            r[k] += 1e-6 * n;
        }
        let mut terms = Vec::with_capacity(68);
        for rhs in &atb {
            let mut t = [[0.0; BASIS]; 2];
            for axis in 0..2 {
                let x = crate::linalg::solve_spd(ata, rhs[axis])?;
                t[axis].copy_from_slice(&x[1..]);
            }
            terms.push(t);
        }
        Some(Self { range, terms })
    }

    /// Moves face-frame landmarks of a head turned by `turn` to a head facing the camera.
    pub(crate) fn frontalise(&self, f: &mut [P; 68], turn: HeadTurn) {
        let b = basis(HeadTurn {
            across: turn.across.clamp(self.range[0], self.range[1]),
            down: turn.down.clamp(self.range[2], self.range[3]),
        });
        for (p, t) in f.iter_mut().zip(&self.terms) {
            let dot = |row: &[f64; BASIS]| row.iter().zip(&b).map(|(a, b)| a * b).sum::<f64>();
            p.0 -= dot(&t[0]);
            p.1 -= dot(&t[1]);
        }
    }

    /// The text form (`models/assets/blendshape_pose.txt`): `#` comments, then `range amin amax bmin bmax`
    /// and 68 lines of ten numbers (the x row, then the y row).
    pub fn to_text(&self, comment: &str) -> String {
        let mut s = String::new();
        for line in comment.lines() {
            s.push_str("# ");
            s.push_str(line);
            s.push('\n');
        }
        let r = self.range;
        s.push_str(&format!(
            "range {:.6} {:.6} {:.6} {:.6}\n",
            r[0], r[1], r[2], r[3]
        ));
        for t in &self.terms {
            let nums: Vec<String> = t.iter().flatten().map(|v| format!("{v:.6}")).collect();
            s.push_str(&nums.join(" "));
            s.push('\n');
        }
        s
    }

    /// Parses [`Self::to_text`]'s form.
    pub fn parse(text: &str) -> Result<Self, String> {
        let mut lines = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'));
        let mut numbers = |tag: &str, count: usize| -> Result<Vec<f64>, String> {
            let line = lines.next().ok_or_else(|| format!("missing line {tag}"))?;
            let rest = line
                .strip_prefix(tag)
                .ok_or_else(|| format!("expected `{tag}`, found `{line}`"))?;
            let v: Vec<f64> = rest
                .split_whitespace()
                .map(|w| w.parse::<f64>().map_err(|e| format!("`{w}`: {e}")))
                .collect::<Result<_, _>>()?;
            if v.len() != count || v.iter().any(|x| !x.is_finite()) {
                return Err(format!("`{line}`: expected {count} finite numbers"));
            }
            Ok(v)
        };
        let range = numbers("range", 4)?;
        let mut terms = Vec::with_capacity(68);
        for _ in 0..68 {
            let v = numbers("", 2 * BASIS)?;
            let mut t = [[0.0; BASIS]; 2];
            t[0].copy_from_slice(&v[..BASIS]);
            t[1].copy_from_slice(&v[BASIS..]);
            terms.push(t);
        }
        if lines.next().is_some() {
            return Err("more than 68 landmark lines".into());
        }
        if range[0] > range[1] || range[2] > range[3] {
            return Err("range: minimum above maximum".into());
        }
        Ok(Self {
            range: [range[0], range[1], range[2], range[3]],
            terms,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A face-frame shape whose landmarks shift by known quadratics of the turn.
    fn posed(t: HeadTurn, truth: &[[[f64; BASIS]; 2]]) -> [P; 68] {
        let b = basis(t);
        std::array::from_fn(|i| {
            let dot = |row: &[f64; BASIS]| row.iter().zip(&b).map(|(a, b)| a * b).sum::<f64>();
            (i as f64 * 0.01 + dot(&truth[i][0]), 0.5 + dot(&truth[i][1]))
        })
    }

    fn turn(a: f64, b: f64) -> HeadTurn {
        HeadTurn { across: a, down: b }
    }

    #[test]
    fn fitted_terms_undo_a_known_turn_and_survive_their_text_form() {
        let truth: Vec<[[f64; BASIS]; 2]> = (0..68)
            .map(|i| {
                let k = i as f64 / 68.0;
                [
                    [0.3 * k, 0.0, 0.5 * k, 0.0, 0.0],
                    [0.0, -0.2 * k, 0.0, 0.1, 0.4 * k],
                ]
            })
            .collect();
        let frames: Vec<([P; 68], HeadTurn)> = (0..400)
            .map(|j| {
                let t = turn(
                    ((j * 37) % 41) as f64 / 100.0 - 0.2,
                    ((j * 13) % 29) as f64 / 100.0 - 0.14,
                );
                (posed(t, &truth), t)
            })
            .collect();
        let terms = PoseTerms::fit(&frames).unwrap();
        let again = PoseTerms::parse(&terms.to_text("a test\nof two lines")).unwrap();
        for t in [&terms, &again] {
            let mut f = posed(turn(0.15, -0.1), &truth);
            t.frontalise(&mut f, turn(0.15, -0.1));
            let rest = posed(turn(0.0, 0.0), &truth);
            for i in 0..68 {
                assert!(
                    (f[i].0 - rest[i].0).abs() < 1e-4 && (f[i].1 - rest[i].1).abs() < 1e-4,
                    "{i}"
                );
            }
        }
        assert!(PoseTerms::fit(&frames[..10]).is_none());
        assert!(PoseTerms::parse("range 0 1 0 1\n1 2 3").is_err());
        assert!(PoseTerms::parse("range 0 NaN 0 1\n").is_err());
        assert!(PoseTerms::parse("").is_err());
    }

    #[test]
    fn the_turn_is_zero_facing_the_camera_and_follows_yaw_and_pitch() {
        let ahead = Vec3::new(0.0, 0.0, 0.6);
        assert_eq!(HeadTurn::from_pose(Quat::IDENTITY, ahead), HeadTurn::default());
        let yawed = HeadTurn::from_pose(Quat::from_axis_angle(Vec3::new(0.0, 0.3, 0.0)), ahead);
        assert!(
            (yawed.across - 0.3f64.sin()).abs() < 1e-9 && yawed.down.abs() < 1e-9,
            "{yawed:?}"
        );
        let pitched = HeadTurn::from_pose(Quat::from_axis_angle(Vec3::new(0.2, 0.0, 0.0)), ahead);
        assert!(
            pitched.across.abs() < 1e-9 && (pitched.down + 0.2f64.sin()).abs() < 1e-9,
            "{pitched:?}"
        );
        // Off to the side, a head turned to face the camera is not turned.
        let aside = Vec3::new(0.3, 0.0, 0.6);
        let facing = Quat::from_axis_angle(Vec3::new(0.0, (0.3f64).atan2(0.6), 0.0));
        assert!(HeadTurn::from_pose(facing, aside).across.abs() < 1e-9);
    }
}
