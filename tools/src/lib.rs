//! The `holoface` command-line tools and what only tools need: annotated data folders and the validation
//! split ([`data`]), teacher-label files ([`labels`]), the synthetic headset renderer ([`render`]), plots ([`plot`]), annotated output
//! ([`annotate`]), the fault-injecting UDP relay ([`relay`]), the in-process loopback server ([`loopback`]), summary statistics ([`stats`]) and the command-line asset options ([`args`]).
//!
//! The headset runtime they drive is `holoface-headset-client`; the demo's in-process alignment server is
//! `holoface-server`. A headset app depends on neither this crate nor the server.
#![deny(missing_docs)]

pub mod annotate;
pub mod args;
pub mod cli;
pub mod dan_aligner;
pub mod data;
pub mod labels;
pub mod loopback;
pub mod plot;
pub mod relay;
pub mod render;
pub mod stability;
pub mod stats;
