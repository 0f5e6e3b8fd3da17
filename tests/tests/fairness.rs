//! Fair shares per client (issue 30): a one-face headset at 30 fps keeps its answers and its latency while an
//! eight-face headset sends at its limit (eight crops a frame at 30 fps, 240 crops/s: three times what this
//! server's one inference thread aligns) to the same server. Before the batcher served clients (it served
//! faces), the one-face headset lost two thirds of its frames in this scenario.
#![allow(clippy::unwrap_used)]

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use holoface_protocol::ReplyOutcome;
use holoface_quic::Fingerprint;
use holoface_tests::{
    RunningServer, TEST_TOKEN, TestClient, frame, hello, loopback_settings, send_frame_on, within,
};

const INTERVAL: Duration = Duration::from_millis(33);
const DEADLINE_MS: u16 = 100;

/// What one headset saw.
#[derive(Debug)]
struct Seen {
    sent: u64,
    answered: u64,
    latencies: Vec<Duration>,
    /// Per answered frame, the server's own time for it: queued plus aligned (`queue_us + infer_us`).
    server_times: Vec<Duration>,
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
}

fn percentile(v: &mut [Duration], pct: usize) -> Duration {
    v.sort_unstable();
    v.get(v.len() * pct / 100).copied().unwrap_or(Duration::MAX)
}

/// A headset sending `faces` crops (tracks 1..=faces, or track 0 for one face) every 33 ms for `length`,
/// counting the frames answered with landmarks and their latencies; `answering` hears of its first answer.
async fn headset(
    addr: SocketAddr,
    fp: Fingerprint,
    name: &str,
    faces: u16,
    length: Duration,
    mut answering: Option<tokio::sync::oneshot::Sender<()>>,
) -> Seen {
    let mut h = hello(TEST_TOKEN);
    h.client_name = name.to_owned();
    h.max_in_flight = faces;
    let mut client = TestClient::connect(addr, fp, h).await.unwrap();
    assert_eq!(client.welcome.max_in_flight, faces);
    let sent_at: Arc<Mutex<HashMap<(u64, u16), Instant>>> = Arc::default();
    let conn = client.conn.clone();
    let sender = {
        let sent_at = Arc::clone(&sent_at);
        tokio::spawn(async move {
            let start = tokio::time::Instant::now();
            let mut frames = 0u64;
            while start.elapsed() < length {
                frames += 1;
                for track in 0..faces {
                    let mut f = frame(frames, u8::try_from(track).unwrap_or(0), DEADLINE_MS);
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
                tokio::time::sleep_until(start + INTERVAL * u32::try_from(frames).unwrap()).await;
            }
            frames * u64::from(faces)
        })
    };
    let mut seen = Seen {
        sent: 0,
        answered: 0,
        latencies: Vec::new(),
        server_times: Vec::new(),
    };
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
            if let Some(tx) = answering.take() {
                let _ = tx.send(());
            }
            seen.latencies.push(t.elapsed());
            seen.server_times
                .push(Duration::from_micros(u64::from(queue_us) + u64::from(infer_us)));
        }
    }
    seen.sent = sender.await.unwrap();
    seen
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_headset_with_eight_faces_does_not_starve_a_one_face_headset() {
    let server = RunningServer::start(loopback_settings()).await.unwrap();
    let (addr, fp) = (server.addr, server.fingerprint);
    let mut alone = headset(addr, fp, "one-face", 1, Duration::from_secs(3), None).await;
    // The one-face headset starts again once the eight-face one is being answered.
    let (answering, answered) = tokio::sync::oneshot::channel();
    let heavy = tokio::spawn(headset(
        addr,
        fp,
        "eight-faces",
        8,
        Duration::from_secs(5),
        Some(answering),
    ));
    within("the eight-face headset's first answer", answered)
        .await
        .unwrap();
    let mut shared = headset(addr, fp, "one-face", 1, Duration::from_secs(4), None).await;
    let heavy = heavy.await.unwrap();
    let (p95_alone, p95_shared) = (alone.percentile(95), shared.percentile(95));
    let (p99_alone, p99_shared) = (alone.percentile(99), shared.percentile(99));
    let (s95_alone, s95_shared) = (alone.server_percentile(95), shared.server_percentile(95));
    eprintln!("server's own time p95: alone {s95_alone:?}, beside eight faces {s95_shared:?}");
    eprintln!(
        "one-face alone: {:.3} answered, p95 {p95_alone:?}, p99 {p99_alone:?}; beside eight faces: {:.3} answered, \
         p95 {p95_shared:?}, p99 {p99_shared:?}; eight-face headset: {} of {} answered",
        alone.answered_fraction(),
        shared.answered_fraction(),
        heavy.answered,
        heavy.sent
    );
    assert!(alone.answered_fraction() >= 0.95, "alone: {alone:?}");
    // Before the batcher served clients the one-face headset lost two thirds of its frames here; now it loses
    // at most a few, to the two shared cores (measured 0.94-1.00 over runs on an idle 2-core machine).
    assert!(
        shared.answered_fraction() >= 0.9,
        "the one-face headset lost frames: {:.3} answered",
        shared.answered_fraction()
    );
    // The scheduler's promise, on the server's own clock (queued + aligned, from each reply), so that the test
    // runtime's and the loopback's scheduling on two shared cores does not count: the engine is not
    // preemptible, and while several clients are active a batch holds at most one crop per client, so a crop
    // that arrives while a batch runs waits for it (at most its own previous crop and one other client's) and
    // then for its own: at most three crop times, three times its time alone. A batcher that let the
    // eight-face headset fill its batches would put eight crops ahead of it. The 95th percentile: of about 120
    // frames the 99th is the second slowest, the operating system's scheduling rather than ours.
    assert!(
        s95_shared <= s95_alone * 3 + Duration::from_millis(5),
        "the one-face headset's crops wait behind more than one batch: server time p95 {s95_shared:?} beside \
         eight faces, {s95_alone:?} alone"
    );
    // And end to end, what the headset sees stays within its deadline.
    assert!(
        p95_shared < Duration::from_millis(u64::from(DEADLINE_MS)),
        "p95 {p95_shared:?} beside eight faces"
    );
    assert!(heavy.answered > 0, "the heavy headset is served too: {heavy:?}");
    server.shutdown().await.unwrap();
}
