"""Benchmark: can the data tell how far the object reaches? (the exterior model's ``exterior_half_width_mm``)

The exterior model (robot_ct_ros.ct.calibration.exterior) needs the object's reach from the ROI centre, and
a scan does not state it: ``auto`` models the exterior only once the user gives it
(docs/calibration.md, "The exterior model"). This bench asks whether the data could choose it instead, with
the two consistency figures at hand, on two strongly truncated scans whose reach is known:

* ``neck``: the interior neck of bench_interior.py (41 mm, far side 29.5 mm from the ROI centre, stated as
  30 mm as bench_interior.py does; 180 views, axis +y, robot errors ``--sigma``), its data binned 4 x 4 (the
  ``exterior`` schedule's coarse level);
* ``mouse``: the truncation sweep's mouse at 3 times scenario (a)'s width (bench_truncation_sweep.py; far
  side 13.5 mm, as the sweep states it; 90 views, robot errors 0.3 mm / 0.3 deg), its data binned 2 x 2.

For each reach, the exterior model (ROI + exterior with the default settings' voxels, subsets and the
``exterior`` schedule's SIRT passes: 0.5 mm, 10, 30) is
reconstructed with the nominal geometry from 9 in 10 views (two interleaved folds), and scored by

* *held-out NCC*: the mean projection NCC of its reprojection into the views it did not see;
* *fit NCC*: the same on views it was built from (every tenth of them), the kind of figure the guard's
  first test reads (the estimation model's projection NCC).

Then ncc-lle-exact calibrates the scan (default settings: the ``exterior`` schedule; the neck with the prior
at the robots' accuracy, as bench_interior.py) with the reach each figure picks, the stated reach, and
``--also`` reaches. Writes ``reach_selection.md`` and ``reach_selection.json`` into ``--out``.

    .venv/bin/python bench/bench_reach_selection.py --out docs/results      # about 10 min on 2 cores
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

from bench_calibration import make_scenario  # noqa: E402
from bench_interior import REACH_MM, make_scan  # noqa: E402

from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.calibration.exterior import held_out_ncc  # noqa: E402
from robot_ct_ros.ct.calibration.masks import bin_masked  # noqa: E402
from robot_ct_ros.ct.calibration.volume import estimation_grid  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402

CASES = {
    "neck": {"binning": 4, "reaches": "8,12,16,20,25,30,40,60,0", "also": "20"},
    "mouse": {"binning": 2, "reaches": "3,4,5,6,8,10,12,15,20", "also": "9"},
}
DEFAULTS = calibration.CalibrationSettings()
"""The exterior model's voxels, subsets and padding, as a user gets them."""
EXTERIOR_PASSES = DEFAULTS.plan(exterior=True)["exterior_iterations"]
"""The default ``exterior`` schedule's SIRT passes of the exterior model (30)."""
FOLDS = 10
HELD_OUT = (0, 5)
"""The interleaved folds held out in turn: views f, f + 10, f + 20, ..."""


def scan(case: str, sigma: float, seed: int, say):
    """(scan namespace with li, mask, nominal, true, grid; the reach a user states, mm; calibration settings)."""
    if case == "neck":
        sc = make_scan(sigma, views=180, det=(96, 160), axis="y", seed=seed, nxy=96, say=say)
        # the reach its user states (bench_interior's REACH_MM; the far side lies 29.5 mm away); the prior at the
        # robots' accuracy
        return sc, REACH_MM, DEFAULTS.replace(method="ncc-lle-exact").with_prior(sigma, sigma)
    sc = make_scenario("a", 90, (64, 96), 64, 4, seed, say, phantom_scale=3.0)
    return sc, float(sc.exterior_half_width_mm), DEFAULTS.replace(method="ncc-lle-exact", seed=0)


def scores(sc, binning: int, reach_mm: float) -> tuple[float, float]:
    """(held-out NCC, fit NCC) of the exterior model reaching ``reach_mm``, built with the nominal geometry
    (exterior.held_out_ncc, the score the loop's reach guess uses)."""
    li, mask = bin_masked(sc.li, sc.mask, binning)
    grid = estimation_grid(sc.grid, DEFAULTS.padding).binned(binning)
    return held_out_ncc(li, sc.nominal.binned(binning), grid, mask, reach_mm, voxel_mm=DEFAULTS.exterior_voxel_mm,
                        iterations=EXTERIOR_PASSES, subsets=DEFAULTS.exterior_subsets, folds=FOLDS,
                        held_out=HELD_OUT, with_fit=True)


def mm_list(text: str) -> list[float]:
    """``--*-reaches`` / ``--*-also``: comma-separated reaches, mm, none negative (0: up to the sources)."""
    try:
        values = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of mm: {text!r}") from None
    if any(not v >= 0 for v in values):
        raise argparse.ArgumentTypeError(f"a reach is a distance from the ROI centre, 0 or more mm: {text!r}")
    return values


def f5(x) -> str:
    """A score for the table, "-" where the reach was only calibrated."""
    return "-" if x is None else f"{x:.5f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--sigma", type=float, default=0.1, help="the neck's robot errors, mm and deg")
    ap.add_argument("--seed", type=int, default=0)
    for case, c in CASES.items():
        ap.add_argument(f"--{case}-reaches", type=mm_list, default=c["reaches"],
                        help=f"{case}: the reaches scored, mm (0: up to the sources)")
        ap.add_argument(f"--{case}-also", type=mm_list, default=c["also"],
                        help=f"{case}: reaches calibrated besides the picks, mm")
    ap.add_argument("--out", default="out/bench_reach_selection")
    args = ap.parse_args(argv)
    unknown = [c for c in args.cases.split(",") if c.strip() and c.strip() not in CASES]
    if unknown:
        ap.error(f"--cases: unknown {', '.join(unknown)} (known: {', '.join(CASES)})")
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    report = {"bench": "bench/bench_reach_selection.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "cases": {}}
    lines = ["# Can the data tell the object's reach? (bench/bench_reach_selection.py)", "",
             f"The exterior model (ROI + exterior on {DEFAULTS.exterior_voxel_mm:g} mm voxels, "
             f"{EXTERIOR_PASSES} SIRT passes, {DEFAULTS.exterior_subsets} subsets) "
             "reconstructed with the "
             "nominal geometry from 9 in 10 views, for each reach: *held-out NCC*, the mean projection NCC in the "
             "views it did not see (two interleaved folds), and *fit NCC*, the same in views it was built from. "
             "Then ncc-lle-exact (default settings, the `exterior` schedule) with the reach each figure picks, the "
             "reach a user states (the object's far side), and more. Error: gauge-aligned reprojection error of ROI "
             "points, mean, px; in brackets the estimate before the guard where the guard kept the nominal "
             "geometry.", ""]
    for case in (c.strip() for c in args.cases.split(",") if c.strip()):
        cfg = CASES[case]
        sc, stated_mm, settings = scan(case, args.sigma, args.seed, say)
        pts = roi_points(sc.grid)
        nominal_px = reprojection_error(sc.nominal, sc.true, pts)["mean_px"]
        rows = {}
        for reach in getattr(args, f"{case}_reaches"):
            t0 = time.perf_counter()
            held, fit = scores(sc, cfg["binning"], reach)
            rows[reach] = {"reach_mm": reach, "held_out_ncc": held, "fit_ncc": fit,
                           "score_s": time.perf_counter() - t0}
            say(f"{case}: reach {reach:g} mm: held-out NCC {held:.5f}, fit NCC {fit:.5f}")
        by_held = max(rows, key=lambda r: rows[r]["held_out_ncc"])
        by_fit = max(rows, key=lambda r: rows[r]["fit_ncc"])
        picks = {"held-out NCC": by_held, "fit NCC": by_fit, "stated": stated_mm}
        calibrate_at = {r: [] for r in getattr(args, f"{case}_also")}
        for why, r in picks.items():
            calibrate_at.setdefault(r, []).append(why)
        for reach, why in sorted(calibrate_at.items()):
            t0 = time.perf_counter()
            # reach 0 with the guess off: exterior auto keeps the ROI model (it does not reach up to the sources)
            res = calibration.calibrate(sc.li, sc.nominal, sc.grid,
                                        settings.replace(exterior_half_width_mm=reach, exterior_reach_guess=False),
                                        valid_mask=sc.mask)
            err = reprojection_error(res.geom, sc.true, pts)["mean_px"]
            unguarded = (reprojection_error(sc.nominal.perturbed(res.params_unguarded), sc.true, pts)["mean_px"]
                         if res.params_unguarded is not None else err)
            row = rows.setdefault(reach, {"reach_mm": reach, "held_out_ncc": None, "fit_ncc": None})
            row.update({"picked_by": why, "error_px": err, "unguarded_px": unguarded,
                        "kept_nominal": any("nominal geometry is kept" in n for n in res.notes),
                        "iterations": len(res.history), "calibrate_s": time.perf_counter() - t0})
            say(f"{case}: reach {reach:g} mm ({', '.join(why) or 'also'}): {err:.3f} px (before the guard "
                f"{unguarded:.3f}), {row['calibrate_s']:.0f} s")
        report["cases"][case] = {"stated_reach_mm": stated_mm, "nominal_px": nominal_px, "binning": cfg["binning"],
                                 "picks": picks, "rows": [rows[r] for r in sorted(rows, key=lambda r: (r == 0, r))]}
        title = (f"interior neck ({sc.body_mm:.0f} mm, field of view {sc.fov_mm:.2f} mm), robot errors "
                 f"{args.sigma:g} mm / {args.sigma:g} deg" if case == "neck" else
                 "the sweep's mouse at 3 times the width (field of view 7.75 mm), robot errors 0.3 mm / 0.3 deg")
        lines += [f"## {case}: {title}, seed {args.seed}", "",
                  f"Stated reach (the far side's distance from the ROI centre) {stated_mm:g} mm; data binned "
                  f"{cfg['binning']} x {cfg['binning']} for the scores; nominal geometry {nominal_px:.3f} px. "
                  f"Held-out NCC picks {by_held:g} mm, fit NCC "
                  f"{'up to the sources' if by_fit == 0 else format(by_fit, 'g') + ' mm'}.", "",
                  "| reach (mm) | held-out NCC | fit NCC | picked by | ncc-lle-exact (px) | iterations "
                  "| wall time (s) |",
                  "| --- | --- | --- | --- | --- | --- | --- |"]
        for r in report["cases"][case]["rows"]:
            err = "-" if "error_px" not in r else (f"{r['error_px']:.3f}" + (
                f" ({r['unguarded_px']:.3f}, guard)" if r["kept_nominal"] else ""))
            lines.append(f"| {'up to the sources' if r['reach_mm'] == 0 else format(r['reach_mm'], 'g')} "
                         f"| {f5(r['held_out_ncc'])} | {f5(r['fit_ncc'])} | {', '.join(r.get('picked_by', [])) or '-'} "
                         f"| {err} | {r.get('iterations', '-')} | "
                         f"{format(r['calibrate_s'], '.0f') if 'calibrate_s' in r else '-'} |")
        lines.append("")
    report["wall_s"] = time.perf_counter() - t_all
    lines.append(f"Total {report['wall_s'] / 60:.1f} min on this machine ({report['machine']}).")
    with open(os.path.join(args.out, "reach_selection.json"), "w") as f:
        json.dump(report, f, indent=2)
    with open(os.path.join(args.out, "reach_selection.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
