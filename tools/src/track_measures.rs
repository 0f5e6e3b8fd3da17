//! Landmark stability on unannotated video (`holoface stability`): pure measures over per-frame landmark
//! tracks, no IO.
//!
//! `jitter49` at frame t is the mean over the 49 inner points (the 300-W protocol's) of
//! `|p(t) - (p(t-1) + p(t+1)) / 2|`, divided by the outer-eye-corner distance at t: a second difference, so
//! smooth head motion at video rates contributes almost nothing and the aligner's frame-to-frame noise
//! shows. A switch between aligners (remote and local) at t is measured by the jump
//! `|p(t) - 2 p(t-1) + p(t-2)|` (the change of velocity across the switch), also per point, in eye distances.

use holoface_models::geometry::Point2;
use holoface_models::shape::{OUTER_EYE_CORNERS, PROTOCOL49};

/// One frame's landmarks, or none.
pub type Landmarks = Option<[Point2; 68]>;

fn eye_distance(p: &[Point2; 68]) -> Option<f64> {
    let d = f64::from(p[OUTER_EYE_CORNERS.0].dist(p[OUTER_EYE_CORNERS.1]));
    (d.is_finite() && d > 1e-6).then_some(d)
}

/// Mean over the 49 points of `|a + c - 2 b| * k`, in eye distances of `eye`.
fn second_difference(a: &[Point2; 68], b: &[Point2; 68], c: &[Point2; 68], k: f64, eye: f64) -> f64 {
    PROTOCOL49
        .iter()
        .map(|&i| {
            let dx = f64::from(a[i].x) + f64::from(c[i].x) - 2.0 * f64::from(b[i].x);
            let dy = f64::from(a[i].y) + f64::from(c[i].y) - 2.0 * f64::from(b[i].y);
            dx.hypot(dy) * k / eye
        })
        .sum::<f64>()
        / PROTOCOL49.len() as f64
}

/// `jitter49` per frame: `Some` where the frame and both its neighbours have landmarks.
pub fn jitter49(frames: &[Landmarks]) -> Vec<Option<f64>> {
    jitter_of(frames, |prev, now, next| {
        Some(second_difference(prev, now, next, 0.5, eye_distance(now)?))
    })
}

/// `jitter49` in pixels (not divided by the eye distance), to set beside [`point_jitter_px`].
pub fn jitter49_px(frames: &[Landmarks]) -> Vec<Option<f64>> {
    jitter_of(frames, |prev, now, next| {
        Some(second_difference(prev, now, next, 0.5, 1.0))
    })
}

/// The same second difference for one point per frame (an anchored object's projection), pixels:
/// `|p(t) - (p(t-1) + p(t+1)) / 2|`.
pub fn point_jitter_px(track: &[Option<Point2>]) -> Vec<Option<f64>> {
    jitter_of(track, |a, b, c| {
        let dx = f64::from(a.x) + f64::from(c.x) - 2.0 * f64::from(b.x);
        let dy = f64::from(a.y) + f64::from(c.y) - 2.0 * f64::from(b.y);
        Some(dx.hypot(dy) * 0.5)
    })
}

/// `f(previous, now, next)` per frame where the frame and both its neighbours have a value.
fn jitter_of<T>(frames: &[Option<T>], f: impl Fn(&T, &T, &T) -> Option<f64>) -> Vec<Option<f64>> {
    (0..frames.len())
        .map(|t| {
            let (Some(prev), Some(now), Some(next)) = (
                t.checked_sub(1).and_then(|p| frames[p].as_ref()),
                frames[t].as_ref(),
                frames.get(t + 1).and_then(Option::as_ref),
            ) else {
                return None;
            };
            f(prev, now, next)
        })
        .collect()
}

/// The jump at frame t (`|p(t) - 2 p(t-1) + p(t-2)|` per point, eye distances): `None` without three frames.
pub fn jump(frames: &[Landmarks], t: usize) -> Option<f64> {
    let (Some(a), Some(b), Some(c)) = (
        frames.get(t.checked_sub(2)?)?.as_ref(),
        frames.get(t - 1)?.as_ref(),
        frames.get(t)?.as_ref(),
    ) else {
        return None;
    };
    Some(second_difference(a, b, c, 1.0, eye_distance(c)?))
}

/// Mean, median, 95th percentile and count of the `Some` values.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Summary {
    /// Frames measured.
    pub frames: usize,
    /// Mean.
    pub mean: f64,
    /// Median (nearest rank).
    pub median: f64,
    /// 95th percentile (nearest rank).
    pub p95: f64,
    /// Largest.
    pub max: f64,
}

/// Summarises the `Some` values; `None` when there is none.
pub fn summarise(values: &[Option<f64>]) -> Option<Summary> {
    let mut v: Vec<f64> = values
        .iter()
        .flatten()
        .copied()
        .filter(|x| x.is_finite())
        .collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let rank = |q: f64| ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
    Some(Summary {
        frames: v.len(),
        mean: v.iter().sum::<f64>() / v.len() as f64,
        median: v[rank(0.5)],
        p95: v[rank(0.95)],
        max: v[v.len() - 1],
    })
}

/// Per frame where both have landmarks: the mean distance over the 49 points between `ours` and `peer`,
/// divided by the peer's outer-eye-corner distance (NME49 against the peer).
pub fn agreement(ours: &[Landmarks], peer: &[Landmarks]) -> Vec<Option<f64>> {
    ours.iter()
        .zip(peer)
        .map(|(a, b)| {
            let (a, b) = (a.as_ref()?, b.as_ref()?);
            let eye = eye_distance(b)?;
            Some(
                PROTOCOL49
                    .iter()
                    .map(|&i| f64::from(a[i].dist(b[i])))
                    .sum::<f64>()
                    / (49.0 * eye),
            )
        })
        .collect()
}

/// Parses the per-frame peer file of `models/peer_video_dlib.py`: one line per frame, `index` then 136
/// numbers, or `index -` without a face. Frames must be listed in order from 0.
pub fn parse_peer(text: &str) -> Result<Vec<Landmarks>, String> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let mut it = line.split_ascii_whitespace();
        let index: usize = it
            .next()
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| format!("line {}: no frame index", n + 1))?;
        if index != out.len() {
            return Err(format!("line {}: frame {index}, expected {}", n + 1, out.len()));
        }
        let rest: Vec<&str> = it.collect();
        if rest == ["-"] {
            out.push(None);
            continue;
        }
        if rest.len() != 136 {
            return Err(format!(
                "line {}: {} numbers, expected 136 or \"-\"",
                n + 1,
                rest.len()
            ));
        }
        let mut p = [Point2::default(); 68];
        for (k, q) in p.iter_mut().enumerate() {
            let v = |s: &str| {
                s.parse::<f32>()
                    .ok()
                    .filter(|v| v.is_finite())
                    .ok_or_else(|| format!("line {}: {s:?} is not a finite number", n + 1))
            };
            *q = Point2::new(v(rest[2 * k])?, v(rest[2 * k + 1])?);
        }
        out.push(Some(p));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use holoface_models::geometry::Similarity2;
    use holoface_models::shape::dan_mean_shape;

    fn face(dx: f32) -> [Point2; 68] {
        let mut p = [Point2::default(); 68];
        Similarity2::from_parts(2.0, 0.0, 100.0 + f64::from(dx), 80.0).apply_all(&dan_mean_shape(), &mut p);
        p
    }

    #[test]
    fn steady_motion_has_no_jitter_and_noise_has_some() {
        let moving: Vec<Landmarks> = (0..10).map(|t| Some(face(3.0 * t as f32))).collect();
        let j = jitter49(&moving);
        assert_eq!(j[0], None);
        assert_eq!(j[9], None);
        assert!(j[1..9].iter().all(|v| v.is_some_and(|v| v < 1e-6)), "{j:?}");
        // One frame shifted by 2 px sideways: half of it shows at that frame.
        let mut shaken = moving.clone();
        shaken[5] = Some(face(15.0 + 2.0));
        let eye = f64::from(face(0.0)[36].dist(face(0.0)[45]));
        let j = jitter49(&shaken);
        assert!(
            (j[5].unwrap() - 2.0 / eye).abs() < 1e-4,
            "{:?} vs {}",
            j[5],
            2.0 / eye
        );
        assert!((j[4].unwrap() - 1.0 / eye).abs() < 1e-4);
        // A missing frame removes its neighbours' values.
        shaken[7] = None;
        let j = jitter49(&shaken);
        assert_eq!((j[6], j[7], j[8]), (None, None, None));
        let s = summarise(&j).unwrap();
        assert_eq!(s.frames, 5);
        assert!((s.max - 2.0 / eye).abs() < 1e-4);
        // In pixels: the same shake, not divided by the eye distance; one point's track alike.
        assert!((jitter49_px(&shaken)[5].unwrap() - 2.0).abs() < 1e-4);
        let point: Vec<Option<Point2>> = shaken.iter().map(|f| f.map(|p| p[30])).collect();
        let pj = point_jitter_px(&point);
        assert!((pj[5].unwrap() - 2.0).abs() < 1e-4 && pj[3].unwrap() < 1e-6);
        assert_eq!((pj[6], pj[7], pj[8]), (None, None, None));
    }

    #[test]
    fn a_step_is_a_jump_of_its_size_and_motion_is_none() {
        let eye = f64::from(face(0.0)[36].dist(face(0.0)[45]));
        let mut f: Vec<Landmarks> = (0..6).map(|t| Some(face(3.0 * t as f32))).collect();
        assert!(jump(&f, 4).unwrap() < 1e-6);
        f[4] = Some(face(12.0 + 5.0));
        assert!((jump(&f, 4).unwrap() - 5.0 / eye).abs() < 1e-4);
        assert_eq!(jump(&f, 1), None);
        assert_eq!(jump(&f, 9), None);
    }

    #[test]
    fn agreement_is_nme49_against_the_peer() {
        let a = face(0.0);
        let b = face(4.0);
        let eye = f64::from(b[36].dist(b[45]));
        let g = agreement(&[Some(a), None, Some(a)], &[Some(b), Some(b), None]);
        assert!((g[0].unwrap() - 4.0 / eye).abs() < 1e-4);
        assert_eq!((g[1], g[2]), (None, None));
    }

    #[test]
    fn peer_files_parse_and_bad_ones_say_where() {
        let nums: Vec<String> = (0..136).map(|k| format!("{}", k % 50)).collect();
        let text = format!("0 {}\n1 -\n\n2 {}\n", nums.join(" "), nums.join(" "));
        let p = parse_peer(&text).unwrap();
        assert_eq!(p.len(), 3);
        assert!(p[1].is_none());
        assert_eq!(p[2].unwrap()[1], Point2::new(2.0, 3.0));
        assert!(parse_peer("1 -\n").unwrap_err().contains("expected 0"));
        assert!(parse_peer("0 1 2\n").unwrap_err().contains("2 numbers"));
        assert!(
            parse_peer(&format!("0 nan {}", nums[1..].join(" ")))
                .unwrap_err()
                .contains("finite")
        );
        assert!(parse_peer("x\n").unwrap_err().contains("line 1"));
        assert_eq!(summarise(&[None, None]), None);
    }
}
