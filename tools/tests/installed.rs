//! The CLI and the server as a user installs them (`cargo install --path tools` / `--path alignment-server`): copies of
//! the binaries in a temporary folder, run from another working directory with `HOME` pointed at a temporary
//! folder and no `HOLOFACE_*` or `ORT_*` variable. Before `holoface setup` every missing asset is an error
//! naming the data folder and the command; after it the CLI tracks the sample exactly as the checkout's build
//! does, and the installed server answers the installed CLI over QUIC.
#![allow(clippy::unwrap_used)]

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// A command for an installed binary: the environment a fresh user shell has (`PATH`, `HOME`, the TLS trust
/// store and proxy settings for the downloads), nothing of the checkout's.
fn installed(bin: &Path, home: &Path, work: &Path) -> Command {
    let mut cmd = Command::new(bin);
    cmd.env_clear()
        .current_dir(work)
        .env("HOME", home)
        .env("RUST_BACKTRACE", "0");
    for keep in [
        "PATH",
        "SSL_CERT_FILE",
        "SSL_CERT_DIR",
        "HTTPS_PROXY",
        "https_proxy",
        "ALL_PROXY",
        "all_proxy",
        "NO_PROXY",
        "no_proxy",
    ] {
        if let Some(v) = std::env::var_os(keep) {
            cmd.env(keep, v);
        }
    }
    cmd
}

fn output(cmd: &mut Command) -> (bool, String) {
    common::finished(&cmd.output().unwrap())
}

/// Copies a built binary into `bin/`, as `cargo install` would.
fn install(built: &Path, bin: &Path) -> PathBuf {
    assert!(
        built.is_file(),
        "{} is not built (cargo build -p holoface-alignment-server --profile test)",
        built.display()
    );
    let to = bin.join(built.file_name().unwrap());
    std::fs::copy(built, &to).unwrap();
    to
}

/// The landmarks of the first face of each frame of a `track` output.
fn landmarks(jsonl: &Path) -> Vec<serde_json::Value> {
    common::json_lines(jsonl)
        .iter()
        .map(|l| l["faces"][0]["landmarks_px"].clone())
        .collect()
}

/// The installed server's access token.
const TOKEN: &str = "installed-test-token";

/// Runs `cmd` with `frames` copies of the photo written to its standard input as a gray y4m stream, one per
/// 33 ms, as ffmpeg would from a camera.
fn live_camera(cmd: &mut Command, photo: &Path, frames: usize) -> (bool, String) {
    let image = holoface_sources::images::read_gray(photo).unwrap();
    let mut child = cmd
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let stdin = child.stdin.take().unwrap();
    let mut y4m = holoface_sources::y4m::Y4mWriter::new(stdin, image.width(), image.height(), 30, 1).unwrap();
    for _ in 0..frames {
        y4m.push(&image).unwrap();
        std::thread::sleep(std::time::Duration::from_millis(33));
    }
    drop(y4m.finish().unwrap());
    common::finished(&child.wait_with_output().unwrap())
}

#[test]
fn installed_binaries_find_their_assets_in_the_data_folder_after_setup() {
    let root = common::tmp("installed");
    let (bin, home, work) = (root.join("bin"), root.join("home"), root.join("work"));
    for d in [&bin, &home, &work] {
        std::fs::create_dir_all(d).unwrap();
    }
    let cli = install(Path::new(env!("CARGO_BIN_EXE_holoface")), &bin);
    let server = install(
        &Path::new(env!("CARGO_BIN_EXE_holoface")).with_file_name("holoface-server"),
        &bin,
    );
    let data = home.join(".local/share/holoface");

    // Before set-up: errors that name the asset, the data folder and the fix; no panic.
    let (ok, text) =
        output(installed(&server, &home, &work).args(["--listen", "127.0.0.1:0", "--token", TOKEN]));
    assert!(!ok, "{text}");
    for want in ["not found at", data.to_str().unwrap(), "holoface setup"] {
        assert!(
            text.contains(want),
            "server without assets: no {want:?} in {text}"
        );
    }
    let (ok, text) = output(installed(&cli, &home, &work).args(["demo", "--frames", "1"]));
    assert!(
        !ok && text.contains("demo sample image not found") && text.contains("holoface setup"),
        "{text}"
    );

    // Set-up: the pinned downloads (reused from the checkout's download folder when the Makefile names one),
    // our models, the user's CANDIDE-3.
    let candide = std::env::var_os("HOLOFACE_CANDIDE").map_or_else(
        || common::workspace().join("../shared/data/candide3/candide3.wfm"),
        PathBuf::from,
    );
    let mut setup = installed(&cli, &home, &work);
    setup.arg("setup").arg("--candide").arg(&candide);
    if let Some(dl) = std::env::var_os("HOLOFACE_DOWNLOADS") {
        setup.arg("--downloads").arg(dl);
    }
    let (ok, text) = output(&mut setup);
    assert!(ok, "{text}");
    for asset in [
        "libonnxruntime.so.1.31.1",
        "face_detection_front_128x128.onnx",
        "krfws.bin",
        "dan.onnx",
        "dan.int8.onnx",
        "refiner.bin",
        "candide3.wfm",
        "astronaut.png",
        "BLAZEFACE_LICENSE",
        "ONNXRUNTIME_LICENSE",
    ] {
        assert!(
            data.join(asset).is_file(),
            "{asset} not in {}: {text}",
            data.display()
        );
    }
    // A second run has nothing to do.
    let (ok, again) = output(installed(&cli, &home, &work).arg("setup"));
    assert!(
        ok && !again.contains("downloading") && !again.contains(" installed"),
        "{again}"
    );

    // The installed CLI tracks the sample as the checkout's build does with the checkout's assets.
    let frames = work.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    std::fs::copy(data.join("astronaut.png"), frames.join("000.png")).unwrap();
    let (ok, text) =
        output(installed(&cli, &home, &work).args(["track", "--source", "frames", "--log", "warn"]));
    assert!(ok, "{text}");
    let here = landmarks(&work.join("runs/track.jsonl"));
    assert!(here[0].is_array(), "no face found: {here:?}");
    let checkout_out = root.join("checkout.jsonl");
    let (ok, text) = common::holoface(&[
        "track",
        "--source",
        frames.to_str().unwrap(),
        "--out",
        checkout_out.to_str().unwrap(),
        "--log",
        "warn",
    ]);
    assert!(ok, "{text}");
    assert_eq!(here, landmarks(&checkout_out));

    // The installed server answers the installed CLI over QUIC: a live camera (y4m on standard input, paced
    // at 30 fps, long enough for the client's 1 s of healthy probes before it trusts the link).
    let mut child = installed(&server, &home, &work)
        .args(["--listen", "127.0.0.1:0", "--token", TOKEN, "--log-level", "warn"])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    // Its first line says where it listens (or it exits); a server that hangs fails the test after a minute.
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let _ = BufReader::new(stdout).read_line(&mut line);
        let _ = tx.send(line);
    });
    let first = rx
        .recv_timeout(std::time::Duration::from_secs(60))
        .unwrap_or_default();
    let words: Vec<&str> = first.split_whitespace().collect();
    let (addr, fingerprint) = match words.as_slice() {
        ["holoface-server", "on", addr, "certificate-sha256", fp, ..] => (addr.to_string(), fp.to_string()),
        _ => {
            let _ = child.kill();
            panic!("server did not start: {first:?}");
        }
    };
    let mut track = installed(&cli, &home, &work);
    track.args([
        "track",
        "--source",
        "-",
        "--aligner",
        "remote",
        "--server",
        &addr,
        "--fingerprint",
        &fingerprint,
        "--token",
        TOKEN,
        "--deadline-ms",
        "2000",
        "--out",
        "remote.jsonl",
        "--log",
        "warn",
    ]);
    let result = live_camera(&mut track, &data.join("astronaut.png"), 75);
    let _ = child.kill();
    let _ = child.wait();
    let (ok, text) = result;
    assert!(ok, "{text}");
    let remote = common::json_lines(&work.join("remote.jsonl"))
        .iter()
        .filter(|l| {
            l["faces"][0]["aligner"]
                .as_str()
                .is_some_and(|a| a.starts_with("remote"))
        })
        .count();
    assert!(remote > 0, "the installed server answered no frame: {text}");

    // Without CANDIDE-3 in the data folder, `setup` asks for it, unless $HOLOFACE_CANDIDE already names a copy
    // (the checkout's Makefile does): then it says which one the runtime reads.
    std::fs::remove_file(data.join("candide3.wfm")).unwrap();
    let (ok, text) = output(installed(&cli, &home, &work).arg("setup"));
    assert!(ok && text.contains(holoface_files::home::CANDIDE.setup), "{text}");
    let (ok, text) = output(
        installed(&cli, &home, &work)
            .arg("setup")
            .env("HOLOFACE_CANDIDE", &candide),
    );
    assert!(
        ok && text.contains("$HOLOFACE_CANDIDE")
            && text.contains(candide.to_str().unwrap())
            && !text.contains(holoface_files::home::CANDIDE.setup),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&root);
}
