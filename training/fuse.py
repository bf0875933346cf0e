"""Fit how the element combines the student's utility with the geometric prior, and write it
into the models' `leangate.geometry` metadata (the element reads it; see src/geometry.rs).

The prior, tau_geo, is the teacher's score of the chained frame-to-frame homography from the
reference to the current frame (`leangate geometry`: exactly the element's computation). It sees
rotation and image motion precisely but no depth, so it reads low where the teacher's 3-D check
or parallax removes matches; the student sees some of that. The fusion is

    utility = clip(w0 + w1 tau_geo + w2 tau_geo^2 + w3 s, 0, 1)      (s: the calibrated student)

fitted by least squares to the exact teacher's tau on gate-like pairs (every frame as the
reference against each of its next --max-gap frames) of tum_fr1_rpy's **train and cal parts**
(frames 0-399 and 415-559). The test part (575-717), 7-Scenes and the synthetic sequences are
never used. The fit must be increasing in both inputs over [0, 1] (checked; it refuses otherwise).

It also prints where tau_geo and the teacher differ near the decision: the teacher's 3-D distance
check (teacher vs `leangate label --max-dist 5`) and depth effects (parallax, holes).

Usage: python -m training.fuse [--models models] [--write]    (without --write: report only)
"""
import argparse
import os
import subprocess

import numpy as np
import onnx

from .calibrate import encode, score_pairs, sessions
from .compare import pair_set
from .config import DATA_ROOT, LEANGATE, MODELS_DIR, NAME, SHARED

FORM = "raster-homography-v1"  # src/geometry.rs FUSION_FORM
# the files whose metadata the element reads (pair model, split encoders of both builds)
FILES = [f"{NAME}.onnx", f"{NAME}-encoder.onnx", f"{NAME}-int8-encoder.onnx"]


def geometry(seq, pairs_csv, out_csv):
    r = subprocess.run([LEANGATE, "geometry", "--sequence", seq, "--pairs", pairs_csv, "--out", out_csv],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"leangate geometry failed:\n{r.stderr}")
    d = np.genfromtxt(out_csv, delimiter=",", names=True)
    return np.stack([d["i"], d["j"], d["tau_geo"]], 1)


def no_dist_tau(seq, pairs_csv, out_csv):
    """The teacher without its 3-D distance check (`--max-dist 5`): overlap with depth, parallax
    and holes, but no rejection of matches that land on another surface."""
    r = subprocess.run([LEANGATE, "label", "--sequence", seq, "--pairs", pairs_csv, "--max-dist", "5", "--out", out_csv],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"leangate label failed:\n{r.stderr}")
    d = np.genfromtxt(out_csv, delimiter=",", names=True)
    return {(int(i), int(j)): t for i, j, t in zip(d["i"], d["j"], d["tau"])}


def pair_data(out, models, name, seq, max_gap):
    """(teacher tau, student s, tau_geo, teacher tau without the distance check) on the gate-like
    pairs of `seq`, and how many pairs lost their chain (dropped: the element uses s alone)."""
    frames, P = pair_set(out, name, seq, max_gap)
    lab = os.path.join(out, "labels")
    pairs_csv = os.path.join(lab, f"{name}_{max_gap}_pairs.csv")
    G = geometry(seq, pairs_csv, os.path.join(lab, f"{name}_{max_gap}_geo.csv"))
    geo = {(int(i), int(j)): g for i, j, g in G}
    g = np.array([geo.get((int(i), int(j)), np.nan) for i, j in P[:, :2]])
    nd = no_dist_tau(seq, pairs_csv, os.path.join(lab, f"{name}_{max_gap}_nodist.csv"))
    n = np.array([nd.get((int(i), int(j)), np.nan) for i, j in P[:, :2]])
    enc, head, _ = sessions(models)
    s = score_pairs(head, encode(enc, frames), P[:, 0].astype(int), P[:, 1].astype(int))
    ok = np.isfinite(g)
    return P[ok, 2], s[ok], g[ok], n[ok], int((~ok).sum())


def features(s, g):
    return np.stack([np.ones_like(g), g, g * g, s], 1)


def fuse(w, s, g):
    return np.clip(features(s, g) @ w, 0.0, 1.0)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=MODELS_DIR, help="folder with the calibrated student (FP32 split files)")
    ap.add_argument("--root", default=DATA_ROOT, help="where gen_data put tum/")
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "evals", "fuse"))
    ap.add_argument("--max-gap", type=int, default=24)
    ap.add_argument("--write", action="store_true", help="write leangate.geometry into the model files")
    a = ap.parse_args()
    fit_sets = {"tum_train": os.path.join(a.root, "tum", "train"), "tum_cal": os.path.join(a.root, "tum", "cal")}
    report_sets = {"tum_test": os.path.join(a.root, "tum", "test"), "7scenes": os.path.join(SHARED, "7scenes_redkitchen_dev")}
    data = {k: pair_data(a.out, a.models, k, s, a.max_gap) for k, s in {**fit_sets, **report_sets}.items() if os.path.exists(s)}
    missing = [k for k in fit_sets if k not in data]
    if missing:
        raise SystemExit(f"missing {missing}: run `python -m training.gen_data --steps tum` first")
    print("Where tau_geo and the teacher differ, near the decision (teacher tau in [0.35, 0.65)), mean of:")
    print("| pairs | teacher - teacher without the 3-D check | that - tau_geo (depth: parallax, holes) |")
    print("|---|---|---|")
    for k, (t, s, g, n, lost) in data.items():
        near = (t >= 0.35) & (t < 0.65)
        if near.any():
            print(f"| {k} | {np.mean(t[near] - n[near]):+.3f} | {np.mean(n[near] - g[near]):+.3f} |")
        else:
            print(f"| {k} | no pair near the decision | |")
    X = np.concatenate([features(data[k][1], data[k][2]) for k in fit_sets])
    y = np.concatenate([data[k][0] for k in fit_sets])
    w = np.linalg.lstsq(X, y, rcond=None)[0]
    grid = np.linspace(0, 1, 101)
    if not (w[3] > 0 and np.all(w[1] + 2 * w[2] * grid > 0)):
        raise SystemExit(f"fit {w} is not increasing in both inputs on [0, 1]; not written")
    print(f"fit on {' + '.join(fit_sets)} ({len(y)} pairs): w = {', '.join(f'{v:.4f}' for v in w)}")
    print("| pairs | n | lost | student RMSE / bias | tau_geo corr | fused RMSE / bias |")
    print("|---|---|---|---|---|---|")
    for k, (t, s, g, n, lost) in data.items():
        u = fuse(w, s, g)
        print(f"| {k}{' (fitted)' if k in fit_sets else ''} | {len(t)} | {lost} | {np.sqrt(np.mean((s - t) ** 2)):.3f} / {np.mean(s - t):+.3f} "
              f"| {np.corrcoef(g, t)[0, 1]:.3f} | {np.sqrt(np.mean((u - t) ** 2)):.3f} / {np.mean(u - t):+.3f} |")
    value = f"{FORM}: " + ", ".join(f"{v:.6f}" for v in w)
    if a.write:
        for f in FILES:
            p = os.path.join(a.models, f)
            m = onnx.load(p)
            props = [x for x in m.metadata_props if x.key != "leangate.geometry"]
            del m.metadata_props[:]
            m.metadata_props.extend(props)
            m.metadata_props.add(key="leangate.geometry", value=value)
            onnx.save(m, p)
            print(f"wrote leangate.geometry = {value!r} into {p}")
    else:
        print(f"not written (--write): leangate.geometry = {value!r}")


if __name__ == "__main__":
    main()
