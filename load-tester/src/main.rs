//! `holoface-load`: replays recorded streams of real crops from many simulated headsets against an
//! alignment server, at the recorded timing or a set frame rate, with staggered starts; reports throughput,
//! latency percentiles (HdrHistogram), drops and deadline misses every interval and at the end; writes JSON
//! and a latency plot; exits 3 when an SLO flag is broken, 1 on any error (including unwritable results).
//!
//! Record a stream of crops with `holoface record --source <frames> --crops jpeg:75 --out s.hfrec`.

mod replay;
mod report;
mod swarm;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use clap::Parser;
use holoface_process::stop::Stop;
use holoface_quic::Fingerprint;
use holoface_runtime::assets::home;

use crate::report::{Stats, Window};

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
    #[arg(long, env = "HOLOFACE_DAN_MODEL", default_value_os_t = home::DAN.default_path())]
    dan_model: PathBuf,
    /// Refinement-cascade model for `--spawn-server`.
    #[arg(long, env = "HOLOFACE_REFINE_MODEL", default_value_os_t = home::REFINER.default_path())]
    refine_model: PathBuf,
    /// `--spawn-server` without the refinement cascade (DAN alone).
    #[arg(long)]
    no_refine: bool,
    /// ONNX Runtime library for `--spawn-server`.
    #[arg(long, env = "ORT_DYLIB_PATH", default_value_os_t = home::ORT_LIBRARY.default_path())]
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
    /// SLO: fail when fewer than this fraction of the frames that fell due got landmarks: frames the server
    /// dropped, frames lost, or never sent because the server was unreachable, break it. 0 = off (a run in
    /// which no frame was answered fails whatever this is).
    #[arg(long, default_value_t = 0.9)]
    min_answered: f64,
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

fn main() -> ExitCode {
    let args = Args::parse();
    holoface_process::logging::init(holoface_process::logging::env_filter_or("warn"));
    let stop = Stop::new();
    stop_on_signals(&stop);
    let result = run(args, &stop);
    if let (Some(sig), Ok(_)) = (stop.requested(), &result) {
        // Ended by a signal, its report written: the shell's code for the signal.
        return ExitCode::from(u8::try_from(sig.exit_code()).unwrap_or(1));
    }
    match result {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::from(3),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Ctrl-C and SIGTERM, recorded in `stop` (which the run watches): the first ends the test early, with the report
/// (table, `--out`, `--plot`) for the time it ran; a second ends the process at once.
fn stop_on_signals(stop: &Stop) {
    let stop = stop.clone();
    let installed = holoface_process::signals::on_signals(move |sig| {
        if stop.request(sig) {
            eprintln!(
                "{}: ending the test and writing its report for the time it ran (send it again to stop at once)",
                sig.name()
            );
            return;
        }
        eprintln!("{}: stopped at once, no report", sig.name());
        std::process::exit(sig.exit_code());
    });
    if let Err(e) = installed {
        eprintln!("warning: no signal handler ({e}): Ctrl-C ends the test without a report");
    }
}

/// The server under test: the one at `--server`, or one spawned in this process (with its stop switch).
struct Target {
    addr: SocketAddr,
    fingerprint: Fingerprint,
    token: String,
    spawned: Option<SpawnedServer>,
}

/// A server running in this process: the switch that stops it, and its task.
type SpawnedServer = (
    tokio::sync::oneshot::Sender<()>,
    tokio::task::JoinHandle<Result<(), holoface_alignment_server::ServerError>>,
);

fn target(args: &Args, rt: &tokio::runtime::Runtime) -> anyhow::Result<Target> {
    if args.spawn_server {
        let token = "load-test".to_owned();
        let mut s = holoface_alignment_server::config::Settings::for_loopback(
            &token,
            args.dan_model.clone(),
            (!args.no_refine).then(|| args.refine_model.clone()),
            args.ort_dylib.clone(),
        )?;
        s.engine.intra_threads = args.server_threads;
        s.batch.max_batch = args.server_max_batch;
        s.engine.max_batch = args.server_max_batch;
        s.max_clients = s.max_clients.max(args.clients);
        let server = rt.block_on(holoface_alignment_server::AlignmentServer::bind(s))?;
        let (addr, fingerprint) = (server.local_addr()?, server.fingerprint());
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = rt.spawn(server.run(async move {
            let _ = rx.await;
        }));
        Ok(Target {
            addr,
            fingerprint,
            token,
            spawned: Some((tx, task)),
        })
    } else {
        let addr = args.server.context("--server (or --spawn-server) is required")?;
        let fingerprint = args
            .fingerprint
            .as_deref()
            .context("--fingerprint is required with --server")?
            .parse()
            .map_err(|e| anyhow::anyhow!("--fingerprint: {e}"))?;
        Ok(Target {
            addr,
            fingerprint,
            token: args.token.clone(),
            spawned: None,
        })
    }
}

/// Runs the test until its end or until `stop` is asked for; `Ok(false)` when an SLO was broken.
fn run(args: Args, stop: &Stop) -> anyhow::Result<bool> {
    if args.clients == 0 || args.duration_s <= 0.0 || args.interval_s <= 0.0 {
        bail!("--clients, --duration-s and --interval-s must be positive");
    }
    if !(0.0..=1.0).contains(&args.min_answered) {
        bail!(
            "--min-answered {} must be within 0..=1 (0 turns the check off)",
            args.min_answered
        );
    }
    let mut streams = Vec::new();
    for p in &args.recordings {
        streams.push(replay::read_stream(p, args.fps)?);
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let target = target(&args, &rt)?;
    // Resident memory: of --server-pid, else of this process when it runs the server, else of nothing.
    let rss_pid = args
        .server_pid
        .or(if args.spawn_server { None } else { Some(u32::MAX) });

    let stats = Arc::new(Mutex::new(Stats::new()?));
    let t0 = Instant::now() + Duration::from_millis(200);
    let (warmup, duration) = (
        Duration::from_secs_f64(args.warmup_s),
        Duration::from_secs_f64(args.duration_s),
    );
    let window = Window {
        t0,
        warmup,
        duration,
        end: t0 + warmup + duration,
    };
    let mean_interval = streams[0].1.as_secs_f64() / streams[0].0.len() as f64;
    let stagger = Duration::from_secs_f64(
        args.stagger_ms
            .map_or(mean_interval / args.clients as f64, |m| m / 1e3),
    );
    let tasks = swarm::launch(&rt, &args, &target, &streams, &window, stagger, &stats);
    let measured = report::monitor(&stats, &window, args.interval_s, rss_pid, &tasks, stop);
    if measured.stopped_by.is_some() {
        // A signal ended the test: the headsets stop now, not at the planned end.
        for t in &tasks {
            t.abort();
        }
    }
    for t in tasks {
        match rt.block_on(t) {
            Err(e) if e.is_cancelled() => {}
            r => r.context("headset task panicked")??,
        }
    }
    if let Some((tx, task)) = target.spawned {
        let _ = tx.send(());
        rt.block_on(task)??;
    }
    report::finish(&args, &stats, measured, target.addr, stagger)
}
