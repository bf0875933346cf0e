#!/usr/bin/env bash
# file.sh — gate a video file with leangate and print how many frames were kept.
#
# Usage:  pipelines/file.sh VIDEO [THRESHOLD]
# Env:    LEANGATE_MODEL  model (.onnx); default: the student embedded in the plugin (leangate-s)
#         SINK            where kept frames go; default "fakesink sync=false" (as fast as possible);
#                         SINK="videoconvert ! autovideosink" to watch the kept frames
#         MODE            drop (default) or annotate
#
# Equivalent gst-launch line (-m prints bus messages, including the `leangate-stats` element
# message posted at EOS with frames-in, frames-kept, keep-ratio and inference timings):
#
#   GST_PLUGIN_PATH=target/debug gst-launch-1.0 -m \
#       filesrc location=VIDEO ! decodebin ! queue max-size-buffers=2 ! \
#       leangate ! fakesink sync=false
#
# decodebin's usual outputs (I420, NV12, RGB...) link to leangate directly: no videoconvert.
# The small queue puts the gate in a streaming thread of its own, so decoding and scoring overlap
# on a multi-core machine (measured on 2 cores, H.264 854x480: 1.39x identity's wall time instead
# of 1.67x, `cargo bench --bench perf -- pipeline`).
set -euo pipefail
. "$(dirname "$0")/common.sh"

if [ $# -lt 1 ]; then
    sed -n '2,20p' "$0" >&2
    exit 2
fi
VIDEO="$1"
THRESHOLD="${2:-}"
[ -f "$VIDEO" ] || { echo "error: no such file: $VIDEO" >&2; exit 2; }
leangate_require_plugin

SINK="${SINK:-fakesink sync=false}"
MODE="${MODE:-drop}"
set -f # no globbing: the pipeline words below are passed as they are
# shellcheck disable=SC2086
gst-launch-1.0 -m \
    filesrc location="$(gst_quote "$VIDEO")" ! decodebin ! queue max-size-buffers=2 ! \
    leangate ${MODEL_PROP:+"$MODEL_PROP"} ${THRESHOLD:+threshold=$THRESHOLD} mode="$MODE" ! \
    $SINK | leangate_summarise
exit "${PIPESTATUS[0]}"
