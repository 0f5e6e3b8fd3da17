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

use holoface_client::assets::{
    AssetPaths, CANDIDE_ENV, DEFAULT_ORT_DYLIB, DETECTOR_ENV, KRFWS_ENV, ORT_DYLIB_ENV,
};
use pyo3::prelude::*;

use crate::{AssetError, PyTrackerOptions};

/// Environment variable naming the user's holoface data folder.
pub(crate) const HOME_ENV: &str = "HOLOFACE_HOME";
/// The detector's file name in the package data.
const DETECTOR_FILE: &str = "face_detection_front_128x128.onnx";
/// The KRFWS model's file name in the package data.
const KRFWS_FILE: &str = "krfws.bin";
/// CANDIDE-3's file name in the data folder.
const CANDIDE_FILE: &str = "candide3.wfm";

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

/// The user's holoface data folder: `$HOLOFACE_HOME`, else `$XDG_DATA_HOME/holoface`, else
/// `~/.local/share/holoface` (it need not exist yet).
#[pyfunction]
pub(crate) fn data_dir() -> PyResult<PathBuf> {
    let var = |v: &str| std::env::var_os(v).filter(|s| !s.is_empty()).map(PathBuf::from);
    if let Some(home) = var(HOME_ENV) {
        return Ok(home);
    }
    if let Some(xdg) = var("XDG_DATA_HOME") {
        return Ok(xdg.join("holoface"));
    }
    var("HOME")
        .map(|h| h.join(".local/share/holoface"))
        .ok_or_else(|| {
            AssetError::new_err(format!("no data folder: set {HOME_ENV} (HOME is not set either)"))
        })
}

/// Checks that `path` is a CANDIDE-3 `.wfm` and copies it into [`data_dir`], where every tracker then finds
/// it; returns where it went.
#[pyfunction]
pub(crate) fn install_candide(py: Python<'_>, path: PathBuf) -> PyResult<PathBuf> {
    let dest = data_dir()?.join(CANDIDE_FILE);
    py.detach(|| -> Result<(), String> {
        holoface_client::assets::load_face_model(&path).map_err(|e| e.to_string())?;
        let bytes = std::fs::read(&path).map_err(|e| format!("reading {}: {e}", path.display()))?;
        holoface_sources::output::write_atomic(&dest, bytes).map_err(|e| format!("{e:#}"))
    })
    .map_err(AssetError::new_err)?;
    Ok(dest)
}

/// One asset's defaults: where an installed package looks when neither the option nor the variable is set.
struct Default {
    what: &'static str,
    var: &'static str,
    places: Vec<PathBuf>,
    fix: String,
}

/// Fills every asset path that neither `opts` nor its environment variable set with the installed
/// package's (see the module docs), or fails naming the places looked and the fix.
pub(crate) fn resolve(py: Python<'_>, opts: &PyTrackerOptions, assets: &mut AssetPaths) -> PyResult<()> {
    let pkg = package_dir(py);
    let ort_name = Path::new(DEFAULT_ORT_DYLIB)
        .file_name()
        .map_or_else(PathBuf::new, PathBuf::from);
    let in_pkg = |f: &str| pkg.iter().map(|p| p.join("assets").join(f)).collect::<Vec<_>>();
    let defaults = [
        (
            opts.ort_dylib.is_some(),
            &mut assets.ort_dylib,
            Default {
                what: "ONNX Runtime library",
                var: ORT_DYLIB_ENV,
                places: pkg
                    .iter()
                    .filter_map(|p| p.parent())
                    .map(|site| site.join("onnxruntime/capi").join(&ort_name))
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
