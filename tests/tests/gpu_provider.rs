//! The CUDA execution provider path with the real `onnxruntime-gpu` library (`make ort-gpu`) on a machine
//! without CUDA: the server falls back to the CPU and says why, or refuses to start when told to.
//!
//! ONNX Runtime allows one library per process, so these tests live in their own test binary (and nextest
//! runs each in its own process): every engine here comes from the GPU build. Where a GPU, CUDA 13 and
//! cuDNN 9 are present, `cuda_falls_back_...` fails by design (the provider runs): that machine is
//! where `holoface-server-bench --cuda` measures instead (BENCHMARKS.md).

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

fn gpu_build_settings(provider: Provider) -> holoface_alignment_server::config::Settings {
    let mut s = loopback_settings();
    s.engine.ort_dylib = ort_gpu_dylib_path();
    s.engine.provider = provider;
    s.max_frame_age = Duration::from_secs(3);
    s
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cuda_falls_back_to_the_cpu_and_says_why() {
    let settings = gpu_build_settings(Provider::Cuda {
        device: 0,
        required: false,
    });
    // The engine on its own: it loads, runs on the CPU, and the reason names what is missing.
    let mut engine = OnnxEngine::load(&settings.engine).unwrap();
    let execution = engine.execution();
    assert_eq!(execution.provider, CPU_PROVIDER, "{execution}");
    let why = execution.fallback.clone().expect("a fallback reason");
    assert!(
        why.contains("CUDA") && (why.contains(".so") || why.contains("device")),
        "the reason should name the CUDA library or device that is missing: {why}"
    );
    let mut batch = BatchTensor::new(1, 112 * 112);
    batch.push(&frame(0, 7, 0).crop.data).unwrap();
    let mut expected = vec![LandmarkOut::default()];
    engine.infer(&batch, &mut expected).unwrap();
    assert!(expected[0].problem(68).is_none(), "{:?}", expected[0].problem(68));

    // The server: starts, serves the same landmarks, and its metrics say the CPU runs the model.
    let server = RunningServer::start(settings).await.unwrap();
    let text = server.metrics.render();
    assert!(
        text.contains(&format!("provider=\"{CPU_PROVIDER}\",fallback=\"true\"")),
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
    for (got, want) in landmarks.iter().zip(&expected[0].landmarks) {
        assert!(
            (got[0] - want[0]).abs() < 1e-2 && (got[1] - want[1]).abs() < 1e-2,
            "{got:?} vs {want:?}"
        );
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cuda_required_refuses_to_start_with_the_reason() {
    let settings = gpu_build_settings(Provider::Cuda {
        device: 0,
        required: true,
    });
    let e = RunningServer::start(settings).await.unwrap_err().to_string();
    assert!(
        e.contains(&format!("{CUDA_PROVIDER} is required")) && e.contains("engine.cuda_required"),
        "{e}"
    );
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
