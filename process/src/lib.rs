//! What a holoface binary (`holoface`, `holoface-server`, `holoface-load`, the server bench) sets up for its
//! process, and nothing a library needs: the one tracing set-up ([`logging`]), a thread that turns Ctrl-C and
//! SIGTERM into calls ([`signals`]), and the [`stop::Stop`] a binary makes, hands to that thread and passes to
//! the run it ends ([`stop`]). Libraries never install a subscriber or a signal handler.
#![deny(missing_docs)]

pub mod logging;
pub mod signals;
pub mod stop;
