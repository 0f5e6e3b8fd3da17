//! The HoloFace headset runtime, the library a headset app embeds: the frame type, face detection, tracking
//! with an interchangeable aligner (remote DAN over QUIC with KRFWS fallback, or KRFWS alone), CANDIDE-3
//! fitting, world pose and prediction. The command-line tools live in `holoface-tools` and the readers of
//! image folders, videos and recordings in `holoface-sources`; neither the alignment server nor a video
//! decoder is ever compiled into a headset app.
#![deny(missing_docs)]

pub mod align;
pub mod assets;
pub mod crop_codec;
pub mod detect;
pub mod frame;
pub mod frame_step;
pub mod link;
pub mod session;
pub mod tracker;
