//! The blendshape coefficients' cost per face and frame (the face's frame from 7 rigid points, the head's turn
//! undone, 27 features,
//! 39 coefficients against the calibrated neutral); the budget is 0.1 ms per face.
//!
//! `cargo bench -p holoface-models --bench blendshapes -- --warm-up-time 1 --measurement-time 3`

use std::hint::black_box;

use criterion::{Criterion, criterion_group};
use holoface_models::blendshapes::{BlendshapeEstimator, BlendshapeParams, HeadTurn};
use holoface_models::geometry::{Point2, Similarity2};
use holoface_models::rng::Rng;
use holoface_models::shape::dan_mean_shape;

fn bench_blendshapes(c: &mut Criterion) {
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
    let mut e = BlendshapeEstimator::new(BlendshapeParams::default());
    // The head turned a little (its shift undone by the pose terms, as in the runtime).
    let turn = Some(HeadTurn {
        across: 0.1,
        down: -0.05,
    });
    for f in &frames[..30] {
        e.update(f, true, turn, 1.0 / 30.0);
    }
    let mut k = 0usize;
    let mut g = c.benchmark_group("blendshapes");
    g.bench_function("one_face_one_frame", |b| {
        b.iter(|| {
            k += 1;
            black_box(e.update(black_box(&frames[k % frames.len()]), true, turn, 1.0 / 30.0))
        })
    });
    g.finish();
}

criterion_group!(benches, bench_blendshapes);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
