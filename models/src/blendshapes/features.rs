//! What the coefficients are read from: the landmarks in the face's own frame (a similarity on seven rigid
//! points onto a template), and the features measured there (lid gaps, brow heights, mouth shape).

use super::*;

/// The subject's side.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Side {
    /// The subject's left: the image's right (iBUG 42-47, 22-26, 54).
    Left,
    /// The subject's right: the image's left (iBUG 36-41, 17-21, 48).
    Right,
}

/// One measurement in the face's frame (eye distances; y down, x toward the subject's left).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Feature {
    LidGap(Side),
    LowerLid(Side),
    Brow(Side),
    InnerBrows,
    OuterBrow(Side),
    NoseWing(Side),
    LipGap,
    ChinX,
    ClosedJawDrop,
    MouthWidth,
    MouthX,
    CornerY(Side),
    CornerOut(Side),
    LipThickness(Side),
    UpperLipThickness,
    LowerLipThickness,
    UpperLipY,
    LowerLipY,
    UpperLipSideY(Side),
    LowerLipSideY(Side),
}

/// The rigid points the face's frame is fitted on: eye corners, nasion, nose wings.
pub(super) const RIGID: [usize; 7] = [36, 39, 42, 45, 27, 31, 35];
/// Their place in the face's frame (eye distance 1 between the outer corners, origin at the nasion, x
/// toward the subject's left, y down): a mean face.
pub(super) const TEMPLATE: [(f64, f64); 7] = [
    (-0.50, 0.04),
    (-0.19, 0.06),
    (0.19, 0.06),
    (0.50, 0.04),
    (0.0, 0.0),
    (-0.13, 0.45),
    (0.13, 0.45),
];

pub(super) type P = (f64, f64);

/// The landmarks in the face's frame: the least-squares affine map of the rigid points onto [`TEMPLATE`],
/// applied to all 68. `None` for a degenerate shape (not finite, collapsed).
pub(super) fn face_frame(lm: &[Point2; 68]) -> Option<[P; 68]> {
    // Solve [x y 1] · M = [u v] in least squares (3x3 normal equations, two right-hand sides).
    let mut ata = [[0.0f64; 3]; 3];
    let mut atb = [[0.0f64; 2]; 3];
    for (k, &i) in RIGID.iter().enumerate() {
        let p = lm[i];
        let row = [f64::from(p.x), f64::from(p.y), 1.0];
        for r in 0..3 {
            for c in 0..3 {
                ata[r][c] += row[r] * row[c];
            }
            atb[r][0] += row[r] * TEMPLATE[k].0;
            atb[r][1] += row[r] * TEMPLATE[k].1;
        }
    }
    let col = |k: usize| crate::linalg::solve_spd(ata, [atb[0][k], atb[1][k], atb[2][k]]);
    let (mu, mv) = (col(0)?, col(1)?);
    let mut out = [(0.0, 0.0); 68];
    for (o, p) in out.iter_mut().zip(lm) {
        let (x, y) = (f64::from(p.x), f64::from(p.y));
        *o = (x * mu[0] + y * mu[1] + mu[2], x * mv[0] + y * mv[1] + mv[2]);
    }
    out.iter()
        .all(|p| p.0.is_finite() && p.1.is_finite())
        .then_some(out)
}

/// Every feature of one frame (in [`Feature`] order of [`FEATURES`]).
pub(super) const FEATURES: [Feature; 26] = [
    Feature::LidGap(Side::Left),
    Feature::LidGap(Side::Right),
    Feature::LowerLid(Side::Left),
    Feature::LowerLid(Side::Right),
    Feature::Brow(Side::Left),
    Feature::Brow(Side::Right),
    Feature::InnerBrows,
    Feature::OuterBrow(Side::Left),
    Feature::OuterBrow(Side::Right),
    Feature::NoseWing(Side::Left),
    Feature::NoseWing(Side::Right),
    Feature::LipGap,
    Feature::ChinX,
    Feature::ClosedJawDrop,
    Feature::MouthWidth,
    Feature::MouthX,
    Feature::CornerY(Side::Left),
    Feature::CornerY(Side::Right),
    Feature::CornerOut(Side::Left),
    Feature::CornerOut(Side::Right),
    Feature::LipThickness(Side::Left),
    Feature::LipThickness(Side::Right),
    Feature::UpperLipThickness,
    Feature::LowerLipThickness,
    Feature::UpperLipY,
    Feature::LowerLipY,
];

/// Where `f` is in [`FEATURES`].
pub(super) fn slot(f: Feature) -> usize {
    FEATURES.iter().position(|&g| g == f).unwrap_or(0)
}

pub(super) type Features = [f64; FEATURES.len()];

/// The features of landmarks in the face's frame. The lip-side features read the lip points nearest the
/// side's corner; `ClosedJawDrop` is the chin's drop less the lips' opening.
pub(super) fn features(n: &[P; 68]) -> Features {
    let y = |i: usize| n[i].1;
    let x = |i: usize| n[i].0;
    let mean_y = |is: &[usize]| is.iter().map(|&i| y(i)).sum::<f64>() / is.len() as f64;
    // The subject's left is the image's right: iBUG's second eye, brow and corner.
    let (eye_l, eye_r) = (([43, 44], [47, 46]), ([37, 38], [41, 40]));
    let lid_gap = |(up, low): ([usize; 2], [usize; 2])| mean_y(&low) - mean_y(&up);
    let gap = mean_y(&[65, 66, 67]) - mean_y(&[61, 62, 63]);
    let width = x(54) - x(48);
    let chin_drop = y(8) - y(33);
    let mut f = [0.0; FEATURES.len()];
    for (k, feat) in FEATURES.iter().enumerate() {
        f[k] = match *feat {
            Feature::LidGap(Side::Left) => lid_gap(eye_l),
            Feature::LidGap(Side::Right) => lid_gap(eye_r),
            Feature::LowerLid(Side::Left) => mean_y(&[46, 47]),
            Feature::LowerLid(Side::Right) => mean_y(&[40, 41]),
            Feature::Brow(Side::Left) => mean_y(&[22, 24, 26]),
            Feature::Brow(Side::Right) => mean_y(&[17, 19, 21]),
            Feature::InnerBrows => mean_y(&[21, 22]),
            Feature::OuterBrow(Side::Left) => y(26),
            Feature::OuterBrow(Side::Right) => y(17),
            Feature::NoseWing(Side::Left) => y(35),
            Feature::NoseWing(Side::Right) => y(31),
            Feature::LipGap => gap,
            Feature::ChinX => x(8),
            Feature::ClosedJawDrop => chin_drop - gap,
            Feature::MouthWidth => width,
            Feature::MouthX => 0.5 * (x(51) + x(57)),
            // Against the upper lip's centre, which the jaw does not move.
            Feature::CornerY(Side::Left) => y(54) - y(51),
            Feature::CornerY(Side::Right) => y(48) - y(51),
            // Half the mouth's width on both sides: a corner pulled out also moves back along the face's
            // curve, which a turned head shows as a sideways shift of one corner and not the other; the
            // width cancels it (and so cannot tell a one-sided stretch from a symmetric one).
            Feature::CornerOut(_) => 0.5 * width,
            Feature::LipThickness(Side::Left) => (y(63) - y(52)) + (y(56) - y(65)),
            Feature::LipThickness(Side::Right) => (y(61) - y(50)) + (y(58) - y(67)),
            Feature::UpperLipThickness => y(62) - y(51),
            Feature::LowerLipThickness => y(57) - y(66),
            Feature::UpperLipY => y(51),
            Feature::LowerLipY => y(57),
            Feature::UpperLipSideY(_) | Feature::LowerLipSideY(_) => 0.0,
        };
    }
    f
}

/// A feature's value, the lip-side ones computed on demand (they are not calibrated separately: they are
/// the lip points next to each corner).
pub(super) fn value(f: &Features, n: &[P; 68], feat: Feature) -> f64 {
    match feat {
        Feature::UpperLipSideY(Side::Left) => n[52].1,
        Feature::UpperLipSideY(Side::Right) => n[50].1,
        Feature::LowerLipSideY(Side::Left) => n[56].1,
        Feature::LowerLipSideY(Side::Right) => n[58].1,
        other => f[slot(other)],
    }
}
