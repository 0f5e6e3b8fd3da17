#!/usr/bin/env bash
# Fails when maturin's build of the Python wheel (holoface-python with extension-module + ci-unify, which adds workspace-hack/) would give
# a shared dependency other features than the workspace's test build does: then the wheel would compile those
# dependencies (and everything above them) a second time (docs/experiments/build-time.md). No compilation:
# `cargo tree` only.
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
feat() {
    local name=$1
    shift
    cargo tree --locked "$@" -f '{p}|{f}' --prefix none | sed 's/ (\*)//;s/ (proc-macro)//' | sort -u >"$tmp/$name"
    [ -s "$tmp/$name" ] || { echo "cargo tree gave nothing for $name" >&2; exit 1; }
}
feat ws -e normal,build,dev --workspace --features holoface-python/extension-module
feat py -e normal,build -p holoface-python --features extension-module,ci-unify
python3 - "$tmp/ws" "$tmp/py" <<'PY'
import sys
def load(path):
    d = {}
    for line in open(path):
        pkg, _, feats = line.rstrip("\n").partition("|")
        d.setdefault(pkg, []).append(frozenset(f for f in feats.split(",") if f))
    return d
ws, py = load(sys.argv[1]), load(sys.argv[2])
# holoface-python itself differs by design; syn 2 appears as a target unit only through cbindgen (a build tool).
# A package is reused when every feature set the wheel builds it with is one the test build has built (a
# build-dependency such as bindgen's regex can sit beside the same package built for the target with others).
# holoface-sources is the exception: the wheel never reads video through the system's FFmpeg (the `ffmpeg`
# feature, on in the test build through the CLI), so it compiles that small crate (and itself) once more.
for p in ws:
    if p.startswith("holoface-sources "):
        ws[p] = [f - {"ffmpeg", "dep:ffmpeg-next"} for f in ws[p]]
bad = [p for p in py if p in ws and not set(py[p]) <= set(ws[p])
       and not p.startswith("holoface-python") and not p.startswith("syn v2")]
if bad:
    print("the wheel's build resolves these dependencies with other features than the test build:", *bad, sep="\n  ")
    print("update workspace-hack/Cargo.toml")
    sys.exit(1)
print("holoface-python (ci-unify): the same dependency features as the test build")
PY
