//! `holoface demo` end to end: in-process server, relay, client over the bundled sample, link cut.
#![allow(clippy::unwrap_used)]

use std::path::PathBuf;
use std::process::Command;

fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

#[test]
fn demo_answers_every_frame_and_never_answers_remotely_through_a_cut_link() {
    let sample = std::env::var_os("HOLOFACE_SAMPLE").map_or_else(
        || workspace().join(".cache/holoface/astronaut.png"),
        PathBuf::from,
    );
    assert!(
        sample.is_file(),
        "demo sample missing at {} (run `make setup`)",
        sample.display()
    );
    let out = std::env::temp_dir().join(format!("holoface-demo-test-{}", std::process::id()));
    let status = Command::new(env!("CARGO_BIN_EXE_holoface"))
        .current_dir(workspace())
        .args([
            "demo",
            "--frames",
            "90",
            "--cut-at",
            "40",
            "--cut-frames",
            "20",
            "--log",
            "warn",
        ])
        .arg("--out")
        .arg(&out)
        .arg("--sample")
        .arg(&sample)
        .status()
        .unwrap();
    assert!(status.success());
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(out.join("frames.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 90);
    for l in &lines {
        // Every frame gets an answer: a face with its aligner, or an explicit no-face reason.
        let face = l["face"].as_bool().unwrap();
        assert!(
            if face {
                !l["answered_by"].is_null()
            } else {
                l["reason"].is_string()
            },
            "{l}"
        );
        if l["phase"] == "link_cut" {
            assert_ne!(
                l["answered_by"], "remote_dan",
                "answered remotely through a cut link: {l}"
            );
        }
    }
    let faces = lines.iter().filter(|l| l["face"] == true).count();
    assert!(faces >= 80, "the face was tracked in only {faces} of 90 frames");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["frames"], 90);
    let png = std::fs::read(out.join("strip.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    let _ = std::fs::remove_dir_all(&out);
}
