//! `holoface teacher-labels`: labels unannotated face photographs with two teachers and keeps the faces they
//! agree on (issue 36).
//!
//! Teacher 1 is dlib's shipped 68-point predictor on the image and on its mirror image
//! (`models/teacher/dlib_teacher.py` writes its answers); teacher 2 is our own remote pipeline (the crop
//! through the wire's JPEG q75 round trip, DAN, the refinement cascade), started from dlib's answer the way a
//! tracker starts from the previous landmarks. The label is `w · dlib + (1 − w) · remote`; a face is kept
//! when dlib agrees with its own mirror image and with the remote answer within the thresholds, and DAN
//! calls it a face.
//!
//! With `--gt` the images are annotated (the validation split of `faces68/train`): nothing is written but a
//! report of every teacher, every weight and every threshold against the ground truth, which is how the
//! defaults below were chosen.

use std::collections::BTreeMap;
use std::io::BufRead as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, bail, ensure};
use holoface_models::accuracy::{nme49, nme68};
use holoface_models::geometry::Point2;
use holoface_runtime::align::Aligner;
use serde::Serialize;

use crate::args::RuntimeArgs;
use crate::labels::{LabelHeader, LabelRecord};

/// Arguments of `holoface teacher-labels`.
#[derive(Debug, clap::Args)]
pub struct Args {
    /// dlib's answers (`models/teacher/dlib_teacher.py --out`).
    #[arg(long)]
    pub dlib: PathBuf,
    /// The folder the images are in (the names in `--dlib` are relative to it).
    #[arg(long)]
    pub images: PathBuf,
    /// Collection name written into the labels (default: the `--dlib` file's first name part).
    #[arg(long)]
    pub collection: Option<String>,
    /// Label file to write (`.hflabels`); its manifest goes beside it (`.json`). Not with `--gt`.
    #[arg(long, required_unless_present = "gt")]
    pub out: Option<PathBuf>,
    /// The images are annotated (`NAME.pts` beside each): measure the teachers against the annotation and
    /// write the report to `--report` instead of labels.
    #[arg(long)]
    pub gt: bool,
    /// The measurement report (`--gt`).
    #[arg(long, default_value = "runs/teacher/validation.json")]
    pub report: PathBuf,
    /// Weight of dlib's answer (image and mirror averaged) in the label; the remote answer has the rest.
    #[arg(long, default_value_t = DLIB_WEIGHT)]
    pub dlib_weight: f32,
    /// Largest disagreement (NME68) between dlib's answer and the remote one for a face to be kept.
    #[arg(long, default_value_t = MAX_DISAGREEMENT)]
    pub max_disagreement: f64,
    /// Largest disagreement (NME68) between dlib's answers on the image and on its mirror image.
    #[arg(long, default_value_t = MAX_SELF_DISAGREEMENT)]
    pub max_self_disagreement: f64,
    #[command(flatten)]
    /// Runtime assets (DAN, refiner, ONNX Runtime).
    pub runtime: RuntimeArgs,
}

/// The measured defaults (docs/experiments/teacher-labels.md).
pub const DLIB_WEIGHT: f32 = 0.8;
/// See [`DLIB_WEIGHT`].
pub const MAX_DISAGREEMENT: f64 = 0.04;
/// See [`DLIB_WEIGHT`].
pub const MAX_SELF_DISAGREEMENT: f64 = 0.04;
const WEIGHTS: [f32; 9] = [0.0, 0.25, 0.5, 0.6, 0.7, 0.75, 0.8, 0.9, 1.0];
const THRESHOLDS: [f64; 7] = [0.02, 0.03, 0.04, 0.05, 0.06, 0.08, f64::INFINITY];

/// One line of dlib's answers.
#[derive(Debug)]
struct DlibAnswer {
    name: String,
    image: [Point2; 68],
    mirror: [Point2; 68],
}

fn parse_points(v: &[f32]) -> [Point2; 68] {
    std::array::from_fn(|i| Point2::new(v[2 * i], v[2 * i + 1]))
}

fn parse_dlib_line(line: &str) -> anyhow::Result<DlibAnswer> {
    let (name, rest) = line.split_once('\t').context("no tab after the image name")?;
    let v: Vec<f32> = rest
        .split_ascii_whitespace()
        .map(str::parse)
        .collect::<Result<_, _>>()
        .context("a number does not parse")?;
    ensure!(v.len() == 4 + 272, "{} numbers, expected 276", v.len());
    ensure!(v.iter().all(|x| x.is_finite()), "a number is not finite");
    Ok(DlibAnswer {
        name: name.to_owned(),
        image: parse_points(&v[4..140]),
        mirror: parse_points(&v[140..276]),
    })
}

/// Reads dlib's answers (bounded: a line per image, at most 64 MiB of them).
fn read_dlib(path: &Path) -> anyhow::Result<Vec<DlibAnswer>> {
    const MAX: u64 = 256 << 20;
    let f = std::fs::File::open(path).with_context(|| {
        format!(
            "reading dlib's answers {} (models/teacher/dlib_teacher.py writes them)",
            path.display()
        )
    })?;
    let len = f.metadata()?.len();
    ensure!(len <= MAX, "{} is {len} bytes, more than {MAX}", path.display());
    let mut out = Vec::new();
    for (i, line) in std::io::BufReader::new(f).lines().enumerate() {
        let line = line?;
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        out.push(parse_dlib_line(&line).with_context(|| format!("{} line {}", path.display(), i + 1))?);
    }
    Ok(out)
}

fn mean_of(a: &[Point2; 68], b: &[Point2; 68], wa: f32) -> [Point2; 68] {
    std::array::from_fn(|i| {
        Point2::new(
            wa * a[i].x + (1.0 - wa) * b[i].x,
            wa * a[i].y + (1.0 - wa) * b[i].y,
        )
    })
}

/// Mean and 95th percentile of a list of errors.
#[derive(Debug, Default, Serialize)]
struct Stat {
    faces: usize,
    nme68_mean: f64,
    nme68_p95: f64,
    nme49_mean: f64,
}

fn stat(e68: &[f64], e49: &[f64]) -> Stat {
    let mut s = e68.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len().max(1) as f64;
    Stat {
        faces: e68.len(),
        nme68_mean: s.iter().sum::<f64>() / n,
        nme68_p95: s
            .get(((s.len() as f64 * 0.95) as usize).min(s.len().saturating_sub(1)))
            .copied()
            .unwrap_or(0.0),
        nme49_mean: e49.iter().sum::<f64>() / n,
    }
}

/// One labelled face with every teacher's answer.
struct Labelled {
    name: String,
    dlib_image: [Point2; 68],
    dlib_mirror: [Point2; 68],
    dlib: [Point2; 68],
    remote: [Point2; 68],
    self_disagreement: f64,
    disagreement: f64,
}

#[derive(Debug, Serialize)]
struct FilterRow {
    max_disagreement: f64,
    kept: usize,
    kept_fraction: f64,
    label: Stat,
}

#[derive(Debug, Serialize)]
struct GtReport {
    images: usize,
    dlib_found: usize,
    remote_accepted: usize,
    teachers: BTreeMap<String, Stat>,
    filter: Vec<FilterRow>,
    chosen: FilterRow,
    dlib_weight: f32,
    max_self_disagreement: f64,
}

#[derive(Debug, Serialize)]
struct Manifest {
    collection: String,
    images_folder: PathBuf,
    label_file: PathBuf,
    dlib_answers: PathBuf,
    faces_with_dlib_answer: usize,
    remote_rejected: usize,
    dropped_self_disagreement: usize,
    dropped_disagreement: usize,
    kept: usize,
    dlib_weight: f32,
    max_disagreement: f64,
    max_self_disagreement: f64,
    teachers: String,
    seconds: f64,
}

/// Runs `holoface teacher-labels`.
pub fn run(args: Args) -> anyhow::Result<()> {
    ensure!(
        (0.0..=1.0).contains(&args.dlib_weight),
        "--dlib-weight must be within 0..=1"
    );
    let t0 = Instant::now();
    let answers = read_dlib(&args.dlib)?;
    if answers.is_empty() {
        bail!("{} holds no answers", args.dlib.display());
    }
    let mut remote = args.runtime.remote_aligner()?;
    let teachers = format!(
        "dlib 68-point predictor (face_recognition_models 0.3.0 via dlib-bin 20.0.1, image + mirror image, 2x scale) \
         and the remote pipeline (DAN {} + refiner {}, JPEG q75), label = {:.2} dlib + {:.2} remote",
        args.runtime.dan_model.display(),
        args.runtime.refine_model.display(),
        args.dlib_weight,
        1.0 - args.dlib_weight
    );
    let mut labelled = Vec::with_capacity(answers.len());
    let mut rejected = 0usize;
    for (i, a) in answers.iter().enumerate() {
        let image = holoface_sources::images::read_gray(&args.images.join(&a.name))?;
        let dlib = mean_of(&a.image, &a.mirror, 0.5);
        // The tracker's path: the previous landmarks (here dlib's) are the start.
        let r = remote
            .align(&image.view(), &dlib)
            .with_context(|| format!("remote teacher on {}", a.name))?;
        if !r.accepted {
            rejected += 1;
            continue;
        }
        labelled.push(Labelled {
            name: a.name.clone(),
            dlib_image: a.image,
            dlib_mirror: a.mirror,
            dlib,
            remote: r.landmarks,
            self_disagreement: nme68(&a.mirror, &a.image).unwrap_or(f64::INFINITY),
            disagreement: nme68(&r.landmarks, &dlib).unwrap_or(f64::INFINITY),
        });
        if (i + 1).is_multiple_of(2000) {
            tracing::info!(faces = i + 1, of = answers.len(), "remote teacher");
        }
    }
    if args.gt {
        return gt_report(&args, &answers, rejected, &labelled);
    }
    let out = args.out.clone().context("--out is required without --gt")?;
    let keep = |l: &&Labelled| {
        l.self_disagreement <= args.max_self_disagreement && l.disagreement <= args.max_disagreement
    };
    let dropped_self = labelled
        .iter()
        .filter(|l| l.self_disagreement > args.max_self_disagreement)
        .count();
    let records: Vec<LabelRecord> = labelled
        .iter()
        .filter(keep)
        .map(|l| LabelRecord {
            name: l.name.clone(),
            landmarks: mean_of(&l.dlib, &l.remote, args.dlib_weight),
            disagreement: l.disagreement as f32,
        })
        .collect();
    let collection = args.collection.clone().unwrap_or_else(|| {
        let stem = args
            .dlib
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        stem.split('.').next().unwrap_or("faces").to_owned()
    });
    let images = std::path::absolute(&args.images)?;
    let header = LabelHeader {
        collection: collection.clone(),
        images: images.clone(),
        teachers: teachers.clone(),
        settings: serde_json::json!({
            "dlib_weight": args.dlib_weight,
            "max_disagreement": args.max_disagreement,
            "max_self_disagreement": args.max_self_disagreement,
        }),
    };
    let bytes = crate::labels::to_bytes(&header, &records)?;
    crate::cli::write_atomic(&out, &bytes)?;
    let manifest = Manifest {
        collection,
        images_folder: images,
        label_file: out.clone(),
        dlib_answers: args.dlib.clone(),
        faces_with_dlib_answer: answers.len(),
        remote_rejected: rejected,
        dropped_self_disagreement: dropped_self,
        dropped_disagreement: labelled.len() - dropped_self - records.len(),
        kept: records.len(),
        dlib_weight: args.dlib_weight,
        max_disagreement: args.max_disagreement,
        max_self_disagreement: args.max_self_disagreement,
        teachers,
        seconds: t0.elapsed().as_secs_f64(),
    };
    let json = out.with_extension("json");
    crate::cli::write_atomic(&json, serde_json::to_string_pretty(&manifest)? + "\n")?;
    crate::say!(
        "{}: {} faces with dlib's answer, {} rejected by DAN, {} dropped (dlib vs its mirror), {} dropped (dlib vs \
         remote), {} kept -> {} ({:.0} s)",
        manifest.collection,
        manifest.faces_with_dlib_answer,
        rejected,
        dropped_self,
        manifest.dropped_disagreement,
        records.len(),
        out.display(),
        manifest.seconds
    );
    Ok(())
}

fn gt_report(
    args: &Args,
    answers: &[DlibAnswer],
    rejected: usize,
    labelled: &[Labelled],
) -> anyhow::Result<()> {
    let gts: Vec<[Point2; 68]> = labelled
        .iter()
        .map(|l| holoface_harness::data::read_pts(&args.images.join(&l.name).with_extension("pts")))
        .collect::<anyhow::Result<_>>()?;
    let errors = |f: &dyn Fn(&Labelled) -> [Point2; 68], which: &dyn Fn(&Labelled) -> bool| {
        let (mut e68, mut e49) = (Vec::new(), Vec::new());
        for (l, gt) in labelled.iter().zip(&gts).filter(|(l, _)| which(l)) {
            let p = f(l);
            e68.push(nme68(&p, gt).unwrap_or(f64::INFINITY));
            e49.push(nme49(&p, gt).unwrap_or(f64::INFINITY));
        }
        stat(&e68, &e49)
    };
    let all = |_: &Labelled| true;
    let mut teachers = BTreeMap::new();
    teachers.insert("dlib (image)".to_owned(), errors(&|l| l.dlib_image, &all));
    teachers.insert("dlib (mirror image)".to_owned(), errors(&|l| l.dlib_mirror, &all));
    teachers.insert("dlib (both, averaged)".to_owned(), errors(&|l| l.dlib, &all));
    teachers.insert(
        "remote (DAN + refiner, from dlib)".to_owned(),
        errors(&|l| l.remote, &all),
    );
    for w in WEIGHTS {
        teachers.insert(
            format!("combined, dlib weight {w:.2}"),
            errors(&|l| mean_of(&l.dlib, &l.remote, w), &all),
        );
    }
    let w = args.dlib_weight;
    let row = |t: f64| {
        let keep = |l: &Labelled| l.self_disagreement <= args.max_self_disagreement && l.disagreement <= t;
        let label = errors(&|l| mean_of(&l.dlib, &l.remote, w), &keep);
        FilterRow {
            max_disagreement: t,
            kept: label.faces,
            kept_fraction: label.faces as f64 / answers.len().max(1) as f64,
            label,
        }
    };
    let filter: Vec<FilterRow> = THRESHOLDS.iter().map(|&t| row(t)).collect();
    let report = GtReport {
        images: answers.len(),
        dlib_found: answers.len(),
        remote_accepted: answers.len() - rejected,
        teachers,
        filter,
        chosen: row(args.max_disagreement),
        dlib_weight: w,
        max_self_disagreement: args.max_self_disagreement,
    };
    crate::say!(
        "teachers against the annotation ({} faces with dlib's answer, {} accepted by DAN):",
        report.images,
        report.remote_accepted
    );
    for (name, s) in &report.teachers {
        crate::say!(
            "  {name:<36} NME68 {:.2} % (p95 {:.2} %)  NME49 {:.2} %",
            100.0 * s.nme68_mean,
            100.0 * s.nme68_p95,
            100.0 * s.nme49_mean
        );
    }
    crate::say!(
        "kept faces (dlib vs its mirror <= {:.1} %, label = {w:.2} dlib):",
        100.0 * args.max_self_disagreement
    );
    for r in report.filter.iter().chain(std::iter::once(&report.chosen)) {
        crate::say!(
            "  dlib vs remote <= {:>5.1} %: kept {:>4} ({:.1} %), label NME68 {:.2} % (p95 {:.2} %) NME49 {:.2} %",
            100.0 * r.max_disagreement,
            r.kept,
            100.0 * r.kept_fraction,
            100.0 * r.label.nme68_mean,
            100.0 * r.label.nme68_p95,
            100.0 * r.label.nme49_mean
        );
    }
    if let Some(dir) = args.report.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    crate::cli::write_atomic(&args.report, serde_json::to_string_pretty(&report)? + "\n")?;
    crate::say!("wrote {}", args.report.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dlib_lines_parse_and_bad_ones_say_why() {
        let nums: Vec<String> = (0..276).map(|i| format!("{}.5", i % 200)).collect();
        let line = format!("a/b.jpg\t{}", nums.join(" "));
        let a = parse_dlib_line(&line).unwrap();
        assert_eq!(a.name, "a/b.jpg");
        assert_eq!(a.image[0], Point2::new(4.5, 5.5));
        assert_eq!(a.mirror[67], Point2::new(74.5, 75.5));
        let short = format!("a.jpg\t{}", nums[..100].join(" "));
        assert!(
            parse_dlib_line(&short)
                .unwrap_err()
                .to_string()
                .contains("expected 276")
        );
        assert!(parse_dlib_line("no tab here").is_err());
        let nan = line.replacen("4.5", "NaN", 1);
        assert!(
            parse_dlib_line(&nan)
                .unwrap_err()
                .to_string()
                .contains("not finite")
        );
    }

    #[test]
    fn weights_blend_the_teachers() {
        let a: [Point2; 68] = std::array::from_fn(|i| Point2::new(i as f32, 0.0));
        let b: [Point2; 68] = std::array::from_fn(|i| Point2::new(i as f32 + 4.0, 8.0));
        let m = mean_of(&a, &b, 0.25);
        assert_eq!(m[3], Point2::new(6.0, 6.0));
        assert_eq!(mean_of(&a, &b, 1.0), a);
    }
}
