//! Pure algorithms of HoloFace: crop geometry, landmark accuracy, HOG, the KRFWS aligner, the server's
//! refinement cascade (`refine`), DAN pre- and
//! post-processing, the CANDIDE-3 fit and the Kalman predictor.
//!
//! **Architecture invariant:** this crate never touches the filesystem, the network or a clock. Models
//! are loaded from byte slices; time enters as explicit `dt` arguments. Hot-path functions write into
//! caller-provided buffers.
#![deny(missing_docs)]

pub mod accuracy;
pub mod adapt;
pub mod anchor;
#[cfg(feature = "train")]
pub mod augment;
pub mod blendshapes;
pub mod camera;
pub mod candide;
pub mod crop;
pub mod expression;
pub mod geometry;
pub mod hog;
pub mod image;
pub mod isa;
pub mod kalman;
pub mod krfws;
pub mod linalg;
pub mod math3;
pub mod pose;
pub mod refine;
pub mod rng;
pub mod shape;
pub mod steady;

pub use camera::Intrinsics;
pub use crop::{CROP_PIXELS, CROP_SIZE, Crop112, crop_bilinear};
pub use geometry::{Point2, Similarity2};
pub use image::{GrayImage, GrayView, ImageError};
