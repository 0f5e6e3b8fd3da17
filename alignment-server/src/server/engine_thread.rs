//! The engine thread: runs each batch through the [`InferenceEngine`] and answers its frames.

use std::sync::atomic::Ordering;
use std::time::Instant;

use holoface_inference::{BatchTensor, InferenceEngine, LandmarkOut};
use holoface_protocol::DropReason;
use tokio::sync::mpsc;
use tracing::warn;

use super::scheduler::{FrameJob, FrameOutcome};
use crate::batcher::Batch;
use crate::metrics::Metrics;

pub(super) fn engine_loop(
    mut engine: Box<dyn InferenceEngine>,
    jobs: &std::sync::mpsc::Receiver<Batch<FrameJob>>,
    done: &mpsc::UnboundedSender<()>,
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
        let infer_us = u32::try_from(infer.as_micros()).unwrap_or(u32::MAX);
        match result {
            Ok(()) => {
                for (item, out) in items.into_iter().zip(&outs) {
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
                warn!(%e, frames = items.len(), "inference failed");
                metrics.inference_errors.fetch_add(1, Ordering::Relaxed);
                for item in items {
                    metrics.count_drop(DropReason::Overloaded);
                    let _ = item
                        .payload
                        .reply
                        .send(FrameOutcome::Dropped(DropReason::Overloaded));
                }
            }
        }
        if done.send(()).is_err() {
            break;
        }
    }
}
