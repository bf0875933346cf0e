"""How far could a better student move the default gate? The shipped fusion replayed with the
student's score `s` replaced by the exact teacher's tau (a perfect student), beside the fusion as
shipped, the student alone and the oracle.

The default's utility is `clip(w0 + w1 tau_geo + w2 tau_geo^2 + w3 s)` (`leangate.geometry`,
`w3` = 0.25): the prior carries it, so retraining the student (on near objects, say) can move the
gate only as far as a perfect `s` would. `fuse.sequence_data`'s cached tables (every frame against
its next 120 frames) are replayed from `--phases` start frames with `fuse.replay`, as
`training.experiments.feedback` does.

Prints per sequence: the oracle's keep count, then kept and late keeps of the fusion as shipped,
of the fusion with a perfect student, and of the student alone.

Usage: python -m training.experiments.student_bound SEQ [SEQ ...] [--phases 3]
"""
import argparse
import os

import numpy as np

from ..config import DATA_ROOT, MODELS_DIR
from ..fuse import replay
from .feedback import fused, fusion_weights, sequence_table


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", nargs="+", help="sequence directories (TUM layout with depth and poses)")
    ap.add_argument("--phases", type=int, default=3, help="start frames per sequence")
    ap.add_argument("--models", default=MODELS_DIR)
    ap.add_argument("--tables", default=os.path.join(DATA_ROOT, "evals", "feedback"))
    a = ap.parse_args()
    if a.phases < 1:
        raise SystemExit("--phases must be at least 1")
    w = fusion_weights(a.models)
    print(f"{'sequence':<36} oracle | shipped fusion kept/late | perfect student in it | student alone")
    for seq in a.sequences:
        label, tab = sequence_table(seq, a.tables, a.models)
        tau = tab["tau"]
        perfect = {**tab, "s": np.where(np.isfinite(tau), tau, tab["s"])}
        n = tau.shape[0]
        rows = np.zeros((4, 2), int)
        for p in range(a.phases):
            for r, u in enumerate((tau, fused(tab, w), fused(perfect, w), tab["s"])):
                rows[r] += replay(u, tau, 0.5, p, n - 1)[:2]
        print(f"{label:<36} {rows[0, 0]:6d} | " + " | ".join(f"{k:4d} / {l:3d}" for k, l in rows[1:]))


if __name__ == "__main__":
    main()
