//! The ONNX Runtime library and the process-wide environment.
//!
//! ONNX Runtime allows one environment per process, ever; [`load_runtime`] creates it on first use and hands
//! the same one to every later caller (the server's engines and the client's face detector alike). The
//! library is found at an explicit path, else `$ORT_DYLIB_PATH`, else in the holoface data folder
//! ([`default_ort_dylib`], `holoface_files::home`).

use std::path::{Path, PathBuf};

use crate::error::EngineError;

/// The environment variable that names the ONNX Runtime library (the `ort` crate's convention).
pub const ORT_DYLIB_ENV: &str = holoface_files::home::ORT_LIBRARY.env;
/// The name ONNX Runtime logs for this process's environment.
const ENVIRONMENT_NAME: &str = "holoface";

/// `$ORT_DYLIB_PATH` when set and not empty, else `libonnxruntime.so.1.31.1` in the data folder.
pub fn default_ort_dylib() -> PathBuf {
    holoface_files::home::ORT_LIBRARY.default_path()
}

/// The process's ONNX Runtime environment and the library it came from (canonical path): ort allows one per
/// process, ever, so it is created once and shared by every engine.
static ENVIRONMENT: std::sync::Mutex<Option<(PathBuf, ort::environment::Environment)>> =
    std::sync::Mutex::new(None);

/// Loads the ONNX Runtime library (once per process) and returns the shared environment. ONNX Runtime
/// allows one environment per process; every session of the process shares this one. A later call with
/// the same library (by any path to it) gets that environment; one with another library is refused
/// ([`EngineError::RuntimeAlreadyLoaded`]) rather than silently given the first.
pub fn load_runtime(dylib: &Path) -> Result<ort::environment::Environment, EngineError> {
    if dylib.is_dir() {
        return Err(EngineError::RuntimeIsDirectory {
            path: dylib.to_path_buf(),
        });
    }
    if !dylib.is_file() {
        return Err(holoface_files::home::ORT_LIBRARY.missing(dylib).into());
    }
    let mut slot = ENVIRONMENT
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let canonical = std::fs::canonicalize(dylib).unwrap_or_else(|_| dylib.to_path_buf());
    if let Some((loaded, env)) = slot.as_ref() {
        if *loaded != canonical {
            return Err(EngineError::RuntimeAlreadyLoaded {
                loaded: loaded.clone(),
                asked: dylib.to_path_buf(),
            });
        }
        return Ok(env.clone());
    }
    // A truncated or foreign file would be mapped by the dynamic loader and kill the process (SIGBUS) the
    // first time a missing page is touched: its ELF headers are checked against its size first.
    check_shared_library(dylib).map_err(|detail| EngineError::RuntimeLoad {
        path: dylib.to_path_buf(),
        detail: format!("{detail}; reinstall it with `{}`", holoface_files::home::SETUP),
    })?;
    let builder = ort::init_from(dylib).map_err(|e| EngineError::RuntimeLoad {
        path: dylib.to_path_buf(),
        detail: e.to_string(),
    })?;
    let env = builder.with_name(ENVIRONMENT_NAME).build()?;
    *slot = Some((canonical, env.clone()));
    Ok(env)
}

/// The ELF machine number of this build's target.
const ELF_MACHINE: u16 = if cfg!(target_arch = "x86_64") {
    62
} else if cfg!(target_arch = "aarch64") {
    183
} else {
    0
};

/// Checks that `path` is a whole 64-bit little-endian ELF shared library for this machine: the header, every
/// loadable segment and the section headers lie within the file (a truncated copy fails here instead of
/// being mapped), and it carries ONNX Runtime's API entry point. Also refuses anything that is not a regular
/// file, and files that are far too large, before reading.
pub fn check_shared_library(path: &Path) -> Result<(), String> {
    use std::io::{Read as _, Seek as _, SeekFrom};
    let meta = holoface_files::regular_file(path, "ONNX Runtime library").map_err(|e| e.to_string())?;
    let len = meta.len();
    if len > holoface_files::home::ORT_LIBRARY.max_bytes {
        return Err(format!("{len} bytes, more than any ONNX Runtime library"));
    }
    let mut f = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut h = [0u8; 64];
    f.read_exact(&mut h)
        .map_err(|_| format!("only {len} bytes: not a shared library (truncated?)"))?;
    if h[..4] != *b"\x7fELF" {
        return Err("not an ELF file".into());
    }
    if h[4] != 2 || h[5] != 1 {
        return Err("not a 64-bit little-endian ELF file".into());
    }
    let u16_at = |b: &[u8], i: usize| u16::from_le_bytes([b[i], b[i + 1]]);
    let u64_at = |b: &[u8], i: usize| {
        let mut a = [0u8; 8];
        a.copy_from_slice(&b[i..i + 8]);
        u64::from_le_bytes(a)
    };
    if u16_at(&h, 16) != 3 {
        return Err("an ELF file but not a shared library".into());
    }
    let machine = u16_at(&h, 18);
    if ELF_MACHINE != 0 && machine != ELF_MACHINE {
        return Err(format!(
            "built for ELF machine {machine}, this one is {ELF_MACHINE}"
        ));
    }
    let (phoff, shoff) = (u64_at(&h, 32), u64_at(&h, 40));
    let (phentsize, phnum) = (u64::from(u16_at(&h, 54)), u64::from(u16_at(&h, 56)));
    let (shentsize, shnum) = (u64::from(u16_at(&h, 58)), u64::from(u16_at(&h, 60)));
    let truncated =
        |what: &str, end: u64| format!("{what} ends at byte {end} but the file has {len}: truncated");
    let ph_end = phoff.saturating_add(phentsize.saturating_mul(phnum));
    if phentsize < 56 || ph_end > len {
        return Err(truncated("the program header table", ph_end));
    }
    let sh_end = shoff.saturating_add(shentsize.saturating_mul(shnum));
    if sh_end > len {
        return Err(truncated("the section header table", sh_end));
    }
    let mut ph = vec![0u8; usize::try_from(phentsize * phnum).map_err(|e| e.to_string())?];
    f.seek(SeekFrom::Start(phoff)).map_err(|e| e.to_string())?;
    f.read_exact(&mut ph).map_err(|e| e.to_string())?;
    for seg in ph.chunks_exact(phentsize as usize) {
        // PT_LOAD: p_offset at 8, p_filesz at 32.
        let end = u64_at(seg, 8).saturating_add(u64_at(seg, 32));
        if u32::from_le_bytes([seg[0], seg[1], seg[2], seg[3]]) == 1 && end > len {
            return Err(truncated("a loadable segment", end));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn truncated_or_foreign_libraries_are_refused_before_mapping() {
        let dir = std::env::temp_dir().join(format!("holoface-elf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // A real shared library of this machine passes; cut in half, it is refused by name.
        // This machine's own first: an x86-64 machine that runs the aarch64 tests under qemu has both.
        let real = [
            format!("/lib/{}-linux-gnu/libc.so.6", std::env::consts::ARCH),
            "/usr/lib/libc.so.6".to_owned(),
        ]
        .into_iter()
        .map(PathBuf::from)
        .find(|p| p.is_file());
        if let Some(real) = real {
            check_shared_library(&real).unwrap();
            let bytes = std::fs::read(&real).unwrap();
            let cut = dir.join("libcut.so");
            std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
            let err = check_shared_library(&cut).unwrap_err();
            assert!(err.contains("truncated"), "{err}");
        }
        let text = dir.join("notes.so");
        std::fs::write(
            &text,
            "not a library at all, just some text padding it out to more than 64 bytes.....",
        )
        .unwrap();
        assert_eq!(check_shared_library(&text).unwrap_err(), "not an ELF file");
        std::fs::write(&text, "short").unwrap();
        assert!(check_shared_library(&text).unwrap_err().contains("truncated"));
        assert!(
            check_shared_library(Path::new("/dev/zero"))
                .unwrap_err()
                .contains("character device")
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
