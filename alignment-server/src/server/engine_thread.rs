//! The engine thread: runs each batch through the [`InferenceEngine`] and answers its frames.

use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use holoface_inference::{BatchTensor, EngineError, InferenceEngine, LandmarkOut};
use holoface_protocol::DropReason;
use tokio::sync::mpsc;
use tracing::{error, warn};

use super::scheduler::{FrameJob, FrameOutcome};
use crate::batcher::Batch;
use crate::metrics::Metrics;

/// Logs unusable model output at error level: the first time at once, then at most once a second with the
/// number of frames since, so a model that emits NaN for every frame is loud without flooding the log.
#[derive(Debug, Default)]
struct ModelAlarm {
    last: Option<Instant>,
    since_last: u64,
}

impl ModelAlarm {
    fn raise(&mut self, problem: &str, frames: usize) {
        self.since_last += frames as u64;
        let now = Instant::now();
        if self
            .last
            .is_none_or(|t| now.duration_since(t) >= Duration::from_secs(1))
        {
            error!(
                problem,
                frames = self.since_last,
                "the model's output is unusable; those frames are answered Dropped(ModelOutput). \
                 Check the model file (engine.model) and its export"
            );
            self.last = Some(now);
            self.since_last = 0;
        }
    }
}

/// Runs engine instance `index`: each batch from `jobs`, then `index` on `done` (the scheduler's signal that
/// this instance is idle again).
pub(super) fn engine_loop(
    mut engine: Box<dyn InferenceEngine>,
    index: usize,
    jobs: &std::sync::mpsc::Receiver<Batch<FrameJob>>,
    done: &mpsc::UnboundedSender<usize>,
    metrics: &Metrics,
) {
    let max_batch = engine.max_batch();
    let mut tensor = BatchTensor::new(max_batch, engine.info().crop_pixels());
    let mut outs = vec![
        LandmarkOut {
            landmarks: Vec::with_capacity(engine.info().landmark_count),
            face_prob: 0.0,
        };
        max_batch
    ];
    let mut alarm = ModelAlarm::default();
    while let Ok(batch) = jobs.recv() {
        tensor.clear();
        let mut items = Vec::with_capacity(batch.items.len());
        for item in batch.items {
            match tensor.push(&item.payload.pixels) {
                Ok(()) => items.push(item),
                Err(e) => {
                    warn!(%e, "crop does not fit the batch");
                    metrics.count_drop(DropReason::BadCrop);
                    let _ = item
                        .payload
                        .reply
                        .send(FrameOutcome::Dropped(DropReason::BadCrop));
                }
            }
        }
        let started = Instant::now();
        let result = engine.infer(&tensor, &mut outs);
        let infer = started.elapsed();
        metrics.batch_size.observe(items.len() as u64);
        metrics.inference_us.observe_duration(infer);
        if let Some(r) = engine.last_refinement().filter(|r| r.crops > 0 && result.is_ok()) {
            metrics
                .refine_us
                .observe_duration(r.elapsed / u32::try_from(r.crops).unwrap_or(u32::MAX));
        }
        let infer_us = u32::try_from(infer.as_micros()).unwrap_or(u32::MAX);
        match result {
            Ok(()) => {
                let landmark_count = engine.info().landmark_count;
                for (item, out) in items.into_iter().zip(&outs) {
                    if let Some(problem) = out.problem(landmark_count) {
                        alarm.raise(&problem, 1);
                        metrics.model_output_errors.fetch_add(1, Ordering::Relaxed);
                        metrics.count_drop(DropReason::ModelOutput);
                        let _ = item
                            .payload
                            .reply
                            .send(FrameOutcome::Dropped(DropReason::ModelOutput));
                        continue;
                    }
                    let queue = batch.formed_at.saturating_duration_since(item.arrived);
                    metrics.frames_aligned.fetch_add(1, Ordering::Relaxed);
                    let _ = item.payload.reply.send(FrameOutcome::Landmarks {
                        landmarks: out.landmarks.clone(),
                        face_prob: out.face_prob,
                        queue_us: u32::try_from(queue.as_micros()).unwrap_or(u32::MAX),
                        infer_us,
                    });
                }
            }
            Err(e) => {
                metrics.inference_errors.fetch_add(1, Ordering::Relaxed);
                // A model whose outputs contradict its declaration is broken, not busy: say so.
                let reason = if matches!(e, EngineError::BadOutput(_)) {
                    alarm.raise(&e.to_string(), items.len());
                    metrics
                        .model_output_errors
                        .fetch_add(items.len() as u64, Ordering::Relaxed);
                    DropReason::ModelOutput
                } else {
                    warn!(%e, frames = items.len(), "inference failed");
                    DropReason::Overloaded
                };
                for item in items {
                    metrics.count_drop(reason);
                    let _ = item.payload.reply.send(FrameOutcome::Dropped(reason));
                }
            }
        }
        if done.send(index).is_err() {
            break;
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use holoface_inference::FakeEngine;
    use holoface_inference::{EngineError, ModelInfo};
    use tokio::sync::oneshot;

    use super::*;
    use crate::batcher::Batch;
    use crate::server::scheduler::FrameJob;

    /// A fake model broken in one way.
    #[derive(Debug, Clone, Copy)]
    enum Broken {
        /// Landmark 3 of the second crop is NaN.
        NanLandmark,
        /// The face probability of every crop is infinite.
        InfiniteProb,
        /// One landmark fewer than the model declares.
        ShortOutput,
        /// The engine reports outputs shaped against the declaration.
        ShapeError,
    }

    struct BrokenEngine(FakeEngine, Broken);

    impl InferenceEngine for BrokenEngine {
        fn info(&self) -> &ModelInfo {
            self.0.info()
        }
        fn max_batch(&self) -> usize {
            self.0.max_batch()
        }
        fn infer(&mut self, input: &BatchTensor, out: &mut [LandmarkOut]) -> Result<(), EngineError> {
            self.0.infer(input, out)?;
            match self.1 {
                Broken::NanLandmark => out[1].landmarks[3][0] = f32::NAN,
                Broken::InfiniteProb => out.iter_mut().for_each(|o| o.face_prob = f32::INFINITY),
                Broken::ShortOutput => out.iter_mut().for_each(|o| {
                    o.landmarks.pop();
                }),
                Broken::ShapeError => return Err(EngineError::BadOutput("landmarks shape [2, 10]".into())),
            }
            Ok(())
        }
    }

    /// Runs one batch of three crops through `engine_loop`; returns the three outcomes.
    fn run(broken: Broken, metrics: &Metrics) -> Vec<FrameOutcome> {
        let engine = BrokenEngine(FakeEngine::new(4), broken);
        let (jobs_tx, jobs_rx) = std::sync::mpsc::channel();
        let (done_tx, mut done_rx) = mpsc::unbounded_channel();
        let now = Instant::now();
        let mut replies = Vec::new();
        let mut items = Vec::new();
        for k in 0..3u8 {
            let (tx, rx) = oneshot::channel();
            replies.push(rx);
            items.push(crate::batcher::Pending {
                client: u64::from(k),
                track: 0,
                frame_id: 1,
                arrived: now,
                expires: now + Duration::from_secs(1),
                payload: FrameJob {
                    pixels: vec![k * 10; 112 * 112].into(),
                    reply: tx,
                },
            });
        }
        jobs_tx
            .send(Batch {
                items,
                formed_at: now,
            })
            .unwrap();
        drop(jobs_tx);
        engine_loop(Box::new(engine), 7, &jobs_rx, &done_tx, metrics);
        assert_eq!(
            done_rx.try_recv().ok(),
            Some(7),
            "the batch is reported done by its instance"
        );
        replies.into_iter().map(|mut r| r.try_recv().unwrap()).collect()
    }

    fn dropped(o: &FrameOutcome) -> Option<DropReason> {
        match o {
            FrameOutcome::Dropped(r) => Some(*r),
            FrameOutcome::Landmarks { .. } => None,
        }
    }

    #[test]
    fn a_non_finite_landmark_is_a_model_output_drop_for_that_frame_only() {
        let m = Metrics::new(8);
        let got: Vec<_> = run(Broken::NanLandmark, &m).iter().map(dropped).collect();
        assert_eq!(got, [None, Some(DropReason::ModelOutput), None]);
        assert_eq!(
            m.frames_aligned.load(Ordering::Relaxed),
            2,
            "the broken frame is not counted aligned"
        );
        assert_eq!(m.model_output_errors.load(Ordering::Relaxed), 1);
        assert_eq!(m.drops_for(DropReason::ModelOutput), 1);
    }

    #[test]
    fn unusable_probabilities_short_outputs_and_shape_errors_are_model_output_drops() {
        for broken in [Broken::InfiniteProb, Broken::ShortOutput, Broken::ShapeError] {
            let m = Metrics::new(8);
            let got: Vec<_> = run(broken, &m).iter().map(dropped).collect();
            assert_eq!(got, [Some(DropReason::ModelOutput); 3], "{broken:?}");
            assert_eq!(m.frames_aligned.load(Ordering::Relaxed), 0, "{broken:?}");
            assert_eq!(m.model_output_errors.load(Ordering::Relaxed), 3, "{broken:?}");
            assert_eq!(
                m.drops_for(DropReason::Overloaded),
                0,
                "{broken:?}: not reported as load"
            );
            let text = m.render();
            assert!(text.contains("holoface_model_output_errors_total 3"), "{text}");
            assert!(text.contains("reason=\"model_output\"} 3"), "{text}");
        }
    }

    #[test]
    fn a_version_1_client_hears_overloaded_instead() {
        assert_eq!(DropReason::ModelOutput.for_version(1), DropReason::Overloaded);
        assert_eq!(DropReason::ModelOutput.for_version(2), DropReason::ModelOutput);
        for r in DropReason::ALL {
            if *r != DropReason::ModelOutput {
                assert_eq!(r.for_version(1), *r);
            }
        }
    }
}
