//! World pose of the head, expression attributes, and headset-motion-compensated landmark initialisation.

use crate::blendshapes::{Blendshape, Blendshapes};
use crate::camera::Intrinsics;
use crate::candide::FitResult;
use crate::geometry::Point2;
use crate::math3::{Mat3, Pose, Quat, Vec3};

/// Head pose in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WorldPose {
    /// Head origin in the world frame (metres).
    pub position: Vec3,
    /// Head-to-world rotation.
    pub rotation: Quat,
    /// Head rotation relative to the line of sight from the head to the camera: identity when the face looks
    /// straight at the camera, wherever it is in the image (HoloFace's lookAt decomposition).
    pub rotation_rel_line_of_sight: Quat,
}

/// The "look-at" rotation of a head at `position` (camera frame) facing the camera: its z axis points away
/// from the camera along the line of sight, its y axis is as close to the camera's y (down) as possible.
pub fn line_of_sight_rotation(position: Vec3) -> Mat3 {
    let z = position.normalized().unwrap_or(Vec3::new(0.0, 0.0, 1.0));
    let down = Vec3::new(0.0, 1.0, 0.0);
    let x = down.cross(z).normalized().unwrap_or(Vec3::new(1.0, 0.0, 0.0));
    let y = z.cross(x);
    Mat3::from_cols(x, y, z)
}

/// Converts a camera-frame fit into a world pose with the camera-to-world transform of the frame.
pub fn world_pose(fit: &FitResult, world_from_camera: &Pose) -> WorldPose {
    let r_cam = fit.rotation.to_mat3();
    let los = line_of_sight_rotation(fit.translation);
    WorldPose {
        position: world_from_camera.apply(fit.translation),
        rotation: Quat::from_mat3(&(world_from_camera.rotation * r_cam)),
        rotation_rel_line_of_sight: Quat::from_mat3(&(los.transpose() * r_cam)),
    }
}

/// Headset-motion compensation (algorithms.md 3.5): back-projects last frame's landmarks to the head's
/// distance, moves them into the world with last frame's pose, and re-projects them with the current pose.
///
/// `distance` is the camera-to-head distance of the last fit (metres). Points that land behind the new
/// camera keep their old position. Returns the number of points re-projected.
pub fn compensate_headset_motion(
    previous: &[Point2],
    k_prev: &Intrinsics,
    world_from_prev_camera: &Pose,
    k_now: &Intrinsics,
    world_from_camera: &Pose,
    distance: f64,
    out: &mut [Point2],
) -> usize {
    let camera_from_world = world_from_camera.inverse();
    let mut moved = 0;
    for (o, p) in out.iter_mut().zip(previous) {
        let world = world_from_prev_camera.apply(k_prev.ray(*p).scale(distance));
        match k_now.project(camera_from_world.apply(world)) {
            Some(q) => {
                *o = q;
                moved += 1;
            }
            None => *o = *p,
        }
    }
    moved
}

/// Binary facial attributes derived from the blendshape coefficients.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Attributes {
    /// `mouthSmileLeft/Right` (their mean) above its threshold.
    pub smile: bool,
    /// `browInnerUp` or `browOuterUpLeft/Right` (their mean) above its threshold.
    pub brows_raised: bool,
    /// `jawOpen` above its threshold.
    pub mouth_open: bool,
}

/// Thresholds and hysteresis for [`Attributes`], on the coefficients (each in [0, 1]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AttributeThresholds {
    /// Smile coefficient that turns `smile` on.
    pub smile: f64,
    /// Brow-raise coefficient that turns `brows_raised` on.
    pub brows_raised: f64,
    /// `jawOpen` that turns `mouth_open` on.
    pub mouth_open: f64,
    /// An attribute turns off only below `threshold − hysteresis`.
    pub hysteresis: f64,
}

impl Default for AttributeThresholds {
    /// Half a full movement for the mouth, a bit more for the brows (their readings at rest on real video
    /// reach 0.3 at the 95th percentile).
    fn default() -> Self {
        Self {
            smile: 0.45,
            brows_raised: 0.45,
            mouth_open: 0.40,
            hysteresis: 0.05,
        }
    }
}

impl AttributeThresholds {
    /// Next attribute state from the blendshape coefficients and the previous state.
    pub fn update(&self, b: &Blendshapes, prev: Attributes) -> Attributes {
        let hyst = |on: bool, value: f64, thr: f64| {
            if on {
                value > thr - self.hysteresis
            } else {
                value > thr
            }
        };
        Attributes {
            mouth_open: hyst(
                prev.mouth_open,
                f64::from(b.get(Blendshape::JawOpen)),
                self.mouth_open,
            ),
            smile: hyst(prev.smile, b.smile(), self.smile),
            brows_raised: hyst(prev.brows_raised, b.brows_raised(), self.brows_raised),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn k() -> Intrinsics {
        Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        }
    }

    #[test]
    fn compensation_follows_a_headset_turn() {
        // A point at the image centre, 1 m away; the headset turns 5 degrees about y.
        let prev = [Point2::new(320.0, 240.0)];
        let turned = Pose {
            rotation: Mat3::rot_y(5f64.to_radians()),
            translation: Vec3::default(),
        };
        let mut out = [Point2::default()];
        assert_eq!(
            compensate_headset_motion(&prev, &k(), &Pose::IDENTITY, &k(), &turned, 1.0, &mut out),
            1
        );
        // The camera turned right (towards +x), so the world point moves left in the image.
        let expect = 320.0 - 500.0 * 5f64.to_radians().tan();
        assert!((f64::from(out[0].x) - expect).abs() < 1e-3, "{:?}", out[0]);
        assert!((out[0].y - 240.0).abs() < 1e-3);
    }

    #[test]
    fn line_of_sight_is_identity_on_the_optical_axis() {
        let r = line_of_sight_rotation(Vec3::new(0.0, 0.0, 2.0));
        assert!(r.angle() < 1e-12);
        let off = line_of_sight_rotation(Vec3::new(0.5, 0.0, 1.0));
        assert!((off.angle() - 0.5f64.atan()).abs() < 1e-9);
    }

    #[test]
    fn attributes_have_hysteresis() {
        let t = AttributeThresholds::default();
        let coef = |jaw: f32, brow: f32| {
            let mut b = Blendshapes::default();
            for (s, v) in [(Blendshape::JawOpen, jaw), (Blendshape::BrowInnerUp, brow)] {
                let i = Blendshape::ALL.iter().position(|&x| x == s).unwrap_or(0);
                b.0[i] = v;
            }
            b
        };
        let a = t.update(&coef(0.5, 0.5), Attributes::default());
        assert!(a.mouth_open && a.brows_raised && !a.smile);
        let b = t.update(&coef(0.37, 0.42), a);
        assert!(
            b.mouth_open && b.brows_raised,
            "stays on inside the hysteresis band"
        );
        let c = t.update(&coef(0.37, 0.42), Attributes::default());
        assert!(
            !c.mouth_open && !c.brows_raised,
            "does not turn on below the threshold"
        );
    }
}
