#!/usr/bin/env python3
"""Pick the default gate threshold so the model gate keeps as many frames as the oracle gate.

For each held-out validation sequence (gen_data.py's val seeds, never trained on): the oracle gate
(`leangate label --sequence S --threshold T`, the teacher-driven gate) gives the reference keep count;
the model gate is simulated exactly as the element runs it (first frame kept, each frame scored
against the last kept frame, keep when utility >= T) with the exported encoder + head in ONNX
Runtime, for T on a grid. By default the oracle runs at the same T as the model (`--tau-keep same`):
that is how `leangate eval` compares them (one threshold for every policy), so the chosen T is the one
where the student's gate and the ideal gate at that threshold keep the same number of frames.
`--tau-keep 0.5` instead matches the oracle at a fixed tau_keep (the paper's). The chosen T minimises
the summed |log(kept_model/kept_oracle)| (ties: closest to 0.5). It is written as leangate.threshold
into the three ONNX files.

Usage: python training/choose_threshold.py [--seqs '/work/train-data/seqs/val/seq_*'] [--models models]
"""
import argparse
import glob
import json
import os
import re
import subprocess
import sys

import numpy as np
import onnx
import onnxruntime as ort

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from gen_data import LEANGATE, load_resized, read_list  # noqa: E402
from model import IN_H, IN_W, MEAN, STD  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def oracle_kept(seq, tau_keep):
    r = subprocess.run([LEANGATE, "label", "--sequence", seq, "--threshold", str(tau_keep), "--out", os.devnull],
                       capture_output=True, text=True, check=True)
    m = re.search(r"kept (\d+) of (\d+)", r.stderr)
    return int(m.group(1)), int(m.group(2))


def model_gate_counts(enc, head, seq, thresholds):
    files = read_list(seq)
    x = np.stack([load_resized(os.path.join(seq, f), IN_W, IN_H) for f in files]).astype(np.float32) / 255.0
    x = ((x - np.array(MEAN, np.float32)) / np.array(STD, np.float32)).transpose(0, 3, 1, 2).copy()
    feats = np.concatenate([enc.run(["features"], {"image": x[k:k + 64]})[0] for k in range(0, len(x), 64)])
    counts = []
    for t in thresholds:
        ref, kept = 0, 1
        for i in range(1, len(feats)):
            u = head.run(["utility"], {"reference_features": feats[ref:ref + 1],
                                       "current_features": feats[i:i + 1]})[0][0]
            if u >= t:
                ref, kept = i, kept + 1
        counts.append(kept)
    return np.array(counts)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seqs", default="/work/train-data/seqs/val/seq_*")
    ap.add_argument("--models", default=os.path.join(REPO, "models"))
    ap.add_argument("--tau-keep", default="same",
                    help="the oracle's threshold: `same` (= the model's T, default) or a number (paper: 0.5)")
    ap.add_argument("--json", default="", help="write the sweep here")
    a = ap.parse_args()
    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    enc = ort.InferenceSession(os.path.join(a.models, "leangate-s-encoder.onnx"), so, providers=["CPUExecutionProvider"])
    head = ort.InferenceSession(os.path.join(a.models, "leangate-s-head.onnx"), so, providers=["CPUExecutionProvider"])
    thresholds = np.round(np.arange(0.20, 0.851, 0.01), 3)
    seqs = sorted(s for s in glob.glob(a.seqs) if os.path.isdir(s))
    oracle, model = [], []
    i5 = int(np.argmin(np.abs(thresholds - 0.5)))
    for s in seqs:
        if a.tau_keep == "same":
            ks = [oracle_kept(s, float(t)) for t in thresholds]
            k, n = np.array([x[0] for x in ks]), ks[0][1]
        else:
            k1, n = oracle_kept(s, float(a.tau_keep))
            k = np.full(len(thresholds), k1)
        c = model_gate_counts(enc, head, s, thresholds)
        oracle.append(k)
        model.append(c)
        print(f"{os.path.basename(s)}: {n} frames; at T=0.5 oracle kept {k[i5]}, model kept {c[i5]}", flush=True)
    oracle = np.array(oracle, np.float64)
    model = np.array(model, np.float64)
    cost = np.abs(np.log(model / oracle)).sum(0) + 1e-3 * np.abs(thresholds - 0.5)
    best = int(np.argmin(cost))
    T = float(thresholds[best])
    print(f"at the chosen T={T:.2f}: oracle total {int(oracle[:, best].sum())}, model total "
          f"{int(model[:, best].sum())} (per sequence {model[:, best].astype(int).tolist()} vs oracle "
          f"{oracle[:, best].astype(int).tolist()})")
    if a.json:
        json.dump({"thresholds": thresholds.tolist(), "oracle": oracle.tolist(), "model": model.tolist(),
                   "chosen": T, "sequences": seqs}, open(a.json, "w"), indent=1)
    for name in ("leangate-s.onnx", "leangate-s-encoder.onnx", "leangate-s-head.onnx"):
        p = os.path.join(a.models, name)
        m = onnx.load(p)
        for q in m.metadata_props:
            if q.key == "leangate.threshold":
                q.value = f"{T:.3f}"
        onnx.save(m, p)
    print(f"leangate.threshold = {T:.3f} written to {a.models}")


if __name__ == "__main__":
    main()
