//! Per-person correction of the local aligner towards the remote one (issue 55).
//!
//! While the link is up the headset receives, for this very person, camera and lighting, the server's
//! precise answer on frames where the local aligner (KRFWS) can also run. [`PersonCorrection`] learns from
//! those pairs how KRFWS's answer differs from the server's, and corrects KRFWS's answers when the link is
//! down.
//!
//! **The face's own frame.** Each pair is compared after the least-squares similarity that maps the local
//! answer's 51 inner points onto a reference shape whose outer eye corners are one unit apart: head
//! position, in-plane rotation and scale do not leak into the correction, and every length is in eye
//! distances. A correction is a shift per point in that frame, mapped back with the same similarity.
//!
//! **What it learns.** The person's mean offset per point (exponentially weighted), and by default, per
//! point, how that point's offset follows what the local aligner sees around it in the same frame
//! ([`Appearance`]: KRFWS's 144-value HOG at the point, pooled over 2×2 cells to 36 values): a ridge regression
//! per point ([`AdaptParams::appearance_ridge`]) whose intercept, not penalised, is the mean offset. KRFWS's
//! errors that follow the image around a point (a brow raised, the lips parted, a shadow) are then corrected
//! too. On the development clips' link cuts this closed 53-58 % of the gap between KRFWS and the server,
//! against 37-38 % for the mean offset alone, and lowered the local answers' jitter (BENCHMARKS.md, "A
//! fallback that learned from the server"). The 51 regressions are solved only when a corrected answer asks
//! for them after new pairs (about a third of a millisecond, once per link cut), not at each pair.
//!
//! As an option, a finite [`AdaptParams::ridge`] adds a ridge regression of the 102 offsets on a few shape
//! features of the local answer in that frame ([`FEATURES`]: the nose's offset from the eyes across and
//! along the face, which follow the head's turn and tilt; the mouth's opening and width; the eyes' opening;
//! the brows' height); its intercept is not penalised either, so as the ridge grows it becomes the mean
//! offset. It followed KRFWS's own errors on the clips and is off by default. Each regression is fitted on
//! its own; use one at a time.
//!
//! **Bounds against a bad stretch.** A pair whose answers differ by more than [`AdaptParams::gate`] is not
//! learnt (one of the two failed); every pair's weight fades by `1 - 1/memory` per later pair, so a stretch
//! of bad answers is forgotten as good ones come; features are clamped to three standard deviations of
//! those seen (no extrapolation); no point moves by more than [`AdaptParams::max_shift`].
//!
//! No clock: memory is counted in learnt pairs, not time (the caller decides how often it learns).

use crate::geometry::{Point2, Similarity2};
use crate::hog::{BINS, CELLS, HOG_DIM};
use crate::shape::{INNER51, OUTER_EYE_CORNERS, dan_mean_shape};

const N: usize = 51;
const D: usize = 2 * N;
/// How many shape features the regression uses (see the module docs).
pub const FEATURES: usize = 6;
/// Values describing what the local aligner sees around one point ([`pool_hog`]).
pub const APPEARANCE: usize = 4 * BINS;
/// Packed lower triangle of an `APPEARANCE`-square symmetric matrix.
const PACKED: usize = APPEARANCE * (APPEARANCE + 1) / 2;
/// What the local aligner sees around each of the 51 inner points of one answer.
pub type Appearance = [[f32; APPEARANCE]; N];

/// KRFWS's 51×144 HOG (per point 4×4 cells of 9 bins, cell-major: [`crate::hog`]) pooled over 2×2 cells:
/// 51×36 (four quadrants of the point's window, 9 bins each). `None` unless `hog` holds 51×144 values.
pub fn pool_hog(hog: &[f32]) -> Option<Box<Appearance>> {
    if hog.len() != N * HOG_DIM {
        return None;
    }
    let mut out = Box::new([[0.0; APPEARANCE]; N]);
    for (row, pooled) in hog.chunks_exact(HOG_DIM).zip(out.iter_mut()) {
        for (cell, bins) in row.chunks_exact(BINS).enumerate() {
            let quadrant = (cell / CELLS / 2) * 2 + (cell % CELLS) / 2;
            for (b, v) in bins.iter().enumerate() {
                pooled[quadrant * BINS + b] += v;
            }
        }
    }
    Some(out)
}

/// Settings of [`PersonCorrection`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdaptParams {
    /// Effective memory in learnt pairs: each pair's weight is multiplied by `1 - 1/memory_pairs` per later
    /// pair (at least 1).
    pub memory_pairs: f64,
    /// Learnt pairs before a correction is applied.
    pub min_pairs: u32,
    /// A pair whose two answers differ by more than this (mean over the 51 points, eye distances) is not
    /// learnt.
    pub gate: f64,
    /// The longest shift of one point (eye distances).
    pub max_shift: f64,
    /// Ridge on the regression's slopes, in units of the features' variance (eye distances squared);
    /// `f64::INFINITY` (the default): off.
    pub ridge: f64,
    /// Ridge of each point's regression on its [`Appearance`], in units of the mean variance of that point's
    /// 36 values; `f64::INFINITY`: off (the answers' appearance is not used). The default, 3, closed the
    /// most of the gap on the development clips' link cuts (docs/experiments/fallback-adaptation.md).
    pub appearance_ridge: f64,
}

impl Default for AdaptParams {
    /// Chosen on the development clips (docs/experiments/fallback-adaptation.md).
    fn default() -> Self {
        Self {
            memory_pairs: 2000.0,
            min_pairs: 10,
            gate: 0.10,
            max_shift: 0.08,
            ridge: f64::INFINITY,
            appearance_ridge: 3.0,
        }
    }
}

/// What [`PersonCorrection::learn`] did with a pair.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Learnt {
    /// The pair was learnt.
    Yes,
    /// The two answers differ by more than the gate: not learnt.
    Gated,
    /// An answer is degenerate (no extent, not finite): not learnt.
    Degenerate,
}

/// The fitted correction: offsets = `intercept + slopes · clamp(features)`.
#[derive(Clone, Debug, PartialEq)]
struct Fitted {
    intercept: [f64; D],
    slopes: [[f64; D]; FEATURES],
    low: [f64; FEATURES],
    high: [f64; FEATURES],
}

/// The per-point regressions on the [`Appearance`] (see the module docs): exponentially weighted sums, and
/// the fit they last gave.
#[derive(Clone, Debug, PartialEq)]
struct AppearanceFit {
    ridge: f64,
    sw: f64,
    /// Per point: the features' sums, their products (packed lower triangle), the offsets' sums and the
    /// feature-offset products.
    sh: Vec<[f64; APPEARANCE]>,
    shh: Vec<[f64; PACKED]>,
    sd: Vec<[f64; 2]>,
    shd: Vec<[[f64; 2]; APPEARANCE]>,
    /// Whether pairs came since the last fit.
    stale: bool,
    fitted: Option<Box<FittedAppearance>>,
}

/// Per point: the features' mean and three standard deviations (the clamp), the slopes per coordinate.
#[derive(Clone, Debug, PartialEq)]
struct FittedAppearance {
    mean: Vec<[f64; APPEARANCE]>,
    spread: Vec<[f64; APPEARANCE]>,
    slopes: Vec<[[f64; 2]; APPEARANCE]>,
}

/// Index of `(a, b)`, `b <= a`, in a packed lower triangle.
const fn packed(a: usize, b: usize) -> usize {
    a * (a + 1) / 2 + b
}

impl AppearanceFit {
    fn new(ridge: f64) -> Self {
        Self {
            ridge,
            sw: 0.0,
            sh: vec![[0.0; APPEARANCE]; N],
            shh: vec![[0.0; PACKED]; N],
            sd: vec![[0.0; 2]; N],
            shd: vec![[[0.0; 2]; APPEARANCE]; N],
            stale: false,
            fitted: None,
        }
    }

    fn learn(&mut self, look: &Appearance, d: &[f64; D], keep: f64) {
        self.sw = self.sw * keep + 1.0;
        for i in 0..N {
            let h = look[i].map(f64::from);
            let (di, sh, shh, shd) = (
                [d[2 * i], d[2 * i + 1]],
                &mut self.sh[i],
                &mut self.shh[i],
                &mut self.shd[i],
            );
            for a in 0..APPEARANCE {
                sh[a] = sh[a] * keep + h[a];
                for (b, hb) in h.iter().enumerate().take(a + 1) {
                    let s = &mut shh[packed(a, b)];
                    *s = *s * keep + h[a] * hb;
                }
                for c in 0..2 {
                    shd[a][c] = shd[a][c] * keep + h[a] * di[c];
                }
            }
            for (s, v) in self.sd[i].iter_mut().zip(di) {
                *s = *s * keep + v;
            }
        }
        self.stale = true;
    }

    /// Solves each point's ridge regression of its centred offsets on its centred features.
    fn fit(&self) -> Option<FittedAppearance> {
        let w = self.sw;
        if w <= 0.0 {
            return None;
        }
        let mut out = FittedAppearance {
            mean: Vec::with_capacity(N),
            spread: Vec::with_capacity(N),
            slopes: Vec::with_capacity(N),
        };
        let mut cov = vec![0.0; APPEARANCE * APPEARANCE];
        for i in 0..N {
            let mh: [f64; APPEARANCE] = self.sh[i].map(|v| v / w);
            let md = self.sd[i].map(|v| v / w);
            for a in 0..APPEARANCE {
                for b in 0..=a {
                    let c = self.shh[i][packed(a, b)] / w - mh[a] * mh[b];
                    cov[a * APPEARANCE + b] = c;
                    cov[b * APPEARANCE + a] = c;
                }
            }
            let var: [f64; APPEARANCE] = std::array::from_fn(|a| cov[a * APPEARANCE + a].max(0.0));
            let ridge = self.ridge * (var.iter().sum::<f64>() / APPEARANCE as f64).max(1e-12);
            for a in 0..APPEARANCE {
                cov[a * APPEARANCE + a] += ridge;
            }
            if !crate::linalg::cholesky_factor(&mut cov, APPEARANCE) {
                return None;
            }
            let mut slopes = [[0.0; 2]; APPEARANCE];
            for c in 0..2 {
                let mut b: [f64; APPEARANCE] = std::array::from_fn(|a| self.shd[i][a][c] / w - mh[a] * md[c]);
                crate::linalg::solve_factored(&cov, APPEARANCE, &mut b);
                for (s, v) in slopes.iter_mut().zip(b) {
                    s[c] = v;
                }
            }
            out.mean.push(mh);
            out.spread.push(var.map(|v| 3.0 * v.sqrt()));
            out.slopes.push(slopes);
        }
        let finite = out.slopes.iter().flatten().flatten().all(|v| v.is_finite());
        finite.then_some(out)
    }

    /// Point `i`'s shift (reference frame, eye distances) for its features `h`, by the last fit.
    fn shift(&self, i: usize, h: &[f32; APPEARANCE]) -> Option<[f64; 2]> {
        let f = self.fitted.as_deref()?;
        let mut c = [0.0; 2];
        for (a, v) in h.iter().enumerate() {
            let x = (f64::from(*v) - f.mean[i][a]).clamp(-f.spread[i][a], f.spread[i][a]);
            c[0] += f.slopes[i][a][0] * x;
            c[1] += f.slopes[i][a][1] * x;
        }
        Some(c)
    }
}

/// One person's correction of the local aligner towards the remote one (see the module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct PersonCorrection {
    params: AdaptParams,
    reference: [Point2; N],
    /// Exponentially weighted sums: weight, features, feature products, offsets, feature-offset products.
    sw: f64,
    sx: [f64; FEATURES],
    sxx: [[f64; FEATURES]; FEATURES],
    sd: [f64; D],
    sxd: [[f64; D]; FEATURES],
    pairs: u32,
    gated: u32,
    fitted: Option<Box<Fitted>>,
    appearance: Option<Box<AppearanceFit>>,
}

/// The reference shape: DAN's mean shape's inner 51 points, centred, outer eye corners one unit apart and
/// level.
fn reference() -> [Point2; N] {
    let mean = dan_mean_shape();
    let (l, r) = (mean[OUTER_EYE_CORNERS.0], mean[OUTER_EYE_CORNERS.1]);
    let (dx, dy) = (f64::from(r.x - l.x), f64::from(r.y - l.y));
    let eye = dx.hypot(dy).max(1e-9);
    let c = crate::geometry::centroid(&mean[INNER51]);
    let s = Similarity2::from_parts(1.0 / eye, -dy.atan2(dx), 0.0, 0.0);
    std::array::from_fn(|i| {
        let p = mean[INNER51.start + i];
        s.apply(Point2::new(p.x - c.x, p.y - c.y))
    })
}

/// Index into the 51 inner points of an iBUG index.
const fn at(ibug: usize) -> usize {
    ibug - INNER51.start
}

/// The shape features of a face in the reference frame (see the module docs).
fn features(p: &[Point2; N]) -> [f64; FEATURES] {
    let x = |i: usize| f64::from(p[at(i)].x);
    let y = |i: usize| f64::from(p[at(i)].y);
    let d = |i: usize, j: usize| f64::from(p[at(i)].dist(p[at(j)]));
    let (eye_x, eye_y) = ((x(36) + x(45)) / 2.0, (y(36) + y(45)) / 2.0);
    let brows = (17..27).map(|i| eye_y - y(i)).sum::<f64>() / 10.0;
    [
        x(30) - eye_x,
        y(30) - eye_y,
        d(62, 66),
        d(48, 54),
        (d(37, 41) + d(38, 40) + d(43, 47) + d(44, 46)) / 4.0,
        brows,
    ]
}

impl PersonCorrection {
    /// An empty correction (nothing learnt: [`Self::correct`] answers `None`).
    pub fn new(params: AdaptParams) -> Self {
        Self {
            params,
            reference: reference(),
            sw: 0.0,
            sx: [0.0; FEATURES],
            sxx: [[0.0; FEATURES]; FEATURES],
            sd: [0.0; D],
            sxd: [[0.0; D]; FEATURES],
            pairs: 0,
            gated: 0,
            fitted: None,
            appearance: params
                .appearance_ridge
                .is_finite()
                .then(|| Box::new(AppearanceFit::new(params.appearance_ridge))),
        }
    }

    /// Whether [`Self::correct`] can correct an answer yet ([`AdaptParams::min_pairs`] pairs learnt): before,
    /// there is no need to find out what the local aligner saw.
    pub fn ready(&self) -> bool {
        self.pairs >= self.params.min_pairs && self.fitted.is_some()
    }

    /// Whether the correction uses the answers' [`Appearance`] ([`AdaptParams::appearance_ridge`]): the
    /// caller then passes it to [`Self::learn`] and [`Self::correct`].
    pub fn wants_appearance(&self) -> bool {
        self.appearance.is_some()
    }

    /// Pairs learnt so far.
    pub fn pairs(&self) -> u32 {
        self.pairs
    }

    /// Pairs not learnt because their answers disagreed by more than the gate.
    pub fn gated(&self) -> u32 {
        self.gated
    }

    /// The similarity from `shape`'s 51 inner points to the reference frame and the points mapped there.
    fn to_reference(&self, shape: &[Point2; 68]) -> Option<(Similarity2, [Point2; N])> {
        let inner = &shape[INNER51];
        if inner.iter().any(|p| !p.x.is_finite() || !p.y.is_finite()) {
            return None;
        }
        let s = Similarity2::fit(inner, &self.reference)?;
        (s.scale() > 1e-9).then(|| (s, std::array::from_fn(|i| s.apply(inner[i]))))
    }

    /// Learns one pair: the local aligner's answer and the remote one for the same frame (68 points in
    /// image pixels; only the 51 inner points are used), with what the local aligner saw at its answer when
    /// the correction [wants it](Self::wants_appearance) (a pair without it teaches only the rest).
    pub fn learn(
        &mut self,
        local: &[Point2; 68],
        remote: &[Point2; 68],
        look: Option<&Appearance>,
    ) -> Learnt {
        let Some((s, k)) = self.to_reference(local) else {
            return Learnt::Degenerate;
        };
        if remote[INNER51]
            .iter()
            .any(|p| !p.x.is_finite() || !p.y.is_finite())
        {
            return Learnt::Degenerate;
        }
        let mut d = [0.0; D];
        let mut mean_gap = 0.0;
        for i in 0..N {
            let r = s.apply(remote[INNER51.start + i]);
            d[2 * i] = f64::from(r.x - k[i].x);
            d[2 * i + 1] = f64::from(r.y - k[i].y);
            mean_gap += d[2 * i].hypot(d[2 * i + 1]) / N as f64;
        }
        if !mean_gap.is_finite() || mean_gap > self.params.gate {
            self.gated += 1;
            return Learnt::Gated;
        }
        let x = features(&k);
        let keep = 1.0 - 1.0 / self.params.memory_pairs.max(1.0);
        self.sw = self.sw * keep + 1.0;
        for a in 0..FEATURES {
            self.sx[a] = self.sx[a] * keep + x[a];
            for b in 0..FEATURES {
                self.sxx[a][b] = self.sxx[a][b] * keep + x[a] * x[b];
            }
            for (s, v) in self.sxd[a].iter_mut().zip(&d) {
                *s = *s * keep + x[a] * v;
            }
        }
        for (s, v) in self.sd.iter_mut().zip(&d) {
            *s = *s * keep + v;
        }
        if let (Some(fit), Some(look)) = (self.appearance.as_deref_mut(), look)
            && look.iter().flatten().all(|v| v.is_finite())
        {
            fit.learn(look, &d, keep);
        }
        self.pairs = self.pairs.saturating_add(1);
        self.fitted = self.fit().map(Box::new);
        Learnt::Yes
    }

    /// The ridge regression of the offsets on the centred features (see the module docs).
    fn fit(&self) -> Option<Fitted> {
        let w = self.sw;
        if w <= 0.0 {
            return None;
        }
        let mx: [f64; FEATURES] = std::array::from_fn(|a| self.sx[a] / w);
        let md: [f64; D] = std::array::from_fn(|k| self.sd[k] / w);
        let var: [f64; FEATURES] = std::array::from_fn(|a| (self.sxx[a][a] / w - mx[a] * mx[a]).max(0.0));
        let mut slopes = [[0.0; D]; FEATURES];
        if self.params.ridge.is_finite() {
            let cxx: [[f64; FEATURES]; FEATURES] = std::array::from_fn(|a| {
                std::array::from_fn(|b| {
                    self.sxx[a][b] / w - mx[a] * mx[b] + if a == b { self.params.ridge } else { 0.0 }
                })
            });
            // The inverse, one column per unit vector (a row too: it is symmetric), then
            // slopes = inverse · cov(features, offsets).
            let mut inv = [[0.0; FEATURES]; FEATURES];
            for (c, row) in inv.iter_mut().enumerate() {
                let e = std::array::from_fn(|r| f64::from(u8::from(r == c)));
                *row = crate::linalg::solve_spd(cxx, e)?;
            }
            for (a, row) in slopes.iter_mut().enumerate() {
                for (k, s) in row.iter_mut().enumerate() {
                    *s = (0..FEATURES)
                        .map(|b| inv[a][b] * (self.sxd[b][k] / w - mx[b] * md[k]))
                        .sum();
                }
            }
        }
        let intercept =
            std::array::from_fn(|k| md[k] - (0..FEATURES).map(|a| slopes[a][k] * mx[a]).sum::<f64>());
        let spread: [f64; FEATURES] = std::array::from_fn(|a| 3.0 * var[a].sqrt());
        let fitted = Fitted {
            intercept,
            slopes,
            low: std::array::from_fn(|a| mx[a] - spread[a]),
            high: std::array::from_fn(|a| mx[a] + spread[a]),
        };
        let finite = fitted
            .intercept
            .iter()
            .chain(fitted.slopes.iter().flatten())
            .all(|v| v.is_finite());
        finite.then_some(fitted)
    }

    /// The local answer corrected (its 51 inner points; the jaw is returned as given) and the correction's
    /// mean length over those points (eye distances); `None` before [`AdaptParams::min_pairs`] pairs or for
    /// a degenerate answer. With what the local aligner saw at this answer (`look`), the appearance's part
    /// is added when the correction [wants it](Self::wants_appearance); its regressions are solved here
    /// first when pairs came since they last were.
    pub fn correct(
        &mut self,
        local: &[Point2; 68],
        look: Option<&Appearance>,
    ) -> Option<([Point2; 68], f32)> {
        if !self.ready() {
            return None;
        }
        if let (Some(fit), Some(_)) = (self.appearance.as_deref_mut(), look)
            && fit.stale
        {
            fit.fitted = fit.fit().map(Box::new);
            fit.stale = false;
        }
        let seen = look
            .filter(|l| l.iter().flatten().all(|v| v.is_finite()))
            .zip(self.appearance.as_deref());
        let fitted = self.fitted.as_deref()?;
        let (s, k) = self.to_reference(local)?;
        let back = s.inverse()?;
        let x = features(&k);
        let x: [f64; FEATURES] = std::array::from_fn(|a| x[a].clamp(fitted.low[a], fitted.high[a]));
        let mut out = *local;
        let mut total = 0.0;
        for i in 0..N {
            let mut c = [0.0; 2];
            for (j, v) in c.iter_mut().enumerate() {
                let k = 2 * i + j;
                *v = fitted.intercept[k] + (0..FEATURES).map(|a| fitted.slopes[a][k] * x[a]).sum::<f64>();
            }
            if let Some(shift) = seen.and_then(|(look, fit)| fit.shift(i, &look[i])) {
                c = [c[0] + shift[0], c[1] + shift[1]];
            }
            let len = c[0].hypot(c[1]);
            if len > self.params.max_shift {
                let f = self.params.max_shift / len;
                c = [c[0] * f, c[1] * f];
            }
            total += c[0].hypot(c[1]);
            let q = Point2::new(k[i].x + c[0] as f32, k[i].y + c[1] as f32);
            out[INNER51.start + i] = back.apply(q);
        }
        Some((out, (total / N as f64) as f32))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// The regression on the features, with a short memory.
    const REGRESSION: AdaptParams = AdaptParams {
        memory_pairs: 300.0,
        min_pairs: 10,
        gate: 0.10,
        max_shift: 0.08,
        ridge: 2e-4,
        appearance_ridge: f64::INFINITY,
    };

    /// A face in the image: the mean shape placed by `sim`, its mouth opened by `open` (crop pixels).
    fn face(sim: &Similarity2, open: f32) -> [Point2; 68] {
        let mut p = dan_mean_shape();
        for i in [57, 58, 56, 65, 66, 67] {
            p[i].y += open;
        }
        let mut out = [Point2::default(); 68];
        sim.apply_all(&p, &mut out);
        out
    }

    /// The remote answer: the local one with a person-specific bias in the face's frame (a fixed shift of
    /// the brows and, growing with the mouth's opening, of the lower lip), placed by the same similarity.
    fn remote_of(sim: &Similarity2, open: f32) -> [Point2; 68] {
        let mut p = dan_mean_shape();
        for i in [57, 58, 56, 65, 66, 67] {
            p[i].y += open * 1.15;
        }
        for q in &mut p[17..27] {
            q.y -= 1.5;
        }
        let mut out = [Point2::default(); 68];
        sim.apply_all(&p, &mut out);
        out
    }

    fn mean_error(a: &[Point2; 68], b: &[Point2; 68]) -> f32 {
        let eye = b[36].dist(b[45]);
        (17..68).map(|i| a[i].dist(b[i])).sum::<f32>() / (51.0 * eye)
    }

    fn between(rng: &mut Rng, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * rng.uniform()
    }

    fn placement(rng: &mut Rng) -> Similarity2 {
        Similarity2::from_parts(
            between(rng, 2.0, 4.0),
            between(rng, -0.4, 0.4),
            between(rng, 50.0, 300.0),
            between(rng, 50.0, 300.0),
        )
    }

    #[test]
    fn it_learns_a_persons_offset_and_its_dependence_on_the_mouth_in_the_faces_own_frame() {
        let mut rng = Rng::new(7);
        let mut c = PersonCorrection::new(REGRESSION);
        let probe = Similarity2::from_parts(3.0, 0.3, 120.0, 90.0);
        assert_eq!(c.correct(&face(&probe, 4.0), None), None, "nothing learnt yet");
        for _ in 0..200 {
            let sim = placement(&mut rng);
            let open = between(&mut rng, 0.0, 8.0) as f32;
            assert_eq!(
                c.learn(&face(&sim, open), &remote_of(&sim, open), None),
                Learnt::Yes
            );
        }
        assert_eq!(c.pairs(), 200);
        // Any placement, any opening within those seen: the corrected answer is the remote one.
        for open in [0.5, 4.0, 7.5] {
            let local = face(&probe, open);
            let target = remote_of(&probe, open);
            let (fixed, size) = c.correct(&local, None).unwrap();
            let before = mean_error(&local, &target);
            let after = mean_error(&fixed, &target);
            assert!(before > 0.005, "{before}");
            assert!(after < 0.1 * before, "open {open}: {before} -> {after}");
            assert!(size > 0.0);
            // The jaw is left as it was.
            assert_eq!(&fixed[..17], &local[..17]);
        }
    }

    /// What the local aligner "sees" at each point: random values, and the remote answer's offset of each
    /// point depends on its first two (a point whose look says "raised" is shifted up by the server).
    fn looked(rng: &mut Rng) -> Box<Appearance> {
        let mut look = Box::new([[0.0; APPEARANCE]; N]);
        for v in look.iter_mut().flatten() {
            *v = rng.uniform() as f32;
        }
        look
    }

    fn remote_seen(sim: &Similarity2, look: &Appearance) -> [Point2; 68] {
        let mut p = dan_mean_shape();
        for (i, l) in look.iter().enumerate() {
            p[INNER51.start + i].x += 2.0 * (l[0] - 0.5);
            p[INNER51.start + i].y += 0.5 - 3.0 * (l[1] - 0.5);
        }
        let mut out = [Point2::default(); 68];
        sim.apply_all(&p, &mut out);
        out
    }

    #[test]
    fn it_follows_what_the_local_aligner_sees_at_each_point() {
        let mut rng = Rng::new(5);
        let params = AdaptParams {
            appearance_ridge: 0.1,
            ..AdaptParams::default()
        };
        let mut seeing = PersonCorrection::new(params);
        let mut blind = PersonCorrection::new(AdaptParams {
            appearance_ridge: f64::INFINITY,
            ..params
        });
        assert!(seeing.wants_appearance() && !blind.wants_appearance());
        for _ in 0..300 {
            let sim = placement(&mut rng);
            let look = looked(&mut rng);
            let (local, remote) = (face(&sim, 0.0), remote_seen(&sim, &look));
            assert_eq!(seeing.learn(&local, &remote, Some(&look)), Learnt::Yes);
            assert_eq!(blind.learn(&local, &remote, Some(&look)), Learnt::Yes);
        }
        let probe = Similarity2::from_parts(3.0, 0.2, 140.0, 120.0);
        let (mut seen_err, mut blind_err, mut before) = (0.0, 0.0, 0.0);
        for _ in 0..20 {
            let look = looked(&mut rng);
            let (local, target) = (face(&probe, 0.0), remote_seen(&probe, &look));
            seen_err += mean_error(&seeing.correct(&local, Some(&look)).unwrap().0, &target);
            blind_err += mean_error(&blind.correct(&local, Some(&look)).unwrap().0, &target);
            before += mean_error(&local, &target);
        }
        // The mean offset takes the common half-pixel shift only; the appearance follows each point.
        assert!(blind_err > 0.6 * before, "{blind_err} of {before}");
        assert!(seen_err < 0.15 * before, "{seen_err} of {before}");
        // Without a look the appearance's part is left out: the mean offset again.
        let look = looked(&mut rng);
        let local = face(&probe, 0.0);
        assert_eq!(seeing.correct(&local, None), blind.correct(&local, None));
        assert_ne!(
            seeing.correct(&local, Some(&look)),
            blind.correct(&local, Some(&look))
        );
        // A look that is not finite is not learnt from; the rest of the pair is.
        let mut bad = looked(&mut rng);
        bad[3][7] = f32::NAN;
        let sim = placement(&mut rng);
        assert_eq!(
            seeing.learn(&face(&sim, 0.0), &remote_seen(&sim, &bad), Some(&bad)),
            Learnt::Yes
        );
        assert!(seeing.correct(&local, Some(&look)).is_some());
        // Nor is one used to correct: the answer gets the rest of the correction.
        let (rest, _) = seeing.correct(&local, None).unwrap();
        assert_eq!(seeing.correct(&local, Some(&bad)).unwrap().0, rest);
    }

    #[test]
    fn hog_pools_to_four_quadrants_of_nine_bins() {
        assert!(pool_hog(&[0.0; 10]).is_none());
        let mut hog = vec![0.0; N * HOG_DIM];
        // Point 2: cell (row 3, column 0) bin 4 and cell (row 0, column 3) bin 8.
        hog[2 * HOG_DIM + (3 * CELLS) * BINS + 4] = 1.0;
        hog[2 * HOG_DIM + 3 * BINS + 8] = 0.5;
        hog[2 * HOG_DIM + (2 * CELLS) * BINS + 4] = 0.25;
        let pooled = pool_hog(&hog).unwrap();
        assert_eq!(pooled[2][2 * BINS + 4], 1.25, "lower-left quadrant");
        assert_eq!(pooled[2][BINS + 8], 0.5, "upper-right quadrant");
        assert_eq!(pooled.iter().flatten().sum::<f32>(), 1.75);
    }

    #[test]
    fn the_default_mean_offset_ignores_the_features() {
        let mut rng = Rng::new(3);
        assert_eq!(AdaptParams::default().ridge, f64::INFINITY);
        let mut c = PersonCorrection::new(AdaptParams::default());
        for _ in 0..100 {
            let sim = placement(&mut rng);
            let open = between(&mut rng, 0.0, 8.0) as f32;
            c.learn(&face(&sim, open), &remote_of(&sim, open), None);
        }
        let probe = Similarity2::from_parts(2.5, 0.0, 100.0, 100.0);
        // The brows' fixed shift is learnt; the mouth's part only on average.
        let (fixed, _) = c.correct(&face(&probe, 0.0), None).unwrap();
        let target = remote_of(&probe, 0.0);
        let brows = (17..27).map(|i| fixed[i].dist(target[i])).sum::<f32>() / 10.0;
        assert!(brows < 0.3, "{brows} px of a 3.75-px shift");
        assert!(
            fixed[66].dist(target[66]) > 0.2,
            "the mean offset cannot follow the mouth"
        );
    }

    #[test]
    fn a_bad_stretch_is_gated_bounded_and_forgotten() {
        let mut rng = Rng::new(11);
        let params = AdaptParams {
            memory_pairs: 300.0,
            ..REGRESSION
        };
        let mut c = PersonCorrection::new(params);
        for _ in 0..100 {
            let sim = placement(&mut rng);
            c.learn(&face(&sim, 2.0), &remote_of(&sim, 2.0), None);
        }
        let probe = Similarity2::from_parts(3.0, 0.0, 150.0, 150.0);
        let good = c.correct(&face(&probe, 2.0), None).unwrap().0;
        // Answers far off (the server locked onto something else): gated, nothing changes.
        for _ in 0..50 {
            let sim = placement(&mut rng);
            let far = Similarity2::from_parts(sim.scale(), sim.angle(), sim.tx + 40.0, sim.ty);
            assert_eq!(c.learn(&face(&sim, 2.0), &face(&far, 2.0), None), Learnt::Gated);
        }
        assert_eq!(c.gated(), 50);
        assert_eq!(c.correct(&face(&probe, 2.0), None).unwrap().0, good);
        // A stretch just inside the gate pulls it, but no point moves by more than the bound.
        for _ in 0..100 {
            let sim = placement(&mut rng);
            let off = Similarity2::from_parts(sim.scale(), sim.angle(), sim.tx + 2.0 * sim.scale(), sim.ty);
            c.learn(&face(&sim, 2.0), &face(&off, 2.0), None);
        }
        let local = face(&probe, 2.0);
        let (pulled, size) = c.correct(&local, None).unwrap();
        let eye = local[36].dist(local[45]);
        let bound = params.max_shift as f32 * eye * 1.001;
        assert!((17..68).all(|i| pulled[i].dist(local[i]) <= bound));
        assert!(size <= params.max_shift as f32 + 1e-6);
        // Good pairs again: the bad stretch fades.
        for _ in 0..1500 {
            let sim = placement(&mut rng);
            c.learn(&face(&sim, 2.0), &remote_of(&sim, 2.0), None);
        }
        let back = c.correct(&local, None).unwrap().0;
        let target = remote_of(&probe, 2.0);
        assert!(mean_error(&back, &target) < 0.2 * mean_error(&pulled, &target));
    }

    #[test]
    fn degenerate_answers_are_not_learnt_and_not_corrected() {
        let mut c = PersonCorrection::new(AdaptParams::default());
        let sim = Similarity2::from_parts(2.0, 0.0, 100.0, 100.0);
        let mut nan = face(&sim, 0.0);
        nan[40].x = f32::NAN;
        assert_eq!(c.learn(&nan, &remote_of(&sim, 0.0), None), Learnt::Degenerate);
        assert_eq!(c.learn(&face(&sim, 0.0), &nan, None), Learnt::Degenerate);
        let point = [Point2::new(5.0, 5.0); 68];
        assert_eq!(c.learn(&point, &point, None), Learnt::Degenerate);
        for _ in 0..20 {
            c.learn(&face(&sim, 0.0), &remote_of(&sim, 0.0), None);
        }
        assert_eq!(c.correct(&point, None), None);
        assert_eq!(c.correct(&nan, None), None);
        assert!(c.correct(&face(&sim, 0.0), None).is_some());
    }
}
