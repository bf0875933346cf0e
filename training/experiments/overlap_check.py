"""Where the teacher's tau comes from on a real sequence, at a few frame gaps: the 0.1 m 3-D check,
depth holes, or the geometry of the views itself.

For pairs (reference j, current j + gap), j every `--every` frames, from the sequence's depth and
ground-truth poses (depth at a quarter of the resolution), it prints the mean of:

  * `tau(0.1 m)`: the teacher's own tau (`leangate label --max-dist 0.1`, its default);
  * `tau(no check)`: the teacher without the 3-D check (`--max-dist 1e6`): a match only has to
    land inside the reference on a pixel with depth;
  * `dense tau`: the same overlap with every depth hole filled by the pair's median depth, so that
    every pixel counts (what a dense pointmap would give): 1 - min(inside fraction, fraction of the
    reference's pixels hit);
  * `inside`: the fraction of the current frame's valid pixels that land inside the reference;
  * `far`: the fraction of valid depth beyond 4 m;
  * `tau_geo`: the element's prior on the same pairs (`leangate geometry`), for comparison.

Usage: python -m training.experiments.overlap_check SEQ [SEQ ...] [--gaps 1,5,10,15] [--every 7]
"""
import argparse
import os
import tempfile

import numpy as np

from ..fuse import _csv, _run
from ..import_tum import check_pose, read_list
from ..seqio import check_intrinsics, rows
from ..tum import quat_to_rot


def load(seq):
    """Intrinsics (at the quarter resolution), camera-to-world poses and a depth reader (metres) of a
    one-row-per-frame sequence; bad input is an error naming the file (the importers' checks)."""
    from PIL import Image

    check_intrinsics(os.path.join(seq, "intrinsics.txt"))
    fx, fy, cx, cy, scale = (float(v) for v in rows(os.path.join(seq, "intrinsics.txt"))[1][0].split()[:5])
    gt = os.path.join(seq, "groundtruth.txt")
    poses = []
    for t, rest in read_list(gt):
        check_pose(gt, t, rest)
        v = [float(x) for x in rest.split()]
        T = np.eye(4)
        T[:3, :3] = quat_to_rot(np.array(v[3:7]) / np.linalg.norm(v[3:7]))
        T[:3, 3] = v[:3]
        poses.append(T)
    depth = [os.path.join(seq, rest.split()[0]) for _, rest in read_list(os.path.join(seq, "depth.txt")) if rest]
    if len(depth) != len(poses):
        raise SystemExit(f"{seq}: {len(depth)} depth rows but {len(poses)} poses (one row per frame expected)")

    def z(k):
        try:
            return np.asarray(Image.open(depth[k]), np.float64)[::4, ::4] / scale
        except OSError as e:
            raise SystemExit(f"{depth[k]}: cannot read it as a depth image ({e})")

    return (fx / 4, fy / 4, cx / 4, cy / 4), poses, z


def dense_tau(K, Pj, Pi, zi, zj):
    fx, fy, cx, cy = K
    med = np.median(np.concatenate([zi[zi > 0], zj[zj > 0]]))
    h, w = zi.shape
    v, u = np.mgrid[0:h, 0:w]

    def project(z, fill):
        zz = np.where(z > 0, z, fill) if fill else z
        m = zz > 0
        X = np.stack([(u - cx) / fx * zz, (v - cy) / fy * zz, zz, np.ones_like(zz)], -1)[m]
        Y = (np.linalg.inv(Pj) @ Pi @ X.T).T
        pu = np.round(fx * Y[:, 0] / Y[:, 2] + cx).astype(int)
        pv = np.round(fy * Y[:, 1] / Y[:, 2] + cy).astype(int)
        ins = (Y[:, 2] > 0) & (pu >= 0) & (pu < w) & (pv >= 0) & (pv < h)
        return ins, pu[ins], pv[ins]

    ins, _, _ = project(zi, None)
    ins2, pu, pv = project(zi, med)
    hit = np.zeros((h, w), bool)
    hit[pv, pu] = True
    return 1 - min(ins2.mean(), hit.mean()), ins.mean()


def leangate_tau(seq, pairs, cmd):
    """tau (`label`) or tau_geo (`geometry`) of `pairs` [(i, j)], NaN where undefined."""
    with tempfile.TemporaryDirectory() as d:
        p, o = os.path.join(d, "pairs.csv"), os.path.join(d, "out.csv")
        with open(p, "w") as f:
            f.write("i,j\n" + "".join(f"{i},{j}\n" for i, j in pairs))
        try:
            _run([*cmd, "--sequence", seq, "--pairs", p, "--out", o])
        except RuntimeError as e:
            raise SystemExit(f"leangate {cmd[0]} on {seq} failed: {str(e).strip().splitlines()[-1]}")
        tab = _csv(o)
    return np.atleast_1d(tab["tau" if "tau" in tab.dtype.names else "tau_geo"]).astype(float)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", nargs="+")
    ap.add_argument("--gaps", default="1,5,10,15")
    ap.add_argument("--every", type=int, default=7, help="a reference every this many frames")
    a = ap.parse_args()
    try:
        gaps = [int(g) for g in a.gaps.split(",")]
    except ValueError:
        gaps = []
    if not gaps or min(gaps) < 1:
        raise SystemExit(f"--gaps {a.gaps}: expected comma-separated frame gaps of at least 1")
    if a.every < 1:
        raise SystemExit(f"--every {a.every}: expected at least 1")
    print("| sequence | gap | tau (0.1 m) | tau (no check) | dense tau | inside | far (> 4 m) | tau_geo |")
    print("|---|---|---|---|---|---|---|---|")
    for seq in a.sequence:
        if not os.path.isdir(seq):
            raise SystemExit(f"{seq}: no such sequence directory")
        K, poses, z = load(seq)
        if max(gaps) >= len(poses):
            raise SystemExit(f"--gaps {a.gaps}: {seq} has {len(poses)} frames, fewer than the largest gap + 1")
        for g in gaps:
            pairs = [(j + g, j) for j in range(0, len(poses) - g, a.every)]
            t01 = leangate_tau(seq, pairs, ["label"])
            tinf = leangate_tau(seq, pairs, ["label", "--max-dist", "1000000"])
            geo = leangate_tau(seq, pairs, ["geometry"])
            dense, inside, far = [], [], []
            for i, j in pairs:
                zi, zj = z(i), z(j)
                d, ins = dense_tau(K, poses[j], poses[i], zi, zj)
                dense.append(d)
                inside.append(ins)
                far.append((zi[zi > 0] > 4).mean())
            print(f"| {os.path.basename(os.path.normpath(seq))} | {g} | {t01.mean():.3f} | {tinf.mean():.3f} | "
                  f"{np.mean(dense):.3f} | {np.mean(inside):.3f} | {np.mean(far):.3f} | {np.nanmean(geo):.3f} |", flush=True)


if __name__ == "__main__":
    main()
