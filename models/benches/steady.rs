//! The landmark filter's cost per face and frame (68 points, One-Euro in the face's frame, with the camera's
//! motion applied to its state); the budget is 20 us per face.
//!
//! `cargo bench -p holoface-models --bench steady -- --warm-up-time 1 --measurement-time 3`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;

use criterion::{Criterion, criterion_group};
use holoface_models::geometry::{Point2, Similarity2};
use holoface_models::rng::Rng;
use holoface_models::shape::{OUTER_EYE_CORNERS, dan_mean_shape};
use holoface_models::steady::{LandmarkFilter, Source, SteadyParams};

fn bench_steady(c: &mut Criterion) {
    let mean = dan_mean_shape();
    let mut rng = Rng::new(1);
    // 64 noisy frames of a face of about 90 px moving and turning a little, cycled.
    let frames: Vec<[Point2; 68]> = (0..64)
        .map(|k| {
            let s = Similarity2::from_parts(1.6, 0.01 * f64::from(k), 200.0 + f64::from(k), 150.0);
            let mut p = [Point2::default(); 68];
            s.apply_all(&mean, &mut p);
            p.map(|q| Point2::new(q.x + rng.normal() as f32, q.y + rng.normal() as f32))
        })
        .collect();
    let moved = Similarity2::from_parts(1.0, 0.001, 0.5, -0.2);
    let mut f = LandmarkFilter::new(&mean, OUTER_EYE_CORNERS, SteadyParams::default()).unwrap();
    let mut t = 0u64;
    let mut g = c.benchmark_group("steady");
    g.bench_function("one_face_one_frame", |b| {
        b.iter(|| {
            t += 33_333;
            let raw = &frames[(t / 33_333) as usize % frames.len()];
            black_box(f.filter(
                black_box(raw),
                t,
                Source {
                    id: 0,
                    precise: false,
                },
                &moved,
            ))
        })
    });
    g.finish();
}

criterion_group!(benches, bench_steady);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
