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

#[cfg(test)]
mod tests {
    use super::*;

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
