//! Augmented frames: 3D objects anchored on each tracked face, drawn into the camera image where a headset
//! would show them, and effects the face triggers (`holoface track --augment SCENE`, `make demo`'s
//! `augmented.png`).
//!
//! Driven only by what the facade returns per face: the predicted (display) head pose in the world, the fitted
//! expression (for the occluding head), blendshapes and attributes, with the frame's intrinsics and headset
//! pose. A headset shows what it computed from a frame captured `delay` earlier; the tracker predicts the head
//! that far ahead. So frame `t` is drawn with the face result of the latest frame captured at or before
//! `t - delay`, at that result's display pose, seen from frame `t`'s camera: the picture is what the wearer
//! would see, the prediction's error included. The delay is the scene's `display_delay_ms`, or the tracker's
//! look-ahead (120 ms, as in the paper).
//!
//! Rendering is our own small rasteriser ([`raster`]): deterministic to the pixel (a golden image tests it), no
//! GPU or system library, nothing added to the build beyond this module; a headset app renders with its engine
//! (the Unity sample reads the same anchors through the C ABI).

pub mod mesh;
pub mod raster;
pub mod scene;

use std::collections::{BTreeMap, VecDeque};

use holoface_harness::plot::Canvas;
use holoface_models::anchor::{Anchor, head_pose};
use holoface_models::camera::Intrinsics;
use holoface_models::candide::FaceModel;
use holoface_models::math3::{Pose, Vec3};
use holoface_runtime::{Attributes, Blendshapes, ExpressionWeights, FaceResult};

use mesh::Role;
use raster::{Material, Mesh, Target};
use scene::{Action, Attribute, Scene, Shape, Trigger};

/// Frames kept while waiting for the display delay (a stream with timestamps going backwards cannot grow it).
const MAX_HISTORY: usize = 1024;
/// Most live particles per face.
const MAX_PARTICLES: usize = 2000;
/// The skull occluder's centre in the head frame (behind the CANDIDE-3 mask; `mesh::skull`).
const SKULL_CENTRE: Vec3 = Vec3::new(0.0, -0.03, 0.1);

/// What the augmentation needs of one tracked face.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FaceSnapshot {
    /// The track's id.
    pub id: u32,
    /// The head in the world, as predicted for display (head → world).
    pub world_from_head: Pose,
    /// The fitted expression (shapes the occluding head).
    pub weights: ExpressionWeights,
    /// Blendshape coefficients.
    pub blendshapes: Blendshapes,
    /// Attributes.
    pub attributes: Attributes,
}

impl FaceSnapshot {
    /// What a face result gives: its display pose, expression, blendshapes and attributes.
    pub fn of(f: &FaceResult) -> Self {
        Self {
            id: f.id,
            world_from_head: head_pose(f.display.0, f.display.1),
            weights: f.fit.weights,
            blendshapes: f.blendshapes,
            attributes: f.attributes,
        }
    }
}

/// How still an anchored point stayed over a run: its spread and its steps from frame to frame.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Drift {
    /// Frames with a position.
    pub frames: usize,
    /// Standard deviation per world axis, millimetres.
    pub std_mm: [f64; 3],
    /// Median distance between consecutive frames' positions, millimetres.
    pub step_median_mm: f64,
    /// 95th percentile of that distance, millimetres.
    pub step_p95_mm: f64,
}

/// The drift of a point over frames (`None` where it was not placed: no step is taken across it); `None`
/// with fewer than two positions in a row.
pub fn drift(track: &[Option<Vec3>]) -> Option<Drift> {
    let placed: Vec<Vec3> = track.iter().flatten().copied().collect();
    let steps: Vec<f64> = track
        .windows(2)
        .filter_map(|w| Some((w[1]? - w[0]?).norm() * 1e3))
        .collect();
    if steps.is_empty() {
        return None;
    }
    let n = placed.len() as f64;
    let mean = placed.iter().fold(Vec3::default(), |a, &p| a + p).scale(1.0 / n);
    let axis =
        |f: fn(Vec3) -> f64| (placed.iter().map(|&p| (f(p) - f(mean)).powi(2)).sum::<f64>() / n).sqrt() * 1e3;
    Some(Drift {
        frames: placed.len(),
        std_mm: [axis(|p| p.x), axis(|p| p.y), axis(|p| p.z)],
        step_median_mm: crate::stats::percentile(&steps, 0.5),
        step_p95_mm: crate::stats::percentile(&steps, 0.95),
    })
}

/// One object, ready to draw: its meshes in its own frame (scaled) and its colours.
#[derive(Debug)]
struct Prepared {
    name: String,
    anchor: Anchor,
    parts: Vec<(Role, Mesh)>,
    colour: [u8; 3],
    trim: [u8; 3],
    glass: [u8; 3],
    glass_opacity: f64,
}

#[derive(Clone, Copy, Debug)]
struct Particle {
    position: Vec3,
    velocity: Vec3,
    age_s: f64,
    effect: usize,
}

/// Per face: which effects are on, and its particles.
#[derive(Debug, Default)]
struct FaceFx {
    on: Vec<bool>,
    particles: Vec<Particle>,
    to_emit: Vec<f64>,
    last_us: Option<u64>,
}

/// The augmentation of a stream: feed every frame's faces to [`Self::update`], draw with [`Self::draw`].
#[derive(Debug)]
pub struct Augmenter {
    model: FaceModel,
    objects: Vec<Prepared>,
    scene: Scene,
    skull: Mesh,
    delay_us: u64,
    history: VecDeque<(u64, Vec<FaceSnapshot>)>,
    shown: Vec<FaceSnapshot>,
    fx: BTreeMap<u32, FaceFx>,
    rng: u64,
}

impl Augmenter {
    /// The augmentation of `scene` on heads of `model`, drawn for the scene's display delay or, when it
    /// names none, `default_delay_ms` (the tracker's look-ahead).
    pub fn new(scene: Scene, model: FaceModel, default_delay_ms: f64) -> Self {
        let delay_ms = scene
            .display_delay_ms
            .unwrap_or(default_delay_ms)
            .clamp(0.0, scene::MAX_DELAY_MS);
        let objects = scene
            .objects
            .iter()
            .map(|o| Prepared {
                name: o.name.clone(),
                anchor: o.anchor,
                parts: match o.shape {
                    Shape::Glasses => mesh::glasses(),
                    Shape::TopHat => mesh::top_hat(),
                }
                .into_iter()
                .map(|(role, m)| (role, m.scaled(o.scale)))
                .collect(),
                colour: o.colour,
                trim: o.trim,
                glass: o.glass,
                glass_opacity: o.glass_opacity,
            })
            .collect();
        Self {
            model,
            objects,
            scene,
            skull: mesh::skull(SKULL_CENTRE),
            delay_us: (delay_ms * 1e3).round() as u64,
            history: VecDeque::new(),
            shown: Vec::new(),
            fx: BTreeMap::new(),
            rng: 0x9E37_79B9_7F4A_7C15,
        }
    }

    /// The display delay drawn for, milliseconds.
    pub fn delay_ms(&self) -> f64 {
        self.delay_us as f64 / 1e3
    }

    /// The frame captured at `t_us` had `faces`: chooses what the frame shows (the faces of the latest frame
    /// captured at or before `t_us` minus the delay) and advances the effects to that time.
    pub fn update(&mut self, t_us: u64, faces: Vec<FaceSnapshot>) {
        self.history.push_back((t_us, faces));
        while self.history.len() > MAX_HISTORY {
            self.history.pop_front();
        }
        let due = t_us.saturating_sub(self.delay_us);
        while self.history.len() >= 2 && self.history[1].0 <= due {
            self.history.pop_front();
        }
        let (shown_us, shown) = match self.history.front() {
            Some((t, f)) if *t <= due && t_us >= self.delay_us => (*t, f.clone()),
            _ => (t_us, Vec::new()),
        };
        self.fx.retain(|id, _| shown.iter().any(|f| f.id == *id));
        for f in &shown {
            self.advance_effects(f, shown_us);
        }
        self.shown = shown;
    }

    /// The faces the current frame shows, with each object's pose in the world (object → world).
    pub fn anchors(&self) -> Vec<(u32, Vec<Pose>)> {
        self.shown
            .iter()
            .map(|f| {
                let poses = self
                    .objects
                    .iter()
                    .map(|o| o.anchor.world_from_object(&self.model, &f.world_from_head))
                    .collect();
                (f.id, poses)
            })
            .collect()
    }

    /// Object `k` of the scene (in its order) on `face`, in the world (object → world); the identity when the
    /// scene has no such object.
    pub fn place(&self, k: usize, face: &FaceSnapshot) -> Pose {
        self.objects.get(k).map_or(Pose::IDENTITY, |o| {
            o.anchor.world_from_object(&self.model, &face.world_from_head)
        })
    }

    /// The name of object `k` of the scene ("" when there is none).
    pub fn object_name(&self, k: usize) -> &str {
        self.objects.get(k).map_or("", |o| o.name.as_str())
    }

    /// Whether effect `k` of the scene is on for face `id` (what the current frame shows).
    pub fn effect_on(&self, id: u32, k: usize) -> bool {
        self.fx
            .get(&id)
            .and_then(|fx| fx.on.get(k).copied())
            .unwrap_or(false)
    }

    /// Draws the current frame's objects and effects into `canvas` (the camera image), seen through `k` from
    /// the headset at `world_from_camera`.
    pub fn draw(&self, canvas: &mut Canvas, k: &Intrinsics, world_from_camera: &Pose) {
        let (w, h) = (canvas.width(), canvas.height());
        let mut target = Target::new(canvas.rgb_mut(), w, h, *k);
        let camera_from_world = world_from_camera.inverse();
        let heads: Vec<(u32, Pose)> = self
            .shown
            .iter()
            .map(|f| (f.id, camera_from_world.after(&f.world_from_head)))
            .collect();
        // The heads hide what is behind them: the fitted face, and the skull behind it.
        for (f, (_, cam_from_head)) in self.shown.iter().zip(&heads) {
            target.occlude(&self.face_mesh(&f.weights).moved(cam_from_head));
            target.occlude(&self.skull.moved(cam_from_head));
        }
        let mut glass = Vec::new();
        for (f, (id, cam_from_head)) in self.shown.iter().zip(&heads) {
            for o in &self.objects {
                let pose = cam_from_head.after(&o.anchor.head_from_object(&self.model));
                let tint = self.tint(*id, &o.name);
                for (role, m) in &o.parts {
                    let material = o.material(*role, tint);
                    if material.opacity < 1.0 {
                        glass.push((m.moved(&pose), material));
                    } else {
                        target.draw(&m.moved(&pose), &material);
                    }
                }
            }
            if let Some(fx) = self.fx.get(&f.id) {
                for p in &fx.particles {
                    if let Action::Particles(spec) = &self.scene.effects[p.effect].action {
                        let life = (p.age_s / spec.lifetime_s).clamp(0.0, 1.0);
                        target.splat(
                            camera_from_world.apply(p.position),
                            spec.size_m * (1.0 - 0.5 * life),
                            spec.colour.map(|c| f64::from(c) / 255.0),
                            1.0 - life * life,
                        );
                    }
                }
            }
        }
        for (m, material) in &glass {
            target.draw(m, material);
        }
    }

    /// The fitted CANDIDE-3 mesh in the head frame (for depth; its normals are not used).
    fn face_mesh(&self, weights: &ExpressionWeights) -> Mesh {
        let positions = self.model.mesh_with(&weights.0);
        Mesh {
            normals: vec![Vec3::new(0.0, 0.0, -1.0); positions.len()],
            positions,
            triangles: self.model.faces.iter().map(|t| t.map(|v| v as u32)).collect(),
        }
    }

    /// The tint on object `name` of face `id`: colour and strength of the last tint effect that is on.
    fn tint(&self, id: u32, name: &str) -> Option<([u8; 3], f64)> {
        self.scene
            .effects
            .iter()
            .enumerate()
            .rev()
            .find_map(|(k, e)| match &e.action {
                Action::Tint {
                    object,
                    colour,
                    strength,
                } if object == name && self.effect_on(id, k) => Some((*colour, *strength)),
                _ => None,
            })
    }

    /// Moves face `f`'s triggers and particles to `t_us`.
    fn advance_effects(&mut self, f: &FaceSnapshot, t_us: u64) {
        let n = self.scene.effects.len();
        let mut fx = self.fx.remove(&f.id).unwrap_or_else(|| FaceFx {
            on: vec![false; n],
            to_emit: vec![0.0; n],
            ..FaceFx::default()
        });
        let dt = fx
            .last_us
            .map_or(0.0, |l| t_us.saturating_sub(l) as f64 / 1e6)
            .min(0.1);
        fx.last_us = Some(t_us);
        for (k, e) in self.scene.effects.iter().enumerate() {
            fx.on[k] = match e.when {
                Trigger::Blendshape { shape, on, off } => {
                    let v = f.blendshapes.get(shape);
                    if fx.on[k] { v > off } else { v >= on }
                }
                Trigger::Attribute(a) => match a {
                    Attribute::Smile => f.attributes.smile,
                    Attribute::BrowsRaised => f.attributes.brows_raised,
                    Attribute::MouthOpen => f.attributes.mouth_open,
                },
            };
        }
        // Particles: age and move, then the new ones.
        let lifetimes: Vec<f64> = self
            .scene
            .effects
            .iter()
            .map(|e| match &e.action {
                Action::Particles(p) => p.lifetime_s,
                Action::Tint { .. } => 0.0,
            })
            .collect();
        fx.particles.retain_mut(|p| {
            p.age_s += dt;
            p.position = p.position + p.velocity.scale(dt);
            p.velocity = p.velocity.scale((-1.5 * dt).exp());
            p.age_s < lifetimes[p.effect]
        });
        let forward = f.world_from_head.rotation * Vec3::new(0.0, 0.0, -1.0);
        for (k, e) in self.scene.effects.iter().enumerate() {
            let Action::Particles(spec) = &e.action else {
                continue;
            };
            if !fx.on[k] {
                fx.to_emit[k] = 0.0;
                continue;
            }
            fx.to_emit[k] += spec.per_second * dt;
            let origin = f.world_from_head.apply(spec.from.position(&self.model));
            while fx.to_emit[k] >= 1.0 && fx.particles.len() < MAX_PARTICLES {
                fx.to_emit[k] -= 1.0;
                let mut u = || uniform(&mut self.rng) - 0.5;
                let spread = Vec3::new(u(), u(), u());
                fx.particles.push(Particle {
                    position: origin,
                    velocity: (forward.scale(0.5) + spread).scale(spec.speed_m_s),
                    age_s: 0.0,
                    effect: k,
                });
            }
            fx.to_emit[k] = fx.to_emit[k].min(1.0);
        }
        self.fx.insert(f.id, fx);
    }
}

/// A deterministic uniform number in [0, 1) (xorshift): the same stream gives the same pictures.
fn uniform(state: &mut u64) -> f64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    (*state >> 11) as f64 / (1u64 << 53) as f64
}

#[cfg(test)]
mod tests;

impl Prepared {
    /// The material of a part in `role`, with a tint (colour, strength) mixed in.
    fn material(&self, role: Role, tint: Option<([u8; 3], f64)>) -> Material {
        let (rgb, opacity, gloss) = match role {
            Role::Body => (self.colour, 1.0, 0.35),
            Role::Trim => (self.trim, 1.0, 0.2),
            Role::Glass => (self.glass, self.glass_opacity, 0.8),
        };
        let mut m = Material::opaque(rgb, gloss);
        m.opacity = opacity;
        if let Some((c, s)) = tint {
            // The lenses take the whole tint and grow more opaque; the frame a share of it.
            let s = if role == Role::Glass { s } else { s * 0.5 };
            for (v, t) in m.colour.iter_mut().zip(c) {
                *v += (f64::from(t) / 255.0 - *v) * s;
            }
            if role == Role::Glass {
                m.opacity = (m.opacity + 0.3 * s).min(0.9);
            }
        }
        m
    }
}
