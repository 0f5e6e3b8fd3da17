//! Embedding the client: find a face in a still image (image mode), then track it over 30 frames (video
//! mode), printing the head pose.
//!
//! ```sh
//! holoface setup --candide /path/to/candide3.wfm   # fills the data folder (in a checkout: make setup)
//! cargo run --release -p holoface-headset-client --example embed -- [photo.png]
//! ```
//! Assets are found through `ORT_DYLIB_PATH`, `HOLOFACE_DETECTOR_MODEL`, `HOLOFACE_KRFWS_MODEL` and
//! `HOLOFACE_CANDIDE`, else in the holoface data folder (`holoface_headset_client::assets::home`); the photo defaults
//! to the data folder's demo sample.

// Everything comes from the facade: an app depends on this one crate.
use holoface_headset_client::errors::{AlignError, AssetError, DetectError};
use holoface_headset_client::results::Unit;
use holoface_headset_client::{
    FaceTracker, Frame, GrayImage, Intrinsics, Pose, RunningMode, TrackerError, TrackerOptions,
};

/// What an app might tell its user: every part of the error is a type the facade names.
fn advice(e: &TrackerError) -> String {
    match e {
        TrackerError::Asset(AssetError::Missing(m)) => format!("install the assets (holoface setup): {m}"),
        TrackerError::Asset(other) => format!("a model file is damaged: {other}"),
        TrackerError::Options(o) => format!("fix the settings: {o}"),
        TrackerError::Link(l) => format!("check the server settings: {l}"),
        TrackerError::Detect(DetectError::Missing(m)) => format!("install the detector: {m}"),
        TrackerError::Detect(d) => format!("the detector failed: {d}"),
        TrackerError::Align(AlignError::Engine(engine)) => format!("the aligner's engine failed: {engine}"),
        TrackerError::Align(a) => format!("alignment failed: {a}"),
        TrackerError::Timestamp { previous, got } => format!("frame at {got} µs after one at {previous} µs"),
        other => other.to_string(),
    }
}

fn main() -> anyhow::Result<()> {
    run().map_err(|e| match e.downcast_ref::<TrackerError>() {
        Some(t) => anyhow::anyhow!("{}", advice(t)),
        None => e,
    })
}

fn run() -> anyhow::Result<()> {
    let path = std::env::args_os().nth(1).map_or_else(
        || holoface_headset_client::assets::home::SAMPLE.default_path(),
        std::path::PathBuf::from,
    );
    let photo = image::open(&path)?.into_luma8();
    let (w, h) = (photo.width() as usize, photo.height() as usize);
    let image = GrayImage::from_vec(photo.into_raw(), w, h)?;
    let camera = Intrinsics {
        fx: 500.0,
        fy: 500.0,
        cx: w as f64 / 2.0,
        cy: h as f64 / 2.0,
    };

    // Image mode: every call detects afresh.
    let mut still = FaceTracker::new(TrackerOptions {
        mode: RunningMode::Image,
        ..TrackerOptions::default()
    })?;
    let frame = Frame {
        timestamp_us: 0,
        image: image.view(),
        intrinsics: camera,
        world_from_camera: Pose::IDENTITY,
    };
    let r = still.process(&frame)?;
    let face = r
        .face()
        .ok_or_else(|| anyhow::anyhow!("no face in {}: {:?}", path.display(), r.no_face))?;
    println!(
        "image: head at {:.3?} m (camera frame), jaw drop {:.2}, answered by {:?}",
        face.fit.translation.to_array(),
        face.expression[Unit::JawDrop],
        r.answered_by
    );

    // Video mode: detect once, then track frame to frame (a still headset here: identity camera-to-world,
    // so world and camera frames coincide; pass the headset's real pose per frame in an app).
    let mut video = FaceTracker::new(TrackerOptions::default())?;
    let mut faces = 0;
    for i in 0..30u32 {
        let frame = Frame {
            timestamp_us: u64::from(i) * 33_333,
            image: image.view(),
            intrinsics: camera,
            world_from_camera: Pose::IDENTITY,
        };
        let r = video.process(&frame)?;
        if let Some(f) = r.face() {
            faces += 1;
            if i % 10 == 0 {
                println!(
                    "video frame {i:2}: world {:.3?} m, display {:.3?} m, {:.2} ms total",
                    f.world.position.to_array(),
                    f.display.0.to_array(),
                    (r.timings.prepare + r.timings.align + r.timings.complete).as_secs_f64() * 1e3
                );
            }
        }
    }
    println!("{faces} of 30 video frames with a face");
    anyhow::ensure!(faces >= 25, "the face was lost");
    Ok(())
}
