#!/usr/bin/env bash
# camera.sh — gate a live V4L2 camera with leangate and watch (or discard) the kept frames.
#
# NOT TESTED ON A REAL CAMERA: the development machine has no /dev/video*. What is checked is
# that the pipeline description parses and every element in it exists (`camera.sh --check`,
# which builds it with Gst.parse_launch without starting it; the Rust test suite runs it).
#
# Usage:  pipelines/camera.sh [--check] [DEVICE] [THRESHOLD]      (DEVICE default /dev/video0)
# Env:    LEANGATE_MODEL  model (.onnx); default: the student embedded in the plugin (leangate-s)
#         SINK            default "videoconvert ! autovideosink sync=false"; e.g. "fakesink" headless
#         CAPS            camera caps to request, default "video/x-raw,width=640,height=480"
#         MAX_GAP         keep at least one frame every N (default 30: a live SLAM front end
#                         should never starve)
#         LOOKBACK        sharpness-lookback (default: the element's 3 frames held, 100 ms at
#                         30 frames/s); LOOKBACK=0 when latency matters (docs/element.md,
#                         "Live cameras")
#
# Equivalent gst-launch line (-m prints the periodic `leangate-stats` messages: one per second
# of stream time here, via stats-interval):
#
#   GST_PLUGIN_PATH=target/debug gst-launch-1.0 -m \
#       v4l2src device=/dev/video0 ! video/x-raw,width=640,height=480 ! videoconvert ! \
#       leangate max-gap=30 stats-interval=1000000000 ! \
#       videoconvert ! autovideosink sync=false
#
# (leangate reads the raw formats cameras give most, YUY2, NV12 and I420, directly; the
# videoconvert before it covers the others. A camera that gives only MJPEG needs
# `image/jpeg ! jpegdec` in place of the caps.)
# Stop with Ctrl-C: gst-launch's -e sends EOS so the final statistics are printed too.
set -euo pipefail
. "$(dirname "$0")/common.sh"

CHECK=0
if [ "${1:-}" = "--check" ]; then CHECK=1; shift; fi
DEVICE="${1:-/dev/video0}"
THRESHOLD="${2:-}"
SINK="${SINK:-videoconvert ! autovideosink sync=false}"
CAPS="${CAPS:-video/x-raw,width=640,height=480}"
MAX_GAP="${MAX_GAP:-30}"
LOOKBACK="${LOOKBACK:-}"
case "$LOOKBACK" in
    "" | [0-9] | [12][0-9] | 30) ;;
    *) echo "error: LOOKBACK=$LOOKBACK: sharpness-lookback takes 0 to 30 frames" >&2; exit 2 ;;
esac
leangate_require_plugin

# The pipeline's words (CAPS and SINK split as gst-launch would; the device and the model quoted
# as one word each), and the same as one description for --check.
set -f
# shellcheck disable=SC2206
WORDS=(v4l2src "device=$(gst_quote "$DEVICE")" ! $CAPS ! videoconvert !
    leangate ${MODEL_PROP:+"$MODEL_PROP"} ${THRESHOLD:+threshold=$THRESHOLD} max-gap="$MAX_GAP"
    ${LOOKBACK:+sharpness-lookback=$LOOKBACK} stats-interval=1000000000 ! $SINK)
set +f
PIPELINE="${WORDS[*]}"

if [ "$CHECK" = 1 ]; then
    exec /usr/bin/python3 - "$PIPELINE" <<'PY'
import sys
import gi
gi.require_version("Gst", "1.0")
from gi.repository import Gst
Gst.init(None)
try:
    p = Gst.parse_launch(sys.argv[1])
except Exception as e:
    sys.exit(f"camera.sh: the pipeline does not parse: {e}")
names = sorted({e.get_factory().get_name() for e in p.iterate_recurse() if e.get_factory()})
print("camera.sh: pipeline parses:", sys.argv[1])
print("camera.sh: elements:", " ".join(names))
PY
fi

[ -e "$DEVICE" ] || { echo "error: no camera at $DEVICE (pass another device as the first argument)" >&2; exit 2; }
gst-launch-1.0 -e -m "${WORDS[@]}" | leangate_summarise
exit "${PIPESTATUS[0]}"
