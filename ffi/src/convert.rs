//! What the facade returns, as the C ABI's plain structs: a frame's result, every face of it, the link's state.

use std::ffi::c_char;

use holoface_headset_client::link::{FailureKind, LinkInfo, LinkState};
use holoface_headset_client::results::AnsweredBy;
use holoface_headset_client::{FaceResult, NoFaceReason};

use crate::{
    HF_BLENDSHAPES, HF_MAX_FACES, HfAnsweredBy, HfFace, HfFaces, HfLinkFailure, HfLinkState, HfLinkStatus,
    HfResult,
};

pub(crate) fn link_failure(kind: Option<FailureKind>) -> HfLinkFailure {
    match kind {
        None => HfLinkFailure::None,
        Some(FailureKind::Unreachable) => HfLinkFailure::Unreachable,
        Some(FailureKind::Unauthorized) => HfLinkFailure::Unauthorized,
        Some(FailureKind::CertificateMismatch) => HfLinkFailure::CertificateMismatch,
        Some(FailureKind::BadVersion) => HfLinkFailure::BadVersion,
        Some(FailureKind::ServerFull) => HfLinkFailure::ServerFull,
        Some(FailureKind::ShuttingDown) => HfLinkFailure::ShuttingDown,
        Some(FailureKind::ConnectionLost) => HfLinkFailure::ConnectionLost,
        Some(FailureKind::Protocol) => HfLinkFailure::Protocol,
        Some(_) => HfLinkFailure::Local,
    }
}

pub(crate) fn link_status(status: Option<LinkInfo>) -> HfLinkStatus {
    let mut out = HfLinkStatus {
        state: HfLinkState::Local,
        failure: HfLinkFailure::None,
        message: [0; 256],
    };
    let Some(status) = status else { return out };
    let failure = status.failure().cloned();
    (out.state, out.failure) = match status.state() {
        LinkState::Connecting => (HfLinkState::Connecting, HfLinkFailure::None),
        LinkState::Up => (HfLinkState::Up, HfLinkFailure::None),
        LinkState::Retrying(k) => (HfLinkState::Retrying, link_failure(Some(k))),
        LinkState::Failed(k) => (HfLinkState::Failed, link_failure(Some(k))),
        LinkState::Stopped => (HfLinkState::Stopped, HfLinkFailure::None),
    };
    if let Some(f) = failure.filter(|_| out.failure != HfLinkFailure::None) {
        let text = f.to_string().replace('\0', " ");
        // Truncate on a character boundary, keeping the NUL.
        let mut end = text.len().min(out.message.len() - 1);
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        for (o, b) in out.message.iter_mut().zip(&text.as_bytes()[..end]) {
            *o = *b as c_char;
        }
    }
    out
}

pub(crate) fn answered_by_c(a: Option<AnsweredBy>) -> HfAnsweredBy {
    match a {
        None => HfAnsweredBy::None,
        Some(AnsweredBy::RemoteDan) => HfAnsweredBy::RemoteDan,
        Some(AnsweredBy::Krfws) => HfAnsweredBy::Krfws,
        Some(AnsweredBy::LocalDan) => HfAnsweredBy::LocalDan,
    }
}

pub(crate) fn no_face_code(reason: NoFaceReason) -> u32 {
    match reason {
        NoFaceReason::NotDetected => 1,
        NoFaceReason::Rejected => 2,
        NoFaceReason::NoAnswer => 3,
        _ => 4,
    }
}

/// An `HfResult` without a face.
pub(crate) fn empty_result(answered_by: HfAnsweredBy, no_face_reason: u32) -> HfResult {
    HfResult {
        has_face: 0,
        answered_by,
        no_face_reason,
        landmarks_px: [0.0; 136],
        camera_translation_m: [0.0; 3],
        camera_rotation_wxyz: [1.0, 0.0, 0.0, 0.0],
        world_position_m: [0.0; 3],
        world_rotation_wxyz: [1.0, 0.0, 0.0, 0.0],
        predicted_position_m: [0.0; 3],
        display_position_m: [0.0; 3],
        display_rotation_wxyz: [1.0, 0.0, 0.0, 0.0],
        weights: [0.0; 5],
        smile: 0,
        brows_raised: 0,
        mouth_open: 0,
        raw_landmarks_px: [0.0; 136],
        blendshapes: [0.0; HF_BLENDSHAPES],
        adapt_pairs: 0,
        adapt_corrected: 0,
        adapt_correction: 0.0,
    }
}

pub(crate) fn face_to_c(u: &FaceResult, answered_by: HfAnsweredBy) -> HfResult {
    let q = |q: holoface_headset_client::geometry::Quat| [q.w, q.x, q.y, q.z];
    let mut c = empty_result(answered_by, 0);
    c.has_face = 1;
    for (i, (p, r)) in u.landmarks.iter().zip(&u.raw_landmarks).enumerate() {
        c.landmarks_px[2 * i] = p.x;
        c.landmarks_px[2 * i + 1] = p.y;
        c.raw_landmarks_px[2 * i] = r.x;
        c.raw_landmarks_px[2 * i + 1] = r.y;
    }
    c.camera_translation_m = u.fit.translation.to_array();
    c.camera_rotation_wxyz = q(u.fit.rotation);
    c.world_position_m = u.world.position.to_array();
    c.world_rotation_wxyz = q(u.world.rotation);
    c.predicted_position_m = u.predicted_position.to_array();
    c.display_position_m = u.display.0.to_array();
    c.display_rotation_wxyz = q(u.display.1);
    c.weights = u.expression.0;
    c.blendshapes = u.blendshapes.0;
    c.smile = u8::from(u.attributes.smile);
    c.brows_raised = u8::from(u.attributes.brows_raised);
    c.mouth_open = u8::from(u.attributes.mouth_open);
    if let Some(a) = u.adaptation {
        c.adapt_pairs = a.pairs;
        c.adapt_corrected = u8::from(a.corrected);
        c.adapt_correction = a.correction;
    }
    c
}

pub(crate) fn to_c(r: &holoface_headset_client::FrameResult) -> HfResult {
    let by = answered_by_c(r.answered_by);
    match (r.face(), r.no_face) {
        (Some(u), _) => face_to_c(u, by),
        (None, reason) => empty_result(by, no_face_code(reason.unwrap_or(NoFaceReason::NotDetected))),
    }
}

pub(crate) fn faces_to_c(r: &holoface_headset_client::FrameResult, struct_size: u32) -> HfFaces {
    let none = HfFace {
        id: 0,
        face: empty_result(HfAnsweredBy::None, 0),
    };
    let mut out = HfFaces {
        struct_size,
        count: 0,
        no_face_reason: 0,
        faces: [none; HF_MAX_FACES],
    };
    for (slot, f) in out.faces.iter_mut().zip(&r.faces) {
        *slot = HfFace {
            id: f.id,
            face: face_to_c(f, answered_by_c(Some(f.answered_by))),
        };
    }
    out.count = u32::try_from(r.faces.len().min(HF_MAX_FACES)).unwrap_or(0);
    out.no_face_reason = r.no_face.map_or(0, no_face_code);
    out
}
