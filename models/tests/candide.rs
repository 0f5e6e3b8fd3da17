//! CANDIDE-3 parsing and fitting against the real model file (`$HOLOFACE_DATA/candide3/candide3.wfm`).
#![allow(clippy::unwrap_used)]

use std::path::PathBuf;

use holoface_models::camera::Intrinsics;
use holoface_models::candide::{
    CORRESPONDENCES, FITTED_UNITS, FaceModel, FitOptions, FitResult, Wfm, fit, project_landmarks,
};
use holoface_models::expression::ExpressionWeights;
use holoface_models::geometry::Point2;
use holoface_models::math3::{Quat, Vec3};

fn data() -> PathBuf {
    std::env::var_os("HOLOFACE_DATA").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
        PathBuf::from,
    )
}

fn wfm_text() -> String {
    let p = data().join("candide3/candide3.wfm");
    let bytes = std::fs::read(&p).unwrap_or_else(|e| panic!("{}: {e} (set HOLOFACE_DATA)", p.display()));
    String::from_utf8_lossy(&bytes).into_owned()
}

fn model() -> FaceModel {
    FaceModel::from_wfm(&Wfm::parse(&wfm_text()).unwrap()).unwrap()
}

const K: Intrinsics = Intrinsics::new(600.0, 600.0, 320.0, 240.0);

#[test]
fn wfm_parses_with_the_documented_counts() {
    let w = Wfm::parse(&wfm_text()).unwrap();
    assert_eq!(w.vertices.len(), 113);
    assert_eq!(w.faces.len(), 184);
    assert_eq!(w.animation_units.len(), 65);
    for name in FITTED_UNITS {
        assert!(w.animation_units.iter().any(|(n, _)| n == name), "{name}");
    }
}

#[test]
fn wfm_agrees_with_holoface_meshes() {
    // HoloFace's candide.obj is the wfm with y and z negated (its x carries a few 1e-3 of round-off);
    // blendshape1.obj is AUV11 (jaw drop) applied.
    let w = Wfm::parse(&wfm_text()).unwrap();
    let read_obj = |name: &str| -> Vec<[f64; 3]> {
        std::fs::read_to_string(data().join("candide3/holoface-meshes").join(name))
            .unwrap()
            .lines()
            .filter_map(|l| l.strip_prefix("v "))
            .map(|l| {
                let v: Vec<f64> = l.split_whitespace().map(|t| t.parse().unwrap()).collect();
                [v[0], v[1], v[2]]
            })
            .collect()
    };
    let neutral = read_obj("candide.obj");
    assert_eq!(neutral.len(), 113);
    for (a, b) in w.vertices.iter().zip(&neutral) {
        assert!(
            (a[0] - b[0]).abs() < 5e-3 && (a[1] + b[1]).abs() < 5e-3 && (a[2] + b[2]).abs() < 5e-3,
            "{a:?} vs {b:?}"
        );
    }
    let jaw = read_obj("blendshape1.obj");
    let (_, disp) = w.animation_units.iter().find(|(n, _)| n == "AUV11").unwrap();
    for &(v, d) in disp {
        let delta = [
            jaw[v][0] - neutral[v][0],
            -(jaw[v][1] - neutral[v][1]),
            -(jaw[v][2] - neutral[v][2]),
        ];
        for k in 0..3 {
            assert!((delta[k] - d[k]).abs() < 5e-3, "vertex {v}: {delta:?} vs {d:?}");
        }
    }
}

#[test]
fn correspondences_are_mirror_consistent() {
    // A left/right landmark pair must map to vertices mirrored in x.
    let w = Wfm::parse(&wfm_text()).unwrap();
    let mirror = holoface_models::shape::MIRROR68;
    for &(i, v) in &CORRESPONDENCES {
        let Some(&(_, vm)) = CORRESPONDENCES.iter().find(|(j, _)| *j == mirror[i]) else {
            continue;
        };
        let (a, b) = (w.vertices[v], w.vertices[vm]);
        assert!(
            (a[0] + b[0]).abs() < 1e-3 && (a[1] - b[1]).abs() < 1e-3,
            "iBUG {i} vertex {v} vs {vm}"
        );
    }
    // Image-left landmarks (smaller iBUG x in a frontal face) sit on the CANDIDE side with x < 0.
    for (i, v) in [(36, 53), (17, 48), (48, 64)] {
        assert!(CORRESPONDENCES.contains(&(i, v)) && w.vertices[v][0] < 0.0);
    }
}

fn truth(yaw: f64, pitch: f64, roll: f64, t: Vec3, w: [f64; 5]) -> FitResult {
    let q = Quat::from_axis_angle(Vec3::new(0.0, yaw, 0.0))
        * Quat::from_axis_angle(Vec3::new(pitch, 0.0, 0.0))
        * Quat::from_axis_angle(Vec3::new(0.0, 0.0, roll));
    FitResult {
        rotation: q,
        translation: t,
        weights: ExpressionWeights(w),
        rmse_px: 0.0,
        iterations: 0,
        converged: true,
    }
}

#[test]
fn fit_recovers_pose_and_weights_from_noiseless_projections() {
    let m = model();
    let cases = [
        truth(0.0, 0.0, 0.0, Vec3::new(0.0, 0.0, 0.8), [0.0; 5]),
        truth(
            0.4,
            -0.2,
            0.1,
            Vec3::new(0.1, -0.05, 1.2),
            [0.5, 0.3, -0.3, 0.1, 0.2],
        ),
        truth(
            -0.6,
            0.25,
            -0.3,
            Vec3::new(-0.2, 0.1, 1.6),
            [0.2, 0.6, 0.2, 0.0, 0.0],
        ),
    ];
    for gt in cases {
        let mut lm = [Point2::default(); 68];
        assert!(project_landmarks(&m, &K, &gt, &mut lm));
        let opts = FitOptions {
            max_iterations: 50,
            weight_prior: 0.0,
            tolerance: 1e-12,
        };
        let f = fit(&m, &K, &lm, None, &opts).unwrap();
        let angle = f.rotation.angle_to(gt.rotation).to_degrees();
        let dt = (f.translation - gt.translation).norm();
        assert!(angle < 2.0, "rotation error {angle} deg");
        assert!(dt < 0.01, "translation error {dt} m");
        assert!(f.rmse_px < 0.05, "rmse {}", f.rmse_px);
        for (a, b) in f.weights.0.iter().zip(gt.weights.0) {
            assert!(
                (a - b).abs() < 0.05,
                "weights {:?} vs {:?}",
                f.weights,
                gt.weights
            );
        }
    }
}

#[test]
fn warm_start_converges_in_few_iterations_and_bad_input_is_an_error() {
    let m = model();
    let gt = truth(0.2, 0.1, 0.0, Vec3::new(0.0, 0.0, 1.0), [0.3, 0.0, 0.0, 0.0, 0.0]);
    let mut lm = [Point2::default(); 68];
    project_landmarks(&m, &K, &gt, &mut lm);
    let mut start = gt;
    start.translation = start.translation + Vec3::new(0.005, 0.0, 0.0);
    let f = fit(
        &m,
        &K,
        &lm,
        Some(&start),
        &FitOptions {
            max_iterations: 3,
            ..FitOptions::default()
        },
    )
    .unwrap();
    assert!(f.rmse_px < 0.5, "{f:?}");
    assert!(fit(&m, &K, &lm[..40], None, &FitOptions::default()).is_err());
    let bad = Intrinsics { fx: 0.0, ..K };
    assert!(fit(&m, &bad, &lm, None, &FitOptions::default()).is_err());
}

#[test]
fn wfm_parser_rejects_garbage() {
    assert!(Wfm::parse("").is_err());
    assert!(Wfm::parse("# VERTEX LIST:\n2\n0 0 0\n").is_err());
    assert!(Wfm::parse("# VERTEX LIST:\n1\n0 0 x\n").is_err());
    let bad_face = "# VERTEX LIST:\n1\n0 0 0\n# FACE LIST:\n1\n0 0 5\n# ANIMATION UNITS LIST:\n0\n";
    assert!(Wfm::parse(bad_face).is_err());
}
