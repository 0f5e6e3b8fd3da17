//! Helpers shared by the client's integration tests.
#![allow(clippy::unwrap_used, dead_code)]

use std::path::{Path, PathBuf};
use std::process::Command;

/// The workspace root (the binary runs there, like a user after `make setup`).
pub(crate) fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// Runs the `holoface` binary; returns success and stdout + stderr. Fails the test on a panic.
pub(crate) fn holoface(args: &[&str]) -> (bool, String) {
    holoface_with_stdin(args, None)
}

/// [`holoface`] with standard input read from `stdin` (none: inherited).
pub(crate) fn holoface_with_stdin(args: &[&str], stdin: Option<&Path>) -> (bool, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_holoface"));
    cmd.args(args).current_dir(workspace()).env("RUST_BACKTRACE", "0");
    if let Some(path) = stdin {
        cmd.stdin(std::fs::File::open(path).unwrap());
    }
    finished(&cmd.output().unwrap())
}

/// A finished command's success and stdout + stderr. Fails the test on a panic.
pub(crate) fn finished(out: &std::process::Output) -> (bool, String) {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!text.contains("panicked"), "panic: {text}");
    (out.status.success(), text)
}

/// A fresh, empty temporary folder unique to this process and `name`.
pub(crate) fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("holoface-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Parses a JSON-lines file.
pub(crate) fn json_lines(path: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// A small textured grey PNG (no face in it).
pub(crate) fn write_png(path: &Path, w: u32, h: u32) {
    let px: Vec<u8> = (0..w * h).map(|i| (i % 251) as u8).collect();
    image::save_buffer(path, &px, w, h, image::ExtendedColorType::L8).unwrap();
}
