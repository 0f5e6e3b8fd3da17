//! The integration tests, one binary: each file below is a module, so the crate and its dependencies are linked
//! once rather than once per file (build time; nextest still runs every test in a process of its own).

mod common;
mod interrupt;
mod outage;
mod overload;
