//! `holoface-load`: replays recorded streams from many simulated headsets against an alignment server.
//!
//! Not implemented yet (tracked by the "remote link, demo, recorded streams and load tester" issue). Until
//! then the binary refuses to run rather than pretend to have measured anything.

fn main() -> std::process::ExitCode {
    eprintln!("holoface-load is not implemented yet; see ARCHITECTURE.md (load-tester)");
    std::process::ExitCode::from(2)
}
