//! Files holoface reads from the user's machine, apart from what the files mean: where the data folder is and
//! which assets live in it ([`home`]), and bounded reads of the files users and operators name ([`bounded`]:
//! the kind of file and its size checked before a byte is read).
//!
//! Its only dependency is `thiserror`, so the ONNX crate, the headset runtime, the frame sources and the
//! server share one rule for finding and reading files without depending on each other.
#![deny(missing_docs)]

pub mod bounded;
pub mod home;

pub use bounded::{FileError, FileKind, read_bounded, read_text_bounded, regular_file};
