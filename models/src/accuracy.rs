//! Landmark error metrics: normalised mean error, CED, AUC and failure rate (algorithms.md 1.6, 4.1).

use crate::geometry::Point2;
use crate::shape::{OUTER_EYE_CORNERS, PROTOCOL49};

/// Failure threshold and AUC integration limit of the 300-W / 300-VW protocols.
pub const FAILURE_THRESHOLD: f64 = 0.08;

/// Mean point-to-point error over `indices`, divided by the ground truth's outer-eye-corner distance.
///
/// Returns `None` when the shapes are shorter than 68 points or the normaliser is zero.
pub fn nme_outer_corners(pred: &[Point2], gt: &[Point2], indices: &[usize]) -> Option<f64> {
    let (l, r) = OUTER_EYE_CORNERS;
    let norm = f64::from(gt.get(l)?.dist(*gt.get(r)?));
    if norm <= 0.0 || indices.is_empty() {
        return None;
    }
    let mut sum = 0.0;
    for &i in indices {
        sum += f64::from(pred.get(i)?.dist(*gt.get(i)?));
    }
    Some(sum / indices.len() as f64 / norm)
}

/// NME over all 68 points, outer-corner normalised.
pub fn nme68(pred: &[Point2], gt: &[Point2]) -> Option<f64> {
    let all: [usize; 68] = std::array::from_fn(|i| i);
    nme_outer_corners(pred, gt, &all)
}

/// NME over the 49-point protocol, outer-corner normalised.
pub fn nme49(pred: &[Point2], gt: &[Point2]) -> Option<f64> {
    nme_outer_corners(pred, gt, &PROTOCOL49)
}

/// How far a face is turned left or right, from its landmarks: `|l − r| / (l + r)` with `l` and `r` the
/// distances from the nose tip (30) to the two ends of the jaw line (0 and 16). 0 for a frontal face,
/// towards 1 as the head turns (the nearer jaw end moves behind the nose). A ranking key for "largest head
/// yaw" (the hardest faces of a set), not an angle; `None` for a degenerate shape.
pub fn yaw_proxy(shape: &[Point2]) -> Option<f64> {
    let nose = *shape.get(30)?;
    let l = f64::from(nose.dist(*shape.first()?));
    let r = f64::from(nose.dist(*shape.get(16)?));
    (l + r > 0.0).then(|| (l - r).abs() / (l + r))
}

/// The indices of the `fraction` of `shapes` with the largest [`yaw_proxy`] (at least one when any).
pub fn largest_yaw(shapes: &[&[Point2]], fraction: f64) -> Vec<usize> {
    let mut keyed: Vec<(usize, f64)> = shapes
        .iter()
        .enumerate()
        .map(|(i, s)| (i, yaw_proxy(s).unwrap_or(0.0)))
        .collect();
    keyed.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
    let n = ((shapes.len() as f64 * fraction).round() as usize)
        .clamp(usize::from(!shapes.is_empty()), shapes.len());
    let mut out: Vec<usize> = keyed[..n].iter().map(|k| k.0).collect();
    out.sort_unstable();
    out
}

/// Summary of a set of per-sample errors. A sample without an answer (no detection, "no face") counts
/// as an infinite error: a failure, and outside every CED bin.
#[derive(Clone, Debug, PartialEq)]
pub struct ErrorSummary {
    /// Number of samples.
    pub count: usize,
    /// Mean error over the samples that have one (finite).
    pub mean: f64,
    /// Area under the CED up to [`FAILURE_THRESHOLD`], divided by it (0..1).
    pub auc: f64,
    /// Share of samples with error above the threshold or without an answer (0..1).
    pub failure_rate: f64,
}

/// CED value at `x`: share of samples with error ≤ x.
pub fn ced_at(sorted: &[f64], total: usize, x: f64) -> f64 {
    if total == 0 {
        return 0.0;
    }
    sorted.partition_point(|&e| e <= x) as f64 / total as f64
}

/// Summarises errors (`f64::INFINITY` or NaN for samples without an answer).
pub fn summarise(errors: &[f64]) -> ErrorSummary {
    let mut sorted: Vec<f64> = errors.iter().copied().filter(|e| e.is_finite()).collect();
    sorted.sort_by(f64::total_cmp);
    let total = errors.len();
    let mean = if sorted.is_empty() {
        f64::NAN
    } else {
        sorted.iter().sum::<f64>() / sorted.len() as f64
    };
    // Trapezoid integration of the CED step function on a 1e-4 grid (DAN's tests.AUCError uses Simpson on
    // the same grid; the difference is below 1e-4).
    let steps = 800;
    let dx = FAILURE_THRESHOLD / steps as f64;
    let mut area = 0.0;
    let mut prev = ced_at(&sorted, total, 0.0);
    for k in 1..=steps {
        let cur = ced_at(&sorted, total, k as f64 * dx);
        area += 0.5 * (prev + cur) * dx;
        prev = cur;
    }
    ErrorSummary {
        count: total,
        mean,
        auc: area / FAILURE_THRESHOLD,
        failure_rate: 1.0 - ced_at(&sorted, total, FAILURE_THRESHOLD),
    }
}

/// ROC AUC of `scores` for the positive `labels` (higher score = more positive), ties counted half.
/// `None` when one class is empty.
pub fn roc_auc(scores: &[f32], labels: &[bool]) -> Option<f64> {
    let mut v: Vec<(f32, bool)> = scores.iter().copied().zip(labels.iter().copied()).collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let pos = v.iter().filter(|x| x.1).count();
    let neg = v.len() - pos;
    if pos == 0 || neg == 0 {
        return None;
    }
    let mut rank_sum = 0.0f64;
    let mut i = 0;
    while i < v.len() {
        let mut j = i;
        while j < v.len() && v[j].0 == v[i].0 {
            j += 1;
        }
        let avg = (i + j + 1) as f64 / 2.0;
        rank_sum += avg * v[i..j].iter().filter(|x| x.1).count() as f64;
        i = j;
    }
    Some((rank_sum - (pos * (pos + 1)) as f64 / 2.0) / (pos as f64 * neg as f64))
}

/// Threshold maximising Youden's J (TPR − FPR) for "score ≥ threshold ⇒ failure" on labelled scores;
/// returns `(threshold, tpr, fpr)`.
pub fn youden_threshold(scores: &[f32], labels: &[bool]) -> Option<(f32, f64, f64)> {
    let mut v: Vec<(f32, bool)> = scores.iter().copied().zip(labels.iter().copied()).collect();
    v.sort_by(|a, b| b.0.total_cmp(&a.0));
    let pos = v.iter().filter(|x| x.1).count() as f64;
    let neg = v.len() as f64 - pos;
    if pos == 0.0 || neg == 0.0 {
        return None;
    }
    let (mut tp, mut fp) = (0.0, 0.0);
    let mut best = (f64::NEG_INFINITY, f32::INFINITY, 0.0, 0.0);
    for k in 0..v.len() {
        if v[k].1 {
            tp += 1.0;
        } else {
            fp += 1.0;
        }
        if k + 1 < v.len() && v[k + 1].0 == v[k].0 {
            continue;
        }
        let j = tp / pos - fp / neg;
        if j > best.0 {
            let thr = match v.get(k + 1) {
                Some(next) => 0.5 * (v[k].0 + next.0),
                None => v[k].0,
            };
            best = (j, thr, tp / pos, fp / neg);
        }
    }
    Some((best.1, best.2, best.3))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn yaw_proxy_ranks_turned_faces_first() {
        let frontal: Vec<Point2> = (0..68)
            .map(|i| match i {
                0 => Point2::new(0.0, 0.0),
                16 => Point2::new(100.0, 0.0),
                30 => Point2::new(50.0, 40.0),
                _ => Point2::new(50.0, 50.0),
            })
            .collect();
        let mut turned = frontal.clone();
        turned[30] = Point2::new(80.0, 40.0);
        let mut slightly = frontal.clone();
        slightly[30] = Point2::new(60.0, 40.0);
        assert!(yaw_proxy(&frontal).unwrap() < 1e-9);
        assert!(yaw_proxy(&turned).unwrap() > yaw_proxy(&slightly).unwrap());
        let set: Vec<&[Point2]> = vec![&frontal, &turned, &slightly, &frontal, &frontal];
        assert_eq!(largest_yaw(&set, 0.2), vec![1]);
        assert_eq!(largest_yaw(&set, 0.4), vec![1, 2]);
        assert!(largest_yaw(&[], 0.2).is_empty());
        assert_eq!(yaw_proxy(&frontal[..10]), None);
    }

    #[test]
    fn nme_is_normalised_by_outer_corners() {
        let mut gt = [Point2::default(); 68];
        gt[45] = Point2::new(100.0, 0.0);
        let pred: Vec<Point2> = gt.iter().map(|p| Point2::new(p.x + 3.0, p.y + 4.0)).collect();
        assert!((nme68(&pred, &gt).unwrap() - 0.05).abs() < 1e-9);
        assert!((nme49(&pred, &gt).unwrap() - 0.05).abs() < 1e-9);
        assert!(nme68(&pred[..10], &gt).is_none());
        assert!(nme68(&pred, &[Point2::default(); 68]).is_none());
    }

    #[test]
    fn summary_counts_missing_answers_as_failures() {
        let s = summarise(&[0.0, 0.0, 0.1, f64::INFINITY]);
        assert_eq!(s.count, 4);
        assert!((s.failure_rate - 0.5).abs() < 1e-12);
        // Half the samples are at zero error for the whole range: AUC = 0.5.
        assert!((s.auc - 0.5).abs() < 1e-3, "{}", s.auc);
        let perfect = summarise(&[0.04; 10]);
        assert!((perfect.auc - 0.5).abs() < 2e-3 && perfect.failure_rate == 0.0);
    }
}
