"""Fit a monotone calibration of the student's utility to the teacher's tau, and bake it into the
exported ONNX models, so that `threshold` is tau_keep in the teacher's units (default 0.5).

1. Raw utilities u of the uncalibrated split model (encoder + head, ONNX Runtime) on gate-like
   pairs of tum_fr1_rpy's calibration part (cache/tum_cal.npz from `gen_data --steps tum`: every
   frame as the reference against each of its next 45 frames; frames 415-559, see config.TUM_SPLIT),
   optionally plus held-out synthetic validation pairs (--synth N).
2. Monotone piecewise-linear map f: knots at fixed raw values (--knots), f(u) = v0 + sum_k s_k *
   clip(u - k_k, 0, k_{k+1} - k_k) with every slope s_k >= --min-slope (bounded least squares), then
   clipped to [0, 1]. Strictly increasing (a segment the data would leave flat, e.g. raw scores
   above the real pairs' range, keeps the minimum slope), so the student's ranking is unchanged and
   every threshold inside the map's range selects a different cut; only the scale moves.
3. The map is appended to the pair model and the head as ONNX ops after the sigmoid (Unsqueeze,
   Sub, Max, Min, MatMul, Add, Clip); the output is still `utility` [N]. Metadata:
   `leangate.threshold` = 0.5, `leangate.calibration` = the knots and what they were fitted on,
   `leangate.score_max` = the map's top (rounded up): no score exceeds it, so the element's
   screening can bound the fused utility tighter.
4. Checks with ONNX Runtime: head(encoder) == pair to 1e-5, calibrated == f(raw) to 1e-5.

Usage: python -m training.calibrate [--models models] [--out-dir models] [--data $DATA_ROOT/cache]
       (run it on freshly exported, uncalibrated models; it refuses calibrated ones)
"""
import argparse
import json
import os

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from .config import DATA_ROOT, DEFAULT_THRESHOLD, MODELS_DIR, NAME, TUM_SEQ, TUM_SPLIT
from .preprocess import normalise

DEFAULT_KNOTS = "0,0.1,0.2,0.3,0.4,0.5,0.6,0.8,1"


def sessions(models):
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    mk = lambda n: ort.InferenceSession(os.path.join(models, f"{NAME}{n}.onnx"), so, providers=["CPUExecutionProvider"])
    return mk("-encoder"), mk("-head"), mk("")


def encode(enc, frames):
    x = normalise(frames)
    return np.concatenate([enc.run(["features"], {"image": x[k:k + 64]})[0] for k in range(0, len(x), 64)])


def score_pairs(head, F, cur, ref, G=None):
    G = F if G is None else G
    out = []
    for k in range(0, len(cur), 256):
        out.append(head.run(["utility"], {"reference_features": G[ref[k:k + 256]], "current_features": F[cur[k:k + 256]]})[0])
    return np.concatenate(out).reshape(-1)


def raw_on_cache(enc, head, path, n=None, seed=0, max_gap=None):
    d = np.load(path)
    P = d["pairs"]
    if max_gap is not None:
        P = P[np.abs(P[:, 0] - P[:, 1]) <= max_gap]
    if n is not None and n < len(P):
        P = P[np.random.default_rng(seed).choice(len(P), n, replace=False)]
    F = encode(enc, d["frames"])
    return score_pairs(head, F, P[:, 0].astype(int), P[:, 1].astype(int)), P[:, 2]


def basis(u, knots):
    k = np.asarray(knots)
    return np.clip(u[:, None] - k[None, :-1], 0, np.diff(k)[None, :])


def nnls_fit(u, t, knots, w=None, iters=3000, min_slope=0.0):
    """Least squares v0 + B s with s >= min_slope (coordinate descent on the normal equations)."""
    B = np.concatenate([np.ones((len(u), 1)), basis(u, knots)], 1)
    w = np.ones(len(u)) if w is None else w
    A = B.T @ (B * w[:, None]) + 1e-9 * np.eye(B.shape[1])
    b = B.T @ (t * w)
    x = np.zeros(B.shape[1])
    x[1:] = 1.0
    for _ in range(iters):
        for j in range(len(x)):
            r = b[j] - A[j] @ x + A[j, j] * x[j]
            x[j] = r / A[j, j]
            if j > 0:
                x[j] = max(x[j], min_slope)
    return x[0], x[1:]


def apply(u, knots, v0, s):
    return np.clip(v0 + basis(np.asarray(u, np.float64), knots) @ s, 0.0, 1.0)


def knot_values(knots, v0, s):
    return np.clip(v0 + np.concatenate([[0.0], np.cumsum(s * np.diff(knots))]), 0, 1)


def gate_keeps(F, thr, calib=None, head=None):
    """The element's gate on one sequence of features: first frame kept, score against the last keep."""
    ref, keeps = 0, [0]
    for i in range(1, len(F)):
        u = head.run(["utility"], {"reference_features": F[ref:ref + 1], "current_features": F[i:i + 1]})[0].reshape(-1)
        if calib is not None:
            u = calib(u)
        if u[0] >= thr:
            ref = i
            keeps.append(i)
    return keeps


def bake(path, knots, v0, s, meta):
    """Append the calibration after the graph's `utility` output."""
    m = onnx.load(path)
    g = m.graph
    if any(o == "utility_raw" for n in g.node for o in n.output):
        raise SystemExit(f"{path} is already calibrated (has utility_raw); export it again first")
    for n in g.node:
        for k, o in enumerate(n.output):
            if o == "utility":
                n.output[k] = "utility_raw"
    kn = np.asarray(knots, np.float32)
    inits = [
        numpy_helper.from_array(np.array([1], np.int64), "calib_axes"),
        numpy_helper.from_array(kn[:-1], "calib_knots"),
        numpy_helper.from_array(np.diff(kn).astype(np.float32), "calib_widths"),
        numpy_helper.from_array(np.zeros(len(kn) - 1, np.float32), "calib_zeros"),
        numpy_helper.from_array(np.asarray(s, np.float32), "calib_slopes"),
        numpy_helper.from_array(np.array(v0, np.float32), "calib_offset"),
        numpy_helper.from_array(np.array(0.0, np.float32), "calib_lo"),
        numpy_helper.from_array(np.array(1.0, np.float32), "calib_hi"),
    ]
    nodes = [
        helper.make_node("Unsqueeze", ["utility_raw", "calib_axes"], ["calib_u"], name="calib_unsqueeze"),
        helper.make_node("Sub", ["calib_u", "calib_knots"], ["calib_d"], name="calib_sub"),
        helper.make_node("Max", ["calib_d", "calib_zeros"], ["calib_pos"], name="calib_max"),
        helper.make_node("Min", ["calib_pos", "calib_widths"], ["calib_seg"], name="calib_min"),
        helper.make_node("MatMul", ["calib_seg", "calib_slopes"], ["calib_lin"], name="calib_matmul"),
        helper.make_node("Add", ["calib_lin", "calib_offset"], ["calib_y"], name="calib_add"),
        helper.make_node("Clip", ["calib_y", "calib_lo", "calib_hi"], ["utility"], name="calib_clip"),
    ]
    g.initializer.extend(inits)
    g.node.extend(nodes)
    keep = [p for p in m.metadata_props if p.key not in meta]
    del m.metadata_props[:]
    m.metadata_props.extend(keep)
    for k, v in meta.items():
        m.metadata_props.add(key=k, value=str(v))
    onnx.checker.check_model(m, full_check=True)
    onnx.save(m, path)


def score_max(vals):
    """`leangate.score_max` of a map with these knot values: its largest value (the map is
    monotone, the top knot's), clipped to [0, 1] as the graph clips, rounded up to 4 decimals so
    that the graph's float32 arithmetic stays below it."""
    top = min(max(float(np.max(vals)), 0.0), 1.0)
    return f"{min(np.ceil(top * 1e4 + 1e-6) / 1e4, 1.0):.4f}"


def is_calibrated(path):
    return any(o == "utility_raw" for n in onnx.load(path).graph.node for o in n.output)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=MODELS_DIR, help="directory of the uncalibrated leangate-s*.onnx")
    ap.add_argument("--out-dir", default=None, help="write the calibrated models here (default: in place)")
    ap.add_argument("--data", default=os.path.join(DATA_ROOT, "cache"))
    ap.add_argument("--knots", default=DEFAULT_KNOTS)
    ap.add_argument("--max-gap", type=int, default=24,
                    help="use the cal part's pairs up to this frame gap (the oracle keeps every ~12-15 frames)")
    ap.add_argument("--synth", type=int, default=3000, help="also fit on N held-out synthetic validation pairs (0: real only)")
    ap.add_argument("--synth-weight", type=float, default=0.5, help="weight of each synthetic pair in the fit")
    ap.add_argument("--min-slope", type=float, default=0.05,
                    help="least slope of every segment: keeps the map strictly increasing (0: plain NNLS, "
                         "which may leave segments flat)")
    ap.add_argument("--json", default="", help="write the fit and its diagnostics here")
    a = ap.parse_args()
    out_dir = a.out_dir or a.models
    names = [f"{NAME}.onnx", f"{NAME}-encoder.onnx", f"{NAME}-head.onnx"]
    for n in names:
        if is_calibrated(os.path.join(a.models, n)):
            raise SystemExit(f"{a.models}/{n} is already calibrated; calibrate freshly exported models")
    knots = [float(x) for x in a.knots.split(",")]
    enc, head, pair = sessions(a.models)

    u, t = raw_on_cache(enc, head, os.path.join(a.data, "tum_cal.npz"), max_gap=a.max_gap)
    fitted_on = (f"{TUM_SEQ} frames {TUM_SPLIT['cal'][0]}-{TUM_SPLIT['cal'][1]} ({len(u)} gate-like pairs: each frame "
                 f"vs its next {a.max_gap})")
    w = np.ones(len(u))
    if a.synth:
        import glob
        us, ts = [], []
        files = sorted(glob.glob(os.path.join(a.data, "val", "*.npz")))
        for k, f in enumerate(files):
            x, y = raw_on_cache(enc, head, f, a.synth // len(files), seed=k)
            us.append(x)
            ts.append(y)
        us, ts = np.concatenate(us), np.concatenate(ts)
        u, t = np.concatenate([u, us]), np.concatenate([t, ts])
        w = np.concatenate([w, np.full(len(us), a.synth_weight)])
        fitted_on += f" + {len(us)} held-out synthetic validation pairs (weight {a.synth_weight:g})"
    v0, s = nnls_fit(u, t, knots, w, min_slope=a.min_slope)
    vals = knot_values(np.asarray(knots), v0, s)
    cal_u = apply(u, knots, v0, s)
    print(f"fit on {fitted_on}")
    n_real = int(w.size if not a.synth else len(w) - len(us))
    rm = lambda x, y: float(np.sqrt(np.mean((x - y) ** 2)))
    print(f"  RMSE raw -> calibrated: cal part {rm(u[:n_real], t[:n_real]):.4f} -> {rm(cal_u[:n_real], t[:n_real]):.4f}"
          + (f", synthetic {rm(u[n_real:], t[n_real:]):.4f} -> {rm(cal_u[n_real:], t[n_real:]):.4f}" if a.synth else ""))
    print("  knots (raw -> calibrated): " + ", ".join(f"{k:g}->{v:.3f}" for k, v in zip(knots, vals)))

    desc = ("monotone piecewise-linear map of the sigmoid output, knots raw->calibrated "
            + " ".join(f"{k:g}:{v:.3f}" for k, v in zip(knots, vals))
            + f", clipped to [0,1]; least squares (every slope >= {a.min_slope:g}) to the exact teacher's tau on "
            + fitted_on)
    # The map's top, rounded up: no score of the calibrated graph exceeds it (the element's
    # screening relies on it, src/geometry.rs Fusion::s_max).
    meta = {"leangate.threshold": f"{DEFAULT_THRESHOLD:.3f}", "leangate.calibration": desc,
            "leangate.score_max": score_max(vals)}
    os.makedirs(out_dir, exist_ok=True)
    for n in names:
        src, dst = os.path.join(a.models, n), os.path.join(out_dir, n)
        if n.endswith("-encoder.onnx"):
            m = onnx.load(src)
            keep = [p for p in m.metadata_props if p.key not in meta]
            del m.metadata_props[:]
            m.metadata_props.extend(keep)
            for k, v in meta.items():
                m.metadata_props.add(key=k, value=v)
            onnx.save(m, dst)
        else:
            if src != dst:
                onnx.save(onnx.load(src), dst)
            bake(dst, knots, v0, s, meta)

    # checks
    enc2, head2, pair2 = sessions(out_dir)
    d = np.load(os.path.join(a.data, "tum_cal.npz"))
    x = normalise(d["frames"][:24])
    r, c = x[:12], x[12:]
    up = pair2.run(["utility"], {"reference": r, "current": c})[0]
    us_ = head2.run(["utility"], {"reference_features": enc2.run(["features"], {"image": r})[0],
                                  "current_features": enc2.run(["features"], {"image": c})[0]})[0]
    raw = pair.run(["utility"], {"reference": r, "current": c})[0]
    d1, d2 = np.abs(up - us_).max(), np.abs(up - apply(raw, knots, v0, s)).max()
    print(f"checks: |pair - split| = {d1:.2e}, |calibrated - f(raw)| = {d2:.2e}, shape {up.shape}")
    assert up.shape == (12,) and d1 <= 1e-5 and d2 <= 1e-5
    # the gate on the calibration part (diagnostic; `leangate eval` is the judge)
    F = encode(enc2, d["frames"])
    k5 = gate_keeps(F, DEFAULT_THRESHOLD, head=head2)
    print(f"gate at {DEFAULT_THRESHOLD} on the calibration part ({len(F)} frames): {len(k5)} keeps")
    if a.json:
        json.dump({"knots": knots, "values": vals.tolist(), "offset": float(v0), "slopes": s.tolist(),
                   "fitted_on": fitted_on, "calibration": desc, "keeps_cal": k5}, open(a.json, "w"), indent=1)


if __name__ == "__main__":
    main()
