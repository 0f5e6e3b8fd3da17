//! Helpers shared by the load tester's integration tests.
#![allow(clippy::unwrap_used, dead_code)]

use std::path::{Path, PathBuf};

use holoface_protocol::recording::{
    CameraIntrinsics, FramePayload, FrameRecord, RecordingHeader, RecordingWriter,
};
use holoface_runtime::link::CropCodec;

pub(crate) fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A one-second stream of 30 JPEG crops cut from the demo sample (a real face photo).
pub(crate) fn recording(dir: &Path) -> PathBuf {
    let sample = std::env::var_os("HOLOFACE_SAMPLE").map_or_else(
        || workspace().join(".cache/holoface/astronaut.png"),
        PathBuf::from,
    );
    let photo = image::open(&sample)
        .unwrap_or_else(|e| panic!("demo sample {} ({e}); run `make setup`", sample.display()))
        .into_luma8();
    let path = dir.join("crops.hfrec");
    let header = RecordingHeader {
        intrinsics: CameraIntrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 256.0,
            cy: 256.0,
            width: 512,
            height: 512,
        },
        source: "load-tester test".into(),
        created_unix_ms: 0,
    };
    let mut w = RecordingWriter::new(std::fs::File::create(&path).unwrap(), &header).unwrap();
    for k in 0..30u32 {
        // The face region, shifted a little per frame.
        let crop = image::imageops::crop_imm(&photo, 150 + k, 60 + k / 2, 180, 180).to_image();
        let crop = image::imageops::resize(&crop, 112, 112, image::imageops::FilterType::Triangle);
        let wire =
            holoface_runtime::crop_codec::encode(CropCodec::default(), crop.as_raw(), 112, 112).unwrap();
        w.write_record(&FrameRecord {
            timestamp_us: u64::from(k) * 33_333,
            camera_to_world: [
                1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            ],
            payload: FramePayload::Crop {
                image_from_crop: [1.6, 0.0, 150.0, 60.0],
                crop: wire,
            },
            ground_truth: None,
            face_present: Some(true),
        })
        .unwrap();
    }
    w.finish().unwrap();
    path
}

/// Polls `ready` every 10 ms until it gives a value, for at most 20 s (a bound only a hang reaches), then
/// panics naming `what`: the tests wait for events, not for fixed times.
pub(crate) fn wait_for_some<T>(what: &str, mut ready: impl FnMut() -> Option<T>) -> T {
    let end = std::time::Instant::now() + std::time::Duration::from_secs(20);
    loop {
        if let Some(v) = ready() {
            return v;
        }
        assert!(std::time::Instant::now() < end, "timed out waiting for {what}");
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
}
