"""Cross-sequence validation of the gate's utility on the real labelled sequences.

For every real sequence with depth and poses (`config.REAL_SPLITS`: tum_fr1_rpy and tum_fr1_desk)
this gathers, on gate-like pairs (every frame as the reference against each of its next
`--horizon` frames), the exact teacher's tau, the embedded student's utility `s` (the INT8 build the
element runs on the CPU) and the element's geometric prior (`leangate geometry`: tau_geo, f_m, f_u
of the chained homography; NaN where the chain is lost). It then

  * fits each fusion candidate on one sequence and reports it on the other (leave one sequence
    out, both directions), and on the held-out parts of the documented split;
  * replays the gate in numpy on those pairs (keep when utility >= threshold, the kept frame
    becomes the reference; exactly the element's rule) and counts kept frames against the oracle,
    late keeps (teacher S with the previous keep < 0.333) and breaks (S < 0.05).

The numpy replay is for choosing quickly; the figures that ship are `leangate eval`'s (the real
element in a real pipeline).

Usage: python -m training.fuse [--models models] [--regeo] [--write]
"""
import argparse
import json
import os
import subprocess

import numpy as np
import onnx

from .calibrate import encode, score_pairs
from .config import DATA_ROOT, FUSION_FIT_PARTS as FIT_PARTS, LEANGATE, MODELS_DIR, NAME, REAL_SPLITS, SHARED
from .preprocess import load_resized, read_list
from .tum import gate_pairs, make_part

KEYFRAME_S, BREAK_S = 0.333, 0.05
FORM = "raster-homography-v1"  # src/geometry.rs FUSION_FORM: clip(w0 + w1 g + w2 g^2 + w3 s)
SHIPPED = "s+geo"  # the candidate --write puts into the embedded model (w2 = 0)
# The student's share in the shipped fusion, fixed rather than fitted: fitted freely, its weight
# swings from 0.09 to 0.34 between the fits (rpy cal + desk fit; either whole sequence) at equal
# fit error, while with 0.25 the other weights agree across all three fits (w0 0.106-0.114, w1
# 0.69-0.73) and the fit parts' RMSE rises by 0.002 only. See training/experiments/NOTEBOOK.md.
STUDENT_WEIGHT = 0.25
# the files whose metadata the element reads (pair model, split encoders of both builds)
FILES = [f"{NAME}.onnx", f"{NAME}-encoder.onnx", f"{NAME}-int8-encoder.onnx"]


# ------------------------------------------------------------------------------------- data
def _csv(path):
    return np.genfromtxt(path, delimiter=",", names=True)


def _run(args):
    r = subprocess.run([LEANGATE, *args], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"leangate {' '.join(args)} failed:\n{r.stderr}")


def int8_sessions(models):
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    mk = lambda n: ort.InferenceSession(os.path.join(models, f"{NAME}{n}.onnx"), so, providers=["CPUExecutionProvider"])
    return mk("-int8-encoder"), mk("-int8-head")


def sequence_data(seq, out, models, horizon, regeo=False):
    """Dense [n, horizon] tables for one sequence directory: teacher tau, student s, tau_geo, f_m,
    f_u of (current = ref + k, reference = ref), k = 1..horizon; NaN where undefined. The teacher
    and the student are cached; `regeo` recomputes the prior (after a change to src/geometry.rs)."""
    os.makedirs(out, exist_ok=True)
    cache = os.path.join(out, f"pairs_{horizon}.npz")
    geo = os.path.join(out, "geometry.csv")
    pcsv = os.path.join(out, f"pairs_{horizon}.csv")
    if os.path.exists(cache):
        tab = dict(np.load(cache))
        if not regeo:
            return tab
        _run(["geometry", "--sequence", seq, "--pairs", pcsv, "--out", geo])
        _geo_into(tab, _csv(geo))
        np.savez(cache, **tab)
        return tab
    files = read_list(seq)
    n = len(files)
    P = gate_pairs(n, horizon)
    with open(pcsv, "w") as f:
        f.write("i,j\n" + "".join(f"{i},{j}\n" for i, j in P))
    lab = os.path.join(out, "teacher.csv")
    _run(["label", "--sequence", seq, "--pairs", pcsv, "--out", lab])
    _run(["geometry", "--sequence", seq, "--pairs", pcsv, "--out", geo])
    T, G = _csv(lab), _csv(geo)
    enc, head = int8_sessions(models)
    frames = np.stack([load_resized(f) for f in files])
    F = encode(enc, frames)
    s = score_pairs(head, F, np.array([i for i, _ in P]), np.array([j for _, j in P]))
    tab = {k: np.full((n, horizon), np.nan) for k in ("tau", "s", "geo", "fm", "fu")}
    for r, (i, j) in enumerate(P):
        c = i - j - 1
        tab["s"][j, c] = s[r]
    for col, key in (("tau", "tau"),):
        tab[key][T["j"].astype(int), (T["i"] - T["j"] - 1).astype(int)] = T[col]
    _geo_into(tab, G)
    np.savez(cache, **tab)
    return tab


def _geo_into(tab, G):
    for key in ("geo", "fm", "fu"):
        tab[key][:] = np.nan
    gj, gc = G["j"].astype(int), (G["i"] - G["j"] - 1).astype(int)
    for col, key in (("tau_geo", "geo"), ("f_m", "fm"), ("f_u", "fu")):
        tab[key][gj, gc] = G[col]


def parts_of(name, tab):
    """Row ranges (reference frames) of each part of the documented split; pairs stay inside."""
    n = tab["tau"].shape[0]
    parts = {"all": (0, n - 1)}
    parts.update(REAL_SPLITS.get(name, {}))
    return parts


# ----------------------------------------------------------------------------------- fusions
class Fusion:
    """A candidate: features(s, geo, fm, fu) -> utility, fitted by least squares to the teacher."""

    def __init__(self, name, feats, geometric=True, fixed=None, s_weight=None):
        """`fixed`: all weights given (nothing fitted); `s_weight`: the student's weight given (the
        last feature must be `s`), the rest fitted."""
        self.name, self.feats, self.geometric, self.fixed, self.s_weight = name, feats, geometric, fixed, s_weight
        self.w = None
        self.offset = 0.0

    def X(self, d):
        return np.stack(self.feats(d), -1)

    def fit(self, rows):
        """Weighted least squares on the pairs near the decision (see `decision_weight`)."""
        self.offset = 0.0
        if self.fixed is not None:
            self.w = np.array(self.fixed)
            return self
        rows = [r if len(r) == 3 else (*r, 1.0) for r in rows]
        X = np.concatenate([self.X(d)[m] for d, m, _ in rows])
        y = np.concatenate([d["tau"][m] for d, m, _ in rows])
        k = np.concatenate([np.full(int(m.sum()), wt) for _, m, wt in rows])
        sw = np.sqrt(decision_weight(y) * k)
        if self.s_weight is None:
            self.w = np.linalg.lstsq(X * sw[:, None], y * sw, rcond=None)[0]
        else:
            rest = np.linalg.lstsq(X[:, :-1] * sw[:, None], (y - self.s_weight * X[:, -1]) * sw, rcond=None)[0]
            self.w = np.append(rest, self.s_weight)
        return self

    def __call__(self, d):
        u = np.clip(self.X(d) @ self.w + self.offset, 0.0, 1.0)
        if self.geometric:  # the element uses s alone where the chain is lost
            u = np.where(np.isfinite(d["geo"]), u, d["s"])
        return u


class MaxFusion(Fusion):
    """max(student line, geometry quadratic), each fitted alone: either signal can call a keep."""

    def __init__(self, name):
        super().__init__(name, None)
        one = lambda d: np.ones_like(d["s"])
        self.a = Fusion("s", lambda d: [one(d), d["s"]], geometric=False)
        self.b = Fusion("g", lambda d: [one(d), d["geo"], d["geo"] ** 2])

    def fit(self, rows):
        self.offset = 0.0
        self.a.fit(rows)
        self.b.fit([(r[0], r[1] & np.isfinite(r[0]["geo"]), *r[2:]) for r in rows])
        self.w = np.concatenate([self.a.w, self.b.w])
        return self

    def __call__(self, d):
        g = self.b(d)
        u = np.where(np.isfinite(d["geo"]), np.maximum(self.a(d), g), self.a(d))
        return np.clip(u + self.offset, 0.0, 1.0)


def decision_weight(tau):
    """Pairs near the paper's tau_keep decide the gate: weight 1 + 4 exp(-((tau - 0.5) / 0.15)^2)."""
    return 1.0 + 4.0 * np.exp(-(((tau - 0.5) / 0.15) ** 2))


def candidates():
    one = lambda d: np.ones_like(d["s"])
    return [
        Fusion("shipped student", lambda d: [d["s"]], geometric=False, fixed=[1.0]),
        Fusion("student", lambda d: [d["s"]], geometric=False),
        Fusion("student+bias", lambda d: [one(d), d["s"]], geometric=False),
        Fusion("geo only", lambda d: [one(d), d["geo"], d["geo"] ** 2]),
        Fusion("s+geo (all fitted)", lambda d: [one(d), d["geo"], d["s"]]),
        Fusion("s+geo", lambda d: [one(d), d["geo"], d["s"]], s_weight=STUDENT_WEIGHT),
        Fusion("s+geo+geo^2", lambda d: [one(d), d["geo"], d["geo"] ** 2, d["s"]]),
        MaxFusion("max(s, geo)"),
    ]


# --------------------------------------------------------------------------------- the gate
def replay(u, tau, threshold, a, b, correction=None):
    """The gate over frames a..b on the dense tables: kept frames, late keeps, breaks, min pair S.
    A frame beyond the horizon from its reference is kept (the tables end there). `correction`
    (optional; `training.experiments.feedback`) adds `correction.offset(i)` to frame i's utility and is told
    `correction.report(i, tau)` of every keep, as the element's feedback is."""
    H = u.shape[1]
    ref, kept, late, breaks, min_s = a, 1, 0, 0, 1.0
    for i in range(a + 1, b + 1):
        k = i - ref - 1
        v = u[ref, k] if k < H else 1.0
        off = correction.offset(i) if correction is not None else 0.0
        if not np.isfinite(v) or v + off >= threshold:
            t = tau[ref, k] if k < H else 1.0
            S = 1.0 - t
            late += S < KEYFRAME_S
            breaks += S < BREAK_S
            min_s = min(min_s, S)
            kept += 1
            ref = i
            if correction is not None and np.isfinite(t):
                correction.report(i, t)
    return kept, late, breaks, min_s


def mask(tab, a, b, horizon=None):
    n, H = tab["tau"].shape
    j = np.arange(n)[:, None]
    i = j + 1 + np.arange(H)[None, :]
    m = (j >= a) & (i <= b) & np.isfinite(tab["tau"]) & np.isfinite(tab["s"])
    return m & (i - j <= horizon) if horizon else m


def match_budget(fusion, spans, threshold):
    """Gate-level calibration: the offset added to the utility that makes the replayed gate keep as
    many frames as the oracle over `spans` ([(table, first, last)]), by bisection (the keep count
    rises with the offset)."""
    target = sum(replay(t["tau"], t["tau"], threshold, a, b)[0] for t, a, b in spans)
    lo, hi = -0.3, 0.3
    for _ in range(30):
        fusion.offset = 0.5 * (lo + hi)
        kept = sum(replay(fusion(t), t["tau"], threshold, a, b)[0] for t, a, b in spans)
        lo, hi = (fusion.offset, hi) if kept < target else (lo, fusion.offset)
    fusion.offset = 0.5 * (lo + hi)
    return fusion


def fit(fusion, data, spans, threshold, horizon, synth=None, synth_weight=0.0):
    """Least squares on the pairs of `spans` ({sequence: [(first, last)]}) and, at `synth_weight`,
    of the synthetic sequences `synth` ({name: table}); then the budget match over all of them."""
    rows = [(data[n], mask(data[n], a, b, horizon)) for n, parts in spans.items() for a, b in parts]
    whole = [(t, 0, len(t["tau"]) - 1) for t in (synth or {}).values()] if synth_weight > 0 else []
    rows += [(t, mask(t, a, b, horizon), synth_weight) for t, a, b in whole]
    fusion.fit(rows)
    if fusion.fixed is None:
        match_budget(fusion, [(data[n], a, b) for n, parts in spans.items() for a, b in parts] + whole, threshold)
    return fusion


def evaluate(fusion, data, threshold):
    """{(sequence, part): row} for every part of every sequence."""
    out = {}
    for name, tab in data.items():
        u = fusion(tab)
        for part, (a, b) in parts_of(name, tab).items():
            m = mask(tab, a, b)
            e = u[m] - tab["tau"][m]
            ok = np.isfinite(e)
            kept, late, breaks, min_s = replay(u, tab["tau"], threshold, a, b)
            okk = replay(tab["tau"], tab["tau"], threshold, a, b)[0]
            out[(name, part)] = dict(frames=b - a + 1, oracle=okk, kept=kept, late=late, breaks=breaks,
                                     min_pair_S=round(float(min_s), 3),
                                     rmse=float(np.sqrt(np.mean(e[ok] ** 2))), bias=float(np.mean(e[ok])))
    return out


def cell(r):
    return f"{r['kept']}/{r['oracle']} ({100 * (r['kept'] / r['oracle'] - 1):+.0f} %), {r['late']} late, {r['rmse']:.3f}"


def write_metadata(models, value, key="leangate.geometry"):
    """Set `key` = `value` in the files whose metadata the element reads (`FILES`)."""
    for f in FILES:
        p = os.path.join(models, f)
        m = onnx.load(p)
        props = [x for x in m.metadata_props if x.key != key]
        del m.metadata_props[:]
        m.metadata_props.extend(props)
        m.metadata_props.add(key=key, value=value)
        onnx.save(m, p)
        print(f"wrote {key} = {value!r} into {p}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=MODELS_DIR, help="folder with the student's split files (FP32 and INT8)")
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "evals", "fuse"))
    ap.add_argument("--horizon", type=int, default=60, help="pairs: every frame against its next H frames")
    ap.add_argument("--fit-horizon", type=int, default=30, help="fit on pairs at most this many frames apart")
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--synth", default="", help="comma-separated synthetic TUM sequences to fit on as well (not the held-out eval ones)")
    ap.add_argument("--synth-weight", type=float, default=0.0, help="their weight in the fit (0: real only, the shipped fit)")
    ap.add_argument("--regeo", action="store_true", help="recompute the prior's columns (after a change to src/geometry.rs); the teacher and the student stay cached")
    ap.add_argument("--eval-synth", default=",".join(os.path.join(DATA_ROOT, "eval", f"synth_900{k}") for k in (1, 2, 3)),
                    help="synthetic held-out sequences reported (never fitted on); those missing are skipped")
    ap.add_argument("--write", action="store_true", help=f"write the `{SHIPPED}` fusion fitted on the fit parts into the models")
    a = ap.parse_args()
    data = {}
    for name in REAL_SPLITS:
        seq = os.path.join(SHARED, name)
        if not os.path.isdir(seq):
            raise SystemExit(f"{seq} is missing: the real sequences live in ../shared/data")
        data[name] = sequence_data(seq, os.path.join(a.out, name), a.models, a.horizon, a.regeo)
    base = lambda p: os.path.basename(os.path.normpath(p))
    synth = {base(p): sequence_data(p, os.path.join(a.out, base(p)), a.models, a.horizon, a.regeo)
             for p in filter(None, a.synth.split(","))}
    held_synth = {base(p): sequence_data(p, os.path.join(a.out, base(p)), a.models, a.horizon, a.regeo)
                  for p in filter(None, a.eval_synth.split(",")) if os.path.isdir(p)}
    names = list(data)
    whole = {n: [(0, len(data[n]["tau"]) - 1)] for n in names}
    fit_parts = {n: [REAL_SPLITS[n][p] for p in FIT_PARTS[n]] for n in names}
    results, shipped = {}, None
    print(f"Leave one sequence out (fit on the whole of one, report on the whole of the other), gate at {a.threshold}:")
    print(f"kept/oracle, late keeps, utility RMSE on pairs up to {a.horizon} apart\n")
    print("| candidate | " + " | ".join(f"fit {f} -> {t}" for f in names for t in names if t != f) + " |")
    print("|---|" + "---|" * (len(names) * (len(names) - 1)))
    for fz in candidates():
        cells = []
        for f in names:
            fit(fz, data, {f: whole[f]}, a.threshold, a.fit_horizon)
            ev = evaluate(fz, data, a.threshold)
            for t in names:
                if t != f:
                    cells.append(cell(ev[(t, "all")]))
                    results[f"{fz.name} | fit {f} | {t}"] = dict(w=fz.w.tolist(), offset=fz.offset, **ev[(t, "all")])
        print(f"| {fz.name} | " + " | ".join(cells) + " |")
    held = [(n, p) for n in names for p in REAL_SPLITS[n] if p not in FIT_PARTS[n] and p != "train"]
    print(f"\nThe documented split: fit on {', '.join(f'{n} {p}' for n in names for p in FIT_PARTS[n])}; "
          f"report on the held-out parts and the whole sequences\n")
    cols = held + [(n, "all") for n in names] + [(n, "all") for n in held_synth]
    print("| candidate | w, offset | " + " | ".join(f"{n} {p}" for n, p in cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for fz in candidates():
        fit(fz, data, fit_parts, a.threshold, a.fit_horizon, synth, a.synth_weight)
        ev = evaluate(fz, {**data, **held_synth}, a.threshold)
        print(f"| {fz.name} | {np.round(fz.w, 3).tolist()}, {fz.offset:+.3f} | " + " | ".join(cell(ev[c]) for c in cols) + " |")
        for c in cols:
            results[f"{fz.name} | split | {c[0]} {c[1]}"] = dict(w=fz.w.tolist(), offset=fz.offset, **ev[c])
        if fz.name == SHIPPED:
            shipped = fz
    with open(os.path.join(a.out, "fuse.json"), "w") as f:
        json.dump(results, f, indent=1, default=float)
    w = shipped.w
    value = f"{FORM}: {w[0] + shipped.offset:.6f}, {w[1]:.6f}, 0, {w[2]:.6f}"
    if a.write:
        write_metadata(a.models, value)
    else:
        print(f"\nnot written (--write): leangate.geometry = {value!r}")


if __name__ == "__main__":
    main()
