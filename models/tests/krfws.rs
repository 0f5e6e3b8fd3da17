//! KRFWS behaviour on synthetic faces: training reduces the error, the model file round-trips, and a
//! damaged file is a typed error, never a panic.
#![allow(clippy::unwrap_used)]

use std::sync::OnceLock;

use holoface_models::geometry::{Point2, Similarity2};
use holoface_models::image::GrayImage;
use holoface_models::krfws::format::{FORMAT_VERSION, MAGIC};
use holoface_models::krfws::nme49_inner;
use holoface_models::krfws::train::{self, NoProgress, TrainConfig, TrainFace, gt_box};
use holoface_models::krfws::{Krfws, KrfwsScratch, ModelError, N_POINTS};
use holoface_models::rng::Rng;
use holoface_models::shape::dan_mean_shape;
use holoface_protocol::framing::Damage;
use proptest::prelude::*;

/// A synthetic face: dark dots at the 68 landmarks of a randomly placed mean shape on a noisy
/// background, with strokes joining consecutive points of each facial part.
fn synthetic_face(rng: &mut Rng) -> TrainFace {
    let (w, h) = (160usize, 160usize);
    let mean = dan_mean_shape();
    let scale = 1.6 + 0.2 * rng.normal();
    let ang = 0.08 * rng.normal();
    let sim = Similarity2::from_parts(scale, ang, 0.0, 0.0);
    let c = Point2::new(56.0, 56.0);
    let (tx, ty) = (80.0 + 4.0 * rng.normal() as f32, 80.0 + 4.0 * rng.normal() as f32);
    let mut lm = [Point2::default(); 68];
    for (o, p) in lm.iter_mut().zip(mean.iter()) {
        // A little shape noise so not every face is the mean.
        let q = sim.apply(Point2::new(p.x - c.x, p.y - c.y));
        *o = Point2::new(
            q.x + tx + 0.6 * rng.normal() as f32,
            q.y + ty + 0.6 * rng.normal() as f32,
        );
    }
    let mut img: Vec<u8> = (0..w * h)
        .map(|_| (150.0 + 8.0 * rng.normal()).clamp(0.0, 255.0) as u8)
        .collect();
    let mut dot = |p: Point2, r: f32, v: u8| {
        let (x0, y0) = ((p.x - r).floor() as i64, (p.y - r).floor() as i64);
        for y in y0..=y0 + (2.0 * r) as i64 + 1 {
            for x in x0..=x0 + (2.0 * r) as i64 + 1 {
                if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
                    let d = ((x as f32 - p.x).powi(2) + (y as f32 - p.y).powi(2)).sqrt();
                    if d <= r {
                        img[y as usize * w + x as usize] = v;
                    }
                }
            }
        }
    };
    let parts: [std::ops::Range<usize>; 8] = [0..17, 17..22, 22..27, 27..31, 31..36, 36..42, 42..48, 48..68];
    for part in parts {
        for i in part.clone() {
            dot(lm[i], 2.2, 30);
            if i + 1 < part.end {
                for k in 1..4 {
                    let t = k as f32 / 4.0;
                    let q = Point2::new(
                        lm[i].x + t * (lm[i + 1].x - lm[i].x),
                        lm[i].y + t * (lm[i + 1].y - lm[i].y),
                    );
                    dot(q, 1.0, 70);
                }
            }
        }
    }
    TrainFace {
        image: GrayImage::from_vec(img, w, h).unwrap(),
        landmarks: lm,
        starts: None,
        lid_weight: 1.0,
    }
}

fn small_config() -> TrainConfig {
    TrainConfig {
        seed: 5,
        trees: 3,
        depth: 3,
        perturbations: 6,
        min_leaf: 4,
        lda_samples: 120,
        ridge: vec![1.0],
        threads: 2,
        failure_fits: 4,
        ..TrainConfig::default()
    }
}

/// One small model shared by the tests. nextest runs each test in a process of its own, so a model kept in the
/// process alone would be trained once per test (about 3 CPU-s each); it is trained once per build of this test
/// binary instead and kept in the target's scratch folder, under a name made from the binary's size and time, while
/// the other processes wait on a file lock and then read it.
fn model() -> &'static (Krfws, Vec<TrainFace>) {
    static M: OnceLock<(Krfws, Vec<TrainFace>)> = OnceLock::new();
    M.get_or_init(|| {
        let mut rng = Rng::new(42);
        let faces: Vec<TrainFace> = (0..40).map(|_| synthetic_face(&mut rng)).collect();
        (shared_model(&faces[..30]), faces)
    })
}

/// The model of [`model`] trained on `faces`, or read back from where a test of this same binary wrote it.
fn shared_model(faces: &[TrainFace]) -> Krfws {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"));
    let exe = std::fs::metadata(std::env::current_exe().unwrap()).unwrap();
    let stamp = exe
        .modified()
        .unwrap()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap();
    let path = dir.join(format!("krfws-fixture-{}-{}.bin", exe.len(), stamp.as_nanos()));
    let lock = std::fs::File::create(dir.join("krfws-fixture.lock")).unwrap();
    lock.lock().unwrap();
    if let Ok(bytes) = std::fs::read(&path) {
        return Krfws::from_bytes(&bytes).unwrap();
    }
    let (mut m, report) = train::train(faces, &small_config(), &NoProgress).unwrap();
    // Training error falls stage by stage.
    assert!(
        report.stage_nme.windows(2).all(|w| w[1] < w[0]),
        "{:?}",
        report.stage_nme
    );
    m.set_threshold(0.1);
    // Older builds' models go; this one is written whole before its name appears.
    for old in std::fs::read_dir(dir).unwrap().flatten() {
        if old.file_name().to_string_lossy().starts_with("krfws-fixture-") {
            let _ = std::fs::remove_file(old.path());
        }
    }
    let bytes = m.to_bytes().unwrap();
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, &bytes).unwrap();
    std::fs::rename(&tmp, &path).unwrap();
    // Every process tests the model as read back, whichever trained it.
    Krfws::from_bytes(&bytes).unwrap()
}

#[test]
fn trained_model_reduces_error_on_unseen_faces() {
    let (m, faces) = model();
    let mut scratch = KrfwsScratch::new();
    let mut rng = Rng::new(7);
    let (mut before, mut after) = (0.0, 0.0);
    for f in &faces[30..] {
        let init = holoface_models::augment::perturb(
            &m.init_from_box(&gt_box(&f.landmarks)),
            train::SMALL_PERTURBATION,
            &mut rng,
        );
        let mut out = [Point2::default(); N_POINTS];
        let score = m.align(&f.image.view(), &init, &mut scratch, &mut out);
        assert!(score.is_finite());
        before += nme49_inner(&init, &f.landmarks);
        after += nme49_inner(&out, &f.landmarks);
    }
    assert!(after < 0.6 * before, "NME before {before}, after {after}");
}

#[test]
fn failure_score_ranks_gross_failures_above_good_fits() {
    let (m, faces) = model();
    let (fits, _) = train::perturbed_fits(m, &faces[30..], 8, 3, 1, false, &NoProgress);
    let scores: Vec<f32> = fits.iter().map(|f| f.score).collect();
    let labels: Vec<bool> = fits.iter().map(|f| f.nme > 0.08).collect();
    let auc = holoface_models::accuracy::roc_auc(&scores, &labels).unwrap();
    assert!(auc > 0.8, "AUC {auc}");
}

#[test]
fn init_from_previous_is_a_similarity_of_the_mean() {
    let (m, faces) = model();
    let prev: [Point2; N_POINTS] = std::array::from_fn(|i| faces[0].landmarks[17 + i]);
    let init = m.init_from_previous(&prev);
    let s = Similarity2::fit(m.mean_shape(), &init).unwrap();
    for (a, b) in m.mean_shape().iter().zip(&init) {
        assert!(s.apply(*a).dist(*b) < 1e-3);
    }
    // Idempotent: fitting to a fitted mean gives it back.
    let again = m.init_from_previous(&init);
    assert!(again.iter().zip(&init).all(|(a, b)| a.dist(*b) < 1e-3));
}

#[test]
fn model_round_trips_through_bytes() {
    let (m, _) = model();
    let bytes = m.to_bytes().unwrap();
    assert_eq!(&bytes[..8], &MAGIC);
    let back = Krfws::from_bytes(&bytes).unwrap();
    assert_eq!(&back, m);
    assert_eq!(back.to_bytes().unwrap(), bytes);
}

#[test]
fn damaged_headers_are_typed_errors() {
    let (m, _) = model();
    let bytes = m.to_bytes().unwrap();
    let damage = |b: &[u8]| {
        let e = Krfws::from_bytes(b).unwrap_err();
        e.damage()
            .cloned()
            .unwrap_or_else(|| panic!("not the framing's error: {e}"))
    };
    let mut bad = bytes.clone();
    bad[0] ^= 0xFF;
    assert!(matches!(damage(&bad), Damage::BadMagic { .. }));
    let mut bad = bytes.clone();
    bad[8..12].copy_from_slice(&(FORMAT_VERSION + 1).to_le_bytes());
    assert!(matches!(damage(&bad), Damage::UnsupportedVersion { found, .. } if found == FORMAT_VERSION + 1));
    let mut bad = bytes.clone();
    let mid = bytes.len() / 2;
    bad[mid] ^= 0x10;
    assert!(matches!(damage(&bad), Damage::Checksum { .. }));
    let len = bytes.len() as u64;
    assert_eq!(
        damage(&bytes[..bytes.len() - 1]),
        Damage::Truncated {
            offset: len - 1,
            needed: 1,
            len: len - 1
        }
    );
    assert!(matches!(damage(&bytes[..5]), Damage::Truncated { .. }));
    assert!(matches!(damage(&[]), Damage::Truncated { .. }));
    let text = Krfws::from_bytes(&bytes[..5]).unwrap_err().to_string();
    assert!(text.starts_with("KRFWS model: truncated"), "{text}");
}

/// Re-seals a payload with a valid header and CRC, so the structural checks (not the CRC) are tested.
fn seal(payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    out.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    out.extend_from_slice(payload);
    let crc = crc32fast::hash(&out);
    out.extend_from_slice(&crc.to_le_bytes());
    out
}

#[test]
fn bad_tree_pointers_are_rejected_even_with_a_valid_checksum() {
    let (m, _) = model();
    let bytes = m.to_bytes().unwrap();
    let payload = &bytes[16..bytes.len() - 4];
    // The first tree's first node starts after: 3 u32 + 51·2 f32 mean + scale f32 + trees u32 + 2 u32.
    let first_node = 12 + N_POINTS * 8 + 8 + 8;
    for (offset, value, what) in [
        (first_node, 0i32, "self loop"),
        (first_node, 10_000, "child out of range"),
        (first_node, -10_000, "leaf out of range"),
    ] {
        let mut p = payload.to_vec();
        p[offset..offset + 4].copy_from_slice(&value.to_le_bytes());
        let r = Krfws::from_bytes(&seal(&p));
        assert!(matches!(r, Err(ModelError::BadTree { .. })), "{what}: {r:?}");
    }
    // A NaN threshold.
    let mut p = payload.to_vec();
    p[first_node + 8..first_node + 12].copy_from_slice(&f32::NAN.to_le_bytes());
    assert!(matches!(
        Krfws::from_bytes(&seal(&p)),
        Err(ModelError::BadTree { .. })
    ));
    // A huge tree count.
    let mut p = payload.to_vec();
    p[12 + N_POINTS * 8 + 4..12 + N_POINTS * 8 + 8].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(matches!(
        Krfws::from_bytes(&seal(&p)).unwrap_err().damage(),
        Some(Damage::OutOfRange { .. })
    ));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn truncation_is_an_error(cut in 0usize..1_000_000) {
        let (m, _) = model();
        let bytes = m.to_bytes().unwrap();
        let cut = cut % bytes.len();
        prop_assert!(Krfws::from_bytes(&bytes[..cut]).is_err());
        // Also with a header and CRC rewritten to match the shorter payload.
        let payload = &bytes[16..bytes.len() - 4];
        let short = &payload[..cut % payload.len()];
        prop_assert!(Krfws::from_bytes(&seal(short)).is_err());
    }

    #[test]
    fn bit_flips_never_panic(pos in 0usize..1_000_000, bit in 0u8..8, reseal in any::<bool>()) {
        let (m, _) = model();
        let bytes = m.to_bytes().unwrap();
        let mut payload = bytes[16..bytes.len() - 4].to_vec();
        let p = pos % payload.len();
        payload[p] ^= 1 << bit;
        if reseal {
            // Structural checks only: may load (a flipped weight is still a model) but must not panic.
            if let Ok(loaded) = Krfws::from_bytes(&seal(&payload)) {
                let (_, faces) = model();
                let mut scratch = KrfwsScratch::new();
                let mut out = [Point2::default(); N_POINTS];
                let init = loaded.init_from_box(&gt_box(&faces[0].landmarks));
                let _ = loaded.align(&faces[0].image.view(), &init, &mut scratch, &mut out);
            }
        } else {
            let mut b = bytes.clone();
            let q = pos % b.len();
            b[q] ^= 1 << bit;
            prop_assert!(Krfws::from_bytes(&b).is_err());
        }
    }
}

#[test]
fn training_is_deterministic_whatever_the_thread_count() {
    let mut rng = Rng::new(99);
    let faces: Vec<TrainFace> = (0..12).map(|_| synthetic_face(&mut rng)).collect();
    let cfg = TrainConfig {
        trees: 2,
        depth: 2,
        perturbations: 3,
        failure_fits: 4,
        ..small_config()
    };
    let (a, _) = train::train(
        &faces,
        &TrainConfig {
            threads: 1,
            ..cfg.clone()
        },
        &NoProgress,
    )
    .unwrap();
    let (b, _) = train::train(
        &faces,
        &TrainConfig {
            threads: 3,
            ..cfg.clone()
        },
        &NoProgress,
    )
    .unwrap();
    assert_eq!(a.to_bytes().unwrap(), b.to_bytes().unwrap());
    let (c, _) = train::train(
        &faces,
        &TrainConfig {
            seed: 6,
            threads: 2,
            ..cfg
        },
        &NoProgress,
    )
    .unwrap();
    assert_ne!(a.to_bytes().unwrap(), c.to_bytes().unwrap());
}

/// Mean distance of the 8 lid points of a 51-point fit from the truth (image pixels).
fn lid_error(fit: &[Point2; N_POINTS], truth: &[Point2; 68]) -> f64 {
    train::LID_POINTS
        .iter()
        .map(|&k| {
            let (p, t) = (fit[k], truth[17 + k]);
            f64::from(((p.x - t.x).powi(2) + (p.y - t.y).powi(2)).sqrt())
        })
        .sum::<f64>()
        / train::LID_POINTS.len() as f64
}

#[test]
fn lid_weight_zero_keeps_bad_teacher_lids_out_of_the_lids() {
    let mut rng = Rng::new(17);
    let faces: Vec<TrainFace> = (0..30).map(|_| synthetic_face(&mut rng)).collect();
    // "Teacher" copies of the first 20 faces whose lid labels sit 6 px too low.
    let teacher = |w: f32| -> Vec<TrainFace> {
        let mut all: Vec<TrainFace> = faces[..20].to_vec();
        all.extend(faces[..20].iter().map(|f| {
            let mut t = f.clone();
            for &k in &train::LID_POINTS {
                t.landmarks[17 + k].y += 6.0;
            }
            t.starts = Some(6);
            t.lid_weight = w;
            t
        }));
        all
    };
    let lid_error_on_unseen = |w: f32| {
        let (m, _) = train::train(&teacher(w), &small_config(), &NoProgress).unwrap();
        let mut scratch = KrfwsScratch::new();
        let mut out = [Point2::default(); N_POINTS];
        faces[20..]
            .iter()
            .map(|f| {
                m.align(
                    &f.image.view(),
                    &m.init_from_box(&gt_box(&f.landmarks)),
                    &mut scratch,
                    &mut out,
                );
                lid_error(&out, &f.landmarks)
            })
            .sum::<f64>()
            / 10.0
    };
    let (trusted, ignored) = (lid_error_on_unseen(1.0), lid_error_on_unseen(0.0));
    assert!(
        ignored < 0.7 * trusted,
        "lid error with the bad lids weighed 1: {trusted} px, 0: {ignored} px"
    );
    let mut bad = teacher(f32::NAN);
    bad.truncate(21);
    assert!(train::train(&bad, &small_config(), &NoProgress).is_err());
}
