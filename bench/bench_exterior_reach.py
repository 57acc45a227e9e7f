"""Benchmark: how far the exterior model must reach, on the interior neck of bench_interior.py.

The exterior model (calibrate(exterior="on"), robot_ct_ros.ct.calibration.exterior) fills a
coarse grid around the ROI out to ``exterior_half_width_mm`` from the ROI centre across the scan
axis; 0 means up to the sources, the largest region an object can fill. The scan does not state
the object's extent, so this measures what a wrong one costs: ncc-lle-exact with the exterior at
several reaches, on the 41 mm neck (half-width 20.5 mm) of bench_interior.py with its scan
arguments (180 views, axis +y, independent robot errors), the prior and the guard at the robots'
accuracy. Per reach: gauge-aligned reprojection error of ROI points (mean, p95, px), model NCC,
the guard's verdict, and the estimate before the guard. Writes ``exterior_reach.md`` and
``exterior_reach.json`` into ``--out``.

    .venv/bin/python bench/bench_exterior_reach.py --out docs/results      # about 35 min on 2 cores

Every other calibration setting has its option as on ``robot-ct calibrate`` (``--exterior-iterations 30``, ...),
named in ``exterior_reach.md``; the bench sets the method, the iterations, the exterior and its reach, and the
prior (the robots' accuracy, ``--sigma``) itself.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_calibration import EXTERIOR_OWNS, _det, bench_settings, changed_sentence  # noqa: E402
from bench_interior import make_scan  # noqa: E402

from robot_ct_ros.cli import add_settings_arguments  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402

OWNS = (*EXTERIOR_OWNS, "exterior_reach_guess")
"""Each row states its reach (0: up to the sources, never a guess)."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sigma", type=float, default=0.1, help="robot errors, mm and deg")
    ap.add_argument("--reaches", default="22,30,45,64,0",
                    help="exterior half-widths in mm, comma-separated (0: up to the sources)")
    ap.add_argument("--views", type=int, default=180)
    ap.add_argument("--det", type=_det, default=(96, 160), help="ROWSxCOLS binned pixels (110 um)")
    ap.add_argument("--nxy", type=int, default=96, help="ROI grid voxels across")
    ap.add_argument("--iterations", type=int, default=None,
                    help="outer iterations at most (default: the calibration's, its schedule's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/bench_exterior_reach")
    add_settings_arguments(ap, skip=OWNS)  # each row: the exterior model with its reach
    args = ap.parse_args(argv)
    if args.prior_sigma is not None:
        ap.error("--prior-sigma: the prior is the robots' accuracy (--sigma), as a user states it")
    base, changed = bench_settings(args, OWNS)
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(msg, flush=True)

    rows_det, cols_det = args.det
    sc = make_scan(args.sigma, views=args.views, det=(rows_det, cols_det), axis="y", seed=args.seed, nxy=args.nxy,
                   say=say)
    pts = roi_points(sc.grid)
    settings = (base if args.iterations is None else base.replace(iterations=args.iterations)).with_prior(
        args.sigma, args.sigma)
    nominal = reprojection_error(sc.nominal, sc.true, pts)
    rows = []
    for reach in (float(x) for x in args.reaches.split(",")):
        say(f"  exterior reaching {reach:g} mm:")
        t0 = time.perf_counter()
        result = calibration.calibrate(sc.li, sc.nominal, sc.grid,
                                       settings.replace(method="ncc-lle-exact", exterior="on",
                                                        exterior_half_width_mm=reach,
                                                        exterior_reach_guess=False),  # 0: up to the sources
                                       valid_mask=sc.mask, progress=lambda m: say(f"    {m}"))
        err = reprojection_error(result.geom, sc.true, pts)
        unguarded = (reprojection_error(sc.nominal.perturbed(result.params_unguarded), sc.true, pts)
                     if result.params_unguarded is not None else err)
        rows.append({"half_width_mm": reach, "mean_px": err["mean_px"], "p95_px": err["p95_px"],
                     "unguarded_mean_px": unguarded["mean_px"],
                     "model_ncc": float(result.history[-1].projection_ncc) if result.history else None,
                     "notes": list(result.notes), "wall_s": time.perf_counter() - t0})
        say(f"    {err['mean_px']:.3f} px (before the guard {unguarded['mean_px']:.3f} px), "
            f"{rows[-1]['wall_s']:.0f} s")
    report = {"bench": "bench/bench_exterior_reach.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "sigma": args.sigma,
              "settings_changed": changed,
              "body_mm": sc.body_mm, "fov_mm": sc.fov_mm, "nominal_mean_px": nominal["mean_px"],
              "nominal_p95_px": nominal["p95_px"], "rows": rows, "wall_s": time.perf_counter() - t_all}
    lines = ["# How far the exterior model must reach (bench/bench_exterior_reach.py)", "",
             f"The interior neck of bench_interior.py ({sc.body_mm:.0f} mm wide, half-width {sc.body_mm / 2:.1f} mm, "
             f"field of view {sc.fov_mm:.2f} mm, {args.views} views, {rows_det} x {cols_det} detector, axis +y), "
             f"robot errors {args.sigma:g} mm / "
             f"{args.sigma:g} deg, seed {args.seed}; ncc-lle-exact with the exterior model reaching the given "
             f"half-width from the ROI centre (0: up to the sources), at most {settings.iterations_text()} "
             f"iterations, the prior and the "
             f"guard at the robots' accuracy. The nominal geometry: {nominal['mean_px']:.3f} px mean, "
             f"{nominal['p95_px']:.3f} px p95 (gauge-aligned, ROI points)."
             + ("" if not changed else " " + changed_sentence(changed)), "",
             "| exterior half-width (mm) | reproj. error mean (px) | p95 (px) | before the guard (px) | model NCC "
             "| guard | wall time (s) |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        guard = "; ".join(n for n in r["notes"] if n.startswith("guard")) or "-"
        lines.append(f"| {'up to the sources' if r['half_width_mm'] == 0 else format(r['half_width_mm'], 'g')} "
                     f"| {r['mean_px']:.3f} | {r['p95_px']:.3f} | {r['unguarded_mean_px']:.3f} "
                     f"| {r['model_ncc']:.3f} | {guard} | {r['wall_s']:.0f} |")
    lines += ["", f"Total {report['wall_s'] / 60:.1f} min on this machine ({report['machine']})."]
    with open(os.path.join(args.out, "exterior_reach.json"), "w") as f:
        json.dump(report, f, indent=2)
    with open(os.path.join(args.out, "exterior_reach.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    say("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
