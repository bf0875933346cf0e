"""LeanGate → Python hand-off: the frames a `leangate` pipeline keeps, as numpy arrays with their
LeanGateMeta, for a Python SLAM process (e.g. a MASt3R-SLAM front end)::

    from leangate_client import LeanGateSource
    with LeanGateSource("clip.mp4") as src:         # model=None: the embedded leangate-s
        for frame, meta in src:                    # frame: (H, W, 3) uint8 RGB
            slam.track(frame, timestamp=meta["pts"] / 1e9)
            if slam.lost_tracking():
                src.force_keyframe()               # keep the next frame whatever its score
    print(src.stats.frames_kept, src.stats.keep_ratio)   # the `leangate-stats` message at EOS

    save_kept("clip.mp4", "keyframes/")   # kept frames as kf_000000.jpg, ... + keyframes.csv/.json

Needs PyGObject with the Gst/GstVideo typelibs and numpy from the system (Debian:
python3-gi gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 python3-numpy) and the plugin on
GST_PLUGIN_PATH (or ``plugin_path=``). Importing this package needs neither: the bindings are
checked, with a message naming the packages, when a source is created.

Logging: records go to the ``leangate_client`` logger (a NullHandler is attached; configure
``logging`` to see them). GStreamer warnings from the pipeline are logged at WARNING.
"""

import logging as _logging

__version__ = "0.1.0"

from .errors import NotRunningError, PipelineError, SetupError  # noqa: E402
from .meta import (  # noqa: E402
    FEEDBACK_EVENT,
    FORCE_KEYFRAME_EVENT,
    META_KEYS,
    META_NAME,
    REASONS,
    RESET_EVENT,
    STATS_MESSAGE,
    meta_dict,
    meta_from_structure,
)
from .stats import LeanGateStats  # noqa: E402
from ._gst import ensure_plugin  # noqa: E402
from .keyframes import KeptFrameSaver  # noqa: E402
from .source import LeanGateSource, buffer_to_rgb, parse_test_uri, save_kept  # noqa: E402
from .push import FrameGate  # noqa: E402

_logging.getLogger(__name__).addHandler(_logging.NullHandler())

__all__ = [
    "__version__",
    "LeanGateSource",
    "FrameGate",
    "LeanGateStats",
    "KeptFrameSaver",
    "save_kept",
    "PipelineError",
    "SetupError",
    "NotRunningError",
    "ensure_plugin",
    "meta_dict",
    "meta_from_structure",
    "buffer_to_rgb",
    "parse_test_uri",
    "META_NAME",
    "META_KEYS",
    "STATS_MESSAGE",
    "FEEDBACK_EVENT",
    "FORCE_KEYFRAME_EVENT",
    "RESET_EVENT",
    "REASONS",
]
