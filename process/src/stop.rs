//! Stopping a run on a signal: the first Ctrl-C (SIGINT) or SIGTERM of a live run ends it after the frame in hand,
//! as its source ending would, so that everything it saw stays in its outputs. A binary makes one [`Stop`], hands
//! a clone to its signal handler and one to the command it runs, whose frame loop asks [`Stop::requested`] before
//! each frame (mini-redis passes its shutdown trigger the same way): no library keeps the state in a global.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};

/// A signal that stops a run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Signal {
    /// SIGINT (Ctrl-C).
    Interrupt,
    /// SIGTERM.
    Terminate,
}

impl Signal {
    /// The signal's number (2, 15).
    pub fn number(self) -> i32 {
        match self {
            Self::Interrupt => 2,
            Self::Terminate => 15,
        }
    }

    /// The shell's exit code for a command the signal ended (130, 143).
    pub fn exit_code(self) -> i32 {
        128 + self.number()
    }

    /// The signal's name, for messages.
    pub fn name(self) -> &'static str {
        match self {
            Self::Interrupt => "SIGINT",
            Self::Terminate => "SIGTERM",
        }
    }
}

/// A stop shared by a signal handler and the run it ends: clones share one state.
#[derive(Clone, Debug, Default)]
pub struct Stop(Arc<State>);

#[derive(Debug, Default)]
struct State {
    /// 0: no stop asked for; 1: SIGINT; 2: SIGTERM.
    signal: AtomicU8,
    /// Whether the running command stops after the frame in hand ([`Stop::stop_gracefully`]).
    graceful: AtomicBool,
}

impl Stop {
    /// No stop asked for yet; the command ends at once on a signal until it calls [`Self::stop_gracefully`].
    pub fn new() -> Self {
        Self::default()
    }

    /// Records a stop asked for by `signal`. Returns `false` when a stop was already asked for (the caller then
    /// stops at once).
    pub fn request(&self, signal: Signal) -> bool {
        let code = match signal {
            Signal::Interrupt => 1,
            Signal::Terminate => 2,
        };
        self.0
            .signal
            .compare_exchange(0, code, Ordering::SeqCst, Ordering::SeqCst)
            .is_ok()
    }

    /// The signal that asked for a stop, if one did.
    pub fn requested(&self) -> Option<Signal> {
        match self.0.signal.load(Ordering::SeqCst) {
            0 => None,
            1 => Some(Signal::Interrupt),
            _ => Some(Signal::Terminate),
        }
    }

    /// Called by a command that reads a live source (`track --source -`): a signal then asks it to stop after the
    /// frame in hand, as if its source had ended, instead of ending the process.
    pub fn stop_gracefully(&self) {
        self.0.graceful.store(true, Ordering::SeqCst);
    }

    /// Whether the running command asked to stop after the frame in hand.
    pub fn is_graceful(&self) -> bool {
        self.0.graceful.load(Ordering::SeqCst)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_signal_asks_for_a_stop_and_a_second_finds_one_asked() {
        let stop = Stop::new();
        let handler = stop.clone();
        assert_eq!(stop.requested(), None);
        assert!(
            !stop.is_graceful(),
            "a command ends at once unless it asks otherwise"
        );
        stop.stop_gracefully();
        assert!(handler.is_graceful(), "clones share the choice");
        assert!(handler.request(Signal::Interrupt), "the first signal asks");
        assert!(
            !handler.request(Signal::Terminate),
            "the second finds a stop already asked for"
        );
        assert_eq!(
            stop.requested(),
            Some(Signal::Interrupt),
            "the first one's signal is kept, and the run sees it"
        );
        assert_eq!(Stop::new().requested(), None, "another stop is another state");
        let (int, term) = (Signal::Interrupt, Signal::Terminate);
        assert_eq!((int.exit_code(), term.exit_code()), (130, 143));
        assert_eq!((int.name(), term.name()), ("SIGINT", "SIGTERM"));
    }
}
