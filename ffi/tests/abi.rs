//! The C ABI's promises, driven as a C caller would, with real trackers (assets from the environment, as
//! `make test` sets it). Issue 68's probe: with addresses for handles a new tracker got a freed one's address
//! within 8-44 create/free cycles, and the stale handle then drove (and freed) the new tracker; one absurd
//! timestamp locked a tracker for good; a second `ort_dylib` was silently ignored; a pose 1e30 m away passed.
#![allow(unsafe_code, clippy::unwrap_used)]

use std::collections::HashMap;
use std::ffi::CStr;
use std::mem::MaybeUninit;
use std::sync::{PoisonError, RwLock, RwLockReadGuard};

use holoface::{
    HfAnchorPoint, HfCamera, HfOptions, HfResult, HfStatus, HfTracker, hf_last_error, hf_options_default,
    hf_tracker_anchor, hf_tracker_free, hf_tracker_link_status, hf_tracker_new, hf_tracker_process,
    hf_tracker_process_buf,
};

const SIDE: u32 = 64;

/// The frames' camera: a 64-px image, principal point at its centre.
const CAMERA: HfCamera = HfCamera {
    fx: 60.0,
    fy: 60.0,
    cx: 32.0,
    cy: 32.0,
};

/// The handle registry is one per process, and `cargo test` (as `make arm64-test` runs it) runs these tests as
/// threads of one process: the property test forges small handle values that another test's live tracker can
/// hold, so it holds this lock exclusively and every other test holds it shared.
static REGISTRY: RwLock<()> = RwLock::new(());

fn shared_registry() -> RwLockReadGuard<'static, ()> {
    REGISTRY.read().unwrap_or_else(PoisonError::into_inner)
}

/// Under qemu (`make arm64-test` sets `HOLOFACE_EMULATED`).
fn emulated() -> bool {
    std::env::var_os("HOLOFACE_EMULATED").is_some()
}

fn last_error() -> String {
    // SAFETY: hf_last_error returns a valid NUL-terminated string.
    unsafe { CStr::from_ptr(hf_last_error()) }
        .to_string_lossy()
        .into_owned()
}

/// A local tracker with the default options (assets from the environment).
fn new_tracker() -> *mut HfTracker {
    let mut t = std::ptr::null_mut();
    // SAFETY: NULL options are the defaults; `t` is writable.
    let s = unsafe { hf_tracker_new(std::ptr::null(), &mut t) };
    assert_eq!(s, HfStatus::Ok, "hf_tracker_new: {}", last_error());
    assert!(!t.is_null());
    t
}

/// One blank frame (no face) at `timestamp_us`, the camera at the world origin.
fn process(t: *mut HfTracker, timestamp_us: u64) -> HfStatus {
    process_at(t, timestamp_us, &IDENTITY)
}

const IDENTITY: [f32; 16] = [
    1.0, 0.0, 0.0, 0.0, //
    0.0, 1.0, 0.0, 0.0, //
    0.0, 0.0, 1.0, 0.0, //
    0.0, 0.0, 0.0, 1.0,
];

/// One blank frame (no face) at `timestamp_us` with the row-major camera-to-world matrix `pose`.
fn process_at(t: *mut HfTracker, timestamp_us: u64, pose: &[f32; 16]) -> HfStatus {
    let px = [0u8; (SIDE * SIDE) as usize];
    let cam = CAMERA;
    let mut out = MaybeUninit::<HfResult>::uninit();
    // SAFETY: `px` holds stride * height bytes, `cam` and `out` are valid; the handle is looked up.
    unsafe {
        hf_tracker_process(
            t,
            px.as_ptr(),
            SIDE,
            SIDE,
            SIDE,
            timestamp_us,
            &cam,
            pose.as_ptr(),
            out.as_mut_ptr(),
        )
    }
}

fn free(t: *mut HfTracker) -> HfStatus {
    // SAFETY: any pointer value may be passed; it is looked up, never dereferenced.
    unsafe { hf_tracker_free(t) }
}

#[test]
fn a_stale_handle_never_reaches_a_tracker_created_after_it() {
    let _registry = shared_registry();
    let stale = new_tracker();
    assert_eq!(process(stale, 1), HfStatus::Ok, "{}", last_error());
    assert_eq!(free(stale), HfStatus::Ok);
    // The probe saw the address come back within 8-44 cycles; each new tracker here gets a handle of its own,
    // and the stale handle stays refused while the live tracker keeps working.
    // Under emulation (`make arm64-test`: a tracker takes seconds to create under qemu) a few cycles; the native
    // run covers the reuse window.
    let cycles = if emulated() { 3 } else { 48 };
    let mut seen = vec![stale];
    for cycle in 0..cycles {
        let live = new_tracker();
        assert!(!seen.contains(&live), "cycle {cycle}: a handle was issued twice");
        seen.push(live);
        assert_eq!(process(live, 10), HfStatus::Ok, "{}", last_error());
        assert_eq!(process(stale, 20), HfStatus::InvalidHandle);
        assert!(
            last_error().contains("not a live tracker handle"),
            "{}",
            last_error()
        );
        // A second free of the stale handle frees nothing ...
        assert_eq!(free(stale), HfStatus::InvalidHandle);
        // ... and the live tracker never saw the stale calls: its next frame, at 15 us, is after its own 10 us
        // (a stale call at 20 us that had reached it would make 15 us a step back), and it is still there to
        // free.
        assert_eq!(process(live, 15), HfStatus::Ok, "cycle {cycle}: {}", last_error());
        assert_eq!(free(live), HfStatus::Ok);
    }
}

#[test]
fn an_absurd_timestamp_is_refused_for_its_frame_and_the_tracker_goes_on() {
    let _registry = shared_registry();
    let t = new_tracker();
    let other = new_tracker();
    assert_eq!(process(t, 1_000), HfStatus::Ok, "{}", last_error());
    assert_eq!(process(t, u64::MAX), HfStatus::InvalidArgument);
    assert!(
        last_error().contains("after the previous 1000"),
        "{}",
        last_error()
    );
    // The next 100 ordinary frames are accepted (0f48427 refused every one of them; under emulation, where a
    // frame takes a third of a second, 10), and the other tracker never noticed.
    let frames = if emulated() { 10 } else { 100 };
    for k in 1..=frames {
        assert_eq!(
            process(t, 1_000 + k * 33_333),
            HfStatus::Ok,
            "frame {k}: {}",
            last_error()
        );
        assert_eq!(last_error(), "", "a success clears the last error");
    }
    assert_eq!(process(other, 5), HfStatus::Ok, "{}", last_error());
    // A stream that really resumes two hours later: its first frame is refused, the next one follows it and
    // is accepted.
    let later = 1_000 + frames * 33_333 + 2 * 3_600_000_000;
    assert_eq!(process(t, later), HfStatus::InvalidArgument);
    assert_eq!(process(t, later + 33_333), HfStatus::Ok, "{}", last_error());
    assert_eq!(free(t), HfStatus::Ok);
    assert_eq!(free(other), HfStatus::Ok);
}

#[test]
fn a_camera_beyond_ten_kilometres_is_refused_and_the_next_frame_is_not() {
    let _registry = shared_registry();
    let t = new_tracker();
    let mut far = IDENTITY;
    far[3] = 1e30;
    assert_eq!(process_at(t, 1_000, &far), HfStatus::InvalidArgument);
    assert!(
        last_error().contains("from the world origin (at most 10000 m)"),
        "{}",
        last_error()
    );
    // The same frame time, from a plausible pose, is the tracker's first frame.
    far[3] = 9_000.0;
    assert_eq!(process_at(t, 1_000, &far), HfStatus::Ok, "{}", last_error());
    assert_eq!(free(t), HfStatus::Ok);
}

#[test]
fn a_second_onnx_runtime_library_is_refused_naming_the_loaded_one() {
    let _registry = shared_registry();
    let first = new_tracker();
    let mut o = MaybeUninit::<HfOptions>::uninit();
    // SAFETY: a writable HfOptions.
    assert_eq!(unsafe { hf_options_default(o.as_mut_ptr()) }, HfStatus::Ok);
    // SAFETY: initialised by hf_options_default.
    let mut o = unsafe { o.assume_init() };
    // Any other regular file: 0f48427 returned OK without looking at it.
    let other = std::ffi::CString::new(env!("CARGO_MANIFEST_DIR").to_owned() + "/Cargo.toml").unwrap();
    o.ort_dylib = other.as_ptr();
    let mut t = std::ptr::null_mut();
    // SAFETY: valid options whose strings live for the call; `t` is writable.
    assert_eq!(unsafe { hf_tracker_new(&o, &mut t) }, HfStatus::AssetError);
    assert!(t.is_null());
    let message = last_error();
    assert!(
        message.contains("ONNX Runtime is already loaded in this process from")
            && message.contains("libonnxruntime")
            && message.contains("Cargo.toml"),
        "{message}"
    );
    assert_eq!(process(first, 1), HfStatus::Ok, "{}", last_error());
    assert_eq!(free(first), HfStatus::Ok);
}

#[test]
fn with_its_length_a_short_buffer_or_an_absurd_stride_is_refused_not_read_past() {
    let _registry = shared_registry();
    let t = new_tracker();
    let px = vec![0u8; (SIDE * SIDE) as usize];
    let cam = CAMERA;
    let mut out = MaybeUninit::<HfResult>::uninit();
    let call =
        |len: usize, width: u32, height: u32, stride: u32, ts: u64, out: &mut MaybeUninit<HfResult>| {
            // SAFETY: `px` holds `px.len()` >= `len` bytes; the other pointers are valid.
            unsafe {
                hf_tracker_process_buf(
                    t,
                    px.as_ptr(),
                    len,
                    width,
                    height,
                    stride,
                    ts,
                    &cam,
                    std::ptr::null(),
                    out.as_mut_ptr(),
                )
            }
        };
    // The probe's cases: a 16384x16384 frame over this 4 KB buffer, and stride UINT32_MAX.
    assert_eq!(
        call(px.len(), 16_384, 16_384, 16_384, 1, &mut out),
        HfStatus::InvalidArgument
    );
    assert!(
        last_error().contains("spans 268435456 bytes, the buffer holds 4096"),
        "{}",
        last_error()
    );
    assert_eq!(
        call(px.len(), SIDE, SIDE, u32::MAX, 1, &mut out),
        HfStatus::InvalidArgument
    );
    // One byte short of what the image spans (the last row needs only its width).
    let spans = (SIDE * (SIDE - 1) + SIDE) as usize;
    assert_eq!(
        call(spans - 1, SIDE, SIDE, SIDE, 1, &mut out),
        HfStatus::InvalidArgument
    );
    assert_eq!(
        call(spans, SIDE, SIDE, SIDE, 1, &mut out),
        HfStatus::Ok,
        "{}",
        last_error()
    );
    assert_eq!(free(t), HfStatus::Ok);
}

fn link_status(t: *mut HfTracker) -> HfStatus {
    let mut out = MaybeUninit::uninit();
    // SAFETY: any pointer value may be passed; `out` is writable.
    unsafe { hf_tracker_link_status(t, out.as_mut_ptr()) }
}

/// xorshift64*: the property test's sequences, reproducible from their seed.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

/// Random sequences of create, process, link status, free, stale use, double free and forged handles, checked
/// against a model of which handles are live: a live handle always works and keeps its own clock, anything
/// else is INVALID_HANDLE, and no handle is ever issued twice. 10,000 operations natively (creating a tracker
/// is the costly one, so the sequences create about one in three hundred). Under emulation, where a frame takes a
/// third of a second, one sequence of 100: the handle table is the same code on both architectures, and the
/// sequence shows it behaves there too.
#[test]
fn random_sequences_of_handle_operations_match_the_model() {
    let _registry = REGISTRY.write().unwrap_or_else(PoisonError::into_inner);
    let (seeds, ops_per_seed) = if emulated() { (1, 100) } else { (4, 2_500) };
    for seed in [0x5eed_0001_u64, 0x5eed_0002, 0x5eed_0003, 0x5eed_0004]
        .into_iter()
        .take(seeds)
    {
        let mut rng = Rng(seed);
        let mut live: Vec<*mut HfTracker> = Vec::new();
        let mut dead: Vec<*mut HfTracker> = Vec::new();
        let mut clock: HashMap<usize, u64> = HashMap::new();
        for op in 0..ops_per_seed {
            let at = format!("seed {seed:#x}, operation {op}");
            let roll = rng.below(1_000);
            if live.is_empty() || (roll < 3 && live.len() < 3) {
                let t = new_tracker();
                assert!(
                    !live.contains(&t) && !dead.contains(&t),
                    "{at}: handle {t:p} issued twice"
                );
                live.push(t);
            } else if roll < 6 {
                let t = live.swap_remove(rng.below(live.len()));
                assert_eq!(free(t), HfStatus::Ok, "{at}: {}", last_error());
                dead.push(t);
            } else if roll < 100 {
                let t = live[rng.below(live.len())];
                let ts = clock.entry(t.addr()).or_insert(0);
                *ts += 1 + rng.next() % 100_000;
                assert_eq!(process(t, *ts), HfStatus::Ok, "{at}: {}", last_error());
                assert_eq!(last_error(), "", "{at}: a success clears the last error");
            } else if roll < 450 {
                let t = live[rng.below(live.len())];
                assert_eq!(link_status(t), HfStatus::Ok, "{at}: {}", last_error());
            } else {
                // Something that is not a live handle: a freed one, or a forged value (small numbers, which a
                // later tracker could be given, an address, the extremes).
                let t = if !dead.is_empty() && roll < 725 {
                    dead[rng.below(dead.len())]
                } else {
                    let forged = match rng.below(4) {
                        0 => rng.below(64),
                        1 => rng.next() as usize,
                        2 => (&raw const roll).addr(),
                        _ => usize::MAX - rng.below(8),
                    };
                    std::ptr::without_provenance_mut(forged)
                };
                if live.contains(&t) {
                    continue;
                }
                let status = match rng.below(3) {
                    0 => process(t, 1),
                    1 => link_status(t),
                    _ => free(t),
                };
                assert_eq!(status, HfStatus::InvalidHandle, "{at}: {t:p}");
                assert!(
                    last_error().contains("not a live tracker handle"),
                    "{at}: {}",
                    last_error()
                );
            }
        }
        for t in live {
            assert_eq!(free(t), HfStatus::Ok, "seed {seed:#x}: {}", last_error());
        }
    }
}

/// `hf_tracker_anchor` of `face`: the status and the object-to-world matrix (row-major).
fn anchor(
    t: *mut HfTracker,
    face: &HfResult,
    point: u32,
    offset: [f64; 3],
    rotation_deg: [f64; 3],
) -> (HfStatus, [f32; 16]) {
    let mut m = [0f32; 16];
    // SAFETY: every pointer is valid for its length.
    let s = unsafe {
        hf_tracker_anchor(
            t,
            face,
            point,
            offset.as_ptr(),
            rotation_deg.as_ptr(),
            m.as_mut_ptr(),
        )
    };
    (s, m)
}

#[test]
fn an_anchored_object_is_the_display_pose_after_the_anchor() {
    let _shared = shared_registry();
    let t = new_tracker();
    // A result with a face at (0.1, -0.2, 0.9) m, turned 90 degrees about the vertical (y).
    // SAFETY: HfResult is plain data; all zeros is a valid value.
    let mut face: HfResult = unsafe { std::mem::zeroed() };
    face.has_face = 1;
    face.display_position_m = [0.1, -0.2, 0.9];
    let h = std::f64::consts::FRAC_1_SQRT_2;
    face.display_rotation_wxyz = [h, 0.0, h, 0.0];
    let close = |a: &[f32], b: &[f32]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-5);
    // At the origin, without offset or rotation: the display pose itself (the turn takes z to x).
    let (s, m) = anchor(t, &face, HfAnchorPoint::Origin as u32, [0.0; 3], [0.0; 3]);
    assert_eq!(s, HfStatus::Ok, "{}", last_error());
    let display = [
        0.0, 0.0, 1.0, 0.1, 0.0, 1.0, 0.0, -0.2, -1.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0, 1.0,
    ];
    assert!(close(&m, &display), "{m:?}");
    // 18 mm in front of the eyes (head -z): 18 mm along the world's -x from the eyes; the rotation unchanged.
    let (_, eyes) = anchor(t, &face, HfAnchorPoint::Eyes as u32, [0.0; 3], [0.0; 3]);
    let (_, glasses) = anchor(t, &face, HfAnchorPoint::Eyes as u32, [0.0, 0.0, -0.018], [0.0; 3]);
    assert!(close(
        &[glasses[3] - eyes[3], glasses[7] - eyes[7], glasses[11] - eyes[11]],
        &[-0.018, 0.0, 0.0]
    ));
    // The eyes are a few centimetres from the head's origin, above it (head -y is world -y here).
    let d = ((eyes[3] - 0.1).powi(2) + (eyes[7] + 0.2).powi(2) + (eyes[11] - 0.9).powi(2)).sqrt();
    assert!(
        (0.005..0.05).contains(&d) && eyes[7] < -0.2,
        "eyes {d} m from the origin: {eyes:?}"
    );
    // Turned 90 degrees about the head's x: the object's y axis becomes the head's z (world x).
    let (_, tipped) = anchor(t, &face, HfAnchorPoint::Origin as u32, [0.0; 3], [90.0, 0.0, 0.0]);
    assert!(
        close(&[tipped[1], tipped[5], tipped[9]], &[1.0, 0.0, 0.0]),
        "{tipped:?}"
    );
    // Refused: an unknown point, a result without a face, a NaN offset, a non-unit rotation, NULL.
    let (s, _) = anchor(t, &face, 5, [0.0; 3], [0.0; 3]);
    assert!(
        s == HfStatus::InvalidArgument && last_error().contains("point 5"),
        "{}",
        last_error()
    );
    let mut none = face;
    none.has_face = 0;
    assert_eq!(
        anchor(t, &none, 1, [0.0; 3], [0.0; 3]).0,
        HfStatus::InvalidArgument
    );
    assert_eq!(
        anchor(t, &face, 1, [f64::NAN, 0.0, 0.0], [0.0; 3]).0,
        HfStatus::InvalidArgument
    );
    let mut zero = face;
    zero.display_rotation_wxyz = [0.0; 4];
    assert_eq!(
        anchor(t, &zero, 1, [0.0; 3], [0.0; 3]).0,
        HfStatus::InvalidArgument
    );
    let mut m = [0f32; 16];
    // SAFETY: NULL is what is checked; the other pointers are valid.
    let s = unsafe {
        hf_tracker_anchor(
            t,
            std::ptr::null(),
            1,
            [0.0; 3].as_ptr(),
            [0.0; 3].as_ptr(),
            m.as_mut_ptr(),
        )
    };
    assert_eq!(s, HfStatus::NullPointer);
    assert_eq!(free(t), HfStatus::Ok);
    assert_eq!(anchor(t, &face, 1, [0.0; 3], [0.0; 3]).0, HfStatus::InvalidHandle);
}
