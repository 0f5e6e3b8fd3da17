#!/usr/bin/env bash
# `make test`, phase by phase, with the wall time of each (BENCHMARKS.md, "Build time"). Runs the same
# targets in the order `make test` runs them (`setup` runs the test build's `holoface setup`, so it follows
# `test-build`); a phase's time includes whatever set-up it is the first to need. Prints a Markdown table and appends it to runs/test-timings.md.
set -euo pipefail
cd "$(dirname "$0")/.."
phases=(deploy-check check deps-check test-build setup unit c-example csharp-example python-test fuzz-build)
mkdir -p runs
out=runs/test-timings.md
rows=()
total_start=$(date +%s)
for p in "${phases[@]}"; do
    start=$(date +%s)
    make --no-print-directory "$p"
    rows+=("| \`$p\` | $(($(date +%s) - start)) |")
done
total=$(($(date +%s) - total_start))
{
    echo
    echo "### $(date -u +%Y-%m-%dT%H:%MZ), $(nproc) cores, $(lscpu | sed -n 's/^Model name: *//p' | head -n1)"
    echo
    echo "| phase | wall s |"
    echo "|---|---:|"
    printf '%s\n' "${rows[@]}"
    echo "| **make test** | **$total** |"
} | tee -a "$out"
