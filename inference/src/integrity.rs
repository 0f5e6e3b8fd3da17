//! Model-file integrity: a file is checked before anyone is answered with it.
//!
//! * **Sidecar checksums.** `holoface setup` writes `<file>.sha256` (the `sha256sum` format) beside every
//!   file it installs; [`verify_sidecar`] compares a file with its sidecar when there is one, so a file
//!   damaged on disk after it was installed is refused with the expected and the found checksum and how to
//!   restore it. (`sha256sum -c dan.onnx.sha256` checks the same by hand.)
//! * **Known releases.** The DAN models this project shipped are listed with their checksums
//!   ([`KNOWN_MODELS`]): a file whose metadata names one of them but whose bytes differ is damaged, sidecar or
//!   not.
//! * **Self-test.** [`self_test`] runs a loaded engine on a fixed synthetic crop: every output must be finite,
//!   the face probability within [0, 1] and the landmarks near the crop; for a known release, within
//!   [`SELF_TEST_TOLERANCE_PX`] of the answer recorded for it. A model whose weights were changed in a way
//!   that keeps its metadata (one weight set to 1e30) answers garbage here and is refused at start-up.

use std::path::{Path, PathBuf};

use crate::contract::{BatchTensor, InferenceEngine, LandmarkOut};
use crate::error::EngineError;

/// The sidecar of `path`: `dan.onnx` -> `dan.onnx.sha256`.
pub fn sidecar_path(path: &Path) -> PathBuf {
    let mut s = path.as_os_str().to_owned();
    s.push(".sha256");
    PathBuf::from(s)
}

/// Lower-case hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use std::fmt::Write as _;
    ring::digest::digest(&ring::digest::SHA256, bytes)
        .as_ref()
        .iter()
        .fold(String::with_capacity(64), |mut s, b| {
            let _ = write!(s, "{b:02x}");
            s
        })
}

/// The sidecar's text for a file installed as `file_name` whose SHA-256 is `sha` (`sha256sum`'s format).
pub fn sidecar_text(file_name: &str, sha: &str) -> String {
    format!("{sha}  {file_name}\n")
}

/// What the sidecar of a file says, if there is a readable one.
fn sidecar_sha(path: &Path) -> Result<Option<String>, EngineError> {
    let side = sidecar_path(path);
    let text = match std::fs::metadata(&side) {
        Err(_) => return Ok(None),
        Ok(m) if !m.is_file() || m.len() > 4096 => {
            return Err(EngineError::Damaged {
                path: path.to_path_buf(),
                detail: format!("its checksum file {} is not a small regular file", side.display()),
            });
        }
        Ok(_) => std::fs::read_to_string(&side).map_err(|e| EngineError::Damaged {
            path: path.to_path_buf(),
            detail: format!("reading its checksum file {}: {e}", side.display()),
        })?,
    };
    let sha = text
        .split_ascii_whitespace()
        .next()
        .unwrap_or_default()
        .to_ascii_lowercase();
    if sha.len() != 64 || !sha.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(EngineError::Damaged {
            path: path.to_path_buf(),
            detail: format!("its checksum file {} does not hold a SHA-256", side.display()),
        });
    }
    Ok(Some(sha))
}

/// Compares `bytes` (the content of `path`) with the sidecar checksum, when `path` has one.
pub fn verify_sidecar(path: &Path, bytes: &[u8]) -> Result<(), EngineError> {
    let Some(expected) = sidecar_sha(path)? else {
        return Ok(());
    };
    let found = sha256_hex(bytes);
    if found != expected {
        return Err(EngineError::Damaged {
            path: path.to_path_buf(),
            detail: format!(
                "SHA-256 {found}, but {} records {expected}",
                sidecar_path(path).display()
            ),
        });
    }
    Ok(())
}

/// A DAN model this project shipped.
#[derive(Clone, Copy, Debug)]
pub struct KnownModel {
    /// `holoface.name`.
    pub name: &'static str,
    /// `holoface.version`.
    pub version: &'static str,
    /// `holoface.precision`.
    pub precision: &'static str,
    /// SHA-256 of the file.
    pub sha256: &'static str,
    /// Its answer on [`self_test_crop`]: face probability, then the mean x and y of its landmarks and the
    /// nose tip (point 30), crop pixels.
    pub self_test: [f32; 5],
}

/// The shipped DAN models, newest first (`models/assets/dan.onnx` is the first; a test keeps it equal to the
/// committed file). Older releases stay, so that a data folder installed by an older `holoface setup` still
/// verifies.
pub const KNOWN_MODELS: &[KnownModel] = &[
    KnownModel {
        name: "holoface-dan",
        version: "0.4.0",
        precision: "fp32",
        sha256: "01269b68e38377bec48e6a267ca24b6f0c45608a721b3614ee0f094e4b64b1a1",
        self_test: [0.157_111_6, 61.585_55, 61.030_037, 67.124_61, 60.174_355],
    },
    // `models/assets/dan.int8.onnx`, quantised from the release above (`make dan-int8`).
    KnownModel {
        name: "holoface-dan",
        version: "0.4.0",
        precision: "int8",
        sha256: "8262860abed29d588665a2d00831f4f747b22fb0ecfac3af155795f4d2f49d9b",
        self_test: [0.137_254_9, 62.370_506, 61.856_014, 68.379_14, 60.872_463],
    },
    KnownModel {
        name: "holoface-dan",
        version: "0.3.0",
        precision: "fp32",
        sha256: "e0a26bc0fe0445d74a971d9ad7a39db96b132c364037ca534ad9ab2297f89863",
        self_test: [0.031_045, 59.169_86, 63.416_6, 64.161_19, 62.172_12],
    },
];

/// How far a known model's self-test answer may be from the recorded one (crop pixels; GPU and CPU
/// arithmetic differ by far less).
pub const SELF_TEST_TOLERANCE_PX: f32 = 0.5;

/// The release a model's metadata names, if it is one of [`KNOWN_MODELS`].
pub fn known(name: &str, version: &str, precision: &str) -> Option<&'static KnownModel> {
    KNOWN_MODELS
        .iter()
        .find(|k| k.name == name && k.version == version && k.precision == precision)
}

/// Checks a known release's bytes against its recorded checksum.
pub fn verify_known(path: &Path, model: &KnownModel, bytes: &[u8]) -> Result<(), EngineError> {
    let found = sha256_hex(bytes);
    if found != model.sha256 {
        return Err(EngineError::Damaged {
            path: path.to_path_buf(),
            detail: format!(
                "its metadata says {} {} but its SHA-256 is {found}, not the release's {}",
                model.name, model.version, model.sha256
            ),
        });
    }
    Ok(())
}

/// The fixed synthetic crop of the self-test: a smooth gray pattern (`size`² bytes).
pub fn self_test_crop(size: usize) -> Vec<u8> {
    (0..size * size)
        .map(|i| {
            let (x, y) = ((i % size) as f64, (i / size) as f64);
            (128.0 + 60.0 * (x / 7.0).sin() * (y / 9.0).cos()).round() as u8
        })
        .collect()
}

/// The summary of an answer compared by the self-test (see [`KnownModel::self_test`]).
pub fn self_test_summary(out: &LandmarkOut) -> [f32; 5] {
    let n = out.landmarks.len().max(1) as f32;
    let mx = out.landmarks.iter().map(|p| p[0]).sum::<f32>() / n;
    let my = out.landmarks.iter().map(|p| p[1]).sum::<f32>() / n;
    let nose = out.landmarks.get(30).copied().unwrap_or([mx, my]);
    [out.face_prob, mx, my, nose[0], nose[1]]
}

/// Runs `engine` once on [`self_test_crop`]: its answer must be finite, a probability and landmarks near
/// the crop, and, for a known release (`known`), the recorded answer. `path` names the model in errors.
pub fn self_test<E: InferenceEngine + ?Sized>(
    engine: &mut E,
    path: &Path,
    known: Option<&KnownModel>,
) -> Result<(), EngineError> {
    let size = engine.info().crop_size;
    let mut batch = BatchTensor::new(1, size * size);
    batch.push(&self_test_crop(size))?;
    let mut out = vec![LandmarkOut::default(); 1];
    engine.infer(&batch, &mut out)?;
    let o = &out[0];
    let s = size as f32;
    let fail = |detail: String| EngineError::SelfTest {
        path: path.to_path_buf(),
        detail,
    };
    if !o.face_prob.is_finite() || !(0.0..=1.0).contains(&o.face_prob) {
        return Err(fail(format!("face probability {} on the test crop", o.face_prob)));
    }
    if let Some((i, p)) = o.landmarks.iter().enumerate().find(|(_, p)| {
        !(p[0].is_finite() && p[1].is_finite()) || p[0].abs() > 2.0 * s || p[1].abs() > 2.0 * s
    }) {
        return Err(fail(format!(
            "landmark {i} at ({}, {}) on a {size}-px test crop",
            p[0], p[1]
        )));
    }
    if let Some(k) = known {
        let got = self_test_summary(o);
        let bad = got
            .iter()
            .zip(&k.self_test)
            .enumerate()
            .any(|(i, (g, e))| (g - e).abs() > if i == 0 { 0.05 } else { SELF_TEST_TOLERANCE_PX });
        if bad {
            // ONNX Runtime's int8 kernels for CPUs without VNNI (AVX2's and AVX-512BW's u8 x s8 products)
            // saturate in 16 bits: there the int8 model is refused for its answers, not for its file.
            let cpu = crate::cpu::CpuInt8::detect();
            let why = if cfg!(target_arch = "x86_64") && engine.info().precision == "int8" && !cpu.has_vnni()
            {
                format!(
                    "this CPU ({}) has no VNNI, where ONNX Runtime's int8 kernels saturate: serve fp32 here \
                     (engine.precision = \"fp32\", or \"auto\", which picks int8 only with VNNI); ",
                    cpu.label()
                )
            } else {
                String::new()
            };
            return Err(fail(format!(
                "{why}answered {got:?} on the test crop, {} {} answers {:?}",
                k.name, k.version, k.self_test
            )));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sidecars_catch_a_changed_byte_and_say_how_to_restore() {
        let dir = std::env::temp_dir().join(format!("holoface-integrity-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("model.bin");
        let bytes = b"some model bytes".to_vec();
        // No sidecar: nothing to compare.
        verify_sidecar(&path, &bytes).unwrap();
        std::fs::write(
            sidecar_path(&path),
            sidecar_text("model.bin", &sha256_hex(&bytes)),
        )
        .unwrap();
        verify_sidecar(&path, &bytes).unwrap();
        let mut bad = bytes.clone();
        bad[3] ^= 1;
        let err = verify_sidecar(&path, &bad).unwrap_err().to_string();
        assert!(
            err.contains("model.bin") && err.contains("holoface setup"),
            "{err}"
        );
        std::fs::write(sidecar_path(&path), "not a checksum").unwrap();
        assert!(
            verify_sidecar(&path, &bytes)
                .unwrap_err()
                .to_string()
                .contains("does not hold")
        );
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn the_known_int8_release_is_the_committed_file() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/assets/dan.int8.onnx");
        let bytes = std::fs::read(&path).unwrap();
        let k = known("holoface-dan", "0.4.0", "int8").expect("the int8 release is known");
        verify_known(&path, k, &bytes).unwrap();
    }

    #[test]
    fn the_known_release_is_the_committed_file() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/assets/dan.onnx");
        let bytes = std::fs::read(&path).unwrap();
        let k = &KNOWN_MODELS[0];
        verify_known(&path, k, &bytes).unwrap();
        let mut bad = bytes;
        let at = bad.len() / 2;
        bad[at] ^= 0x40;
        let err = verify_known(&path, k, &bad).unwrap_err().to_string();
        assert!(err.contains("not the release's"), "{err}");
    }
}
