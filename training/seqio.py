"""Writing a selection of a real TUM-layout sequence's frames as a sequence of its own (standard
library only): the lists keep the chosen rows and point at the original images by absolute path,
so nothing is copied; `intrinsics.txt` is copied. Used by `tum.make_part` (the documented split)
and `speedup` (every k-th frame)."""
import os

LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt")


def rows(path):
    """(comment lines, data lines) of a TUM list, blank lines dropped."""
    head, body = [], []
    for line in open(path):
        s = line.strip()
        if s:
            (head if s.startswith("#") else body).append(s)
    return head, body


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
    for name in LISTS:
        head, body = rows(os.path.join(src, name))
        sel = pick(body, name)
        if name != "groundtruth.txt":
            sel = [f"{r.split()[0]} {os.path.join(src, r.split()[1])}" for r in sel]
        with open(os.path.join(out, name), "w") as f:
            f.write("\n".join(head + [f"# {note}"] + sel) + "\n")
    with open(os.path.join(src, "intrinsics.txt")) as f, open(os.path.join(out, "intrinsics.txt"), "w") as g:
        g.write(f.read())
