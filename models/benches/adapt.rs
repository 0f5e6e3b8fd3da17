//! The per-person adaptation's cost per face (`holoface_models::adapt`): learning one pair with what KRFWS saw
//! (the sums of 51 per-point regressions on 36 values), solving those regressions (once per link cut, when the
//! first corrected answer asks after new pairs), and correcting one answer. What KRFWS sees at an answer is
//! `krfws/hog_at` in the `krfws` bench.
//!
//! `cargo bench -p holoface-models --bench adapt -- --warm-up-time 1 --measurement-time 3`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;

use criterion::{Criterion, criterion_group};
use holoface_models::adapt::{APPEARANCE, AdaptParams, Appearance, PersonCorrection};
use holoface_models::geometry::{Point2, Similarity2};
use holoface_models::rng::Rng;
use holoface_models::shape::dan_mean_shape;

/// A noisy face of about 90 px and a random look at each point.
fn pair(rng: &mut Rng) -> ([Point2; 68], [Point2; 68], Box<Appearance>) {
    let s = Similarity2::from_parts(1.6, 0.05 * rng.normal(), 200.0, 150.0);
    let mut local = [Point2::default(); 68];
    s.apply_all(&dan_mean_shape(), &mut local);
    let remote = local.map(|q| Point2::new(q.x + 0.5 * rng.normal() as f32, q.y + 0.5 * rng.normal() as f32));
    let mut look = Box::new([[0.0; APPEARANCE]; 51]);
    for v in look.iter_mut().flatten() {
        *v = rng.uniform() as f32;
    }
    (local, remote, look)
}

fn bench_adapt(c: &mut Criterion) {
    let mut rng = Rng::new(1);
    let pairs: Vec<_> = (0..64).map(|_| pair(&mut rng)).collect();
    let mut trained = PersonCorrection::new(AdaptParams::default());
    for (l, r, look) in &pairs {
        trained.learn(l, r, Some(look));
    }
    let mut g = c.benchmark_group("adapt");
    let mut k = 0;
    let mut learning = trained.clone();
    g.bench_function("learn_one_pair", |b| {
        b.iter(|| {
            k += 1;
            let (l, r, look) = &pairs[k % pairs.len()];
            black_box(learning.learn(l, r, Some(look)))
        })
    });
    let (probe, _, look) = pair(&mut rng);
    g.bench_function("refit_and_correct", |b| {
        b.iter_batched_ref(
            || {
                let mut c = trained.clone();
                c.learn(&pairs[0].0, &pairs[0].1, Some(&pairs[0].2));
                c
            },
            |c| black_box(c.correct(&probe, Some(&look))),
            criterion::BatchSize::SmallInput,
        )
    });
    let mut fitted = trained.clone();
    fitted.correct(&probe, Some(&look));
    g.bench_function("correct_one_answer", |b| {
        b.iter(|| black_box(fitted.correct(&probe, Some(&look))))
    });
    g.finish();
}

criterion_group!(benches, bench_adapt);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
