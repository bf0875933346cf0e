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
import errno
import json
import logging
import os
import re
import secrets
import shutil
import stat
import tempfile
import threading
from typing import Any, Callable, Dict, List, Optional, Sequence, Set, Tuple

from . import _gst
from ._gst import PathLike, _make, _set
from . import _outdir
from ._outdir import interrupts_deferred
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
#: The staging directory of a run: ``.DIRNAME.leangate-staging-XXXXXXXX`` beside DIR (or
#: ``.leangate-staging-XXXXXXXX`` inside DIR when its parent is on another filesystem or
#: cannot be written).
STAGING_TAG = ".leangate-staging-"


def image_name(index: int, fmt: str) -> str:
    """The file name of the ``index``-th saved frame (0-based): ``kf_000000.jpg``, ..."""
    return f"{IMAGE_PREFIX}{index:0{IMAGE_DIGITS}d}.{fmt}"


def _is_output(name: str) -> bool:
    """Whether a run of the client may write a file of this name (its images and tables)."""
    return name in (CSV_NAME, JSON_NAME) or _OUTPUT.match(name) is not None


def _listed_images(d: str) -> Set[str]:
    """The image names the tables of an earlier run in ``d`` list (keyframes.json and
    keyframes.csv; an unreadable or malformed table lists nothing). Only names the client
    writes count, so a table cannot make it delete anything else (``../x``, ``notes.txt``)."""
    names: Set[str] = set()
    try:
        with open(os.path.join(d, JSON_NAME)) as f:
            doc = json.load(f)
        for r in doc.get("frames", []) if isinstance(doc, dict) else []:
            if isinstance(r, dict) and isinstance(r.get("image"), str):
                names.add(r["image"])
    except (OSError, ValueError):
        pass
    try:
        with open(os.path.join(d, CSV_NAME), newline="") as f:
            for r in csv.DictReader(f):
                if r.get("image"):
                    names.add(r["image"])
    except (OSError, ValueError, csv.Error):
        pass
    return {n for n in names if _OUTPUT.match(n)}


def earlier_output(d: str, entries: Sequence[str]) -> Tuple[List[str], List[str]]:
    """Split ``entries`` of ``d`` that a run could write into (the earlier run's output: its
    tables and the images they list, all regular files; the others: images no table lists,
    or entries that are not files). Entries named otherwise are in neither list."""
    listed = _listed_images(d)
    own: List[str] = []
    strange: List[str] = []
    for n in entries:
        if not _is_output(n):
            continue
        p = os.path.join(d, n)
        is_file = os.path.isfile(p) and not os.path.islink(p)
        if is_file and (n in (CSV_NAME, JSON_NAME) or n in listed):
            own.append(n)
        else:
            strange.append(n)
    return own, strange


def _shown(names: Sequence[str]) -> str:
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


def prepare_dir(directory: PathLike, overwrite: bool = False) -> str:
    """Check that ``directory`` can take a run's output and return its absolute path.

    Created (with its parents) when missing; nothing in it is deleted here, and only a probe
    file is written (and removed) to check that it can be: the run goes to a staging directory
    and replaces the earlier output only when it succeeds (see ``KeptFrameSaver``). An existing directory must be empty, unless ``overwrite``: then it may
    hold an earlier run's output (``keyframes.csv``, ``keyframes.json`` and the ``kf_*``
    images they list), which the run will replace, and files of other names, which are left
    alone (with a warning). Raises SetupError naming the directory when it is a file, cannot
    be created, listed or written, is not empty (without ``overwrite``), or (with it) holds
    ``kf_*`` images no table of an earlier run lists: the client deletes only files it wrote.
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
        raise SetupError(
            f"{d} is not empty ({len(entries)} entr{'y' if len(entries) == 1 else 'ies'}: "
            f"{_shown(entries)}); choose an empty or new "
            "directory, or pass --overwrite (overwrite=True) to replace an earlier run's "
            "kf_* images and keyframes.csv/.json there"
        )
    own, strange = earlier_output(d, entries)
    if strange:
        raise SetupError(
            f"--overwrite: {d} holds {len(strange)} entr{'y' if len(strange) == 1 else 'ies'} "
            f"named like the client's output that no {CSV_NAME}/{JSON_NAME} there lists "
            f"({_shown(strange)}): the client replaces only what it wrote itself; move "
            "them away or choose another directory"
        )
    try:
        fd, probe = tempfile.mkstemp(prefix=".leangate-write-test-", dir=d)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise SetupError(f"cannot write to {d}: {e.strerror}") from None
    others = [n for n in entries if not _is_output(n)]
    if own:
        log.info("%s holds an earlier run's output (%d files): replaced if this run succeeds",
                 d, len(own))
    if others:
        log.warning(
            "%s also holds %d file(s) that are not leangate output (left alone): %s",
            d,
            len(others),
            _shown(others),
        )
    return d


def _unused_name(parent: str, prefix: str) -> str:
    """A name in ``parent`` starting with ``prefix`` that nothing has (to rename a folder to)."""
    while True:
        p = os.path.join(parent, prefix + secrets.token_hex(4))
        if not os.path.lexists(p):
            return p


def _unlink_quietly(p: str) -> None:
    try:
        os.unlink(p)
    except OSError:
        pass


def _copy_xattrs(src: str, dst: str) -> None:
    """Give ``dst`` the extended attributes of ``src`` (its ACLs among them), as far as allowed."""
    try:
        names = os.listxattr(src)
    except (OSError, AttributeError):
        return
    for n in names:
        try:
            os.setxattr(dst, n, os.getxattr(src, n))
        except OSError:
            pass


class KeptFrameSaver:
    """Writes the frames leaving `leangate` with ``keep`` set into ``directory`` as
    ``kf_000000.jpg``, ``kf_000001.jpg``, ... (or ``.png``), and at ``finish`` the tables
    ``keyframes.csv`` and ``keyframes.json`` with one row per image: ``image``, ``frame`` (index
    in the input stream), ``pts_ns``, ``utility`` (empty / null for the `first` frame),
    ``reason``, ``keyframe_index``, ``frames_since_keyframe``, ``inference_us``, ``depth``.

    A run is all or nothing: the images and tables are written into a staging directory beside
    ``directory`` (same filesystem; inside it when the parent is on another one or cannot be
    written), and ``finish`` moves them into ``directory`` only after the run succeeded,
    replacing an earlier run's output there (``overwrite``); ``discard`` (a failed or
    interrupted run) deletes the staging directory and leaves ``directory`` as it was (one this
    saver created is removed again). Without ``overwrite``, ``finish`` refuses (PipelineError,
    staging directory removed) when ``directory``, empty at the start, now holds keyframes
    output: another run saving into it at the same time; that run's output is left as it is.

    Made by ``LeanGateSource(..., save_kept=DIR)``, which builds the branch into its pipeline
    (``attach``), hands it the bus messages (``on_message``) and calls ``finish`` or ``discard``
    when it closes. After that: ``committed`` (the run's output is in ``directory``), ``rows``
    (one dict per image written; empty after ``discard``), ``csv_path``, ``json_path``.
    """

    def __init__(self, directory: PathLike, fmt: str = "jpg", overwrite: bool = False):
        if fmt not in FORMATS:
            raise SetupError(f"image format must be one of {', '.join(FORMATS)}, not {fmt!r}")
        self.format = fmt
        target = os.path.abspath(os.fspath(directory))
        missing: List[str] = []  # the directories prepare_dir creates, deepest first
        p = target
        while not os.path.lexists(p) and os.path.dirname(p) != p:
            missing.append(p)
            p = os.path.dirname(p)
        self.directory = prepare_dir(target, overwrite)
        self.overwrite = overwrite
        self._created = missing
        self.csv_path = os.path.join(self.directory, CSV_NAME)
        self.json_path = os.path.join(self.directory, JSON_NAME)
        self.staging: Optional[str] = None  # made by attach
        self._keep_staging = False  # the swap failed: this run's files stay in staging
        self.committed = False
        self.discarded = False
        self.limit: Optional[int] = None  # at most this many images (the source's max_frames)
        self.rows: List[Dict[str, Any]] = []  # frames sent to the encoder, in order
        self.written = 0  # files multifilesink has closed (the first `written` rows)
        self._lock = threading.Lock()
        self._sink = None
        self._elements: tuple = ()

    @property
    def done(self) -> bool:
        """``finish`` or ``discard`` has run."""
        return self.committed or self.discarded

    def _make_staging(self) -> str:
        """A new staging directory beside DIR (on its filesystem: the swap renames it into
        DIR's place), or inside DIR when DIR is a mount point or its parent is on another
        filesystem or cannot be written (then ``_commit`` moves the files in one by one)."""
        d = self.directory
        real = os.path.realpath(d)  # DIR a symbolic link: the folder it names is replaced
        parent = os.path.dirname(real)
        try:
            if not os.path.ismount(real) and os.stat(parent).st_dev == os.stat(real).st_dev:
                return tempfile.mkdtemp(
                    prefix=f".{os.path.basename(real)}{STAGING_TAG}", dir=parent
                )
        except OSError:
            pass  # the parent cannot be written: stage inside DIR (same filesystem too)
        try:
            return tempfile.mkdtemp(prefix=STAGING_TAG, dir=d)
        except OSError as e:
            raise SetupError(f"cannot write to {d}: {e.strerror}") from None

    @property
    def queued(self) -> int:
        """Kept frames sent to the encoder so far (``written`` of them are on disk)."""
        with self._lock:
            return len(self.rows)

    def attach(self, pipeline, tee, frame_index: Callable[[Optional[int]], Optional[int]]) -> None:
        """Add ``queue ! videoconvert ! ENCODER ! multifilesink`` to ``pipeline``, fed by a new
        pad of ``tee``; ``frame_index(pts)`` gives the input index of the frame with that PTS."""
        Gst = _gst.Gst
        encoder, props = FORMATS[self.format]
        if self.staging is None:
            self.staging = self._make_staging()
        queue = _make("queue", "save-queue")
        convert = _make("videoconvert", "save-convert")
        enc = _make(encoder, "save-encoder")
        for k, v in props.items():
            _set(enc, k, v)
        sink = _make("multifilesink", "save-sink")
        pattern = f"{IMAGE_PREFIX}%0{IMAGE_DIGITS}d.{self.format}"
        _set(sink, "location", os.path.join(self.staging.replace("%", "%%"), pattern))
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
        # Weakly: the probe's GObject closure must not keep the saver (and through it the
        # pipeline's elements) alive in a cycle the garbage collector cannot see.
        queue.get_static_pad("sink").add_probe(
            Gst.PadProbeType.BUFFER, _gst.weak_method(self._probe, Gst.PadProbeReturn.OK)
        )

    @property
    def description(self) -> str:
        encoder, props = FORMATS[self.format]
        enc = " ".join([encoder] + [f"{k}={v}" for k, v in props.items()])
        return (
            f"queue ! videoconvert ! {enc} ! multifilesink location="
            f"{os.path.join(self.staging or self.directory, IMAGE_PREFIX)}%0{IMAGE_DIGITS}d."
            f"{self.format}" + (f" (staged: moved into {self.directory} when the run succeeds)"
                                if self.staging else "")
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
        """The run succeeded: write keyframes.csv and keyframes.json for the images on disk (the
        first ``written`` rows; an image cut short by stopping the pipeline is left out) into
        the staging directory, then move the images and tables into ``directory``, replacing
        an earlier run's output there. Call after the pipeline has stopped. Raises
        PipelineError when the tables cannot be written (then ``directory`` is left as it
        was) or the output cannot be moved into place (then this run's files stay in
        ``staging``, named in the message)."""
        if self.done:
            return
        with self._lock:
            rows = self.rows[: self.written]
            self.rows = rows
        if self.staging is None:  # never attached: nothing ran
            self.discard()
            return
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
            try:
                with open(os.path.join(self.staging, CSV_NAME), "w", newline="") as f:
                    w = csv.writer(f)
                    w.writerow(COLUMNS)
                    for r in rows:
                        w.writerow([csv_value(r[k]) for k in COLUMNS])
                with open(os.path.join(self.staging, JSON_NAME), "w") as f:
                    json.dump(doc, f, indent=1)
                    f.write("\n")
            except OSError as e:
                raise PipelineError(
                    f"cannot write the kept frames' meta: {e}; {self.directory} is left as it was"
                ) from None
            self._commit([r["image"] for r in rows])
        except BaseException:
            # Ctrl-C, SIGTERM or SIGHUP before the swap (during it they wait for its end), or
            # an error: nothing saved, the staging directory removed. A swap that failed
            # (PipelineError naming the staging directory) keeps this run's files there.
            if not self.committed:
                self.discard()
            raise
        log.info("wrote %d images, %s and %s to %s", len(rows), CSV_NAME, JSON_NAME,
                 self.directory)

    def _commit(self, images: List[str]) -> None:
        """Put the staged run (``images`` and the tables, all in ``staging``) in ``directory``'s
        place. Ctrl-C, SIGTERM and SIGHUP wait for the end of it (``interrupts_deferred``).

        With the staging directory beside DIR (the usual case) the swap is all at once for a
        reader: the files of DIR that are not the earlier run's output are hard-linked into
        the staging directory (folders and what cannot be linked are moved across right after
        the swap), which gets DIR's mode and owner, and then trades places with DIR in one
        ``renameat2(RENAME_EXCHANGE)`` (Linux), so that DIR is at every instant either the
        earlier complete folder or the new complete one, tables included. Where the system
        cannot exchange, two renames do it (DIR aside, the staging directory in its place),
        and DIR is missing, never mixed, for the instant between them. Then the earlier folder
        is emptied of what the earlier run wrote and removed.

        With the staging directory inside DIR (DIR is a mount point, or its parent is on
        another filesystem or cannot be written), or when DIR's owner cannot be given to a
        new folder, the files are moved in one by one: the earlier tables go first (so that
        an interrupted swap leaves no table claiming a complete set), then the images, the
        earlier images this run did not replace are deleted, and the tables come last."""
        d, staging = self.directory, self.staging
        assert staging is not None
        try:
            entries = sorted(os.listdir(d))
            old, strange = earlier_output(d, entries)
        except OSError as e:
            self._keep_staging = True
            raise PipelineError(
                f"cannot move the kept frames into {d}: {e}; this run's images and tables are "
                f"in {staging}"
            ) from None
        if not self.overwrite and (old or strange):
            # DIR was empty when this run started (prepare_dir refuses anything else without
            # overwrite): another run saving into it wrote its output meanwhile. It is not
            # replaced; this run's output is dropped.
            self.discarded = True
            shutil.rmtree(staging, ignore_errors=True)
            raise PipelineError(
                f"{d} now holds keyframes output that was not there when this run started "
                f"({_shown(old + strange)}; another run saving into it?): not replaced without "
                "--overwrite (overwrite=True); this run's images and tables are discarded"
            )
        with interrupts_deferred():
            try:
                if strange:  # appeared during the run
                    raise OSError(
                        f"{d} now holds files the client did not write: {_shown(strange)}"
                    )
                replaced = self._swap(d, staging, entries, old)
                if replaced is None:
                    self._move_in(d, staging, images, old)
            except OSError as e:
                self._keep_staging = True
                raise PipelineError(
                    f"cannot move the kept frames into {d}: {e}; this run's images and tables "
                    f"are in {staging}"
                ) from None
            self.committed = True
            if replaced is not None:
                self._remove_replaced(d, replaced, old)
            else:
                shutil.rmtree(staging, ignore_errors=True)
        if old:
            log.info("replaced an earlier run's output in %s (%d files)", d, len(old))

    def _swap(self, d: str, staging: str, entries: List[str], old: List[str]) -> Optional[str]:
        """Trade DIR for the staging directory beside it (see ``_commit``); return where the
        earlier DIR now is, or None when the swap cannot be done (staging inside DIR, DIR's
        owner cannot be kept) and nothing was changed. OSError when it failed: DIR is then as
        it was."""
        real = os.path.realpath(d)
        if os.path.dirname(staging) != os.path.dirname(real):
            return None  # staged inside DIR
        st, sst = os.stat(real), os.stat(staging)
        if (st.st_uid, st.st_gid) != (sst.st_uid, sst.st_gid):
            try:
                os.chown(staging, st.st_uid, st.st_gid)
            except OSError:
                return None  # a new folder would not be DIR's owner's
        own = set(old)
        linked = []
        for n in entries:
            if n in own:
                continue
            src = os.path.join(real, n)
            try:
                if not os.path.isdir(src) or os.path.islink(src):
                    os.link(src, os.path.join(staging, n), follow_symlinks=False)
                    linked.append(n)
            except OSError:
                pass  # moved across after the swap
        _copy_xattrs(real, staging)
        os.chmod(staging, stat.S_IMODE(st.st_mode))  # last: DIR's mode may forbid writing
        try:
            cwd_is_dir = os.path.samestat(os.stat("."), st)
        except OSError:
            cwd_is_dir = False
        try:
            if _outdir.exchange(staging, real):
                replaced = staging
            else:  # no exchange here: DIR aside, the staging directory in its place
                replaced = _unused_name(
                    os.path.dirname(real), f".{os.path.basename(real)}{STAGING_TAG}"
                )
                os.rename(real, replaced)
                try:
                    os.rename(staging, real)
                except OSError:
                    os.rename(replaced, real)
                    raise
        except OSError as e:
            os.chmod(staging, 0o700)
            for n in linked:  # the links are this run's; DIR keeps its files
                _unlink_quietly(os.path.join(staging, n))
            if e.errno in (errno.EACCES, errno.EPERM, errno.EBUSY):
                return None  # DIR cannot be renamed: file by file
            raise
        if cwd_is_dir:  # this process stood in DIR: it follows DIR to the new folder
            os.chdir(real)
        return replaced

    def _remove_replaced(self, d: str, replaced: str, old: List[str]) -> None:
        """Empty the earlier DIR (at ``replaced`` after the swap) and remove it: the earlier
        run's output is deleted; what else it holds (a folder, a file that could not be
        linked, one made during the swap) is moved into the new DIR; a second link of a file
        the new DIR has is dropped. Anything that cannot go is left there, with a warning."""
        real = os.path.realpath(d)
        own = set(old)
        try:
            names = os.listdir(replaced)
        except OSError as e:
            log.warning("cannot list the replaced folder %s: %s", replaced, e.strerror)
            return
        # The earlier tables last: a reader that opened the earlier DIR just before the swap
        # finds them as long as its images are there.
        names.sort(key=lambda n: n in (CSV_NAME, JSON_NAME))
        left = []
        for n in names:
            p, q = os.path.join(replaced, n), os.path.join(real, n)
            try:
                if n in own:
                    os.unlink(p)
                elif os.path.lexists(q):
                    if os.path.samestat(os.lstat(p), os.lstat(q)):
                        os.unlink(p)  # the same file, linked into the new DIR
                    else:
                        left.append(n)
                else:
                    os.rename(p, q)
            except OSError:
                left.append(n)
        try:
            os.rmdir(replaced)
        except OSError:
            log.warning(
                "%s holds what was in %s and could not be moved back (%s): look there",
                replaced, d, _shown(sorted(left)) or "?",
            )

    def _move_in(self, d: str, staging: str, images: List[str], old: List[str]) -> None:
        """The swap file by file (staging inside DIR): see ``_commit``."""
        for n in (JSON_NAME, CSV_NAME):
            if n in old:
                os.unlink(os.path.join(d, n))
        for n in images:
            os.replace(os.path.join(staging, n), os.path.join(d, n))
        new = set(images)
        for n in old:
            if n not in new and n not in (CSV_NAME, JSON_NAME):
                os.unlink(os.path.join(d, n))
        for n in (CSV_NAME, JSON_NAME):
            os.replace(os.path.join(staging, n), os.path.join(d, n))

    def discard(self) -> None:
        """The run failed or was interrupted: delete the staging directory and leave
        ``directory`` as it was before (removed again when this saver created it). Not after
        ``finish`` (done), nor when its swap failed (this run's files stay in the staging
        directory its error named)."""
        if self.done or self._keep_staging:
            return
        self.discarded = True
        with self._lock:
            self.rows = []
        with interrupts_deferred():  # a second Ctrl-C does not leave half a staging folder
            if self.staging is not None:
                shutil.rmtree(self.staging, ignore_errors=True)
            for p in self._created:
                try:
                    os.rmdir(p)
                except OSError:
                    break
        log.info("nothing saved: %s is as it was before this run", self.directory)
