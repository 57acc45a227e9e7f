"""Benchmark: the calibration from mild to strong truncation (scenario (a)'s mouse, wider and wider).

Scenario (a) of bench_calibration.py (the mouse thorax, independent 0.3 mm / 0.3 deg robot errors,
90 views) with the mouse scaled 1x, 1.5x, 2x and 3x in the same field of view: each step
truncates the projections more. Every method through calibration.calibrate with default settings
(no reach stated: the ROI model), ncc-lle-exact with the exterior model on reaching the mouse's
far side, and every method with that reach stated and ``exterior`` left at auto (the "(reach
stated)" rows); per width the
gauge-aligned reprojection error (mean, px), the truncation level (calibration.volume.
truncation_level), and whether the method ended worse than the nominal geometry. Writes
``sweep.md`` and ``sweep.json`` into ``--out``.

    .venv/bin/python bench/bench_truncation_sweep.py --out docs/results     # about 90 min on 2 cores
    .venv/bin/python bench/bench_truncation_sweep.py --out docs/results --keep --scales 3 --methods gdc

Every other calibration setting has its option as on ``robot-ct calibrate`` (``--exterior-iterations 30``, ...),
applied to every method and named in ``sweep.md``; the bench sets the method, the iterations, the sampling
seed and the exterior's reach itself.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_calibration import (EXTERIOR_METHOD, EXTERIOR_OWNS, _det, bench_settings, changed_sentence,  # noqa: E402
                               make_scenario, run_method)

from robot_ct_ros.cli import add_settings_arguments  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.calibration.volume import truncation_level  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.jobs.figures import method_notes  # noqa: E402

CORRECTING = calibration.method_names(include_none=False)
REACH_STATED = {f"{m} (reach stated)": m for m in CORRECTING}
"""Each method with the mouse's reach stated (exterior_half_width_mm, the mouse's far side) and ``exterior`` at its
default, auto: the object outside the ROI is modelled above the truncation level EXTERIOR_ABOVE."""
METHODS = ("none", *CORRECTING, EXTERIOR_METHOD, *REACH_STATED)


def run(method: str, sc, iterations: int, base=None):
    """One row's method on the scan ``sc``; ``base`` (CalibrationSettings, default: the defaults) holds the
    settings every correcting method starts from."""
    base = calibration.CalibrationSettings() if base is None else base
    if method in REACH_STATED:
        settings = base.replace(method=REACH_STATED[method], iterations=iterations, seed=0,
                                exterior_half_width_mm=sc.exterior_half_width_mm)
        return calibration.calibrate(sc.li, sc.nominal, sc.grid, settings, valid_mask=sc.mask)
    return run_method(method, sc, iterations, lambda s: None, seed=0, base=base)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scales", default="1,1.5,2,3", help="widths of the mouse, times scenario (a)'s")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--views", type=int, default=90)
    ap.add_argument("--det", type=_det, default=(64, 96), help="detector ROWSxCOLS after binning (default 64x96)")
    ap.add_argument("--vol", type=int, default=64, help="ROI grid voxels across (default 64)")
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/bench_sweep")
    ap.add_argument("--keep", action="store_true",
                    help="keep the cells of the existing sweep.json in --out that this run does not compute")
    add_settings_arguments(ap, skip=EXTERIOR_OWNS)  # the rows: the method, with or without the reach stated
    args = ap.parse_args(argv)
    base, changed = bench_settings(args, EXTERIOR_OWNS)
    run_methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    run_scales = [float(x) for x in args.scales.split(",")]
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()
    table, kept_from = {}, None
    if args.keep and os.path.exists(os.path.join(args.out, "sweep.json")):
        with open(os.path.join(args.out, "sweep.json")) as f:
            old = json.load(f)
        if ((old["views"], tuple(old.get("det", (64, 96))), old.get("vol", 64), old["iterations"], old["seed"],
             old.get("settings_changed", {})) != (args.views, args.det, args.vol, args.iterations, args.seed, changed)):
            raise SystemExit("--keep: the existing sweep.json was run with other --views, --det, --vol, --iterations, "
                             "--seed or calibration settings")
        table = {float(s): r for s, r in old["scales"].items()}
        kept_from = old.get("runs", [{"argv": "earlier run", "total_s": old.get("total_s")}])

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    for scale in run_scales:
        sc = make_scenario("a", args.views, args.det, args.vol, 4, args.seed, say, phantom_scale=scale)
        pts = roi_points(sc.grid)
        level = truncation_level(sc.li, sc.mask)
        row = table.setdefault(scale, {"errors_px": {}, "wall_s": {}, "model_ncc": {}, "notes": {}})
        row["truncation_level"] = level
        for m in run_methods:
            res = run(m, sc, args.iterations, base)
            geom = res.geom if hasattr(res, "geom") else res[0]
            row["errors_px"][m] = reprojection_error(geom, sc.true, pts)["mean_px"]
            row["wall_s"][m] = res.wall_s if hasattr(res, "wall_s") else res[3]
            history = getattr(res, "history", ())
            row["model_ncc"][m] = float(history[-1].projection_ncc) if history else None
            # the notes, and where the guard kept the nominal geometry, the error of the estimate before it
            row["notes"][m] = method_notes({m: res}, sc.nominal, sc.true, pts).get(m, [])
            say(f"  scale {scale:g}: {m} {row['errors_px'][m]:.3f} px ({row['wall_s'][m]:.1f} s)")
    scales = sorted(table)
    methods = [m for m in METHODS if any(m in table[s]["errors_px"] for s in scales)]
    methods += [m for s in scales for m in table[s]["errors_px"] if m not in methods]
    nominal = {s: r["errors_px"].get("none") for s, r in table.items()}
    lines = ["# Truncation sweep (bench/bench_truncation_sweep.py)", "",
             f"Scenario (a)'s mouse scaled in the same field of view, {args.views} views, robot errors 0.3 mm / "
             f"0.3 deg, {args.iterations} iterations, seed {args.seed}. Gauge-aligned reprojection error of ROI "
             "points, mean, px; bold: worse than the nominal geometry; (g): the guard kept the nominal geometry "
             "for the whole scan (its notes are in sweep.json). Second table: the model NCC (the last iteration's "
             "projection NCC, the guard's first test). Rows '(reach stated)': the method with the mouse's reach "
             "(exterior_half_width_mm, its far side) stated and exterior left at auto, which models the object "
             "outside the ROI above a truncation level of 0.3."
             + ("" if not changed else " " + changed_sentence(changed, "every method")), "",
             "| method | " + " | ".join(f"{s:g}x (truncation {table[s]['truncation_level']:.3f})" for s in scales) + " |",
             "| --- | " + " | ".join("---" for _ in scales) + " |"]
    for m in methods:
        cells = []
        for s in scales:
            e = table[s]["errors_px"].get(m)
            if e is None:
                cells.append("-")
                continue
            worse = m != "none" and nominal[s] is not None and e > nominal[s]
            kept = any("nominal geometry is kept" in n for n in table[s]["notes"][m])
            cells.append((f"**{e:.3f}**" if worse else f"{e:.3f}") + (" (g)" if kept else ""))
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    lines += ["", "| method | " + " | ".join(f"{s:g}x" for s in scales) + " |",
              "| --- | " + " | ".join("---" for _ in scales) + " |"]
    for m in methods:
        if all(table[s]["model_ncc"].get(m) is None for s in scales):
            continue
        lines.append(f"| {m} | " + " | ".join("-" if table[s]["model_ncc"].get(m) is None
                                              else f"{table[s]['model_ncc'][m]:.3f}" for s in scales) + " |")
    total = time.perf_counter() - t_all
    runs = (kept_from or []) + [{"argv": sys.argv[1:] if argv is None else list(argv), "total_s": total}]
    lines += ["", "; ".join(f"{r['argv'] if isinstance(r['argv'], str) else ' '.join(r['argv']) or 'defaults'}: "
                            f"{r['total_s'] / 60:.1f} min" for r in runs if r.get("total_s") is not None)
              + f" on {os.cpu_count()} CPU(s)" + (" (the cells this run did not compute are kept from the earlier "
                                                  "one, --keep)." if kept_from else ".")]
    with open(os.path.join(args.out, "sweep.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    with open(os.path.join(args.out, "sweep.json"), "w") as f:
        json.dump({"views": args.views, "det": list(args.det), "vol": args.vol, "iterations": args.iterations,
                   "seed": args.seed, "settings_changed": changed,
                   "scales": {str(s): table[s] for s in scales}, "runs": runs,
                   "total_s": sum(r["total_s"] for r in runs if r.get("total_s") is not None)}, f, indent=2)
    say(f"wrote {args.out}/sweep.md, sweep.json ({total / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
