//! [`FakeEngine`], a deterministic stand-in for unit tests (`cfg(test)` or the `test-util` feature).

use crate::contract::{BatchTensor, InferenceEngine, LandmarkOut, ModelInfo};
use crate::error::EngineError;

/// A deterministic stand-in for unit tests: landmarks are the mean shape
/// shifted by the crop's first pixel / 16, face probability is the mean
/// pixel / 255.
#[derive(Debug)]
pub struct FakeEngine {
    info: ModelInfo,
    max_batch: usize,
    /// Batches run so far (length of each).
    pub batches: Vec<usize>,
}

impl FakeEngine {
    /// A fake 68-point, 112-pixel model.
    pub fn new(max_batch: usize) -> Self {
        let mean_shape = (0..68)
            .map(|i| [20.0 + (i % 17) as f32 * 4.0, 30.0 + (i / 17) as f32 * 15.0])
            .collect();
        Self {
            info: ModelInfo {
                name: "fake".into(),
                version: "0".into(),
                landmark_count: 68,
                crop_size: 112,
                mean_shape,
                face_threshold: 0.5,
                licence: None,
                untrained: true,
                precision: "fp32".into(),
            },
            max_batch,
            batches: Vec::new(),
        }
    }
}

impl InferenceEngine for FakeEngine {
    fn info(&self) -> &ModelInfo {
        &self.info
    }

    fn max_batch(&self) -> usize {
        self.max_batch
    }

    fn infer(&mut self, input: &BatchTensor, out: &mut [LandmarkOut]) -> Result<(), EngineError> {
        let n = input.len();
        if n > self.max_batch || out.len() < n {
            return Err(EngineError::BatchTooLarge {
                len: n,
                max: self.max_batch,
            });
        }
        self.batches.push(n);
        for (crop, slot) in input
            .as_slice()
            .chunks_exact(input.crop_pixels())
            .zip(out.iter_mut())
        {
            let shift = f32::from(crop.first().copied().unwrap_or(0)) / 16.0;
            let mean = crop.iter().map(|p| f32::from(*p)).sum::<f32>() / crop.len() as f32;
            slot.landmarks.clear();
            slot.landmarks
                .extend(self.info.mean_shape.iter().map(|[x, y]| [x + shift, y + shift]));
            slot.face_prob = mean / 255.0;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fake_engine_is_deterministic() {
        let mut e = FakeEngine::new(4);
        let mut b = BatchTensor::new(4, 112 * 112);
        b.push(&[32; 112 * 112]).unwrap();
        let mut out = vec![LandmarkOut::default(); 4];
        e.infer(&b, &mut out).unwrap();
        assert_eq!(out[0].landmarks[0], [22.0, 32.0]);
        assert!((out[0].face_prob - 32.0 / 255.0).abs() < 1e-6);
        assert_eq!(e.batches, vec![1]);
    }
}
