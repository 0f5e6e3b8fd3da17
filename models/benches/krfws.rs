//! The full KRFWS pipeline per face on one thread: 3 stages + failure score, from a full frame and an
//! initial shape (the GT-box initialisation).
//!
//! Loads `models/assets/krfws.bin` at bench time. The frame is the first validation image of
//! `$HOLOFACE_DATA/faces68/train` (default `../shared/data`) when present, else a synthetic frame.
//!
//! `cargo bench -p holoface-models --bench krfws -- --warm-up-time 1 --measurement-time 5`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;
use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group};
use holoface_models::geometry::{Point2, Rect};
use holoface_models::hog::{HOG_DIM, PATCH_PIXELS, hog_patch_dispatch};
use holoface_models::image::{GrayImage, GrayView};
use holoface_models::isa::Isa;
#[cfg(target_arch = "x86_64")]
use holoface_models::krfws::Avx512;
use holoface_models::krfws::{
    FAILURE_DIM, Krfws, KrfwsScratch, N_POINTS, stage_features, stage_features_with,
};
use holoface_models::shape::parse_pts68;

fn data_root() -> PathBuf {
    std::env::var_os("HOLOFACE_DATA")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"))
}

/// A validation face (image + GT box) or a synthetic 352×352 frame with a box in the middle.
fn frame() -> (GrayImage, Rect, &'static str) {
    let base = data_root().join("faces68/train");
    let split = include_str!("../splits/val.txt");
    if let Some(name) = split
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty() && !l.starts_with('#'))
    {
        let jpg = base.join(format!("{name}.jpg"));
        let pts = base.join(format!("{name}.pts"));
        if let (Ok(img), Ok(text)) = (image::open(&jpg), std::fs::read_to_string(&pts)) {
            let g = img.to_luma8();
            let (w, h) = (g.width() as usize, g.height() as usize);
            let lm = parse_pts68(&text).unwrap();
            return (
                GrayImage::from_vec(g.into_raw(), w, h).unwrap(),
                Rect::bounding(&lm).unwrap(),
                "validation",
            );
        }
    }
    let (w, h) = (352usize, 352usize);
    let img = (0..w * h)
        .map(|i| {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            (120.0 + 50.0 * (x / 17.0).sin() * (y / 13.0).cos()) as u8
        })
        .collect();
    let r = Rect {
        x0: 96.0,
        y0: 96.0,
        x1: 256.0,
        y1: 256.0,
    };
    (GrayImage::from_vec(img, w, h).unwrap(), r, "synthetic")
}

fn bench_align(c: &mut Criterion) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/krfws.bin");
    let Ok(bytes) = std::fs::read(&path) else {
        eprintln!(
            "{} missing: train it with `holoface train-krfws` first; skipping",
            path.display()
        );
        return;
    };
    let model = Krfws::from_bytes(&bytes).unwrap();
    let (img, bbox, kind) = frame();
    eprintln!("frame: {kind} {}x{}", img.width(), img.height());
    let view: GrayView<'_> = img.view();
    let init = model.init_from_box(&bbox);
    let mut scratch = KrfwsScratch::new();
    let mut out = [Point2::default(); N_POINTS];
    let mut g = c.benchmark_group("krfws");
    g.throughput(Throughput::Elements(1));
    g.bench_function("align_3_stages+failure", |b| {
        b.iter(|| model.align(black_box(&view), black_box(&init), &mut scratch, &mut out))
    });
    // The same on the slower code paths (taken on CPUs without AVX-512 / AVX2).
    for (name, isa) in [("align/avx2", Isa::Avx2), ("align/baseline", Isa::Baseline)] {
        g.bench_function(name, |b| {
            b.iter(|| model.align_on(isa, black_box(&view), black_box(&init), &mut scratch, &mut out))
        });
    }
    // The parts of one stage, compiled like `align` (AVX-512F / AVX2 when the CPU has them).
    let stage = &model.stages()[0];
    let mut patch = [0u8; PATCH_PIXELS];
    let mut norm = [Point2::default(); N_POINTS];
    let mut hog = vec![0f32; FAILURE_DIM];
    g.bench_function("part/sample_51_windows+hog", |b| {
        b.iter(|| fast::features(&view, black_box(&init), stage, &mut patch, &mut norm, &mut hog))
    });
    // What the per-person adaptation asks for at an answer (`Krfws::hog_at`, the portable kernels).
    let mut scratch_at = KrfwsScratch::new();
    g.bench_function("hog_at", |b| {
        b.iter(|| black_box(model.hog_at(&view, black_box(&init), &mut scratch_at)))
    });
    let mut row = [0f32; HOG_DIM];
    g.bench_function("part/hog_51_windows", |b| {
        b.iter(|| {
            for _ in 0..N_POINTS {
                hog_patch_dispatch(black_box(&patch), &mut row);
            }
        })
    });
    let mut leaves = vec![0u32; stage.trees.len()];
    g.bench_function("part/route_306_trees", |b| {
        b.iter(|| fast::route(stage, black_box(&hog), &mut leaves))
    });
    g.bench_function("from_bytes", |b| {
        b.iter(|| Krfws::from_bytes(black_box(&bytes)).unwrap())
    });
    g.finish();
}

/// The parts compiled like `Krfws::align` compiles them on this CPU (AVX-512F, AVX2 or baseline).
mod fast {
    use super::*;
    use holoface_models::krfws::Stage;

    /// Tree routing of one stage, as `align` runs it.
    pub(super) fn route(stage: &Stage, hog: &[f32], leaves: &mut [u32]) {
        #[cfg(target_arch = "x86_64")]
        if let Some(k) = Avx512::detect() {
            #[target_feature(enable = "avx512f")]
            fn avx512(k: Avx512, stage: &Stage, hog: &[f32], leaves: &mut [u32]) {
                stage.leaves_with(k, hog, leaves)
            }
            #[allow(unsafe_code)]
            // SAFETY: the token proves AVX-512F.
            return unsafe { avx512(k, stage, hog, leaves) };
        }
        stage.leaves(hog, leaves)
    }

    /// Window sampling and HOG of one stage, as `align` runs them.
    pub(super) fn features(
        view: &GrayView<'_>,
        init: &[Point2; N_POINTS],
        stage: &Stage,
        patch: &mut [u8; PATCH_PIXELS],
        norm: &mut [Point2; N_POINTS],
        hog: &mut [f32],
    ) {
        #[cfg(target_arch = "x86_64")]
        if let Some(k) = Avx512::detect() {
            #[target_feature(enable = "avx512f")]
            fn avx512(
                k: Avx512,
                view: &GrayView<'_>,
                init: &[Point2; N_POINTS],
                stage: &Stage,
                patch: &mut [u8; PATCH_PIXELS],
                norm: &mut [Point2; N_POINTS],
                hog: &mut [f32],
            ) {
                black_box(stage_features_with(k, view, init, stage.dest(), patch, norm, hog));
            }
            #[allow(unsafe_code)]
            // SAFETY: the token proves AVX-512F.
            return unsafe { avx512(k, view, init, stage, patch, norm, hog) };
        }
        black_box(stage_features(view, init, stage.dest(), patch, norm, hog));
    }
}

/// On-CPU nanoseconds of this thread (`/proc/thread-self/schedstat`), robust to a loaded machine.
fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

/// Prints wall and on-CPU time per face over a fixed number of aligns (the machine may be shared).
fn cpu_time_report() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("assets/krfws.bin");
    let Ok(bytes) = std::fs::read(&path) else { return };
    let model = Krfws::from_bytes(&bytes).unwrap();
    let (img, bbox, _) = frame();
    let view = img.view();
    let init = model.init_from_box(&bbox);
    let mut scratch = KrfwsScratch::new();
    let mut out = [Point2::default(); N_POINTS];
    for _ in 0..200 {
        model.align(&view, &init, &mut scratch, &mut out);
    }
    let n = 3000;
    let (t0, c0) = (std::time::Instant::now(), thread_cpu_ns());
    for _ in 0..n {
        black_box(model.align(black_box(&view), &init, &mut scratch, &mut out));
    }
    let wall = t0.elapsed().as_secs_f64() / f64::from(n);
    if let (Some(c0), Some(c1)) = (c0, thread_cpu_ns()) {
        let cpu = (c1 - c0) as f64 * 1e-9 / f64::from(n);
        eprintln!(
            "krfws align: {:.1} us/face on-CPU ({:.0} faces/s per core), {:.1} us/face wall",
            cpu * 1e6,
            1.0 / cpu,
            wall * 1e6
        );
    }
}

criterion_group!(benches, bench_align);

fn main() {
    cpu_time_report();
    benches();
    Criterion::default().configure_from_args().final_summary();
}
