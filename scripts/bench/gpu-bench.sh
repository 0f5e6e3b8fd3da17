#!/usr/bin/env bash
# The GPU benchmark of the alignment server (issue 17, item 3), prepared to run as one command on a machine
# with an NVIDIA GPU, CUDA 13 and cuDNN 9:
#
#   scripts/bench/gpu-bench.sh                 # raw ONNX Runtime CUDA at batch 1/8/32/64, the server saturated, latency
#   scripts/bench/gpu-bench.sh --cpu-rehearsal # the same commands, short, on the CPU (checks the script, not a GPU)
#
# Needs target/release/holoface-server and holoface-server-bench (cargo build --release -p holoface-alignment-server
# -p holoface-tests), `make ort-gpu` and `make dan-fp16`. Both models (fp32, fp16) are measured. Results: one
# JSON line each in $OUT/gpu.jsonl (default target/bench), the commands' output on stdout. Where the system
# has no CUDA libraries on its path, the nvidia-* Python wheels' (PyTorch's) are used.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-target/bench}
B=${BENCH_BIN:-target/release/holoface-server-bench}
SERVER=${SERVER_BIN:-target/release/holoface-server}
FP16=${HOLOFACE_DAN_FP16_MODEL:-.cache/models/dan.fp16.onnx}
mkdir -p "$OUT"

if [[ ${1:-} == --cpu-rehearsal ]]; then
  flags=(--ort-dylib "${ORT_DYLIB_PATH:-.cache/holoface/libonnxruntime.so.1.31.1}")
  batches=1,8 clients=8 latency_clients=1,2 seconds=2 big=8
else
  flags=(--cuda --ort-dylib "${HOLOFACE_ORT_GPU_DYLIB:-.cache/onnxruntime-gpu/libonnxruntime.so.1.31.1}")
  batches=1,8,32,64 clients=64 latency_clients=1,8,32 seconds=8 big=32
  if command -v python3 >/dev/null; then
    wheel_libs=$(python3 - <<'PY' || true
import glob, os, importlib.util
spec = importlib.util.find_spec("nvidia")
roots = list(spec.submodule_search_locations) if spec and spec.submodule_search_locations else []
print(":".join(sorted({os.path.dirname(p) for r in roots for p in glob.glob(os.path.join(r, "*", "lib", "lib*.so*"))})))
PY
)
    [[ -n $wheel_libs ]] && export LD_LIBRARY_PATH=$wheel_libs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  fi
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv || true
fi

for model in models/assets/dan.onnx "$FP16"; do
  common=("${flags[@]}" --model "$model" --server-bin "$SERVER" --threads 2 --out "$OUT/gpu.jsonl")
  echo "== $model: raw ONNX Runtime"
  "$B" "${common[@]}" ort --batches "$batches" --seconds "$seconds"
  for batch in 8 "$big"; do
    echo "== $model: server saturated, batch $batch, $clients clients"
    "$B" "${common[@]}" throughput --batch "$batch" --clients "$clients" --seconds "$seconds"
  done
  echo "== $model: latency at 30 fps per client, batch <= $big"
  "$B" "${common[@]}" latency --clients "$latency_clients" --batch "$big" --seconds "$seconds"
done
