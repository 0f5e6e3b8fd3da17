#!/usr/bin/env bash
# The C example cross-built for aarch64, run under qemu-aarch64, tracking the demo's sample through an x86-64
# holoface-server on loopback (make arm64-test). The server is stopped (SIGSTOP) once the example prints a
# server answer, so the link is cut and the example answers with local KRFWS; 4 s after its first local answer
# the server goes on (SIGCONT) and the example reconnects. The example exits 0 only when its answers went
# remote, local and remote again (ffi/examples/track.c, track_linked).
#
#   scripts/arm64-link.sh TRACK_AARCH64 SAMPLE.pgm SERVER_BIN SERVER_ORT_DYLIB
#
# The example's own assets (ORT_DYLIB_PATH for aarch64, the detector, KRFWS, CANDIDE-3) come from the
# environment, as for any app; the server's ONNX Runtime is named on its command line.
set -euo pipefail
track=$1 pgm=$2 server=$3 server_ort=$4
dir=$(mktemp -d)
srv=
client=
cleanup() {
    [ -n "$client" ] && kill "$client" 2>/dev/null || true
    if [ -n "$srv" ]; then kill -CONT "$srv" 2>/dev/null || true; kill "$srv" 2>/dev/null || true; wait "$srv" 2>/dev/null || true; fi
    rm -rf "$dir"
}
trap cleanup EXIT

# Waits (at most $2 s) until file $1 has a line matching $3, or the client has exited.
wait_for() {
    local deadline=$((SECONDS + $2))
    until grep -q "$3" "$1"; do
        kill -0 "$client" 2>/dev/null || return 1
        [ $SECONDS -lt $deadline ] || { echo "arm64-link: no '$3' within $2 s" >&2; return 1; }
        sleep 0.2
    done
}

"$server" --listen 127.0.0.1:0 --self-signed-name localhost --token arm64-link --intra-threads 1 \
    --ort-dylib "$server_ort" --log-level warn >"$dir/server.out" 2>"$dir/server.err" &
srv=$!
for _ in $(seq 300); do [ -s "$dir/server.out" ] && break; sleep 0.2; done
# "holoface-server on ADDR certificate-sha256 FP ..."
read -r _ _ addr _ fingerprint _ <"$dir/server.out" || { cat "$dir/server.err" >&2; exit 1; }
echo "arm64-link: x86-64 server on $addr, certificate $fingerprint"

# The client runs about 50x slower under qemu than on a device; a 33-ms deadline then measures the machine's load
# (with another process busy, every answer came late), so the deadline here is 400 ms.
HOLOFACE_SERVER=$addr HOLOFACE_SERVER_FINGERPRINT=$fingerprint HOLOFACE_TOKEN=arm64-link HOLOFACE_DEADLINE_MS=400 \
    qemu-aarch64 "$track" "$pgm" >"$dir/track.out" 2>&1 &
client=$!
status=0
if wait_for "$dir/track.out" 240 "answered by remote"; then
    kill -STOP "$srv"
    echo "arm64-link: the server answered; link cut (server stopped)"
    if wait_for "$dir/track.out" 60 "answered by local"; then
        sleep 4
        kill -CONT "$srv"
        echo "arm64-link: link back (server resumed)"
    fi
fi
wait "$client" || status=$?
client=
cat "$dir/track.out"
if [ $status -ne 0 ]; then
    echo "arm64-link: the aarch64 C example failed ($status); server log:" >&2
    tail -20 "$dir/server.err" >&2
fi
exit $status
