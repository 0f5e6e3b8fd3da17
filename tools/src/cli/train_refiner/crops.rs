//! The refiner's training crops: starts perturbed as tracking and detection leave them, image augmentation, the
//! wire's JPEG round trip, DAN's answers on them (batched), and the cache of those answers.

use holoface_models::augment::{self, Perturbation};
use holoface_protocol::framing::{Damage, Format, FramedReader, FramedWriter, StreamError};

use super::*;

/// The wire encoding every crop goes through (the client's default).
pub(super) const WIRE: CropCodec = CropCodec::Jpeg {
    quality: holoface_runtime::defaults::CROP_JPEG_QUALITY,
};
/// The cache of DAN's answers, in the one framing (version 3 follows the unframed `HFRDATA2`, which is made
/// again): payload `u16` key length + key, `u64` crop count, then per crop its pixels and 2 x 68 (x, y) `f32`.
pub(super) const CACHE: Format = Format {
    name: "refiner training cache",
    magic: *b"HFRDATA\0",
    oldest: 3,
    newest: 3,
    sized_from: 3,
    max_payload: u32::MAX as u64,
};
pub(super) const BATCH: usize = 16;

/// One crop with DAN's answer on it.
pub(super) struct Answered {
    /// The crop after the JPEG round trip (112² bytes).
    pub(super) crop: Vec<u8>,
    /// DAN's landmarks, in the refiner's crop pixels.
    pub(super) start: [Point2; 68],
    /// Ground truth in the refiner's crop pixels.
    pub(super) target: [Point2; 68],
}

/// The refiner's starts: `shape` moved by a random similarity about its centroid (translation σ `t` of its
/// extent, rotation σ `r_deg`, scale σ `s` clamped to 0.5..=1.6, a narrower range than KRFWS's trainer draws).
pub(super) fn perturb(shape: &[Point2; 68], rng: &mut Rng, t: f64, r_deg: f64, s: f64) -> [Point2; 68] {
    augment::perturb(shape, Perturbation::new(t, r_deg, s).clamp_scale(0.5, 1.6), rng)
}

/// A tracker's start: the truth with per-point alignment noise (σ 2.5 % of the eye-corner distance,
/// about a good tracker's error), then moved by a small similarity (the headset and head motion that
/// motion compensation leaves).
pub(super) fn tracker_start(gt: &[Point2; 68], rng: &mut Rng) -> [Point2; 68] {
    let iod = f64::from(gt[36].dist(gt[45])).max(1.0);
    let noisy: [Point2; 68] = std::array::from_fn(|i| {
        Point2::new(
            gt[i].x + (rng.normal() * 0.025 * iod) as f32,
            gt[i].y + (rng.normal() * 0.025 * iod) as f32,
        )
    });
    perturb(&noisy, rng, 0.03, 3.0, 0.03)
}

/// The JPEG q75 round trip of the wire.
pub(super) fn wire_round_trip(px: &[u8], size: usize) -> anyhow::Result<Vec<u8>> {
    let side = u16::try_from(size).context("crop too large")?;
    let crop = holoface_runtime::crop_codec::encode(WIRE, px, side, side)?;
    Ok(holoface_inference::decode_crop(&crop)?.to_vec())
}

/// A start's crop, after the wire round trip, and the annotation mapped into it.
pub(super) struct CropJob {
    pub(super) crop: Vec<u8>,
    pub(super) target: [Point2; 68],
}

pub(super) fn make_crops(
    image: &GrayView<'_>,
    mean: &[Point2; 68],
    init: &[Point2; 68],
    gt: &[Point2; 68],
    rng: Option<&mut Rng>,
) -> anyhow::Result<CropJob> {
    let sim = crop_from_image(init, mean)?;
    let mut px = vec![0u8; CROP_SIZE * CROP_SIZE];
    warp_bilinear(image, &sim, CROP_SIZE, CROP_SIZE, &mut px)?;
    if let Some(rng) = rng {
        // Its own stream, seeded from the start's (the recipe the shipped model was trained with).
        augment::augment(&mut px, CROP_SIZE, &mut Rng::new(rng.next_u64()));
    }
    Ok(CropJob {
        crop: wire_round_trip(&px, CROP_SIZE)?,
        target: std::array::from_fn(|i| sim.apply(gt[i])),
    })
}

/// Runs DAN on queued crops in batches; keeps the accepted answers.
pub(super) struct DanRunner {
    pub(super) engine: OnnxEngine,
    pub(super) batch: BatchTensor,
    pub(super) outs: Vec<LandmarkOut>,
    pub(super) queued: Vec<CropJob>,
    pub(super) threshold: f32,
    pub(super) answered: Vec<Answered>,
    pub(super) rejected: usize,
}

impl DanRunner {
    pub(super) fn push(&mut self, job: CropJob) -> anyhow::Result<()> {
        self.queued.push(job);
        if self.queued.len() == BATCH {
            self.flush()?;
        }
        Ok(())
    }

    pub(super) fn flush(&mut self) -> anyhow::Result<()> {
        self.batch.clear();
        for j in &self.queued {
            self.batch.push(&j.crop)?;
        }
        self.engine.infer(&self.batch, &mut self.outs)?;
        for (j, o) in self.queued.drain(..).zip(&self.outs) {
            if o.problem(68).is_some() || o.face_prob < self.threshold {
                self.rejected += 1;
                continue;
            }
            self.answered.push(Answered {
                crop: j.crop,
                start: std::array::from_fn(|i| Point2::new(o.landmarks[i][0], o.landmarks[i][1])),
                target: j.target,
            });
        }
        Ok(())
    }
}

/// The key the cache is valid for.
pub(super) fn cache_key(dan_model: &Path, args: &Args, faces: usize) -> anyhow::Result<Vec<u8>> {
    let model = std::fs::read(dan_model).with_context(|| format!("reading {}", dan_model.display()))?;
    let mut key = Vec::new();
    key.extend_from_slice(&crc32fast::hash(&model).to_le_bytes());
    for v in [args.crops, faces, args.seed as usize] {
        key.extend_from_slice(&(v as u64).to_le_bytes());
    }
    Ok(key)
}

/// What the teacher-labelled crops' cache is valid for: which labels, how many faces, how many crops each.
pub(super) fn teacher_cache_key(args: &Args, teacher_faces: usize) -> anyhow::Result<Vec<u8>> {
    let mut labels = crc32fast::Hasher::new();
    for path in &args.teacher_labels {
        labels.update(&std::fs::read(path).with_context(|| format!("reading {}", path.display()))?);
    }
    let mut key = Vec::new();
    for v in [
        u64::from(labels.finalize()),
        teacher_faces as u64,
        args.teacher_crops as u64,
    ] {
        key.extend_from_slice(&v.to_le_bytes());
    }
    Ok(key)
}

/// DAN's answers from the cache at `path` when its key matches, else from `make` (then cached).
pub(super) fn cached_answers(
    path: &Path,
    key: &[u8],
    size: usize,
    runner: &mut DanRunner,
    make: impl FnOnce(&mut DanRunner) -> anyhow::Result<()>,
) -> anyhow::Result<Vec<Answered>> {
    if let Some(a) = read_cache(path, key, size)? {
        tracing::info!(crops = a.len(), cache = %path.display(), "DAN's answers from the cache");
        return Ok(a);
    }
    runner.answered.clear();
    make(runner)?;
    let a = std::mem::take(&mut runner.answered);
    write_cache(path, key, size, &a)?;
    Ok(a)
}

pub(super) fn write_cache(path: &Path, key: &[u8], size: usize, data: &[Answered]) -> anyhow::Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let tmp = path.with_extension("tmp");
    let rec = size * size + 2 * 68 * 8;
    let payload = 2 + key.len() + 8 + data.len() * rec;
    let file = BufWriter::new(std::fs::File::create(&tmp)?);
    let mut w = FramedWriter::new(file, &CACHE, payload as u64)?;
    w.write_all(&u16::try_from(key.len())?.to_le_bytes())?;
    w.write_all(key)?;
    w.write_all(&(data.len() as u64).to_le_bytes())?;
    for a in data {
        debug_assert_eq!(a.crop.len(), size * size);
        w.write_all(&a.crop)?;
        for p in a.start.iter().chain(&a.target) {
            w.write_all(&p.x.to_le_bytes())?;
            w.write_all(&p.y.to_le_bytes())?;
        }
    }
    w.finish()?.into_inner()?.sync_all()?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// The cached answers when the cache at `path` exists, is whole and was made for `key`; `None` (make them
/// again) when it is missing, made for other settings, of an older build or damaged.
pub(super) fn read_cache(path: &Path, key: &[u8], size: usize) -> anyhow::Result<Option<Vec<Answered>>> {
    let Ok(f) = std::fs::File::open(path) else {
        return Ok(None);
    };
    let len = f.metadata()?.len();
    match read_framed_cache(BufReader::new(f), len, key, size) {
        Ok(answers) => Ok(answers),
        Err(StreamError::Format(e)) => {
            tracing::warn!(cache = %path.display(), "{e}; making it again");
            Ok(None)
        }
        Err(StreamError::Io(e)) => Err(anyhow::Error::new(e).context(format!("reading {}", path.display()))),
    }
}

fn read_framed_cache(
    file: impl Read,
    len: u64,
    key: &[u8],
    size: usize,
) -> Result<Option<Vec<Answered>>, StreamError> {
    let mut r = FramedReader::new(file, &CACHE, len)?;
    let mut n = [0u8; 2];
    r.read_exact(&mut n)?;
    let mut stored = vec![0u8; usize::from(u16::from_le_bytes(n))];
    r.read_exact(&mut stored)?;
    if stored != key {
        return Ok(None);
    }
    let mut n = [0u8; 8];
    r.read_exact(&mut n)?;
    let n = u64::from_le_bytes(n);
    let rec = (size * size + 2 * 68 * 8) as u64;
    if n.saturating_mul(rec) != r.left() {
        let fits = r.left() / rec;
        return Err(CACHE
            .error(Damage::OutOfRange {
                field: "crop count",
                value: n,
                min: fits,
                max: fits,
            })
            .into());
    }
    let mut out = Vec::with_capacity(n as usize);
    let mut pts = vec![0u8; 2 * 68 * 8];
    for _ in 0..n {
        let mut crop = vec![0u8; size * size];
        r.read_exact(&mut crop)?;
        r.read_exact(&mut pts)?;
        let f = |i: usize| f32::from_le_bytes([pts[4 * i], pts[4 * i + 1], pts[4 * i + 2], pts[4 * i + 3]]);
        out.push(Answered {
            crop,
            start: std::array::from_fn(|i| Point2::new(f(2 * i), f(2 * i + 1))),
            target: std::array::from_fn(|i| Point2::new(f(136 + 2 * i), f(136 + 2 * i + 1))),
        });
    }
    r.finish()?;
    Ok(Some(out))
}

/// DAN's answers on the augmented crops of `faces` (each face and its mirror, `crops_per_face` starts each);
/// the random streams are numbered from `first` (the teacher-labelled faces follow the annotated ones).
pub(super) fn answer_training_crops(
    faces: &[Sample],
    crops_per_face: &[usize],
    first: usize,
    args: &Args,
    runner: &mut DanRunner,
    detector: &mut holoface_runtime::detect::BlazeFace,
) -> anyhow::Result<()> {
    let mean = dan_mean_shape();
    for (fi, (face, &crops)) in faces.iter().zip(crops_per_face).enumerate() {
        let fi = first + fi;
        if crops == 0 {
            continue;
        }
        let gt0 = face.landmarks.context("annotation missing")?;
        let mirrored = face.image.mirrored();
        for (side, (img, gt)) in [
            (&face.image, gt0),
            (&mirrored, mirror68(&gt0, face.image.width())),
        ]
        .into_iter()
        .enumerate()
        {
            let view = img.view();
            let detected = initial_shape(Some(detector), &mean, &view, &gt)?;
            let boxed = {
                let mut out = [Point2::default(); 68];
                fit_to_box(&mean, &Rect::bounding(&gt).context("empty annotation")?, &mut out);
                out
            };
            let placed = detected.unwrap_or(boxed);
            for k in 0..crops {
                let mut rng = Rng::stream(args.seed, &[fi as u64, side as u64, k as u64]);
                // Starts cycle through what a headset sends: the detector's placement, a tracker's
                // previous landmarks (twice as often: most frames are tracked), a moved detection, a
                // badly placed box.
                let init = match k % 5 {
                    0 => placed,
                    1 | 3 => tracker_start(&gt, &mut rng),
                    2 => perturb(&placed, &mut rng, 0.05, 5.0, 0.05),
                    _ => perturb(&boxed, &mut rng, 0.1, 10.0, 0.1),
                };
                let augmented = k > 0;
                let job = make_crops(&view, &mean, &init, &gt, augmented.then_some(&mut rng))
                    .with_context(|| format!("cropping {}", face.name))?;
                runner.push(job)?;
            }
        }
        if (fi + 1).is_multiple_of(200) {
            tracing::info!(
                faces = fi + 1,
                of = first + faces.len(),
                crops = runner.answered.len(),
                "DAN answered"
            );
        }
    }
    runner.flush()
}

/// Every framed file kind, damaged the same four ways, gives the same structured error: the kind's name and
/// what is wrong. The shipped models still load byte for byte.
#[cfg(test)]
mod framed_files {
    #![allow(clippy::unwrap_used)]
    use holoface_models::krfws::Krfws;
    use holoface_protocol::framing::FormatError;

    use super::*;

    fn shipped(name: &str) -> Vec<u8> {
        std::fs::read(
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../models/assets")
                .join(name),
        )
        .unwrap()
    }

    fn cache_bytes() -> Vec<u8> {
        let path = std::env::temp_dir().join(format!("holoface-cache-{}.bin", std::process::id()));
        let answered = Answered {
            crop: vec![7; 16],
            start: [Point2::new(1.0, 2.0); 68],
            target: [Point2::new(3.0, 4.0); 68],
        };
        write_cache(&path, b"key", 4, &[answered]).unwrap();
        let back = read_cache(&path, b"key", 4).unwrap().unwrap();
        assert_eq!(
            (back.len(), back[0].crop.as_slice(), back[0].target[67]),
            (1, &[7u8; 16][..], Point2::new(3.0, 4.0))
        );
        assert!(
            read_cache(&path, b"other key", 4).unwrap().is_none(),
            "made for other settings"
        );
        let bytes = std::fs::read(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        bytes
    }

    fn labels_bytes() -> Vec<u8> {
        let header = crate::labels::LabelHeader {
            collection: "lfw".into(),
            images: "/data/lfw".into(),
            teachers: "dlib + remote".into(),
            settings: serde_json::json!({}),
        };
        let record = crate::labels::LabelRecord {
            name: "a.jpg".into(),
            landmarks: [Point2::new(5.0, 6.0); 68],
            disagreement: 0.01,
        };
        crate::labels::to_bytes(&header, &[record]).unwrap()
    }

    /// The shipped refiner as this build writes it (version 3): the shipped file is version 2, whose header
    /// has no length, so a truncated one is caught by its checksum instead (checked below).
    fn refiner_v3() -> Vec<u8> {
        let shipped = shipped("refiner.bin");
        let e = load_refiner(&shipped[..shipped.len() - 3]).unwrap_err();
        assert!(matches!(e.damage, Damage::Checksum { .. }), "{e}");
        RefineCascade::from_bytes(&shipped).unwrap().to_bytes().unwrap()
    }

    type Load = fn(&[u8]) -> Result<(), FormatError>;

    fn load_krfws(b: &[u8]) -> Result<(), FormatError> {
        match Krfws::from_bytes(b) {
            Ok(_) => Ok(()),
            Err(holoface_models::krfws::ModelError::Format(e)) => Err(e),
            Err(e) => panic!("not the framing's error: {e}"),
        }
    }

    fn load_refiner(b: &[u8]) -> Result<(), FormatError> {
        match RefineCascade::from_bytes(b) {
            Ok(_) => Ok(()),
            Err(holoface_models::refine::RefineError::Format(e)) => Err(e),
            Err(e) => panic!("not the framing's error: {e}"),
        }
    }

    fn load_labels(b: &[u8]) -> Result<(), FormatError> {
        crate::labels::from_bytes(b).map(drop)
    }

    fn load_cache(b: &[u8]) -> Result<(), FormatError> {
        match read_framed_cache(b, b.len() as u64, b"key", 4) {
            Ok(Some(_)) => Ok(()),
            Ok(None) => panic!("the key did not match"),
            Err(StreamError::Format(e)) => Err(e),
            Err(StreamError::Io(e)) => panic!("{e}"),
        }
    }

    #[test]
    fn each_kind_damaged_four_ways_is_the_same_structured_error() {
        let kinds: [(&str, Vec<u8>, Load); 4] = [
            ("KRFWS model", shipped("krfws.bin"), load_krfws),
            ("refiner model", refiner_v3(), load_refiner),
            ("teacher labels", labels_bytes(), load_labels),
            ("refiner training cache", cache_bytes(), load_cache),
        ];
        for (name, good, load) in kinds {
            load(&good).unwrap();
            let damage = |bytes: &[u8]| {
                let e = load(bytes).unwrap_err();
                assert_eq!(e.file, name, "{e}");
                e.damage
            };
            let len = good.len() as u64;
            let cut = damage(&good[..good.len() - 3]);
            assert!(
                matches!(cut, Damage::Truncated { len: l, .. } if l == len - 3),
                "{name}: {cut:?}"
            );
            let mut crc = good.clone();
            crc[good.len() - 1] ^= 0x01;
            assert!(matches!(damage(&crc), Damage::Checksum { .. }), "{name}");
            let mut magic = good.clone();
            magic[..8].copy_from_slice(b"NOTOURS!");
            assert!(
                matches!(damage(&magic), Damage::BadMagic { found, .. } if &found == b"NOTOURS!"),
                "{name}"
            );
            let mut future = good.clone();
            future[8..12].copy_from_slice(&99u32.to_le_bytes());
            assert!(
                matches!(damage(&future), Damage::UnsupportedVersion { found: 99, .. }),
                "{name}"
            );
        }
    }

    /// The shipped KRFWS model is the framing's first version as it was written; the shipped refiner (format
    /// 2, before the length field) loads to the model whose version-3 payload is its payload.
    #[test]
    fn shipped_models_load_byte_for_byte() {
        let krfws = shipped("krfws.bin");
        assert_eq!(Krfws::from_bytes(&krfws).unwrap().to_bytes().unwrap(), krfws);
        let refiner = shipped("refiner.bin");
        assert_eq!(&refiner[8..12], &2u32.to_le_bytes());
        let again = RefineCascade::from_bytes(&refiner).unwrap().to_bytes().unwrap();
        assert_eq!(&again[16..again.len() - 4], &refiner[12..refiner.len() - 4]);
    }
}
