//! Position prediction and smoothing for rendering (algorithms.md 3.9, 3.10).
//!
//! One Singer-like Kalman filter per world axis with state (x, v, a): the acceleration decays with time
//! constant τ and is driven by white noise; the output is the position predicted `lookahead` seconds ahead,
//! which hides the capture-to-display latency. Time enters only as `dt` arguments.

// Small fixed-size matrix code reads best with explicit indices.
#![allow(clippy::needless_range_loop)]

use crate::math3::{Quat, Vec3};

/// Filter parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KalmanParams {
    /// Acceleration noise σₐ (m/s²).
    pub sigma_a: f64,
    /// Measurement noise σ_z (m).
    pub sigma_z: f64,
    /// Acceleration decay time constant τ (s).
    pub tau: f64,
    /// Initial velocity standard deviation (m/s); HoloFace starts with P = 0, which makes early gains tiny.
    pub initial_sigma_v: f64,
    /// Initial acceleration standard deviation (m/s²).
    pub initial_sigma_a: f64,
}

impl Default for KalmanParams {
    fn default() -> Self {
        Self {
            sigma_a: 10.0,
            sigma_z: 0.01,
            tau: 0.1,
            initial_sigma_v: 0.5,
            initial_sigma_a: 2.0,
        }
    }
}

/// One axis: state (x, v, a) and covariance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisFilter {
    x: [f64; 3],
    p: [[f64; 3]; 3],
    params: KalmanParams,
}

fn transition(dt: f64, tau: f64) -> [[f64; 3]; 3] {
    let alpha = (-dt / tau).exp();
    [[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, alpha]]
}

fn mat_mul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    r
}

fn transpose(a: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = a[j][i];
        }
    }
    r
}

impl AxisFilter {
    /// Starts at measurement `z` with zero velocity and acceleration.
    pub fn new(z: f64, params: KalmanParams) -> Self {
        let mut p = [[0.0; 3]; 3];
        p[0][0] = params.sigma_z * params.sigma_z;
        p[1][1] = params.initial_sigma_v * params.initial_sigma_v;
        p[2][2] = params.initial_sigma_a * params.initial_sigma_a;
        Self {
            x: [z, 0.0, 0.0],
            p,
            params,
        }
    }

    /// Predicts `dt` seconds forward and fuses measurement `z`.
    pub fn step(&mut self, dt: f64, z: f64) {
        let dt = if dt.is_finite() { dt.max(0.0) } else { 0.0 };
        let f = transition(dt, self.params.tau);
        let alpha = f[2][2];
        let q = (self.params.sigma_a * (1.0 - alpha) * (1.0 - alpha)).powi(2);
        let x = self.x;
        self.x = [
            f[0][0] * x[0] + f[0][1] * x[1] + f[0][2] * x[2],
            f[1][1] * x[1] + f[1][2] * x[2],
            f[2][2] * x[2],
        ];
        let mut p = mat_mul(&mat_mul(&f, &self.p), &transpose(&f));
        p[2][2] += q;
        // Update with H = [1 0 0].
        let s = p[0][0] + self.params.sigma_z * self.params.sigma_z;
        let k = [p[0][0] / s, p[1][0] / s, p[2][0] / s];
        let y = z - self.x[0];
        for i in 0..3 {
            self.x[i] += k[i] * y;
        }
        let row0 = p[0];
        for i in 0..3 {
            for j in 0..3 {
                p[i][j] -= k[i] * row0[j];
            }
        }
        self.p = p;
    }

    /// Position predicted `horizon` seconds ahead (first row of F(horizon)·x).
    pub fn predict(&self, horizon: f64) -> f64 {
        let f = transition(horizon, self.params.tau);
        f[0][0] * self.x[0] + f[0][1] * self.x[1] + f[0][2] * self.x[2]
    }

    /// Current state (x, v, a).
    pub fn state(&self) -> [f64; 3] {
        self.x
    }
}

/// Three axis filters for a 3-D position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PositionPredictor {
    axes: [AxisFilter; 3],
}

impl PositionPredictor {
    /// Starts at `p`.
    pub fn new(p: Vec3, params: KalmanParams) -> Self {
        Self {
            axes: [
                AxisFilter::new(p.x, params),
                AxisFilter::new(p.y, params),
                AxisFilter::new(p.z, params),
            ],
        }
    }
    /// Fuses a measurement taken `dt` seconds after the previous one.
    pub fn step(&mut self, dt: f64, p: Vec3) {
        self.axes[0].step(dt, p.x);
        self.axes[1].step(dt, p.y);
        self.axes[2].step(dt, p.z);
    }
    /// Position `horizon` seconds ahead.
    pub fn predict(&self, horizon: f64) -> Vec3 {
        Vec3::new(
            self.axes[0].predict(horizon),
            self.axes[1].predict(horizon),
            self.axes[2].predict(horizon),
        )
    }
}

/// Two-frame denoising of the displayed pose: small changes are blended 50/50 with the previous display,
/// large ones are shown at once (HoloFace: < 5 mm and < 4°). Rotation is blended on quaternions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Denoiser {
    /// Position change below which the display blends (metres).
    pub max_blend_distance: f64,
    /// Rotation change below which the display blends (radians).
    pub max_blend_angle: f64,
    last: Option<(Vec3, Quat)>,
}

impl Default for Denoiser {
    fn default() -> Self {
        Self {
            max_blend_distance: 0.005,
            max_blend_angle: 4f64.to_radians(),
            last: None,
        }
    }
}

impl Denoiser {
    /// Returns the pose to display for a new target pose.
    pub fn apply(&mut self, position: Vec3, rotation: Quat) -> (Vec3, Quat) {
        let out = match self.last {
            Some((lp, lq)) => {
                let p = if (position - lp).norm() < self.max_blend_distance {
                    (position + lp).scale(0.5)
                } else {
                    position
                };
                let q = if rotation.angle_to(lq) < self.max_blend_angle {
                    lq.slerp(rotation, 0.5)
                } else {
                    rotation
                };
                (p, q)
            }
            None => (position, rotation),
        };
        self.last = Some(out);
        out
    }
    /// Forgets the previous display (after a tracking reset).
    pub fn reset(&mut self) {
        self.last = None;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_velocity_is_predicted_ahead() {
        let mut f = AxisFilter::new(0.0, KalmanParams::default());
        let dt = 1.0 / 30.0;
        for i in 1..=90 {
            f.step(dt, 0.3 * dt * i as f64);
        }
        let now = 0.3 * dt * 90.0;
        let ahead = f.predict(0.12);
        assert!(
            (ahead - (now + 0.3 * 0.12)).abs() < 0.01,
            "{ahead} vs {}",
            now + 0.036
        );
        assert!((f.state()[1] - 0.3).abs() < 0.05);
    }

    #[test]
    fn static_measurements_are_smoothed_not_amplified() {
        let mut f = AxisFilter::new(1.0, KalmanParams::default());
        for i in 0..60 {
            let noise = if i % 2 == 0 { 0.004 } else { -0.004 };
            f.step(1.0 / 30.0, 1.0 + noise);
        }
        assert!((f.predict(0.12) - 1.0).abs() < 0.01);
    }

    #[test]
    fn denoiser_blends_small_moves_only() {
        let mut d = Denoiser::default();
        let q = Quat::IDENTITY;
        d.apply(Vec3::new(0.0, 0.0, 1.0), q);
        let (p, _) = d.apply(Vec3::new(0.002, 0.0, 1.0), q);
        assert!((p.x - 0.001).abs() < 1e-12);
        let (p, _) = d.apply(Vec3::new(0.1, 0.0, 1.0), q);
        assert_eq!(p.x, 0.1);
        let turned = Quat::from_axis_angle(Vec3::new(0.0, 2f64.to_radians(), 0.0));
        let (_, r) = d.apply(Vec3::new(0.1, 0.0, 1.0), turned);
        assert!((r.angle_to(q) - 1f64.to_radians()).abs() < 1e-6);
    }
}
