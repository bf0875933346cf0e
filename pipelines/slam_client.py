#!/usr/bin/python3
"""pipelines/slam_client.py — the `leangate_client` command line, run from the repository.

A thin wrapper kept so that existing commands keep working; the code is the package
`leangate_client` beside this file (pip-installable: `pip install --no-deps ./pipelines`,
then `leangate-client` or `python3 -m leangate_client`). Python puts this script's directory
on sys.path, so the package is found without installing it.

    pipelines/slam_client.py clip.mp4                       # the embedded student
    pipelines/slam_client.py clip.mp4 --model other.onnx --threshold 0.6
    pipelines/slam_client.py clip.mp4 --mode annotate --csv scores.csv
    pipelines/slam_client.py --source videotestsrc --max-frames 100 --force-every 10

The plugin is found through GST_PLUGIN_PATH (or --plugin-path); when neither has it, this
wrapper also tries the repository's target/release and target/debug. Run with Debian's
/usr/bin/python3 (python3-gi, gir1.2-gstreamer-1.0, gir1.2-gst-plugins-base-1.0,
python3-numpy). `from slam_client import LeanGateSource` still works from this directory.
"""

import os
import sys

# The names the former single-file module offered, for `from slam_client import ...`.
from leangate_client import (
    FORCE_KEYFRAME_EVENT,
    META_NAME,
    REASONS,
    RESET_EVENT,
    STATS_MESSAGE,
    LeanGateSource,
    LeanGateStats,
    PipelineError,
    SetupError,
    buffer_to_rgb,
    ensure_plugin,
    meta_dict,
)
from leangate_client._gst import Gst
from leangate_client.cli import CSV_COLUMNS
from leangate_client.cli import main as _main

__all__ = [
    "CSV_COLUMNS",
    "FORCE_KEYFRAME_EVENT",
    "META_NAME",
    "REASONS",
    "RESET_EVENT",
    "STATS_MESSAGE",
    "Gst",
    "LeanGateSource",
    "LeanGateStats",
    "PipelineError",
    "SetupError",
    "buffer_to_rgb",
    "ensure_plugin",
    "meta_dict",
    "main",
]

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLUGIN_FALLBACKS = [os.path.join(REPO, "target", p) for p in ("release", "debug")]


def main(argv=None) -> int:
    return _main(argv, prog="slam_client", plugin_fallbacks=PLUGIN_FALLBACKS)


if __name__ == "__main__":
    sys.exit(main())
