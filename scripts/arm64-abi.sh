#!/usr/bin/env bash
# The aarch64 build is what it says and exports what the x86-64 one does (make arm64-test, make arm64):
# `file` names ARM aarch64 for the C ABI's library and each binary given, and the C symbols libholoface.so
# exports (hf_*) are the same on both architectures.
#
#   scripts/arm64-abi.sh X86_64_LIBHOLOFACE AARCH64_LIBHOLOFACE [AARCH64_BINARY ...]
set -euo pipefail
x86=$1 arm=$2
shift 2
for f in "$arm" "$@"; do
    desc=$(file -bL "$f")
    case "$desc" in
        *"ARM aarch64"*) echo "arm64-abi: $f: ${desc%%,*}, ARM aarch64" ;;
        *) echo "arm64-abi: $f is not an aarch64 binary: $desc" >&2; exit 1 ;;
    esac
done
# The hf_* functions a library exports, read with the given nm.
symbols() { "$1" -D --defined-only "$2" | awk '$2 == "T" && $3 ~ /^hf_/ { print $3 }' | sort; }
diff <(symbols nm "$x86") <(symbols aarch64-linux-gnu-nm "$arm") \
    || { echo "arm64-abi: the two libraries export different C symbols (< x86-64, > aarch64)" >&2; exit 1; }
echo "arm64-abi: both libraries export the same $(symbols nm "$x86" | wc -l) C symbols;" \
    "libholoface.so is $(stat -c %s "$x86") bytes on x86-64, $(stat -c %s "$arm") on aarch64 (this build's profile)"
