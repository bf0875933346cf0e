"""The frames leangate keeps, into a real reconstruction engine: COLMAP's incremental SfM through
its Python bindings ``pycolmap``.

Two ways to choose the frames:

* **gated** (the default): the input goes through ``leangate`` in drop mode (a video file through
  ``filesrc ! decodebin``, an image sequence through ``multifilesrc ! decodebin``, both via
  ``LeanGateSource``), and the frames it lets through, with their LeanGateMeta, are the images;
* **explicit**: ``frames=[...]`` (indices into the sequence, or ``(index, path)`` pairs) or
  ``every=k``; the gate is not run. ``leangate eval --reconstruct`` uses this for each policy.

COLMAP sees the frames as ``OUT/images/frame_<index>.<ext>`` (written for a video, links for a
sequence; a file listed twice goes in once; ``OUT/images`` and ``OUT/sparse`` are replaced only
when a run of this module made them, see ``check_output_dir``). Then SIFT features
(``pycolmap.extract_features``), matching (exhaustive for small sets, sequential otherwise),
incremental mapping (``pycolmap.incremental_mapping``), in a child process (``run_sfm``: a
COLMAP abort becomes a PipelineError). The sparse models are written under ``OUT/sparse/N``, COLMAP's messages into
``OUT/colmap.log``; the largest model is reported: frames registered (with their camera-to-world
poses), number of models, mean reprojection error, and, when the input has ground truth, the ATE
of the camera centres after a similarity (Umeyama, with scale) alignment. ``--ply`` exports its
points.

Inputs: a video file; a directory in TUM RGB-D layout (``rgb.txt``, optional
``intrinsics.txt`` ``fx fy cx cy depth_scale`` -> a shared PINHOLE camera, optional
``groundtruth.txt`` camera-to-world ``t tx ty tz qx qy qz qw``); or a folder of images
(``rgb/`` inside it, or the folder itself; sorted by name).

Needs ``pycolmap`` (``bash scripts/setup.sh`` installs it into ``.venv-sfm``, a venv that also
sees the system's PyGObject), imported only when a reconstruction runs.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import shutil
import signal
import stat as stat_mod
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple

from . import _gst
from .errors import PipelineError, SetupError
from ._gst import _make, _set
from .source import LeanGateSource, buffer_to_rgb

log = logging.getLogger("leangate_client.reconstruct")

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
MATCHERS = ("auto", "exhaustive", "sequential")
#: ``matcher="auto"`` matches exhaustively up to this many images, sequentially above.
EXHAUSTIVE_MAX = 40
#: Ground-truth poses further than this from a frame's timestamp are not associated.
GT_MAX_DIFFERENCE_S = 0.02
PYCOLMAP_VERSION = "4.2.1"


def import_pycolmap():
    """``pycolmap``, or a SetupError saying which interpreter lacks it and how to install it.

    Import pycolmap *before* this package when you can (``pipelines/reconstruct.py`` does):
    importing it after the GStreamer bindings crashed the interpreter (SIGSEGV while unwinding a
    C++ exception inside pycolmap's import) in about half of the runs with pycolmap 4.2.1 on
    Debian 12."""
    if "pycolmap" not in sys.modules and "gi.repository.Gst" in sys.modules:
        log.warning(
            "importing pycolmap after the GStreamer bindings; if this crashes, import pycolmap "
            "before leangate_client (pipelines/reconstruct.py does)"
        )
    try:
        import pycolmap  # noqa: F401
    except ImportError as e:
        raise SetupError(
            f"pycolmap cannot be imported by {sys.executable} ({e}); run `bash scripts/setup.sh` "
            f"(it creates .venv-sfm with pycolmap=={PYCOLMAP_VERSION} and the system's PyGObject) "
            f"and use .venv-sfm/bin/python, or `pip install pycolmap=={PYCOLMAP_VERSION}`"
        ) from None
    return pycolmap


# -- inputs ------------------------------------------------------------------------------------
@dataclass
class FrameRef:
    """One frame of an input: its index in the sequence, timestamp (s) and image file (None for
    a video frame not yet written)."""

    index: int
    timestamp: Optional[float] = None
    path: Optional[str] = None


@dataclass
class InputSequence:
    """What ``open_input`` found: ``kind`` is ``video``, ``sequence`` (rgb.txt) or ``images``."""

    path: str
    kind: str
    frames: List[FrameRef] = field(default_factory=list)
    intrinsics: Optional[Tuple[float, float, float, float]] = None
    #: (timestamp, camera centre x, y, z), camera-to-world translations, sorted by time.
    groundtruth: List[Tuple[float, float, float, float]] = field(default_factory=list)

    def centre_at(self, t: Optional[float]) -> Optional[Tuple[float, float, float]]:
        """Ground-truth camera centre nearest to ``t`` (within 20 ms), or None."""
        if t is None or not self.groundtruth:
            return None
        import bisect

        ts = [g[0] for g in self.groundtruth]
        k = bisect.bisect_left(ts, t)
        best = None
        for j in (k - 1, k):
            if 0 <= j < len(ts) and abs(ts[j] - t) <= GT_MAX_DIFFERENCE_S:
                if best is None or abs(ts[j] - t) < abs(ts[best] - t):
                    best = j
        return None if best is None else tuple(self.groundtruth[best][1:])  # type: ignore


def _data_lines(path: str) -> Iterable[Tuple[int, List[str]]]:
    with open(path) as f:
        for n, line in enumerate(f, 1):
            s = line.strip()
            if s and not s.startswith("#"):
                yield n, s.split()


def _float_or_none(text: str) -> Optional[float]:
    """``text`` as a finite float, else None."""
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) else None


def read_intrinsics(path: str) -> Tuple[float, float, float, float]:
    """``fx fy cx cy [depth_scale]`` from the first data line of intrinsics.txt."""
    for n, parts in _data_lines(path):
        try:
            fx, fy, cx, cy = (float(v) for v in parts[:4])
        except ValueError:
            raise SetupError(f"{path} line {n}: expected `fx fy cx cy depth_scale`") from None
        return fx, fy, cx, cy
    raise SetupError(f"{path}: no intrinsics line")


def open_input(path: str) -> InputSequence:
    """Describe a video file, a TUM-layout directory or a folder of images."""
    if os.path.isfile(path):
        return InputSequence(path=path, kind="video")
    if not os.path.isdir(path):
        raise SetupError(f"input not found: {path}")
    rgb_txt = os.path.join(path, "rgb.txt")
    if os.path.isfile(rgb_txt):
        frames = []
        for n, parts in _data_lines(rgb_txt):
            t = _float_or_none(parts[0]) if len(parts) >= 2 else None
            if t is None:
                raise SetupError(
                    f"{rgb_txt} line {n}: expected `timestamp path` with a numeric timestamp, "
                    f"got {' '.join(parts)!r}"
                )
            frames.append(FrameRef(len(frames), t, os.path.join(path, parts[1])))
        seq = InputSequence(path=path, kind="sequence", frames=frames)
    else:
        folder = os.path.join(path, "rgb") if os.path.isdir(os.path.join(path, "rgb")) else path
        names = sorted(n for n in os.listdir(folder) if n.lower().endswith(IMAGE_EXTS))
        if not names:
            raise SetupError(f"{path}: no rgb.txt and no .png/.jpg images")
        seq = InputSequence(
            path=path,
            kind="images",
            frames=[FrameRef(i, i / 30.0, os.path.join(folder, n)) for i, n in enumerate(names)],
        )
    intr = os.path.join(path, "intrinsics.txt")
    if os.path.isfile(intr):
        seq.intrinsics = read_intrinsics(intr)
    for name in ("groundtruth.txt", "groundtruth_tum.txt"):
        gt = os.path.join(path, name)
        if os.path.isfile(gt):
            rows = []
            for n, parts in _data_lines(gt):
                try:
                    rows.append(tuple(float(v) for v in parts[:4]))
                except ValueError:
                    raise SetupError(f"{gt} line {n}: expected `t tx ty tz qx qy qz qw`") from None
            seq.groundtruth = sorted(rows)  # type: ignore[arg-type]
            break
    return seq


# -- gating ------------------------------------------------------------------------------------
class SequenceGateSource(LeanGateSource):
    """``LeanGateSource`` over an image sequence: ``multifilesrc ! decodebin ! leangate ! ...``.
    The images are linked (symlinks, else copies) as ``%06d.EXT`` into a temporary directory so
    that multifilesrc reads them in sequence order at 30 fps; ``meta["frame"]`` is the index in
    ``frames``. All images must share one format (PNG or JPEG)."""

    def __init__(self, frames: Sequence[FrameRef], **kwargs):
        if not frames:
            raise SetupError("empty image sequence")
        exts = {os.path.splitext(f.path or "")[1].lower() for f in frames}
        exts = {".jpg" if e == ".jpeg" else e for e in exts}
        if len(exts) != 1 or not exts <= {".jpg", ".png"}:
            raise SetupError(f"an image sequence must be all PNG or all JPEG, found {sorted(exts)}")
        self._ext = exts.pop()
        self._tmp = tempfile.mkdtemp(prefix="leangate-seq-")
        for k, f in enumerate(frames):
            dst = os.path.join(self._tmp, f"{k:06d}{self._ext}")
            try:
                os.symlink(os.path.abspath(f.path), dst)  # type: ignore[arg-type]
            except OSError:
                shutil.copyfile(f.path, dst)  # type: ignore[arg-type]
        self._count = len(frames)
        super().__init__(self._tmp, **kwargs)

    @staticmethod
    def _check_source(source: str) -> None:
        if not os.path.isdir(source):
            raise SetupError(f"not a directory: {source}")

    def _caps(self) -> str:
        kind = "image/jpeg" if self._ext == ".jpg" else "image/png"
        return f"{kind},framerate=30/1"

    @property
    def description(self) -> str:
        props = " ".join(f"{k}={v}" for k, v in self.gate_properties.items())
        return (
            f"multifilesrc location={self._tmp}/%06d{self._ext} index=0 "
            f"stop-index={self._count - 1} caps={self._caps()} ! decodebin ! leangate name=gate "
            f"{props} ! videoconvert ! appsink name=sink caps=video/x-raw,format=RGB sync=false"
        )

    _pipeline_name = "leangate-sequence"

    def _build_source(self, pipeline, gate) -> None:
        Gst = _gst.Gst
        src = _make("multifilesrc", "src")
        _set(src, "location", os.path.join(self._tmp, f"%06d{self._ext}"))
        _set(src, "index", 0)
        _set(src, "stop-index", self._count - 1)
        _set(src, "caps", Gst.Caps.from_string(self._caps()))
        dec = _make("decodebin", "decode")
        pipeline.add(src)
        pipeline.add(dec)
        if not src.link(dec):
            raise SetupError("cannot link multifilesrc ! decodebin")
        self._watch_decoder(dec, gate)

    def close(self) -> None:
        super().close()
        if getattr(self, "_tmp", None):
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None


def write_image(path: str, rgb) -> None:
    """Write an (H, W, 3) uint8 RGB array (PNG or JPEG by extension) with pycolmap's Bitmap."""
    pycolmap = import_pycolmap()
    bmp = pycolmap.Bitmap.from_array(_gst.np.ascontiguousarray(rgb))
    if not bmp.write(path):
        raise SetupError(f"cannot write {path}")


@dataclass
class GateResult:
    """The frames the gate kept (with their meta) and the element's statistics."""

    kept: List[FrameRef]
    metas: List[Dict[str, Any]]
    frames_in: int
    stats: Any = None


def gate_input(
    inp: InputSequence,
    image_dir: str,
    *,
    model=None,
    threshold: Optional[float] = None,
    warmup: Optional[int] = None,
    max_gap: Optional[int] = None,
    execution_provider: Optional[str] = None,
    plugin_path=None,
    plugin_fallbacks=(),
    max_frames: Optional[int] = None,
) -> GateResult:
    """Run the input through leangate (drop mode); kept video frames are written as PNG into
    ``image_dir`` (a sequence's kept frames are used from their files)."""
    kw = dict(
        model=model,
        threshold=threshold,
        mode="drop",
        warmup=warmup,
        max_gap=max_gap,
        execution_provider=execution_provider,
        plugin_path=plugin_path,
        plugin_fallbacks=plugin_fallbacks,
    )
    kept: List[FrameRef] = []
    metas: List[Dict[str, Any]] = []
    if inp.kind == "video":
        os.makedirs(image_dir, exist_ok=True)
        src: LeanGateSource = LeanGateSource(inp.path, arrays=True, max_frames=max_frames, **kw)
    else:
        frames = inp.frames[:max_frames] if max_frames else inp.frames
        src = SequenceGateSource(frames, arrays=False, **kw)
    log.info("gating %s", inp.path)
    with src:
        for frame, meta in src:
            idx = meta["frame"]
            if idx is None:
                raise PipelineError("a kept frame without a PTS: cannot tell its index")
            if inp.kind == "video":
                ref = FrameRef(idx, None if meta["pts"] is None else meta["pts"] / 1e9)
                ref.path = os.path.join(image_dir, f"frame_{idx:06d}.png")
                write_image(ref.path, frame)
            else:
                ref = inp.frames[idx]
            kept.append(ref)
            metas.append(meta)
            log.info(
                "kept frame %d (%s, utility %s, keyframe %d)",
                idx,
                meta["reason"],
                "nan" if math.isnan(meta["utility"]) else f"{meta['utility']:.3f}",
                meta["keyframe_index"],
            )
    log.info("gate: kept %d of %d frames", len(kept), src.frames_in)
    return GateResult(kept, metas, src.frames_in, src.stats)


def decode_video_frames(path: str, wanted: Iterable[int], image_dir: str) -> List[FrameRef]:
    """Decode a video (``filesrc ! decodebin ! videoconvert ! appsink``, no gate) and write the
    frames whose decode index is in ``wanted`` as PNG into ``image_dir``."""
    Gst, GstVideo = _gst.Gst, _gst.GstVideo
    wanted = sorted(set(wanted))
    if not wanted:
        return []
    _gst._init()  # bindings present, Gst initialised
    os.makedirs(image_dir, exist_ok=True)
    pipeline = Gst.Pipeline.new("decode")
    src, dec = _make("filesrc"), _make("decodebin")
    convert, sink = _make("videoconvert"), _make("appsink")
    _set(src, "location", os.path.abspath(path))
    _set(sink, "caps", Gst.Caps.from_string("video/x-raw,format=RGB"))
    _set(sink, "sync", False)
    for el in (src, dec, convert, sink):
        pipeline.add(el)
    src.link(dec)
    convert.link(sink)

    def on_pad(_dec, pad):
        caps = pad.get_current_caps() or pad.query_caps(None)
        if caps.get_structure(0).get_name().startswith("video/"):
            target = convert.get_static_pad("sink")
            if not target.is_linked():
                pad.link(target)

    dec.connect("pad-added", on_pad)
    out: List[FrameRef] = []
    pipeline.set_state(Gst.State.PLAYING)
    bus = pipeline.get_bus()
    index = 0
    todo = set(wanted)
    try:
        while todo:
            msg = bus.pop_filtered(Gst.MessageType.ERROR)
            if msg is not None:
                err, dbg = msg.parse_error()
                raise PipelineError(f"decoding {path}: {err.message}")
            sample = sink.emit("try-pull-sample", Gst.SECOND)
            if sample is None:
                if sink.get_property("eos"):
                    break
                continue
            if index in todo:
                info = GstVideo.VideoInfo.new_from_caps(sample.get_caps())
                buf = sample.get_buffer()
                ref = FrameRef(index, None if buf.pts == Gst.CLOCK_TIME_NONE else buf.pts / 1e9)
                ref.path = os.path.join(image_dir, f"frame_{index:06d}.png")
                write_image(ref.path, buffer_to_rgb(buf, info))
                out.append(ref)
                todo.discard(index)
            index += 1
    finally:
        pipeline.set_state(Gst.State.NULL)
    if todo:
        log.warning("%s has %d frames: %d requested frames are past its end", path, index, len(todo))
    return out


# -- SfM ---------------------------------------------------------------------------------------
@dataclass
class SfmOptions:
    """COLMAP settings. ``matcher``: auto (exhaustive up to EXHAUSTIVE_MAX images, else
    sequential), exhaustive or sequential (``overlap`` neighbours). ``intrinsics`` (fx, fy, cx,
    cy): a shared PINHOLE camera, kept fixed unless ``refine_intrinsics``; None: a shared
    SIMPLE_RADIAL camera (focal guessed, refined). ``min_model_size``: smaller models are
    discarded (COLMAP's default is 10; 3 here, for gates that keep few frames).
    ``init_min_tri_angle``: degrees between the two initial views (COLMAP's default 16 is too
    strict for the short baselines of handheld video). ``threads``: -1 for every core."""

    matcher: str = "auto"
    overlap: int = 10
    max_features: int = 4096
    intrinsics: Optional[Tuple[float, float, float, float]] = None
    camera_model: Optional[str] = None
    refine_intrinsics: bool = False
    min_model_size: int = 3
    init_min_tri_angle: float = 4.0
    threads: int = -1
    seed: int = 0

    def check(self) -> None:
        """SetupError naming the first setting COLMAP would reject (some it aborts on)."""
        if self.matcher not in MATCHERS:
            raise SetupError(f"matcher must be one of {', '.join(MATCHERS)}, not {self.matcher!r}")
        for name, lo in (("overlap", 1), ("max_features", 1), ("min_model_size", 2)):
            if getattr(self, name) < lo:
                raise SetupError(f"{name} must be at least {lo}, not {getattr(self, name)}")
        if self.threads != -1 and self.threads < 1:
            raise SetupError(f"threads must be -1 (every core) or at least 1, not {self.threads}")
        if not 0 < self.init_min_tri_angle < 180:
            raise SetupError(
                f"init_min_tri_angle must be in (0, 180) degrees, not {self.init_min_tri_angle}"
            )
        if self.camera_model is not None and self.camera_model not in CAMERA_MODELS:
            raise SetupError(
                f"unknown COLMAP camera model {self.camera_model!r}; one of "
                f"{', '.join(CAMERA_MODELS)}"
            )
        if self.intrinsics is not None:
            if len(self.intrinsics) != 4 or not all(math.isfinite(v) for v in self.intrinsics):
                raise SetupError(f"intrinsics must be four finite numbers, not {self.intrinsics}")
            if min(self.intrinsics[:2]) <= 0:
                raise SetupError(f"intrinsics: the focal lengths must be positive: {self.intrinsics}")
            if self.camera_model not in (None, "PINHOLE"):
                raise SetupError(
                    f"intrinsics FX,FY,CX,CY are PINHOLE parameters; camera model "
                    f"{self.camera_model} takes others (drop --camera-model, or the intrinsics)"
                )


#: COLMAP 3.x/4.x camera models (``pycolmap.CameraModelId`` of pycolmap 4.2.1, less INVALID).
CAMERA_MODELS = (
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL",
    "RADIAL_FISHEYE", "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE",
    "RAD_TAN_THIN_PRISM_FISHEYE", "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE",
    "EUCM", "EQUIRECTANGULAR",
)  # fmt: skip


@dataclass
class SfmResult:
    """The outcome: ``images`` fed to COLMAP; ``models``: models that register at least one
    frame no larger model has (COLMAP may also build models from frames a larger one already
    holds; those are not counted); ``registered``: frames in the largest model, with their
    camera centres in ``centres`` (name -> centre) and orientations in ``rotations`` (name ->
    camera-to-world quaternion x, y, z, w); ``registered_total``: frames in any model; mean
    reprojection error, 3-D points and directory of the largest model; ``unreadable``: images
    COLMAP could not read (left out)."""

    images: int
    models: int
    registered: int
    registered_total: int
    centres: Dict[str, Tuple[float, float, float]]
    mean_reprojection_error_px: Optional[float]
    points3d: int
    model_dir: Optional[str]
    seconds: Dict[str, float]
    matcher: str
    camera_model: str
    rotations: Dict[str, Tuple[float, float, float, float]] = field(default_factory=dict)
    unreadable: List[str] = field(default_factory=list)


#: The child's log records on its stderr: ``PREFIX<levelno>:<message>``; other lines are COLMAP's.
_CHILD_LOG = "\x1eleangate-sfm:"
_GLOG_LINE = re.compile(r"^[IWEF]\d{4,8} [\d:.]+ +\d+ [^\]]+\] (.*)$")


def run_sfm(
    image_root: str,
    names: Sequence[str],
    out_dir: str,
    opts: SfmOptions = SfmOptions(),
    colmap_log: bool = False,
) -> SfmResult:
    """Incremental SfM on ``names`` (paths relative to ``image_root``): database and sparse
    models under ``out_dir`` (``database.db``, ``sparse/N``, COLMAP's messages in
    ``colmap.log``).

    COLMAP runs in a child Python process: COLMAP ends the process on a failed internal check
    (glog ``CHECK``: SIGABRT), which here becomes a PipelineError naming the check and the stage,
    and the caller goes on. Its progress comes back through this process's log."""
    opts.check()
    os.makedirs(out_dir, exist_ok=True)
    request = os.path.join(out_dir, "sfm_request.json")
    response = os.path.join(out_dir, "sfm_result.json")
    if os.path.exists(response):
        os.remove(response)
    with open(request, "w") as f:
        json.dump({
            "image_root": image_root,
            "names": list(names),
            "out_dir": out_dir,
            "opts": opts.__dict__,
            "colmap_log": colmap_log,
            "response": response,
        }, f)
    package_parent = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (package_parent, env.get("PYTHONPATH")) if p)
    # pycolmap first: see import_pycolmap.
    code = (
        "import sys, pycolmap\n"
        "from leangate_client.reconstruct import _sfm_child\n"
        "sys.exit(_sfm_child(sys.argv[1]))\n"
    )
    log_path = os.path.join(out_dir, "colmap.log")
    stage = "start"
    colmap_errors: List[str] = []
    with open(log_path, "w") as colmap_file:
        proc = subprocess.Popen(
            [sys.executable, "-c", code, request],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
            text=True,
            errors="replace",
        )
        try:
            for line in proc.stderr:  # type: ignore[union-attr]
                if line.startswith(_CHILD_LOG):
                    level, _, msg = line[len(_CHILD_LOG):].rstrip("\n").partition(":")
                    if level == "stage":
                        stage = msg
                    else:
                        log.log(int(level), "%s", msg)
                    continue
                colmap_file.write(line)
                m = _GLOG_LINE.match(line.rstrip("\n"))
                if m and line[0] in "EF":
                    colmap_errors.append(m.group(1).strip())
                elif "what():" in line:  # an uncaught C++ exception: std::terminate, SIGABRT
                    colmap_errors.append(line.split("what():", 1)[1].strip())
                if colmap_log:
                    sys.stderr.write(line)
        finally:
            rc = proc.wait()
    outcome = None
    if os.path.exists(response):
        with open(response) as f:
            outcome = json.load(f)
    if rc != 0 or outcome is None:
        why = f"killed by {signal.Signals(-rc).name}" if rc < 0 else f"exit status {rc}"
        detail = f": {colmap_errors[-1]}" if colmap_errors else ""
        raise PipelineError(
            f"COLMAP failed during {stage} of {len(names)} images ({why}){detail}; "
            f"its messages are in {log_path}"
        )
    if "error" in outcome:
        kind = SetupError if outcome.get("kind") == "setup" else PipelineError
        raise kind(outcome["error"])
    r = outcome["result"]
    r["centres"] = {k: tuple(v) for k, v in r["centres"].items()}
    r["rotations"] = {k: tuple(v) for k, v in r["rotations"].items()}
    return SfmResult(**r)


def _sfm_child(request_path: str) -> int:
    """The child process of ``run_sfm``: run COLMAP, write the result (or the error) as JSON.
    Log records go to stderr tagged for the parent, which re-logs them."""

    class _Tagged(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            sys.stderr.write(f"{_CHILD_LOG}{record.levelno}:{record.getMessage()}\n")
            sys.stderr.flush()

    root = logging.getLogger("leangate_client")
    root.handlers[:] = [_Tagged()]
    root.setLevel(logging.DEBUG)
    root.propagate = False
    with open(request_path) as f:
        req = json.load(f)
    try:
        result = _run_sfm_here(
            req["image_root"], req["names"], req["out_dir"], SfmOptions(**req["opts"]),
            req["colmap_log"],
        )
        outcome: Dict[str, Any] = {"result": result.__dict__}
    except SetupError as e:
        outcome = {"error": str(e), "kind": "setup"}
    except Exception as e:  # pycolmap raises RuntimeError/ValueError with COLMAP's message
        outcome = {"error": f"COLMAP: {e}", "kind": "pipeline"}
    with open(req["response"], "w") as f:
        json.dump(outcome, f)
    return 0


def _stage(name: str) -> None:
    sys.stderr.write(f"{_CHILD_LOG}stage:{name}\n")
    sys.stderr.flush()


def _run_sfm_here(
    image_root: str,
    names: Sequence[str],
    out_dir: str,
    opts: SfmOptions,
    colmap_log: bool,
) -> SfmResult:
    """``run_sfm``'s work, in this process."""
    pycolmap = import_pycolmap()
    if not colmap_log:
        pycolmap.logging.minloglevel = 1  # warnings and errors from COLMAP's glog
    db = os.path.join(out_dir, "database.db")
    if os.path.exists(db):
        os.remove(db)
    sparse = os.path.join(out_dir, "sparse")
    check_output_subdir(out_dir, "sparse")  # only a folder this module made is replaced
    if os.path.lexists(sparse):
        shutil.rmtree(sparse)
    _make_owned_dir(sparse)
    seconds: Dict[str, float] = {}
    pycolmap.set_random_seed(opts.seed)
    device = pycolmap.Device.cpu

    reader = pycolmap.ImageReaderOptions()
    if opts.intrinsics is not None:
        reader.camera_model = opts.camera_model or "PINHOLE"
        reader.camera_params = ",".join(f"{v:g}" for v in opts.intrinsics)
    elif opts.camera_model:
        reader.camera_model = opts.camera_model
    extract = pycolmap.FeatureExtractionOptions()
    extract.sift.max_num_features = opts.max_features
    extract.num_threads = opts.threads
    t = time.monotonic()
    _stage("feature extraction")
    log.info("SIFT features of %d images (%s camera, shared)", len(names), reader.camera_model)
    pycolmap.extract_features(
        db,
        image_root,
        image_names=list(names),
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extract,
        device=device,
    )
    seconds["features"] = time.monotonic() - t
    with pycolmap.Database.open(db) as database:
        read = {img.name for img in database.read_all_images()}
    unreadable = [n for n in names if n not in read]
    if unreadable:
        where = os.path.realpath(os.path.join(image_root, unreadable[0]))
        if len(read) < 2:
            raise SetupError(
                f"COLMAP could read {len(read)} of {len(names)} images (not an image, or "
                f"corrupt: {where}{' and others' if len(unreadable) > 1 else ''})"
            )
        log.warning("COLMAP could not read %d of %d images (left out), the first: %s",
                    len(unreadable), len(names), where)

    matcher = opts.matcher
    if matcher == "auto":
        matcher = "exhaustive" if len(read) <= EXHAUSTIVE_MAX else "sequential"
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = opts.threads
    t = time.monotonic()
    _stage(f"{matcher} matching")
    if matcher == "exhaustive":
        log.info("exhaustive matching: %d pairs", len(read) * (len(read) - 1) // 2)
        pycolmap.match_exhaustive(db, matching_options=match, device=device)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = opts.overlap
        log.info("sequential matching: each image with its %d successors", opts.overlap)
        pycolmap.match_sequential(db, matching_options=match, pairing_options=pairing, device=device)
    seconds["matching"] = time.monotonic() - t

    mo = pycolmap.IncrementalPipelineOptions()
    mo.min_model_size = opts.min_model_size
    mo.num_threads = opts.threads
    mo.random_seed = opts.seed
    mo.mapper.init_min_tri_angle = opts.init_min_tri_angle
    if opts.intrinsics is not None and not opts.refine_intrinsics:
        mo.ba_refine_focal_length = False
        mo.ba_refine_extra_params = False
        mo.mapper.abs_pose_refine_focal_length = False
        mo.mapper.abs_pose_refine_extra_params = False
    registered = [0]

    def next_image():
        registered[0] += 1
        log.info("mapping: %d images registered after the initial pair", registered[0])

    t = time.monotonic()
    _stage("incremental mapping")
    log.info("incremental mapping")
    models = pycolmap.incremental_mapping(
        db, image_root, sparse, options=mo, next_image_callback=next_image
    )
    seconds["mapping"] = time.monotonic() - t
    recs = sorted(models.items(), key=lambda kv: -kv[1].num_reg_images())
    # COLMAP may start a further model from frames a larger one already registered (up to
    # max_model_overlap shared images): such a model splits nothing off and is not counted.
    covered: set = set()
    distinct = 0
    for _, rec in recs:
        names_in = {img.name for img in rec.images.values() if img.has_pose}
        if names_in - covered:
            distinct += 1
            covered |= names_in
    if len(recs) != distinct:
        log.info("%d models, %d of them only re-register frames of a larger one", len(recs),
                 len(recs) - distinct)
    centres: Dict[str, Tuple[float, float, float]] = {}
    rotations: Dict[str, Tuple[float, float, float, float]] = {}
    err = None
    points = 0
    model_dir = None
    if recs:
        key, rec = recs[0]
        for img in rec.images.values():
            if img.has_pose:
                c = img.projection_center()
                centres[img.name] = (float(c[0]), float(c[1]), float(c[2]))
                q = img.cam_from_world().inverse().rotation.quat  # x, y, z, w
                rotations[img.name] = (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
        err = float(rec.compute_mean_reprojection_error())
        points = int(rec.num_points3D())
        model_dir = os.path.join(sparse, str(key))
    return SfmResult(
        images=len(names),
        models=distinct,
        registered=len(centres),
        registered_total=len(covered),
        centres=centres,
        mean_reprojection_error_px=err,
        points3d=points,
        model_dir=model_dir,
        seconds=seconds,
        matcher=matcher,
        camera_model=reader.camera_model,
        rotations=rotations,
        unreadable=unreadable,
    )


def export_ply(model_dir: str, path: str) -> None:
    pycolmap = import_pycolmap()
    pycolmap.Reconstruction(model_dir).export_PLY(path)


# -- trajectory error --------------------------------------------------------------------------
def umeyama_sim3(src, dst):
    """Similarity (s, R, t) minimising sum |dst - (s R src + t)|^2 (Umeyama 1991); src, dst:
    (N, 3) arrays, N >= 3."""
    np = _gst.np
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var_s = (xs**2).sum() / len(src)
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    s_fix = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s_fix[2, 2] = -1
    r = u @ s_fix @ vt
    scale = float((d * np.diag(s_fix)).sum() / var_s) if var_s > 0 else 1.0
    t = mu_d - scale * r @ mu_s
    return scale, r, t


def ate_rmse(est, gt) -> Optional[float]:
    """RMSE (in gt units) of the estimated camera centres against ground truth after the
    similarity alignment; None with fewer than 3 pairs."""
    np = _gst.np
    if len(est) < 3:
        return None
    s, r, t = umeyama_sim3(est, gt)
    aligned = (s * (r @ np.asarray(est, dtype=np.float64).T)).T + t
    return float(np.sqrt(((aligned - np.asarray(gt)) ** 2).sum(1).mean()))


# -- the whole consumer ------------------------------------------------------------------------
@dataclass
class Reconstruction:
    """What ``reconstruct`` did: the frames used (``frames``: FrameRef, in order) and the image
    name COLMAP saw for each (``names``), the gate's result when it ran, the SfM result, ATE
    (cm) when ground truth exists, and where it wrote."""

    input: InputSequence
    frames: List[FrameRef]
    names: List[str]
    sfm: SfmResult
    gate: Optional[GateResult]
    ate_rmse_cm: Optional[float]
    out_dir: str

    def frame_rows(self) -> List[Dict[str, Any]]:
        """Per frame: index, timestamp, the image name COLMAP saw (``images/frame_<index>``
        under the output directory), the source file, whether it registered in the largest
        model, and its camera-to-world pose there (``center``, ``rotation`` x, y, z, w)."""
        rows = []
        for f, name in zip(self.frames, self.names):
            c = self.sfm.centres.get(name)
            q = self.sfm.rotations.get(name)
            rows.append({
                "frame": f.index,
                "timestamp": f.timestamp,
                "name": name,
                "path": os.path.abspath(f.path) if f.path else None,
                "registered": c is not None,
                "center": list(c) if c else None,
                "rotation": list(q) if q else None,
            })
        return rows

    @property
    def registered(self) -> int:
        """Frames (not images: a repeated image counts for each frame) in the largest model."""
        return sum(1 for n in self.names if n in self.sfm.centres)

    def to_dict(self) -> Dict[str, Any]:
        s = self.sfm
        d = {
            "input": self.input.path,
            "kind": self.input.kind,
            "engine": f"pycolmap {_pycolmap_version()}",
            "kept": len(self.frames),
            "images": s.images,
            "registered": self.registered,
            "registered_images": s.registered,
            "registered_total": s.registered_total,
            "models": s.models,
            "mean_reprojection_error_px": s.mean_reprojection_error_px,
            "points3D": s.points3d,
            "ate_rmse_cm": self.ate_rmse_cm,
            "matcher": s.matcher,
            "camera_model": s.camera_model,
            "model_dir": s.model_dir,
            "seconds": s.seconds,
            "unreadable": s.unreadable,
            "frames": self.frame_rows(),
        }
        if self.gate is not None:
            d["frames_in"] = self.gate.frames_in
            d["gate"] = [{k: _jsonable(v) for k, v in m.items()} for m in self.gate.metas]
        return d


def _jsonable(v):
    return None if isinstance(v, float) and math.isnan(v) else v


def _pycolmap_version() -> str:
    try:
        import pycolmap

        return pycolmap.__version__
    except ImportError:
        return "?"


def image_name(f: FrameRef) -> str:
    """The name COLMAP knows a frame by, relative to the output directory:
    ``images/frame_<index>.<ext>``. By index, not by file: a sequence may list one file twice
    (a pause written by repeating a frame), and COLMAP's database refuses two images of one
    name."""
    ext = os.path.splitext(f.path or "")[1] or ".png"
    return f"images/frame_{f.index:06d}{ext}"


#: Written into ``OUT/images`` and ``OUT/sparse`` when this module makes them: a later run
#: replaces (deletes and makes anew) only folders that hold it, never a user's or COLMAP's own.
OUTPUT_MARKER = ".leangate-reconstruct"
#: The folders under ``--out`` that a run replaces.
OUTPUT_SUBDIRS = ("images", "sparse")


def _make_owned_dir(d: str) -> None:
    """Make ``d`` (missing or just removed) with the marker that lets a later run replace it."""
    os.makedirs(d)
    with open(os.path.join(d, OUTPUT_MARKER), "w") as f:
        f.write("made by leangate_client.reconstruct (pipelines/reconstruct.py); a later run "
                "with the same --out deletes and remakes this folder\n")


def check_output_subdir(out_dir: str, sub: str) -> None:
    """Raise SetupError unless ``OUT/sub`` may be replaced: it is missing, an empty folder, or a
    folder this module made (it holds ``OUTPUT_MARKER``). A symbolic link is refused, never
    followed (deleting it would delete what it points to)."""
    p = os.path.join(out_dir, sub)
    if os.path.islink(p):
        raise SetupError(
            f"--out {out_dir}: {p} is a symbolic link (to {os.readlink(p)}); reconstruct.py "
            "does not follow it to replace what it points to; choose another --out or remove it"
        )
    if not os.path.lexists(p):
        return
    if not os.path.isdir(p):
        raise SetupError(
            f"--out {out_dir}: {p} exists and is not a folder; choose another --out or remove it"
        )
    marker = os.path.join(p, OUTPUT_MARKER)
    if os.path.isfile(marker) and not os.path.islink(marker):
        return
    if os.listdir(p):
        raise SetupError(
            f"--out {out_dir}: {p} is not empty and was not made by reconstruct.py (no "
            f"{OUTPUT_MARKER} in it), so it is not replaced; choose another --out or remove it"
        )


def _input_under_output(
    inp: InputSequence, out_dir: str, extra: Sequence[str] = ()
) -> Optional[Tuple[str, str]]:
    """The first input file (the video, or a frame's image; ``extra``: more frame files) that
    lies under ``OUT/images`` or ``OUT/sparse`` (resolved, links followed), or is the same file
    as one there (a hard link: same st_dev/st_ino), with the folder; else None."""
    roots = [os.path.realpath(os.path.join(out_dir, s)) for s in OUTPUT_SUBDIRS]
    inodes: Dict[Tuple[int, int], str] = {}
    for top in roots:
        for dirpath, _dirs, files in os.walk(top):  # links not followed
            for n in files:
                try:
                    st = os.lstat(os.path.join(dirpath, n))
                except OSError:
                    continue
                if stat_mod.S_ISREG(st.st_mode):
                    inodes[(st.st_dev, st.st_ino)] = top
    paths = [inp.path] if inp.kind == "video" else [f.path for f in inp.frames if f.path]
    for path in list(paths) + list(extra):
        real = os.path.realpath(path)
        for top in roots:
            if real == top or real.startswith(top + os.sep):
                return path, top
        try:
            st = os.stat(path)
        except OSError:
            continue  # a missing file is reported later
        top = inodes.get((st.st_dev, st.st_ino))  # type: ignore[assignment]
        if top is not None:
            return path, f"{top} (a hard link to it)"
    return None


def check_output_dir(inp: InputSequence, out_dir: str, extra: Sequence[str] = ()) -> None:
    """Raise SetupError (nothing deleted) when a run into ``out_dir`` would delete the input
    (the input, or a file of it, lies in ``OUT/images`` or ``OUT/sparse``, also through a hard
    link) or a folder this module did not make (see ``check_output_subdir``)."""
    src = os.path.realpath(inp.path)
    for sub in OUTPUT_SUBDIRS:
        d = os.path.realpath(os.path.join(out_dir, sub))
        if src == d or src.startswith(d + os.sep):
            raise SetupError(
                f"--out {out_dir}: its {sub}/ folder is (or holds) the input {inp.path}, which "
                "would be deleted; choose another output directory"
            )
    hit = _input_under_output(inp, out_dir, extra)
    if hit is not None:
        raise SetupError(
            f"--out {out_dir}: the input file {hit[0]} lies in {hit[1]}, which a run replaces "
            "(the input would be deleted); choose another output directory"
        )
    for sub in OUTPUT_SUBDIRS:
        check_output_subdir(out_dir, sub)


def fresh_image_dir(inp: InputSequence, out_dir: str, extra: Sequence[str] = ()) -> str:
    """Empty ``OUT/images`` (made anew, with ``OUTPUT_MARKER``), after ``check_output_dir``:
    nothing is deleted when the input lies there or the folder was not made by this module."""
    check_output_dir(inp, out_dir, extra)
    d = os.path.join(out_dir, "images")
    if os.path.lexists(d):
        shutil.rmtree(d)
    _make_owned_dir(d)
    return d


def link_images(frames: Sequence[FrameRef], out_dir: str) -> List[str]:
    """Make each frame's file visible as ``OUT/image_name(f)`` (a symlink, else a copy) and
    return the name of each frame's image. A frame whose file an earlier frame already uses (a
    pause written by repeating a frame) gets that frame's image: COLMAP sees each file once (two
    identical images are a zero-baseline pair that can wreck its initialisation), and the
    repeat takes the same pose."""
    first: Dict[str, str] = {}
    names = []
    for f in frames:
        src = os.path.realpath(f.path)  # type: ignore[arg-type]
        name = first.get(src)
        if name is None:
            name = first[src] = image_name(f)
            dst = os.path.join(out_dir, name)
            try:
                os.symlink(src, dst)
            except OSError:
                shutil.copyfile(src, dst)
        else:
            log.info("frame %d repeats the image %s: reconstructed once", f.index, name)
        names.append(name)
    return names


def select_frames(
    inp: InputSequence,
    out_dir: str,
    frames: Optional[Sequence[Any]] = None,
    every: Optional[int] = None,
) -> List[FrameRef]:
    """Explicit frames: ``frames`` (indices, or (index, path) pairs whose path overrides the
    sequence's file) or every ``every``-th frame; video frames are decoded and written."""
    if every is not None and every < 1:
        raise SetupError(f"every must be at least 1, not {every}")
    idx = [f[0] if isinstance(f, (tuple, list)) else f for f in frames or []]
    for i in idx:
        if not isinstance(i, int) or i < 0:
            raise SetupError(f"frame indices are integers >= 0, not {i!r}")
    seen: set = set()
    for i in idx:
        if i in seen:
            raise SetupError(f"frame {i} is listed twice")
        seen.add(i)
    image_dir = os.path.join(out_dir, "images")
    if inp.kind == "video":
        if every:
            raise SetupError("--every needs an image sequence; give --frames for a video")
        return decode_video_frames(inp.path, idx, image_dir)
    if every:
        return inp.frames[::every]
    out = []
    by_path = {os.path.abspath(f.path): f for f in inp.frames if f.path}
    for f in frames or []:
        if isinstance(f, (tuple, list)):
            i, p = f[0], f[1]
        else:
            i, p = f, None
        if p:
            # The caller's own index (e.g. eval's, over frames with ground truth); the timestamp
            # comes from the sequence's listing of that file.
            p = os.path.abspath(p if os.path.isabs(p) else os.path.join(inp.path, p))
            known = by_path.get(p)
            out.append(FrameRef(i, known.timestamp if known else None, p))
        elif 0 <= i < len(inp.frames):
            out.append(inp.frames[i])
        else:
            raise SetupError(f"frame {i} out of range ({len(inp.frames)} frames in {inp.path})")
    return out


def reconstruct(
    input_path: str,
    out_dir: str,
    *,
    frames: Optional[Sequence[Any]] = None,
    every: Optional[int] = None,
    sfm: Optional[SfmOptions] = None,
    gate: Optional[Dict[str, Any]] = None,
    ply: Optional[str] = None,
    colmap_log: bool = False,
) -> Reconstruction:
    """The consumer: choose the frames (the gate, or ``frames`` / ``every``), reconstruct them,
    measure ATE where ground truth exists. ``gate``: keyword arguments of ``gate_input``.
    COLMAP sees the frames as ``OUT/images/frame_<index>.<ext>`` (written for a video, linked
    for a sequence) and runs in a child process (``run_sfm``)."""
    opts = sfm or SfmOptions()
    opts.check()
    import_pycolmap()
    inp = open_input(input_path)
    if opts.intrinsics is None and inp.intrinsics is not None:
        if opts.camera_model in (None, "PINHOLE"):
            opts = SfmOptions(**{**opts.__dict__, "intrinsics": inp.intrinsics})
        else:
            log.info("camera model %s: the PINHOLE intrinsics.txt is not used", opts.camera_model)
    extra = []  # files given with --frames @FILE
    for f in frames or []:
        if isinstance(f, (tuple, list)) and f[1]:
            extra.append(f[1] if os.path.isabs(f[1]) else os.path.join(inp.path, f[1]))
    check_output_dir(inp, out_dir, extra)
    os.makedirs(out_dir, exist_ok=True)
    fresh_image_dir(inp, out_dir, extra)
    gate_result = None
    if frames is not None or every is not None:
        chosen = select_frames(inp, out_dir, frames, every)
        log.info("%d frames chosen explicitly", len(chosen))
    else:
        gate_result = gate_input(inp, os.path.join(out_dir, "images"), **(gate or {}))
        chosen = gate_result.kept
        listed = len(inp.frames[: (gate or {}).get("max_frames") or None])
        if gate_result.frames_in == 0:
            # The decoders skip a few undecodable frames with a warning rather than an error.
            first = f" (the first: {inp.frames[0].path})" if inp.frames else ""
            raise SetupError(f"no frame of {inp.path} could be decoded{first}")
        if inp.kind != "video" and gate_result.frames_in < listed:
            log.warning("%d of %d images of %s could not be decoded (left out)",
                        listed - gate_result.frames_in, listed, inp.path)
    if inp.kind != "video":
        missing = [f.path for f in chosen if not os.path.isfile(f.path)]  # type: ignore[arg-type]
        if missing:
            raise SetupError(f"image not found: {missing[0]}")
        names = link_images(chosen, out_dir)
    else:
        names = [image_name(f) for f in chosen]
    root = os.path.abspath(out_dir)
    unique = list(dict.fromkeys(names))
    if len(unique) < 2:
        log.warning("%d image(s): nothing to reconstruct", len(unique))
        result = SfmResult(len(unique), 0, 0, 0, {}, None, 0, None, {}, "-", "-")
    else:
        result = run_sfm(root, unique, out_dir, opts, colmap_log=colmap_log)
    ate = None
    if inp.groundtruth and result.registered >= 3:
        est, gt = [], []
        for f, n in zip(chosen, names):
            c, g = result.centres.get(n), inp.centre_at(f.timestamp)
            if c is not None and g is not None:
                est.append(c)
                gt.append(g)
        e = ate_rmse(est, gt)
        ate = None if e is None else 100.0 * e
    if ply and result.model_dir:
        export_ply(result.model_dir, ply)
        log.info("points written to %s", ply)
    return Reconstruction(
        inp, list(chosen), names, result, gate_result, ate, os.path.abspath(out_dir)
    )


# -- command line ------------------------------------------------------------------------------
def _frame_index(text: str, where: str = "") -> int:
    at = f"{where}: " if where else ""
    try:
        i = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{at}{text!r} is not a frame index") from None
    if i < 0:
        raise argparse.ArgumentTypeError(f"{at}frame {i} is negative")
    return i


def _parse_frames(spec: str) -> List[Any]:
    """``0,5,10`` or ``@FILE`` (one ``index [path]`` per line, # comments): indices >= 0, none
    twice; argparse.ArgumentTypeError naming the bad entry (and the file and line)."""
    out: List[Any] = []
    if spec.startswith("@"):
        try:
            for n, parts in _data_lines(spec[1:]):
                i = _frame_index(parts[0], f"{spec[1:]} line {n}")
                out.append((i, " ".join(parts[1:]) or None))
        except OSError as e:
            raise argparse.ArgumentTypeError(f"cannot read {spec[1:]}: {e.strerror}") from None
    else:
        out = [_frame_index(v) for v in spec.replace(" ", "").split(",") if v]
    twice = _listed_twice(out)
    if twice is not None:
        raise argparse.ArgumentTypeError(f"frame {twice} is listed twice")
    if not out:
        raise argparse.ArgumentTypeError(f"no frame in {spec!r}")
    return out


def _listed_twice(frames: Sequence[Any]) -> Optional[int]:
    """The first frame index that ``frames`` (indices or (index, path) pairs) lists twice."""
    seen: set = set()
    for f in frames:
        i = f[0] if isinstance(f, tuple) else f
        if i in seen:
            return i
        seen.add(i)
    return None


def _integer(lo: int, *, also: Optional[int] = None, meaning: str = "") -> Callable[[str], int]:
    """An argparse type: an integer >= ``lo`` (or ``also``)."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo and v != also:
            alt = f" or {also}{meaning}" if also is not None else ""
            raise argparse.ArgumentTypeError(f"must be at least {lo}{alt}, got {v}")
        return v

    return parse


def _number(lo: float, hi: float, *, open_lo: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number in [lo, hi] (or (lo, hi] with ``open_lo``)."""

    def parse(text: str) -> float:
        v = _float_or_none(text)
        if v is None:
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if v > hi or v < lo or (open_lo and v == lo):
            raise argparse.ArgumentTypeError(
                f"must be in {'(' if open_lo else '['}{lo:g}, {hi:g}], got {text}")
        return v

    return parse


def _intrinsics(text: str) -> Tuple[float, float, float, float]:
    vals = [_float_or_none(v) for v in text.split(",")]
    if len(vals) != 4 or any(v is None for v in vals):
        raise argparse.ArgumentTypeError(f"expected FX,FY,CX,CY (four numbers), got {text!r}")
    if min(vals[:2]) <= 0:  # type: ignore[type-var]
        raise argparse.ArgumentTypeError(f"the focal lengths FX,FY must be positive, got {text!r}")
    return tuple(vals)  # type: ignore[return-value]


def build_parser(prog: Optional[str] = None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=prog,
        description="Gate a video or image sequence with leangate and reconstruct the kept "
        "frames with COLMAP (pycolmap): sparse model, frames registered, models, reprojection "
        "error, ATE against ground truth when the input has it.",
        epilog="The frames are written (video) or linked (sequence) as OUT/images/frame_<index>; "
        "the models go under OUT/sparse/N, COLMAP's messages into OUT/colmap.log. A run "
        "replaces OUT/images and OUT/sparse only when it made them itself (each holds a "
        f"{OUTPUT_MARKER} file): a non-empty images/ or sparse/ without it, a symbolic link "
        "there, or an input file inside them is refused and nothing is deleted. The plugin is "
        "found through GST_PLUGIN_PATH or --plugin-path.",
    )
    from . import __version__

    ap.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    ap.add_argument("input", help="video file, TUM-layout directory (rgb.txt), or image folder")
    ap.add_argument("--out", default="out/reconstruct", help="output directory (default %(default)s)")
    which = ap.add_mutually_exclusive_group()
    which.add_argument("--frames", metavar="LIST", type=_parse_frames, action="extend",
                       help="reconstruct these frames instead of gating: `0,5,10` (indices into "
                       "the sequence / decode order) or @FILE (`index [path]` per line); "
                       "repeatable, the lists add up (`--frames 0,5 --frames @more.txt`)")
    which.add_argument("--every", type=_integer(1), metavar="K",
                       help="reconstruct every K-th frame instead of gating (a dense reference)")
    g = ap.add_argument_group("gate (when neither --frames nor --every)")
    g.add_argument("--model", default=os.environ.get("LEANGATE_MODEL") or None,
                   help="LeanGate model (.onnx); default $LEANGATE_MODEL, else the embedded student")
    g.add_argument("--threshold", type=_number(0.0, 1.0), default=None, help="tau_keep in [0, 1]")
    g.add_argument("--warmup", type=_integer(0), default=None)
    g.add_argument("--max-gap", type=_integer(0), default=None, help="0: off")
    g.add_argument("--max-frames", type=_integer(1), default=None,
                   help="gate only the first N frames of an image sequence / keep at most N of a video")
    g.add_argument("--execution-provider", choices=("auto", "cpu", "cuda", "tensorrt"))
    g.add_argument("--plugin-path", metavar="PATH")
    s = ap.add_argument_group("COLMAP")
    s.add_argument("--matcher", choices=MATCHERS, default="auto",
                   help=f"auto: exhaustive up to {EXHAUSTIVE_MAX} images, else sequential")
    s.add_argument("--overlap", type=_integer(1), default=10,
                   help="sequential matching neighbours (at least 1)")
    s.add_argument("--max-features", type=_integer(1), default=4096, help="SIFT features per image")
    s.add_argument("--intrinsics", metavar="FX,FY,CX,CY", type=_intrinsics,
                   help="PINHOLE intrinsics (default: the input's intrinsics.txt, else unknown)")
    s.add_argument("--camera-model", choices=CAMERA_MODELS, metavar="MODEL",
                   help="COLMAP camera model (default PINHOLE with intrinsics, else "
                   "SIMPLE_RADIAL); one of " + ", ".join(CAMERA_MODELS))
    s.add_argument("--refine-intrinsics", action="store_true",
                   help="let bundle adjustment refine given intrinsics")
    s.add_argument("--min-model-size", type=_integer(2), default=3)
    s.add_argument("--init-min-tri-angle", type=_number(0.0, 179.0, open_lo=True), default=4.0,
                   metavar="DEG")
    s.add_argument("--threads", type=_integer(1, also=-1, meaning=" (every core)"), default=-1)
    ap.add_argument("--ply", metavar="PATH", help="export the largest model's points as PLY")
    ap.add_argument("--json", metavar="PATH", help="write the result (per frame too) as JSON")
    ap.add_argument("--colmap-log", action="store_true", help="let COLMAP log (glog) to stderr")
    ap.add_argument("-v", "--verbose", action="count", default=0,
                    help="progress on stderr (-v: info, -vv: debug)")
    return ap


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


def main(
    argv: Optional[Sequence[str]] = None,
    prog: Optional[str] = None,
    plugin_fallbacks: Iterable[str] = (),
) -> int:
    from .cli import configure_logging

    ap = build_parser(prog)
    args = ap.parse_args(argv)
    configure_logging(ap.prog, args.verbose)
    twice = _listed_twice(args.frames or [])
    if twice is not None:  # across repeated --frames (each list is checked as it is parsed)
        ap.error(f"argument --frames: frame {twice} is listed twice")
    if args.intrinsics and args.camera_model not in (None, "PINHOLE"):
        ap.error(f"--intrinsics are PINHOLE parameters; --camera-model {args.camera_model} "
                 "takes others")
    try:
        opts = SfmOptions(
            matcher=args.matcher,
            overlap=args.overlap,
            max_features=args.max_features,
            intrinsics=args.intrinsics,
            camera_model=args.camera_model,
            refine_intrinsics=args.refine_intrinsics,
            min_model_size=args.min_model_size,
            init_min_tri_angle=args.init_min_tri_angle,
            threads=args.threads,
        )
        gate = dict(
            model=args.model,
            threshold=args.threshold,
            warmup=args.warmup,
            max_gap=args.max_gap,
            execution_provider=args.execution_provider,
            plugin_path=args.plugin_path,
            plugin_fallbacks=plugin_fallbacks,
            max_frames=args.max_frames,
        )
        t = time.monotonic()
        rec = reconstruct(
            args.input,
            args.out,
            frames=args.frames,
            every=args.every,
            sfm=opts,
            gate=gate,
            ply=args.ply,
            colmap_log=args.colmap_log,
        )
        elapsed = time.monotonic() - t
        if args.json:
            with open(args.json, "w") as f:
                json.dump(rec.to_dict(), f, indent=1)
    except SetupError as e:
        log.error("%s", e)
        return 2
    except (PipelineError, RuntimeError) as e:
        log.error("%s", e)
        return 1
    except OSError as e:
        log.error("%s", e)
        return 2
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130

    s = rec.sfm
    for row in rec.frame_rows():
        print(f"frame {row['frame']} {row['name']} registered {int(row['registered'])}")
    frames_in = f"frames-in={rec.gate.frames_in} " if rec.gate else ""
    print(
        f"summary: {frames_in}kept={len(rec.frames)} registered={rec.registered}/{len(rec.frames)} "
        f"models={s.models} mean-reproj-px={_fmt(s.mean_reprojection_error_px, '.3f')} "
        f"points={s.points3d} ate-rmse-cm={_fmt(rec.ate_rmse_cm, '.2f')} matcher={s.matcher} "
        f"camera={s.camera_model} seconds={elapsed:.1f} model={s.model_dir or '-'}"
        + (f" ply={args.ply}" if args.ply and s.model_dir else ""),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
