//! The command-line options naming the runtime assets (same environment variables and data-folder defaults
//! as `holoface_runtime::assets`) and how the tools build engines from them.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Args, ValueEnum};
use holoface_inference::{ORT_DYLIB_ENV, OnnxEngine, OnnxOptions};
use holoface_runtime::{
    AssetPaths, CANDIDE_ENV, DETECTOR_ENV, FaceTracker, KRFWS_ENV, SessionOptions, SteadySettings,
    TrackerError, TrackerOptions, home,
};

use holoface_harness::dan_aligner::DanAligner;
use holoface_runtime::align::KrfwsAligner;
use holoface_runtime::detect::DetectError;

/// The command line's names for the files it loads, in the runtime's messages (each front end names its own).
pub const CLI_OPTIONS: &[(holoface_runtime::Asset, &str)] = &[
    (home::ORT_LIBRARY, "--ort-dylib"),
    (home::DETECTOR, "--detector"),
    (home::KRFWS, "--krfws-model"),
    (home::CANDIDE, "--candide"),
    (home::DAN, "--dan-model"),
    (home::REFINER, "--refine-model"),
];

/// [`FaceTracker::new`], its errors naming the command line's options.
pub fn tracker(opts: TrackerOptions) -> Result<FaceTracker, TrackerError> {
    FaceTracker::new(opts).map_err(|e| e.given_by(CLI_OPTIONS))
}

/// [`FaceTracker::with_aligner`], its errors naming the command line's options.
pub fn tracker_with<A: holoface_runtime::align::Aligner + ?Sized>(
    opts: &TrackerOptions,
    aligner: Box<A>,
    link: Option<holoface_runtime::link::LinkWatch>,
) -> Result<FaceTracker<A>, TrackerError> {
    FaceTracker::with_aligner(opts, aligner, link).map_err(|e| e.given_by(CLI_OPTIONS))
}

/// Paths and threads of the runtime assets: each path is the option, else its environment variable, else its
/// file in the holoface data folder, which `holoface setup` fills (`holoface_runtime::assets::home`).
#[derive(Debug, Clone, Args)]
pub struct RuntimeArgs {
    /// ONNX Runtime shared library (`holoface setup` fetches it from the pinned PyPI wheel).
    #[arg(long, env = ORT_DYLIB_ENV, default_value_os_t = home::ORT_LIBRARY.default_path())]
    pub ort_dylib: PathBuf,
    /// DAN model (ONNX).
    #[arg(long, env = home::DAN.env, default_value_os_t = home::DAN.default_path())]
    pub dan_model: PathBuf,
    /// Face detector model (BlazeFace short range, ONNX).
    #[arg(long, env = DETECTOR_ENV, default_value_os_t = home::DETECTOR.default_path())]
    pub detector: PathBuf,
    /// The server's refinement cascade (run after DAN by the server and by `--aligner remote`).
    #[arg(long, env = home::REFINER.env, default_value_os_t = home::REFINER.default_path())]
    pub refine_model: PathBuf,
    /// KRFWS model (the local aligner).
    #[arg(long, env = KRFWS_ENV, default_value_os_t = home::KRFWS.default_path())]
    pub krfws_model: PathBuf,
    /// ONNX Runtime intra-op threads for DAN.
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
}

impl RuntimeArgs {
    /// The ONNX Runtime library path.
    pub fn ort_dylib(&self) -> PathBuf {
        self.ort_dylib.clone()
    }
    /// The detector model path.
    pub fn detector_model(&self) -> PathBuf {
        self.detector.clone()
    }
    /// In-process DAN's engine options (CPU, batch 1).
    pub fn dan_options(&self) -> OnnxOptions {
        OnnxOptions {
            model: self.dan_model.clone(),
            ort_dylib: self.ort_dylib.clone(),
            intra_threads: self.threads,
            max_batch: 1,
            provider: holoface_inference::Provider::Cpu,
            spin: false,
        }
    }

    /// DAN alone in this process.
    pub fn dan_aligner(&self) -> anyhow::Result<DanAligner<OnnxEngine>> {
        holoface_harness::dan_aligner::dan_alone(&self.dan_options())
            .map_err(|e| e.given_by(CLI_OPTIONS))
            .with_context(|| format!("loading DAN model {}", self.dan_model.display()))
    }

    /// The server's pipeline in this process (`holoface_harness::dan_aligner::server_pipeline`).
    pub fn remote_aligner(
        &self,
    ) -> anyhow::Result<DanAligner<holoface_inference::CascadeEngine<OnnxEngine>>> {
        holoface_harness::dan_aligner::server_pipeline(&self.dan_options(), &self.refine_model)
            .map_err(|e| e.given_by(CLI_OPTIONS))
            .with_context(|| format!("loading DAN model {} and the refiner", self.dan_model.display()))
    }

    /// The tracker options of a video with these assets, the CANDIDE-3 model of `candide`, `session`'s settings,
    /// the local aligner and the detector's defaults (the commands change what their options say).
    pub fn tracker_options(&self, candide: &CandideArg, session: SessionOptions) -> TrackerOptions {
        TrackerOptions {
            assets: AssetPaths {
                ort_dylib: self.ort_dylib.clone(),
                detector: self.detector.clone(),
                krfws: self.krfws_model.clone(),
                candide: candide.candide.clone(),
            },
            session,
            ..TrackerOptions::default()
        }
    }

    /// BlazeFace through ONNX Runtime (1 thread).
    pub fn detector(&self) -> anyhow::Result<holoface_runtime::detect::BlazeFace> {
        holoface_runtime::detect::BlazeFace::load(&self.detector, &self.ort_dylib, 1)
            .map_err(|e| match e {
                DetectError::Missing(m) => DetectError::Missing(m.given_by(CLI_OPTIONS)),
                e => e,
            })
            .with_context(|| format!("loading the face detector {}", self.detector.display()))
    }

    /// KRFWS from its model file.
    pub fn krfws_aligner(&self) -> anyhow::Result<KrfwsAligner> {
        let model =
            holoface_runtime::assets::load_krfws(&self.krfws_model).map_err(|e| e.given_by(CLI_OPTIONS))?;
        Ok(KrfwsAligner::new(model))
    }
}

/// The CANDIDE-3 model option shared by the commands that fit a face (`--candide`).
#[derive(Debug, Clone, clap::Args)]
pub struct CandideArg {
    /// CANDIDE-3 model (`.wfm`; `holoface setup --candide FILE` installs it in the data folder).
    #[arg(long, env = CANDIDE_ENV, default_value_os_t = home::CANDIDE.default_path())]
    pub candide: PathBuf,
}

impl CandideArg {
    /// Loads the model.
    pub fn load(&self) -> anyhow::Result<holoface_models::candide::FaceModel> {
        Ok(holoface_runtime::assets::load_face_model(&self.candide).map_err(|e| e.given_by(CLI_OPTIONS))?)
    }
}

/// Which aligner answers: one choice for every command (`track`, `eval`, `multi-face`, `tracking-losses`); a
/// command refuses, with a message, the ones it cannot run.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum AlignerKind {
    /// KRFWS, the headset's local aligner (51 inner points; reported on the 49-point protocol only).
    Krfws,
    /// DAN in-process through ONNX Runtime (DAN alone).
    Dan,
    /// What a headset gets from the alignment server: DAN, then the refinement cascade. `track`: over QUIC
    /// (`--server`, `--fingerprint`, `--token`), KRFWS on the same frame when the server misses the deadline
    /// or the link is down; `multi-face`: a server started in this process, on loopback; `eval`: the
    /// server's engine in-process, the crop through the wire's JPEG q75 round trip.
    Remote,
}

impl AlignerKind {
    /// The name in reports and on the command line.
    pub fn label(self) -> &'static str {
        match self {
            Self::Krfws => "krfws",
            Self::Dan => "dan",
            Self::Remote => "remote",
        }
    }
}

/// The landmark filter's settings ([`SteadySettings`], with its defaults).
#[derive(Debug, Clone, Copy, Args)]
pub struct SteadyArgs {
    /// Turn the landmark filter off (the steadied landmarks then equal the aligner's raw ones).
    #[arg(long)]
    pub no_steady: bool,
    /// Local aligner's (KRFWS's) answers: One-Euro cut-off at rest of the shape in the face's frame, Hz.
    #[arg(long, default_value_t = SteadySettings::default().shape_cutoff_hz)]
    pub steady_shape_cutoff_hz: f64,
    /// Local aligner's answers: One-Euro speed coefficient of the shape (per eye distance per second).
    #[arg(long, default_value_t = SteadySettings::default().shape_beta)]
    pub steady_shape_beta: f64,
    /// Local aligner's answers: One-Euro cut-off at rest of the face's placement (translation, scale,
    /// rotation), Hz.
    #[arg(long, default_value_t = SteadySettings::default().rigid_cutoff_hz)]
    pub steady_rigid_cutoff_hz: f64,
    /// Local aligner's answers: One-Euro speed coefficient of the placement.
    #[arg(long, default_value_t = SteadySettings::default().rigid_beta)]
    pub steady_rigid_beta: f64,
    /// DAN's (and the server's) answers: shape cut-off at rest, Hz.
    #[arg(long, default_value_t = SteadySettings::default().precise_shape_cutoff_hz)]
    pub steady_precise_shape_cutoff_hz: f64,
    /// DAN's answers: shape speed coefficient.
    #[arg(long, default_value_t = SteadySettings::default().precise_shape_beta)]
    pub steady_precise_shape_beta: f64,
    /// DAN's answers: placement cut-off at rest, Hz.
    #[arg(long, default_value_t = SteadySettings::default().precise_rigid_cutoff_hz)]
    pub steady_precise_rigid_cutoff_hz: f64,
    /// DAN's answers: placement speed coefficient.
    #[arg(long, default_value_t = SteadySettings::default().precise_rigid_beta)]
    pub steady_precise_rigid_beta: f64,
}

impl SteadyArgs {
    /// The session's `steady` setting.
    pub fn settings(&self) -> SteadySettings {
        SteadySettings {
            enabled: !self.no_steady,
            shape_cutoff_hz: self.steady_shape_cutoff_hz,
            shape_beta: self.steady_shape_beta,
            rigid_cutoff_hz: self.steady_rigid_cutoff_hz,
            rigid_beta: self.steady_rigid_beta,
            precise_shape_cutoff_hz: self.steady_precise_shape_cutoff_hz,
            precise_shape_beta: self.steady_precise_shape_beta,
            precise_rigid_cutoff_hz: self.steady_precise_rigid_cutoff_hz,
            precise_rigid_beta: self.steady_precise_rigid_beta,
        }
    }
}

/// Where the frames come from (`track`, `record`): every source `holoface_sources::source::open_source` reads.
#[derive(Debug, Clone, Args)]
pub struct SourceArgs {
    /// A folder of PNG/JPEG frames (name order), a video file (MP4, MOV, WebM, MKV: H.264, HEVC, VP8/VP9,
    /// through the system's FFmpeg libraries; MP4/H.264 only in a build without them), a YUV4MPEG2 stream
    /// (`.y4m`, or `-` for standard input: a live camera through ffmpeg, taken as fixed without `--poses`), or a
    /// recorded stream (`.hfrec`).
    #[arg(long)]
    pub source: PathBuf,
    /// Pose sidecar (JSON lines: frame, camera_to_world, optional intrinsics): the headset's pose per frame for
    /// a video or image folder.
    #[arg(long)]
    pub poses: Option<PathBuf>,
    /// Frame rate of an image folder and of a `.y4m` without one in its header.
    #[arg(long, default_value_t = 30.0)]
    pub fps: f64,
}

impl SourceArgs {
    /// Opens the source.
    pub fn open(&self) -> anyhow::Result<Box<dyn holoface_sources::FrameSource>> {
        Ok(holoface_sources::source::open_source(
            &self.source,
            self.fps,
            self.poses.as_deref(),
        )?)
    }

    /// Whether the frames come from standard input (a live stream).
    pub fn is_stdin(&self) -> bool {
        self.source == std::path::Path::new("-")
    }
}
