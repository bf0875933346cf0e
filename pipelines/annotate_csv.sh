#!/usr/bin/env bash
# annotate_csv.sh — score every frame of a video and write the per-frame verdicts to CSV.
#
# Usage:  pipelines/annotate_csv.sh VIDEO OUT.csv [THRESHOLD]
#         (VIDEO may also be a URI or test://ball?num-buffers=100 for videotestsrc)
# Env:    LEANGATE_MODEL  model (.onnx); default: the student embedded in the plugin (leangate-s)
#
# In annotate mode leangate lets every frame through, tagged with LeanGateMeta; the Python
# client (the package pipelines/leangate_client, run through pipelines/slam_client.py with
# Debian's /usr/bin/python3 + python3-gi) reads the meta at an appsink and writes one row per
# input frame:
#
#   frame,pts_ns,utility,keep,reason,keyframe_index,frames_since_keyframe,inference_us
#   0,66666666,nan,1,first,1,0,3329
#   1,100000000,0.014414,0,score,1,1,3641
#
# (utility is "nan" for the first frame, which has no reference; keep is 1/0.)
# The pipeline it runs is the equivalent of
#
#   GST_PLUGIN_PATH=target/debug gst-launch-1.0 \
#       filesrc location=VIDEO ! decodebin ! \
#       leangate mode=annotate ! \
#       videoconvert ! video/x-raw,format=RGB ! appsink
#
# with the appsink read from Python; gst-launch alone cannot dump buffer metas to a file.
set -euo pipefail
. "$(dirname "$0")/common.sh"

if [ $# -lt 2 ]; then
    sed -n '2,25p' "$0" >&2
    exit 2
fi
VIDEO="$1"
OUT="$2"
THRESHOLD="${3:-}"
leangate_require_plugin

ARGS=(--mode annotate --csv "$OUT" --quiet)
[ -n "$MODEL" ] && ARGS+=(--model "$MODEL")
[ -n "$THRESHOLD" ] && ARGS+=(--threshold "$THRESHOLD")
exec /usr/bin/python3 "$(dirname "$0")/slam_client.py" "$VIDEO" "${ARGS[@]}"
