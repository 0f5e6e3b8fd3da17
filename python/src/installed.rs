//! Where an installed `holoface` package finds its assets when neither a `TrackerOptions` field nor an
//! environment variable names them, so that `pip install holoface` works from any directory:
//!
//! * the ONNX Runtime library from the `onnxruntime` package the wheel depends on (pinned), beside this one
//!   in `site-packages`;
//! * the BlazeFace detector and the KRFWS model from the wheel's own package data (`holoface/assets/`);
//! * CANDIDE-3 from the user's data folder (`$HOLOFACE_HOME`, else `$XDG_DATA_HOME/holoface`, else
//!   `~/.local/share/holoface`): it is free for research use and not ours to redistribute, so
//!   [`install_candide`] copies it there from a file the user has.
//!
//! An asset found nowhere is an `AssetError` naming the asset, every place looked and the one step that
//! fixes it. Nothing here is relative to the repository or the working directory.

use std::path::{Path, PathBuf};

use holoface_headset_client::assets::{
    AssetPaths, CANDIDE_ENV, DETECTOR_ENV, KRFWS_ENV, ORT_DYLIB_ENV, home,
};
use pyo3::prelude::*;

use crate::{AssetError, PyTrackerOptions};

/// The detector's file name in the package data.
const DETECTOR_FILE: &str = home::DETECTOR.file;
/// The KRFWS model's file name in the package data.
const KRFWS_FILE: &str = home::KRFWS.file;
/// CANDIDE-3's file name in the data folder.
const CANDIDE_FILE: &str = home::CANDIDE.file;

/// The installed package's folder (where `_holoface` is).
fn package_dir(py: Python<'_>) -> Option<PathBuf> {
    let file: PathBuf = py
        .import("holoface._holoface")
        .ok()?
        .getattr("__file__")
        .ok()?
        .extract()
        .ok()?;
    file.parent().map(Path::to_path_buf)
}

fn env_set(var: &str) -> bool {
    std::env::var_os(var).is_some_and(|v| !v.is_empty())
}

/// The user's holoface data folder, shared with the `holoface` CLI and the server: `$HOLOFACE_HOME`, else
/// `$XDG_DATA_HOME/holoface`, else `~/.local/share/holoface` (it need not exist yet).
#[pyfunction]
pub(crate) fn data_dir() -> PyResult<PathBuf> {
    home::data_dir().ok_or_else(|| {
        AssetError::new_err(format!(
            "no data folder: set {} (XDG_DATA_HOME and HOME are not set either)",
            home::HOME_ENV
        ))
    })
}

/// Checks that `path` is a CANDIDE-3 `.wfm` and copies it into [`data_dir`], where every tracker then finds
/// it; returns where it went.
#[pyfunction]
pub(crate) fn install_candide(py: Python<'_>, path: PathBuf) -> PyResult<PathBuf> {
    let dest = data_dir()?.join(CANDIDE_FILE);
    py.detach(|| -> Result<(), String> {
        let bytes = std::fs::read(&path).map_err(|e| format!("reading {}: {e}", path.display()))?;
        holoface_headset_client::assets::parse_face_model(&bytes, &path).map_err(|e| e.to_string())?;
        holoface_sources::output::write_atomic(&dest, bytes, &holoface_sources::output::Temporaries::new())
            .map_err(|e| format!("{e:#}"))
    })
    .map_err(AssetError::new_err)?;
    Ok(dest)
}

/// One asset's defaults: where an installed package looks when neither the option nor the variable is set.
struct Default {
    what: &'static str,
    /// The `TrackerOptions` field that names it.
    field: &'static str,
    var: &'static str,
    places: Vec<PathBuf>,
    fix: String,
}

/// Fills every asset path that neither `opts` nor its environment variable set with the installed
/// package's (see the module docs), or fails naming the places looked and the fix.
pub(crate) fn resolve(py: Python<'_>, opts: &PyTrackerOptions, assets: &mut AssetPaths) -> PyResult<()> {
    let pkg = package_dir(py);
    let ort_name = home::ORT_LIBRARY.file;
    let in_pkg = |f: &str| pkg.iter().map(|p| p.join("assets").join(f)).collect::<Vec<_>>();
    let defaults = [
        (
            opts.ort_dylib.is_some(),
            &mut assets.ort_dylib,
            Default {
                what: "ONNX Runtime library",
                field: "ort_dylib",
                var: ORT_DYLIB_ENV,
                places: pkg
                    .iter()
                    .filter_map(|p| p.parent())
                    .map(|site| site.join("onnxruntime/capi").join(ort_name))
                    .collect(),
                fix: "pip install onnxruntime==1.31.1 (the holoface wheel depends on it), or set ORT_DYLIB_PATH"
                    .to_owned(),
            },
        ),
        (
            opts.detector_model.is_some(),
            &mut assets.detector,
            Default {
                what: "face detector model",
                field: "detector_model",
                var: DETECTOR_ENV,
                places: in_pkg(DETECTOR_FILE),
                fix: "reinstall the holoface wheel (it ships the model), or set HOLOFACE_DETECTOR_MODEL".to_owned(),
            },
        ),
        (
            opts.krfws_model.is_some(),
            &mut assets.krfws,
            Default {
                what: "KRFWS model",
                field: "krfws_model",
                var: KRFWS_ENV,
                places: in_pkg(KRFWS_FILE),
                fix: "reinstall the holoface wheel (it ships the model), or set HOLOFACE_KRFWS_MODEL".to_owned(),
            },
        ),
        (
            opts.candide.is_some(),
            &mut assets.candide,
            Default {
                what: "CANDIDE-3 model",
                field: "candide",
                var: CANDIDE_ENV,
                places: data_dir().map(|d| vec![d.join(CANDIDE_FILE)]).unwrap_or_default(),
                fix: "holoface.install_candide(\"/path/to/candide3.wfm\") (CANDIDE-3 is free for research use and \
                      not redistributed with holoface: get it from its authors), or set HOLOFACE_CANDIDE"
                    .to_owned(),
            },
        ),
    ];
    for (given, slot, d) in defaults {
        if given || env_set(d.var) {
            // Named explicitly: the fix is that name, not the data folder `holoface setup` fills.
            if !slot.is_file() {
                let by = if given {
                    format!("TrackerOptions.{}", d.field)
                } else {
                    format!("${}", d.var)
                };
                let default = d.places.first().map_or_else(
                    || "the installed package's".to_owned(),
                    |p| p.display().to_string(),
                );
                return Err(AssetError::new_err(format!(
                    "{} not found at {} (named by {by}); correct it, or leave it unset to use {default}",
                    d.what,
                    slot.display(),
                )));
            }
            continue;
        }
        match d.places.iter().find(|p| p.is_file()) {
            Some(found) => slot.clone_from(found),
            None => {
                let looked: Vec<String> = d.places.iter().map(|p| p.display().to_string()).collect();
                return Err(AssetError::new_err(format!(
                    "{} not found: looked in {} (${} is not set); {}",
                    d.what,
                    if looked.is_empty() {
                        "no installed package".to_owned()
                    } else {
                        looked.join(", ")
                    },
                    d.var,
                    d.fix
                )));
            }
        }
    }
    Ok(())
}
