"""The element's `leangate-stats` bus message as a typed, read-only value."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Dict, Iterator, Optional

from .meta import STATS_MESSAGE

# wire name -> (attribute, conversion, GType name used by the element)
_FIELDS = {
    "frames-in": ("frames_in", int, "guint64"),
    "frames-kept": ("frames_kept", int, "guint64"),
    "frames-screened": ("frames_screened", int, "guint64"),
    "frames-junk": ("frames_junk", int, "guint64"),
    "keep-ratio": ("keep_ratio", float, "gdouble"),
    "inference-mean-us": ("inference_mean_us", float, "gdouble"),
    "inference-p50-us": ("inference_p50_us", int, "guint64"),
    "inference-p99-us": ("inference_p99_us", int, "guint64"),
    "interval-frames-in": ("interval_frames_in", int, "guint64"),
    "interval-frames-kept": ("interval_frames_kept", int, "guint64"),
    "interval-frames-screened": ("interval_frames_screened", int, "guint64"),
    "interval-inference-mean-us": ("interval_inference_mean_us", float, "gdouble"),
    "interval-inference-p50-us": ("interval_inference_p50_us", int, "guint64"),
    "interval-inference-p99-us": ("interval_inference_p99_us", int, "guint64"),
    "execution-provider": ("execution_provider", str, "gchararray"),
    "server": ("server", str, "gchararray"),
    "server-model": ("server_model", str, "gchararray"),
    "server-requests": ("server_requests", int, "guint64"),
    "server-failed-requests": ("server_failed_requests", int, "guint64"),
    "server-latency-p50-us": ("server_latency_p50_us", int, "guint64"),
    "server-latency-p99-us": ("server_latency_p99_us", int, "guint64"),
    "model": ("model", str, "gchararray"),
    "model-precision": ("model_precision", str, "gchararray"),
    "threshold": ("threshold", float, "gdouble"),
    "feedback-offset": ("feedback_offset", float, "gdouble"),
}
_ATTR_TO_WIRE = {attr: wire for wire, (attr, _, _) in _FIELDS.items()}


@dataclasses.dataclass(frozen=True)
class LeanGateStats(Mapping):
    """One `leangate-stats` message (posted at EOS and every ``stats-interval``).

    The known fields are typed attributes (None when the message lacks one); fields this
    version does not know (fields added by later versions) are kept, unconverted, in
    ``extra`` under their wire names. The value is also a read-only mapping keyed by the wire
    names, known and extra alike, so code written against the earlier plain-dict ``stats``
    (``stats["frames-in"]``, ``stats.get("model")``) keeps working.
    """

    frames_in: Optional[int] = None
    frames_kept: Optional[int] = None
    #: frames the model did not run on: the geometric prior alone bounded their utility below the
    #: threshold (``screen``; dropped unless warmup, max-gap or a forced keyframe kept them)
    frames_screened: Optional[int] = None
    #: frames dropped because they carry no usable picture (dark, saturated, noise: ``reject-junk``)
    frames_junk: Optional[int] = None
    keep_ratio: Optional[float] = None
    inference_mean_us: Optional[float] = None
    inference_p50_us: Optional[int] = None
    inference_p99_us: Optional[int] = None
    #: since the previous message (the whole run for the first one)
    interval_frames_in: Optional[int] = None
    interval_frames_kept: Optional[int] = None
    interval_frames_screened: Optional[int] = None
    interval_inference_mean_us: Optional[float] = None
    interval_inference_p50_us: Optional[int] = None
    interval_inference_p99_us: Optional[int] = None
    execution_provider: Optional[str] = None
    #: remote scoring only (the element's ``server`` property set)
    server: Optional[str] = None
    server_model: Optional[str] = None
    server_requests: Optional[int] = None
    server_failed_requests: Optional[int] = None
    server_latency_p50_us: Optional[int] = None
    server_latency_p99_us: Optional[int] = None
    model: Optional[str] = None
    #: the arithmetic of the graph that runs: "fp32" or "int8" (the element's ``precision``)
    model_precision: Optional[str] = None
    threshold: Optional[float] = None
    #: what the consumer's ``leangate-feedback`` adds to the utility now (0 without feedback)
    feedback_offset: Optional[float] = None
    extra: Dict[str, Any] = dataclasses.field(default_factory=dict, hash=False)

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_mapping(cls, fields: "Mapping[str, Any]") -> "LeanGateStats":
        """From wire names to values (e.g. a dict read from a structure, or JSON)."""
        known: Dict[str, Any] = {}
        extra: Dict[str, Any] = {}
        for name, value in fields.items():
            spec = _FIELDS.get(name)
            if spec is None:
                extra[name] = value
            else:
                attr, conv, _ = spec
                known[attr] = None if value is None else conv(value)
        return cls(**known, extra=extra)

    @classmethod
    def from_structure(cls, s) -> "LeanGateStats":
        """From the message's ``Gst.Structure`` (its name must be ``leangate-stats``)."""
        if s.get_name() != STATS_MESSAGE:
            raise ValueError(f"not a {STATS_MESSAGE} structure: {s.get_name()}")
        return cls.from_mapping(
            {s.nth_field_name(i): s.get_value(s.nth_field_name(i)) for i in range(s.n_fields())}
        )

    @classmethod
    def from_message(cls, msg) -> Optional["LeanGateStats"]:
        """From a bus ``Gst.Message``; None when it is not a `leangate-stats` message."""
        s = msg.get_structure()
        if s is None or s.get_name() != STATS_MESSAGE:
            return None
        return cls.from_structure(s)

    # -- conversion --------------------------------------------------------------------------
    def to_dict(self) -> Dict[str, Any]:
        """Wire names to values (known fields that are set, then the extra ones)."""
        return dict(self.items())

    def to_structure(self):
        """A ``Gst.Structure`` named ``leangate-stats`` with the element's field types."""
        from ._gst import GObject, Gst, require_bindings

        require_bindings()
        s = Gst.Structure.new_empty(STATS_MESSAGE)
        for wire, (attr, _, gtype) in _FIELDS.items():
            value = getattr(self, attr)
            if value is not None:
                s.set_value(wire, GObject.Value(GObject.type_from_name(gtype), value))
        for wire, value in self.extra.items():
            s.set_value(wire, value)
        return s

    # -- Mapping over the wire names -------------------------------------------------------
    def __getitem__(self, key: str) -> Any:
        attr = _FIELDS.get(key)
        if attr is not None:
            value = getattr(self, attr[0])
            if value is not None:
                return value
            raise KeyError(key)
        return self.extra[key]

    def __iter__(self) -> Iterator[str]:
        for wire, (attr, _, _) in _FIELDS.items():
            if getattr(self, attr) is not None:
                yield wire
        yield from self.extra

    def __len__(self) -> int:
        return sum(1 for _ in self)
