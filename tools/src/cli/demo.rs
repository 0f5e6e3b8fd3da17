//! `holoface demo`: the alignment server and the headset client on loopback, over the bundled sample.
//!
//! The sample photograph hangs as a flat picture 60 cm in front of a headset that moves (known
//! camera-to-world poses), so every frame is a known homography of the photo. The client tracks the face
//! with remote DAN over QUIC (through a fault-injecting relay) and local KRFWS as fallback; part-way the
//! relay cuts the link, later restores it. Reference landmarks: DAN run in-process on the still photo,
//! moved into each frame by its homography (so "error" means drift from that reference, not from a human
//! annotation). Prints a summary table, writes one JSON line per frame, a PNG strip of annotated frames and
//! one of augmented frames (the shipped scene's glasses and hat, drawn where a headset would show them), and
//! says how still the anchored glasses stayed in the world while each aligner answered.

use crate::cli::write_atomic;
use holoface_sources::output::Output;
use std::io::Write;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use crate::render::SCENE_CAMERA;
use crate::stats::percentile;
use anyhow::{Context, bail};
use clap::Args as ClapArgs;
use holoface_models::accuracy::{nme49, nme68};
use holoface_models::geometry::Point2;
use holoface_models::image::GrayImage;
use holoface_models::math3::{Mat3, Pose, Vec3};
use holoface_models::shape::dan_mean_shape;
use serde_json::json;

use crate::args::RuntimeArgs;
use crate::render::PlanarScene;
use holoface_harness::plot::Canvas;
use holoface_harness::relay::UdpRelay;
use holoface_runtime::align::{Aligner, AnsweredBy};
use holoface_runtime::assets::home;
use holoface_runtime::detect::{FaceDetector, shape_from_detection};
use holoface_runtime::frame::Frame;
use holoface_runtime::link::{CropCodec, RemoteOptions};
use holoface_runtime::{FaceOutcome, SessionOptions};

/// Arguments of `holoface demo`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// The sample photograph (`holoface setup` extracts NASA's public-domain astronaut photo from the pinned
    /// scikit-image wheel into the data folder).
    #[arg(long, env = home::SAMPLE.env, default_value_os_t = home::SAMPLE.default_path())]
    pub sample: PathBuf,
    /// Frames to run.
    #[arg(long, default_value_t = 360)]
    pub frames: usize,
    /// Camera frame rate (frames are paced in real time).
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
    /// First frame of the link cut.
    #[arg(long, default_value_t = 100)]
    pub cut_at: usize,
    /// Length of the link cut in frames (longer than the 3 s QUIC idle timeout shows a reconnect).
    #[arg(long, default_value_t = 120)]
    pub cut_frames: usize,
    /// Per-frame deadline for the server's answer, milliseconds (one frame interval at 30 fps).
    #[arg(long, default_value_t = holoface_runtime::defaults::DEADLINE_MS)]
    pub deadline_ms: u64,
    /// Crop encoding on the wire (`raw`, `png`, `jpeg`, `jpeg:Q`).
    #[arg(long, default_value = holoface_runtime::defaults::CROP_ENCODING)]
    pub crop_encoding: CropCodec,
    /// ONNX Runtime threads of the in-process server.
    #[arg(long, default_value_t = 1)]
    pub server_threads: usize,
    /// CANDIDE-3 model.
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
    /// Output folder (frames.jsonl, strip.png, summary.json).
    #[arg(long, default_value = "runs/demo")]
    pub out: PathBuf,
    /// Runtime assets.
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

const FRAME_W: usize = 640;
const FRAME_H: usize = 480;
const PHOTO_DISTANCE_M: f64 = 0.6;

/// The photo hangs 60 cm in front of the headset's starting position.
fn photo_pose() -> Pose {
    Pose {
        rotation: Mat3::IDENTITY,
        translation: Vec3::new(0.0, 0.0, PHOTO_DISTANCE_M),
    }
}

/// Headset camera-to-world pose at time `t` (seconds): smooth head-like motion of a few degrees and
/// centimetres (OpenCV axes: x right, y down, z forward).
fn headset(t: f64) -> Pose {
    let tau = std::f64::consts::TAU;
    let yaw = 8f64.to_radians() * (tau * t / 4.0).sin();
    let pitch = 5f64.to_radians() * (tau * t / 3.0 + 1.0).sin();
    let roll = 4f64.to_radians() * (tau * t / 5.0).sin();
    Pose {
        rotation: Mat3::rot_y(yaw) * Mat3::rot_x(pitch) * Mat3::rot_z(roll),
        translation: Vec3::new(
            0.06 * (tau * t / 6.0).sin(),
            0.04 * (tau * t / 4.5 + 0.5).sin(),
            0.08 * (tau * t / 7.0).sin(),
        ),
    }
}

/// Reference landmarks on the still: detection, then DAN three times, each from the previous answer.
fn reference_landmarks(args: &Args, photo: &GrayImage) -> anyhow::Result<[Point2; 68]> {
    let mut detector = args.runtime.detector()?;
    let found = detector.detect(&photo.view())?;
    let det = found
        .first()
        .with_context(|| format!("no face detected in the sample {}", args.sample.display()))?;
    let mut shape = [Point2::default(); 68];
    if !shape_from_detection(&dan_mean_shape(), det, &mut shape) {
        bail!("the detection in {} is degenerate", args.sample.display());
    }
    let mut dan = args.runtime.dan_aligner()?;
    for _ in 0..3 {
        let a = dan.align(&photo.view(), &shape)?;
        if !a.accepted {
            bail!("DAN does not accept the face in {}", args.sample.display());
        }
        shape = a.landmarks;
    }
    Ok(shape)
}

fn load_scene(args: &Args) -> anyhow::Result<PlanarScene> {
    if !args.sample.exists() {
        bail!(
            "{}",
            home::SAMPLE
                .missing(&args.sample)
                .given_by(&[(home::SAMPLE, "--sample")])
        );
    }
    let photo = holoface_sources::images::read_gray(&args.sample)
        .with_context(|| format!("reading the sample {}", args.sample.display()))?;
    let reference = reference_landmarks(args, &photo)?;
    PlanarScene::life_size(photo, reference)
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
enum Phase {
    BeforeCut,
    LinkCut,
    AfterRestore,
}

struct Record {
    phase: Phase,
    answered_by: Option<AnsweredBy>,
    latency_ms: f64,
    nme49: Option<f64>,
    sent_bytes: usize,
}

/// Each blendshape coefficient's mean over the frames with a face, as JSON, and a line naming the five
/// strongest.
fn mean_blendshapes(frames: &[holoface_runtime::Blendshapes]) -> (serde_json::Value, String) {
    let n = frames.len().max(1) as f64;
    let mut mean: Vec<(&'static str, f64)> = holoface_runtime::Blendshape::ALL
        .iter()
        .enumerate()
        .map(|(k, b)| {
            let sum: f64 = frames.iter().map(|f| f64::from(f.0[k])).sum();
            (b.arkit_name(), sum / n)
        })
        .collect();
    let json = mean
        .iter()
        .map(|&(name, v)| (name.to_owned(), json!(v)))
        .collect::<serde_json::Map<_, _>>()
        .into();
    mean.sort_by(|a, b| b.1.total_cmp(&a.1));
    let top: Vec<String> = mean
        .iter()
        .take(5)
        .map(|(name, v)| format!("{name} {v:.2}"))
        .collect();
    (
        json,
        format!(
            "expression (ARKit blendshapes, mean over the frames with a face): {}",
            top.join(", ")
        ),
    )
}

/// Runs `holoface demo`.
pub fn run(args: Args) -> anyhow::Result<()> {
    if args.frames == 0 || args.fps <= 0.0 {
        bail!("--frames and --fps must be positive");
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    crate::say!(
        "preparing: reference landmarks on the still {}",
        args.sample.display()
    );
    let scene = load_scene(&args)?;
    let (server, relay, mut tracker) = start_link(&args)?;

    let log_path = args.out.join("frames.jsonl");
    let mut log = Output::create(&log_path, crate::cli::temporaries())?;
    let interval = Duration::from_secs_f64(1.0 / args.fps);
    let cut_end = args.cut_at + args.cut_frames;
    let strip_at = strip_frames(args.frames, args.cut_at, cut_end);
    let mut strip = Vec::new();
    let mut augmented = DemoAugment::new(tracker.face_model(), strip_at.clone())?;
    let mut records = Vec::with_capacity(args.frames);
    let mut expressions = Vec::with_capacity(args.frames);
    let mut image = GrayImage::zeros(FRAME_W, FRAME_H);
    let mut healthy_wire = None;
    let start = Instant::now();
    for i in 0..args.frames {
        let t = i as f64 / args.fps;
        let pose = headset(t);
        let h = scene.homography(&SCENE_CAMERA, &pose, &photo_pose());
        scene.render(&h, &mut image, 40)?;
        let truth = scene.landmarks_in(&h);
        if i == args.cut_at {
            // Wire cost while the link is healthy (during the cut, lost packets inflate it).
            healthy_wire = Some(wire(tracker.aligner()));
            relay.faults().set_cut(true);
        } else if i == cut_end {
            relay.faults().set_cut(false);
        }
        if let Some(wait) = (start + interval * i as u32).checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        let phase = match i {
            _ if i < args.cut_at => Phase::BeforeCut,
            _ if i < cut_end => Phase::LinkCut,
            _ => Phase::AfterRestore,
        };
        let frame = Frame {
            timestamp_us: (t * 1e6) as u64,
            image: image.view(),
            intrinsics: SCENE_CAMERA,
            world_from_camera: pose,
        };
        let t0 = Instant::now();
        let step = tracker.process_step(&frame)?;
        let (result, alignment) = (step.faces.first(), step.first_alignment());
        let latency_ms = t0.elapsed().as_secs_f64() * 1e3;
        let aligner = tracker.aligner();
        let report = aligner.last_report();
        let (answered_by, landmarks) = match (&result, alignment) {
            (_, Some(a)) => (Some(a.answered_by), Some(a.landmarks)),
            _ => (None, None),
        };
        let n49 = landmarks.and_then(|l| nme49(&l, &truth));
        let n68 = match answered_by {
            Some(AnsweredBy::RemoteDan) => landmarks.and_then(|l| nme68(&l, &truth)),
            _ => None,
        };
        records.push(Record {
            phase,
            answered_by,
            latency_ms,
            nme49: n49,
            sent_bytes: report.sent_bytes,
        });
        let mut line = json!({
            "frame": i,
            "t_s": t,
            "phase": phase,
            "answered_by": answered_by,
            "mode": report.mode,
            "fell_back": report.fell_back,
            "remote_rtt_ms": report.remote_rtt_us.map(|u| u as f64 / 1e3),
            "latency_ms": latency_ms,
            "sent_bytes": report.sent_bytes,
            "nme49_vs_reference": n49,
            "nme68_vs_reference": n68,
        });
        add_face(&mut line, &result);
        if let FaceOutcome::Face(u) = &result {
            expressions.push(u.blendshapes);
        }
        augmented.frame(
            (i, frame.timestamp_us),
            (&image, &pose),
            answered_by,
            &step.faces.faces,
        );
        serde_json::to_writer(&mut log, &line)?;
        log.write_all(b"\n")?;
        if strip_at.contains(&i) {
            strip.push((i, image.clone(), landmarks, answered_by, truth));
        }
    }
    let wall = start.elapsed().as_secs_f64();
    log.commit()?;
    let (udp_tx, remote_sent) = healthy_wire.unwrap_or_else(|| wire(tracker.aligner()));
    let switches = tracker.aligner().policy().switches();
    drop(tracker);
    drop(relay);
    server.stop();
    let mut summary = summarise(&args, &records, wall, udp_tx, remote_sent, switches);
    summary["anchored_glasses"] = augmented.finish(&args.out.join("augmented.png"))?;
    write_outputs(&args, &strip, summary, &expressions, &log_path)?;
    let unanswered = records.iter().filter(|r| r.answered_by.is_none()).count();
    if unanswered == records.len() {
        bail!("no frame was aligned: the tracker never found the face");
    }
    Ok(())
}

/// The link's UDP bytes sent and the frames sent to the server so far.
fn wire(
    aligner: &holoface_runtime::link::LinkedAligner<holoface_runtime::align::KrfwsAligner>,
) -> (u64, u64) {
    let sent = aligner
        .link()
        .counters()
        .frames_sent
        .load(std::sync::atomic::Ordering::Relaxed);
    (aligner.link().udp_bytes().0, sent)
}

/// The strip and the summary (with the mean blendshapes) beside the frame log.
fn write_outputs(
    args: &Args,
    strip: &[StripFrame],
    mut summary: serde_json::Value,
    expressions: &[holoface_runtime::Blendshapes],
    log_path: &std::path::Path,
) -> anyhow::Result<()> {
    let expression = mean_blendshapes(expressions);
    let strip_path = args.out.join("strip.png");
    write_atomic(&strip_path, strip_png(strip))?;
    crate::say!("{}", expression.1);
    summary["blendshapes_mean"] = expression.0;
    let summary_path = args.out.join("summary.json");
    write_atomic(&summary_path, serde_json::to_string_pretty(&summary)?.as_bytes())?;
    crate::say!(
        "wrote {}, {}, {} and {}",
        log_path.display(),
        strip_path.display(),
        args.out.join("augmented.png").display(),
        summary_path.display()
    );
    Ok(())
}

/// The demo's tracker as a headset runs it: the alignment server in-process on loopback, behind a relay that
/// can cut the link, KRFWS behind the link.
fn start_link(
    args: &Args,
) -> anyhow::Result<(
    crate::loopback::LoopbackServer,
    UdpRelay,
    holoface_runtime::FaceTracker<
        holoface_runtime::link::LinkedAligner<holoface_runtime::align::KrfwsAligner>,
    >,
)> {
    let server = crate::loopback::LoopbackServer::start(&args.runtime, args.server_threads, |_| {})?;
    let (server_addr, fingerprint, token) = (server.addr, server.fingerprint, server.token.clone());
    let relay = server.runtime().block_on(UdpRelay::start(server_addr))?;
    crate::say!(
        "server on {server_addr} (certificate {fingerprint}), client via relay {}",
        relay.addr()
    );
    let mut remote = RemoteOptions::new(relay.addr(), fingerprint, token);
    remote.client_name = "holoface-demo".into();
    remote.deadline = Duration::from_millis(args.deadline_ms);
    remote.codec = args.crop_encoding;
    let linked = holoface_runtime::link::LinkedAligner::start(&remote, args.runtime.krfws_aligner()?, 1)?;
    let watch = linked.link().watch();
    let opts = args
        .runtime
        .tracker_options(&args.candide, SessionOptions::default());
    let tracker = crate::args::tracker_with(&opts, Box::new(linked), Some(watch))?;
    Ok((server, relay, tracker))
}

/// A frame line's face: poses, weights, attributes and blendshapes, or why there is none.
fn add_face(line: &mut serde_json::Value, result: &FaceOutcome) {
    match result {
        FaceOutcome::Face(u) => {
            line["face"] = json!(true);
            line["world_position_m"] = json!(u.world.position.to_array());
            line["display_position_m"] = json!(u.display.0.to_array());
            line["weights"] = json!(u.expression.0);
            line["attributes"] = json!({
                "smile": u.attributes.smile,
                "brows_raised": u.attributes.brows_raised,
                "mouth_open": u.attributes.mouth_open,
            });
            line["blendshapes"] = u
                .blendshapes
                .iter()
                .map(|(b, v)| (b.arkit_name().to_owned(), json!(v)))
                .collect::<serde_json::Map<_, _>>()
                .into();
        }
        FaceOutcome::NoFace(reason) => {
            line["face"] = json!(false);
            line["reason"] = json!(reason);
        }
    }
}

/// Frames shown in the strip: before the cut, just after it, mid-cut, after the restore, late, last.
fn strip_frames(n: usize, cut_at: usize, cut_end: usize) -> Vec<usize> {
    let mut v = vec![
        cut_at.saturating_sub(10),
        cut_at + 2,
        (cut_at + cut_end) / 2,
        cut_end + 5,
        (cut_end + n) / 2,
        n - 1,
    ];
    v.retain(|&f| f < n);
    v.dedup();
    v
}

type StripFrame = (
    usize,
    GrayImage,
    Option<[Point2; 68]>,
    Option<AnsweredBy>,
    [Point2; 68],
);

fn strip_png(frames: &[StripFrame]) -> Vec<u8> {
    let (tw, th, band) = (FRAME_W / 2, FRAME_H / 2, 20);
    let cols = 3;
    let rows = frames.len().div_ceil(cols).max(1);
    let mut cv = Canvas::new(cols * tw, rows * (th + band));
    for (k, (i, img, landmarks, by, truth)) in frames.iter().enumerate() {
        let (x0, y0) = ((k % cols * tw) as i64, (k / cols * (th + band)) as i64);
        cv.blit_gray(x0, y0 + band as i64, img.as_bytes(), FRAME_W, FRAME_H, 2);
        let (colour, label) = crate::annotate::aligner_style(*by);
        cv.text(x0 + 4, y0 + 3, &format!("frame {i} {label}"), colour);
        for p in truth {
            cv.dot(
                x0 as f64 + f64::from(p.x) / 2.0,
                y0 as f64 + band as f64 + f64::from(p.y) / 2.0,
                0,
                [31, 119, 180],
            );
        }
        for p in landmarks.iter().flatten() {
            cv.dot(
                x0 as f64 + f64::from(p.x) / 2.0,
                y0 as f64 + band as f64 + f64::from(p.y) / 2.0,
                1,
                colour,
            );
        }
    }
    cv.to_png()
}

/// The shipped scene on the demo: its augmenter, the frames of the strip drawn with it, and the glasses in the
/// world frame by frame for each aligner (`None` on the other's frames): the face is a picture hanging still, so
/// every movement of theirs is the tracker's.
struct DemoAugment {
    augmenter: crate::augment::Augmenter,
    /// The frames drawn (the strip's).
    shown: Vec<usize>,
    frames: Vec<(usize, Canvas, Option<AnsweredBy>)>,
    remote: Vec<Option<Vec3>>,
    local: Vec<Option<Vec3>>,
}

impl DemoAugment {
    fn new(model: &holoface_models::candide::FaceModel, shown: Vec<usize>) -> anyhow::Result<Self> {
        Ok(Self {
            shown,
            augmenter: crate::augment::Augmenter::new(
                crate::augment::scene::Scene::parse(crate::augment::scene::DEFAULT_SCENE)?,
                model.clone(),
                SessionOptions::default().lookahead_s * 1e3,
            ),
            frames: Vec::new(),
            remote: Vec::new(),
            local: Vec::new(),
        })
    }

    /// Frame `i` captured at `t_us` (`image`, the headset at `pose`), answered by `by` with `faces`; drawn and
    /// kept when it is one of the strip's.
    fn frame(
        &mut self,
        (i, t_us): (usize, u64),
        (image, pose): (&GrayImage, &Pose),
        by: Option<AnsweredBy>,
        faces: &[holoface_runtime::FaceResult],
    ) {
        let snapshots: Vec<_> = faces.iter().map(crate::augment::FaceSnapshot::of).collect();
        let at = snapshots.first().map(|f| self.augmenter.place(0, f).translation);
        let remote = by == Some(AnsweredBy::RemoteDan);
        self.remote.push(at.filter(|_| remote));
        self.local.push(at.filter(|_| !remote));
        self.augmenter.update(t_us, snapshots);
        if self.shown.contains(&i) {
            let mut canvas = Canvas::new(FRAME_W, FRAME_H);
            canvas.blit_gray(0, 0, image.as_bytes(), FRAME_W, FRAME_H, 1);
            self.augmenter.draw(&mut canvas, &SCENE_CAMERA, pose);
            self.frames.push((i, canvas, by));
        }
    }

    /// Writes the strip to `path`; says and returns the glasses' drift for each aligner.
    fn finish(self, path: &std::path::Path) -> anyhow::Result<serde_json::Value> {
        write_atomic(path, augmented_png(&self.frames))?;
        Ok(self.report())
    }

    /// Says and returns the drift for each aligner.
    fn report(&self) -> serde_json::Value {
        let mut out = serde_json::Map::new();
        for (name, track) in [("remote", &self.remote), ("local", &self.local)] {
            let Some(d) = crate::augment::drift(track) else {
                continue;
            };
            crate::say!(
                "anchored glasses, {name}: {} frames, std {:.1} / {:.1} / {:.1} mm (x/y/z), frame to frame median \
                 {:.2} mm, p95 {:.2} mm",
                d.frames,
                d.std_mm[0],
                d.std_mm[1],
                d.std_mm[2],
                d.step_median_mm,
                d.step_p95_mm
            );
            out.insert(name.into(), json!(d));
        }
        out.into()
    }
}

/// The augmented frames, three to a row at half size, each labelled with its frame and aligner.
fn augmented_png(frames: &[(usize, Canvas, Option<AnsweredBy>)]) -> Vec<u8> {
    let (tw, th, band) = (FRAME_W / 2, FRAME_H / 2, 20);
    let cols = 3;
    let rows = frames.len().div_ceil(cols).max(1);
    let mut cv = Canvas::new(cols * tw, rows * (th + band));
    for (k, (i, frame, by)) in frames.iter().enumerate() {
        let (x0, y0) = ((k % cols * tw) as i64, (k / cols * (th + band)) as i64);
        let px = frame.rgb();
        for y in 0..th {
            for x in 0..tw {
                // The mean of each 2 x 2 block.
                let c = [0, 1, 2].map(|ch| {
                    let at =
                        |dx: usize, dy: usize| u16::from(px[((2 * y + dy) * FRAME_W + 2 * x + dx) * 3 + ch]);
                    ((at(0, 0) + at(1, 0) + at(0, 1) + at(1, 1) + 2) / 4) as u8
                });
                cv.set(x0 + x as i64, y0 + band as i64 + y as i64, c);
            }
        }
        let (colour, label) = crate::annotate::aligner_style(*by);
        cv.text(x0 + 4, y0 + 3, &format!("frame {i} {label}"), colour);
    }
    cv.to_png()
}

fn summarise(
    args: &Args,
    records: &[Record],
    wall_s: f64,
    udp_tx: u64,
    remote_sent: u64,
    switches: u32,
) -> serde_json::Value {
    crate::say!();
    crate::say!(
        "HoloFace demo: {} frames at {} fps, DAN on a loopback QUIC server (crops {}), KRFWS fallback; link cut for frames {}..{}",
        records.len(),
        args.fps,
        args.crop_encoding,
        args.cut_at,
        args.cut_at + args.cut_frames
    );
    crate::say!(
        "{:<14} {:>6} {:>7} {:>6} {:>8} {:>7} {:>7} {:>7} {:>12}",
        "phase",
        "frames",
        "remote",
        "local",
        "no face",
        "p50 ms",
        "p99 ms",
        "max ms",
        "NME49 vs ref"
    );
    let mut phases = Vec::new();
    let groups: [(&str, Option<Phase>); 4] = [
        ("before cut", Some(Phase::BeforeCut)),
        ("link cut", Some(Phase::LinkCut)),
        ("after restore", Some(Phase::AfterRestore)),
        ("all", None),
    ];
    for (name, phase) in groups {
        let sel: Vec<&Record> = records
            .iter()
            .filter(|r| phase.is_none_or(|p| r.phase == p))
            .collect();
        if sel.is_empty() {
            continue;
        }
        let remote = sel
            .iter()
            .filter(|r| r.answered_by == Some(AnsweredBy::RemoteDan))
            .count();
        let local = sel
            .iter()
            .filter(|r| r.answered_by == Some(AnsweredBy::Krfws))
            .count();
        let none = sel.iter().filter(|r| r.answered_by.is_none()).count();
        let lat: Vec<f64> = sel.iter().map(|r| r.latency_ms).collect();
        let (p50, p99, max) = (
            percentile(&lat, 0.5),
            percentile(&lat, 0.99),
            percentile(&lat, 1.0),
        );
        let errs: Vec<f64> = sel.iter().filter_map(|r| r.nme49).collect();
        let nme = errs.iter().sum::<f64>() / errs.len().max(1) as f64;
        crate::say!(
            "{name:<14} {:>6} {:>7} {:>6} {:>8} {p50:>7.1} {p99:>7.1} {max:>7.1} {:>11.2}%",
            sel.len(),
            remote,
            local,
            none,
            100.0 * nme
        );
        phases.push(json!({
            "phase": name, "frames": sel.len(), "remote": remote, "local": local, "no_face": none,
            "latency_ms": {"p50": p50, "p99": p99, "max": max}, "nme49_vs_reference": nme,
        }));
    }
    let sent: Vec<usize> = records.iter().map(|r| r.sent_bytes).filter(|&b| b > 0).collect();
    let payload = sent.iter().sum::<usize>() as f64 / sent.len().max(1) as f64;
    let udp_per_frame = udp_tx as f64 / remote_sent.max(1) as f64;
    let first_local = records
        .iter()
        .position(|r| r.phase == Phase::LinkCut && r.answered_by == Some(AnsweredBy::Krfws));
    let back = records
        .iter()
        .position(|r| r.phase == Phase::AfterRestore && r.answered_by == Some(AnsweredBy::RemoteDan));
    let cut_end = args.cut_at + args.cut_frames;
    crate::say!(
        "wire: {payload:.0} B per crop message; before the cut {udp_per_frame:.0} UDP B per frame sent incl. QUIC, TLS and handshake ({remote_sent} frames); \
         {:.1} fps achieved; {switches} switches remote<->local",
        records.len() as f64 / wall_s
    );
    match (first_local, back) {
        (Some(f), Some(b)) => crate::say!(
            "fallback: local answers from frame {f} ({} after the cut); back to remote at frame {b} ({:.2} s after the restore)",
            f - args.cut_at,
            (b - cut_end) as f64 / args.fps
        ),
        _ => crate::say!("fallback: first local frame {first_local:?}, back to remote at {back:?}"),
    }
    json!({
        "frames": records.len(), "fps": args.fps, "achieved_fps": records.len() as f64 / wall_s,
        "crop_encoding": args.crop_encoding.to_string(), "deadline_ms": args.deadline_ms,
        "cut": {"from": args.cut_at, "to": cut_end},
        "phases": phases,
        "payload_bytes_per_crop": payload, "udp_tx_bytes_per_sent_frame": udp_per_frame,
        "switches": switches, "first_local_frame": first_local, "back_to_remote_frame": back,
    })
}
