//! The scheduler task: owns the [`DynamicBatcher`], feeds the engine thread and answers dropped frames.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use bytes::Bytes;
use holoface_protocol::DropReason;
use tokio::sync::{mpsc, oneshot, watch};
use tracing::{debug, warn};

use crate::batcher::{Batch, ClientId, DynamicBatcher, Pending};
use crate::metrics::Metrics;

/// Why a frame was not aligned, or its landmarks.
#[derive(Debug)]
pub(super) enum FrameOutcome {
    Landmarks {
        landmarks: Vec<[f32; 2]>,
        face_prob: f32,
        queue_us: u32,
        infer_us: u32,
    },
    Dropped(DropReason),
}

/// What the batcher carries for each frame.
#[derive(Debug)]
pub(super) struct FrameJob {
    pub(super) pixels: Bytes,
    pub(super) reply: oneshot::Sender<FrameOutcome>,
}

#[derive(Debug)]
pub(super) enum SchedMsg {
    Submit(Pending<FrameJob>),
    Disconnect(ClientId),
}

pub(super) async fn scheduler_loop(
    mut batcher: DynamicBatcher<FrameJob>,
    mut rx: mpsc::Receiver<SchedMsg>,
    job_txs: Vec<std::sync::mpsc::SyncSender<Batch<FrameJob>>>,
    mut done_rx: mpsc::UnboundedReceiver<usize>,
    mut stop: watch::Receiver<bool>,
    metrics: Arc<Metrics>,
) {
    // Engine instances free for a batch (all of them at first); a batch goes to the last one freed.
    let mut idle: Vec<usize> = (0..job_txs.len()).rev().collect();
    let instances = job_txs.len();
    let mut inputs_open = true;
    let now = || tokio::time::Instant::now().into_std();
    loop {
        while let Some(d) = batcher.poll_dropped() {
            metrics.count_drop(d.reason);
            let _ = d.item.payload.reply.send(FrameOutcome::Dropped(d.reason));
        }
        let busy = idle.len() < instances;
        let batch = if idle.is_empty() {
            None
        } else {
            batcher.poll_batch(now())
        };
        metrics
            .queued_frames
            .store(batcher.len() as i64, Ordering::Relaxed);
        if let Some(batch) = batch {
            for item in &batch.items {
                metrics
                    .queue_wait_us
                    .observe_duration(batch.formed_at.saturating_duration_since(item.arrived));
            }
            let Some(engine) = idle.pop() else { continue };
            if let Err(std::sync::mpsc::SendError(batch)) = job_txs[engine].send(batch) {
                warn!(engine, "engine thread is gone; dropping queued frames");
                for item in batch.items {
                    metrics.count_drop(DropReason::Overloaded);
                    let _ = item
                        .payload
                        .reply
                        .send(FrameOutcome::Dropped(DropReason::Overloaded));
                }
                batcher.start_drain();
            }
            continue;
        }
        if (batcher.is_draining() || !inputs_open) && !busy && batcher.is_empty() {
            break;
        }
        // While every engine is busy only expiries can be acted on; arming the
        // (already passed) flush time would spin this loop.
        let timeout = if idle.is_empty() {
            batcher.next_expiry()
        } else {
            batcher.poll_timeout()
        }
        .map(tokio::time::Instant::from_std);
        tokio::select! {
            msg = rx.recv(), if inputs_open => match msg {
                Some(SchedMsg::Submit(p)) => batcher.push(p, now()),
                Some(SchedMsg::Disconnect(client)) => {
                    batcher.remove_client(client);
                }
                None => {
                    inputs_open = false;
                    batcher.start_drain();
                }
            },
            done = done_rx.recv(), if busy => match done {
                Some(engine) => idle.push(engine),
                None => {
                    warn!("engine threads stopped");
                    idle = (0..instances).collect();
                    batcher.start_drain();
                    inputs_open = false;
                }
            },
            () = async {
                if let Some(t) = timeout {
                    tokio::time::sleep_until(t).await;
                }
            }, if timeout.is_some() => batcher.handle_timeout(now()),
            () = super::lifecycle::stopped(&mut stop), if !batcher.is_draining() => {
                debug!(queued = batcher.len(), "scheduler draining");
                batcher.start_drain();
            },
        }
    }
    debug!("scheduler stopped");
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    use crate::batcher::{BatchPolicy, BatcherConfig};
    use crate::server::engine_thread::engine_loop;
    use holoface_inference::FakeEngine;

    fn submit(client: ClientId, seed: u8, at: Instant) -> (SchedMsg, oneshot::Receiver<FrameOutcome>) {
        let (tx, rx) = oneshot::channel();
        let msg = SchedMsg::Submit(Pending {
            client,
            track: 0,
            frame_id: 1,
            arrived: at,
            expires: at + Duration::from_secs(1),
            payload: FrameJob {
                pixels: Bytes::from(vec![seed; 112 * 112]),
                reply: tx,
            },
        });
        (msg, rx)
    }

    /// The scheduler task and the engine thread (fake engine, max batch 4) wired as the server wires them.
    struct Harness {
        tx: mpsc::Sender<SchedMsg>,
        stop_tx: watch::Sender<bool>,
        sched: tokio::task::JoinHandle<()>,
        engine: std::thread::JoinHandle<()>,
        metrics: Arc<Metrics>,
    }

    impl Harness {
        fn start(policy: BatchPolicy) -> Self {
            let (h, _) = Self::with_engines(policy, 4, vec![Box::new(FakeEngine::new(4))]);
            h
        }

        /// The scheduler over these engine instances; the extra join handles are the other instances'.
        fn with_engines(
            policy: BatchPolicy,
            max_batch: usize,
            engines: Vec<Box<dyn holoface_inference::InferenceEngine>>,
        ) -> (Self, Vec<std::thread::JoinHandle<()>>) {
            let metrics = Arc::new(Metrics::new(4));
            let (done_tx, done_rx) = mpsc::unbounded_channel();
            let mut job_txs = Vec::new();
            let mut threads = Vec::new();
            for (i, engine) in engines.into_iter().enumerate() {
                let (job_tx, job_rx) = std::sync::mpsc::sync_channel(1);
                let (done_tx, engine_metrics) = (done_tx.clone(), Arc::clone(&metrics));
                threads.push(std::thread::spawn(move || {
                    engine_loop(engine, i, &job_rx, &done_tx, &engine_metrics);
                }));
                job_txs.push(job_tx);
            }
            let (tx, rx) = mpsc::channel(16);
            let (stop_tx, stop_rx) = watch::channel(false);
            let batcher = DynamicBatcher::new(BatcherConfig {
                max_batch,
                policy,
                per_client_queue: 1,
                max_queued: 100,
            });
            let sched = tokio::spawn(scheduler_loop(
                batcher,
                rx,
                job_txs,
                done_rx,
                stop_rx,
                Arc::clone(&metrics),
            ));
            let engine = threads.remove(0);
            let h = Self {
                tx,
                stop_tx,
                sched,
                engine,
                metrics,
            };
            (h, threads)
        }
    }

    /// A fake engine that says when a batch starts and holds it until released.
    struct Gated {
        inner: FakeEngine,
        started: std::sync::mpsc::Sender<usize>,
        release: Arc<std::sync::Mutex<std::sync::mpsc::Receiver<()>>>,
    }

    impl holoface_inference::InferenceEngine for Gated {
        fn info(&self) -> &holoface_inference::ModelInfo {
            self.inner.info()
        }
        fn max_batch(&self) -> usize {
            self.inner.max_batch()
        }
        fn infer(
            &mut self,
            input: &holoface_inference::BatchTensor,
            out: &mut [holoface_inference::LandmarkOut],
        ) -> Result<(), holoface_inference::EngineError> {
            let _ = self.started.send(input.len());
            let release = self.release.lock().unwrap();
            let _ = release.recv_timeout(Duration::from_secs(10));
            drop(release);
            self.inner.infer(input, out)
        }
    }

    /// Two engine instances: while one is busy with a batch, the next batch goes to the other at once
    /// (both are inside `infer` together), and every frame is answered.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn two_engine_instances_run_two_batches_at_once() {
        let (started_tx, started_rx) = std::sync::mpsc::channel();
        let mut releases = Vec::new();
        let mut engines: Vec<Box<dyn holoface_inference::InferenceEngine>> = Vec::new();
        for _ in 0..2 {
            let (tx, rx) = std::sync::mpsc::channel();
            releases.push(tx);
            engines.push(Box::new(Gated {
                inner: FakeEngine::new(1),
                started: started_tx.clone(),
                release: Arc::new(std::sync::Mutex::new(rx)),
            }));
        }
        let (h, others) = Harness::with_engines(BatchPolicy::WorkConserving, 1, engines);
        let now = Instant::now();
        let mut replies = Vec::new();
        for client in 0..2_u8 {
            let (msg, reply) = submit(u64::from(client), client, now);
            h.tx.send(msg).await.unwrap();
            replies.push(reply);
        }
        let both = tokio::task::spawn_blocking(move || {
            (0..2)
                .map(|_| started_rx.recv_timeout(Duration::from_secs(5)))
                .collect::<Result<Vec<_>, _>>()
        })
        .await
        .unwrap();
        assert_eq!(
            both.unwrap(),
            [1, 1],
            "both instances were inside infer at the same time"
        );
        for r in &releases {
            r.send(()).unwrap();
        }
        for reply in replies {
            assert!(matches!(reply.await.unwrap(), FrameOutcome::Landmarks { .. }));
        }
        h.stop_tx.send(true).unwrap();
        drop(h.tx);
        h.sched.await.unwrap();
        h.engine.join().unwrap();
        for t in others {
            t.join().unwrap();
        }
        assert_eq!(h.metrics.batch_size.count(), 2);
    }

    /// The driver around the batcher and the engine thread, with the fake
    /// engine and tokio's paused clock: no sockets, no sleeps.
    #[tokio::test(start_paused = true)]
    async fn scheduler_flushes_a_partial_batch_at_max_wait_and_drains_on_stop() {
        let Harness {
            tx,
            stop_tx,
            sched,
            engine,
            metrics,
        } = Harness::start(BatchPolicy::MaxWait(Duration::from_millis(5)));

        let t0 = tokio::time::Instant::now().into_std();
        let mut replies = Vec::new();
        for client in 0..3_u8 {
            let (msg, reply) = submit(u64::from(client), client * 50, t0);
            tx.send(msg).await.unwrap();
            replies.push(reply);
        }
        for (client, reply) in replies.into_iter().enumerate() {
            match reply.await.unwrap() {
                FrameOutcome::Landmarks {
                    face_prob, queue_us, ..
                } => {
                    assert!((face_prob - (client as f32 * 50.0) / 255.0).abs() < 1e-6);
                    assert_eq!(queue_us, 5_000, "a batch of 3 was flushed at t0 + max_wait");
                }
                other => panic!("{other:?}"),
            }
        }
        assert_eq!(metrics.batch_size.count(), 1);
        assert_eq!(metrics.batch_size.sum(), 3);

        // A frame still waiting for a fuller batch when shutdown starts is
        // answered ShuttingDown, and the scheduler stops.
        let (msg, reply) = submit(9, 1, tokio::time::Instant::now().into_std());
        tx.send(msg).await.unwrap();
        tokio::task::yield_now().await;
        stop_tx.send(true).unwrap();
        assert!(matches!(
            reply.await.unwrap(),
            FrameOutcome::Dropped(DropReason::ShuttingDown)
        ));
        sched.await.unwrap();
        engine.join().unwrap();
        assert_eq!(metrics.drops_for(DropReason::ShuttingDown), 1);
    }

    /// Work-conserving batching through the real driver: a lone frame reaches the idle engine with no
    /// queueing delay (paused clock: any wait would show as `queue_us`).
    #[tokio::test(start_paused = true)]
    async fn work_conserving_scheduler_sends_a_lone_frame_at_once() {
        let Harness {
            tx,
            stop_tx,
            sched,
            engine,
            metrics,
        } = Harness::start(BatchPolicy::WorkConserving);
        let (msg, reply) = submit(1, 10, tokio::time::Instant::now().into_std());
        tx.send(msg).await.unwrap();
        match reply.await.unwrap() {
            FrameOutcome::Landmarks { queue_us, .. } => assert_eq!(queue_us, 0),
            other => panic!("{other:?}"),
        }
        assert_eq!((metrics.batch_size.count(), metrics.batch_size.sum()), (1, 1));
        stop_tx.send(true).unwrap();
        sched.await.unwrap();
        engine.join().unwrap();
    }
}
