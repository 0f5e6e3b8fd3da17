//! The `krfws.bin` model file: versioned, little-endian, CRC-32 checked.
//!
//! ```text
//! offset  size  field
//! 0       8     magic  b"HFKRFWS\0"
//! 8       4     version u32 (= FORMAT_VERSION)
//! 12      4     payload length P u32
//! 16      P     payload
//! 16+P    4     CRC-32 (IEEE, crc32fast) of bytes 0 .. 16+P
//!
//! payload:
//!   n_points u32 (= 51) · hog_dim u32 (= 144) · n_stages u32 (1..=8)
//!   mean shape: 51 × (x f32, y f32)
//!   per stage:
//!     scale f32 · trees_per_forest u32 (1..=64)
//!     51 · trees_per_forest trees, landmark-major, each:
//!       n_nodes u32 (1..=4095) · n_leaves u32 (= n_nodes + 1)
//!       n_nodes × (left i32, right i32, threshold f32)   child ≥ 0: node index > parent; < 0: leaf −c−1
//!       n_nodes × 144 projections, f16
//!     n_leaves_total u32 (= Σ n_leaves) · n_leaves_total × 102 regression weights, f16
//!   failure detector: 51·144 weights f32 · intercept f32 · threshold f32
//! ```
//!
//! Projections and `W` are stored as IEEE half floats (the model is about half the size; the trainer
//! rounds them before it evaluates, so the numbers it reports are those of the stored model). Every
//! count is bounded and checked against the remaining bytes before anything is allocated; every child
//! pointer and leaf id is checked so that each tree is a proper binary tree (each node and each leaf
//! reached exactly once, children after parents). A bad file is a [`ModelError`], never a panic.

use half::f16;
use holoface_protocol::framing::{self, Damage, Format, FormatError, PayloadReader};
use thiserror::Error;

use super::{DELTA_DIM, FAILURE_DIM, FailureModel, Krfws, N_POINTS, Node, Stage, Tree};
use crate::geometry::Point2;
use crate::hog::HOG_DIM;

/// File magic.
pub const MAGIC: [u8; 8] = *b"HFKRFWS\0";
/// Format version this build reads and writes.
pub const FORMAT_VERSION: u32 = 1;
/// Largest accepted payload (256 MiB).
pub const MAX_PAYLOAD: u32 = 256 << 20;
/// The file in the one framing ([`holoface_protocol::framing`]), whose layout is this format's v1.
pub const FILE: Format = Format {
    name: "KRFWS model",
    magic: MAGIC,
    oldest: FORMAT_VERSION,
    newest: FORMAT_VERSION,
    sized_from: FORMAT_VERSION,
    max_payload: MAX_PAYLOAD as u64,
};
const MAX_STAGES: u32 = 8;
const MAX_TREES: u32 = 64;
const MAX_NODES: u32 = 4095;

/// Errors loading a model file.
#[derive(Debug, Error, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum ModelError {
    /// A foreign or damaged file, or a field outside its range (the framing's error).
    #[error(transparent)]
    Format(#[from] FormatError),
    /// A tree's structure is invalid.
    #[error("KRFWS model: stage {stage}, tree {tree}, node {node}: {reason}")]
    BadTree {
        /// Stage index.
        stage: usize,
        /// Tree index within the stage.
        tree: usize,
        /// Node index within the tree.
        node: usize,
        /// What is wrong.
        reason: &'static str,
    },
}

impl ModelError {
    /// What is damaged, when the error is the framing's.
    pub fn damage(&self) -> Option<&Damage> {
        match self {
            Self::Format(e) => Some(&e.damage),
            Self::BadTree { .. } => None,
        }
    }
}

/// `n` IEEE half floats, which must be finite.
fn f16s(
    r: &mut PayloadReader<'_>,
    n: usize,
    field: &'static str,
    out: &mut Vec<f32>,
) -> Result<(), FormatError> {
    let b = r.take(n.saturating_mul(2))?;
    for (i, c) in b.chunks_exact(2).enumerate() {
        let v = f16::from_bits(u16::from_le_bytes([c[0], c[1]])).to_f32();
        if !v.is_finite() {
            return Err(r.error(Damage::NotFinite { field, index: i }));
        }
        out.push(v);
    }
    Ok(())
}

fn check_tree(tree: &Tree, stage: usize, index: usize) -> Result<(), ModelError> {
    let n = tree.nodes.len();
    let bad = |node: usize, reason: &'static str| ModelError::BadTree {
        stage,
        tree: index,
        node,
        reason,
    };
    let mut node_seen = vec![false; n];
    let mut leaf_seen = vec![false; tree.n_leaves as usize];
    for (i, node) in tree.nodes.iter().enumerate() {
        if !node.threshold.is_finite() {
            return Err(bad(i, "non-finite threshold"));
        }
        for c in [node.left, node.right] {
            if c >= 0 {
                let c = c as usize;
                if c <= i || c >= n {
                    return Err(bad(i, "child node index out of order or out of range"));
                }
                if std::mem::replace(&mut node_seen[c], true) {
                    return Err(bad(i, "node reached twice"));
                }
            } else {
                let leaf = (-(i64::from(c) + 1)) as usize;
                match leaf_seen.get_mut(leaf) {
                    None => return Err(bad(i, "leaf id out of range")),
                    Some(s) if *s => return Err(bad(i, "leaf reached twice")),
                    Some(s) => *s = true,
                }
            }
        }
    }
    if node_seen.iter().skip(1).any(|s| !s) {
        return Err(bad(0, "unreachable node"));
    }
    if leaf_seen.iter().any(|s| !s) {
        return Err(bad(0, "unreachable leaf"));
    }
    Ok(())
}

impl Krfws {
    /// Loads a model from the bytes of a `krfws.bin` file (see the module docs for the layout).
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, ModelError> {
        let mut r = framing::decode(&FILE, bytes)?.payload;
        let model = parse_payload(&mut r)?;
        r.finish()?;
        Ok(model)
    }

    /// Serialises the model (projections and `W` rounded to f16; see [`Krfws::round_to_storage`]).
    ///
    /// # Errors
    /// The model is over the format's 256-MiB payload limit.
    pub fn to_bytes(&self) -> Result<Vec<u8>, ModelError> {
        let mut p = Vec::new();
        let put_u32 = |p: &mut Vec<u8>, v: u32| p.extend_from_slice(&v.to_le_bytes());
        let put_f32 = |p: &mut Vec<u8>, v: f32| p.extend_from_slice(&v.to_le_bytes());
        let put_f16 =
            |p: &mut Vec<u8>, v: f32| p.extend_from_slice(&f16::from_f32(v).to_bits().to_le_bytes());
        put_u32(&mut p, N_POINTS as u32);
        put_u32(&mut p, HOG_DIM as u32);
        put_u32(&mut p, self.stages.len() as u32);
        for m in &self.mean {
            put_f32(&mut p, m.x);
            put_f32(&mut p, m.y);
        }
        for s in &self.stages {
            put_f32(&mut p, s.scale);
            put_u32(&mut p, s.trees_per_forest as u32);
            for t in &s.trees {
                put_u32(&mut p, t.nodes.len() as u32);
                put_u32(&mut p, t.n_leaves);
                for n in &t.nodes {
                    put_u32(&mut p, n.left as u32);
                    put_u32(&mut p, n.right as u32);
                    put_f32(&mut p, n.threshold);
                }
                for &v in &t.projections {
                    put_f16(&mut p, v);
                }
            }
            put_u32(&mut p, s.n_leaves() as u32);
            for &v in &s.weights {
                put_f16(&mut p, v);
            }
        }
        for &w in &self.failure.weights {
            put_f32(&mut p, w);
        }
        put_f32(&mut p, self.failure.intercept);
        put_f32(&mut p, self.failure.threshold);
        Ok(framing::encode(&FILE, &p)?)
    }

    /// Rounds projections and `W` to their stored (f16) precision, saturating at ±65504, so that
    /// `from_bytes(to_bytes(m)) == m`.
    pub fn round_to_storage(&mut self) {
        for s in &mut self.stages {
            for t in &mut s.trees {
                round_f16(&mut t.projections);
            }
            round_f16(&mut s.weights);
            s.refresh();
        }
    }
}

/// Rounds values to f16 precision in place (saturating, NaN → 0).
pub fn round_f16(v: &mut [f32]) {
    for x in v {
        let c = if x.is_nan() {
            0.0
        } else {
            x.clamp(-65504.0, 65504.0)
        };
        *x = f16::from_f32(c).to_f32();
    }
}

fn parse_payload(r: &mut PayloadReader<'_>) -> Result<Krfws, ModelError> {
    r.count("n_points", N_POINTS as u32, N_POINTS as u32)?;
    r.count("hog_dim", HOG_DIM as u32, HOG_DIM as u32)?;
    let n_stages = r.count("n_stages", 1, MAX_STAGES)? as usize;
    let mut mean = [Point2::default(); N_POINTS];
    for (i, m) in mean.iter_mut().enumerate() {
        *m = Point2::new(r.f32("mean", 2 * i)?, r.f32("mean", 2 * i + 1)?);
    }
    if crate::geometry::Rect::bounding(&mean).is_none_or(|b| b.width() <= 0.0 || b.height() <= 0.0) {
        return Err(r.out_of_range("mean shape extent", 0, 1, u64::MAX).into());
    }
    let mut stages = Vec::with_capacity(n_stages);
    for si in 0..n_stages {
        let scale = r.f32("scale", si)?;
        if !(0.01..=100.0).contains(&scale) {
            let value = (scale.abs() * 1000.0) as u64;
            return Err(r.out_of_range("stage scale (x1000)", value, 10, 100_000).into());
        }
        let tpf = r.count("trees_per_forest", 1, MAX_TREES)? as usize;
        let n_trees = N_POINTS * tpf;
        let mut trees = Vec::with_capacity(n_trees);
        let mut total_leaves = 0u64;
        for ti in 0..n_trees {
            let n_nodes = r.count("n_nodes", 1, MAX_NODES)? as usize;
            let n_leaves = r.count("n_leaves", 2, MAX_NODES + 1)?;
            if n_leaves as usize != n_nodes + 1 {
                return Err(ModelError::BadTree {
                    stage: si,
                    tree: ti,
                    node: 0,
                    reason: "a binary tree has one leaf more than internal nodes",
                });
            }
            r.need((n_nodes * (12 + 2 * HOG_DIM)) as u64)?;
            let mut nodes = Vec::with_capacity(n_nodes);
            for _ in 0..n_nodes {
                let left = r.i32()?;
                let right = r.i32()?;
                let threshold = f32::from_le_bytes(r.array()?);
                nodes.push(Node {
                    left,
                    right,
                    threshold,
                });
            }
            let mut projections = Vec::with_capacity(n_nodes * HOG_DIM);
            f16s(r, n_nodes * HOG_DIM, "projections", &mut projections)?;
            let tree = Tree {
                nodes,
                projections,
                n_leaves,
            };
            check_tree(&tree, si, ti)?;
            total_leaves += u64::from(n_leaves);
            trees.push(tree);
        }
        let declared = r.u32()?;
        if u64::from(declared) != total_leaves {
            let value = u64::from(declared);
            return Err(r
                .out_of_range("n_leaves_total", value, total_leaves, total_leaves)
                .into());
        }
        let nw = total_leaves as usize * DELTA_DIM;
        r.need(2 * nw as u64)?;
        let mut weights = Vec::with_capacity(nw);
        f16s(r, nw, "W", &mut weights)?;
        stages.push(Stage::new(&mean, scale, tpf, trees, weights));
    }
    r.need(4 * (FAILURE_DIM as u64 + 2))?;
    let mut fw = Vec::with_capacity(FAILURE_DIM);
    for i in 0..FAILURE_DIM {
        fw.push(r.f32("failure weights", i)?);
    }
    let intercept = r.f32("failure intercept", 0)?;
    let threshold = r.f32("failure threshold", 0)?;
    Ok(Krfws::new(
        mean,
        stages,
        FailureModel {
            weights: fw,
            intercept,
            threshold,
        },
    ))
}
