"""Replay the element's gate with feedback from the SLAM (`leangate-feedback`), to choose its rule
and rate without running pipelines.

For each sequence directory (e.g. the documented parts written by `python -m training.tum`), the
teacher's tau, the student's INT8 score and the prior's tau_geo of every frame against each of its
next 120 frames (`fuse.sequence_data`'s cached tables) give the default's fused utility (the
model's `leangate.geometry`). The gate is replayed from ten start frames as `leangate eval
--phases 10` runs it; after each keep the teacher's tau of that keep reaches the gate `--delays`
frames later and moves the correction by one of three rules:

  sum+       the first rule: a sum moved by rate * (tau - threshold) within +-0.3, the utility
             raised by its positive part;
  floor      an offset moved the same way, kept within 0..0.3;
  symmetric  an offset moved the same way, within +-0.3 (the utility may go down);
  both       the element's rule now (`Utility::feedback`): the sum moved by
             gain * clip(tau - threshold, +-CLIP), gain = max(rate, FIRST / (1 + n)) for report n;
             raised by the sum's positive part, lowered by what lies below -BAND, at most LOWER.
             Each of --first-gains x --clips x --bands is one variant.

Prints, per rule, rate and delay, each sequence's kept / oracle and late keeps and the sums; with
`--fit NAME,...` also the sums over those sequences and over the others apart (choose on the fit
set, report on the rest), and which of each set leave the issue's band (kept within 15 % of the
oracle, or within one keyframe a run where the oracle keeps fewer than seven).
(`training/experiments/NOTEBOOK.md`, "Feedback from the SLAM" and "Feedback: the first reports
count more", has the tables that chose the default).

Usage: python -m training.experiments.feedback SEQ [SEQ ...] [--rules sum+,floor,symmetric,both]
       [--rates 0.2,0.3,0.4] [--delays 3,10] [--phases 10] [--first-gains 0.7] [--clips 0.25]
       [--bands 0.05] [--lower 0.15] [--fit NAME,...]
"""
import argparse
import os

import numpy as np

from ..config import DATA_ROOT, MODELS_DIR, NAME
from ..fuse import replay, sequence_data
from ..quantize import metadata

LIMIT = 0.3
RULES = ("sum+", "floor", "symmetric", "both")


def fusion_weights(models):
    """w0..w3 of the model's `leangate.geometry` (`raster-homography-v1: w0, w1, w2, w3`)."""
    meta = metadata(os.path.join(models, f"{NAME}-int8-encoder.onnx"))
    form, rest = meta["leangate.geometry"].split(":", 1)
    return [float(v) for v in rest.split(",")]


def sequence_table(seq, tables, models):
    """(`parent/name`, `fuse.sequence_data`'s horizon-120 table) of a sequence directory with
    depth and poses, cached under `tables`; the scripts that replay the element's gate share it."""
    if not os.path.isfile(os.path.join(seq, "depth.txt")):
        raise SystemExit(f"{seq}: not a sequence with depth and poses")
    name = os.path.basename(os.path.normpath(seq))
    parent = os.path.basename(os.path.dirname(os.path.normpath(seq)))
    return f"{parent}/{name}", sequence_data(seq, os.path.join(tables, f"{parent}_{name}"), models, 120)


def fused(tab, w):
    """The element's utility of every (reference, k) pair: the fusion, or the student alone
    where the prior's chain is lost."""
    s, g = tab["s"], tab["geo"]
    u = np.clip(w[0] + w[1] * g + w[2] * g * g + w[3] * np.clip(s, 0, 1), 0, 1)
    return np.where(np.isfinite(g), u, s)


class Feedback:
    """The consumer's reports and the correction they make (`fuse.replay`'s `correction`): the
    report of a keep at frame i reaches the gate before frame i + 1 + `delay`, as in `leangate
    eval --feedback`, and moves the correction by `rule` (module docstring)."""

    def __init__(self, rule, rate, delay, threshold=0.5, first=0.0, clip=None, band=0.0, lower=LIMIT):
        self.rule, self.rate, self.delay, self.threshold = rule, rate, delay, threshold
        self.first, self.clip, self.band, self.lower = first, clip, band, lower
        self.acc = 0.0
        self.n = 0
        self.pending = []

    def report(self, i, tau):
        self.pending.append((i + 1 + self.delay, tau))

    def offset(self, i):
        while self.pending and self.pending[0][0] <= i:
            error = self.pending.pop(0)[1] - self.threshold
            if self.rule == "both":
                error = min(max(error, -self.clip), self.clip) if self.clip is not None else error
                step = max(self.rate, self.first / (1 + self.n)) * error
            else:
                step = self.rate * error
            self.n += 1
            lo = 0.0 if self.rule == "floor" else -LIMIT
            self.acc = min(max(self.acc + step, lo), LIMIT)
        if self.rule == "both":
            return self.acc if self.acc >= 0 else -min(max(-self.acc - self.band, 0.0), self.lower)
        return max(self.acc, 0.0) if self.rule == "sum+" else self.acc


def outside_band(kept, oracle, phases):
    """Whether a sequence's keep count leaves the issue's band: more than 15 % from the oracle's,
    and more than one keyframe a run from it where the oracle keeps fewer than seven a run."""
    return abs(kept / oracle - 1) > 0.15 and (oracle >= 7 * phases or abs(kept - oracle) > phases)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", nargs="+", help="sequence directories (TUM layout with depth and poses)")
    ap.add_argument("--rules", default=",".join(RULES))
    ap.add_argument("--rates", default="0.2,0.3,0.4")
    ap.add_argument("--delays", default="3,10", help="frames between a keep and its report")
    ap.add_argument("--phases", type=int, default=10, help="start frames per sequence")
    ap.add_argument("--models", default=MODELS_DIR)
    ap.add_argument("--tables", default=os.path.join(DATA_ROOT, "evals", "feedback"))
    ap.add_argument("--first-gains", default="0.7", help="rule both: FIRST values")
    ap.add_argument("--clips", default="0.25", help="rule both: CLIP values (none: no clip)")
    ap.add_argument("--bands", default="0.05", help="rule both: BAND values")
    ap.add_argument("--lower", type=float, default=0.15, help="rule both: LOWER (feedback-lower)")
    ap.add_argument("--fit", default="", help="names (folder names) of the sequences the rule is chosen on")
    a = ap.parse_args()
    rules = [r for r in a.rules.split(",") if r]
    bad = [r for r in rules if r not in RULES]
    if bad:
        raise SystemExit(f"--rules: {', '.join(bad)} unknown (known: {', '.join(RULES)})")
    try:
        rates = [float(x) for x in a.rates.split(",")]
        delays = [int(x) for x in a.delays.split(",")]
        firsts = [float(x) for x in a.first_gains.split(",")]
        clips = [None if x == "none" else float(x) for x in a.clips.split(",")]
        bands = [float(x) for x in a.bands.split(",")]
    except ValueError as e:
        raise SystemExit(f"--rates / --delays / --first-gains / --clips / --bands: {e}")
    fit = {x for x in a.fit.split(",") if x}
    if a.phases < 1:
        raise SystemExit("--phases must be at least 1")
    w = fusion_weights(a.models)
    data = []
    for seq in a.sequences:
        label, tab = sequence_table(seq, a.tables, a.models)
        data.append((label, fused(tab, w), tab["tau"]))

    def row(label, rule, rate, delay, **kw):
        cells, sums = [], {True: [0, 0, 0, []], False: [0, 0, 0, []]}
        for name, u, tau in data:
            n = tau.shape[0]
            k = l = o = 0
            for p in range(a.phases):
                fb = Feedback(rule, rate, delay, **kw) if rule else None
                kk, ll, _, _ = replay(u, tau, 0.5, p, n - 1, fb)
                k, l, o = k + kk, l + ll, o + replay(tau, tau, 0.5, p, n - 1)[0]
            cells.append(f"{name} {k}/{o} ({k / o:.2f}), {l} late")
            t = sums[name.split("/")[-1] in fit]
            t[0], t[1], t[2] = t[0] + k, t[1] + o, t[2] + l
            if outside_band(k, o, a.phases):
                t[3].append(f"{name.split('/')[-1]} {k / o:.2f}")
        parts = [(f"fit", sums[True]), ("held out", sums[False])] if fit else [("sum", sums[False])]
        print(f"{label:<36} " + " | ".join(
            f"{what} {K}/{O} ({K / O:.3f}), {L} late, outside the band: {', '.join(out) or 'none'}"
            for what, (K, O, L, out) in parts if O))
        print("    " + "; ".join(cells))

    row("without feedback", None, 0.0, 0)
    for rule in rules:
        for rate in rates:
            for delay in delays:
                if rule != "both":
                    row(f"{rule} rate {rate} delay {delay}", rule, rate, delay)
                    continue
                for first in firsts:
                    for clip in clips:
                        for band in bands:
                            row(f"both rate {rate} delay {delay} first {first} clip {clip} band {band}",
                                rule, rate, delay, first=first, clip=clip, band=band, lower=a.lower)


if __name__ == "__main__":
    main()
