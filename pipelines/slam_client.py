#!/usr/bin/python3
"""LeanGate → Python hand-off: kept frames as numpy arrays plus their LeanGateMeta.

This is what a Python SLAM process (e.g. a MASt3R-SLAM front end) needs from LeanGate: it builds

    <source> ! leangate [model=...] ! videoconvert ! video/x-raw,format=RGB ! appsink

and yields ``(frame, meta)`` pairs where ``frame`` is an ``(H, W, 3)`` ``uint8`` RGB array (row
padding of the GStreamer buffer removed) and ``meta`` is a dict with the buffer's ``LeanGateMeta``
fields plus the frame's position in the stream:

    from slam_client import LeanGateSource
    with LeanGateSource("clip.mp4") as src:        # model=None: the embedded leangate-s
        for frame, meta in src:
            slam.track(frame, timestamp=meta["pts"] / 1e9)
            if slam.lost_tracking():
                src.force_keyframe()          # keep the next frame whatever its score
        print(src.stats)                      # the element's `leangate-stats` message at EOS

``meta`` keys: ``frame`` (index of the frame in the input stream, counted at leangate's sink
pad), ``pts`` (ns or None), ``utility`` (float, NaN for the first frame), ``keep`` (bool),
``reason`` (first|warmup|score|max-gap|forced|error), ``keyframe_index``, ``reference_pts``
(ns or None), ``frames_since_keyframe``, ``inference_us``.

Sources: a file path (``filesrc ! decodebin``), a URI (``uridecodebin``: file://, rtsp://,
http://, ...), or the test pseudo-URI ``test://PATTERN?num-buffers=N&width=W&height=H&fps=F``
(``videotestsrc``; also ``--source videotestsrc``), which needs no data.

Command line (runs with Debian's /usr/bin/python3 + python3-gi, gir1.2-gstreamer-1.0,
gir1.2-gst-plugins-base-1.0, python3-numpy; the plugin is found through GST_PLUGIN_PATH, and
this script adds the repository's target/{debug,release} when the plugin is not found):

    pipelines/slam_client.py clip.mp4                       # the embedded student
    pipelines/slam_client.py clip.mp4 --model other.onnx --threshold 0.6
    pipelines/slam_client.py clip.mp4 --mode annotate --csv scores.csv
    pipelines/slam_client.py --source videotestsrc --max-frames 100 --force-every 10

It prints one line per received frame (unless --quiet) and a summary line at the end:

    summary: frames-in=82 received=31 kept=31 forced=0 shape=480x854x3 ...

Exit status: 0 on success, 1 on a pipeline error, 2 on a usage/setup error (missing file,
missing plugin, missing Python bindings).
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import urllib.parse

U64_MAX = (1 << 64) - 1
META_NAME = "LeanGateMeta"
FORCE_KEYFRAME_EVENT = "leangate-force-keyframe"
RESET_EVENT = "leangate-reset"
STATS_MESSAGE = "leangate-stats"
REASONS = ("first", "warmup", "score", "max-gap", "forced", "error")
CSV_COLUMNS = (
    "frame",
    "pts_ns",
    "utility",
    "keep",
    "reason",
    "keyframe_index",
    "frames_since_keyframe",
    "inference_us",
)
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class SetupError(Exception):
    """Missing bindings, plugin or input: a usage problem, not a pipeline failure."""


class PipelineError(Exception):
    """An ERROR message from the pipeline (element name, message and debug text)."""


try:
    import numpy as np
    import gi

    gi.require_version("Gst", "1.0")
    gi.require_version("GstVideo", "1.0")
    from gi.repository import GLib, Gst, GstVideo  # noqa: E402
except (ImportError, ValueError) as _e:  # pragma: no cover - exercised only without bindings
    _IMPORT_ERROR = _e
    np = None
    Gst = None
else:
    _IMPORT_ERROR = None


def _require_bindings():
    if _IMPORT_ERROR is not None:
        raise SetupError(
            f"cannot import the GStreamer Python bindings or numpy ({_IMPORT_ERROR}); on Debian/"
            "Ubuntu: apt install python3-gi gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 "
            "python3-numpy (and run with /usr/bin/python3, not a virtualenv without them)"
        )


def ensure_plugin():
    """Gst.init and make sure `leangate` is found, adding the repo's build dirs if needed."""
    _require_bindings()
    if not Gst.is_initialized():
        Gst.init(None)
    if Gst.ElementFactory.find("leangate") is not None:
        return
    registry = Gst.Registry.get()
    tried = []
    for profile in ("release", "debug"):
        d = os.path.join(REPO, "target", profile)
        lib = os.path.join(d, "libgstleangate.so")
        if os.path.exists(lib):
            tried.append(lib)
            plugin = Gst.Plugin.load_file(lib)
            registry.add_plugin(plugin)
            if Gst.ElementFactory.find("leangate") is not None:
                return
    raise SetupError(
        "GStreamer element `leangate` not found. Build the plugin (`cargo build` in "
        f"{REPO}) and set GST_PLUGIN_PATH to the directory holding libgstleangate.so, e.g. "
        f"export GST_PLUGIN_PATH={os.path.join(REPO, 'target', 'debug')}"
        + (f" (tried loading {', '.join(tried)})" if tried else "")
    )


def _test_source(spec: str) -> str:
    """`test://PATTERN?num-buffers=N&width=W&height=H&fps=F` → a videotestsrc description."""
    u = urllib.parse.urlsplit(spec)
    pattern = (u.netloc or u.path.strip("/") or "ball").strip()
    q = {k: v[-1] for k, v in urllib.parse.parse_qs(u.query).items()}
    known = {"num-buffers", "width", "height", "fps", "format"}
    unknown = set(q) - known
    if unknown:
        raise SetupError(f"unknown test:// parameter(s) {sorted(unknown)}; known: {sorted(known)}")
    try:
        n = int(q.get("num-buffers", "300"))
        w = int(q.get("width", "640"))
        h = int(q.get("height", "480"))
        fps = int(q.get("fps", "30"))
    except ValueError as e:
        raise SetupError(f"bad test:// parameter in {spec!r}: {e}") from None
    fmt = q.get("format")
    caps = f"video/x-raw,width={w},height={h},framerate={fps}/1"
    if fmt:
        caps += f",format={fmt}"
    return f"videotestsrc pattern={pattern} num-buffers={n} ! {caps}"


def source_description(source: str) -> str:
    """The gst-launch description of the decoding part for a path, URI or test:// spec."""
    if source == "videotestsrc":
        source = "test://ball"
    if source.startswith("test://"):
        return _test_source(source)
    if "://" in source:
        if source.startswith("file://"):
            path = Gst.uri_get_location(source) or ""
            if not os.path.exists(path):
                raise SetupError(f"input file not found: {path}")
        return f'uridecodebin uri="{source}"'
    if not os.path.exists(source):
        raise SetupError(f"input file not found: {source}")
    if os.path.isdir(source):
        raise SetupError(f"input is a directory, not a video file: {source}")
    loc = os.path.abspath(source).replace("\\", "\\\\").replace('"', '\\"')
    return f'filesrc location="{loc}" ! decodebin'


def meta_dict(buf) -> dict | None:
    """LeanGateMeta of a Gst.Buffer as a dict (None when the buffer carries none)."""
    m = buf.get_custom_meta(META_NAME)
    if m is None:
        return None
    s = m.get_structure()
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


def buffer_to_rgb(buf, info) -> "np.ndarray":
    """Copy an RGB buffer into an (H, W, 3) uint8 array, honouring stride and plane offset
    (from the buffer's GstVideoMeta when it has one, else from the negotiated VideoInfo)."""
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


class LeanGateSource:
    """Iterate over the frames that leave `leangate` as ``(rgb_array, meta_dict)``.

    Parameters mirror the element's properties (None = the element's default). With
    ``arrays=False`` the frame is None (cheaper, for score dumps). ``max_frames`` stops after
    that many frames have entered the gate (the pipeline is then shut down without EOS, so no
    end-of-stream statistics are posted).
    """

    def __init__(
        self,
        source: str,
        model: str | None = None,
        threshold: float | None = None,
        mode: str = "drop",
        warmup: int | None = None,
        max_gap: int | None = None,
        execution_provider: str | None = None,
        max_frames: int | None = None,
        arrays: bool = True,
        timeout_s: float = 60.0,
    ):
        ensure_plugin()
        if mode not in ("drop", "annotate"):
            raise SetupError(f"mode must be drop or annotate, not {mode!r}")
        if model and not os.path.exists(model):
            raise SetupError(f"model not found: {model}")
        if threshold is not None and not (threshold == -1 or 0.0 <= threshold <= 1.0):
            raise SetupError(f"threshold must be -1 or in [0, 1], not {threshold}")
        props = [f"mode={mode}"]
        if model:
            props.append('model="{}"'.format(os.path.abspath(model).replace('"', '\\"')))
        if threshold is not None:
            props.append(f"threshold={threshold}")
        if warmup is not None:
            props.append(f"warmup={int(warmup)}")
        if max_gap is not None:
            props.append(f"max-gap={int(max_gap)}")
        if execution_provider:
            props.append(f"execution-provider={execution_provider}")
        self.description = (
            f"{source_description(source)} ! leangate name=gate {' '.join(props)} ! "
            "videoconvert ! video/x-raw,format=RGB ! "
            "appsink name=sink sync=false max-buffers=8 drop=false"
        )
        self.mode = mode
        self.max_frames = max_frames
        self.arrays = arrays
        self.timeout_s = timeout_s
        self.stats: dict | None = None  # the last `leangate-stats` message, as a dict
        self.frames_in = 0  # frames that entered the gate (sink-pad probe)
        self.received = 0  # frames handed to the caller
        self.forced_events = 0
        self._pts_to_index: dict[int, int] = {}
        self._pipeline = None
        self._started = False

    # -- control -----------------------------------------------------------------------
    def force_keyframe(self) -> bool:
        """Ask the gate to keep the next frame (what a SLAM back end does when it loses
        tracking): a `leangate-force-keyframe` custom event pushed upstream from the appsink.
        Frames already past the gate (queued for the appsink) are not affected; the forced
        keep lands on the next frame the gate processes. Returns whether an upstream element
        reported handling the event (often False: see _push_upstream)."""
        return self._push_upstream(FORCE_KEYFRAME_EVENT)

    def reset(self) -> bool:
        """Ask the gate to drop its reference (the next frame is kept as a new `first`)."""
        return self._push_upstream(RESET_EVENT)

    def _push_upstream(self, name: str) -> bool:
        if self._pipeline is None:
            return False
        ev = Gst.Event.new_custom(Gst.EventType.CUSTOM_UPSTREAM, Gst.Structure.new_empty(name))
        # push_event on a *sink* pad sends the event to its upstream peer. leangate notes the
        # event and forwards it further upstream, where sources usually do not handle custom
        # events, so the result is often False even though the gate acted on it.
        ok = self._sink.get_static_pad("sink").push_event(ev)
        if name == FORCE_KEYFRAME_EVENT:
            self.forced_events += 1
        return ok

    @property
    def gate(self):
        return self._pipeline.get_by_name("gate") if self._pipeline else None

    # -- life cycle --------------------------------------------------------------------
    def start(self):
        if self._started:
            return
        try:
            self._pipeline = Gst.parse_launch(self.description)
        except GLib.Error as e:
            raise SetupError(f"cannot build the pipeline `{self.description}`: {e.message}")
        self._sink = self._pipeline.get_by_name("sink")
        self._bus = self._pipeline.get_bus()
        gate_sink = self._pipeline.get_by_name("gate").get_static_pad("sink")
        gate_sink.add_probe(Gst.PadProbeType.BUFFER, self._count_input)
        self._started = True
        if self._pipeline.set_state(Gst.State.PLAYING) == Gst.StateChangeReturn.FAILURE:
            self._raise_bus_error(default="the pipeline failed to start")

    def _count_input(self, pad, info):
        buf = info.get_buffer()
        if buf is not None:
            if buf.pts != Gst.CLOCK_TIME_NONE:
                self._pts_to_index[buf.pts] = self.frames_in
            self.frames_in += 1
        return Gst.PadProbeReturn.OK

    def close(self):
        if self._pipeline is not None:
            self._pipeline.set_state(Gst.State.NULL)
            self._pipeline = None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # -- bus -----------------------------------------------------------------------------
    def _handle_bus(self, msg) -> None:
        t = msg.type
        if t == Gst.MessageType.ERROR:
            err, dbg = msg.parse_error()
            src = msg.src.get_name() if msg.src else "?"
            raise PipelineError(f"{src}: {err.message}" + (f" ({dbg})" if dbg else ""))
        if t == Gst.MessageType.WARNING:
            w, dbg = msg.parse_warning()
            src = msg.src.get_name() if msg.src else "?"
            print(f"warning from {src}: {w.message}", file=sys.stderr)
        elif t == Gst.MessageType.ELEMENT:
            s = msg.get_structure()
            if s is not None and s.get_name() == STATS_MESSAGE:
                self.stats = {s.nth_field_name(i): s.get_value(s.nth_field_name(i))
                              for i in range(s.n_fields())}

    def _drain_bus(self) -> None:
        while True:
            msg = self._bus.pop()
            if msg is None:
                return
            self._handle_bus(msg)

    def _raise_bus_error(self, default: str):
        while True:
            msg = self._bus.timed_pop(Gst.SECOND)
            if msg is None:
                raise PipelineError(default)
            self._handle_bus(msg)

    # -- iteration -----------------------------------------------------------------------
    def __iter__(self):
        self.start()
        info = None
        caps = None
        idle = 0.0
        try:
            while True:
                if self.max_frames is not None and self.received >= self.max_frames:
                    return
                sample = self._sink.emit("try-pull-sample", 100 * Gst.MSECOND)
                self._drain_bus()
                if sample is None:
                    if self._sink.get_property("eos"):
                        # EOS reached the sink; the stats message was posted before it.
                        self._drain_bus()
                        return
                    idle += 0.1
                    if idle > self.timeout_s:
                        raise PipelineError(f"no frame and no EOS for {self.timeout_s:.0f} s")
                    continue
                idle = 0.0
                buf = sample.get_buffer()
                if sample.get_caps() is not caps:
                    caps = sample.get_caps()
                    info = GstVideo.VideoInfo.new_from_caps(caps)
                meta = meta_dict(buf)
                if meta is None:
                    raise PipelineError(
                        f"a buffer arrived without {META_NAME}: something between leangate and "
                        "the appsink dropped the meta"
                    )
                pts = None if buf.pts == Gst.CLOCK_TIME_NONE else int(buf.pts)
                index = self._pts_to_index.pop(pts, None) if pts is not None else None
                if pts is not None:
                    # Forget entries of frames the gate dropped (they are older than this one).
                    for k in [k for k in self._pts_to_index if k < pts]:
                        del self._pts_to_index[k]
                meta = {"frame": index, "pts": pts, **meta}
                frame = buffer_to_rgb(buf, info) if self.arrays else None
                self.received += 1
                yield frame, meta
        finally:
            self._drain_bus_quietly()

    def _drain_bus_quietly(self):
        try:
            self._drain_bus()
        except PipelineError:
            pass


def _fmt_util(u: float) -> str:
    return "nan" if math.isnan(u) else f"{u:.6f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description="Run a video through leangate and receive the kept frames as numpy arrays "
        "with their LeanGateMeta (the hand-off to a Python SLAM process).",
    )
    ap.add_argument(
        "input",
        nargs="?",
        help="video file, URI, or test://PATTERN?num-buffers=N&width=W&height=H (videotestsrc)",
    )
    ap.add_argument(
        "--source",
        choices=("auto", "videotestsrc"),
        default="auto",
        help="videotestsrc: ignore INPUT and use test://ball (or INPUT if it is a test:// URI)",
    )
    ap.add_argument(
        "--model",
        default=os.environ.get("LEANGATE_MODEL") or None,
        help="LeanGate pair model (.onnx); default $LEANGATE_MODEL, else the element's default",
    )
    ap.add_argument("--threshold", type=float, default=None,
                    help="keep threshold in [0,1]; default: the model's")
    ap.add_argument("--mode", choices=("drop", "annotate"), default="drop")
    ap.add_argument("--warmup", type=int, default=None)
    ap.add_argument("--max-gap", type=int, default=None)
    ap.add_argument("--execution-provider", choices=("auto", "cpu", "cuda", "tensorrt"))
    ap.add_argument("--csv", metavar="OUT", help="write one row per received frame to OUT")
    ap.add_argument("--max-frames", type=int, default=None,
                    help="stop after receiving this many frames")
    ap.add_argument("--force-every", type=int, default=0, metavar="N",
                    help="send a leangate-force-keyframe event upstream after every N received "
                    "frames (what a SLAM process does when it loses tracking)")
    ap.add_argument("--quiet", action="store_true", help="no per-frame lines, only the summary")
    args = ap.parse_args(argv)

    if args.source == "videotestsrc":
        src = args.input if args.input and args.input.startswith("test://") else "test://ball"
    elif args.input:
        src = args.input
    else:
        ap.error("INPUT is required (or --source videotestsrc)")
    if args.force_every < 0:
        ap.error("--force-every must be >= 0")

    out = None
    writer = None
    kept = forced = 0
    shapes = set()
    try:
        source = LeanGateSource(
            src,
            model=args.model,
            threshold=args.threshold,
            mode=args.mode,
            warmup=args.warmup,
            max_gap=args.max_gap,
            execution_provider=args.execution_provider,
            max_frames=args.max_frames,
            arrays=True,
        )
        if args.csv:
            out = open(args.csv, "w", newline="")
            writer = csv.writer(out)
            writer.writerow(CSV_COLUMNS)
        with source:
            for frame, m in source:
                shapes.add(f"{frame.shape[0]}x{frame.shape[1]}x{frame.shape[2]}:{frame.dtype}")
                kept += m["keep"]
                forced += m["reason"] == "forced"
                if writer:
                    writer.writerow([
                        "" if m["frame"] is None else m["frame"],
                        "" if m["pts"] is None else m["pts"],
                        _fmt_util(m["utility"]),
                        int(m["keep"]),
                        m["reason"],
                        m["keyframe_index"],
                        m["frames_since_keyframe"],
                        m["inference_us"],
                    ])
                if not args.quiet:
                    print(
                        f"frame {m['frame']} pts {m['pts']} shape {frame.shape} mean "
                        f"{frame.mean():.1f} utility {_fmt_util(m['utility'])} keep "
                        f"{int(m['keep'])} reason {m['reason']} keyframe {m['keyframe_index']} "
                        f"since {m['frames_since_keyframe']} inference-us {m['inference_us']}",
                        flush=True,
                    )
                if args.force_every and source.received % args.force_every == 0:
                    source.force_keyframe()
            stats = source.stats
    except SetupError as e:
        print(f"slam_client: {e}", file=sys.stderr)
        return 2
    except PipelineError as e:
        print(f"slam_client: pipeline error: {e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("slam_client: interrupted", file=sys.stderr)
        return 130
    finally:
        if out:
            out.close()

    stats_txt = ""
    if stats:
        stats_txt = (
            f" provider={stats.get('execution-provider')} model={stats.get('model')}"
            f" threshold={stats.get('threshold'):.4g}"
            f" inference-mean-us={stats.get('inference-mean-us'):.0f}"
            f" inference-p99-us={stats.get('inference-p99-us'):.0f}"
        )
    print(
        f"summary: frames-in={source.frames_in} received={source.received} kept={kept} "
        f"forced={forced} force-events={source.forced_events} mode={args.mode} "
        f"shape={','.join(sorted(shapes)) or '-'}{stats_txt}"
        + (f" csv={args.csv}" if args.csv else ""),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
