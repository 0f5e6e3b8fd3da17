//! Where the runtime's assets are and how they load: the ONNX Runtime library, the face detector, the KRFWS
//! model and CANDIDE-3. Each path is, in order: given explicitly, else named by its environment variable,
//! else its file in the holoface data folder (`$HOLOFACE_HOME`, else `$XDG_DATA_HOME/holoface`, else
//! `~/.local/share/holoface`), which `holoface setup` fills ([`holoface_files::home`], re-exported as
//! [`home`]). No default is relative to the working directory; the tools' options use the same variables.

use std::path::{Path, PathBuf};

pub use holoface_files::home;
pub use holoface_files::home::{Asset, HOME_ENV, MissingAsset, data_dir};
pub use holoface_inference::ORT_DYLIB_ENV;

/// Environment variable naming the BlazeFace model.
pub const DETECTOR_ENV: &str = home::DETECTOR.env;
/// Environment variable naming the KRFWS model.
pub const KRFWS_ENV: &str = home::KRFWS.env;
/// Environment variable naming the CANDIDE-3 `.wfm`.
pub const CANDIDE_ENV: &str = home::CANDIDE.env;

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

impl Default for AssetPaths {
    fn default() -> Self {
        Self {
            ort_dylib: home::ORT_LIBRARY.default_path(),
            detector: home::DETECTOR.default_path(),
            krfws: home::KRFWS.default_path(),
            candide: home::CANDIDE.default_path(),
        }
    }
}

/// Why an asset could not be loaded; the message names the asset and its path.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum AssetError {
    /// The file does not exist: the message says why that path was looked at and what installs the asset.
    #[error(transparent)]
    Missing(#[from] MissingAsset),
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

impl AssetError {
    /// Names the front end's setting of a missing asset (see [`MissingAsset::given_by`]).
    #[must_use]
    pub fn given_by(self, options: &[(Asset, &str)]) -> Self {
        match self {
            Self::Missing(m) => Self::Missing(m.given_by(options)),
            other => other,
        }
    }
}

fn read_asset(asset: &'static Asset, path: &Path) -> Result<Vec<u8>, AssetError> {
    use holoface_files::{FileError, read_bounded};
    let bytes = read_bounded(path, asset.max_bytes, asset.name).map_err(|e| match e {
        FileError::Missing { .. } => AssetError::Missing(asset.missing(path)),
        FileError::Io { source, .. } => AssetError::Read {
            asset: asset.name,
            path: path.to_owned(),
            source,
        },
        other => invalid(asset.name, path, other),
    })?;
    // The checksum `holoface setup` recorded beside the file, when there is one.
    holoface_inference::integrity::verify_sidecar(path, &bytes).map_err(|e| invalid(asset.name, path, e))?;
    Ok(bytes)
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
    parse_face_model(&read_asset(&home::CANDIDE, path)?, path)
}

/// Parses a CANDIDE-3 `.wfm` already read from `path` (named in errors).
pub fn parse_face_model(text: &[u8], path: &Path) -> Result<holoface_models::candide::FaceModel, AssetError> {
    const ASSET: &str = home::CANDIDE.name;
    let wfm = holoface_models::candide::Wfm::parse(&String::from_utf8_lossy(text))
        .map_err(|e| invalid(ASSET, path, e))?;
    holoface_models::candide::FaceModel::from_wfm(&wfm).map_err(|e| invalid(ASSET, path, e))
}

/// Loads the KRFWS model file.
pub fn load_krfws(path: &Path) -> Result<holoface_models::krfws::Krfws, AssetError> {
    const ASSET: &str = home::KRFWS.name;
    let bytes = read_asset(&home::KRFWS, path)?;
    holoface_models::krfws::Krfws::from_bytes(&bytes).map_err(|e| invalid(ASSET, path, e))
}
