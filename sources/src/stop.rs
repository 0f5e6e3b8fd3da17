//! A stop asked for by a signal: the first Ctrl-C (SIGINT) or SIGTERM of a live run ends it after the frame in
//! hand, as its source ending would, so that everything it saw stays in its outputs. The binaries' signal
//! handler calls [`request`]; a command's frame loop asks [`requested`] before each frame. Process-wide state:
//! one process, one stop.

use std::sync::atomic::{AtomicI32, Ordering};

static STOP: AtomicI32 = AtomicI32::new(0);

/// Records a stop asked for by `signal` (2 = SIGINT, 15 = SIGTERM). Returns `false` when a stop was already
/// asked for (the caller then stops at once).
pub fn request(signal: i32) -> bool {
    STOP.compare_exchange(0, signal, Ordering::SeqCst, Ordering::SeqCst)
        .is_ok()
}

/// The signal that asked for a stop, if one did.
pub fn requested() -> Option<i32> {
    match STOP.load(Ordering::SeqCst) {
        0 => None,
        s => Some(s),
    }
}

/// The shell's exit code for a command ended by `signal` (130 for SIGINT, 143 for SIGTERM).
pub fn exit_code(signal: i32) -> i32 {
    128 + signal
}

/// The signal's name, for messages.
pub fn name(signal: i32) -> &'static str {
    match signal {
        2 => "SIGINT",
        15 => "SIGTERM",
        _ => "a signal",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_signal_asks_for_a_stop_and_a_second_finds_one_asked() {
        assert_eq!(requested(), None);
        assert!(request(2), "the first signal asks");
        assert!(!request(15), "the second finds a stop already asked for");
        assert_eq!(requested(), Some(2), "the first one's signal is kept");
        assert_eq!((exit_code(2), exit_code(15)), (130, 143));
        assert_eq!((name(2), name(15)), ("SIGINT", "SIGTERM"));
    }
}
