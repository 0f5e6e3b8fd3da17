#!/usr/bin/env bash
# `make test`'s steps (the Makefile's TEST_STEPS), in order. A step is one phase, or `A,B+C`: the phases A then B
# here, and C beside them in the background (its output held and printed, each line marked, once both end); the
# step fails if either side does. A side-by-side pair is a phase that leaves a core idle (downloads, installs, one
# process) beside one that can use it, and the two touch no common lock: the aarch64 build has its own target
# folder, and only one side installs packages (apt's lock), so neither waits on the other.
set -euo pipefail
cd "$(dirname "$0")/.."
for step in "$@"; do
    here=${step%%+*}
    beside=
    [[ $step == *+* ]] && beside=${step#*+}
    if [ -z "$beside" ]; then
        make --no-print-directory ${here//,/ }
        continue
    fi
    log=$(mktemp)
    # No jobserver passes to either side (this script is not run by make with -j), so each cargo uses both cores
    # and the kernel shares them.
    make --no-print-directory ${beside//,/ } >"$log" 2>&1 &
    pid=$!
    status=0
    make --no-print-directory ${here//,/ } || status=$?
    wait "$pid" || status=$?
    sed "s/^/[${beside}] /" "$log"
    rm -f "$log"
    if [ "$status" -ne 0 ]; then
        echo "test-steps: $step failed" >&2
        exit "$status"
    fi
done
