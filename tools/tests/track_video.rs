//! `holoface tracking-losses` and `holoface track` end to end over video: a rendered validation-face
//! sequence exported as MP4 + pose sidecar is tracked with annotated PNGs; a video without a face gets an
//! explicit "no face" line for every frame; bad sources and sidecars fail with clear errors.
#![allow(clippy::unwrap_used)]

mod common;

use common::{holoface, json_lines as lines, tmp};

use holoface_client::video::Mp4Writer;
use holoface_models::image::GrayImage;

/// `holoface ARGS --log warn`.
fn run(args: &[&str]) -> (bool, String) {
    let mut all = args.to_vec();
    all.extend(["--log", "warn"]);
    holoface(&all)
}

#[test]
fn rendered_sequence_tracks_from_mp4_with_sidecar_and_annotations() {
    let d = tmp("seq");
    let seq = d.join("seq");
    let report = d.join("losses.json");
    let (ok, text) = run(&[
        "tracking-losses",
        "--faces",
        "2",
        "--seconds",
        "2",
        "--out",
        report.to_str().unwrap(),
        "--write-sequence",
        seq.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    assert_eq!(r["faces"], 2);
    for mode in ["motion_compensated", "uncompensated"] {
        assert_eq!(r[mode]["frames"], 120, "{mode}: {r}");
        assert!(r[mode]["losses"].as_u64().is_some(), "{mode}: {r}");
    }

    let out = d.join("track.jsonl");
    let ann = d.join("ann");
    let (ok, text) = run(&[
        "track",
        "--source",
        seq.join("sequence.mp4").to_str().unwrap(),
        "--poses",
        seq.join("poses.jsonl").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--annotate",
        ann.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let got = lines(&out);
    let truth = lines(&seq.join("truth.jsonl"));
    assert_eq!(got.len(), 60);
    assert_eq!(truth.len(), 60);
    let mut tracked = 0;
    for (g, t) in got.iter().zip(&truth) {
        assert_eq!(g["frame"], t["frame"]);
        if g["face"] == true {
            // Landmarks near the truth (the nose tip, point 30), world pose present.
            let (p, q) = (&g["landmarks_px"][30], &t["landmarks_px"][30]);
            let dx = p[0].as_f64().unwrap() - q[0].as_f64().unwrap();
            let dy = p[1].as_f64().unwrap() - q[1].as_f64().unwrap();
            if dx.hypot(dy) < 10.0 {
                tracked += 1;
            }
            assert!(g["world"]["position_m"].is_array());
        } else {
            assert!(g["reason"].is_string(), "{g}");
        }
    }
    assert!(
        tracked >= 45,
        "nose within 10 px of the truth in only {tracked} of 60 frames"
    );
    let pngs = std::fs::read_dir(&ann).unwrap().count();
    assert_eq!(pngs, 60);
    let png = std::fs::read(ann.join("frame_000010.png")).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_video_without_a_face_gets_a_no_face_line_per_frame() {
    let d = tmp("noface");
    let video = d.join("wall.mp4");
    let mut w = Mp4Writer::create(&video, 160, 120, 30).unwrap();
    for i in 0..8u8 {
        let px = (0..160 * 120)
            .map(|k| ((k % 160) as u8 / 4).wrapping_add(i * 3))
            .collect();
        w.push(&GrayImage::from_vec(px, 160, 120).unwrap()).unwrap();
    }
    w.finish().unwrap();
    let out = d.join("track.jsonl");
    let (ok, text) = run(&[
        "track",
        "--source",
        video.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let got = lines(&out);
    assert_eq!(got.len(), 8);
    for (i, g) in got.iter().enumerate() {
        assert_eq!(g["frame"], i);
        assert_eq!(g["face"], false);
        assert_eq!(g["reason"], "not_detected");
    }
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn bad_videos_and_sidecars_fail_with_clear_errors() {
    let d = tmp("bad");
    let broken = d.join("broken.mp4");
    std::fs::write(&broken, b"\0\0\0\x18ftypisom definitely not a movie").unwrap();
    let (ok, text) = run(&["track", "--source", broken.to_str().unwrap()]);
    assert!(!ok && text.contains("broken.mp4"), "{text}");

    let missing = d.join("missing.mp4");
    let (ok, text) = run(&["track", "--source", missing.to_str().unwrap()]);
    assert!(!ok && text.contains("does not exist"), "{text}");

    let video = d.join("ok.mp4");
    let mut w = Mp4Writer::create(&video, 64, 48, 30).unwrap();
    w.push(&GrayImage::zeros(64, 48)).unwrap();
    w.finish().unwrap();
    let sidecar = d.join("bad.jsonl");
    std::fs::write(&sidecar, "{\"frame\": 0, \"camera_to_world\": [1, 2, 3]}\n").unwrap();
    let (ok, text) = run(&[
        "track",
        "--source",
        video.to_str().unwrap(),
        "--poses",
        sidecar.to_str().unwrap(),
    ]);
    assert!(!ok && text.contains("bad.jsonl line 1"), "{text}");
    let _ = std::fs::remove_dir_all(&d);
}
