//! The headset's own path on annotated stills: BlazeFace finds the face, KRFWS aligns it from the
//! detection (its detection starts, as a tracker's first frame does), scored against the annotation (NME49,
//! outer eye corners). One line per face on stdout, tab-separated: `name`, `detected` (0/1), `nme49` (`nan`
//! when missed), the detection's box `x0 y0 x1 y1`, then the 51 landmarks as `x y` pairs.
//!
//! `make arm64-test` runs it twice on the same faces, natively on x86-64 and cross-built for aarch64 under
//! qemu-aarch64, and `scripts/arm64-accuracy.py` compares the two (the architectures' accuracy must agree).
//!
//! ```sh
//! cargo run --release -p holoface-runtime --example detector_krfws -- DATA/faces68/train models/splits/val.txt 4
//! ```
//! Arguments: the annotated folder (`NAME.jpg` beside `NAME.pts`), the list of names, `K`: every K-th
//! name of the list, and optionally a folder of grey images: each photo is read from `GRAY/NAME.pgm` when it is
//! there, else decoded from its JPEG and written there, so that a second run (the emulated one) reads the
//! very pixels the first one decoded and spends no time decoding; and `FIRST`, the index of the first name
//! taken (several runs with `K` = their number and `FIRST` = 0, 1, ... share a list). Assets (`ORT_DYLIB_PATH`, `HOLOFACE_DETECTOR_MODEL`, `HOLOFACE_KRFWS_MODEL`) come from
//! the environment, else from the data folder (`holoface setup`).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use holoface_models::accuracy::nme49;
use holoface_models::geometry::{Point2, Rect};
use holoface_models::image::GrayImage;
use holoface_models::shape::{dan_mean_shape, parse_pts68};
use holoface_runtime::align::{Aligner, KRFWS_DETECTION_STARTS, KrfwsAligner};
use holoface_runtime::assets::{AssetPaths, load_krfws};
use holoface_runtime::detect::{BlazeFace, FaceDetector, shape_from_detection};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (folder, names, every, gray, first) = match args.as_slice() {
        [f, n, e] => (f, n, e, None, "0"),
        [f, n, e, g] => (f, n, e, Some(PathBuf::from(g)), "0"),
        [f, n, e, g, o] => (f, n, e, Some(PathBuf::from(g)), o.as_str()),
        _ => bail!("usage: detector_krfws FOLDER NAMES_FILE EVERY_KTH [GRAY_FOLDER [FIRST]]"),
    };
    let first: usize = first.parse().context("FIRST is a name's index in the list")?;
    let folder = PathBuf::from(folder);
    let every: usize = every.parse().context("EVERY_KTH is a positive integer")?;
    let list = std::fs::read_to_string(names).with_context(|| format!("reading {names}"))?;
    let paths = AssetPaths::default();
    let mut detector = BlazeFace::load(&paths.detector, &paths.ort_dylib, 1)?;
    let mut krfws = KrfwsAligner::new(load_krfws(&paths.krfws)?);
    krfws.set_detection_starts(KRFWS_DETECTION_STARTS);
    let mean = dan_mean_shape();
    let names = list
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'));
    for name in names.skip(first).step_by(every.max(1)) {
        let image = gray_photo(&folder, name, gray.as_deref())?;
        let gt = parse_pts68(&std::fs::read_to_string(folder.join(format!("{name}.pts")))?)?;
        let gt_box = Rect::bounding(&gt).context("empty annotation")?;
        // The detection that matches the annotated face (the photos may hold others), as `holoface eval` picks it.
        let found = detector.detect(&image.view())?;
        let best = found
            .iter()
            .filter(|d| d.bbox.iou(&gt_box) > 0.2)
            .max_by(|a, b| a.bbox.iou(&gt_box).total_cmp(&b.bbox.iou(&gt_box)));
        let mut init = [Point2::default(); 68];
        let mut line = String::from(name);
        match best.filter(|d| shape_from_detection(&mean, d, &mut init)) {
            Some(d) => {
                let a = krfws.align_detection(&image.view(), &init)?;
                let e = nme49(&a.landmarks, &gt).unwrap_or(f64::NAN);
                let b = d.bbox;
                write!(
                    line,
                    "\t1\t{e:.9}\t{:.6} {:.6} {:.6} {:.6}",
                    b.x0, b.y0, b.x1, b.y1
                )?;
                for p in &a.landmarks[17..] {
                    write!(line, "\t{:.4} {:.4}", p.x, p.y)?;
                }
            }
            None => line.push_str("\t0\tnan"),
        }
        println!("{line}");
    }
    Ok(())
}

/// The photo `NAME` as grey levels: from `gray/NAME.pgm` when it is there, else decoded from `NAME.jpg` (and
/// written to `gray/NAME.pgm` when a gray folder is given).
fn gray_photo(folder: &Path, name: &str, gray: Option<&Path>) -> anyhow::Result<GrayImage> {
    let cached = gray.map(|g| g.join(format!("{name}.pgm")));
    if let Some(bytes) = cached.as_ref().and_then(|p| std::fs::read(p).ok()) {
        return read_pgm(&bytes).with_context(|| format!("reading the grey copy of {name}"));
    }
    let photo = image::open(folder.join(format!("{name}.jpg")))
        .with_context(|| format!("reading {name}.jpg"))?
        .into_luma8();
    let (w, h) = (photo.width() as usize, photo.height() as usize);
    if let Some(p) = &cached {
        std::fs::create_dir_all(p.parent().context("a grey copy's folder")?)?;
        let mut pgm = format!("P5\n{w} {h}\n255\n").into_bytes();
        pgm.extend_from_slice(photo.as_raw());
        std::fs::write(p, pgm).with_context(|| format!("writing {}", p.display()))?;
    }
    Ok(GrayImage::from_vec(photo.into_raw(), w, h)?)
}

/// A binary 8-bit PGM as this example writes it (`P5`, width, height, 255, one whitespace, the pixels).
fn read_pgm(bytes: &[u8]) -> anyhow::Result<GrayImage> {
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while bytes.get(at).is_some_and(u8::is_ascii_whitespace) {
            at += 1;
        }
        let start = at;
        while bytes.get(at).is_some_and(|b| !b.is_ascii_whitespace()) {
            at += 1;
        }
        anyhow::ensure!(at > start, "a PGM header with {} of its 4 fields", fields.len());
        fields.push(std::str::from_utf8(&bytes[start..at])?);
    }
    let [magic, w, h, max] = fields[..] else {
        bail!("a PGM header")
    };
    anyhow::ensure!(
        magic == "P5" && max == "255",
        "not a binary 8-bit PGM ({magic}, maximum {max})"
    );
    let (w, h): (usize, usize) = (w.parse()?, h.parse()?);
    let pixels = bytes
        .get(at + 1..)
        .filter(|p| p.len() == w.saturating_mul(h))
        .context("a PGM whose pixels are not width x height bytes")?;
    Ok(GrayImage::from_vec(pixels.to_vec(), w, h)?)
}
