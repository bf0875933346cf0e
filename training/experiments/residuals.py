"""Where a student's utility errs on the real parts: its residual (utility - teacher tau) on the
fixed pairs of `training.compare` near the decision (tau in [0.35, 0.65)), against the ground-truth
relative pose and the depth holes.

For each pair (current i, reference j) of tum_fr1_rpy's cal and test parts: the relative rotation's
axis-angle in the reference camera's frame, split into roll (about the optical axis, z) and pitch/yaw
(x, y); the translation; the larger fraction of invalid-depth pixels of the two frames (the teacher
counts only valid-depth pixels). Printed per model: the mean residual, on roll-dominated pairs and on
the others, and a least-squares fit of the residual on the four quantities.

Usage: python -m training.experiments.residuals --models DIR[,DIR...] [--names a,b]
       (each DIR holds leangate-s-encoder.onnx and leangate-s-head.onnx, calibrated or not)
"""
import argparse
import os

import numpy as np
from PIL import Image

from ..calibrate import encode, score_pairs, sessions
from ..compare import pair_set
from ..config import DATA_ROOT
from ..seqio import rows as _rows
from ..tum import quat_to_rot


def nearest(stamps, ts):
    return np.abs(stamps[None] - ts[:, None]).argmin(1)


def pose_features(part_dir, P):
    """Per pair: |roll| and |pitch/yaw| in degrees, translation in cm, max hole fraction."""
    rgb = [r.split() for r in _rows(os.path.join(part_dir, "rgb.txt"))[1]]
    dep = [r.split() for r in _rows(os.path.join(part_dir, "depth.txt"))[1]]
    gt = np.array([[float(x) for x in r.split()] for r in _rows(os.path.join(part_dir, "groundtruth.txt"))[1]])
    ts = np.array([float(r[0]) for r in rgb])
    g = nearest(gt[:, 0], ts)
    R = [quat_to_rot(gt[k, 4:8]) for k in g]
    T = [gt[k, 1:4] for k in g]
    d = nearest(np.array([float(r[0]) for r in dep]), ts)
    hole = np.array([np.mean(np.asarray(Image.open(os.path.join(part_dir, dep[k][1]))) == 0) for k in d])
    out = []
    for i, j in P[:, :2].astype(int):
        rel = R[j].T @ R[i]
        ang = np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))
        v = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
        v = v / (np.linalg.norm(v) + 1e-12) * np.degrees(ang)
        out.append([abs(v[2]), np.hypot(v[0], v[1]), 100 * np.linalg.norm(R[j].T @ (T[i] - T[j])),
                    max(hole[i], hole[j])])
    return np.array(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", required=True)
    ap.add_argument("--names", default="")
    ap.add_argument("--root", default=DATA_ROOT, help="where gen_data put tum/")
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "evals", "compare"), help="compare's labels")
    a = ap.parse_args()
    dirs = a.models.split(",")
    names = a.names.split(",") if a.names else [os.path.basename(os.path.normpath(d)) for d in dirs]
    models = [(n, sessions(d)) for n, d in zip(names, dirs)]
    for part in ("cal", "test"):
        part_dir = os.path.join(a.root, "tum", part)
        frames, P = pair_set(a.out, f"tum_{part}", part_dir, 24)
        X = pose_features(part_dir, P)
        t = P[:, 2]
        sel = (t >= 0.35) & (t < 0.65)
        roll = sel & (X[:, 0] > X[:, 1])
        print(f"tum {part}: {len(t)} pairs, {sel.sum()} with tau in [0.35, 0.65), {roll.sum()} of them "
              f"roll-dominated; depth holes {X[:, 3].mean():.3f} of the pixels (max of the pair)")
        A = np.column_stack([X[sel], np.ones(sel.sum())])
        for name, (enc, head, _) in models:
            u = score_pairs(head, encode(enc, frames), P[:, 0].astype(int), P[:, 1].astype(int))
            r = u - t
            c, *_ = np.linalg.lstsq(A, r[sel], rcond=None)
            print(f"  {name:14s} mean residual {r[sel].mean():+.3f}: roll-dominated {r[roll].mean():+.3f}, "
                  f"other {r[sel & ~roll].mean():+.3f} | per 10 deg roll {10 * c[0]:+.3f}, per 10 deg "
                  f"pitch/yaw {10 * c[1]:+.3f}, per 10 cm {10 * c[2]:+.3f}, per 10 % holes {0.1 * c[3]:+.3f}")


if __name__ == "__main__":
    main()
