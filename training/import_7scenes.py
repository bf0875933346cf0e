"""Write a Microsoft 7-Scenes clip (its own layout: `frame-XXXXXX.color.jpg` or `.color.png`,
`.depth.png` with millimetres and 65535 = no reading, `.pose.txt` a 4x4 camera-to-world matrix, and
`camera-intrinsics.txt`, or the file `--intrinsics` names) as a TUM-layout sequence that `leangate
eval` and `leangate label` read: `rgb/`, `depth/` (the files copied unchanged, colour in its own
format; the tools read 65535 as no reading), `rgb.txt`, `depth.txt`, `groundtruth.txt` (`t tx ty
tz qx qy qz qw`, camera-to-world; t = frame index / 30 s) and `intrinsics.txt` (`fx fy cx cy
1000`). Every input file is checked (poses rigid, intrinsics
finite) before anything is written, and the output appears all at once or not at all (a file that
cannot be copied leaves it untouched). Standard library only.

This is how `../shared/data/7scenes_redkitchen_long` (the held-out sequence from another camera and
room in the model card) is made; ../shared/data is not in the repository, so a fresh machine rebuilds
it from the public repository andyzeng/tsdf-fusion-python, whose history holds redkitchen frames
0-999 (commit 3f22a940, folder `data/`; deleted at its HEAD):

    git clone https://github.com/andyzeng/tsdf-fusion-python /tmp/tsdf
    git -C /tmp/tsdf archive 3f22a940 data | tar -x -C /tmp/tsdf-data
    python -m training.import_7scenes /tmp/tsdf-data/data ../shared/data/7scenes_redkitchen_long \
        --first 60 --last 999

(`7scenes_redkitchen_dev` is frames 0-59 of the same clip.) The two SUN3D clips of the model card
(an Asus Xtion in a study room, PNG colour) come from the history of andyzeng/3dmatch-toolbox the
same way (training/README.md).
"""
import argparse
import math
import os
import shutil

from .seqio import staged, write_lists

SOURCE = "7-Scenes {scene} (Microsoft Research, non-commercial research terms)"
HEAD = "# {source}, frames {a}-{b}, nominal 30 Hz"


def read_matrix(path):
    """The rows of a whitespace-separated numeric matrix file; an error naming it otherwise."""
    try:
        with open(path) as f:
            return [[float(v) for v in line.split()] for line in f if line.strip()]
    except (OSError, ValueError) as e:
        raise SystemExit(f"{path}: {e}")


def quaternion(r):
    """(qx, qy, qz, qw) of a 3x3 rotation matrix (rows), qw >= 0."""
    t = r[0][0] + r[1][1] + r[2][2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        q = ((r[2][1] - r[1][2]) / s, (r[0][2] - r[2][0]) / s, (r[1][0] - r[0][1]) / s, 0.25 * s)
    elif r[0][0] > r[1][1] and r[0][0] > r[2][2]:
        s = math.sqrt(1.0 + r[0][0] - r[1][1] - r[2][2]) * 2
        q = (0.25 * s, (r[0][1] + r[1][0]) / s, (r[0][2] + r[2][0]) / s, (r[2][1] - r[1][2]) / s)
    elif r[1][1] > r[2][2]:
        s = math.sqrt(1.0 + r[1][1] - r[0][0] - r[2][2]) * 2
        q = ((r[0][1] + r[1][0]) / s, 0.25 * s, (r[1][2] + r[2][1]) / s, (r[0][2] - r[2][0]) / s)
    else:
        s = math.sqrt(1.0 + r[2][2] - r[0][0] - r[1][1]) * 2
        q = ((r[0][2] + r[2][0]) / s, (r[1][2] + r[2][1]) / s, 0.25 * s, (r[1][0] - r[0][1]) / s)
    n = math.sqrt(sum(v * v for v in q))
    q = tuple(v / n for v in q)
    return q if q[3] >= 0 else tuple(-v for v in q)


def pose_line(path):
    """`tx ty tz qx qy qz qw` of a 7-Scenes pose file; an error naming the file if it is not a
    rigid 4x4 matrix (a rotation: orthonormal rows, determinant 1; last row 0 0 0 1)."""
    m = read_matrix(path)
    if len(m) != 4 or any(len(r) != 4 for r in m) or not all(math.isfinite(v) for r in m for v in r):
        raise SystemExit(f"{path}: expected a 4x4 camera-to-world matrix")
    if max(abs(v - e) for v, e in zip(m[3], (0, 0, 0, 1))) > 1e-6:
        raise SystemExit(f"{path}: the last row is not `0 0 0 1`")
    r = [row[:3] for row in m[:3]]
    det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
           + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
    off = max(abs(sum(r[i][k] * r[j][k] for k in range(3)) - (i == j)) for i in range(3) for j in range(3))
    if abs(det - 1) > 1e-3 or off > 1e-3:
        raise SystemExit(f"{path}: the rotation part is not a rotation (determinant {det:.4f}, "
                         f"R R^T off the identity by {off:.4f})")
    q = quaternion(r)
    return " ".join(f"{v:.7f}" for v in (m[0][3], m[1][3], m[2][3]) + q)


def colour_file(base, first, last):
    """The colour image of the frame `base`: `.color.jpg` or `.color.png`, exactly one of them."""
    found = [base + ext for ext in (".color.jpg", ".color.png") if os.path.isfile(base + ext)]
    if not found:
        raise SystemExit(f"{base}.color.jpg is missing or not a file, and so is its .color.png "
                         f"(frames {first}-{last} requested)")
    if len(found) > 1:
        raise SystemExit(f"{base}: both .color.jpg and .color.png exist; which is the frame is unclear")
    return found[0]


def import_clip(src, out, first, last, scene, intrinsics=None, source=None):
    """Write frames first..last (inclusive) of the 7-Scenes folder `src` into `out` (the
    intrinsics from `intrinsics`, else `src/camera-intrinsics.txt`; `source` describes the clip
    in the lists' header). Every input file is checked before anything is written."""
    intr_path = intrinsics or os.path.join(src, "camera-intrinsics.txt")
    intr = read_matrix(intr_path)
    if len(intr) != 3 or any(len(r) != 3 for r in intr) or not all(math.isfinite(v) for r in intr for v in r):
        raise SystemExit(f"{intr_path}: missing, or not a 3x3 matrix of finite numbers")
    if intr[0][0] <= 0 or intr[1][1] <= 0:
        raise SystemExit(f"{intr_path}: the focal lengths fx, fy must be positive")
    if not 0 <= first <= last:
        raise SystemExit(f"--first {first} --last {last}: need 0 <= first <= last")
    names = []
    for k in range(first, last + 1):
        base = os.path.join(src, f"frame-{k:06d}")
        colour = colour_file(base, first, last)
        for ext in (".depth.png", ".pose.txt"):
            if not os.path.isfile(base + ext):
                raise SystemExit(f"{base + ext} is missing or not a file (frames {first}-{last} requested)")
        names.append((k, base, colour, pose_line(base + ".pose.txt")))
    head = HEAD.format(source=source or SOURCE.format(scene=scene), a=first, b=last)
    rgb = [head, "# timestamp filename"]
    depth = [head, "# timestamp filename (16-bit PNG, millimetres, 0 or 65535 = no reading)"]
    gt = [head, "# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    with staged(out) as tmp:
        for d in ("rgb", "depth"):
            os.makedirs(os.path.join(tmp, d))
        for k, base, colour, pose in names:
            t = f"{k / 30:.6f}"
            ext = colour[-3:]
            shutil.copyfile(colour, os.path.join(tmp, "rgb", f"{k:06d}.{ext}"))
            shutil.copyfile(base + ".depth.png", os.path.join(tmp, "depth", f"{k:06d}.png"))
            rgb.append(f"{t} rgb/{k:06d}.{ext}")
            depth.append(f"{t} depth/{k:06d}.png")
            gt.append(f"{t} {pose}")
        write_lists(tmp, {
            "rgb.txt": rgb, "depth.txt": depth, "groundtruth.txt": gt,
            "intrinsics.txt": ["# fx fy cx cy depth_scale (depth units per metre); intrinsics of the depth camera",
                               f"{intr[0][0]:.3f} {intr[1][1]:.3f} {intr[0][2]:.3f} {intr[1][2]:.3f} 1000"],
        })
    return len(names)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", help="a 7-Scenes folder (frame-XXXXXX.color.jpg or .color.png, .depth.png, .pose.txt; camera-intrinsics.txt)")
    ap.add_argument("out", help="the TUM-layout sequence to write")
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--last", type=int, required=True)
    ap.add_argument("--scene", default="redkitchen", help="scene name for the lists' header")
    ap.add_argument("--intrinsics", metavar="FILE",
                    help="the 3x3 camera matrix, when it is not SRC/camera-intrinsics.txt")
    ap.add_argument("--source", help="what the clip is, for the lists' header (default: 7-Scenes SCENE)")
    a = ap.parse_args()
    if a.source is not None and (not a.source.strip() or any(c in a.source for c in "\r\n")):
        raise SystemExit("--source: one line of text, for the lists' header")
    n = import_clip(a.src, a.out, a.first, a.last, a.scene, a.intrinsics, a.source)
    print(f"{a.out}: {n} frames")


if __name__ == "__main__":
    main()
