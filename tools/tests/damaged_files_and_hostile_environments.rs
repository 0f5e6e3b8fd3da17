//! Damaged files and hostile surroundings, each as the user or operator meets them: a damaged model, a
//! truncated ONNX Runtime library, files that are devices, pipes or link loops, a closed standard output,
//! interrupted commands and a stalled download (found by an outside probe, issue 40; each failed before its
//! fix).
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::{finished, holoface, tmp, workspace, write_png};

/// A folder with one annotated (meaningless) face for `eval --init gt-box`.
fn one_face(tag: &str) -> PathBuf {
    let d = tmp(tag);
    write_png(&d.join("c.png"), 64, 64);
    let pts: String = (0..68)
        .map(|i| format!("{} {}\n", 10 + i % 40, 20 + i % 7))
        .collect();
    std::fs::write(d.join("c.pts"), pts).unwrap();
    d
}

fn eval_args(d: &Path, aligner: &str, extra: &[&str]) -> Vec<String> {
    let (out, plot) = (d.join("eval.json"), d.join("ced.png"));
    let mut v: Vec<String> = [
        "eval",
        "--data",
        d.to_str().unwrap(),
        "--init",
        "gt-box",
        "--aligner",
        aligner,
    ]
    .iter()
    .map(|s| (*s).to_owned())
    .collect();
    v.extend(["--out".to_owned(), out.to_string_lossy().into_owned()]);
    v.extend(["--plot".to_owned(), plot.to_string_lossy().into_owned()]);
    v.extend(extra.iter().map(|s| (*s).to_owned()));
    v
}

fn run(args: &[String]) -> (bool, String) {
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    holoface(&refs)
}

fn ort_library() -> PathBuf {
    std::env::var_os("ORT_DYLIB_PATH").map_or_else(
        || workspace().join(".cache/holoface/libonnxruntime.so.1.31.1"),
        PathBuf::from,
    )
}

/// Finding 2: a DAN model with one byte changed was served, answering NME 1e28 %.
#[test]
fn a_damaged_dan_model_is_refused_naming_the_file_and_the_fix() {
    let d = one_face("damaged-dan");
    let mut bytes = std::fs::read(workspace().join("models/assets/dan.onnx")).unwrap();
    let at = bytes.len() / 2;
    bytes[at] ^= 0x5a;
    let bad = d.join("dan.onnx");
    std::fs::write(&bad, &bytes).unwrap();
    let (ok, text) = run(&eval_args(&d, "dan", &["--dan-model", bad.to_str().unwrap()]));
    assert!(!ok, "{text}");
    assert!(
        text.contains("dan.onnx is damaged") && text.contains("holoface setup"),
        "{text}"
    );
    // A missing file: the message names this command's own options, not the server's or another tool's.
    let gone = d.join("gone.onnx");
    let (ok, text) = run(&eval_args(&d, "dan", &["--dan-model", gone.to_str().unwrap()]));
    assert!(!ok, "{text}");
    assert!(
        text.contains("DAN model not found at") && text.contains("(the path given with --dan-model)"),
        "{text}"
    );
    assert!(
        !text.contains("engine.model") && !text.contains("--model /"),
        "{text}"
    );
    let (ok, text) = run(&eval_args(
        &d,
        "krfws",
        &["--krfws-model", gone.to_str().unwrap()],
    ));
    assert!(
        !ok && text.contains("(the path given with --krfws-model)"),
        "{text}"
    );
}

/// Finding 4: a truncated ONNX Runtime library killed the process with SIGBUS (exit 135, no message).
#[test]
fn a_truncated_onnx_runtime_library_is_a_clear_error() {
    let d = one_face("truncated-ort");
    let lib = std::fs::read(ort_library()).unwrap();
    let cut = d.join("libonnxruntime.so.1.31.1");
    std::fs::write(&cut, &lib[..lib.len() / 3]).unwrap();
    let args = eval_args(&d, "dan", &["--ort-dylib", cut.to_str().unwrap()]);
    let out = Command::new(env!("CARGO_BIN_EXE_holoface"))
        .args(&args)
        .current_dir(workspace())
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1), "killed by a signal? {out:?}");
    let (_, text) = finished(&out);
    assert!(
        text.contains("truncated") && text.contains(cut.to_str().unwrap()),
        "{text}"
    );
    assert!(text.contains("holoface setup"), "{text}");
}

/// Finding 6: `--candide /dev/zero` grew past 4 GiB; a FIFO or a link loop as `--source` read "does not
/// exist"; a sparse 2 GB `--poses` was read for 10 s.
#[test]
fn devices_pipes_loops_and_huge_files_are_refused_before_reading() {
    let d = tmp("kinds");
    let frames = d.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    write_png(&frames.join("000.png"), 64, 48);
    let t0 = Instant::now();
    let (ok, text) = holoface(&[
        "track",
        "--source",
        frames.to_str().unwrap(),
        "--candide",
        "/dev/zero",
    ]);
    assert!(!ok && text.contains("character device"), "{text}");
    let fifo = d.join("pipe");
    assert!(Command::new("mkfifo").arg(&fifo).status().unwrap().success());
    let (ok, text) = holoface(&["track", "--source", fifo.to_str().unwrap()]);
    assert!(
        !ok && text.contains("named pipe") && text.contains("--source -"),
        "{text}"
    );
    let a = d.join("a");
    std::os::unix::fs::symlink(d.join("b"), &a).unwrap();
    std::os::unix::fs::symlink(&a, d.join("b")).unwrap();
    let (ok, text) = holoface(&["track", "--source", a.to_str().unwrap()]);
    assert!(!ok && text.contains("loop of symbolic links"), "{text}");
    let sparse = d.join("poses.jsonl");
    std::fs::File::create(&sparse).unwrap().set_len(2 << 30).unwrap();
    let (ok, text) = holoface(&[
        "track",
        "--source",
        frames.to_str().unwrap(),
        "--poses",
        sparse.to_str().unwrap(),
    ]);
    assert!(!ok && text.contains("more than such a file can be"), "{text}");
    assert!(t0.elapsed() < Duration::from_secs(60), "took {:?}", t0.elapsed());
}

/// Finding 5: `holoface setup | head -1` panicked (exit 101) with one file installed; any command whose
/// stdout closes ends quietly.
#[test]
fn a_closed_standard_output_ends_quietly_and_setup_still_installs_everything() {
    let home = tmp("closed-stdout");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_holoface"));
    cmd.arg("setup")
        .env("HOLOFACE_HOME", &home)
        .env_remove("HOLOFACE_CANDIDE");
    if let Some(dl) = std::env::var_os("HOLOFACE_DOWNLOADS") {
        cmd.arg("--downloads").arg(dl);
    }
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    drop(child.stdout.take()); // the reader is gone before the first line
    let out = child.wait_with_output().unwrap();
    let (ok, text) = finished(&out);
    assert!(ok, "{text}");
    for f in [
        "dan.onnx",
        "refiner.bin",
        "krfws.bin",
        "face_detection_front_128x128.onnx",
    ] {
        assert!(home.join(f).is_file(), "{f} not installed: {text}");
        assert!(
            home.join(format!("{f}.sha256")).is_file(),
            "{f}'s checksum not recorded"
        );
    }
    // A command whose product is its standard output stops, quietly and successfully.
    let d = one_face("closed-stdout-eval");
    let mut child = Command::new(env!("CARGO_BIN_EXE_holoface"))
        .args(eval_args(&d, "krfws", &[]))
        .current_dir(workspace())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let (ok, text) = finished(&out);
    assert!(ok, "{text}");
}

/// Finding 7: a stalled download waited up to 600 s without a word.
#[test]
fn a_stalled_download_says_what_it_waits_for_and_gives_up() {
    // A proxy that accepts connections and never answers.
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let addr = listener.local_addr().unwrap();
    std::thread::spawn(move || {
        let mut held = Vec::new();
        for s in listener.incoming().flatten() {
            held.push(s);
        }
    });
    let home = tmp("stalled-home");
    let downloads = tmp("stalled-downloads");
    let t0 = Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_holoface"))
        .args(["setup", "--downloads", downloads.to_str().unwrap()])
        .env("HOLOFACE_HOME", &home)
        .env("HTTPS_PROXY", format!("http://{addr}"))
        .env("HOLOFACE_DOWNLOAD_TIMEOUT_S", "3")
        .output()
        .unwrap();
    let (ok, text) = finished(&out);
    assert!(!ok, "{text}");
    assert!(
        text.contains("gave up after") && text.contains("https://"),
        "{text}"
    );
    assert!(t0.elapsed() < Duration::from_secs(60), "took {:?}", t0.elapsed());
}
