//! The 112×112 DAN crop of one face, alone and with a neighbour blanked out of it (several faces), in the
//! same run: what blanking adds per face.
//!
//! `cargo bench -p holoface-models --bench crop -- --warm-up-time 1 --measurement-time 3`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;

use criterion::{Criterion, criterion_group};
use holoface_models::crop::{Crop112, blank_outside, crop_bilinear};
use holoface_models::geometry::{Rect, Similarity2};
use holoface_models::image::GrayView;

fn bench_crop(c: &mut Criterion) {
    let (w, h) = (640usize, 480usize);
    let img: Vec<u8> = (0..w * h).map(|i| ((i % w) ^ (i / w)) as u8).collect();
    let view = GrayView::new(&img, w, h, w).unwrap();
    // A face of about 95 px at (300, 240), rotated a little; its neighbour 90 px to the right.
    let sim = Similarity2::from_parts(0.9, 0.1, -220.0, -190.0);
    let keep = Rect {
        x0: 250.0,
        y0: 190.0,
        x1: 350.0,
        y1: 300.0,
    };
    let others = [Rect {
        x0: 335.0,
        y0: 185.0,
        x1: 450.0,
        y1: 305.0,
    }];
    let mut crop = Crop112::default();
    let mut g = c.benchmark_group("dan_crop");
    g.bench_function("crop", |b| {
        b.iter(|| crop_bilinear(&view, black_box(&sim), &mut crop).unwrap())
    });
    g.bench_function("crop_and_blank_one_neighbour", |b| {
        b.iter(|| {
            crop_bilinear(&view, black_box(&sim), &mut crop).unwrap();
            blank_outside(&mut crop, &sim, &keep, black_box(&others));
        })
    });
    g.finish();
}

criterion_group!(benches, bench_crop);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
