//! Small fixed-size 3-D math: vectors, rotation matrices, quaternions, rigid poses.
//!
//! Rotation matrices are row-major; `Mat3 * Vec3` rotates the vector. Quaternions are unit `(w, x, y, z)`.

use std::ops::{Add, Mul, Neg, Sub};

/// A 3-vector.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Vec3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

impl Vec3 {
    /// A vector from its components.
    pub const fn new(x: f64, y: f64, z: f64) -> Self {
        Self { x, y, z }
    }
    /// Dot product.
    pub fn dot(self, o: Self) -> f64 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }
    /// Cross product.
    pub fn cross(self, o: Self) -> Self {
        Self::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }
    /// Euclidean norm.
    pub fn norm(self) -> f64 {
        self.dot(self).sqrt()
    }
    /// Scaled by `k`.
    pub fn scale(self, k: f64) -> Self {
        Self::new(self.x * k, self.y * k, self.z * k)
    }
    /// Unit vector in the same direction (`None` for a zero vector).
    pub fn normalized(self) -> Option<Self> {
        let n = self.norm();
        (n > 1e-300 && n.is_finite()).then(|| self.scale(1.0 / n))
    }
    /// Components as an array.
    pub fn to_array(self) -> [f64; 3] {
        [self.x, self.y, self.z]
    }
}

impl Add for Vec3 {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        Self::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}
impl Sub for Vec3 {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        Self::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}
impl Neg for Vec3 {
    type Output = Self;
    fn neg(self) -> Self {
        Self::new(-self.x, -self.y, -self.z)
    }
}

/// A 3×3 matrix, row-major.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mat3(pub [[f64; 3]; 3]);

impl Default for Mat3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Mat3 {
    /// The identity.
    pub const IDENTITY: Self = Self([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]);

    /// From three column vectors.
    pub fn from_cols(c0: Vec3, c1: Vec3, c2: Vec3) -> Self {
        Self([[c0.x, c1.x, c2.x], [c0.y, c1.y, c2.y], [c0.z, c1.z, c2.z]])
    }
    /// Column `j`.
    pub fn col(&self, j: usize) -> Vec3 {
        let m = &self.0;
        Vec3::new(m[0][j], m[1][j], m[2][j])
    }
    /// Transpose (the inverse of a rotation).
    pub fn transpose(&self) -> Self {
        let m = &self.0;
        Self([
            [m[0][0], m[1][0], m[2][0]],
            [m[0][1], m[1][1], m[2][1]],
            [m[0][2], m[1][2], m[2][2]],
        ])
    }
    /// Rotation by `|v|` radians about `v` (Rodrigues).
    pub fn from_axis_angle(v: Vec3) -> Self {
        Quat::from_axis_angle(v).to_mat3()
    }
    /// Rotation about x by `a` radians.
    pub fn rot_x(a: f64) -> Self {
        let (s, c) = a.sin_cos();
        Self([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    }
    /// Rotation about y by `a` radians.
    pub fn rot_y(a: f64) -> Self {
        let (s, c) = a.sin_cos();
        Self([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    }
    /// Rotation about z by `a` radians.
    pub fn rot_z(a: f64) -> Self {
        let (s, c) = a.sin_cos();
        Self([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    }
    /// Re-orthonormalises a nearly orthonormal matrix through its quaternion.
    pub fn orthonormalized(&self) -> Self {
        Quat::from_mat3(self).to_mat3()
    }
    /// Angle of the rotation in radians.
    pub fn angle(&self) -> f64 {
        let m = &self.0;
        ((m[0][0] + m[1][1] + m[2][2] - 1.0) * 0.5)
            .clamp(-1.0, 1.0)
            .acos()
    }
}

impl Mul<Vec3> for Mat3 {
    type Output = Vec3;
    fn mul(self, v: Vec3) -> Vec3 {
        let m = &self.0;
        Vec3::new(
            m[0][0] * v.x + m[0][1] * v.y + m[0][2] * v.z,
            m[1][0] * v.x + m[1][1] * v.y + m[1][2] * v.z,
            m[2][0] * v.x + m[2][1] * v.y + m[2][2] * v.z,
        )
    }
}

impl Mul for Mat3 {
    type Output = Self;
    fn mul(self, o: Self) -> Self {
        let mut r = [[0.0; 3]; 3];
        for (i, row) in r.iter_mut().enumerate() {
            for (j, v) in row.iter_mut().enumerate() {
                *v = (0..3).map(|k| self.0[i][k] * o.0[k][j]).sum();
            }
        }
        Self(r)
    }
}

/// A unit quaternion `(w, x, y, z)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Quat {
    /// Scalar part.
    pub w: f64,
    /// x of the vector part.
    pub x: f64,
    /// y of the vector part.
    pub y: f64,
    /// z of the vector part.
    pub z: f64,
}

impl Default for Quat {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Quat {
    /// No rotation.
    pub const IDENTITY: Self = Self {
        w: 1.0,
        x: 0.0,
        y: 0.0,
        z: 0.0,
    };

    /// Rotation by `|v|` radians about `v`.
    pub fn from_axis_angle(v: Vec3) -> Self {
        let angle = v.norm();
        if angle < 1e-12 {
            return Self {
                w: 1.0,
                x: 0.5 * v.x,
                y: 0.5 * v.y,
                z: 0.5 * v.z,
            }
            .normalized();
        }
        let (s, c) = (0.5 * angle).sin_cos();
        let k = s / angle;
        Self {
            w: c,
            x: v.x * k,
            y: v.y * k,
            z: v.z * k,
        }
    }

    /// Unit length copy (identity for a zero quaternion).
    pub fn normalized(self) -> Self {
        let n = (self.w * self.w + self.x * self.x + self.y * self.y + self.z * self.z).sqrt();
        if n < 1e-300 || !n.is_finite() {
            return Self::IDENTITY;
        }
        Self {
            w: self.w / n,
            x: self.x / n,
            y: self.y / n,
            z: self.z / n,
        }
    }

    /// Rotation matrix.
    pub fn to_mat3(self) -> Mat3 {
        let Self { w, x, y, z } = self.normalized();
        Mat3([
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ])
    }

    /// From a rotation matrix (Shepperd's method).
    pub fn from_mat3(m: &Mat3) -> Self {
        let m = &m.0;
        let tr = m[0][0] + m[1][1] + m[2][2];
        let q = if tr > 0.0 {
            let s = (tr + 1.0).sqrt() * 2.0;
            Self {
                w: 0.25 * s,
                x: (m[2][1] - m[1][2]) / s,
                y: (m[0][2] - m[2][0]) / s,
                z: (m[1][0] - m[0][1]) / s,
            }
        } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
            let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
            Self {
                w: (m[2][1] - m[1][2]) / s,
                x: 0.25 * s,
                y: (m[0][1] + m[1][0]) / s,
                z: (m[0][2] + m[2][0]) / s,
            }
        } else if m[1][1] > m[2][2] {
            let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
            Self {
                w: (m[0][2] - m[2][0]) / s,
                x: (m[0][1] + m[1][0]) / s,
                y: 0.25 * s,
                z: (m[1][2] + m[2][1]) / s,
            }
        } else {
            let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
            Self {
                w: (m[1][0] - m[0][1]) / s,
                x: (m[0][2] + m[2][0]) / s,
                y: (m[1][2] + m[2][1]) / s,
                z: 0.25 * s,
            }
        };
        q.normalized()
    }

    /// Inverse rotation.
    pub fn conjugate(self) -> Self {
        Self {
            w: self.w,
            x: -self.x,
            y: -self.y,
            z: -self.z,
        }
    }

    /// Angle between two rotations in radians.
    pub fn angle_to(self, o: Self) -> f64 {
        let d = (self.w * o.w + self.x * o.x + self.y * o.y + self.z * o.z)
            .abs()
            .min(1.0);
        2.0 * d.acos()
    }

    /// Spherical interpolation: `t = 0` gives `self`, `t = 1` gives `o` (shortest path).
    pub fn slerp(self, o: Self, t: f64) -> Self {
        let mut d = self.w * o.w + self.x * o.x + self.y * o.y + self.z * o.z;
        let o = if d < 0.0 {
            d = -d;
            Self {
                w: -o.w,
                x: -o.x,
                y: -o.y,
                z: -o.z,
            }
        } else {
            o
        };
        if d > 0.9995 {
            return Self {
                w: self.w + t * (o.w - self.w),
                x: self.x + t * (o.x - self.x),
                y: self.y + t * (o.y - self.y),
                z: self.z + t * (o.z - self.z),
            }
            .normalized();
        }
        let th = d.clamp(-1.0, 1.0).acos();
        let s = th.sin();
        let (a, b) = (((1.0 - t) * th).sin() / s, (t * th).sin() / s);
        Self {
            w: a * self.w + b * o.w,
            x: a * self.x + b * o.x,
            y: a * self.y + b * o.y,
            z: a * self.z + b * o.z,
        }
    }
}

impl Mul for Quat {
    type Output = Self;
    /// `self · o`: apply `o` first.
    fn mul(self, o: Self) -> Self {
        Self {
            w: self.w * o.w - self.x * o.x - self.y * o.y - self.z * o.z,
            x: self.w * o.x + self.x * o.w + self.y * o.z - self.z * o.y,
            y: self.w * o.y - self.x * o.z + self.y * o.w + self.z * o.x,
            z: self.w * o.z + self.x * o.y - self.y * o.x + self.z * o.w,
        }
    }
}

/// A rigid transform `p ↦ R·p + t`, named output-first (`world_from_camera` maps camera points to world).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Pose {
    /// Rotation.
    pub rotation: Mat3,
    /// Translation (metres).
    pub translation: Vec3,
}

impl Pose {
    /// The identity transform.
    pub const IDENTITY: Self = Self {
        rotation: Mat3::IDENTITY,
        translation: Vec3::new(0.0, 0.0, 0.0),
    };

    /// Maps a point.
    pub fn apply(&self, p: Vec3) -> Vec3 {
        self.rotation * p + self.translation
    }
    /// The inverse transform.
    pub fn inverse(&self) -> Self {
        let rt = self.rotation.transpose();
        Self {
            rotation: rt,
            translation: -(rt * self.translation),
        }
    }
    /// `self ∘ first`.
    pub fn after(&self, first: &Self) -> Self {
        Self {
            rotation: self.rotation * first.rotation,
            translation: self.apply(first.translation),
        }
    }
    /// From a row-major 4×4 matrix (the last row is ignored). Returns `None` when the 3×3 block is not a
    /// rotation (orthonormal within 1e-3, determinant +1) or a value is not finite.
    pub fn from_row_major_4x4(m: &[f32; 16]) -> Option<Self> {
        if m.iter().any(|v| !v.is_finite()) {
            return None;
        }
        let g = |r: usize, c: usize| f64::from(m[r * 4 + c]);
        let rot = Mat3([
            [g(0, 0), g(0, 1), g(0, 2)],
            [g(1, 0), g(1, 1), g(1, 2)],
            [g(2, 0), g(2, 1), g(2, 2)],
        ]);
        let should_be_id = rot * rot.transpose();
        for (i, row) in should_be_id.0.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let want = if i == j { 1.0 } else { 0.0 };
                if (v - want).abs() > 1e-3 {
                    return None;
                }
            }
        }
        let det = rot.col(0).dot(rot.col(1).cross(rot.col(2)));
        if det < 0.0 {
            return None;
        }
        Some(Self {
            rotation: rot.orthonormalized(),
            translation: Vec3::new(g(0, 3), g(1, 3), g(2, 3)),
        })
    }
    /// Row-major 4×4 matrix.
    pub fn to_row_major_4x4(&self) -> [f32; 16] {
        let r = &self.rotation.0;
        let t = self.translation;
        [
            r[0][0] as f32,
            r[0][1] as f32,
            r[0][2] as f32,
            t.x as f32,
            r[1][0] as f32,
            r[1][1] as f32,
            r[1][2] as f32,
            t.y as f32,
            r[2][0] as f32,
            r[2][1] as f32,
            r[2][2] as f32,
            t.z as f32,
            0.0,
            0.0,
            0.0,
            1.0,
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_and_matrix_agree() {
        let v = Vec3::new(0.3, -0.5, 0.2);
        let q = Quat::from_axis_angle(v);
        let m = q.to_mat3();
        let back = Quat::from_mat3(&m);
        assert!(q.angle_to(back) < 1e-9);
        assert!((m.angle() - v.norm()).abs() < 1e-9);
        let p = Vec3::new(1.0, 2.0, 3.0);
        let r1 = m * p;
        let r2 = (Mat3::rot_z(0.0) * m) * p;
        assert!((r1 - r2).norm() < 1e-12);
        let half = Quat::IDENTITY.slerp(q, 0.5);
        assert!((half.angle_to(Quat::IDENTITY) - 0.5 * v.norm()).abs() < 1e-9);
    }

    #[test]
    fn pose_inverse_and_4x4() {
        let p = Pose {
            rotation: Mat3::rot_y(0.7) * Mat3::rot_x(-0.2),
            translation: Vec3::new(1.0, -2.0, 0.5),
        };
        let x = Vec3::new(0.1, 0.2, 0.3);
        assert!((p.inverse().apply(p.apply(x)) - x).norm() < 1e-12);
        let back = Pose::from_row_major_4x4(&p.to_row_major_4x4()).unwrap();
        assert!((back.apply(x) - p.apply(x)).norm() < 1e-5);
        let mut bad = p.to_row_major_4x4();
        bad[0] = 3.0;
        assert!(Pose::from_row_major_4x4(&bad).is_none());
        bad[0] = f32::NAN;
        assert!(Pose::from_row_major_4x4(&bad).is_none());
    }
}
