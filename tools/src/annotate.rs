//! Annotated frames: the tracker's answer drawn over the camera image (landmarks, the fitted CANDIDE-3
//! mesh, the head's pose axes, who answered). `holoface track --annotate DIR` writes one PNG per frame.

use holoface_models::camera::Intrinsics;
use holoface_models::candide::FaceModel;
use holoface_models::image::GrayImage;
use holoface_models::math3::Vec3;

use holoface_harness::plot::Canvas;
use holoface_runtime::align::AnsweredBy;
use holoface_runtime::session::{FaceResult, NoFaceReason};

/// Length of the drawn pose axes, metres.
const AXIS_M: f64 = 0.05;

/// Colour and label of the aligner that answered (`None`: no face).
pub fn aligner_style(by: Option<AnsweredBy>) -> ([u8; 3], &'static str) {
    match by {
        Some(AnsweredBy::RemoteDan) => ([44, 160, 44], "remote DAN"),
        Some(AnsweredBy::Krfws) => ([255, 127, 14], "local KRFWS"),
        Some(AnsweredBy::LocalDan) => ([31, 119, 180], "local DAN"),
        None => ([214, 39, 40], "no face"),
    }
}

/// Draws one frame: each tracked face's fitted CANDIDE-3 mesh, landmarks, pose axes and id (coloured by
/// the aligner that answered it), and a header line (the face's depth and world position with one face; the
/// count with several; the reason with none).
pub fn annotate(
    image: &GrayImage,
    index: usize,
    faces: &[FaceResult],
    no_face: Option<NoFaceReason>,
    model: &FaceModel,
    k: &Intrinsics,
) -> Canvas {
    let (w, h) = (image.width(), image.height());
    let mut cv = Canvas::new(w, h);
    cv.blit_gray(0, 0, image.as_bytes(), w, h, 1);
    for f in faces {
        draw_face(&mut cv, f, model, k);
        let (colour, _) = aligner_style(Some(f.answered_by));
        if let Some(b) = holoface_models::geometry::Rect::bounding(&f.landmarks) {
            cv.text(b.x0 as i64, b.y0 as i64 - 14, &format!("#{}", f.id), colour);
        }
    }
    match (faces, no_face) {
        ([f], _) => {
            let u = f;
            let (colour, label) = aligner_style(Some(u.answered_by));
            let t = u.world.position;
            cv.text(
                6,
                6,
                &format!("frame {index} {label} z {:.2} m", u.fit.translation.z),
                colour,
            );
            cv.text(
                6,
                22,
                &format!("world {:+.2} {:+.2} {:+.2}", t.x, t.y, t.z),
                colour,
            );
            blendshape_bars(&mut cv, &u.blendshapes, 40);
        }
        ([], reason) => {
            let (colour, _) = aligner_style(None);
            let why = serde_json::to_value(reason.unwrap_or(NoFaceReason::NotDetected))
                .ok()
                .and_then(|v| v.as_str().map(str::to_owned))
                .unwrap_or_default()
                .replace('_', " ");
            cv.text(6, 6, &format!("frame {index} no face {why}"), colour);
        }
        (many, _) => {
            let (colour, _) = aligner_style(Some(many[0].answered_by));
            cv.text(6, 6, &format!("frame {index} {} faces", many.len()), colour);
        }
    }
    cv
}

/// The six strongest blendshape coefficients (above 0.05) as labelled bars, one per line from `y0`: the full
/// bar (coefficient 1) is 100 px.
fn blendshape_bars(cv: &mut Canvas, b: &holoface_runtime::Blendshapes, y0: i64) {
    let mut top: Vec<_> = b.iter().filter(|&(_, v)| v > 0.05).collect();
    top.sort_by(|a, b| b.1.total_cmp(&a.1));
    for (row, (shape, v)) in top.into_iter().take(6).enumerate() {
        let y = y0 + 14 * row as i64;
        cv.text(6, y, shape.arkit_name(), [255, 255, 255]);
        let x0 = 6.0 + 8.0 * 20.0;
        cv.line(
            (x0, y as f64 + 5.0),
            (x0 + 100.0 * f64::from(v), y as f64 + 5.0),
            [90, 200, 255],
            4,
        );
    }
}

fn draw_face(cv: &mut Canvas, u: &FaceResult, model: &FaceModel, k: &Intrinsics) {
    let (colour, _) = aligner_style(Some(u.answered_by));
    // Mesh: every triangle edge whose ends are in front of the camera.
    let verts: Vec<_> = model
        .mesh_in_camera(&u.fit)
        .into_iter()
        .map(|p| k.project(p))
        .collect();
    for tri in &model.faces {
        for (a, b) in [(tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])] {
            if let (Some(Some(p)), Some(Some(q))) = (verts.get(a), verts.get(b)) {
                cv.line(
                    (f64::from(p.x), f64::from(p.y)),
                    (f64::from(q.x), f64::from(q.y)),
                    [200, 190, 90],
                    1,
                );
            }
        }
    }
    let first = match u.landmark_set {
        holoface_runtime::align::LandmarkSet::Ibug68 => 0,
        holoface_runtime::align::LandmarkSet::Inner51 => 17,
    };
    for p in &u.landmarks[first..] {
        cv.dot(f64::from(p.x), f64::from(p.y), 1, colour);
    }
    // Pose axes from the head origin: x red, y green, z blue.
    let r = u.fit.rotation.to_mat3();
    let o = u.fit.translation;
    if let Some(po) = k.project(o) {
        let axes = [
            (Vec3::new(AXIS_M, 0.0, 0.0), [230, 30, 30]),
            (Vec3::new(0.0, AXIS_M, 0.0), [30, 200, 30]),
            (Vec3::new(0.0, 0.0, AXIS_M), [40, 80, 255]),
        ];
        for (axis, c) in axes {
            if let Some(pa) = k.project(o + r * axis) {
                cv.line(
                    (f64::from(po.x), f64::from(po.y)),
                    (f64::from(pa.x), f64::from(pa.y)),
                    c,
                    3,
                );
            }
        }
    }
}
