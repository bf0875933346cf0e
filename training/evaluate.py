"""Run `leangate eval` (the real GStreamer element) with a pair model on the held-out synthetic
sequences, the calibration and test parts of tum_fr1_rpy and the whole sequence, 7-Scenes, EuRoC
static, every cotracker clip and webcam_classroom; write the JSON reports and a Markdown summary.

Usage: python -m training.evaluate [--model models/leangate-s.onnx | --model embedded [--precision auto|fp32|int8]]
                                   [--threshold T] [--out $DATA_ROOT/evals/new]
       (--model embedded: the student compiled into the plugin, as the element runs it by default)
       (--threshold defaults to the model's leangate.threshold; the tum parts come from `gen_data --steps tum`)
"""
import argparse
import glob
import json
import os
import subprocess

from .config import DATA_ROOT, LEANGATE, MODELS_DIR, NAME, SHARED, TUM_SEQ, TUM_SPLIT


def fmt(v, p=3):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{p}f}"
    return str(v)


def sequences(root):
    seqs = [(os.path.basename(s), s) for s in sorted(glob.glob(os.path.join(root, "eval", "synth_*")))]
    for part in ("cal", "test"):
        a, b = TUM_SPLIT[part]
        seqs.append((f"{TUM_SEQ}[{a}-{b}] ({part})", os.path.join(root, "tum", part)))
    seqs.append((f"{TUM_SEQ} (all 718)", os.path.join(SHARED, TUM_SEQ)))
    seqs += [(n, os.path.join(SHARED, n)) for n in ("7scenes_redkitchen_dev", "euroc_v101_static")]
    seqs += [(os.path.basename(s), s) for s in sorted(glob.glob(os.path.join(SHARED, "cotracker_clips", "*.mp4")))]
    seqs.append(("webcam_classroom", os.path.join(SHARED, "webcam_classroom")))
    return seqs


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default=os.path.join(MODELS_DIR, f"{NAME}.onnx"))
    ap.add_argument("--out", default=os.path.join(DATA_ROOT, "evals", "new"))
    ap.add_argument("--root", default=DATA_ROOT, help="where gen_data put eval/ and tum/")
    ap.add_argument("--threshold", type=float, default=None)
    ap.add_argument("--precision", choices=("auto", "fp32", "int8"), default=None,
                    help="the element's precision (which build of the embedded student runs)")
    ap.add_argument("--only", default="", help="comma-separated substrings: evaluate only matching sequences")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    rows = []
    for name, s in sequences(a.root):
        if a.only and not any(k in name for k in a.only.split(",")):
            continue
        if not os.path.exists(s):
            rows.append(f"| {name} | missing: {s} |")
            continue
        tag = name.replace(" ", "_").replace("(", "").replace(")", "").replace("[", "_").replace("]", "")
        js = os.path.join(a.out, tag + ".json")
        cmd = [LEANGATE, "eval", "--sequence", s, "--json", js]
        if a.model != "embedded":
            cmd += ["--model", a.model]
        if a.precision:
            cmd += ["--precision", a.precision]
        if a.threshold is not None:
            cmd += ["--threshold", str(a.threshold)]
        if name.startswith(("synth_", "7scenes", TUM_SEQ)):
            cmd += ["--plot", os.path.join(a.out, tag + ".png")]
        r = subprocess.run(cmd, capture_output=True, text=True)
        print(r.stdout.strip() or r.stderr.strip()[-2000:], flush=True)
        if r.returncode != 0:
            rows.append(f"| {name} | eval failed: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode} |")
            continue
        d = json.load(open(js))
        P = d["policies"]
        m, o, st, pdf, mo = (P["model"], P.get("oracle", {}), P.get("stride", {}), P.get("pixel_diff", {}),
                             P.get("motion", {}))
        dropped = 1 - m["kept"] / d["frames"]
        rows.append(
            f"| {name} | {d['frames']} | {fmt(d['threshold'], 2)} | {m['kept']} ({100 * dropped:.0f}% dropped) | "
            f"{fmt(o.get('kept'))} | {fmt(st.get('kept'))} / {fmt(pdf.get('kept'))} / {fmt(mo.get('kept'))} | "
            f"{fmt(m.get('breaks'))} / {fmt(st.get('breaks'))} / {fmt(pdf.get('breaks'))} / {fmt(mo.get('breaks'))} | "
            f"{fmt(m.get('late_keeps'))} / {fmt(st.get('late_keeps'))} / {fmt(pdf.get('late_keeps'))} / "
            f"{fmt(mo.get('late_keeps'))} | {fmt(m.get('overdue_drops'))} | "
            f"{fmt(m.get('min_pair_S'))} | {fmt(m.get('utility_rmse'))} | {fmt(m.get('utility_mae'))} | "
            f"{fmt(m.get('fps'), 1)} |")
    head = ("| sequence | frames | T | model kept | oracle kept | stride / pixel_diff / motion kept | breaks model / "
            "stride / pixel_diff / motion | late keeps model / stride / pixel_diff / motion | overdue drops | "
            "min pair S | utility RMSE | utility MAE | fps |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    table = head + "\n" + "\n".join(rows) + "\n"
    open(os.path.join(a.out, "summary.md"), "w").write(table)
    print(table)


if __name__ == "__main__":
    main()
