"""Kept frames to disk: one image per frame `leangate` keeps, with a CSV and a JSON of their meta,
the input of COLMAP, nerfstudio or Gaussian splatting.

The images are encoded by GStreamer inside the client's own pipeline: the gate's output is
split by a ``tee``; one branch goes to the appsink (the frames the caller iterates over), the
other is the pipeline one would write with ``gst-launch-1.0``::

    ... ! leangate ! tee ! queue ! videoconvert ! jpegenc quality=95 ! multifilesink location=DIR/kf_%06d.jpg

A probe at the head of that branch keeps only frames whose meta says ``keep`` (so annotate mode
saves the kept frames too) and records each one's meta; ``multifilesink`` reports every file it
has closed (``post-messages``), and the tables list exactly those files.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import re
import tempfile
import threading
from typing import Any, Callable, Dict, List, Optional

from . import _gst
from ._gst import PathLike
from .errors import PipelineError, SetupError
from .meta import ROW_COLUMNS, csv_value, json_value, meta_dict, meta_row

log = logging.getLogger(__name__)

#: --format → (encoder element, its properties)
FORMATS = {"jpg": ("jpegenc", {"quality": 95}), "png": ("pngenc", {"compression-level": 1})}
IMAGE_PREFIX = "kf_"
IMAGE_DIGITS = 6
CSV_NAME = "keyframes.csv"
JSON_NAME = "keyframes.json"
#: Columns of keyframes.csv (and keys of each entry of keyframes.json's "frames").
COLUMNS = ("image",) + tuple(c for c in ROW_COLUMNS if c != "keep")
_OUTPUT = re.compile(r"^kf_\d{%d,}\.(jpg|png)$" % IMAGE_DIGITS)
_SINK_MESSAGE = "GstMultiFileSink"


def image_name(index: int, fmt: str) -> str:
    """The file name of the ``index``-th saved frame (0-based): ``kf_000000.jpg``, ..."""
    return f"{IMAGE_PREFIX}{index:0{IMAGE_DIGITS}d}.{fmt}"


def _is_output(name: str) -> bool:
    return name in (CSV_NAME, JSON_NAME) or _OUTPUT.match(name) is not None


def prepare_dir(directory: PathLike, overwrite: bool = False) -> str:
    """Make ``directory`` ready for a run's output and return its absolute path.

    Created (with its parents) when missing. An existing directory must be empty, unless
    ``overwrite``: then an earlier run's output there (``kf_*`` images, ``keyframes.csv``,
    ``keyframes.json``) is deleted and any other file is left alone. Raises SetupError naming
    the directory when it is a file, cannot be created, is not empty, or cannot be written.
    """
    d = os.path.abspath(os.fspath(directory))
    if os.path.exists(d) and not os.path.isdir(d):
        raise SetupError(f"cannot save kept frames to {d}: it exists and is not a directory")
    try:
        os.makedirs(d, exist_ok=True)
    except OSError as e:
        raise SetupError(f"cannot create the directory {d} for the kept frames: {e.strerror}") from None
    try:
        entries = sorted(os.listdir(d))
    except OSError as e:
        raise SetupError(f"cannot list {d}: {e.strerror}") from None
    if entries and not overwrite:
        shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
        raise SetupError(
            f"{d} is not empty ({len(entries)} entr{'y' if len(entries) == 1 else 'ies'}: "
            f"{shown}); choose an empty or new "
            "directory, or pass --overwrite (overwrite=True) to replace an earlier run's "
            "kf_* images and keyframes.csv/.json there"
        )
    try:
        fd, probe = tempfile.mkstemp(prefix=".leangate-write-test-", dir=d)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise SetupError(f"cannot write to {d}: {e.strerror}") from None
    old = [n for n in entries if _is_output(n)]
    for n in old:
        try:
            os.unlink(os.path.join(d, n))
        except OSError as e:
            raise SetupError(f"--overwrite: cannot delete {os.path.join(d, n)}: {e.strerror}") from None
    others = [n for n in entries if not _is_output(n)]
    if old:
        log.info("deleted an earlier run's output in %s (%d files)", d, len(old))
    if others:
        log.warning(
            "%s also holds %d file(s) that are not leangate output (left alone): %s",
            d,
            len(others),
            ", ".join(others[:3]) + (", ..." if len(others) > 3 else ""),
        )
    return d


class KeptFrameSaver:
    """Writes the frames leaving `leangate` with ``keep`` set into ``directory`` as
    ``kf_000000.jpg``, ``kf_000001.jpg``, ... (or ``.png``), and at ``finish`` the tables
    ``keyframes.csv`` and ``keyframes.json`` with one row per image: ``image``, ``frame`` (index
    in the input stream), ``pts_ns``, ``utility`` (empty / null for the `first` frame),
    ``reason``, ``keyframe_index``, ``frames_since_keyframe``, ``inference_us``.

    Made by ``LeanGateSource(..., save_kept=DIR)``, which builds the branch into its pipeline
    (``attach``), hands it the bus messages (``on_message``) and calls ``finish`` when it
    closes. After that: ``rows`` (one dict per image written), ``csv_path``, ``json_path``.
    """

    def __init__(self, directory: PathLike, fmt: str = "jpg", overwrite: bool = False):
        if fmt not in FORMATS:
            raise SetupError(f"image format must be one of {', '.join(FORMATS)}, not {fmt!r}")
        self.format = fmt
        self.directory = prepare_dir(directory, overwrite)
        self.csv_path = os.path.join(self.directory, CSV_NAME)
        self.json_path = os.path.join(self.directory, JSON_NAME)
        self.limit: Optional[int] = None  # at most this many images (the source's max_frames)
        self.rows: List[Dict[str, Any]] = []  # frames sent to the encoder, in order
        self.written = 0  # files multifilesink has closed (the first `written` rows)
        self._lock = threading.Lock()
        self._sink = None
        self._elements: tuple = ()
        self._finished = False

    @property
    def queued(self) -> int:
        """Kept frames sent to the encoder so far (``written`` of them are on disk)."""
        with self._lock:
            return len(self.rows)

    def attach(self, pipeline, tee, frame_index: Callable[[Optional[int]], Optional[int]]) -> None:
        """Add ``queue ! videoconvert ! ENCODER ! multifilesink`` to ``pipeline``, fed by a new
        pad of ``tee``; ``frame_index(pts)`` gives the input index of the frame with that PTS."""
        from .source import _make, _set

        Gst = _gst.Gst
        encoder, props = FORMATS[self.format]
        queue = _make("queue", "save-queue")
        convert = _make("videoconvert", "save-convert")
        enc = _make(encoder, "save-encoder")
        for k, v in props.items():
            _set(enc, k, v)
        sink = _make("multifilesink", "save-sink")
        pattern = f"{IMAGE_PREFIX}%0{IMAGE_DIGITS}d.{self.format}"
        _set(sink, "location", os.path.join(self.directory.replace("%", "%%"), pattern))
        _set(sink, "post-messages", True)
        _set(sink, "sync", False)
        for el in (queue, convert, enc, sink):
            pipeline.add(el)
        if not (
            tee.link(queue) and queue.link(convert) and convert.link(enc) and enc.link(sink)
        ):
            raise SetupError(f"cannot link tee ! queue ! videoconvert ! {encoder} ! multifilesink")
        self._sink = sink
        self._elements = (queue, convert, enc, sink)
        self._frame_index = frame_index
        queue.get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER, self._probe)

    @property
    def description(self) -> str:
        encoder, props = FORMATS[self.format]
        enc = " ".join([encoder] + [f"{k}={v}" for k, v in props.items()])
        return (
            f"queue ! videoconvert ! {enc} ! multifilesink location="
            f"{os.path.join(self.directory, IMAGE_PREFIX)}%0{IMAGE_DIGITS}d.{self.format}"
        )

    def _probe(self, pad, info):
        # A streaming thread: no exception may leave; frames not kept (annotate mode) are dropped.
        Gst = _gst.Gst
        buf = info.get_buffer()
        if buf is None:
            return Gst.PadProbeReturn.OK
        pts = None if buf.pts == Gst.CLOCK_TIME_NONE else int(buf.pts)
        index = self._frame_index(pts)
        meta = meta_dict(buf)
        if meta is None or not meta["keep"]:
            return Gst.PadProbeReturn.DROP
        with self._lock:
            n = len(self.rows)
            if self.limit is not None and n >= self.limit:
                return Gst.PadProbeReturn.DROP
            row = {"image": image_name(n, self.format)}
            row.update(meta_row({"frame": index, "pts": pts, **meta}))
            del row["keep"]
            self.rows.append(row)
        return Gst.PadProbeReturn.OK

    def owns(self, element) -> bool:
        """Whether ``element`` is one of the image branch's (to name the directory in errors)."""
        return element is not None and element in self._elements

    def on_message(self, msg) -> bool:
        """Count the files multifilesink reports; True when ``msg`` was one of those reports."""
        if self._sink is None or msg.src is not self._sink:
            return False
        s = msg.get_structure()
        if s is None or s.get_name() != _SINK_MESSAGE:
            return False
        self.written = max(self.written, int(s.get_value("index")) + 1)
        return True

    def finish(self, source: str, frames_in: int, stats=None) -> None:
        """Write keyframes.csv and keyframes.json for the images on disk (the first ``written``
        rows) and delete any image file beyond them (a write cut short by an error or by
        stopping the pipeline). Call after the pipeline has stopped; raises PipelineError
        when the tables cannot be written."""
        if self._finished:
            return
        self._finished = True
        with self._lock:
            rows = self.rows[: self.written]
            dropped = self.rows[self.written :]
            self.rows = rows
        for r in dropped:
            try:
                os.unlink(os.path.join(self.directory, r["image"]))
            except FileNotFoundError:
                pass
            except OSError as e:
                log.warning("cannot delete the unfinished image %s: %s", r["image"], e.strerror)
        doc = {
            "source": source,
            "directory": self.directory,
            "format": self.format,
            "frames_in": frames_in,
            "kept": len(rows),
            "threshold": None if stats is None else stats.threshold,
            "model": None if stats is None else stats.model,
            "columns": list(COLUMNS),
            "frames": [{k: json_value(r[k]) for k in COLUMNS} for r in rows],
        }
        try:
            with open(self.csv_path, "w", newline="") as f:
                w = csv.writer(f)
                w.writerow(COLUMNS)
                for r in rows:
                    w.writerow([csv_value(r[k]) for k in COLUMNS])
            with open(self.json_path, "w") as f:
                json.dump(doc, f, indent=1)
                f.write("\n")
        except OSError as e:
            raise PipelineError(f"cannot write the kept frames' meta: {e}") from None
        log.info("wrote %d images, %s and %s", len(rows), CSV_NAME, JSON_NAME)
