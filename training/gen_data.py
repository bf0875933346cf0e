"""Generate LeanGate training data (never inside the repository's tracked tree).

Steps (all under --root, default config.DATA_ROOT: $LEANGATE_TRAIN_DATA or <repo>/out/train-data):
  photos    copy/decode a subset of real photos from ../shared/data (never the validation sets)
  synth     render `leangate synth` sequences (train / val seeds) and label them with
            `leangate label --random` (pairs across the whole tau range, gaps up to 120 frames)
  cache     decode + resize (short-side-crop, area averaging, as the element does) to uint8 arrays
            in <root>/cache/{train,val}/seq_<seed>.npz: frames [F,H,W,3] + pairs [P,5] (i,j,tau,f_m,f_u)
  homog     pairs of real photos under random homographies with exact overlap labels
            -> <root>/cache/homog_{train,val}.npz (ref [P,H,W,3], cur [P,H,W,3], y [P,3] tau,f_m,f_u)
  tum       tum_fr1_rpy cut into its train / cal / test parts (config.TUM_SPLIT) as sub-sequence
            directories <root>/tum/<part>; teacher-labelled pairs of the train part (training) and
            gate-like pairs of the cal part (calibration) -> cache/tum_{train,cal}.npz (see tum.py)
  replay    synthetic sequences whose camera replays a real trajectory (the train part of
            tum_fr1_rpy, fox_orbit's COLMAP poses) with sensor realism (`--sensor`: exposure and
            white-balance drift, motion blur from the real motion, rolling shutter, depth noise and
            holes, vignetting, JPEG), labelled like `synth` -> <root>/cache/replay/seq_<seed>.npz
  evalseqs  held-out 300-frame mixed-motion sequences (new seeds, 640x480) for `leangate eval`
  roll      (not a default step) replayed sequences whose trajectory is tum_fr1_rpy's train part
            with an added roll about the optical axis -> <root>/cache/replay/seq_21xx.npz
  tumhomog  (not a default step) homography pairs of tum_fr1_rpy's train-part frames (the real
            camera's look, exact overlap labels, any direction of motion) -> cache/homog_tum.npz

Usage: python -m training.gen_data [--root DIR] [--steps photos,synth,cache,homog,tum,replay,evalseqs]
                                   [--n-train 64] [--n-val 6] [--frames 240] [--homog-train 12000]
                                   [--n-replay 40] [--n-roll 24]
"""
import argparse
import glob
import math
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from PIL import Image

from . import tum
from .config import (DATA_ROOT, EVAL_SEED0, HELDOUT_PREFIXES, IN_H, IN_W, LEANGATE, MOTIONS, REPLAY_SEED0, REPO, ROLL_SEED0,
                     SHARED, TRAIN_SEED0, VAL_SEED0)
from .preprocess import load_resized, read_list


def run(cmd):
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{r.stderr}")
    return r


# ----------------------------------------------------------------------------------------- photos
def step_photos(root):
    out = os.path.join(root, "photos")
    os.makedirs(out, exist_ok=True)
    srcs = sorted(glob.glob(os.path.join(SHARED, "webcam_classroom", "rgb", "*.jpg")))[::8]
    srcs += sorted(glob.glob(os.path.join(SHARED, "fox_orbit", "data", "nerf", "fox", "images", "*.jpg")))[::3]
    for s in srcs:
        tag = "webcam" if "webcam" in s else "fox"
        im = Image.open(s).convert("RGB")
        im.thumbnail((640, 640), Image.BOX)
        im.save(os.path.join(out, f"{tag}_{os.path.basename(s)}"), quality=92)
    # decode the cotracker clips at 2 frames/s with GStreamer
    for clip in sorted(glob.glob(os.path.join(SHARED, "cotracker_clips", "*.mp4"))):
        name = os.path.splitext(os.path.basename(clip))[0]
        tmp = os.path.join(root, "vid", name)
        os.makedirs(tmp, exist_ok=True)
        subprocess.run(["gst-launch-1.0", "-q", "filesrc", f"location={clip}", "!", "decodebin", "!",
                        "videoconvert", "!", "videorate", "!", "video/x-raw,framerate=2/1", "!",
                        "jpegenc", "quality=90", "!", "multifilesink", f"location={tmp}/%04d.jpg"],
                       check=False, capture_output=True, timeout=300)
        for f in sorted(glob.glob(os.path.join(tmp, "*.jpg"))):
            im = Image.open(f).convert("RGB")
            im.thumbnail((640, 640), Image.BOX)
            im.save(os.path.join(out, f"{name}_{os.path.basename(f)}"), quality=92)
    tex_train = os.path.join(root, "textures_train")
    tex_held = os.path.join(root, "textures_heldout")
    for d in (tex_train, tex_held):
        os.makedirs(d, exist_ok=True)
    for f in sorted(glob.glob(os.path.join(out, "*.jpg"))):
        b = os.path.basename(f)
        shutil.copy(f, os.path.join(tex_held if b.startswith(HELDOUT_PREFIXES) else tex_train, b))
    print(f"photos: {len(glob.glob(os.path.join(out, '*.jpg')))} "
          f"(train {len(os.listdir(tex_train))}, held out {len(os.listdir(tex_held))})")


# ------------------------------------------------------------------------------------------ synth
def synth_one(root, split, seed, frames, motion_args=None, extra=None):
    """Render and label one sequence. Default: a procedural motion (config.MOTIONS); `motion_args`
    replaces `--motion ...` (e.g. a replayed trajectory) and `extra` replaces the random
    blur/lighting/jpeg flags (e.g. `--sensor realistic`)."""
    rng = np.random.default_rng(seed)
    seq = os.path.join(root, "seqs", split, f"seq_{seed}")
    csv = seq + ".csv"
    if os.path.exists(csv):
        return seq
    if os.path.exists(seq):
        shutil.rmtree(seq)
    motion = MOTIONS[seed % len(MOTIONS)]
    tex = os.path.join(root, "textures_train")
    cmd = [LEANGATE, "synth", "--out", seq, "--seed", str(seed), "--frames", str(frames),
           *(motion_args or ["--motion", motion]), "--width", "320", "--height", "240",
           "--noise", f"{rng.uniform(0.0, 0.03):.4f}"]
    if rng.random() < 0.8:
        cmd += ["--textures", tex]
    if extra is not None:
        cmd += extra
    else:
        if rng.random() < 0.4:
            cmd += ["--blur"]
        if rng.random() < 0.4:
            cmd += ["--lighting"]
        if rng.random() < 0.3:
            cmd += ["--jpeg"]
    run(cmd)
    # pairs across the whole tau range: several gap scales so both small and large tau are common
    parts = []
    for k, gap in enumerate((8, 30, 120)):
        out = f"{seq}_{gap}.csv"
        run([LEANGATE, "label", "--sequence", seq, "--random", "1200", "--max-gap", str(gap),
             "--seed", str(seed * 10 + k), "--out", out])
        parts.append(out)
    with open(csv + ".tmp", "w") as fo:
        for k, p in enumerate(parts):
            lines = open(p).read().splitlines()
            fo.write("\n".join(lines if k == 0 else lines[1:]) + "\n")
            os.remove(p)
    os.replace(csv + ".tmp", csv)
    shown = [c for c in cmd[2:] if not c.startswith("/") and not c.startswith(root)]
    print(f"  {split} seed {seed}: {' '.join(shown)}", flush=True)
    return seq


def step_synth(root, n_train, n_val, frames, jobs):
    todo = [("train", TRAIN_SEED0 + k) for k in range(n_train)] + [("val", VAL_SEED0 + k) for k in range(n_val)]
    with ThreadPoolExecutor(jobs) as ex:
        list(ex.map(lambda t: synth_one(root, t[0], t[1], frames), todo))


# ------------------------------------------------------------------------------------------ cache
def cache_one(root, split, seq, keep_raw):
    out = os.path.join(root, "cache", split, os.path.basename(seq) + ".npz")
    if os.path.exists(out):
        return
    # frame indices in the label CSV are indices into the *associated* frame list; synth writes
    # rgb and depth for every frame, so that equals rgb.txt order.
    files = read_list(seq)
    frames = np.stack([load_resized(f) for f in files])
    d = np.genfromtxt(seq + ".csv", delimiter=",", names=True)
    pairs = np.stack([d["i"], d["j"], d["tau"], d["f_m"], d["f_u"]], 1).astype(np.float32)
    np.savez(out, frames=frames, pairs=pairs)
    if not keep_raw:
        shutil.rmtree(seq)


def step_cache(root, keep_train_raw=False):
    for split in ("train", "val"):
        os.makedirs(os.path.join(root, "cache", split), exist_ok=True)
        seqs = sorted(s[:-4] for s in glob.glob(os.path.join(root, "seqs", split, "seq_*.csv")))
        with ThreadPoolExecutor(2) as ex:
            list(ex.map(lambda s: cache_one(root, split, s, split == "val" or keep_train_raw), seqs))
    taus = []
    for f in glob.glob(os.path.join(root, "cache", "train", "*.npz")):
        taus.append(np.load(f)["pairs"][:, 2])
    taus = np.concatenate(taus)
    h, _ = np.histogram(taus, bins=10, range=(0, 1))
    print(f"cache: {len(taus)} synthetic train pairs, tau histogram (10 bins) {h.tolist()}")


# ----------------------------------------------------------------------------------------- replay
SENSOR_SUBSETS = ["realistic", "realistic", "realistic", "exposure,wb,blur,depth-noise,holes",
                  "blur,rolling,vignette,jpeg,depth-noise", "wb,blur,holes,jpeg"]


def replay_trajectories(root):
    """Real camera paths that may be replayed: (file, usable seconds). Only the *train* part of
    tum_fr1_rpy (its cal and test parts' motion is never seen), and fox_orbit's COLMAP poses.
    7-Scenes is an evaluation sequence and is not replayed."""
    out = []
    gt = os.path.join(root, "tum", "train", "groundtruth.txt")
    if os.path.exists(gt):
        ts = [float(l.split()[0]) for l in open(gt) if l.strip() and not l.startswith("#")]
        out.append((gt, ts[-1] - ts[0]))
    fox = os.path.join(SHARED, "fox_orbit", "data", "nerf", "fox", "transforms.json")
    if os.path.exists(fox):
        out.append((fox, 0.0))
    return out


def replay_one(root, k, seed, frames, traj, secs):
    """Render, label and cache replayed sequence `seed` (the k-th of its step): `traj` from a random
    start (bouncing at its end), the k-th sensor subset."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(0.0, max(secs - frames / 30.0 * 0.6, 0.0)) if secs > 0 else 0.0
    motion = ["--motion", f"replay:{traj}", "--replay-start", f"{start:.2f}", "--replay-end", "bounce"]
    extra = ["--sensor", SENSOR_SUBSETS[k % len(SENSOR_SUBSETS)]]
    seq = synth_one(root, "replay", seed, frames, motion, extra)
    os.makedirs(os.path.join(root, "cache", "replay"), exist_ok=True)
    cache_one(root, "replay", seq, False)


def step_replay(root, n, frames, jobs):
    trajs = replay_trajectories(root)
    if not trajs:
        sys.exit("replay: no trajectory (run the `tum` step first)")

    def one(k):
        # 4 of 5 sequences replay the real handheld trajectory, 1 of 5 fox_orbit's poses
        traj, secs = trajs[0] if (k % 5 != 4 or len(trajs) == 1) else trajs[1]
        replay_one(root, k, REPLAY_SEED0 + k, frames, traj, secs)

    with ThreadPoolExecutor(jobs) as ex:
        list(ex.map(one, range(n)))
    taus = np.concatenate([np.load(f)["pairs"][:, 2] for f in glob.glob(os.path.join(root, "cache", "replay", "*.npz"))])
    h, _ = np.histogram(taus, bins=10, range=(0, 1))
    print(f"replay: {len(taus)} pairs, tau histogram (10 bins) {h.tolist()}")


# ------------------------------------------------------------------------------------------ homog
def view_homography(corners):
    """Homography mapping model-input pixel coords (0..W, 0..H) to the 4 source-image corners."""
    src = np.array([[0, 0], [IN_W, 0], [IN_W, IN_H], [0, IN_H]], np.float64)
    A = []
    for (x, y), (u, v) in zip(src, corners):
        A.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
        A.append([0, 0, 0, x, y, 1, -v * x, -v * y, -v])
    _, _, vt = np.linalg.svd(np.asarray(A))
    H = vt[-1].reshape(3, 3)
    return H / H[2, 2]


def render_view(img, H):
    """Sample the source image at H(p) for every output pixel p (PIL's PERSPECTIVE is output->input)."""
    c = H.ravel()[:8]
    # supersample x2 then box-downsample: anti-aliasing like the element's area averaging
    S = np.diag([0.5, 0.5, 1.0])
    Hs = H @ S
    Hs = Hs / Hs[2, 2]
    big = img.transform((IN_W * 2, IN_H * 2), Image.PERSPECTIVE, tuple(Hs.ravel()[:8]), Image.BILINEAR)
    return np.asarray(big.resize((IN_W, IN_H), Image.BOX), np.uint8)


GRID = np.stack(np.meshgrid(np.arange(IN_W) + 0.5, np.arange(IN_H) + 0.5), -1).reshape(-1, 2)


def overlap_labels(Hr, Hc):
    """Exact teacher analogue on the 160x120 grid: current pixel centres mapped into the reference."""
    p = np.concatenate([GRID, np.ones((len(GRID), 1))], 1)
    q = (np.linalg.inv(Hr) @ Hc @ p.T).T
    ok = q[:, 2] > 1e-9
    q = q[:, :2] / np.where(ok, q[:, 2], 1.0)[:, None]
    inside = ok & (q[:, 0] >= 0) & (q[:, 0] < IN_W) & (q[:, 1] >= 0) & (q[:, 1] < IN_H)
    f_m = inside.mean()
    qi = np.floor(q[inside]).astype(np.int64)
    f_u = len(np.unique(qi[:, 1] * IN_W + qi[:, 0])) / (IN_W * IN_H)
    return 1.0 - min(f_m, f_u), f_m, f_u


def rolled_trajectory(src, dst, seed):
    """`src` (a TUM trajectory) with an added roll about each camera's optical axis: a sum of two
    sinusoids (amplitudes 8-40 degrees, 0.15-0.9 Hz, random phases) and a slow drift, i.e. roll rates
    up to about 3 degrees per frame at 30 Hz, as a handheld camera that is rolled back and forth.
    The positions and the other rotations are the real ones."""
    rng = np.random.default_rng(seed)
    comps = [(math.radians(rng.uniform(8, 40)), rng.uniform(0.15, 0.9), rng.uniform(0, 2 * math.pi))
             for _ in range(2)]
    drift = math.radians(rng.uniform(-10, 10))
    rows = [l.split() for l in open(src) if l.strip() and not l.startswith("#")]
    t0 = float(rows[0][0])
    with open(dst, "w") as f:
        f.write(f"# {os.path.basename(src)} with an added roll (seed {seed})\n")
        for r in rows:
            t = float(r[0]) - t0
            phi = sum(a * math.sin(2 * math.pi * fr * t + ph) for a, fr, ph in comps) + drift * t
            x, y, z, w = (float(v) for v in r[4:8])
            # q * q_z(phi): the roll is about the camera's own z (optical) axis
            cz, sz = math.cos(phi / 2), math.sin(phi / 2)
            q = (x * cz + y * sz, y * cz - x * sz, z * cz + w * sz, w * cz - z * sz)
            f.write(" ".join(r[:4]) + " " + " ".join(f"{v:.7f}" for v in q) + "\n")


def step_roll(root, n, frames, jobs):
    """Replayed sequences whose trajectory is tum_fr1_rpy's train part plus an added roll: rolls about
    the optical axis are rare in the train part (about 3 degrees per 10 frames, against 7-9 for pitch
    and yaw), common in handheld video. Cached with the replay sequences (cache/replay/)."""
    trajs = replay_trajectories(root)
    if not trajs or "tum" not in trajs[0][0]:
        sys.exit("roll: no tum_fr1_rpy train trajectory (run the `tum` step first)")
    gt, secs = trajs[0]

    def one(k):
        seed = ROLL_SEED0 + k
        traj = os.path.join(root, "tum", f"rolled_{seed}.txt")
        rolled_trajectory(gt, traj, seed)
        replay_one(root, k, seed, frames, traj, secs)

    with ThreadPoolExecutor(jobs) as ex:
        list(ex.map(one, range(n)))
    taus = np.concatenate([np.load(f)["pairs"][:, 2] for f in
                           glob.glob(os.path.join(root, "cache", "replay", f"seq_{ROLL_SEED0 // 100}*.npz"))])
    h, _ = np.histogram(taus, bins=10, range=(0, 1))
    print(f"roll: {len(taus)} pairs, tau histogram (10 bins) {h.tolist()}")


def rand_pair(rng, img):
    sw, sh = img.size
    for _ in range(30):
        s = rng.uniform(0.35, 0.75) * min(sw / IN_W, sh / IN_H)  # window = s * (160x120) source px
        w, h = IN_W * s, IN_H * s
        if w > sw or h > sh:
            continue
        x0, y0 = rng.uniform(0, sw - w), rng.uniform(0, sh - h)
        ref = np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]])
        mode = rng.random()
        if mode < 0.08:
            cur = ref + rng.normal(0, 0.3, ref.shape)  # near-identical view
        else:
            mag = rng.choice([0.03, 0.1, 0.25, 0.5, 0.9], p=[0.15, 0.2, 0.25, 0.25, 0.15])
            ang = rng.normal(0, 0.15 if rng.random() < 0.8 else 0.4)
            sc = math.exp(rng.normal(0, 0.18))
            t = rng.normal(0, mag, 2) * np.array([w, h])
            c = ref.mean(0)
            R = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]]) * sc
            cur = (ref - c) @ R.T + c + t
            cur = cur + rng.normal(0, rng.uniform(0, 0.06) * w, cur.shape)  # perspective
        if cur[:, 0].min() < 0 or cur[:, 1].min() < 0 or cur[:, 0].max() > sw or cur[:, 1].max() > sh:
            continue
        return ref, cur
    return None


def make_homog(photos, n, seed):
    rng = np.random.default_rng(seed)
    imgs = []
    for f in photos:
        im = Image.open(f).convert("RGB")
        im.thumbnail((480, 480), Image.BOX)
        imgs.append(im)
    R = np.zeros((n, IN_H, IN_W, 3), np.uint8)
    C = np.zeros_like(R)
    Y = np.zeros((n, 3), np.float32)
    k = 0
    while k < n:
        a = imgs[rng.integers(len(imgs))]
        if rng.random() < 0.06:  # unrelated photos: no overlap at all
            b = imgs[rng.integers(len(imgs))]
            if b is a:
                continue
            pa, pb = rand_pair(rng, a), rand_pair(rng, b)
            if pa is None or pb is None:
                continue
            R[k] = render_view(a, view_homography(pa[0]))
            C[k] = render_view(b, view_homography(pb[1]))
            Y[k] = (1.0, 0.0, 0.0)
            k += 1
            continue
        p = rand_pair(rng, a)
        if p is None:
            continue
        Hr, Hc = view_homography(p[0]), view_homography(p[1])
        R[k] = render_view(a, Hr)
        C[k] = render_view(a, Hc)
        Y[k] = overlap_labels(Hr, Hc)
        k += 1
    return R, C, Y


def write_homog(out, images, n, seed, what):
    """make_homog over `images`, saved to `out` with the tau histogram printed (skipped if it exists)."""
    if os.path.exists(out):
        return
    R, C, Y = make_homog(images, n, seed)
    np.savez(out, ref=R, cur=C, y=Y)
    h, _ = np.histogram(Y[:, 0], bins=10, range=(0, 1))
    print(f"{what}: {n} pairs from {len(images)} images, tau histogram {h.tolist()}", flush=True)


def step_homog(root, n_train, n_val):
    photos = sorted(glob.glob(os.path.join(root, "photos", "*.jpg")))
    train = [p for p in photos if not os.path.basename(p).startswith(HELDOUT_PREFIXES)]
    val = [p for p in photos if os.path.basename(p).startswith(HELDOUT_PREFIXES)]
    os.makedirs(os.path.join(root, "cache"), exist_ok=True)
    for name, ph, n, seed in (("train", train, n_train, 1), ("val", val, n_val, 2)):
        write_homog(os.path.join(root, "cache", f"homog_{name}.npz"), ph, n, seed, f"homog {name}")


def step_tumhomog(root, n):
    """Homography pairs of tum_fr1_rpy's *train-part* frames (every 2nd of 0-399): the real camera's
    colours, blur and exposure with exact overlap labels, in any direction of motion (pitch and yaw
    are where the student under-estimates real video). -> cache/homog_tum.npz (same layout as
    homog_train.npz; `train --homog-extra homog_tum.npz --p-homog-extra F`). The cal and test parts
    are not read."""
    part = os.path.join(root, "tum", "train")
    if not os.path.exists(os.path.join(part, "rgb.txt")):
        sys.exit("tumhomog: no tum/train/rgb.txt (run the `tum` step first)")
    os.makedirs(os.path.join(root, "cache"), exist_ok=True)
    write_homog(os.path.join(root, "cache", "homog_tum.npz"), read_list(part)[::2], n, 4, "tumhomog")


# --------------------------------------------------------------------------------------- evalseqs
def step_evalseqs(root, n=3):
    for k in range(n):
        seed = EVAL_SEED0 + k
        out = os.path.join(root, "eval", f"synth_{seed}")
        if os.path.exists(os.path.join(out, "rgb.txt")):
            continue
        cmd = [LEANGATE, "synth", "--out", out, "--seed", str(seed), "--frames", "300", "--motion", "mixed",
               "--textures", os.path.join(root, "textures_heldout")]
        if k >= 1:
            cmd += ["--blur"]
        if k >= 2:
            cmd += ["--lighting", "--jpeg"]
        run(cmd)
        print(f"eval sequence {out}: {' '.join(cmd[1:])}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default=DATA_ROOT)
    ap.add_argument("--steps", default="photos,synth,cache,homog,tum,replay,evalseqs")
    ap.add_argument("--n-train", type=int, default=64)
    ap.add_argument("--n-val", type=int, default=6)
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--homog-train", type=int, default=12000)
    ap.add_argument("--homog-val", type=int, default=1000)
    ap.add_argument("--n-replay", type=int, default=40)
    ap.add_argument("--n-roll", type=int, default=24)
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    root = os.path.abspath(a.root)
    if root.startswith(REPO + os.sep) and not root.startswith(os.path.join(REPO, "out") + os.sep):
        sys.exit("refusing to write generated data inside the repository (outside the git-ignored out/)")
    steps = a.steps.split(",")
    if "photos" in steps:
        step_photos(a.root)
    if "synth" in steps:
        step_synth(a.root, a.n_train, a.n_val, a.frames, a.jobs)
    if "cache" in steps:
        step_cache(a.root)
    if "homog" in steps:
        step_homog(a.root, a.homog_train, a.homog_val)
    if "tum" in steps:
        tum.build(a.root)
    if "replay" in steps:
        step_replay(a.root, a.n_replay, a.frames, a.jobs)
    if "roll" in steps:
        step_roll(a.root, a.n_roll, a.frames, a.jobs)
    if "tumhomog" in steps:
        step_tumhomog(a.root, a.homog_train)
    if "evalseqs" in steps:
        step_evalseqs(a.root)


if __name__ == "__main__":
    main()
