//! The `holoface` command line. Each subcommand lives in its own module and exposes `Args` + `run`.

use clap::{Parser, Subcommand};

pub mod demo;
pub mod eval;
pub mod multi_face;
pub mod record;
pub mod setup;
pub mod simulate;
pub mod track;
pub mod tracking_losses;
pub mod train_krfws;
pub mod train_refiner;

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
    /// Track faces over an image folder, an MP4 video or a recorded stream; one JSON line per frame.
    Track(track::Args),
    /// Tracking losses with and without headset-motion compensation, on rendered sequences of the
    /// validation faces with a real aligner.
    TrackingLosses(tracking_losses::Args),
    /// Train the KRFWS local aligner and evaluate it on the validation split.
    TrainKrfws(train_krfws::Args),
    /// Train the server's refinement cascade on DAN's answers to augmented training crops.
    TrainRefiner(train_refiner::Args),
}

/// Runs the parsed command line.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Setup(args) => setup::run(args),
        Command::Demo(args) => demo::run(args),
        Command::Eval(args) => eval::run(args),
        Command::MultiFace(args) => multi_face::run(args),
        Command::Track(args) => track::run(args),
        Command::Record(args) => record::run(args),
        Command::Simulate(args) => simulate::run(args),
        Command::TrackingLosses(args) => tracking_losses::run(args),
        Command::TrainKrfws(args) => train_krfws::run(args),
        Command::TrainRefiner(args) => train_refiner::run(args),
    }
}

/// Installs the tracing subscriber (binaries only; libraries never do).
pub fn init_logging(filter: &str) {
    holoface_server::logging::init(holoface_server::logging::env_filter_or(&format!(
        "{filter},quinn=info,rustls=info"
    )));
}
