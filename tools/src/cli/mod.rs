//! The `holoface` command line. Each subcommand lives in its own module and exposes `Args` + `run`.

use clap::{Parser, Subcommand};
use holoface_process::stop::Stop;
use holoface_sources::output::Temporaries;

pub mod demo;
pub mod eval;
pub mod multi_face;
pub mod record;
pub mod setup;
pub mod simulate;
pub mod stability;
#[cfg(feature = "train")]
pub mod teacher_labels;
pub mod track;
pub mod tracking_losses;
#[cfg(feature = "train")]
pub mod train_blendshapes;
#[cfg(feature = "train")]
pub mod train_krfws;
#[cfg(feature = "train")]
pub mod train_refiner;

/// What the trainers' tests share: a subcommand's arguments parsed from a command line alone, and the training
/// report a shipped model was written with.
#[cfg(all(test, feature = "train"))]
mod trainer_tests {
    #[derive(clap::Parser)]
    struct Cli<T: clap::Args> {
        #[command(flatten)]
        args: T,
    }

    /// `argv` (its first word the subcommand's name) parsed as `T`.
    pub(crate) fn parse<T: clap::Args>(argv: &[&str]) -> Result<T, clap::Error> {
        <Cli<T> as clap::Parser>::try_parse_from(argv).map(|c| c.args)
    }

    /// `models/assets/<name>`, the JSON report the trainer wrote beside the shipped model.
    pub(crate) fn shipped_report(name: &str) -> serde_json::Value {
        let path = format!("{}/../models/assets/{name}", env!("CARGO_MANIFEST_DIR"));
        let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{path}: {e}"));
        serde_json::from_str(&text).unwrap_or_else(|e| panic!("{path}: {e}"))
    }
}

/// HoloFace: find, track and understand faces for AR headsets.
#[derive(Debug, Parser)]
#[command(name = "holoface", version, about)]
pub struct Cli {
    /// Log filter (tracing `EnvFilter` syntax); `RUST_LOG` overrides it.
    #[arg(long, global = true, default_value = "info", env = "HOLOFACE_LOG")]
    pub log: String,
    /// What to do.
    #[command(subcommand)]
    pub command: Command,
}

/// Subcommands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Fill the holoface data folder ($HOLOFACE_HOME, else ~/.local/share/holoface): ONNX Runtime, the face
    /// detector and the sample from their pinned registry files, our models; `--candide FILE` adds CANDIDE-3.
    Setup(setup::Args),
    /// The main job: server + client on loopback over the bundled sample, link cut part-way.
    Demo(demo::Args),
    /// Evaluate aligners on an annotated folder (detect or GT box, align, NME/AUC/failures, CED plot).
    Eval(eval::Args),
    /// Several faces at once on rendered scenes (1, 2, 3, 5 faces): per-face NME against tracking each face
    /// alone, id switches, detector runs, losses.
    MultiFace(multi_face::Args),
    /// Write a recorded stream (`.hfrec`) from an image folder or another recording.
    Record(record::Args),
    /// Synthetic headset sequences from CANDIDE-3: fit recovery, prediction and motion-compensation numbers.
    Simulate(simulate::Args),
    /// Landmark stability on real, unannotated video: per aligner, jitter of the raw and the steadied
    /// landmarks, re-detections, jumps at remote/local switches, agreement with a per-frame peer (dlib).
    Stability(stability::Args),
    /// Track faces over an image folder, an MP4 video or a recorded stream; one JSON line per frame.
    Track(track::Args),
    #[cfg(feature = "train")]
    /// Label unannotated face photographs with dlib's predictor and our remote pipeline, keeping the faces
    /// they agree on (`--gt`: measure the teachers on annotated faces instead).
    TeacherLabels(teacher_labels::Args),
    /// Tracking losses with and without headset-motion compensation, on rendered sequences of the
    /// validation faces with a real aligner.
    TrackingLosses(tracking_losses::Args),
    #[cfg(feature = "train")]
    /// Learn how head turns move the landmarks in the blendshapes' face frame (their pose terms) from the
    /// training annotations.
    TrainBlendshapes(train_blendshapes::Args),
    #[cfg(feature = "train")]
    /// Train the KRFWS local aligner and evaluate it on the validation split.
    TrainKrfws(train_krfws::Args),
    #[cfg(feature = "train")]
    /// Train the server's refinement cascade on DAN's answers to augmented training crops.
    TrainRefiner(train_refiner::Args),
}

/// Runs the parsed command line; `stop` is the one [`handle_signals`] records Ctrl-C and SIGTERM in.
pub fn run(cli: Cli, stop: &Stop) -> anyhow::Result<()> {
    match cli.command {
        Command::Setup(args) => {
            // Setup's product is the files it installs: a closed stdout must not stop it half-way.
            STOP_ON_CLOSED_STDOUT.store(false, std::sync::atomic::Ordering::Relaxed);
            setup::run(args)
        }
        Command::Demo(args) => demo::run(args),
        Command::Eval(args) => eval::run(args),
        Command::MultiFace(args) => multi_face::run(args),
        Command::Track(args) => track::run(args, stop),
        Command::Record(args) => record::run(args, stop),
        Command::Simulate(args) => simulate::run(args),
        Command::Stability(args) => stability::run(args, stop),
        #[cfg(feature = "train")]
        Command::TeacherLabels(args) => teacher_labels::run(args),
        Command::TrackingLosses(args) => tracking_losses::run(args),
        #[cfg(feature = "train")]
        Command::TrainBlendshapes(args) => train_blendshapes::run(args),
        #[cfg(feature = "train")]
        Command::TrainKrfws(args) => train_krfws::run(args),
        #[cfg(feature = "train")]
        Command::TrainRefiner(args) => train_refiner::run(args),
    }
}

/// Ctrl-C and SIGTERM (binaries only), recorded in `stop`, which the binary also hands to [`run`]. A command that
/// called [`Stop::stop_gracefully`] (one reading a live source, `track --source -`) is asked to stop after the
/// current frame by the first one, as if its source had ended, and ended at once by a second, its journals (live
/// outputs, flushed per frame) kept. Any other command ends at once without leaving its own temporary files behind
/// (whole-or-nothing outputs not yet committed); the exit code is the shell's for the signal (130 / 143).
pub fn handle_signals(stop: &Stop) {
    let stop = stop.clone();
    let installed = holoface_process::signals::on_signals(move |sig| {
        let graceful = stop.is_graceful();
        if graceful && stop.request(sig) {
            eprintln!(
                "{}: finishing the frame in hand and keeping every frame so far (send it again to stop at once)",
                sig.name()
            );
            return;
        }
        let removed = if graceful { 0 } else { temporaries().remove_all() };
        eprintln!(
            "{}: stopped at once{}",
            sig.name(),
            if graceful {
                "; every frame written so far is kept".to_owned()
            } else if removed > 0 {
                format!("; removed {removed} unfinished output file(s)")
            } else {
                String::new()
            }
        );
        std::process::exit(sig.exit_code());
    });
    if let Err(e) = installed {
        tracing::warn!(error = %e, "no signal handler: an interrupted command may leave temporary files");
    }
}

/// The temporary files of this process's whole-or-nothing outputs: the CLI's own registry (the binary's state,
/// like its signal handler), handed to every `Output` a command writes and emptied by [`handle_signals`] when a
/// signal ends the command at once. The libraries keep no such list.
pub fn temporaries() -> &'static Temporaries {
    static TEMPORARIES: std::sync::OnceLock<Temporaries> = std::sync::OnceLock::new();
    TEMPORARIES.get_or_init(Temporaries::new)
}

/// [`holoface_sources::output::write_atomic`] with the CLI's [`temporaries`]: how every command writes a file
/// whole or not at all.
pub fn write_atomic(
    path: &std::path::Path,
    bytes: impl AsRef<[u8]>,
) -> Result<(), holoface_sources::SourceError> {
    holoface_sources::output::write_atomic(path, bytes, temporaries())
}

/// Whether standard output carries a command's data (`--out -`): then [`say`] prints to standard error.
static STDOUT_CARRIES_DATA: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Says that standard output now carries the command's data (a journal on `-`, [`holoface_sources::output::Output::is_stdout`]).
pub fn stdout_carries_data() {
    STDOUT_CARRIES_DATA.store(true, std::sync::atomic::Ordering::Relaxed);
}

/// Whether a closed standard output ends the command (the default) or is ignored (`holoface setup`, whose
/// work is the files it installs, not what it prints).
static STOP_ON_CLOSED_STDOUT: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(true);

/// Writes one line to standard output, or to standard error when standard output carries the command's data
/// (`--out -`). When the reader has gone (`holoface eval | head -1`), the command ends quietly (exit 0, its
/// unfinished outputs removed) instead of panicking, unless it asked to carry on.
pub fn say(args: std::fmt::Arguments<'_>) {
    use std::io::Write as _;
    if STDOUT_CARRIES_DATA.load(std::sync::atomic::Ordering::Relaxed) {
        eprintln!("{args}");
        return;
    }
    let mut out = std::io::stdout().lock();
    let result = out
        .write_fmt(args)
        .and_then(|()| out.write_all(b"\n"))
        .and_then(|()| out.flush());
    if let Err(e) = result
        && e.kind() == std::io::ErrorKind::BrokenPipe
        && STOP_ON_CLOSED_STDOUT.load(std::sync::atomic::Ordering::Relaxed)
    {
        temporaries().remove_all();
        std::process::exit(0);
    }
}

/// `println!` for the commands: see [`say`].
#[macro_export]
macro_rules! say {
    () => { $crate::cli::say(format_args!("")) };
    ($($arg:tt)*) => { $crate::cli::say(format_args!($($arg)*)) };
}

/// Installs the tracing subscriber (binaries only; libraries never do).
pub fn init_logging(filter: &str) {
    holoface_process::logging::init(holoface_process::logging::env_filter_or(&format!(
        "{filter},quinn=info,rustls=info"
    )));
}
