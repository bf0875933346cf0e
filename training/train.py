#!/usr/bin/env python3
"""Train LeanGate-S on the cached pairs made by gen_data.py.

Huber loss (delta 0.1) on tau, supervising every refinement iteration (weights 0.8^(K-k)), AdamW,
linear warm-up then cosine decay driven by wall-clock time (--minutes), so a run ends on time.
Tau-balanced sampling of synthetic pairs (inverse bin frequency), mixed with real-photo homography
pairs; photometric / grey / flip augmentation. Validation on held-out synthetic sequences (other
seeds) and held-out photos every --val-every steps; checkpoints <out>/last.pt and <out>/best.pt,
log <out>/log.csv.

Usage: python training/train.py [--data /work/train-data/cache] [--out /work/train-data/runs/s]
                                [--minutes 45] [--batch 32] [--lr 2e-3]
"""
import argparse
import glob
import math
import os
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from model import MEAN, STD, LeanGateS, count_flops  # noqa: E402

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


def make_batch(rng, g, synth, homog, n, p_homog=0.35, p_ident=0.04, augment=True):
    nh = int(round(n * p_homog))
    ni = int(round(n * p_ident))
    ns = n - nh - ni
    parts = [synth.sample(rng, ns), homog.sample(rng, nh), synth.identical(rng, ni)]
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


def huber(pred, y, delta=0.1):
    return F.huber_loss(pred, y, delta=delta)


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
    ap.add_argument("--data", default="/work/train-data/cache")
    ap.add_argument("--out", default="/work/train-data/runs/s")
    ap.add_argument("--minutes", type=float, default=45)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--wd", type=float, default=1e-4)
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--val-every", type=int, default=250)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--init", default="", help="checkpoint to start from")
    ap.add_argument("--p-homog", type=float, default=0.35, help="fraction of real-photo homography pairs")
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
    print(f"train: {len(synth.pairs)} synthetic pairs in {len(synth.frames)} sequences, {len(homog.y)} "
          f"homography pairs; val: {len(vidx)} synthetic pairs ({len(vsynth.frames)} sequences), "
          f"{len(vhom.y)} homography pairs", flush=True)

    model = LeanGateS()
    if a.init:
        model.load_state_dict(torch.load(a.init)["model"])
    fl = count_flops(model)
    print(f"params {sum(p.numel() for p in model.parameters())}, GFLOPs encoder {fl['encoder'] / 1e9:.3f} "
          f"head {fl['head'] / 1e9:.3f}", flush=True)
    decay = [p for n, p in model.named_parameters() if p.ndim > 1]
    other = [p for n, p in model.named_parameters() if p.ndim <= 1]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": a.wd}, {"params": other, "weight_decay": 0}], lr=a.lr)

    log = open(os.path.join(a.out, "log.csv"), "a")
    if log.tell() == 0:
        log.write("step,minutes,lr,train_huber,val_synth_huber,val_synth_rmse,val_synth_mae,"
                  "val_homog_huber,val_homog_rmse,val_homog_mae\n")
    t0 = time.time()
    budget = a.minutes * 60
    step, run_loss, best = 0, [], float("inf")
    while True:
        el = time.time() - t0
        frac = el / budget
        if frac >= 1:
            break
        lr = a.lr * min(1.0, (step + 1) / a.warmup) * 0.5 * (1 + math.cos(math.pi * frac))
        for gr in opt.param_groups:
            gr["lr"] = lr
        ref, cur, y = make_batch(rng, g, synth, homog, a.batch, p_homog=a.p_homog)
        outs = model(ref, cur, all_iters=True)
        K = len(outs) - 1
        loss = sum(0.8 ** (K - k) * huber(o, y) for k, o in enumerate(outs))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        run_loss.append(huber(outs[-1].detach(), y).item())
        step += 1
        last = time.time() - t0 >= budget
        if step % a.val_every == 0 or last:
            r = evaluate(model, sets)
            tr = float(np.mean(run_loss))
            run_loss = []
            vs, vh = r["val_synth"], r["val_homog"]
            log.write(f"{step},{(time.time() - t0) / 60:.2f},{lr:.2e},{tr:.5f},{vs['huber']:.5f},{vs['rmse']:.4f},"
                      f"{vs['mae']:.4f},{vh['huber']:.5f},{vh['rmse']:.4f},{vh['mae']:.4f}\n")
            log.flush()
            print(f"step {step} {(time.time() - t0) / 60:.1f} min lr {lr:.1e} train huber {tr:.4f} | val synth "
                  f"huber {vs['huber']:.4f} rmse {vs['rmse']:.3f} mae {vs['mae']:.3f} | val homog rmse "
                  f"{vh['rmse']:.3f} mae {vh['mae']:.3f}", flush=True)
            ck = {"model": model.state_dict(), "step": step, "val": r}
            torch.save(ck, os.path.join(a.out, "last.pt.tmp"))
            os.replace(os.path.join(a.out, "last.pt.tmp"), os.path.join(a.out, "last.pt"))
            score = vs["huber"] + 0.5 * vh["huber"]
            if score < best:
                best = score
                torch.save(ck, os.path.join(a.out, "best.pt"))
    print(f"done: {step} steps in {(time.time() - t0) / 60:.1f} min", flush=True)


if __name__ == "__main__":
    main()
