"""``leangate-client`` (also ``python3 -m leangate_client``): run a video through leangate and
receive the kept frames as numpy arrays with their LeanGateMeta.

stdout is the product: one line per received frame (unless --quiet) and a ``summary:`` line::

    summary: frames-in=82 received=31 kept=31 forced=0 force-events=0 mode=drop shape=480x854x3:uint8 ...

With ``--save-kept DIR`` every kept frame is also written to DIR as an image (``--format jpg|png``)
with ``keyframes.csv`` and ``keyframes.json`` of their meta, and a progress line goes to stderr.
The run is staged beside DIR, which it replaces in one step only when it succeeds: a run that
fails or is interrupted leaves DIR as it was, and a reader sees DIR complete, old or new.
``--csv OUT`` likewise: checked before the run (not the input, not inside the --save-kept DIR,
its directory exists), written beside OUT and moved over it only when the run succeeds.

A ROS bag as INPUT (a ``.bag`` file, or a ROS 2 bag folder with metadata.yaml / ``*.db3`` /
``*.mcap``) goes to :mod:`leangate_client.bag`: ``BAG --topic IMAGE_TOPIC [--topic T2 ...] --out
OUT`` writes a bag with the kept images, every other topic and the decisions (``--topic`` and
``--out`` are refused with any other input).

Diagnostics go through ``logging`` to stderr (warnings by default; -v info, -vv debug).
Exit status: 0 on success, 1 on a pipeline error, 2 on a usage/setup error (missing file,
missing plugin, missing Python bindings, an output that cannot be written), 130 when
interrupted (Ctrl-C), 143 on SIGTERM, 129 on SIGHUP.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import logging
import math
import os
import signal
import sys
import threading
import time
from typing import Iterable, Iterator, List, Optional, Sequence
from urllib.parse import unquote, urlparse

from ._outdir import AtomicFile, check_output_file
from .argtypes import non_negative_int, non_negative_seconds, uint32, unit_interval
from .errors import PipelineError, SetupError
from .keyframes import CSV_NAME, FORMATS, JSON_NAME
from .meta import ROW_COLUMNS, csv_value, meta_row
from .source import EXECUTION_PROVIDERS, PRECISIONS, LeanGateSource

log = logging.getLogger("leangate_client")

CSV_COLUMNS = ROW_COLUMNS


class _Formatter(logging.Formatter):
    """``PROG: LEVEL: message`` (level in lower case), the usual shape of a CLI diagnostic."""

    def __init__(self, prog: str):
        super().__init__()
        self.prog = prog

    def format(self, record: logging.LogRecord) -> str:
        text = f"{self.prog}: {record.levelname.lower()}: {record.getMessage()}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


def configure_logging(prog: str, verbosity: int = 0, stream=None) -> logging.Handler:
    """Send the package's log records to stderr (or ``stream``) as ``PROG: level: message``.
    verbosity 0: warnings and errors, 1: info, 2 or more: debug."""
    handler = logging.StreamHandler(stream if stream is not None else sys.stderr)
    handler.setFormatter(_Formatter(prog))
    logger = logging.getLogger("leangate_client")
    for h in list(logger.handlers):
        if getattr(h, "_leangate_cli", False):
            logger.removeHandler(h)
    handler._leangate_cli = True  # type: ignore[attr-defined]
    logger.addHandler(handler)
    logger.setLevel(
        logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    )
    logger.propagate = False
    return handler


def _fmt_util(u: float) -> str:
    return "nan" if math.isnan(u) else f"{u:.6f}"


def _fmt(v, spec: str) -> str:
    return "-" if v is None else format(v, spec)


class _Progress:
    """A progress line on stderr: redrawn in place (at most 4 times a second) on a terminal,
    a new line every 10 s otherwise (a log file), and a last one at the end."""

    def __init__(self, prog: str, stream=None):
        self.prog = prog
        self.stream = stream if stream is not None else sys.stderr
        self.tty = self.stream.isatty()
        self.interval = 0.25 if self.tty else 10.0
        self.last = time.monotonic()
        self.drawn = False

    def update(self, text: str, final: bool = False) -> None:
        now = time.monotonic()
        if not final and now - self.last < self.interval:
            return
        self.last = now
        line = f"{self.prog}: {text}"
        if self.tty:
            self.stream.write("\r\x1b[K" + line + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
        self.drawn = not final


def build_parser(prog: Optional[str] = None) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog=prog,
        description="Run a video through leangate and receive the kept frames as numpy arrays "
        "with their LeanGateMeta (the hand-off to a Python SLAM process).",
        epilog="The plugin is found through GST_PLUGIN_PATH (the directory holding "
        "libgstleangate.so) or --plugin-path.",
    )
    from . import __version__

    ap.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    ap.add_argument(
        "input",
        nargs="?",
        help="video file, URI, or test://PATTERN?num-buffers=N&width=W&height=H (videotestsrc); "
        "with --depth a TUM-layout RGB-D directory",
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
        help="LeanGate model (.onnx); default $LEANGATE_MODEL, else the element's default "
        "(the embedded student leangate-s)",
    )
    ap.add_argument("--threshold", type=unit_interval, default=None,
                    help="keep threshold in [0,1]; default: the model's")
    ap.add_argument("--mode", choices=("drop", "annotate"), default="drop")
    ap.add_argument("--warmup", type=uint32, default=None)
    ap.add_argument("--max-gap", type=uint32, default=None)
    ap.add_argument("--execution-provider", choices=EXECUTION_PROVIDERS)
    ap.add_argument("--precision", choices=PRECISIONS, default=None,
                    help="which build of the embedded student runs; default: the element's (auto: "
                    "INT8 on the CPU)")
    ap.add_argument("--stats-interval", type=non_negative_seconds, default=None, metavar="SECONDS",
                    help="have the element post leangate-stats this often (logged at -v)")
    ap.add_argument("--csv", metavar="OUT",
                    help="write one row per received frame to OUT (checked before the run: "
                    "not the input, not in the --save-kept DIR; written to a temporary file "
                    "beside OUT that replaces it only when the run succeeds)")
    ap.add_argument("--save-kept", metavar="DIR",
                    help="write every kept frame to DIR as kf_000000.jpg, ... with "
                    f"{CSV_NAME} and {JSON_NAME} of their meta (frame, pts_ns, utility, reason, "
                    "...); DIR is created, and must be empty unless --overwrite. The run goes to "
                    "a staging directory beside DIR that takes DIR's place in one step only when "
                    "the run succeeds: a failed or interrupted run leaves DIR as it was")
    ap.add_argument("--format", choices=tuple(FORMATS), default="jpg",
                    help="image format of --save-kept (jpg: quality 95; png: lossless, "
                    "compression level 1)")
    ap.add_argument("--overwrite", action="store_true",
                    help="let --save-kept use a non-empty DIR: an earlier run's kf_* images and "
                    "tables there are replaced when this run succeeds; other files are left alone, "
                    "and kf_* images no table there lists (not written by this client) make it "
                    "refuse DIR")
    ap.add_argument("--max-frames", type=non_negative_int, default=None,
                    help="stop after receiving this many frames")
    ap.add_argument("--force-every", type=non_negative_int, default=0, metavar="N",
                    help="send a leangate-force-keyframe event upstream after every N received "
                    "frames (what a SLAM process does when it loses tracking)")
    ap.add_argument("--depth", action="store_true",
                    help="gate with depth (RGB-D): INPUT is then a TUM-layout directory (rgb.txt, "
                    "depth.txt of 16-bit PNGs, intrinsics.txt `fx fy cx cy depth_scale`), every "
                    "colour frame with a depth image within 20 ms; its frames go through "
                    "leangatedepthmux into leangate. A video, or a directory without them, is "
                    "refused (exit 2)")
    ap.add_argument("--topic", action="append", metavar="TOPIC",
                    help="with a ROS bag INPUT (a .bag file or a ROS 2 bag folder): the image "
                    "topic to gate; given again, the rig's other cameras, of which the message "
                    "nearest in stamp to each keep is kept (docs/python.md, \"ROS bags\")")
    ap.add_argument("--out", metavar="OUT",
                    help="with a ROS bag INPUT: the bag to write (same kind and storage): the "
                    "kept images, every other topic whole, TOPIC/leangate with the decisions")
    ap.add_argument("--set", action="append", default=[], metavar="PROPERTY=VALUE",
                    dest="set_properties",
                    help="set another property of the element, as gst-launch-1.0 would "
                    "(e.g. --set sharpness-lookback=0); repeatable")
    ap.add_argument("--quiet", action="store_true", help="no per-frame lines, only the summary")
    ap.add_argument("--plugin-path", metavar="PATH",
                    help="libgstleangate.so or its directory, when it is not on GST_PLUGIN_PATH")
    ap.add_argument("-v", "--verbose", action="count", default=0,
                    help="log more to stderr (-v: info, -vv: debug)")
    return ap


def main(
    argv: Optional[Sequence[str]] = None,
    prog: Optional[str] = None,
    plugin_fallbacks: Iterable[str] = (),
) -> int:
    """The command line. ``prog`` names the tool in usage and log lines (default: the name it
    was started as); ``plugin_fallbacks``: plugin files/directories to try when `leangate` is
    on neither ``--plugin-path`` nor ``GST_PLUGIN_PATH``."""
    ap = build_parser(prog)
    args = ap.parse_args(argv)
    configure_logging(ap.prog, args.verbose)
    args._plugin_fallbacks = plugin_fallbacks
    args.properties = {}
    for kv in args.set_properties:
        k, sep, v = kv.partition("=")
        if not sep or not k.strip():
            ap.error(f"--set takes PROPERTY=VALUE, not {kv!r}")
        args.properties[k.strip()] = v

    # SIGTERM and SIGHUP (a service stopped, `timeout`, a closed terminal) end the run the way
    # Ctrl-C does: the pipeline is stopped and a --save-kept run leaves DIR as it was and its
    # staging folder removed. During the swap that puts the run in DIR's place all three wait
    # for its end (_outdir.interrupts_deferred): DIR is then the new run's.
    with terminated_like_ctrl_c():
        return _run(ap, args)


class _Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, handled as Ctrl-C is (the signal number in ``args[0]``)."""


def _terminate(signum, _frame):
    raise _Terminated(signum)


@contextlib.contextmanager
def terminated_like_ctrl_c() -> Iterator[None]:
    """In the block, SIGTERM and SIGHUP raise ``_Terminated`` (a KeyboardInterrupt) as Ctrl-C
    raises KeyboardInterrupt; the earlier handlers come back after it. Signals can be handled
    in the main thread only (elsewhere a no-op). Install it after importing pycolmap: its glog
    replaces the SIGTERM handler with a stack dump."""
    handlers = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGHUP):
            handlers[sig] = signal.signal(sig, _terminate)
    try:
        yield
    finally:
        for sig, h in handlers.items():
            signal.signal(sig, h)


def _local_path(src: str) -> Optional[str]:
    """The file a source names (a path or a file:// URI), else None."""
    if src.startswith("file://"):
        return unquote(urlparse(src).path)
    return None if "://" in src else src


def _run(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """The run itself (`main`'s body once the arguments are read)."""
    plugin_fallbacks = args._plugin_fallbacks
    if args.input and args.source == "auto" and "://" not in args.input:
        from .bag import is_bag

        if is_bag(args.input):
            return _run_bag(ap, args)
    if args.topic or args.out:
        which = "--topic" if args.topic else "--out"
        what = (
            f"{args.input} is not one" if args.input and os.path.exists(args.input)
            else f"{args.input} does not exist" if args.input else "no INPUT was given"
        )
        ap.error(f"{which} applies to a ROS bag (a .bag file, or a ROS 2 bag folder with "
                 f"metadata.yaml); {what}")
    if args.source == "videotestsrc":
        src = args.input if args.input and args.input.startswith("test://") else "test://ball"
    elif args.input:
        src = args.input
    else:
        ap.error("INPUT is required (or --source videotestsrc)")
    if args.overwrite and not args.save_kept:
        ap.error("--overwrite applies to --save-kept DIR")
    if args.csv:  # before anything is opened, created or run
        try:
            check_output_file(
                args.csv,
                "--csv",
                inputs=[("the input", _local_path(src) or ""), ("the model", args.model or "")],
                inside=[(f"the --save-kept directory {args.save_kept}", args.save_kept)]
                if args.save_kept else [],
            )
        except SetupError as e:
            log.error("%s", e)
            return 2

    out: Optional[AtomicFile] = None
    progress = None
    writer = None
    kept = forced = with_depth = 0
    shapes: List[str] = []
    source = None
    try:
        source = _open_source(
            src,
            args.depth,
            model=args.model,
            threshold=args.threshold,
            mode=args.mode,
            warmup=args.warmup,
            max_gap=args.max_gap,
            execution_provider=args.execution_provider,
            precision=args.precision,
            max_frames=args.max_frames,
            arrays=True,
            stats_interval=args.stats_interval,
            plugin_path=args.plugin_path,
            plugin_fallbacks=plugin_fallbacks,
            properties=args.properties or None,
            save_kept=args.save_kept,
            save_format=args.format,
            overwrite=args.overwrite,
        )
        if args.csv:
            out = AtomicFile(args.csv, newline="")
            writer = csv.writer(out.file)
            writer.writerow(CSV_COLUMNS)
        saver = source.saver
        progress = _Progress(ap.prog) if saver is not None else None
        try:
            with source:
                for frame, m in source:
                    shape = f"{frame.shape[0]}x{frame.shape[1]}x{frame.shape[2]}:{frame.dtype}"
                    if shape not in shapes:
                        shapes.append(shape)
                    kept += m["keep"]
                    forced += m["reason"] == "forced"
                    with_depth += m["depth"] == "used"
                    if writer:
                        row = meta_row(m)
                        writer.writerow([csv_value(row[k]) for k in CSV_COLUMNS])
                    if not args.quiet:
                        print(
                            f"frame {m['frame']} pts {m['pts']} shape {frame.shape} mean "
                            f"{frame.mean():.1f} utility {_fmt_util(m['utility'])} keep "
                            f"{int(m['keep'])} reason {m['reason']} keyframe {m['keyframe_index']} "
                            f"since {m['frames_since_keyframe']} inference-us {m['inference_us']}"
                            + (f" depth {m['depth']}" if args.depth else ""),
                            flush=True,
                        )
                    if args.force_every and source.received % args.force_every == 0:
                        source.force_keyframe()
                    if progress:
                        progress.update(_saving(source))
                if out:  # flushed while a write error (ENOSPC) can still fail the whole run
                    out.close()
        finally:
            if progress:  # the last counts; it also ends the line before any error message
                progress.update(_saving(source), final=True)
        stats = source.stats
        if out:
            out.commit()  # the finished CSV replaces an earlier one only now
    except SetupError as e:
        log.error("%s", e)
        return _failed(source, 2)
    except PipelineError as e:
        log.error("pipeline error: %s", e)
        return _failed(source, 1)
    except _Terminated as e:
        log.error("terminated")
        return _failed(source, 128 + int(e.args[0]))
    except KeyboardInterrupt:
        log.error("interrupted")
        return _failed(source, 130)
    except OSError as e:  # the CSV file
        if args.csv:
            log.error("--csv %s: %s", args.csv, e.strerror or e)
        else:
            log.error("%s", e)
        return _failed(source, 2)
    finally:
        if out:
            out.discard()  # a failed or interrupted run: an earlier CSV is left as it was

    stats_txt = ""
    if stats:
        stats_txt = (
            f" provider={_fmt(stats.execution_provider, '')} model={_fmt(stats.model, '')}"
            f" precision={_fmt(stats.model_precision, '')}"
            f" threshold={_fmt(stats.threshold, '.4g')}"
            f" inference-mean-us={_fmt(stats.inference_mean_us, '.0f')}"
            f" inference-p99-us={_fmt(stats.inference_p99_us, '.0f')}"
        )
    else:
        log.info("no leangate-stats message (the stream was stopped before EOS)")
    print(
        f"summary: frames-in={source.frames_in} received={source.received} kept={kept} "
        f"forced={forced} force-events={source.forced_events} mode={args.mode} "
        f"shape={','.join(sorted(shapes)) or '-'}{stats_txt}"
        + (f" depth-used={with_depth}" if args.depth else "")
        + (f" csv={args.csv}" if args.csv else "")
        + (f" saved={len(saver.rows)} save-dir={saver.directory}" if saver else ""),
        flush=True,
    )
    return 0


def _open_source(src: str, depth: bool, **kwargs) -> LeanGateSource:
    """``LeanGateSource(src, ...)``; with ``depth``, ``src`` must be a TUM-layout RGB-D
    directory, gated through ``leangatedepthmux`` (``_inputs.SequenceGateSource``)."""
    if not depth:
        return LeanGateSource(src, **kwargs)
    from ._inputs import SequenceGateSource, attach_depth, open_input

    path = _local_path(src)
    need = (
        "--depth needs a TUM-layout RGB-D directory (rgb.txt, depth.txt, intrinsics.txt with "
        "`fx fy cx cy depth_scale`)"
    )
    if path is None or not os.path.isdir(path):
        raise SetupError(
            f"{need}, not {src}"
            + (" (a video file)" if path is not None and os.path.isfile(path) else "")
        )
    if not os.path.isfile(os.path.join(path, "rgb.txt")):
        raise SetupError(f"{need}; {path} has no rgb.txt")
    seq = open_input(path)
    attach_depth(seq)
    log.info(
        "%s: %d frames with depth, intrinsics %s, depth-scale %g",
        path, len(seq.frames), seq.intrinsics, seq.depth_scale,
    )
    return SequenceGateSource(
        seq.frames,
        depth_intrinsics=seq.intrinsics,
        depth_scale=seq.depth_scale,
        label=path,
        **kwargs,
    )


# -- ROS bags ------------------------------------------------------------------------
#: CLI options that do not apply to a bag (dest, how it is spelled).
_NOT_FOR_BAGS = (
    ("save_kept", "--save-kept"), ("csv", "--csv"), ("depth", "--depth"),
    ("max_frames", "--max-frames"), ("force_every", "--force-every"),
)


def _run_bag(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """``leangate-client BAG --topic T [--topic T2 ...] --out OUT`` (leangate_client.bag): the
    exit status."""
    from .bag import gate_bag, open_bag

    for dest, opt in _NOT_FOR_BAGS:
        if getattr(args, dest, None):
            ap.error(f"{opt} does not apply to a ROS bag (the kept frames go to --out OUT)")
    if args.source != "auto":
        ap.error("--source does not apply to a ROS bag")
    if not args.out:
        try:
            bag = open_bag(args.input)
            listing = bag.image_topics()
            bag.close()
        except SetupError as e:
            listing = str(e)
        ap.error(f"a ROS bag needs --topic IMAGE_TOPIC and --out OUT; {listing}")
    progress = _Progress(ap.prog)

    def on_keep(m):
        log.info(
            "keep frame %d stamp %d utility %s reason %s keyframe %s", m["frame"], m["stamp"],
            _fmt_util(m["utility"]), m["reason"], m["keyframe_index"],
        )

    try:
        summary = gate_bag(
            args.input, args.topic or [], args.out, overwrite=args.overwrite,
            progress=progress.update, on_keep=on_keep,
            model=args.model, threshold=args.threshold, mode=args.mode, warmup=args.warmup,
            max_gap=args.max_gap, execution_provider=args.execution_provider,
            precision=args.precision, stats_interval=args.stats_interval,
            properties=args.properties or None, plugin_path=args.plugin_path,
            plugin_fallbacks=args._plugin_fallbacks,
        )
    except SetupError as e:
        _end_progress(progress)
        log.error("%s", e)
        return 2
    except PipelineError as e:
        _end_progress(progress)
        log.error("pipeline error: %s", e)
        return 1
    except _Terminated as e:
        _end_progress(progress)
        log.error("terminated: nothing written to %s", args.out)
        return 128 + int(e.args[0])
    except KeyboardInterrupt:
        _end_progress(progress)
        log.error("interrupted: nothing written to %s", args.out)
        return 130
    except OSError as e:  # writing OUT (ENOSPC, permissions)
        _end_progress(progress)
        log.error("--out %s: %s (nothing written)", args.out, e.strerror or e)
        return 2
    progress.update(f"{summary.topic}: {summary.frames_in} frames gated, {summary.kept} kept; "
                    f"{summary.out} written", final=True)
    print(summary.line(), flush=True)
    return 0


def _end_progress(progress) -> None:
    if progress.drawn and progress.tty:
        progress.stream.write("\n")
        progress.stream.flush()


def _saving(source: LeanGateSource) -> str:
    s = source.saver
    if s.discarded:
        return f"{source.frames_in} frames in, {source.kept_received} kept, none saved"
    return (
        f"{source.frames_in} frames in, {source.kept_received} kept, {s.written} images "
        f"written to {s.directory}"
    )


def _failed(source: Optional[LeanGateSource], status: int) -> int:
    """Exit ``status``, after saying that --save-kept saved nothing (the source closed and
    discarded the run's staged files; closed here if the failure came before it ran)."""
    saver = source.saver if source is not None else None
    if saver is not None:
        try:
            source.close()  # a no-op when the `with` block closed it
        except PipelineError as e:
            log.debug("while stopping: %s", e)
        if saver.discarded:
            log.error("nothing saved: %s is as it was before this run", saver.directory)
        elif saver.committed:  # a signal during the swap waited for its end
            log.error("the kept frames had been saved to %s before that", saver.directory)
    return status
