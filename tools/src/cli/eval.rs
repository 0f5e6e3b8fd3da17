//! `holoface eval`: the single-image pipeline (detect, place the mean shape, align) over an annotated folder,
//! with 68- and 49-point errors normalised by the outer eye corners, AUC@0.08, failure rate and a CED plot.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use anyhow::{Context, bail};
use clap::{Args as ClapArgs, ValueEnum};
use holoface_models::accuracy::{ErrorSummary, largest_yaw, nme49, nme68, summarise};
use holoface_models::blendshapes::{BlendshapeEstimator, Blendshapes};
use holoface_models::geometry::{Point2, Rect};
use holoface_models::shape::{dan_mean_shape, fit_to_box};
use serde::Serialize;

use crate::args::{AlignerKind, RuntimeArgs};
use crate::expressions::{CoefficientAgreement, agreement, overall_abs_diff};
use holoface_harness::data::{Split, faces68_or, list_folder};
use holoface_harness::plot::{Curve, ced_plot_png};
use holoface_runtime::align::{Aligner, Confidence};
use holoface_runtime::detect::{BlazeFace, FaceDetector, shape_from_detection};

/// How the initial shape is placed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Init {
    /// BlazeFace detection, mean shape placed on its keypoints (the full pipeline).
    Detector,
    /// Mean shape fitted to the ground truth's bounding box (compares aligners without the detector).
    GtBox,
}

/// Which split of the folder to evaluate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum SplitArg {
    /// Every image.
    All,
    /// The fixed validation split (`models/splits/val.txt`).
    Validation,
}

/// Arguments of `holoface eval`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// Folder of `NAME.jpg`/`.png` + `NAME.pts` (68 points, 0-based), optionally one level of subfolders.
    #[arg(long)]
    pub data: Option<PathBuf>,
    /// Evaluate every image or only the validation split.
    #[arg(long, value_enum, default_value = "all")]
    pub split: SplitArg,
    /// Aligners to run (comma-separated).
    #[arg(long, value_enum, value_delimiter = ',', default_value = "dan")]
    pub aligner: Vec<AlignerKind>,
    /// Initial shape.
    #[arg(long, value_enum, default_value = "detector")]
    pub init: Init,
    #[command(flatten)]
    /// Runtime assets.
    pub runtime: RuntimeArgs,
    /// KRFWS starts per face (several starts with the median answer, as on a tracker's detection frames;
    /// 1 = a single alignment, the headset's per-frame cost when tracking).
    #[arg(long, default_value_t = holoface_runtime::align::KRFWS_DETECTION_STARTS)]
    pub krfws_starts: usize,
    /// Time this many passes over the faces (accuracy is from the first); `ms_per_face` is the mean.
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// JSON report.
    #[arg(long, default_value = "runs/eval.json")]
    pub out: PathBuf,
    /// CED plot (PNG).
    #[arg(long, default_value = "runs/ced.png")]
    pub plot: PathBuf,
    /// Pass DAN's crops through this wire encoding first (`raw`, `png`, `jpeg`, `jpeg:Q`), as the server
    /// would receive them; measures the accuracy cost of an encoding. Default: the crop as is.
    #[arg(long)]
    pub crop_encoding: Option<holoface_runtime::link::CropCodec>,
}

#[derive(Debug, Serialize)]
struct PerImage {
    name: String,
    detected: bool,
    nme68: Option<f64>,
    nme49: Option<f64>,
    confidence: Option<Confidence>,
    accepted: bool,
}

#[derive(Debug, Serialize)]
struct SummaryJson {
    mean: f64,
    auc: f64,
    failure_rate: f64,
}

impl From<ErrorSummary> for SummaryJson {
    fn from(s: ErrorSummary) -> Self {
        Self {
            mean: s.mean,
            auc: s.auc,
            failure_rate: s.failure_rate,
        }
    }
}

#[derive(Debug, Serialize)]
struct AlignerReport {
    aligner: &'static str,
    init: Init,
    images: usize,
    detected: usize,
    /// NME over 68 points (outer-eye-corner normalised); `null` for aligners that only give 51 points.
    nme68: Option<SummaryJson>,
    nme49: SummaryJson,
    ms_per_face: f64,
    /// The same numbers per subset (the name's first folder: `afw`, `helen`, `lfpw`), when there are several.
    subsets: BTreeMap<String, SubsetReport>,
    /// The fifth of the faces turned furthest (yaw estimated from the ground-truth landmarks).
    hardest_fifth: SubsetReport,
    /// The wire encoding DAN's crops went through, and the mean frame-request size it gave.
    crop_encoding: Option<String>,
    mean_request_bytes: Option<f64>,
    /// The blendshape coefficients from the aligner's landmarks against those from the ground truth (both
    /// against the mean face's neutral), per coefficient, over the aligned faces.
    blendshapes_vs_truth: Vec<CoefficientAgreement>,
    per_image: Vec<PerImage>,
}

#[derive(Debug, Serialize)]
struct SubsetReport {
    images: usize,
    nme68: Option<SummaryJson>,
    nme49: SummaryJson,
}

/// The subset of a sample name (`afw/123` -> `afw`); a flat folder's names have none.
fn subset_of(name: &str) -> Option<&str> {
    name.split_once('/').map(|(sub, _)| sub)
}

/// Per-subset summaries of per-image errors (`e68`, `e49` in sample order), when there is more than one subset.
fn by_subset(names: &[&str], e68: &[f64], e49: &[f64], has68: bool) -> BTreeMap<String, SubsetReport> {
    let mut groups: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, n) in names.iter().enumerate() {
        if let Some(sub) = subset_of(n) {
            groups.entry(sub).or_default().push(i);
        }
    }
    if groups.len() < 2 {
        return BTreeMap::new();
    }
    groups
        .into_iter()
        .map(|(sub, idx)| {
            let pick = |e: &[f64]| idx.iter().map(|&i| e[i]).collect::<Vec<_>>();
            let report = SubsetReport {
                images: idx.len(),
                nme68: has68.then(|| summarise(&pick(e68)).into()),
                nme49: summarise(&pick(e49)).into(),
            };
            (sub.to_owned(), report)
        })
        .collect()
}

/// The initial shape of an annotated face: with a detector, the mean shape placed on the detection that
/// matches the annotation (`None` when none does); without, the mean shape fitted to the annotation's box.
pub fn initial_shape(
    detector: Option<&mut BlazeFace>,
    mean: &[Point2; 68],
    image: &holoface_models::GrayView<'_>,
    gt: &[Point2; 68],
) -> anyhow::Result<Option<[Point2; 68]>> {
    let gt_box = Rect::bounding(gt).context("empty annotation")?;
    let mut out = [Point2::default(); 68];
    let Some(det) = detector else {
        fit_to_box(mean, &gt_box, &mut out);
        return Ok(Some(out));
    };
    let found = det.detect(image)?;
    // The detection that matches the annotated face (the images may hold others).
    Ok(found
        .iter()
        .filter(|d| d.bbox.iou(&gt_box) > 0.2)
        .max_by(|a, b| a.bbox.iou(&gt_box).total_cmp(&b.bbox.iou(&gt_box)))
        .and_then(|d| shape_from_detection(mean, d, &mut out).then_some(out)))
}

/// One face to evaluate on: its name (`subset/stem`), ground truth and initial shape (`None`: the detector
/// missed it).
#[derive(Clone, Copy, Debug)]
struct Case<'a> {
    name: &'a str,
    gt: [Point2; 68],
    init: Option<[Point2; 68]>,
}

/// Aligns every case from its initial shape (the aligner's detection path: both initialisations are boxes)
/// and scores it against the ground truth: NME and its summaries over every face, per subset and over the
/// `hardest` faces, and the time per face over `repeat` runs. Computes only: `image(i)` gives case `i`'s
/// image, nothing is printed or written. The report's aligner and init are the caller's to fill.
fn evaluate(
    aligner: &mut dyn Aligner,
    cases: &[Case<'_>],
    image: impl Fn(usize) -> anyhow::Result<holoface_models::image::GrayImage>,
    repeat: usize,
    hardest: &[usize],
) -> anyhow::Result<AlignerReport> {
    let mut per_image = Vec::with_capacity(cases.len());
    let (mut e68, mut e49) = (Vec::new(), Vec::new());
    let mut aligned = 0usize;
    let (mut shapes_ours, mut shapes_truth): (Vec<Blendshapes>, Vec<Blendshapes>) = (Vec::new(), Vec::new());
    let mut align_time = std::time::Duration::ZERO;
    for (i, c) in cases.iter().enumerate() {
        let Some(init) = &c.init else {
            per_image.push(PerImage {
                name: c.name.to_owned(),
                detected: false,
                nme68: None,
                nme49: None,
                confidence: None,
                accepted: false,
            });
            e68.push(f64::INFINITY);
            e49.push(f64::INFINITY);
            continue;
        };
        let image = image(i)?;
        let t0 = Instant::now();
        let a = aligner
            .align_detection(&image.view(), init)
            .with_context(|| format!("aligning {}", c.name))?;
        for _ in 1..repeat {
            std::hint::black_box(aligner.align_detection(&image.view(), init)?);
        }
        align_time += t0.elapsed();
        aligned += 1;
        let n68 = match a.set {
            holoface_runtime::LandmarkSet::Ibug68 => nme68(&a.landmarks, &c.gt),
            holoface_runtime::LandmarkSet::Inner51 => None,
        };
        let n49 = nme49(&a.landmarks, &c.gt);
        // A still has no person to calibrate: both against the mean face (a fresh estimator's first frame).
        let jaw_line = a.set == holoface_runtime::LandmarkSet::Ibug68;
        let fresh = || BlendshapeEstimator::new(Default::default());
        shapes_ours.push(fresh().update(&a.landmarks, jaw_line, None, 0.0));
        shapes_truth.push(fresh().update(&c.gt, jaw_line, None, 0.0));
        e68.push(n68.unwrap_or(f64::INFINITY));
        e49.push(n49.unwrap_or(f64::INFINITY));
        per_image.push(PerImage {
            name: c.name.to_owned(),
            detected: true,
            nme68: n68,
            nme49: n49,
            confidence: Some(a.confidence),
            accepted: a.accepted,
        });
    }
    let has68 = per_image.iter().any(|p| p.nme68.is_some());
    let names: Vec<&str> = cases.iter().map(|c| c.name).collect();
    let pick = |e: &[f64]| hardest.iter().map(|&i| e[i]).collect::<Vec<_>>();
    Ok(AlignerReport {
        aligner: "",
        init: Init::GtBox,
        images: cases.len(),
        detected: aligned,
        nme68: has68.then(|| summarise(&e68).into()),
        nme49: summarise(&e49).into(),
        ms_per_face: align_time.as_secs_f64() * 1e3 / (aligned * repeat.max(1)).max(1) as f64,
        subsets: by_subset(&names, &e68, &e49, has68),
        hardest_fifth: SubsetReport {
            images: hardest.len(),
            nme68: has68.then(|| summarise(&pick(&e68)).into()),
            nme49: summarise(&pick(&e49)).into(),
        },
        crop_encoding: None,
        mean_request_bytes: None,
        blendshapes_vs_truth: agreement(&shapes_ours, &shapes_truth),
        per_image,
    })
}

/// Prints a report's summary lines (all faces, each subset, the hardest fifth).
fn say_report(r: &AlignerReport) {
    let with68 = |s: &Option<SummaryJson>, fail: bool| {
        s.as_ref().map_or_else(String::new, |s| {
            if fail {
                format!(
                    " NME68={:.2}% AUC68={:.2} fail68={:.2}%",
                    100.0 * s.mean,
                    100.0 * s.auc,
                    100.0 * s.failure_rate
                )
            } else {
                format!(" NME68={:.2}%", 100.0 * s.mean)
            }
        })
    };
    crate::say!(
        "{:<6} init={:?} images={} detected={} NME49={:.2}% AUC49={:.2} fail49={:.2}%{}",
        r.aligner,
        r.init,
        r.images,
        r.detected,
        100.0 * r.nme49.mean,
        100.0 * r.nme49.auc,
        100.0 * r.nme49.failure_rate,
        with68(&r.nme68, true)
    );
    for (sub, s) in &r.subsets {
        crate::say!(
            "{:<6}   {sub:<6} images={} NME49={:.2}%{}",
            r.aligner,
            s.images,
            100.0 * s.nme49.mean,
            with68(&s.nme68, false)
        );
    }
    let hard = &r.hardest_fifth;
    crate::say!(
        "{:<6}   hardest fifth (largest yaw) images={} NME49={:.2}% fail49={:.2}%{}",
        r.aligner,
        hard.images,
        100.0 * hard.nme49.mean,
        100.0 * hard.nme49.failure_rate,
        hard.nme68.as_ref().map_or_else(String::new, |s| format!(
            " NME68={:.2}% fail68={:.2}%",
            100.0 * s.mean,
            100.0 * s.failure_rate
        ))
    );
    let rows = &r.blendshapes_vs_truth;
    if !rows.is_empty() {
        let mut rs: Vec<f64> = rows.iter().filter_map(|c| c.correlation).collect();
        rs.sort_by(f64::total_cmp);
        let worst = rows
            .iter()
            .max_by(|a, b| a.mean_abs_diff.total_cmp(&b.mean_abs_diff));
        crate::say!(
            "{:<6}   blendshapes vs ground truth: mean |diff| {:.3}, median r {}{}",
            r.aligner,
            overall_abs_diff(rows),
            rs.get(rs.len() / 2).map_or("-".into(), |v| format!("{v:.2}")),
            worst.map_or_else(String::new, |w| format!(
                "; largest {} {:.3}",
                w.name, w.mean_abs_diff
            ))
        );
    }
}

/// Runs `holoface eval`.
pub fn run(args: Args) -> anyhow::Result<()> {
    let data = faces68_or(args.data.as_deref());
    let split = match args.split {
        SplitArg::All => Split::All,
        SplitArg::Validation => Split::Validation,
    };
    // Images are decoded one at a time and dropped after use: memory does not grow with the folder.
    let samples = list_folder(&data, split, true)?;
    tracing::info!(count = samples.len(), folder = %data.display(), "evaluating");

    // Initial shapes, shared by all aligners.
    let mut inits: Vec<Option<[Point2; 68]>> = Vec::with_capacity(samples.len());
    let mut detector = match args.init {
        Init::Detector => Some(args.runtime.detector()?),
        Init::GtBox => None,
    };
    let mean = dan_mean_shape();
    for s in &samples {
        let gt = s.landmarks.context("annotation missing")?;
        let image = s.image()?;
        let init = initial_shape(detector.as_mut(), &mean, &image.view(), &gt)
            .with_context(|| format!("detecting faces in {}", s.name))?;
        inits.push(init);
    }

    // The hardest fifth: the faces turned furthest (yaw estimated from the ground truth).
    let gts: Vec<[Point2; 68]> = samples
        .iter()
        .map(|s| s.landmarks.context("annotation missing"))
        .collect::<anyhow::Result<_>>()?;
    let gt_refs: Vec<&[Point2]> = gts.iter().map(|g| &g[..]).collect();
    let hardest = largest_yaw(&gt_refs, 0.2);
    let cases: Vec<Case<'_>> = samples
        .iter()
        .zip(&gts)
        .zip(&inits)
        .map(|((s, gt), init)| Case {
            name: &s.name,
            gt: *gt,
            init: *init,
        })
        .collect();
    let mut reports = Vec::new();
    let mut curves = Vec::new();
    for which in &args.aligner {
        let mut dan = None;
        let mut remote = None;
        let mut krfws = None;
        let aligner: &mut dyn Aligner = match which {
            AlignerKind::Dan => {
                let d = dan.insert(args.runtime.dan_aligner()?);
                d.set_wire_codec(args.crop_encoding);
                d
            }
            AlignerKind::Remote => {
                let r = remote.insert(args.runtime.remote_aligner()?);
                if args.crop_encoding.is_some() {
                    r.set_wire_codec(args.crop_encoding);
                }
                r
            }
            AlignerKind::Krfws => {
                let k = krfws.insert(args.runtime.krfws_aligner()?);
                k.set_detection_starts(args.krfws_starts);
                k
            }
        };
        let mut report = evaluate(aligner, &cases, |i| samples[i].image(), args.repeat, &hardest)?;
        report.aligner = which.label();
        report.init = args.init;
        report.crop_encoding = match (&dan, &remote) {
            (Some(_), _) => args.crop_encoding.map(|c| c.to_string()),
            (_, Some(_)) => Some(args.crop_encoding.unwrap_or_default().to_string()),
            _ => None,
        };
        report.mean_request_bytes = dan
            .as_ref()
            .and_then(|d| d.mean_request_bytes())
            .or_else(|| remote.as_ref().and_then(|r| r.mean_request_bytes()));
        say_report(&report);
        curves.push(Curve {
            label: which.label().to_owned(),
            errors: report
                .per_image
                .iter()
                .map(|p| p.nme49.unwrap_or(f64::INFINITY))
                .collect(),
        });
        reports.push(report);
    }
    if reports.is_empty() {
        bail!("no aligner selected");
    }
    for path in [&args.out, &args.plot] {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    let json = serde_json::to_string_pretty(&reports)?;
    crate::cli::write_atomic(&args.out, &json)?;
    let png = ced_plot_png(&curves, 0.08);
    crate::cli::write_atomic(&args.plot, &png)?;
    crate::say!("wrote {} and {}", args.out.display(), args.plot.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use holoface_models::image::{GrayImage, GrayView};
    use holoface_runtime::align::{AlignError, Alignment};
    use holoface_runtime::{AnsweredBy, LandmarkSet};

    /// Answers its initial shape moved `dx` pixels to the right.
    struct Shifted(f32);

    impl Aligner for Shifted {
        fn name(&self) -> &'static str {
            "shifted"
        }
        fn align(&mut self, _: &GrayView<'_>, init: &[Point2; 68]) -> Result<Alignment, AlignError> {
            Ok(Alignment {
                landmarks: init.map(|p| Point2::new(p.x + self.0, p.y)),
                set: LandmarkSet::Ibug68,
                confidence: Confidence::FaceProbability(1.0),
                accepted: true,
                answered_by: AnsweredBy::LocalDan,
                adaptation: None,
            })
        }
    }

    #[test]
    fn evaluate_scores_every_face_without_printing_or_writing() {
        let mut gt = dan_mean_shape();
        for p in &mut gt {
            *p = Point2::new(100.0 + 2.0 * p.x, 100.0 + 2.0 * p.y);
        }
        let cases = [
            Case {
                name: "afw/a",
                gt,
                init: Some(gt),
            },
            Case {
                name: "lfpw/b",
                gt,
                init: Some(gt),
            },
            Case {
                name: "lfpw/c",
                gt,
                init: None,
            },
        ];
        let images = std::cell::Cell::new(0);
        let r = evaluate(
            &mut Shifted(2.0),
            &cases,
            |_| {
                images.set(images.get() + 1);
                Ok(GrayImage::zeros(320, 320))
            },
            1,
            &[1],
        )
        .unwrap();
        assert_eq!(images.get(), 2, "the missed face's image is never read");
        assert_eq!((r.images, r.detected), (3, 2));
        let want = 2.0 / f64::from(gt[36].dist(gt[45]));
        for p in &r.per_image[..2] {
            assert!((p.nme68.unwrap() - want).abs() < 1e-6, "{p:?}");
            assert!((p.nme49.unwrap() - want).abs() < 1e-6, "{p:?}");
        }
        assert!(!r.per_image[2].detected && r.per_image[2].nme49.is_none());
        assert_eq!(r.subsets.len(), 2);
        assert_eq!(r.subsets["lfpw"].images, 2);
        assert_eq!(r.hardest_fifth.images, 1);
        assert!((r.hardest_fifth.nme49.mean - want).abs() < 1e-6);
        // A shifted answer reads the same expression: the coefficients come from the face's own frame.
        assert_eq!(
            r.blendshapes_vs_truth.len(),
            holoface_models::blendshapes::N_BLENDSHAPES
        );
        assert!(
            overall_abs_diff(&r.blendshapes_vs_truth) < 1e-4,
            "{:?}",
            r.blendshapes_vs_truth
        );
        // The same aligner unshifted: no error.
        let exact = evaluate(
            &mut Shifted(0.0),
            &cases[..2],
            |_| Ok(GrayImage::zeros(320, 320)),
            1,
            &[],
        )
        .unwrap();
        assert!(exact.per_image.iter().all(|p| p.nme68 == Some(0.0)));
    }

    #[test]
    fn subsets_split_the_errors_by_folder() {
        let names = ["afw/a", "afw/b", "lfpw/c"];
        let e = [0.02, 0.04, 0.10];
        let r = by_subset(&names, &e, &e, true);
        assert_eq!(r.len(), 2);
        assert_eq!(r["afw"].images, 2);
        assert!((r["afw"].nme49.mean - 0.03).abs() < 1e-12);
        assert!((r["lfpw"].nme68.as_ref().map(|s| s.mean).unwrap_or(0.0) - 0.10).abs() < 1e-12);
        // One folder (or a flat one): nothing to split.
        assert!(by_subset(&["x", "y"], &e[..2], &e[..2], true).is_empty());
        assert!(by_subset(&["afw/x"], &e[..1], &e[..1], false).is_empty());
    }
}
