//! The live trackers by handle and the per-thread last error: how a C caller's `HfTracker *` finds its tracker
//! (never by address), and how each call reports what went wrong.

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::ffi::CString;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};

use holoface_headset_client::FaceTracker;

use crate::HfStatus;

/// An opaque tracker. C code holds `HfTracker *` handles, which are ids from a table of live trackers, never
/// addresses.
#[derive(Debug)]
pub struct HfTracker {
    pub(crate) inner: FaceTracker,
}

/// A live tracker as the table holds it: shared with the calls in flight on it, locked by each.
pub(crate) type Shared = Arc<Mutex<HfTracker>>;

/// The live trackers by handle. Handles come from a counter that only goes up, so none is ever issued twice
/// in a process; when it would pass what a pointer holds (2^64 creations, or 2^32 on a 32-bit target),
/// creation fails rather than reuse one.
#[derive(Debug)]
pub(crate) struct Registry {
    /// The last handle issued (0: none yet; 0 is never a handle, it is NULL).
    last: usize,
    live: BTreeMap<usize, Shared>,
}

static REGISTRY: Mutex<Registry> = Mutex::new(Registry {
    last: 0,
    live: BTreeMap::new(),
});

pub(crate) fn registry() -> MutexGuard<'static, Registry> {
    REGISTRY.lock().unwrap_or_else(PoisonError::into_inner)
}

impl Registry {
    /// Registers a tracker under a new handle, or `None` once the handles are used up.
    pub(crate) fn insert(&mut self, tracker: HfTracker) -> Option<*mut HfTracker> {
        let id = self.last.checked_add(1)?;
        self.last = id;
        self.live.insert(id, Arc::new(Mutex::new(tracker)));
        Some(std::ptr::without_provenance_mut(id))
    }

    /// The live tracker a handle names.
    pub(crate) fn get(&self, handle: *const HfTracker) -> Option<Shared> {
        self.live.get(&handle.addr()).cloned()
    }

    /// Unregisters the tracker a handle names; it is dropped when the last call using it returns.
    pub(crate) fn remove(&mut self, handle: *const HfTracker) -> Option<Shared> {
        self.live.remove(&handle.addr())
    }
}

/// The live tracker `handle` names, or `HF_STATUS_INVALID_HANDLE` with `what` in the message.
pub(crate) fn tracker(what: &str, handle: *const HfTracker) -> Result<Shared, HfStatus> {
    registry().get(handle).ok_or_else(|| {
        fail(
            HfStatus::InvalidHandle,
            format!("{what}: not a live tracker handle"),
        )
    })
}

/// Locks a tracker for one call (a panic inside an earlier call leaves it usable, as it was before).
pub(crate) fn lock(t: &Shared) -> MutexGuard<'_, HfTracker> {
    t.lock().unwrap_or_else(PoisonError::into_inner)
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

pub(crate) fn set_error(msg: &str) {
    let c = CString::new(msg.replace('\0', " ")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = c);
}

pub(crate) fn fail(status: HfStatus, msg: impl AsRef<str>) -> HfStatus {
    set_error(msg.as_ref());
    status
}

/// Runs `f` with panics turned into `HF_STATUS_PANIC`; a call that returns `HF_STATUS_OK` clears the calling
/// thread's last error, so `hf_last_error` always describes the thread's most recent call.
pub(crate) fn guard(f: impl FnOnce() -> HfStatus) -> HfStatus {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(HfStatus::Ok) => {
            LAST_ERROR.with(|e| *e.borrow_mut() = CString::default());
            HfStatus::Ok
        }
        Ok(s) => s,
        Err(p) => {
            let what = p
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".to_owned());
            fail(HfStatus::Panic, format!("internal error (panic): {what}"))
        }
    }
}

/// The calling thread's last error message (valid until its next call that returns a status).
pub(crate) fn last_error_ptr() -> *const std::ffi::c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}
