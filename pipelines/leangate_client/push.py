"""`FrameGate`: frames the application holds (numpy arrays, or encoded JPEG/PNG bytes), pushed
one at a time through `leangate`, optionally each with its depth image::

    from leangate_client import FrameGate
    with FrameGate(depth_intrinsics=(525.0, 525.0, 319.5, 239.5), depth_scale=5000) as gate:
        for rgb, depth, t_ns in camera:                 # (H, W, 3) uint8, (H, W) uint16, ns
            for frame, meta in gate.push(rgb, t_ns, depth=depth):
                slam.add_keyframe(frame, meta)          # the kept frames that have left the gate
        for frame, meta in gate.finish():               # end of stream: the frames still held
            slam.add_keyframe(frame, meta)

The pipeline, built at the first ``push``::

    appsrc name=src ! videoconvert | decodebin ! leangate name=gate ! videoconvert ! appsink
    appsrc name=src ! ... ! m.sink  appsrc name=depth-src ! m.depth  leangatedepthmux name=m ! leangate ...

(the second with ``depth_intrinsics``). A frame leaves the gate later than it was pushed: the gate
holds the last ``sharpness-lookback`` frames (3 by default) so that a keep due on a blurred frame
can go to a sharper one, so ``push`` returns what has left by then and ``finish`` the rest;
``meta["frame"]`` is the frame's index among the pushes.
"""

from __future__ import annotations

import math
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

from . import _gst
from ._gst import _depth_mux, _make, _set
from .errors import PipelineError, SetupError
from .source import LeanGateSource

#: Raw formats ``push`` takes, with the (channels, numpy dtype) an array of each has.
RAW_FORMATS: Dict[str, Tuple[int, str]] = {
    "RGB": (3, "uint8"),
    "BGR": (3, "uint8"),
    "RGBA": (4, "uint8"),
    "BGRA": (4, "uint8"),
    "RGBx": (4, "uint8"),
    "BGRx": (4, "uint8"),
    "GRAY8": (1, "uint8"),
    "GRAY16_LE": (1, "uint16"),
}
#: Encoded formats ``push`` takes as bytes, with their caps.
ENCODED_FORMATS: Dict[str, str] = {"jpeg": "image/jpeg", "jpg": "image/jpeg", "png": "image/png"}

Frame = Tuple[Any, Dict[str, Any]]


def _packed(arr, bytes_per_pixel: int) -> bytes:
    """An (H, W[, C]) array as the bytes of a GStreamer raw frame: rows padded to a multiple of 4
    bytes (the default stride GStreamer assumes for a buffer without a GstVideoMeta)."""
    np = _gst.np
    h, w = arr.shape[:2]
    row = w * bytes_per_pixel
    stride = (row + 3) & ~3
    flat = np.ascontiguousarray(arr).view(np.uint8).reshape(h, row)
    if stride == row:
        return flat.tobytes()
    out = np.zeros((h, stride), dtype=np.uint8)
    out[:, :row] = flat
    return out.tobytes()


def raw_frame(image, format: Optional[str]) -> Tuple[str, bytes]:
    """``(caps, data)`` of an (H, W), (H, W, 1), (H, W, 3) or (H, W, 4) array in ``format`` (None:
    RGB, RGBA, GRAY8 or GRAY16_LE by its shape and dtype). Raises TypeError or ValueError naming
    what does not fit."""
    np = _gst.np
    if not isinstance(image, np.ndarray):
        raise TypeError(
            f"push: a frame is a numpy array or, with format='jpeg' or 'png', encoded bytes; not "
            f"{type(image).__name__}"
        )
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if (
        image.ndim not in (2, 3)
        or image.shape[0] < 1
        or image.shape[1] < 1
        or (image.ndim == 3 and image.shape[2] not in (3, 4))
    ):
        raise ValueError(f"push: a frame is (H, W), (H, W, 3) or (H, W, 4), not {image.shape}")
    channels = 1 if image.ndim == 2 else image.shape[2]
    if format is None:
        format = {(1, "uint8"): "GRAY8", (1, "uint16"): "GRAY16_LE", (3, "uint8"): "RGB"}.get(
            (channels, image.dtype.name), "RGBA" if (channels, image.dtype.name) == (4, "uint8") else ""
        )
        if not format:
            raise ValueError(
                f"push: cannot tell the format of a {image.dtype} array of shape {image.shape}: "
                f"give format= (one of {', '.join(RAW_FORMATS)})"
            )
    if format not in RAW_FORMATS:
        hint = ""
        if format == "GRAY16_BE":
            hint = " (give the values as a uint16 array: np.frombuffer(data, '>u2'))"
        raise ValueError(
            f"push: unknown format {format!r}; raw arrays: {', '.join(RAW_FORMATS)}; encoded "
            f"bytes: jpeg, png{hint}"
        )
    want_channels, want_dtype = RAW_FORMATS[format]
    if channels != want_channels or image.dtype.name != want_dtype:
        raise ValueError(
            f"push: a {format} frame is a {want_dtype} array with {want_channels} channel(s), "
            f"not {image.dtype} of shape {image.shape}"
        )
    if want_dtype == "uint16":
        image = image.astype("<u2", copy=False)
    bpp = want_channels * image.dtype.itemsize
    h, w = image.shape[:2]
    caps = f"video/x-raw,format={format},width={w},height={h},framerate=0/1"
    return caps, _packed(image, bpp)


def depth_frame(depth) -> Tuple[str, bytes]:
    """``(caps, data)`` of a depth image: (H, W) uint16 (GRAY16_LE, in the gate's ``depth_scale``
    units per metre) or float32/float64 metres (GRAY32F)."""
    np = _gst.np
    if not isinstance(depth, np.ndarray):
        raise TypeError(f"push: depth is a numpy array, not {type(depth).__name__}")
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[:, :, 0]
    if depth.ndim != 2 or depth.shape[0] < 1 or depth.shape[1] < 1:
        raise ValueError(f"push: depth is an (H, W) array, not shape {depth.shape}")
    if depth.dtype == np.uint16:
        fmt, arr = "GRAY16_LE", depth.astype("<u2", copy=False)
    elif depth.dtype in (np.float32, np.float64):
        fmt, arr = "GRAY32F", depth.astype("<f4", copy=False)
    else:
        raise ValueError(
            f"push: depth is uint16 (units of depth_scale per metre) or float32 metres, not "
            f"{depth.dtype}"
        )
    h, w = arr.shape
    return f"video/x-raw,format={fmt},width={w},height={h},framerate=0/1", _packed(arr, arr.dtype.itemsize)


class FrameGate(LeanGateSource):
    """Push frames through `leangate` one at a time and get back the ones that leave it.

    ``push(image, pts=None, *, depth=None, format=None)`` → the ``(frame, meta)`` pairs that have
    left the gate by then (drop mode: the kept ones; ``mode="annotate"``: every frame), and
    ``finish()`` → the rest (it ends the stream). Each ``meta`` is ``LeanGateSource``'s, with
    ``frame`` the index of the push (0, 1, ...) and ``pts`` the timestamp given.

    ``image``: an (H, W, 3) uint8 RGB array, or (H, W, 4) RGBA, (H, W) GRAY8 uint8 or GRAY16_LE
    uint16 values, or any of ``RAW_FORMATS`` named by ``format`` (BGR, BGRA, ...), or ``bytes``
    of a JPEG or PNG picture with ``format="jpeg"`` / ``"png"`` (decoded in the pipeline). The
    first push sets the kind (raw or which encoding) for the whole stream; the size and raw format
    may change between pushes (the gate then starts afresh, as on any caps change). ``pts``:
    nanoseconds, strictly increasing (None: 1/30 s after the previous one, 0 for the first).

    ``depth_intrinsics`` ``(fx, fy, cx, cy)`` of the colour frames: every push may give
    ``depth``, the frame's depth image: (H, W) uint16 in ``depth_scale`` units per metre (1000:
    millimetres, RealSense and Azure Kinect; 5000: TUM) or float32 metres, registered to the
    colour frame (same viewpoint; another size is resized by the gate). The gate then computes
    the teacher's overlap from it (the meta's ``depth`` is ``"used"``, or ``"lost"`` when the
    pose could not be tracked); a push without ``depth`` is gated colour-only (``"missing"``).

    A push waits while ``queue`` frames are still on their way into the gate (memory stays a few
    frames, whatever the caller's rate), at most ``timeout_s``. Errors in the pipeline raise
    PipelineError from ``push``/``finish``; a bad frame raises TypeError or ValueError before
    anything is sent, and the gate goes on. ``force_keyframe``, ``reset``, ``feedback`` and
    ``gate`` work between pushes (from the first push on). Everything else (``model``,
    ``threshold``, ``mode``, ``properties``, ``arrays``, ``save_kept``, ``plugin_path``, ...) is
    ``LeanGateSource``'s; there is no ``max_frames`` (stop pushing) and no iteration.
    """

    _pipeline_name = "leangate-push"

    def __init__(
        self,
        *,
        depth_intrinsics: Optional[Sequence[float]] = None,
        depth_scale: float = 1000.0,
        queue: int = 4,
        label: str = "pushed frames",
        **kwargs: Any,
    ):
        if "max_frames" in kwargs:
            raise SetupError("FrameGate has no max_frames: stop pushing, then call finish()")
        if not isinstance(queue, int) or isinstance(queue, bool) or queue < 1:
            raise SetupError(f"queue must be a positive integer, not {queue!r}")
        self._depth: Optional[Tuple[str, float]] = None
        if depth_intrinsics is not None:
            try:
                intr = [float(v) for v in depth_intrinsics]
            except (TypeError, ValueError):
                intr = []
            if len(intr) != 4 or not all(math.isfinite(v) for v in intr) or min(intr[:2]) <= 0:
                raise SetupError(
                    f"depth_intrinsics must be 4 numbers fx, fy, cx, cy (fx, fy > 0), not "
                    f"{depth_intrinsics!r}"
                )
            try:
                scale = float(depth_scale)
            except (TypeError, ValueError):
                scale = math.nan
            if not (math.isfinite(scale) and scale > 0):
                raise SetupError(
                    f"depth_scale must be positive (units per metre), not {depth_scale!r}"
                )
            self._depth = (",".join(repr(v) for v in intr), scale)
        super().__init__("appsrc", **kwargs)
        self.source = label
        self.queue = queue
        self._kind: Optional[str] = None  # "raw", or the encoded caps name
        self._caps: Optional[str] = None
        self._depth_caps: Optional[str] = None
        self._last_pts: Optional[int] = None
        self._pushed = 0
        self._finished = False
        self._want_start = False
        self._src = None
        self._depth_src = None

    @staticmethod
    def _check_source(source: str) -> None:
        pass

    @property
    def description(self) -> str:
        props = " ".join(f"{k}={v}" for k, v in self.gate_properties.items())
        head = "appsrc name=src ! " + ("videoconvert" if self._kind in (None, "raw") else "decodebin")
        if self._depth:
            head += (
                " ! m.sink appsrc name=depth-src ! m.depth leangatedepthmux name=m "
                f"intrinsics={self._depth[0]} depth-scale={self._depth[1]:g}"
            )
        return (
            f"{head} ! leangate name=gate {props} ! videoconvert ! appsink name=sink "
            "caps=video/x-raw,format=RGB sync=false"
        )

    # -- building ------------------------------------------------------------------------
    def start(self) -> None:
        """Nothing to build before the first push (which tells raw from encoded frames): the
        pipeline starts then."""
        if self._closed:
            raise self._state_error("start()")
        if self._kind is None:
            self._want_start = True
            return
        super().start()

    def _appsrc(self, name: str):
        Gst = _gst.Gst
        src = _make("appsrc", name)
        _set(src, "format", Gst.Format.TIME)
        _set(src, "is-live", False)
        _set(src, "block", False)  # push() waits itself, watching the bus (no hang on an error)
        _set(src, "max-bytes", 0)
        return src

    def _build_source(self, pipeline, gate) -> None:
        Gst = _gst.Gst
        self._src = self._appsrc("src")
        pipeline.add(self._src)
        target = gate
        if self._depth:
            mux = _depth_mux(self.plugin, self._depth[0], self._depth[1])
            self._depth_src = self._appsrc("depth-src")
            pipeline.add(mux)
            pipeline.add(self._depth_src)
            if self._depth_src.get_static_pad("src").link(
                mux.get_static_pad("depth")
            ) != Gst.PadLinkReturn.OK or not mux.link(gate):
                raise SetupError("cannot link appsrc ! leangatedepthmux ! leangate")
            target = mux
        if self._kind == "raw":
            conv = _make("videoconvert", "src-convert")
            pipeline.add(conv)
            if not self._src.link(conv) or not conv.link(target):
                raise SetupError("cannot link appsrc ! videoconvert ! leangate")
        else:
            dec = _make("decodebin", "decode")
            pipeline.add(dec)
            if not self._src.link(dec):
                raise SetupError("cannot link appsrc ! decodebin")
            self._watch_decoder(dec, target)

    # -- pushing -------------------------------------------------------------------------
    def push(
        self, image, pts: Optional[int] = None, *, depth=None, format: Optional[str] = None
    ) -> List[Frame]:
        """Send one frame (and its depth) into the gate; returns the frames that have left it
        since the last call (see the class)."""
        if self._closed:
            raise self._state_error("push()")
        if self._finished:
            raise self._ended_error("push()")
        if self._depth is None and depth is not None:
            raise SetupError("push: depth given, but the gate was made without depth_intrinsics")
        if isinstance(image, (bytes, bytearray, memoryview)):
            enc = ENCODED_FORMATS.get((format or "").lower())
            if enc is None:
                raise ValueError(
                    f"push: encoded bytes need format='jpeg' or 'png', not {format!r} (raw "
                    "frames are numpy arrays)"
                )
            kind, caps, data = enc, enc, bytes(image)
            if not data:
                raise ValueError("push: an empty picture")
        else:
            caps, data = raw_frame(image, format)
            kind = "raw"
        dcaps = ddata = None
        if depth is not None:
            dcaps, ddata = depth_frame(depth)
        if pts is None:
            pts = 0 if self._last_pts is None else self._last_pts + 33_333_333
        if isinstance(pts, bool) or not isinstance(pts, int):
            raise TypeError(f"push: pts is an int of nanoseconds, not {pts!r}")
        if pts < 0 or (self._last_pts is not None and pts <= self._last_pts):
            raise ValueError(
                f"push: pts must increase (nanoseconds, >= 0): {pts} after {self._last_pts}"
            )
        if self._kind is None:
            self._kind = kind
            super().start()
        elif kind != self._kind:
            raise ValueError(
                f"push: this gate takes {self._kind} frames (its first push); not {kind}"
            )
        out: List[Frame] = []
        self._wait_for_room(out)
        Gst = _gst.Gst
        if caps != self._caps:
            self._caps = caps
            self._src.set_property("caps", Gst.Caps.from_string(caps))
        self._send(self._src, data, pts)
        if self._depth_src is not None:
            if ddata is not None:
                if dcaps != self._depth_caps:
                    self._depth_caps = dcaps
                    self._depth_src.set_property("caps", Gst.Caps.from_string(dcaps))
                self._send(self._depth_src, ddata, pts)
            else:  # no depth for this frame: say so, the mux lets the colour frame go without
                self._depth_src.send_event(Gst.Event.new_gap(pts, Gst.CLOCK_TIME_NONE))
        self._last_pts = pts
        self._pushed += 1
        self._collect(out, 0)
        return out

    def _send(self, src, data: bytes, pts: int) -> None:
        Gst = _gst.Gst
        buf = Gst.Buffer.new_wrapped(data)
        buf.pts = pts
        ret = src.emit("push-buffer", buf)
        if ret != Gst.FlowReturn.OK:
            self._drain_bus()  # an ERROR message says why
            self._check_stream()
            raise PipelineError(f"{src.get_name()}: the frame was refused ({ret.value_nick})")

    def _wait_for_room(self, out: List[Frame]) -> None:
        deadline = time.monotonic() + self.timeout_s
        srcs = [s for s in (self._src, self._depth_src) if s is not None]
        while any(s.get_property("current-level-buffers") >= self.queue for s in srcs):
            # Short waits: in drop mode few frames reach the appsink, and the room comes from
            # the appsrc draining, not from a sample arriving.
            self._collect(out, 1)
            if time.monotonic() > deadline:
                raise PipelineError(
                    f"no frame went into the gate for {self.timeout_s:.0f} s (the pipeline is "
                    "stuck)"
                )

    def _collect(self, out: List[Frame], wait_ms: int) -> None:
        """Append the samples waiting at the appsink (the first waited for up to ``wait_ms``)."""
        Gst = _gst.Gst
        timeout = wait_ms * Gst.MSECOND
        try:
            while True:
                sample = self._sink.emit("try-pull-sample", timeout)
                self._check_stream()
                self._drain_bus()
                if sample is None:
                    return
                out.append(self._take_sample(sample))
                timeout = 0
        except BaseException:
            self._aborted = True
            raise

    def finish(self) -> List[Frame]:
        """End the stream: the frames still held or on their way leave the gate and are returned;
        ``stats`` is then the end-of-stream `leangate-stats`. ``push`` raises afterwards."""
        if self._closed:
            raise self._state_error("finish()")
        out: List[Frame] = []
        if self._finished:
            return out
        self._finished = True
        if self._pipeline is None:  # nothing was pushed
            self._ended = True
            return out
        for s in (self._src, self._depth_src):
            if s is not None:
                s.emit("end-of-stream")
        idle = 0.0
        while not self._sink.get_property("eos"):
            n = len(out)
            self._collect(out, 100)
            if len(out) == n:
                idle += 0.1
                if idle > self.timeout_s:
                    self._aborted = True
                    raise PipelineError(f"no frame and no EOS for {self.timeout_s:.0f} s")
            else:
                idle = 0.0
        self._collect(out, 0)
        self._ended = True
        self._drain_bus()
        return out

    @property
    def pushed(self) -> int:
        """Frames pushed so far."""
        return self._pushed

    def __iter__(self):
        raise TypeError("a FrameGate is not iterated: push() returns the frames that left it")

    def __enter__(self) -> "FrameGate":
        self.start()
        return self


__all__ = ["FrameGate", "RAW_FORMATS", "ENCODED_FORMATS", "raw_frame", "depth_frame"]
