//! Golden tests against the Python training side and the real training data.
//!
//! * The committed mean shape is what our Rust Procrustes computes from `faces68/train` (minus the
//!   validation split).
//! * The Rust crop equals the Python crop DAN was trained on (`models/dan/golden_crops.py`, run by
//!   `make golden` before the tests).
//!
//! Data comes from `$HOLOFACE_DATA` (default `../shared/data` beside the checkout).
#![allow(clippy::unwrap_used)]

use std::path::PathBuf;

use holoface_models::crop::{Crop112, crop_bilinear};
use holoface_models::geometry::Similarity2;
use holoface_models::image::GrayView;
use holoface_models::shape::{canonical_from_mean, dan_mean_shape, parse_pts68, procrustes_mean};

/// Largest per-pixel difference between the Rust and Python crops (grey levels). Both sample in f32 in the
/// same order; only the f64 -> f32 rounding of the inverse similarity differs, which moves a sample by far
/// less than 1e-3 px and flips a rounding at most by one level.
const CROP_MAX_DIFF: u8 = 1;
/// Largest share of pixels allowed to differ at all.
const CROP_MAX_DIFF_SHARE: f64 = 0.001;
/// PIL and image-rs decode the same JPEG with different IDCTs: one grey level on about 0.7 % of pixels.
const DECODE_MAX_DIFF: u8 = 1;
/// Largest share of decoded pixels allowed to differ.
const DECODE_MAX_DIFF_SHARE: f64 = 0.02;
/// Mean shape agreement, crop pixels.
const MEAN_SHAPE_TOL_PX: f32 = 1e-3;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn faces_root() -> PathBuf {
    let base = std::env::var_os("HOLOFACE_DATA").map_or_else(|| repo().join("../shared/data"), PathBuf::from);
    let root = base.join("faces68/train");
    assert!(
        root.is_dir(),
        "training data not found at {} (set HOLOFACE_DATA)",
        root.display()
    );
    root
}

fn split() -> Vec<String> {
    std::fs::read_to_string(repo().join("models/splits/val.txt"))
        .unwrap()
        .lines()
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .map(str::to_owned)
        .collect()
}

#[test]
fn committed_mean_shape_is_the_procrustes_mean_of_the_training_split() {
    let root = faces_root();
    let val: std::collections::HashSet<String> = split().into_iter().collect();
    let mut shapes = Vec::new();
    for sub in ["afw", "helen"] {
        for entry in std::fs::read_dir(root.join(sub)).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "pts") {
                let name = format!("{sub}/{}", path.file_stem().unwrap().to_string_lossy());
                if !val.contains(&name) {
                    shapes.push(parse_pts68(&std::fs::read_to_string(&path).unwrap()).unwrap());
                }
            }
        }
    }
    assert_eq!(shapes.len(), 1106);
    let canon = canonical_from_mean(&procrustes_mean(&shapes).unwrap());
    for (i, (a, b)) in canon.iter().zip(dan_mean_shape().iter()).enumerate() {
        assert!(
            a.dist(*b) < MEAN_SHAPE_TOL_PX,
            "point {i}: rust {a:?} vs committed {b:?}"
        );
    }
}

#[test]
fn rust_crop_matches_the_python_training_crop() {
    let path = repo().join("target/golden/dan_crops.bin");
    let bytes = std::fs::read(&path).unwrap_or_else(|e| {
        panic!(
            "{}: {e}; run `make golden` (the test command does)",
            path.display()
        )
    });
    let root = faces_root();
    let mut cur = Cursor { bytes: &bytes, at: 0 };
    let count = cur.u32() as usize;
    assert!(count >= 20);
    let (mut warp_diff, mut decode_diff, mut total, mut src_total) = (0usize, 0usize, 0usize, 0usize);
    for _ in 0..count {
        let n = cur.u16() as usize;
        let name = std::str::from_utf8(cur.take(n)).unwrap().to_owned();
        let (w, h) = (cur.u32() as usize, cur.u32() as usize);
        let python_src = cur.take(w * h);
        let sim = Similarity2 {
            a: cur.f64(),
            b: cur.f64(),
            tx: cur.f64(),
            ty: cur.f64(),
        };
        let expected = cur.take(112 * 112);

        // 1. The warp alone: same source pixels in, same crop out.
        let view = GrayView::new(python_src, w, h, w).unwrap();
        let mut crop = Crop112::default();
        crop_bilinear(&view, &sim, &mut crop).unwrap();
        for (&r, &p) in crop.as_slice().iter().zip(expected) {
            assert!(r.abs_diff(p) <= CROP_MAX_DIFF, "{name}: rust {r} vs python {p}");
            warp_diff += usize::from(r != p);
            total += 1;
        }

        // 2. The JPEG decoders (image-rs at run time, PIL in training) agree to one grey level.
        let img = image::open(root.join(format!("{name}.jpg"))).unwrap().to_luma8();
        assert_eq!((img.width() as usize, img.height() as usize), (w, h));
        for (&r, &p) in img.as_raw().iter().zip(python_src) {
            assert!(
                r.abs_diff(p) <= DECODE_MAX_DIFF,
                "{name}: decoders differ by {}",
                r.abs_diff(p)
            );
            decode_diff += usize::from(r != p);
            src_total += 1;
        }
    }
    assert_eq!(cur.at, bytes.len());
    let share = warp_diff as f64 / total as f64;
    assert!(share <= CROP_MAX_DIFF_SHARE, "warp: {share:.5} of pixels differ");
    let share = decode_diff as f64 / src_total as f64;
    assert!(
        share <= DECODE_MAX_DIFF_SHARE,
        "jpeg decode: {share:.5} of pixels differ"
    );
}

struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize) -> &'a [u8] {
        let s = &self.bytes[self.at..self.at + n];
        self.at += n;
        s
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take(2).try_into().unwrap())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take(4).try_into().unwrap())
    }
    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take(8).try_into().unwrap())
    }
}
