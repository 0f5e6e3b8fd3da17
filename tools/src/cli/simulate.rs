//! `holoface simulate`: synthetic headset sequences generated from the CANDIDE-3 model itself, with known
//! head and headset poses, to measure the geometric parts of the tracker without images:
//!
//! * the fit's pose and weight recovery on noiseless and noisy projections;
//! * the render-time position error with and without Kalman prediction at a capture-to-display delay;
//! * the tracking initialisation error with and without headset-motion compensation (how far the initial
//!   shape is from the truth, in inter-ocular units; an aligner's capture range is a fraction of that);
//! * the anchored objects' error: where the shipped scene's glasses and hat are placed from the fitted head,
//!   against where the true head puts them (millimetres and degrees).

use std::path::PathBuf;

use clap::Args as ClapArgs;
use holoface_models::camera::Intrinsics;
use holoface_models::candide::{FaceModel, FitOptions, FitResult, fit, project_landmarks};
use holoface_models::geometry::Point2;
use holoface_models::kalman::{KalmanParams, PositionPredictor};
use holoface_models::math3::{Mat3, Pose, Quat, Vec3};
use holoface_models::pose::{compensate_headset_motion, world_pose};
use serde_json::json;

use crate::stats::percentile;

/// Arguments of `holoface simulate`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// CANDIDE-3 model.
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
    /// Sequence length in seconds.
    #[arg(long, default_value_t = 20.0)]
    pub seconds: f64,
    /// Frame rate.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// Landmark noise (pixels, standard deviation) for the noisy runs.
    #[arg(long, default_value_t = 1.0)]
    pub noise_px: f64,
    /// Capture-to-display delay the prediction must cover (milliseconds).
    #[arg(long, default_value_t = holoface_runtime::defaults::LOOKAHEAD_MS)]
    pub delay_ms: f64,
    /// Headset yaw amplitude (degrees): how far the wearer turns their head.
    #[arg(long, default_value_t = 20.0)]
    pub headset_yaw_deg: f64,
    /// Seed of the landmark noise.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// JSON report.
    #[arg(long, default_value = "runs/simulate.json")]
    pub out: PathBuf,
}

/// A small deterministic Gaussian source (xorshift + Box–Muller); results depend only on the seed.
struct Noise(u64);

impl Noise {
    fn uniform(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        ((self.0 >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }
    fn gauss(&mut self) -> f64 {
        let (u, v) = (self.uniform(), self.uniform());
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }
}

const K: Intrinsics = Intrinsics::new(600.0, 600.0, 320.0, 240.0);

/// Ground truth of one frame.
struct Truth {
    t: f64,
    head_world: Pose,
    camera: Pose,
    weights: [f64; 5],
}

fn truth_at(t: f64, headset_yaw: f64) -> Truth {
    use std::f64::consts::TAU;
    let s = |f: f64, ph: f64| (TAU * f * t + ph).sin();
    let head_world = Pose {
        rotation: Mat3::rot_y(30f64.to_radians() * s(0.23, 0.0))
            * Mat3::rot_x(10f64.to_radians() * s(0.31, 1.0))
            * Mat3::rot_z(6f64.to_radians() * s(0.17, 2.0)),
        translation: Vec3::new(0.12 * s(0.2, 0.3), 0.05 * s(0.27, 0.7), 0.9 + 0.15 * s(0.13, 1.3)),
    };
    // The wearer looks around (yaw) and sways a little.
    let camera = Pose {
        rotation: Mat3::rot_y(headset_yaw * s(0.35, 0.5)) * Mat3::rot_x(4f64.to_radians() * s(0.5, 0.2)),
        translation: Vec3::new(0.02 * s(0.6, 0.0), 0.01 * s(0.8, 0.4), 0.0),
    };
    let w = |f: f64, ph: f64| (0.3 + 0.3 * s(f, ph)).max(0.0);
    Truth {
        t,
        head_world,
        camera,
        weights: [w(0.4, 0.0), w(0.3, 1.0), -0.2 * s(0.25, 0.5), 0.0, 0.0],
    }
}

fn head_in_camera(tr: &Truth) -> FitResult {
    let p = tr.camera.inverse().after(&tr.head_world);
    FitResult {
        rotation: Quat::from_mat3(&p.rotation),
        translation: p.translation,
        weights: holoface_models::expression::ExpressionWeights(tr.weights),
        rmse_px: 0.0,
        iterations: 0,
        converged: true,
    }
}

/// The model's landmarks for a head pose, with Gaussian pixel noise; `None` when behind the camera.
fn noisy_landmarks(model: &FaceModel, gt: &FitResult, sigma: f64, noise: &mut Noise) -> Option<[Point2; 68]> {
    let mut lm = [Point2::default(); 68];
    if !project_landmarks(model, &K, gt, &mut lm) {
        return None;
    }
    for p in lm.iter_mut() {
        p.x += (sigma * noise.gauss()) as f32;
        p.y += (sigma * noise.gauss()) as f32;
    }
    Some(lm)
}

fn mean(v: &[f64]) -> f64 {
    if v.is_empty() {
        f64::NAN
    } else {
        v.iter().sum::<f64>() / v.len() as f64
    }
}

/// Runs `holoface simulate`.
pub fn run(args: Args) -> anyhow::Result<()> {
    let model = args.candide.load()?;
    let n = (args.seconds * args.fps).round() as usize;
    let dt = 1.0 / args.fps;
    let yaw = args.headset_yaw_deg.to_radians();
    let truths: Vec<Truth> = (0..n).map(|i| truth_at(i as f64 * dt, yaw)).collect();
    let mut noise = Noise(args.seed.max(1));

    let mut report = serde_json::Map::new();
    let mut lines = Vec::new();
    // (c) fit recovery, noiseless and noisy, warm-started frame to frame as in tracking.
    for sigma in [0.0, args.noise_px] {
        fit_recovery(&model, &truths, sigma, &mut noise, &mut lines, &mut report)?;
    }
    render_error(&args, &model, &truths, &mut noise, &mut lines, &mut report)?;
    for (name, e) in anchor_errors(&model, &truths, args.noise_px, &mut noise)? {
        lines.push(format!(
            "anchored {name:<8} position err mean {:.1} mm (p95 {:.1}), rotation err mean {:.2} deg (p95 {:.2})",
            e.position_mm_mean, e.position_mm_p95, e.rotation_deg_mean, e.rotation_deg_p95
        ));
        report.insert(format!("anchored_{name}"), serde_json::to_value(e)?);
    }
    tracking_init(&model, &truths, &mut lines, &mut report);
    for l in &lines {
        crate::say!("{l}");
    }
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    crate::cli::write_atomic(&args.out, serde_json::to_string_pretty(&report)?)?;
    Ok(())
}

/// (c) How well the fit recovers the head from landmarks with noise `sigma` (pixels), warm-started frame to
/// frame as in tracking: a line and a report entry.
fn fit_recovery(
    model: &FaceModel,
    truths: &[Truth],
    sigma: f64,
    noise: &mut Noise,
    lines: &mut Vec<String>,
    report: &mut serde_json::Map<String, serde_json::Value>,
) -> anyhow::Result<()> {
    let (mut rot, mut trans, mut werr, mut rmse) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut prev: Option<FitResult> = None;
    for tr in truths {
        let gt = head_in_camera(tr);
        let Some(lm) = noisy_landmarks(model, &gt, sigma, noise) else {
            continue;
        };
        let opts = if prev.is_some() {
            FitOptions {
                max_iterations: 3,
                ..FitOptions::default()
            }
        } else {
            FitOptions::default()
        };
        let f = fit(model, &K, &lm, prev.as_ref(), &opts)?;
        rot.push(f.rotation.angle_to(gt.rotation).to_degrees());
        trans.push((f.translation - gt.translation).norm() * 1e3);
        werr.push(
            f.weights
                .0
                .iter()
                .zip(&gt.weights.0)
                .map(|(a, b)| (a - b).abs())
                .sum::<f64>()
                / 5.0,
        );
        rmse.push(f.rmse_px);
        prev = Some(f);
    }
    let key = if sigma == 0.0 {
        "fit_noiseless".to_owned()
    } else {
        format!("fit_noise_{sigma}px")
    };
    lines.push(format!(
        "{key:<22} rotation err mean {:.3} deg (p99 {:.3}), translation err mean {:.2} mm (p99 {:.2}), weight err mean {:.3}",
        mean(&rot),
        percentile(&rot, 0.99),
        mean(&trans),
        percentile(&trans, 0.99),
        mean(&werr)
    ));
    report.insert(
        key,
        json!({"frames": rot.len(), "rotation_deg_mean": mean(&rot), "rotation_deg_p99": percentile(&rot, 0.99),
               "translation_mm_mean": mean(&trans), "translation_mm_p99": percentile(&trans, 0.99),
               "weight_abs_err_mean": mean(&werr), "rmse_px_mean": mean(&rmse)}),
    );
    Ok(())
}

/// (b) Render-time position error: the content is drawn `delay` after capture, at the head's true position
/// then; without prediction the last measurement is shown, with prediction the Kalman look-ahead.
fn render_error(
    args: &Args,
    model: &FaceModel,
    truths: &[Truth],
    noise: &mut Noise,
    lines: &mut Vec<String>,
    report: &mut serde_json::Map<String, serde_json::Value>,
) -> anyhow::Result<()> {
    let dt = 1.0 / args.fps;
    let yaw = args.headset_yaw_deg.to_radians();
    let delay = args.delay_ms / 1e3;
    let (mut err_none, mut err_kalman) = (Vec::new(), Vec::new());
    let mut predictor: Option<PositionPredictor> = None;
    let mut prev: Option<FitResult> = None;
    for tr in truths {
        let gt = head_in_camera(tr);
        let Some(lm) = noisy_landmarks(model, &gt, args.noise_px, noise) else {
            continue;
        };
        let f = fit(
            model,
            &K,
            &lm,
            prev.as_ref(),
            &FitOptions {
                max_iterations: 3,
                ..FitOptions::default()
            },
        )?;
        prev = Some(f);
        let measured = world_pose(&f, &tr.camera).position;
        let pr = predictor.get_or_insert_with(|| PositionPredictor::new(measured, KalmanParams::default()));
        pr.step(dt, measured);
        let future = truth_at(tr.t + delay, yaw).head_world.translation;
        if tr.t > 1.0 {
            err_none.push((measured - future).norm() * 1e3);
            err_kalman.push((pr.predict(delay) - future).norm() * 1e3);
        }
    }
    lines.push(format!(
        "render error at {:.0} ms  no prediction mean {:.1} mm (p99 {:.1}); Kalman mean {:.1} mm (p99 {:.1})",
        args.delay_ms,
        mean(&err_none),
        percentile(&err_none, 0.99),
        mean(&err_kalman),
        percentile(&err_kalman, 0.99)
    ));
    report.insert(
        "render_error".into(),
        json!({"delay_ms": args.delay_ms, "no_prediction_mm_mean": mean(&err_none), "no_prediction_mm_p99": percentile(&err_none, 0.99),
               "kalman_mm_mean": mean(&err_kalman), "kalman_mm_p99": percentile(&err_kalman, 0.99)}),
    );

    Ok(())
}

/// How far an anchored object is placed from where the true head puts it.
#[derive(Clone, Copy, Debug, serde::Serialize)]
pub struct AnchorError {
    /// Frames measured.
    pub frames: usize,
    /// Mean distance, millimetres.
    pub position_mm_mean: f64,
    /// Its 95th percentile.
    pub position_mm_p95: f64,
    /// Mean rotation error, degrees.
    pub rotation_deg_mean: f64,
    /// Its 95th percentile.
    pub rotation_deg_p95: f64,
}

/// (d) The shipped scene's objects placed from the head fitted to landmarks with `sigma` px of noise
/// (warm-started, as tracking runs it), against the true head's placement, per object.
fn anchor_errors(
    model: &FaceModel,
    truths: &[Truth],
    sigma: f64,
    noise: &mut Noise,
) -> anyhow::Result<Vec<(String, AnchorError)>> {
    let scene = crate::augment::scene::Scene::parse(crate::augment::scene::DEFAULT_SCENE)?;
    let mut errs = vec![(Vec::new(), Vec::new()); scene.objects.len()];
    let mut prev: Option<FitResult> = None;
    for tr in truths {
        let gt = head_in_camera(tr);
        let Some(lm) = noisy_landmarks(model, &gt, sigma, noise) else {
            continue;
        };
        let opts = FitOptions {
            max_iterations: if prev.is_some() {
                3
            } else {
                FitOptions::default().max_iterations
            },
            ..FitOptions::default()
        };
        let f = fit(model, &K, &lm, prev.as_ref(), &opts)?;
        prev = Some(f);
        let w = world_pose(&f, &tr.camera);
        let head = holoface_models::anchor::head_pose(w.position, w.rotation);
        for (o, (pos, rot)) in scene.objects.iter().zip(errs.iter_mut()) {
            let got = o.anchor.world_from_object(model, &head);
            let want = o.anchor.world_from_object(model, &tr.head_world);
            pos.push((got.translation - want.translation).norm() * 1e3);
            rot.push((got.rotation.transpose() * want.rotation).angle().to_degrees());
        }
    }
    Ok(scene
        .objects
        .iter()
        .zip(errs)
        .map(|(o, (pos, rot))| {
            let e = AnchorError {
                frames: pos.len(),
                position_mm_mean: mean(&pos),
                position_mm_p95: percentile(&pos, 0.95),
                rotation_deg_mean: mean(&rot),
                rotation_deg_p95: percentile(&rot, 0.95),
            };
            (o.name.clone(), e)
        })
        .collect())
}

/// (a) Tracking initialisation: last frame's landmarks as they are, or moved with the headset.
fn tracking_init(
    model: &FaceModel,
    truths: &[Truth],
    lines: &mut Vec<String>,
    report: &mut serde_json::Map<String, serde_json::Value>,
) {
    let (mut init_plain, mut init_comp) = (Vec::new(), Vec::new());
    for pair in truths.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        let (ga, gb) = (head_in_camera(a), head_in_camera(b));
        let (mut la, mut lb) = ([Point2::default(); 68], [Point2::default(); 68]);
        if !project_landmarks(model, &K, &ga, &mut la) || !project_landmarks(model, &K, &gb, &mut lb) {
            continue;
        }
        let iod = f64::from(lb[36].dist(lb[45]));
        let err = |init: &[Point2; 68]| {
            holoface_models::candide::CORRESPONDENCES
                .iter()
                .map(|&(i, _)| f64::from(init[i].dist(lb[i])))
                .sum::<f64>()
                / holoface_models::candide::CORRESPONDENCES.len() as f64
                / iod
        };
        let mut comp = la;
        compensate_headset_motion(
            &la,
            &K,
            &a.camera,
            &K,
            &b.camera,
            ga.translation.norm(),
            &mut comp,
        );
        init_plain.push(err(&la));
        init_comp.push(err(&comp));
    }
    let over = |v: &[f64], t: f64| v.iter().filter(|&&e| e > t).count() as f64 / v.len().max(1) as f64;
    lines.push(format!(
        "init error (IOD units)  plain mean {:.3} p99 {:.3}, >0.25: {:.1}%; compensated mean {:.3} p99 {:.3}, >0.25: {:.1}%",
        mean(&init_plain),
        percentile(&init_plain, 0.99),
        100.0 * over(&init_plain, 0.25),
        mean(&init_comp),
        percentile(&init_comp, 0.99),
        100.0 * over(&init_comp, 0.25)
    ));
    report.insert(
        "tracking_init".into(),
        json!({"plain_mean": mean(&init_plain), "plain_p99": percentile(&init_plain, 0.99), "plain_over_0_25": over(&init_plain, 0.25),
               "compensated_mean": mean(&init_comp), "compensated_p99": percentile(&init_comp, 0.99),
               "compensated_over_0_25": over(&init_comp, 0.25)}),
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bounds on the shipped scene's anchors over `simulate`'s default sequence (20 s, 1 px of landmark
    /// noise, seed 1), from the first measurement (glasses 14.9 mm and hat 15.9 mm p95, 3.46 degrees p95;
    /// seeds 2 and 3 gave up to 17.0 mm and 3.30 degrees) with about a quarter of headroom.
    const ANCHOR_P95_MM: f64 = 20.0;
    const ANCHOR_P95_DEG: f64 = 4.5;

    #[test]
    fn anchored_objects_land_where_the_true_head_puts_them() {
        let path = holoface_runtime::assets::AssetPaths::default().candide;
        let model = holoface_runtime::assets::load_face_model(&path).unwrap_or_else(|e| {
            panic!(
                "CANDIDE-3 ({}): {e}; `make test` sets HOLOFACE_CANDIDE",
                path.display()
            )
        });
        let truths: Vec<Truth> = (0..600)
            .map(|i| truth_at(f64::from(i) / 30.0, 20f64.to_radians()))
            .collect();
        // Without noise the fit recovers the head, and the anchors are exact but for the fit's tolerance.
        for (name, e) in anchor_errors(&model, &truths, 0.0, &mut Noise(1)).unwrap() {
            assert_eq!(e.frames, 600);
            assert!(
                e.position_mm_p95 < 0.5 && e.rotation_deg_p95 < 0.1,
                "{name} noiseless: {e:?}"
            );
        }
        let errs = anchor_errors(&model, &truths, 1.0, &mut Noise(1)).unwrap();
        assert_eq!(
            errs.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(),
            ["glasses", "top-hat"]
        );
        for (name, e) in errs {
            assert!(
                e.position_mm_p95 <= ANCHOR_P95_MM && e.rotation_deg_p95 <= ANCHOR_P95_DEG,
                "{name} with 1 px of noise: {e:?} (bounds {ANCHOR_P95_MM} mm, {ANCHOR_P95_DEG} deg)"
            );
        }
    }
}
