//! The one tracing set-up of the binaries (`holoface-server`, `holoface`, `holoface-load`, the server bench):
//! events to standard error, in colour only when standard error is a terminal, so a log written to a file or
//! a pipe (systemd's journal, `2> server.log`, a container runtime) carries no escape codes. Libraries never
//! install a subscriber. Peers' strings in events go through `holoface_protocol::untrusted`.

use std::io::IsTerminal;

use tracing_subscriber::EnvFilter;
use tracing_subscriber::fmt::MakeWriter;

/// `RUST_LOG` when it is set and valid, else `default` (an `EnvFilter` directive such as `"info"`).
pub fn env_filter_or(default: &str) -> EnvFilter {
    EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default))
}

/// Installs the subscriber: `filter`'s events to standard error, coloured only on a terminal. A second call
/// (or another subscriber already installed) changes nothing.
pub fn init(filter: EnvFilter) {
    init_with(filter, std::io::stderr, std::io::stderr().is_terminal());
}

/// [`init`] with another writer and an explicit colour choice (tests capture the log this way).
pub fn init_with<W>(filter: EnvFilter, writer: W, ansi: bool)
where
    W: for<'w> MakeWriter<'w> + Send + Sync + 'static,
{
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(writer)
        .with_ansi(ansi)
        .try_init();
}
