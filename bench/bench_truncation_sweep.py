"""Benchmark: the calibration from mild to strong truncation (scenario (a)'s mouse, wider and wider).

Scenario (a) of bench_calibration.py (the mouse thorax, independent 0.3 mm / 0.3 deg robot errors,
90 views) with the mouse scaled 1x, 1.5x, 2x and 3x in the same field of view: each step
truncates the projections more. Every method through calibration.calibrate, and ncc-lle-exact
with the exterior model reaching the mouse's far side; per width the
gauge-aligned reprojection error (mean, px), the truncation level (calibration.volume.
truncation_level), and whether the method ended worse than the nominal geometry. Writes
``sweep.md`` and ``sweep.json`` into ``--out``.

    .venv/bin/python bench/bench_truncation_sweep.py --out docs/results     # about 25 min on 2 cores
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_calibration import EXTERIOR_METHOD, make_scenario, run_method  # noqa: E402

from robot_ct_ros.ct.calibration.volume import truncation_level  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402

METHODS = ("none", "l2-lle", "ncc-lle", "ncc-lle-exact", "gdc", "gdc-log", EXTERIOR_METHOD)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scales", default="1,1.5,2,3", help="widths of the mouse, times scenario (a)'s")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--views", type=int, default=90)
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/bench_sweep")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    scales = [float(x) for x in args.scales.split(",")]
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    table = {}
    for scale in scales:
        sc = make_scenario("a", args.views, (64, 96), 64, 4, args.seed, say, phantom_scale=scale)
        pts = roi_points(sc.grid)
        level = truncation_level(sc.li, sc.mask)
        row = {"truncation_level": level, "errors_px": {}, "wall_s": {}, "model_ncc": {}, "notes": {}}
        for m in methods:
            res, _ = run_method(m, sc, args.iterations, lambda s: None, seed=0)
            geom = res.geom if hasattr(res, "geom") else res[0]
            row["errors_px"][m] = reprojection_error(geom, sc.true, pts)["mean_px"]
            row["wall_s"][m] = res.wall_s if hasattr(res, "wall_s") else res[3]
            history = getattr(res, "history", ())
            row["model_ncc"][m] = float(history[-1].projection_ncc) if history else None
            row["notes"][m] = list(getattr(res, "notes", ()))
            say(f"  scale {scale:g}: {m} {row['errors_px'][m]:.3f} px ({row['wall_s'][m]:.1f} s)")
        table[scale] = row
    nominal = {s: r["errors_px"].get("none") for s, r in table.items()}
    lines = ["# Truncation sweep (bench/bench_truncation_sweep.py)", "",
             f"Scenario (a)'s mouse scaled in the same field of view, {args.views} views, robot errors 0.3 mm / "
             f"0.3 deg, {args.iterations} iterations, seed {args.seed}. Gauge-aligned reprojection error of ROI "
             "points, mean, px; bold: worse than the nominal geometry; (g): the guard kept the nominal geometry "
             "for the whole scan (its notes are in sweep.json). Second table: the model NCC (the last iteration's "
             "projection NCC, the guard's first test).", "",
             "| method | " + " | ".join(f"{s:g}x (truncation {table[s]['truncation_level']:.3f})" for s in scales) + " |",
             "| --- | " + " | ".join("---" for _ in scales) + " |"]
    for m in methods:
        cells = []
        for s in scales:
            e = table[s]["errors_px"][m]
            worse = m != "none" and nominal[s] is not None and e > nominal[s]
            kept = any("nominal geometry is kept" in n for n in table[s]["notes"][m])
            cells.append((f"**{e:.3f}**" if worse else f"{e:.3f}") + (" (g)" if kept else ""))
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    lines += ["", "| method | " + " | ".join(f"{s:g}x" for s in scales) + " |",
              "| --- | " + " | ".join("---" for _ in scales) + " |"]
    for m in methods:
        if all(table[s]["model_ncc"][m] is None for s in scales):
            continue
        lines.append(f"| {m} | " + " | ".join("-" if table[s]["model_ncc"][m] is None
                                              else f"{table[s]['model_ncc'][m]:.3f}" for s in scales) + " |")
    total = time.perf_counter() - t_all
    lines += ["", f"Total {total / 60:.1f} min on {os.cpu_count()} CPU(s)."]
    with open(os.path.join(args.out, "sweep.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    with open(os.path.join(args.out, "sweep.json"), "w") as f:
        json.dump({"views": args.views, "iterations": args.iterations, "seed": args.seed,
                   "scales": {str(s): r for s, r in table.items()}, "total_s": total}, f, indent=2)
    say(f"wrote {args.out}/sweep.md, sweep.json ({total / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
