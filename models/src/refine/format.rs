//! The refiner's file format (`models/assets/refiner.bin`), little-endian:
//!
//! ```text
//! magic      8 bytes  "HFREFINE"
//! version    u32      1 or 2
//! name       u16 length + UTF-8 (at most 128 bytes)
//! crop_size  u16      16..=1024
//! depth      u8       1..=8
//! starts     u8       1..=9 (refine from this many starts and take the per-coordinate median)
//! mirror     u8       1 = also refine the mirror image and answer the mean, 0 = not
//! sampling   u8       (version 2 only) 0 = nearest pixel, 1 = bilinear; version 1 is nearest
//! stages     u16      1..=64
//! mean       68 x (f32 x, f32 y)
//! per stage:
//!   features u16      2..=4096
//!   trees    u32      1..=20000
//!   anchors  features x u8 (< 68)
//!   offsets  features x (f32, f32)
//!   per tree: (2^depth - 1) x (u16 u, u16 v, f32 threshold), then 2^depth leaves of
//!             (f32 scale, 136 x i8 values): increment = scale x value
//! crc32      u32      of every byte before it
//! ```
//!
//! Every count is checked against its bound and against the bytes left before anything is allocated;
//! every index and float is validated, so a damaged file is an error naming what is wrong, never a panic.

use super::{
    REFINE_LANDMARKS, RefineCascade, RefineError, RefineStage, RegressionTree, SHAPE_DIM, Sampling, SplitTest,
};
use crate::geometry::Point2;

/// File magic.
pub const MAGIC: &[u8; 8] = b"HFREFINE";
/// Newest format version (2: the sampling byte). A nearest-pixel model is written as version 1, so the
/// files of older builds stay byte for byte the same.
pub const FORMAT_VERSION: u32 = 2;
const MAX_NAME: usize = 128;
const MAX_STAGES: usize = 64;
const MAX_FEATURES: usize = 4096;
const MAX_TREES: usize = 20_000;
const MAX_DEPTH: usize = 8;

fn bad(msg: impl Into<String>) -> RefineError {
    RefineError::Format(msg.into())
}

struct Reader<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], RefineError> {
        let end = self.pos.checked_add(n).filter(|&e| e <= self.data.len());
        let end = end.ok_or_else(|| bad(format!("truncated in {what} (offset {})", self.pos)))?;
        let s = &self.data[self.pos..end];
        self.pos = end;
        Ok(s)
    }
    fn left(&self) -> usize {
        self.data.len() - self.pos
    }
    fn u8(&mut self, what: &str) -> Result<u8, RefineError> {
        Ok(self.take(1, what)?[0])
    }
    fn u16(&mut self, what: &str) -> Result<u16, RefineError> {
        let b = self.take(2, what)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&mut self, what: &str) -> Result<u32, RefineError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn f32(&mut self, what: &str) -> Result<f32, RefineError> {
        let v = f32::from_bits(self.u32(what)?);
        if v.is_finite() {
            Ok(v)
        } else {
            Err(bad(format!("{what} is not finite")))
        }
    }
}

impl RefineCascade {
    /// The model as file bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(MAGIC);
        let version: u32 = match self.sampling {
            Sampling::Nearest => 1,
            Sampling::Bilinear => FORMAT_VERSION,
        };
        out.extend_from_slice(&version.to_le_bytes());
        let name = self.name.as_bytes();
        let name = &name[..name.len().min(MAX_NAME)];
        out.extend_from_slice(&(name.len() as u16).to_le_bytes());
        out.extend_from_slice(name);
        out.extend_from_slice(&(self.crop_size as u16).to_le_bytes());
        out.push(self.depth as u8);
        out.push(self.starts as u8);
        out.push(u8::from(self.mirror));
        if version >= 2 {
            out.push(u8::from(self.sampling == Sampling::Bilinear));
        }
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
        let crc = crc32fast::hash(&out);
        out.extend_from_slice(&crc.to_le_bytes());
        out
    }

    /// CRC-32 of a model file's contents (its last four bytes): the model's identity in logs and metrics.
    pub fn file_crc(bytes: &[u8]) -> Option<u32> {
        let b = bytes.get(bytes.len().checked_sub(4)?..)?;
        Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// Loads a model from file bytes, validating everything.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, RefineError> {
        if bytes.len() < MAGIC.len() + 8 || &bytes[..MAGIC.len()] != MAGIC {
            return Err(bad("not a refiner model (bad magic)"));
        }
        let (body, crc) = bytes.split_at(bytes.len() - 4);
        let stored = u32::from_le_bytes([crc[0], crc[1], crc[2], crc[3]]);
        if crc32fast::hash(body) != stored {
            return Err(bad("checksum mismatch: the file is damaged"));
        }
        let mut r = Reader {
            data: body,
            pos: MAGIC.len(),
        };
        let version = r.u32("version")?;
        if !(1..=FORMAT_VERSION).contains(&version) {
            return Err(bad(format!(
                "format version {version}, this build reads 1..={FORMAT_VERSION}"
            )));
        }
        let name_len = usize::from(r.u16("name length")?);
        if name_len > MAX_NAME {
            return Err(bad(format!("name of {name_len} bytes (at most {MAX_NAME})")));
        }
        let name = std::str::from_utf8(r.take(name_len, "name")?)
            .map_err(|_| bad("name is not UTF-8"))?
            .to_owned();
        let crop_size = usize::from(r.u16("crop size")?);
        if !(16..=1024).contains(&crop_size) {
            return Err(bad(format!("crop size {crop_size} (16..=1024)")));
        }
        let depth = usize::from(r.u8("depth")?);
        if !(1..=MAX_DEPTH).contains(&depth) {
            return Err(bad(format!("tree depth {depth} (1..={MAX_DEPTH})")));
        }
        let starts = usize::from(r.u8("starts")?);
        if !(1..=super::START_OFFSETS.len()).contains(&starts) {
            return Err(bad(format!(
                "{starts} starts (1..={})",
                super::START_OFFSETS.len()
            )));
        }
        let mirror = match r.u8("mirror")? {
            0 => false,
            1 => true,
            v => return Err(bad(format!("mirror flag {v} (0 or 1)"))),
        };
        let sampling = match version {
            1 => Sampling::Nearest,
            _ => match r.u8("sampling")? {
                0 => Sampling::Nearest,
                1 => Sampling::Bilinear,
                v => return Err(bad(format!("sampling {v} (0 nearest or 1 bilinear)"))),
            },
        };
        let n_stages = usize::from(r.u16("stage count")?);
        if !(1..=MAX_STAGES).contains(&n_stages) {
            return Err(bad(format!("{n_stages} stages (1..={MAX_STAGES})")));
        }
        let mut mean = [Point2::default(); REFINE_LANDMARKS];
        for p in &mut mean {
            *p = Point2::new(r.f32("mean shape")?, r.f32("mean shape")?);
        }
        let mut stages = Vec::with_capacity(n_stages);
        for si in 0..n_stages {
            stages.push(read_stage(&mut r, si, depth)?);
        }
        if r.left() != 0 {
            return Err(bad(format!("{} bytes after the last stage", r.left())));
        }
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
fn read_stage(r: &mut Reader<'_>, si: usize, depth: usize) -> Result<RefineStage, RefineError> {
    let n_splits = (1usize << depth) - 1;
    let n_leaves = 1usize << depth;
    let tree_bytes = n_splits * 8 + n_leaves * (4 + SHAPE_DIM);
    let n_feat = usize::from(r.u16("feature count")?);
    if !(2..=MAX_FEATURES).contains(&n_feat) {
        return Err(bad(format!("stage {si}: {n_feat} features (2..={MAX_FEATURES})")));
    }
    let n_trees = r.u32("tree count")? as usize;
    if !(1..=MAX_TREES).contains(&n_trees) {
        return Err(bad(format!("stage {si}: {n_trees} trees (1..={MAX_TREES})")));
    }
    if n_feat * 9 + n_trees * tree_bytes > r.left() {
        return Err(bad(format!(
            "stage {si}: {n_trees} trees of depth {depth} need more bytes than the file has"
        )));
    }
    let anchors = r.take(n_feat, "anchors")?.to_vec();
    if let Some(a) = anchors.iter().find(|&&a| usize::from(a) >= REFINE_LANDMARKS) {
        return Err(bad(format!(
            "stage {si}: anchor landmark {a} (< {REFINE_LANDMARKS})"
        )));
    }
    let mut offsets = Vec::with_capacity(n_feat);
    for _ in 0..n_feat {
        offsets.push([r.f32("offset")?, r.f32("offset")?]);
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

/// Tree `ti` of stage `si` (`at`), over `n_feat` features, of `depth`, read and checked.
fn read_tree(
    r: &mut Reader<'_>,
    (si, ti): (usize, usize),
    n_feat: usize,
    depth: usize,
) -> Result<RegressionTree, RefineError> {
    let (n_splits, n_leaves) = ((1usize << depth) - 1, 1usize << depth);
    let mut splits = Vec::with_capacity(n_splits);
    for _ in 0..n_splits {
        let (u, v) = (r.u16("split")?, r.u16("split")?);
        let threshold = r.f32("threshold")?;
        if usize::from(u.max(v)) >= n_feat {
            return Err(bad(format!(
                "stage {si} tree {ti}: feature {} of {n_feat}",
                u.max(v)
            )));
        }
        splits.push(SplitTest { u, v, threshold });
    }
    let mut scales = Vec::with_capacity(n_leaves);
    let mut values = Vec::with_capacity(n_leaves * SHAPE_DIM);
    for _ in 0..n_leaves {
        let scale = r.f32("leaf scale")?;
        if scale < 0.0 {
            return Err(bad(format!("stage {si} tree {ti}: negative leaf scale")));
        }
        scales.push(scale);
        values.extend(r.take(SHAPE_DIM, "leaf")?.iter().map(|b| i8::from_le_bytes([*b])));
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
    use super::*;
    use crate::refine::tests::tiny;

    /// The file with its checksum recomputed: a consistent checksum over edited content.
    fn reseal(mut b: Vec<u8>) -> Vec<u8> {
        b.truncate(b.len() - 4);
        let c = crc32fast::hash(&b);
        b.extend_from_slice(&c.to_le_bytes());
        b
    }

    #[test]
    fn round_trip_keeps_the_model() {
        let r = tiny(0.5, -1.25);
        let bytes = r.to_bytes();
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
        let bytes = tiny(0.5, -1.25).to_bytes();
        let head = 8 + 4 + 2 + 4 + 2 + 1 + 1 + 1 + 2;
        assert_eq!(&bytes[..8], b"HFREFINE");
        assert_eq!(&bytes[8..12], &1u32.to_le_bytes());
        assert_eq!(&bytes[12..14], &4u16.to_le_bytes());
        assert_eq!(&bytes[14..18], b"tiny");
        assert_eq!(&bytes[18..20], &112u16.to_le_bytes());
        assert_eq!(bytes[20], 1);
        assert_eq!(bytes[21], 1, "one start");
        assert_eq!(bytes[22], 0, "no mirror");
        assert_eq!(&bytes[23..25], &1u16.to_le_bytes());
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

    /// A bilinear model is format v2: one sampling byte after the mirror flag, the rest as v1.
    #[test]
    fn a_bilinear_model_is_version_2_with_its_sampling_byte() {
        let nearest = tiny(0.5, -1.25);
        let mut r = nearest.clone();
        r.sampling = Sampling::Bilinear;
        let (v1, v2) = (nearest.to_bytes(), r.to_bytes());
        assert_eq!(&v2[8..12], &2u32.to_le_bytes());
        assert_eq!(v2[23], 1, "bilinear");
        assert_eq!(v2.len(), v1.len() + 1);
        assert_eq!(&v2[24..v2.len() - 4], &v1[23..v1.len() - 4]);
        assert_eq!(RefineCascade::from_bytes(&v2).unwrap(), r);
        let mut bad = v2.clone();
        bad[23] = 7;
        let err = RefineCascade::from_bytes(&reseal(bad)).unwrap_err().to_string();
        assert!(err.contains("sampling 7"), "{err}");
    }

    #[test]
    fn damaged_files_are_clear_errors() {
        let good = tiny(0.5, -1.25).to_bytes();
        let err = |b: &[u8]| RefineCascade::from_bytes(b).unwrap_err().to_string();
        assert!(err(b"").contains("bad magic"));
        assert!(err(b"GARBAGE!GARBAGE!").contains("bad magic"));
        let mut flipped = good.clone();
        flipped[40] ^= 1;
        assert!(err(&flipped).contains("checksum"), "{}", err(&flipped));
        // Truncation is caught by the checksum (the last four bytes are no longer the CRC).
        assert!(err(&good[..good.len() - 10]).contains("checksum"));
        // A consistent checksum over inconsistent content: each check still names the problem.
        let mut v = good.clone();
        v[8] = 9;
        assert!(err(&reseal(v)).contains("format version 9"));
        let mut d = good.clone();
        d[20] = 30;
        assert!(err(&reseal(d)).contains("tree depth 30"));
        let mut st = good.clone();
        st[21] = 10;
        assert!(err(&reseal(st)).contains("10 starts"));
        let mut sm = good.clone();
        sm[22] = 2;
        assert!(err(&reseal(sm)).contains("mirror flag 2"));
        let stage = 25 + 68 * 8;
        let mut t = good.clone();
        t[stage + 2..stage + 6].copy_from_slice(&5000u32.to_le_bytes());
        assert!(err(&reseal(t)).contains("more bytes than the file has"));
        let mut a = good.clone();
        a[stage + 6] = 68;
        assert!(err(&reseal(a)).contains("anchor landmark 68"));
        let tree = stage + 8 + 16;
        let mut f = good.clone();
        f[tree..tree + 2].copy_from_slice(&7u16.to_le_bytes());
        assert!(err(&reseal(f)).contains("feature 7 of 2"));
        let mut n = good.clone();
        n[tree + 4..tree + 8].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(err(&reseal(n)).contains("not finite"));
        let mut extra = good[..good.len() - 4].to_vec();
        extra.push(0);
        assert!(
            err(&reseal({
                extra.extend_from_slice(&[0; 4]);
                extra
            }))
            .contains("after the last stage")
        );
    }
}
