#!/usr/bin/env bash
# Install everything LeanGate needs on a Debian 12 machine, idempotently:
#   1. GStreamer 1.22 development files, tools, plugins and Python bindings (apt), and ffmpeg
#      (tests/element.rs encodes clips in the formats phones and cameras record);
#   2. ONNX Runtime 1.31.1: libonnxruntime.so from the PyPI wheel, extracted into .deps/
#      (ORT_FLAVOR=gpu takes onnxruntime-gpu==1.31.1, for CUDA 13, into .deps/onnxruntime-gpu);
#   3. a project-local Python venv (.venv) with `onnx` (to regenerate the test fixture models),
#      numpy and pillow (the training package's preprocessing, checked against the element's);
#   4. .venv-sfm: Debian's python3 in a venv that sees the system's PyGObject and numpy
#      (--system-site-packages), with pycolmap (COLMAP's bindings, a manylinux wheel) for the
#      reconstruction consumer (pipelines/reconstruct.py, `leangate eval --reconstruct`), and
#      evo (`evo_ape`, the SLAM trajectory evaluator, for `eval --trajectory-dir` files; it
#      brings its own numpy 2, matplotlib, scipy and pandas into this venv);
#   5. .venv-bag: Debian's python3 with the system's PyGObject and numpy and rosbags (ROS bags for
#      leangate-client, pipelines/leangate_client/bag.py);
#   6. .venv-triton: Debian's /usr/bin/python3 in a venv with nvidia-pytriton (NVIDIA Triton
#      Inference Server, CPU) and onnxruntime, the KServe V2 server the remote-scoring tests and
#      benchmark start on loopback (scripts/v2_server.py). Debian's python, not pyenv's: the
#      Python backend bundled in PyTriton loads the interpreter's libpython. If it cannot be
#      installed, setup goes on and those tests skip, saying why.
# Safe to run again: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")/.."
# The checks below import Microsoft's onnxruntime wheel, which otherwise writes a device id and
# usage events under ~/.cache/Microsoft when it loads (a value of the user's own is kept).
export ORT_DISABLE_TELEMETRY=${ORT_DISABLE_TELEMETRY:-1}

ORT_VERSION=1.31.1
ORT_FLAVOR=${ORT_FLAVOR:-cpu}

APT_PACKAGES=(pkg-config libgstreamer1.0-dev libgstreamer-plugins-base1.0-dev gstreamer1.0-tools
  gstreamer1.0-plugins-base gstreamer1.0-plugins-good gstreamer1.0-libav python3-gi
  gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 python3-gst-1.0 python3-numpy
  python3-venv python3-pip fonts-dejavu-core unzip ffmpeg)

missing=()
for p in "${APT_PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing apt packages: ${missing[*]}"
  SUDO=""
  if [ "$(id -u)" != 0 ]; then
    command -v sudo >/dev/null || { echo "setup: need root or sudo to install: ${missing[*]}" >&2; exit 1; }
    SUDO=sudo
  fi
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

# A Python with pip for downloading wheels (pyenv's or Debian's).
PY=""
for c in python3 /usr/bin/python3; do
  if command -v "$c" >/dev/null && "$c" -m pip --version >/dev/null 2>&1; then PY=$c; break; fi
done

if [ "$ORT_FLAVOR" = gpu ]; then
  ORT_DIR=.deps/onnxruntime-gpu; WHEEL=onnxruntime-gpu
else
  ORT_DIR=.deps/onnxruntime; WHEEL=onnxruntime
fi
if [ ! -f "$ORT_DIR/libonnxruntime.so.$ORT_VERSION" ]; then
  [ -n "$PY" ] || { echo "setup: no python3 with pip to download the $WHEEL wheel" >&2; exit 1; }
  echo "setup: downloading $WHEEL==$ORT_VERSION from PyPI"
  tmp=$(mktemp -d)
  "$PY" -m pip download -q --no-deps --only-binary=:all: -d "$tmp" "$WHEEL==$ORT_VERSION"
  mkdir -p "$ORT_DIR"
  # The shared libraries live in onnxruntime/capi/ inside the wheel.
  unzip -q -o -j "$tmp"/*.whl 'onnxruntime/capi/libonnxruntime*.so*' -d "$ORT_DIR"
  rm -rf "$tmp"
  ln -sf "libonnxruntime.so.$ORT_VERSION" "$ORT_DIR/libonnxruntime.so"
  echo "setup: ONNX Runtime in $ORT_DIR"
fi

if [ ! -x .venv/bin/python ] || ! .venv/bin/python -c 'import onnx, PIL' 2>/dev/null; then
  [ -n "$PY" ] || PY=/usr/bin/python3
  echo "setup: creating .venv with onnx, numpy, pillow"
  [ -x .venv/bin/python ] || "$PY" -m venv .venv
  .venv/bin/pip install -q --disable-pip-version-check onnx==1.23.2 numpy pillow==13.0.0
fi
PYCOLMAP_VERSION=4.2.1
EVO_VERSION=1.38.1
if [ ! -x .venv-sfm/bin/python ] || ! .venv-sfm/bin/python -c 'import pycolmap, evo' 2>/dev/null; then
  echo "setup: creating .venv-sfm (system site packages + pycolmap==$PYCOLMAP_VERSION, evo==$EVO_VERSION)"
  [ -x .venv-sfm/bin/python ] || /usr/bin/python3 -m venv --system-site-packages .venv-sfm
  .venv-sfm/bin/pip install -q --disable-pip-version-check --only-binary=:all: \
    "pycolmap==$PYCOLMAP_VERSION" "evo==$EVO_VERSION"
fi
# .venv-bag: Debian's python3 seeing the system's PyGObject and numpy, with rosbags (pure Python:
# ROS 1 and ROS 2 bags, sqlite3 and MCAP, without ROS) for `leangate-client BAG --topic T --out OUT`
# (pipelines/leangate_client/bag.py) and its tests (tests/bag.rs).
ROSBAGS_VERSION=0.11.9
if [ ! -x .venv-bag/bin/python ] || ! .venv-bag/bin/python -c "import gi, importlib.metadata as m; assert m.version('rosbags') == '$ROSBAGS_VERSION'" 2>/dev/null; then
  echo "setup: creating .venv-bag (system site packages + rosbags==$ROSBAGS_VERSION)"
  [ -x .venv-bag/bin/python ] || /usr/bin/python3 -m venv --system-site-packages .venv-bag
  .venv-bag/bin/pip install -q --disable-pip-version-check --only-binary=:all: \
    "rosbags==$ROSBAGS_VERSION"
fi
PYTRITON_VERSION=0.7.0
if [ ! -x .venv-triton/bin/python ] || ! .venv-triton/bin/python -c 'import pytriton, onnxruntime' 2>/dev/null; then
  echo "setup: creating .venv-triton (nvidia-pytriton==$PYTRITON_VERSION, onnxruntime==$ORT_VERSION)"
  if { [ -x .venv-triton/bin/python ] || /usr/bin/python3 -m venv .venv-triton; } &&
    .venv-triton/bin/pip install -q --disable-pip-version-check --only-binary=:all: \
      "nvidia-pytriton==$PYTRITON_VERSION" "onnxruntime==$ORT_VERSION" "numpy<2"; then
    :
  else
    echo "setup: WARNING: could not install PyTriton into .venv-triton; the remote-scoring" \
      "tests (tests/remote.rs) and benches/remote.rs will skip" >&2
  fi
fi
echo "setup: done"
