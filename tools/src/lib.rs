//! The `holoface` command-line tools and what only they need: teacher-label files ([`labels`]), the synthetic
//! headset renderer ([`render`]), annotated output ([`annotate`]), how the blendshapes follow real faces
//! ([`expressions`]), the in-process loopback server
//! ([`loopback`]), link cuts on a schedule in media time ([`link_cuts`]), summary statistics ([`stats`]) and the command-line asset options ([`args`]). A leaf:
//! nothing else in the workspace depends on this crate; what the load tester and the end-to-end tests share
//! with it (data folders, plots, the fault relay, DAN in-process) is `holoface-harness`.
//!
//! The headset runtime they drive is `holoface-runtime`; the demo's in-process alignment server is
//! `holoface-server`. A headset app depends on neither this crate nor the server.
#![deny(missing_docs)]

pub mod annotate;
pub mod args;
pub mod augment;
pub mod cli;
pub mod expressions;
#[cfg(feature = "train")]
pub mod labels;
pub mod link_cuts;
pub mod loopback;
pub mod render;
pub mod stats;
pub mod track_measures;
