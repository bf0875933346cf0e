#!/usr/bin/env bash
# The main job: gate a video with leangate in a real GStreamer pipeline and show what it kept.
#   scripts/demo.sh [OUT_DIR]            a synthetic flythrough with pauses and bursts
#   VIDEO=walk.mp4 scripts/demo.sh       your own video (or an image-sequence directory)
#   MODEL=student.onnx scripts/demo.sh   another pair or split model (default: the embedded one)
#   THRESHOLD=0.6 scripts/demo.sh        another tau_keep (default: the model's)
# Writes OUT_DIR/eval.json, OUT_DIR/eval.png (teacher vs predicted utility, kept frames per
# policy) and OUT_DIR/kept.png (contact sheet of the kept frames).
# Relative paths (OUT_DIR, VIDEO, MODEL) are taken from where it is run; the default OUT_DIR is the
# checkout's out/demo.
set -euo pipefail
HERE=$PWD
REPO=$(cd "$(dirname "$0")/.." && pwd)
abs() { case $1 in /*) printf '%s\n' "$1" ;; *) printf '%s\n' "$HERE/$1" ;; esac; }
OUT=$(abs "${1:-$REPO/out/demo}")
[ -z "${VIDEO:-}" ] || VIDEO=$(abs "$VIDEO")
[ -z "${MODEL:-}" ] || MODEL=$(abs "$MODEL")
cd "$REPO"
BIN=target/release/leangate
mkdir -p "$OUT"

if [ -n "${VIDEO:-}" ]; then
  SEQ=$VIDEO
else
  SEQ=$OUT/flythrough
  echo "== rendering a synthetic indoor flythrough: pans, walks, shaky handheld, pauses and bursts (300 frames, 640x480)"
  "$BIN" synth --out "$SEQ" --seed 42 --frames 300 --motion mixed --blur --jpeg
fi

ARGS=()
# No --model: the student embedded in the plugin (leangate-s) gates the video.
[ -n "${MODEL:-}" ] && ARGS+=(--model "$MODEL")
[ -n "${THRESHOLD:-}" ] && ARGS+=(--threshold "$THRESHOLD")

echo "== gating $SEQ with leangate (annotate mode, real pipeline) and judging it"
"$BIN" eval --sequence "$SEQ" ${ARGS[@]+"${ARGS[@]}"} --json "$OUT/eval.json" --plot "$OUT/eval.png" \
  --contact-sheet "$OUT/kept.png"
echo "== frames in / kept: $(python3 -c 'import json, sys; d = json.load(open(sys.argv[1])); print(d["frames"], "/", d["policies"]["model"]["kept"])' "$OUT/eval.json" 2>/dev/null || echo see above)"
echo "== wrote $OUT/eval.json, $OUT/eval.png, $OUT/kept.png"
