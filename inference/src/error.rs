//! The one error type of loading and running an engine.

use std::path::PathBuf;

/// Loading or running the engine failed.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EngineError {
    /// An asset (the ONNX Runtime library, the DAN model, the refiner) is not where it was looked for.
    #[error(transparent)]
    Missing(#[from] holoface_files::home::MissingAsset),
    /// A directory was given where the ONNX Runtime library belongs.
    #[error("ONNX Runtime library path {path} is a directory, not libonnxruntime.so")]
    RuntimeIsDirectory {
        /// The path that was given.
        path: PathBuf,
    },
    /// The ONNX Runtime library exists but could not be loaded.
    #[error("loading ONNX Runtime from {path}: {detail}")]
    RuntimeLoad {
        /// The library.
        path: PathBuf,
        /// The loader's message.
        detail: String,
    },
    /// ONNX Runtime is already loaded in this process from another library (one per process, ever).
    #[error(
        "ONNX Runtime is already loaded in this process from {loaded}; {asked} cannot be loaded beside it (one \
         library per process): give the same path, or none"
    )]
    RuntimeAlreadyLoaded {
        /// The library the process loaded first.
        loaded: PathBuf,
        /// The one asked for now.
        asked: PathBuf,
    },
    /// A directory was given where the model file belongs.
    #[error("DAN model path {path} is a directory, not an .onnx file: give the model file itself")]
    ModelIsDirectory {
        /// The path that was given.
        path: PathBuf,
    },
    /// A model file is not the file it should be (its checksum or its recorded release disagree).
    #[error(
        "{path} is damaged: {detail}; restore it (`holoface setup` reinstalls the shipped models, or copy the file again)"
    )]
    Damaged {
        /// The file.
        path: PathBuf,
        /// What disagrees.
        detail: String,
    },
    /// The engine's start-up self-test on a fixed crop failed: the model answers garbage.
    #[error(
        "{path} failed its start-up self-test: {detail}; the model file is damaged or not a face-alignment model (`holoface setup` restores the shipped one)"
    )]
    SelfTest {
        /// The model file.
        path: PathBuf,
        /// What the engine answered.
        detail: String,
    },
    /// The model's inputs or outputs break the contract.
    #[error("model {tensor}: {problem}")]
    BadModelIo {
        /// The input or output concerned.
        tensor: String,
        /// What is wrong with it.
        problem: String,
    },
    /// A metadata key is missing or unusable.
    #[error("model metadata {key}: {problem}")]
    BadMetadata {
        /// The `metadata_props` key.
        key: &'static str,
        /// What is wrong with it.
        problem: String,
    },
    /// The requested execution provider cannot run the model, and falling back to the CPU was not allowed.
    #[error("{provider} is required (engine.cuda_required) but cannot run: {detail}")]
    ProviderUnavailable {
        /// ONNX Runtime's name of the provider.
        provider: &'static str,
        /// Why it cannot run.
        detail: String,
    },
    /// A batch larger than the engine's maximum, or with a wrong output slice.
    #[error("batch of {len} does not fit (max {max})")]
    BatchTooLarge {
        /// Frames in the batch.
        len: usize,
        /// The engine's limit.
        max: usize,
    },
    /// A crop of the wrong size was pushed into a batch.
    #[error("crop of {len} bytes, expected {expected}")]
    CropSize {
        /// Bytes given.
        len: usize,
        /// Bytes expected (S * S).
        expected: usize,
    },
    /// The model's outputs are missing or shaped against its declaration (landmark count, batch).
    #[error("model output contradicts its declaration: {0}")]
    BadOutput(String),
    /// The refinement cascade's model file is unreadable, damaged or does not fit the DAN model.
    #[error("refiner model {path}: {detail} (another file{}, or DAN alone)", option.as_ref().map(|o| format!(" in {o}")).unwrap_or_default())]
    Cascade {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        detail: String,
        /// The front end's name for the refiner's setting ([`EngineError::given_by`]).
        option: Option<String>,
    },
    /// The refinement cascade refused an input.
    #[error("refinement: {0}")]
    Refine(String),
    /// ONNX Runtime reported an error.
    #[error("ONNX Runtime: {0}")]
    Ort(String),
}

impl EngineError {
    /// Names the front end's setting of a missing asset (see [`holoface_files::home::MissingAsset::given_by`]).
    #[must_use]
    pub fn given_by(self, options: &[(holoface_files::home::Asset, &str)]) -> Self {
        match self {
            Self::Missing(m) => Self::Missing(m.given_by(options)),
            Self::Cascade { path, detail, .. } => Self::Cascade {
                path,
                detail,
                option: options
                    .iter()
                    .find(|(a, _)| *a == holoface_files::home::REFINER)
                    .map(|(_, o)| (*o).to_owned()),
            },
            other => other,
        }
    }
}

impl From<ort::Error> for EngineError {
    fn from(e: ort::Error) -> Self {
        Self::Ort(e.to_string())
    }
}
