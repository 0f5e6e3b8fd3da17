#!/usr/bin/env bash
# The alignment server's container image, built and smoke-tested on this machine (`make image`, `make
# image-test`; deploy/README.md, "Container image").
#
#   deploy/image.sh base      # the base image: debian:12.12-slim from a registry, else debootstrap (bookworm)
#   deploy/image.sh context   # stage the host-built binaries and downloads in .cache/image/context
#   deploy/image.sh build     # base + context + podman/docker build -> holoface-server:$IMAGE_TAG
#   deploy/image.sh test      # start it, wait for /health, load-test it, scrape /metrics, refuse strangers,
#                             # SIGTERM it during a load and check the drain, the exit code and the log
#
# Podman or Docker, whichever answers (CONTAINER_ENGINE=podman|docker picks). With podman, podman's default
# ulimits are emptied (deploy/podman-containers.conf through CONTAINERS_CONF): raising RLIMIT_NOFILE past the
# caller's hard limit is refused on some hosts, this one included, and the server needs no more than it gets.
set -euo pipefail

cd "$(dirname "$0")/.."
IMAGE=${IMAGE:-holoface-server}
IMAGE_TAG=${IMAGE_TAG:-$(sed -n 's/^version = "\(.*\)"/\1/p' Cargo.toml | head -1)}
BASE_SUITE=bookworm # Debian 12, the release the binaries are built on
BASE_REGISTRY_IMAGE=${BASE_REGISTRY_IMAGE:-debian:12.12-slim}
BASE_LOCAL_IMAGE=localhost/holoface-base:$BASE_SUITE
DEBIAN_MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
CONTEXT=.cache/image/context
SERVER_BIN=target/release/holoface-server
CLI_BIN=target/demo/holoface # the lean CLI (no FFmpeg): `make setup-demo`
LOAD_BIN=target/release/holoface-load
OUT=${OUT:-runs/image}

say() { echo "image.sh: $*" >&2; }
die() {
    say "$*"
    exit 1
}

engine() {
    if [ -n "${CONTAINER_ENGINE:-}" ]; then
        echo "$CONTAINER_ENGINE"
    elif command -v podman >/dev/null; then
        echo podman
    elif command -v docker >/dev/null && docker info >/dev/null 2>&1; then
        echo docker
    else
        die "neither podman nor a running docker: install one (Debian: apt-get install podman runc)"
    fi
}
ENGINE=$(engine)
if [ "$ENGINE" = podman ]; then
    export CONTAINERS_CONF=${CONTAINERS_CONF:-$PWD/deploy/podman-containers.conf}
fi
ce() { "$ENGINE" "$@"; }

# The base image's name: the registry's when it can be pulled, else one made from Debian's package archive.
base() {
    if ce image inspect "$BASE_REGISTRY_IMAGE" >/dev/null 2>&1; then
        echo "$BASE_REGISTRY_IMAGE"
        return
    fi
    if [ "${IMAGE_BASE:-auto}" != debootstrap ] && timeout 60 "$ENGINE" pull -q "$BASE_REGISTRY_IMAGE" >/dev/null 2>&1; then
        say "base: $BASE_REGISTRY_IMAGE from the registry"
        echo "$BASE_REGISTRY_IMAGE"
        return
    fi
    if ce image inspect "$BASE_LOCAL_IMAGE" >/dev/null 2>&1; then
        say "base: $BASE_LOCAL_IMAGE (made earlier with debootstrap)"
        echo "$BASE_LOCAL_IMAGE"
        return
    fi
    command -v debootstrap >/dev/null || die "no registry reachable and no debootstrap: apt-get install debootstrap"
    say "base: no registry reachable; debootstrap $BASE_SUITE from $DEBIAN_MIRROR"
    local root=.cache/image/rootfs
    rm -rf "$root"
    mkdir -p "$(dirname "$root")"
    debootstrap --variant=minbase "$BASE_SUITE" "$root" "$DEBIAN_MIRROR" >&2
    # What a slim image leaves out: the package lists and caches, documentation.
    rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/var/cache/apt/archives/*.deb \
        "$root"/usr/share/doc/* "$root"/usr/share/man/*
    tar -C "$root" -c . | ce import --change 'CMD ["/bin/bash"]' - "$BASE_LOCAL_IMAGE" >&2
    rm -rf "$root"
    echo "$BASE_LOCAL_IMAGE"
}

context() {
    for f in "$SERVER_BIN" "$CLI_BIN" "$LOAD_BIN"; do
        [ -x "$f" ] || die "$f is missing: make image builds it (cargo build --release, make setup-demo)"
    done
    [ -d "${HOLOFACE_DOWNLOADS:-.cache/downloads}" ] || die "no downloads folder: make setup-demo fills it"
    rm -rf "$CONTEXT"
    mkdir -p "$CONTEXT/downloads"
    cp "$SERVER_BIN" "$CLI_BIN" deploy/server.container.toml "$CONTEXT/"
    cp "${HOLOFACE_DOWNLOADS:-.cache/downloads}"/* "$CONTEXT/downloads/"
    say "context: $(du -sh "$CONTEXT" | cut -f1) in $CONTEXT"
}

build() {
    local from
    from=$(base)
    context
    local t0=$SECONDS
    # --format docker keeps HEALTHCHECK (podman's default OCI format has no health check).
    local fmt=()
    [ "$ENGINE" = podman ] && fmt=(--format docker)
    ce build "${fmt[@]}" --network host --build-arg "RUNTIME_IMAGE=$from" -f deploy/Dockerfile \
        -t "$IMAGE:$IMAGE_TAG" "$CONTEXT"
    local size
    size=$(ce image inspect --format '{{.Size}}' "$IMAGE:$IMAGE_TAG")
    say "built $IMAGE:$IMAGE_TAG on $from in $((SECONDS - t0)) s: $((size / 1000000)) MB"
}

# ---- the smoke test ------------------------------------------------------------------------------------
HEALTH_WITHIN_S=10
LOAD_S=${LOAD_S:-20}
SLO_P99_MS=${SLO_P99_MS:-50}
SLO_ANSWERED=0.99
# "N of M answered, D dropped, U unanswered, p50 / p99 ms" from a holoface-load report.
summary() {
    "${PY:-python3}" -c 'import json, sys
t = json.load(open(sys.argv[1]))["totals"]
lat = t["latency_ms"]
print("%d of %d answered, %d dropped, %d unanswered, p50 %.1f ms, p99 %.1f ms" % (t["answered"], t["sent"],
      sum(t["dropped"].values()), t["unanswered"], lat["p50"], lat["p99"]))' "$1"
}
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

smoke() {
    ce image inspect "$IMAGE:$IMAGE_TAG" >/dev/null 2>&1 || die "no image $IMAGE:$IMAGE_TAG: make image"
    command -v openssl >/dev/null || die "openssl is needed for the test certificate"
    mkdir -p "$OUT"
    local work name port mport token fp
    work=$(mktemp -d)
    name=holoface-smoke-$$
    port=$(free_port)
    mport=$(free_port)
    token=smoke-$RANDOM$RANDOM
    # The mounted secrets as an operator provides them: certificate, key, tokens.
    openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes -days 1 -subj /CN=localhost \
        -addext subjectAltName=DNS:localhost -keyout "$work/tls.key" -out "$work/tls.crt" 2>/dev/null
    echo "$token" >"$work/tokens"
    chmod 0755 "$work" && chmod 0644 "$work"/*
    fp=$(openssl x509 -in "$work/tls.crt" -outform DER | sha256sum | cut -d' ' -f1)
    # shellcheck disable=SC2064
    trap "$ENGINE rm -f $name >/dev/null 2>&1 || true; rm -rf $work" EXIT

    # A recorded stream: the demo's sample photograph, 30 frames panning across it, through the tracker.
    mkdir -p "$work/frames"
    "${PY:-python3}" - "$work/frames" <<'EOF'
import sys
from PIL import Image
photo = Image.open(".cache/holoface/astronaut.png").convert("L")
for k in range(30):
    photo.crop((k * 2, k, k * 2 + 448, k + 448)).save(f"{sys.argv[1]}/{k:03}.png")
EOF
    # The tracker that makes the crops needs the data folder and CANDIDE-3 (make exports both).
    HOLOFACE_HOME=${HOLOFACE_HOME:-$PWD/.cache/holoface} \
        HOLOFACE_CANDIDE=${HOLOFACE_CANDIDE:-${HOLOFACE_DATA:-../shared/data}/candide3/candide3.wfm} \
        "$CLI_BIN" --log warn record --source "$work/frames" --crops jpeg:75 --out "$work/stream.hfrec"

    local t0
    t0=$(date +%s.%N)
    ce run -d --name "$name" --network host -v "$work:/etc/holoface/secrets:ro" \
        -e HOLOFACE_LISTEN="127.0.0.1:$port" -e HOLOFACE_METRICS_LISTEN="127.0.0.1:$mport" \
        "$IMAGE:$IMAGE_TAG" >/dev/null
    local healthy=""
    for _ in $(seq 1 $((HEALTH_WITHIN_S * 10))); do
        if curl -fsS -o /dev/null "http://127.0.0.1:$mport/health" 2>/dev/null; then
            healthy=$(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }')
            break
        fi
        sleep 0.1
    done
    [ -n "$healthy" ] || {
        ce logs "$name" >&2
        die "FAIL: /health did not answer within $HEALTH_WITHIN_S s"
    }
    say "PASS /health answered within ${healthy} s of the start (bound $HEALTH_WITHIN_S s)"
    if [ "$ENGINE" = podman ]; then
        ce healthcheck run "$name" || die "FAIL: the image's HEALTHCHECK failed inside the container"
        say "PASS the image's HEALTHCHECK passes inside the container"
    fi
    local uid
    uid=$(ce exec "$name" id -u)
    [ "$uid" = 10001 ] || die "FAIL: the server runs as uid $uid, not the image's unprivileged 10001"
    say "PASS the server runs as uid 10001 (not root)"
    local banner
    banner=$(ce logs "$name" 2>/dev/null | grep -m1 '^holoface-server on') || die "FAIL: no start-up line in the log"
    grep -q "certificate-sha256 $fp" <<<"$banner" || die "FAIL: the server's fingerprint ($banner) is not the mounted certificate's ($fp)"
    say "PASS the server serves the mounted certificate: $banner"

    # Strangers refused, from outside the container.
    local refused
    if refused=$("$LOAD_BIN" --server "127.0.0.1:$port" --fingerprint "$fp" --token "not-$token" \
        --recording "$work/stream.hfrec" --clients 1 --duration-s 2 --warmup-s 0 --out "$work/x.json" \
        --plot "$work/x.png" 2>&1); then
        die "FAIL: a wrong token was served"
    fi
    grep -qiE "unauthori|token rejected" <<<"$refused" || die "FAIL: a wrong token was refused without saying why: $refused"
    say "PASS a wrong token is refused: $(grep -iE -m1 "unauthori|token rejected" <<<"$refused")"
    local other_fp
    other_fp=$(printf '%064d' 0)
    if refused=$("$LOAD_BIN" --server "127.0.0.1:$port" --fingerprint "$other_fp" --token "$token" \
        --recording "$work/stream.hfrec" --clients 1 --duration-s 2 --warmup-s 0 --out "$work/x.json" \
        --plot "$work/x.png" 2>&1); then
        die "FAIL: a server with another certificate was accepted"
    fi
    grep -qi "fingerprint\|certificate" <<<"$refused" || die "FAIL: a wrong fingerprint failed without saying why: $refused"
    say "PASS a wrong fingerprint is refused: $(grep -i -m1 'fingerprint\|certificate' <<<"$refused")"

    # The load replay with its SLOs.
    "$LOAD_BIN" --server "127.0.0.1:$port" --fingerprint "$fp" --token "$token" --recording "$work/stream.hfrec" \
        --clients 2 --fps 30 --duration-s "$LOAD_S" --warmup-s 2 --interval-s 5 --deadline-ms 100 \
        --min-answered "$SLO_ANSWERED" --max-p99-ms "$SLO_P99_MS" --out "$OUT/load.json" --plot "$OUT/load.png" \
        || die "FAIL: the load replay missed its SLOs (answered >= $SLO_ANSWERED, p99 <= $SLO_P99_MS ms): $OUT/load.json"
    say "PASS load replay: $(summary "$OUT/load.json")"

    # The series the autoscaler and the alerts use.
    curl -fsS "http://127.0.0.1:$mport/metrics" >"$OUT/metrics.txt" || die "FAIL: /metrics did not answer"
    local series missing=()
    mapfile -t series < <(grep -ohE 'holoface_[a-z_]+' deploy/prometheus/alerts.yml deploy/k8s/hpa.yaml \
        deploy/k8s/prometheus-adapter-rules.yaml | sed -E 's/_(bucket|sum|count)$//' | sort -u)
    for s in "${series[@]}"; do
        grep -qE "^${s}(_bucket|_sum|_count)?[{ ]" "$OUT/metrics.txt" || missing+=("$s")
    done
    [ ${#missing[@]} -eq 0 ] || die "FAIL: /metrics lacks ${missing[*]}"
    say "PASS /metrics has the ${#series[@]} series the HPA and the alerts name: ${series[*]}"

    # SIGTERM during a load: every frame in flight answered or explicitly dropped, exit 0 within the timeout.
    local timeout_ms
    timeout_ms=$(sed -n 's/^shutdown_timeout_ms = \([0-9]*\)/\1/p' deploy/server.container.toml)
    "$LOAD_BIN" --server "127.0.0.1:$port" --fingerprint "$fp" --token "$token" --recording "$work/stream.hfrec" \
        --clients 2 --fps 30 --duration-s 8 --warmup-s 0 --interval-s 1 --deadline-ms 100 --min-answered 0 \
        --out "$OUT/drain.json" --plot "$OUT/drain.png" >"$OUT/drain.txt" 2>&1 &
    local load_pid=$!
    sleep 3
    local t1=$SECONDS
    ce stop -t $((timeout_ms / 1000 + 10)) "$name" >/dev/null
    local took=$((SECONDS - t1)) code
    wait "$load_pid" || true
    code=$(ce inspect --format '{{.State.ExitCode}}' "$name")
    ce logs "$name" >"$OUT/server.log" 2>&1
    [ "$code" = 0 ] || die "FAIL: the server exited $code on SIGTERM ($OUT/server.log)"
    [ "$took" -le $((timeout_ms / 1000 + 1)) ] || die "FAIL: stopping took $took s, shutdown timeout ${timeout_ms} ms"
    grep -q "shutdown complete" "$OUT/server.log" || die "FAIL: no 'shutdown complete' in the log ($OUT/server.log)"
    # The only warnings allowed are the refusals of the wrong token above.
    if grep -E ' (ERROR|WARN) ' "$OUT/server.log" | grep -v 'detail=token rejected' >"$work/unexpected"; then
        die "FAIL: warnings or errors in the log: $(head -3 "$work/unexpected")"
    fi
    local unanswered
    unanswered=$("${PY:-python3}" -c 'import json,sys; print(json.load(open(sys.argv[1]))["totals"]["unanswered"])' "$OUT/drain.json")
    [ "$unanswered" = 0 ] || die "FAIL: $unanswered frames went unanswered across the SIGTERM ($OUT/drain.json)"
    say "PASS SIGTERM during a load: exit 0 in ${took} s (timeout ${timeout_ms} ms); $(summary "$OUT/drain.json"); 'shutdown complete' logged"
    say "smoke test passed; reports in $OUT/"
}

case "${1:-}" in
base) base ;;
context) context ;;
build) build ;;
test) smoke ;;
*)
    echo "usage: deploy/image.sh base|context|build|test" >&2
    exit 2
    ;;
esac
