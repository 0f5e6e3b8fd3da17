//! Steadying landmarks over time: the One-Euro filter (Casiez, Roussel and Vogel, CHI 2012), applied in the
//! face's own frame.
//!
//! A landmark track mixes two signals: the head moving (fast, large, shared by every point) and the aligner's
//! frame-to-frame noise (small, different per point). Filtering image coordinates directly smooths both, so
//! the overlay lags behind a turning head. [`LandmarkFilter`] separates them first: a least-squares
//! similarity (translation, rotation, scale) maps a fixed reference shape onto the raw landmarks; the rigid
//! part is filtered with a responsive One-Euro filter (it is estimated from every point at once, so its own
//! noise is small) and the shape in the face's frame (the raw landmarks mapped back through the similarity)
//! with a stronger one. The steadied landmarks are the filtered shape placed by the filtered similarity.
//!
//! The One-Euro filter is a first-order low-pass whose cut-off rises with the signal's speed:
//! `cutoff = min_cutoff + beta * |dx/dt|`. At rest it smooths hard; in motion it lets the movement through
//! with little lag. The placement's filter starts each step from the value its filtered speed predicts, so a
//! face moving at a steady speed is not left behind. Time comes from the caller's timestamps (no clock
//! here).
//!
//! Switching aligners (remote DAN and local KRFWS disagree by a few percent of the eye distance) would make
//! the raw landmarks jump. [`LandmarkFilter::filter`] is told which source answered; on a change it blends the
//! old source into the new one over [`SteadyParams::switch_fade_s`], along a smoothstep (whose speed is zero
//! where it starts and where it ends), instead of passing the jump through:
//! - the shape in the face's frame is crossfaded from the old source's path (its last input continued at its
//!   speed) to the new source's answers, so the new source's offset, and its own frame-to-frame noise, come in
//!   gradually;
//! - the placement takes the new source's answers moved back to where its filtered position and speed were
//!   going, and lets that offset go along the blend (the headset's motion moves the placement's state every
//!   frame, so it blends by offset);
//! - the filters' settings move from the stronger of the old and the new ones to the new source's.
//!
//! So the shown landmarks keep their position and their speed across a switch (a face or an expression moving
//! when the link drops does not stop for a frame). A switch back before the blend has ended starts a new blend
//! from where the output is going: a single missed deadline (one local answer between two remote ones) makes no
//! jump, neither to the local answer nor back (docs/experiments/fallback-adaptation.md, "A blended switch").

use crate::geometry::{Point2, Similarity2};

/// One-Euro filter parameters for one signal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OneEuroParams {
    /// Cut-off frequency at rest, Hz (lower: steadier, more lag at low speed).
    pub min_cutoff_hz: f64,
    /// How fast the cut-off rises with speed (per unit of the signal's speed; higher: less lag in motion).
    pub beta: f64,
    /// Cut-off of the speed estimate, Hz.
    pub d_cutoff_hz: f64,
}

/// One-Euro settings for the answers of one kind of aligner. Units of the shape and translation: eye
/// distances (the reference shape's outer-eye-corner distance is 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FilterParams {
    /// The shape in the face's frame (expressions, the aligner's noise).
    pub shape: OneEuroParams,
    /// Translation (eye distances), log scale and rotation (radians) of the face in the image.
    pub rigid: OneEuroParams,
}

/// The landmark filter's parameters. A noisy aligner needs a strong filter to look steady; a precise one
/// a light filter, or the filter's lag costs more than its noise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SteadyParams {
    /// For a noisy aligner (KRFWS on the headset).
    pub noisy: FilterParams,
    /// For a precise aligner (DAN with the server's refinement: about a third of KRFWS's frame-to-frame
    /// noise on real video).
    pub precise: FilterParams,
    /// After an aligner switch, the blend from the old source to the new one takes this long (seconds, along a
    /// smoothstep); 0 passes the jump through.
    pub switch_fade_s: f64,
    /// A gap between frames longer than this (seconds) restarts the filter (the face was lost or the
    /// stream paused: the old state says nothing about now).
    pub max_gap_s: f64,
}

impl Default for SteadyParams {
    /// Measured on real video and rendered head turns (docs/experiments/steady-landmarks.md).
    fn default() -> Self {
        let one_euro = |min_cutoff_hz, beta, d_cutoff_hz| OneEuroParams {
            min_cutoff_hz,
            beta,
            d_cutoff_hz,
        };
        Self {
            noisy: FilterParams {
                shape: one_euro(1.0, 10.0, 1.0),
                rigid: one_euro(3.0, 2.0, 3.0),
            },
            precise: FilterParams {
                shape: one_euro(3.0, 10.0, 1.0),
                rigid: one_euro(20.0, 5.0, 3.0),
            },
            switch_fade_s: SWITCH_FADE_S,
            max_gap_s: 0.5,
        }
    }
}

impl SteadyParams {
    /// Whether every value is finite and in range (cut-offs > 0, beta >= 0, times >= 0).
    pub fn is_valid(&self) -> bool {
        let ok = |p: &OneEuroParams| {
            p.min_cutoff_hz.is_finite()
                && p.min_cutoff_hz > 0.0
                && p.beta.is_finite()
                && p.beta >= 0.0
                && p.d_cutoff_hz.is_finite()
                && p.d_cutoff_hz > 0.0
        };
        [self.noisy, self.precise]
            .iter()
            .all(|f| ok(&f.shape) && ok(&f.rigid))
            && self.switch_fade_s.is_finite()
            && self.switch_fade_s >= 0.0
            && self.max_gap_s.is_finite()
            && self.max_gap_s > 0.0
    }
}

/// The blend's window after a switch ([`SteadyParams::switch_fade_s`]), measured on the development clips in both
/// directions (docs/experiments/fallback-adaptation.md, "A blended switch").
const SWITCH_FADE_S: f64 = 0.25;

/// How much of a switch's offset is still taken off the new source when `left` of the blend's `total` window
/// remains: a smoothstep from 1 to 0, whose slope is zero at both ends (the blend adds no step in speed where it
/// starts or where it ends).
#[inline]
fn blend_weight(left: f64, total: f64) -> f64 {
    if left <= 0.0 || total <= 0.0 {
        return 0.0;
    }
    let u = (left / total).min(1.0);
    u * u * (3.0 - 2.0 * u)
}

/// `f` applied to each setting of `a` and `b` (cut-offs and speed coefficients, shape and placement).
fn each(a: &FilterParams, b: &FilterParams, f: impl Fn(f64, f64) -> f64) -> FilterParams {
    let one = |a: &OneEuroParams, b: &OneEuroParams| OneEuroParams {
        min_cutoff_hz: f(a.min_cutoff_hz, b.min_cutoff_hz),
        beta: f(a.beta, b.beta),
        d_cutoff_hz: f(a.d_cutoff_hz, b.d_cutoff_hz),
    };
    FilterParams {
        shape: one(&a.shape, &b.shape),
        rigid: one(&a.rigid, &b.rigid),
    }
}

/// `new` moved towards `old` by `w` (0: `new`; 1: `old`), every setting.
fn mix(new: &FilterParams, old: &FilterParams, w: f64) -> FilterParams {
    each(new, old, |n, o| n + w * (o - n))
}

/// Per setting, the one that smooths more (the lower cut-offs and speed coefficient).
fn stronger(a: &FilterParams, b: &FilterParams) -> FilterParams {
    each(a, b, f64::min)
}

/// Smoothing factor of a first-order low-pass with cut-off `cutoff_hz` sampled every `dt` seconds.
#[inline]
fn alpha(cutoff_hz: f64, dt: f64) -> f64 {
    let tau = 1.0 / (2.0 * std::f64::consts::PI * cutoff_hz);
    1.0 / (1.0 + tau / dt)
}

/// One scalar One-Euro filter's state.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct OneEuro {
    x: f64,
    dx: f64,
    /// The last input (where a switch continues the input's path from).
    input: f64,
}

impl OneEuro {
    fn start(x: f64) -> Self {
        Self { x, dx: 0.0, input: x }
    }

    /// Where the input would be after `dt` more seconds on its path: the last input moved at the filtered speed.
    #[inline]
    fn next_input(&self, dt: f64) -> f64 {
        self.input + self.dx * dt
    }

    /// One step: the new raw value `x` after `dt` seconds; returns the filtered value.
    #[inline]
    fn step(&mut self, x: f64, dt: f64, p: &OneEuroParams) -> f64 {
        self.input = x;
        let dx = (x - self.x) / dt;
        self.dx += alpha(p.d_cutoff_hz, dt) * (dx - self.dx);
        let cutoff = p.min_cutoff_hz + p.beta * self.dx.abs();
        self.x += alpha(cutoff, dt) * (x - self.x);
        self.x
    }

    /// [`Self::step`] from the value predicted with the filtered speed: no lag at a constant speed, so a
    /// face crossing the image is not left behind (the placement's filter).
    #[inline]
    fn step_predicted(&mut self, x: f64, dt: f64, p: &OneEuroParams) -> f64 {
        self.input = x;
        let predicted = self.x + self.dx * dt;
        let dx = (x - self.x) / dt;
        self.dx += alpha(p.d_cutoff_hz, dt) * (dx - self.dx);
        let cutoff = p.min_cutoff_hz + p.beta * self.dx.abs();
        self.x = predicted + alpha(cutoff, dt) * (x - predicted);
        self.x
    }
}

/// Who answered a frame: `id` tells sources apart (a change starts the switch fade), `precise` picks
/// [`SteadyParams::precise`] over [`SteadyParams::noisy`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Source {
    /// Any id, one per aligner.
    pub id: u8,
    /// Whether the aligner is a precise one.
    pub precise: bool,
}

/// Which rigid parameters are filtered: translation x, y (eye distances), log scale, rotation (radians).
const RIGID: usize = 4;

/// The state of one face's landmark filter; see the module documentation.
#[derive(Clone, Debug)]
pub struct LandmarkFilter<const N: usize> {
    params: SteadyParams,
    /// The reference shape, centred, outer-eye-corner distance 1.
    reference: [Point2; N],
    state: Option<State<N>>,
}

#[derive(Clone, Debug)]
struct State<const N: usize> {
    timestamp_us: u64,
    source: u8,
    /// The filters' settings on the last frame, and those a blend starts from (the stronger of the settings
    /// in effect when the source changed and the new source's): they move to the new source's along with its
    /// offset.
    last_params: FilterParams,
    blend_from: FilterParams,
    shape: [[OneEuro; 2]; N],
    rigid: [OneEuro; RIGID],
    /// The rigid parameters last seen (angle unwrapping).
    last_angle: f64,
    /// After a switch, the blend's state. The shape in the face's frame: where its input was going (the
    /// position at the switch, per coordinate, and the speed it was moving at), the old source continued, which
    /// the new source's answers are crossfaded with. The placement: how far the new source's parameters sit from
    /// where its filter was going, taken off its inputs as it fades (the headset's motion moves the placement's
    /// state every frame, so it blends by offset, not by position). The time since the switch, and the time the
    /// blend has left of its window.
    blend_shape: [[(f64, f64); 2]; N],
    bias_rigid: [f64; RIGID],
    since_switch_s: f64,
    fade_left_s: f64,
    fade_total_s: f64,
}

/// Why a [`LandmarkFilter`] could not be built.
#[derive(Debug, thiserror::Error, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum SteadyError {
    /// A parameter is not finite or out of range.
    #[error("landmark filter parameters out of range (cut-offs > 0, beta >= 0, times >= 0)")]
    Params,
    /// The reference shape is degenerate (its two eye corners coincide).
    #[error("the landmark filter's reference shape has no eye distance")]
    Reference,
}

impl<const N: usize> LandmarkFilter<N> {
    /// A filter over `N` landmarks. `reference` is any shape of the same face layout (the mean shape); its
    /// points `eyes.0` and `eyes.1` (the outer eye corners) set the unit of distance.
    pub fn new(
        reference: &[Point2; N],
        eyes: (usize, usize),
        params: SteadyParams,
    ) -> Result<Self, SteadyError> {
        if !params.is_valid() {
            return Err(SteadyError::Params);
        }
        let (Some(&l), Some(&r)) = (reference.get(eyes.0), reference.get(eyes.1)) else {
            return Err(SteadyError::Reference);
        };
        let eye = f64::from(l.dist(r));
        if !(eye.is_finite() && eye > 1e-9) {
            return Err(SteadyError::Reference);
        }
        let c = crate::geometry::centroid(reference);
        let mut norm = [Point2::default(); N];
        for (n, p) in norm.iter_mut().zip(reference) {
            *n = Point2::new(
                ((f64::from(p.x) - f64::from(c.x)) / eye) as f32,
                ((f64::from(p.y) - f64::from(c.y)) / eye) as f32,
            );
        }
        Ok(Self {
            params,
            reference: norm,
            state: None,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &SteadyParams {
        &self.params
    }

    /// Forgets the past: the next frame is passed through unchanged.
    pub fn reset(&mut self) {
        self.state = None;
    }

    /// Filters one frame's `raw` landmarks (image pixels) taken at `timestamp_us`, answered by `source`
    /// (any id; a change starts the switch fade). `moved` maps the previous frame's image onto this one's
    /// where the camera itself moved (the headset's motion, known from its poses; identity for a fixed
    /// camera): the filter's state is moved with it first, so the wearer turning their head is followed
    /// without lag and only the face's own motion and the aligner's noise are filtered.
    ///
    /// Returns the steadied landmarks. The first frame, a frame after a gap longer than `max_gap_s`, a
    /// timestamp that does not increase, or a degenerate or non-finite shape restarts the filter and
    /// returns `raw` unchanged.
    pub fn filter(
        &mut self,
        raw: &[Point2; N],
        timestamp_us: u64,
        source: Source,
        moved: &Similarity2,
    ) -> [Point2; N] {
        let params = if source.precise {
            self.params.precise
        } else {
            self.params.noisy
        };
        let Some((sim, face)) = self.in_face_frame(raw) else {
            self.state = None;
            return *raw;
        };
        let scale = sim.scale();
        let rigid_raw = |angle: f64| [sim.tx / scale, sim.ty / scale, scale.ln(), angle];
        let dt = self
            .state
            .as_ref()
            .filter(|s| timestamp_us > s.timestamp_us)
            .map(|s| (timestamp_us - s.timestamp_us) as f64 * 1e-6)
            .filter(|&dt| dt <= self.params.max_gap_s);
        let (Some(dt), Some(st)) = (dt, self.state.as_mut()) else {
            self.state = Some(State::start(
                timestamp_us,
                source.id,
                params,
                &face,
                rigid_raw(sim.angle()),
            ));
            return *raw;
        };
        st.follow_camera(moved);
        let r = rigid_raw(st.unwrap_angle(sim.angle()));
        if source.id != st.source {
            st.switch_to(source.id, &params, &r, dt, self.params.switch_fade_s);
        } else {
            st.fade_left_s = (st.fade_left_s - dt).max(0.0);
            st.since_switch_s += dt;
        }
        let w = blend_weight(st.fade_left_s, st.fade_total_s);
        // The filters' settings move to the new source's with the offset, from the stronger of the old and the
        // new: the precise source's light filter does not let the blend through at once after a noisy one, and a
        // noisy source gets its strong filter from its first answer.
        let p = if w > 0.0 {
            mix(&params, &st.blend_from, w)
        } else {
            params
        };
        st.last_params = p;
        let mut rf = [0.0; RIGID];
        for k in 0..RIGID {
            rf[k] = st.rigid[k].step_predicted(r[k] - w * st.bias_rigid[k], dt, &p.rigid);
        }
        let (s, a) = (rf[2].exp(), rf[3]);
        let placed = Similarity2::from_parts(s, a, rf[0] * s, rf[1] * s);
        let shape = st.step_shape(&face, w, dt, &p);
        let mut out = [Point2::default(); N];
        placed.apply_all(&shape, &mut out);
        st.timestamp_us = timestamp_us;
        out
    }

    /// The similarity placing the reference on `raw`, and `raw` in the face's own frame; `None` for a
    /// degenerate or non-finite shape.
    fn in_face_frame(&self, raw: &[Point2; N]) -> Option<(Similarity2, [Point2; N])> {
        let sim = Similarity2::fit(&self.reference, raw).filter(|s| {
            s.scale() > 1e-9 && s.a.is_finite() && s.b.is_finite() && s.tx.is_finite() && s.ty.is_finite()
        })?;
        let inv = sim.inverse()?;
        let mut face = [Point2::default(); N];
        inv.apply_all(raw, &mut face);
        face.iter()
            .all(|p| p.x.is_finite() && p.y.is_finite())
            .then_some((sim, face))
    }
}

impl<const N: usize> State<N> {
    /// A filter at rest on `face` (the face's frame) placed by `rigid`.
    fn start(
        timestamp_us: u64,
        source: u8,
        params: FilterParams,
        face: &[Point2; N],
        rigid: [f64; RIGID],
    ) -> Self {
        Self {
            timestamp_us,
            source,
            last_params: params,
            blend_from: params,
            shape: std::array::from_fn(|i| {
                [
                    OneEuro::start(f64::from(face[i].x)),
                    OneEuro::start(f64::from(face[i].y)),
                ]
            }),
            rigid: rigid.map(OneEuro::start),
            last_angle: rigid[3],
            blend_shape: [[(0.0, 0.0); 2]; N],
            bias_rigid: [0.0; RIGID],
            since_switch_s: 0.0,
            fade_left_s: 0.0,
            fade_total_s: 0.0,
        }
    }

    /// Moves the filtered placement with the camera's own motion since the last frame.
    fn follow_camera(&mut self, moved: &Similarity2) {
        if *moved == Similarity2::IDENTITY
            || moved.scale() <= 1e-9
            || ![moved.a, moved.b, moved.tx, moved.ty]
                .iter()
                .all(|v| v.is_finite())
        {
            return;
        }
        let (s0, a0) = (self.rigid[2].x.exp(), self.rigid[3].x);
        let prev = Similarity2::from_parts(s0, a0, self.rigid[0].x * s0, self.rigid[1].x * s0);
        let now = moved.after(&prev);
        let s1 = now.scale();
        // Keep the angle continuous: the camera turned by `moved`'s angle.
        let a1 = a0 + moved.angle();
        self.rigid[0].x = now.tx / s1;
        self.rigid[1].x = now.ty / s1;
        self.rigid[2].x = s1.ln();
        self.rigid[3].x = a1;
        self.last_angle = a1;
    }

    /// `angle` unwrapped next to the last one, so the filter never sees a 2π jump (and remembered).
    fn unwrap_angle(&mut self, mut angle: f64) -> f64 {
        while angle - self.last_angle > std::f64::consts::PI {
            angle -= std::f64::consts::TAU;
        }
        while angle - self.last_angle < -std::f64::consts::PI {
            angle += std::f64::consts::TAU;
        }
        self.last_angle = angle;
        angle
    }

    /// A change of source to `source` (whose settings are `params`, whose placement is `r`): the blend starts.
    fn switch_to(&mut self, source: u8, params: &FilterParams, r: &[f64; RIGID], dt: f64, fade_s: f64) {
        self.source = source;
        self.blend_from = stronger(&self.last_params, params);
        // The new source's offset from where the filters' inputs were going: its answers are moved back onto that
        // path, then let go along the blend, so that nothing jumps and nothing stops. A switch during a blend
        // starts a new one from there (the old offset belonged to the source that no longer answers).
        if fade_s > 0.0 {
            for ((b, f), now) in self.bias_rigid.iter_mut().zip(&self.rigid).zip(r) {
                *b = now - (f.x + f.dx * dt);
            }
            for (b, f) in self.blend_shape.iter_mut().zip(&self.shape) {
                *b = [(f[0].next_input(dt), f[0].dx), (f[1].next_input(dt), f[1].dx)];
            }
            self.since_switch_s = 0.0;
            self.fade_left_s = fade_s;
            self.fade_total_s = fade_s;
        }
    }

    /// One step of the shape's filters. Their input: the new source's answer (`face`), crossfaded from the old
    /// source's path (continued at its speed) by `w` along the blend; so the new source's own frame-to-frame
    /// noise also comes in gradually.
    fn step_shape(&mut self, face: &[Point2; N], w: f64, dt: f64, p: &FilterParams) -> [Point2; N] {
        let mut shape = [Point2::default(); N];
        if w > 0.0 {
            let since = self.since_switch_s;
            let blend =
                |(at, speed): (f64, f64), now: f32| w * (at + speed * since) + (1.0 - w) * f64::from(now);
            for ((shown, f), (b, now)) in shape
                .iter_mut()
                .zip(&mut self.shape)
                .zip(self.blend_shape.iter().zip(face))
            {
                *shown = Point2::new(
                    f[0].step(blend(b[0], now.x), dt, &p.shape) as f32,
                    f[1].step(blend(b[1], now.y), dt, &p.shape) as f32,
                );
            }
        } else {
            for ((shown, f), now) in shape.iter_mut().zip(&mut self.shape).zip(face) {
                *shown = Point2::new(
                    f[0].step(f64::from(now.x), dt, &p.shape) as f32,
                    f[1].step(f64::from(now.y), dt, &p.shape) as f32,
                );
            }
        }
        shape
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    const NOISY0: Source = Source {
        id: 0,
        precise: false,
    };
    const NOISY1: Source = Source {
        id: 1,
        precise: false,
    };

    fn reference() -> [Point2; 68] {
        crate::shape::dan_mean_shape()
    }

    fn eye(p: &[Point2; 68]) -> f32 {
        p[36].dist(p[45])
    }

    /// Mean second difference over the points, in eye distances (the issue's `jitter`).
    fn jitter(frames: &[[Point2; 68]]) -> f64 {
        let mut sum = 0.0;
        let mut n = 0;
        for w in frames.windows(3) {
            let e = f64::from(eye(&w[1]));
            for ((a, b), c) in w[0].iter().zip(&w[1]).zip(&w[2]) {
                let mx = (f64::from(a.x) + f64::from(c.x)) / 2.0;
                let my = (f64::from(a.y) + f64::from(c.y)) / 2.0;
                sum += (f64::from(b.x) - mx).hypot(f64::from(b.y) - my) / e;
                n += 1;
            }
        }
        sum / f64::from(n)
    }

    fn placed(s: &Similarity2) -> [Point2; 68] {
        let mut out = [Point2::default(); 68];
        s.apply_all(&reference(), &mut out);
        out
    }

    fn noisy(s: &Similarity2, rng: &mut Rng, sigma_px: f32) -> [Point2; 68] {
        let mut p = placed(s);
        for q in &mut p {
            q.x += sigma_px * rng.normal() as f32;
            q.y += sigma_px * rng.normal() as f32;
        }
        p
    }

    #[test]
    fn first_frame_passes_through_and_a_still_face_is_steadied() {
        let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
        let s = Similarity2::from_parts(2.0, 0.1, 200.0, 150.0);
        let mut rng = Rng::new(7);
        let first = noisy(&s, &mut rng, 1.5);
        assert_eq!(f.filter(&first, 0, NOISY0, &Similarity2::IDENTITY), first);
        let (mut raw, mut out) = (vec![first], vec![first]);
        for k in 1..300u64 {
            let r = noisy(&s, &mut rng, 1.5);
            out.push(f.filter(&r, k * 33_333, NOISY0, &Similarity2::IDENTITY));
            raw.push(r);
        }
        let (jr, jo) = (jitter(&raw[30..]), jitter(&out[30..]));
        assert!(jo < jr / 3.0, "raw jitter {jr}, steadied {jo}");
        // And centred on the truth: mean error of the steadied points below the raw noise.
        let truth = placed(&s);
        let err = |frames: &[[Point2; 68]]| {
            frames
                .iter()
                .flat_map(|o| o.iter().zip(&truth).map(|(a, b)| f64::from(a.dist(*b))))
                .sum::<f64>()
                / (frames.len() as f64 * 68.0)
        };
        let (eo, er) = (err(&out[30..]), err(&raw[30..]));
        assert!(eo < 0.6 * er, "steadied error {eo} px, raw {er} px");
    }

    /// Where the face is at `t` seconds when it crosses the image at `speed` px/s turning `turn` rad/s.
    fn crossing(t: f64, speed: f64, turn: f64) -> Similarity2 {
        Similarity2::from_parts(2.0, turn * t, 100.0 + speed * t, 150.0)
    }

    /// The worst lag (in frames of motion) of the steadied landmarks over 3 s at 30 fps, after the first
    /// half second; `camera`: the motion is the camera's and is passed to the filter.
    fn worst_lag(speed: f64, turn: f64, camera: bool) -> f32 {
        let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
        let mut worst = 0.0f32;
        for k in 0..90u64 {
            let (t, dt) = (k as f64 / 30.0, 1.0 / 30.0);
            let now = crossing(t, speed, turn);
            let moved = if camera && k > 0 {
                now.after(&crossing(t - dt, speed, turn).inverse().unwrap())
            } else {
                Similarity2::IDENTITY
            };
            let out = f.filter(&placed(&now), k * 33_333, NOISY0, &moved);
            if k > 15 {
                let per_frame = (speed / 30.0) as f32;
                let lag = out
                    .iter()
                    .zip(&placed(&now))
                    .map(|(a, b)| a.dist(*b))
                    .fold(0.0f32, f32::max);
                worst = worst.max(lag / per_frame);
            }
        }
        worst
    }

    /// The wearer turning their head: the camera's motion is known and followed without lag.
    #[test]
    fn camera_motion_is_followed_without_lag() {
        let lag = worst_lag(1200.0, 2.0, true);
        assert!(lag < 0.01, "lag {lag} frames");
    }

    /// The face's own motion at a head's speed lags less than a frame.
    #[test]
    fn the_faces_own_motion_lags_less_than_a_frame() {
        for (speed, turn) in [(60.0, 0.0), (240.0, 0.5), (600.0, 1.0)] {
            let lag = worst_lag(speed, turn, false);
            assert!(lag <= 1.0, "{speed} px/s, {turn} rad/s: lag {lag} frames");
        }
    }

    #[test]
    fn a_switch_does_not_jump_and_fades_to_the_new_source() {
        let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
        let s = Similarity2::from_parts(2.0, 0.0, 200.0, 150.0);
        let a = placed(&s);
        // The other source answers 4 px (about 3 % of this face's eye distance) to the right of the mouth.
        let mut b = a;
        for p in &mut b[48..] {
            p.x += 4.0;
        }
        let mut last = a;
        for k in 0..30u64 {
            last = f.filter(&a, k * 33_333, NOISY0, &Similarity2::IDENTITY);
        }
        let mut worst_step = 0.0f32;
        let mut out = last;
        for k in 30..90u64 {
            out = f.filter(&b, k * 33_333, NOISY1, &Similarity2::IDENTITY);
            let step = out
                .iter()
                .zip(&last)
                .map(|(p, q)| p.dist(*q))
                .fold(0.0f32, f32::max);
            worst_step = worst_step.max(step);
            last = out;
        }
        // The raw answers jump 4 px (6 % of this face's eye distance); the steadied ones move less than half
        // of that in any one frame (`holoface stability` measures the jumps on real video).
        assert!(worst_step < 2.0, "a frame moved {worst_step} px at the switch");
        let settled = out.iter().zip(&b).map(|(p, q)| p.dist(*q)).fold(0.0f32, f32::max);
        assert!(settled < 0.1, "still {settled} px off the new source");
    }

    #[test]
    fn a_switch_while_the_face_moves_keeps_its_speed() {
        let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
        // A face crossing the image at 3 px per frame; the second source answers 5 px lower and its mouth 3 px
        // to the right, and is the precise kind (its light filter would pass a placement jump through).
        let at = |k: u64| placed(&Similarity2::from_parts(2.0, 0.0, 150.0 + 3.0 * k as f64, 150.0));
        let other = |k: u64| {
            let mut b = at(k);
            for (i, p) in b.iter_mut().enumerate() {
                p.y += 5.0;
                if i >= 48 {
                    p.x += 3.0;
                }
            }
            b
        };
        let precise = Source { id: 2, precise: true };
        let mut out = Vec::new();
        for k in 0..60u64 {
            let (lm, src) = if k < 30 {
                (at(k), NOISY0)
            } else {
                (other(k), precise)
            };
            out.push(f.filter(&lm, k * 33_333, src, &Similarity2::IDENTITY));
        }
        // The largest change of speed (second difference, any point) around the switch, in pixels per frame.
        let worst = largest_second(&out, 28..40);
        // Stopping for a frame would change the speed by the face's 3 px per frame.
        assert!(
            worst < 1.2,
            "the speed changed by {worst} px per frame at the switch"
        );
        let settled = out[59]
            .iter()
            .zip(&other(59))
            .map(|(p, q)| p.dist(*q))
            .fold(0.0f32, f32::max);
        assert!(settled < 0.5, "still {settled} px off the new source");
    }

    /// The largest second difference (change of speed, px per frame) of any point at frames `range` of `out`.
    fn largest_second(out: &[[Point2; 68]], range: std::ops::Range<usize>) -> f32 {
        range
            .map(|t| {
                (0..68)
                    .map(|i| {
                        let (a, b, c) = (out[t - 2][i], out[t - 1][i], out[t][i]);
                        (a.x + c.x - 2.0 * b.x).hypot(a.y + c.y - 2.0 * b.y)
                    })
                    .fold(0.0f32, f32::max)
            })
            .fold(0.0f32, f32::max)
    }

    /// A switch between two sources whose answers differ by a known offset: the shown landmarks take the
    /// offset over the blend, never faster than the blend's bound, still or moving, in both directions.
    #[test]
    fn a_blended_switch_changes_speed_at_most_by_the_blends_bound() {
        let params = SteadyParams::default();
        // 30 fps; the blend covers n frames; its smoothstep changes speed by at most 6 D / n^2 per frame for an
        // offset D (its second derivative's peak), and moves at most 1.5 D / n per frame.
        let n = params.switch_fade_s * 30.0;
        let precise = Source { id: 2, precise: true };
        for (speed, from, to) in [
            (0.0, NOISY0, precise),
            (0.0, precise, NOISY0),
            (3.0, NOISY0, precise),
            (3.0, precise, NOISY0),
        ] {
            let mut f = LandmarkFilter::new(&reference(), (36, 45), params).unwrap();
            let at = |k: u64| {
                placed(&Similarity2::from_parts(
                    2.0,
                    0.0,
                    150.0 + speed * k as f64,
                    150.0,
                ))
            };
            // The second source: 5 px lower, its mouth 3 px further right (offset D = 5.83 px at the mouth).
            let offset = |i: usize| Point2::new(if i >= 48 { 3.0 } else { 0.0 }, 5.0);
            let d = 34f32.sqrt();
            let mut out = Vec::new();
            for k in 0..90u64 {
                let mut lm = at(k);
                let src = if k < 45 {
                    from
                } else {
                    for (i, p) in lm.iter_mut().enumerate() {
                        p.x += offset(i).x;
                        p.y += offset(i).y;
                    }
                    to
                };
                out.push(f.filter(&lm, k * 33_333, src, &Similarity2::IDENTITY));
            }
            let bound = 6.0 * d / (n * n) as f32;
            let worst = largest_second(&out, 40..90);
            assert!(
                worst <= 1.1 * bound,
                "{speed} px/frame, {from:?} -> {to:?}: speed changed by {worst} px/frame (bound {bound})"
            );
            // Not slower than the blend either: on the new source once it has ended.
            let end = at(89);
            let settled = out[89]
                .iter()
                .zip(&end)
                .enumerate()
                .map(|(i, (p, q))| (p.x - q.x - offset(i).x).hypot(p.y - q.y - offset(i).y))
                .fold(0.0f32, f32::max);
            assert!(
                settled < 0.3,
                "{speed} px/frame: still {settled} px off the new source"
            );
        }
    }

    /// An expression in motion when the link drops (the mouth opening at 0.6 px per frame, the new source's mouth
    /// 4 px off): the mouth keeps its speed across the switch instead of holding for a frame.
    #[test]
    fn an_expression_in_motion_keeps_its_speed_across_a_switch() {
        let precise = Source { id: 2, precise: true };
        let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
        let s = Similarity2::from_parts(2.0, 0.0, 200.0, 150.0);
        let mut out = Vec::new();
        for k in 0..60u64 {
            let mut lm = placed(&s);
            for p in &mut lm[56..60] {
                p.y += 0.6 * k as f32;
            }
            let src = if k < 30 { precise } else { NOISY0 };
            if k >= 30 {
                for p in &mut lm[48..] {
                    p.x += 4.0;
                }
            }
            out.push(f.filter(&lm, k * 33_333, src, &Similarity2::IDENTITY));
        }
        let worst = largest_second(&out, 29..33);
        assert!(
            worst < 0.25,
            "the mouth's speed changed by {worst} px per frame at the switch"
        );
    }

    /// After a switch to a noisy source, its noise comes in along the blend: the first frames move less than
    /// the same source's frames do once the blend is over.
    #[test]
    fn a_noisy_sources_noise_comes_in_gradually() {
        let precise = Source { id: 2, precise: true };
        let (mut first, mut later) = (0.0f32, 0.0f32);
        for seed in 0..20 {
            let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
            let s = Similarity2::from_parts(2.0, 0.0, 200.0, 150.0);
            let mut rng = Rng::new(seed);
            let mut out = Vec::new();
            for k in 0..90u64 {
                let (lm, src) = if k < 30 {
                    (placed(&s), precise)
                } else {
                    (noisy(&s, &mut rng, 1.5), NOISY0)
                };
                out.push(f.filter(&lm, k * 33_333, src, &Similarity2::IDENTITY));
            }
            first += largest_second(&out, 30..33);
            later += largest_second(&out, 70..73);
        }
        assert!(
            first < 0.5 * later,
            "first frames {first} px, later {later} px (20 runs)"
        );
    }

    /// One missed deadline: a single local answer, 4 px off, between two runs of remote ones. The shown
    /// landmarks neither jump to it nor back: they stay on the remote path within a fraction of a pixel.
    #[test]
    fn a_single_missed_deadline_makes_no_jump() {
        let precise = Source { id: 2, precise: true };
        let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
        let at = |k: u64| {
            placed(&Similarity2::from_parts(
                2.0,
                0.01 * k as f64,
                150.0 + 2.0 * k as f64,
                150.0,
            ))
        };
        let mut worst = 0.0f32;
        for k in 0..60u64 {
            let (mut lm, src) = (at(k), if k == 30 { NOISY0 } else { precise });
            if k == 30 {
                for p in &mut lm {
                    p.x += 4.0;
                }
            }
            let out = f.filter(&lm, k * 33_333, src, &Similarity2::IDENTITY);
            if k >= 20 {
                let off = out
                    .iter()
                    .zip(&at(k))
                    .map(|(p, q)| p.dist(*q))
                    .fold(0.0f32, f32::max);
                worst = worst.max(off);
            }
        }
        assert!(
            worst < 0.25,
            "the shown landmarks left the remote path by {worst} px"
        );
    }

    #[test]
    fn gaps_bad_time_and_bad_shapes_restart() {
        let mut f = LandmarkFilter::new(&reference(), (36, 45), SteadyParams::default()).unwrap();
        let s = Similarity2::from_parts(2.0, 0.0, 200.0, 150.0);
        let a = placed(&s);
        let b = placed(&Similarity2::from_parts(2.0, 0.0, 260.0, 150.0));
        f.filter(&a, 0, NOISY0, &Similarity2::IDENTITY);
        assert_eq!(
            f.filter(&b, 2_000_000, NOISY0, &Similarity2::IDENTITY),
            b,
            "a 2 s gap restarts"
        );
        assert_eq!(
            f.filter(&a, 2_000_000, NOISY0, &Similarity2::IDENTITY),
            a,
            "a repeated timestamp restarts"
        );
        let mut nan = a;
        nan[3].x = f32::NAN;
        let out = f.filter(&nan, 2_033_333, NOISY0, &Similarity2::IDENTITY);
        assert!(out[3].x.is_nan(), "a non-finite shape passes through unchanged");
        let collapsed = [Point2::new(5.0, 5.0); 68];
        assert_eq!(
            f.filter(&collapsed, 2_066_666, NOISY0, &Similarity2::IDENTITY),
            collapsed
        );
        let out = f.filter(&a, 2_100_000, NOISY0, &Similarity2::IDENTITY);
        assert!(out.iter().all(|p| p.x.is_finite() && p.y.is_finite()));
    }

    #[test]
    fn bad_parameters_and_references_are_refused() {
        let mut p = SteadyParams::default();
        p.noisy.shape.min_cutoff_hz = 0.0;
        assert_eq!(
            LandmarkFilter::new(&reference(), (36, 45), p).unwrap_err(),
            SteadyError::Params
        );
        p = SteadyParams::default();
        p.precise.rigid.beta = f64::NAN;
        assert_eq!(
            LandmarkFilter::new(&reference(), (36, 45), p).unwrap_err(),
            SteadyError::Params
        );
        assert_eq!(
            LandmarkFilter::new(&reference(), (36, 36), SteadyParams::default()).unwrap_err(),
            SteadyError::Reference
        );
        assert_eq!(
            LandmarkFilter::new(&reference(), (36, 99), SteadyParams::default()).unwrap_err(),
            SteadyError::Reference
        );
    }
}
