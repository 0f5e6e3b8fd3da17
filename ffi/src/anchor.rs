//! Objects anchored on a face, for an engine to render (`hf_tracker_anchor`): the arithmetic of
//! `holoface_models::anchor`, which the tools' renderer uses too, through the facade's `anchor` module.

use crate::{HfResult, HfStatus, HfTracker, fail, guard, lock};

/// A point of the fitted CANDIDE-3 head that an object is anchored at (`hf_tracker_anchor`'s `point`).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HfAnchorPoint {
    /// The head frame's origin.
    Origin = 0,
    /// Midway between the eye centres (glasses).
    Eyes = 1,
    /// The nose bridge.
    NoseBridge = 2,
    /// The top of the forehead (a hat).
    HeadTop = 3,
    /// The mouth's centre.
    Mouth = 4,
}

/// Where an object anchored on a face sits in the world: the face's display pose (`display_position_m`,
/// `display_rotation_wxyz`: predicted for display) after the anchor, which is the head point `point` (an
/// `HfAnchorPoint` value) of the tracker's CANDIDE-3 model, moved by `offset_m` and turned by `rotation_deg`
/// (about the head's x, then y, then z), both in the head frame (x right, y down, z into the head; metres,
/// degrees). Writes the object-to-world transform as a row-major 4x4 (the layout of the camera-to-world poses
/// passed in) to `out_world_from_object`. The tools' renderer (`holoface track --augment`) places its objects
/// with the same arithmetic; `ffi/unity/README.md` places its scene with this call. A call on the tracker in
/// flight on another thread finishes first.
///
/// # Safety
/// `tracker` is any pointer (checked); `face` is NULL or points to one readable `HfResult`; `offset_m` and
/// `rotation_deg` are NULL or point to 3 readable doubles; `out_world_from_object` is NULL or points to 16
/// writable floats.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn hf_tracker_anchor(
    tracker: *const HfTracker,
    face: *const HfResult,
    point: u32,
    offset_m: *const f64,
    rotation_deg: *const f64,
    out_world_from_object: *mut f32,
) -> HfStatus {
    use holoface_headset_client::anchor::{Anchor, AnchorPoint};
    use holoface_headset_client::geometry::{Quat, Vec3};
    guard(|| {
        let tracker = match crate::tracker("hf_tracker_anchor", tracker) {
            Ok(t) => t,
            Err(status) => return status,
        };
        if face.is_null() || offset_m.is_null() || rotation_deg.is_null() || out_world_from_object.is_null() {
            return fail(
                HfStatus::NullPointer,
                "hf_tracker_anchor: face, offset_m, rotation_deg and out_world_from_object must not be NULL",
            );
        }
        // SAFETY: each pointer is non-NULL and readable for its length per the contract.
        let (face, offset, rotation) = unsafe {
            (
                face.read(),
                std::ptr::read(offset_m.cast::<[f64; 3]>()),
                std::ptr::read(rotation_deg.cast::<[f64; 3]>()),
            )
        };
        let Some(&point) = AnchorPoint::ALL.get(point as usize) else {
            return fail(
                HfStatus::InvalidArgument,
                format!(
                    "hf_tracker_anchor: point {point} is not an HfAnchorPoint (0..={})",
                    AnchorPoint::ALL.len() - 1
                ),
            );
        };
        if face.has_face != 1 {
            return fail(
                HfStatus::InvalidArgument,
                "hf_tracker_anchor: the result has no face",
            );
        }
        let [w, x, y, z] = face.display_rotation_wxyz;
        let q = Quat { w, x, y, z };
        let norm = (w * w + x * x + y * y + z * z).sqrt();
        let finite = |v: &[f64]| v.iter().all(|c| c.is_finite());
        if !(finite(&offset)
            && finite(&rotation)
            && finite(&face.display_position_m)
            && norm > 0.5
            && norm < 2.0)
        {
            return fail(
                HfStatus::InvalidArgument,
                "hf_tracker_anchor: offset_m, rotation_deg and the face's display pose must be finite, the rotation a unit quaternion",
            );
        }
        let [px, py, pz] = face.display_position_m;
        let head = holoface_headset_client::geometry::head_pose(Vec3::new(px, py, pz), q.normalized());
        let anchor = Anchor::new(point, Vec3::new(offset[0], offset[1], offset[2]), rotation);
        let pose = anchor.world_from_object(lock(&tracker).inner.face_model(), &head);
        let m = pose.to_row_major_4x4();
        // SAFETY: non-NULL and writable for 16 floats per the contract.
        unsafe { std::ptr::copy_nonoverlapping(m.as_ptr(), out_world_from_object, 16) };
        HfStatus::Ok
    })
}
