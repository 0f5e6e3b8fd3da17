//! HOG for one face (51 landmark windows): the fast path against the naive `atan2` reference, in the
//! same run, with and without the window extraction.
//!
//! `cargo bench -p holoface-models --bench hog -- --warm-up-time 1 --measurement-time 3`
#![allow(clippy::unwrap_used)] // bench setup; a panic is a failed run

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group};
use holoface_models::geometry::Point2;
use holoface_models::hog::{
    HOG_DIM, PATCH_PIXELS, hog_patch, hog_patch_dispatch, hog_patch_naive, hog_points, window_at,
};
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
                hog_patch_dispatch(black_box(w), o);
            }
        })
    });
    g.bench_function("fast_portable", |b| {
        b.iter(|| {
            for (w, o) in windows.iter().zip(out.iter_mut()) {
                hog_patch(black_box(w), o);
            }
        })
    });
    // The peer: imageproc's HOG on the same 51 windows (4×4-pixel cells, 9 unsigned bins, one-cell
    // blocks), each window already an image so only the descriptor is timed.
    let opts = imageproc::hog::HogOptions::new(9, false, 4, 1, 1);
    let peer_windows: Vec<image::GrayImage> = windows
        .iter()
        .map(|w| image::GrayImage::from_raw(16, 16, w.to_vec()).unwrap())
        .collect();
    g.bench_function("imageproc", |b| {
        b.iter(|| {
            for w in &peer_windows {
                black_box(imageproc::hog::hog(black_box(w), opts).unwrap());
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

/// On-CPU nanoseconds of this thread (`/proc/thread-self/schedstat`), robust to a loaded machine.
fn thread_cpu_ns() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

/// Prints on-CPU time per face (51 windows) of the fast and the naive HOG.
fn cpu_time_report() {
    let (img, pts) = scene();
    let view = GrayView::new(&img, 352, 352, 352).unwrap();
    let mut flat = vec![0.0f32; 51 * HOG_DIM];
    let windows: Vec<[u8; PATCH_PIXELS]> = pts
        .iter()
        .map(|p| {
            let mut w = [0u8; PATCH_PIXELS];
            window_at(&view, *p, &mut w);
            w
        })
        .collect();
    let mut out = [0.0f32; HOG_DIM];
    let time = |f: &mut dyn FnMut()| {
        let n = 2000;
        let c0 = thread_cpu_ns().unwrap_or(0);
        for _ in 0..n {
            f();
        }
        (thread_cpu_ns().unwrap_or(0) - c0) as f64 * 1e-3 / f64::from(n)
    };
    let fast = time(&mut || {
        for w in &windows {
            hog_patch_dispatch(black_box(w), &mut out);
        }
    });
    let naive = time(&mut || {
        for w in &windows {
            hog_patch_naive(black_box(w), &mut out);
        }
    });
    let with_windows = time(&mut || hog_points(black_box(&view), black_box(&pts), &mut flat).unwrap());
    eprintln!(
        "hog51 on-CPU per face: fast {fast:.1} us, fast+windows {with_windows:.1} us, naive {naive:.1} us"
    );
}

criterion_group!(benches, bench_hog);

fn main() {
    cpu_time_report();
    benches();
    Criterion::default().configure_from_args().final_summary();
}
