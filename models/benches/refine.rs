//! The refinement cascade per crop on one thread: the server's cost after DAN (issue 27: <= 1.0 ms).
//!
//! Loads `models/assets/refiner.bin` (or `$HOLOFACE_REFINE_MODEL`). The crop is the DAN crop of the first
//! validation face of `$HOLOFACE_DATA/faces68/train` (default `../shared/data`) placed on its
//! ground-truth box, started from the mean shape moved by a few pixels (a start as far off as DAN's
//! typical answer); a synthetic crop when the data is not there.
//!
//! `cargo bench -p holoface-models --bench refine -- --warm-up-time 1 --measurement-time 5`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use holoface_models::crop::{Crop112, crop_bilinear};
use holoface_models::geometry::{Point2, Rect, Similarity2};
use holoface_models::image::GrayImage;
use holoface_models::refine::{RefineCascade, RefineScratch};
use holoface_models::shape::{dan_mean_shape, fit_to_box, parse_pts68};

fn data_root() -> PathBuf {
    std::env::var_os("HOLOFACE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"))
}

fn model() -> RefineCascade {
    let path = std::env::var_os("HOLOFACE_REFINE_MODEL")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/refiner.bin"));
    RefineCascade::from_bytes(&std::fs::read(&path).unwrap()).unwrap()
}

/// A validation face's 112-px crop, or a synthetic one.
fn crop() -> Crop112 {
    let base = data_root().join("faces68/train");
    let name = include_str!("../splits/val.txt")
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
        .unwrap_or_default();
    let mut out = Crop112::default();
    if let (Ok(img), Ok(text)) = (
        image::open(base.join(format!("{name}.jpg"))),
        std::fs::read_to_string(base.join(format!("{name}.pts"))),
    ) {
        let g = img.to_luma8();
        let (w, h) = (g.width() as usize, g.height() as usize);
        let image = GrayImage::from_vec(g.into_raw(), w, h).unwrap();
        let lm = parse_pts68(&text).unwrap();
        let mean = dan_mean_shape();
        let mut init = [Point2::default(); 68];
        fit_to_box(&mean, &Rect::bounding(&lm).unwrap(), &mut init);
        let sim = Similarity2::fit(&init, &mean).unwrap();
        crop_bilinear(&image.view(), &sim, &mut out).unwrap();
    } else {
        for (i, p) in out.0.iter_mut().enumerate() {
            *p = ((i % 112) as f32 * 2.0 + (i / 112) as f32)
                .sin()
                .mul_add(60.0, 120.0) as u8;
        }
    }
    out
}

fn bench(c: &mut Criterion) {
    let model = model();
    let crop = crop();
    let start: [Point2; 68] = dan_mean_shape().map(|p| Point2::new(p.x + 1.5, p.y - 1.0));
    let mut scratch = RefineScratch::default();
    let mut g = c.benchmark_group("refine");
    g.throughput(Throughput::Elements(1));
    g.bench_function(
        format!("crop/{}x{}trees", model.stages.len(), model.stages[0].trees.len()),
        |b| {
            b.iter(|| {
                let mut shape = start;
                model
                    .refine(black_box(crop.as_slice()), &mut shape, &mut scratch)
                    .unwrap();
                black_box(shape)
            });
        },
    );
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
