//! Annotated face folders (`NAME.jpg` + `NAME.pts`, 68 points, 0-based) and the fixed validation split.
//!
//! This is the only place the tools read training or evaluation data; `models` stays IO-free, and the
//! headset runtime never sees annotations.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use holoface_models::geometry::Point2;
use holoface_models::image::GrayImage;
use holoface_models::shape::parse_pts68;
use holoface_sources::images::{list_images, read_gray};

/// The committed validation split (names `<subset>/<stem>` relative to `faces68/train`).
pub const VALIDATION_SPLIT: &str = include_str!("../../models/splits/val.txt");

/// One annotated face.
#[derive(Debug, Clone)]
pub struct Sample {
    /// `<subset>/<stem>` relative to the data root (or the stem for a flat folder).
    pub name: String,
    /// Grayscale image.
    pub image: GrayImage,
    /// Ground-truth landmarks in image pixels, when a `.pts` file exists.
    pub landmarks: Option<[Point2; 68]>,
}

/// Names in the validation split.
pub fn validation_names() -> HashSet<String> {
    VALIDATION_SPLIT
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(str::to_owned)
        .collect()
}

/// Which part of a folder to take.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    /// Every sample.
    All,
    /// Samples named in the validation split.
    Validation,
    /// Samples not named in the validation split.
    Train,
}

/// The data folder: `$HOLOFACE_DATA`, else the first `shared/data` beside the current directory or one of its
/// parents (a checkout's `../shared/data`, from any folder inside it), else `../shared/data` (named in the
/// error of whatever reads it). Found at run time: no path of the machine that built the binary is in it.
pub fn default_data_root() -> PathBuf {
    if let Some(p) = std::env::var_os("HOLOFACE_DATA").filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    let beside = Path::new("..").join("shared").join("data");
    std::env::current_dir()
        .ok()
        .and_then(|cwd| {
            cwd.ancestors()
                .map(|dir| dir.join(&beside))
                .find(|candidate| candidate.is_dir())
        })
        .unwrap_or(beside)
}

/// The annotated faces (`faces68/train` of the data folder) unless `given` names another folder: the default
/// of every command's `--data`.
pub fn faces68_or(given: Option<&Path>) -> PathBuf {
    given.map_or_else(|| default_data_root().join("faces68/train"), Path::to_path_buf)
}

/// Reads a 68-point `.pts` file.
pub fn read_pts(path: &Path) -> anyhow::Result<[Point2; 68]> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    parse_pts68(&text).with_context(|| format!("parsing {}", path.display()))
}

/// One annotated face before its image is decoded: what `eval` streams (decode, align, drop), so its memory
/// does not grow with the folder.
#[derive(Debug, Clone)]
pub struct Entry {
    /// `<subset>/<stem>` relative to the data root (or the stem for a flat folder).
    pub name: String,
    /// The image file.
    pub path: PathBuf,
    /// Ground-truth landmarks in image pixels, when a `.pts` file exists.
    pub landmarks: Option<[Point2; 68]>,
}

impl Entry {
    /// Decodes the image (bounded by the image-size limit of `holoface_sources::images`).
    pub fn image(&self) -> anyhow::Result<GrayImage> {
        Ok(read_gray(&self.path)?)
    }
}

/// Loads a folder of images with their `.pts` annotations.
///
/// With `require_landmarks`, a folder without any `.pts` file or an image without one is an error.
pub fn load_folder(root: &Path, split: Split, require_landmarks: bool) -> anyhow::Result<Vec<Sample>> {
    list_folder(root, split, require_landmarks)?
        .into_iter()
        .map(|e| {
            Ok(Sample {
                image: e.image()?,
                name: e.name,
                landmarks: e.landmarks,
            })
        })
        .collect()
}

/// The folder's annotated faces without decoding their images (see [`load_folder`]).
pub fn list_folder(root: &Path, split: Split, require_landmarks: bool) -> anyhow::Result<Vec<Entry>> {
    if !root.is_dir() {
        bail!(
            "data folder {} does not exist (set --data or HOLOFACE_DATA)",
            root.display()
        );
    }
    let val = validation_names();
    let mut out = Vec::new();
    for (name, path) in list_images(root)? {
        let keep = match split {
            Split::All => true,
            Split::Validation => val.contains(&name),
            Split::Train => !val.contains(&name),
        };
        if !keep {
            continue;
        }
        let pts_path = path.with_extension("pts");
        let landmarks = if pts_path.is_file() {
            Some(read_pts(&pts_path)?)
        } else if require_landmarks {
            bail!("{} has no annotation {}", path.display(), pts_path.display());
        } else {
            None
        };
        out.push(Entry {
            name,
            path,
            landmarks,
        });
    }
    if out.is_empty() {
        bail!("no images found in {} for the {:?} split", root.display(), split);
    }
    Ok(out)
}
