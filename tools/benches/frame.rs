//! Client CPU per tracked frame **excluding the aligner** (the target: ≤ 0.5 ms), one thread:
//! `FaceTracker::process` as an app calls it: tracking init with headset-motion compensation, the 112×112
//! DAN crop the remote path sends, verification, CANDIDE-3 fit warm-started, world pose, Kalman prediction,
//! two-frame denoising, attributes. The aligner ([`TruthAligner`]) cuts the crop, then answers with the true
//! landmarks of the rendered frame (a perfect aligner), so the numbers contain none of its cost. Also
//! reported: the same frame with the per-person adaptation the remote aligner adds (KRFWS beside every
//! `learn_every`-th server answer, the pair learnt: `+adapt`), and the JPEG q75 encoding of the crop (the
//! remote path's wire format).
//!
//! Frames: the first validation face rendered as a life-size picture seen by a moving headset
//! (`render.rs`), 60 frames. The detector (BlazeFace through ONNX Runtime) runs once in the set-up to
//! start tracking. Needs `make setup` (the env vars the Makefile exports) and `../shared/data`; skips
//! otherwise.
//!
//! Beside it, `augment/draw_glasses_and_hat_640x480`: drawing the shipped scene (`holoface track --augment
//! default`: glasses and a top hat, the fitted head and a skull as occluders) into one of these frames, for the
//! face tracked over the 30 frames before it (the display delay's history filled).
//!
//! `make bench` or `cargo bench -p holoface-tools --bench frame`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group};
use std::sync::{Arc, Mutex};

use holoface_harness::data::{VALIDATION_SPLIT, default_data_root, read_pts};
use holoface_models::crop::{Crop112, crop_bilinear};
use holoface_models::geometry::Point2;
use holoface_models::image::GrayImage;
use holoface_models::math3::{Mat3, Pose, Vec3};
use holoface_models::shape::dan_mean_shape;
use holoface_runtime::adapt::{AdaptOptions, LocalAdaptation};
use holoface_runtime::align::{
    AlignError, Aligner, Alignment, Candidate, KrfwsAligner, align_from, crop_from_image,
};
use holoface_runtime::detect::BlazeFace;
use holoface_runtime::{
    AnsweredBy, AssetPaths, Confidence, CropCodec, FaceTracker, Frame, FrameResult, GrayView, LandmarkSet,
    SessionOptions, TrackerOptions,
};
use holoface_sources::images::read_gray;
use holoface_tools::render::PlanarScene;
use holoface_tools::render::SCENE_CAMERA;

/// The true landmarks of the frame being processed, shared with the [`TruthAligner`].
type Truths = Arc<Mutex<Vec<[Point2; 68]>>>;

struct Setup {
    /// Without and with the per-person adaptation.
    trackers: [(FaceTracker<TruthAligner>, Truths); 2],
    frames: Vec<(GrayImage, Pose, [Point2; 68])>,
}

/// A perfect aligner: cuts the crop the remote aligner would send, then answers each face with the true
/// landmarks (of the frame being processed) nearest its initial shape, as the server would. With `adapt`,
/// also what the remote aligner adds for the per-person adaptation: KRFWS beside every
/// `learn_every`-th answer, the pair learnt ([`LocalAdaptation`]).
struct TruthAligner {
    truths: Truths,
    canonical: [Point2; 68],
    crop: Crop112,
    adapt: Option<(KrfwsAligner, LocalAdaptation)>,
}

impl TruthAligner {
    fn new() -> (Self, Truths) {
        let truths = Arc::new(Mutex::new(Vec::new()));
        let mean = holoface_models::shape::canonical_from_mean(&dan_mean_shape());
        let aligner = Self {
            truths: Arc::clone(&truths),
            canonical: std::array::from_fn(|i| mean[i]),
            crop: Crop112::default(),
            adapt: None,
        };
        (aligner, truths)
    }
}

impl Aligner for TruthAligner {
    fn name(&self) -> &'static str {
        "truth"
    }

    fn align(&mut self, image: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
        let sim = crop_from_image(init, &self.canonical)?;
        crop_bilinear(image, &sim, &mut self.crop)?;
        let centre = holoface_models::geometry::centroid(init);
        let truths = self.truths.lock().unwrap();
        let nearest = truths
            .iter()
            .min_by(|a, b| {
                let da = holoface_models::geometry::centroid(&a[..]).dist(centre);
                da.total_cmp(&holoface_models::geometry::centroid(&b[..]).dist(centre))
            })
            .ok_or_else(|| AlignError::BadOutput("no truth".into()))?;
        Ok(truth_alignment(nearest))
    }

    fn align_faces(
        &mut self,
        image: &GrayView<'_>,
        faces: &[Candidate],
    ) -> Result<Vec<Alignment>, AlignError> {
        let mut out = faces
            .iter()
            .map(|c| align_from(self, image, &c.init, c.source))
            .collect::<Result<Vec<_>, _>>()?;
        if let Some((krfws, adapt)) = &mut self.adapt {
            adapt.update(krfws, image, faces, &mut out)?;
        }
        Ok(out)
    }
}

/// The tracker of a video with these assets and the perfect aligner.
fn tracker(
    ort: PathBuf,
    det: PathBuf,
    wfm: PathBuf,
    max_faces: usize,
    adapt: bool,
    several: bool,
) -> (FaceTracker<TruthAligner>, Truths) {
    let opts = TrackerOptions {
        assets: AssetPaths {
            ort_dylib: ort,
            detector: det,
            candide: wfm,
            ..AssetPaths::default()
        },
        session: SessionOptions {
            max_faces,
            ..SessionOptions::default()
        },
        // The several-face scenes' faces are small: the several-face detector for every count, one included
        // (with the whole frame alone, the single 0.75-m face of `client_frame_faces/1_faces` went undetected).
        detector: holoface_runtime::DetectorOptions {
            several_faces: Some(several),
            ..Default::default()
        },
        ..TrackerOptions::default()
    };
    let (mut aligner, truths) = TruthAligner::new();
    if adapt {
        let krfws = holoface_runtime::assets::load_krfws(&opts.assets.krfws).unwrap();
        aligner.adapt = Some((
            KrfwsAligner::new(krfws),
            LocalAdaptation::new(AdaptOptions::default()),
        ));
    }
    (
        FaceTracker::with_aligner(&opts, Box::new(aligner), None).unwrap(),
        truths,
    )
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
    let plain = tracker(ort.clone(), det.clone(), wfm.clone(), 1, false, false);
    let adapting = tracker(ort, det, wfm, 1, true, false);
    Some(Setup {
        trackers: [plain, adapting],
        frames,
    })
}

fn truth_alignment(lm: &[Point2; 68]) -> Alignment {
    Alignment {
        landmarks: *lm,
        set: LandmarkSet::Ibug68,
        confidence: Confidence::FaceProbability(1.0),
        accepted: true,
        answered_by: AnsweredBy::RemoteDan,
        adaptation: None,
    }
}

fn bench_frame(c: &mut Criterion) {
    let Some(Setup { trackers, frames }) = setup() else {
        eprintln!("runtime assets or ../shared/data missing (run `make setup`); skipping");
        return;
    };
    let mut g = c.benchmark_group("client_frame");
    g.throughput(Throughput::Elements(1));
    let mut crop = Crop112::default();
    let names = [
        "prepare+crop+fit+pose+filter",
        "prepare+crop+fit+pose+filter+adapt",
    ];
    for ((mut tracker, truths), name) in trackers.into_iter().zip(names) {
        let mut step = |n: usize| -> FrameResult {
            let (img, cam, truth) = &frames[n % frames.len()];
            *truths.lock().unwrap() = vec![*truth];
            let frame = Frame {
                timestamp_us: n as u64 * 33_333,
                image: img.view(),
                intrinsics: SCENE_CAMERA,
                world_from_camera: *cam,
            };
            tracker.process(&frame).unwrap()
        };
        // Start tracking (the detector runs here, outside the measurement).
        let mut n = 0usize;
        assert!(step(n).face().is_some(), "no face in the first frame");
        g.bench_function(name, |b| {
            b.iter(|| {
                n += 1;
                let r = step(n);
                assert!(r.face().is_some(), "tracking lost at frame {n}");
                black_box(r)
            })
        });
        crop.clone_from(&tracker.aligner().crop);
    }
    g.bench_function("crop_jpeg_q75", |b| {
        let codec: CropCodec = "jpeg:75".parse().unwrap();
        b.iter(|| {
            black_box(
                holoface_runtime::crop_codec::encode(codec, black_box(crop.as_slice()), 112, 112).unwrap(),
            )
        })
    });
    g.finish();
}

/// The first validation face's landmark box grown by 15 % on every side, as a life-size picture.
fn face_picture() -> Option<PlanarScene> {
    let name = VALIDATION_SPLIT
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))?;
    let base = default_data_root().join("faces68/train").join(name);
    let photo = read_gray(&base.with_extension("jpg")).ok()?;
    let lm = read_pts(&base.with_extension("pts")).ok()?;
    let r = holoface_models::geometry::Rect::bounding(&lm)?;
    let m = 0.15 * r.width().max(r.height());
    let (x0, y0) = ((r.x0 - m).max(0.0) as usize, (r.y0 - m).max(0.0) as usize);
    let x1 = ((r.x1 + m) as usize).min(photo.width());
    let y1 = ((r.y1 + m) as usize).min(photo.height());
    let mut data = Vec::new();
    for y in y0..y1 {
        data.extend_from_slice(&photo.as_bytes()[y * photo.width() + x0..y * photo.width() + x1]);
    }
    let cut = GrayImage::from_vec(data, x1 - x0, y1 - y0).ok()?;
    let moved = lm.map(|p| Point2::new(p.x - x0 as f32, p.y - y0 as f32));
    PlanarScene::life_size(cut, moved).ok()
}

/// Client CPU per frame with 1, 2, 3 and 5 tracked faces (the same picture side by side, 17 cm apart at
/// 0.75 m, a moving headset), excluding the aligner as above: prepare (every face's motion-compensated
/// init), one crop per face, complete (every face's fit, pose, filters). All faces are tracked before the
/// measurement, so the detector does not run in it.
fn bench_faces(c: &mut Criterion) {
    let (Some(ort), Some(det), Some(picture)) = (
        env_path("ORT_DYLIB_PATH"),
        env_path("HOLOFACE_DETECTOR_MODEL"),
        face_picture(),
    ) else {
        eprintln!("runtime assets or ../shared/data missing (run `make setup`); skipping");
        return;
    };
    let wfm =
        env_path("HOLOFACE_CANDIDE").unwrap_or_else(|| default_data_root().join("candide3/candide3.wfm"));
    let mut g = c.benchmark_group("client_frame_faces");
    for n in [1usize, 2, 3, 5] {
        let frames: Vec<(GrayImage, Pose, Vec<[Point2; 68]>)> = (0..60)
            .map(|i| {
                let t = i as f64 / 30.0;
                let cam = Pose {
                    rotation: Mat3::rot_y(0.05 * (4.0 * t).sin()),
                    translation: Vec3::new(0.01 * t.sin(), 0.0, 0.0),
                };
                let mut img = GrayImage::zeros(640, 480);
                let mut truths = Vec::new();
                for k in 0..n {
                    let plane = Pose {
                        rotation: Mat3::IDENTITY,
                        translation: Vec3::new((k as f64 - (n as f64 - 1.0) / 2.0) * 0.17, 0.0, 0.75),
                    };
                    let h = picture.homography(&SCENE_CAMERA, &cam, &plane);
                    picture.render_over(&h, &mut img).unwrap();
                    truths.push(picture.landmarks_in(&h));
                }
                (img, cam, truths)
            })
            .collect();
        if n == 5 {
            // What a detection costs on such a frame: the whole frame, and with the several-face tiles.
            use holoface_runtime::detect::FaceDetector as _;
            let mut whole = BlazeFace::load(&det, &ort, 1).unwrap();
            let mut tiled = BlazeFace::load(&det, &ort, 1).unwrap();
            tiled.for_several_faces();
            let img = &frames[0].0;
            g.throughput(Throughput::Elements(1));
            g.bench_function("detect_whole_frame", |b| {
                b.iter(|| black_box(whole.detect(&img.view()).unwrap()))
            });
            g.bench_function("detect_with_3x3_tiles", |b| {
                b.iter(|| black_box(tiled.detect(&img.view()).unwrap()))
            });
        }
        let (mut tracker, current) = tracker(ort.clone(), det.clone(), wfm.clone(), n, false, true);
        let mut step = |i: usize| -> usize {
            let (img, cam, truths) = &frames[i % frames.len()];
            current.lock().unwrap().clone_from(truths);
            let frame = Frame {
                timestamp_us: i as u64 * 33_333,
                image: img.view(),
                intrinsics: SCENE_CAMERA,
                world_from_camera: *cam,
            };
            tracker.process(&frame).unwrap().faces.len()
        };
        // Track every face first (the detector runs here, outside the measurement).
        let mut i = 0usize;
        while step(i) < n {
            i += 1;
            assert!(i < 60, "{n} faces: not all detected");
        }
        g.throughput(Throughput::Elements(n as u64));
        g.bench_function(format!("{n}_faces"), |b| {
            b.iter(|| {
                i += 1;
                let tracked = step(i);
                assert_eq!(tracked, n, "a face was lost at frame {i}");
                black_box(tracked)
            })
        });
    }
    g.finish();
}

fn bench_augment(c: &mut Criterion) {
    let Some(Setup { trackers, frames }) = setup() else {
        return;
    };
    let [(mut tracker, truths), _] = trackers;
    let scene =
        holoface_tools::augment::scene::Scene::parse(holoface_tools::augment::scene::DEFAULT_SCENE).unwrap();
    let mut augmenter = holoface_tools::augment::Augmenter::new(scene, tracker.face_model().clone(), 120.0);
    for (n, (img, cam, truth)) in frames.iter().enumerate().take(30) {
        *truths.lock().unwrap() = vec![*truth];
        let frame = Frame {
            timestamp_us: n as u64 * 33_333,
            image: img.view(),
            intrinsics: SCENE_CAMERA,
            world_from_camera: *cam,
        };
        let r = tracker.process(&frame).unwrap();
        augmenter.update(
            frame.timestamp_us,
            r.faces
                .iter()
                .map(holoface_tools::augment::FaceSnapshot::of)
                .collect(),
        );
    }
    assert_eq!(augmenter.anchors().len(), 1, "no face to draw");
    let (img, cam, _) = &frames[29];
    let mut canvas = holoface_harness::plot::Canvas::new(640, 480);
    canvas.blit_gray(0, 0, img.as_bytes(), 640, 480, 1);
    let mut g = c.benchmark_group("augment");
    g.throughput(Throughput::Elements(1));
    g.bench_function("draw_glasses_and_hat_640x480", |b| {
        b.iter_batched_ref(
            || canvas.clone(),
            |cv| augmenter.draw(cv, &SCENE_CAMERA, cam),
            criterion::BatchSize::LargeInput,
        )
    });
    g.finish();
}

criterion_group!(benches, bench_frame, bench_augment, bench_faces);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
