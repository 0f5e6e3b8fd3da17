//! Scene files: the objects anchored on each tracked face and the effects the face triggers (TOML).
//!
//! ```toml
//! display_delay_ms = 120            # optional: the capture-to-display delay the objects are drawn for
//! [[object]]
//! shape = "glasses"                 # "glasses" or "top-hat" (generated meshes, tools/src/augment/mesh.rs)
//! anchor = "eyes"                   # origin, eyes, nose-bridge, head-top, mouth
//! offset_m = [0.0, 0.0, -0.018]     # head frame: x right, y down, z into the head
//! rotation_deg = [0.0, 0.0, 0.0]    # about the head's x, y, z
//! scale = 1.0
//! colour = [25, 25, 30]
//! [[effect]]
//! when = { blendshape = "jawOpen", on = 0.5, off = 0.35 }   # or { attribute = "smile" }
//! particles = { colour = [255, 210, 80] }                     # or tint = { object = "glasses", colour = [...] }
//! ```
//!
//! A file is at most [`MAX_SCENE_BYTES`] with at most [`MAX_OBJECTS`] objects and [`MAX_EFFECTS`] effects;
//! unknown keys, names and out-of-range numbers are refused with the key that holds them.

use std::path::Path;

use anyhow::{Context, bail, ensure};
use holoface_models::anchor::{Anchor, AnchorPoint};
use holoface_models::blendshapes::Blendshape;
use holoface_models::math3::Vec3;
use serde::Deserialize;

/// The shipped scene: glasses on the eyes, a top hat, particles from an open mouth, rose lenses on a smile.
pub const DEFAULT_SCENE: &str = include_str!("../../assets/augment/glasses-and-hat.toml");
/// Largest scene file read.
pub const MAX_SCENE_BYTES: u64 = 64 * 1024;
/// Most objects in a scene.
pub const MAX_OBJECTS: usize = 16;
/// Most effects in a scene.
pub const MAX_EFFECTS: usize = 16;
/// Longest display delay, milliseconds.
pub const MAX_DELAY_MS: f64 = 1000.0;

/// The shapes a scene can place.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Shape {
    /// Glasses centred on their bridge (`mesh::glasses`).
    Glasses,
    /// A top hat standing on its brim (`mesh::top_hat`).
    TopHat,
}

/// One object of a scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Object {
    /// Its name (the shape's, unless the file names it): what a tint addresses.
    pub name: String,
    /// What it is.
    pub shape: Shape,
    /// Where it sits on the head.
    pub anchor: Anchor,
    /// Size relative to the shape's own.
    pub scale: f64,
    /// Body colour.
    pub colour: [u8; 3],
    /// Trim colour (a hat's band).
    pub trim: [u8; 3],
    /// See-through parts' colour and opacity (lenses).
    pub glass: [u8; 3],
    /// Opacity of the see-through parts, 0-1.
    pub glass_opacity: f64,
}

/// What turns an effect on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Trigger {
    /// A blendshape coefficient with hysteresis: on at `on` or above, off at `off` or below.
    Blendshape {
        /// The coefficient.
        shape: Blendshape,
        /// Turns on at or above.
        on: f32,
        /// Turns off at or below.
        off: f32,
    },
    /// One of the tracker's attributes (already with its own hysteresis).
    Attribute(Attribute),
}

/// The attributes a trigger can name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Attribute {
    /// `smile`.
    Smile,
    /// `brows-raised`.
    BrowsRaised,
    /// `mouth-open`.
    MouthOpen,
}

/// What an effect does while its trigger is on.
#[derive(Clone, Debug, PartialEq)]
pub enum Action {
    /// Particles leave the anchor point towards the viewer.
    Particles(Particles),
    /// An object's colours move towards `colour` by `strength`.
    Tint {
        /// The object (its name).
        object: String,
        /// The tint.
        colour: [u8; 3],
        /// 0-1.
        strength: f64,
    },
}

/// A particle effect.
#[derive(Clone, Copy, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Particles {
    /// Where they start.
    #[serde(deserialize_with = "anchor_point")]
    pub from: AnchorPoint,
    /// Colour.
    pub colour: [u8; 3],
    /// Emitted per second while on.
    pub per_second: f64,
    /// Initial speed, metres per second.
    pub speed_m_s: f64,
    /// Life, seconds.
    pub lifetime_s: f64,
    /// Radius, metres.
    pub size_m: f64,
}

impl Default for Particles {
    fn default() -> Self {
        Self {
            from: AnchorPoint::Mouth,
            colour: [255, 210, 80],
            per_second: 90.0,
            speed_m_s: 0.35,
            lifetime_s: 0.7,
            size_m: 0.005,
        }
    }
}

/// One effect.
#[derive(Clone, Debug, PartialEq)]
pub struct Effect {
    /// When.
    pub when: Trigger,
    /// What.
    pub action: Action,
}

/// A parsed, checked scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    /// The capture-to-display delay the objects are drawn for, milliseconds (`None`: the tracker's
    /// look-ahead).
    pub display_delay_ms: Option<f64>,
    /// The objects.
    pub objects: Vec<Object>,
    /// The effects.
    pub effects: Vec<Effect>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SceneFile {
    display_delay_ms: Option<f64>,
    #[serde(default)]
    object: Vec<ObjectFile>,
    #[serde(default)]
    effect: Vec<EffectFile>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ObjectFile {
    name: Option<String>,
    shape: Shape,
    #[serde(deserialize_with = "anchor_point")]
    anchor: AnchorPoint,
    #[serde(default)]
    offset_m: [f64; 3],
    #[serde(default)]
    rotation_deg: [f64; 3],
    #[serde(default = "one")]
    scale: f64,
    #[serde(default = "dark")]
    colour: [u8; 3],
    #[serde(default = "trim")]
    trim: [u8; 3],
    #[serde(default = "glass")]
    glass: [u8; 3],
    #[serde(default = "glass_opacity")]
    glass_opacity: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct EffectFile {
    when: TriggerFile,
    particles: Option<Particles>,
    tint: Option<TintFile>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TriggerFile {
    blendshape: Option<String>,
    attribute: Option<Attribute>,
    on: Option<f32>,
    off: Option<f32>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct TintFile {
    object: String,
    colour: [u8; 3],
    #[serde(default = "half")]
    strength: f64,
}

fn one() -> f64 {
    1.0
}
fn half() -> f64 {
    0.5
}
fn dark() -> [u8; 3] {
    [30, 30, 36]
}
fn trim() -> [u8; 3] {
    [170, 30, 40]
}
fn glass() -> [u8; 3] {
    [150, 200, 230]
}
fn glass_opacity() -> f64 {
    0.3
}

fn anchor_point<'de, D: serde::Deserializer<'de>>(d: D) -> Result<AnchorPoint, D::Error> {
    let name = String::deserialize(d)?;
    AnchorPoint::from_name(&name).ok_or_else(|| {
        let names: Vec<_> = AnchorPoint::ALL.iter().map(|p| p.name()).collect();
        serde::de::Error::custom(format!("unknown anchor {name:?} (one of {})", names.join(", ")))
    })
}

impl Scene {
    /// Reads and checks a scene file; `default` names the shipped scene ([`DEFAULT_SCENE`]).
    pub fn load(path: &Path) -> anyhow::Result<Self> {
        if path == Path::new("default") {
            return Self::parse(DEFAULT_SCENE).context("the shipped scene");
        }
        let bytes = holoface_files::read_bounded(path, MAX_SCENE_BYTES, "scene file")?;
        let text =
            String::from_utf8(bytes).map_err(|_| anyhow::anyhow!("{}: not UTF-8 text", path.display()))?;
        Self::parse(&text).with_context(|| format!("scene file {}", path.display()))
    }

    /// Parses and checks a scene.
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let f: SceneFile = toml::from_str(text)?;
        ensure!(
            f.object.len() <= MAX_OBJECTS,
            "{} objects: at most {MAX_OBJECTS}",
            f.object.len()
        );
        ensure!(
            f.effect.len() <= MAX_EFFECTS,
            "{} effects: at most {MAX_EFFECTS}",
            f.effect.len()
        );
        if let Some(d) = f.display_delay_ms {
            ensure!(
                (0.0..=MAX_DELAY_MS).contains(&d),
                "display_delay_ms {d}: must be within 0..={MAX_DELAY_MS}"
            );
        }
        let objects = f
            .object
            .into_iter()
            .enumerate()
            .map(|(i, o)| object(o).with_context(|| format!("object {}", i + 1)))
            .collect::<anyhow::Result<Vec<_>>>()?;
        let effects = f
            .effect
            .into_iter()
            .enumerate()
            .map(|(i, e)| effect(e, &objects).with_context(|| format!("effect {}", i + 1)))
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(Self {
            display_delay_ms: f.display_delay_ms,
            objects,
            effects,
        })
    }
}

fn object(o: ObjectFile) -> anyhow::Result<Object> {
    for (key, v) in [("offset_m", o.offset_m), ("rotation_deg", o.rotation_deg)] {
        ensure!(v.iter().all(|x| x.is_finite()), "{key} {v:?}: not finite");
    }
    ensure!(
        o.offset_m.iter().all(|x| x.abs() <= 1.0),
        "offset_m {:?}: more than 1 m from the head",
        o.offset_m
    );
    ensure!(
        (0.1..=10.0).contains(&o.scale),
        "scale {}: must be within 0.1..=10",
        o.scale
    );
    ensure!(
        (0.0..=1.0).contains(&o.glass_opacity),
        "glass_opacity {}: must be within 0..=1",
        o.glass_opacity
    );
    let name = o.name.unwrap_or_else(|| match o.shape {
        Shape::Glasses => "glasses".into(),
        Shape::TopHat => "top-hat".into(),
    });
    let [x, y, z] = o.offset_m;
    Ok(Object {
        name,
        shape: o.shape,
        anchor: Anchor::new(o.anchor, Vec3::new(x, y, z), o.rotation_deg),
        scale: o.scale,
        colour: o.colour,
        trim: o.trim,
        glass: o.glass,
        glass_opacity: o.glass_opacity,
    })
}

fn effect(e: EffectFile, objects: &[Object]) -> anyhow::Result<Effect> {
    let w = e.when;
    let when = match (w.blendshape, w.attribute) {
        (Some(name), None) => {
            let shape = Blendshape::ALL
                .into_iter()
                .find(|b| b.arkit_name() == name)
                .with_context(|| {
                    format!("when.blendshape {name:?}: not an ARKit blendshape name (e.g. jawOpen)")
                })?;
            let on =
                w.on.context("when.on: a blendshape trigger needs its on threshold")?;
            let off = w.off.unwrap_or(on * 0.7);
            ensure!(
                (0.0..=1.0).contains(&on) && (0.0..=1.0).contains(&off) && off <= on,
                "when.on {on} and when.off {off}: need 0 <= off <= on <= 1"
            );
            Trigger::Blendshape { shape, on, off }
        }
        (None, Some(a)) => {
            ensure!(
                w.on.is_none() && w.off.is_none(),
                "when.on/off: an attribute has its own thresholds"
            );
            Trigger::Attribute(a)
        }
        _ => bail!("when: needs exactly one of blendshape and attribute"),
    };
    let action = match (e.particles, e.tint) {
        (Some(p), None) => {
            let checks = [
                ("per_second", p.per_second, 0.0, 1000.0),
                ("speed_m_s", p.speed_m_s, 0.0, 10.0),
                ("lifetime_s", p.lifetime_s, 0.01, 10.0),
                ("size_m", p.size_m, 0.0005, 0.1),
            ];
            for (key, v, lo, hi) in checks {
                ensure!(
                    (lo..=hi).contains(&v),
                    "particles.{key} {v}: must be within {lo}..={hi}"
                );
            }
            Action::Particles(p)
        }
        (None, Some(t)) => {
            ensure!(
                objects.iter().any(|o| o.name == t.object),
                "tint.object {:?}: no object has that name",
                t.object
            );
            ensure!(
                (0.0..=1.0).contains(&t.strength),
                "tint.strength {}: must be within 0..=1",
                t.strength
            );
            Action::Tint {
                object: t.object,
                colour: t.colour,
                strength: t.strength,
            }
        }
        _ => bail!("needs exactly one of particles and tint"),
    };
    Ok(Effect { when, action })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_scene_has_two_objects_and_two_effects() {
        let s = Scene::parse(DEFAULT_SCENE).unwrap();
        let names: Vec<_> = s.objects.iter().map(|o| o.name.as_str()).collect();
        assert_eq!(names, ["glasses", "top-hat"]);
        assert!(matches!(
            s.effects[0].when,
            Trigger::Blendshape { shape: Blendshape::JawOpen, on, off } if on == 0.5 && off == 0.35
        ));
        assert!(matches!(&s.effects[1].action, Action::Tint { object, .. } if object == "glasses"));
        assert_eq!(s.display_delay_ms, None);
    }

    #[test]
    fn a_bad_scene_is_refused_with_the_key_that_is_wrong() {
        let err = |text: &str| format!("{:#}", Scene::parse(text).unwrap_err());
        let obj = "[[object]]\nshape = \"glasses\"\nanchor = \"eyes\"\n";
        assert!(err("[[object]]\nshape = \"crown\"\nanchor = \"eyes\"\n").contains("crown"));
        assert!(
            err("[[object]]\nshape = \"glasses\"\nanchor = \"ear\"\n").contains("unknown anchor \"ear\"")
        );
        assert!(err(&format!("{obj}scale = 100.0\n")).contains("scale 100"));
        assert!(err(&format!("{obj}offset_m = [0.0, 5.0, 0.0]\n")).contains("more than 1 m"));
        assert!(err(&format!("{obj}colour = [300, 0, 0]\n")).contains("colour"));
        assert!(err(&format!("{obj}hat = 1\n")).contains("unknown field"));
        assert!(err("display_delay_ms = -5.0\n").contains("display_delay_ms"));
        let effect = |when: &str, what: &str| format!("{obj}[[effect]]\nwhen = {when}\n{what}\n");
        let smile = "{ attribute = \"smile\" }";
        for (when, what, says) in [
            (
                "{ blendshape = \"jawopen\", on = 0.5 }",
                "particles = {}",
                "jawopen",
            ),
            ("{ blendshape = \"jawOpen\" }", "particles = {}", "on threshold"),
            (
                "{ blendshape = \"jawOpen\", on = 0.3, off = 0.6 }",
                "particles = {}",
                "off <= on",
            ),
            (
                smile,
                "tint = { object = \"hat\", colour = [1, 2, 3] }",
                "no object",
            ),
            (smile, "", "exactly one of particles and tint"),
            (
                "{ attribute = \"smile\", on = 0.2 }",
                "particles = {}",
                "own thresholds",
            ),
            (smile, "particles = { lifetime_s = 0.0 }", "lifetime_s"),
        ] {
            let e = err(&effect(when, what));
            assert!(e.contains(says), "{when} {what}: {e}");
        }
        let many = obj.repeat(MAX_OBJECTS + 1);
        assert!(err(&many).contains("at most 16"));
    }

    #[test]
    fn a_missing_or_gigantic_scene_file_is_refused() {
        let d = std::env::temp_dir().join(format!("holoface-scene-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        let big = d.join("big.toml");
        std::fs::write(&big, vec![b'#'; MAX_SCENE_BYTES as usize + 1]).unwrap();
        let e = format!("{:#}", Scene::load(&big).unwrap_err());
        assert!(e.contains("scene file"), "{e}");
        let e = format!("{:#}", Scene::load(&d.join("none.toml")).unwrap_err());
        assert!(e.contains("none.toml"), "{e}");
        assert_eq!(
            Scene::load(Path::new("default")).unwrap(),
            Scene::parse(DEFAULT_SCENE).unwrap()
        );
        std::fs::remove_dir_all(&d).unwrap();
    }
}
