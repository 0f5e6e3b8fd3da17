//! Loopback benchmark of the alignment server (numbers in BENCHMARKS.md).
//!
//! ```text
//! cargo build --release -p holoface-alignment-server -p holoface-tests
//! target/release/holoface-server-bench ort        # raw ONNX Runtime, batch 1/8/32
//! target/release/holoface-server-bench throughput # server vs raw ORT, same run
//! target/release/holoface-server-bench latency    # p50/p99/p999 at 30 fps per client
//! target/release/holoface-server-bench idle       # memory per idle connection, 1000 held
//! ```
//!
//! The server runs as a child process (`target/release/holoface-server`), so
//! its RSS is its own; the raw-ORT baseline runs in this process with the
//! same model, threads and batch size.

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow, bail};
use clap::{Parser, Subcommand, ValueEnum};
use hdrhistogram::Histogram;
use holoface_inference::{BatchTensor, InferenceEngine, LandmarkOut, OnnxEngine, OnnxOptions};
use holoface_protocol::ReplyOutcome;
use holoface_quic::Fingerprint;
use holoface_tests::{TestClient, client_endpoint_with, frame, hello};

const TOKEN: &str = "bench-token";

#[derive(Debug, Parser)]
#[command(about = "Loopback benchmark of the HoloFace alignment server")]
struct Cli {
    /// ONNX model [default: $HOLOFACE_DAN_MODEL or models/assets/dan.onnx].
    #[arg(long, global = true)]
    model: Option<PathBuf>,
    /// libonnxruntime [default: $ORT_DYLIB_PATH, .cache/holoface/…, .venv].
    #[arg(long, global = true)]
    ort_dylib: Option<PathBuf>,
    /// The server binary.
    #[arg(long, global = true, default_value = "target/release/holoface-server")]
    server_bin: PathBuf,
    /// Intra-op threads (server and raw baseline).
    #[arg(long, global = true, default_value_t = 2)]
    threads: usize,
    /// The server's engine instances (each with `--threads` intra-op threads).
    #[arg(long, global = true, default_value_t = 1)]
    engine_instances: usize,
    /// ONNX Runtime intra-op spinning (server and raw baseline).
    #[arg(long, global = true)]
    spin: bool,
    /// Run the model on the CUDA execution provider (server and raw baseline; `--ort-dylib` must be the
    /// onnxruntime-gpu build). Required, never a silent CPU fallback: the run fails without a GPU.
    #[arg(long, global = true)]
    cuda: bool,
    /// The server's batching policy (`work-conserving`, or `max-wait` with `--max-wait-us`).
    #[arg(long, global = true, default_value = "work-conserving")]
    batch_policy: String,
    /// With `--batch-policy max-wait`: the wait, µs.
    #[arg(long, global = true, default_value_t = 2000)]
    max_wait_us: u64,
    /// The server's refinement cascade after DAN (`--refine false`: DAN alone, the pipeline before issue 27).
    #[arg(long, global = true, default_value_t = true, action = clap::ArgAction::Set)]
    refine: bool,
    /// Send crops of real faces (the validation faces of `$HOLOFACE_DATA`, placed on their ground-truth
    /// boxes) instead of synthetic patterns, so that DAN accepts them and the refinement cascade runs.
    #[arg(long, global = true)]
    face_crops: bool,
    /// Append one JSON line per result here.
    #[arg(long, global = true, default_value = "target/bench/server.jsonl")]
    out: PathBuf,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum Reply {
    Datagram,
    Stream,
}

impl Reply {
    const fn as_str(self) -> &'static str {
        match self {
            Self::Datagram => "datagram",
            Self::Stream => "stream",
        }
    }
}

#[derive(Debug, Subcommand)]
enum Cmd {
    /// Raw ONNX Runtime throughput at several batch sizes.
    Ort {
        #[arg(long, value_delimiter = ',', default_value = "1,8,32")]
        batches: Vec<usize>,
        #[arg(long, default_value_t = 8.0)]
        seconds: f64,
        /// Start a call every this many ms (as a camera would) instead of back to back; 0 = back to back.
        #[arg(long, default_value_t = 0.0)]
        pace_ms: f64,
    },
    /// Saturated server throughput versus raw ORT at the same batch size.
    Throughput {
        #[arg(long, default_value_t = 8)]
        batch: usize,
        #[arg(long, default_value_t = 16)]
        clients: usize,
        #[arg(long, default_value_t = 15.0)]
        seconds: f64,
        #[arg(long, value_enum, default_value = "datagram")]
        reply: Reply,
        /// Frames each client keeps outstanding.
        #[arg(long, default_value_t = 1)]
        in_flight: usize,
    },
    /// Latency at a fixed frame rate per client.
    Latency {
        #[arg(long, value_delimiter = ',', default_value = "1,4")]
        clients: Vec<usize>,
        #[arg(long, default_value_t = 30.0)]
        fps: f64,
        #[arg(long, default_value_t = 20.0)]
        seconds: f64,
        #[arg(long, default_value_t = 1)]
        batch: usize,
        #[arg(long, default_value_t = 200)]
        deadline_ms: u16,
        #[arg(long, value_enum, default_value = "datagram")]
        reply: Reply,
    },
    /// Memory per idle connection; holds N idle connections.
    Idle {
        #[arg(long, default_value_t = 1000)]
        connections: usize,
        #[arg(long, default_value_t = 15.0)]
        hold_seconds: f64,
    },
}

fn model(cli: &Cli) -> PathBuf {
    cli.model.clone().unwrap_or_else(holoface_tests::model_path)
}

fn dylib(cli: &Cli) -> PathBuf {
    cli.ort_dylib
        .clone()
        .unwrap_or_else(holoface_tests::ort_dylib_path)
}

fn record(cli: &Cli, value: &serde_json::Value) -> anyhow::Result<()> {
    use std::io::Write as _;
    if let Some(dir) = cli.out.parent() {
        std::fs::create_dir_all(dir)?;
    }
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&cli.out)
        .with_context(|| format!("opening {}", cli.out.display()))?;
    writeln!(f, "{value}")?;
    println!("{value}");
    Ok(())
}

/// Raw ORT: images per second at `batch` for about `seconds`.
/// Raw ONNX Runtime in this process: img/s and the per-call time distribution (ms).
struct RawOrt {
    img_s: f64,
    mean_ms: f64,
    p50_ms: f64,
    p99_ms: f64,
    max_ms: f64,
}

fn provider(cli: &Cli) -> holoface_inference::Provider {
    if cli.cuda {
        holoface_inference::Provider::Cuda {
            device: 0,
            required: true,
        }
    } else {
        holoface_inference::Provider::Cpu
    }
}

fn raw_ort(cli: &Cli, batch: usize, seconds: f64, pace_ms: f64) -> anyhow::Result<RawOrt> {
    let mut engine = OnnxEngine::load(&OnnxOptions {
        model: model(cli),
        ort_dylib: dylib(cli),
        intra_threads: cli.threads,
        max_batch: batch,
        provider: provider(cli),
        spin: cli.spin,
    })?;
    let mut tensor = BatchTensor::new(batch, 112 * 112);
    for i in 0..batch {
        tensor.push(&frame(0, u8::try_from(i % 200).unwrap_or(0), 0).crop.data)?;
    }
    let mut out = vec![LandmarkOut::default(); batch];
    engine.infer(&tensor, &mut out)?; // warm-up
    let mut calls = Histogram::<u64>::new_with_bounds(1, 60_000_000, 3)?;
    let pace = Duration::from_secs_f64(pace_ms.max(0.0) / 1e3);
    let start = Instant::now();
    let mut busy = Duration::ZERO;
    let mut next = start;
    while start.elapsed().as_secs_f64() < seconds {
        if !pace.is_zero() {
            std::thread::sleep(next.saturating_duration_since(Instant::now()));
            next += pace;
        }
        let t = Instant::now();
        engine.infer(&tensor, &mut out)?;
        let dt = t.elapsed();
        busy += dt;
        calls.record(u64::try_from(dt.as_micros()).unwrap_or(u64::MAX).max(1))?;
    }
    let runs = calls.len().max(1) as f64;
    let ms = |q: f64| calls.value_at_quantile(q) as f64 / 1e3;
    Ok(RawOrt {
        img_s: runs * batch as f64 / busy.as_secs_f64(),
        mean_ms: busy.as_secs_f64() * 1e3 / runs,
        p50_ms: ms(0.5),
        p99_ms: ms(0.99),
        max_ms: calls.max() as f64 / 1e3,
    })
}

/// The server as a child process.
struct ServerChild {
    child: Child,
    addr: SocketAddr,
    fingerprint: Fingerprint,
    metrics: Option<SocketAddr>,
}

impl ServerChild {
    fn start(cli: &Cli, extra: &[String]) -> anyhow::Result<Self> {
        let mut cmd = Command::new(&cli.server_bin);
        if cli.batch_policy == "max-wait" {
            cmd.args(["--max-wait-us", &cli.max_wait_us.to_string()]);
        }
        cmd.args(["--listen", "127.0.0.1:0", "--token", TOKEN, "--log-level", "warn"])
            .arg("--model")
            .arg(model(cli))
            // The file named, at its own precision: the server must run what the raw baseline measures, not
            // switch to int8 on a VNNI CPU (`engine.precision = "auto"`).
            .args(["--precision", "model"])
            .arg("--ort-dylib")
            .arg(dylib(cli))
            .args(["--intra-threads", &cli.threads.to_string()])
            .args(["--engine-instances", &cli.engine_instances.to_string()])
            .args(["--spin", if cli.spin { "true" } else { "false" }])
            .args(if cli.cuda {
                &["--cuda", "--cuda-required"][..]
            } else {
                &[][..]
            })
            .args(["--metrics-listen", "127.0.0.1:0"])
            .args(["--batch-policy", &cli.batch_policy])
            .args(["--refine", if cli.refine { "true" } else { "false" }])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        let mut child = cmd
            .spawn()
            .with_context(|| format!("starting {} (build it with --release)", cli.server_bin.display()))?;
        let stdout = child.stdout.take().ok_or_else(|| anyhow!("no stdout"))?;
        let mut line = String::new();
        let mut reader = BufReader::new(stdout);
        while !line.starts_with("holoface-server on") {
            line.clear();
            if reader.read_line(&mut line)? == 0 {
                let _ = child.kill();
                bail!("the server exited before printing its address");
            }
        }
        // "holoface-server on ADDR certificate-sha256 FP metrics ADDR"
        let words: Vec<&str> = line.split_whitespace().collect();
        let (Some(addr), Some(fp), Some(m)) = (words.get(2), words.get(4), words.get(6)) else {
            let _ = child.kill();
            bail!("unexpected server output {line:?}");
        };
        Ok(Self {
            addr: addr.parse()?,
            fingerprint: fp.parse()?,
            metrics: m.parse().ok(),
            child,
        })
    }

    fn rss_kib(&self) -> anyhow::Result<u64> {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))?;
        status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .ok_or_else(|| anyhow!("no VmRSS"))
    }

    async fn metric(&self, name: &str) -> anyhow::Result<f64> {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let addr = self.metrics.ok_or_else(|| anyhow!("no metrics listener"))?;
        let mut s = tokio::net::TcpStream::connect(addr).await?;
        s.write_all(b"GET /metrics HTTP/1.1\r\n\r\n").await?;
        let mut body = String::new();
        s.read_to_string(&mut body).await?;
        body.lines()
            .find_map(|l| l.strip_prefix(name).and_then(|v| v.trim().parse().ok()))
            .ok_or_else(|| anyhow!("metric {name} not found"))
    }

    fn stop(mut self) {
        // SIGTERM would be nicer; kill is enough for a benchmark child.
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

async fn connect(server: &ServerChild, max_in_flight: u16) -> anyhow::Result<TestClient> {
    let mut h = hello(TOKEN);
    h.max_in_flight = max_in_flight;
    let endpoint = client_endpoint_with(server.fingerprint, Some(Duration::from_secs(2)))?;
    Ok(TestClient::connect_on(endpoint, server.addr, h).await?)
}

/// Saturating client: keeps `in_flight` frames outstanding; counts aligned
/// replies that arrive between `count_from` and `until`.
/// Raw 112-px crops of the validation faces, each on its ground-truth box (`--face-crops`).
fn face_crops() -> anyhow::Result<Vec<holoface_protocol::Crop>> {
    use holoface_harness::data::{Split, default_data_root, load_folder};
    use holoface_models::crop::{Crop112, crop_bilinear};
    use holoface_models::geometry::{Point2, Rect, Similarity2};
    use holoface_models::shape::{dan_mean_shape, fit_to_box};
    let mean = dan_mean_shape();
    let faces = load_folder(
        &default_data_root().join("faces68/train"),
        Split::Validation,
        true,
    )?;
    faces
        .iter()
        .map(|f| {
            let gt = f.landmarks.context("annotation missing")?;
            let mut init = [Point2::default(); 68];
            fit_to_box(
                &mean,
                &Rect::bounding(&gt).context("empty annotation")?,
                &mut init,
            );
            let sim = Similarity2::fit(&init, &mean).context("degenerate annotation")?;
            let mut crop = Crop112::default();
            crop_bilinear(&f.image.view(), &sim, &mut crop)?;
            Ok(holoface_protocol::Crop::raw(112, 112, crop.as_slice().to_vec()))
        })
        .collect()
}

async fn saturate(
    mut c: TestClient,
    in_flight: usize,
    count_from: Instant,
    until: Instant,
    aligned: Arc<AtomicU64>,
    crops: Arc<Vec<holoface_protocol::Crop>>,
) -> anyhow::Result<()> {
    let mut next = 1_u64;
    let mut outstanding = 0;
    while Instant::now() < until {
        while outstanding < in_flight {
            let mut req = frame(next, u8::try_from(next % 200).unwrap_or(0), 0);
            if !crops.is_empty() {
                req.crop = crops[usize::try_from(next).unwrap_or(0) % crops.len()].clone();
            }
            c.send_frame(&req).await?;
            next += 1;
            outstanding += 1;
        }
        let reply = tokio::time::timeout(Duration::from_secs(10), c.next_reply()).await??;
        outstanding -= 1;
        let now = Instant::now();
        if matches!(reply.outcome, ReplyOutcome::Landmarks { .. }) && now >= count_from && now < until {
            aligned.fetch_add(1, Ordering::Relaxed);
        }
    }
    Ok(())
}

async fn throughput(
    cli: &Cli,
    batch: usize,
    clients: usize,
    seconds: f64,
    reply: Reply,
    in_flight: usize,
) -> anyhow::Result<()> {
    let crops = Arc::new(if cli.face_crops { face_crops()? } else { Vec::new() });
    // Raw ORT before and after the server run (background load drifts).
    let first = raw_ort(cli, batch, seconds, 0.0)?;
    let (raw_before, raw_ms) = (first.img_s, first.mean_ms);
    let server = ServerChild::start(
        cli,
        &[
            "--max-batch".into(),
            batch.to_string(),
            "--max-clients".into(),
            (clients + 8).to_string(),
            "--max-frame-age-ms".into(),
            "60000".into(),
            "--reply-channel".into(),
            reply.as_str().into(),
        ],
    )?;
    let mut conns = Vec::new();
    for _ in 0..clients {
        conns.push(connect(&server, u16::try_from(in_flight).unwrap_or(1)).await?);
    }
    // Warm-up, then the measured window.
    let start_at = Instant::now() + Duration::from_secs(3);
    let until = start_at + Duration::from_secs_f64(seconds);
    let measured = Arc::new(AtomicU64::new(0));
    let mut tasks = Vec::new();
    for c in conns {
        tasks.push(tokio::spawn(saturate(
            c,
            in_flight,
            start_at,
            until,
            Arc::clone(&measured),
            Arc::clone(&crops),
        )));
    }
    tokio::time::sleep_until(tokio::time::Instant::from_std(start_at)).await;
    let infer_before = server
        .metric("holoface_inference_seconds_sum")
        .await
        .unwrap_or(0.0);
    let before = server.metric("holoface_batch_size_count").await.unwrap_or(0.0);
    let frames_before = server
        .metric("holoface_frames_aligned_total")
        .await
        .unwrap_or(0.0);
    tokio::time::sleep_until(tokio::time::Instant::from_std(until)).await;
    let after = server.metric("holoface_batch_size_count").await.unwrap_or(0.0);
    let frames_after = server
        .metric("holoface_frames_aligned_total")
        .await
        .unwrap_or(0.0);
    for t in tasks {
        t.await??;
    }
    let got = measured.load(Ordering::Relaxed) as f64 / seconds;
    let mean_batch = (frames_after - frames_before) / (after - before).max(1.0);
    let infer_after = server
        .metric("holoface_inference_seconds_sum")
        .await
        .unwrap_or(0.0);
    let engine_busy = (infer_after - infer_before) / seconds;
    // Refinement time per refined crop over the whole run (the histogram's sum over its count).
    let refine_us = match (
        server.metric("holoface_refine_seconds_sum").await,
        server.metric("holoface_refine_seconds_count").await,
    ) {
        (Ok(sum), Ok(n)) if n > 0.0 => Some(sum * 1e6 / n),
        _ => None,
    };
    let server_ms_per_batch = (infer_after - infer_before) * 1e3 / (after - before).max(1.0);
    server.stop();
    let raw_after = raw_ort(cli, batch, seconds, 0.0)?.img_s;
    let raw = f64::midpoint(raw_before, raw_after);
    record(
        cli,
        &serde_json::json!({
            "bench": "throughput", "refine": cli.refine, "face_crops": cli.face_crops, "policy": policy_label(cli), "batch": batch, "threads": cli.threads, "spin": cli.spin, "clients": clients, "in_flight": in_flight,
            "reply": reply.as_str(), "seconds": seconds,
            "raw_ort_img_s": raw, "raw_ort_before_img_s": raw_before, "raw_ort_after_img_s": raw_after,
            "raw_ort_ms_per_batch": raw_ms,
            "server_img_s": got, "ratio": got / raw, "server_mean_batch": mean_batch,
            "server_engine_busy_fraction": engine_busy, "server_ms_per_batch": server_ms_per_batch,
            "server_refine_us_per_crop": refine_us,
        }),
    )
}

async fn latency(
    cli: &Cli,
    clients: usize,
    fps: f64,
    seconds: f64,
    batch: usize,
    deadline_ms: u16,
    reply: Reply,
) -> anyhow::Result<()> {
    let server = ServerChild::start(
        cli,
        &[
            "--max-batch".into(),
            batch.to_string(),
            "--max-clients".into(),
            (clients + 8).to_string(),
            "--reply-channel".into(),
            reply.as_str().into(),
            "--max-frame-age-ms".into(),
            deadline_ms.to_string(),
        ],
    )?;
    let period = Duration::from_secs_f64(1.0 / fps);
    let start = Instant::now() + Duration::from_millis(500);
    let until = start + Duration::from_secs_f64(seconds);
    let mut tasks = Vec::new();
    for i in 0..clients {
        let mut c = connect(&server, 1).await?;
        // Stagger clients across one frame period.
        let offset = period.mul_f64(i as f64 / clients as f64);
        tasks.push(tokio::spawn(async move {
            let mut hist = Histogram::<u64>::new_with_bounds(1, 60_000_000, 3)?;
            // Per stage, from the reply's own timings: queue wait, inference, and the rest of the round trip
            // (QUIC both ways, stream receive, crop check, scheduling, reply).
            let mut stages = [us_histogram()?, us_histogram()?, us_histogram()?];
            let mut drops: HashMap<&'static str, u64> = HashMap::new();
            let mut sent_at: HashMap<u64, Instant> = HashMap::new();
            let mut ticker = tokio::time::interval_at(tokio::time::Instant::from_std(start + offset), period);
            ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
            let (mut next, mut skipped, mut sent) = (1_u64, 0_u64, 0_u64);
            loop {
                tokio::select! {
                    _ = ticker.tick() => {
                        if Instant::now() >= until { break; }
                        // At most one frame in flight, newest wins: a tick
                        // while one is outstanding is a skipped frame.
                        if sent_at.is_empty() {
                            c.send_frame(&frame(next, u8::try_from(next % 200).unwrap_or(0), deadline_ms)).await?;
                            sent_at.insert(next, Instant::now());
                            sent += 1;
                        } else {
                            skipped += 1;
                        }
                        next += 1;
                    }
                    r = c.next_reply() => {
                        let r = r?;
                        let Some(t) = sent_at.remove(&r.frame_id) else { continue };
                        match r.outcome {
                            ReplyOutcome::Landmarks { queue_us, infer_us, .. } => {
                                let rtt = u64::try_from(t.elapsed().as_micros()).unwrap_or(u64::MAX);
                                hist.record(rtt)?;
                                let (q, i) = (u64::from(queue_us), u64::from(infer_us));
                                for (h, v) in stages.iter_mut().zip([q, i, rtt.saturating_sub(q + i)]) {
                                    h.record(v.max(1))?;
                                }
                            }
                            ReplyOutcome::Dropped { reason } => {
                                *drops.entry(reason.name()).or_default() += 1;
                            }
                        }
                    }
                }
            }
            Ok::<_, anyhow::Error>((hist, drops, sent, skipped, stages))
        }));
    }
    let mut all = Histogram::<u64>::new_with_bounds(1, 60_000_000, 3)?;
    let mut all_stages = [us_histogram()?, us_histogram()?, us_histogram()?];
    let mut drops: HashMap<&'static str, u64> = HashMap::new();
    let (mut sent, mut skipped) = (0, 0);
    for t in tasks {
        let (h, d, s, k, st) = t.await??;
        all.add(&h)?;
        for (a, b) in all_stages.iter_mut().zip(&st) {
            a.add(b)?;
        }
        for (k2, v) in d {
            *drops.entry(k2).or_default() += v;
        }
        sent += s;
        skipped += k;
    }
    server.stop();
    let ms = |q: f64| all.value_at_quantile(q) as f64 / 1e3;
    record(
        cli,
        &serde_json::json!({
            "bench": "latency", "policy": policy_label(cli), "spin": cli.spin, "clients": clients, "fps": fps, "batch": batch, "threads": cli.threads,
            "reply": reply.as_str(), "seconds": seconds, "deadline_ms": deadline_ms,
            "sent": sent, "aligned": all.len(), "skipped_ticks": skipped, "drops": drops,
            "p50_ms": ms(0.5), "p99_ms": ms(0.99), "p999_ms": ms(0.999), "max_ms": all.max() as f64 / 1e3,
            "stages_p50_ms": stage_p50(&all_stages)?,
        }),
    )
}

fn us_histogram() -> anyhow::Result<Histogram<u64>> {
    Ok(Histogram::new_with_bounds(1, 60_000_000, 3)?)
}

/// Median of each stage histogram (queue, inference, rest of the round trip), ms.
fn stage_p50(stages: &[Histogram<u64>; 3]) -> anyhow::Result<serde_json::Value> {
    let p50 = |i: usize| stages[i].value_at_quantile(0.5) as f64 / 1e3;
    Ok(serde_json::json!({"queue": p50(0), "inference": p50(1), "rest_of_round_trip": p50(2)}))
}

fn policy_label(cli: &Cli) -> String {
    let policy = match cli.batch_policy.as_str() {
        "max-wait" => format!("max-wait {} us", cli.max_wait_us),
        other => other.to_owned(),
    };
    if cli.engine_instances > 1 {
        format!(
            "{policy}, {} engines x {} threads",
            cli.engine_instances, cli.threads
        )
    } else {
        policy
    }
}

async fn idle(cli: &Cli, connections: usize, hold_seconds: f64) -> anyhow::Result<()> {
    let server = ServerChild::start(
        cli,
        &[
            "--max-clients".into(),
            (connections + 16).to_string(),
            "--idle-timeout-ms".into(),
            "10000".into(),
        ],
    )?;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let rss0 = server.rss_kib()?;
    // A few client endpoints (UDP sockets), many connections each.
    let endpoints: Vec<_> = (0..8)
        .map(|_| client_endpoint_with(server.fingerprint, Some(Duration::from_secs(3))))
        .collect::<Result<_, _>>()?;
    let mut clients = Vec::with_capacity(connections);
    for i in 0..connections {
        let ep = endpoints
            .get(i % endpoints.len())
            .ok_or_else(|| anyhow!("no endpoint"))?
            .clone();
        clients.push(TestClient::connect_on(ep, server.addr, hello(TOKEN)).await?);
    }
    let connected_at = server.metric("holoface_connected_clients").await?;
    tokio::time::sleep(Duration::from_secs_f64(hold_seconds)).await;
    let rss1 = server.rss_kib()?;
    let connected_after = server.metric("holoface_connected_clients").await?;
    let still_open = clients.iter().filter(|c| c.conn.close_reason().is_none()).count();
    server.stop();
    record(
        cli,
        &serde_json::json!({
            "bench": "idle", "connections": connections, "hold_seconds": hold_seconds,
            "server_rss_before_kib": rss0, "server_rss_after_kib": rss1,
            "kib_per_connection": (rss1.saturating_sub(rss0)) as f64 / connections as f64,
            "server_connected_gauge_start": connected_at, "server_connected_gauge_end": connected_after,
            "client_side_still_open": still_open,
        }),
    )
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    holoface_process::logging::init(holoface_process::logging::env_filter_or("warn"));
    let cli = Cli::parse();
    println!(
        "machine: {} cores; note any background load (load average {})",
        std::thread::available_parallelism().map_or(0, usize::from),
        std::fs::read_to_string("/proc/loadavg")
            .unwrap_or_default()
            .trim()
    );
    match &cli.cmd {
        Cmd::Ort {
            batches,
            seconds,
            pace_ms,
        } => {
            for &b in batches {
                let r = raw_ort(&cli, b, *seconds, *pace_ms)?;
                record(
                    &cli,
                    &serde_json::json!({"bench": "raw_ort", "batch": b, "threads": cli.threads, "spin": cli.spin,
                        "cuda": cli.cuda, "model": model(&cli), "pace_ms": pace_ms, "img_s": r.img_s,
                        "ms_per_batch": r.mean_ms, "p50_ms": r.p50_ms, "p99_ms": r.p99_ms, "max_ms": r.max_ms}),
                )?;
            }
            Ok(())
        }
        Cmd::Throughput {
            batch,
            clients,
            seconds,
            reply,
            in_flight,
        } => throughput(&cli, *batch, *clients, *seconds, *reply, *in_flight).await,
        Cmd::Latency {
            clients,
            fps,
            seconds,
            batch,
            deadline_ms,
            reply,
        } => {
            for &n in clients {
                latency(&cli, n, *fps, *seconds, *batch, *deadline_ms, *reply).await?;
            }
            Ok(())
        }
        Cmd::Idle {
            connections,
            hold_seconds,
        } => idle(&cli, *connections, *hold_seconds).await,
    }
}
