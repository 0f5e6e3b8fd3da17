//! MP4/H.264 sources and pose sidecars: a written video reads back frame for frame, poses come from the
//! sidecar, and corrupt videos or sidecars are errors that name the file (never a panic).
#![allow(clippy::unwrap_used)]

use std::path::Path;

use holoface_headset_client::FrameSource;
use holoface_models::image::GrayImage;
use holoface_models::math3::{Mat3, Pose, Vec3};
use holoface_sources::poses::write_line;
use holoface_sources::source::open_source;
use holoface_sources::video::Mp4Writer;

/// A moving pattern with smooth structure (what a camera sees, not noise).
fn frame(i: usize, w: usize, h: usize) -> GrayImage {
    let px = (0..w * h)
        .map(|k| {
            let (x, y) = ((k % w) as f32, (k / w) as f32);
            let v = 128.0 + 60.0 * ((x + 3.0 * i as f32) / 9.0).sin() + 50.0 * (y / 7.0).cos();
            v.clamp(0.0, 255.0) as u8
        })
        .collect();
    GrayImage::from_vec(px, w, h).unwrap()
}

fn write_video(path: &Path, n: usize) -> Vec<GrayImage> {
    let frames: Vec<_> = (0..n).map(|i| frame(i, 96, 64)).collect();
    let mut w = Mp4Writer::create(path, 96, 64, 30).unwrap();
    for f in &frames {
        w.push(f).unwrap();
    }
    assert_eq!(w.finish().unwrap(), n as u64);
    frames
}

fn pose(i: usize) -> Pose {
    Pose {
        rotation: Mat3::rot_y(0.01 * i as f64),
        translation: Vec3::new(0.001 * i as f64, 0.0, 0.0),
    }
}

fn read_all(src: &mut dyn FrameSource) -> anyhow::Result<Vec<holoface_headset_client::OwnedFrame>> {
    let mut out = Vec::new();
    while let Some(f) = src.next_frame()? {
        out.push(f);
    }
    Ok(out)
}

#[test]
fn written_video_reads_back_with_sidecar_poses() {
    let d = tmp("roundtrip");
    let video = d.join("clip.mp4");
    let frames = write_video(&video, 12);
    let sidecar = d.join("poses.jsonl");
    let mut text = Vec::new();
    for i in 0..12 {
        write_line(&mut text, i, &pose(i), None, None).unwrap();
    }
    std::fs::write(&sidecar, text).unwrap();

    let got = read_all(&mut *open_source(&video, 30.0, Some(&sidecar)).unwrap()).unwrap();
    assert_eq!(got.len(), 12);
    for (i, (g, want)) in got.iter().zip(&frames).enumerate() {
        assert_eq!(g.index, i);
        assert_eq!(g.timestamp_us, (i as u64 * 1_000_000) / 30, "frame {i}");
        assert_eq!((g.image.width(), g.image.height()), (96, 64));
        // Lossy codec: close, not equal; luma range expanded back to 0-255.
        let mad: f64 = g
            .image
            .as_bytes()
            .iter()
            .zip(want.as_bytes())
            .map(|(&a, &b)| (f64::from(a) - f64::from(b)).abs())
            .sum::<f64>()
            / want.as_bytes().len() as f64;
        assert!(mad < 4.0, "frame {i}: mean abs difference {mad}");
        assert!((g.world_from_camera.translation - pose(i).translation).norm() < 1e-6);
    }
    // Without a sidecar the pose is the identity.
    let first = open_source(&video, 30.0, None)
        .unwrap()
        .next_frame()
        .unwrap()
        .unwrap();
    assert_eq!(first.world_from_camera, Pose::IDENTITY);
}

#[test]
fn a_sidecar_that_misses_a_frame_names_it() {
    let d = tmp("short-sidecar");
    let video = d.join("clip.mp4");
    write_video(&video, 5);
    let sidecar = d.join("poses.jsonl");
    let mut text = Vec::new();
    for i in 0..3 {
        write_line(&mut text, i, &pose(i), None, None).unwrap();
    }
    std::fs::write(&sidecar, text).unwrap();
    let err = read_all(&mut *open_source(&video, 30.0, Some(&sidecar)).unwrap()).unwrap_err();
    let msg = format!("{err:#}");
    assert!(
        msg.contains("no pose for frame 3") && msg.contains("poses.jsonl"),
        "{msg}"
    );
}

#[test]
fn corrupt_videos_are_errors_naming_the_file() {
    let d = tmp("corrupt");
    let good = d.join("good.mp4");
    write_video(&good, 6);
    let bytes = std::fs::read(&good).unwrap();
    let mut cases: Vec<(&str, Vec<u8>)> = vec![
        ("truncated.mp4", bytes[..bytes.len() / 2].to_vec()),
        ("empty.mp4", Vec::new()),
        ("text.mp4", b"\0\0\0\x18ftypisomthis is not a video".to_vec()),
    ];
    // Payload damage: overwrite the middle of the file (sample data and possibly tables).
    let mut damaged = bytes.clone();
    let mid = damaged.len() / 3;
    for b in &mut damaged[mid..mid + 200] {
        *b = 0xff;
    }
    cases.push(("damaged.mp4", damaged));
    // Every byte position of the header region flipped, one file each (deterministic fuzzing).
    for k in (0..bytes.len().min(600)).step_by(37) {
        let mut f = bytes.clone();
        f[k] ^= 0x5a;
        cases.push(("flipped.mp4", f));
    }
    for (name, data) in cases {
        let path = d.join(name);
        std::fs::write(&path, &data).unwrap();
        let result = std::panic::catch_unwind(|| match open_source(&path, 30.0, None) {
            Ok(mut s) => read_all(&mut *s).map(|f| f.len()),
            Err(e) => Err(e),
        });
        let result = result.unwrap_or_else(|_| panic!("{name}: panicked"));
        if let Err(e) = result {
            let msg = format!("{e:#}");
            assert!(msg.contains(name), "{name}: error does not name the file: {msg}");
        }
    }
    // The cases that cannot decode at all must be errors.
    for name in ["truncated.mp4", "empty.mp4", "text.mp4"] {
        let path = d.join(name);
        std::fs::write(
            &path,
            match name {
                "truncated.mp4" => bytes[..bytes.len() / 2].to_vec(),
                "empty.mp4" => Vec::new(),
                _ => b"\0\0\0\x18ftypisomthis is not a video".to_vec(),
            },
        )
        .unwrap();
        let r = open_source(&path, 30.0, None).and_then(|mut s| read_all(&mut *s).map(|f| f.len()));
        assert!(r.is_err(), "{name}: read {:?} frames", r.ok());
    }
}

#[test]
fn bad_writer_input_is_an_error() {
    let d = tmp("writer");
    assert!(Mp4Writer::create(&d.join("odd.mp4"), 95, 64, 30).is_err());
    assert!(Mp4Writer::create(&d.join("zero.mp4"), 96, 64, 0).is_err());
    let mut w = Mp4Writer::create(&d.join("size.mp4"), 96, 64, 30).unwrap();
    assert!(w.push(&frame(0, 64, 64)).is_err());
    let w = Mp4Writer::create(&d.join("none.mp4"), 96, 64, 30).unwrap();
    assert!(w.finish().is_err());
}

/// A fresh, empty temporary folder unique to this process and `name`.
fn tmp(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("holoface-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Debian's ffmpeg (the test set-up installs it: `make ffmpeg`).
fn ffmpeg(args: &[&str]) {
    let out = std::process::Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-y"])
        .args(args)
        .output()
        .expect("ffmpeg is needed to make test clips (make ffmpeg installs Debian's)");
    assert!(
        out.status.success(),
        "ffmpeg {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Camera MP4s as encoders write them (x264's defaults use B-frames; most cameras and screen recorders
/// too): every frame decodes, in display order, with increasing times, and matches ffmpeg's own decode (luma,
/// expanded from limited to full range as every frame of ours). Without B-frames the match is exact; with
/// them OpenH264 is not bit-exact in a few B-frame blocks (measured: at most 199 of 19,200 pixels of a frame,
/// by at most 7 grey levels, with x264's temporal direct mode; BENCHMARKS.md "Video input"), so each frame
/// must be ffmpeg's frame of the same index and differ in under 2 % of its pixels by at most 8 levels.
#[test]
fn h264_of_every_common_profile_with_b_frames_decodes_every_frame_in_order() {
    let d = tmp("profiles");
    let (w, h, n) = (160usize, 120usize, 60usize);
    let to_full = |v: u8| ((f64::from(v) - 16.0) * 255.0 / 219.0).round().clamp(0.0, 255.0) as u8;
    for (name, x264, exact) in [
        ("baseline", vec!["-profile:v", "baseline"], true),
        ("high-no-b-frames", vec!["-profile:v", "high", "-bf", "0"], true),
        ("main-b-frames", vec!["-profile:v", "main", "-bf", "3"], false),
        (
            "high-b-frames",
            vec!["-profile:v", "high", "-bf", "3", "-b_strategy", "2"],
            false,
        ),
        ("x264-defaults", vec![], false),
        (
            "high-temporal-direct",
            vec!["-profile:v", "high", "-x264-params", "direct=temporal"],
            false,
        ),
    ] {
        let clip = d.join(format!("{name}.mp4"));
        let clip_s = clip.to_str().unwrap();
        let mut args = vec![
            "-f",
            "lavfi",
            "-i",
            "testsrc2=size=160x120:rate=25",
            "-frames:v",
            "60",
        ];
        args.extend(["-pix_fmt", "yuv420p", "-c:v", "libx264"]);
        args.extend(x264.iter().copied());
        args.push(clip_s);
        ffmpeg(&args);
        // ffmpeg's decode: the raw Y planes, expanded to full range.
        let raw = d.join(format!("{name}.yuv"));
        ffmpeg(&[
            "-i",
            clip_s,
            "-f",
            "rawvideo",
            "-pix_fmt",
            "yuv420p",
            raw.to_str().unwrap(),
        ]);
        let yuv = std::fs::read(&raw).unwrap();
        let frame_bytes = w * h * 3 / 2;
        assert_eq!(yuv.len(), n * frame_bytes, "{name}: ffmpeg's frame count");
        let theirs: Vec<Vec<u8>> = (0..n)
            .map(|i| {
                yuv[i * frame_bytes..i * frame_bytes + w * h]
                    .iter()
                    .map(|&v| to_full(v))
                    .collect()
            })
            .collect();
        let mut src = open_source(&clip, 25.0, None).unwrap();
        let frames = read_all(src.as_mut()).unwrap_or_else(|e| panic!("{name}: {e:#}"));
        assert_eq!(frames.len(), n, "{name}: every frame");
        let differing = |a: &[u8], b: &[u8]| a.iter().zip(b).filter(|(x, y)| x != y).count();
        for (i, f) in frames.iter().enumerate() {
            assert_eq!((f.image.width(), f.image.height()), (w, h), "{name} frame {i}");
            let ours = f.image.view().data();
            if exact {
                assert!(
                    ours == theirs[i].as_slice(),
                    "{name}: frame {i} differs from ffmpeg's"
                );
            } else {
                let closest = (0..n).min_by_key(|&j| differing(ours, &theirs[j])).unwrap();
                assert_eq!(
                    closest, i,
                    "{name}: frame {i} is ffmpeg's frame {closest} (out of order)"
                );
                let diff = differing(ours, &theirs[i]);
                let max = ours
                    .iter()
                    .zip(&theirs[i])
                    .map(|(a, b)| a.abs_diff(*b))
                    .max()
                    .unwrap();
                assert!(
                    diff * 50 < w * h && max <= 8,
                    "{name}: frame {i}: {diff} pixels differ, by up to {max}"
                );
            }
            if i > 0 {
                assert!(
                    f.timestamp_us > frames[i - 1].timestamp_us,
                    "{name}: frame {i} out of order"
                );
            }
        }
    }
    // A codec OpenH264 cannot read is refused by name, with the ffmpeg pipe that reads it.
    for (file, codec, want) in [
        ("clip.webm", ["-c:v", "libvpx-vp9"].as_slice(), "WebM"),
        (
            "hevc.mp4",
            ["-c:v", "libx265", "-tag:v", "hev1"].as_slice(),
            "no H.264 video track",
        ),
    ] {
        let clip = d.join(file);
        let mut args = vec![
            "-f",
            "lavfi",
            "-i",
            "testsrc2=size=160x120:rate=25",
            "-frames:v",
            "5",
        ];
        args.extend(codec.iter().copied());
        args.push(clip.to_str().unwrap());
        ffmpeg(&args);
        let err = open_source(&clip, 25.0, None)
            .err()
            .unwrap_or_else(|| panic!("{file} is refused"))
            .to_string();
        assert!(
            err.contains(want) && err.contains("yuv4mpegpipe"),
            "{file}: {err}"
        );
    }
    let _ = std::fs::remove_dir_all(&d);
}
