"""Writing a selection of a real TUM-layout sequence's frames as a sequence of its own (standard
library only): the lists keep the chosen rows and point at the original images by absolute path,
so nothing is copied; `intrinsics.txt` is copied. Used by `tum.make_part` (the documented split)
and `speedup` (every k-th frame). Also what the importers (`import_tum`, `import_7scenes`) share:
the checks of an `intrinsics.txt` and writing a sequence all or nothing (`staged`)."""
import contextlib
import math
import os
import shutil
import tempfile

LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt")


def rows(path):
    """(comment lines, data lines) of a TUM list, blank lines dropped."""
    head, body = [], []
    for line in open(path):
        s = line.strip()
        if s:
            (head if s.startswith("#") else body).append(s)
    return head, body


def write_lists(folder, lists):
    """Write each `name: lines` of `lists` into `folder` (one line each, newline-terminated): the
    TUM lists and `intrinsics.txt` of every sequence these tools write."""
    for name, lines in lists.items():
        with open(os.path.join(folder, name), "w") as f:
            f.write("\n".join(lines) + "\n")


def write_subset(src, out, pick, note):
    """Write `pick(rows, name)` of each of `src`'s three lists into `out` (a `# note` line after
    their comments; image paths made absolute), and copy the intrinsics. A missing list is an
    error naming it, before anything is written."""
    src = os.path.abspath(src)
    for name in LISTS + ("intrinsics.txt",):  # all checked before anything is written
        path = os.path.join(src, name)
        if not os.path.exists(path):
            raise SystemExit(f"{path} is missing: a sequence with depth, poses and intrinsics is needed")
    os.makedirs(out, exist_ok=True)
    lists = {}
    for name in LISTS:
        head, body = rows(os.path.join(src, name))
        sel = pick(body, name)
        if name != "groundtruth.txt":
            sel = [f"{r.split()[0]} {os.path.join(src, r.split()[1])}" for r in sel]
        lists[name] = head + [f"# {note}"] + sel
    write_lists(out, lists)
    with open(os.path.join(src, "intrinsics.txt")) as f, open(os.path.join(out, "intrinsics.txt"), "w") as g:
        g.write(f.read())


def check_intrinsics(path):
    """Exit with an error naming `path` unless its first non-comment line is `fx fy cx cy
    depth_scale`, five finite numbers with fx, fy and depth_scale positive (as `leangate` reads it)."""
    try:
        with open(path) as f:
            lines = [(n, s.strip()) for n, s in enumerate(f, 1) if s.strip() and not s.strip().startswith("#")]
    except (OSError, UnicodeDecodeError) as e:
        raise SystemExit(f"{path}: cannot read it: {getattr(e, 'strerror', None) or e}")
    if not lines:
        raise SystemExit(f"{path}: no `fx fy cx cy depth_scale` line")
    n, line = lines[0]
    try:
        v = [float(t) for t in line.split()]
    except ValueError:
        v = []
    if len(v) != 5 or not all(map(math.isfinite, v)) or min(v[0], v[1], v[4]) <= 0:
        raise SystemExit(f"{path}:{n}: `{line}` is not `fx fy cx cy depth_scale` (five finite numbers, "
                         "fx, fy and depth_scale positive)")


@contextlib.contextmanager
def staged(out):
    """Write a sequence into `out` all or nothing: yields an empty staging folder beside `out`
    whose files move into `out` (created if needed; files of the same name replaced) only when the
    block finishes. An error in the block (a file that cannot be read, decoded or written) removes
    the staging folder and exits with one line naming `out` and the cause; `out` is untouched."""
    dest = os.path.abspath(out)
    if os.path.exists(dest) and not os.path.isdir(dest):
        raise SystemExit(f"{out}: exists and is not a folder")
    try:
        os.makedirs(os.path.dirname(dest), exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=f".{os.path.basename(dest)}.partial-", dir=os.path.dirname(dest))
    except OSError as e:
        raise SystemExit(f"{out}: cannot write there: {e.strerror or e}")
    try:
        try:
            yield tmp
        except SystemExit:
            raise
        except Exception as e:  # noqa: BLE001 - any failure (OSError, an undecodable image) is the user's input
            raise SystemExit(f"{out}: nothing written: {e}")
        try:
            for root, _, files in os.walk(tmp):
                rel = os.path.relpath(root, tmp)
                os.makedirs(os.path.normpath(os.path.join(dest, rel)), exist_ok=True)
                for name in sorted(files):
                    os.replace(os.path.join(root, name), os.path.normpath(os.path.join(dest, rel, name)))
        except OSError as e:
            raise SystemExit(f"{out}: cannot write there: {e}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
