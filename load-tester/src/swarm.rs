//! The simulated headsets: each connects like the real client, replays its recorded stream in a loop at the
//! planned instants and records what the server answers.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::Context;
use holoface_protocol::{FrameRequest, Message, ReplyOutcome};
use holoface_runtime::link::Backoff;
use holoface_runtime::link::connection::{ConnectConfig, client_endpoint, connect, send_frame};

use crate::replay::ReplayFrame;
use crate::report::{Outage, Stats};

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

impl Plan {
    /// When frame `k` (1-based, counting every loop) is due.
    fn due(&self, k: u64) -> Instant {
        let n = self.frames.len() as u64;
        let i = k.saturating_sub(1);
        self.start
            + self.period * u32::try_from(i / n).unwrap_or(u32::MAX)
            + self.frames[(i % n) as usize].offset
    }
}

/// How a connection ended.
enum SessionEnd {
    /// The run is over (its end, or every frame sent).
    Done,
    /// The server said Goaway: the headset leaves, as a real one does.
    Goaway,
    /// The connection broke (the server died, the network dropped it): reconnect. The outage started at
    /// the last answer of the session (or at its start when nothing was answered), not when QUIC noticed.
    Lost(String, Instant),
}

/// Connects like the real client, replays `plan.frames` in a loop from `plan.start` to `plan.end` (or the
/// server's Goaway) and records every answer, drop and deadline miss in `stats`. When the connection breaks
/// it reconnects with the client's backoff (100 ms doubling to 2 s), counts every frame that fell due
/// meanwhile as unsent, and records the outage (when, how long; unrecovered when the run ends first).
pub(crate) async fn headset(plan: Plan, stats: Arc<Mutex<Stats>>) -> anyhow::Result<()> {
    let endpoint = client_endpoint(&plan.cfg)?;
    let backoff = Backoff::default();
    let mut delay = backoff.initial;
    let mut next_frame = 1u64;
    let mut outage: Option<Instant> = None;
    let mut ever_connected = false;
    loop {
        // An attempt never outlives the run (a dead server makes it wait for the connect timeout).
        let attempt = tokio::time::timeout_at(plan.end.into(), connect(&endpoint, &plan.cfg)).await;
        if attempt.is_err() && ever_connected {
            skip_unsent(&plan, next_frame, plan.end, &stats);
            break;
        }
        let attempt = attempt.unwrap_or_else(|_| {
            Err(holoface_runtime::link::LinkError::Timeout(
                plan.cfg.connect_timeout,
            ))
        });
        match attempt {
            // The first attempt failing, or a refusal retrying cannot fix (a revoked token, another
            // certificate, an unserved version), ends the headset with the error, as the real client gives up.
            Err(e) if !ever_connected || e.kind().is_permanent() => {
                if let Some(since) = outage.take() {
                    lock(&stats).outages.push(Outage {
                        headset: plan.id,
                        at: since,
                        length: None,
                    });
                }
                return Err(e)
                    .with_context(|| format!("headset {}: connecting to {}", plan.id, plan.cfg.server));
            }
            Err(_) => {
                let retry_at = (Instant::now() + delay).min(plan.end);
                next_frame = skip_unsent(&plan, next_frame, retry_at, &stats);
                if retry_at >= plan.end {
                    break;
                }
                tokio::time::sleep_until(retry_at.into()).await;
                delay = (delay * 2).min(backoff.max);
            }
            Ok(session) => {
                ever_connected = true;
                delay = backoff.initial;
                // Frames that fell due while this attempt was in progress were not sent either.
                next_frame = skip_unsent(&plan, next_frame, Instant::now(), &stats);
                if let Some(since) = outage.take() {
                    let gone = since.elapsed();
                    eprintln!(
                        "headset {}: reconnected to {} after {:.2} s",
                        plan.id,
                        plan.cfg.server,
                        gone.as_secs_f64()
                    );
                    lock(&stats).outages.push(Outage {
                        headset: plan.id,
                        at: since,
                        length: Some(gone),
                    });
                }
                match run_session(&plan, session, &mut next_frame, &stats).await {
                    SessionEnd::Done | SessionEnd::Goaway => break,
                    SessionEnd::Lost(why, since) => {
                        eprintln!(
                            "headset {}: connection to {} lost ({why}), {:.2} s after its last answer; reconnecting",
                            plan.id,
                            plan.cfg.server,
                            since.elapsed().as_secs_f64()
                        );
                        outage = Some(since);
                    }
                }
            }
        }
    }
    if let Some(since) = outage {
        eprintln!(
            "headset {}: {} still unreachable at the end of the run",
            plan.id, plan.cfg.server
        );
        lock(&stats).outages.push(Outage {
            headset: plan.id,
            at: since,
            length: None,
        });
    }
    let _ = tokio::time::timeout(Duration::from_secs(1), endpoint.wait_idle()).await;
    Ok(())
}

fn lock(stats: &Mutex<Stats>) -> std::sync::MutexGuard<'_, Stats> {
    stats.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Counts the frames from `next` that fall due before `until` (and before the end) as unsent; returns the
/// first frame still to come.
fn skip_unsent(plan: &Plan, mut next: u64, until: Instant, stats: &Mutex<Stats>) -> u64 {
    while plan.due(next) < until.min(plan.end) {
        lock(stats).each(|c| c.unsent += 1);
        next += 1;
    }
    next
}

/// One connection: replays frames from `next_frame` until the end, a Goaway or the connection breaking.
async fn run_session(
    plan: &Plan,
    session: holoface_runtime::link::connection::Established,
    next_frame: &mut u64,
    stats: &Arc<Mutex<Stats>>,
) -> SessionEnd {
    let (id, deadline) = (plan.id, plan.deadline);
    let (conn, _welcome, mut control, mut replies) = session.split();
    // A headset honours the server's Goaway: it stops sending new frames, lets the in-flight ones be
    // answered, and leaves (the server refuses frame streams that arrive well after its Goaway).
    let (goaway_tx, mut goaway) = tokio::sync::watch::channel(false);
    let watcher = {
        let stats = Arc::clone(stats);
        tokio::spawn(async move {
            while let Ok(msg) = control.next_message().await {
                if let Message::Goaway(g) = msg {
                    eprintln!(
                        "headset {id}: server going away ({}): {}",
                        g.reason.name(),
                        holoface_protocol::untrusted(&g.text)
                    );
                    lock(&stats).goaways += 1;
                    let _ = goaway_tx.send(true);
                    break;
                }
            }
        })
    };
    let sent_at: Arc<Mutex<HashMap<u64, Instant>>> = Arc::default();
    // When the server last answered (landmarks or an explicit drop): where an outage starts.
    let last_answer = Arc::new(Mutex::new(Instant::now()));
    let reader = {
        let (sent_at, stats, last) = (Arc::clone(&sent_at), Arc::clone(stats), Arc::clone(&last_answer));
        tokio::spawn(async move {
            while let Ok(r) = replies.next().await {
                *last.lock().unwrap_or_else(PoisonError::into_inner) = Instant::now();
                let Some(t) = sent_at
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .remove(&r.frame_id)
                else {
                    continue;
                };
                let latency = t.elapsed();
                let mut s = lock(&stats);
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
    let end = loop {
        let k = *next_frame;
        let due = plan.due(k);
        if due >= plan.end {
            break SessionEnd::Done;
        }
        if *goaway.borrow() {
            break SessionEnd::Goaway;
        }
        // Only a Goaway the watcher saw ends the session as one: when the connection dies the watcher
        // stops and drops its sender, `changed()` fails, and that branch is disabled, so a lost connection
        // is always a loss (it used to race `closed()` and be taken for a Goaway half the time).
        tokio::select! {
            () = tokio::time::sleep_until(due.into()) => {}
            Ok(()) = goaway.changed() => break SessionEnd::Goaway,
            e = conn.closed() => {
                let since = *last_answer.lock().unwrap_or_else(PoisonError::into_inner);
                break SessionEnd::Lost(e.to_string(), since);
            }
        }
        *next_frame += 1;
        let f = &plan.frames[((k - 1) % plan.frames.len() as u64) as usize];
        let req = FrameRequest {
            track_id: 0,
            frame_id: k,
            captured_at_us: due.duration_since(plan.start).as_micros() as u64,
            deadline_ms: u16::try_from(deadline.as_millis()).unwrap_or(u16::MAX),
            crop: f.crop.clone(),
        };
        sent_at
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(k, Instant::now());
        lock(stats).each(|c| c.sent += 1);
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
    };
    if !matches!(end, SessionEnd::Lost(..)) {
        // Let the last replies arrive.
        tokio::time::sleep(deadline + Duration::from_millis(200)).await;
    }
    reader.abort();
    watcher.abort();
    conn.close(0u32.into(), b"load test done");
    end
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
            // The real client's timeouts and keep-alives (ConnectConfig's defaults), so a dead server is
            // noticed and reconnected to as a headset would.
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
