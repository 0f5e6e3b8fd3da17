//! The HoloFace headset client: frame sources, face detection, tracking with an interchangeable aligner,
//! CANDIDE-3 fitting, world pose and prediction, and the `holoface` command line.
#![deny(missing_docs)]

pub mod align;
pub mod annotate;
pub mod cli;
pub mod data;
pub mod detect;
pub mod link;
pub mod plot;
pub mod poses;
pub mod render;
pub mod runtime;
pub mod session;
pub mod source;
pub mod tracker;
pub mod video;
