//! Client CPU per tracked frame **excluding the aligner** (the target: ≤ 0.5 ms), one thread:
//! `prepare` (tracking init with headset-motion compensation), the 112×112 DAN crop the remote path
//! sends, and `complete` (verification, CANDIDE-3 fit warm-started, world pose, Kalman prediction,
//! two-frame denoising, attributes). The aligner's answer is replaced by the true landmarks of the
//! rendered frame (a perfect aligner), so the numbers contain none of its cost. Also reported: the JPEG
//! q75 encoding of the crop (the remote path's wire format).
//!
//! Frames: the first validation face rendered as a life-size picture seen by a moving headset
//! (`render.rs`), 60 frames. The detector (BlazeFace through ONNX Runtime) runs once in the set-up to
//! start tracking. Needs `make setup` (the env vars the Makefile exports) and `../shared/data`; skips
//! otherwise.
//!
//! `make bench` or `cargo bench -p holoface-tools --bench frame`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group};
use holoface_client::align::{Alignment, AnsweredBy, Confidence, LandmarkSet, crop_from_image};
use holoface_client::assets::load_face_model;
use holoface_client::detect::BlazeFace;
use holoface_client::frame::Frame;
use holoface_client::images::read_gray;
use holoface_client::link::CropCodec;
use holoface_client::session::{FrameResult, Prepared, SessionOptions, TrackerSession};
use holoface_models::crop::{Crop112, crop_bilinear};
use holoface_models::geometry::Point2;
use holoface_models::image::GrayImage;
use holoface_models::math3::{Mat3, Pose, Vec3};
use holoface_models::shape::dan_mean_shape;
use holoface_tools::data::{VALIDATION_SPLIT, default_data_root, read_pts};
use holoface_tools::render::PlanarScene;
use holoface_tools::render::SCENE_CAMERA;

struct Setup {
    session: TrackerSession,
    frames: Vec<(GrayImage, Pose, [Point2; 68])>,
}

fn env_path(var: &str) -> Option<PathBuf> {
    std::env::var_os(var).map(PathBuf::from).filter(|p| p.exists())
}

fn setup() -> Option<Setup> {
    let (ort, det, wfm) = (
        env_path("ORT_DYLIB_PATH")?,
        env_path("HOLOFACE_DETECTOR_MODEL")?,
        env_path("HOLOFACE_CANDIDE").or_else(|| Some(default_data_root().join("candide3/candide3.wfm")))?,
    );
    let name = VALIDATION_SPLIT
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))?;
    let base = default_data_root().join("faces68/train").join(name);
    let photo = read_gray(&base.with_extension("jpg")).ok()?;
    let lm = read_pts(&base.with_extension("pts")).ok()?;
    let scene = PlanarScene::life_size(photo, lm).unwrap();
    let plane = Pose {
        rotation: Mat3::IDENTITY,
        translation: Vec3::new(0.0, 0.0, 0.6),
    };
    let frames = (0..60)
        .map(|i| {
            let t = i as f64 / 30.0;
            let cam = Pose {
                rotation: Mat3::rot_y(0.2 * (4.0 * t).sin()) * Mat3::rot_x(0.05 * (3.0 * t).sin()),
                translation: Vec3::new(0.02 * t.sin(), 0.0, 0.0),
            };
            let h = scene.homography(&SCENE_CAMERA, &cam, &plane);
            let mut img = GrayImage::zeros(640, 480);
            scene.render(&h, &mut img, 90).unwrap();
            (img, cam, scene.landmarks_in(&h))
        })
        .collect();
    let detector = BlazeFace::load(&det, &ort, 1).unwrap();
    let session = TrackerSession::new(
        Box::new(detector),
        load_face_model(&wfm).unwrap(),
        dan_mean_shape(),
        SessionOptions::default(),
    );
    Some(Setup { session, frames })
}

fn truth_alignment(lm: &[Point2; 68]) -> Alignment {
    Alignment {
        landmarks: *lm,
        set: LandmarkSet::Ibug68,
        confidence: Confidence::FaceProbability(1.0),
        accepted: true,
        answered_by: AnsweredBy::RemoteDan,
    }
}

fn bench_frame(c: &mut Criterion) {
    let Some(Setup { mut session, frames }) = setup() else {
        eprintln!("runtime assets or ../shared/data missing (run `make setup`); skipping");
        return;
    };
    let mean = holoface_models::shape::canonical_from_mean(&dan_mean_shape());
    let canonical: [Point2; 68] = std::array::from_fn(|i| mean[i]);
    let mut crop = Crop112::default();
    let mut step = |n: usize, crop: &mut Crop112| -> FrameResult {
        let (img, cam, truth) = &frames[n % frames.len()];
        let frame = Frame {
            timestamp_us: n as u64 * 33_333,
            image: img.view(),
            intrinsics: SCENE_CAMERA,
            world_from_camera: *cam,
        };
        let Prepared::Align { init, .. } = session.prepare(&frame).unwrap() else {
            panic!("frame {n}: no face")
        };
        let sim = crop_from_image(&init, &canonical).unwrap();
        crop_bilinear(&frame.image, &sim, crop).unwrap();
        session.complete(&frame, Some(truth_alignment(truth)))
    };
    // Start tracking (the detector runs here, outside the measurement).
    let mut n = 0usize;
    assert!(
        matches!(step(n, &mut crop), FrameResult::Face(_)),
        "no face in the first frame"
    );
    let mut g = c.benchmark_group("client_frame");
    g.throughput(Throughput::Elements(1));
    g.bench_function("prepare+crop+fit+pose+filter", |b| {
        b.iter(|| {
            n += 1;
            let r = step(n, &mut crop);
            assert!(matches!(r, FrameResult::Face(_)), "tracking lost at frame {n}");
            black_box(r)
        })
    });
    g.bench_function("crop_jpeg_q75", |b| {
        let codec: CropCodec = "jpeg:75".parse().unwrap();
        b.iter(|| black_box(codec.encode(black_box(crop.as_slice()), 112, 112).unwrap()))
    });
    g.finish();
}

criterion_group!(benches, bench_frame);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
