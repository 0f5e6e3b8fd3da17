//! Teacher-label files (`.hflabels`): 68 landmarks per unannotated face photograph, made by `holoface
//! teacher-labels` and read by the trainers (`train-refiner --teacher-labels`, `train-krfws
//! --teacher-labels`).
//!
//! Layout: the one framing of [`holoface_protocol::framing`] (magic `HFLABELS`, version 2, length, payload,
//! CRC-32); the payload (little-endian) is a `u32` header length + UTF-8 JSON header ([`LabelHeader`]: the
//! collection, the folder its images are in, the teachers and thresholds), `u32` record count, then per record
//! `u16` name length + UTF-8 name (the image's path relative to the folder), 136 `f32` (x, y of the 68 points
//! in the image's pixels) and one `f32` (the teachers' disagreement, NME68). Every length is bounded and
//! checked before anything is allocated for it. Version 1 (magic `HFLABEL1`, before the framing was shared)
//! is not read: label files are remade by `make teacher-labels`, never shipped.
//!
//! These files hold labels of other people's photographs: they live in the git-ignored `.data/` folder and
//! are never committed (`../shared/docs/data.md`).

use std::path::{Path, PathBuf};

use anyhow::{Context, bail, ensure};
use holoface_models::geometry::Point2;
use holoface_protocol::framing::{self, Format, FormatError};
use serde::{Deserialize, Serialize};

use holoface_harness::data::Sample;

/// Largest label file read (a 45,000-face collection is about 25 MB).
pub const MAX_FILE_BYTES: u64 = 512 << 20;
/// Label files in the one framing.
pub const FILE: Format = Format {
    name: "teacher labels",
    magic: *b"HFLABELS",
    oldest: 2,
    newest: 2,
    sized_from: 2,
    max_payload: MAX_FILE_BYTES - 20,
};
const MAX_HEADER: usize = 64 << 10;
const MAX_NAME: usize = 4096;
const RECORD_FLOATS: usize = 137;

/// What a label file says about itself.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LabelHeader {
    /// Collection name (`lfw`, `utkface`, ...).
    pub collection: String,
    /// The folder the record names are relative to.
    pub images: PathBuf,
    /// The teachers and how they were combined (free text for the model cards).
    pub teachers: String,
    /// Free-form settings (thresholds, weights) as JSON.
    pub settings: serde_json::Value,
}

/// One labelled face.
#[derive(Clone, Debug, PartialEq)]
pub struct LabelRecord {
    /// Image path relative to [`LabelHeader::images`].
    pub name: String,
    /// The kept label, in the image's pixels.
    pub landmarks: [Point2; 68],
    /// How much the teachers disagreed (NME68, outer-eye-corner normalised).
    pub disagreement: f32,
}

/// Serialises a label file.
pub fn to_bytes(header: &LabelHeader, records: &[LabelRecord]) -> anyhow::Result<Vec<u8>> {
    let head = serde_json::to_vec(header)?;
    ensure!(head.len() <= MAX_HEADER, "label header too large");
    let mut out = Vec::with_capacity(8 + head.len() + records.len() * (RECORD_FLOATS * 4 + 40));
    out.extend_from_slice(&(head.len() as u32).to_le_bytes());
    out.extend_from_slice(&head);
    out.extend_from_slice(&u32::try_from(records.len())?.to_le_bytes());
    for r in records {
        ensure!(r.name.len() <= MAX_NAME, "image name too long: {}", r.name);
        out.extend_from_slice(&(r.name.len() as u16).to_le_bytes());
        out.extend_from_slice(r.name.as_bytes());
        for p in &r.landmarks {
            out.extend_from_slice(&p.x.to_le_bytes());
            out.extend_from_slice(&p.y.to_le_bytes());
        }
        out.extend_from_slice(&r.disagreement.to_le_bytes());
    }
    Ok(framing::encode(&FILE, &out)?)
}

/// Parses a label file, checking its checksum, every length and every number.
pub fn from_bytes(bytes: &[u8]) -> Result<(LabelHeader, Vec<LabelRecord>), FormatError> {
    let mut r = framing::decode(&FILE, bytes)?.payload;
    let head_len = r.count("header length", 0, MAX_HEADER as u32)? as usize;
    let header: LabelHeader =
        serde_json::from_slice(r.take(head_len)?).map_err(|e| r.invalid("header", e.to_string()))?;
    let count = r.u32()? as usize;
    // Each record takes at least its points: a count the file cannot hold is refused before allocating.
    r.need((count as u64).saturating_mul((RECORD_FLOATS * 4 + 2) as u64))?;
    let mut records = Vec::with_capacity(count);
    for i in 0..count {
        let name = r.text("image name", MAX_NAME)?.to_owned();
        if name.is_empty() || Path::new(&name).is_absolute() || name.split('/').any(|p| p == "..") {
            let reason = format!("record {i}: {name:?} is not a path inside the collection");
            return Err(r.invalid("image name", reason));
        }
        let mut landmarks = [Point2::default(); 68];
        for (k, p) in landmarks.iter_mut().enumerate() {
            *p = Point2::new(r.f32("landmarks", 2 * k)?, r.f32("landmarks", 2 * k + 1)?);
        }
        let disagreement = r.f32("disagreement", i)?;
        records.push(LabelRecord {
            name,
            landmarks,
            disagreement,
        });
    }
    r.finish()?;
    Ok((header, records))
}

/// Reads a label file (bounded by [`MAX_FILE_BYTES`]).
pub fn read(path: &Path) -> anyhow::Result<(LabelHeader, Vec<LabelRecord>)> {
    let len = std::fs::metadata(path)
        .with_context(|| {
            format!(
                "reading teacher labels {} (make teacher-labels writes them)",
                path.display()
            )
        })?
        .len();
    if len > MAX_FILE_BYTES {
        bail!(
            "{} is {len} bytes, more than a label file can be ({MAX_FILE_BYTES})",
            path.display()
        );
    }
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    from_bytes(&bytes).with_context(|| {
        format!(
            "parsing teacher labels {} (make it again with `make teacher-labels`)",
            path.display()
        )
    })
}

/// The labelled faces of a label file as training samples (images decoded; an unreadable image is an error
/// naming it). At most `limit` faces, taken evenly over the file when it holds more.
pub fn load_samples(path: &Path, limit: Option<usize>) -> anyhow::Result<Vec<Sample>> {
    load_samples_where(path, limit, |_| true)
}

/// [`load_samples`] of the faces whose label `keep` accepts (the filter runs before any image is decoded; the
/// limit applies to the kept faces).
pub fn load_samples_where(
    path: &Path,
    limit: Option<usize>,
    keep: impl Fn(&[Point2; 68]) -> bool,
) -> anyhow::Result<Vec<Sample>> {
    let (header, mut records) = read(path)?;
    records.retain(|r| keep(&r.landmarks));
    let take = limit.unwrap_or(records.len()).min(records.len());
    let mut out = Vec::with_capacity(take);
    for k in 0..take {
        // Evenly spaced, so a limit does not keep only the first folders of a collection.
        let r = &records[k * records.len() / take.max(1)];
        let image = holoface_sources::images::read_gray(&header.images.join(&r.name))
            .with_context(|| format!("teacher labels {}: image {}", path.display(), r.name))?;
        out.push(Sample {
            name: format!("{}/{}", header.collection, r.name),
            image,
            landmarks: Some(r.landmarks),
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use holoface_protocol::framing::Damage;

    use super::*;

    fn sample() -> (LabelHeader, Vec<LabelRecord>) {
        let header = LabelHeader {
            collection: "lfw".into(),
            images: PathBuf::from("/data/lfw"),
            teachers: "dlib + remote".into(),
            settings: serde_json::json!({"max_disagreement": 0.05}),
        };
        let records = (0..3)
            .map(|i| LabelRecord {
                name: format!("a/img{i}.jpg"),
                landmarks: std::array::from_fn(|k| Point2::new(k as f32 + i as f32, 2.0 * k as f32)),
                disagreement: 0.01 * i as f32,
            })
            .collect();
        (header, records)
    }

    #[test]
    fn round_trips() {
        let (h, r) = sample();
        let bytes = to_bytes(&h, &r).unwrap();
        assert_eq!(from_bytes(&bytes).unwrap(), (h, r));
    }

    #[test]
    fn damage_is_refused_with_a_reason() {
        let (h, r) = sample();
        let bytes = to_bytes(&h, &r).unwrap();
        assert_eq!(&bytes[..8], b"HFLABELS");
        // Any flipped byte: the checksum catches it.
        for at in [0, 9, 40, bytes.len() / 2, bytes.len() - 5] {
            let mut bad = bytes.clone();
            bad[at] ^= 0x20;
            assert!(from_bytes(&bad).is_err(), "byte {at}");
        }
        // Truncated anywhere.
        for n in [0, 10, bytes.len() - 1] {
            assert!(matches!(
                from_bytes(&bytes[..n]).unwrap_err().damage,
                Damage::Truncated { .. }
            ));
        }
        // A huge count with a valid checksum: refused before allocating.
        let mut body = bytes[16..bytes.len() - 4].to_vec();
        let count_at = 4 + u32::from_le_bytes(body[..4].try_into().unwrap()) as usize;
        body[count_at..count_at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        let err = from_bytes(&framing::encode(&FILE, &body).unwrap()).unwrap_err();
        assert!(matches!(err.damage, Damage::Truncated { .. }), "{err}");
    }

    #[test]
    fn the_filter_picks_faces_before_any_image_is_decoded() {
        let dir = std::env::temp_dir().join(format!("holoface-labels-where-{}", std::process::id()));
        std::fs::create_dir_all(dir.join("a")).unwrap();
        let (mut h, mut r) = sample();
        h.images = dir.clone();
        for (i, rec) in r.iter_mut().enumerate() {
            rec.name = format!("a/img{i}.png");
        }
        image::GrayImage::from_pixel(8, 6, image::Luma([7]))
            .save(dir.join("a/img1.png"))
            .unwrap();
        // img0 is missing and img2 is not an image: only the filter keeps them from failing the load.
        std::fs::write(dir.join("a/img2.png"), b"not a png").unwrap();
        let path = dir.join("labels.hflabels");
        std::fs::write(&path, to_bytes(&h, &r).unwrap()).unwrap();

        let kept = load_samples_where(&path, None, |l| l[0].x == 1.0).unwrap();
        assert_eq!(kept.len(), 1);
        assert_eq!(kept[0].name, "lfw/a/img1.png");
        assert_eq!((kept[0].image.width(), kept[0].image.height()), (8, 6));
        assert_eq!(kept[0].landmarks, Some(r[1].landmarks));
        let err = format!("{:#}", load_samples(&path, None).unwrap_err());
        assert!(err.contains("img0.png"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn names_outside_the_collection_are_refused() {
        let (h, mut r) = sample();
        r[1].name = "../../etc/passwd".into();
        let err = from_bytes(&to_bytes(&h, &r).unwrap()).unwrap_err().to_string();
        assert!(
            err.contains("not a path inside") && err.starts_with("teacher labels: "),
            "{err}"
        );
    }
}
