//! The CUDA execution provider path with the real `onnxruntime-gpu` library (`make ort-gpu`), on either kind of
//! machine: where CUDA can run, the provider runs and gives the CPU's landmarks; where it cannot (no NVIDIA device,
//! or CUDA 13 / cuDNN 9 missing), the server falls back to the CPU and says why, or refuses to start when told to.
//! A machine without an NVIDIA device node must fall back: the engine cannot claim a GPU it does not have.
//!
//! ONNX Runtime allows one library per process, so these tests live in their own test binary (and nextest
//! runs each in its own process): every engine here comes from the GPU build.

#![allow(clippy::unwrap_used)] // test helpers outside #[test] fns

use std::time::Duration;

use holoface_inference::{
    BatchTensor, CPU_PROVIDER, CUDA_PROVIDER, InferenceEngine, LandmarkOut, OnnxEngine, Provider,
};
use holoface_protocol::ReplyOutcome;
use holoface_tests::{
    RunningServer, TEST_TOKEN, TestClient, frame, hello, loopback_settings, ort_gpu_dylib_path,
};

const WAIT: Duration = Duration::from_secs(30);
/// CUDA's and the CPU's fp32 kernels sum in different orders: landmarks agree to well under a pixel.
const CUDA_VS_CPU_PX: f32 = 0.05;

fn gpu_build_settings(provider: Provider) -> holoface_alignment_server::config::Settings {
    let mut s = loopback_settings();
    s.engine.ort_dylib = ort_gpu_dylib_path();
    s.engine.provider = provider;
    s.max_frame_age = Duration::from_secs(3);
    s
}

/// Whether the kernel shows an NVIDIA GPU at all (its driver's device nodes). Without one, CUDA cannot run.
fn nvidia_device_present() -> bool {
    ["/dev/nvidiactl", "/dev/nvidia0"]
        .iter()
        .any(|p| std::path::Path::new(p).exists())
}

/// One crop's landmarks from an engine of the GPU build with the given provider, and what ran it.
fn landmarks_with(provider: Provider) -> (holoface_inference::Execution, LandmarkOut) {
    let mut opts = gpu_build_settings(provider).engine;
    opts.ort_dylib = ort_gpu_dylib_path();
    let mut engine = OnnxEngine::load(&opts).unwrap();
    let mut batch = BatchTensor::new(1, 112 * 112);
    batch.push(&frame(0, 7, 0).crop.data).unwrap();
    let mut out = vec![LandmarkOut::default()];
    engine.infer(&batch, &mut out).unwrap();
    assert!(out[0].problem(68).is_none(), "{:?}", out[0].problem(68));
    (engine.execution(), out.pop().unwrap())
}

fn assert_close(got: &[[f32; 2]], want: &[[f32; 2]], tol: f32) {
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(want) {
        assert!(
            (g[0] - w[0]).abs() < tol && (g[1] - w[1]).abs() < tol,
            "{g:?} vs {w:?}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cuda_runs_where_it_can_and_elsewhere_the_cpu_takes_over_and_says_why() {
    let cuda = Provider::Cuda {
        device: 0,
        required: false,
    };
    let (_, on_cpu) = landmarks_with(Provider::Cpu);
    let (execution, answer) = landmarks_with(cuda);
    if execution.provider == CUDA_PROVIDER {
        // A GPU machine: the provider runs, nothing fell back, and it reads the crop as the CPU does.
        assert!(
            nvidia_device_present(),
            "CUDA claimed without an NVIDIA device: {execution}"
        );
        assert_eq!(
            (execution.fallback.as_deref(), execution.device),
            (None, Some(0)),
            "{execution}"
        );
        assert_close(&answer.landmarks, &on_cpu.landmarks, CUDA_VS_CPU_PX);
    } else {
        // No GPU, or CUDA/cuDNN missing: the CPU runs the model and the reason names what is missing.
        assert_eq!(execution.provider, CPU_PROVIDER, "{execution}");
        let why = execution.fallback.clone().expect("a fallback reason");
        assert!(
            why.contains("CUDA") && (why.contains(".so") || why.contains("device")),
            "the reason should name the CUDA library or device that is missing: {why}"
        );
        assert_close(&answer.landmarks, &on_cpu.landmarks, 1e-2);
    }
    let fallback = execution.fallback.is_some();

    // The server: starts, serves the same landmarks, and its metrics say which provider runs the model.
    let server = RunningServer::start(gpu_build_settings(cuda)).await.unwrap();
    let text = server.metrics.render();
    assert!(
        text.contains(&format!(
            "provider=\"{}\",fallback=\"{fallback}\"",
            execution.provider
        )),
        "{text}"
    );
    let mut client = tokio::time::timeout(
        WAIT,
        TestClient::connect(server.addr, server.fingerprint, hello(TEST_TOKEN)),
    )
    .await
    .unwrap()
    .unwrap();
    let reply = tokio::time::timeout(WAIT, client.request(&frame(1, 7, 3_000)))
        .await
        .unwrap()
        .unwrap();
    let ReplyOutcome::Landmarks { landmarks, .. } = &reply.outcome else {
        panic!("not aligned: {:?}", reply.outcome)
    };
    assert_close(landmarks, &answer.landmarks, 1e-2);
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cuda_required_starts_only_where_cuda_runs_and_otherwise_refuses_with_the_reason() {
    let (execution, _) = landmarks_with(Provider::Cuda {
        device: 0,
        required: false,
    });
    let settings = gpu_build_settings(Provider::Cuda {
        device: 0,
        required: true,
    });
    if execution.provider == CUDA_PROVIDER {
        let server = RunningServer::start(settings).await.unwrap();
        let text = server.metrics.render();
        assert!(
            text.contains(&format!("provider=\"{CUDA_PROVIDER}\",fallback=\"false\"")),
            "{text}"
        );
        server.shutdown().await.unwrap();
    } else {
        let e = RunningServer::start(settings).await.unwrap_err().to_string();
        assert!(
            e.contains(&format!("{CUDA_PROVIDER} is required")) && e.contains("engine.cuda_required"),
            "{e}"
        );
    }
}

#[test]
fn the_cpu_provider_of_the_gpu_build_runs_as_asked() {
    let mut opts = loopback_settings().engine;
    opts.ort_dylib = ort_gpu_dylib_path();
    let engine = OnnxEngine::load(&opts).unwrap();
    let execution = engine.execution();
    assert_eq!(
        (execution.provider.as_str(), execution.fallback),
        (CPU_PROVIDER, None)
    );
}
