//! The ONNX Runtime library and the process-wide environment.
//!
//! ONNX Runtime allows one environment per process, ever; [`load_runtime`] creates it on first use and hands
//! the same one to every later caller (the server's engines and the client's face detector alike). The
//! library is found at an explicit path, else `$ORT_DYLIB_PATH`, else in the holoface data folder
//! ([`default_ort_dylib`], [`crate::home`]).

use std::path::{Path, PathBuf};

use crate::error::EngineError;

/// The environment variable that names the ONNX Runtime library (the `ort` crate's convention).
pub const ORT_DYLIB_ENV: &str = crate::home::ORT_LIBRARY.env;
/// The name ONNX Runtime logs for this process's environment.
const ENVIRONMENT_NAME: &str = "holoface";

/// `$ORT_DYLIB_PATH` when set and not empty, else `libonnxruntime.so.1.31.1` in the data folder.
pub fn default_ort_dylib() -> PathBuf {
    crate::home::ORT_LIBRARY.default_path()
}

/// The process's ONNX Runtime environment: ort allows one per process, ever,
/// so it is created once and shared by every engine.
static ENVIRONMENT: std::sync::Mutex<Option<ort::environment::Environment>> = std::sync::Mutex::new(None);

/// Loads the ONNX Runtime library (once per process; later calls reuse the
/// first library) and returns the shared environment. ONNX Runtime allows one
/// environment per process; every session of the process shares this one.
pub fn load_runtime(dylib: &Path) -> Result<ort::environment::Environment, EngineError> {
    if dylib.is_dir() {
        return Err(EngineError::RuntimeIsDirectory {
            path: dylib.to_path_buf(),
        });
    }
    if !dylib.is_file() {
        return Err(EngineError::RuntimeMissing {
            path: dylib.to_path_buf(),
        });
    }
    let mut slot = ENVIRONMENT
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(env) = slot.as_ref() {
        return Ok(env.clone());
    }
    let builder = ort::init_from(dylib).map_err(|e| EngineError::RuntimeLoad {
        path: dylib.to_path_buf(),
        detail: e.to_string(),
    })?;
    let env = builder.with_name(ENVIRONMENT_NAME).build()?;
    *slot = Some(env.clone());
    Ok(env)
}
