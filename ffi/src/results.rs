//! What a call gives back, as C structs: one frame's answer (`HfResult`), every face of a frame (`HfFaces`), the
//! link's state (`HfLinkStatus`), and the blendshapes' names.

use std::ffi::{CString, c_char};

use crate::HfAnsweredBy;

/// One frame's answer. Landmarks: image pixels. `camera_*`: head in the camera frame (x right, y down,
/// z forward, metres). `world_*`, `predicted_*`, `display_*`: the world frame of the poses you pass.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct HfResult {
    /// 1 when a face was tracked in this frame.
    pub has_face: u8,
    /// Who aligned it.
    pub answered_by: HfAnsweredBy,
    /// Without a face: 1 not detected, 2 rejected by the aligner's own check, 3 no aligner answered,
    /// 4 the 3D fit failed; 0 with a face.
    pub no_face_reason: u32,
    /// 68 landmarks (x, y) in image pixels, steadied over time (One-Euro in the face's frame): what to draw.
    pub landmarks_px: [f32; 136],
    /// Head translation in the camera frame, metres.
    pub camera_translation_m: [f64; 3],
    /// Head rotation in the camera frame (w, x, y, z).
    pub camera_rotation_wxyz: [f64; 4],
    /// Head position in the world, metres.
    pub world_position_m: [f64; 3],
    /// Head rotation in the world (w, x, y, z).
    pub world_rotation_wxyz: [f64; 4],
    /// World position predicted `lookahead_ms` ahead (Kalman).
    pub predicted_position_m: [f64; 3],
    /// Position to render (prediction after denoising).
    pub display_position_m: [f64; 3],
    /// Rotation to render (denoised, w, x, y, z).
    pub display_rotation_wxyz: [f64; 4],
    /// HoloFace's expression weights (jaw drop, lip stretcher, brow lowerer, lip-corner depressor, eyes closed),
    /// derived from `blendshapes`, each in [-1, 1] (negative brow lowerer: raised; negative lip-corner
    /// depressor: a smile).
    pub weights: [f64; 5],
    /// Attributes (0/1).
    pub smile: u8,
    /// Brows raised (0/1).
    pub brows_raised: u8,
    /// Mouth open (0/1).
    pub mouth_open: u8,
    /// The aligner's own landmarks for this frame (x, y), unfiltered, image pixels.
    pub raw_landmarks_px: [f32; 136],
    /// ARKit-named blendshape coefficients in [0, 1], `HF_BLENDSHAPES` of them; `hf_blendshape_name(i)` names
    /// slot `i` (against this person's neutral, calibrated on the first second of tracking).
    pub blendshapes: [f32; HF_BLENDSHAPES],
    /// With a server and the adaptation on (`HfSettings.adapt`): pairs of local and server answers learnt for
    /// this face so far; 0 otherwise.
    pub adapt_pairs: u32,
    /// 1 when these landmarks are the local aligner's answer corrected by what it learnt.
    pub adapt_corrected: u8,
    /// The size of this face's correction: its mean length over the 51 inner points, in eye distances.
    pub adapt_correction: f32,
}

/// How many blendshape coefficients an `HfResult` carries.
pub const HF_BLENDSHAPES: usize = 39;

/// ARKit's name of blendshape slot `i` (`"jawOpen"`, `"eyeBlinkLeft"`, ...): a static NUL-terminated string,
/// or NULL when `i >= HF_BLENDSHAPES`.
#[unsafe(no_mangle)]
pub extern "C" fn hf_blendshape_name(i: u32) -> *const c_char {
    static NAMES: std::sync::OnceLock<Vec<CString>> = std::sync::OnceLock::new();
    let names = NAMES.get_or_init(|| {
        holoface_headset_client::results::Blendshape::ALL
            .iter()
            .filter_map(|b| CString::new(b.arkit_name()).ok())
            .collect()
    });
    names.get(i as usize).map_or(std::ptr::null(), |n| n.as_ptr())
}

/// Most faces one `HfFaces` holds (`hf_tracker_new_faces` accepts 1..=`HF_MAX_FACES`).
pub const HF_MAX_FACES: usize = 8;

/// One tracked face of a frame: its stable id and its answer (`face.has_face` is 1).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct HfFace {
    /// The track id: the same for as long as the face is tracked, never reused by this tracker.
    pub id: u32,
    /// The face (landmarks, poses, weights, attributes, who answered).
    pub face: HfResult,
}

/// Every face of one frame (`hf_tracker_process_faces`). Versioned by size: set `struct_size` to
/// `sizeof(HfFaces)` before the call; a library built with another layout refuses it
/// (`HF_STATUS_INVALID_ARGUMENT`) instead of writing past it.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct HfFaces {
    /// `sizeof(HfFaces)`, set by the caller.
    pub struct_size: u32,
    /// Faces in `faces`, oldest track first.
    pub count: u32,
    /// With no face: 1 not detected, 2 rejected, 3 no aligner answered, 4 the 3D fit failed; else 0.
    pub no_face_reason: u32,
    /// The faces; entries from `count` on are zeroed.
    pub faces: [HfFace; HF_MAX_FACES],
}

/// Where the link to the alignment server stands.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HfLinkState {
    /// No server configured: the local aligner answers every frame.
    Local = 0,
    /// First connection attempt under way.
    Connecting = 1,
    /// Connected: frames go to the server.
    Up = 2,
    /// Down (see `failure`); retrying with backoff, frames answered locally meanwhile.
    Retrying = 3,
    /// Gave up (see `failure`: wrong token, certificate mismatch, protocol version); frames answered locally
    /// until the tracker is recreated with a fixed configuration.
    Failed = 4,
    /// The link was shut down.
    Stopped = 5,
}

/// Why the link is not up.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum HfLinkFailure {
    /// No failure.
    None = 0,
    /// No answer from the server's address.
    Unreachable = 1,
    /// The server rejected the token.
    Unauthorized = 2,
    /// The server's certificate does not match `server_fingerprint`.
    CertificateMismatch = 3,
    /// The server speaks another protocol version.
    BadVersion = 4,
    /// The server is at its client limit.
    ServerFull = 5,
    /// The server is shutting down.
    ShuttingDown = 6,
    /// An established connection broke.
    ConnectionLost = 7,
    /// The server broke the protocol.
    Protocol = 8,
    /// A failure on this device (socket, TLS set-up).
    Local = 9,
}

/// The link's status: state, failure kind, and the failure message (NUL-terminated UTF-8, truncated).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct HfLinkStatus {
    /// State.
    pub state: HfLinkState,
    /// Why it is not up (`HF_LINK_FAILURE_NONE` when up or never failed).
    pub failure: HfLinkFailure,
    /// The failure message for logs; empty when there is none.
    pub message: [c_char; 256],
}
