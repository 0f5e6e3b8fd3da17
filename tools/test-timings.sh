#!/usr/bin/env bash
# `make test`, phase by phase, with the wall time of each (BENCHMARKS.md, "Build time"). Runs the Makefile's
# own list of phases (TEST_PHASES, what `make test` runs), in its order; each phase names the set-up it needs, so
# a phase's time includes whatever set-up it is the first to need. Prints a Markdown table and appends it to runs/test-timings.md.
set -euo pipefail
cd "$(dirname "$0")/.."
read -r -a phases <<<"$(make -s --no-print-directory print-TEST_PHASES)"
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
