"""Names shared with the element, and the per-buffer `LeanGateMeta` as a dict."""

from __future__ import annotations

import math
from typing import Any, Dict, Optional

U64_MAX = (1 << 64) - 1
META_NAME = "LeanGateMeta"
FORCE_KEYFRAME_EVENT = "leangate-force-keyframe"
RESET_EVENT = "leangate-reset"
FEEDBACK_EVENT = "leangate-feedback"
STATS_MESSAGE = "leangate-stats"
REASONS = (
    "first",
    "warmup",
    "score",
    "max-gap",
    "forced",
    "error",
    "junk",
    "deferred",
    "sharper",
)
#: The meta's ``quality``: ``usable``, junk (never kept), or ``textureless`` (utility 0).
QUALITIES = ("usable", "dark", "saturated", "noise", "textureless", "corrupted")
#: The meta's ``depth``: what depth did for the frame (RGB-D input; ``none`` without depth).
DEPTH_USES = ("none", "used", "missing", "lost")

#: Keys of the dicts yielded by ``LeanGateSource`` (``frame`` and ``pts`` come from the
#: stream, the rest from the buffer's LeanGateMeta).
META_KEYS = (
    "frame",
    "pts",
    "utility",
    "keep",
    "reason",
    "keyframe_index",
    "reference_pts",
    "frames_since_keyframe",
    "inference_us",
    "screened",
    "quality",
    "depth",
)


def meta_from_structure(s) -> Dict[str, Any]:
    """The fields of a LeanGateMeta ``Gst.Structure`` as a dict with Python names."""
    ref = s.get_value("reference-pts")
    return {
        "utility": float(s.get_value("utility")),
        "keep": bool(s.get_value("keep")),
        "reason": s.get_value("reason"),
        "keyframe_index": int(s.get_value("keyframe-index")),
        "reference_pts": None if ref is None or ref == U64_MAX else int(ref),
        "frames_since_keyframe": int(s.get_value("frames-since-keyframe")),
        "inference_us": int(s.get_value("inference-us")),
        # the model did not run: the prior alone bounded the utility (then this bound) below the
        # threshold (the element's `screen`); dropped unless warmup, max-gap or a forced keyframe kept it
        "screened": bool(s.get_value("screened")) if s.has_field("screened") else False,
        # whether the frame carries a usable picture (the element's `reject-junk`)
        "quality": s.get_value("quality") if s.has_field("quality") else "usable",
        # what depth did (RGB-D input): none, used (the metric gate's utility), missing, lost
        "depth": s.get_value("depth") if s.has_field("depth") else "none",
    }


def meta_dict(buf) -> Optional[Dict[str, Any]]:
    """LeanGateMeta of a ``Gst.Buffer`` as a dict (None when the buffer carries none)."""
    m = buf.get_custom_meta(META_NAME)
    if m is None:
        return None
    return meta_from_structure(m.get_structure())


#: Columns of the per-frame tables (``leangate-client --csv`` and the saved keyframes' CSV),
#: in order; ``meta_row`` gives them from a meta dict.
ROW_COLUMNS = (
    "frame",
    "pts_ns",
    "utility",
    "keep",
    "reason",
    "keyframe_index",
    "frames_since_keyframe",
    "inference_us",
    "depth",
)


def meta_row(meta: Dict[str, Any]) -> Dict[str, Any]:
    """A meta dict as yielded by ``LeanGateSource`` → the ``ROW_COLUMNS`` values (Python values:
    None for a missing frame index or PTS, NaN utility for a `first` frame)."""
    return {
        "frame": meta["frame"],
        "pts_ns": meta["pts"],
        "utility": meta["utility"],
        "keep": bool(meta["keep"]),
        "reason": meta["reason"],
        "keyframe_index": meta["keyframe_index"],
        "frames_since_keyframe": meta["frames_since_keyframe"],
        "inference_us": meta["inference_us"],
        "depth": meta.get("depth", "none"),
    }


def csv_value(v: Any) -> str:
    """One table cell: empty for None, ``nan`` / 6 decimals for a float, 0/1 for a bool."""
    if v is None:
        return ""
    if isinstance(v, bool):
        return str(int(v))
    if isinstance(v, float):
        return "nan" if math.isnan(v) else f"{v:.6f}"
    return str(v)


def json_value(v: Any) -> Any:
    """A value for JSON: NaN (not valid JSON) becomes null."""
    return None if isinstance(v, float) and math.isnan(v) else v
