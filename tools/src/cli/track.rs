//! `holoface track`: runs the tracker session over a frame source and writes one JSON line per frame.

use crate::cli::write_atomic;
use holoface_sources::output::Output;
use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args as ClapArgs;
use serde_json::json;

use crate::args::{AlignerKind, RuntimeArgs};
use holoface_process::stop::{Signal, Stop};
use holoface_runtime::{
    AlignerChoice, AnsweredBy, FaceTracker, RemoteOptions, SessionOptions, TrackerOptions,
};

/// Arguments of `holoface track`.
#[derive(Debug, ClapArgs)]
pub struct Args {
    /// The frames (also the frame rate of `--annotate out.mp4`).
    #[command(flatten)]
    pub input: crate::args::SourceArgs,
    /// Aligner.
    #[arg(long, value_enum, default_value = "krfws")]
    pub aligner: AlignerKind,
    /// CANDIDE-3 model.
    #[command(flatten)]
    pub candide: crate::args::CandideArg,
    /// Disable headset-motion compensation of the tracking initialisation.
    #[arg(long)]
    pub no_motion_compensation: bool,
    /// Prediction horizon in milliseconds.
    #[arg(long, default_value_t = holoface_runtime::defaults::LOOKAHEAD_MS)]
    pub lookahead_ms: f64,
    /// Most faces tracked at once, each with a stable id.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u16).range(1..=64))]
    pub max_faces: u16,
    /// While fewer than `--max-faces` are tracked (and at least one), run the detector every N frames.
    #[arg(long, default_value_t = holoface_runtime::defaults::DETECT_EVERY, value_parser = clap::value_parser!(u32).range(1..))]
    pub detect_every: u32,
    /// Detector tiles per side besides the whole frame (default: none for one face, 3 x 3 for several).
    /// BlazeFace sees 128 px; a face narrower than about a tenth of a tile's side is missed, so a group
    /// photo of small faces needs more (a 50-px face in a 1666-px photo: 10).
    #[arg(long, value_parser = clap::value_parser!(u16).range(1..=32))]
    pub detect_tiles: Option<u16>,
    /// Also draw each frame annotated (landmarks, fitted CANDIDE-3 mesh, pose axes, aligner): a path ending
    /// in `.mp4` gets an H.264 video at `--fps`, any other path a folder of PNGs (`frame_000000.png`, ...).
    #[arg(long)]
    pub annotate: Option<PathBuf>,
    /// Also draw the objects and effects of a scene file anchored on each face, where a headset would show
    /// them: each frame with the face result of the frame captured the display delay earlier (the scene's
    /// `display_delay_ms`, else `--lookahead-ms`), at its predicted pose. `default` is the shipped scene
    /// (glasses, a top hat, sparks from an open mouth, rose lenses on a smile). Written to `--augment-out`.
    #[arg(long, value_name = "SCENE")]
    pub augment: Option<PathBuf>,
    /// Where `--augment` draws: a path ending in `.mp4` gets an H.264 video, any other a folder of PNGs
    /// [default: runs/augmented.mp4 from a video or stream, runs/augmented/ from a folder of images].
    #[arg(long, requires = "augment")]
    pub augment_out: Option<PathBuf>,
    /// JSON-lines output, one line per frame; `-` is standard output (then every human message goes to standard
    /// error). From a live source (`--source -`) each line is written and flushed as its frame is tracked, under
    /// the file's real name: Ctrl-C or SIGTERM ends the run after the frame in hand, keeping every line (a second
    /// signal stops at once), and even a killed run leaves whole lines. From a file or folder the lines appear
    /// when every frame was tracked (whole or nothing).
    #[arg(long, default_value = "runs/track.jsonl")]
    pub out: PathBuf,
    /// Alignment server for `--aligner remote`.
    #[arg(long)]
    pub server: Option<std::net::SocketAddr>,
    /// SHA-256 fingerprint of the server's certificate (printed by the server at start).
    #[arg(long)]
    pub fingerprint: Option<String>,
    /// Access token for the server.
    #[arg(long, env = "HOLOFACE_TOKEN", default_value = "")]
    pub token: String,
    /// Per-frame deadline for the server's answer, milliseconds.
    #[arg(long, default_value_t = holoface_runtime::defaults::DEADLINE_MS)]
    pub deadline_ms: u64,
    /// Crop encoding on the wire (`raw`, `png`, `jpeg`, `jpeg:Q`).
    #[arg(long, default_value = holoface_runtime::defaults::CROP_ENCODING)]
    pub crop_encoding: holoface_runtime::link::CropCodec,
    /// `--aligner remote`: do not adapt the local aligner to the person while the link is up (by default
    /// its answers when the link drops are corrected towards what the server answered for this face).
    #[arg(long)]
    pub no_adapt: bool,
    /// `--aligner remote`: cut the link on a schedule in media time, `START:LENGTH[,...]` in seconds
    /// (`20:10,60:10`: at 20 s for 10 s and at 60 s for 10 s), through a relay in front of `--server`.
    #[arg(long)]
    pub link_cuts: Option<crate::link_cuts::LinkCuts>,
    /// The landmark filter.
    #[command(flatten)]
    pub steady: crate::args::SteadyArgs,
    /// Runtime assets.
    #[command(flatten)]
    pub runtime: RuntimeArgs,
}

/// The remote options from `--server`, `--fingerprint`, `--token`, `--deadline-ms` and `--crop-encoding`.
fn remote_options(args: &Args) -> anyhow::Result<RemoteOptions> {
    let server = args.server.context("--aligner remote needs --server ADDR")?;
    let fingerprint = args
        .fingerprint
        .as_deref()
        .context("--aligner remote needs --fingerprint (the server prints it at start)")?
        .parse()
        .map_err(|e| anyhow::anyhow!("--fingerprint: {e}"))?;
    let mut remote = RemoteOptions::new(server, fingerprint, args.token.clone());
    remote.deadline = std::time::Duration::from_millis(args.deadline_ms);
    remote.codec = args.crop_encoding;
    if args.no_adapt {
        remote.adapt = None;
    }
    Ok(remote)
}

/// One face of a `track` line.
fn face_json(f: &holoface_runtime::FaceResult) -> serde_json::Value {
    let u = f;
    json!({
        "id": f.id,
        "aligner": u.answered_by,
        "init": u.init,
        "confidence": u.confidence,
        "adaptation": u.adaptation,
        "landmarks_px": u.landmarks.iter().map(|p| [p.x, p.y]).collect::<Vec<_>>(),
        "raw_landmarks_px": u.raw_landmarks.iter().map(|p| [p.x, p.y]).collect::<Vec<_>>(),
        "camera": {
            "translation_m": u.fit.translation.to_array(),
            "rotation_wxyz": [u.fit.rotation.w, u.fit.rotation.x, u.fit.rotation.y, u.fit.rotation.z],
            "rmse_px": u.fit.rmse_px,
        },
        "world": {
            "position_m": u.world.position.to_array(),
            "rotation_wxyz": [u.world.rotation.w, u.world.rotation.x, u.world.rotation.y, u.world.rotation.z],
            "predicted_position_m": u.predicted_position.to_array(),
            "display_position_m": u.display.0.to_array(),
        },
        "weights": u.expression.iter()
            .map(|(unit, w)| (unit.name().to_owned(), json!(w)))
            .collect::<serde_json::Map<_, _>>(),
        "attributes": {
            "smile": u.attributes.smile, "brows_raised": u.attributes.brows_raised,
            "mouth_open": u.attributes.mouth_open,
        },
        "blendshapes": u.blendshapes.iter()
            .map(|(b, v)| (b.arkit_name().to_owned(), json!(v)))
            .collect::<serde_json::Map<_, _>>(),
    })
}

/// The tracker `args` ask for and, with `--link-cuts`, the relay that cuts its link.
fn start_tracker(args: &Args) -> anyhow::Result<(FaceTracker, Option<crate::link_cuts::CutRelay>)> {
    let session = SessionOptions {
        motion_compensation: !args.no_motion_compensation,
        lookahead_s: args.lookahead_ms / 1e3,
        max_faces: usize::from(args.max_faces),
        detect_every: args.detect_every,
        steady: args.steady.settings(),
        ..SessionOptions::default()
    };
    let mut opts = args.runtime.tracker_options(&args.candide, session);
    opts.detector.tiles = args.detect_tiles.map(usize::from);
    anyhow::ensure!(
        args.link_cuts.is_none() || args.aligner == AlignerKind::Remote,
        "--link-cuts cuts the remote aligner's link: it needs --aligner remote"
    );
    let mut relay = None;
    // KRFWS and the remote aligner as an app runs them; DAN in-process is the tools' own aligner.
    let tracker = match args.aligner {
        AlignerKind::Krfws => crate::args::tracker(opts)?,
        AlignerKind::Remote => {
            let mut remote = remote_options(args)?;
            if let Some(cuts) = &args.link_cuts {
                let r = crate::link_cuts::CutRelay::start(remote.server, cuts.clone())?;
                remote.server = r.addr();
                relay = Some(r);
            }
            crate::args::tracker(TrackerOptions {
                aligner: AlignerChoice::Remote(remote),
                ..opts
            })?
        }
        AlignerKind::Dan => crate::args::tracker_with(&opts, args.runtime.dan_aligner()?.boxed(), None)?,
    };
    Ok((tracker, relay))
}

/// Runs `holoface track`.
pub fn run(args: Args, stop: &Stop) -> anyhow::Result<()> {
    let (mut tracker, mut relay) = start_tracker(&args)?;
    let mut source = args.input.open()?;
    // A live source has no end but the user's: its lines are a journal (written per frame under the real name, or
    // to standard output), and a signal ends the run as the source's end would. From a file, the lines appear at
    // --out only when every frame was tracked: a failed run leaves no file.
    let stdout = args.out == std::path::Path::new("-");
    let live = args.input.is_stdin() || stdout;
    let mut out = if live {
        stop.stop_gracefully();
        let out = Output::live(&args.out)?;
        if out.is_stdout() {
            crate::cli::stdout_carries_data();
        }
        out
    } else {
        Output::create(&args.out, crate::cli::temporaries())?
    };
    let mut annotated = args
        .annotate
        .as_deref()
        .map(|p| Frames::open(p, args.input.fps, "annotated"))
        .transpose()?;
    let mut augmented = args
        .augment
        .as_deref()
        .map(|scene| open_augment(&args, scene, &tracker))
        .transpose()?;
    let (mut frames, mut faces, mut remote_frames) = (0usize, 0usize, 0usize);
    // The cuts are in media time and the link runs on the wall clock: the frames come at their timestamps.
    let mut pacer = relay.is_some().then(crate::link_cuts::Pacer::default);
    let mut reader_gone = false;
    let mut line_bytes = Vec::new();
    while stop.requested().is_none() {
        let sf = match source.next_frame() {
            Ok(Some(sf)) => sf,
            Ok(None) => break,
            // The signal reached the whole pipeline: ffmpeg, stopped mid-frame, ends the stream short.
            Err(_) if stop.requested().is_some() => break,
            Err(e) => return Err(e.into()),
        };
        if let Some(p) = pacer.as_mut() {
            p.wait(sf.timestamp_us);
        }
        let link_cut = relay.as_mut().map(|r| r.at(sf.timestamp_us));
        let frame = sf.view();
        let step = tracker
            .process_step(&frame)
            .with_context(|| format!("frame {} of {}", sf.index, args.input.source.display()))?;
        let link_state = tracker.link_status().map(|s| s.state());
        remote_frames += step
            .faces
            .faces
            .iter()
            .filter(|f| f.answered_by == AnsweredBy::RemoteDan)
            .count();
        let no_face = step.faces.no_face_reason();
        if let Some(out) = annotated.as_mut() {
            let canvas = crate::annotate::annotate(
                &sf.image,
                sf.index,
                &step.faces.faces,
                no_face,
                tracker.face_model(),
                &sf.intrinsics,
            );
            out.push(sf.index, &canvas)?;
        }
        if let Some(a) = augmented.as_mut() {
            a.frame(&sf, &step.faces.faces)?;
        }
        let line = frame_line(&sf, &step, link_state, link_cut);
        line_bytes.clear();
        serde_json::to_writer(&mut line_bytes, &line)?;
        line_bytes.push(b'\n');
        if live {
            match out.end_frame(&line_bytes) {
                // The reader of standard output has gone (`| head -n 100`): the run is over, not failed.
                Err(e) if stdout && e.kind() == std::io::ErrorKind::BrokenPipe => {
                    reader_gone = true;
                    break;
                }
                r => r?,
            }
        } else {
            out.write_all(&line_bytes)?;
        }
        frames += 1;
        faces += step.faces.faces.len();
    }
    // The annotation first: when it fails, the lines of a file source are not committed either.
    let annotated = annotated.map(Frames::finish).transpose()?;
    let augmented = augmented.map(Augmented::finish).transpose()?;
    if !reader_gone {
        out.commit()?;
    }
    let stopped = stop.requested();
    say_summary(
        &args,
        &tracker,
        stopped,
        (frames, faces, remote_frames),
        annotated.into_iter().chain(augmented),
    );
    if let Some(p) = &pacer {
        crate::say!(
            "--link-cuts: frames fed at their timestamps, as a camera's come (the link connects, holds off and \
             backs off on the wall clock); held back {:.1} s in all",
            p.waited().as_secs_f64()
        );
    }
    if let Some(sig) = stopped {
        // The shell's code for the signal, as for any command it ends; the outputs are complete.
        std::process::exit(sig.exit_code());
    }
    Ok(())
}

/// One frame's JSON line.
fn frame_line(
    sf: &holoface_runtime::OwnedFrame,
    step: &holoface_runtime::frame_step::StepFrame,
    link_state: Option<holoface_runtime::LinkState>,
    link_cut: Option<bool>,
) -> serde_json::Value {
    let mut line = json!({
        "frame": sf.index,
        "timestamp_us": sf.timestamp_us,
        "face": !step.faces.faces.is_empty(),
        "faces": step.faces.faces.iter().map(face_json).collect::<Vec<_>>(),
        "detected": step.detected,
        "timings": {
            "prepare_ms": step.timings.prepare.as_secs_f64() * 1e3,
            "align_ms": step.timings.align.as_secs_f64() * 1e3,
            "fit_pose_filter_ms": step.timings.complete.as_secs_f64() * 1e3,
        },
        "link": link_state,
    });
    if let Some(cut) = link_cut {
        line["link_cut"] = json!(cut);
    }
    if let Some(reason) = step.faces.no_face_reason() {
        line["reason"] = json!(reason);
    }
    line
}

/// What the run did, in words: frames and faces, where the lines went, the annotation, the link.
fn say_summary(
    args: &Args,
    tracker: &FaceTracker,
    stopped: Option<Signal>,
    (frames, faces, remote_frames): (usize, usize, usize),
    drawn: impl Iterator<Item = String>,
) {
    let stdout = args.out == std::path::Path::new("-");
    match stopped {
        Some(sig) => crate::say!(
            "stopped by {} after {frames} frames, {faces} faces; kept every one in {}",
            sig.name(),
            if stdout {
                "standard output".into()
            } else {
                args.out.display().to_string()
            }
        ),
        None if stdout => crate::say!("{frames} frames, {faces} faces"),
        None => crate::say!("{frames} frames, {faces} faces; wrote {}", args.out.display()),
    }
    for d in drawn {
        crate::say!("{d}");
    }
    if let Some(status) = tracker.link_status() {
        if matches!(status, holoface_runtime::LinkInfo::Up(_)) {
            crate::say!("{remote_frames} of {faces} faces aligned by the remote DAN");
        } else {
            let why = match (&status, status.failure()) {
                (holoface_runtime::LinkInfo::Failed(f), _) => format!("gave up: {f}"),
                (_, Some(f)) => format!("retrying: {f}"),
                (_, None) => "still connecting".to_owned(),
            };
            tracing::warn!(
                "the alignment server link is not up ({why}); {remote_frames} of {faces} faces were aligned \
                 remotely, the rest by the local aligner"
            );
        }
    }
}

/// The augmentation `--augment` asks for, and where it draws.
fn open_augment(args: &Args, scene: &std::path::Path, tracker: &FaceTracker) -> anyhow::Result<Augmented> {
    let scene = crate::augment::scene::Scene::load(scene)?;
    let augmenter = crate::augment::Augmenter::new(scene, tracker.face_model().clone(), args.lookahead_ms);
    let out = args.augment_out.clone().unwrap_or_else(|| {
        if args.input.source.is_dir() {
            PathBuf::from("runs/augmented")
        } else {
            PathBuf::from("runs/augmented.mp4")
        }
    });
    crate::say!(
        "--augment: drawn for a display {:.0} ms after capture, into {}",
        augmenter.delay_ms(),
        out.display()
    );
    Ok(Augmented {
        augmenter,
        out: Frames::open(&out, args.input.fps, "augmented")?,
        jitter: ScreenJitter::default(),
    })
}

/// `--augment`: the augmentation, where it draws, and the objects' jitter on screen.
struct Augmented {
    augmenter: crate::augment::Augmenter,
    out: Frames,
    jitter: ScreenJitter,
}

impl Augmented {
    /// Draws frame `sf`, whose faces the tracker found to be `faces`.
    fn frame(
        &mut self,
        sf: &holoface_runtime::OwnedFrame,
        faces: &[holoface_runtime::FaceResult],
    ) -> anyhow::Result<()> {
        let a = &mut self.augmenter;
        a.update(
            sf.timestamp_us,
            faces.iter().map(crate::augment::FaceSnapshot::of).collect(),
        );
        let mut canvas = holoface_harness::plot::Canvas::new(sf.image.width(), sf.image.height());
        canvas.blit_gray(0, 0, sf.image.as_bytes(), sf.image.width(), sf.image.height(), 1);
        a.draw(&mut canvas, &sf.intrinsics, &sf.world_from_camera);
        self.out.push(sf.index, &canvas)?;
        self.jitter.push(a, sf, faces);
        Ok(())
    }

    /// Says the jitter and closes the output; says what was written.
    fn finish(self) -> anyhow::Result<String> {
        self.jitter.say(&self.augmenter);
        self.out.finish()
    }
}

/// Where the first face's anchored objects land in each frame (their origins projected), and its landmarks:
/// their jitter side by side at the end of an `--augment` run.
#[derive(Default)]
struct ScreenJitter {
    objects: Vec<Vec<Option<holoface_models::geometry::Point2>>>,
    landmarks: Vec<crate::track_measures::Landmarks>,
}

impl ScreenJitter {
    fn push(
        &mut self,
        a: &crate::augment::Augmenter,
        sf: &holoface_runtime::OwnedFrame,
        faces: &[holoface_runtime::FaceResult],
    ) {
        let camera_from_world = sf.world_from_camera.inverse();
        let shown = a.anchors().into_iter().next();
        let n = shown.as_ref().map_or(self.objects.len(), |(_, p)| p.len());
        self.objects
            .resize_with(n.max(self.objects.len()), || vec![None; self.landmarks.len()]);
        for (k, track) in self.objects.iter_mut().enumerate() {
            let at = shown
                .as_ref()
                .and_then(|(_, poses)| poses.get(k))
                .and_then(|p| sf.intrinsics.project(camera_from_world.apply(p.translation)));
            track.push(at);
        }
        self.landmarks.push(faces.first().map(|f| f.landmarks));
    }

    /// Says each object's screen-space jitter beside the landmarks'.
    fn say(&self, a: &crate::augment::Augmenter) {
        use crate::track_measures::{jitter49_px, point_jitter_px, summarise};
        let Some(lm) = summarise(&jitter49_px(&self.landmarks)) else {
            return;
        };
        for (k, track) in self.objects.iter().enumerate() {
            if let Some(o) = summarise(&point_jitter_px(track)) {
                crate::say!(
                    "--augment: {} on screen jitters {:.2} px median, {:.2} p95 ({} frames); the steadied \
                     landmarks {:.2} px median, {:.2} p95 (second difference, 49 points)",
                    a.object_name(k),
                    o.median,
                    o.p95,
                    o.frames,
                    lm.median,
                    lm.p95
                );
            }
        }
    }
}

/// Where `--annotate` and `--augment` draw: a folder of PNGs, or an H.264 MP4 (created at the first frame's
/// size); `noun` says which in the summary.
enum Frames {
    Pngs(PathBuf, &'static str),
    Video {
        path: PathBuf,
        fps: u32,
        writer: Option<Box<holoface_sources::video::Mp4Writer>>,
        noun: &'static str,
    },
}

impl Frames {
    fn open(path: &std::path::Path, fps: f64, noun: &'static str) -> anyhow::Result<Self> {
        let is_mp4 = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("mp4"));
        if is_mp4 {
            anyhow::ensure!(
                fps.is_finite() && (1.0..=1000.0).contains(&fps),
                "{} frames to {}: --fps {fps} must be within 1..=1000",
                noun,
                path.display()
            );
            if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            }
            Ok(Self::Video {
                path: path.to_path_buf(),
                fps: fps.round() as u32,
                writer: None,
                noun,
            })
        } else {
            std::fs::create_dir_all(path).with_context(|| format!("creating {}", path.display()))?;
            Ok(Self::Pngs(path.to_path_buf(), noun))
        }
    }

    fn push(&mut self, index: usize, canvas: &holoface_harness::plot::Canvas) -> anyhow::Result<()> {
        match self {
            Self::Pngs(dir, _) => {
                let path = dir.join(format!("frame_{index:06}.png"));
                Ok(write_atomic(&path, canvas.to_png())?)
            }
            Self::Video {
                path, fps, writer, ..
            } => {
                let w = match writer {
                    Some(w) => w,
                    None => {
                        // H.264 4:2:0 needs even sizes: an odd last row or column is left out.
                        let (vw, vh) = (canvas.width() & !1, canvas.height() & !1);
                        writer.insert(Box::new(holoface_sources::video::Mp4Writer::create(
                            path,
                            vw,
                            vh,
                            *fps,
                            crate::cli::temporaries(),
                        )?))
                    }
                };
                w.push_rgb(canvas.rgb(), canvas.width())
                    .with_context(|| format!("frame {index} of {}", path.display()))
            }
        }
    }

    /// Closes the video; says what was written.
    fn finish(self) -> anyhow::Result<String> {
        Ok(match self {
            Self::Pngs(dir, noun) => format!("{noun} frames in {}", dir.display()),
            Self::Video {
                path, writer, noun, ..
            } => match writer {
                Some(w) => format!("{} {noun} frames in {}", w.finish()?, path.display()),
                None => format!("no frames, so no video at {}", path.display()),
            },
        })
    }
}
