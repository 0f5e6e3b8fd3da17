//! Objects anchored on a face: where a virtual object (glasses, a hat) sits in the world, given the head's
//! pose. The one definition of an anchor that the tools' renderer, the C ABI and the Unity sample share.
//!
//! An object is attached at a named point of the fitted CANDIDE-3 head ([`AnchorPoint`]), moved by an offset
//! and turned by a rotation, both in the head frame (x: towards the image right of a face looking at the
//! camera, y: down, z: into the head; metres). Its pose in the world is the head's world pose after that
//! attachment: `world_from_object = world_from_head ∘ head_from_object`.

use crate::candide::FaceModel;
use crate::math3::{Mat3, Pose, Quat, Vec3};

/// A named point of the CANDIDE-3 head (its neutral shape), in the head frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AnchorPoint {
    /// The head frame's origin.
    Origin,
    /// Midway between the eye centres (where glasses are centred).
    Eyes,
    /// The nose bridge (CANDIDE-3 vertex 94, landmark 28).
    NoseBridge,
    /// The top of the forehead (the mesh's highest vertex; a hat's band sits above and behind it).
    HeadTop,
    /// The mouth's centre: the mean of the mouth corners and the lips' middles.
    Mouth,
}

impl AnchorPoint {
    /// Every point, in the C ABI's numbering (`HOLOFACE_ANCHOR_*`, 0 = origin).
    pub const ALL: [Self; 5] = [
        Self::Origin,
        Self::Eyes,
        Self::NoseBridge,
        Self::HeadTop,
        Self::Mouth,
    ];

    /// The point's name in scene files.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Origin => "origin",
            Self::Eyes => "eyes",
            Self::NoseBridge => "nose-bridge",
            Self::HeadTop => "head-top",
            Self::Mouth => "mouth",
        }
    }

    /// The point named `name` ([`Self::name`]).
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|p| p.name() == name)
    }

    /// Where the point is on `model`'s neutral head, head frame, metres.
    pub fn position(self, model: &FaceModel) -> Vec3 {
        let mean = |ids: &[usize]| {
            let found: Vec<Vec3> = ids.iter().filter_map(|&v| model.mesh.get(v).copied()).collect();
            let n = found.len().max(1) as f64;
            found
                .into_iter()
                .fold(Vec3::default(), |a, p| a + p)
                .scale(1.0 / n)
        };
        match self {
            Self::Origin => Vec3::default(),
            Self::Eyes => mean(&crate::candide::EYE_VERTICES),
            Self::NoseBridge => mean(&[94]),
            Self::HeadTop => model
                .mesh
                .iter()
                .copied()
                .min_by(|a, b| a.y.total_cmp(&b.y))
                .unwrap_or_default(),
            // Mouth corners 64 and 31, upper lip 7, lower lip 8 (landmarks 48, 54, 51, 57).
            Self::Mouth => mean(&[64, 31, 7, 8]),
        }
    }
}

/// Where an object is attached to the head: a point, then an offset and a rotation in the head frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Anchor {
    /// The head point.
    pub point: AnchorPoint,
    /// Offset from the point, head frame, metres.
    pub offset: Vec3,
    /// The object's rotation in the head frame (object → head).
    pub rotation: Mat3,
}

impl Anchor {
    /// An anchor at `point`, moved by `offset` (metres) and turned by the rotations about the head's x, y and
    /// z axes given in degrees (applied in that order: pitch, then yaw, then roll).
    pub fn new(point: AnchorPoint, offset: Vec3, rotation_deg: [f64; 3]) -> Self {
        let [rx, ry, rz] = rotation_deg.map(f64::to_radians);
        Self {
            point,
            offset,
            rotation: Mat3::rot_z(rz) * Mat3::rot_y(ry) * Mat3::rot_x(rx),
        }
    }

    /// The object's frame in the head frame (object → head).
    pub fn head_from_object(&self, model: &FaceModel) -> Pose {
        Pose {
            rotation: self.rotation,
            translation: self.point.position(model) + self.offset,
        }
    }

    /// The object's frame in the world (object → world) for a head at `world_from_head`.
    pub fn world_from_object(&self, model: &FaceModel, world_from_head: &Pose) -> Pose {
        world_from_head.after(&self.head_from_object(model))
    }
}

/// A head pose (position, head → world rotation) as a transform.
pub fn head_pose(position: Vec3, rotation: Quat) -> Pose {
    Pose {
        rotation: rotation.to_mat3(),
        translation: position,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A model whose mesh is a few points, for the named points' arithmetic.
    fn tiny_model() -> FaceModel {
        let mut mesh = vec![Vec3::new(0.0, 0.0, 0.0); 113];
        mesh[0] = Vec3::new(0.0, -0.11, 0.04);
        for (k, &v) in crate::candide::EYE_VERTICES.iter().enumerate() {
            let side = if k < 6 { -0.0315 } else { 0.0315 };
            mesh[v] = Vec3::new(side, -0.016, 0.004);
        }
        mesh[94] = Vec3::new(0.0, -0.01, -0.01);
        mesh[64] = Vec3::new(-0.025, 0.045, 0.0);
        mesh[31] = Vec3::new(0.025, 0.045, 0.0);
        mesh[7] = Vec3::new(0.0, 0.04, -0.01);
        mesh[8] = Vec3::new(0.0, 0.05, -0.01);
        FaceModel {
            points: [Vec3::default(); crate::candide::N_CORR],
            units: [[Vec3::default(); crate::candide::N_CORR]; crate::candide::N_UNITS],
            mesh_units: vec![[Vec3::default(); crate::candide::N_UNITS]; 113],
            mesh,
            faces: Vec::new(),
            scale: 1.0,
        }
    }

    fn close(a: Vec3, b: Vec3) -> bool {
        (a - b).norm() < 1e-12
    }

    #[test]
    fn named_points_are_where_the_mesh_puts_them() {
        let m = tiny_model();
        assert!(close(
            AnchorPoint::Eyes.position(&m),
            Vec3::new(0.0, -0.016, 0.004)
        ));
        assert!(close(
            AnchorPoint::HeadTop.position(&m),
            Vec3::new(0.0, -0.11, 0.04)
        ));
        assert!(close(
            AnchorPoint::NoseBridge.position(&m),
            Vec3::new(0.0, -0.01, -0.01)
        ));
        assert!(close(
            AnchorPoint::Mouth.position(&m),
            Vec3::new(0.0, 0.045, -0.005)
        ));
        assert!(close(AnchorPoint::Origin.position(&m), Vec3::default()));
        for p in AnchorPoint::ALL {
            assert_eq!(AnchorPoint::from_name(p.name()), Some(p));
        }
        assert_eq!(AnchorPoint::from_name("hat"), None);
    }

    #[test]
    fn an_object_follows_the_head_through_the_world() {
        let m = tiny_model();
        // Glasses 18 mm in front of the eyes, turned 10 degrees down.
        let a = Anchor::new(AnchorPoint::Eyes, Vec3::new(0.0, 0.0, -0.018), [-10.0, 0.0, 0.0]);
        // A head 1 m in front of the world origin, turned 90 degrees about the vertical.
        let head = Pose {
            rotation: Mat3::rot_y(std::f64::consts::FRAC_PI_2),
            translation: Vec3::new(0.0, 0.0, 1.0),
        };
        let o = a.world_from_object(&m, &head);
        // The turn takes the head's z (into the head) to the world's x: the glasses' centre, at head-frame
        // (0, -0.016, -0.014), lands 14 mm along the world's -x from the head.
        assert!(
            close(o.translation, Vec3::new(-0.014, -0.016, 1.0)),
            "{:?}",
            o.translation
        );
        // The object's rotation is the head's after the anchor's own.
        let want = head.rotation * Mat3::rot_x(-10f64.to_radians());
        for (r, w) in o.rotation.0.iter().zip(want.0.iter()) {
            for (x, y) in r.iter().zip(w) {
                assert!((x - y).abs() < 1e-12);
            }
        }
        // And the head pose from a position and quaternion is the same transform.
        let q = Quat::from_mat3(&head.rotation);
        let hp = head_pose(head.translation, q);
        assert!(close(
            hp.apply(Vec3::new(0.1, 0.2, 0.3)),
            head.apply(Vec3::new(0.1, 0.2, 0.3))
        ));
    }
}
