//! The augmentation's pictures and effects, on the CANDIDE-3 head of the data folder (as the tracker uses it).

use super::*;
use holoface_models::blendshapes::Blendshape;
use holoface_models::math3::Mat3;

/// The golden image: tools/tests/golden/augmented.png, rewritten by `HOLOFACE_BLESS=1`.
const GOLDEN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/golden/augmented.png");
/// The golden test's tolerance: pixels whose channels differ by more than this from the golden image ...
const GOLDEN_PIXEL_TOLERANCE: u8 = 24;
/// ... may be at most this share of the image (rounding at triangle edges, another libm's sin/cos).
const GOLDEN_MAX_DIFFERENT: f64 = 0.002;

const K: Intrinsics = Intrinsics::new(300.0, 300.0, 160.0, 120.0);

fn model() -> FaceModel {
    let path = holoface_runtime::assets::AssetPaths::default().candide;
    holoface_runtime::assets::load_face_model(&path).unwrap_or_else(|e| {
        panic!(
            "CANDIDE-3 ({}): {e}; `make test` sets HOLOFACE_CANDIDE",
            path.display()
        )
    })
}

/// A head 75 cm in front of a camera at the world's origin, turned 25 degrees to the side and 8 down.
fn head() -> Pose {
    Pose {
        rotation: Mat3::rot_y(25f64.to_radians()) * Mat3::rot_x(-8f64.to_radians()),
        translation: Vec3::new(0.0, 0.05, 0.75),
    }
}

fn face(jaw: f32, smile: bool) -> FaceSnapshot {
    let mut b = Blendshapes::default();
    b.0[Blendshape::ALL
        .iter()
        .position(|&s| s == Blendshape::JawOpen)
        .unwrap()] = jaw;
    FaceSnapshot {
        id: 1,
        world_from_head: head(),
        weights: ExpressionWeights([0.4, 0.0, 0.0, 0.0, 0.0]),
        blendshapes: b,
        attributes: Attributes {
            smile,
            brows_raised: false,
            mouth_open: jaw > 0.5,
        },
    }
}

/// A grey gradient, as a camera image under the objects.
fn background() -> Canvas {
    let mut c = Canvas::new(320, 240);
    for (i, px) in c.rgb_mut().chunks_mut(3).enumerate() {
        let v = 60 + (i % 320 / 4) as u8;
        px.copy_from_slice(&[v, v, v]);
    }
    c
}

fn augmenter(delay_ms: f64) -> Augmenter {
    Augmenter::new(Scene::parse(scene::DEFAULT_SCENE).unwrap(), model(), delay_ms)
}

#[test]
fn the_shipped_scene_renders_as_the_golden_image() {
    let mut a = augmenter(0.0);
    // Half a second of an open, smiling mouth: sparks in flight, rose lenses.
    for i in 0..16u64 {
        a.update(i * 33_333, vec![face(0.8, true)]);
    }
    let mut c = background();
    a.draw(&mut c, &K, &Pose::IDENTITY);
    if std::env::var_os("HOLOFACE_BLESS").is_some() {
        std::fs::create_dir_all(std::path::Path::new(GOLDEN).parent().unwrap()).unwrap();
        std::fs::write(GOLDEN, c.to_png()).unwrap();
    }
    let golden = image::open(GOLDEN).expect("the golden image").to_rgb8();
    assert_eq!((golden.width(), golden.height()), (320, 240));
    let different = golden
        .as_raw()
        .chunks(3)
        .zip(c.rgb().chunks(3))
        .filter(|(g, r)| {
            g.iter()
                .zip(r.iter())
                .any(|(a, b)| a.abs_diff(*b) > GOLDEN_PIXEL_TOLERANCE)
        })
        .count();
    let share = different as f64 / (320.0 * 240.0);
    assert!(
        share <= GOLDEN_MAX_DIFFERENT,
        "{different} pixels ({:.3} %) differ from {GOLDEN} by more than {GOLDEN_PIXEL_TOLERANCE}",
        share * 100.0
    );
    // And the picture is not the background: the objects cover a share of it.
    let changed = background()
        .rgb()
        .chunks(3)
        .zip(c.rgb().chunks(3))
        .filter(|(a, b)| a != b)
        .count();
    assert!(changed > 320 * 240 / 20, "{changed} pixels drawn");
}

/// The face of `face(jaw, smile)` moved `x` metres along the world's x.
fn moved(x: f64, jaw: f32) -> FaceSnapshot {
    let mut f = face(jaw, false);
    f.world_from_head.translation.x += x;
    f
}

#[test]
fn each_frame_shows_the_face_captured_the_display_delay_earlier() {
    let mut a = augmenter(100.0);
    assert_eq!(a.delay_ms(), 100.0);
    let glasses_x = |a: &Augmenter| a.anchors().first().map(|(_, p)| p[0].translation.x);
    // Frames 40 ms apart, the face 1 cm further each time.
    let mut shown = Vec::new();
    for i in 0..8u64 {
        a.update(i * 40_000, vec![moved(0.01 * i as f64, 0.0)]);
        shown.push(glasses_x(&a));
    }
    let at = |i: u64| Some(a.place(0, &moved(0.01 * i as f64, 0.0)).translation.x);
    // Nothing for the first 100 ms; then frame t shows the latest frame captured at or before t - 100 ms.
    assert_eq!(&shown[..3], &[None, None, None]);
    assert_eq!(shown[3], at(0), "120 ms: the frame of 0 ms");
    assert_eq!(shown[4], at(1), "160 ms: the frame of 40 ms");
    assert_eq!(shown[7], at(4), "280 ms: the frame of 160 ms");
    // A frame without a face shows nothing once its time comes.
    for i in 8..12u64 {
        a.update(i * 40_000, Vec::new());
    }
    assert_eq!(glasses_x(&a), None);
    // Timestamps that go backwards cannot grow what is kept.
    for i in 0..3000u64 {
        a.update(1_000_000 - i, vec![face(0.0, false)]);
    }
    assert!(a.history.len() <= MAX_HISTORY);
}

#[test]
fn an_effect_turns_on_and_off_with_hysteresis_and_its_particles_are_bounded() {
    let mut a = augmenter(0.0);
    let jaw = [0.4, 0.55, 0.4, 0.36, 0.3, 0.45, 0.5];
    let on: Vec<bool> = jaw
        .iter()
        .enumerate()
        .map(|(i, &j)| {
            a.update(i as u64 * 33_333, vec![face(j, false)]);
            a.effect_on(1, 0)
        })
        .collect();
    // On at 0.5 and above, off at 0.35 and below.
    assert_eq!(on, [false, true, true, true, false, false, true]);
    let sparks = |a: &Augmenter| a.fx.get(&1).map_or(0, |fx| fx.particles.len());
    // 90 a second, living 0.7 s: about 63 once it has run a while, never more than the cap.
    for i in 7..100u64 {
        a.update(i * 33_333, vec![face(0.9, true)]);
    }
    assert!((55..=70).contains(&sparks(&a)), "{} sparks", sparks(&a));
    assert!(a.effect_on(1, 1), "the smile's tint");
    // Closing the mouth stops new ones; the last die within their life.
    for i in 100..130u64 {
        a.update(i * 33_333, vec![face(0.0, false)]);
    }
    assert_eq!(sparks(&a), 0);
    assert!(!a.effect_on(1, 1));
}

#[test]
fn the_tint_reaches_the_lenses_of_a_smiling_face_only() {
    let draw = |smile: bool| {
        let mut a = augmenter(0.0);
        a.update(0, vec![face(0.0, smile)]);
        let mut c = background();
        a.draw(&mut c, &K, &Pose::IDENTITY);
        c
    };
    let (plain, smiling) = (draw(false), draw(true));
    // Rose lenses: more red than green where they differ, and only around the glasses (the upper half).
    let differ: Vec<usize> = (0..320 * 240)
        .filter(|&i| plain.rgb()[i * 3..i * 3 + 3] != smiling.rgb()[i * 3..i * 3 + 3])
        .collect();
    assert!(differ.len() > 200, "{} pixels tinted", differ.len());
    let redder = differ
        .iter()
        .filter(|&&i| smiling.rgb()[i * 3] > smiling.rgb()[i * 3 + 1])
        .count();
    assert!(
        redder * 10 > differ.len() * 9,
        "{redder} of {} redder than green",
        differ.len()
    );
}
