//! The builder as an app meets it (the runtime's root only): settings are checked before any asset loads,
//! video timestamps must increase, and `reset` starts over from a detection at any timestamp. Needs the
//! runtime assets of `make setup` (the data folder or the environment variables).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use holoface_headset_client::assets::{AssetPaths, home};
use holoface_headset_client::errors::SessionOptionsError;
use holoface_headset_client::{
    DetectorOptions, FaceTracker, Frame, GrayImage, Intrinsics, Pose, TrackerError, TrackerOptions,
};

fn sample() -> GrayImage {
    let photo = image::open(home::SAMPLE.default_path())
        .expect("the demo sample (make setup)")
        .into_luma8();
    let (w, h) = (photo.width() as usize, photo.height() as usize);
    GrayImage::from_vec(photo.into_raw(), w, h).unwrap()
}

fn frame(image: &GrayImage, timestamp_us: u64) -> Frame<'_> {
    let (w, h) = (image.width() as f64, image.height() as f64);
    Frame {
        timestamp_us,
        image: image.view(),
        intrinsics: Intrinsics {
            fx: w,
            fy: w,
            cx: w / 2.0,
            cy: h / 2.0,
        },
        world_from_camera: Pose::IDENTITY,
    }
}

#[test]
fn detector_tiles_out_of_range_are_refused_before_any_asset_loads() {
    for tiles in [0, 33] {
        let opts = TrackerOptions {
            // Paths that do not exist: the settings are checked first.
            assets: AssetPaths {
                ort_dylib: "/nonexistent/libonnxruntime.so".into(),
                detector: "/nonexistent/detector.onnx".into(),
                krfws: "/nonexistent/krfws.bin".into(),
                candide: "/nonexistent/candide3.wfm".into(),
            },
            detector: DetectorOptions {
                tiles: Some(tiles),
                several_faces: None,
            },
            ..TrackerOptions::default()
        };
        match FaceTracker::new(opts) {
            Err(TrackerError::Options(SessionOptionsError::DetectTiles(t))) => assert_eq!(t, tiles),
            other => panic!("tiles {tiles}: {other:?}"),
        }
    }
}

#[test]
fn video_timestamps_must_increase_until_reset() {
    let image = sample();
    let mut tracker = FaceTracker::new(TrackerOptions::default()).unwrap();
    let first = tracker.process(&frame(&image, 1_000)).unwrap();
    assert!(first.detected && first.face().is_some(), "{first:?}");
    let second = tracker.process(&frame(&image, 34_333)).unwrap();
    assert!(!second.detected, "the second frame is tracked, not detected");
    match tracker.process(&frame(&image, 34_333)) {
        Err(TrackerError::Timestamp {
            previous: 34_333,
            got: 34_333,
        }) => {}
        other => panic!("a repeated timestamp: {other:?}"),
    }
    tracker.reset();
    let again = tracker.process(&frame(&image, 0)).unwrap();
    assert!(again.detected && again.face().is_some(), "after reset: {again:?}");
}

#[test]
fn blendshapes_are_named_bounded_and_a_face_at_rest_reads_near_zero_after_calibration() {
    let image = sample();
    let mut tracker = FaceTracker::new(TrackerOptions::default()).unwrap();
    let mut last = None;
    for i in 0..40u64 {
        let r = tracker.process(&frame(&image, i * 33_333)).unwrap();
        let face = r.face().expect("the sample's face");
        assert!(
            face.blendshapes.0.iter().all(|v| (0.0..=1.0).contains(v)),
            "{:?}",
            face.blendshapes
        );
        last = Some(face.blendshapes);
    }
    // The same photograph for 40 frames: after the first 30 calibrate the neutral, it is the neutral.
    let rest = last.unwrap();
    for (b, v) in rest.iter() {
        assert!(v < 0.15, "{} = {v} at rest", b.arkit_name());
    }
    tracker.recalibrate_blendshapes();
    let r = tracker.process(&frame(&image, 40 * 33_333)).unwrap();
    assert!(r.face().is_some());
}
