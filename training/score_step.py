"""Measure `leangate.score_step`: how much the student's score rises from one frame to the next
against the same reference, and (with --write) put it into the shipped models.

The element's screening (src/utility.rs, `Utility::screen`) skips the student on a frame when no
score it could give would lift the fused utility to the threshold. Without this key it assumes
any score up to `leangate.score_max`. With it, k frames after one the student scored against
the same reference, it assumes a score up to that score plus k times `leangate.score_step`, so
the prior alone decides more frames, each frame with one step more until the student runs again
(the step is measured from one frame to the next, and k steps cover any rise over k frames
that stays within a step per frame). A rise larger than the
step on a frame whose utility reaches the threshold drops that frame, and the keep goes to the next
frame that reaches it (the next one while the utility keeps rising; later after a short peak).

The step is measured on the parts the fusion was fitted on (`config.FUSION_FIT_PARTS`:
tum_fr1_rpy's cal part, tum_fr1_desk's fit part): every frame of a part as the reference against
each of its next `--horizon` frames (inside the part), the INT8 build the element runs on the CPU,
and the `--percentile` of the rises of the score between consecutive current frames, rounded up to
two decimals. It is a percentile, not a bound: the largest rises (0.29-0.34 there) come from a few
references far from any keep, and a step that large would leave little to screen. A rise above the
step matters only where the fused utility is about to cross the threshold, and then costs one
frame. Every other sequence is reported only: `leangate eval --set screen=...` on each real
sequence, kept frames and late keeps against the exact screening (models/README.md).

Usage: python -m training.score_step [--models models] [--horizon 30] [--percentile 99] [--write]
"""
import argparse
import os

import numpy as np

from .calibrate import encode, score_pairs
from .config import FUSION_FIT_PARTS, MODELS_DIR, REAL_SPLITS, SHARED
from .fuse import int8_sessions, write_metadata
from .preprocess import load_resized, read_list
from .tum import gate_pairs

KEY = "leangate.score_step"


def rises(enc, head, files, horizon):
    """Every rise s(ref, cur + 1) - s(ref, cur), each frame of `files` as the reference against
    its next `horizon` frames."""
    F = encode(enc, np.stack([load_resized(f) for f in files]))
    pairs = np.array(gate_pairs(len(files), horizon))
    cur, ref = pairs[:, 0], pairs[:, 1]
    s = score_pairs(head, F, cur, ref)
    same = (ref[1:] == ref[:-1]) & (cur[1:] == cur[:-1] + 1)
    return (s[1:] - s[:-1])[same]


def step_value(r, percentile):
    """The `percentile` of the rises, rounded up to two decimals (at least 0.01, at most 1)."""
    v = float(np.percentile(r, percentile))
    return f"{min(max(np.ceil(v * 100 - 1e-9) / 100, 0.01), 1.0):.2f}"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=MODELS_DIR)
    ap.add_argument("--horizon", type=int, default=30, help="each reference against its next H frames")
    ap.add_argument("--percentile", type=float, default=99.0, help="which percentile of the rises is the step")
    ap.add_argument("--write", action="store_true", help=f"write {KEY} into the models' metadata")
    a = ap.parse_args()
    enc, head = int8_sessions(a.models)
    fit = []
    for name, parts in FUSION_FIT_PARTS.items():
        seq = os.path.join(SHARED, name)
        if not os.path.isdir(seq):
            raise SystemExit(f"{seq} is missing: the real sequences live in ../shared/data")
        files = read_list(seq)
        for part in parts:
            lo, hi = REAL_SPLITS[name][part]
            r = rises(enc, head, files[lo:hi + 1], a.horizon)
            fit.append(r)
            print(f"{name} {part} ({lo}-{hi}): {len(r)} rises, largest {r.max():.3f}, "
                  f"99th percentile {np.percentile(r, 99):.3f}, 99.9th {np.percentile(r, 99.9):.3f}")
    value = step_value(np.concatenate(fit), a.percentile)
    if a.write:
        write_metadata(a.models, value, KEY)  # the files that carry leangate.geometry
    else:
        print(f"not written (--write): {KEY} = {value}")


if __name__ == "__main__":
    main()
