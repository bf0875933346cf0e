"""Issue 50's speed and memory target: gating a ROS 2 bag is bound by decoding, not by the bag
code. Side by side in one run, interleaved A/B, medians of ROUNDS:

  A  leangate-client desk.mkv --quiet         the same 572 JPEG pictures of tum_fr1_desk in a
                                              Matroska file (MJPEG, not re-encoded: the same
                                              pictures through the same jpegdec)
  B  leangate-client desk_bag --topic /cam0/image_raw --out OUT
                                              a ROS 2 sqlite3 bag of them (CompressedImage, with
                                              camera_info and IMU at 200 Hz), OUT written

frames/s of each, the ratio (target: B within 1.5x of A), and each run's peak RSS. Then the
memory claim: B on a bag of the raw rgb8 frames (sensor_msgs/Image, 572 x 921,600 bytes, about
530 MB), whose peak RSS must stay far below the bag's size (the bag is streamed).

    .venv-bag/bin/python benches/bag_speed.py [--rounds 3] [--seq ../shared/data/tum_fr1_desk]

Needs `cargo build --release` (the plugin in target/release; --plugin-path to choose) and
.venv-bag (scripts/setup.sh). Writes only into a temporary directory, removed at the end.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests/fixtures"))

import rosbag_fixture  # noqa: E402


def run(cmd, env):
    """Wall seconds and peak RSS (MiB) of one command (its own rusage, os.wait4)."""
    t0 = time.monotonic()
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, ru = os.wait4(p.pid, 0)
    wall = time.monotonic() - t0
    out, err = p.stdout.read().decode(), p.stderr.read().decode()
    p.stdout.close()
    p.stderr.close()
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed:\n{err}")
    summary = next((l for l in out.splitlines() if l.startswith("summary:")), "")
    return wall, ru.ru_maxrss / 1024, summary


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seq", default=str(REPO / "../shared/data/tum_fr1_desk"))
    ap.add_argument("--plugin-path", default=str(REPO / "target/release"))
    ap.add_argument("--skip-raw", action="store_true", help="no rgb8 memory run")
    a = ap.parse_args()
    if not (Path(a.plugin_path) / "libgstleangate.so").exists() and not a.plugin_path.endswith(".so"):
        raise SystemExit(f"no libgstleangate.so in {a.plugin_path}: cargo build --release")
    env = dict(os.environ, PYTHONPATH=str(REPO / "pipelines"), GST_PLUGIN_PATH=a.plugin_path)
    env.pop("LEANGATE_MODEL", None)
    py = sys.executable
    client = [py, "-m", "leangate_client"]
    tmp = Path(tempfile.mkdtemp(prefix="leangate-bag-bench-"))
    try:
        rows = rosbag_fixture.frames_of(a.seq, 0)
        n = len(rows)
        pics = tmp / "pics"
        pics.mkdir()
        for i, (_, path) in enumerate(rows):
            os.symlink(path, pics / f"{i:06d}.jpg")
        video = tmp / "desk.mkv"
        # the JPEGs copied into Matroska as they are (ffmpeg, which scripts/setup.sh installs:
        # GStreamer's muxers need jpegparse from plugins-bad for the caps of loose JPEGs)
        subprocess.run(
            ["ffmpeg", "-loglevel", "error", "-framerate", "30", "-i", f"{pics}/%06d.jpg",
             "-c:v", "copy", str(video)],
            check=True,
        )
        bag = tmp / "desk_bag"
        rosbag_fixture.make("sqlite3", a.seq, str(bag), partner=False)
        print(f"{n} frames of {a.seq}: video {video.stat().st_size / 1e6:.1f} MB (MJPEG in "
              f"Matroska), ROS 2 sqlite3 bag {sum(f.stat().st_size for f in bag.iterdir()) / 1e6:.1f} MB")
        results = {"video": [], "bag": []}
        for r in range(a.rounds):
            w, rss, s = run(client + [str(video), "--quiet"], env)
            results["video"].append((w, rss))
            out = tmp / f"out{r}"
            w, rss, s = run(client + [str(bag), "--topic", "/cam0/image_raw", "--out", str(out)],
                            env)
            results["bag"].append((w, rss))
            shutil.rmtree(out)
            print(f"round {r + 1}: video {n / results['video'][-1][0]:.1f} frames/s, bag "
                  f"{n / w:.1f} frames/s ({s.split(' rig=')[0].split('summary: ')[-1]})")
        med = {k: statistics.median(x[0] for x in v) for k, v in results.items()}
        rss = {k: max(x[1] for x in v) for k, v in results.items()}
        print(f"video: {n / med['video']:.1f} frames/s (median of {a.rounds}), peak RSS "
              f"{rss['video']:.0f} MiB")
        print(f"bag:   {n / med['bag']:.1f} frames/s (median of {a.rounds}), peak RSS "
              f"{rss['bag']:.0f} MiB")
        ratio = med["bag"] / med["video"]
        print(f"bag time / video time: {ratio:.2f}x (target: within 1.5x) "
              f"{'OK' if ratio <= 1.5 else 'MISSED'}")
        if not a.skip_raw:
            raw = tmp / "raw_bag"
            rosbag_fixture.make("sqlite3", a.seq, str(raw), image="rgb8", partner=False)
            size = sum(f.stat().st_size for f in raw.iterdir()) / 2**20
            w, peak, s = run(client + [str(raw), "--topic", "/cam0/image_raw", "--out",
                                       str(tmp / "raw_out")], env)
            print(f"rgb8 bag of {size:.0f} MiB: {n / w:.1f} frames/s, peak RSS {peak:.0f} MiB "
                  f"({peak / size:.2f} of the bag's size)")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
