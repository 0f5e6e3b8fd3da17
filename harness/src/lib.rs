//! The harness the `holoface` tools, the load tester and the end-to-end tests exercise the system with (hence the
//! name: none of it runs in an app or the server), so that none of them leans on
//! the command line's crate (`holoface-tools`, a leaf binary with the trainers, the set-up's HTTP stack and
//! the video encoder): the annotated face folders and the validation split ([`data`]), self-contained PNG
//! plots ([`plot`]), the UDP relay that cuts or degrades a link ([`relay`]), DAN run in-process
//! ([`dan_aligner`]). Files the tools write appear whole or not at all through `holoface_sources::output`.
#![deny(missing_docs)]

pub mod dan_aligner;
pub mod data;
pub mod plot;
pub mod relay;
