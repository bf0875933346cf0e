#!/usr/bin/env python3
"""Train LeanGate-S on the cached pairs made by gen_data.py.

Huber loss (delta 0.1) on tau, supervising every refinement iteration (weights 0.8^(K-k)), AdamW,
linear warm-up then cosine decay driven by wall-clock time (--minutes), so a run ends on time.
Tau-balanced sampling of synthetic pairs (inverse bin frequency), mixed with real-photo homography
pairs; photometric / grey / flip augmentation. Validation on held-out synthetic sequences (other
seeds) and held-out photos every --val-every steps; checkpoints <out>/last.pt and <out>/best.pt,
log <out>/log.csv.

Replayed pairs (--p-replay): synthetic scenes seen along real camera trajectories with sensor realism
(cache/replay, `gen_data --steps replay`), drawn with inverse tau-bin frequency like the synthetic ones.

Real pairs: tum_fr1_rpy's training part (cache/tum_train.npz, teacher labels) are a fixed share of
each batch (--p-real), and "unrelated" pairs (reference and current from two different sequences:
a complete view change, tau = 1) another (--p-unrelated), the case where the first student
saturated near 0.5. Model selection adds the RMSE on tum_fr1_rpy's calibration part
(cache/tum_cal.npz, gate-like pairs); its test part is never read here.

Start: from scratch, from a checkpoint (--init ckpt.pt), or from exported ONNX weights
(--init-onnx models/leangate-s-encoder.onnx; BatchNorms folded, so they stay frozen).
--resume continues <out>/last.pt (weights, optimiser, step, elapsed time) after an interruption.

Usage: python -m training.train [--data $DATA_ROOT/cache] [--out $DATA_ROOT/runs/s]
                                [--minutes 45] [--batch 32] [--lr 2e-3] [--resume]
"""
import argparse
import glob
import math
import os
import time

import numpy as np
import torch
import torch.nn.functional as F

from .config import DATA_ROOT, MEAN, STD
from .model import ARCHS, LeanGateS, count_flops, freeze_bn, load_onnx_weights

MEAN_T = torch.tensor(MEAN).view(1, 3, 1, 1)
STD_T = torch.tensor(STD).view(1, 3, 1, 1)


class SynthPool:
    def __init__(self, files):
        self.frames, pairs = [], []
        for k, f in enumerate(sorted(files)):
            d = np.load(f)
            self.frames.append(d["frames"])
            p = d["pairs"]
            pairs.append(np.concatenate([np.full((len(p), 1), k, np.float32), p], 1))
        self.pairs = np.concatenate(pairs)  # seq, i, j, tau, f_m, f_u
        tau = self.pairs[:, 3]
        bins = np.clip((tau * 10).astype(int), 0, 9)
        cnt = np.bincount(bins, minlength=10).astype(np.float64)
        w = 1.0 / np.maximum(cnt[bins], 1)
        self.p = w / w.sum()

    def sample(self, rng, n, balanced=True):
        idx = rng.choice(len(self.pairs), n, p=self.p if balanced else None)
        return self.get(idx)

    def get(self, idx):
        P = self.pairs[idx]
        ref = np.stack([self.frames[int(s)][int(j)] for s, j in zip(P[:, 0], P[:, 2])])
        cur = np.stack([self.frames[int(s)][int(i)] for s, i in zip(P[:, 0], P[:, 1])])
        return ref, cur, P[:, 3].copy()

    def unrelated(self, rng, n, other=None):
        """Reference from one sequence, current from another (of `other` if given): tau = 1."""
        other = other or self
        ref, cur = [], []
        while len(ref) < n:
            a, b = rng.integers(len(self.frames)), rng.integers(len(other.frames))
            if other is self and a == b:
                continue
            ref.append(self.frames[a][rng.integers(len(self.frames[a]))])
            cur.append(other.frames[b][rng.integers(len(other.frames[b]))])
        if rng.random() < 0.5:
            ref, cur = cur, ref
        return np.stack(ref), np.stack(cur), np.ones(n, np.float32)

    def identical(self, rng, n):
        s = rng.integers(len(self.frames), size=n)
        i = [rng.integers(len(self.frames[k])) for k in s]
        im = np.stack([self.frames[k][j] for k, j in zip(s, i)])
        return im, im.copy(), np.zeros(n, np.float32)


class HomogPool:
    def __init__(self, f):
        d = np.load(f)
        self.ref, self.cur, self.y = d["ref"], d["cur"], d["y"]

    def sample(self, rng, n):
        idx = rng.integers(len(self.y), size=n)
        return self.ref[idx], self.cur[idx], self.y[idx, 0].copy()


def to_tensor(a):
    return torch.from_numpy(a).permute(0, 3, 1, 2).float().div_(255.0)


def photometric(x, g):
    """x: [B,3,H,W] in [0,1]; independent jitter per image."""
    b = x.shape[0]
    gain = torch.exp(torch.randn(b, 1, 1, 1, generator=g) * 0.15)
    cgain = torch.exp(torch.randn(b, 3, 1, 1, generator=g) * 0.04)
    gamma = torch.exp(torch.randn(b, 1, 1, 1, generator=g) * 0.15)
    x = (x.clamp(1e-4, 1) ** gamma) * gain * cgain
    m = x.mean(dim=(1, 2, 3), keepdim=True)
    contrast = torch.exp(torch.randn(b, 1, 1, 1, generator=g) * 0.12)
    x = (x - m) * contrast + m
    sigma = torch.rand(b, 1, 1, 1, generator=g) * 0.025
    x = x + torch.randn(x.shape, generator=g) * sigma
    return x.clamp(0, 1)


def make_batch(rng, g, synth, homog, n, p_homog=0.35, p_ident=0.04, augment=True, real=None, p_real=0.0,
               p_unrel=0.0, replay=None, p_replay=0.0, homog2=None, p_homog2=0.0):
    nh = int(round(n * p_homog))
    nh2 = int(round(n * p_homog2)) if homog2 is not None else 0
    ni = int(round(n * p_ident))
    nr = int(round(n * p_real)) if real is not None else 0
    nrp = int(round(n * p_replay)) if replay is not None else 0
    nu = int(round(n * p_unrel))
    ns = n - nh - nh2 - ni - nr - nrp - nu
    if ns < 0:
        raise ValueError("the fractions --p-homog, --p-homog-extra, --p-real, --p-replay and --p-unrelated add up "
                         "to more than 1")
    parts = [synth.sample(rng, ns), homog.sample(rng, nh), synth.identical(rng, ni)]
    if nh2:
        parts.append(homog2.sample(rng, nh2))
    if nr:
        parts.append(real.sample(rng, nr))
    if nrp:
        parts.append(replay.sample(rng, nrp))
    if nu:
        # half across synthetic sequences, half between a real frame and a synthetic one
        nu1 = nu // 2
        if nu1:
            parts.append(synth.unrelated(rng, nu1))
        parts.append((real or synth).unrelated(rng, nu - nu1, synth))
    ref = to_tensor(np.concatenate([p[0] for p in parts]))
    cur = to_tensor(np.concatenate([p[1] for p in parts]))
    y = torch.from_numpy(np.concatenate([p[2] for p in parts])).float()
    if augment:
        flip = torch.rand(n, generator=g) < 0.5
        ref[flip] = ref[flip].flip(3)
        cur[flip] = cur[flip].flip(3)
        ref, cur = photometric(ref, g), photometric(cur, g)
        grey = torch.rand(n, generator=g) < 0.08
        ref[grey] = ref[grey].mean(1, keepdim=True).expand(-1, 3, -1, -1)
        cur[grey] = cur[grey].mean(1, keepdim=True).expand(-1, 3, -1, -1)
    return (ref - MEAN_T) / STD_T, (cur - MEAN_T) / STD_T, y


def huber(pred, y, delta=0.1, w=None):
    if w is None:
        return F.huber_loss(pred, y, delta=delta)
    return (F.huber_loss(pred, y, delta=delta, reduction="none") * w).sum() / w.sum()


def decision_weights(y, strength, width=0.15):
    """1 + strength * exp(-((tau - 0.5) / width)^2): pairs near the paper's tau_keep weigh more."""
    return 1.0 + strength * torch.exp(-((y - 0.5) / width) ** 2)


@torch.no_grad()
def evaluate(model, sets, bs=128):
    model.eval()
    res = {}
    for name, (ref, cur, y) in sets.items():
        preds = []
        for k in range(0, len(y), bs):
            r = (to_tensor(ref[k:k + bs]) - MEAN_T) / STD_T
            c = (to_tensor(cur[k:k + bs]) - MEAN_T) / STD_T
            preds.append(model(r, c))
        p = torch.cat(preds)
        t = torch.from_numpy(y).float()
        res[name] = dict(huber=huber(p, t).item(), rmse=((p - t) ** 2).mean().sqrt().item(),
                         mae=(p - t).abs().mean().item())
    model.train()
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=os.path.join(DATA_ROOT, "cache"))
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "runs", "s"))
    ap.add_argument("--minutes", type=float, default=45)
    ap.add_argument("--stop-minutes", type=float, default=None,
                    help="end the run after this many minutes of the --minutes schedule (the learning rate "
                         "follows the --minutes cosine); --resume continues it later")
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--wd", type=float, default=1e-4)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--val-every", type=int, default=250)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--arch", default="s16", choices=ARCHS,
                    help="s16: 8x10 feature grid (the shipped model); s8: 15x20 grid, 64 channels")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--init", default="", help="checkpoint to start from")
    ap.add_argument("--init-onnx", default="", help="encoder .onnx (its head beside it) to start from")
    ap.add_argument("--resume", action="store_true", help="continue <out>/last.pt")
    ap.add_argument("--p-homog", type=float, default=0.35, help="fraction of real-photo homography pairs")
    ap.add_argument("--p-real", type=float, default=0.0, help="fraction of real tum_fr1_rpy training pairs")
    ap.add_argument("--p-replay", type=float, default=0.0,
                    help="fraction of replayed-trajectory synthetic pairs with sensor realism (cache/replay)")
    ap.add_argument("--p-unrelated", type=float, default=0.0, help="fraction of unrelated pairs (tau = 1)")
    ap.add_argument("--homog-extra", default="",
                    help="a second homography cache relative to --data (e.g. homog_tum.npz from "
                         "`gen_data --steps tumhomog`), drawn for --p-homog-extra of each batch")
    ap.add_argument("--p-homog-extra", type=float, default=0.0)
    ap.add_argument("--decision-weight", type=float, default=0.0,
                    help="weigh each pair's loss by 1 + W * exp(-((tau - 0.5) / 0.15)^2) (0: plain mean)")
    ap.add_argument("--replay-glob", default="replay/*.npz",
                    help="which cached replayed sequences (--p-replay) to draw from, relative to --data "
                         "(replay/seq_20*.npz: the real trajectories only, without the added-roll ones)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    torch.manual_seed(a.seed)
    rng = np.random.default_rng(a.seed)
    g = torch.Generator().manual_seed(a.seed)
    os.makedirs(a.out, exist_ok=True)

    synth = SynthPool(glob.glob(os.path.join(a.data, "train", "*.npz")))
    homog = HomogPool(os.path.join(a.data, "homog_train.npz"))
    vsynth = SynthPool(glob.glob(os.path.join(a.data, "val", "*.npz")))
    vrng = np.random.default_rng(123)
    vidx = vrng.choice(len(vsynth.pairs), min(2000, len(vsynth.pairs)), replace=False)
    vhom = HomogPool(os.path.join(a.data, "homog_val.npz"))
    sets = {"val_synth": vsynth.get(vidx), "val_homog": (vhom.ref, vhom.cur, vhom.y[:, 0])}
    real = None
    if a.p_real > 0:
        real = SynthPool([os.path.join(a.data, "tum_train.npz")])
        print(f"real: {len(real.pairs)} tum_fr1_rpy training pairs", flush=True)
    replay = None
    if a.p_replay > 0:
        replay = SynthPool(glob.glob(os.path.join(a.data, a.replay_glob)))
        print(f"replay: {len(replay.pairs)} pairs in {len(replay.frames)} replayed-trajectory sequences", flush=True)
    homog2 = None
    if a.p_homog_extra > 0:
        if not a.homog_extra:
            raise SystemExit("--p-homog-extra needs --homog-extra FILE (e.g. homog_tum.npz)")
        homog2 = HomogPool(os.path.join(a.data, a.homog_extra))
        print(f"extra homographies: {len(homog2.y)} pairs from {a.homog_extra}", flush=True)
    cal_f = os.path.join(a.data, "tum_cal.npz")
    if os.path.exists(cal_f):
        cal = SynthPool([cal_f])
        sets["val_real"] = cal.get(np.sort(vrng.choice(len(cal.pairs), min(1500, len(cal.pairs)), replace=False)))
    print(f"train: {len(synth.pairs)} synthetic pairs in {len(synth.frames)} sequences, {len(homog.y)} "
          f"homography pairs; val: {len(vidx)} synthetic pairs ({len(vsynth.frames)} sequences), "
          f"{len(vhom.y)} homography pairs", flush=True)

    model = LeanGateS(a.arch)
    frozen_bn = False
    if a.init:
        ck0 = torch.load(a.init)
        model.load_state_dict(ck0["model"])
        frozen_bn = ck0.get("frozen_bn", False)
    elif a.init_onnx:
        head_onnx = a.init_onnx.replace("-encoder.onnx", "-head.onnx")
        load_onnx_weights(model, a.init_onnx, head_onnx)
        frozen_bn = True
        print(f"initialised from {a.init_onnx} + {head_onnx} (BatchNorm folded: frozen)", flush=True)
    fl = count_flops(model)
    print(f"params {sum(p.numel() for p in model.parameters())}, GFLOPs encoder {fl['encoder'] / 1e9:.3f} "
          f"head {fl['head'] / 1e9:.3f}", flush=True)
    decay = [p for n, p in model.named_parameters() if p.ndim > 1]
    other = [p for n, p in model.named_parameters() if p.ndim <= 1]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": a.wd}, {"params": other, "weight_decay": 0}], lr=a.lr)

    step, t_done, best = 0, 0.0, float("inf")
    if a.resume and os.path.exists(os.path.join(a.out, "last.pt")):
        ck = torch.load(os.path.join(a.out, "last.pt"))
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["opt"])
        step, t_done, best, frozen_bn = ck["step"], ck["elapsed"], ck["best"], ck.get("frozen_bn", False)
        rng = np.random.default_rng(a.seed + step)
        g = torch.Generator().manual_seed(a.seed + step)
        print(f"resumed at step {step}, {t_done / 60:.1f} min done", flush=True)
    model.train()
    if frozen_bn:
        freeze_bn(model)

    log = open(os.path.join(a.out, "log.csv"), "a")
    if log.tell() == 0:
        log.write("step,minutes,lr,train_huber,val_synth_huber,val_synth_rmse,val_synth_mae,"
                  "val_homog_huber,val_homog_rmse,val_homog_mae,val_real_rmse,val_real_mae\n")
    t0 = time.time() - t_done
    budget = a.minutes * 60
    # The learning rate follows the --minutes schedule; the run ends there or at --stop-minutes.
    end = budget if a.stop_minutes is None else min(budget, a.stop_minutes * 60)
    run_loss = []
    while True:
        el = time.time() - t0
        frac = el / budget
        if el >= end:
            break
        lr = a.lr * min(1.0, (step + 1) / a.warmup) * 0.5 * (1 + math.cos(math.pi * frac))
        for gr in opt.param_groups:
            gr["lr"] = lr
        ref, cur, y = make_batch(rng, g, synth, homog, a.batch, p_homog=a.p_homog, real=real, p_real=a.p_real,
                                 p_unrel=a.p_unrelated, replay=replay, p_replay=a.p_replay, homog2=homog2,
                                 p_homog2=a.p_homog_extra)
        outs = model(ref, cur, all_iters=True)
        K = len(outs) - 1
        w = decision_weights(y, a.decision_weight) if a.decision_weight > 0 else None
        loss = sum(0.8 ** (K - k) * huber(o, y, w=w) for k, o in enumerate(outs))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        run_loss.append(huber(outs[-1].detach(), y).item())
        step += 1
        last = time.time() - t0 >= end
        if step % a.val_every == 0 or last:
            r = evaluate(model, sets)
            if frozen_bn:
                freeze_bn(model)
            tr = float(np.mean(run_loss))
            run_loss = []
            vs, vh = r["val_synth"], r["val_homog"]
            vr = r.get("val_real", {"rmse": float("nan"), "mae": float("nan"), "huber": 0.0})
            log.write(f"{step},{(time.time() - t0) / 60:.2f},{lr:.2e},{tr:.5f},{vs['huber']:.5f},{vs['rmse']:.4f},"
                      f"{vs['mae']:.4f},{vh['huber']:.5f},{vh['rmse']:.4f},{vh['mae']:.4f},{vr['rmse']:.4f},"
                      f"{vr['mae']:.4f}\n")
            log.flush()
            print(f"step {step} {(time.time() - t0) / 60:.1f} min lr {lr:.1e} train huber {tr:.4f} | val synth "
                  f"huber {vs['huber']:.4f} rmse {vs['rmse']:.3f} mae {vs['mae']:.3f} | val homog rmse "
                  f"{vh['rmse']:.3f} mae {vh['mae']:.3f} | val real rmse {vr['rmse']:.3f} mae {vr['mae']:.3f}",
                  flush=True)
            score = vs["huber"] + 0.5 * vh["huber"] + vr["huber"]
            improved = score < best
            best = min(best, score)
            ck = {"model": model.state_dict(), "arch": model.arch, "step": step, "val": r, "frozen_bn": frozen_bn,
                  "opt": opt.state_dict(), "elapsed": time.time() - t0, "best": best}
            torch.save(ck, os.path.join(a.out, "last.pt.tmp"))
            os.replace(os.path.join(a.out, "last.pt.tmp"), os.path.join(a.out, "last.pt"))
            if improved:
                torch.save(ck, os.path.join(a.out, "best.pt"))
    print(f"done: {step} steps in {(time.time() - t0) / 60:.1f} min", flush=True)


if __name__ == "__main__":
    main()
