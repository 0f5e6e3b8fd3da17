//! The integration tests, one binary: each file below is a module, so the crate and its dependencies are linked
//! once rather than once per file (build time; nextest still runs every test in a process of its own).

mod blendshapes;
mod candide;
mod golden;
// Trains small models: only where the trainers are compiled in.
#[cfg(feature = "train")]
mod krfws;
mod krfws_golden;
