"""Fine-tune the shipped student's head on teacher-labelled pairs of several real sequences.

The encoder stays as shipped (frozen; its FP32 features are computed once per frame). The head
starts from the shipped weights (read from the ONNX files, `model.load_onnx_weights`) and is trained
*through* the shipped calibration, kept as a fixed last layer, so its output stays in the
teacher's units and the same calibration is baked into the export (`calibrate.bake`): only the
network's ranking of pairs changes.

Data: each sequence's fitting part (`config.FINETUNE_PARTS`: tum_fr1_rpy's train part, which the
student was trained on already, and the `fit` parts of tum_fr1_desk, tum_fr1_xyz and
7scenes_redkitchen_long; `config.ALL_SPLITS`), every frame as the reference against each of its
next `--fit-horizon` frames inside the part, labelled by the exact teacher (`fuse.sequence_data`'s
cached tables), sampled with `fuse.decision_weight` (pairs near tau 0.5 decide the gate), Huber
loss with delta 0.1 as in training, Adam.

Writes a checkpoint (`<out>/finetuned.pt`, `training.export`'s format) and the exported, calibrated
FP32 split and pair models (`<out>/leangate-s*.onnx`). Then `training.quantize --head-only`,
`training.fuse --write` and `leangate eval` (training/README.md). `training.experiments.head_loso` validates the
procedure leave-one-sequence-out.

`--extra SEQ` (repeatable) adds whole sequences to the fitting data, e.g. the near-object orbit scenes
of `leangate synth --motion orbit` (NOTEBOOK: "Near objects: the head fine-tuned on orbit scenes").

Usage: python -m training.experiments.finetune [--out out/train-data/finetune] [--steps 1500] [--lr 1e-4]
       [--extra SEQ ...]
"""
import argparse
import os
import shutil
import subprocess
import sys

import numpy as np

from ..calibrate import bake, encode
from ..config import ALL_SPLITS, DATA_ROOT, FINETUNE_PARTS, MODELS_DIR, NAME, SHARED
from ..fuse import decision_weight, sequence_data
from ..preprocess import load_resized, read_list
from ..quantize import metadata, set_metadata

HORIZON = 120  # the cached teacher tables (fuse.sequence_data) hold every frame's next 120 frames


def need_torch():
    """torch, or an error saying how to install it (only the fine-tuning steps need it)."""
    try:
        import torch
    except ModuleNotFoundError:
        raise SystemExit("this step needs torch: .venv-train/bin/pip install -r training/requirements.txt "
                         "(training/README.md, Setup)")
    return torch


def check_sequence(seq, what="--sequence"):
    """Exit with an error naming `seq` unless it is a sequence folder with depth and poses."""
    if not os.path.isdir(seq):
        raise SystemExit(f"{what} {seq}: no such directory")
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.txt"):
        if not os.path.isfile(os.path.join(seq, name)):
            raise SystemExit(f"{what} {seq}: not a sequence with depth and poses (no {name})")


def calibration(path):
    """(knots, widths, slopes, offset) of the calibration baked into a head (`calibrate.bake`)."""
    import onnx
    from onnx import numpy_helper

    init = {i.name: numpy_helper.to_array(i) for i in onnx.load(path).graph.initializer}
    if "calib_knots" not in init:
        raise SystemExit(f"{path} has no baked calibration (run training.calibrate first)")
    return init["calib_knots"], init["calib_widths"], init["calib_slopes"], float(init["calib_offset"])


class Shipped:
    """The shipped split student in torch: its calibration as a fixed function and fresh copies of
    its full model (encoder + head)."""

    def __init__(self, models):
        import torch

        self.enc_path = os.path.join(models, f"{NAME}-encoder.onnx")
        self.head_path = os.path.join(models, f"{NAME}-head.onnx")
        for p in (self.enc_path, self.head_path):
            if not os.path.exists(p):
                raise SystemExit(f"{p} is missing: give the folder of the calibrated FP32 split student")
        kn, wd, sl, v0 = calibration(self.head_path)
        # every knot (`calibrate.bake`'s form): the baked ones are the segments' starts
        self.knots, self.v0, self.slopes = np.append(kn, kn[-1] + wd[-1]).tolist(), v0, sl
        self._kn, self._wd, self._sl = (torch.from_numpy(np.array(x, np.float32)) for x in (kn, wd, sl))

    def calib(self, u):
        import torch

        return torch.clamp(self.v0 + (torch.clamp(u[:, None] - self._kn, min=0).minimum(self._wd) * self._sl).sum(1), 0, 1)

    def model(self):
        from ..model import LeanGateS, load_onnx_weights

        m = LeanGateS("s16")
        load_onnx_weights(m, self.enc_path, self.head_path)
        return m.eval()


def features(models, seqs):
    """{name: FP32 encoder features [n, 96, 8, 10] as a torch tensor} of every frame of each sequence."""
    import onnxruntime as ort
    import torch

    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    enc = ort.InferenceSession(os.path.join(models, f"{NAME}-encoder.onnx"), so, providers=["CPUExecutionProvider"])
    out = {}
    for name, seq in seqs.items():
        frames = np.stack([load_resized(f) for f in read_list(seq)])
        out[name] = torch.from_numpy(encode(enc, frames).astype(np.float32))
    return out


def training_pairs(tabs, spans, fit_horizon):
    """([k, 3] rows (sequence index, reference j, current i), teacher tau [k]) of every pair inside
    `spans` ({name: (first, last)}) at most `fit_horizon` frames apart; names indexed in `tabs` order."""
    names = list(tabs)
    P, Y = [], []
    for name, (a, b) in spans.items():
        t = tabs[name]["tau"][:, :fit_horizon]
        j, g = np.nonzero(np.isfinite(t))
        i = j + g + 1
        ok = (j >= a) & (i <= b)
        P.append(np.stack([np.full(ok.sum(), names.index(name)), j[ok], i[ok]], 1))
        Y.append(t[j[ok], g[ok]])
    return np.concatenate(P), np.concatenate(Y)


def finetune_head(shipped, feats, tabs, spans, steps, lr, seed=0, fit_horizon=60, log=print):
    """The shipped model with its head fine-tuned on the pairs of `spans` (see the module's doc)."""
    import torch

    model = shipped.model()
    head = model.head
    names = list(tabs)
    P, Y = training_pairs(tabs, spans, fit_horizon)
    if len(P) == 0:
        raise SystemExit("no labelled pair to fine-tune on")
    p = decision_weight(Y)
    p /= p.sum()
    opt = torch.optim.Adam(head.parameters(), lr=lr)
    loss_fn = torch.nn.HuberLoss(delta=0.1)
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    head.train()
    for step in range(steps):
        k = rng.choice(len(P), 64, p=p)
        fr = torch.stack([feats[names[s]][j] for s, j, _ in P[k]])
        fc = torch.stack([feats[names[s]][i] for s, _, i in P[k]])
        loss = loss_fn(shipped.calib(head(fr, fc)), torch.from_numpy(Y[k].astype(np.float32)))
        opt.zero_grad()
        loss.backward()
        opt.step()
        if (step + 1) % 500 == 0:
            log(f"  step {step + 1}: Huber loss {loss.item():.5f}")
    return model.eval()


def load_tables(seqs, models, out):
    return {name: sequence_data(seq, os.path.join(out, name), models, HORIZON) for name, seq in seqs.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=MODELS_DIR, help="the calibrated FP32 split student to start from")
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "finetune"))
    ap.add_argument("--tables", default=os.path.join(DATA_ROOT, "evals", "fuse120"), help="cached teacher tables")
    ap.add_argument("--steps", type=int, default=1500, help="steps of 64 pairs")
    ap.add_argument("--lr", type=float, default=1e-4)
    ap.add_argument("--fit-horizon", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--extra", action="append", default=[], metavar="SEQ",
                    help="a further sequence with depth and poses, fitted on whole (repeatable; e.g. "
                         "`leangate synth --motion orbit` scenes: near objects)")
    a = ap.parse_args()
    seqs = {name: os.path.join(SHARED, name) for name in FINETUNE_PARTS}
    extra = {os.path.basename(os.path.normpath(x)): x for x in a.extra}
    if set(extra) & set(seqs) or len(extra) != len(a.extra):
        raise SystemExit("--extra: each sequence once, and none of the fitting parts' sequences")
    seqs.update(extra)
    for name, seq in seqs.items():
        if not os.path.isdir(seq):
            raise SystemExit(f"{seq} is missing: build it first (training/README.md, the importers)")
        check_sequence(seq, "fine-tuning data")
    torch = need_torch()
    torch.set_num_threads(2)
    shipped = Shipped(a.models)
    tabs = load_tables(seqs, a.models, a.tables)
    feats = features(a.models, seqs)
    spans = {name: ALL_SPLITS[name][part] for name, part in FINETUNE_PARTS.items()}
    spans.update({name: (0, len(read_list(seq)) - 1) for name, seq in extra.items()})
    print("fine-tuning on " + ", ".join(f"{n} {FINETUNE_PARTS.get(n, 'whole')} {a_}-{b}" for n, (a_, b) in spans.items()),
          flush=True)
    model = finetune_head(shipped, feats, tabs, spans, a.steps, a.lr, a.seed, a.fit_horizon,
                          log=lambda m: print(m, flush=True))
    os.makedirs(a.out, exist_ok=True)
    ckpt = os.path.join(a.out, "finetuned.pt")
    torch.save({"model": model.state_dict(), "arch": "s16", "step": a.steps}, ckpt)
    subprocess.run([sys.executable, "-m", "training.export", "--ckpt", ckpt, "--out-dir", a.out], check=True)
    old = metadata(shipped.enc_path)
    note = (f"; head fine-tuned through this calibration for {a.steps} steps on "
            + ", ".join(f"{n} frames {s}-{e}" for n, (s, e) in spans.items()) + " (training.experiments.finetune)")
    meta = {"leangate.threshold": old["leangate.threshold"], "leangate.calibration": old["leangate.calibration"] + note}
    for n in (f"{NAME}.onnx", f"{NAME}-head.onnx"):
        bake(os.path.join(a.out, n), shipped.knots, shipped.v0, shipped.slopes, meta)
    p = os.path.join(a.out, f"{NAME}-encoder.onnx")
    shutil.copyfile(shipped.enc_path, p)  # the encoder is not trained: keep the shipped file's weights exactly
    set_metadata(p, {**metadata(p), **meta})
    # check: the calibrated export against the fine-tuned torch model through the calibration
    import onnxruntime as ort

    names = list(tabs)
    P, _ = training_pairs(tabs, spans, a.fit_horizon)
    k = np.random.default_rng(1).choice(len(P), 256, replace=False)
    fr = np.stack([feats[names[s]][j].numpy() for s, j, _ in P[k]])
    fc = np.stack([feats[names[s]][i].numpy() for s, _, i in P[k]])
    head = ort.InferenceSession(os.path.join(a.out, f"{NAME}-head.onnx"), providers=["CPUExecutionProvider"])
    u = head.run(["utility"], {"reference_features": fr, "current_features": fc})[0]
    with torch.no_grad():
        t = shipped.calib(model.head(torch.from_numpy(fr), torch.from_numpy(fc))).numpy()
    d = float(np.abs(u - t).max())
    print(f"check: |onnx head - torch head through the calibration| = {d:.2e} on 256 training pairs")
    assert d <= 1e-4, d
    print(f"wrote {a.out}: {NAME}.onnx, {NAME}-encoder.onnx, {NAME}-head.onnx (FP32, calibrated); next: "
          f"python -m training.quantize --models {a.out} --out-dir {a.out} --head-only")


if __name__ == "__main__":
    main()
