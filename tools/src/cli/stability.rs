//! `holoface stability`: how steady the landmarks are on real, unannotated video, per aligner, raw and
//! steadied, against a per-frame peer (dlib through `models/peer_video_dlib.py`). Measures in
//! [`crate::stability`].

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::{Args as ClapArgs, ValueEnum};
use holoface_runtime::{
    AlignerChoice, AnsweredBy, BlendshapeParams, Blendshapes, FaceTracker, InitSource, RemoteOptions,
    SessionOptions, TrackerOptions,
};
use holoface_sources::output::write_atomic;
use holoface_sources::source::open_source;
use serde_json::json;

use crate::args::RuntimeArgs;
use crate::expressions::{RestRule, VideoReport, video_report};
use crate::stability::{Landmarks, Summary, agreement, jitter49, jump, parse_peer, summarise};

/// The aligners `stability` can run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum StabilityAligner {
    /// KRFWS on this device (what a headset shows without the link).
    Krfws,
    /// DAN and the refiner on an alignment server started in this process on loopback, KRFWS when it misses
    /// the deadline.
    Remote,
}

/// Arguments of `holoface stability`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// A video file (MP4, WebM, MKV, ...: whatever the system's FFmpeg libraries decode), `.y4m`, or `-` for a
    /// YUV4MPEG2 stream on standard input (`ffmpeg -i CLIP -f yuv4mpegpipe - | holoface stability --source -`).
    #[arg(long)]
    pub source: PathBuf,
    /// Frame rate when the source has none.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// The per-frame peer's landmarks (`models/peer_video_dlib.py --video CLIP --out FILE`).
    #[arg(long)]
    pub peer: Option<PathBuf>,
    /// Aligners to measure, each in its own tracker over the same frames.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "krfws,remote")]
    pub aligners: Vec<StabilityAligner>,
    /// The landmark filter.
    #[command(flatten)]
    pub steady: crate::args::SteadyArgs,
    /// Per-frame deadline for the server's answer, milliseconds (`remote`).
    #[arg(long, default_value_t = holoface_runtime::defaults::DEADLINE_MS)]
    pub deadline_ms: u64,
    /// Intra-op threads of the in-process server (`remote`).
    #[arg(long, default_value_t = 1)]
    pub server_threads: usize,
    /// Report (JSON).
    #[arg(long, default_value = "runs/stability/stability.json")]
    pub out: PathBuf,
    /// Plot of jitter over time (PNG), a 15-frame running mean per series.
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Stop after this many frames.
    #[arg(long, default_value_t = 100_000)]
    pub max_frames: usize,
    /// Also write every frame (JSON lines: per aligner, who answered, the blendshape coefficients and the
    /// steadied and raw landmarks).
    #[arg(long)]
    pub frames: Option<PathBuf>,
    /// CANDIDE-3 model.
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
    /// Runtime assets.
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

/// One aligner's tracker and what it answered per frame.
struct Run {
    name: &'static str,
    tracker: FaceTracker,
    raw: Vec<Landmarks>,
    steady: Vec<Landmarks>,
    by: Vec<Option<AnsweredBy>>,
    detections: usize,
    /// The blendshape coefficients per frame.
    shapes: Vec<Option<Blendshapes>>,
}

/// One aligner's report.
#[derive(Debug, serde::Serialize)]
struct Report {
    aligner: &'static str,
    frames: usize,
    faces_found: usize,
    /// Faces found by a fresh detection after the first one (tracking was lost and found again).
    redetections: usize,
    remote_answers: usize,
    raw_jitter49: Option<Summary>,
    steadied_jitter49: Option<Summary>,
    raw_vs_peer_nme49: Option<Summary>,
    steadied_vs_peer_nme49: Option<Summary>,
    switches: usize,
    /// The largest jump at a remote/local switch (eye distances), raw and steadied.
    largest_switch_jump_raw: Option<f64>,
    largest_switch_jump_steadied: Option<f64>,
    /// The blendshapes against the lips' gap and the eyes' opening measured on the peer's landmarks (ours,
    /// raw, without a peer), after calibration.
    expressions: VideoReport,
}

fn report(r: &Run, peer: Option<&[Landmarks]>) -> Report {
    let frames = r.raw.len();
    // Calibration takes the first frames of the first track.
    let calibrated_from =
        r.raw.iter().position(Option::is_some).unwrap_or(0) + BlendshapeParams::default().calibration_frames;
    let switch_frames: Vec<usize> = (1..frames)
        .filter(|&t| matches!((r.by[t - 1], r.by[t]), (Some(a), Some(b)) if a != b))
        .collect();
    let largest = |lm: &[Landmarks]| {
        switch_frames
            .iter()
            .filter_map(|&t| jump(lm, t))
            .fold(None, |m: Option<f64>, v| Some(m.map_or(v, |m| m.max(v))))
    };
    let vs_peer = |lm: &[Landmarks]| peer.and_then(|p| summarise(&agreement(lm, p)));
    Report {
        aligner: r.name,
        frames,
        faces_found: r.raw.iter().filter(|l| l.is_some()).count(),
        redetections: r.detections.saturating_sub(1),
        remote_answers: r.by.iter().filter(|b| **b == Some(AnsweredBy::RemoteDan)).count(),
        raw_jitter49: summarise(&jitter49(&r.raw)),
        steadied_jitter49: summarise(&jitter49(&r.steady)),
        raw_vs_peer_nme49: vs_peer(&r.raw),
        steadied_vs_peer_nme49: vs_peer(&r.steady),
        switches: switch_frames.len(),
        largest_switch_jump_raw: largest(&r.raw),
        largest_switch_jump_steadied: largest(&r.steady),
        expressions: video_report(
            &r.shapes,
            peer.unwrap_or(&r.raw),
            calibrated_from,
            RestRule::default(),
        ),
    }
}

fn pct(s: Option<Summary>, f: impl Fn(&Summary) -> f64) -> String {
    s.map_or_else(|| "-".to_owned(), |s| format!("{:.2} %", 100.0 * f(&s)))
}

/// Tracks the clip's frames (at most `max_frames`) with every run's tracker, recording each run's raw and
/// steadied landmarks, who answered and the re-detections; `paced` replays at the clip's own rate. Returns
/// the frame count.
fn track_clip(
    runs: &mut [Run],
    source: &mut dyn holoface_sources::FrameSource,
    max_frames: usize,
    paced: bool,
) -> anyhow::Result<usize> {
    let mut frames = 0usize;
    let mut clock: Option<(std::time::Instant, u64)> = None;
    while frames < max_frames {
        let Some(sf) = source.next_frame()? else {
            break;
        };
        if paced {
            let (t0, ts0) = *clock.get_or_insert((std::time::Instant::now(), sf.timestamp_us));
            let due = t0 + Duration::from_micros(sf.timestamp_us.saturating_sub(ts0));
            std::thread::sleep(due.saturating_duration_since(std::time::Instant::now()));
        }
        let frame = sf.view();
        for r in runs.iter_mut() {
            let step = r
                .tracker
                .process_step(&frame)
                .with_context(|| format!("frame {} ({})", sf.index, r.name))?;
            let face = step.faces.faces.first().map(|f| f.update);
            r.raw.push(face.map(|u| u.raw_landmarks));
            r.steady.push(face.map(|u| u.landmarks));
            r.by.push(face.map(|u| u.answered_by));
            r.shapes.push(face.map(|u| u.blendshapes));
            r.detections += usize::from(face.is_some_and(|u| u.init == InitSource::Detection));
        }
        frames += 1;
    }
    Ok(frames)
}

/// One JSON line per frame: per aligner, who answered, the blendshape coefficients (by ARKit name) and the
/// steadied and raw landmarks (x, y pairs).
fn frame_lines(runs: &[Run], frames: usize) -> String {
    let mut out = String::new();
    for t in 0..frames {
        let per: serde_json::Map<String, serde_json::Value> = runs
            .iter()
            .map(|r| {
                let shapes = r.shapes.get(t).copied().flatten().map(|b| {
                    b.iter()
                        .map(|(s, v)| (s.arkit_name().to_owned(), json!(v)))
                        .collect::<serde_json::Map<_, _>>()
                });
                let by = r.by.get(t).copied().flatten().map(|b| format!("{b:?}"));
                let points = |lm: Option<&Landmarks>| {
                    lm.copied()
                        .flatten()
                        .map(|p| p.iter().flat_map(|q| [q.x, q.y]).collect::<Vec<f32>>())
                };
                (
                    r.name.to_owned(),
                    json!({
                        "answered_by": by,
                        "blendshapes": shapes,
                        "landmarks": points(r.steady.get(t)),
                        "raw_landmarks": points(r.raw.get(t)),
                    }),
                )
            })
            .collect();
        out.push_str(&json!({ "frame": t, "aligners": per }).to_string());
        out.push('\n');
    }
    out
}

/// Prints the table: one line per aligner (and its switch jumps), then the peer's.
fn say_table(reports: &[Report], peer: Option<&[Landmarks]>, peer_jitter: Option<Summary>) {
    crate::say!(
        "{:<8} {:>7} {:>6} {:>9} {:>14} {:>14} {:>14} {:>13} {:>13}",
        "aligner",
        "faces",
        "redet",
        "remote",
        "raw jitter49",
        "steady jit49",
        "steady p95",
        "vs peer raw",
        "vs peer st."
    );
    for r in reports {
        crate::say!(
            "{:<8} {:>7} {:>6} {:>9} {:>14} {:>14} {:>14} {:>13} {:>13}",
            r.aligner,
            r.faces_found,
            r.redetections,
            r.remote_answers,
            pct(r.raw_jitter49, |s| s.mean),
            pct(r.steadied_jitter49, |s| s.mean),
            pct(r.steadied_jitter49, |s| s.p95),
            pct(r.raw_vs_peer_nme49, |s| s.mean),
            pct(r.steadied_vs_peer_nme49, |s| s.mean),
        );
        if r.switches > 0 {
            crate::say!(
                "         {} remote/local switches; largest jump raw {}, steadied {}",
                r.switches,
                r.largest_switch_jump_raw
                    .map_or("-".into(), |v| format!("{:.2} %", 100.0 * v)),
                r.largest_switch_jump_steadied
                    .map_or("-".into(), |v| format!("{:.2} %", 100.0 * v)),
            );
        }
    }
    for r in reports {
        let e = &r.expressions;
        let r2 = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.2}"));
        crate::say!(
            "{:<8} blendshapes ({} frames): r(jawOpen, lip gap) {}, r(eyeBlink, eye closing) {}; at rest ({} frames) largest mean {}, largest p95 {}",
            r.aligner,
            e.frames,
            r2(e.jaw_open_vs_lip_gap),
            r2(e.blink_vs_eye_closing),
            e.rest_frames,
            e.rest_max.map_or("-".into(), |(n, v)| format!("{n} {v:.3}")),
            e.rest_p95_max.map_or("-".into(), |(n, v)| format!("{n} {v:.3}")),
        );
    }
    if let Some(p) = peer {
        crate::say!(
            "{:<8} {:>7} {:>6} {:>9} {:>14} (per frame, its own detector; p95 {})",
            "dlib",
            p.iter().filter(|l| l.is_some()).count(),
            "-",
            "-",
            pct(peer_jitter, |s| s.mean),
            pct(peer_jitter, |s| s.p95),
        );
    }
}

/// The jitter of every run's landmarks over the clip (a 15-frame running mean) as a PNG plot.
fn write_plot(
    plot: &std::path::Path,
    runs: &[Run],
    peer: Option<&[Landmarks]>,
    steady: bool,
) -> anyhow::Result<()> {
    let running_mean = |v: Vec<Option<f64>>| -> Vec<(f64, f64)> {
        (0..v.len())
            .filter_map(|t| {
                let w: Vec<f64> = v[t.saturating_sub(7)..(t + 8).min(v.len())]
                    .iter()
                    .flatten()
                    .copied()
                    .collect();
                (!w.is_empty()).then(|| (t as f64, 100.0 * w.iter().sum::<f64>() / w.len() as f64))
            })
            .collect()
    };
    let mut series = Vec::new();
    for r in runs {
        series.push(crate::plot::Series {
            label: format!("{} raw", r.name),
            points: running_mean(jitter49(&r.raw)),
        });
        if steady {
            series.push(crate::plot::Series {
                label: format!("{} steadied", r.name),
                points: running_mean(jitter49(&r.steady)),
            });
        }
    }
    if let Some(p) = peer {
        series.push(crate::plot::Series {
            label: "dlib per frame".into(),
            points: running_mean(jitter49(p)),
        });
    }
    write_atomic(
        plot,
        crate::plot::series_plot_png(&series, "frame", "jitter49 (% eye distance)"),
    )
}

/// Runs `holoface stability`.
pub fn run(args: Args) -> anyhow::Result<()> {
    anyhow::ensure!(!args.aligners.is_empty(), "--aligners names none");
    let peer = args
        .peer
        .as_deref()
        .map(|p| -> anyhow::Result<Vec<Landmarks>> {
            let bytes = holoface_inference::files::read_bounded(p, 256 << 20, "peer landmarks")?;
            parse_peer(&String::from_utf8_lossy(&bytes)).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))
        })
        .transpose()?;
    let session_opts = SessionOptions {
        steady: args.steady.params(),
        ..SessionOptions::default()
    };
    let opts = args.runtime.tracker_options(&args.candide, session_opts);
    let mut server = None;
    let mut runs = Vec::new();
    for &a in &args.aligners {
        let aligner = match a {
            StabilityAligner::Krfws => AlignerChoice::Local,
            StabilityAligner::Remote => {
                let s = match server.take() {
                    Some(s) => s,
                    None => {
                        crate::loopback::LoopbackServer::start(&args.runtime, args.server_threads, |_| {})?
                    }
                };
                let mut remote = RemoteOptions::new(s.addr, s.fingerprint, s.token.clone());
                remote.client_name = "holoface-stability".into();
                remote.deadline = Duration::from_millis(args.deadline_ms);
                server = Some(s);
                AlignerChoice::Remote(remote)
            }
        };
        runs.push(Run {
            name: match a {
                StabilityAligner::Krfws => "krfws",
                StabilityAligner::Remote => "remote",
            },
            tracker: crate::args::tracker(TrackerOptions {
                aligner,
                ..opts.clone()
            })?,
            raw: Vec::new(),
            steady: Vec::new(),
            by: Vec::new(),
            detections: 0,
            shapes: Vec::new(),
        });
    }
    let mut source = open_source(&args.source, args.fps, None)?;
    // With a server in the loop the frames come at the video's own rate, as from a camera: its deadline and
    // the link's health are measured against the wall clock.
    let paced = args.aligners.contains(&StabilityAligner::Remote);
    let frames = track_clip(&mut runs, &mut *source, args.max_frames, paced)
        .with_context(|| args.source.display().to_string())?;
    anyhow::ensure!(frames > 0, "{} has no frames", args.source.display());
    if let Some(p) = &peer
        && p.len() != frames
    {
        eprintln!(
            "warning: the peer file has {} frames, the video {frames}; the common prefix is compared",
            p.len()
        );
    }
    let reports: Vec<Report> = runs.iter().map(|r| report(r, peer.as_deref())).collect();
    let peer_jitter = peer.as_deref().and_then(|p| summarise(&jitter49(p)));
    crate::say!("{}: {frames} frames", args.source.display());
    say_table(&reports, peer.as_deref(), peer_jitter);
    let doc = json!({
        "source": args.source.display().to_string(),
        "frames": frames,
        "steady": !args.steady.no_steady,
        "aligners": reports,
        "peer": peer.as_ref().map(|p| json!({
            "file": args.peer.as_ref().map(|f| f.display().to_string()),
            "faces_found": p.iter().filter(|l| l.is_some()).count(),
            "jitter49": peer_jitter,
        })),
    });
    write_atomic(&args.out, &serde_json::to_vec_pretty(&doc)?)?;
    crate::say!("wrote {}", args.out.display());
    if let Some(path) = &args.frames {
        write_atomic(path, frame_lines(&runs, frames))?;
        crate::say!("wrote {}", path.display());
    }
    if let Some(plot) = &args.plot {
        write_plot(plot, &runs, peer.as_deref(), !args.steady.no_steady)?;
        crate::say!("wrote {}", plot.display());
    }
    if let Some(s) = server {
        s.stop();
    }
    Ok(())
}
