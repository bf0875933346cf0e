"""Which constant added to the default's utility puts each real sequence's keep count within
+-15 % of the oracle's (issue 21's band), replayed: whether one intercept could serve them all.

For each sequence directory (e.g. the documented parts written by `python -m training.tum`), the
teacher's tau, the student's INT8 score and the prior's tau_geo of every frame against each of
its next 120 frames (`fuse.sequence_data`'s cached tables, the same as `training.experiments.feedback`'s)
give the default's fused utility (`feedback.fused`). The gate is replayed from `--phases` start
frames (`fuse.replay`, as `leangate eval --phases` runs it) with a constant `offset` added to the
utility wherever the prior's chain holds (where it is lost the element uses the student alone,
which an intercept of the fusion does not move), for every offset of `--offsets`.

Prints each sequence's kept / oracle at every offset and the interval of offsets that puts it in
the band, then the offsets inside every sequence's interval (none: no intercept serves them all,
so what separates the sequences has to be seen per stream). With `--depth`, also each
sequence's median sensor depth, its share of depth readings beyond 3.5 m and of pixels without
depth (every 6th frame), the scene property the teacher's 0.1 m check is most sensitive to.

Usage: python -m training.experiments.band SEQ [SEQ ...] [--offsets=-0.06:0.08:0.005] [--phases 10]
       [--threshold 0.5] [--depth]
"""
import argparse
import os

import numpy as np

from ..config import DATA_ROOT, MODELS_DIR
from .feedback import fused, fusion_weights, sequence_table
from ..fuse import replay
from ..seqio import rows

BAND = 0.15


def offsets_arg(text):
    """`lo:hi:step` (inclusive) or a comma-separated list."""
    try:
        if ":" in text:
            lo, hi, step = (float(v) for v in text.split(":"))
            if step <= 0 or hi < lo:
                raise ValueError("need lo <= hi and step > 0")
            return np.round(np.arange(lo, hi + step / 2, step), 6)
        return np.array([float(v) for v in text.split(",")])
    except ValueError as e:
        raise argparse.ArgumentTypeError(f"{text!r}: {e}") from None


def kept_ratios(u, tab, offsets, threshold, phases):
    """kept / oracle summed over `phases` start frames, at each offset."""
    tau, geo = tab["tau"], tab["geo"]
    n = tau.shape[0]
    oracle = sum(replay(tau, tau, threshold, p, n - 1)[0] for p in range(phases))
    out = []
    for o in offsets:
        v = np.where(np.isfinite(geo), np.clip(u + o, 0.0, 1.0), u)
        out.append(sum(replay(v, tau, threshold, p, n - 1)[0] for p in range(phases)) / oracle)
    return np.array(out)


def depth_stats(seq, every=6, far=3.5):
    """(median depth m, share of readings beyond `far` m, share of pixels without depth) over
    every `every`-th depth image of a TUM-layout sequence."""
    from PIL import Image

    scale = float(rows(os.path.join(seq, "intrinsics.txt"))[1][0].split()[4])
    files = [os.path.join(seq, r.split()[1]) for r in rows(os.path.join(seq, "depth.txt"))[1]]
    med, beyond, holes = [], [], []
    for f in files[::every]:
        d = np.asarray(Image.open(f), dtype=np.float64) / scale
        v = d[d > 0]
        holes.append(1.0 - v.size / d.size)
        if v.size:
            med.append(np.median(v))
            beyond.append(np.mean(v > far))
    return float(np.mean(med)), float(np.mean(beyond)), float(np.mean(holes))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", nargs="+", help="sequence directories (TUM layout with depth and poses)")
    ap.add_argument("--offsets", type=offsets_arg, default=offsets_arg("-0.06:0.08:0.005"),
                    help="lo:hi:step or a list (default -0.06:0.08:0.005)")
    ap.add_argument("--phases", type=int, default=10, help="start frames per sequence")
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--depth", action="store_true", help="also the sequences' sensor depth statistics")
    ap.add_argument("--models", default=MODELS_DIR)
    ap.add_argument("--tables", default=os.path.join(DATA_ROOT, "evals", "feedback"))
    a = ap.parse_args()
    if a.phases < 1:
        raise SystemExit("--phases must be at least 1")
    if not 0.0 < a.threshold < 1.0:
        raise SystemExit("--threshold must be inside (0, 1)")
    w = fusion_weights(a.models)
    offs = a.offsets
    print(f"{'offset':<36}" + "".join(f"{o:+7.3f}" for o in offs))
    common = np.ones(len(offs), bool)
    for seq in a.sequences:
        label, tab = sequence_table(seq, a.tables, a.models)
        r = kept_ratios(fused(tab, w), tab, offs, a.threshold, a.phases)
        inside = np.abs(r - 1.0) <= BAND + 1e-9
        common &= inside
        band = f"{offs[inside].min():+.3f} .. {offs[inside].max():+.3f}" if inside.any() else "none"
        extra = ""
        if a.depth:
            med, beyond, holes = depth_stats(seq)
            extra = f" | depth median {med:.2f} m, beyond 3.5 m {beyond:.3f}, no depth {holes:.3f}"
        print(f"{label:<36}" + "".join(f"{x:7.2f}" for x in r) + f" | in band: {band}{extra}")
    print("offsets in every sequence's band: "
          + (", ".join(f"{o:+.3f}" for o in offs[common]) if common.any() else "none"))


if __name__ == "__main__":
    main()
