//! `holoface stability`: how steady the landmarks are on real, unannotated video, per aligner, raw and
//! steadied, against a per-frame peer (dlib through `models/peer_video_dlib.py`). Measures in
//! [`crate::track_measures`].

use std::path::{Path, PathBuf};
use std::time::Duration;

use crate::cli::write_atomic;
use anyhow::Context;
use clap::{Args as ClapArgs, ValueEnum};
use holoface_process::stop::Stop;
use holoface_runtime::AdaptParams;
use holoface_runtime::adapt::AdaptOptions;
use holoface_runtime::align::AdaptState;
use holoface_runtime::{
    AlignerChoice, AnsweredBy, BlendshapeParams, Blendshapes, FaceTracker, InitSource, RemoteOptions,
    SessionOptions, TrackerOptions,
};
use holoface_sources::source::open_source;
use serde_json::json;

use crate::args::RuntimeArgs;
use crate::expressions::{RestRule, VideoReport, video_report};
use crate::link_cuts::CutRelay;
use crate::track_measures::{Landmarks, Summary, agreement, jitter49, jump, parse_peer, summarise};

mod measure;
use measure::*;

/// `NAME=FILE` of `--also-peer`.
fn parse_named_peer(s: &str) -> Result<(String, PathBuf), String> {
    let (name, file) = s
        .split_once('=')
        .filter(|(n, f)| !n.is_empty() && !f.is_empty())
        .ok_or_else(|| format!("{s:?}: expected NAME=FILE"))?;
    Ok((name.to_owned(), PathBuf::from(file)))
}

/// Reads a per-frame landmark file in the peer's format.
fn read_peer(p: &Path) -> anyhow::Result<Vec<Landmarks>> {
    let bytes = holoface_files::read_bounded(p, 256 << 20, "peer landmarks")?;
    parse_peer(&String::from_utf8_lossy(&bytes)).map_err(|e| anyhow::anyhow!("{}: {e}", p.display()))
}

/// Another per-frame tracker beside the peer: its jitter, its agreement with the peer and its time per frame
/// (as its own measurement recorded it).
#[derive(Debug, serde::Serialize)]
struct OtherPeer {
    name: String,
    file: String,
    faces_found: usize,
    jitter49: Option<Summary>,
    vs_peer_nme49: Option<Summary>,
    ms_per_frame: Option<serde_json::Value>,
}

fn other_peer(name: &str, file: &Path, peer: Option<&[Landmarks]>) -> anyhow::Result<OtherPeer> {
    let lm = read_peer(file)?;
    let mut side = file.as_os_str().to_owned();
    side.push(".json");
    let ms_per_frame = std::fs::read(&side)
        .ok()
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| v.get("ms_per_frame").cloned());
    Ok(OtherPeer {
        name: name.to_owned(),
        file: file.display().to_string(),
        faces_found: lm.iter().filter(|l| l.is_some()).count(),
        jitter49: summarise(&jitter49(&lm)),
        vs_peer_nme49: peer.and_then(|p| summarise(&agreement(&lm, p))),
        ms_per_frame,
    })
}

/// The aligners `stability` can run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum StabilityAligner {
    /// KRFWS on this device (what a headset shows without the link).
    Krfws,
    /// DAN and the refiner on an alignment server started in this process on loopback, KRFWS when it misses
    /// the deadline, adapted to the person while the link is up.
    Remote,
    /// `remote` with the local aligner's adaptation off: KRFWS's own answers when the server misses.
    RemoteNoAdapt,
    /// `remote` whose link is never cut (`--link-cuts` spares it): the steadied landmarks' jump at each of the
    /// other runs' switches, where this run did not switch, is what the head's own motion gives there.
    RemoteUncut,
}

impl StabilityAligner {
    fn name(self) -> &'static str {
        match self {
            Self::Krfws => "krfws",
            Self::Remote => "remote",
            Self::RemoteNoAdapt => "remote-no-adapt",
            Self::RemoteUncut => "remote-uncut",
        }
    }
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
    /// Another per-frame tracker to compare with the peer, `NAME=FILE` in the peer's format (MediaPipe Face
    /// Mesh mapped to 68 points: `models/peer_video_mediapipe.py`); its time per frame is read from
    /// `FILE.json` when there is one. Repeatable.
    #[arg(long, value_parser = parse_named_peer)]
    pub also_peer: Vec<(String, PathBuf)>,
    /// Aligners to measure, each in its own tracker over the same frames.
    #[arg(long, value_enum, value_delimiter = ',', default_value = "krfws,remote")]
    pub aligners: Vec<StabilityAligner>,
    /// The landmark filter.
    #[command(flatten)]
    pub steady: crate::args::SteadyArgs,
    /// Per-frame deadline for the server's answer, milliseconds (`remote`).
    #[arg(long, default_value_t = holoface_runtime::defaults::DEADLINE_MS)]
    pub deadline_ms: u64,
    /// Cut the link on a schedule in media time, `START:LENGTH[,...]` in seconds (`20:10,60:10`: at 20 s for
    /// 10 s and at 60 s for 10 s): the remote aligners' local answers during the cuts are reported apart.
    #[arg(long)]
    pub link_cuts: Option<crate::link_cuts::LinkCuts>,
    /// The adaptation's settings (`remote`).
    #[command(flatten)]
    pub adapt: AdaptArgs,
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

/// The settings of the local aligner's adaptation (`remote`), defaults as an app gets them.
#[derive(Debug, ClapArgs)]
pub struct AdaptArgs {
    /// The local aligner learns beside every this many remote answers of a face.
    #[arg(long, default_value_t = AdaptOptions::default().learn_every, value_parser = clap::value_parser!(u32).range(1..))]
    pub adapt_every: u32,
    /// A face's first this many remote answers each get a local run beside them, before `--adapt-every`.
    #[arg(long, default_value_t = AdaptOptions::default().warm_pairs)]
    pub adapt_warm: u32,
    /// The correction's memory in learnt pairs.
    #[arg(long, default_value_t = AdaptParams::default().memory_pairs)]
    pub adapt_memory: f64,
    /// Ridge on the correction's slopes (features' variance units); `inf`: the mean offset only.
    #[arg(long, default_value_t = AdaptParams::default().ridge)]
    pub adapt_ridge: f64,
    /// Ridge of each point's regression on what KRFWS sees there (its HOG, pooled), in units of those
    /// values' mean variance; `inf`: off.
    #[arg(long, default_value_t = AdaptParams::default().appearance_ridge)]
    pub adapt_appearance_ridge: f64,
    /// The longest shift of one point, eye distances.
    #[arg(long, default_value_t = AdaptParams::default().max_shift)]
    pub adapt_max_shift: f64,
}

impl AdaptArgs {
    fn options(&self) -> AdaptOptions {
        AdaptOptions {
            learn_every: self.adapt_every,
            warm_pairs: self.adapt_warm,
            params: AdaptParams {
                memory_pairs: self.adapt_memory,
                ridge: self.adapt_ridge,
                appearance_ridge: self.adapt_appearance_ridge,
                max_shift: self.adapt_max_shift,
                ..AdaptParams::default()
            },
        }
    }
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
    /// The local aligner's adaptation per frame.
    adapt: Vec<Option<AdaptState>>,
    /// The remote aligner's link after each frame.
    link: Vec<Option<holoface_runtime::LinkState>>,
    /// The tracker's time per frame (detection or motion-compensated start, the aligner, fit, expressions,
    /// filters), ms.
    ms: Vec<Option<f64>>,
    /// Each frame's time from the clip's first, seconds.
    times_s: Vec<f64>,
    /// A remote run's own server (each headset has its server to itself: two remote runs on one would
    /// delay each other's frames) and the relay that cuts its link.
    server: Option<(crate::loopback::LoopbackServer, Option<CutRelay>)>,
}

fn pct(s: Option<Summary>, f: impl Fn(&Summary) -> f64) -> String {
    s.map_or_else(|| "-".to_owned(), |s| format!("{:.2} %", 100.0 * f(&s)))
}

/// Tracks the clip's frames (at most `max_frames`) with every run's tracker, recording each run's raw and
/// steadied landmarks, who answered and the re-detections; `paced` replays at the clip's own rate; each
/// run's relay cuts its link on the schedule of `cuts`; a stop asked for ends the clip after the frame in hand.
/// Returns whether the link was cut, per frame.
fn track_clip(
    runs: &mut [Run],
    source: &mut dyn holoface_sources::FrameSource,
    (max_frames, stop): (usize, &Stop),
    paced: bool,
    cuts: Option<&crate::link_cuts::LinkCuts>,
) -> anyhow::Result<Vec<bool>> {
    let mut in_cut = Vec::new();
    let mut frames = 0usize;
    let mut pacer = paced.then(crate::link_cuts::Pacer::default);
    let mut first_us = None;
    while frames < max_frames && stop.requested().is_none() {
        let sf = match source.next_frame() {
            Ok(Some(sf)) => sf,
            Ok(None) => break,
            // A source cut by the same signal has ended.
            Err(_) if stop.requested().is_some() => break,
            Err(e) => return Err(e.into()),
        };
        if let Some(p) = pacer.as_mut() {
            p.wait(sf.timestamp_us);
        }
        let origin = *first_us.get_or_insert(sf.timestamp_us);
        in_cut.push(cuts.is_some_and(|c| c.contains(sf.timestamp_us.saturating_sub(origin) as f64 * 1e-6)));
        let frame = sf.view();
        for r in runs.iter_mut() {
            if let Some((_, Some(relay))) = &mut r.server {
                relay.at(sf.timestamp_us);
            }
            r.times_s
                .push(sf.timestamp_us.saturating_sub(origin) as f64 * 1e-6);
            let step = r
                .tracker
                .process_step(&frame)
                .with_context(|| format!("frame {} ({})", sf.index, r.name))?;
            let face = step.faces.faces.first().copied();
            r.raw.push(face.map(|u| u.raw_landmarks));
            r.steady.push(face.map(|u| u.landmarks));
            r.by.push(face.map(|u| u.answered_by));
            r.shapes.push(face.map(|u| u.blendshapes));
            r.adapt.push(face.and_then(|u| u.adaptation));
            r.link.push(r.tracker.link_status().map(|s| s.state()));
            let t = step.timings;
            r.ms.push(Some((t.prepare + t.align + t.complete).as_secs_f64() * 1e3));
            r.detections += usize::from(face.is_some_and(|u| u.init == InitSource::Detection));
        }
        frames += 1;
    }
    Ok(in_cut)
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
                let link = r.link.get(t).copied().flatten();
                let adaptation = r.adapt.get(t).copied().flatten();
                let points = |lm: Option<&Landmarks>| {
                    lm.copied()
                        .flatten()
                        .map(|p| p.iter().flat_map(|q| [q.x, q.y]).collect::<Vec<f32>>())
                };
                (
                    r.name.to_owned(),
                    json!({
                        "answered_by": by,
                        "link": link,
                        "adaptation": adaptation,
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

/// The share of the gap between KRFWS's own answers during the cuts (`remote-no-adapt`) and the remote answers
/// (`remote`) that the adapted local answers (`remote`, during the cuts) close, raw landmarks against the peer.
fn gap_closed(reports: &[Report]) -> Option<f64> {
    let cuts = |name: &str| reports.iter().find(|r| r.aligner == name)?.cuts.as_ref();
    let (adapted, plain) = (cuts("remote")?, cuts("remote-no-adapt")?);
    let krfws = plain.local_in_cuts_vs_peer_raw?.mean;
    let remote = adapted.remote_vs_peer_raw?.mean;
    let ours = adapted.local_in_cuts_vs_peer_raw?.mean;
    (krfws - remote > 1e-9).then(|| (krfws - ours) / (krfws - remote))
}

/// Prints run `r`'s switches between remote and local: how many and why, the largest jumps, each beside the
/// never-cut run's at that frame, and the excess over it against the bar (KRFWS's median steadied jitter49).
fn say_switches(r: &Report, reports: &[Report]) {
    if r.switches == 0 {
        return;
    }
    crate::say!(
        "         {} remote/local switches ({} at the link's changes, {} around missed deadlines; {} where the clip itself jumps, left out); largest jump raw {}, steadied {}",
        r.switches,
        r.switches - r.switches_at_missed_deadlines,
        r.switches_at_missed_deadlines,
        r.switches_at_clip_jumps,
        r.largest_switch_jump_raw
            .map_or("-".into(), |v| format!("{:.2} %", 100.0 * v)),
        r.largest_switch_jump_steadied
            .map_or("-".into(), |v| format!("{:.2} %", 100.0 * v)),
    );
    let beside: Vec<String> = r
        .switch_jumps
        .iter()
        .filter_map(|j| {
            let (ours, theirs) = (j.steadied?, j.uncut_steadied?);
            Some(format!(
                "{}: {:.2} / {:.2} %",
                j.frame,
                100.0 * ours,
                100.0 * theirs
            ))
        })
        .collect();
    if !beside.is_empty() {
        crate::say!(
            "         steadied jump at each switch / remote-uncut's at that frame: {}",
            beside.join(", ")
        );
    }
    if let (Some(worst), Some(median)) = (r.largest_switch_excess, r.median_switch_excess) {
        let bar = reports
            .iter()
            .find(|k| k.aligner == "krfws")
            .and_then(|k| k.steadied_jitter49)
            .map_or(String::new(), |j| {
                format!(
                    "; the bar, KRFWS's median steadied jitter49: {:.2} %",
                    100.0 * j.median
                )
            });
        crate::say!(
            "         excess over remote-uncut at a switch (its frame or the next): worst {:.2} %, median {:.2} %{bar}",
            100.0 * worst,
            100.0 * median
        );
    }
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
        say_switches(r, reports);
    }
    for r in reports {
        if let Some(c) = &r.cuts {
            crate::say!(
                "{:<8} link cut for {} frames: {} answered locally ({} corrected, {} pairs learnt before); vs peer raw {}, steadied {}; steadied jitter49 {}; remote answers vs peer raw {}, steadied {}",
                r.aligner,
                c.frames_in_cuts,
                c.local_in_cuts,
                c.corrected_in_cuts,
                c.pairs_at_first_cut.map_or("-".into(), |p| p.to_string()),
                pct(c.local_in_cuts_vs_peer_raw, |s| s.mean),
                pct(c.local_in_cuts_vs_peer_steadied, |s| s.mean),
                pct(c.local_in_cuts_jitter_steadied, |s| s.mean),
                pct(c.remote_vs_peer_raw, |s| s.mean),
                pct(c.remote_vs_peer_steadied, |s| s.mean),
            );
        }
    }
    for r in reports
        .iter()
        .filter(|r| r.aligner != "krfws" && r.remote_answers == 0)
    {
        // Its rows measure the local aligner, not the remote pipeline: said, not left to be read off the table.
        tracing::warn!(
            aligner = r.aligner,
            "no answer from its server came in time on any frame: its numbers are the local aligner's (a machine \
             too loaded for this many remote runs at once misses every deadline; run fewer --aligners)"
        );
    }
    if let Some(g) = gap_closed(reports) {
        crate::say!(
            "adaptation: during the cuts it closes {:.0} % of the gap between KRFWS alone and the remote answers (raw)",
            100.0 * g
        );
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
fn write_plot(plot: &Path, runs: &[Run], peer: Option<&[Landmarks]>, steady: bool) -> anyhow::Result<()> {
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
        series.push(holoface_harness::plot::Series {
            label: format!("{} raw", r.name),
            points: running_mean(jitter49(&r.raw)),
        });
        if steady {
            series.push(holoface_harness::plot::Series {
                label: format!("{} steadied", r.name),
                points: running_mean(jitter49(&r.steady)),
            });
        }
    }
    if let Some(p) = peer {
        series.push(holoface_harness::plot::Series {
            label: "dlib per frame".into(),
            points: running_mean(jitter49(p)),
        });
    }
    let png = holoface_harness::plot::series_plot_png(&series, "frame", "jitter49 (% eye distance)");
    Ok(write_atomic(plot, png)?)
}

/// One aligner's tracker (a remote one with its own in-process server, behind the relay that cuts the link
/// when cuts are asked for), nothing recorded yet.
fn start_run(a: StabilityAligner, args: &Args, opts: &TrackerOptions) -> anyhow::Result<Run> {
    let mut server = None;
    let aligner = match a {
        StabilityAligner::Remote | StabilityAligner::RemoteNoAdapt | StabilityAligner::RemoteUncut => {
            let s = crate::loopback::LoopbackServer::start(&args.runtime, args.server_threads, |_| {})?;
            let relay = args
                .link_cuts
                .as_ref()
                .filter(|_| a != StabilityAligner::RemoteUncut)
                .map(|c| CutRelay::start(s.addr, c.clone()))
                .transpose()?;
            let addr = relay.as_ref().map_or(s.addr, CutRelay::addr);
            let mut remote = RemoteOptions::new(addr, s.fingerprint, s.token.clone());
            remote.client_name = "holoface-stability".into();
            remote.deadline = Duration::from_millis(args.deadline_ms);
            remote.adapt = (a != StabilityAligner::RemoteNoAdapt).then(|| args.adapt.options());
            server = Some((s, relay));
            AlignerChoice::Remote(remote)
        }
        StabilityAligner::Krfws => AlignerChoice::Local,
    };
    Ok(Run {
        name: a.name(),
        tracker: crate::args::tracker(TrackerOptions {
            aligner,
            ..opts.clone()
        })?,
        raw: Vec::new(),
        steady: Vec::new(),
        by: Vec::new(),
        detections: 0,
        shapes: Vec::new(),
        adapt: Vec::new(),
        link: Vec::new(),
        ms: Vec::new(),
        times_s: Vec::new(),
        server,
    })
}

/// Prints the other per-frame peers' lines and each tracker's time per frame.
fn say_others(reports: &[Report], others: &[OtherPeer]) {
    for o in others {
        crate::say!(
            "{:<8} {:>7} {:>6} {:>9} {:>14} (per frame; vs peer {}; {} ms per frame, its own measurement)",
            o.name,
            o.faces_found,
            "-",
            "-",
            pct(o.jitter49, |s| s.mean),
            pct(o.vs_peer_nme49, |s| s.mean),
            o.ms_per_frame
                .as_ref()
                .and_then(|v| v.get("mean"))
                .and_then(serde_json::Value::as_f64)
                .map_or("-".into(), |v| format!("{v:.2}")),
        );
    }
    for r in reports {
        if let Some(ms) = r.ms_per_frame {
            crate::say!(
                "{:<8} time per frame on this thread: mean {:.2} ms, p95 {:.2} ms",
                r.aligner,
                ms.mean,
                ms.p95
            );
        }
    }
}

/// Runs `holoface stability`.
pub fn run(args: Args, stop: &Stop) -> anyhow::Result<()> {
    anyhow::ensure!(!args.aligners.is_empty(), "--aligners names none");
    if args.source == Path::new("-") {
        // A live source (a camera on standard input) has no end: a first Ctrl-C ends it after the frame in hand
        // and the frames so far are measured.
        stop.stop_gracefully();
    }
    let peer = args.peer.as_deref().map(read_peer).transpose()?;
    let session_opts = SessionOptions {
        steady: args.steady.settings(),
        ..SessionOptions::default()
    };
    let opts = args.runtime.tracker_options(&args.candide, session_opts);
    let remote_runs = args.aligners.iter().any(|a| *a != StabilityAligner::Krfws);
    let runs: anyhow::Result<Vec<Run>> = args
        .aligners
        .iter()
        .map(|&a| start_run(a, &args, &opts))
        .collect();
    let mut runs = runs?;
    let mut source = open_source(&args.source, args.fps, None)?;
    // With a server in the loop the frames come at the video's own rate, as from a camera: its deadline and
    // the link's health are measured against the wall clock.
    let in_cut = track_clip(
        &mut runs,
        &mut *source,
        (args.max_frames, stop),
        remote_runs,
        args.link_cuts.as_ref(),
    )
    .with_context(|| args.source.display().to_string())?;
    let frames = in_cut.len();
    anyhow::ensure!(frames > 0, "{} has no frames", args.source.display());
    if let Some(p) = &peer
        && p.len() != frames
    {
        tracing::warn!(
            "the peer file has {} frames, the video {frames}; the common prefix is compared",
            p.len()
        );
    }
    let cut_mask = args.link_cuts.is_some().then_some(&in_cut[..]);
    let reports: Vec<Report> = runs
        .iter()
        .map(|r| {
            let uncut = runs
                .iter()
                .find(|u| u.name == StabilityAligner::RemoteUncut.name());
            report(r, peer.as_deref(), cut_mask, uncut)
        })
        .collect();
    let peer_jitter = peer.as_deref().and_then(|p| summarise(&jitter49(p)));
    let others = args
        .also_peer
        .iter()
        .map(|(n, f)| other_peer(n, f, peer.as_deref()))
        .collect::<anyhow::Result<Vec<_>>>()?;
    crate::say!(
        "{}: {frames} frames{}",
        args.source.display(),
        if remote_runs {
            ", fed at their timestamps as a camera's come (a server is in the loop: the link and its deadlines \
             run on the wall clock)"
        } else {
            ", as fast as they decode"
        }
    );
    say_table(&reports, peer.as_deref(), peer_jitter);
    say_others(&reports, &others);
    let doc = json!({
        "source": args.source.display().to_string(),
        "frames": frames,
        "steady": !args.steady.no_steady,
        "link_cuts": args.link_cuts.as_ref().map(|c| c.windows().to_vec()),
        "paced": remote_runs,
        "aligners": reports,
        "other_peers": others,
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
    for r in runs {
        if let Some((s, relay)) = r.server {
            drop(relay);
            s.stop();
        }
    }
    if let Some(sig) = stop.requested() {
        eprintln!(
            "stopped by {} after {frames} frames; the report covers them",
            sig.name()
        );
        std::process::exit(sig.exit_code());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_switch_is_set_beside_the_uncut_runs_motion_unless_that_run_switched_too() {
        use holoface_models::geometry::Point2;
        // Points moving at a constant speed, then 2 px further from frame 3 on; eyes 90 px apart.
        let track = |step_at: usize| -> Vec<Landmarks> {
            (0..6)
                .map(|t| {
                    let x = t as f32 + if t >= step_at { 2.0 } else { 0.0 };
                    let mut p = [Point2::new(x, 0.0); 68];
                    p[36].x -= 45.0;
                    p[45].x += 45.0;
                    Some(p)
                })
                .collect()
        };
        let (ours, theirs) = (track(3), track(99));
        let remote = Some(AnsweredBy::RemoteDan);
        let local = Some(AnsweredBy::Krfws);
        let steady_by = vec![remote; 6];
        let jumps = switch_jumps(&[3], &ours, Some((&steady_by, &theirs)));
        assert!((jumps[0].steadied.unwrap() - 2.0 / 90.0).abs() < 1e-4);
        assert!(
            jumps[0].uncut_steadied.unwrap() < 1e-6,
            "the uncut run moved evenly"
        );
        // The excess: the step shows at the switch and again (the other way) on the next frame; the uncut run
        // moved evenly on both, so all of it is the switch's.
        assert!((jumps[0].excess.unwrap() - 2.0 / 90.0).abs() < 1e-4);
        // Where the switching run is the smoother one, the excess is negative.
        let smoother = switch_jumps(&[3], &theirs, Some((&steady_by, &ours)));
        assert!((smoother[0].excess.unwrap() + 2.0 / 90.0).abs() < 1e-4);
        // Where the uncut run switched too, its jump says nothing about the head: left out.
        let mut switching = steady_by.clone();
        switching[3] = local;
        assert_eq!(
            switch_jumps(&[3], &ours, Some((&switching, &theirs)))[0].uncut_steadied,
            None
        );
        assert_eq!(switch_jumps(&[3], &ours, None)[0].uncut_steadied, None);
        assert_eq!(switch_jumps(&[3], &ours, None)[0].excess, None);
        assert_eq!(
            switch_jumps(&[1], &ours, None)[0].steadied,
            None,
            "no two frames before"
        );
    }

    #[test]
    fn switches_around_a_missed_deadline_are_told_from_the_links_changes() {
        let (r, l) = (Some(AnsweredBy::RemoteDan), Some(AnsweredBy::Krfws));
        // Local until the link is up (frame 2), one missed deadline (4), a cut over 7..9 whose return comes
        // after it (11), a two-frame miss (13, 14), no face (16), a miss at the very end (18, never returns).
        let by = [l, l, r, r, l, r, r, l, l, l, l, r, r, l, l, r, None, r, l];
        let mut in_cut = [false; 19];
        in_cut[7..9].fill(true);
        let all = (1..by.len()).filter(|&t| switched(&by, t)).count();
        assert_eq!(all, 8);
        assert_eq!(missed_deadline_switches(&by, Some(&in_cut)), 4);
        // Without cuts, the run from 7 to 10 is an interlude too.
        assert_eq!(missed_deadline_switches(&by, None), 6);
    }

    #[test]
    fn other_peers_are_named() {
        assert_eq!(
            parse_named_peer("mediapipe=runs/a.tsv").unwrap(),
            ("mediapipe".to_owned(), PathBuf::from("runs/a.tsv"))
        );
        for bad in ["mediapipe", "=a.tsv", "mediapipe="] {
            assert!(parse_named_peer(bad).unwrap_err().contains("NAME=FILE"), "{bad}");
        }
    }
}
