# LeanGate — the two commands a newcomer needs are `make demo` and `make test`; both install
# what they need first (scripts/setup.sh: apt packages, ONNX Runtime, a Python venv).

CARGO ?= cargo
PLUGIN_DIR := $(CURDIR)/target/release
DEMO_DIR ?= out/demo
# `make install`: where (default ~/.local; `PREFIX=/usr/local` as root), and where to link the
# plugin so GStreamer finds it with no variables set (see scripts/install.sh; empty: no link).
PREFIX ?= $(HOME)/.local
GST_LINK_DIR ?= auto

.PHONY: all setup build release fixtures test lint bench demo inspect install uninstall clean

all: build

setup:
	bash scripts/setup.sh

build: setup
	$(CARGO) build --workspace

release: setup
	$(CARGO) build --workspace --release

# Regenerate the ONNX fixture models the tests use (deterministic).
fixtures: setup
	.venv/bin/python tests/fixtures/make_fixtures.py tests/fixtures

# Everything: unit tests, element harness tests, pipeline tests on real clips (skipped when
# ../shared is absent), the Python appsink client, the CLI end to end. `cargo build` first: the
# gst-launch and Python tests load the cdylib target/debug/libgstleangate.so, which `cargo test`
# alone does not rebuild.
test: setup fixtures lint
	$(CARGO) build --workspace --all-targets
	$(CARGO) test --workspace --lib --bins --tests --no-fail-fast

# Formatting and lints, as CI checks them (part of `make test`).
lint: setup
	$(CARGO) fmt --all --check
	$(CARGO) clippy --workspace --all-targets -- -D warnings

bench: release
	$(CARGO) bench --workspace

# The one prepared GPU check (scripts/gpu-check.sh): installs the GPU ONNX Runtime, builds, runs the
# GPU tests and benchmarks within 470 s, writes one figures file (GPU_FIGURES; default
# $OUT/gpu-figures.md or out/gpu-figures.md). Exits 2 at once, saying so, without a GPU.
GPU_FIGURES ?=
.PHONY: gpu-check gpu-bundle
gpu-check:
	bash scripts/gpu-check.sh $(GPU_FIGURES)

# What gpu-check needs on a lent machine without Rust, GStreamer or network (docs/element.md, "The
# GPU check on a lent machine"): the release builds, the GPU ONNX Runtime (CUDA kernels for sm_90)
# and a minimal GStreamer, packed into .gpu-bundle/1..K, one part per call.
gpu-bundle: setup
	bash scripts/gpu-bundle.sh

# The main job: gate a synthetic flythrough (pauses and bursts) with the element in a real
# pipeline, print frames in/kept, write the eval plot and a contact sheet of the kept frames.
demo: release
	bash scripts/demo.sh $(DEMO_DIR)

# gst-inspect-1.0 documentation of the element.
inspect: release
	GST_PLUGIN_PATH=$(PLUGIN_DIR) gst-inspect-1.0 leangate

# The plugin, ONNX Runtime beside it, the `leangate` CLI and leangate-client, under $(PREFIX).
# Only copies what `make release` built (no cargo, no setup): `make release && sudo make install
# PREFIX=/usr/local` works although root has no Rust toolchain. Writes a manifest that `make
# uninstall` follows (scripts/install.sh).
# $(call shell_word,VAR): VAR as one shell word, exactly as given (spaces, quotes and $ kept): a
# value from the command line or the environment unexpanded, single-quoted, each ' as '\''.
shell_word = '$(subst ','\'',$(if $(filter command line environment,$(origin $(1))),$(value $(1)),$($(1))))'
install:
	PREFIX=$(call shell_word,PREFIX) GST_LINK_DIR=$(call shell_word,GST_LINK_DIR) bash scripts/install.sh

uninstall:
	PREFIX=$(call shell_word,PREFIX) GST_LINK_DIR=$(call shell_word,GST_LINK_DIR) bash scripts/install.sh --uninstall

clean:
	$(CARGO) clean
	rm -rf out
