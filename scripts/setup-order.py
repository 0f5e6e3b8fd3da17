#!/usr/bin/env python3
"""Fails when a make target would run a step before the set-up step that step needs, on a bare machine.

A bare machine has none of what the Makefile installs (apt packages, the venv and its packages, the data folder
`holoface setup` fills, the fetched files). So each target is dry-run as if nothing were there: `make -n -B
TARGET` prints every recipe line the target would run, in order, including each set-up step's own install
commands (which a real run skips when the thing is already present). The lines are then read in order: a line
that *provides* something (an `apt-get install` of the FFmpeg headers, `python -m venv`, `holoface setup`, ...)
marks it present; a line that *needs* something (clippy compiling the CLI with FFmpeg, the venv's python,
nextest reading the data folder, ...) must come after its provider. This is how `make test` failed on a bare
machine until 2026-12-05: `check` ran clippy over the workspace (FFmpeg's bindings) before `unit` reached
`video-deps`, and every CI machine had the packages already.

    scripts/setup-order.py [TARGET ...]    # default: every phase of `make test` alone, `test`, and the README's targets

Each phase of `make test` is also checked alone (`make test-timings` runs them one by one, and a developer runs
one phase by hand). No compilation, no network: `make -n` only.
"""

import os
import re
import subprocess
import sys

# What each set-up step provides: a regex over one dry-run line -> the things it makes present.
PROVIDERS = [
    (r"apt-get install .*libavcodec-dev=", {"ffmpeg-dev"}),
    (r"apt-get install .*libclang-dev=", {"libclang"}),
    (r"apt-get install .*\bffmpeg=", {"ffmpeg-cli"}),
    (r"mono-mcs=.*apt-get install|apt-get install .*mono-mcs=", {"mono"}),
    (r"-m venv \.venv\b", {"venv"}),
    (r"pip install .*-r models/dan/requirements-eval\.txt", {"py-eval"}),
    (r"pip install .*-r models/dan/requirements-peer\.txt", {"py-peer"}),
    (r"pip install .*-r models/dan/requirements\.txt", {"py-train"}),
    (r"pip install .*-r python/requirements-dev\.txt", {"py-dev"}),
    (r"pip install .*-r deploy/requirements-validate\.txt", {"py-deploy"}),
    (r"\bholoface setup\b", {"home"}),
    (r"pip download .*onnxruntime-gpu==", {"ort-gpu"}),
    (r"to_fp16\.py", {"dan-fp16"}),
    (r"golden_crops\.py", {"golden"}),
    (r"rustface-\S*\.crate", {"group-photo"}),
    (r"apt-get install .*\bpodman=", {"container-tools"}),
    (r"apt-get install .*\bcargo-web=.*\bqemu-user=", {"arm64-toolchain"}),
    (r"\bholoface setup --arch aarch64\b", {"home-arm64"}),
]

# Commands that compile the `holoface` CLI (holoface-tools) with its default features, which bind the system's
# FFmpeg libraries through bindgen (libclang).
CARGO_COMPILE = re.compile(r"\bcargo (?:\+\S+ )?(clippy|doc|build|run|test|nextest run|bench|check|install)\b")


def compiles_ffmpeg(line: str) -> bool:
    m = CARGO_COMPILE.search(line)
    if not m or "--no-default-features" in line:
        return False
    if line.lstrip().startswith("cd fuzz"):
        return False  # the fuzz crate depends on protocol and models only
    return "--workspace" in line or "-p holoface-tools" in line or "--path tools" in line


# What each kind of line needs: a predicate over one dry-run line -> the things that must already be present.
CONSUMERS = [
    (compiles_ffmpeg, {"ffmpeg-dev", "libclang"}, "compiles holoface-tools with FFmpeg"),
    (lambda l: re.search(r"(^|\s)\.venv/bin/python\b", l) is not None and "-m pip" not in l, {"venv", "py-eval"},
     "runs the venv's python"),
    (lambda l: re.search(r"(^|\s)\.venv/bin/python -m pip\b", l) is not None, {"venv"}, "installs into the venv"),
    (lambda l: "peer_dlib.py" in l or "dlib_teacher.py" in l or "peer_video_dlib.py" in l or "speed_vs_dlib.py" in l,
     {"py-peer"}, "runs dlib"),
    (lambda l: "models/dan/train.py" in l or "export_onnx.py" in l, {"py-train"}, "trains or exports DAN"),
    (lambda l: ".venv/bin/maturin" in l or "-m pytest" in l, {"py-dev"}, "builds or tests the wheel"),
    (lambda l: "deploy/validate.sh" in l, {"py-deploy"}, "validates deploy/"),
    (lambda l: re.search(r"\bnextest run\b", l) is not None,
     {"home", "ort-gpu", "dan-fp16", "golden", "group-photo", "ffmpeg-cli"}, "runs the tests"),
    (lambda l: re.search(r"\bcargo test\b.*--doc", l) is not None, {"home"}, "runs the doc tests"),
    (lambda l: re.search(r"target/[a-z]+/holoface (?!setup)\S", l) is not None, {"home"}, "runs holoface"),
    (lambda l: "target/c-example/track " in l or "target/debug/examples/embed " in l, {"home"}, "runs the C/Rust examples"),
    (lambda l: re.search(r"(^|\s)mcs ", l) is not None, {"mono"}, "compiles C#"),
    (lambda l: re.search(r"(^|\s)mono [^-]", l) is not None, {"mono", "home"}, "runs C#"),
    (lambda l: "-m pytest" in l, {"home"}, "runs pytest"),
    (lambda l: re.search(r"(^|[|;&]\s*)ffmpeg -", l) is not None, {"ffmpeg-cli"}, "runs ffmpeg"),
    (lambda l: "deploy/image.sh build" in l, {"container-tools", "home"}, "builds the container image"),
    (lambda l: "deploy/image.sh test" in l, {"container-tools", "home", "venv", "py-eval"}, "smoke-tests the image"),
    # The aarch64 build (make arm64, arm64-build, arm64-test): Debian's cargo, the cross gcc, qemu. Building with
    # the test profile (`--profile test`) runs nothing; `cargo test` does.
    (lambda l: re.search(r"(^|\s)(/usr/bin/cargo|aarch64-linux-gnu-gcc|qemu-aarch64) ", l) is not None,
     {"arm64-toolchain"}, "uses the aarch64 cross toolchain"),
    (lambda l: re.search(r"(^|\s)qemu-aarch64 [^-\s]|--target aarch64\S* .*(?<!--profile )\btest\b|(?<!--profile )\btest\b.*--target aarch64|arm64-link\.sh", l)
     is not None, {"home-arm64", "home"}, "runs aarch64 binaries"),
    (lambda l: "examples/detector_krfws " in l, {"home"}, "runs the accuracy example"),
]


def dry_run(target: str) -> list[str]:
    env = dict(os.environ, MAKEFLAGS="", MFLAGS="")
    out = subprocess.run(
        ["make", "-n", "-B", "--no-print-directory", target],
        capture_output=True, text=True, env=env, check=False,
    )
    if out.returncode != 0:
        sys.exit(f"make -n -B {target} failed:\n{out.stderr}")
    lines = out.stdout.replace("\\\n", " ").splitlines()  # a command continued with backslashes is one line
    if not lines or "Nothing to be done" in out.stdout:
        sys.exit(f"make -n -B {target} runs nothing: is the target missing?")
    return lines


def check(target: str) -> list[str]:
    present: set[str] = set()
    problems = []
    for n, line in enumerate(dry_run(target), 1):
        gives = set().union(*(g for pattern, g in PROVIDERS if re.search(pattern, line)))
        # An install line may look for what it installs (`test -x .venv/bin/python || python3 -m venv .venv`,
        # `command -v mcs || apt-get install mono-mcs`): that is not a use.
        probe = re.sub(r"(test -x|command -v) \S+", "", line)
        for pred, needs, what in CONSUMERS:
            if pred(probe):
                missing = sorted(needs - present - gives)
                if missing:
                    problems.append(f"make {target}: line {n} {what} before {', '.join(missing)} is set up:\n    "
                                    + line.strip()[:160])
        present |= gives
    return problems


def main() -> int:
    phases = subprocess.run(["make", "-s", "--no-print-directory", "print-TEST_PHASES"], capture_output=True,
                            text=True, check=True).stdout.split()
    targets = sys.argv[1:] or [p for p in phases if p != "setup-order"] + [
        "test", "demo", "setup", "setup-demo", "compare", "stability", "speed-vs-dlib", "bench", "wheel",
        "train-refiner", "train-krfws", "train-blendshapes", "train-dan", "export-dan", "teacher-eval", "dan-int8",
        "image", "image-test",
    ]
    problems = [p for t in targets for p in check(t)]
    for p in problems:
        print(p, file=sys.stderr)
    if problems:
        print(f"{len(problems)} step(s) run before the set-up they need (scripts/setup-order.py)", file=sys.stderr)
        return 1
    print(f"setup-order: {len(targets)} targets dry-run as on a bare machine; every step after its set-up")
    return 0


if __name__ == "__main__":
    sys.exit(main())
