//! The tracker's options as C structs (`HfOptions`, `HfSettings`), their defaults, and their conversion into
//! the facade's `TrackerOptions`.

use std::ffi::c_char;
use std::path::PathBuf;

use holoface_headset_client::errors::RemoteOptionsError;
use holoface_headset_client::options::{AdaptOptions, SteadySettings};
use holoface_headset_client::{AlignerChoice, RemoteOptions, RunningMode, TrackerOptions, defaults};

use crate::registry::{fail, guard};
use crate::{HF_MAX_FACES, HfStatus, check_struct_size, opt_str};

/// Tracker options. Initialise with `hf_options_default`, then override fields. Strings are NUL-terminated
/// UTF-8 paths; NULL means the default: the asset's environment variable (`ORT_DYLIB_PATH`,
/// `HOLOFACE_DETECTOR_MODEL`, `HOLOFACE_KRFWS_MODEL`, `HOLOFACE_CANDIDE`), else its file in the holoface data
/// folder (`$HOLOFACE_HOME`, else `$XDG_DATA_HOME/holoface`, else `~/.local/share/holoface`, filled by
/// `holoface setup`). An app that ships its assets passes their paths here.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct HfOptions {
    /// 0 = independent images (detect every frame), 1 = video / live (track between frames).
    pub mode: u32,
    /// ONNX Runtime shared library. A process loads one: the first tracker's; a later tracker whose library
    /// is another file (NULL: the default one) is refused with `HF_STATUS_ASSET_ERROR` naming the loaded one.
    pub ort_dylib: *const c_char,
    /// BlazeFace ONNX model.
    pub detector_model: *const c_char,
    /// KRFWS model.
    pub krfws_model: *const c_char,
    /// CANDIDE-3 `.wfm`.
    pub candide: *const c_char,
    /// Alignment server `ip:port`; NULL = local KRFWS only.
    pub server: *const c_char,
    /// Server certificate SHA-256 (64 hex digits); required with `server`.
    pub server_fingerprint: *const c_char,
    /// Access token for the server (NULL = empty).
    pub token: *const c_char,
    /// Per-frame deadline for the server, ms.
    pub deadline_ms: u32,
    /// Prediction horizon, ms.
    pub lookahead_ms: f32,
    /// 1 = compensate headset motion when initialising from the previous frame.
    pub motion_compensation: u8,
}

/// The tracker's further settings (`hf_tracker_new_with`): faces, detector, crop encoding and the landmark
/// filter, under the names and with the defaults of Python's `TrackerOptions` and the `holoface` CLI's flags.
/// Versioned by size: set `struct_size = sizeof(HfSettings)`, call `hf_settings_default`, then override fields.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct HfSettings {
    /// `sizeof(HfSettings)`, set by the caller before `hf_settings_default` (a library with another layout
    /// refuses the struct instead of reading or writing past it).
    pub struct_size: u32,
    /// Faces tracked at once, 1..=`HF_MAX_FACES` (default 1).
    pub max_faces: u32,
    /// While some but fewer than `max_faces` faces are tracked, the detector runs every this many frames
    /// (at least 1; default 10).
    pub detect_every: u32,
    /// Detector tiles per side besides the whole frame (1..=32); 0 = automatic: 1 for one face, 3 for several.
    pub detect_tiles: u32,
    /// Crop encoding on the wire: "raw", "png", "jpeg" or "jpeg:Q" (NUL-terminated); NULL = "jpeg:75".
    pub crop_encoding: *const c_char,
    /// 1 = steady the landmarks over time (One-Euro in the face's frame; default), 0 = raw landmarks.
    pub steady: u8,
    /// The local aligner's answers: shape cut-off at rest, Hz (default 1).
    pub steady_shape_cutoff_hz: f64,
    /// The local aligner's answers: shape speed coefficient (default 10).
    pub steady_shape_beta: f64,
    /// The local aligner's answers: placement cut-off at rest, Hz (default 3).
    pub steady_rigid_cutoff_hz: f64,
    /// The local aligner's answers: placement speed coefficient (default 2).
    pub steady_rigid_beta: f64,
    /// The server's answers: shape cut-off at rest, Hz (default 3).
    pub steady_precise_shape_cutoff_hz: f64,
    /// The server's answers: shape speed coefficient (default 10).
    pub steady_precise_shape_beta: f64,
    /// The server's answers: placement cut-off at rest, Hz (default 20).
    pub steady_precise_rigid_cutoff_hz: f64,
    /// The server's answers: placement speed coefficient (default 5).
    pub steady_precise_rigid_beta: f64,
    /// With a server: 1 = while the link is up, learn each tracked person's correction of the local aligner
    /// towards the server's answers and apply it when the link is down (default), 0 = the local aligner as
    /// it is.
    pub adapt: u8,
}

impl HfSettings {
    pub(crate) fn defaults() -> Self {
        let st = SteadySettings::default();
        Self {
            struct_size: size_of::<Self>() as u32,
            max_faces: defaults::MAX_FACES as u32,
            detect_every: defaults::DETECT_EVERY,
            detect_tiles: 0,
            crop_encoding: std::ptr::null(),
            steady: u8::from(st.enabled),
            steady_shape_cutoff_hz: st.shape_cutoff_hz,
            steady_shape_beta: st.shape_beta,
            steady_rigid_cutoff_hz: st.rigid_cutoff_hz,
            steady_rigid_beta: st.rigid_beta,
            steady_precise_shape_cutoff_hz: st.precise_shape_cutoff_hz,
            steady_precise_shape_beta: st.precise_shape_beta,
            steady_precise_rigid_cutoff_hz: st.precise_rigid_cutoff_hz,
            steady_precise_rigid_beta: st.precise_rigid_beta,
            adapt: u8::from(defaults::ADAPT),
        }
    }

    /// Applies the settings (the crop encoding is applied with the remote options).
    pub(crate) fn apply(&self, t: &mut TrackerOptions) -> Result<(), HfStatus> {
        if self.max_faces == 0 || self.max_faces as usize > HF_MAX_FACES {
            return Err(fail(
                HfStatus::InvalidArgument,
                format!("max_faces {} must be within 1..={HF_MAX_FACES}", self.max_faces),
            ));
        }
        t.session.max_faces = self.max_faces as usize;
        t.session.detect_every = self.detect_every;
        if let AlignerChoice::Remote(r) = &mut t.aligner {
            r.adapt = (self.adapt != 0).then(AdaptOptions::default);
        }
        t.detector.tiles = (self.detect_tiles != 0).then_some(self.detect_tiles as usize);
        t.session.steady = SteadySettings {
            enabled: self.steady != 0,
            shape_cutoff_hz: self.steady_shape_cutoff_hz,
            shape_beta: self.steady_shape_beta,
            rigid_cutoff_hz: self.steady_rigid_cutoff_hz,
            rigid_beta: self.steady_rigid_beta,
            precise_shape_cutoff_hz: self.steady_precise_shape_cutoff_hz,
            precise_shape_beta: self.steady_precise_shape_beta,
            precise_rigid_cutoff_hz: self.steady_precise_rigid_cutoff_hz,
            precise_rigid_beta: self.steady_precise_rigid_beta,
        };
        let bad = |e: &dyn std::fmt::Display| fail(HfStatus::InvalidArgument, e.to_string());
        t.session.validate().map_err(|e| bad(&e))?;
        t.detector.validate().map_err(|e| bad(&e))
    }
}

/// Fills `out` with the defaults (video mode, local KRFWS, 33 ms deadline, 120 ms look-ahead): the Rust
/// facade's `TrackerOptions::default()` and `defaults`.
///
/// # Safety
/// `out` is NULL or points to writable memory for one `HfOptions`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn hf_options_default(out: *mut HfOptions) -> HfStatus {
    guard(|| {
        if out.is_null() {
            return fail(HfStatus::NullPointer, "hf_options_default: out is NULL");
        }
        // The facade's defaults, never typed again here (the test below compares them).
        let d = TrackerOptions::default();
        let o = HfOptions {
            mode: match d.mode {
                RunningMode::Image => 0,
                RunningMode::Video | RunningMode::LiveStream => 1,
            },
            ort_dylib: std::ptr::null(),
            detector_model: std::ptr::null(),
            krfws_model: std::ptr::null(),
            candide: std::ptr::null(),
            server: std::ptr::null(),
            server_fingerprint: std::ptr::null(),
            token: std::ptr::null(),
            deadline_ms: u32::try_from(defaults::DEADLINE_MS).unwrap_or(u32::MAX),
            lookahead_ms: (d.session.lookahead_s * 1e3) as f32,
            motion_compensation: u8::from(d.session.motion_compensation),
        };
        // SAFETY: checked non-NULL; the caller guarantees it is writable.
        unsafe { out.write(o) };
        HfStatus::Ok
    })
}

/// Fills `out` with the defaults (one face, detection every 10 frames, automatic tiles, JPEG q75 crops, the
/// landmark filter on with its default settings). Set `out->struct_size = sizeof(HfSettings)` first.
///
/// # Safety
/// `out` is NULL or points to writable memory for one `HfSettings` whose `struct_size` is initialised.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn hf_settings_default(out: *mut HfSettings) -> HfStatus {
    guard(|| {
        if out.is_null() {
            return fail(HfStatus::NullPointer, "hf_settings_default: out is NULL");
        }
        // SAFETY: non-NULL; the caller initialised `struct_size`.
        if let Err(s) = unsafe { check_struct_size("hf_settings_default", "HfSettings", out) } {
            return s;
        }
        // SAFETY: checked non-NULL and of this library's size; the caller guarantees it is writable.
        unsafe { out.write(HfSettings::defaults()) };
        HfStatus::Ok
    })
}

pub(crate) fn options_from(o: &HfOptions, crop_encoding: Option<&str>) -> Result<TrackerOptions, HfStatus> {
    let mode = match o.mode {
        0 => RunningMode::Image,
        1 => RunningMode::Video,
        m => {
            return Err(fail(
                HfStatus::InvalidArgument,
                format!("mode {m}: use 0 (images) or 1 (video)"),
            ));
        }
    };
    let mut t = TrackerOptions {
        mode,
        ..TrackerOptions::default()
    };
    // SAFETY (all opt_str calls): the C API documents these as NULL or NUL-terminated strings.
    let path = |p, what| unsafe { opt_str(p, what) }.map(|s| s.map(PathBuf::from));
    if let Some(p) = path(o.ort_dylib, "ort_dylib")? {
        t.assets.ort_dylib = p;
    }
    if let Some(p) = path(o.detector_model, "detector_model")? {
        t.assets.detector = p;
    }
    if let Some(p) = path(o.krfws_model, "krfws_model")? {
        t.assets.krfws = p;
    }
    if let Some(p) = path(o.candide, "candide")? {
        t.assets.candide = p;
    }
    t.session.lookahead_s = f64::from(o.lookahead_ms) / 1e3;
    t.session.motion_compensation = o.motion_compensation != 0;
    t.session
        .validate()
        .map_err(|e| fail(HfStatus::InvalidArgument, e.to_string()))?;
    // SAFETY: as above.
    if let Some(server) = unsafe { opt_str(o.server, "server") }? {
        // SAFETY: as above.
        let fingerprint = unsafe { opt_str(o.server_fingerprint, "server_fingerprint") }?;
        // SAFETY: as above.
        let token = unsafe { opt_str(o.token, "token") }?.unwrap_or_default();
        let remote = RemoteOptions::parse(
            &server,
            fingerprint.as_deref(),
            &token,
            u64::from(o.deadline_ms),
            crop_encoding,
        )
        .map_err(|e| {
            // The same checks as every front end, named as this ABI's fields are.
            let msg = match e {
                RemoteOptionsError::MissingFingerprint => {
                    "server_fingerprint is required with server".to_owned()
                }
                RemoteOptionsError::Fingerprint(why) => format!("server_fingerprint: {why}"),
                other => other.to_string(),
            };
            fail(HfStatus::InvalidArgument, msg)
        })?;
        t.aligner = AlignerChoice::Remote(remote);
    }
    Ok(t)
}
