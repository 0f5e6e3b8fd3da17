//! 68-point face shapes: iBUG index sets, mirroring, the Procrustes mean shape and the canonical DAN
//! crop frame.

use thiserror::Error;

use crate::geometry::{Point2, Rect, Similarity2, centroid};

/// Number of iBUG landmarks.
pub const N68: usize = 68;
/// The 51 inner landmarks (iBUG 17..=67) that KRFWS tracks.
pub const INNER51: std::ops::Range<usize> = 17..68;
/// Outer eye corners (0-based), the 300-W inter-ocular normalisation.
pub const OUTER_EYE_CORNERS: (usize, usize) = (36, 45);

/// The 49-point 300-VW protocol: 68 points minus the jaw (0..=16) and the inner-mouth corners 60 and 64
/// (61 and 65 when counted from 1).
pub const PROTOCOL49: [usize; 49] = [
    17, 18, 19, 20, 21, 22, 23, 24, 25, 26, 27, 28, 29, 30, 31, 32, 33, 34, 35, 36, 37, 38, 39, 40, 41, 42,
    43, 44, 45, 46, 47, 48, 49, 50, 51, 52, 53, 54, 55, 56, 57, 58, 59, 61, 62, 63, 65, 66, 67,
];

/// iBUG 68-point left/right swap used when mirroring an image horizontally.
pub const MIRROR68: [usize; 68] = [
    16, 15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0, // jaw
    26, 25, 24, 23, 22, 21, 20, 19, 18, 17, // brows
    27, 28, 29, 30, 35, 34, 33, 32, 31, // nose
    45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40, // eyes
    54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55, // outer mouth
    64, 63, 62, 61, 60, 67, 66, 65, // inner mouth
];

/// The committed DAN canonical mean shape (crop pixels), produced by `models/dan/train.py`.
const MEAN_SHAPE_68_TXT: &str = include_str!("../assets/mean_shape_68.txt");

/// Errors parsing point lists.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum ShapeError {
    /// A line is not two finite numbers.
    #[error("line {line}: expected `x y`, found {text:?}")]
    BadLine {
        /// 1-based line number.
        line: usize,
        /// The offending text (truncated to 60 characters).
        text: String,
    },
    /// Wrong number of points.
    #[error("expected {expected} points, found {actual}")]
    WrongCount {
        /// Expected count.
        expected: usize,
        /// Count found.
        actual: usize,
    },
}

/// Parses `x y` lines (blank lines and `#` comments skipped; the iBUG `.pts` header and braces also).
pub fn parse_points(text: &str) -> Result<Vec<Point2>, ShapeError> {
    let mut out = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        if line.is_empty()
            || line.starts_with('#')
            || line.starts_with("version")
            || line.starts_with("n_points")
            || line == "{"
            || line == "}"
        {
            continue;
        }
        let mut it = line.split_whitespace();
        let parse = |s: Option<&str>| s.and_then(|v| v.parse::<f32>().ok()).filter(|v| v.is_finite());
        match (parse(it.next()), parse(it.next()), it.next()) {
            (Some(x), Some(y), None) => out.push(Point2::new(x, y)),
            _ => {
                return Err(ShapeError::BadLine {
                    line: i + 1,
                    text: line.chars().take(60).collect(),
                });
            }
        }
    }
    Ok(out)
}

/// Parses exactly 68 points.
pub fn parse_pts68(text: &str) -> Result<[Point2; 68], ShapeError> {
    let v = parse_points(text)?;
    v.as_slice().try_into().map_err(|_| ShapeError::WrongCount {
        expected: N68,
        actual: v.len(),
    })
}

/// DAN's canonical 68-point mean shape in 112×112 crop pixels (the shape every crop is warped onto).
pub fn dan_mean_shape() -> [Point2; 68] {
    // The asset is checked by `committed_mean_shape_parses`; a broken build-time asset falls back to zeros
    // only in a build that fails its own tests.
    parse_pts68(MEAN_SHAPE_68_TXT).unwrap_or([Point2::default(); 68])
}

/// Mirrors a 68-point shape for an image of `width` pixels flipped horizontally.
pub fn mirror68(pts: &[Point2; 68], width: usize) -> [Point2; 68] {
    let w = width as f32 - 1.0;
    std::array::from_fn(|i| {
        let p = pts[MIRROR68[i]];
        Point2::new(w - p.x, p.y)
    })
}

fn normalise(shape: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let n = shape.len() as f64;
    let (mx, my) = shape.iter().fold((0.0, 0.0), |(x, y), p| (x + p[0], y + p[1]));
    let (mx, my) = (mx / n, my / n);
    let norm = shape
        .iter()
        .map(|p| (p[0] - mx).powi(2) + (p[1] - my).powi(2))
        .sum::<f64>()
        .sqrt();
    shape
        .iter()
        .map(|p| [(p[0] - mx) / norm, (p[1] - my) / norm])
        .collect()
}

fn upright(shape: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let mean = |r: std::ops::Range<usize>| {
        let k = r.len() as f64;
        let s = shape[r].iter().fold((0.0, 0.0), |(x, y), p| (x + p[0], y + p[1]));
        (s.0 / k, s.1 / k)
    };
    let (el, er) = (mean(36..42), mean(42..48));
    let ang = (er.1 - el.1).atan2(er.0 - el.0);
    let (c, s) = ((-ang).cos(), (-ang).sin());
    let n = shape.len() as f64;
    let (mx, my) = shape.iter().fold((0.0, 0.0), |(x, y), p| (x + p[0], y + p[1]));
    let (mx, my) = (mx / n, my / n);
    shape
        .iter()
        .map(|p| {
            let (x, y) = (p[0] - mx, p[1] - my);
            [c * x - s * y + mx, s * x + c * y + my]
        })
        .collect()
}

fn fit64(src: &[[f64; 2]], dst: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let n = src.len() as f64;
    let (msx, msy) = src.iter().fold((0.0, 0.0), |(x, y), p| (x + p[0], y + p[1]));
    let (mdx, mdy) = dst.iter().fold((0.0, 0.0), |(x, y), p| (x + p[0], y + p[1]));
    let (msx, msy, mdx, mdy) = (msx / n, msy / n, mdx / n, mdy / n);
    let (mut ss, mut sd, mut cr) = (0.0, 0.0, 0.0);
    for (s, d) in src.iter().zip(dst) {
        let (sx, sy, dx, dy) = (s[0] - msx, s[1] - msy, d[0] - mdx, d[1] - mdy);
        ss += sx * sx + sy * sy;
        sd += sx * dx + sy * dy;
        cr += sx * dy - sy * dx;
    }
    let (a, b) = (sd / ss, cr / ss);
    let (tx, ty) = (mdx - (a * msx - b * msy), mdy - (b * msx + a * msy));
    src.iter()
        .map(|p| [a * p[0] - b * p[1] + tx, b * p[0] + a * p[1] + ty])
        .collect()
}

/// Generalised Procrustes mean of `shapes` and of their mirror images: centred, unit norm, eye centres
/// level. Same algorithm as `models/dan/geometry.py::procrustes_mean`. Returns `None` for no shapes.
pub fn procrustes_mean(shapes: &[[Point2; 68]]) -> Option<[Point2; 68]> {
    if shapes.is_empty() {
        return None;
    }
    let to64 = |s: &[Point2; 68]| {
        s.iter()
            .map(|p| [f64::from(p.x), f64::from(p.y)])
            .collect::<Vec<_>>()
    };
    let mut pool = Vec::with_capacity(shapes.len() * 2);
    for s in shapes {
        let v = to64(s);
        let m: Vec<[f64; 2]> = MIRROR68.iter().map(|&j| [-v[j][0], v[j][1]]).collect();
        pool.push(v);
        pool.push(m);
    }
    let mut reference = upright(&normalise(&pool[0]));
    for _ in 0..20 {
        let mut acc = vec![[0.0f64; 2]; 68];
        for s in &pool {
            for (a, p) in acc.iter_mut().zip(fit64(s, &reference)) {
                a[0] += p[0];
                a[1] += p[1];
            }
        }
        let k = pool.len() as f64;
        let mean: Vec<[f64; 2]> = acc.iter().map(|a| [a[0] / k, a[1] / k]).collect();
        let new = upright(&normalise(&mean));
        let delta = new
            .iter()
            .zip(&reference)
            .map(|(a, b)| (a[0] - b[0]).abs().max((a[1] - b[1]).abs()))
            .fold(0.0, f64::max);
        reference = new;
        if delta < 1e-12 {
            break;
        }
    }
    Some(std::array::from_fn(|i| {
        Point2::new(reference[i][0] as f32, reference[i][1] as f32)
    }))
}

/// Scales and centres a mean shape into the 112×112 crop (DAN's rule: larger extent 56 px, i.e. 25 %
/// margin, mean of the points at (56, 56)).
pub fn canonical_from_mean(mean: &[Point2]) -> Vec<Point2> {
    let Some(r) = Rect::bounding(mean) else {
        return Vec::new();
    };
    let ext = r.width().max(r.height());
    let scale = 56.0 / ext;
    let scaled: Vec<Point2> = mean
        .iter()
        .map(|p| Point2::new(p.x * scale, p.y * scale))
        .collect();
    let c = centroid(&scaled);
    scaled
        .iter()
        .map(|p| Point2::new(p.x - c.x + 56.0, p.y - c.y + 56.0))
        .collect()
}

/// DAN's `bestFitRect`: places `shape` in `bbox` with no rotation; scale is the mean of the width and height
/// ratios, the shape's extent centre goes on the box centre. Writes into `out` (same length as `shape`).
pub fn fit_to_box(shape: &[Point2], bbox: &Rect, out: &mut [Point2]) {
    let Some(r) = Rect::bounding(shape) else { return };
    let s = 0.5 * (bbox.width() / r.width() + bbox.height() / r.height());
    let (c, bc) = (r.centre(), bbox.centre());
    for (o, p) in out.iter_mut().zip(shape) {
        *o = Point2::new((p.x - c.x) * s + bc.x, (p.y - c.y) * s + bc.y);
    }
}

/// The similarity that places `shape` onto `target` in the least-squares sense, applied to `shape`
/// (the "mean shape similarity-fitted to the previous landmarks" initialisation).
pub fn similarity_fit_onto(shape: &[Point2], target: &[Point2], out: &mut [Point2]) -> Option<Similarity2> {
    let s = Similarity2::fit(shape, target)?;
    s.apply_all(shape, out);
    Some(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn committed_mean_shape_parses_and_is_canonical() {
        let m = parse_pts68(MEAN_SHAPE_68_TXT).unwrap();
        let r = Rect::bounding(&m).unwrap();
        assert!((r.width().max(r.height()) - 56.0).abs() < 1e-3);
        let c = centroid(&m);
        assert!((c.x - 56.0).abs() < 1e-3 && (c.y - 56.0).abs() < 1e-3);
        // Left eye on the left, mouth below the nose.
        assert!(m[36].x < m[45].x && m[57].y > m[30].y);
        // Symmetric: the mirror of the mean is the mean.
        let mirrored = mirror68(&m, 112);
        for (a, b) in m.iter().zip(&mirrored) {
            assert!(a.dist(Point2::new(b.x + 1.0, b.y)) < 1e-3, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn mirror_is_an_involution_and_protocol49_is_sound() {
        for (i, &j) in MIRROR68.iter().enumerate() {
            assert_eq!(MIRROR68[j], i);
        }
        assert!(PROTOCOL49.windows(2).all(|w| w[0] < w[1]));
        assert!(!PROTOCOL49.contains(&60) && !PROTOCOL49.contains(&64) && !PROTOCOL49.contains(&16));
    }

    #[test]
    fn parse_rejects_garbage() {
        assert!(matches!(
            parse_points("1 2\nx 3\n"),
            Err(ShapeError::BadLine { line: 2, .. })
        ));
        assert!(matches!(parse_points("1 2 3\n"), Err(ShapeError::BadLine { .. })));
        assert!(matches!(parse_points("1 NaN\n"), Err(ShapeError::BadLine { .. })));
        assert!(matches!(
            parse_pts68("1 2\n"),
            Err(ShapeError::WrongCount {
                expected: 68,
                actual: 1
            })
        ));
        let ibug = "version: 1\nn_points: 1\n{\n3 4\n}\n";
        assert_eq!(parse_points(ibug).unwrap(), vec![Point2::new(3.0, 4.0)]);
    }

    #[test]
    fn procrustes_of_rotated_copies_is_the_shape() {
        let base = dan_mean_shape();
        let copies: Vec<[Point2; 68]> = (0..5)
            .map(|k| {
                let s = Similarity2::from_parts(1.0 + k as f64 * 0.3, 0.1 * k as f64, 5.0 * k as f64, -3.0);
                std::array::from_fn(|i| s.apply(base[i]))
            })
            .collect();
        let mean = canonical_from_mean(&procrustes_mean(&copies).unwrap());
        for (a, b) in mean.iter().zip(&base) {
            assert!(a.dist(*b) < 1e-2, "{a:?} vs {b:?}");
        }
    }
}
