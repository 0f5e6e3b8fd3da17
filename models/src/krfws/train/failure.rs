//! The failure detector's training data (perturbed fits of every training face through the trained cascade)
//! and its regression (see [`super`]: "Failure detector").

use super::ridge::ridge_dense;
use super::*;

pub(super) fn empty_failure() -> FailureModel {
    FailureModel {
        weights: vec![0.0; FAILURE_DIM],
        intercept: 0.0,
        threshold: f32::INFINITY,
    }
}

/// Kind of a perturbed fit for the failure detector.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FitKind {
    /// Small jitter of the box initialisation.
    Small,
    /// DAN σ perturbation.
    Full,
    /// Twice DAN σ: mostly gross failures.
    Gross,
    /// Box moved off the face onto background: a non-face patch.
    NonFace,
}

/// One perturbed fit.
#[derive(Clone, Debug)]
pub struct PerturbedFit {
    /// Index of the face.
    pub face: usize,
    /// How the start shape was made.
    pub kind: FitKind,
    /// Failure score of the fit.
    pub score: f32,
    /// NME49 of the fit against the ground truth.
    pub nme: f64,
}

/// Start shape of fit `j` of a face (kinds cycle Small, Full, Gross, NonFace).
pub fn perturbed_init(
    model: &Krfws,
    face: &TrainFace,
    j: usize,
    rng: &mut Rng,
) -> (FitKind, [Point2; N_POINTS]) {
    let bbox = gt_box(&face.landmarks);
    let base = model.init_from_box(&bbox);
    match j % 4 {
        0 => (FitKind::Small, perturb(&base, SMALL_PERTURBATION, rng)),
        1 => (FitKind::Full, perturb(&base, DAN_PERTURBATION, rng)),
        2 => {
            let gross = Perturbation::new(0.4, 40.0, 0.5);
            (FitKind::Gross, perturb(&base, gross, rng))
        }
        _ => {
            let ang = rng.uniform() * std::f64::consts::TAU;
            let dist = 0.8 + 0.7 * rng.uniform();
            let (dx, dy) = (
                (ang.cos() * dist * f64::from(bbox.width())) as f32,
                (ang.sin() * dist * f64::from(bbox.height())) as f32,
            );
            (FitKind::NonFace, base.map(|p| Point2::new(p.x + dx, p.y + dy)))
        }
    }
}

/// Runs `per_face` perturbed fits per face through `model`, keeping the last stage's HOG when `keep_hog`.
pub fn perturbed_fits(
    model: &Krfws,
    faces: &[TrainFace],
    per_face: usize,
    seed: u64,
    threads: usize,
    keep_hog: bool,
    progress: &dyn Progress,
) -> (Vec<PerturbedFit>, Vec<f32>) {
    let mut rows: Vec<(PerturbedFit, Vec<f32>)> = (0..faces.len() * per_face)
        .map(|i| {
            (
                PerturbedFit {
                    face: i / per_face.max(1),
                    kind: FitKind::Small,
                    score: 0.0,
                    nme: 0.0,
                },
                Vec::new(),
            )
        })
        .collect();
    progress.begin("perturbed fits", rows.len() as u64);
    par_for_each(&mut rows, threads, KrfwsScratch::new, |scratch, i, row| {
        let f = i / per_face.max(1);
        let j = i % per_face.max(1);
        let face = &faces[f];
        let mut rng = Rng::stream(seed, &[7, f as u64, j as u64]);
        let (kind, init) = perturbed_init(model, face, j, &mut rng);
        let mut out = [Point2::default(); N_POINTS];
        let score = model.align(&face.image.view(), &init, scratch, &mut out);
        row.0 = PerturbedFit {
            face: f,
            kind,
            score,
            nme: nme49_inner(&out, &face.landmarks),
        };
        if keep_hog {
            row.1 = scratch.last_hog().to_vec();
        }
        if i % 64 == 0 {
            progress.inc(64);
        }
    });
    progress.end("");
    let mut fits = Vec::with_capacity(rows.len());
    let mut hog = Vec::with_capacity(if keep_hog { rows.len() * FAILURE_DIM } else { 0 });
    for (f, h) in rows {
        fits.push(f);
        hog.extend_from_slice(&h);
    }
    (fits, hog)
}

/// Fits the failure detector on perturbed fits of `faces` (mirrors added) and installs it in `model`
/// (threshold left at +∞; choose it on validation data). Returns the number of fits used.
pub fn train_failure(
    model: &mut Krfws,
    faces: &[TrainFace],
    cfg: &TrainConfig,
    progress: &dyn Progress,
) -> usize {
    let mut all: Vec<TrainFace> = Vec::with_capacity(faces.len() * 2);
    for f in faces {
        all.push(f.clone());
        all.push(mirror_face(f));
    }
    let (fits, hog) = perturbed_fits(
        model,
        &all,
        cfg.failure_fits.max(4),
        cfg.seed ^ 0xFA11,
        cfg.threads,
        true,
        progress,
    );
    let y: Vec<f64> = fits
        .iter()
        .map(|f| f.nme.min(f64::from(FAILURE_TARGET_CAP)))
        .collect();
    progress.begin("failure detector", 1);
    let (w, b) = ridge_dense(&hog, &y, FAILURE_DIM, cfg.failure_ridge);
    progress.inc(1);
    progress.end("");
    model.set_failure(FailureModel {
        weights: w,
        intercept: b,
        threshold: f32::INFINITY,
    });
    fits.len()
}
