"""Merge calibrated students into one ensemble model with the same ONNX contract.

Each member is a directory of calibrated `leangate-s*.onnx` (export + calibrate). The ensemble is
one split model and one pair model, so the element, `leangate eval` and every other consumer treat
it as a single student:

  encoder  image -> features: the members' encoders side by side, features concatenated along the
           channels ([N, 96 * members, 8, 10] for s16 members)
  head     reference_features, current_features -> utility: the features split back per member,
           each member's head (with its own calibration) on its part, utilities averaged (Mean)
  pair     reference, current -> utility: each member's pair model, utilities averaged

Each member is calibrated on its own before the merge (measured: averaging calibrated members fits
the teacher better than calibrating the average of the raw outputs, whose scales differ per member).
Metadata: the first member's, with `leangate.calibration` listing every member's map,
`leangate.members`, and the parameter and FLOP counts summed.
Checks with ONNX Runtime: head(encoder) == pair, and both == the mean of the members.

Usage: python -m training.experiments.ensemble --members DIR,DIR[,...] --out-dir DIR
"""
import argparse
import os

import numpy as np
import onnx
from onnx import helper, numpy_helper

from ..config import IN_H, IN_W, NAME

PARTS = {
    "encoder": (f"{NAME}-encoder.onnx", ["image"], "features"),
    "head": (f"{NAME}-head.onnx", ["reference_features", "current_features"], "utility"),
    "pair": (f"{NAME}.onnx", ["reference", "current"], "utility"),
}


def meta_of(m):
    return {p.key: p.value for p in m.metadata_props}


def channels(enc_model):
    out = enc_model.graph.output[0].type.tensor_type.shape.dim
    return int(out[1].dim_value)


def merge(models, part, ch):
    """One graph running every member's `part` graph on the shared inputs."""
    _, inputs, output = PARTS[part]
    nodes, inits, first = [], [], models[0].graph
    outs = []
    for k, m in enumerate(models):
        m = onnx.compose.add_prefix(m, f"m{k}_")
        g = m.graph
        inits.extend(g.initializer)
        nodes.extend(g.node)
        outs.append(f"m{k}_{output}")
    head_nodes = []
    if part == "head":
        # split each shared input back into the members' channels
        split = numpy_helper.from_array(np.asarray(ch, np.int64), "ens_split")
        inits.append(split)
        for name in inputs:
            head_nodes.append(helper.make_node("Split", [name, "ens_split"], [f"m{k}_{name}" for k in range(len(models))],
                                               axis=1, name=f"ens_split_{name}"))
    else:
        for k in range(len(models)):
            for name in inputs:
                head_nodes.append(helper.make_node("Identity", [name], [f"m{k}_{name}"], name=f"ens_in_{k}_{name}"))
    if part == "encoder":
        tail = [helper.make_node("Concat", outs, [output], axis=1, name="ens_concat")]
    else:
        tail = [helper.make_node("Mean", outs, [output], name="ens_mean")]
    g_in = [onnx.ValueInfoProto() for _ in first.input]
    for v, src in zip(g_in, first.input):
        v.CopyFrom(src)
    out = onnx.ValueInfoProto()
    out.CopyFrom(first.output[0])
    if part == "encoder":
        out.type.tensor_type.shape.dim[1].dim_value = sum(ch)
    if part == "head":
        for v in g_in:
            v.type.tensor_type.shape.dim[1].dim_value = sum(ch)
    graph = helper.make_graph(head_nodes + nodes + tail, f"{first.name}_ensemble", g_in, [out], inits)
    merged = helper.make_model(graph, opset_imports=models[0].opset_import, ir_version=models[0].ir_version)
    return merged


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--members", required=True, help="comma-separated directories of calibrated students")
    ap.add_argument("--out-dir", required=True)
    a = ap.parse_args()
    dirs = a.members.split(",")
    if len(dirs) < 2:
        raise SystemExit("an ensemble needs at least two members")
    encs = [onnx.load(os.path.join(d, PARTS["encoder"][0])) for d in dirs]
    metas = [meta_of(m) for m in encs]
    for d, mt in zip(dirs, metas):
        if "leangate.calibration" not in mt:
            raise SystemExit(f"{d} is not calibrated (no leangate.calibration): run training.calibrate on it first")
        for key in ("leangate.input_size", "leangate.resize", "leangate.mean", "leangate.std", "leangate.threshold"):
            if mt.get(key) != metas[0].get(key):
                raise SystemExit(f"members differ in {key}: {metas[0].get(key)!r} vs {mt.get(key)!r} ({d})")
    ch = [channels(m) for m in encs]
    meta = dict(metas[0])
    meta["leangate.members"] = str(len(dirs))
    meta["leangate.calibration"] = (f"mean of {len(dirs)} students, each calibrated on its own: " + "; ".join(
        f"student {k + 1}: {mt['leangate.calibration']}" for k, mt in enumerate(metas)))
    for key in ("leangate.params",):
        meta[key] = str(sum(int(mt.get(key, 0)) for mt in metas))
    meta["leangate.gflops_per_frame"] = f"{sum(float(mt.get('leangate.gflops_per_frame', 0)) for mt in metas):.4f}"
    meta["leangate.checkpoint_step"] = ",".join(mt.get("leangate.checkpoint_step", "") for mt in metas)
    os.makedirs(a.out_dir, exist_ok=True)
    for part, (fname, _, _) in PARTS.items():
        models = [onnx.load(os.path.join(d, fname)) for d in dirs]
        m = merge(models, part, ch)
        own = meta_of(models[0])
        for k, v in {**meta, "leangate.kind": own["leangate.kind"]}.items():
            own[k] = v
        if part == "encoder":
            own["leangate.head"] = os.path.basename(PARTS["head"][0])
        for k, v in own.items():
            m.metadata_props.add(key=k, value=v)
        onnx.checker.check_model(m, full_check=True)
        onnx.save(m, os.path.join(a.out_dir, fname))

    import onnxruntime as ort
    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    mk = lambda d, f: ort.InferenceSession(os.path.join(d, f), so, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    r = rng.standard_normal((5, 3, IN_H, IN_W)).astype(np.float32)
    c = np.roll(r, 11, axis=3)
    def run(d):
        e, h, p = (mk(d, PARTS[k][0]) for k in ("encoder", "head", "pair"))
        fr, fc = e.run(None, {"image": r})[0], e.run(None, {"image": c})[0]
        return (h.run(None, {"reference_features": fr, "current_features": fc})[0],
                p.run(None, {"reference": r, "current": c})[0], fr.shape)
    us, up, shape = run(a.out_dir)
    mean = np.mean([run(d)[1] for d in dirs], 0)
    d1, d2 = np.abs(us - up).max(), np.abs(up - mean).max()
    print(f"{len(dirs)} members, features {shape}: |split - pair| = {d1:.2e}, |pair - mean of members| = {d2:.2e}")
    assert us.shape == (5,) and d1 <= 1e-5 and d2 <= 1e-5
    for f in (PARTS[k][0] for k in PARTS):
        print(f"{f}: {os.path.getsize(os.path.join(a.out_dir, f)) / 1e6:.2f} MB")
    print(f"params {meta['leangate.params']}, GFLOPs per scored frame {meta['leangate.gflops_per_frame']}")


if __name__ == "__main__":
    main()
