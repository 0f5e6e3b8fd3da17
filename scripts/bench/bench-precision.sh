#!/usr/bin/env bash
# fp32 against int8 DAN, side by side in one run (BENCHMARKS.md, "int8 DAN"; deploy/README.md, capacity planning):
# raw ONNX Runtime at batch 1 and 8 with 1 and 2 intra-op threads (alternating models, two rounds), the server's
# saturated throughput against raw ORT, and latency at 30 fps per headset. Needs the release binaries
# (`cargo build --release -p holoface-tests -p holoface-alignment-server`) and the data folder (`make setup-demo`).
#
#   scripts/bench/bench-precision.sh [OUT.jsonl]      # default target/bench/precision.jsonl
#
# Run it with nothing else on the machine; the JSON lines carry each measurement, the summary goes to stdout.
set -euo pipefail
cd "$(dirname "$0")/../.."
OUT=${1:-target/bench/precision.jsonl}
B=target/release/holoface-server-bench
FP32=${FP32:-models/assets/dan.onnx}
INT8=${INT8:-models/assets/dan.int8.onnx}
SECONDS_ORT=${SECONDS_ORT:-5}
mkdir -p "$(dirname "$OUT")"
echo "# $(date -u +%FT%TZ) $(lscpu | sed -n 's/^Model name: *//p' | head -n1), $(nproc) cores, cpu_int8 flags: $(grep -o -w 'avx512_vnni\|avx_vnni' /proc/cpuinfo | sort -u | tr '\n' ' ')"
for round in 1 2; do
  for t in 1 2; do
    for m in "$FP32" "$INT8"; do
      echo "## raw ORT, round $round, $t thread(s), $m"
      $B --out "$OUT" --model "$m" --threads "$t" ort --batches 1,8 --seconds "$SECONDS_ORT"
    done
  done
done
for m in "$FP32" "$INT8"; do
  echo "## server throughput vs raw, $m (2 threads, batch 8, 16 clients, DAN alone and with the refiner)"
  $B --out "$OUT" --model "$m" --threads 2 --refine false throughput --batch 8 --clients 16 --seconds 8
  $B --out "$OUT" --model "$m" --threads 2 --face-crops throughput --batch 8 --clients 16 --seconds 8
done
for m in "$FP32" "$INT8"; do
  echo "## latency at 30 fps per headset, $m (2 threads, batch <= 8, refiner on)"
  $B --out "$OUT" --model "$m" --threads 2 --face-crops latency --clients 1,2,4,6,8 --batch 8 --seconds 10
done
