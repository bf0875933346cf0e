"""A reference-gap head on the student's features: measured, not shipped (training/experiments/NOTEBOOK.md).

On real video the teacher's tau exceeds the geometric prior's tau_geo by a gap that is a property of
the reference frame (Kinect depth noise, holes and edges fail the teacher's 0.1 m check): 0.12 on
average on tum_fr1_rpy and tum_fr1_desk, about 0 on synthetic video with exact depth. The shipped
fusion adds it as a constant (its intercept). This asks whether the student's encoder can predict
it per reference instead: a ridge regression from the reference's features (per-channel mean and
standard deviation over the 8x10 grid, 192 numbers; the INT8 encoder the element runs) to that
reference's gap (the mean of tau - tau_geo over its pairs with tau in 0.35-0.65), then the fusion
`w0 + w1 tau_geo + w2 gap(ref) [+ w3 s]` fitted like `training.fuse`'s candidates and the gate
replayed on every part.

It reports: leave one sequence out (ridge and fusion fitted on one whole real sequence, reported on
the other), the documented split (ridge on tum_fr1_rpy 0-559 and tum_fr1_desk 0-285, the fusion
on the fusion's fit parts; reported on the test parts, the whole sequences and the synthetic
held-out sequences), and the gap it predicts on sequences it never saw against the teacher's where
there is one (7scenes_redkitchen_dev and _long, the two synthetic fusion-fit sequences).

Usage (after `python -m training.fuse`, whose cached tables it reads):
    python -m training.experiments.gap_head [--lam 300,1000,3000]
"""
import argparse
import os

import numpy as np

from ..calibrate import encode
from ..config import DATA_ROOT, FUSION_FIT_PARTS, MODELS_DIR, REAL_SPLITS, SHARED
from ..fuse import STUDENT_WEIGHT, Fusion, cell, evaluate, fit, int8_sessions, sequence_data
from ..preprocess import load_resized, read_list

HORIZON = 60
NEAR = (0.35, 0.65)


def pooled(models, seq):
    enc, _ = int8_sessions(models)
    F = encode(enc, np.stack([load_resized(f) for f in read_list(seq)]))
    return np.concatenate([F.mean((2, 3)), F.std((2, 3))], 1)


def reference_gap(tab, last=None):
    """Per reference: mean of tau - tau_geo over its pairs near the decision (NaN with fewer than 3,
    or when its pairs reach beyond frame `last`)."""
    t, g = tab["tau"], tab["geo"]
    near = (t > NEAR[0]) & (t < NEAR[1]) & np.isfinite(g)
    y = np.array([np.mean((t[j] - g[j])[near[j]]) if near[j].sum() >= 3 else np.nan for j in range(len(t))])
    if last is not None:
        y[max(0, last - HORIZON + 1):] = np.nan
    return y


def ridge(Xs, ys, lam):
    X, y = np.concatenate(Xs), np.concatenate(ys)
    ok = np.isfinite(y)
    X, y = X[ok], y[ok]
    mu, sd = X.mean(0), X.std(0) + 1e-6
    Z = (X - mu) / sd
    w = np.linalg.solve(Z.T @ Z + lam * np.eye(Z.shape[1]), Z.T @ (y - y.mean()))
    return lambda X2: ((X2 - mu) / sd) @ w + y.mean()


def candidates():
    one = lambda d: np.ones_like(d["s"])
    return [
        Fusion("shipped form: s+geo", lambda d: [one(d), d["geo"], d["s"]], s_weight=STUDENT_WEIGHT),
        Fusion("geo+gap", lambda d: [one(d), d["geo"], d["gap"]]),
        Fusion("geo+gap+s (s 0.25)", lambda d: [one(d), d["geo"], d["gap"], d["s"]], s_weight=STUDENT_WEIGHT),
    ]


def penalties(text):
    """argparse type of --lam: comma-separated positive numbers."""
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}")
    if not v or not all(np.isfinite(x) and x > 0 for x in v):
        raise argparse.ArgumentTypeError(f"every penalty must be a positive number, got {text!r}")
    return v


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=MODELS_DIR)
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "evals", "fuse"))
    ap.add_argument("--lam", type=penalties, default=[300.0, 1000.0, 3000.0], help="ridge penalties (standardised features)")
    ap.add_argument("--eval-synth", default=",".join(os.path.join(DATA_ROOT, "eval", f"synth_900{k}") for k in (1, 2, 3)))
    ap.add_argument("--unseen", default=",".join([os.path.join(SHARED, n) for n in ("7scenes_redkitchen_dev", "7scenes_redkitchen_long")] +
                                                 [os.path.join(DATA_ROOT, "fusefit", f"synth_500{k}") for k in (0, 1)]))
    a = ap.parse_args()
    base = lambda p: os.path.basename(os.path.normpath(p))
    data, X = {}, {}
    for p in [os.path.join(SHARED, n) for n in REAL_SPLITS] + [p for p in a.eval_synth.split(",") if p]:
        data[base(p)] = sequence_data(p, os.path.join(a.out, base(p)), a.models, HORIZON)
        X[base(p)] = pooled(a.models, p)
    unseen = {}
    for p in filter(None, a.unseen.split(",")):
        if os.path.isdir(p):
            unseen[base(p)] = (sequence_data(p, os.path.join(a.out, base(p)), a.models, HORIZON), pooled(a.models, p))
    real = list(REAL_SPLITS)
    synth = [n for n in data if n not in real]

    def set_gap(f):
        for n, d in data.items():
            d["gap"] = np.repeat(f(X[n])[:, None], HORIZON, 1)

    fit_ranges = {n: [REAL_SPLITS[n][p] for p in FUSION_FIT_PARTS[n]] for n in real}
    # the ridge sees every reference of the parts before each sequence's test part
    ridge_last = {n: max(b for p, (a_, b) in REAL_SPLITS[n].items() if p != "test") for n in real}
    for lam in a.lam:
        print(f"\n## ridge penalty {lam:g}\n")
        print("| candidate | LOSO rpy -> desk | LOSO desk -> rpy | " + " | ".join(f"{n} test" for n in real) +
              " | " + " | ".join(f"{n} all" for n in real + synth) + " |")
        print("|---|---|---|" + "---|" * (2 * len(real) + len(synth)))
        for fz in candidates():
            cells = []
            for A, B in [(real[0], real[1]), (real[1], real[0])]:
                set_gap(ridge([X[A]], [reference_gap(data[A])], lam))
                fit(fz, data, {A: [(0, len(data[A]["tau"]) - 1)]}, 0.5, 30)
                cells.append(cell(evaluate(fz, data, 0.5)[(B, "all")]))
            f = ridge([X[n] for n in real], [reference_gap(data[n], ridge_last[n]) for n in real], lam)
            set_gap(f)
            fit(fz, data, fit_ranges, 0.5, 30)
            ev = evaluate(fz, data, 0.5)
            cells += [cell(ev[(n, "test")]) for n in real] + [cell(ev[(n, "all")]) for n in real + synth]
            print(f"| {fz.name} | " + " | ".join(cells) + " |")
        print("\npredicted reference gap (the split's ridge) against the teacher's, mean over references:")
        for n, (d, Xu) in {**{n: (data[n], X[n]) for n in data}, **unseen}.items():
            y, p = reference_gap(d), f(Xu)
            ok = np.isfinite(y)
            r = np.corrcoef(y[ok], p[ok])[0, 1] if ok.sum() > 2 and np.std(y[ok]) > 0 else float("nan")
            print(f"  {n}: teacher {np.mean(y[ok]) if ok.any() else float('nan'):.3f}, predicted {np.mean(p):.3f}"
                  f" (10-90 %: {np.percentile(p, 10):.3f}-{np.percentile(p, 90):.3f}), r {r:.2f}")


if __name__ == "__main__":
    main()
