//! HOG for one face (51 landmark windows): the fast path against the naive `atan2` reference, in the
//! same run, with and without the window extraction.
//!
//! `cargo bench -p holoface-models --bench hog -- --warm-up-time 1 --measurement-time 3`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group};
use holoface_models::geometry::Point2;
use holoface_models::hog::{HOG_DIM, PATCH_PIXELS, hog_patch, hog_patch_naive, hog_points, window_at};
use holoface_models::image::GrayView;

/// A 352×352 textured image (smooth shading, blobs and noise) and 51 landmark-like points.
fn scene() -> (Vec<u8>, Vec<Point2>) {
    let (w, h) = (352usize, 352usize);
    let mut s = 0x2545_f491u32;
    let mut noise = move || {
        s ^= s << 13;
        s ^= s >> 17;
        s ^= s << 5;
        (s >> 27) as f32
    };
    let img = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            let v =
                100.0 + 60.0 * (x / 23.0).sin() * (y / 31.0).cos() + 20.0 * ((x + y) / 9.0).sin() + noise();
            v.clamp(0.0, 255.0) as u8
        })
        .collect();
    let pts = (0..51)
        .map(|k| {
            Point2::new(
                110.0 + 2.7 * (k % 10) as f32 * 5.0,
                120.0 + 2.3 * (k / 10) as f32 * 6.0,
            )
        })
        .collect();
    (img, pts)
}

fn bench_hog(c: &mut Criterion) {
    let (img, pts) = scene();
    let view = GrayView::new(&img, 352, 352, 352).unwrap();
    let windows: Vec<[u8; PATCH_PIXELS]> = pts
        .iter()
        .map(|p| {
            let mut w = [0u8; PATCH_PIXELS];
            window_at(&view, *p, &mut w);
            w
        })
        .collect();
    let mut out = vec![[0.0f32; HOG_DIM]; 51];
    let mut flat = vec![0.0f32; 51 * HOG_DIM];
    let mut g = c.benchmark_group("hog51");
    g.throughput(Throughput::Elements(1));
    g.bench_function("fast", |b| {
        b.iter(|| {
            for (w, o) in windows.iter().zip(out.iter_mut()) {
                hog_patch(black_box(w), o);
            }
        })
    });
    g.bench_function("naive", |b| {
        b.iter(|| {
            for (w, o) in windows.iter().zip(out.iter_mut()) {
                hog_patch_naive(black_box(w), o);
            }
        })
    });
    g.bench_function("fast+windows", |b| {
        b.iter(|| hog_points(black_box(&view), black_box(&pts), &mut flat).unwrap())
    });
    g.finish();
}

criterion_group!(benches, bench_hog);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
