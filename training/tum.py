"""Real training / calibration data from tum_fr1_rpy, labelled by the exact teacher.

The sequence is cut into the parts of `config.TUM_SPLIT`; each part becomes its own TUM-layout
directory <root>/tum/<part>/ whose rgb.txt / depth.txt / groundtruth.txt keep only that part's rows
and point at the original images by absolute path (nothing is copied), so `leangate label` and
`leangate eval` see only that part and pair indices are local to it.

  train  `leangate label --within 30` (every frame against its 30 predecessors) +
         `--random 3000 --max-gap 399` (far pairs, complete view changes included)
         -> cache/tum_train.npz (frames [F,H,W,3] uint8, pairs [P,5] i,j,tau,f_m,f_u)
  cal    pairs as the gate sees them: every frame as the reference against each of its next 45
         frames (beyond the oracle's next keyframe: median keyframe interval ~12)
         -> cache/tum_cal.npz (same layout), for calibration and model selection
  test   the directory only (for `leangate eval`); never labelled for fitting
"""
import os
import subprocess

import numpy as np

from .config import ALL_SPLITS, LEANGATE, SHARED, TUM_SEQ, TUM_SPLIT
from .preprocess import load_resized, read_list
from .seqio import write_subset


def quat_to_rot(q):
    """The rotation matrix of a TUM quaternion `qx qy qz qw` (unit length)."""
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def make_part(root, part, src=None, seq=TUM_SEQ):
    """Write one part of a real sequence's documented split (`config.ALL_SPLITS`) as a TUM-layout
    directory: <root>/tum/<part>/ for tum_fr1_rpy (the training pipeline's layout), else
    <root>/<seq>/<part>/; returns its path."""
    src = src or os.path.join(SHARED, seq)
    a, b = ALL_SPLITS[seq][part]
    out = os.path.join(root, "tum" if seq == TUM_SEQ else seq, part)

    def pick(rows, name):
        if len(rows) <= b:
            raise SystemExit(f"{src}/{name}: {len(rows)} rows, the split needs {b + 1}")
        return rows[a:b + 1]

    write_subset(src, out, pick, f"{seq} frames {a}-{b} ({part} part of the LeanGate split)")
    return out


def _label(seq, args, out):
    r = subprocess.run([LEANGATE, "label", "--sequence", seq, *args, "--out", out], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"leangate label {' '.join(args)} failed:\n{r.stderr}")
    d = np.genfromtxt(out, delimiter=",", names=True)
    return np.stack([d["i"], d["j"], d["tau"], d["f_m"], d["f_u"]], 1).astype(np.float32)


def gate_pairs(n, horizon):
    """(current, reference) pairs: every frame as reference against each of its next `horizon` frames."""
    return [(j + k, j) for j in range(n) for k in range(1, horizon + 1) if j + k < n]


def label_gate_pairs(seq, n, horizon, stem):
    """Teacher labels of `gate_pairs(n, horizon)` on `seq` (pair list `<stem>_pairs.csv`, labels
    `<stem>.csv`): [P,5] i,j,tau,f_m,f_u."""
    pcsv = f"{stem}_pairs.csv"
    with open(pcsv, "w") as f:
        f.write("i,j\n" + "".join(f"{i},{j}\n" for i, j in gate_pairs(n, horizon)))
    return _label(seq, ["--pairs", pcsv], f"{stem}.csv")


def build(root, horizon=45):
    cache = os.path.join(root, "cache")
    os.makedirs(cache, exist_ok=True)
    for part in TUM_SPLIT:
        seq = make_part(root, part)
        if part == "test":
            continue
        out = os.path.join(cache, f"tum_{part}.npz")
        if os.path.exists(out):
            continue
        files = read_list(seq)
        if part == "train":
            p1 = _label(seq, ["--within", "30"], os.path.join(root, "tum", "train_within.csv"))
            p2 = _label(seq, ["--random", "3000", "--max-gap", str(len(files) - 1), "--seed", "7"],
                        os.path.join(root, "tum", "train_random.csv"))
            pairs = np.concatenate([p1, p2])
        else:
            pairs = label_gate_pairs(seq, len(files), horizon, os.path.join(root, "tum", f"{part}_gate"))
        pairs = pairs[np.isfinite(pairs[:, 2])]
        frames = np.stack([load_resized(f) for f in files])
        np.savez(out, frames=frames, pairs=pairs)
        h, _ = np.histogram(pairs[:, 2], bins=10, range=(0, 1))
        print(f"tum {part}: {len(files)} frames, {len(pairs)} labelled pairs, tau histogram {h.tolist()}", flush=True)


def main():
    import argparse

    from .config import DATA_ROOT

    ap = argparse.ArgumentParser(description="Write parts of the documented splits (config.ALL_SPLITS) as TUM-layout "
                                             "folders <root>/<sequence>/<part>/ (tum_fr1_rpy: <root>/tum/<part>/) for "
                                             "`leangate eval`; nothing is copied but the intrinsics.")
    ap.add_argument("--part", action="append", required=True, metavar="SEQUENCE:PART",
                    help="e.g. tum_fr1_xyz:test (repeat); " + "; ".join(f"{s}: {', '.join(p)}" for s, p in ALL_SPLITS.items()))
    ap.add_argument("--root", default=DATA_ROOT)
    a = ap.parse_args()
    todo = []
    for spec in a.part:
        seq, _, part = spec.partition(":")
        if seq not in ALL_SPLITS or part not in ALL_SPLITS[seq]:
            raise SystemExit(f"--part {spec}: not a documented part (one of "
                             + ", ".join(f"{s}:{p}" for s, ps in ALL_SPLITS.items() for p in ps) + ")")
        src = os.path.join(SHARED, seq)
        if not os.path.isdir(src):
            raise SystemExit(f"--part {spec}: {src} is missing (training/README.md says how to build it)")
        todo.append((seq, part))
    for seq, part in todo:
        print(make_part(a.root, part, seq=seq))


if __name__ == "__main__":
    main()
