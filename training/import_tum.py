"""Write a TUM RGB-D benchmark sequence as it is distributed (`rgb.txt`, `depth.txt` and a
100 Hz `groundtruth.txt`, each `timestamp ...` with `#` comments, and the `rgb/`, `depth/` PNGs) as
the one-row-per-frame sequence of ../shared/data that `leangate eval` and `leangate label` read:
each colour frame with the nearest depth frame (within 20 ms) and the nearest ground-truth pose
(within 10 ms, written at the colour frame's timestamp), over the longest run of consecutive colour
frames that have both (or --first..--last), plus `intrinsics.txt` (the calibrated colour camera of
freiburg1, 2 or 3, depth_scale 5000; lens distortion is not removed). Colour frames are copied, or
re-encoded as JPEG with --jpeg Q (needs Pillow); depth PNGs are copied. Nothing is written unless
the lists are well-formed (finite timestamps, no colour timestamp twice, poses of seven numbers with a
unit quaternion) and every chosen file exists and can be copied: an error names the file.

This is how `../shared/data/tum_fr1_xyz` is made (../shared/data is not in the repository; a fresh
machine rebuilds it from a public repository whose history holds the whole freiburg1_xyz):

    git clone https://github.com/ScanAround/KinectFusion-Cool-Edition /tmp/kf
    mkdir -p /tmp/kf-data && git -C /tmp/kf archive 06b688db \\
        src/mapping_as_surface_reconstruction/rgbd_dataset_freiburg1_xyz | tar -x -C /tmp/kf-data
    python -m training.import_tum \\
        /tmp/kf-data/src/mapping_as_surface_reconstruction/rgbd_dataset_freiburg1_xyz \\
        ../shared/data/tum_fr1_xyz --camera fr1 --jpeg 90

(`--jpeg` needs Pillow: `.venv/bin/python -m training.import_tum ...`.)
"""
import argparse
import bisect
import math
import os
import shutil

from .seqio import check_intrinsics, staged, write_lists

# fx fy cx cy of the TUM RGB-D colour cameras (vision.in.tum.de/data/datasets/rgbd-dataset/file_formats)
CAMERAS = {
    "fr1": (517.3, 516.5, 318.6, 255.3),
    "fr2": (520.9, 521.0, 325.1, 249.7),
    "fr3": (535.4, 539.2, 320.1, 247.6),
}
MAX_DEPTH_S = 0.02
MAX_POSE_S = 0.01


def read_list(path, unique=False):
    """[(timestamp, rest of the line)] of a TUM list, in timestamp order; an error naming the file
    and line otherwise (a timestamp that is not a finite number; with `unique`, one given twice)."""
    rows = []
    try:
        with open(path) as f:
            for n, line in enumerate(f, 1):
                s = line.strip()
                if not s or s.startswith("#"):
                    continue
                t, _, rest = s.partition(" ")
                try:
                    v = float(t)
                except ValueError:
                    v = math.nan
                if not math.isfinite(v):
                    raise SystemExit(f"{path}:{n}: `{t}` is not a timestamp")
                rows.append((v, rest.strip(), n))
    except (OSError, UnicodeDecodeError) as e:
        raise SystemExit(f"{path}: cannot read it: {getattr(e, 'strerror', None) or e}")
    rows.sort()
    if unique:
        for (t, _, n0), (t1, _, n1) in zip(rows, rows[1:]):
            if t == t1:
                raise SystemExit(f"{path}:{n1}: timestamp {t:.6f} already on line {n0}")
    return [(t, rest) for t, rest, _ in rows]


def check_pose(path, t, rest):
    """An error naming `path` unless `rest` is `tx ty tz qx qy qz qw`: finite, a unit quaternion."""
    try:
        v = [float(x) for x in rest.split()]
    except ValueError:
        v = []
    if len(v) != 7 or not all(map(math.isfinite, v)):
        raise SystemExit(f"{path}: `{t} {rest}` is not `t tx ty tz qx qy qz qw`")
    if abs(math.sqrt(sum(x * x for x in v[3:])) - 1) > 1e-2:
        raise SystemExit(f"{path}: `{t} {rest}`: the quaternion qx qy qz qw is not of unit length")


def nearest(times, t, max_diff):
    """Index of the entry of sorted `times` nearest to `t`, if within `max_diff`."""
    k = bisect.bisect_left(times, t)
    best = min((i for i in (k - 1, k) if 0 <= i < len(times)), key=lambda i: abs(times[i] - t), default=None)
    return best if best is not None and abs(times[best] - t) <= max_diff else None


def associate(src):
    """[(rgb row, depth row or None, pose row or None)] per colour frame."""
    if not os.path.isdir(src):
        raise SystemExit(f"{src}: no such folder")
    rgb = read_list(os.path.join(src, "rgb.txt"), unique=True)
    depth = read_list(os.path.join(src, "depth.txt"))
    gt = read_list(os.path.join(src, "groundtruth.txt"))
    for name, rows in (("rgb.txt", rgb), ("depth.txt", depth), ("groundtruth.txt", gt)):
        if not rows:
            raise SystemExit(f"{os.path.join(src, name)} has no rows")
    for name, rows in (("rgb.txt", rgb), ("depth.txt", depth)):
        for t, rest in rows:
            if not rest:
                raise SystemExit(f"{os.path.join(src, name)}: `{t}` names no file")
    for t, rest in gt:
        check_pose(os.path.join(src, "groundtruth.txt"), t, rest)
    dt, gtt = [t for t, _ in depth], [t for t, _ in gt]
    out = []
    for r in rgb:
        d = nearest(dt, r[0], MAX_DEPTH_S)
        p = nearest(gtt, r[0], MAX_POSE_S)
        out.append((r, depth[d] if d is not None else None, gt[p] if p is not None else None))
    return out


def longest_run(frames):
    """(first, last) of the longest run of frames with depth and pose."""
    best, start = (0, -1), None
    for i, (_, d, p) in enumerate(frames + [(None, None, None)]):
        if d is not None and p is not None:
            start = i if start is None else start
        elif start is not None:
            if i - 1 - start > best[1] - best[0]:
                best = (start, i - 1)
            start = None
    if best[1] < best[0]:
        raise SystemExit("no colour frame has both a depth frame within 20 ms and a pose within 10 ms")
    return best


def import_sequence(src, out, camera, first=None, last=None, jpeg=None, name=None, intrinsics=None):
    """Write frames first..last (default: the longest run with depth and poses) of `src` into
    `out`; `intrinsics`: an `intrinsics.txt` to copy instead of the `camera`'s."""
    if intrinsics is not None:
        if not os.path.isfile(intrinsics):
            raise SystemExit(f"{intrinsics}: no such intrinsics file")
        check_intrinsics(intrinsics)
    frames = associate(src)
    a, b = longest_run(frames) if first is None and last is None else (
        first if first is not None else 0, last if last is not None else len(frames) - 1)
    if not 0 <= a <= b < len(frames):
        raise SystemExit(f"frames {a}-{b} requested; the sequence has {len(frames)} (0-{len(frames) - 1})")
    chosen = frames[a:b + 1]
    for i, (r, d, p) in enumerate(chosen, a):
        if d is None or p is None:
            raise SystemExit(f"colour frame {i} ({r[1]}) has no {'depth frame' if d is None else 'pose'} near it")
        for rel in (r[1], d[1]):
            if not os.path.isfile(os.path.join(src, rel)):
                raise SystemExit(f"{os.path.join(src, rel)} is missing (or not a file)")
    if jpeg is not None:
        try:
            from PIL import Image
        except ImportError:
            raise SystemExit("--jpeg needs Pillow (run with .venv/bin/python, which has it)")
    name = name or os.path.basename(os.path.normpath(src))
    head = (f"# {name} (TUM RGB-D, CC BY 4.0, Sturm et al. IROS 2012), frames {a}-{b} of {len(frames)}, one row "
            f"per frame (rgb, depth within {MAX_DEPTH_S * 1000:.0f} ms, ground truth within {MAX_POSE_S * 1000:.0f} ms)")
    rgb_rows, depth_rows, gt_rows = [head], [head], [head, "# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    with staged(out) as tmp:
        for sub in ("rgb", "depth"):
            os.makedirs(os.path.join(tmp, sub))
        for r, d, p in chosen:
            stem = os.path.splitext(os.path.basename(r[1]))[0]
            dst = f"rgb/{stem}.jpg" if jpeg is not None else f"rgb/{os.path.basename(r[1])}"
            ddst = f"depth/{os.path.basename(d[1])}"
            for written in (dst, ddst):
                if os.path.exists(os.path.join(tmp, written)):
                    raise SystemExit(f"{out}: two chosen frames would both be written as {written}")
            if jpeg is not None:
                Image.open(os.path.join(src, r[1])).convert("RGB").save(os.path.join(tmp, dst), quality=jpeg)
            else:
                shutil.copyfile(os.path.join(src, r[1]), os.path.join(tmp, dst))
            shutil.copyfile(os.path.join(src, d[1]), os.path.join(tmp, ddst))
            rgb_rows.append(f"{r[0]:.6f} {dst}")
            depth_rows.append(f"{d[0]:.6f} {ddst}")
            gt_rows.append(f"{r[0]:.6f} {p[1]}")
        write_lists(tmp, {"rgb.txt": rgb_rows, "depth.txt": depth_rows, "groundtruth.txt": gt_rows})
        if intrinsics is not None:
            shutil.copyfile(intrinsics, os.path.join(tmp, "intrinsics.txt"))
        else:
            fx, fy, cx, cy = CAMERAS[camera]
            write_lists(tmp, {"intrinsics.txt": [
                f"# fx fy cx cy depth_scale (depth units per metre); TUM {camera} colour camera",
                f"{fx} {fy} {cx} {cy} 5000"]})
    return a, b, len(frames)


def quality(v):
    """A JPEG quality 1-100 (argparse names --jpeg and the value otherwise)."""
    try:
        q = int(v)
    except ValueError:
        q = 0
    if not 1 <= q <= 100:
        raise argparse.ArgumentTypeError(f"`{v}` is not a quality 1-100")
    return q


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("src", help="a TUM RGB-D sequence folder as distributed (rgb.txt, depth.txt, groundtruth.txt)")
    ap.add_argument("out", help="the one-row-per-frame sequence to write")
    cam = ap.add_mutually_exclusive_group(required=True)
    cam.add_argument("--camera", choices=sorted(CAMERAS), help="which freiburg camera recorded it")
    cam.add_argument("--intrinsics", help="an intrinsics.txt (`fx fy cx cy depth_scale`) to use instead")
    ap.add_argument("--first", type=int, help="first colour frame (default: the longest run with depth and poses)")
    ap.add_argument("--last", type=int, help="last colour frame")
    ap.add_argument("--jpeg", type=quality, metavar="Q", help="re-encode colour as JPEG quality Q (1-100)")
    a = ap.parse_args()
    first, last, n = import_sequence(a.src, a.out, a.camera, a.first, a.last, a.jpeg, intrinsics=a.intrinsics)
    print(f"{a.out}: frames {first}-{last} of {n} ({last - first + 1})")


if __name__ == "__main__":
    main()
