"""Start phases: a `leangate eval` report over parts written with `training.tum --phases N`, one row
per part with every policy's figures summed over its phases.

A gate's keyframe chain depends on the frame it starts from: on a part where the camera goes back
and forth (tum_fr1_xyz), starting one frame later can move the kept count by a third, and single
late keeps come and go. Evaluating each part from N start frames and summing them gives N times
the decisions for the same footage, so two gates (or two builds of one) can be compared on more
than a handful of keyframes. The folders `<part>`, `<part>-p1`, ... `<part>-p<N-1>` are one part.

  python -m training.tum --root out/phases --phases 10 --part tum_fr1_desk:test --part ...
  leangate eval --sequence out/phases/tum_fr1_desk/test --sequence out/phases/tum_fr1_desk/test-p1 ... \\
      --json out/phases.json
  python -m training.phases out/phases.json [--markdown]

Per part and policy: the phases, the oracle's and the policy's keyframes summed over them, kept /
oracle, late keeps and breaks summed, the smallest and largest kept count of one phase. Every
cheap gate in `leangate eval` is already at the model's budget of its own phase.
"""
import argparse
import json
import os
import re

POLICIES = ("model", "oracle", "motion", "overlap", "pixel_diff", "stride")


def part_of(sequence):
    """`.../tum_fr1_desk/test-p3` -> (`.../tum_fr1_desk/test`, 3); no suffix is phase 0."""
    m = re.fullmatch(r"(.*)-p(\d+)", os.path.normpath(sequence))
    return (m.group(1), int(m.group(2))) if m else (os.path.normpath(sequence), 0)


def load(path):
    try:
        with open(path) as f:
            report = json.load(f)
    except OSError as e:
        raise SystemExit(f"{path}: cannot read it ({e.strerror})")
    except ValueError as e:
        raise SystemExit(f"{path}: not JSON ({e})")
    seqs = report.get("sequences") if isinstance(report, dict) else None
    if not isinstance(seqs, list) or not seqs:
        raise SystemExit(f"{path}: not a `leangate eval --json` report over several sequences (no `sequences`)")
    return seqs


def table(seqs):
    """{part: {"phases": [k...], policy: {kept, oracle, late, breaks, lo, hi}}} for the parts whose
    every phase has teacher figures (the oracle's row)."""
    parts = {}
    for s in seqs:
        pol = s.get("policies") or {}
        if "oracle" not in pol:
            continue  # no depth or poses: nothing to judge
        name, k = part_of(s["sequence"])
        p = parts.setdefault(name, {"phases": []})
        if k in p["phases"]:
            raise SystemExit(f"{s['sequence']}: phase {k} of {name} appears twice")
        p["phases"].append(k)
        oracle = pol["oracle"]["kept"]
        for policy in POLICIES:
            if policy not in pol:
                continue
            r = pol[policy]
            acc = p.setdefault(policy, {"kept": 0, "oracle": 0, "late": 0, "breaks": 0, "lo": None, "hi": None})
            acc["kept"] += r["kept"]
            acc["oracle"] += oracle
            acc["late"] += r["late_keeps"]
            acc["breaks"] += r["breaks"]
            acc["lo"] = r["kept"] if acc["lo"] is None else min(acc["lo"], r["kept"])
            acc["hi"] = r["kept"] if acc["hi"] is None else max(acc["hi"], r["kept"])
    return parts


def sweep_table(seqs):
    """{part: {threshold: {policy: [kept, late]}}} summed over the phases, from `--sweep`'s points."""
    out = {}
    for s in seqs:
        if not s.get("sweep"):
            continue
        name, _ = part_of(s["sequence"])
        for pt in s["sweep"]:
            cell = out.setdefault(name, {}).setdefault(pt["threshold"], {}).setdefault(pt["policy"], [0, 0])
            cell[0] += pt["kept"]
            cell[1] += pt["late_keeps"]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("report", help="leangate eval --json over the phases of one or more parts")
    ap.add_argument("--out", help="also write the table as JSON here")
    a = ap.parse_args()
    seqs = load(a.report)
    parts = table(seqs)
    if not parts:
        raise SystemExit(f"{a.report}: no sequence with teacher figures (depth and poses)")
    print("| part | phases | policy | kept / oracle (summed) | ratio | late | breaks | kept in one phase |")
    print("|---|---|---|---|---|---|---|---|")
    total = {}
    for name, p in parts.items():
        for policy in POLICIES:
            if policy not in p:
                continue
            r = p[policy]
            t = total.setdefault(policy, {"kept": 0, "oracle": 0, "late": 0, "breaks": 0})
            for key in t:
                t[key] += r[key]
            print(f"| {name} | {len(p['phases'])} | {policy} | {r['kept']} / {r['oracle']} | "
                  f"{r['kept'] / r['oracle']:.2f} | {r['late']} | {r['breaks']} | {r['lo']}–{r['hi']} |")
    for policy, t in total.items():
        print(f"| **sum** | | {policy} | {t['kept']} / {t['oracle']} | {t['kept'] / t['oracle']:.2f} | "
              f"{t['late']} | {t['breaks']} | |")
    sweeps = sweep_table(seqs)
    if sweeps:
        thresholds = sorted({t for p in sweeps.values() for t in p})
        shown = [q for q in ("model", "motion", "overlap", "pixel_diff", "stride")]
        print(f"\nEqual-budget sweep, late keeps summed over the phases ({' / '.join(shown)}), kept by the model:")
        print("| part | " + " | ".join(f"{t:g}" for t in thresholds) + " |")
        print("|---|" + "---|" * len(thresholds))
        every = {}
        for name, p in sweeps.items():
            cells = []
            for t in thresholds:
                c = p.get(t, {})
                for q in shown:
                    every.setdefault(t, {}).setdefault(q, [0, 0])
                    every[t][q][0] += c.get(q, [0, 0])[0]
                    every[t][q][1] += c.get(q, [0, 0])[1]
                cells.append(" / ".join(str(c.get(q, ["-", "-"])[1]) for q in shown) + f" ({c.get('model', ['-'])[0]})")
            print(f"| {name} | " + " | ".join(cells) + " |")
        print("| **sum** | " + " | ".join(" / ".join(str(every[t][q][1]) for q in shown) + f" ({every[t]['model'][0]})"
                                         for t in thresholds) + " |")
    if a.out:
        with open(a.out, "w") as f:
            json.dump({"parts": parts, "sums": total, "sweep": sweeps}, f, indent=1)


if __name__ == "__main__":
    main()
