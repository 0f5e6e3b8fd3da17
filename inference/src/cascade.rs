//! DAN followed by the refinement cascade: the server's alignment pipeline as one [`InferenceEngine`].
//!
//! [`CascadeEngine`] runs the wrapped engine (DAN) on the batch, then refines, on the very crop bytes of
//! the batch, the landmarks of every crop whose output is usable and whose face probability passes the
//! model's threshold (`holoface_models::refine`). Rejected crops keep DAN's answer: the client discards
//! them anyway. The server's engine threads and `holoface eval --aligner remote` run this same type, so the
//! evaluation measures exactly what headsets get.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use holoface_models::refine::{RefineCascade, RefineScratch};

use crate::contract::{BatchTensor, CascadeStats, Execution, InferenceEngine, LandmarkOut, ModelInfo};
use crate::error::EngineError;

/// A loaded refiner with its identity (`name (crc XXXXXXXX)`), shared by every engine instance.
#[derive(Debug, Clone)]
pub struct LoadedCascade {
    model: Arc<RefineCascade>,
    identity: String,
}

impl LoadedCascade {
    /// Loads and validates a refiner model file.
    pub fn load(path: &Path) -> Result<Self, EngineError> {
        let err = |detail: String| EngineError::Cascade {
            path: path.to_path_buf(),
            detail,
            option: None,
        };
        if path.is_dir() {
            return Err(err("is a directory, not a refiner model file".into()));
        }
        let bytes = holoface_files::read_bounded(
            path,
            holoface_files::home::REFINER.max_bytes,
            holoface_files::home::REFINER.name,
        )
        .map_err(|e| match e {
            holoface_files::FileError::Missing { .. } => holoface_files::home::REFINER.missing(path).into(),
            other => err(other.to_string()),
        })?;
        crate::integrity::verify_sidecar(path, &bytes)?;
        Self::from_bytes(&bytes).map_err(|e| match e {
            EngineError::Refine(detail) => err(detail),
            other => other,
        })
    }

    /// A refiner from file bytes.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, EngineError> {
        let model = RefineCascade::from_bytes(bytes).map_err(|e| EngineError::Refine(e.to_string()))?;
        let crc = RefineCascade::file_crc(bytes).unwrap_or(0);
        let identity = format!("{} (crc {crc:08x})", model.name);
        Ok(Self {
            model: Arc::new(model),
            identity,
        })
    }

    /// `name (crc XXXXXXXX)`: the trainer's name and version, and the file's checksum.
    pub fn identity(&self) -> &str {
        &self.identity
    }

    /// The cascade.
    pub fn model(&self) -> &RefineCascade {
        &self.model
    }
}

/// DAN (any [`InferenceEngine`]) followed by the refinement cascade.
#[derive(Debug)]
pub struct CascadeEngine<E> {
    inner: E,
    refiner: LoadedCascade,
    /// One scratch per refinement thread.
    scratch: Vec<RefineScratch>,
    last: CascadeStats,
}

impl<E: InferenceEngine> CascadeEngine<E> {
    /// Wraps `inner`; the refiner must work on the model's crop size.
    pub fn new(inner: E, refiner: LoadedCascade) -> Result<Self, EngineError> {
        let size = inner.info().crop_size;
        if refiner.model().crop_size != size || inner.info().landmark_count != 68 {
            return Err(EngineError::Refine(format!(
                "the refiner works on 68 landmarks in {} px crops; the model gives {} in {size} px crops",
                refiner.model().crop_size,
                inner.info().landmark_count
            )));
        }
        Ok(Self {
            inner,
            refiner,
            scratch: vec![RefineScratch::default()],
            last: CascadeStats::default(),
        })
    }

    /// Refines a batch's crops on up to `threads` threads (default 1). While the cascade runs, ONNX Runtime's
    /// threads are idle, so the server gives it as many as it gives ONNX Runtime (`engine.intra_threads`).
    #[must_use]
    pub fn with_threads(mut self, threads: usize) -> Self {
        self.scratch.resize_with(threads.max(1), RefineScratch::default);
        self
    }
}

impl<E: InferenceEngine> InferenceEngine for CascadeEngine<E> {
    fn info(&self) -> &ModelInfo {
        self.inner.info()
    }

    fn max_batch(&self) -> usize {
        self.inner.max_batch()
    }

    fn execution(&self) -> Execution {
        self.inner.execution()
    }

    fn refiner(&self) -> Option<&str> {
        Some(self.refiner.identity())
    }

    fn last_refinement(&self) -> Option<CascadeStats> {
        Some(self.last)
    }

    fn infer(&mut self, input: &BatchTensor, out: &mut [LandmarkOut]) -> Result<(), EngineError> {
        self.inner.infer(input, out)?;
        let started = Instant::now();
        let info = self.inner.info();
        let (threshold, count) = (info.face_threshold, info.landmark_count);
        let pixels = input.crop_pixels();
        let n = input.len().min(out.len());
        let refiner = self.refiner.model();
        // Crops to refine and their outputs, split into one contiguous part per thread.
        let jobs: Vec<(&[u8], &mut LandmarkOut)> = input
            .as_slice()
            .chunks_exact(pixels)
            .zip(out[..n].iter_mut())
            .filter(|(_, o)| o.problem(count).is_none() && o.face_prob >= threshold)
            .collect();
        let crops = jobs.len();
        let refine_part = |part: Vec<(&[u8], &mut LandmarkOut)>, scratch: &mut RefineScratch| {
            for (crop, o) in part {
                refiner
                    .refine_pairs(crop, &mut o.landmarks, scratch)
                    .map_err(|e| EngineError::Refine(e.to_string()))?;
            }
            Ok::<(), EngineError>(())
        };
        let threads = self.scratch.len().min(crops).max(1);
        if threads == 1 {
            refine_part(jobs, &mut self.scratch[0])?;
        } else {
            let per = crops.div_ceil(threads);
            let mut parts: Vec<Vec<(&[u8], &mut LandmarkOut)>> = Vec::with_capacity(threads);
            let mut jobs = jobs.into_iter();
            for _ in 0..threads {
                parts.push(jobs.by_ref().take(per).collect());
            }
            std::thread::scope(|sc| {
                let handles: Vec<_> = parts
                    .into_iter()
                    .zip(self.scratch.iter_mut())
                    .map(|(part, scratch)| sc.spawn(move || refine_part(part, scratch)))
                    .collect();
                handles.into_iter().try_for_each(|h| {
                    h.join()
                        .unwrap_or_else(|_| Err(EngineError::Refine("a refinement thread panicked".into())))
                })
            })?;
        }
        self.last = CascadeStats {
            crops,
            elapsed: started.elapsed(),
        };
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use holoface_models::geometry::Point2;
    use holoface_models::refine::{RefineStage, RegressionTree, SHAPE_DIM, Sampling, SplitTest};

    use super::*;
    use crate::fake::FakeEngine;

    /// A refiner that moves every landmark by (+1, +1) crop pixels (its mean shape is the fake model's, so
    /// on the fake's output its frame is the identity).
    fn shift_by_one() -> Vec<u8> {
        let fake = FakeEngine::new(1);
        let m = &fake.info().mean_shape;
        RefineCascade {
            crop_size: 112,
            depth: 1,
            mean: std::array::from_fn(|i| Point2::new(m[i][0], m[i][1])),
            stages: vec![RefineStage {
                anchors: vec![0, 1],
                offsets: vec![[0.0, 0.0], [1.0, 0.0]],
                trees: vec![RegressionTree::new(
                    vec![SplitTest {
                        u: 0,
                        v: 1,
                        threshold: 1000.0,
                    }],
                    &[1.0; 2 * SHAPE_DIM],
                )],
            }],
            name: "shift".into(),
            starts: 1,
            mirror: false,
            sampling: Sampling::Nearest,
        }
        .to_bytes()
        .unwrap()
    }

    #[test]
    fn refines_accepted_crops_and_leaves_rejected_ones() {
        let model = LoadedCascade::from_bytes(&shift_by_one()).unwrap();
        assert!(
            model.identity().starts_with("shift (crc "),
            "{}",
            model.identity()
        );
        let mut plain = FakeEngine::new(4);
        let mut refined = CascadeEngine::new(FakeEngine::new(4), model).unwrap();
        assert_eq!(refined.refiner(), Some(refined.refiner.identity()));
        let mut batch = BatchTensor::new(4, 112 * 112);
        // The fake's face probability is the mean pixel / 255: a dark crop is rejected.
        batch.push(&[250u8; 112 * 112]).unwrap();
        batch.push(&[2u8; 112 * 112]).unwrap();
        let mut a = vec![LandmarkOut::default(); 4];
        let mut b = vec![LandmarkOut::default(); 4];
        plain.infer(&batch, &mut a).unwrap();
        refined.infer(&batch, &mut b).unwrap();
        let threshold = plain.info().face_threshold;
        assert!(a[0].face_prob >= threshold && a[1].face_prob < threshold);
        for (p, q) in a[0].landmarks.iter().zip(&b[0].landmarks) {
            assert!((q[0] - p[0] - 1.0).abs() < 1e-4 && (q[1] - p[1] - 1.0).abs() < 1e-4);
        }
        assert_eq!(a[1], b[1], "a rejected crop keeps DAN's answer");
        assert_eq!(refined.last_refinement().map(|r| r.crops), Some(1));
    }

    #[test]
    fn several_threads_give_the_same_answers() {
        let model = LoadedCascade::from_bytes(&shift_by_one()).unwrap();
        let mut one = CascadeEngine::new(FakeEngine::new(8), model.clone()).unwrap();
        let mut three = CascadeEngine::new(FakeEngine::new(8), model)
            .unwrap()
            .with_threads(3);
        let mut batch = BatchTensor::new(8, 112 * 112);
        for k in 0..7u8 {
            // Bright crops are accepted, the dark ones (k = 2, 5) are not.
            let level = if k % 3 == 2 { 3 } else { 200 + k };
            batch.push(&[level; 112 * 112]).unwrap();
        }
        let mut a = vec![LandmarkOut::default(); 8];
        let mut b = vec![LandmarkOut::default(); 8];
        one.infer(&batch, &mut a).unwrap();
        three.infer(&batch, &mut b).unwrap();
        assert_eq!(a, b);
        assert_eq!(three.last_refinement().map(|r| r.crops), Some(5));
    }

    #[test]
    fn a_missing_damaged_or_mismatched_refiner_is_a_clear_error() {
        let dir = std::env::temp_dir().join(format!("holoface-refiner-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let missing = LoadedCascade::load(&dir.join("nope.bin"))
            .unwrap_err()
            .to_string();
        assert!(
            missing.contains("not found at") && missing.contains("nope.bin (the path given)"),
            "{missing}"
        );
        // The front end names its own setting.
        let named = LoadedCascade::load(&dir.join("nope.bin"))
            .unwrap_err()
            .given_by(&[(holoface_files::home::REFINER, "refine.model")])
            .to_string();
        assert!(named.contains("(the path given with refine.model)"), "{named}");
        let corrupt = dir.join("corrupt.bin");
        let mut bytes = shift_by_one();
        bytes[30] ^= 0xff;
        std::fs::write(&corrupt, &bytes).unwrap();
        let e = LoadedCascade::load(&corrupt).unwrap_err().to_string();
        assert!(e.contains("corrupt.bin") && e.contains("checksum"), "{e}");
        let e = LoadedCascade::load(&dir).unwrap_err().to_string();
        assert!(e.contains("directory"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
        let mut big = RefineCascade::from_bytes(&shift_by_one()).unwrap();
        big.crop_size = 224;
        let m = LoadedCascade::from_bytes(&big.to_bytes().unwrap()).unwrap();
        let e = CascadeEngine::new(FakeEngine::new(1), m).unwrap_err().to_string();
        assert!(e.contains("224 px"), "{e}");
    }
}
