//! Ctrl-C and SIGTERM for the binaries (`holoface`, `holoface-load`): one thread waits for either and hands each
//! to the binary's own rule, which records it in the [`crate::stop::Stop`] it shares with the run.

use crate::stop::Signal;

/// Calls `on_signal(signal)` for every Ctrl-C or SIGTERM, on a thread of its own,
/// for the life of the process. Without the thread (none could be started) a signal keeps its default action;
/// the error says so.
pub fn on_signals(on_signal: impl Fn(Signal) + Send + 'static) -> std::io::Result<()> {
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else {
                return;
            };
            rt.block_on(async {
                use tokio::signal::unix::{SignalKind, signal};
                let (Ok(mut int), Ok(mut term)) =
                    (signal(SignalKind::interrupt()), signal(SignalKind::terminate()))
                else {
                    return;
                };
                loop {
                    let sig = tokio::select! {
                        _ = int.recv() => Signal::Interrupt,
                        _ = term.recv() => Signal::Terminate,
                    };
                    on_signal(sig);
                }
            });
        })?;
    Ok(())
}
