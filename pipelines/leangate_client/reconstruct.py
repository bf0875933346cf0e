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

Where things live: this module holds :func:`reconstruct`, :class:`Reconstruction` and the CLI
(``python -m leangate_client.reconstruct``, ``pipelines/reconstruct.py``); ``_inputs`` reads the
inputs, gates them and chooses frames; ``_colmap`` drives COLMAP (child process, models, ATE,
PLY); ``_outdir`` decides which output folders may be replaced. Every name is importable from here
as before.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence, Tuple

from .errors import PipelineError, SetupError
from ._colmap import (  # noqa: F401 (the public names stay importable from here)
    CAMERA_MODELS,
    EXHAUSTIVE_MAX,
    MATCHERS,
    PYCOLMAP_VERSION,
    SfmOptions,
    SfmResult,
    _CHILD_LOG,
    _GLOG_LINE,
    _pycolmap_version,
    _run_sfm_here,
    _sfm_child,
    _stage,
    ate_rmse,
    export_ply,
    import_pycolmap,
    run_sfm,
    umeyama_sim3,
)
from ._outdir import OUTPUT_MARKER, OUTPUT_SUBDIRS, _make_owned_dir, check_output_subdir  # noqa: F401
from ._outdir import AtomicFile, check_distinct_outputs, check_output_file
from ._inputs import (  # noqa: F401
    FrameRef,
    GT_MAX_DIFFERENCE_S,
    GateResult,
    IMAGE_EXTS,
    InputSequence,
    SequenceGateSource,
    _data_lines,
    _float_or_none,
    _input_under_output,
    check_output_dir,
    decode_video_frames,
    fresh_image_dir,
    gate_input,
    image_name,
    link_images,
    open_input,
    read_intrinsics,
    select_frames,
    write_image,
)

log = logging.getLogger("leangate_client.reconstruct")


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
    extra = _frame_files(inp, frames)
    check_output_files(inp, out_dir, [("--ply", ply)], extra)
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


def _frame_files(inp: InputSequence, frames: Optional[Sequence[Any]]) -> List[str]:
    """The files ``frames`` names (``(index, path)`` pairs: --frames @FILE), as paths."""
    out = []
    for f in frames or []:
        if isinstance(f, (tuple, list)) and f[1]:
            out.append(f[1] if os.path.isabs(f[1]) else os.path.join(inp.path, f[1]))
    return out


#: Files a run writes into OUT itself (besides OUT/images and OUT/sparse).
RUN_FILES = ("database.db", "colmap.log", "sfm_request.json", "sfm_result.json")


def check_output_files(
    inp: InputSequence,
    out_dir: str,
    outputs: Sequence[Tuple[str, Optional[str]]],
    extra: Sequence[str] = (),
) -> None:
    """Raise SetupError, before any work, unless each ``(option, path)`` of ``outputs`` (None: not
    given; ``--json``, ``--ply``) can be written without losing anything: not two of them one
    file, none an input (the video; a sequence's list files and images, or any file already in
    its directory; ``extra``), none a file the run writes itself (OUT/images, OUT/sparse,
    OUT/colmap.log, ...), not a directory, and in a directory that exists and can be written."""
    given = [(o, p) for o, p in outputs if p]
    check_distinct_outputs(given)
    if not given:
        return
    inputs = [("the input", inp.path)] if inp.kind == "video" else []
    if inp.kind != "video":
        for name in ("rgb.txt", "intrinsics.txt", "groundtruth.txt", "groundtruth_tum.txt"):
            inputs.append((f"the input's {name}", os.path.join(inp.path, name)))
        inputs += [("an image of the input", f.path) for f in inp.frames if f.path]
    inputs += [("a frame given with --frames", p) for p in extra]
    inputs += [(f"a file the run writes ({os.path.join(out_dir, n)})", os.path.join(out_dir, n))
               for n in RUN_FILES]
    inside = [(f"{os.path.join(out_dir, sub)}, which the run replaces", os.path.join(out_dir, sub))
              for sub in OUTPUT_SUBDIRS]
    if inp.kind != "video":  # any file already in the sequence's folder (links there too)
        tops = {os.path.realpath(inp.path), os.path.abspath(inp.path)}
        for option, path in given:
            names = {os.path.realpath(path), os.path.abspath(path)}
            if os.path.lexists(path) and any(n.startswith(t + os.sep) for n in names for t in tops):
                raise SetupError(
                    f"{option} {path} is a file of the input {inp.path}, which would be "
                    "overwritten; choose another file"
                )
    for option, path in given:
        check_output_file(path, option, inputs, inside)


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


def _integer(
    lo: int, *, also: Optional[int] = None, meaning: str = "", hi: Optional[int] = None
) -> Callable[[str], int]:
    """An argparse type: an integer >= ``lo`` (or ``also``), and <= ``hi`` when given."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo and v != also:
            alt = f" or {also}{meaning}" if also is not None else ""
            raise argparse.ArgumentTypeError(f"must be at least {lo}{alt}, got {v}")
        if hi is not None and v > hi:
            raise argparse.ArgumentTypeError(f"must be at most {hi}, got {v}")
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
    g.add_argument("--sharpness-wait", type=_integer(0, hi=30), default=None, metavar="N",
                   help="the element's sharpness-wait; with --sharpness-lookback, a due keep "
                   "settles N frames later on the sharpest frame held (2 and 4: sharper "
                   "keyframes on footage that is not fast, docs/reconstruction.md)")
    g.add_argument("--sharpness-lookback", type=_integer(0, hi=30), default=None, metavar="N",
                   help="the element's sharpness-lookback: frames held to go back to (default 3)")
    g.add_argument("--sharpness-margin", type=_number(0.0, 1.0), default=None, metavar="M",
                   help="the element's sharpness-margin: a keep due on a blurred frame waits "
                   "while its utility is below threshold + M (default 0.05; 0: keeps at once)")
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
    from .cli import configure_logging, terminated_like_ctrl_c

    ap = build_parser(prog)
    args = ap.parse_args(argv)
    configure_logging(ap.prog, args.verbose)
    twice = _listed_twice(args.frames or [])
    if twice is not None:  # across repeated --frames (each list is checked as it is parsed)
        ap.error(f"argument --frames: frame {twice} is listed twice")
    if args.intrinsics and args.camera_model not in (None, "PINHOLE"):
        ap.error(f"--intrinsics are PINHOLE parameters; --camera-model {args.camera_model} "
                 "takes others")
    # pycolmap before the signal handlers: importing it installs glog's, which answers SIGTERM
    # with a stack dump and leaves COLMAP's child process running. (Missing: reported below.)
    try:
        import_pycolmap()
    except SetupError:
        pass
    # SIGTERM and SIGHUP (`kill PID`, systemd, `timeout`) end the run as Ctrl-C does: COLMAP's
    # child process group is stopped too.
    with terminated_like_ctrl_c():
        return _run(args, plugin_fallbacks)


def _run(args: argparse.Namespace, plugin_fallbacks: Iterable[str]) -> int:
    """``main``'s run, once the arguments are read."""
    from .cli import _Terminated

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
            properties={
                name: value
                for name, value in (
                    ("sharpness-wait", args.sharpness_wait),
                    ("sharpness-lookback", args.sharpness_lookback),
                    ("sharpness-margin", args.sharpness_margin),
                )
                if value is not None
            },
        )
        # The output files, before any work: not an input, not one file twice, a directory to go in.
        inp = open_input(args.input)
        check_output_files(inp, args.out, [("--json", args.json), ("--ply", args.ply)],
                           _frame_files(inp, args.frames))
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
            try:
                with AtomicFile(args.json) as out:  # replaces an earlier file only when complete
                    json.dump(rec.to_dict(), out.file, indent=1)
            except OSError as e:
                raise SetupError(f"--json {args.json}: {e.strerror or e}") from None
    except SetupError as e:
        log.error("%s", e)
        return 2
    except (PipelineError, RuntimeError) as e:
        log.error("%s", e)
        return 1
    except OSError as e:
        log.error("%s", e)
        return 2
    except _Terminated as e:
        log.error("terminated")
        return 128 + int(e.args[0])
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
