"""Compare students on fixed real pairs, the same pairs for every model: utility RMSE, bias and
correlation against the exact teacher.

Pairs: every frame as the reference against each of its next `--max-gap` frames (default 24; the
oracle keeps every ~12-15 frames on tum_fr1_rpy), on
  * tum_fr1_rpy's test part (frames 575-717; labelled here for reporting only, never fitted on),
  * its cal part (the calibration's and model selection's pairs),
  * 7scenes_redkitchen_dev (never trained on).
Labels are written under <out>/labels (reused when present).

Usage: python -m training.compare --models DIR[,DIR...] [--names a,b] [--out $DATA_ROOT/evals/compare]
       (each DIR holds leangate-s-encoder.onnx and leangate-s-head.onnx, calibrated or not)
"""
import argparse
import json
import os

import numpy as np

from .calibrate import encode, score_pairs, sessions
from .config import DATA_ROOT, SHARED
from .preprocess import load_resized, read_list
from .tum import label_gate_pairs


def pair_set(out, name, seq, max_gap):
    lab = os.path.join(out, "labels")
    os.makedirs(lab, exist_ok=True)
    files = read_list(seq)
    npz = os.path.join(lab, f"{name}_{max_gap}.npz")
    if not os.path.exists(npz):
        P = label_gate_pairs(seq, len(files), max_gap, os.path.join(lab, f"{name}_{max_gap}"))
        P = P[np.isfinite(P[:, 2])]
        np.savez(npz, frames=np.stack([load_resized(f) for f in files]), pairs=P)
    d = np.load(npz)
    return d["frames"], d["pairs"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", required=True)
    ap.add_argument("--names", default="")
    ap.add_argument("--root", default=DATA_ROOT, help="where gen_data put tum/")
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "evals", "compare"))
    ap.add_argument("--max-gap", type=int, default=24)
    a = ap.parse_args()
    dirs = a.models.split(",")
    names = a.names.split(",") if a.names else [os.path.basename(os.path.normpath(d)) for d in dirs]
    sets = {
        "tum test": os.path.join(a.root, "tum", "test"),
        "tum cal": os.path.join(a.root, "tum", "cal"),
        "7scenes": os.path.join(SHARED, "7scenes_redkitchen_dev"),
    }
    data = {k: pair_set(a.out, k.replace(" ", "_"), s, a.max_gap) for k, s in sets.items() if os.path.exists(s)}
    res = {}
    for name, d in zip(names, dirs):
        enc, head, _ = sessions(d)
        for k, (frames, P) in data.items():
            F = encode(enc, frames)
            u = score_pairs(head, F, P[:, 0].astype(int), P[:, 1].astype(int))
            t = P[:, 2]
            res[(name, k)] = dict(pairs=len(t), rmse=float(np.sqrt(np.mean((u - t) ** 2))),
                                  bias=float(np.mean(u - t)), corr=float(np.corrcoef(u, t)[0, 1]))
    lines = ["| model | " + " | ".join(f"{k}: RMSE / bias / corr" for k in data) + " |",
             "|---|" + "---|" * len(data)]
    for name in names:
        lines.append(f"| {name} | " + " | ".join(
            f"{res[(name, k)]['rmse']:.3f} / {res[(name, k)]['bias']:+.3f} / {res[(name, k)]['corr']:.3f}"
            for k in data) + " |")
    table = "\n".join(lines)
    print(f"pairs up to {a.max_gap} frames apart: " + ", ".join(f"{k} {len(P)}" for k, (_, P) in data.items()))
    print(table)
    os.makedirs(a.out, exist_ok=True)
    with open(os.path.join(a.out, "compare.json"), "w") as f:
        json.dump({f"{n}|{k}": v for (n, k), v in res.items()}, f, indent=1)


if __name__ == "__main__":
    main()
