//! Where the runtime's assets are and how they load: the ONNX Runtime library, the face detector, the KRFWS
//! model and CANDIDE-3. Each path has a default (where the set-up command puts it) and an environment
//! variable that overrides it; the tools' command-line options use the same names and defaults.

use std::path::{Path, PathBuf};

pub use holoface_inference::{DEFAULT_ORT_DYLIB, ORT_DYLIB_ENV};

/// Environment variable naming the BlazeFace model.
pub const DETECTOR_ENV: &str = "HOLOFACE_DETECTOR_MODEL";
/// Where `make setup` puts the BlazeFace model.
pub const DEFAULT_DETECTOR: &str = ".cache/blazeface/face_detection_front_128x128.onnx";
/// Environment variable naming the KRFWS model.
pub const KRFWS_ENV: &str = "HOLOFACE_KRFWS_MODEL";
/// The shipped KRFWS model.
pub const DEFAULT_KRFWS: &str = "models/assets/krfws.bin";
/// Environment variable naming the DAN model (in-process DAN, tools only).
pub const DAN_ENV: &str = "HOLOFACE_DAN_MODEL";
/// The shipped DAN model.
pub const DEFAULT_DAN: &str = "models/assets/dan.onnx";
/// Environment variable naming the CANDIDE-3 `.wfm`.
pub const CANDIDE_ENV: &str = "HOLOFACE_CANDIDE";
/// Where the set-up command finds CANDIDE-3.
pub const DEFAULT_CANDIDE: &str = "../shared/data/candide3/candide3.wfm";

/// Where the runtime assets are; the defaults follow the environment variables above.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct AssetPaths {
    /// ONNX Runtime shared library (`ORT_DYLIB_PATH`).
    pub ort_dylib: PathBuf,
    /// BlazeFace model (`HOLOFACE_DETECTOR_MODEL`).
    pub detector: PathBuf,
    /// KRFWS model (`HOLOFACE_KRFWS_MODEL`).
    pub krfws: PathBuf,
    /// CANDIDE-3 `.wfm` (`HOLOFACE_CANDIDE`).
    pub candide: PathBuf,
}

/// `$var` when set and not empty, else `default`.
pub fn env_path(var: &str, default: &str) -> PathBuf {
    std::env::var_os(var)
        .filter(|v| !v.is_empty())
        .map_or_else(|| default.into(), PathBuf::from)
}

impl Default for AssetPaths {
    fn default() -> Self {
        Self {
            ort_dylib: env_path(ORT_DYLIB_ENV, DEFAULT_ORT_DYLIB),
            detector: env_path(DETECTOR_ENV, DEFAULT_DETECTOR),
            krfws: env_path(KRFWS_ENV, DEFAULT_KRFWS),
            candide: env_path(CANDIDE_ENV, DEFAULT_CANDIDE),
        }
    }
}

/// Why an asset could not be loaded; the message names the asset and its path.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AssetError {
    /// The file could not be read (missing, unreadable).
    #[error("reading {asset} {}: {source}", path.display())]
    Read {
        /// Which asset (e.g. "KRFWS model").
        asset: &'static str,
        /// Where it was looked for.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// The file was read but is not a valid asset of its kind (corrupt, truncated, wrong version).
    #[error("loading {asset} {}: {reason}", path.display())]
    Invalid {
        /// Which asset.
        asset: &'static str,
        /// Its path.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
}

fn read_asset(asset: &'static str, path: &Path) -> Result<Vec<u8>, AssetError> {
    std::fs::read(path).map_err(|source| AssetError::Read {
        asset,
        path: path.to_owned(),
        source,
    })
}

fn invalid(asset: &'static str, path: &Path, reason: impl std::fmt::Display) -> AssetError {
    AssetError::Invalid {
        asset,
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

/// Loads the CANDIDE-3 face model from a `.wfm` file.
pub fn load_face_model(path: &Path) -> Result<holoface_models::candide::FaceModel, AssetError> {
    const ASSET: &str = "CANDIDE-3 model";
    let text = read_asset(ASSET, path)?;
    let wfm = holoface_models::candide::Wfm::parse(&String::from_utf8_lossy(&text))
        .map_err(|e| invalid(ASSET, path, e))?;
    holoface_models::candide::FaceModel::from_wfm(&wfm).map_err(|e| invalid(ASSET, path, e))
}

/// Loads the KRFWS model file.
pub fn load_krfws(path: &Path) -> Result<holoface_models::krfws::Krfws, AssetError> {
    const ASSET: &str = "KRFWS model";
    let bytes = read_asset(ASSET, path)?;
    holoface_models::krfws::Krfws::from_bytes(&bytes).map_err(|e| invalid(ASSET, path, e))
}
