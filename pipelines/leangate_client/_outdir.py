"""Outputs that lose nothing.

Whose output directory it is: :mod:`leangate_client.reconstruct` replaces ``OUT/images`` and
``OUT/sparse`` only when a run of it made them (a marker file inside); anything else is refused.

Output files (``leangate-client --csv``, ``reconstruct.py --json`` and ``--ply``):
``check_output_file`` refuses, before any work, a path that is an input, lies where the run
writes otherwise, is a directory or has no directory to go in; ``AtomicFile`` writes it to a
temporary file beside it and moves that over it (``os.replace``) only when the run succeeded, so
a failed or interrupted run leaves the previous file as it was.

Swaps: ``interrupts_deferred`` holds Ctrl-C, SIGTERM and SIGHUP back while an output is put in
place; ``exchange`` trades two directories in one step (``--save-kept DIR``, keyframes.py)."""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import secrets
import signal
import sys
import threading
from typing import Iterable, Iterator, List, Optional, Tuple

from .errors import SetupError


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


#: The signals that end a run (Ctrl-C, and SIGTERM and SIGHUP, which the command lines handle
#: as Ctrl-C) and that ``interrupts_deferred`` holds back.
DEFERRED_SIGNALS = tuple(
    getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)
)


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold Ctrl-C (SIGINT), SIGTERM and SIGHUP back until the block is done (the renames that
    swap a run's output into place and the removal of what it replaced), then act on them as
    their handlers would have, in the order they came (a handler that raises, such as Ctrl-C's
    KeyboardInterrupt, ends the delivery there; the default action of SIGTERM or SIGHUP kills
    the process, as it would have). A signal whose handler was not set from Python (C code's,
    which cannot be restored from here) is left alone. Only the main thread can do this;
    elsewhere a no-op."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    got: List[int] = []

    def hold(sig, frame):
        if sig not in got:
            got.append(sig)

    old = {}
    try:
        for sig in DEFERRED_SIGNALS:
            if signal.getsignal(sig) is not None:
                old[sig] = signal.signal(sig, hold)
    except (ValueError, OSError):
        for sig, h in old.items():
            signal.signal(sig, h)
        yield
        return
    try:
        yield
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        for sig in got:
            h = old[sig]
            if callable(h):
                h(sig, None)
            elif h == signal.SIG_DFL:
                os.kill(os.getpid(), sig)


# -- swapping a directory ----------------------------------------------------------------------
_RENAME_EXCHANGE = 2  # linux/fs.h
_renameat2: Optional[object] = None  # libc's renameat2, False when there is none


def _libc_renameat2():
    global _renameat2
    if _renameat2 is None:
        _renameat2 = False
        if sys.platform.startswith("linux"):
            try:
                libc = ctypes.CDLL(None, use_errno=True)
                f = libc.renameat2  # glibc 2.28, musl 1.2.2
                f.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                              ctypes.c_uint]
                f.restype = ctypes.c_int
                _renameat2 = f
            except (OSError, AttributeError):
                pass
    return _renameat2 or None


def exchange(a: str, b: str) -> bool:
    """Swap the two existing paths ``a`` and ``b`` (same filesystem) in one step: Linux's
    ``renameat2(RENAME_EXCHANGE)``, so that at every instant each name is the one or the
    other, complete. False when the system or the filesystem cannot (no renameat2: another
    system, an old libc or kernel; a filesystem without it); OSError when it can but refuses
    (permissions, a mount point: EBUSY, EXDEV)."""
    f = _libc_renameat2()
    if f is None:
        return False
    at_fdcwd = -100
    if f(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), a, None, b)


# -- output files ------------------------------------------------------------------------------
def _same_file(a: str, b: str) -> bool:
    """Whether ``a`` and ``b`` name one file (links followed, hard links too)."""
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return os.path.realpath(a) == os.path.realpath(b)


def _special(path: str) -> bool:
    """An existing output that is not a regular file (/dev/stdout, a FIFO): written directly."""
    return os.path.exists(path) and not os.path.isfile(path) and not os.path.isdir(path)


def check_output_file(
    path: str,
    option: str,
    inputs: Iterable[Tuple[str, str]] = (),
    inside: Iterable[Tuple[str, str]] = (),
) -> None:
    """Raise SetupError (naming ``option`` and ``path``) unless ``path`` can take an output file:
    it is not a directory, its directory exists and can be written, it is not one of ``inputs``
    (``(what, path)`` pairs: the same file, also through a link) and does not lie in one of
    ``inside`` (``(what, directory)`` pairs: where the run writes otherwise). Nothing is
    written; call before any work."""
    p = os.fspath(path)
    if not p:
        raise SetupError(f"{option}: the path is empty")
    if os.path.isdir(p):
        raise SetupError(f"{option} {p}: is a directory; give a file name")
    for what, q in inputs:
        if q and _same_file(p, q):
            raise SetupError(
                f"{option} {p} is {what}, which would be overwritten; choose another file"
            )
    real = os.path.realpath(p)
    for what, d in inside:
        top = os.path.realpath(d)
        if real == top or real.startswith(top + os.sep):
            raise SetupError(f"{option} {p} lies in {what}; choose a file elsewhere")
    if _special(p):
        if not os.access(p, os.W_OK):
            raise SetupError(f"{option} {p}: cannot be written (permission denied)")
        return
    parent = os.path.dirname(real)
    if not os.path.isdir(parent):
        shown = os.path.dirname(p) or "."
        raise SetupError(f"{option} {p}: the directory {shown} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise SetupError(f"{option} {p}: cannot write to the directory {parent}")


def check_distinct_outputs(outputs: Iterable[Tuple[str, Optional[str]]]) -> None:
    """SetupError when two of ``outputs`` (``(option, path)``; None: not given) are one file."""
    given = [(o, p) for o, p in outputs if p]
    for i, (o1, p1) in enumerate(given):
        for o2, p2 in given[i + 1:]:
            if _same_file(p1, p2):
                raise SetupError(f"{o1} and {o2} are the same file ({p2}): give each its own")


class AtomicFile:
    """An output file that is replaced only when the run succeeded: the data goes to a
    temporary file beside ``path`` (``.NAME.XXXXXXXX.tmp``, same directory, same filesystem)
    and ``commit`` moves it over ``path`` (``os.replace``); ``discard`` (a failed or
    interrupted run) deletes it, leaving an earlier ``path`` as it was. ``path`` a link: its
    target is replaced. An existing ``path`` that is not a regular file (/dev/stdout, a FIFO)
    is written directly. ``file``: the open file (None with ``open_file=False``: ``temp`` is
    then the path to give a writer that takes a path, such as pycolmap's PLY export)."""

    def __init__(self, path: str, mode: str = "w", newline: Optional[str] = None,
                 open_file: bool = True):
        self.path = os.fspath(path)
        self.file = None
        self.temp: Optional[str] = None
        if _special(self.path):
            self.target = self.path
            self.temp = None
            if open_file:
                self.file = open(self.path, mode, newline=newline)
            return
        self.target = os.path.realpath(self.path)
        head, base = os.path.split(self.target)
        ext = os.path.splitext(base)[1]
        while True:
            temp = os.path.join(head, f".{base}.{secrets.token_hex(4)}.tmp{ext}")
            try:
                fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # umask applies
                break
            except FileExistsError:
                continue
        self.temp = temp
        try:
            try:
                os.chmod(temp, os.stat(self.target).st_mode & 0o7777)  # the earlier file's mode
            except FileNotFoundError:
                pass
            if open_file:
                self.file = os.fdopen(fd, mode, newline=newline)
                fd = -1
        except BaseException:
            self.discard()
            raise
        finally:
            if fd >= 0:
                os.close(fd)

    @property
    def writes_to(self) -> str:
        """Where the data goes until ``commit``: the temporary file, or ``path`` itself."""
        return self.temp or self.path

    def close(self) -> None:
        """Flush the data to disk and close the file (OSError when it cannot be written, e.g.
        ENOSPC); ``path`` is not replaced yet."""
        f, self.file = self.file, None
        if f is None:
            return
        try:
            f.flush()
            if self.temp is not None:
                os.fsync(f.fileno())
        finally:
            f.close()

    def commit(self) -> None:
        """``close``, then move the temporary file over ``path``. On OSError (the data could
        not be written) the temporary file is deleted and ``path`` left as it was."""
        try:
            self.close()
            if self.temp is not None:
                with interrupts_deferred():
                    os.replace(self.temp, self.target)
                    self.temp = None
        except BaseException:
            self.discard()
            raise

    def discard(self) -> None:
        """Drop what was written: ``path`` is left as it was (a special file keeps what reached
        it). Never raises."""
        f, self.file = self.file, None
        if f is not None:
            try:
                f.close()
            except OSError:
                pass
        if self.temp is not None:
            try:
                os.unlink(self.temp)
            except OSError:
                pass
            self.temp = None

    def __enter__(self) -> "AtomicFile":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()
