"""Quantize the calibrated split student to INT8 for the CPU: the student's convolutions (encoder
and head) run in 8-bit integers, everything else in float32.

Static quantization with ONNX Runtime (`quantize_static`, QDQ format): weights int8 per output
channel with reduce_range (7 bits, so that x86 CPUs without VNNI, whose u8*s8 multiply-add
saturates at 16 bits, compute the same result as those with it), activations uint8 with min/max
ranges observed on training data only:
  encoder: --frames frames (tum_fr1_rpy's training part, training synthetic sequences, training
           photos), normalised as the element does;
  head:    the quantized encoder's features of --pairs training pairs (tum_fr1_rpy training pairs and
           synthetic training pairs), so the head is calibrated on what it will receive.
Only Conv nodes are quantized (--ops): the cost volume, the reductions, the small fully connected
refinement and the calibration map stay float32.

`--fuse-relu-only DIR` (measured, not applied to the shipped build): in an existing INT8 build, drop
the QuantizeLinear/DequantizeLinear pair between each Conv and its ReLU where the ReLU's quantizer
has zero point 0, so that ONNX Runtime runs Conv + ReLU as one QLinearConv writing the ReLU's
quantization (instead of QLinearConv, DequantizeLinear, QuantizeLinear: a double rounding). 8 pairs
in the shipped student; about 14 % off the encoder's and 27 % off the head's CPU time, but its keep
decisions move like any other small change of the student (`training/experiments/NOTEBOOK.md`), so it is not the default. Idempotent
(a fused build stays byte for byte); both models are read and fused before either is rewritten, and
a missing or non-ONNX one is an error naming it. Needs onnx alone (`.venv/bin/python` runs it).

Writes <out-dir>/leangate-s-int8-encoder.onnx and leangate-s-int8-head.onnx with the float model's
leangate.* metadata, leangate.head pointing at the int8 head and leangate.precision = int8, then
reports the utility difference to the float student on tum_fr1_rpy's calibration part and
7-Scenes pairs (never used to quantize).

`--head-only` (after `training.experiments.finetune`, whose encoder is the shipped one): the INT8 encoder of
`--int8-encoder` (the shipped build) is copied into --out-dir with the new models' metadata, and only
the head is quantized, its activation ranges observed on that encoder's features of --pairs pairs of
the fine-tuning parts (`config.FINETUNE_PARTS`, real frames read from ../shared/data): the data the
fine-tuned head was trained on. No cache is needed.

Usage: python -m training.quantize [--models models] [--out-dir models] [--head-only]
"""
import argparse
import glob
import os
import tempfile

import numpy as np
import onnx

from .config import ALL_SPLITS, DATA_ROOT, FINETUNE_PARTS, MODELS_DIR, NAME, SHARED
from .preprocess import normalise


def metadata(path):
    return {p.key: p.value for p in onnx.load(path).metadata_props}


def set_metadata(path, meta):
    m = onnx.load(path)
    del m.metadata_props[:]
    for k, v in meta.items():
        m.metadata_props.add(key=k, value=v)
    onnx.checker.check_model(m)
    onnx.save(m, path)


def fuse_relu(m):
    """Drop the QuantizeLinear -> DequantizeLinear pair between a Conv and the ReLU after it when
    the ReLU's output quantizer has zero point 0 (it clamps at 0 itself), so that ONNX Runtime
    fuses DQ -> Conv -> ReLU -> Q into one QLinearConv. Changes the ModelProto `m` in place (a
    fused graph is left as it is); returns the pairs dropped."""
    from onnx import numpy_helper

    g = m.graph
    init = {i.name: i for i in g.initializer}
    prod = {o: n for n in g.node for o in n.output}
    users = {}
    for n in g.node:
        for i in n.input:
            users.setdefault(i, []).append(n)
    drop = []
    for relu in [n for n in g.node if n.op_type == "Relu"]:
        dq = prod.get(relu.input[0])
        q = prod.get(dq.input[0]) if dq is not None and dq.op_type == "DequantizeLinear" else None
        conv = prod.get(q.input[0]) if q is not None and q.op_type == "QuantizeLinear" else None
        after = users.get(relu.output[0], [])
        if conv is None or conv.op_type != "Conv" or len(after) != 1 or after[0].op_type != "QuantizeLinear":
            continue
        if any(len(users.get(t, [])) != 1 for t in (q.input[0], q.output[0], dq.output[0])):
            continue
        zp = after[0].input[2] if len(after[0].input) > 2 else None
        if zp is None or zp not in init:
            continue
        zp = numpy_helper.to_array(init[zp])
        if zp.size != 1 or int(zp.reshape(-1)[0]) != 0:
            continue
        relu.input[0] = q.input[0]
        drop += [q, dq]
    for n in drop:
        g.node.remove(n)
    used = {i for n in g.node for i in n.input} | {o.name for o in g.output}
    keep = [i for i in g.initializer if i.name in used]
    del g.initializer[:]
    g.initializer.extend(keep)
    onnx.checker.check_model(m)
    return len(drop) // 2


FUSED_NOTE = "; Conv+ReLU fused (the Conv output's Q/DQ pair dropped)"


def fuse_relu_build(d):
    """`--fuse-relu-only DIR`: fuse both models of the INT8 build in `d` (idempotent: a fused build
    stays as it is). Both are read, checked and fused before either is rewritten; a missing or
    unreadable model is an error naming it. Returns [(path, pairs dropped)]."""
    if not os.path.isdir(d):
        raise SystemExit(f"--fuse-relu-only {d}: no such folder")
    models = []
    for kind in ("encoder", "head"):
        p = os.path.join(d, f"{NAME}-int8-{kind}.onnx")
        if not os.path.isfile(p):
            raise SystemExit(f"{p} is missing: quantize first")
        try:
            m = onnx.load(p)
            onnx.checker.check_model(m)
        except Exception as e:  # noqa: BLE001 - DecodeError, ValidationError, OSError: not a usable ONNX file
            raise SystemExit(f"{p}: not a readable ONNX model: {str(e).splitlines()[0] if str(e) else type(e).__name__}")
        try:
            n = fuse_relu(m)
        except Exception as e:  # noqa: BLE001 - the rewritten graph failed the checker
            raise SystemExit(f"{p}: cannot fuse: {str(e).splitlines()[0] if str(e) else type(e).__name__}")
        meta = {q.key: q.value for q in m.metadata_props}
        if n and FUSED_NOTE not in meta.get("leangate.quantization", ""):
            meta["leangate.quantization"] = meta.get("leangate.quantization", "") + FUSED_NOTE
        del m.metadata_props[:]
        for k, v in meta.items():
            m.metadata_props.add(key=k, value=v)
        models.append((p, m, n))
    for p, m, _ in models:
        tmp = p + ".partial"
        try:
            onnx.save(m, tmp)
            os.replace(tmp, p)
        except OSError as e:
            raise SystemExit(f"{p}: cannot write it: {e.strerror or e}")
    return [(p, n) for p, _, n in models]


def quantize(src, dst, batches, ops):
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(batches)

        def get_next(self):
            return next(self.it, None)

    with tempfile.TemporaryDirectory() as tmp:
        pre = os.path.join(tmp, "pre.onnx")
        quant_pre_process(src, pre)
        quantize_static(pre, dst, Reader(), quant_format=QuantFormat.QDQ, activation_type=QuantType.QUInt8,
                        weight_type=QuantType.QInt8, per_channel=True, reduce_range=True, op_types_to_quantize=ops)


def int8_encoder_metadata(path):
    """The metadata of the INT8 encoder `--head-only` keeps; a missing file or a build that is not
    INT8 is an error naming it."""
    if not os.path.isfile(path):
        raise SystemExit(f"--int8-encoder {path}: no such file")
    try:
        old = metadata(path)
    except Exception as e:  # not ONNX
        raise SystemExit(f"--int8-encoder {path}: not an ONNX model ({str(e).splitlines()[0][:120]})")
    if old.get("leangate.precision") != "int8" or old.get("leangate.kind") != "encoder":
        raise SystemExit(f"--int8-encoder {path}: not an INT8 encoder (leangate.precision / leangate.kind)")
    for name, part in FINETUNE_PARTS.items():
        if not os.path.isdir(os.path.join(SHARED, name)):
            raise SystemExit(f"{os.path.join(SHARED, name)} is missing: build it first (training/README.md, the importers)")
    return old


def quantize_head_only(a, head_f, enc_q, head_q, meta, old, rng, ops):
    """`--head-only`: keep the INT8 encoder, quantize the head on real fine-tuning pairs."""
    import onnxruntime as ort

    from .preprocess import load_resized, read_list

    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    encq = ort.InferenceSession(a.int8_encoder, so, providers=["CPUExecutionProvider"])
    per = max(1, a.pairs // 16 // len(FINETUNE_PARTS))
    batches = []
    for name, part in FINETUNE_PARTS.items():
        seq = os.path.join(SHARED, name)
        lo, hi = ALL_SPLITS[name][part]
        files = read_list(seq)[lo:hi + 1]
        for _ in range(per):
            j = rng.integers(0, len(files) - 1, 16)
            i = np.minimum(j + rng.integers(1, 61, 16), len(files) - 1)
            idx = np.unique(np.concatenate([i, j]))
            F = dict(zip(idx.tolist(), encq.run(None, {"image": normalise(np.stack([load_resized(files[k]) for k in idx]))})[0]))
            batches.append({"reference_features": np.stack([F[k] for k in j.tolist()]),
                            "current_features": np.stack([F[k] for k in i.tolist()])})
    quantize(head_f, head_q, batches, ops)
    m = onnx.load(a.int8_encoder)
    onnx.save(m, enc_q)
    note = (f"; head: ONNX Runtime static QDQ, {'+'.join(ops)} int8 weights per channel (7-bit range), uint8 "
            f"activations, min/max over {16 * len(batches)} real fine-tuning pairs (quantize --head-only)")
    set_metadata(enc_q, {**old, **{k: v for k, v in meta.items() if k.startswith("leangate.") and k not in
                                   ("leangate.precision", "leangate.head", "leangate.quantization", "leangate.kind")},
                         "leangate.quantization": old.get("leangate.quantization", "") + note})
    set_metadata(head_q, {**metadata(head_f), "leangate.precision": "int8",
                          "leangate.quantization": old.get("leangate.quantization", "") + note})
    # the quantized head against the float one on the same (quantized) features
    hf, hq = (ort.InferenceSession(p, so, providers=["CPUExecutionProvider"]) for p in (head_f, head_q))
    d = np.abs(np.concatenate([hq.run(None, b)[0].reshape(-1) - hf.run(None, b)[0].reshape(-1) for b in batches]))
    print(f"head int8 - fp32 on those {len(d)} pairs: mean {d.mean():.4f}, p99 {np.quantile(d, 0.99):.4f}, max {d.max():.4f}")
    for p in (enc_q, head_q):
        print(f"{p}: {os.path.getsize(p) / 1e6:.2f} MB")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=MODELS_DIR, help="directory of the calibrated float leangate-s-*.onnx")
    ap.add_argument("--out-dir", default=MODELS_DIR)
    ap.add_argument("--data", default=os.path.join(DATA_ROOT, "cache"))
    ap.add_argument("--frames", type=int, default=256)
    ap.add_argument("--pairs", type=int, default=512)
    ap.add_argument("--ops", default="Conv")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--head-only", action="store_true",
                    help="keep the INT8 encoder of --int8-encoder and quantize the head alone, on real fine-tuning pairs")
    ap.add_argument("--int8-encoder", default=os.path.join(MODELS_DIR, f"{NAME}-int8-encoder.onnx"),
                    help="with --head-only: the INT8 encoder to keep (default: the shipped one)")
    ap.add_argument("--fuse-relu-only", metavar="DIR",
                    help="only apply the Conv+ReLU fusion to the INT8 build in DIR, in place "
                         "(give a copy's directory: the shipped build is not fused)")
    a = ap.parse_args()
    if a.fuse_relu_only:  # onnx alone: .venv's python runs it
        for p, n in fuse_relu_build(a.fuse_relu_only):
            print(f"{p}: {n} Q/DQ pairs dropped")
        return
    rng = np.random.default_rng(a.seed)
    ops = a.ops.split(",")
    enc_f = os.path.join(a.models, f"{NAME}-encoder.onnx")
    head_f = os.path.join(a.models, f"{NAME}-head.onnx")
    enc_q = os.path.join(a.out_dir, f"{NAME}-int8-encoder.onnx")
    head_q = os.path.join(a.out_dir, f"{NAME}-int8-head.onnx")
    for p in (enc_f, head_f):
        if not os.path.exists(p):
            raise SystemExit(f"{p}: no such file (--models: the folder of the calibrated FP32 split student)")
    meta = metadata(enc_f)
    if "leangate.calibration" not in meta:
        raise SystemExit(f"{enc_f} is not calibrated: quantize the calibrated student")
    if meta.get("leangate.precision", "fp32") != "fp32":
        raise SystemExit(f"{enc_f} is already quantized")
    if a.head_only:
        old = int8_encoder_metadata(a.int8_encoder)  # checked before anything is written
        os.makedirs(a.out_dir, exist_ok=True)
        return quantize_head_only(a, head_f, enc_q, head_q, meta, old, rng, ops)
    import onnxruntime as ort

    os.makedirs(a.out_dir, exist_ok=True)

    # training data only: tum_fr1_rpy's training part, synthetic training sequences, training photos
    tum = np.load(os.path.join(a.data, "tum_train.npz"))
    synth = [np.load(f) for f in sorted(glob.glob(os.path.join(a.data, "train", "*.npz")))]
    homog = np.load(os.path.join(a.data, "homog_train.npz"))["ref"]
    n_t, n_h = a.frames * 3 // 8, a.frames // 4
    n_s = a.frames - n_t - n_h
    picks = [tum["frames"][rng.choice(len(tum["frames"]), n_t, replace=False)], homog[rng.choice(len(homog), n_h, replace=False)]]
    for k in rng.choice(len(synth), n_s):
        fr = synth[k]["frames"]
        picks.append(fr[rng.integers(len(fr))][None])
    frames = normalise(np.concatenate(picks))
    quantize(enc_f, enc_q, [{"image": frames[k:k + 16]} for k in range(0, len(frames), 16)], ops)

    so = ort.SessionOptions()
    so.intra_op_num_threads = 2
    sess = lambda p: ort.InferenceSession(p, so, providers=["CPUExecutionProvider"])
    encq = sess(enc_q)
    feats = lambda fr: np.concatenate([encq.run(None, {"image": normalise(fr[k:k + 64])})[0] for k in range(0, len(fr), 64)])
    batches = []
    Ft = feats(tum["frames"])
    P = tum["pairs"][rng.choice(len(tum["pairs"]), a.pairs // 2, replace=False)]
    cur, ref = P[:, 0].astype(int), P[:, 1].astype(int)
    for k in range(0, len(P), 16):
        batches.append({"reference_features": Ft[ref[k:k + 16]], "current_features": Ft[cur[k:k + 16]]})
    for k in rng.choice(len(synth), (a.pairs - a.pairs // 2) // 16):
        d = synth[k]
        P = d["pairs"][rng.choice(len(d["pairs"]), 16, replace=False)]
        idx = np.unique(np.concatenate([P[:, 0], P[:, 1]]).astype(int))
        Fs = dict(zip(idx, feats(d["frames"][idx])))
        batches.append({"reference_features": np.stack([Fs[int(j)] for j in P[:, 1]]),
                        "current_features": np.stack([Fs[int(i)] for i in P[:, 0]])})
    quantize(head_f, head_q, batches, ops)

    qmeta = {**meta, "leangate.precision": "int8", "leangate.head": os.path.basename(head_q),
             "leangate.quantization": (f"ONNX Runtime static QDQ: {'+'.join(ops)} int8 weights per channel (7-bit range), "
                                       f"uint8 activations, min/max over {len(frames)} training frames and "
                                       f"{sum(len(b['current_features']) for b in batches)} training pairs")}
    set_metadata(enc_q, {**qmeta, "leangate.kind": "encoder"})
    hmeta = metadata(head_f)
    set_metadata(head_q, {**hmeta, "leangate.precision": "int8", "leangate.quantization": qmeta["leangate.quantization"]})

    # against the float student, on pairs never used above
    from .compare import pair_set
    from .config import SHARED
    encf, headf, encq2, headq = sess(enc_f), sess(head_f), sess(enc_q), sess(head_q)
    for name, seq in (("tum cal", os.path.join(DATA_ROOT, "tum", "cal")),
                      ("7scenes", os.path.join(SHARED, "7scenes_redkitchen_dev"))):
        if not os.path.exists(seq):
            continue
        fr, P = pair_set(os.path.join(DATA_ROOT, "evals", "compare"), name.replace(" ", "_"), seq, 24)
        x = normalise(fr)
        u = {}
        for tag, e, h in (("fp32", encf, headf), ("int8", encq2, headq)):
            F = np.concatenate([e.run(None, {"image": x[k:k + 64]})[0] for k in range(0, len(x), 64)])
            u[tag] = np.concatenate([h.run(None, {"reference_features": F[P[k:k + 256, 1].astype(int)],
                                                  "current_features": F[P[k:k + 256, 0].astype(int)]})[0].reshape(-1)
                                     for k in range(0, len(P), 256)])
        d = np.abs(u["int8"] - u["fp32"])
        t = P[:, 2]
        rm = lambda v: float(np.sqrt(np.mean((v - t) ** 2)))
        print(f"{name}, {len(t)} pairs: |int8 - fp32| mean {d.mean():.4f}, p99 {np.quantile(d, 0.99):.4f}, max {d.max():.4f}; "
              f"RMSE to the teacher fp32 {rm(u['fp32']):.4f}, int8 {rm(u['int8']):.4f}")
    for p in (enc_q, head_q):
        print(f"{p}: {os.path.getsize(p) / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
