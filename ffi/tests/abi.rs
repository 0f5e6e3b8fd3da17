//! The C ABI's promises, driven as a C caller would, with real trackers (assets from the environment, as
//! `make test` sets it). Issue 68's probe: with addresses for handles a new tracker got a freed one's address
//! within 8-44 create/free cycles, and the stale handle then drove (and freed) the new tracker; one absurd
//! timestamp locked a tracker for good; a second `ort_dylib` was silently ignored; a pose 1e30 m away passed.
#![allow(unsafe_code, clippy::unwrap_used)]

use std::ffi::CStr;
use std::mem::MaybeUninit;

use holoface::{
    HfCamera, HfOptions, HfResult, HfStatus, HfTracker, hf_last_error, hf_options_default, hf_tracker_free,
    hf_tracker_new, hf_tracker_process,
};

const SIDE: u32 = 64;

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
    let cam = HfCamera {
        fx: 60.0,
        fy: 60.0,
        cx: 32.0,
        cy: 32.0,
    };
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
