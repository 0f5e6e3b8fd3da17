//! Fair shares per client (issue 30): a one-face headset keeps its answers and its latency while an eight-face
//! headset sends at its limit (eight crops a frame at 30 fps, 240 crops/s: several times what this server's one
//! inference thread aligns) to the same server. Before the batcher served clients (it served faces), the one-face
//! headset lost two thirds of its frames in this scenario.
//!
//! The one-face headset sends at 30 fps where its fair share of the engine covers that (the engine aligns a crop
//! in under about 11 ms), and otherwise at the rate its share covers on this machine: with another client
//! backlogged, a crop waits for the batch running when it arrives and then takes its own turn, so its share is
//! one crop per two crop times, and on two shared cores a crop under load takes up to about twice its time
//! alone. A 30 fps stream on a machine whose share is 20 fps must lose frames whatever the scheduler does; the
//! test would then measure the machine, not the scheduler.
#![allow(clippy::unwrap_used)]

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use holoface_alignment_server::metrics::Metrics;
use holoface_protocol::ReplyOutcome;
use holoface_quic::Fingerprint;
use holoface_tests::{
    RunningServer, TEST_TOKEN, TestClient, frame, hello, loopback_settings, send_frame_on, within,
};

/// 30 fps.
const INTERVAL: Duration = Duration::from_millis(33);
/// The frames' deadline at 30 fps; a slower machine's stream gets six of its crop times.
const DEADLINE_MS: u16 = 100;

/// How one headset sends: every `interval`, `faces` crops with `deadline_ms`.
#[derive(Debug, Clone, Copy)]
struct Stream {
    faces: u16,
    interval: Duration,
    deadline_ms: u16,
    length: Duration,
}

/// The batches the server ran while a headset was being answered: from its first answer to its last crop sent
/// (it stays an active client for the batcher's active window after that).
#[derive(Debug, Default, Clone, Copy)]
struct Batches {
    count: u64,
    crops: u64,
}

impl Batches {
    fn of(metrics: &Metrics) -> Self {
        Self {
            count: metrics.batch_size.count(),
            crops: metrics.batch_size.sum(),
        }
    }

    fn since(self, start: Self) -> Self {
        Self {
            count: self.count - start.count,
            crops: self.crops - start.crops,
        }
    }

    fn mean(self) -> f64 {
        self.crops as f64 / self.count.max(1) as f64
    }
}

/// What one headset saw.
#[derive(Debug)]
struct Seen {
    sent: u64,
    answered: u64,
    latencies: Vec<Duration>,
    /// Per answered frame, the server's own time for it: queued plus aligned (`queue_us + infer_us`).
    server_times: Vec<Duration>,
    /// Per answered frame, how long it waited for its batch (`queue_us`) ...
    queued: Vec<Duration>,
    /// ... and how long its batch took (`infer_us`).
    batch_times: Vec<Duration>,
    /// The server's batches from this headset's first answer to its last crop.
    batches: Batches,
}

impl Seen {
    fn answered_fraction(&self) -> f64 {
        self.answered as f64 / self.sent.max(1) as f64
    }

    /// The `pct`-th percentile of the answered frames' latencies.
    fn percentile(&mut self, pct: usize) -> Duration {
        percentile(&mut self.latencies, pct)
    }

    /// The `pct`-th percentile of the server's own times.
    fn server_percentile(&mut self, pct: usize) -> Duration {
        percentile(&mut self.server_times, pct)
    }

    fn queued_percentile(&mut self, pct: usize) -> Duration {
        percentile(&mut self.queued, pct)
    }

    fn batch_time_percentile(&mut self, pct: usize) -> Duration {
        percentile(&mut self.batch_times, pct)
    }
}

fn percentile(v: &mut [Duration], pct: usize) -> Duration {
    v.sort_unstable();
    v.get(v.len() * pct / 100).copied().unwrap_or(Duration::MAX)
}

/// Where a headset connects, and the server's counters.
#[derive(Debug, Clone)]
struct Server {
    addr: SocketAddr,
    fingerprint: Fingerprint,
    metrics: Arc<Metrics>,
}

/// A headset sending `stream.faces` crops (tracks 1..=faces, or track 0 for one face) every `stream.interval`
/// for `stream.length`, counting the frames answered with landmarks and their latencies; `answering` hears of its
/// first answer.
async fn headset(
    server: Server,
    name: &str,
    stream: Stream,
    mut answering: Option<tokio::sync::oneshot::Sender<()>>,
) -> Seen {
    let Stream {
        faces,
        interval,
        deadline_ms,
        length,
    } = stream;
    let mut h = hello(TEST_TOKEN);
    h.client_name = name.to_owned();
    h.max_in_flight = faces;
    let mut client = TestClient::connect(server.addr, server.fingerprint, h)
        .await
        .unwrap();
    assert_eq!(client.welcome.max_in_flight, faces);
    let sent_at: Arc<Mutex<HashMap<(u64, u16), Instant>>> = Arc::default();
    let conn = client.conn.clone();
    let sender = {
        let sent_at = Arc::clone(&sent_at);
        let metrics = Arc::clone(&server.metrics);
        tokio::spawn(async move {
            let start = tokio::time::Instant::now();
            let mut frames = 0u64;
            while start.elapsed() < length {
                frames += 1;
                for track in 0..faces {
                    let mut f = frame(frames, u8::try_from(track).unwrap_or(0), deadline_ms);
                    f.track_id = if faces == 1 { 0 } else { track + 1 };
                    sent_at
                        .lock()
                        .unwrap()
                        .insert((frames, f.track_id), Instant::now());
                    let conn = conn.clone();
                    tokio::spawn(async move {
                        let _ = send_frame_on(&conn, &f).await;
                    });
                }
                tokio::time::sleep_until(start + interval * u32::try_from(frames).unwrap()).await;
            }
            (frames * u64::from(faces), Batches::of(&metrics))
        })
    };
    let mut seen = Seen {
        sent: 0,
        answered: 0,
        latencies: Vec::new(),
        server_times: Vec::new(),
        queued: Vec::new(),
        batch_times: Vec::new(),
        batches: Batches::default(),
    };
    let mut first_answer = None;
    let stop = Instant::now() + length + Duration::from_millis(300);
    while let Ok(Ok(r)) = tokio::time::timeout_at(stop.into(), client.next_reply()).await {
        let Some(t) = sent_at.lock().unwrap().remove(&(r.frame_id, r.track_id)) else {
            continue;
        };
        if let ReplyOutcome::Landmarks {
            queue_us, infer_us, ..
        } = r.outcome
        {
            seen.answered += 1;
            first_answer.get_or_insert_with(|| Batches::of(&server.metrics));
            if let Some(tx) = answering.take() {
                let _ = tx.send(());
            }
            seen.latencies.push(t.elapsed());
            let (queued, batch) = (
                Duration::from_micros(u64::from(queue_us)),
                Duration::from_micros(u64::from(infer_us)),
            );
            seen.server_times.push(queued + batch);
            seen.queued.push(queued);
            seen.batch_times.push(batch);
        }
    }
    let (sent, last_sent) = sender.await.unwrap();
    seen.sent = sent;
    seen.batches = last_sent.since(first_answer.unwrap_or(last_sent));
    seen
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_headset_with_eight_faces_does_not_starve_a_one_face_headset() {
    let running = RunningServer::start(loopback_settings()).await.unwrap();
    let server = Server {
        addr: running.addr,
        fingerprint: running.fingerprint,
        metrics: Arc::clone(&running.metrics),
    };
    let at_30_fps = |faces, seconds| Stream {
        faces,
        interval: INTERVAL,
        deadline_ms: DEADLINE_MS,
        length: Duration::from_secs(seconds),
    };
    let mut alone = headset(server.clone(), "one-face", at_30_fps(1, 3), None).await;
    assert!(alone.answered_fraction() >= 0.95, "alone: {alone:?}");
    // This machine's crop time, from the server's own clock with nothing else to do; the one-face headset's
    // stream beside the eight faces is what its fair share covers here (30 fps on a fast machine).
    let crop = alone.server_percentile(50);
    let light = Stream {
        interval: INTERVAL.max(crop * 3),
        deadline_ms: DEADLINE_MS.max(u16::try_from((crop * 6).as_millis()).unwrap_or(u16::MAX)),
        ..at_30_fps(1, 4)
    };
    // The one-face headset starts again once the eight-face one is being answered.
    let (answering, answered) = tokio::sync::oneshot::channel();
    let heavy = tokio::spawn(headset(
        server.clone(),
        "eight-faces",
        at_30_fps(8, 5),
        Some(answering),
    ));
    within("the eight-face headset's first answer", answered)
        .await
        .unwrap();
    let mut shared = headset(server, "one-face", light, None).await;
    let heavy = heavy.await.unwrap();
    let (p95_alone, p95_shared) = (alone.percentile(95), shared.percentile(95));
    let (s95_alone, s95_shared) = (alone.server_percentile(95), shared.server_percentile(95));
    let (queued95, batch95) = (shared.queued_percentile(95), shared.batch_time_percentile(95));
    eprintln!(
        "crop time alone (server's clock, median) {crop:?}: the one-face headset beside eight faces sends every \
         {:?} with a {} ms deadline",
        light.interval, light.deadline_ms
    );
    eprintln!(
        "one-face alone: {:.3} answered, p95 {p95_alone:?} (server {s95_alone:?}); beside eight faces: {:.3} \
         answered, p95 {p95_shared:?} (server {s95_shared:?}: queued p95 {queued95:?}, its batches p95 \
         {batch95:?}); {} batches of {:.2} crops on average meanwhile; eight-face headset: {} of {} answered",
        alone.answered_fraction(),
        shared.answered_fraction(),
        shared.batches.count,
        shared.batches.mean(),
        heavy.answered,
        heavy.sent
    );
    // The scheduler's promise, on the server's own counters so that two shared cores' scheduling does not
    // count. While both headsets are active a batch takes at most one crop per client: batches of two at most,
    // where a batcher that let the eight-face headset fill its batches runs eight.
    assert!(
        shared.batches.count > 0 && shared.batches.mean() <= 2.0,
        "while two headsets are active the batches hold more than one crop per client: {:?}",
        shared.batches
    );
    // And a crop waits at most for the batch that is running when it arrives, never behind the other
    // headset's queue: its wait is within a batch time (the running batch's, which contention on the shared
    // cores makes vary from batch to batch as it does its own).
    assert!(
        queued95 <= batch95 * 3 / 2 + Duration::from_millis(5),
        "the one-face headset's crops wait behind more than one batch: queued p95 {queued95:?}, its batches \
         p95 {batch95:?}"
    );
    // What the headset sees: within its share it keeps its answers (before the batcher served clients it lost
    // two thirds of them) and within its deadline.
    assert!(
        shared.answered_fraction() >= 0.9,
        "the one-face headset lost frames: {:.3} answered",
        shared.answered_fraction()
    );
    assert!(
        p95_shared < Duration::from_millis(u64::from(light.deadline_ms)),
        "p95 {p95_shared:?} beside eight faces, deadline {} ms",
        light.deadline_ms
    );
    assert!(heavy.answered > 0, "the heavy headset is served too: {heavy:?}");
    running.shutdown().await.unwrap();
}
