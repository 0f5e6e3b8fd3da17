//! The integration tests, one binary: each file below is a module, so the crate and its dependencies are linked
//! once rather than once per file (build time; nextest still runs every test in a process of its own).

mod cli_errors;
mod common;
mod damaged_files_and_hostile_environments;
mod demo;
mod installed;
mod live_runs;
mod multi_face;
mod track_video;
