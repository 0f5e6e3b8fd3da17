//! The HoloFace headset runtime, the library a headset app embeds: frame sources, face detection, tracking
//! with an interchangeable aligner (remote DAN over QUIC with KRFWS fallback, or KRFWS alone), CANDIDE-3
//! fitting, world pose and prediction. The command-line tools live in `holoface-tools`; the alignment server
//! is never compiled into a headset app.
#![deny(missing_docs)]

pub mod align;
pub mod assets;
pub mod codec;
pub mod detect;
pub mod frame;
pub mod frame_loop;
pub mod images;
pub mod link;
pub mod poses;
pub mod session;
pub mod source;
pub mod tracker;
pub mod video;
pub mod y4m;
