//! The simulated headsets: each connects like the real client, replays its recorded stream in a loop at the
//! planned instants and records what the server answers.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::Context;
use holoface_client::link::connection::{ConnectConfig, client_endpoint, connect, send_frame};
use holoface_protocol::{FrameRequest, Message, ReplyOutcome};

use crate::replay::ReplayFrame;
use crate::report::Stats;

/// What one simulated headset does.
pub(crate) struct Plan {
    pub(crate) id: usize,
    pub(crate) cfg: ConnectConfig,
    pub(crate) frames: Arc<Vec<ReplayFrame>>,
    /// Length of one loop over `frames`.
    pub(crate) period: Duration,
    pub(crate) start: Instant,
    pub(crate) end: Instant,
    pub(crate) deadline: Duration,
}

/// Connects, replays `plan.frames` in a loop from `plan.start` to `plan.end` (or the server's Goaway) and
/// records every answer, drop and deadline miss in `stats`.
pub(crate) async fn headset(plan: Plan, stats: Arc<Mutex<Stats>>) -> anyhow::Result<()> {
    let Plan {
        id,
        cfg,
        frames,
        period,
        start,
        end,
        deadline,
    } = plan;
    let endpoint = client_endpoint(&cfg)?;
    let session = connect(&endpoint, &cfg)
        .await
        .with_context(|| format!("headset {id}: connecting to {}", cfg.server))?;
    let (conn, _welcome, mut control, mut replies) = session.split();
    // A headset honours the server's Goaway: it stops sending new frames, lets the in-flight ones be
    // answered, and leaves (the server refuses frame streams that arrive well after its Goaway).
    let (goaway_tx, mut goaway) = tokio::sync::watch::channel(false);
    let watcher = {
        let stats = Arc::clone(&stats);
        tokio::spawn(async move {
            while let Ok(msg) = control.next_message().await {
                if let Message::Goaway(g) = msg {
                    eprintln!(
                        "headset {id}: server going away ({}): {}",
                        g.reason.name(),
                        holoface_protocol::untrusted(&g.text)
                    );
                    stats.lock().unwrap_or_else(PoisonError::into_inner).goaways += 1;
                    let _ = goaway_tx.send(true);
                    break;
                }
            }
        })
    };
    let sent_at: Arc<Mutex<HashMap<u64, Instant>>> = Arc::default();
    let reader = {
        let (sent_at, stats) = (Arc::clone(&sent_at), Arc::clone(&stats));
        tokio::spawn(async move {
            while let Ok(r) = replies.next().await {
                let Some(t) = sent_at
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .remove(&r.frame_id)
                else {
                    continue;
                };
                let latency = t.elapsed();
                let mut s = stats.lock().unwrap_or_else(PoisonError::into_inner);
                match r.outcome {
                    ReplyOutcome::Landmarks { .. } => {
                        let us = latency.as_micros().max(1) as u64;
                        let _ = s.interval.record(us);
                        if s.measuring {
                            let _ = s.total.record(us);
                        }
                        let miss = latency > deadline;
                        s.each(|c| {
                            c.answered += 1;
                            c.misses += u64::from(miss);
                        });
                    }
                    ReplyOutcome::Dropped { reason } => {
                        s.each(|c| *c.dropped.entry(reason.name()).or_default() += 1);
                    }
                }
            }
        })
    };
    let mut k = 0u64;
    loop {
        let f = &frames[(k % frames.len() as u64) as usize];
        let due = start + period * (k / frames.len() as u64) as u32 + f.offset;
        if due >= end || *goaway.borrow() {
            break;
        }
        tokio::select! {
            () = tokio::time::sleep_until(due.into()) => {}
            _ = goaway.changed() => break,
        }
        k += 1;
        let req = FrameRequest {
            track_id: 0,
            frame_id: k,
            captured_at_us: due.duration_since(start).as_micros() as u64,
            deadline_ms: u16::try_from(deadline.as_millis()).unwrap_or(u16::MAX),
            crop: f.crop.clone(),
        };
        sent_at
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(k, Instant::now());
        stats
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .each(|c| c.sent += 1);
        let conn = conn.clone();
        tokio::spawn(async move {
            let _ = send_frame(&conn, &req).await;
        });
        // Forget frames that can no longer be answered in any useful time (bounded map).
        let stale = Instant::now() - Duration::from_secs(5);
        sent_at
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .retain(|_, t| *t > stale);
    }
    // Let the last replies arrive.
    tokio::time::sleep(deadline + Duration::from_millis(200)).await;
    reader.abort();
    watcher.abort();
    conn.close(0u32.into(), b"load test done");
    endpoint.wait_idle().await;
    Ok(())
}

/// Starts one task per simulated headset (`--clients`), taking the streams in turn, staggered by `stagger`.
pub(crate) fn launch(
    rt: &tokio::runtime::Runtime,
    args: &crate::Args,
    target: &crate::Target,
    streams: &[(Vec<ReplayFrame>, Duration)],
    window: &crate::report::Window,
    stagger: Duration,
    stats: &Arc<Mutex<Stats>>,
) -> Vec<tokio::task::JoinHandle<anyhow::Result<()>>> {
    let deadline = Duration::from_millis(u64::from(args.deadline_ms));
    (0..args.clients)
        .map(|c| {
            let (frames, period) = &streams[c % streams.len()];
            let mut cfg = ConnectConfig::new(target.addr, target.fingerprint, target.token.clone());
            cfg.client_name = format!("load-{c}");
            cfg.encodings = vec![frames[0].crop.encoding];
            cfg.connect_timeout = Duration::from_secs(5);
            let plan = Plan {
                id: c,
                cfg,
                frames: Arc::new(frames.clone()),
                period: *period,
                start: window.t0 + stagger * c as u32,
                end: window.end,
                deadline,
            };
            rt.spawn(headset(plan, Arc::clone(stats)))
        })
        .collect()
}
