#!/usr/bin/env bash
# The one prepared GPU check (issue 35): on a machine with an NVIDIA GPU, install the GPU ONNX
# Runtime, build, and run the GPU tests and benchmarks in one go, within a time budget (default
# 470 s), writing one figures file:
#
#   bash scripts/gpu-check.sh [FIGURES]          # or: make gpu-check [GPU_FIGURES=...]
#
# FIGURES: default $OUT/gpu-figures.md when $OUT is set (a lent machine's output folder), else
# out/gpu-figures.md. The raw output of every step goes to the same name with .log for .md.
#
# Two ways to get what it runs:
#   built here   (a machine with network access and Rust): setup installs, build builds;
#   from a bundle (a lent machine: no network, no Rust, no GStreamer): scripts/gpu-bundle.sh, run
#                where cargo and the network are, packs the builds, the GPU ONNX Runtime and a
#                minimal GStreamer into .gpu-bundle/1..K; each part travels in one call (`carry`),
#                and this script unpacks them when it finds .gpu-bundle/ (GPU_CHECK_BUNDLE=0: never).
#
# Steps (each under `timeout`, each one's pass/fail/skip written to FIGURES as soon as it ends):
#   gpu        nvidia-smi answers (else: exit 2 at once, FIGURES says "no GPU")
#   prereqs    cargo and python3 are there (else: fail at once, nothing else can run); from a
#              bundle, python3 only
#   setup      ORT_FLAVOR=gpu scripts/setup.sh: onnxruntime-gpu==1.31.1 into .deps/onnxruntime-gpu,
#              GStreamer's development files, .venv-triton (PyTriton) for the remote path; from a
#              bundle: scripts/gpu-bundle.sh --unpack (all parts there, checksum, unpacked)
#   cuda-libs  the libraries ONNX Runtime's CUDA and TensorRT providers load (cuBLAS, cuDNN,
#              cudart, cuRAND; TensorRT 10), looked up in CUDA's folders and in the nvidia-*
#              Python packages of python3; missing ones pip-installed into .deps/cuda-py
#              (TensorRT into .deps/trt-py, when NVIDIA's index is reachable: see pip_libs)
#   build      cargo build (release): the plugin, benches/models.rs, benches/remote.rs,
#              tests/scorer.rs and tests/gpu_check.rs; from a bundle, the bundle's builds of
#              them (and, where the machine has no GStreamer, the bundle's)
#   tests      tests/gpu_check.rs and tests/scorer.rs on the GPU ONNX Runtime
#              (LEANGATE_EXPECT_CUDA=1: CUDA must work; LEANGATE_EXPECT_TENSORRT=1 when TensorRT's
#              libraries are there)
#   scoring    benches/models.rs `providers`: the embedded student on cpu, cuda (and tensorrt),
#              FP32 and INT8 builds, 1 stream and 8/32 streams, unbatched and batched, and the
#              largest utility difference from the CPU provider
#   element    gst-launch-1.0 at 1920x1080: identity, leangate on cpu, cuda (and tensorrt), and
#              8 streams in one pipeline (identity vs cuda with a shared, batched session)
#   remote     benches/remote.rs against a local Triton (PyTriton) server, when .venv-triton works
#              (optional: a failure is a warning)
#
# Exit status: 0 every required step passed, 1 a required step failed (or had no time left),
# 2 no GPU. Environment: GPU_CHECK_BUDGET_S (470), GPU_CHECK_TOLERANCE (largest utility
# difference from the CPU for a pass, 0.02), GPU_CHECK_FRAMES (1080p frames per stream, 300),
# GPU_CHECK_PROFILE (cargo profile, release), GPU_CHECK_SKIP_SETUP=1 (use what is there),
# GPU_CHECK_PIP=0 (never pip-install CUDA/TensorRT libraries), LEANGATE_GPU_ORT (a GPU
# libonnxruntime.so to use instead of .deps/onnxruntime-gpu), LEANGATE_NVIDIA_SMI (the nvidia-smi
# to ask; tests/gpu_check.rs points it at nothing to check the no-GPU path on a GPU machine).
# shellcheck disable=SC2317 # functions run through run_step (a child bash under `timeout`)
set -uo pipefail

START=$(date +%s)
BUDGET=${GPU_CHECK_BUDGET_S:-470}
TOL=${GPU_CHECK_TOLERANCE:-0.02}
FRAMES=${GPU_CHECK_FRAMES:-300}
PROFILE=${GPU_CHECK_PROFILE:-release}
SMI=${LEANGATE_NVIDIA_SMI:-nvidia-smi}
ORT_VERSION=1.31.1

FIGURES=${1:-}
if [ -z "$FIGURES" ]; then
  if [ -n "${OUT:-}" ]; then FIGURES=$OUT/gpu-figures.md; else FIGURES=out/gpu-figures.md; fi
fi
case $FIGURES in /*) ;; *) FIGURES=$PWD/$FIGURES ;; esac
cd "$(dirname "$0")/.." || exit 1
ROOT=$PWD
LOG=${FIGURES%.md}.log
[ "$LOG" != "$FIGURES" ] || LOG=$FIGURES.log
mkdir -p "$(dirname "$FIGURES")" || { echo "gpu-check: cannot create $(dirname "$FIGURES")" >&2; exit 1; }
TMPD=$(mktemp -d "${TMPDIR:-/tmp}/gpu-check.XXXXXX") || exit 1
trap 'rm -rf "$TMPD"' EXIT
export ROOT TMPD # for the functions run_step runs in a child bash
STEP_PID=""
on_signal() { # an interrupt: end the running step, say so, exit 130
  [ -z "$STEP_PID" ] || kill -TERM -- "-$STEP_PID" 2>/dev/null
  trap - INT TERM
  record interrupted fail "$(elapsed)" "SIG$1: the check was stopped here" >/dev/null
  echo "gpu-check: interrupted ($1) after $(elapsed) s; figures so far in $FIGURES" >&2
  exit 130
}
trap 'on_signal INT' INT
trap 'on_signal TERM' TERM
: >"$LOG"

COMMIT=$(git rev-parse --short HEAD 2>/dev/null || echo unknown)
[ -z "$(git status --porcelain --untracked-files=no 2>/dev/null)" ] || COMMIT="$COMMIT (with local changes)"
HOST_LINE="$(hostname 2>/dev/null || echo '?'), $(nproc 2>/dev/null || echo '?') CPU cores"
GPU_LINE="(not probed)"
ORT_LINE="(not found yet)"
LIBS_LINE="(not looked up yet)"

# Steps: name, status (pass, fail, warn, skip), seconds, note. Sections: files in $TMPD/sections.
NAMES=() STATUS=() SECS=() NOTES=()
mkdir -p "$TMPD/sections"
REQUIRED_FAILED=0

elapsed() { echo $(($(date +%s) - START)); }
left() { echo $((BUDGET - $(elapsed))); }
# One line for a table cell: no newlines or bars, ONNX Runtime's source location left out.
one_line() {
  tr '\n|' ' /' | sed 's/  */ /g; s/^ //; s/ $//; s#/onnxruntime_src/[^[]*\[ONNXRuntimeError\] : [0-9]* : [A-Z_]* : ##g' |
    cut -c1-400
}

write_figures() {
  local f=$TMPD/figures.md i
  {
    echo "# LeanGate GPU check"
    echo
    echo "- when: $(date -u '+%Y-%m-%d %H:%M UTC'), $(elapsed) s into the check (budget $BUDGET s)"
    echo "- commit: $COMMIT"
    echo "- machine: $HOST_LINE"
    echo "- GPU: $GPU_LINE"
    echo "- ONNX Runtime: $ORT_LINE"
    echo "- CUDA/TensorRT libraries: $LIBS_LINE"
    echo "- raw output of every step: $LOG"
    echo
    echo "## Steps"
    echo
    echo "| step | status | seconds | note |"
    echo "|---|---|---|---|"
    for i in "${!NAMES[@]}"; do
      echo "| ${NAMES[$i]} | ${STATUS[$i]} | ${SECS[$i]} | ${NOTES[$i]} |"
    done
    local s
    for s in "$TMPD"/sections/*.md; do
      [ -f "$s" ] || continue
      echo
      cat "$s"
    done
  } >"$f"
  cp "$f" "$FIGURES.tmp" && mv "$FIGURES.tmp" "$FIGURES"
}

# record NAME STATUS SECONDS NOTE [required]
record() {
  NAMES+=("$1") STATUS+=("$2") SECS+=("$3") NOTES+=("$(printf '%s' "$4" | one_line)")
  if [ "${5:-}" = required ] && [ "$2" = fail ]; then REQUIRED_FAILED=1; fi
  echo "gpu-check: [$1] $2 ($3 s)${4:+: $(printf '%s' "$4" | one_line)}"
  write_figures
}

# run_step NAME CAP_S CMD...: the command under `timeout` (at most CAP_S and what is left of the
# budget), stdin from /dev/null, output to $TMPD/NAME.out and the log. Sets RC and DUR; RC 124:
# timed out, 125: no time left (not run).
run_step() {
  local name=$1 cap=$2 t0
  shift 2
  local t
  t=$(left)
  [ "$t" -lt "$cap" ] && cap=$t
  DUR=0
  : >"$TMPD/$name.out"
  if [ "$cap" -lt 5 ]; then RC=125; return; fi
  t0=$(date +%s)
  {
    echo "===== $name (limit ${cap} s): $*"
  } >>"$LOG"
  # In the background, so that an interrupt of this script stops the step too: `timeout` runs
  # it in a process group of its own, which on_signal ends.
  if [ "$(type -t "$1")" = function ]; then
    # A function of this script: in a child bash that has them all (`timeout` runs programs).
    timeout --kill-after=10 "$cap" bash -c "$(declare -f); $(printf '%q ' "$@")" </dev/null \
      >"$TMPD/$name.out" 2>&1 &
  else
    timeout --kill-after=10 "$cap" "$@" </dev/null >"$TMPD/$name.out" 2>&1 &
  fi
  STEP_PID=$!
  wait "$STEP_PID"
  RC=$?
  STEP_PID=""
  DUR=$(($(date +%s) - t0))
  cat "$TMPD/$name.out" >>"$LOG"
  echo "===== $name: exit $RC after $DUR s" >>"$LOG"
}

why_rc() { # why_rc NAME: a note for a failed run_step
  case $RC in
    124 | 137) echo "timed out after $DUR s" ;;
    125) echo "not run: the time budget ($BUDGET s) was spent" ;;
    *) echo "exit $RC: $(grep -v '^\s*$' "$TMPD/$1.out" | tail -n 3 | one_line)" ;;
  esac
}

finish() {
  write_figures
  if [ "$REQUIRED_FAILED" = 1 ]; then
    echo "gpu-check: FAILED (a required step failed; see $FIGURES and $LOG)" >&2
    exit 1
  fi
  echo "gpu-check: done in $(elapsed) s; figures in $FIGURES"
  exit 0
}

# Skip the rest: every step not run yet is recorded as skipped, required ones as failures.
skip_rest() { # skip_rest REASON STEP...
  local why=$1 s
  shift
  for s in "$@"; do
    case $s in
      remote) record "$s" skip 0 "$why" ;;
      *) record "$s" fail 0 "not run: $why" required ;;
    esac
  done
  finish
}

# ---- gpu: a GPU answers, or exit 2 at once -----------------------------------------------------
no_gpu() {
  GPU_LINE="no GPU ($1)"
  record gpu skip "$(elapsed)" "no GPU: $1; nothing was measured"
  echo "gpu-check: no GPU: $1; nothing measured (figures: $FIGURES)" >&2
  exit 2
}
exec 3>&1 1>>"$LOG" # progress lines go to the log until the GPU is known (the no-GPU path prints one line)
if ! command -v "$SMI" >/dev/null 2>&1; then
  no_gpu "$SMI not found"
fi
if ! gpu=$(timeout 10 "$SMI" --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1) ||
  [ -z "$gpu" ]; then
  no_gpu "$SMI failed: $(printf '%s' "$gpu" | one_line)"
fi
exec 1>&3 3>&-
if [ -n "${GPU_CHECK_ACTIVE:-}" ]; then
  # Run from a test of an outer check (tests/gpu_check.rs points it at no nvidia-smi, so this
  # only happens when that is overridden): never recurse.
  echo "gpu-check: already running (pid $GPU_CHECK_ACTIVE); a nested run stops here" >&2
  exit 1
fi
export GPU_CHECK_ACTIVE=$$
GPU_LINE=$(printf '%s' "$gpu" | head -n 1 | one_line)
record gpu pass "$(elapsed)" "$GPU_LINE"
echo "===== nvidia-smi" >>"$LOG"
timeout 10 "$SMI" >>"$LOG" 2>&1

# ---- prereqs ------------------------------------------------------------------------------------
# From a bundle (scripts/gpu-bundle.sh) when its parts are here, or it was unpacked before.
BUNDLED=0
if [ "${GPU_CHECK_BUNDLE:-1}" != 0 ] &&
  { compgen -G "$ROOT/.gpu-bundle/*/index" >/dev/null || [ -f "$ROOT/target/release/gpu-bundle.txt" ]; }; then
  BUNDLED=1
fi
missing=()
needed="cargo python3 timeout"
[ "$BUNDLED" = 1 ] && needed="python3 timeout"
for c in $needed; do command -v "$c" >/dev/null 2>&1 || missing+=("$c"); done
if ((${#missing[@]})); then
  record prereqs fail 0 "not installed: ${missing[*]} (cargo: rustup; the check builds the plugin here, or bring a bundle: scripts/gpu-bundle.sh)" required
  skip_rest "prerequisites missing" setup cuda-libs build tests scoring element remote
fi
if [ "$BUNDLED" = 1 ]; then
  record prereqs pass 0 "from a bundle (.gpu-bundle, scripts/gpu-bundle.sh); $(python3 --version 2>&1 | one_line)"
else
  record prereqs pass 0 "$(cargo --version 2>/dev/null | one_line); $(python3 --version 2>&1 | one_line)"
fi

# ---- setup: the GPU ONNX Runtime and the rest of scripts/setup.sh ---------------------------------
if [ -n "${LEANGATE_GPU_ORT:-}" ]; then
  ORT_LIB=$LEANGATE_GPU_ORT
else
  ORT_LIB=$ROOT/.deps/onnxruntime-gpu/libonnxruntime.so.$ORT_VERSION
fi
if [ "$BUNDLED" = 1 ]; then
  if compgen -G "$ROOT/.gpu-bundle/*/index" >/dev/null; then
    run_step setup 120 bash scripts/gpu-bundle.sh --unpack
    SETUP_NOTE=$(grep -m1 '^gpu-bundle: unpacked' "$TMPD/setup.out" | sed 's/^gpu-bundle: //')
    [ "$RC" = 0 ] || SETUP_NOTE="the bundle: $(why_rc setup)"
  else
    RC=0 DUR=0 SETUP_NOTE="the bundle unpacked before: $(head -n 1 "$ROOT/target/release/gpu-bundle.txt")"
  fi
  if [ "$RC" != 0 ]; then
    record setup fail "$DUR" "$SETUP_NOTE" required
    skip_rest "the bundle could not be unpacked" cuda-libs build tests scoring element remote
  fi
elif [ "${GPU_CHECK_SKIP_SETUP:-0}" = 1 ]; then
  RC=0 DUR=0 SETUP_NOTE="skipped (GPU_CHECK_SKIP_SETUP=1)"
else
  # Quick failures instead of long retries when a registry cannot be reached.
  PIP_TIMEOUT=20 PIP_RETRIES=1 ORT_FLAVOR=gpu run_step setup 200 bash scripts/setup.sh
  SETUP_NOTE="scripts/setup.sh with ORT_FLAVOR=gpu"
  [ "$RC" = 0 ] || SETUP_NOTE=$(why_rc setup)
fi
if [ ! -f "$ORT_LIB" ]; then
  record setup fail "$DUR" "no GPU ONNX Runtime at $ORT_LIB: $SETUP_NOTE" required
  skip_rest "no GPU ONNX Runtime" cuda-libs build tests scoring element remote
fi
ORT_DIR=$(dirname "$ORT_LIB")
ORT_LINE="$ORT_LIB"
if [ "$BUNDLED" = 1 ]; then
  record setup pass "$DUR" "$SETUP_NOTE"
elif [ "${GPU_CHECK_SKIP_SETUP:-0}" = 1 ]; then
  record setup skip 0 "$SETUP_NOTE"
elif [ "$RC" = 0 ]; then
  record setup pass "$DUR" "$SETUP_NOTE"
else
  record setup warn "$DUR" "setup did not finish, but the GPU ONNX Runtime is there: $SETUP_NOTE"
fi

# ---- cuda-libs: what the CUDA and TensorRT providers load ---------------------------------------
lib_dirs() {
  local d py sp
  for d in /usr/local/cuda/lib64 /usr/local/cuda/targets/x86_64-linux/lib /usr/local/nvidia/lib64 \
    /usr/lib/x86_64-linux-gnu/nvidia; do
    [ -d "$d" ] && echo "$d"
  done
  for py in python3 /usr/bin/python3; do
    command -v "$py" >/dev/null 2>&1 || continue
    timeout 10 "$py" -c 'import site; print("\n".join(site.getsitepackages()))' 2>/dev/null
  done | sort -u | while read -r sp; do
    for d in "$sp"/nvidia/*/lib "$sp"/tensorrt_libs; do [ -d "$d" ] && echo "$d"; done
  done
  for d in "$ROOT"/.deps/cuda-py/nvidia/*/lib "$ROOT"/.deps/trt-py/tensorrt_libs; do
    [ -d "$d" ] && echo "$d"
  done
}
# From a bundle on a machine without GStreamer: the bundle's (gst-launch-1.0, two plugins, and
# the libraries they load, as one set: never mixed with a system GStreamer).
GST_RT=$ROOT/.deps/gst-runtime GST_LIB=""
if [ "$BUNDLED" = 1 ] && [ -d "$GST_RT" ] &&
  { [ "${GPU_CHECK_BUNDLED_GST:-0}" = 1 ] || ! command -v gst-launch-1.0 >/dev/null 2>&1; }; then
  GST_LIB=$GST_RT/lib
  export PATH=$GST_RT/bin:$PATH GST_PLUGIN_SYSTEM_PATH_1_0=$GST_RT/plugins
  export GST_PLUGIN_SCANNER_1_0=$GST_RT/libexec/gst-plugin-scanner
fi
set_lib_path() {
  local dirs
  dirs=$(lib_dirs | awk '!seen[$0]++' | paste -sd: -)
  GPU_LD_PATH=$ORT_DIR${GST_LIB:+:$GST_LIB}${dirs:+:$dirs}${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
}
# missing_libs PROVIDER: the libraries the provider's .so cannot find (cuDNN too: it is dlopened).
missing_libs() {
  local so=$ORT_DIR/libonnxruntime_providers_$1.so
  [ -f "$so" ] || { echo "libonnxruntime_providers_$1.so"; return; }
  LD_LIBRARY_PATH=$GPU_LD_PATH ldd "$so" 2>/dev/null | awk '/not found/ {print $1}'
  local dirs
  IFS=: read -ra dirs <<<"$GPU_LD_PATH"
  if ! ldconfig -p 2>/dev/null | grep -q 'libcudnn\.so\.9' &&
    ! find "${dirs[@]}" -maxdepth 1 -name 'libcudnn.so.9*' 2>/dev/null | grep -q .; then
    echo libcudnn.so.9
  fi
}
set_lib_path
cuda_missing=$(missing_libs cuda | sort -u | paste -sd' ' -)
trt_missing=$(missing_libs tensorrt | sort -u | paste -sd' ' -)
# pip_libs "CUDA PACKAGES" "TENSORRT PACKAGE": the CUDA wheels into .deps/cuda-py; TensorRT 10 into
# .deps/trt-py (tensorrt-cu13-libs 10.x is a stub that downloads the wheel from NVIDIA's own index
# when it installs: it fails where only the registry is reachable, and TensorRT is skipped then).
pip_libs() {
  local rc=0
  if [ -n "$1" ]; then
    # shellcheck disable=SC2086 # a list of requirements
    python3 -m pip install -q --disable-pip-version-check --only-binary=:all: \
      --target "$ROOT/.deps/cuda-py" $1 || rc=1
  fi
  if [ -n "$2" ]; then
    python3 -m pip install -q --disable-pip-version-check --target "$ROOT/.deps/trt-py" "$2" ||
      echo "gpu-check: TensorRT could not be installed ($2): its rows are skipped"
  fi
  return "$rc"
}
pip_note="" DUR=0
if [ -n "$cuda_missing$trt_missing" ] && [ "${GPU_CHECK_PIP:-1}" != 0 ]; then
  cuda_pkgs="" trt_pkg=""
  case " $cuda_missing $trt_missing " in *" libcublas"*) cuda_pkgs+=" nvidia-cublas~=13.0" ;; esac
  case " $cuda_missing $trt_missing " in *" libcudart"*) cuda_pkgs+=" nvidia-cuda-runtime~=13.0" ;; esac
  case " $cuda_missing " in *" libcurand"*) cuda_pkgs+=" nvidia-curand~=10.0" ;; esac
  case " $cuda_missing $trt_missing " in *" libcudnn"*) cuda_pkgs+=" nvidia-cudnn-cu13~=9.0" ;; esac
  case " $trt_missing " in *" libnvinfer"* | *" libnvonnxparser"*) trt_pkg="tensorrt-cu13-libs>=10.14,<11" ;; esac
  if [ -n "$cuda_pkgs$trt_pkg" ]; then
    PIP_TIMEOUT=20 PIP_RETRIES=1 run_step cuda-libs 150 pip_libs "${cuda_pkgs# }" "$trt_pkg"
    pip_note=ok
    [ "$RC" = 0 ] || pip_note=$(why_rc cuda-libs)
    grep -q 'TensorRT could not be installed' "$TMPD/cuda-libs.out" && pip_note="$pip_note (TensorRT: failed)"
    pip_note="pip install${cuda_pkgs} ${trt_pkg}: $pip_note; "
    set_lib_path
    cuda_missing=$(missing_libs cuda | sort -u | paste -sd' ' -)
    trt_missing=$(missing_libs tensorrt | sort -u | paste -sd' ' -)
  fi
fi
CUDA_OK=$([ -z "$cuda_missing" ] && echo 1 || echo 0)
TRT_OK=$([ -z "$trt_missing" ] && echo 1 || echo 0)
LIBS_LINE="CUDA provider: $([ "$CUDA_OK" = 1 ] && echo "all found" || echo "missing $cuda_missing"); TensorRT provider: $([ "$TRT_OK" = 1 ] && echo "all found" || echo "missing $trt_missing (TensorRT rows skipped)")"
echo "===== library path: $GPU_LD_PATH" >>"$LOG"
if [ "$CUDA_OK" = 1 ]; then
  record cuda-libs pass "$DUR" "$pip_note$LIBS_LINE"
else
  record cuda-libs fail "$DUR" "$pip_note$LIBS_LINE" required
fi

# Everything below runs with the GPU ONNX Runtime; TensorRT engines are cached in the temp folder.
export FRAMES PROFILE TRT_OK CAPS="video/x-raw,width=1920,height=1080,framerate=30/1"
export ORT_DYLIB_PATH=$ORT_LIB LD_LIBRARY_PATH=$GPU_LD_PATH XDG_CACHE_HOME=$TMPD/cache
export GST_REGISTRY=$TMPD/registry.bin
[ "$TRT_OK" = 1 ] && export LEANGATE_EXPECT_TENSORRT=1
export LEANGATE_EXPECT_CUDA=1

# ---- build -----------------------------------------------------------------------------------------
TARGET=${CARGO_TARGET_DIR:-$ROOT/target}
case $PROFILE in dev) OUTDIR=$TARGET/debug ;; *) OUTDIR=$TARGET/$PROFILE ;; esac
[ "$BUNDLED" = 1 ] && OUTDIR=$ROOT/target/release
export OUTDIR
exe() { awk -v n="$1" '$1 == n {p = $2} END {print p}' "$TMPD/exes"; }
if [ "$BUNDLED" = 1 ]; then
  # The bundle's builds. Their tests and benches read the repository (models/, tests/fixtures,
  # scripts/) where it was when they were built (cargo's CARGO_MANIFEST_DIR): where that path is
  # free here, it is linked to this checkout for the run.
  awk -v r="$ROOT" '{print $1, r "/" $2}' "$ROOT/target/release/gpu-bundle-exes" >"$TMPD/exes"
  BUILD_ROOT=$(awk '$1 == "build_root" {print $2}' "$ROOT/target/release/gpu-bundle.txt")
  build_note="the bundle's builds ($(head -n 1 "$ROOT/target/release/gpu-bundle.txt" | sed 's/^LeanGate GPU bundle, //'))"
  if [ -n "$BUILD_ROOT" ] && [ ! -e "$BUILD_ROOT/scripts/gpu-check.sh" ]; then
    if [ ! -e "$BUILD_ROOT" ] && [ ! -L "$BUILD_ROOT" ] && mkdir -p "$(dirname "$BUILD_ROOT")" &&
      ln -s "$ROOT" "$BUILD_ROOT"; then
      LINKED_ROOT=$BUILD_ROOT
      trap 'rm -rf "$TMPD"; rm -f "$LINKED_ROOT"' EXIT
      build_note="$build_note; $BUILD_ROOT linked to this checkout for the run"
    else
      record build fail 0 "$build_note: their tests read $BUILD_ROOT, which is taken here" required
      skip_rest "the bundle's builds cannot find the repository" tests scoring element remote
    fi
  fi
  [ -z "$GST_LIB" ] || build_note="$build_note; the bundle's GStreamer (none here)"
  case $COMMIT:$(head -n 1 "$ROOT/target/release/gpu-bundle.txt") in
    unknown:* | *"commit ${COMMIT%% *}"*) ;;
    *) build_note="$build_note; NOT built from this checkout's commit $COMMIT" ;;
  esac
  missing_exe=""
  for n in models scorer gpu_check; do [ -x "$(exe $n)" ] || missing_exe="$missing_exe $n"; done
  if [ ! -f "$OUTDIR/libgstleangate.so" ] || [ -n "$missing_exe" ]; then
    record build fail 0 "$build_note: missing from it: ${missing_exe:-libgstleangate.so}" required
    skip_rest "the bundle is incomplete" tests scoring element remote
  fi
  record build pass 0 "$build_note"
else
  # cargo's JSON messages (stdout) to build.json, its diagnostics and progress (stderr) to the log.
  cargo_build() {
    cargo build --profile "$PROFILE" -p gst-plugin-leangate --lib --bench models --bench remote \
      --test scorer --test gpu_check --message-format=json-render-diagnostics >"$TMPD/build.json"
  }
  run_step build 300 cargo_build
  # The executables cargo made, one "name path" a line.
  python3 - "$TMPD/build.json" >"$TMPD/exes" 2>/dev/null <<'EOF'
import json, sys
for line in open(sys.argv[1], errors="replace"):
    if not line.startswith("{"):
        continue
    try:
        m = json.loads(line)
    except ValueError:
        continue
    if m.get("reason") == "compiler-artifact" and m.get("executable"):
        print(m["target"]["name"], m["executable"])
EOF
  if [ "$RC" != 0 ] || [ ! -f "$OUTDIR/libgstleangate.so" ] || [ -z "$(exe models)" ]; then
    record build fail "$DUR" "cargo build --profile $PROFILE: $(why_rc build)" required
    skip_rest "the build failed" tests scoring element remote
  fi
  record build pass "$DUR" "cargo build --profile $PROFILE (plugin, benches models and remote, tests scorer and gpu_check)"
fi

# ---- tests ------------------------------------------------------------------------------------------
run_tests() {
  local ok=0 t
  for t in gpu_check scorer; do
    echo "----- $t"
    "$(exe "$t")" || ok=1
  done
  return "$ok"
}
run_step tests 90 run_tests
summary=$(grep '^test result:' "$TMPD/tests.out" | sed 's/^test result: //; s/;.*finished/, finished/' | paste -sd';' -)
failed_tests=$(grep -E '^test .* FAILED$' "$TMPD/tests.out" | sed 's/^test //; s/ \.\.\. FAILED$//' | paste -sd' ' -)
{
  echo "## Tests on the GPU ONNX Runtime (LEANGATE_EXPECT_CUDA=1${LEANGATE_EXPECT_TENSORRT:+, LEANGATE_EXPECT_TENSORRT=1})"
  echo
  grep -E '^(----- |test .* \.\.\. |SKIPPED|test result:)' "$TMPD/tests.out" | sed 's/^/    /'
} >"$TMPD/sections/1-tests.md"
if [ "$RC" = 0 ]; then
  record tests pass "$DUR" "tests/gpu_check.rs, tests/scorer.rs: $summary"
elif [ -n "$failed_tests" ]; then
  record tests fail "$DUR" "failed: $failed_tests (see the section below and the log)" required
else
  record tests fail "$DUR" "$(why_rc tests)" required
fi

# ---- scoring: benches/models.rs providers -----------------------------------------------------------
EPS=cpu,cuda
[ "$TRT_OK" = 1 ] && EPS=cpu,cuda,tensorrt
LEANGATE_BENCH_EPS=$EPS LEANGATE_BENCH_STREAMS=8,32 LEANGATE_BENCH_FRAMES=100 LEANGATE_BENCH_REPS=3 \
  run_step scoring 150 "$(exe models)" providers
{
  grep -vE '^CHECK ' "$TMPD/scoring.out" | grep -E '^(## |\|)'
  [ "$TRT_OK" = 1 ] || printf '\nTensorRT not measured: %s\n' "missing $trt_missing"
  echo
  echo "FP16: not measured (the element has no FP16 setting; TensorRT's FP16 mode is not enabled by src/scorer/session.rs)."
} >"$TMPD/sections/2-scoring.md"
check() { grep -E "^CHECK provider=$1 build=$2 " "$TMPD/scoring.out" | tail -n 1; }
cuda_check=$(check cuda fp32)
diff=$(printf '%s' "$cuda_check" | sed -n 's/.*max_abs_diff=\([0-9.e+-]*\).*/\1/p')
notes=""
for pb in "cuda int8" "tensorrt fp32" "tensorrt int8"; do
  # shellcheck disable=SC2086
  c=$(check $pb)
  case $c in *status=ok*) ;; "") ;; *) notes="$notes; ${pb/ /\/} failed: ${c#*reason=}" ;; esac
done
# A run cut short still counts with the rows it finished (cuda comes before tensorrt).
[ "$RC" = 0 ] || notes="$notes; the run did not finish: $(why_rc scoring)"
if [ "$RC" != 0 ] && [ -z "$cuda_check" ]; then
  record scoring fail "$DUR" "$(why_rc scoring)" required
elif ! check cpu fp32 | grep -q status=ok; then
  record scoring fail "$DUR" "the CPU provider failed: $(check cpu fp32)" required
elif [ -z "$diff" ] || ! printf '%s' "$cuda_check" | grep -q status=ok; then
  record scoring fail "$DUR" "cuda fp32: ${cuda_check:-no result}" required
elif ! awk -v d="$diff" -v t="$TOL" 'BEGIN {exit !(d <= t)}'; then
  record scoring fail "$DUR" "cuda fp32 differs from the CPU by $diff (tolerance $TOL)$notes" required
else
  record scoring "$([ -z "$notes" ] && echo pass || echo warn)" "$DUR" \
    "cuda fp32 within $diff of the CPU ($(printf '%s' "$cuda_check" | sed -n 's/.* \(fps=[0-9.]*\).*/\1/p') 1 stream)$notes"
fi

# ---- element: gst-launch-1.0 at 1080p ---------------------------------------------------------------
# launch LABEL STREAMS FRAMES ELEMENT: one row; the time is gst-launch's "Execution ended after"
# (PLAYING to EOS: the model loading before it is not counted).
launch() {
  local label=$1 n=$2 frames=$3 el=$4 desc="" i out t rc
  for ((i = 0; i < n; i++)); do
    desc="$desc videotestsrc num-buffers=$frames pattern=ball ! $CAPS ! queue ! $el ! fakesink sync=false"
  done
  out=$TMPD/launch.out
  # shellcheck disable=SC2086
  GST_PLUGIN_PATH=$OUTDIR timeout --kill-after=5 "${LAUNCH_LIMIT:-60}" gst-launch-1.0 $desc >"$out" 2>&1
  rc=$?
  { echo "--- $label: gst-launch-1.0$desc"; cat "$out"; } >>"$TMPD/element.log"
  t=$(sed -n 's/.*Execution ended after \([0-9]*\):\([0-9]*\):\([0-9.]*\).*/\1 \2 \3/p' "$out" | tail -n 1)
  if [ "$rc" = 0 ] && [ -n "$t" ] && ! grep -q '^ERROR' "$out"; then
    awk -v l="$label" -v n="$n" -v f="$frames" -v t="$t" 'BEGIN {
      split(t, a, " "); s = a[1] * 3600 + a[2] * 60 + a[3];
      printf "| %s | %d | %d | %.2f | %.1f | ok |\n", l, n, n * f, s, n * f / s }'
    return 0
  fi
  echo "| $label | $n | $((n * frames)) | | | failed: $( (grep -E 'ERROR|error' "$out" || tail -n 2 "$out") | head -n 2 | one_line) |"
  return 1
}
element_rows() {
  local r=0
  echo "## Element at 1920x1080 (gst-launch-1.0, videotestsrc pattern=ball ! queue ! ELEMENT ! fakesink sync=false)"
  echo
  echo "| element | streams | frames | seconds | frames/s | status |"
  echo "|---|---|---|---|---|---|"
  launch identity 1 "$FRAMES" identity
  launch "leangate execution-provider=cpu" 1 "$FRAMES" "leangate execution-provider=cpu"
  launch "leangate execution-provider=cuda" 1 "$FRAMES" "leangate execution-provider=cuda" || r=1
  if [ "$TRT_OK" = 1 ]; then
    # The first run builds the TensorRT engine (cached in XDG_CACHE_HOME); the second is timed.
    LAUNCH_LIMIT=120 launch "leangate execution-provider=tensorrt (engine build)" 1 10 \
      "leangate execution-provider=tensorrt" >/dev/null
    launch "leangate execution-provider=tensorrt" 1 "$FRAMES" "leangate execution-provider=tensorrt"
  fi
  launch identity 8 $((FRAMES / 2)) identity
  launch "leangate execution-provider=cuda shared-session=true batch-size=8" 8 $((FRAMES / 2)) \
    "leangate execution-provider=cuda shared-session=true batch-size=8" || r=1
  return "$r"
}
: >"$TMPD/element.log"
if command -v gst-launch-1.0 >/dev/null 2>&1; then
  run_step element 150 element_rows
  cat "$TMPD/element.log" >>"$LOG"
  grep -E '^(## |\||$)' "$TMPD/element.out" >"$TMPD/sections/3-element.md"
  if [ "$RC" = 0 ]; then
    record element pass "$DUR" "$(grep -F '| leangate execution-provider=cuda |' "$TMPD/element.out" | awk -F'|' '{print "cuda 1080p:" $6 " frames/s"}')"
  else
    failed_row=$(grep -F '| failed: ' "$TMPD/element.out" | head -n 1 | awk -F'|' '{print $2 ":" $7}')
    case $RC in
      124 | 137 | 125) record element fail "$DUR" "$(why_rc element)${failed_row:+; $failed_row}" required ;;
      *) record element fail "$DUR" "${failed_row:-$(why_rc element)}" required ;;
    esac
  fi
else
  record element fail 0 "gst-launch-1.0 not installed (gstreamer1.0-tools; scripts/setup.sh installs it)" required
fi

# ---- remote: benches/remote.rs against a local Triton ------------------------------------------------
if [ ! -x .venv-triton/bin/python ]; then
  record remote skip 0 ".venv-triton is absent (scripts/setup.sh could not install PyTriton)"
elif [ -z "$(exe remote)" ]; then
  record remote skip 0 "benches/remote.rs was not built"
else
  LEANGATE_BENCH_FRAMES=100 LEANGATE_BENCH_CLIENTS=1,8 run_step remote 75 "$(exe remote)"
  {
    echo "## Remote scoring (benches/remote.rs, local Triton through PyTriton on the CPU, 100 frames per client)"
    echo
    grep -E 'remote rows skipped|clients|local|remote' "$TMPD/remote.out" | sed 's/^/    /'
  } >"$TMPD/sections/4-remote.md"
  if [ "$RC" = 125 ]; then
    record remote skip 0 "$(why_rc remote)"
  elif [ "$RC" != 0 ]; then
    record remote warn "$DUR" "$(why_rc remote)"
  elif grep -q 'remote rows skipped' "$TMPD/remote.out"; then
    record remote skip "$DUR" "$(grep -m1 'remote rows skipped' "$TMPD/remote.out")"
  else
    record remote pass "$DUR" "$(awk '$2 == "remote" {printf "%s clients %s frames/s, %s failed; ", $1, $4, $9}' "$TMPD/remote.out")"
  fi
fi

finish
