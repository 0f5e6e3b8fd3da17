//! `holoface-load`: replays recorded streams of real crops from many simulated headsets against an
//! alignment server, at the recorded timing or a set frame rate, with staggered starts; reports throughput,
//! latency percentiles (HdrHistogram), drops and deadline misses every interval and at the end; writes JSON
//! and a latency plot; exits 3 when an SLO flag is broken, 1 on any error (including unwritable results).
//!
//! Record a stream of crops with `holoface record --source <frames> --crops jpeg:75 --out s.hfrec`.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use hdrhistogram::Histogram;
use holoface_client::link::connection::{ConnectConfig, client_endpoint, connect, send_frame};
use holoface_protocol::recording::{FramePayload, RecordingReader};
use holoface_protocol::{Crop, FrameRequest, Message, ReplyOutcome};
use holoface_tools::plot::{Series, series_plot_png};
use serde_json::json;

/// Command line.
#[derive(Debug, Parser)]
#[command(name = "holoface-load", version, about)]
struct Args {
    /// Recorded streams of crops (`.hfrec` from `holoface record --crops`); clients take them in turn.
    #[arg(long = "recording", required = true)]
    recordings: Vec<PathBuf>,
    /// Server address (omit with `--spawn-server`).
    #[arg(long)]
    server: Option<SocketAddr>,
    /// The server certificate's SHA-256 fingerprint (hex).
    #[arg(long)]
    fingerprint: Option<String>,
    /// Access token.
    #[arg(long, env = "HOLOFACE_TOKEN", default_value = "")]
    token: String,
    /// Run an alignment server in this process on loopback with the shipped model.
    #[arg(long)]
    spawn_server: bool,
    /// DAN model for `--spawn-server`.
    #[arg(long, env = "HOLOFACE_DAN_MODEL", default_value = "models/assets/dan.onnx")]
    dan_model: PathBuf,
    /// Refinement-cascade model for `--spawn-server`.
    #[arg(
        long,
        env = "HOLOFACE_REFINE_MODEL",
        default_value = "models/assets/refiner.bin"
    )]
    refine_model: PathBuf,
    /// `--spawn-server` without the refinement cascade (DAN alone).
    #[arg(long)]
    no_refine: bool,
    /// ONNX Runtime library for `--spawn-server`.
    #[arg(
        long,
        env = "ORT_DYLIB_PATH",
        default_value = ".cache/onnxruntime/libonnxruntime.so.1.31.1"
    )]
    ort_dylib: PathBuf,
    /// ONNX Runtime intra-op threads of the spawned server.
    #[arg(long, default_value_t = 2)]
    server_threads: usize,
    /// Largest inference batch of the spawned server.
    #[arg(long, default_value_t = 8)]
    server_max_batch: usize,
    /// Simulated headsets.
    #[arg(long, default_value_t = 4)]
    clients: usize,
    /// Frames per second per headset (default: the recorded timing).
    #[arg(long)]
    fps: Option<f64>,
    /// Test length after the warm-up, seconds.
    #[arg(long, default_value_t = 30.0)]
    duration_s: f64,
    /// Warm-up before measuring, seconds (excluded from the totals).
    #[arg(long, default_value_t = 3.0)]
    warmup_s: f64,
    /// Start offset between consecutive headsets, ms (default: one frame interval spread over all).
    #[arg(long)]
    stagger_ms: Option<f64>,
    /// Per-frame deadline sent to the server; later replies count as deadline misses, ms.
    #[arg(long, default_value_t = 100)]
    deadline_ms: u16,
    /// Report interval, seconds.
    #[arg(long, default_value_t = 5.0)]
    interval_s: f64,
    /// Process whose resident memory is sampled every interval (default: this process with
    /// `--spawn-server`).
    #[arg(long)]
    server_pid: Option<u32>,
    /// JSON results.
    #[arg(long, default_value = "runs/load.json")]
    out: PathBuf,
    /// Latency plot (PNG).
    #[arg(long, default_value = "runs/load.png")]
    plot: PathBuf,
    /// SLO: fail when the measured p99 latency exceeds this, ms.
    #[arg(long)]
    max_p99_ms: Option<f64>,
    /// SLO: fail when more than this fraction of frames is dropped or unanswered.
    #[arg(long)]
    max_drop_rate: Option<f64>,
    /// SLO: fail when fewer answered frames per second than this.
    #[arg(long)]
    min_throughput: Option<f64>,
    /// SLO: fail when resident memory grows by more than this percentage from the end of the warm-up.
    #[arg(long)]
    max_rss_growth_pct: Option<f64>,
}

/// One recorded frame to replay.
#[derive(Clone)]
struct ReplayFrame {
    offset: Duration,
    crop: Crop,
}

fn read_stream(path: &Path, fps: Option<f64>) -> anyhow::Result<(Vec<ReplayFrame>, Duration)> {
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut reader = RecordingReader::new(std::io::BufReader::new(file))
        .with_context(|| format!("reading {}", path.display()))?;
    let mut frames = Vec::new();
    let mut first = None;
    while let Some(r) = reader
        .next_record()
        .with_context(|| format!("reading {}", path.display()))?
    {
        let FramePayload::Crop { crop, .. } = r.payload else {
            bail!(
                "{} holds full frames; record crops with `holoface record --crops jpeg:75`",
                path.display()
            );
        };
        let t0 = *first.get_or_insert(r.timestamp_us);
        let offset = match fps {
            Some(f) => Duration::from_secs_f64(frames.len() as f64 / f),
            None => Duration::from_micros(r.timestamp_us.saturating_sub(t0)),
        };
        frames.push(ReplayFrame { offset, crop });
    }
    if frames.is_empty() {
        bail!("{} holds no frames", path.display());
    }
    // The stream loops: one mean frame interval after its last frame comes its first again.
    let n = frames.len() as u32;
    let last = frames.last().map_or(Duration::ZERO, |f| f.offset);
    let step = match fps {
        Some(f) => Duration::from_secs_f64(1.0 / f),
        None if n > 1 => last / (n - 1),
        None => Duration::from_secs_f64(1.0 / 30.0),
    };
    Ok((frames, last + step))
}

#[derive(Default)]
struct Counts {
    sent: u64,
    answered: u64,
    misses: u64,
    dropped: HashMap<&'static str, u64>,
}

struct Stats {
    interval: Histogram<u64>,
    total: Histogram<u64>,
    window: Counts,
    totals: Counts,
    measuring: bool,
    /// Headsets that stopped sending because the server said Goaway.
    goaways: u64,
}

impl Stats {
    fn new() -> anyhow::Result<Self> {
        Ok(Self {
            interval: Histogram::new_with_bounds(1, 60_000_000, 3)?,
            total: Histogram::new_with_bounds(1, 60_000_000, 3)?,
            window: Counts::default(),
            totals: Counts::default(),
            measuring: false,
            goaways: 0,
        })
    }

    fn each(&mut self, f: impl Fn(&mut Counts)) {
        f(&mut self.window);
        if self.measuring {
            f(&mut self.totals);
        }
    }
}

fn rss_kib(pid: Option<u32>) -> Option<u64> {
    let path = pid.map_or_else(|| "/proc/self/status".to_owned(), |p| format!("/proc/{p}/status"));
    let text = std::fs::read_to_string(path).ok()?;
    let line = text.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// What one simulated headset does.
struct Plan {
    id: usize,
    cfg: ConnectConfig,
    frames: Arc<Vec<ReplayFrame>>,
    /// Length of one loop over `frames`.
    period: Duration,
    start: Instant,
    end: Instant,
    deadline: Duration,
}

async fn headset(plan: Plan, stats: Arc<Mutex<Stats>>) -> anyhow::Result<()> {
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
                        g.text
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

fn main() -> ExitCode {
    let args = Args::parse();
    let env = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(env)
        .with_writer(std::io::stderr)
        .try_init();
    match run(args) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(3),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Runs the test; `Ok(false)` when an SLO was broken.
fn run(args: Args) -> anyhow::Result<bool> {
    if args.clients == 0 || args.duration_s <= 0.0 || args.interval_s <= 0.0 {
        bail!("--clients, --duration-s and --interval-s must be positive");
    }
    let mut streams = Vec::new();
    for p in &args.recordings {
        streams.push(read_stream(p, args.fps)?);
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let mut stop_server = None;
    let (addr, fingerprint, token) = if args.spawn_server {
        let token = "load-test".to_owned();
        let mut s = alignment_server::config::Settings::for_loopback(
            &token,
            args.dan_model.clone(),
            (!args.no_refine).then(|| args.refine_model.clone()),
            args.ort_dylib.clone(),
        )?;
        s.engine.intra_threads = args.server_threads;
        s.batch.max_batch = args.server_max_batch;
        s.engine.max_batch = args.server_max_batch;
        s.max_clients = s.max_clients.max(args.clients);
        let server = rt.block_on(alignment_server::Server::bind(s))?;
        let (addr, fp) = (server.local_addr()?, server.fingerprint());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = rt.spawn(server.run(async move {
            let _ = rx.await;
        }));
        stop_server = Some((tx, task));
        (addr, fp, token)
    } else {
        let addr = args.server.context("--server (or --spawn-server) is required")?;
        let fp = args
            .fingerprint
            .as_deref()
            .context("--fingerprint is required with --server")?
            .parse()
            .map_err(|e| anyhow::anyhow!("--fingerprint: {e}"))?;
        (addr, fp, args.token.clone())
    };
    let rss_pid = args
        .server_pid
        .or(if args.spawn_server { None } else { Some(u32::MAX) });
    let rss = move || {
        if rss_pid == Some(u32::MAX) {
            None
        } else {
            rss_kib(rss_pid)
        }
    };

    let stats = Arc::new(Mutex::new(Stats::new()?));
    let warmup = Duration::from_secs_f64(args.warmup_s);
    let mut duration = Duration::from_secs_f64(args.duration_s);
    let t0 = Instant::now() + Duration::from_millis(200);
    let end = t0 + warmup + duration;
    let mean_interval = streams[0].1.as_secs_f64() / streams[0].0.len() as f64;
    let stagger = Duration::from_secs_f64(
        args.stagger_ms
            .map_or(mean_interval / args.clients as f64, |m| m / 1e3),
    );
    let deadline = Duration::from_millis(u64::from(args.deadline_ms));
    let mut tasks = Vec::new();
    for c in 0..args.clients {
        let (frames, period) = &streams[c % streams.len()];
        let mut cfg = ConnectConfig::new(addr, fingerprint, token.clone());
        cfg.client_name = format!("load-{c}");
        cfg.encodings = vec![frames[0].crop.encoding];
        cfg.connect_timeout = Duration::from_secs(5);
        let plan = Plan {
            id: c,
            cfg,
            frames: Arc::new(frames.clone()),
            period: *period,
            start: t0 + stagger * c as u32,
            end,
            deadline,
        };
        tasks.push(rt.spawn(headset(plan, Arc::clone(&stats))));
    }

    println!(
        "{:>7} {:>8} {:>8} {:>8} {:>8} {:>8} {:>7} {:>7} {:>9}",
        "t s", "sent/s", "ok/s", "p50 ms", "p99 ms", "p999 ms", "drops", "misses", "rss MiB"
    );
    let mut timeline = Vec::new();
    let (mut rss_start, mut rss_end) = (None, None);
    let interval = Duration::from_secs_f64(args.interval_s);
    let mut next = t0 + interval;
    let warm_at = t0 + warmup;
    let mut warmed = false;
    while next <= end + interval / 2 {
        // The totals cover exactly [t0 + warm-up, end), whatever the report interval.
        if !warmed && warm_at < next {
            std::thread::sleep(warm_at.saturating_duration_since(Instant::now()));
            stats.lock().unwrap_or_else(PoisonError::into_inner).measuring = true;
            rss_start = rss();
            warmed = true;
        }
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
        let now_rss = rss();
        rss_end = now_rss;
        let mut s = stats.lock().unwrap_or_else(PoisonError::into_inner);
        let secs = interval.as_secs_f64();
        let ms = |q: f64, h: &Histogram<u64>| h.value_at_quantile(q) as f64 / 1e3;
        let drops: u64 = s.window.dropped.values().sum();
        let row = json!({
            "t_s": next.duration_since(t0).as_secs_f64(),
            "sent_per_s": s.window.sent as f64 / secs, "answered_per_s": s.window.answered as f64 / secs,
            "p50_ms": ms(0.5, &s.interval), "p99_ms": ms(0.99, &s.interval), "p999_ms": ms(0.999, &s.interval),
            "drops": drops, "misses": s.window.misses, "rss_kib": now_rss,
        });
        println!(
            "{:>7.1} {:>8.1} {:>8.1} {:>8.2} {:>8.2} {:>8.2} {:>7} {:>7} {:>9}",
            next.duration_since(t0).as_secs_f64(),
            s.window.sent as f64 / secs,
            s.window.answered as f64 / secs,
            ms(0.5, &s.interval),
            ms(0.99, &s.interval),
            ms(0.999, &s.interval),
            drops,
            s.window.misses,
            now_rss.map_or("-".to_owned(), |k| format!("{:.1}", k as f64 / 1024.0)),
        );
        timeline.push(row);
        s.interval.reset();
        s.window = Counts::default();
        let all_left = s.goaways > 0 && tasks.iter().all(tokio::task::JoinHandle::is_finished);
        drop(s);
        next += interval;
        if all_left {
            // Every headset left on the server's Goaway: the run is over early.
            duration = Instant::now().saturating_duration_since(warm_at).min(duration);
            break;
        }
    }
    for t in tasks {
        rt.block_on(t).context("headset task panicked")??;
    }
    if let Some((tx, task)) = stop_server {
        let _ = tx.send(());
        rt.block_on(task)??;
    }

    let s = stats.lock().unwrap_or_else(PoisonError::into_inner);
    let secs = duration.as_secs_f64();
    let dropped: u64 = s.totals.dropped.values().sum();
    let lost = s.totals.sent.saturating_sub(s.totals.answered + dropped);
    let p = |q: f64| s.total.value_at_quantile(q) as f64 / 1e3;
    let throughput = s.totals.answered as f64 / secs;
    let drop_rate = (dropped + lost) as f64 / s.totals.sent.max(1) as f64;
    let growth = match (rss_start, rss_end) {
        (Some(a), Some(b)) if a > 0 => Some(100.0 * (b as f64 - a as f64) / a as f64),
        _ => None,
    };
    let mut broken = Vec::new();
    if let Some(m) = args.max_p99_ms.filter(|&m| p(0.99) > m) {
        broken.push(format!("p99 {:.2} ms > {m} ms", p(0.99)));
    }
    if let Some(m) = args.max_drop_rate.filter(|&m| drop_rate > m) {
        broken.push(format!("drop rate {drop_rate:.4} > {m}"));
    }
    if let Some(m) = args.min_throughput.filter(|&m| throughput < m) {
        broken.push(format!("throughput {throughput:.1}/s < {m}/s"));
    }
    if let Some(m) = args.max_rss_growth_pct {
        match growth {
            Some(g) if g > m => broken.push(format!("RSS grew {g:.2} % > {m} %")),
            None => broken.push("RSS growth SLO set but RSS could not be sampled".to_owned()),
            _ => {}
        }
    }
    let report = json!({
        "config": {
            "clients": args.clients, "fps": args.fps, "duration_s": args.duration_s, "warmup_s": args.warmup_s,
            "deadline_ms": args.deadline_ms, "stagger_ms": stagger.as_secs_f64() * 1e3,
            "recordings": args.recordings, "server": addr.to_string(), "spawned_server": args.spawn_server,
        },
        "totals": {
            "sent": s.totals.sent, "answered": s.totals.answered, "dropped": s.totals.dropped,
            "unanswered": lost, "deadline_misses": s.totals.misses, "throughput_per_s": throughput,
            "drop_rate": drop_rate, "headsets_told_goaway": s.goaways,
            "latency_ms": {"p50": p(0.5), "p99": p(0.99), "p999": p(0.999), "max": s.total.max() as f64 / 1e3,
                           "mean": s.total.mean() / 1e3},
        },
        "rss_kib": {"start": rss_start, "end": rss_end, "growth_pct": growth},
        "timeline": timeline,
        "slo": {"broken": broken},
    });
    println!(
        "total: {} sent, {} answered ({throughput:.1}/s), {dropped} dropped, {lost} unanswered, {} deadline misses; \
         latency p50 {:.2} p99 {:.2} p999 {:.2} ms; RSS growth {}",
        s.totals.sent,
        s.totals.answered,
        s.totals.misses,
        p(0.5),
        p(0.99),
        p(0.999),
        growth.map_or("n/a".to_owned(), |g| format!("{g:.2} %"))
    );
    for path in [&args.out, &args.plot] {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
    }
    std::fs::write(&args.out, serde_json::to_string_pretty(&report)?)
        .with_context(|| format!("writing {}", args.out.display()))?;
    let series = |key: &str, label: &str| Series {
        label: label.to_owned(),
        points: report["timeline"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|r| Some((r["t_s"].as_f64()?, r[key].as_f64()?)))
            .collect(),
    };
    let png = series_plot_png(
        &[
            series("p50_ms", "p50"),
            series("p99_ms", "p99"),
            series("p999_ms", "p999"),
        ],
        "time s",
        "latency ms",
    );
    std::fs::write(&args.plot, png).with_context(|| format!("writing {}", args.plot.display()))?;
    println!("wrote {} and {}", args.out.display(), args.plot.display());
    if s.goaways > 0 {
        println!(
            "{} of {} headsets stopped early on the server's Goaway",
            s.goaways, args.clients
        );
    }
    for b in &broken {
        eprintln!("SLO broken: {b}");
    }
    Ok(broken.is_empty())
}
