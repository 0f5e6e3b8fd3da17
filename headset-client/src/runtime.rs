//! Where the runtime assets live (ONNX Runtime library, models) and how the CLI builds engines from them.

use std::path::PathBuf;

use alignment_server::engine::{OnnxEngine, OnnxOptions};
use anyhow::Context;
use clap::Args;

use crate::align::{DanAligner, KrfwsAligner};

/// Paths and threads of the runtime assets; every path has an env override set by `make setup`.
#[derive(Debug, Clone, Args)]
pub struct RuntimeArgs {
    /// ONNX Runtime shared library (`make setup` fetches it from the pinned PyPI wheel).
    #[arg(
        long,
        env = "ORT_DYLIB_PATH",
        default_value = ".cache/onnxruntime/libonnxruntime.so.1.31.1"
    )]
    pub ort_dylib: PathBuf,
    /// DAN model (ONNX).
    #[arg(long, env = "HOLOFACE_DAN_MODEL", default_value = "models/assets/dan.onnx")]
    pub dan_model: PathBuf,
    /// Face detector model (BlazeFace short range, ONNX).
    #[arg(
        long,
        env = "HOLOFACE_DETECTOR_MODEL",
        default_value = ".cache/blazeface/face_detection_front_128x128.onnx"
    )]
    pub detector: PathBuf,
    /// KRFWS model (the local aligner).
    #[arg(long, env = "HOLOFACE_KRFWS_MODEL", default_value = "models/assets/krfws.bin")]
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
    /// DAN through ONNX Runtime in this process.
    pub fn dan_aligner(&self) -> anyhow::Result<DanAligner<OnnxEngine>> {
        let engine = OnnxEngine::load(&OnnxOptions {
            model: self.dan_model.clone(),
            ort_dylib: self.ort_dylib.clone(),
            intra_threads: self.threads,
            max_batch: 1,
            cuda: false,
            spin: false,
        })
        .with_context(|| format!("loading DAN model {}", self.dan_model.display()))?;
        Ok(DanAligner::new(engine)?)
    }

    /// BlazeFace through ONNX Runtime (1 thread).
    pub fn detector(&self) -> anyhow::Result<crate::detect::BlazeFace> {
        crate::detect::BlazeFace::load(&self.detector, &self.ort_dylib, 1)
            .with_context(|| format!("loading the face detector {}", self.detector.display()))
    }

    /// KRFWS from its model file.
    pub fn krfws_aligner(&self) -> anyhow::Result<KrfwsAligner> {
        let bytes = std::fs::read(&self.krfws_model)
            .with_context(|| format!("reading KRFWS model {}", self.krfws_model.display()))?;
        let model = holoface_models::krfws::Krfws::from_bytes(&bytes)
            .with_context(|| format!("loading KRFWS model {}", self.krfws_model.display()))?;
        Ok(KrfwsAligner::new(model))
    }
}

/// The CANDIDE-3 model option shared by the commands that fit a face (`--candide`).
#[derive(Debug, Clone, clap::Args)]
pub struct CandideArg {
    /// CANDIDE-3 model (`.wfm`), resolved by the set-up command.
    #[arg(
        long,
        env = "HOLOFACE_CANDIDE",
        default_value = "../shared/data/candide3/candide3.wfm"
    )]
    pub candide: PathBuf,
}

impl CandideArg {
    /// Loads the model.
    pub fn load(&self) -> anyhow::Result<holoface_models::candide::FaceModel> {
        load_face_model(&self.candide)
    }
}

/// Loads the CANDIDE-3 face model from a `.wfm` file.
pub fn load_face_model(path: &std::path::Path) -> anyhow::Result<holoface_models::candide::FaceModel> {
    let text = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let wfm = holoface_models::candide::Wfm::parse(&String::from_utf8_lossy(&text))
        .with_context(|| format!("parsing {}", path.display()))?;
    Ok(holoface_models::candide::FaceModel::from_wfm(&wfm)?)
}
