"""Names shared with the element, and the per-buffer `LeanGateMeta` as a dict."""

from __future__ import annotations

from typing import Any, Dict, Optional

U64_MAX = (1 << 64) - 1
META_NAME = "LeanGateMeta"
FORCE_KEYFRAME_EVENT = "leangate-force-keyframe"
RESET_EVENT = "leangate-reset"
STATS_MESSAGE = "leangate-stats"
REASONS = ("first", "warmup", "score", "max-gap", "forced", "error")

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
    }


def meta_dict(buf) -> Optional[Dict[str, Any]]:
    """LeanGateMeta of a ``Gst.Buffer`` as a dict (None when the buffer carries none)."""
    m = buf.get_custom_meta(META_NAME)
    if m is None:
        return None
    return meta_from_structure(m.get_structure())
