#!/usr/bin/env bash
# `make test`, step by step, with the wall time and the CPU time (user + system, of the step's whole process tree)
# of each (BENCHMARKS.md, "Build time"). Runs the Makefile's own steps (TEST_STEPS, what `make test` runs through
# scripts/test-steps.sh), in their order: a step is a phase, or phases side by side (`A,B+C`), timed together; each
# phase names the set-up it needs, so a step's time includes whatever set-up it is the first to need. Prints a
# Markdown table and appends it to runs/test-timings.md.
set -euo pipefail
cd "$(dirname "$0")/.."
read -r -a phases <<<"$(make -s --no-print-directory print-TEST_STEPS)"
mkdir -p runs
out=runs/test-timings.md
tmp=$(mktemp)
trap 'rm -f "$tmp"' EXIT
rows=()
wall=0
cpu=0
failed=()
for p in "${phases[@]}"; do
    # A failing phase is timed and reported too, and the later phases still run (the table says which failed).
    mark=
    /usr/bin/time -f '%e %U %S' -o "$tmp" scripts/test-steps.sh "$p" || { failed+=("$p"); mark=' (failed)'; }
    read -r e u s < <(tail -n 1 "$tmp")
    w=$(awk -v e="$e" 'BEGIN { printf "%.0f", e }')
    c=$(awk -v u="$u" -v s="$s" 'BEGIN { printf "%.0f", u + s }')
    wall=$((wall + w))
    cpu=$((cpu + c))
    name=$(sed 's/,/, /g; s/+/ beside /' <<<"$p")
    rows+=("| \`$name\`$mark | $w | $c |")
    echo "test-timings: $p ${w} s wall, ${c} CPU-s" >&2
done
{
    echo
    echo "### $(date -u +%Y-%m-%dT%H:%MZ), $(git rev-parse --short HEAD), $(nproc) cores, $(lscpu | sed -n 's/^Model name: *//p' | head -n1)"
    echo
    echo "| step | wall s | CPU s (user + sys) |"
    echo "|---|---:|---:|"
    printf '%s\n' "${rows[@]}"
    echo "| **make test** | **$wall** | **$cpu** |"
} | tee -a "$out"
if [ ${#failed[@]} -gt 0 ]; then
    echo "test-timings: failed: ${failed[*]}" >&2
    exit 1
fi
