"""COLMAP driving for :mod:`leangate_client.reconstruct`: pycolmap feature extraction, matching and
incremental mapping in a child process (a COLMAP abort becomes a PipelineError), the sparse
models read back, ATE after a similarity (Umeyama) alignment, PLY export."""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Sequence, Tuple

from . import _gst
from .errors import PipelineError, SetupError

from ._outdir import AtomicFile, _make_owned_dir, check_output_subdir

log = logging.getLogger("leangate_client.reconstruct")


MATCHERS = ("auto", "exhaustive", "sequential")


#: ``matcher="auto"`` matches exhaustively up to this many images, sequentially above.
EXHAUSTIVE_MAX = 40


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
    # glog writes log files into $TMPDIR (or /tmp) unless told to log to stderr: a write where
    # the user did not say. Its messages go to stderr, which run_sfm collects in OUT/colmap.log.
    pycolmap.logging.logtostderr = True
    return pycolmap


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
    env["GLOG_logtostderr"] = "1"  # no glog files in $TMPDIR: COLMAP's messages go to colmap.log
    # pycolmap first: see import_pycolmap. The child ends with this process (SIGKILL when it
    # dies, even killed), and runs in a process group of its own: a signal meant for this
    # process (Ctrl-C, SIGTERM) is this process's to act on, and it stops the whole group.
    code = (
        "import ctypes, os, signal, sys\n"
        "try:\n"
        "    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGKILL))  # PR_SET_PDEATHSIG\n"
        "except (OSError, AttributeError):\n"
        "    pass\n"
        "if os.getppid() != int(sys.argv[2]):\n"
        "    sys.exit(1)  # the parent is already gone\n"
        "import pycolmap\n"
        "from leangate_client._colmap import _sfm_child\n"
        "sys.exit(_sfm_child(sys.argv[1]))\n"
    )
    log_path = os.path.join(out_dir, "colmap.log")
    stage = "start"
    colmap_errors: List[str] = []
    with open(log_path, "w") as colmap_file:
        proc = subprocess.Popen(
            [sys.executable, "-c", code, request, str(os.getpid())],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            env=env,
            text=True,
            errors="replace",
            start_new_session=True,
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
        except BaseException:  # Ctrl-C, SIGTERM (cli._Terminated), an error here: COLMAP stops too
            _stop_group(proc, colmap_file)
            raise
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


def _stop_group(proc: "subprocess.Popen[str]", sink=None, grace_s: float = 3.0) -> None:
    """End ``proc``, which leads a process group of its own: SIGTERM to the group, what it still
    writes to stderr into ``sink`` (COLMAP's log), then SIGKILL if it has not ended after
    ``grace_s`` seconds; waited for."""
    try:
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except (ProcessLookupError, PermissionError):
            pass
        try:
            rest = proc.communicate(timeout=grace_s)[1]
            if sink is not None and rest:
                sink.write(rest)
        except subprocess.TimeoutExpired:
            pass
    finally:
        if proc.returncode is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
            proc.wait()


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
    """The points of the model in ``model_dir`` as a PLY file at ``path``, written beside it and
    moved over it when complete (an earlier file is replaced only then)."""
    pycolmap = import_pycolmap()
    out = AtomicFile(path, open_file=False)
    try:
        pycolmap.Reconstruction(model_dir).export_PLY(out.writes_to)
    except BaseException:
        out.discard()
        raise
    out.commit()


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


def _pycolmap_version() -> str:
    try:
        import pycolmap

        return pycolmap.__version__
    except ImportError:
        return "?"
