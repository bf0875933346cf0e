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
from .seqio import LISTS, rows, write_subset


def subsample(src, k, dst):
    """Write every `k`-th row of `src`'s lists (and its intrinsics) into `dst`. The rows of
    rgb.txt, depth.txt and groundtruth.txt must be associated one to one, as in ../shared/data."""
    src = os.path.abspath(src)
    counts = {len(rows(os.path.join(src, n))[1]) for n in LISTS if os.path.exists(os.path.join(src, n))}
    if len(counts) > 1:
        raise SystemExit(f"{src}: rgb.txt, depth.txt and groundtruth.txt have {sorted(counts)} rows; "
                         "they must be associated one row per frame")
    write_subset(src, dst, lambda body, _: body[::k], f"every frame k = 0, {k}, {2 * k}, ... of {src}")


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
