//! The integration tests, one binary: each file below is a module, so the crate and its dependencies are linked
//! once rather than once per file (build time; nextest still runs every test in a process of its own).

mod fairness;
mod gpu_provider;
mod link_faults;
mod log_lines;
mod server_e2e;
mod server_process;
