#!/usr/bin/env bash
# What the GPU check needs on a machine that can neither download nor build (issue 35): a lent
# GPU machine (the `device` tool) has a GPU, CUDA's libraries and python3, but no Rust, no
# GStreamer, no GPU ONNX Runtime, and no network; and each call takes at most 64 MiB of files.
#
#   bash scripts/gpu-bundle.sh            # here (network, cargo): build and pack .gpu-bundle/1..K
#   bash scripts/gpu-bundle.sh --status   # anywhere: which parts are here, and whether complete
#   bash scripts/gpu-bundle.sh --unpack   # there (scripts/gpu-check.sh calls it): check, unpack
#
# The bundle holds the release builds of the plugin, benches/models.rs, benches/remote.rs,
# tests/scorer.rs and tests/gpu_check.rs (laid out as target/release, where the check and the
# tests look for them), ONNX Runtime's GPU build (onnxruntime-gpu==1.31.1, CUDA 13) with the CUDA
# provider's kernels cut to the architectures in GPU_BUNDLE_ARCHS (default 90: H100 and H200;
# scripts/cuda_fatbin_keep.py), and a minimal GStreamer runtime from this machine (gst-launch-1.0,
# the core elements and videotestsrc, and the libraries they load that the other machine may
# lack). It is packed with xz and split into parts of GPU_BUNDLE_PART_MIB (default 54) MiB, one
# folder each (.gpu-bundle/N/part, .gpu-bundle/N/index), so that each part travels in one call
# beside the working tree. The folder is git-ignored; a new bundle replaces the old one only once
# it is complete.
#
# On the lent machine (docs/element.md, "The GPU check on a lent machine"): one call per part,
# the next within the machine's warm period, each naming its part in `carry`; the last one runs
# `bash scripts/gpu-check.sh`, which unpacks the bundle when every part is there.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
BUNDLE=$ROOT/.gpu-bundle
ORT_VERSION=1.31.1
ARCHS=${GPU_BUNDLE_ARCHS:-90}
PART_MIB=${GPU_BUNDLE_PART_MIB:-54}

say() { echo "gpu-bundle: $*"; }
die() { echo "gpu-bundle: $*" >&2; exit 1; }

# The parts present: "N K SHA COMMIT" from each part's index (K parts, SHA of the whole archive).
parts() {
  local d
  for d in "$BUNDLE"/*/; do
    [ -f "$d/index" ] && [ -f "$d/part" ] || continue
    awk -v n="$(basename "$d")" '/^part /{k=$4} /^sha256 /{s=$2} /^commit /{c=$2} END {print n, k, s, c}' "$d/index"
  done | sort -n
}

# complete: 0 when every part 1..K of one archive is here; prints what is missing otherwise.
complete() {
  local list k sha n
  list=$(parts)
  [ -n "$list" ] || { echo "no part of a bundle in $BUNDLE"; return 1; }
  k=$(echo "$list" | awk 'NR==1 {print $2}')
  sha=$(echo "$list" | awk 'NR==1 {print $3}')
  if [ "$(echo "$list" | awk -v s="$sha" '$3 != s' | wc -l)" != 0 ]; then
    echo "the parts in $BUNDLE come from different bundles (make one with scripts/gpu-bundle.sh)"
    return 1
  fi
  local missing=()
  for ((n = 1; n <= k; n++)); do
    echo "$list" | awk -v n="$n" '$1 == n {f=1} END {exit !f}' || missing+=("$n")
  done
  if ((${#missing[@]})); then
    echo "parts ${missing[*]} of $k missing (each call carries one: .gpu-bundle/N)"
    return 1
  fi
}

status() {
  local list why
  list=$(parts)
  if [ -z "$list" ]; then say "no bundle in $BUNDLE"; return 1; fi
  echo "$list" | while read -r n k sha commit; do
    say "part $n of $k ($(du -h "$BUNDLE/$n/part" | cut -f1)), commit $commit, archive ${sha:0:12}"
  done
  if why=$(complete); then say "complete"; else say "$why"; return 1; fi
}

# unpack: verify the archive and unpack it into the repository (target/release, .deps/).
unpack() {
  local why sha k n tmp
  why=$(complete) || die "$why"
  read -r _ k sha _ < <(parts | head -n 1)
  tmp=$(mktemp -d "${TMPDIR:-/tmp}/gpu-bundle.XXXXXX")
  trap 'rm -rf "$tmp"' RETURN
  for ((n = 1; n <= k; n++)); do cat "$BUNDLE/$n/part"; done >"$tmp/bundle.tar.xz"
  [ "$(sha256sum "$tmp/bundle.tar.xz" | cut -d' ' -f1)" = "$sha" ] ||
    die "the parts do not make the archive they were cut from (sha256 differs): carry them again"
  if command -v xz >/dev/null 2>&1; then
    xz -dc "$tmp/bundle.tar.xz" >"$tmp/bundle.tar"
  else
    python3 -c 'import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), open(sys.argv[2], "wb"))' \
      "$tmp/bundle.tar.xz" "$tmp/bundle.tar"
  fi
  tar -xf "$tmp/bundle.tar" -C "$ROOT"
  say "unpacked $(cat "$ROOT/target/release/gpu-bundle.txt" | head -n 1) into $ROOT (target/release, .deps/onnxruntime-gpu, .deps/gst-runtime)"
}

case ${1:-} in
  --status) status; exit ;;
  --unpack) unpack; exit ;;
  "") ;;
  *) die "unknown argument '$1' (none: build the bundle; --status; --unpack)" ;;
esac

# ---- build the bundle (here) ------------------------------------------------------------------------
command -v cargo >/dev/null || die "cargo is not installed (the bundle is built where cargo is)"
command -v xz >/dev/null || die "xz is not installed (apt install xz-utils)"
for a in ${ARCHS//,/ }; do [[ $a =~ ^[0-9]+$ ]] || die "GPU_BUNDLE_ARCHS: '$a' is not an SM number such as 90"; done
[[ $PART_MIB =~ ^[0-9]+$ ]] && [ "$PART_MIB" -ge 8 ] && [ "$PART_MIB" -le 60 ] ||
  die "GPU_BUNDLE_PART_MIB must be a whole number of MiB in 8..60 (each call carries 64 MiB with the working tree)"
STAGE=$(mktemp -d "${TMPDIR:-/tmp}/gpu-bundle-stage.XXXXXX")
trap 'rm -rf "$STAGE"' EXIT

say "building the release plugin, benches and GPU tests"
export ORT_DYLIB_PATH=${ORT_DYLIB_PATH:-$ROOT/.deps/onnxruntime/libonnxruntime.so}
cargo build --release -p gst-plugin-leangate --lib --bench models --bench remote --test scorer \
  --test gpu_check --message-format=json-render-diagnostics >"$STAGE/build.json"
TARGET=${CARGO_TARGET_DIR:-$ROOT/target}
mkdir -p "$STAGE/t/target/release/deps"
cp "$TARGET/release/libgstleangate.so" "$STAGE/t/target/release/"
python3 - "$STAGE/build.json" >"$STAGE/exes" <<'EOF'
import json, sys
for line in open(sys.argv[1], errors="replace"):
    if line.startswith("{"):
        m = json.loads(line)
        if m.get("reason") == "compiler-artifact" and m.get("executable"):
            print(m["target"]["name"], m["executable"])
EOF
while read -r name path; do
  cp "$path" "$STAGE/t/target/release/deps/"
  echo "$name target/release/deps/$(basename "$path")"
done <"$STAGE/exes" >"$STAGE/t/target/release/gpu-bundle-exes"
[ "$(wc -l <"$STAGE/t/target/release/gpu-bundle-exes")" = 4 ] || die "cargo did not report the four executables"

say "ONNX Runtime $ORT_VERSION GPU build (onnxruntime-gpu, CUDA 13), kernels for sm_${ARCHS//,/, sm_}"
WHEEL_DIR=$ROOT/.deps/wheels
whl=$(ls "$WHEEL_DIR"/onnxruntime_gpu-$ORT_VERSION-*manylinux*x86_64.whl 2>/dev/null | head -n 1 || true)
if [ -z "$whl" ]; then
  mkdir -p "$WHEEL_DIR"
  python3 -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
    --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64 \
    -d "$WHEEL_DIR" "onnxruntime-gpu==$ORT_VERSION"
  whl=$(ls "$WHEEL_DIR"/onnxruntime_gpu-$ORT_VERSION-*.whl | head -n 1)
fi
ORT_OUT=$STAGE/t/.deps/onnxruntime-gpu
mkdir -p "$ORT_OUT" "$STAGE/whl"
unzip -q -o -j "$whl" 'onnxruntime/capi/libonnxruntime*.so*' -d "$STAGE/whl"
for f in "$STAGE"/whl/*; do
  case $(basename "$f") in
    libonnxruntime_providers_cuda.so)
      keep=()
      for a in ${ARCHS//,/ }; do keep+=(--arch "$a"); done
      python3 scripts/cuda_fatbin_keep.py "$f" "$ORT_OUT/$(basename "$f")" "${keep[@]}" ;;
    *) cp "$f" "$ORT_OUT/" ;;
  esac
done
ln -sf "libonnxruntime.so.$ORT_VERSION" "$ORT_OUT/libonnxruntime.so"

say "GStreamer runtime (gst-launch-1.0, core elements, videotestsrc)"
GST=$STAGE/t/.deps/gst-runtime
mkdir -p "$GST/bin" "$GST/lib" "$GST/plugins" "$GST/libexec"
gst_launch=$(command -v gst-launch-1.0) || die "gst-launch-1.0 is not installed here (scripts/setup.sh)"
plugdir=$(pkg-config --variable=pluginsdir gstreamer-1.0 2>/dev/null || echo /usr/lib/x86_64-linux-gnu/gstreamer-1.0)
scanner=$(pkg-config --variable=pluginscannerdir gstreamer-1.0 2>/dev/null || true)/gst-plugin-scanner
[ -x "$scanner" ] || scanner=/usr/lib/x86_64-linux-gnu/gstreamer1.0/gstreamer-1.0/gst-plugin-scanner
cp "$gst_launch" "$GST/bin/"
cp "$(command -v gst-inspect-1.0)" "$GST/bin/" 2>/dev/null || true
cp "$plugdir/libgstcoreelements.so" "$plugdir/libgstvideotestsrc.so" "$GST/plugins/"
cp "$scanner" "$GST/libexec/"
# The libraries all of these load, except the C runtime every Linux has.
for f in "$GST"/bin/* "$GST"/plugins/* "$GST"/libexec/* "$STAGE"/t/target/release/libgstleangate.so; do
  ldd "$f" | awk '$2 == "=>" && $3 ~ /^\// {print $3}'
done | sort -u | while read -r lib; do
  case $(basename "$lib") in
    libc.so.* | libm.so.* | libdl.so.* | libpthread.so.* | librt.so.* | ld-linux* | libgcc_s.so.* | libstdc++.so.*) ;;
    *) cp -L "$lib" "$GST/lib/" ;;
  esac
done

commit=$(git rev-parse --short HEAD)
[ -z "$(git status --porcelain --untracked-files=no)" ] || commit="$commit+local-changes"
{
  echo "LeanGate GPU bundle, commit $commit, built $(date -u '+%Y-%m-%d %H:%M UTC') on $(. /etc/os-release && echo "$PRETTY_NAME")"
  echo "build_root $ROOT"
  echo "cuda_archs $ARCHS"
  echo "onnxruntime-gpu $ORT_VERSION"
} >"$STAGE/t/target/release/gpu-bundle.txt"

say "packing (xz)"
tar -C "$STAGE/t" -cf - target .deps | xz -6 -T0 >"$STAGE/bundle.tar.xz"
sha=$(sha256sum "$STAGE/bundle.tar.xz" | cut -d' ' -f1)
split -b "${PART_MIB}M" -d -a 2 "$STAGE/bundle.tar.xz" "$STAGE/part."
k=$(ls "$STAGE"/part.* | wc -l)
rm -rf "$BUNDLE.new"
n=0
for p in "$STAGE"/part.*; do
  n=$((n + 1))
  mkdir -p "$BUNDLE.new/$n"
  mv "$p" "$BUNDLE.new/$n/part"
  printf 'part %d of %d\nsha256 %s\ncommit %s\n' "$n" "$k" "$sha" "$commit" >"$BUNDLE.new/$n/index"
done
rm -rf "$BUNDLE"
mv "$BUNDLE.new" "$BUNDLE"
say "$k parts in $BUNDLE ($(du -sh "$BUNDLE" | cut -f1)); on a lent machine, one call per part:"
for ((n = 1; n < k; n++)); do say "  call $n: carry .gpu-bundle/$n, command: bash scripts/gpu-bundle.sh --status"; done
say "  call $k: carry .gpu-bundle/$k, command: bash scripts/gpu-check.sh"
