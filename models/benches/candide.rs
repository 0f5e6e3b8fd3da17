//! CANDIDE-3 fit per frame (the tracker's target: ≤ 50 µs), on exact projections of a moving head with
//! 0.5 px landmark noise, one thread:
//!
//! * `warm`: warm-started from the previous frame's fit, ≤ 3 Levenberg–Marquardt iterations (what the
//!   tracker runs on every tracked frame);
//! * `cold`: from the landmarks alone, ≤ 10 iterations (the first frame after a detection).
//!
//! Needs the CANDIDE-3 `.wfm` (`$HOLOFACE_CANDIDE`, else `../shared/data/candide3/candide3.wfm`); skips
//! without it. `cargo bench -p holoface-models --bench candide`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group};
use holoface_models::camera::Intrinsics;
use holoface_models::candide::{FaceModel, FitOptions, FitResult, Wfm, fit, project_landmarks};
use holoface_models::expression::{ExpressionWeights, Unit};
use holoface_models::geometry::Point2;
use holoface_models::math3::{Mat3, Quat, Vec3};

const K: Intrinsics = Intrinsics::new(500.0, 500.0, 320.0, 240.0);

fn model() -> Option<FaceModel> {
    let path = std::env::var_os("HOLOFACE_CANDIDE")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/candide3/candide3.wfm")
        });
    let text = std::fs::read_to_string(&path).ok()?;
    FaceModel::from_wfm(&Wfm::parse(&text).unwrap()).ok()
}

/// 60 frames of a head turning and moving, with expression changes, projected with deterministic noise.
fn sequence(model: &FaceModel) -> Vec<[Point2; 68]> {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut noise = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        ((state >> 11) as f64 / (1u64 << 53) as f64 - 0.5) * 2.0 * 0.5 * 3f64.sqrt() // σ ≈ 0.5 px
    };
    (0..60)
        .map(|i| {
            let t = i as f64 / 30.0;
            let rot = Mat3::rot_y(0.5 * (1.3 * t).sin()) * Mat3::rot_x(0.15 * (0.9 * t).sin());
            let mut weights = ExpressionWeights::NEUTRAL;
            weights[Unit::JawDrop] = 0.3 * (0.7 * t).sin().max(0.0);
            weights[Unit::LipStretcher] = 0.2 * (1.1 * t).cos().max(0.0);
            let truth = FitResult {
                rotation: Quat::from_mat3(&rot),
                translation: Vec3::new(0.05 * t.sin(), -0.02, 0.6 + 0.05 * t.cos()),
                weights,
                rmse_px: 0.0,
                iterations: 0,
                converged: true,
            };
            let mut lm = [Point2::default(); 68];
            assert!(project_landmarks(model, &K, &truth, &mut lm));
            for p in &mut lm {
                p.x += noise() as f32;
                p.y += noise() as f32;
            }
            lm
        })
        .collect()
}

fn bench_fit(c: &mut Criterion) {
    let Some(model) = model() else {
        eprintln!("CANDIDE-3 .wfm not found (set HOLOFACE_CANDIDE); skipping");
        return;
    };
    let frames = sequence(&model);
    let warm_opts = FitOptions {
        max_iterations: 3,
        ..FitOptions::default()
    };
    let cold_opts = FitOptions {
        max_iterations: 10,
        ..FitOptions::default()
    };
    // The warm start of frame i is the fit of frame i − 1, as in the tracker.
    let mut prev = Vec::with_capacity(frames.len());
    let mut last = fit(&model, &K, &frames[0], None, &cold_opts).unwrap();
    for f in &frames {
        prev.push(last);
        last = fit(&model, &K, f, Some(&last), &warm_opts).unwrap();
    }
    let mut g = c.benchmark_group("candide_fit");
    g.throughput(Throughput::Elements(1));
    let mut i = 0usize;
    g.bench_function("warm_3_iterations", |b| {
        b.iter(|| {
            i = (i + 1) % frames.len();
            black_box(fit(&model, &K, black_box(&frames[i]), Some(&prev[i]), &warm_opts).unwrap())
        })
    });
    g.bench_function("cold_10_iterations", |b| {
        b.iter(|| {
            i = (i + 1) % frames.len();
            black_box(fit(&model, &K, black_box(&frames[i]), None, &cold_opts).unwrap())
        })
    });
    g.finish();
}

criterion_group!(benches, bench_fit);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
