"""Leave one real sequence out: does fine-tuning the student's head on the other real sequences
(`training.experiments.finetune`'s procedure) help the gate on the one left out?

For each real sequence given (`--sequence`, at least two), with the whole of the others as the
training set:

  1. the shipped head is fine-tuned on the others' teacher-labelled pairs exactly as
     `training.experiments.finetune` does (the calibration a fixed last layer, the encoder frozen);
  2. the shipped head and the fine-tuned one each score every pair (FP32, the same features), and
     the fusion of the shipped form (`w0 + w1 tau_geo + 0.25 s`) is fitted on the training
     sequences and replayed on the one left out (`fuse.replay`, horizon 120), as is the student
     alone;
  3. one table: kept / oracle, late keeps and utility RMSE on each sequence left out, shipped head
     against fine-tuned head.

The teacher's tau and the prior's tau_geo come from `fuse.sequence_data` (cached under `--tables`).
Needs torch. Usage:

  python -m training.experiments.head_loso --sequence ../shared/data/tum_fr1_rpy --sequence ... [--steps 1500]
"""
import argparse
import json
import os

import numpy as np

from ..config import DATA_ROOT, MODELS_DIR
from .finetune import HORIZON, Shipped, check_sequence, features, finetune_head, load_tables, need_torch
from ..fuse import STUDENT_WEIGHT, Fusion, cell, evaluate, fit


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequence", action="append", required=True, help="a real sequence with depth and poses (repeat)")
    ap.add_argument("--models", default=MODELS_DIR)
    ap.add_argument("--tables", default=os.path.join(DATA_ROOT, "evals", "fuse120"))
    ap.add_argument("--steps", type=int, default=1500, help="fine-tuning steps of 64 pairs")
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--fit-horizon", type=int, default=60)
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if len(a.sequence) < 2:
        raise SystemExit("--sequence: give at least two (one is left out at a time)")
    seqs = {}
    for s in a.sequence:
        check_sequence(s)
        seqs[os.path.basename(os.path.normpath(s))] = s
    if len(seqs) != len(a.sequence):
        raise SystemExit("--sequence: two sequences share a folder name (their tables would collide)")
    torch = need_torch()
    torch.set_num_threads(2)
    shipped = Shipped(a.models)
    tabs = load_tables(seqs, a.models, a.tables)
    feats = features(a.models, seqs)

    @torch.no_grad()
    def score(head, name, horizon):
        F = feats[name]
        n = F.shape[0]
        out = np.full((n, HORIZON), np.nan)
        j, g = (x.ravel() for x in np.meshgrid(np.arange(n), np.arange(horizon), indexing="ij"))
        ok = j + g + 1 < n
        j, g = j[ok], g[ok]
        for k in range(0, len(j), 1024):
            jj, gg = j[k:k + 1024], g[k:k + 1024]
            out[jj, gg] = shipped.calib(head(F[jj], F[jj + gg + 1])).numpy()
        return out

    one = lambda d: np.ones_like(d["s"])
    results = {}
    for held in seqs:
        train = {n: (0, len(tabs[n]["tau"]) - 1) for n in seqs if n != held}
        row = {}
        heads = (("shipped head", shipped.model().head),
                 ("fine-tuned head", finetune_head(shipped, feats, tabs, train, a.steps, a.lr, a.seed, a.fit_horizon,
                                                   log=lambda m: print(m, flush=True)).head))
        for tag, head in heads:
            data = {n: {**tabs[n], "s": score(head, n, HORIZON if n == held else a.fit_horizon)} for n in seqs}
            alone = Fusion("s", lambda d: [d["s"]], geometric=False, fixed=[1.0]).fit([])
            form = fit(Fusion("s+geo", lambda d: [one(d), d["geo"], d["s"]], s_weight=STUDENT_WEIGHT),
                       data, {n: [span] for n, span in train.items()}, a.threshold, a.fit_horizon)
            row[tag] = {k: cell(evaluate(f, {held: data[held]}, a.threshold)[(held, "all")])
                        for k, f in (("student alone", alone), ("default form", form))}
            print(held, tag, json.dumps(row[tag]), flush=True)
        results[held] = row
    print(f"\nLeave one sequence out: kept / oracle at {a.threshold}, late keeps, utility RMSE (replay, horizon {HORIZON})\n")
    print("| left out | student alone: shipped head | fine-tuned head | w0 + w1 tau_geo + 0.25 s: shipped head | fine-tuned head |")
    print("|---|---|---|---|---|")
    for held, row in results.items():
        sh, ft = row["shipped head"], row["fine-tuned head"]
        print(f"| {held} | {sh['student alone']} | {ft['student alone']} | {sh['default form']} | {ft['default form']} |")
    os.makedirs(a.tables, exist_ok=True)
    with open(os.path.join(a.tables, "head_loso.json"), "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
