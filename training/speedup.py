"""A real sequence played 2x or 3x faster: every k-th frame of a TUM-layout sequence, written as a
TUM directory whose lists point at the original images by absolute path (nothing is copied), so that
`leangate eval` judges a gate on faster camera motion with the same teacher.

Usage: python -m training.speedup [--every 2,3] [--out out/train-data/speed] SEQ [SEQ ...]
e.g. python -m training.speedup ../shared/data/tum_fr1_rpy ../shared/data/tum_fr1_desk \
         ../shared/data/7scenes_redkitchen_long
then leangate eval --sequence out/train-data/speed/tum_fr1_rpy_x2 --sequence ...
"""
import argparse
import os

from .config import DATA_ROOT

LISTS = ("rgb.txt", "depth.txt", "groundtruth.txt")


def subsample(src, k, dst):
    """Write every `k`-th row of `src`'s lists (and its intrinsics) into `dst`. The rows of
    rgb.txt, depth.txt and groundtruth.txt must be associated one to one, as in ../shared/data."""
    src = os.path.abspath(src)
    rows = {}
    for name in LISTS:
        path = os.path.join(src, name)
        if not os.path.exists(path):
            raise SystemExit(f"{path} is missing: a sequence with depth and poses is needed")
        lines = open(path).read().splitlines()
        rows[name] = ([l for l in lines if l.startswith("#")],
                      [l for l in lines if l.strip() and not l.startswith("#")])
    counts = {len(r) for _, r in rows.values()}
    if len(counts) != 1:
        raise SystemExit(f"{src}: rgb.txt, depth.txt and groundtruth.txt have {sorted(counts)} rows; "
                         "they must be associated one row per frame")
    os.makedirs(dst, exist_ok=True)
    for name, (head, body) in rows.items():
        body = body[::k]
        if name != "groundtruth.txt":
            body = [f"{r.split()[0]} {os.path.join(src, r.split()[1])}" for r in body]
        with open(os.path.join(dst, name), "w") as f:
            f.write("\n".join(head + [f"# every frame k = 0, {k}, {2 * k}, ... of {src}"] + body) + "\n")
    with open(os.path.join(src, "intrinsics.txt")) as f, open(os.path.join(dst, "intrinsics.txt"), "w") as g:
        g.write(f.read())


def speedups(text):
    """argparse type of --every: comma-separated integers of at least 1."""
    try:
        ks = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated whole numbers, got {text!r}")
    if not ks or any(k < 1 for k in ks):
        raise argparse.ArgumentTypeError(f"every speed-up must be at least 1, got {text!r}")
    return ks


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--every", type=speedups, default=[2, 3], help="comma-separated speed-ups (keep every k-th frame)")
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "speed"))
    a = ap.parse_args()
    for seq in a.sequences:
        for k in a.every:
            dst = os.path.join(a.out, f"{os.path.basename(os.path.normpath(seq))}_x{k}")
            subsample(seq, k, dst)
            print(dst)


if __name__ == "__main__":
    main()
