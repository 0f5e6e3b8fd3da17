//! The refiner's file format (`models/assets/refiner.bin`), in the one framing of
//! [`holoface_protocol::framing`]; little-endian:
//!
//! ```text
//! magic      8 bytes  "HFREFINE"
//! version    u32      1, 2 or 3
//! length     u32      (version 3 only: the payload's length; versions 1 and 2 run to the CRC)
//! payload:
//!   name       u16 length + UTF-8 (at most 128 bytes)
//!   crop_size  u16      16..=1024
//!   depth      u8       1..=8
//!   starts     u8       1..=9 (refine from this many starts and take the per-coordinate median)
//!   mirror     u8       1 = also refine the mirror image and answer the mean, 0 = not
//!   sampling   u8       (versions 2 and 3) 0 = nearest pixel, 1 = bilinear; version 1 is nearest
//!   stages     u16      1..=64
//!   mean       68 x (f32 x, f32 y)
//!   per stage:
//!     features u16      2..=4096
//!     trees    u32      1..=20000
//!     anchors  features x u8 (< 68)
//!     offsets  features x (f32, f32)
//!     per tree: (2^depth - 1) x (u16 u, u16 v, f32 threshold), then 2^depth leaves of
//!               (f32 scale, 136 x i8 values): increment = scale x value
//! crc32      u32      of every byte before it
//! ```
//!
//! This build writes version 3; versions 1 and 2 (the files of builds before the framing was shared, the
//! shipped `refiner.bin` among them) are read as they are. Every count is checked against its bound and
//! against the bytes left before anything is allocated; every index and float is validated, so a damaged
//! file is a [`FormatError`] naming the field, never a panic.

use holoface_protocol::framing::{self, Format, FormatError, PayloadReader};

use super::{
    REFINE_LANDMARKS, RefineCascade, RefineError, RefineStage, RegressionTree, SHAPE_DIM, Sampling, SplitTest,
};
use crate::geometry::Point2;

/// File magic.
pub const MAGIC: &[u8; 8] = b"HFREFINE";
/// Newest format version (3: the payload's length in the header; 2 added the sampling byte).
pub const FORMAT_VERSION: u32 = 3;
/// The file in the one framing.
pub const FILE: Format = Format {
    name: "refiner model",
    magic: *MAGIC,
    oldest: 1,
    newest: FORMAT_VERSION,
    sized_from: 3,
    max_payload: 256 << 20,
};
const MAX_NAME: usize = 128;
const MAX_STAGES: u16 = 64;
const MAX_FEATURES: u16 = 4096;
const MAX_TREES: u32 = 20_000;
const MAX_DEPTH: u8 = 8;

impl RefineCascade {
    /// The model as file bytes (the newest version).
    ///
    /// # Errors
    /// The model is over the format's 256-MiB payload limit.
    pub fn to_bytes(&self) -> Result<Vec<u8>, RefineError> {
        let mut out = Vec::new();
        let name = self.name.as_bytes();
        let name = &name[..name.len().min(MAX_NAME)];
        out.extend_from_slice(&(name.len() as u16).to_le_bytes());
        out.extend_from_slice(name);
        out.extend_from_slice(&(self.crop_size as u16).to_le_bytes());
        out.push(self.depth as u8);
        out.push(self.starts as u8);
        out.push(u8::from(self.mirror));
        out.push(u8::from(self.sampling == Sampling::Bilinear));
        out.extend_from_slice(&(self.stages.len() as u16).to_le_bytes());
        for p in &self.mean {
            out.extend_from_slice(&p.x.to_le_bytes());
            out.extend_from_slice(&p.y.to_le_bytes());
        }
        for s in &self.stages {
            out.extend_from_slice(&(s.anchors.len() as u16).to_le_bytes());
            out.extend_from_slice(&(s.trees.len() as u32).to_le_bytes());
            out.extend_from_slice(&s.anchors);
            for o in &s.offsets {
                out.extend_from_slice(&o[0].to_le_bytes());
                out.extend_from_slice(&o[1].to_le_bytes());
            }
            for t in &s.trees {
                for sp in &t.splits {
                    out.extend_from_slice(&sp.u.to_le_bytes());
                    out.extend_from_slice(&sp.v.to_le_bytes());
                    out.extend_from_slice(&sp.threshold.to_le_bytes());
                }
                for (leaf, scale) in t.values.chunks_exact(SHAPE_DIM).zip(&t.scales) {
                    out.extend_from_slice(&scale.to_le_bytes());
                    out.extend(leaf.iter().map(|v| v.to_le_bytes()[0]));
                }
            }
        }
        Ok(framing::encode(&FILE, &out)?)
    }

    /// CRC-32 of a model file's contents (its last four bytes): the model's identity in logs and metrics.
    pub fn file_crc(bytes: &[u8]) -> Option<u32> {
        let b = bytes.get(bytes.len().checked_sub(4)?..)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// Loads a model from file bytes, validating everything.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, RefineError> {
        let framed = framing::decode(&FILE, bytes)?;
        let mut r = framed.payload;
        let name = r.text("name length", MAX_NAME)?.to_owned();
        let crop_size = usize::from(r.u16_in("crop size", 16, 1024)?);
        let depth = usize::from(r.u8_in("tree depth", 1, MAX_DEPTH)?);
        let starts = usize::from(r.u8_in("starts", 1, super::START_OFFSETS.len() as u8)?);
        let mirror = r.u8_in("mirror flag", 0, 1)? == 1;
        let sampling = match framed.version {
            1 => Sampling::Nearest,
            _ => match r.u8_in("sampling", 0, 1)? {
                0 => Sampling::Nearest,
                _ => Sampling::Bilinear,
            },
        };
        let n_stages = usize::from(r.u16_in("stage count", 1, MAX_STAGES)?);
        let mut mean = [Point2::default(); REFINE_LANDMARKS];
        for (i, p) in mean.iter_mut().enumerate() {
            *p = Point2::new(r.f32("mean shape", 2 * i)?, r.f32("mean shape", 2 * i + 1)?);
        }
        let mut stages = Vec::with_capacity(n_stages);
        for si in 0..n_stages {
            stages.push(read_stage(&mut r, si, depth)?);
        }
        r.finish()?;
        Ok(Self {
            crop_size,
            depth,
            mean,
            stages,
            name,
            starts,
            mirror,
            sampling,
        })
    }
}

/// Stage `si` of a cascade of trees of `depth`, read and checked.
fn read_stage(r: &mut PayloadReader<'_>, si: usize, depth: usize) -> Result<RefineStage, FormatError> {
    let n_splits = (1usize << depth) - 1;
    let n_leaves = 1usize << depth;
    let tree_bytes = n_splits * 8 + n_leaves * (4 + SHAPE_DIM);
    let n_feat = usize::from(r.u16_in("feature count", 2, MAX_FEATURES)?);
    let n_trees = r.count("tree count", 1, MAX_TREES)? as usize;
    r.need((n_feat * 9 + n_trees * tree_bytes) as u64)?;
    let anchors = r.take(n_feat)?.to_vec();
    if let Some(&a) = anchors.iter().find(|&&a| usize::from(a) >= REFINE_LANDMARKS) {
        return Err(r.invalid(
            "anchors",
            format!("stage {si}: landmark {a} (< {REFINE_LANDMARKS})"),
        ));
    }
    let mut offsets = Vec::with_capacity(n_feat);
    for i in 0..n_feat {
        offsets.push([r.f32("offset", 2 * i)?, r.f32("offset", 2 * i + 1)?]);
    }
    let mut trees = Vec::with_capacity(n_trees);
    for ti in 0..n_trees {
        trees.push(read_tree(r, (si, ti), n_feat, depth)?);
    }
    Ok(RefineStage {
        anchors,
        offsets,
        trees,
    })
}

/// Tree `ti` of stage `si`, over `n_feat` features, of `depth`, read and checked.
fn read_tree(
    r: &mut PayloadReader<'_>,
    (si, ti): (usize, usize),
    n_feat: usize,
    depth: usize,
) -> Result<RegressionTree, FormatError> {
    let (n_splits, n_leaves) = ((1usize << depth) - 1, 1usize << depth);
    let mut splits = Vec::with_capacity(n_splits);
    for i in 0..n_splits {
        let (u, v) = (r.u16()?, r.u16()?);
        let threshold = r.f32("threshold", i)?;
        if usize::from(u.max(v)) >= n_feat {
            let reason = format!("stage {si} tree {ti}: feature {} of {n_feat}", u.max(v));
            return Err(r.invalid("split", reason));
        }
        splits.push(SplitTest { u, v, threshold });
    }
    let mut scales = Vec::with_capacity(n_leaves);
    let mut values = Vec::with_capacity(n_leaves * SHAPE_DIM);
    for i in 0..n_leaves {
        let scale = r.f32("leaf scale", i)?;
        if scale < 0.0 {
            return Err(r.invalid("leaf scale", format!("stage {si} tree {ti}: negative")));
        }
        scales.push(scale);
        values.extend(r.take(SHAPE_DIM)?.iter().map(|b| i8::from_le_bytes([*b])));
    }
    Ok(RegressionTree {
        splits,
        scales,
        values,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use holoface_protocol::framing::Damage;

    use super::*;
    use crate::refine::tests::tiny;

    /// The file with its checksum recomputed: a consistent checksum over edited content.
    fn reseal(mut b: Vec<u8>) -> Vec<u8> {
        b.truncate(b.len() - 4);
        let c = crc32fast::hash(&b);
        b.extend_from_slice(&c.to_le_bytes());
        b
    }

    /// The file as a build before the one framing wrote it: no length field, and version 1 (nearest, no
    /// sampling byte) or 2.
    fn legacy(v3: &[u8], version: u32) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&version.to_le_bytes());
        let payload = &v3[16..v3.len() - 4];
        // The sampling byte follows name (2 + 4), crop size, depth, starts and mirror.
        let sampling = 2 + 4 + 2 + 3;
        out.extend_from_slice(&payload[..sampling]);
        if version >= 2 {
            out.push(payload[sampling]);
        }
        out.extend_from_slice(&payload[sampling + 1..]);
        out.extend_from_slice(&[0; 4]);
        reseal(out)
    }

    fn damage(b: &[u8]) -> Damage {
        match RefineCascade::from_bytes(b) {
            Err(RefineError::Format(e)) => {
                assert_eq!(e.file, "refiner model");
                e.damage
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn round_trip_keeps_the_model() {
        let r = tiny(0.5, -1.25);
        let bytes = r.to_bytes().unwrap();
        let back = RefineCascade::from_bytes(&bytes).unwrap();
        assert_eq!(back, r);
        assert_eq!(
            RefineCascade::file_crc(&bytes),
            Some(crc32fast::hash(&bytes[..bytes.len() - 4]))
        );
    }

    /// The layout is pinned: a one-stage, one-tree, depth-1 model with two features.
    #[test]
    fn the_byte_layout_is_pinned() {
        let bytes = tiny(0.5, -1.25).to_bytes().unwrap();
        let head = 16 + 2 + 4 + 2 + 1 + 1 + 1 + 1 + 2;
        assert_eq!(&bytes[..8], b"HFREFINE");
        assert_eq!(&bytes[8..12], &3u32.to_le_bytes());
        assert_eq!(&bytes[12..16], &((bytes.len() - 20) as u32).to_le_bytes());
        assert_eq!(&bytes[16..18], &4u16.to_le_bytes());
        assert_eq!(&bytes[18..22], b"tiny");
        assert_eq!(&bytes[22..24], &112u16.to_le_bytes());
        assert_eq!(bytes[24], 1);
        assert_eq!(bytes[25], 1, "one start");
        assert_eq!(bytes[26], 0, "no mirror");
        assert_eq!(bytes[27], 0, "nearest pixel");
        assert_eq!(&bytes[28..30], &1u16.to_le_bytes());
        let stage = head + 68 * 8;
        assert_eq!(&bytes[stage..stage + 2], &2u16.to_le_bytes());
        assert_eq!(&bytes[stage + 2..stage + 6], &1u32.to_le_bytes());
        assert_eq!(&bytes[stage + 6..stage + 8], &[30, 30]);
        let tree = stage + 8 + 2 * 8;
        assert_eq!(&bytes[tree..tree + 4], &[0, 0, 1, 0]);
        assert_eq!(&bytes[tree + 4..tree + 8], &20.0f32.to_le_bytes());
        // Left leaf: every value 0.5 = (0.5 / 127) x 127; right leaf: -1.25 = (1.25 / 127) x -127.
        assert_eq!(&bytes[tree + 8..tree + 12], &(0.5f32 / 127.0).to_le_bytes());
        assert!(bytes[tree + 12..tree + 12 + 136].iter().all(|&b| b == 127));
        let right = tree + 12 + 136;
        assert_eq!(&bytes[right..right + 4], &(1.25f32 / 127.0).to_le_bytes());
        assert!(bytes[right + 4..right + 4 + 136].iter().all(|&b| b as i8 == -127));
        assert_eq!(bytes.len(), tree + 8 + 2 * (4 + 136) + 4);
    }

    /// Files of older builds (version 1 nearest-pixel, version 2 with its sampling byte and no length
    /// field, as the shipped `refiner.bin`) load as the same model.
    #[test]
    fn versions_1_and_2_still_load() {
        let nearest = tiny(0.5, -1.25);
        let mut bilinear = nearest.clone();
        bilinear.sampling = Sampling::Bilinear;
        let v1 = legacy(&nearest.to_bytes().unwrap(), 1);
        assert_eq!(RefineCascade::from_bytes(&v1).unwrap(), nearest);
        let v2 = legacy(&bilinear.to_bytes().unwrap(), 2);
        assert_eq!(v2.len(), v1.len() + 1);
        assert_eq!(RefineCascade::from_bytes(&v2).unwrap(), bilinear);
        let mut bad = v2.clone();
        bad[23] = 7;
        assert!(matches!(
            damage(&reseal(bad)),
            Damage::OutOfRange {
                field: "sampling",
                value: 7,
                ..
            }
        ));
    }

    #[test]
    fn damaged_files_are_clear_errors() {
        let good = tiny(0.5, -1.25).to_bytes().unwrap();
        assert!(matches!(damage(b""), Damage::Truncated { .. }));
        assert!(matches!(damage(b"GARBAGE!GARBAGE!"), Damage::BadMagic { .. }));
        let mut flipped = good.clone();
        flipped[40] ^= 1;
        assert!(matches!(damage(&flipped), Damage::Checksum { .. }));
        assert!(matches!(
            damage(&good[..good.len() - 10]),
            Damage::Truncated { needed: 10, .. }
        ));
        // A consistent checksum over inconsistent content: each check still names the field.
        let field = |offset: usize, value: u8| {
            let mut b = good.clone();
            b[offset] = value;
            match damage(&reseal(b)) {
                Damage::OutOfRange { field, .. } | Damage::Invalid { field, .. } => field,
                d => panic!("{d:?}"),
            }
        };
        assert!(matches!(
            damage(&reseal({
                let mut v = good.clone();
                v[8] = 9;
                v
            })),
            Damage::UnsupportedVersion { found: 9, .. }
        ));
        assert_eq!(field(24, 30), "tree depth");
        assert_eq!(field(25, 10), "starts");
        assert_eq!(field(26, 2), "mirror flag");
        assert_eq!(field(27, 2), "sampling");
        let stage = 30 + 68 * 8;
        let mut t = good.clone();
        t[stage + 2..stage + 6].copy_from_slice(&5000u32.to_le_bytes());
        assert!(matches!(damage(&reseal(t)), Damage::Truncated { .. }));
        assert_eq!(field(stage + 6, 68), "anchors");
        let tree = stage + 8 + 16;
        assert_eq!(field(tree, 7), "split");
        let mut n = good.clone();
        n[tree + 4..tree + 8].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(matches!(
            damage(&reseal(n)),
            Damage::NotFinite {
                field: "threshold",
                ..
            }
        ));
        let mut extra = good[..good.len() - 4].to_vec();
        extra.push(0);
        let len = (extra.len() - 16) as u32;
        extra[12..16].copy_from_slice(&len.to_le_bytes());
        extra.extend_from_slice(&[0; 4]);
        assert!(matches!(
            damage(&reseal(extra)),
            Damage::TrailingBytes { count: 1 }
        ));
    }
}
