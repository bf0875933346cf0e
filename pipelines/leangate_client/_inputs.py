"""Inputs and outputs of :mod:`leangate_client.reconstruct`: reading a video, a TUM RGB-D directory or
an image folder; gating it through ``leangate``; choosing explicit frames; the output directory
(``OUT/images`` written or linked, replaced only when this module made it: the marker file)."""

from __future__ import annotations

import logging
import math
import os
import shutil
import stat as stat_mod
import tempfile
from dataclasses import dataclass, field
from typing import Any, Dict, Iterable, List, Optional, Sequence, Tuple

from . import _gst
from .errors import PipelineError, SetupError
from ._gst import _depth_mux, _make, _set
from .source import LeanGateSource, buffer_to_rgb
from ._colmap import import_pycolmap
from ._outdir import OUTPUT_SUBDIRS, _make_owned_dir, check_output_subdir

log = logging.getLogger("leangate_client.reconstruct")


IMAGE_EXTS = (".png", ".jpg", ".jpeg")


#: Ground-truth poses further than this from a frame's timestamp are not associated.
GT_MAX_DIFFERENCE_S = 0.02


# -- inputs ------------------------------------------------------------------------------------
@dataclass
class FrameRef:
    """One frame of an input: its index in the sequence, timestamp (s) and image file (None for
    a video frame not yet written)."""

    index: int
    timestamp: Optional[float] = None
    path: Optional[str] = None
    #: The depth image associated with the frame (``attach_depth``), else None.
    depth: Optional[str] = None


@dataclass
class InputSequence:
    """What ``open_input`` found: ``kind`` is ``video``, ``sequence`` (rgb.txt) or ``images``."""

    path: str
    kind: str
    frames: List[FrameRef] = field(default_factory=list)
    intrinsics: Optional[Tuple[float, float, float, float]] = None
    #: intrinsics.txt's fifth value (depth units per metre), when it has one.
    depth_scale: Optional[float] = None
    #: (timestamp, camera centre x, y, z), camera-to-world translations, sorted by time.
    groundtruth: List[Tuple[float, float, float, float]] = field(default_factory=list)

    def centre_at(self, t: Optional[float]) -> Optional[Tuple[float, float, float]]:
        """Ground-truth camera centre nearest to ``t`` (within 20 ms), or None."""
        if t is None or not self.groundtruth:
            return None
        best = _nearest([g[0] for g in self.groundtruth], t)
        return None if best is None else tuple(self.groundtruth[best][1:])  # type: ignore


def _nearest(ts: List[float], t: float) -> Optional[int]:
    """Index of the time in sorted ``ts`` nearest to ``t`` within ``GT_MAX_DIFFERENCE_S`` (as
    TUM's associate.py), or None."""
    import bisect

    k = bisect.bisect_left(ts, t)
    near = [j for j in (k - 1, k) if 0 <= j < len(ts) and abs(ts[j] - t) <= GT_MAX_DIFFERENCE_S]
    return min(near, key=lambda j: abs(ts[j] - t)) if near else None


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


def read_depth_scale(path: str) -> Optional[float]:
    """The fifth value of intrinsics.txt's first data line (depth units per metre), or None
    when the line has only four; a value that is not a positive finite number is a SetupError."""
    for n, parts in _data_lines(path):
        if len(parts) < 5:
            return None
        v = _float_or_none(parts[4])
        if v is None or v <= 0:
            raise SetupError(
                f"{path} line {n}: depth_scale must be a positive number (depth units per "
                f"metre), not {parts[4]!r}"
            )
        return v
    return None


def attach_depth(seq: InputSequence) -> None:
    """Give each frame of a TUM-layout sequence its depth image: the entry of depth.txt
    nearest in time (within ``GT_MAX_DIFFERENCE_S``, as TUM's associate.py). Raises SetupError,
    naming what is missing, unless the directory has rgb.txt, depth.txt and intrinsics.txt with
    ``fx fy cx cy depth_scale`` and every colour frame has a depth image: a sequence is gated
    with its depth throughout or not at all."""
    need = (
        "needs a TUM-layout RGB-D directory (rgb.txt, depth.txt, intrinsics.txt with "
        "`fx fy cx cy depth_scale`)"
    )
    if seq.kind == "video":
        raise SetupError(f"depth {need}; {seq.path} is a video file")
    depth_txt = os.path.join(seq.path, "depth.txt")
    intr = os.path.join(seq.path, "intrinsics.txt")
    for what in ("rgb.txt", "depth.txt", "intrinsics.txt"):
        if not os.path.isfile(os.path.join(seq.path, what)):
            raise SetupError(f"depth {need}; {seq.path} has no {what}")
    seq.intrinsics = read_intrinsics(intr)
    seq.depth_scale = read_depth_scale(intr)
    if seq.depth_scale is None:
        raise SetupError(f"depth {need}; {intr} gives no depth_scale (its fifth value)")
    rows = []
    for n, parts in _data_lines(depth_txt):
        t = _float_or_none(parts[0]) if len(parts) >= 2 else None
        if t is None:
            raise SetupError(
                f"{depth_txt} line {n}: expected `timestamp path`, got {' '.join(parts)!r}"
            )
        rows.append((t, os.path.join(seq.path, parts[1])))
    rows.sort()
    ts = [r[0] for r in rows]
    missing = []
    for f in seq.frames:
        j = _nearest(ts, f.timestamp)  # type: ignore[arg-type]
        if j is None:
            missing.append(f)
            continue
        f.depth = rows[j][1]
    if missing:
        raise SetupError(
            f"depth: {len(missing)} of {len(seq.frames)} colour frames of {seq.path} have no "
            f"depth image within {GT_MAX_DIFFERENCE_S * 1000:.0f} ms in depth.txt (the first: "
            f"frame {missing[0].index}, t={missing[0].timestamp}); every frame needs one"
        )
    absent = [f.depth for f in seq.frames if not os.path.isfile(f.depth)]  # type: ignore
    if absent:
        raise SetupError(f"depth: {len(absent)} depth images not found (the first: {absent[0]})")


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
    ``frames``. All images must share one format (PNG or JPEG).

    ``depth_intrinsics`` (``(fx, fy, cx, cy)``, e.g. from ``attach_depth``): gate with depth.
    Every frame must then have its 16-bit depth PNG in ``FrameRef.depth`` (a SetupError
    otherwise); they are linked the same way and read by a second ``multifilesrc ! pngdec !
    videoconvert ! capsfilter`` (GRAY16_LE) into ``leangatedepthmux`` (``intrinsics``,
    ``depth_scale`` units per metre) before the gate, each frame's depth the one of its index
    (both streams at 30 fps). The meta's ``depth`` then says whether the frame was gated with it
    (``used``). ``label``: the input's name in messages and keyframes.json (default: the
    temporary directory of links)."""

    def __init__(
        self,
        frames: Sequence[FrameRef],
        *,
        depth_intrinsics: Optional[Sequence[float]] = None,
        depth_scale: float = 1000.0,
        label: Optional[str] = None,
        **kwargs,
    ):
        if not frames:
            raise SetupError("empty image sequence")
        exts = {os.path.splitext(f.path or "")[1].lower() for f in frames}
        exts = {".jpg" if e == ".jpeg" else e for e in exts}
        if len(exts) != 1 or not exts <= {".jpg", ".png"}:
            raise SetupError(f"an image sequence must be all PNG or all JPEG, found {sorted(exts)}")
        self._depth: Optional[Tuple[str, float]] = None
        if depth_intrinsics is not None:
            intr = [float(v) for v in depth_intrinsics]
            if len(intr) != 4 or not all(math.isfinite(v) for v in intr):
                raise SetupError(
                    f"depth_intrinsics must be 4 numbers fx, fy, cx, cy, not {depth_intrinsics!r}"
                )
            if not (math.isfinite(depth_scale) and depth_scale > 0):
                raise SetupError(
                    f"depth_scale must be positive (units per metre), not {depth_scale!r}"
                )
            lacking = [f for f in frames if not f.depth]
            if lacking:
                raise SetupError(
                    f"depth: {len(lacking)} of {len(frames)} frames have no depth image (the "
                    f"first: frame {lacking[0].index}); every frame needs one"
                )
            not_png = sorted(
                {f.depth for f in frames if not f.depth.lower().endswith(".png")}  # type: ignore
            )
            if not_png:
                raise SetupError(f"depth images must be 16-bit PNG, not {not_png[0]}")
            self._depth = (",".join(f"{v:g}" for v in intr), float(depth_scale))
        self._ext = exts.pop()
        self._tmp = tempfile.mkdtemp(prefix="leangate-seq-")
        for k, f in enumerate(frames):
            links = [(f.path, f"{k:06d}{self._ext}")]
            if self._depth:
                links.append((f.depth, f"depth_{k:06d}.png"))
            for src_path, name in links:
                dst = os.path.join(self._tmp, name)
                try:
                    os.symlink(os.path.abspath(src_path), dst)  # type: ignore[arg-type]
                except OSError:
                    shutil.copyfile(src_path, dst)  # type: ignore[arg-type]
        self._count = len(frames)
        super().__init__(self._tmp, **kwargs)
        if label:  # what messages and keyframes.json call the input (not the temporary links)
            self.source = label

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
        head = (
            f"multifilesrc location={self._tmp}/%06d{self._ext} index=0 "
            f"stop-index={self._count - 1} caps={self._caps()} ! decodebin"
        )
        if self._depth:
            head = (
                f"{head} ! m.sink multifilesrc location={self._tmp}/depth_%06d.png index=0 "
                f"stop-index={self._count - 1} caps={self._DEPTH_CAPS} ! pngdec ! videoconvert "
                f"! video/x-raw,format=GRAY16_LE ! m.depth leangatedepthmux name=m "
                f"intrinsics={self._depth[0]} depth-scale={self._depth[1]:g}"
            )
        return (
            f"{head} ! leangate name=gate {props} ! videoconvert ! appsink name=sink "
            "caps=video/x-raw,format=RGB sync=false"
        )

    _DEPTH_CAPS = "image/png,framerate=30/1"

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
        if not self._depth:
            self._watch_decoder(dec, gate)
            return
        # colour: decodebin ! m.sink; depth: multifilesrc ! pngdec ! videoconvert ! GRAY16_LE
        # ! m.depth; leangatedepthmux name=m ! leangate
        mux = _depth_mux(self.plugin, self._depth[0], self._depth[1])
        dsrc = _make("multifilesrc", "depth-src")
        _set(dsrc, "location", os.path.join(self._tmp, "depth_%06d.png"))
        _set(dsrc, "index", 0)
        _set(dsrc, "stop-index", self._count - 1)
        _set(dsrc, "caps", Gst.Caps.from_string(self._DEPTH_CAPS))
        ddec = _make("pngdec", "depth-dec")
        dconv = _make("videoconvert", "depth-convert")
        dcaps = _make("capsfilter", "depth-caps")
        _set(dcaps, "caps", Gst.Caps.from_string("video/x-raw,format=GRAY16_LE"))
        for el in (mux, dsrc, ddec, dconv, dcaps):
            pipeline.add(el)
        if not (dsrc.link(ddec) and ddec.link(dconv) and dconv.link(dcaps)):
            raise SetupError("cannot link the depth branch multifilesrc ! pngdec ! videoconvert")
        if dcaps.get_static_pad("src").link(mux.get_static_pad("depth")) != Gst.PadLinkReturn.OK:
            raise SetupError("cannot link the depth images to leangatedepthmux's depth pad")
        if not mux.link(gate):
            raise SetupError("cannot link leangatedepthmux ! leangate")
        self._watch_decoder(dec, mux)  # the colour pad is the mux's `sink`

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
    properties: Optional[Dict[str, Any]] = None,
) -> GateResult:
    """Run the input through leangate (drop mode); kept video frames are written as PNG into
    ``image_dir`` (a sequence's kept frames are used from their files). ``properties``: more of
    the element's properties, by their names (``{"sharpness-lookback": 4}``)."""
    kw = dict(
        model=model,
        threshold=threshold,
        mode="drop",
        warmup=warmup,
        max_gap=max_gap,
        execution_provider=execution_provider,
        plugin_path=plugin_path,
        plugin_fallbacks=plugin_fallbacks,
        properties=properties,
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


def image_name(f: FrameRef) -> str:
    """The name COLMAP knows a frame by, relative to the output directory:
    ``images/frame_<index>.<ext>``. By index, not by file: a sequence may list one file twice
    (a pause written by repeating a frame), and COLMAP's database refuses two images of one
    name."""
    ext = os.path.splitext(f.path or "")[1] or ".png"
    return f"images/frame_{f.index:06d}{ext}"


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
