//! Which DAN file the server runs: the precision rule.
//!
//! The int8 model (`models/dan/to_int8.py`) runs about 3x faster than fp32 on a CPU whose int8 dot products
//! are one instruction (AVX-512 VNNI, AVX-VNNI: BENCHMARKS.md, "int8 DAN"); without VNNI ONNX Runtime's int8
//! kernels widen through 16-bit sums and its own guide expects no gain, so there the fp32 model serves.
//! [`decide`] is the rule, pure (the CPU's flags and the file's presence are its inputs); the server loads what
//! it names and checks the model's own `holoface.precision` against it ([`Decision::check`]).

use std::fmt;
use std::path::{Path, PathBuf};

use crate::EngineError;
use crate::contract::ModelInfo;
pub use crate::cpu::CpuInt8;
use crate::onnx::Provider;

/// What the operator asked for (`engine.precision`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PrecisionChoice {
    /// int8 where the CPU has VNNI and the int8 model is installed, else the model `engine.model` names.
    #[default]
    Auto,
    /// The model `engine.model` names, whatever its precision (what a server did before int8; tests).
    Model,
    /// `engine.model`, which must be an fp32 graph.
    Fp32,
    /// `engine.model`, which must be an fp16 graph (`make dan-fp16`; for GPUs).
    Fp16,
    /// `engine.int8_model`, even on a CPU without VNNI (where it is no faster: said in the log).
    Int8,
}

/// What [`decide`] chose: the file to load, the precision it must have, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Decision {
    /// The model file to load.
    pub model: PathBuf,
    /// The `holoface.precision` that file must declare (`None`: whatever it is).
    pub expect: Option<&'static str>,
    /// Why, in a sentence for the log.
    pub reason: String,
}

impl Decision {
    /// Checks the loaded model's own precision against the decision; the error says which setting to change.
    pub fn check(&self, info: &ModelInfo) -> Result<(), EngineError> {
        match self.expect {
            Some(want) if info.precision != want => Err(EngineError::BadMetadata {
                key: "holoface.precision",
                problem: format!(
                    "{} is an {} graph, but the server was to serve {want} ({}): point engine.model (or \
                     engine.int8_model) at the {want} file, or change engine.precision",
                    self.model.display(),
                    info.precision,
                    self.reason
                ),
            }),
            _ => Ok(()),
        }
    }
}

impl fmt::Display for Decision {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} ({})", self.model.display(), self.reason)
    }
}

/// The rule: which file serves, given the operator's choice, the fp32 model (`model`), the int8 one
/// (`int8_model`, present or not), the execution provider and the CPU.
pub fn decide(
    choice: PrecisionChoice,
    model: &Path,
    int8_model: &Path,
    int8_present: bool,
    provider: Provider,
    cpu: CpuInt8,
) -> Decision {
    let given = |expect, reason: String| Decision {
        model: model.to_path_buf(),
        expect,
        reason,
    };
    let int8 = |reason: String| Decision {
        model: int8_model.to_path_buf(),
        expect: Some("int8"),
        reason,
    };
    match choice {
        PrecisionChoice::Model => given(None, "engine.precision = \"model\": engine.model as it is".into()),
        PrecisionChoice::Fp32 => given(Some("fp32"), "engine.precision = \"fp32\"".into()),
        PrecisionChoice::Fp16 => given(Some("fp16"), "engine.precision = \"fp16\"".into()),
        PrecisionChoice::Int8 if cpu.has_vnni() => {
            int8(format!("engine.precision = \"int8\"; this CPU has {}", cpu.label()))
        }
        PrecisionChoice::Int8 => int8(
            "engine.precision = \"int8\", but this CPU has no AVX-512 VNNI or AVX-VNNI: ONNX Runtime's int8 \
             kernels may be no faster than fp32 here"
                .into(),
        ),
        PrecisionChoice::Auto => match provider {
            Provider::Cuda { .. } => given(None, "auto: a GPU provider runs engine.model".into()),
            Provider::Cpu if !cpu.has_vnni() => given(
                None,
                "auto: this CPU has no AVX-512 VNNI or AVX-VNNI, so int8 would be no faster; engine.model serves"
                    .into(),
            ),
            Provider::Cpu if !int8_present => given(
                None,
                format!(
                    "auto: no int8 model at {} (engine.int8_model; `holoface setup` installs it); engine.model \
                     serves",
                    int8_model.display()
                ),
            ),
            Provider::Cpu => int8(format!(
                "auto: this CPU has {}, where the int8 model runs about 3x faster than fp32",
                cpu.label()
            )),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const VNNI: CpuInt8 = CpuInt8 {
        avx512_vnni: true,
        avx_vnni: false,
    };
    const AVX_VNNI: CpuInt8 = CpuInt8 {
        avx512_vnni: false,
        avx_vnni: true,
    };
    const NONE: CpuInt8 = CpuInt8 {
        avx512_vnni: false,
        avx_vnni: false,
    };
    const CUDA: Provider = Provider::Cuda {
        device: 0,
        required: false,
    };

    fn run(choice: PrecisionChoice, present: bool, provider: Provider, cpu: CpuInt8) -> Decision {
        decide(
            choice,
            Path::new("/d/dan.onnx"),
            Path::new("/d/dan.int8.onnx"),
            present,
            provider,
            cpu,
        )
    }

    #[test]
    fn auto_serves_int8_only_on_a_vnni_cpu_with_the_file() {
        for cpu in [VNNI, AVX_VNNI] {
            let d = run(PrecisionChoice::Auto, true, Provider::Cpu, cpu);
            assert_eq!(
                (d.model.to_str(), d.expect),
                (Some("/d/dan.int8.onnx"), Some("int8"))
            );
            assert!(d.reason.contains(cpu.label()), "{d}");
        }
        let d = run(PrecisionChoice::Auto, true, Provider::Cpu, NONE);
        assert_eq!((d.model.to_str(), d.expect), (Some("/d/dan.onnx"), None));
        assert!(d.reason.contains("no AVX-512 VNNI"), "{d}");
        let d = run(PrecisionChoice::Auto, false, Provider::Cpu, VNNI);
        assert_eq!(d.model.to_str(), Some("/d/dan.onnx"));
        assert!(d.reason.contains("no int8 model at /d/dan.int8.onnx"), "{d}");
        let d = run(PrecisionChoice::Auto, true, CUDA, VNNI);
        assert_eq!(d.model.to_str(), Some("/d/dan.onnx"));
        assert!(d.reason.contains("GPU"), "{d}");
    }

    #[test]
    fn an_explicit_choice_is_obeyed_and_a_slow_one_says_so() {
        let d = run(PrecisionChoice::Int8, false, Provider::Cpu, NONE);
        assert_eq!(
            (d.model.to_str(), d.expect),
            (Some("/d/dan.int8.onnx"), Some("int8"))
        );
        assert!(d.reason.contains("may be no faster"), "{d}");
        let d = run(PrecisionChoice::Fp32, true, Provider::Cpu, VNNI);
        assert_eq!((d.model.to_str(), d.expect), (Some("/d/dan.onnx"), Some("fp32")));
        let d = run(PrecisionChoice::Fp16, true, CUDA, VNNI);
        assert_eq!(d.expect, Some("fp16"));
        let d = run(PrecisionChoice::Model, true, Provider::Cpu, VNNI);
        assert_eq!((d.model.to_str(), d.expect), (Some("/d/dan.onnx"), None));
    }

    #[test]
    fn a_model_of_another_precision_than_asked_is_refused_by_name() {
        let d = run(PrecisionChoice::Fp16, true, Provider::Cpu, VNNI);
        let mut info = crate::InferenceEngine::info(&crate::FakeEngine::new(1)).clone();
        info.precision = "fp16".into();
        d.check(&info).unwrap();
        info.precision = "fp32".into();
        let e = d.check(&info).unwrap_err().to_string();
        assert!(
            e.contains("fp32 graph") && e.contains("engine.precision = \"fp16\""),
            "{e}"
        );
        assert!(
            run(PrecisionChoice::Model, true, Provider::Cpu, VNNI)
                .check(&info)
                .is_ok()
        );
    }
}
