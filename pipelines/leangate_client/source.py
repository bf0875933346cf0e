"""`LeanGateSource`: a pipeline ending in an appsink, iterated as ``(frame, meta)`` pairs.

The pipeline is built element by element::

    <source> ! leangate name=gate [...] ! videoconvert ! appsink name=sink caps=video/x-raw,format=RGB

where ``<source>`` is ``filesrc ! decodebin`` for a path, ``uridecodebin`` for a URI, and
``videotestsrc ! capsfilter`` for a ``test://`` pseudo-URI; the decoders' video pad is linked
to the gate when it appears (``pad-added``). With ``save_kept`` the gate's output is split by a
``tee`` into that appsink branch (behind a ``queue``) and the image-writing branch of
``keyframes.KeptFrameSaver``.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import urllib.parse
from typing import Any, Dict, Iterator, List, Mapping, Optional, Tuple

from . import _gst
from ._gst import PathLike, _make, _set, ensure_plugin
from .argtypes import (
    non_negative_int,
    non_negative_seconds,
    positive_seconds,
    threshold_or_model,
    uint32,
)
from .errors import NotRunningError, PipelineError, SetupError
from .keyframes import KeptFrameSaver
from .meta import FEEDBACK_EVENT, FORCE_KEYFRAME_EVENT, META_NAME, RESET_EVENT, meta_dict
from .stats import LeanGateStats

log = logging.getLogger(__name__)

MODES = ("drop", "annotate")
EXECUTION_PROVIDERS = ("auto", "cpu", "cuda", "tensorrt")
PRECISIONS = ("auto", "fp32", "int8")
TEST_PARAMETERS = ("num-buffers", "width", "height", "fps", "format")


def parse_test_uri(spec: str) -> Dict[str, Any]:
    """``test://PATTERN?num-buffers=N&width=W&height=H&fps=F&format=FMT`` → its parameters
    (pattern and integers checked here; the pattern is checked against videotestsrc later)."""
    u = urllib.parse.urlsplit(spec)
    pattern = (u.netloc or u.path.strip("/") or "ball").strip()
    q = {k: v[-1] for k, v in urllib.parse.parse_qs(u.query).items()}
    unknown = set(q) - set(TEST_PARAMETERS)
    if unknown:
        raise SetupError(
            f"unknown test:// parameter(s) {sorted(unknown)}; known: {sorted(TEST_PARAMETERS)}"
        )
    try:
        params = {
            "pattern": pattern,
            "num-buffers": int(q.get("num-buffers", "300")),
            "width": int(q.get("width", "640")),
            "height": int(q.get("height", "480")),
            "fps": int(q.get("fps", "30")),
            "format": q.get("format"),
        }
    except ValueError as e:
        raise SetupError(f"bad test:// parameter in {spec!r}: {e}") from None
    for k in ("width", "height", "fps"):
        if params[k] <= 0:
            raise SetupError(f"test:// {k} must be positive, not {params[k]}")
    return params


def buffer_to_rgb(buf, info) -> "Any":
    """Copy an RGB buffer into an (H, W, 3) uint8 array, honouring stride and plane offset
    (from the buffer's GstVideoMeta when it has one, else from the negotiated VideoInfo)."""
    Gst, GstVideo, np = _gst.Gst, _gst.GstVideo, _gst.np
    w, h = info.width, info.height
    stride, offset = info.stride[0], info.offset[0]
    vmeta = GstVideo.buffer_get_video_meta(buf)
    if vmeta is not None:
        stride, offset = vmeta.stride[0], vmeta.offset[0]
    ok, mapinfo = buf.map(Gst.MapFlags.READ)
    if not ok:
        raise PipelineError("cannot map the appsink buffer for reading")
    try:
        need = offset + stride * (h - 1) + 3 * w
        if len(mapinfo.data) < need:
            raise PipelineError(
                f"buffer holds {len(mapinfo.data)} bytes, a {w}x{h} RGB frame with stride "
                f"{stride} needs {need}"
            )
        view = np.ndarray(
            (h, w, 3), dtype=np.uint8, buffer=mapinfo.data, offset=offset, strides=(stride, 3, 1)
        )
        return np.ascontiguousarray(view)  # a copy: the buffer goes back to GStreamer
    finally:
        buf.unmap(mapinfo)


class _FrameIndex:
    """PTS → index of the frame in the input stream, for one consumer downstream of the gate:
    filled by the probe on the gate's sink pad, taken (in stream order) by the consumer."""

    def __init__(self):
        self._lock = threading.Lock()
        self._map: Dict[int, int] = {}

    def add(self, pts: int, index: int) -> None:
        with self._lock:
            self._map[pts] = index

    def take(self, pts: Optional[int]) -> Optional[int]:
        """The index of the frame with this PTS (None when unknown); entries for earlier PTS
        (frames the gate dropped) are forgotten."""
        if pts is None:
            return None
        with self._lock:
            index = self._map.pop(pts, None)
            for k in [k for k in self._map if k < pts]:
                del self._map[k]
        return index


class _InputCounter:
    """The probe on the gate's sink pad: counts the frames entering the gate and fills every
    consumer's ``_FrameIndex``. A separate object, not a method of the source: a GObject
    closure holding a bound method of the source would keep it alive forever (a reference
    cycle the garbage collector cannot see), and a streaming thread must never be the one that
    drops the source's last reference (its ``__del__`` stops the pipeline)."""

    def __init__(self, indexes: List[_FrameIndex]):
        self._lock = threading.Lock()
        self.indexes = indexes
        self.count = 0
        # End-of-stream has reached the gate (seen here before the gate handles it, so before
        # the frames it still holds come out): every frame is decided.
        self.eos = False

    def probe(self, pad, info):
        Gst = _gst.Gst
        buf = info.get_buffer() if info.type & Gst.PadProbeType.BUFFER else None
        if buf is not None:
            with self._lock:
                if buf.pts != Gst.CLOCK_TIME_NONE:
                    for index in self.indexes:
                        index.add(buf.pts, self.count)
                self.count += 1
        elif info.type & Gst.PadProbeType.EVENT_DOWNSTREAM:
            kind = info.get_event().type
            if kind == Gst.EventType.EOS:
                self.eos = True
            elif kind == Gst.EventType.FLUSH_STOP:
                self.eos = False
        return Gst.PadProbeReturn.OK


class _DecoderWatch:
    """Links a decoder's video pad to the gate when it appears (``pad-added``); what went wrong
    is left in ``error``. Separate from the source for the reason given in ``_InputCounter``."""

    def __init__(self, source: str):
        self.source = source
        self.error: Optional[str] = None  # set from the decoder's streaming thread

    def on_pad_added(self, dec, pad, gate) -> None:
        # Runs in a streaming thread: no exceptions out of here, errors go to self.error.
        caps = pad.get_current_caps() or pad.query_caps(None)
        name = caps.get_structure(0).get_name() if caps is not None and caps.get_size() else "?"
        if not name.startswith("video/"):
            log.debug("%s: ignoring pad %s (%s)", dec.get_name(), pad.get_name(), name)
            return
        target = gate.get_static_pad("sink")
        if target.is_linked():
            log.warning("%s: more than one video stream; only the first is gated", self.source)
            return
        ret = pad.link(target)
        if ret != _gst.Gst.PadLinkReturn.OK:
            self.error = (
                f"cannot link the decoded video ({caps.to_string()}) to leangate: "
                f"{ret.value_nick}"
            )
            log.debug(self.error)
        else:
            log.debug("%s: linked %s (%s) to leangate", dec.get_name(), pad.get_name(), name)

    def on_no_more_pads(self, dec, gate) -> None:
        if not gate.get_static_pad("sink").is_linked() and self.error is None:
            self.error = f"no video stream in {self.source}"


class LeanGateSource:
    """Iterate over the frames that leave `leangate` as ``(rgb_array, meta_dict)``.

    ``source``: a video file path (a str or an os.PathLike such as ``pathlib.Path``), a URI (file://, rtsp://, http://, ...: ``uridecodebin``) or
    ``test://PATTERN?num-buffers=N&width=W&height=H&fps=F`` (``videotestsrc``; ``"videotestsrc"``
    alone means ``test://ball``).

    ``model``, ``threshold``, ``mode``, ``warmup``, ``max_gap``, ``execution_provider``,
    ``precision`` (which build of the embedded student runs: auto, fp32, int8): the element's
    properties (None = the element's default; ``model=None`` is the embedded student
    leangate-s). ``stats_interval``: seconds between periodic `leangate-stats` messages (None:
    only at EOS). ``properties``: any other element properties by their GStreamer names, e.g.
    ``{"threads": 2, "device-id": 1}``; a value is converted to the property's type only when
    that is exact (text as gst-launch-1.0 reads it, such as ``"false"`` or ``"12"``; ``3.0`` for
    an integer), and a value of another type (``2.7`` or ``True`` for an integer, ``"maybe"``
    for a boolean) or out of the property's range is a SetupError, and so is ``name`` (the
    element is the source's ``gate``).

    ``max_frames`` stops after that many frames have been handed to the caller (the pipeline is
    then shut down without EOS, so no end-of-stream statistics are posted). Stopping the
    iteration early (``break``) shuts it down too, and a source dropped without ``close`` is
    closed when it is garbage-collected; with ``save_kept`` the pipeline is left to ``close``
    (the ``with`` block's end) so that an exception there still discards the run. With
    ``arrays=False`` the frame is None (cheaper, for score dumps). ``timeout_s``: give up when
    neither a frame nor EOS arrives for that long. ``plugin_path``: libgstleangate.so or its
    directory, when it is not on ``GST_PLUGIN_PATH`` (see ``ensure_plugin``).

    ``save_kept``: a directory to write every kept frame into as an image (``save_format``
    ``"jpg"`` or ``"png"``), with ``keyframes.csv`` and ``keyframes.json`` of their meta written
    when the source closes (see ``keyframes.KeptFrameSaver``; ``self.saver``). The directory is
    created when missing and must be empty unless ``overwrite`` (then an earlier run's output
    there is replaced; files the client did not write are never deleted). The run is written to
    a staging directory beside it and moved into it only when the run completes (the stream
    ended, or the caller stopped iterating); after a pipeline error or an exception that leaves
    the iteration or the ``with`` block (KeyboardInterrupt too), nothing is saved and the
    directory is as it was. Without ``overwrite``, a run that finds keyframes output in the
    directory when it comes to move its own in (another run saving there at the same time)
    does not replace it: ``close`` raises PipelineError and this run's output is discarded.
    Encoding runs in the pipeline, beside the appsink; iterate
    (``arrays=False`` is enough) to run the stream, or use ``save_kept()``. In annotate mode
    too only kept frames are saved; ``max_frames`` also caps the images.

    Each ``meta`` is a dict: ``frame`` (index of the frame in the input stream, counted at
    leangate's sink pad; None when the buffer has no PTS), ``pts`` (ns or None), ``utility``
    (float, NaN for a `first` frame), ``keep``, ``reason``, ``keyframe_index``,
    ``reference_pts`` (ns or None), ``frames_since_keyframe``, ``inference_us``, ``screened``.

    After iteration: ``stats`` (the last `leangate-stats` message, a ``LeanGateStats``, or
    None), ``frames_in`` (frames that entered the gate), ``received`` (frames handed out),
    ``forced_events`` (``force_keyframe`` events that reached the gate).

    ``force_keyframe``, ``reset`` and ``feedback`` need the running pipeline: they raise
    NotRunningError (a RuntimeError) before ``start`` (or the first iteration, or entering the
    ``with`` block), once the stream has ended (``ended``: the ``for`` loop ran to
    end-of-stream; ``state`` ``"ended"``, and ``forced_events`` is not counted: no frame would
    act on it) and after ``close``. A source runs once: ``start`` or iterating after ``close``
    raises it too.
    """

    def __init__(
        self,
        source: PathLike,
        model: Optional[PathLike] = None,
        threshold: Optional[float] = None,
        mode: str = "drop",
        warmup: Optional[int] = None,
        max_gap: Optional[int] = None,
        execution_provider: Optional[str] = None,
        max_frames: Optional[int] = None,
        arrays: bool = True,
        timeout_s: float = 60.0,
        *,
        stats_interval: Optional[float] = None,
        properties: Optional[Mapping[str, Any]] = None,
        precision: Optional[str] = None,
        plugin_path: Optional[PathLike] = None,
        plugin_fallbacks=(),
        save_kept: Optional[PathLike] = None,
        save_format: str = "jpg",
        overwrite: bool = False,
    ):
        if isinstance(source, os.PathLike):
            source = os.fspath(source)
        if not isinstance(source, str):
            raise SetupError(
                "source must be a file path (str or os.PathLike), a URI or \"videotestsrc\", "
                f"not {type(source).__name__} {source!r}"
            )
        self.plugin = ensure_plugin(plugin_path, plugin_fallbacks)
        if mode not in MODES:
            raise SetupError(f"mode must be drop or annotate, not {mode!r}")
        if execution_provider is not None and execution_provider not in EXECUTION_PROVIDERS:
            raise SetupError(
                f"execution_provider must be one of {', '.join(EXECUTION_PROVIDERS)}, "
                f"not {execution_provider!r}"
            )
        if precision is not None and precision not in PRECISIONS:
            raise SetupError(f"precision must be one of {', '.join(PRECISIONS)}, not {precision!r}")
        if model is not None and os.fspath(model) and not os.path.exists(model):
            raise SetupError(f"model not found: {os.fspath(model)}")
        for name, value, checker in (
            ("threshold", threshold, threshold_or_model),
            ("warmup", warmup, uint32),
            ("max_gap", max_gap, uint32),
            ("stats_interval", stats_interval, non_negative_seconds),
            ("max_frames", max_frames, non_negative_int),
        ):
            if value is not None:
                checker.check(name, value)
        positive_seconds.check("timeout_s", timeout_s)

        self.source = "test://ball" if source == "videotestsrc" else source
        self._check_source(self.source)
        self.saver: Optional[KeptFrameSaver] = None
        if save_kept is not None:
            self.saver = KeptFrameSaver(save_kept, save_format, overwrite)
            self.saver.limit = max_frames
        self.gate_properties: Dict[str, Any] = {"mode": mode}
        if model is not None and os.fspath(model):
            self.gate_properties["model"] = os.path.abspath(model)
        if threshold is not None:
            self.gate_properties["threshold"] = float(threshold)
        if warmup is not None:
            self.gate_properties["warmup"] = int(warmup)
        if max_gap is not None:
            self.gate_properties["max-gap"] = int(max_gap)
        if execution_provider:
            self.gate_properties["execution-provider"] = execution_provider
        if precision:
            self.gate_properties["precision"] = precision
        if stats_interval is not None:
            self.gate_properties["stats-interval"] = int(round(stats_interval * 1e9))
        if properties and "name" in properties:
            raise SetupError(
                "properties: `name` cannot be set: the source finds its leangate element by its "
                "name `gate`"
            )
        self.gate_properties.update(properties or {})

        self.mode = mode
        self.max_frames = max_frames
        self.arrays = arrays
        self.timeout_s = timeout_s
        self.stats: Optional[LeanGateStats] = None  # the last `leangate-stats` message
        self.received = 0  # frames handed to the caller
        self.forced_events = 0
        self.kept_received = 0  # frames handed out with keep set
        self._index = _FrameIndex()  # for the appsink branch
        self._sample_caps = None  # the appsink's caps, and their VideoInfo
        self._sample_info = None
        self._indexes = [self._index]  # every consumer's, filled by the sink-pad probe
        self._input = _InputCounter(self._indexes)
        self._decoder = _DecoderWatch(self.source)
        self._pipeline = None
        self._sink = None
        self._bus = None
        self._started = False
        self._closed = False  # close() was called: the source does not run (again)
        # One close() at a time (another thread's waits): a close() that finds the pipeline
        # gone discards a run no earlier close() finished, which must not be one still closing.
        self._close_lock = threading.RLock()
        # the run did not complete (an exception left the iteration or the `with` block, or
        # start failed): close() then discards the saved frames instead of committing them
        self._aborted = False
        self._eos = False  # the pipeline's EOS message was seen (every sink got EOS)
        self._ended = False  # the iteration ended at EOS (not at a close() from another thread)
        self._failed = False  # an ERROR message was seen

    # -- description and building --------------------------------------------------------
    @staticmethod
    def _check_source(source: str) -> None:
        if source.startswith("test://"):
            parse_test_uri(source)
        elif "://" in source:
            if source.startswith("file://"):
                path = _gst.Gst.uri_get_location(source) or ""
                if not os.path.exists(path):
                    raise SetupError(f"input file not found: {path}")
        else:
            if not os.path.exists(source):
                raise SetupError(f"input file not found: {source}")
            if os.path.isdir(source):
                raise SetupError(f"input is a directory, not a video file: {source}")

    @property
    def description(self) -> str:
        """The pipeline in gst-launch notation, for logs (informational: it is never parsed)."""
        s = self.source
        if s.startswith("test://"):
            p = parse_test_uri(s)
            head = (
                f"videotestsrc pattern={p['pattern']} num-buffers={p['num-buffers']} ! "
                f"{self._test_caps_string(p)}"
            )
        elif "://" in s:
            head = f"uridecodebin uri={s}"
        else:
            head = f"filesrc location={os.path.abspath(s)} ! decodebin"
        props = " ".join(f"{k}={v}" for k, v in self.gate_properties.items())
        tail = (
            "videoconvert ! appsink name=sink caps=video/x-raw,format=RGB sync=false "
            "max-buffers=8 drop=false"
        )
        if self.saver is None:
            return f"{head} ! leangate name=gate {props} ! {tail}"
        return (
            f"{head} ! leangate name=gate {props} ! tee name=split ! queue ! {tail} "
            f"split. ! {self.saver.description}"
        )

    @staticmethod
    def _test_caps_string(p: Mapping[str, Any]) -> str:
        caps = f"video/x-raw,width={p['width']},height={p['height']},framerate={p['fps']}/1"
        if p["format"]:
            caps += f",format={p['format']}"
        return caps

    def _build(self):
        pipeline = _gst.Gst.Pipeline.new(self._pipeline_name)
        gate, sink = self._build_tail(pipeline)
        self._build_source(pipeline, gate)
        return pipeline, gate, sink

    _pipeline_name = "leangate-client"

    def _build_tail(self, pipeline):
        """``leangate ! videoconvert ! appsink`` (RGB), added to ``pipeline`` and linked (with
        ``save_kept``: ``leangate ! tee``, one branch ``queue ! videoconvert ! appsink``, the
        other the saver's)."""
        Gst = _gst.Gst
        gate = _make("leangate", "gate")
        for k, v in self.gate_properties.items():
            _set(gate, k, v)
        pipeline.add(gate)
        head = gate
        if self.saver is not None:
            tee = _make("tee", "split")
            queue = _make("queue", "sink-queue")
            pipeline.add(tee)
            pipeline.add(queue)
            if not gate.link(tee) or not tee.link(queue):
                raise SetupError("cannot link leangate ! tee ! queue")
            index = _FrameIndex()
            self._indexes.append(index)
            self.saver.attach(pipeline, tee, index.take)
            head = queue
        convert = _make("videoconvert", "convert")
        sink = _make("appsink", "sink")
        _set(sink, "caps", Gst.Caps.from_string("video/x-raw,format=RGB"))
        _set(sink, "sync", False)
        _set(sink, "max-buffers", 8)
        _set(sink, "drop", False)
        for el in (convert, sink):
            pipeline.add(el)
        if not head.link(convert) or not convert.link(sink):
            raise SetupError("cannot link leangate ! videoconvert ! appsink")
        return gate, sink

    def _build_source(self, pipeline, gate) -> None:
        """The source part, added to ``pipeline`` and linked (or watched) into ``gate``."""
        Gst, GstVideo = _gst.Gst, _gst.GstVideo
        s = self.source
        if s.startswith("test://"):
            p = parse_test_uri(s)
            src = _make("videotestsrc", "src")
            _set(src, "pattern", p["pattern"])
            _set(src, "num-buffers", p["num-buffers"])
            if p["format"] and GstVideo.VideoFormat.from_string(p["format"]) == (
                GstVideo.VideoFormat.UNKNOWN
            ):
                raise SetupError(f"unknown video format in test:// URI: {p['format']!r}")
            caps = _make("capsfilter", "testcaps")
            _set(caps, "caps", Gst.Caps.from_string(self._test_caps_string(p)))
            pipeline.add(src)
            pipeline.add(caps)
            if not src.link(caps) or not caps.link(gate):
                raise SetupError(f"videotestsrc cannot produce {self._test_caps_string(p)}")
        elif "://" in s:
            dec = _make("uridecodebin", "src")
            _set(dec, "uri", s)
            pipeline.add(dec)
            self._watch_decoder(dec, gate)
        else:
            src = _make("filesrc", "src")
            _set(src, "location", os.path.abspath(s))
            dec = _make("decodebin", "decode")
            pipeline.add(src)
            pipeline.add(dec)
            if not src.link(dec):
                raise SetupError("cannot link filesrc ! decodebin")
            self._watch_decoder(dec, gate)

    def _watch_decoder(self, dec, gate) -> None:
        dec.connect("pad-added", self._decoder.on_pad_added, gate)
        dec.connect("no-more-pads", self._decoder.on_no_more_pads, gate)

    @property
    def frames_in(self) -> int:
        """Frames that entered the gate (counted by a probe on its sink pad)."""
        return self._input.count

    # -- control -------------------------------------------------------------------------
    def force_keyframe(self) -> bool:
        """Ask the gate to keep the next frame (what a SLAM back end does when it loses
        tracking): a `leangate-force-keyframe` custom event pushed upstream from the appsink.
        Frames already past the gate (queued for the appsink, or held and decided by its
        ``sharpness-lookback``) are not affected; the forced keep lands on the next frame the
        gate processes: with the default ``sharpness-lookback`` of 3, at least the 4th frame
        after the one in hand (0 makes it the next one, when nothing is queued between).
        Returns True when the event reached the gate with frames still to come, False when it
        cannot act: end-of-stream has already reached the gate (on the stream's last frames,
        which leave the gate after it has decided every frame: the last one, and with
        ``sharpness-lookback`` N the last N + 1 at least), or the pipeline is shutting down.
        Raises NotRunningError before the source is started, once the loop has run to the end
        of the stream (EOS: no frame would be kept for it) and after it is closed."""
        return self._push_upstream("force_keyframe()", FORCE_KEYFRAME_EVENT)

    def reset(self) -> bool:
        """Ask the gate to drop its reference (the next frame is kept as a new `first`).
        Returns and raises as ``force_keyframe``."""
        return self._push_upstream("reset()", RESET_EVENT)

    def feedback(self, tau: float) -> bool:
        """Report what the SLAM measured on a kept frame: ``tau`` = 1 - S between it and the
        keyframe before it (MASt3R-SLAM's match fractions, S = min(f_m, f_u)). Each report adds
        ``gain * (tau - threshold)`` to a sum (a keep reported above the threshold came late, one
        below came early; the error within +-0.25; the gain ``feedback-rate``, or for the
        stream's first reports more, report n at least 0.7 / (1 + n)) whose positive part raises
        the gate's utility from the next frame it processes (at most 0.3); more than 0.05 below 0
        it lowers it by the rest, at most the element's ``feedback-lower`` (0.15);
        ``gate.get_property("feedback-offset")`` says where it stands. Raises ValueError for a
        tau outside [0, 1]. Returns and raises as ``force_keyframe``: True when the report
        reached the gate, False when it could not, NotRunningError before start, after
        end-of-stream or after close."""
        tau = float(tau)
        if not 0.0 <= tau <= 1.0:
            raise ValueError(f"feedback: tau {tau} is not in [0, 1]")
        return self._push_upstream("feedback()", FEEDBACK_EVENT, tau=tau)

    def _state_error(self, call: str) -> NotRunningError:
        return NotRunningError(call, "closed" if self._closed else "not started")

    def _ended_error(self, call: str) -> NotRunningError:
        err = NotRunningError(call, "ended")
        # errors.NotRunningError words only "not started" and "closed"; say what this is.
        err.args = (
            f"{call}: the stream has ended (end-of-stream reached the appsink): no frame will "
            "come through the gate to act on it",
        )
        return err

    @property
    def ended(self) -> bool:
        """The iteration ran to end-of-stream (the ``for`` loop ended at EOS; not when the
        caller stopped early, ``max_frames`` stopped it or ``close`` from another thread did).
        ``force_keyframe``, ``reset`` and ``feedback`` then raise NotRunningError (``state``
        ``"ended"``); inside the loop, once end-of-stream has reached the gate (on the last
        frames, which the gate lets out after deciding every frame), they return False."""
        return self._ended

    def _push_upstream(self, call: str, name: str, **fields) -> bool:
        pipeline, sink = self._pipeline, self._sink  # close() may clear them meanwhile
        if pipeline is None:
            raise self._state_error(call)
        if self.ended:
            raise self._ended_error(call)
        Gst = _gst.Gst
        # Once end-of-stream has reached the gate every frame is decided: inside the loop (the
        # stream's last frames leave the gate after that) the call can act on nothing, and says
        # so. (EOS arriving between this check and the event is a window of one event's
        # travel; the call then acts on nothing too.)
        if self._input.eos:
            log.info("%s: end-of-stream has reached the gate: no frame left to act on it", call)
            return False
        gate = pipeline.get_by_name("gate")
        st = Gst.Structure.new_empty(name)
        for k, v in fields.items():
            st.set_value(k, v)
        ev = Gst.Event.new_custom(Gst.EventType.CUSTOM_UPSTREAM, st)
        seqnum = ev.get_seqnum()
        reached: List[bool] = []

        def seen(pad, info):
            e = info.get_event()
            if e is not None and e.get_seqnum() == seqnum:
                reached.append(True)
            return Gst.PadProbeReturn.OK

        # The event travels upstream in this thread (push_event on a *sink* pad sends it to its
        # upstream peer): a probe on the gate's source pad sees it arrive. Whether an element
        # further up handles it is beside the point (leangate acts on it, then forwards it to
        # the source, which usually ignores custom events).
        gate_src = gate.get_static_pad("src")
        probe = gate_src.add_probe(Gst.PadProbeType.EVENT_UPSTREAM, seen)
        try:
            sink.get_static_pad("sink").push_event(ev)
        finally:
            gate_src.remove_probe(probe)
        ok = bool(reached)
        if name == FORCE_KEYFRAME_EVENT and ok:
            self.forced_events += 1
        log.debug("sent %s upstream (reached the gate: %s)", name, ok)
        return ok

    @property
    def gate(self):
        """The `leangate` element while the pipeline exists (e.g. to change ``threshold``)."""
        return self._pipeline.get_by_name("gate") if self._pipeline else None

    # -- life cycle ----------------------------------------------------------------------
    def start(self) -> None:
        """Build the pipeline and set it playing (iterating or entering a ``with`` block does
        it). Raises NotRunningError after ``close``: a source runs its input once."""
        if self._closed:
            raise self._state_error("start()")
        if self._started:
            return
        Gst = _gst.Gst
        try:
            self._pipeline, gate, self._sink = self._build()
            self._bus = self._pipeline.get_bus()
            gate.get_static_pad("sink").add_probe(
                Gst.PadProbeType.BUFFER | Gst.PadProbeType.EVENT_DOWNSTREAM, self._input.probe
            )
            self._started = True
            log.info("plugin: %s", self.plugin)
            log.info("pipeline: %s", self.description)
            if self._pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
                self._raise_bus_error(default="the pipeline failed to start")
        except BaseException:
            self._aborted = True
            try:
                self.close()
            except PipelineError as e:  # the exception in flight says more
                log.debug("while stopping: %s", e)
            raise

    def close(self) -> None:
        """Stop the pipeline; the source cannot run again. With ``save_kept``, when the run
        completed (the stream ended, or the caller stopped iterating, or ``max_frames``): first
        let the image branch finish (at EOS, every kept frame; stopped early, at least the kept
        frames handed out so far), then write the tables and move the run's output into the
        directory, replacing an earlier run's there; raises PipelineError when that branch
        failed. When the run did not complete (a pipeline error, or an exception, such as
        KeyboardInterrupt, that left the iteration or the ``with`` block), nothing is saved:
        the directory is left as it was."""
        with self._close_lock:
            self._close()

    def _close(self) -> None:
        if self._pipeline is None:
            self._closed = True
            if self.saver is not None:
                # Never ran, or an earlier close() was interrupted (Ctrl-C, SIGTERM) before it
                # could finish: nothing to save (a no-op after finish or discard).
                self.saver.discard()
            return
        self._closed = True
        Gst = _gst.Gst
        error: Optional[PipelineError] = None
        failed = self._failed  # already reported: later errors are its consequences

        def note(e: PipelineError) -> None:
            nonlocal error
            if failed:
                log.debug("after the error: %s", e)
            elif error is None:
                error = e

        completed = False
        try:
            if self.saver is not None:
                if not self._aborted and not failed:
                    try:
                        self._settle_saver()
                    except PipelineError as e:
                        note(e)
                # READY stops the streaming threads but keeps the bus: the last reports are read.
                self._pipeline.set_state(Gst.State.READY)
                while True:
                    try:
                        self._drain_bus()
                        break
                    except PipelineError as e:
                        note(e)
            completed = True
        finally:
            self._pipeline.set_state(Gst.State.NULL)
            self._pipeline = None
            if self.saver is not None:
                if completed and not self._aborted and not self._failed and error is None:
                    self.saver.finish(self.source, self.frames_in, self.stats)
                else:
                    self.saver.discard()
        if error is not None:
            raise error

    def _settle_saver(self) -> None:
        """Wait (at most ``timeout_s``) until the image branch has written what it must."""
        deadline = time.monotonic() + self.timeout_s
        at_eos = self._sink.get_property("eos")
        while not self._failed:
            if self._eos or (not at_eos and self.saver.written >= self.kept_received):
                return
            if time.monotonic() > deadline:
                log.warning(
                    "the images of %d kept frames were not written within %.0f s",
                    self.saver.queued - self.saver.written,
                    self.timeout_s,
                )
                return
            msg = self._bus.timed_pop(100 * _gst.Gst.MSECOND)
            if msg is not None:
                self._handle_bus(msg)

    def __enter__(self) -> "LeanGateSource":
        self.start()
        return self

    def __exit__(self, exc_type, *exc) -> bool:
        # GeneratorExit: a generator around the block was closed early, like a `break`.
        if exc_type is None or issubclass(exc_type, GeneratorExit):
            self.close()
        else:
            self._aborted = True  # the run did not complete: nothing is saved
            try:
                self.close()
            except PipelineError as e:  # the exception in flight says more
                log.warning("while stopping: %s", e)
        return False

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # -- bus -----------------------------------------------------------------------------
    def _handle_bus(self, msg) -> None:
        Gst = _gst.Gst
        t = msg.type
        src = msg.src.get_name() if msg.src else "?"
        if t == Gst.MessageType.ERROR:
            self._failed = True
            err, dbg = msg.parse_error()
            if dbg:  # GStreamer's detail (source file, line, function): -vv
                log.debug("error from %s (debug): %s", src, dbg)
            if self.saver is not None and self.saver.owns(msg.src):
                # The system's reason (disk full, ...) is the last line of the detail.
                why = dbg.strip().splitlines()[-1].strip() if dbg and dbg.strip() else ""
                raise PipelineError(
                    f"cannot save the kept frames to {self.saver.directory}: {src}: "
                    f"{err.message}" + (f" ({why})" if why else "")
                )
            if src != "gate":  # the source part of the pipeline: name the input
                src = f"{self.source}: {src}"
            raise PipelineError(f"{src}: {err.message}")
        if t == Gst.MessageType.WARNING:
            w, dbg = msg.parse_warning()
            log.warning("warning from %s: %s", src, w.message)
            if dbg:
                log.debug("warning from %s (debug): %s", src, dbg)
        elif t == Gst.MessageType.EOS:
            self._eos = True
        elif t == Gst.MessageType.ELEMENT:
            if self.saver is not None and self.saver.on_message(msg):
                return
            stats = LeanGateStats.from_message(msg)
            if stats is not None:
                self.stats = stats
                log.debug("stats from %s: %s", src, stats)

    def _check_stream(self) -> None:
        if self._decoder.error is not None:
            raise PipelineError(self._decoder.error)

    def _drain_bus(self) -> None:
        while True:
            msg = self._bus.pop()
            if msg is None:
                return
            self._handle_bus(msg)

    def _raise_bus_error(self, default: str):
        while True:
            msg = self._bus.timed_pop(_gst.Gst.SECOND)
            if msg is None:
                self._check_stream()
                raise PipelineError(default)
            self._handle_bus(msg)

    # -- iteration -----------------------------------------------------------------------
    def __iter__(self) -> Iterator[Tuple[Any, Dict[str, Any]]]:
        Gst = _gst.Gst
        if self._closed:
            raise self._state_error("iterating")
        self.start()
        idle = 0.0
        stopped = False  # the iteration stopped before end-of-stream: shut the pipeline down
        try:
            while True:
                if self.max_frames is not None and self.received >= self.max_frames:
                    stopped = True
                    return
                sample = self._sink.emit("try-pull-sample", 100 * Gst.MSECOND)
                self._check_stream()
                self._drain_bus()
                if sample is None:
                    if self._closed:  # close() from another thread: no end-of-stream
                        return
                    if self._sink.get_property("eos"):
                        # EOS reached the sink; the stats message was posted before it.
                        self._ended = True
                        self._drain_bus()
                        return
                    idle += 0.1
                    if idle > self.timeout_s:
                        raise PipelineError(f"no frame and no EOS for {self.timeout_s:.0f} s")
                    continue
                idle = 0.0
                yield self._take_sample(sample)
        except GeneratorExit:  # the caller stopped iterating: not a failure
            stopped = True
            raise
        except BaseException:  # an error, or Ctrl-C while waiting for a frame
            self._aborted = True
            raise
        finally:
            self._drain_bus_quietly()
            if stopped and self.saver is None:
                # Not left running until the source is collected; with save_kept, close()
                # (the `with` block's end) decides whether the run is saved.
                self.close()

    def _take_sample(self, sample) -> Tuple[Any, Dict[str, Any]]:
        """An appsink sample as the ``(frame, meta)`` pair handed to the caller (counted)."""
        Gst, GstVideo = _gst.Gst, _gst.GstVideo
        buf = sample.get_buffer()
        caps = sample.get_caps()
        if self._sample_caps is None or not caps.is_equal(self._sample_caps):
            self._sample_caps = caps
            self._sample_info = GstVideo.VideoInfo.new_from_caps(caps)
            log.debug("appsink caps: %s", caps.to_string())
        meta = meta_dict(buf)
        if meta is None:
            raise PipelineError(
                f"a buffer arrived without {META_NAME}: something between leangate and "
                "the appsink dropped the meta"
            )
        pts = None if buf.pts == Gst.CLOCK_TIME_NONE else int(buf.pts)
        meta = {"frame": self._index.take(pts), "pts": pts, **meta}
        frame = buffer_to_rgb(buf, self._sample_info) if self.arrays else None
        self.received += 1
        self.kept_received += meta["keep"]
        return frame, meta

    def _drain_bus_quietly(self) -> None:
        if self._bus is None:
            return
        try:
            self._drain_bus()
        except PipelineError:
            pass


def save_kept(
    source: PathLike,
    directory: PathLike,
    format: str = "jpg",
    overwrite: bool = False,
    **kwargs: Any,
) -> KeptFrameSaver:
    """Run ``source`` through `leangate` to the end and write every kept frame into
    ``directory`` as ``kf_000000.jpg``, ... (``format`` ``"jpg"`` or ``"png"``) with
    ``keyframes.csv`` and ``keyframes.json`` of their meta: the frames to give COLMAP,
    nerfstudio or a Gaussian-splatting trainer. ``kwargs``: any ``LeanGateSource`` argument
    (``model``, ``threshold``, ``max_frames``, ...). Returns the saver: ``rows`` (one dict per
    image), ``csv_path``, ``json_path``, ``directory``. Raises SetupError (bad argument, a
    directory that is not empty without ``overwrite`` or cannot be written) or PipelineError;
    a run that fails (or is interrupted) saves nothing and leaves ``directory`` as it was."""
    kwargs.setdefault("arrays", False)
    src = LeanGateSource(
        source, save_kept=directory, save_format=format, overwrite=overwrite, **kwargs
    )
    with src:
        for _ in src:
            pass
    return src.saver
