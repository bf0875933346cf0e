"""Export a LeanGate-S checkpoint to ONNX (opset 17, IR version 8), with the leangate.* metadata.

Writes three files into --out-dir (default: models/ of the repository):
  leangate-s.onnx          pair model: reference, current [N,3,120,160] -> utility [N]
  leangate-s-encoder.onnx  image [N,3,120,160] -> features [N,96,8,10]
  leangate-s-head.onnx     reference_features, current_features -> utility [N]
and checks with ONNX Runtime that head(encoder(ref), encoder(cur)) == pair(ref, cur) (1e-5) and
that the pair model matches PyTorch. The exported utility is the raw (uncalibrated) sigmoid;
`python -m training.calibrate` then bakes the calibration in and sets leangate.threshold = 0.5.
Export to a scratch directory, not straight over the shipped models/.

Usage: python -m training.export --ckpt out/train-data/runs/s/best.pt --out-dir out/train-data/export
"""
import argparse
import os

import numpy as np
import onnx
import torch
import torch.nn as nn

from .config import DEFAULT_THRESHOLD, IN_H, IN_W, MEAN, MODELS_DIR, NAME, REPO, RESIZE, STD
from .model import LeanGateS, PairWrapper, count_flops


class HeadWrapper(nn.Module):
    def __init__(self, m):
        super().__init__()
        self.m = m

    def forward(self, reference_features, current_features):
        return self.m.head(reference_features, current_features)


def _export(module, args, path, in_names, out_names):
    dyn = {n: {0: "N"} for n in in_names + out_names}
    try:
        torch.onnx.export(module, args, path, input_names=in_names, output_names=out_names,
                          dynamic_axes=dyn, opset_version=17, do_constant_folding=True, dynamo=False)
    except (TypeError, RuntimeError, AttributeError) as e:  # the TorchScript exporter may be gone
        print(f"TorchScript exporter failed ({e}); using the dynamo exporter", flush=True)
        shapes = tuple({0: torch.export.Dim("N", min=1, max=4096)} for _ in in_names)
        prog = torch.onnx.export(module, args, input_names=in_names, output_names=out_names,
                                 dynamic_shapes=shapes, opset_version=17, dynamo=True, external_data=False)
        prog.save(path)


def set_meta(path, meta):
    m = onnx.load(path)
    if m.ir_version > 10:
        m.ir_version = 8
    keep = [p for p in m.metadata_props if p.key not in meta]
    del m.metadata_props[:]
    m.metadata_props.extend(keep)
    for k, v in meta.items():
        m.metadata_props.add(key=k, value=str(v))
    onnx.checker.check_model(m)
    onnx.save(m, path)


def base_meta(threshold):
    return {
        "leangate.input_size": f"{IN_W}x{IN_H}",
        "leangate.resize": RESIZE,
        "leangate.mean": ",".join(f"{v}" for v in MEAN),
        "leangate.std": ",".join(f"{v}" for v in STD),
        "leangate.threshold": f"{threshold:.3f}",
        "leangate.name": NAME,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", required=True)
    ap.add_argument("--out-dir", default=MODELS_DIR)
    ap.add_argument("--threshold", type=float, default=DEFAULT_THRESHOLD)
    a = ap.parse_args()
    torch.set_num_threads(2)
    os.makedirs(a.out_dir, exist_ok=True)
    ck = torch.load(a.ckpt, map_location="cpu")
    model = LeanGateS.from_checkpoint(ck)
    model.eval()
    pair_p = os.path.join(a.out_dir, f"{NAME}.onnx")
    enc_p = os.path.join(a.out_dir, f"{NAME}-encoder.onnx")
    head_p = os.path.join(a.out_dir, f"{NAME}-head.onnx")

    x = torch.rand(2, 3, IN_H, IN_W)
    with torch.no_grad():
        f = model.encoder(x)
    _export(PairWrapper(model), (x, x.flip(0)), pair_p, ["reference", "current"], ["utility"])
    _export(model.encoder, (x,), enc_p, ["image"], ["features"])
    _export(HeadWrapper(model), (f, f.flip(0)), head_p, ["reference_features", "current_features"], ["utility"])

    meta = base_meta(a.threshold)
    fl = count_flops(model)
    params = sum(p.numel() for p in model.parameters())
    extra = {"leangate.gflops_per_frame": f"{(fl['encoder'] + fl['head']) / 1e9:.4f}",
             "leangate.params": str(params), "leangate.checkpoint_step": str(ck.get("step", ""))}
    set_meta(pair_p, {**meta, **extra, "leangate.kind": "pair"})
    set_meta(enc_p, {**meta, **extra, "leangate.kind": "encoder", "leangate.head": os.path.basename(head_p)})
    set_meta(head_p, {**meta, **extra, "leangate.kind": "head"})

    # verification with ONNX Runtime
    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    pair = ort.InferenceSession(pair_p, so, providers=["CPUExecutionProvider"])
    enc = ort.InferenceSession(enc_p, so, providers=["CPUExecutionProvider"])
    head = ort.InferenceSession(head_p, so, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    for n in (1, 3, 7):
        r = ((rng.random((n, 3, IN_H, IN_W), dtype=np.float32) - np.array(MEAN, np.float32)[:, None, None])
             / np.array(STD, np.float32)[:, None, None]).astype(np.float32)
        c = np.roll(r, 9, axis=3) if n > 1 else r[:, :, ::-1].copy()
        up = pair.run(["utility"], {"reference": r, "current": c})[0]
        fr = enc.run(["features"], {"image": r})[0]
        fc = enc.run(["features"], {"image": c})[0]
        us = head.run(["utility"], {"reference_features": fr, "current_features": fc})[0]
        with torch.no_grad():
            ut = model(torch.from_numpy(r), torch.from_numpy(c)).numpy()
        assert up.shape == (n,), up.shape
        d_split = np.abs(up - us).max()
        d_torch = np.abs(up - ut).max()
        print(f"N={n}: |pair - split| = {d_split:.2e}, |pair - torch| = {d_torch:.2e}")
        assert d_split <= 1e-5, d_split
        assert d_torch <= 1e-4, d_torch
    for p in (pair_p, enc_p, head_p):
        m = onnx.load(p)
        print(f"{os.path.relpath(p, REPO)}: {os.path.getsize(p) / 1e6:.2f} MB, IR {m.ir_version}, opset "
              f"{[o.version for o in m.opset_import]}, kind {dict((q.key, q.value) for q in m.metadata_props)['leangate.kind']}")
    print(f"params {params}, GFLOPs per scored frame: encoder {fl['encoder'] / 1e9:.4f} + head {fl['head'] / 1e9:.4f}"
          f" = {(fl['encoder'] + fl['head']) / 1e9:.4f}")


if __name__ == "__main__":
    main()
