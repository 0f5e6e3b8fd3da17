//! How well the blendshape coefficients follow real faces (issue 39): pure measures, no IO.
//!
//! - On annotated still faces ([`agreement`]): the coefficients from an aligner's landmarks against those from
//!   the ground-truth landmarks of the same face (both against the mean face's neutral: a still has no
//!   person to calibrate), per coefficient.
//! - On video ([`video_report`]): `jawOpen` against the inner lips' gap and `eyeBlink*` against the eyes'
//!   closing, both measured from landmarks (a peer's per-frame landmarks where given, so that the measure
//!   does not share our aligner's errors), and the coefficients on the frames where the face is at rest.

use holoface_models::blendshapes::{Blendshape, Blendshapes, N_BLENDSHAPES};
use holoface_models::geometry::Point2;
use holoface_models::shape::OUTER_EYE_CORNERS;
use serde::Serialize;

use crate::track_measures::Landmarks;

/// Pearson's correlation of paired samples; `None` with fewer than 3 pairs or without spread in either.
pub fn pearson(pairs: &[(f64, f64)]) -> Option<f64> {
    let n = pairs.len() as f64;
    if pairs.len() < 3 {
        return None;
    }
    let (ma, mb) = pairs
        .iter()
        .fold((0.0, 0.0), |(a, b), &(x, y)| (a + x / n, b + y / n));
    let (mut sab, mut saa, mut sbb) = (0.0, 0.0, 0.0);
    for &(x, y) in pairs {
        sab += (x - ma) * (y - mb);
        saa += (x - ma) * (x - ma);
        sbb += (y - mb) * (y - mb);
    }
    let r = sab / (saa * sbb).sqrt();
    (saa > 1e-12 && sbb > 1e-12 && r.is_finite()).then_some(r)
}

fn eye_distance(p: &[Point2; 68]) -> Option<f64> {
    let d = f64::from(p[OUTER_EYE_CORNERS.0].dist(p[OUTER_EYE_CORNERS.1]));
    (d.is_finite() && d > 1e-6).then_some(d)
}

fn mean_point(p: &[Point2; 68], idx: &[usize]) -> (f64, f64) {
    let n = idx.len() as f64;
    idx.iter().fold((0.0, 0.0), |(x, y), &i| {
        (x + f64::from(p[i].x) / n, y + f64::from(p[i].y) / n)
    })
}

fn dist(a: (f64, f64), b: (f64, f64)) -> f64 {
    (a.0 - b.0).hypot(a.1 - b.1)
}

/// The gap between the inner lips (iBUG 61-63 against 65-67), in outer-eye-corner distances.
pub fn inner_lip_gap(p: &[Point2; 68]) -> Option<f64> {
    let gap = dist(mean_point(p, &[61, 62, 63]), mean_point(p, &[65, 66, 67]));
    Some(gap / eye_distance(p)?)
}

/// The eyes' mean opening (upper against lower lid, iBUG 37/38 against 41/40 and 43/44 against 47/46), in
/// outer-eye-corner distances.
pub fn eye_opening(p: &[Point2; 68]) -> Option<f64> {
    let right = dist(mean_point(p, &[37, 38]), mean_point(p, &[40, 41]));
    let left = dist(mean_point(p, &[43, 44]), mean_point(p, &[46, 47]));
    Some(0.5 * (right + left) / eye_distance(p)?)
}

/// One coefficient's agreement between two sources over the same faces.
#[derive(Clone, Debug, Serialize)]
pub struct CoefficientAgreement {
    /// ARKit's name.
    pub name: &'static str,
    /// Mean |ours - reference|.
    pub mean_abs_diff: f64,
    /// Pearson's r between ours and the reference; `None` where either does not vary.
    pub correlation: Option<f64>,
    /// Mean of ours and of the reference.
    pub mean_ours: f64,
    /// Mean of the reference.
    pub mean_reference: f64,
}

/// Per coefficient, how `ours` agrees with `reference` (paired by index).
pub fn agreement(ours: &[Blendshapes], reference: &[Blendshapes]) -> Vec<CoefficientAgreement> {
    let n = ours.len().min(reference.len());
    Blendshape::ALL
        .iter()
        .enumerate()
        .map(|(k, b)| {
            let pairs: Vec<(f64, f64)> = (0..n)
                .map(|i| (f64::from(ours[i].0[k]), f64::from(reference[i].0[k])))
                .collect();
            let mean = |f: fn(&(f64, f64)) -> f64| pairs.iter().map(f).sum::<f64>() / n.max(1) as f64;
            CoefficientAgreement {
                name: b.arkit_name(),
                mean_abs_diff: mean(|&(a, b)| (a - b).abs()),
                correlation: pearson(&pairs),
                mean_ours: mean(|&(a, _)| a),
                mean_reference: mean(|&(_, b)| b),
            }
        })
        .collect()
}

/// The mean over every coefficient of the mean absolute difference.
pub fn overall_abs_diff(rows: &[CoefficientAgreement]) -> f64 {
    rows.iter().map(|r| r.mean_abs_diff).sum::<f64>() / rows.len().max(1) as f64
}

/// The frames a face counts as at rest: lips closed (gap under `closed_gap` eye distances) and eyes open
/// (at least `open_fraction` of the clip's median opening).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct RestRule {
    /// Largest inner-lip gap of closed lips, eye distances.
    pub closed_gap: f64,
    /// Smallest opening of open eyes, a fraction of the median.
    pub open_fraction: f64,
}

impl Default for RestRule {
    fn default() -> Self {
        Self {
            closed_gap: 0.02,
            open_fraction: 0.85,
        }
    }
}

/// One aligner's coefficients on a clip, against landmark measures.
#[derive(Clone, Debug, Serialize)]
pub struct VideoReport {
    /// Frames with both coefficients and a measure.
    pub frames: usize,
    /// Pearson's r of `jawOpen` with the inner lips' gap.
    pub jaw_open_vs_lip_gap: Option<f64>,
    /// Pearson's r of the mean of `eyeBlinkLeft` and `eyeBlinkRight` with the eyes' closing
    /// (1 - opening / the clip's median opening).
    pub blink_vs_eye_closing: Option<f64>,
    /// Frames at rest (after calibration).
    pub rest_frames: usize,
    /// Per coefficient, its mean over the frames at rest.
    pub rest_mean: Vec<(&'static str, f64)>,
    /// The largest of those means and its coefficient.
    pub rest_max: Option<(&'static str, f64)>,
    /// Per coefficient, the 95th percentile over the frames at rest.
    pub rest_p95_max: Option<(&'static str, f64)>,
}

/// The coefficients of one aligner over a clip (`ours[t]`, `None` without a face) against the landmark
/// measures of `measured` (the same frames: a peer's or ours). Frames before `skip` (the calibration) are
/// left out.
pub fn video_report(
    ours: &[Option<Blendshapes>],
    measured: &[Landmarks],
    skip: usize,
    rest: RestRule,
) -> VideoReport {
    let n = ours.len().min(measured.len());
    let rows: Vec<(Blendshapes, f64, f64)> = (skip.min(n)..n)
        .filter_map(|t| {
            let (b, lm) = (ours[t]?, measured[t].as_ref()?);
            Some((b, inner_lip_gap(lm)?, eye_opening(lm)?))
        })
        .collect();
    let mut openings: Vec<f64> = rows.iter().map(|r| r.2).collect();
    openings.sort_by(f64::total_cmp);
    let median_opening = openings.get(openings.len() / 2).copied().unwrap_or(f64::NAN);
    let jaw = Blendshape::ALL.iter().position(|&b| b == Blendshape::JawOpen);
    let blink = |b: &Blendshapes| {
        0.5 * (f64::from(b.get(Blendshape::EyeBlinkLeft)) + f64::from(b.get(Blendshape::EyeBlinkRight)))
    };
    let jaw_pairs: Vec<(f64, f64)> = rows
        .iter()
        .filter_map(|(b, gap, _)| Some((f64::from(b.0[jaw?]), *gap)))
        .collect();
    let blink_pairs: Vec<(f64, f64)> = rows
        .iter()
        .map(|(b, _, open)| (blink(b), 1.0 - open / median_opening))
        .collect();
    let at_rest: Vec<&Blendshapes> = rows
        .iter()
        .filter(|(_, gap, open)| *gap <= rest.closed_gap && *open >= rest.open_fraction * median_opening)
        .map(|(b, _, _)| b)
        .collect();
    let per_coefficient = |k: usize| -> Vec<f64> {
        let mut v: Vec<f64> = at_rest.iter().map(|b| f64::from(b.0[k])).collect();
        v.sort_by(f64::total_cmp);
        v
    };
    let rest_mean: Vec<(&'static str, f64)> = (0..N_BLENDSHAPES)
        .map(|k| {
            let v = per_coefficient(k);
            (
                Blendshape::ALL[k].arkit_name(),
                v.iter().sum::<f64>() / v.len().max(1) as f64,
            )
        })
        .collect();
    let largest = |v: Vec<(&'static str, f64)>| v.into_iter().max_by(|a, b| a.1.total_cmp(&b.1));
    let rest_p95: Vec<(&'static str, f64)> = (0..N_BLENDSHAPES)
        .filter_map(|k| {
            let v = per_coefficient(k);
            (!v.is_empty()).then(|| {
                (
                    Blendshape::ALL[k].arkit_name(),
                    crate::stats::percentile(&v, 0.95),
                )
            })
        })
        .collect();
    VideoReport {
        frames: rows.len(),
        jaw_open_vs_lip_gap: pearson(&jaw_pairs),
        blink_vs_eye_closing: pearson(&blink_pairs),
        rest_frames: at_rest.len(),
        rest_max: if at_rest.is_empty() {
            None
        } else {
            largest(rest_mean.clone())
        },
        rest_mean,
        rest_p95_max: largest(rest_p95),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pearson_is_one_for_a_line_and_none_without_spread() {
        let line: Vec<(f64, f64)> = (0..10)
            .map(|i| (f64::from(i), 3.0 * f64::from(i) - 2.0))
            .collect();
        assert!((pearson(&line).unwrap() - 1.0).abs() < 1e-12);
        let flipped: Vec<(f64, f64)> = line.iter().map(|&(a, b)| (a, -b)).collect();
        assert!((pearson(&flipped).unwrap() + 1.0).abs() < 1e-12);
        let flat: Vec<(f64, f64)> = (0..10).map(|i| (f64::from(i), 1.0)).collect();
        assert_eq!(pearson(&flat), None);
        assert_eq!(pearson(&line[..2]), None);
    }

    fn face(gap: f32, lid: f32) -> [Point2; 68] {
        let mut p = holoface_models::shape::dan_mean_shape();
        // Close the inner lips, then open them by `gap` and the eyes by `lid` (pixels), around their centres.
        for (up, low) in [(61, 67), (62, 66), (63, 65)] {
            let mid = 0.5 * (p[up].y + p[low].y);
            p[up].y = mid;
            p[low].y = mid;
        }
        for i in [61, 62, 63] {
            p[i].y -= gap / 2.0;
        }
        for i in [65, 66, 67] {
            p[i].y += gap / 2.0;
        }
        for i in [37, 38, 43, 44] {
            p[i].y -= lid / 2.0;
        }
        for i in [40, 41, 46, 47] {
            p[i].y += lid / 2.0;
        }
        p
    }

    #[test]
    fn the_measures_follow_the_landmarks_and_the_report_correlates_them() {
        let base = holoface_models::shape::dan_mean_shape();
        let eye = f64::from(base[36].dist(base[45]));
        let g0 = inner_lip_gap(&face(0.0, 0.0)).unwrap();
        let g1 = inner_lip_gap(&face(0.1 * eye as f32, 0.0)).unwrap();
        assert!(g0 < 1e-6 && (g1 - 0.1).abs() < 1e-3, "{g0} -> {g1}");
        let o0 = eye_opening(&base).unwrap();
        let o1 = eye_opening(&face(0.0, -0.02 * eye as f32)).unwrap();
        assert!(o1 < o0, "{o0} -> {o1}");

        // A clip whose mouth opens and eyes blink in turn; the estimator reads them.
        let mut est = holoface_models::blendshapes::BlendshapeEstimator::new(Default::default());
        let (mut ours, mut lms) = (Vec::new(), Vec::new());
        for t in 0..120 {
            let open = if t >= 40 {
                ((t as f32) * 0.3).sin().max(0.0) * 0.15 * eye as f32
            } else {
                0.0
            };
            let blink = if t >= 40 && t % 17 == 0 {
                -0.05 * eye as f32
            } else {
                0.0
            };
            let lm = face(open, blink);
            ours.push(Some(est.update(&lm, true, None, 1.0 / 30.0)));
            lms.push(Some(lm));
        }
        let r = video_report(&ours, &lms, 30, RestRule::default());
        assert_eq!(r.frames, 90);
        assert!(r.jaw_open_vs_lip_gap.unwrap() > 0.95, "{r:?}");
        assert!(r.blink_vs_eye_closing.unwrap() > 0.9, "{r:?}");
        assert!(r.rest_frames >= 10, "{r:?}");
        // At rest the lids read their soft knee's foot (0.075), everything else about 0.
        assert!(r.rest_max.unwrap().1 < 0.08, "{r:?}");
        let others = r.rest_mean.iter().filter(|(name, _)| !name.starts_with("eye"));
        assert!(others.clone().all(|(_, v)| *v < 0.05), "{r:?}");
        // Paired with nothing, nothing is reported.
        let empty = video_report(&ours, &vec![None; lms.len()], 30, RestRule::default());
        assert_eq!((empty.frames, empty.rest_max), (0, None));
        assert_eq!(empty.jaw_open_vs_lip_gap, None);
    }

    #[test]
    fn agreement_is_zero_difference_for_identical_sources() {
        let mut est = holoface_models::blendshapes::BlendshapeEstimator::new(Default::default());
        let base = holoface_models::shape::dan_mean_shape();
        let eye = f64::from(base[36].dist(base[45])) as f32;
        let ours: Vec<Blendshapes> = (0..20)
            .map(|i| est.update(&face(0.01 * eye * i as f32, 0.0), true, None, 1.0 / 30.0))
            .collect();
        let rows = agreement(&ours, &ours);
        assert_eq!(rows.len(), N_BLENDSHAPES);
        assert_eq!(overall_abs_diff(&rows), 0.0);
        let jaw = rows.iter().find(|r| r.name == "jawOpen").unwrap();
        assert!(
            (jaw.correlation.unwrap() - 1.0).abs() < 1e-9 && jaw.mean_ours > 0.0,
            "{jaw:?}"
        );
        let shifted: Vec<Blendshapes> = ours
            .iter()
            .map(|b| {
                let mut b = *b;
                b.0.iter_mut().for_each(|v| *v = (*v + 0.1).min(1.0));
                b
            })
            .collect();
        assert!((overall_abs_diff(&agreement(&shifted, &ours)) - 0.1).abs() < 0.01);
    }
}
