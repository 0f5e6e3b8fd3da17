//! `holoface tracking-losses` and `holoface track` end to end over video: a rendered validation-face
//! sequence exported as MP4 + pose sidecar is tracked with annotated PNGs; a video without a face gets an
//! explicit "no face" line for every frame; bad sources, sidecars and scenes fail with clear errors.
#![allow(clippy::unwrap_used)]

use crate::common;
use crate::common::{holoface, json_lines as lines, tmp};
use holoface_sources::output::Temporaries;

use holoface_models::image::GrayImage;
use holoface_sources::video::Mp4Writer;

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
    let aug = d.join("aug/augmented.mp4");
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
        "--augment",
        "default",
        "--augment-out",
        aug.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    // The augmented video has every frame, as the decoder reads it back.
    assert!(text.contains("60 augmented frames in"), "{text}");
    let mut back = holoface_sources::source::open_source(&aug, 30.0, None).unwrap();
    let mut decoded = 0;
    while back.next_frame().unwrap().is_some() {
        decoded += 1;
    }
    assert_eq!(decoded, 60);
    let got = lines(&out);
    let truth = lines(&seq.join("truth.jsonl"));
    assert_eq!(got.len(), 60);
    assert_eq!(truth.len(), 60);
    let mut tracked = 0;
    for (g, t) in got.iter().zip(&truth) {
        assert_eq!(g["frame"], t["frame"]);
        if g["face"] == true {
            // One face (the default --max-faces 1), with id 0 throughout: landmarks near the truth (the nose
            // tip, point 30), world pose present.
            let f = &g["faces"][0];
            assert_eq!(g["faces"].as_array().map(Vec::len), Some(1), "{g}");
            assert_eq!(f["id"], 0, "{g}");
            let (p, q) = (&f["landmarks_px"][30], &t["landmarks_px"][30]);
            let dx = p[0].as_f64().unwrap() - q[0].as_f64().unwrap();
            let dy = p[1].as_f64().unwrap() - q[1].as_f64().unwrap();
            if dx.hypot(dy) < 10.0 {
                tracked += 1;
            }
            assert!(f["world"]["position_m"].is_array());
        } else {
            assert_eq!(g["faces"], serde_json::json!([]), "{g}");
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
    let mut w = Mp4Writer::create(&video, 160, 120, 30, &Temporaries::new()).unwrap();
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
    let mut w = Mp4Writer::create(&video, 64, 48, 30, &Temporaries::new()).unwrap();
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

    // A scene that cannot be read or is wrong fails before any frame, naming the file and the key.
    let scene = d.join("scene.toml");
    std::fs::write(&scene, "[[object]]\nshape = \"glasses\"\nanchor = \"chin\"\n").unwrap();
    for (path, says) in [
        (&scene, "unknown anchor \"chin\""),
        (&d.join("none.toml"), "none.toml"),
    ] {
        let (ok, text) = run(&[
            "track",
            "--source",
            video.to_str().unwrap(),
            "--augment",
            path.to_str().unwrap(),
        ]);
        assert!(!ok && text.contains(says), "{text}");
    }
    let _ = std::fs::remove_dir_all(&d);
}

/// The bundled sample as gray frames moving right by 2 px a frame, cropped to an odd size (so the annotated
/// video drops a column and a row).
fn sample_clip(frames: usize) -> Vec<GrayImage> {
    let sample = std::env::var_os("HOLOFACE_SAMPLE").map_or_else(
        || common::workspace().join(".cache/holoface/astronaut.png"),
        Into::into,
    );
    let gray = holoface_sources::images::read_gray(&sample).unwrap();
    let (w, h) = (gray.width() - 1, gray.height() - 1);
    (0..frames)
        .map(|k| {
            let mut px = vec![0u8; w * h];
            let src = gray.view();
            for y in 0..h {
                let row = src.row(y).unwrap();
                px[y * w + 2 * k..(y + 1) * w].copy_from_slice(&row[..w - 2 * k]);
            }
            GrayImage::from_vec(px, w, h).unwrap()
        })
        .collect()
}

fn write_y4m(path: &std::path::Path, frames: &[GrayImage]) {
    let f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut w =
        holoface_sources::y4m::Y4mWriter::new(f, frames[0].width(), frames[0].height(), 30, 1).unwrap();
    for f in frames {
        w.push(f).unwrap();
    }
    w.finish().unwrap();
}

/// `holoface track --source -` with `input` on stdin.
fn track_stdin(input: &std::path::Path, extra: &[&str]) -> (bool, String) {
    let mut args = vec!["track", "--source", "-", "--log", "warn"];
    args.extend(extra);
    common::holoface_with_stdin(&args, Some(input))
}

#[test]
fn a_y4m_stream_on_stdin_is_tracked_and_annotated_as_mp4() {
    let d = tmp("y4m");
    let clip = sample_clip(8);
    let y4m = d.join("cam.y4m");
    write_y4m(&y4m, &clip);
    let out = d.join("track.jsonl");
    let video = d.join("ann/annotated.mp4");
    let (ok, text) = track_stdin(
        &y4m,
        &[
            "--out",
            out.to_str().unwrap(),
            "--annotate",
            video.to_str().unwrap(),
        ],
    );
    assert!(ok, "{text}");
    assert!(text.contains("8 annotated frames in"), "{text}");
    let got = lines(&out);
    assert_eq!(got.len(), 8);
    for (k, g) in got.iter().enumerate() {
        assert_eq!(g["frame"], k);
        assert_eq!(
            g["timestamp_us"],
            [0, 33_333, 66_666, 100_000, 133_333, 166_666, 200_000, 233_333][k]
        );
        assert_eq!(g["face"], true, "frame {k}: {g}");
        assert_eq!(
            g["faces"][0]["init"],
            if k == 0 { "detection" } else { "tracking" }
        );
        assert_eq!(
            g["detected"],
            k == 0,
            "the detector runs only until a face is tracked"
        );
    }
    // The nose follows the picture: 2 px to the right a frame.
    let nose_x = |g: &serde_json::Value| g["faces"][0]["landmarks_px"][30][0].as_f64().unwrap();
    let moved = nose_x(&got[7]) - nose_x(&got[0]);
    assert!(
        (moved - 14.0).abs() < 4.0,
        "the nose moved {moved} px, the picture 14"
    );

    // The same stream from a file gives the same lines (timings aside).
    let out2 = d.join("file.jsonl");
    let (ok, text) = run(&[
        "track",
        "--source",
        y4m.to_str().unwrap(),
        "--out",
        out2.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    for (a, b) in got.iter().zip(&lines(&out2)) {
        assert_eq!(a["faces"], b["faces"]);
    }

    // The annotated video decodes to 8 frames of the clip's size rounded down to even.
    let mut src = holoface_sources::video::Mp4Source::open(&video, None).unwrap();
    assert_eq!(src.frame_count(), 8);
    use holoface_sources::FrameSource;
    let first = src.next_frame().unwrap().unwrap();
    assert_eq!(
        (first.image.width(), first.image.height()),
        (clip[0].width() & !1, clip[0].height() & !1)
    );
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn a_truncated_or_malformed_y4m_is_an_error_naming_the_frame() {
    let d = tmp("y4m-bad");
    let clip = sample_clip(3);
    let y4m = d.join("cam.y4m");
    write_y4m(&y4m, &clip);
    let mut bytes = std::fs::read(&y4m).unwrap();
    bytes.truncate(bytes.len() - 1000);
    let cut = d.join("cut.y4m");
    std::fs::write(&cut, &bytes).unwrap();
    let (ok, text) = track_stdin(&cut, &["--out", d.join("cut.jsonl").to_str().unwrap()]);
    assert!(!ok, "{text}");
    assert!(
        text.contains("stdin: frame 2") && text.contains("truncated"),
        "{text}"
    );
    let (ok, text) = run(&[
        "track",
        "--source",
        cut.to_str().unwrap(),
        "--out",
        d.join("c.jsonl").to_str().unwrap(),
    ]);
    assert!(!ok && text.contains("cut.y4m: frame 2"), "{text}");

    let wrong = d.join("wrong.y4m");
    std::fs::write(&wrong, b"YUV4MPEG2 W640 H480 F30:1 C420p10\nFRAME\n").unwrap();
    let (ok, text) = track_stdin(&wrong, &[]);
    assert!(
        !ok && text.contains("stdin") && text.contains("C420p10 is not supported"),
        "{text}"
    );
    let not_y4m = d.join("not.y4m");
    std::fs::write(&not_y4m, b"P5 640 480 255\n").unwrap();
    let (ok, text) = track_stdin(&not_y4m, &[]);
    assert!(!ok && text.contains("not a YUV4MPEG2 stream"), "{text}");
    let _ = std::fs::remove_dir_all(&d);
}

/// `holoface stability` over a y4m clip: with our own raw landmarks as the per-frame peer the agreement is
/// exact and the peer's jitter is ours; the steadied columns exist and are the raw ones with `--no-steady`;
/// a malformed peer file is refused naming its line.
#[test]
fn stability_reports_jitter_and_agreement_and_refuses_bad_peers() {
    let d = tmp("stability");
    let clip = sample_clip(12);
    let y4m = d.join("cam.y4m");
    write_y4m(&y4m, &clip);
    let track = d.join("track.jsonl");
    let (ok, text) = run(&[
        "track",
        "--source",
        y4m.to_str().unwrap(),
        "--no-steady",
        "--out",
        track.to_str().unwrap(),
    ]);
    assert!(ok, "{text}");
    let mut peer = String::new();
    for (k, g) in lines(&track).iter().enumerate() {
        let raw = g["faces"][0]["raw_landmarks_px"].as_array().unwrap();
        assert_eq!(
            raw,
            g["faces"][0]["landmarks_px"].as_array().unwrap(),
            "--no-steady shows the raw ones"
        );
        let nums: Vec<String> = raw
            .iter()
            .flat_map(|p| [p[0].as_f64().unwrap(), p[1].as_f64().unwrap()])
            .map(|v| format!("{v}"))
            .collect();
        peer.push_str(&format!("{k} {}\n", nums.join(" ")));
    }
    let peer_file = d.join("peer.tsv");
    std::fs::write(&peer_file, peer).unwrap();
    let report = d.join("report.json");
    let plot = d.join("jitter.png");
    let stability = |extra: &[&str], peer: &std::path::Path| {
        let mut args = vec![
            "stability",
            "--source",
            y4m.to_str().unwrap(),
            "--aligners",
            "krfws",
            "--peer",
            peer.to_str().unwrap(),
            "--out",
            report.to_str().unwrap(),
            "--plot",
            plot.to_str().unwrap(),
        ];
        args.extend(extra);
        run(&args)
    };
    let (ok, text) = stability(&["--no-steady"], &peer_file);
    assert!(ok, "{text}");
    assert!(text.contains("12 frames"), "{text}");
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let a = &r["aligners"][0];
    assert_eq!(
        (
            a["aligner"].as_str(),
            a["frames"].as_u64(),
            a["faces_found"].as_u64()
        ),
        (Some("krfws"), Some(12), Some(12))
    );
    assert_eq!(a["redetections"], 0);
    let f = |v: &serde_json::Value| v.as_f64().unwrap();
    assert!(f(&a["raw_vs_peer_nme49"]["mean"]) < 1e-6, "{a}");
    assert_eq!(
        a["raw_jitter49"]["frames"], 10,
        "every frame but the first and the last"
    );
    assert!(
        (f(&a["raw_jitter49"]["mean"]) - f(&r["peer"]["jitter49"]["mean"])).abs() < 1e-6,
        "{r}"
    );
    assert_eq!(a["raw_jitter49"], a["steadied_jitter49"]);
    assert!(std::fs::read(&plot).unwrap().starts_with(b"\x89PNG"));

    let (ok, text) = stability(&[], &peer_file);
    assert!(ok, "{text}");
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&report).unwrap()).unwrap();
    let a = &r["aligners"][0];
    assert!(
        f(&a["steadied_jitter49"]["mean"]).is_finite() && f(&a["steadied_vs_peer_nme49"]["mean"]) < 0.05,
        "{a}"
    );

    let bad = d.join("bad.tsv");
    std::fs::write(&bad, "0 1 2 3\n").unwrap();
    let (ok, text) = stability(&[], &bad);
    assert!(!ok && text.contains("bad.tsv: line 1: 3 numbers"), "{text}");
    let _ = std::fs::remove_dir_all(&d);
}
