"""Benchmark: the exterior model's reach guessed where nobody states it (``exterior_reach_guess``, the default).

Without ``exterior_half_width_mm`` the loop scores candidate reaches by how well a model built from 9 in 10
views predicts the views it did not see (robot_ct_ros.ct.calibration.exterior.choose_reach, on the coarse
level, with the nominal geometry) and models the object outside the ROI that far. This bench calibrates the
strongly truncated scans of the other benches that way, with ``ncc-lle-exact`` and default settings
otherwise, each as its own bench runs it:

* ``mouse1.5``, ``mouse2``, ``mouse3``: the truncation sweep's mouse at 1.5, 2 and 3 times scenario (a)'s
  width (bench_truncation_sweep.py: 90 views, 3 iterations, robot errors 0.3 mm / 0.3 deg);
* ``b``, ``c``: bench_calibration.py's battery and full neck (90 views, 3 iterations);
* ``neck0.1``, ``neck0.3``: bench_interior.py's interior neck (180 views, axis +y, the prior at the robots'
  accuracy, robot errors 0.1 mm / 0.1 deg and 0.3 mm / 0.3 deg);
* ``bag48``, ``bag64`` and the other ``bag-*`` cases: what a user makes with ``robot-ct simulate`` on small
  centred detectors (robot_ct_ros.jobs.simulate: a scan bag of photon counts with dead pixels; the options in
  each case's title), read back as ``robot-ct calibrate`` reads it (its default grid and settings). ``bag48``
  and ``bag64`` are the carotid in its 13 cm neck through 90 views of 48 x 64 and 180 views of 64 x 96 pixels of
  110 um (fields of view of 2.6 and 3.9 mm, far side 83 mm); the others vary the phantom, the detector, the
  robot errors, a drift and the field of view. The stated reach is the phantom's far side from the ROI centre.

Each scan is calibrated again with the reach its bench states, with the same settings. The same scans
without a reach before the guess (``exterior_reach_guess`` off) are in those benches' own results
(``sweep.md``, ``results.md``, ``interior.md``; docs/calibration.md, "The exterior model"). Writes
``reach_guess.md`` and ``reach_guess.json`` into ``--out``.

    .venv/bin/python bench/bench_reach_guess.py --out docs/results                                # 15 min
    .venv/bin/python bench/bench_reach_guess.py --cases bags --out docs/results/reach_guess_bags  # 7 min
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

from bench_calibration import far_side_mm, make_scenario  # noqa: E402
from bench_interior import REACH_MM, make_scan  # noqa: E402

from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402

DEFAULTS = calibration.CalibrationSettings(method="ncc-lle-exact")
CASES = {
    "mouse1.5": "the sweep's mouse at 1.5 times the width",
    "mouse2": "the sweep's mouse at 2 times the width",
    "mouse3": "the sweep's mouse at 3 times the width",
    "b": "(b), the battery",
    "c": "(c), the carotid plaque in a full neck",
    "neck0.1": "the interior neck, robot errors 0.1 mm / 0.1 deg",
    "neck0.3": "the interior neck, robot errors 0.3 mm / 0.3 deg",
}
BAG_SCANS = {
    "bag48": {"phantom": "carotid", "views": 90, "rows": 48, "cols": 64},
    "bag64": {"phantom": "carotid", "views": 180, "rows": 64, "cols": 96},
    "bag-carotid-thin": {"phantom": "carotid", "views": 120, "rows": 32, "cols": 128},
    "bag-carotid-0.3": {"phantom": "carotid", "views": 90, "rows": 48, "cols": 64, "sigma_mm": 0.3, "sigma_deg": 0.3},
    "bag-carotid-drift": {"phantom": "carotid", "views": 90, "rows": 48, "cols": 64, "drift_mm": 0.3},
    "bag-carotid-fov1.5": {"phantom": "carotid", "views": 90, "rows": 64, "cols": 64, "fov_mm": 1.5},
    "bag-mouse": {"phantom": "mouse", "views": 90, "rows": 32, "cols": 48},
    "bag-mouse-0.3": {"phantom": "mouse", "views": 120, "rows": 48, "cols": 96, "sigma_mm": 0.3, "sigma_deg": 0.3},
    "bag-battery": {"phantom": "battery", "views": 120, "rows": 48, "cols": 96},
    "bag-battery-0.3": {"phantom": "battery", "views": 90, "rows": 32, "cols": 64, "sigma_mm": 0.3, "sigma_deg": 0.3},
}
"""The ``robot-ct simulate`` cases: robot_ct_ros.jobs.simulate.simulate_bag's options (robot errors 0.1 mm / 0.1 deg
where not given)."""


def bag_title(case: str) -> str:
    """The command line that makes ``case``'s bag (its seed aside)."""
    return "robot-ct simulate " + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in BAG_SCANS[case].items())


GROUPS = {"scans": [c for c in CASES if c not in BAG_SCANS], "bags": list(BAG_SCANS)}
"""``--cases`` names for several cases: the other benches' scans (reach_guess.md) and the robot-ct simulate
bags (reach_guess_bags/)."""
CASES.update({case: bag_title(case) for case in BAG_SCANS})
SWEEP_ITERATIONS = 3
"""bench_truncation_sweep.py's and bench_calibration.py's outer iterations; the interior neck runs the defaults."""


def scan(case: str, seed: int, say):
    """(scan namespace with li, mask, nominal, true, grid; the reach its bench states, mm; calibration settings)."""
    if case.startswith("neck"):
        sigma = float(case[4:])
        sc = make_scan(sigma, views=180, det=(96, 160), axis="y", seed=seed, nxy=96, say=say)
        return sc, REACH_MM, DEFAULTS.with_prior(sigma, sigma)
    if case in BAG_SCANS:
        return bag_scan(case, seed, say)
    key, scale = ("a", float(case[5:])) if case.startswith("mouse") else (case, 1.0)
    sc = make_scenario(key, 90, (64, 96), 64, 4, seed, say, phantom_scale=scale)
    return sc, float(sc.exterior_half_width_mm), DEFAULTS.replace(iterations=SWEEP_ITERATIONS, seed=0)


def bag_scan(case: str, seed: int, say):
    """A ``robot-ct simulate`` bag with ``case``'s options (BAG_SCANS), written to a temporary folder and read back as
    ``robot-ct calibrate`` reads it: (scan with li, mask, nominal, true, grid; the phantom's far side from the ROI
    centre, mm; default settings)."""
    import tempfile
    from types import SimpleNamespace

    from robot_ct_ros.bag import read_scan
    from robot_ct_ros.jobs.calibrate import scan_grid
    from robot_ct_ros.jobs.simulate import make_phantom, simulate_bag

    options = BAG_SCANS[case]
    with tempfile.TemporaryDirectory() as tmp:
        bag = simulate_bag(os.path.join(tmp, "scan"), seed=seed, progress=False, say=say, **options)
        scan = read_scan(bag)
    li, mask = scan.to_line_integrals()
    grid = scan_grid(scan)
    sc = SimpleNamespace(li=li, mask=mask, nominal=scan.geom, true=scan.geom_true, grid=grid)
    return sc, far_side_mm(make_phantom(options["phantom"], seed), grid.center_mm), DEFAULTS


def outcome(res, sc, pts) -> dict:
    """A calibration's error (gauge-aligned, mean px over ``pts``), its error before the guard, whether the
    guard kept the nominal geometry, and its outer iterations."""
    err = reprojection_error(res.geom, sc.true, pts)["mean_px"]
    unguarded = (reprojection_error(sc.nominal.perturbed(res.params_unguarded), sc.true, pts)["mean_px"]
                 if res.params_unguarded is not None else err)
    return {"error_px": err, "unguarded_px": unguarded,
            "kept_nominal": any("nominal geometry is kept" in n for n in res.notes), "iterations": len(res.history)}


def ncc3(x) -> str:
    """A model NCC for the table, "-" where the loop ran no iteration."""
    return "-" if x is None else f"{x:.3f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cases", default="scans", help=f"comma-separated, of {', '.join(CASES)}, or the groups "
                    f"{', '.join(GROUPS)} (default scans)")
    ap.add_argument("--seed", type=int, default=0, help="the scans' seed: phantom, errors, noise")
    ap.add_argument("--out", default="out/bench_reach_guess")
    args = ap.parse_args(argv)
    cases = [c for name in args.cases.split(",") if name.strip() for c in GROUPS.get(name.strip(), [name.strip()])]
    unknown = [c for c in cases if c not in CASES]
    if unknown or not cases:
        ap.error(f"--cases: unknown {', '.join(unknown) or '(none given)'} (known: {', '.join(CASES)})")
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    report = {"bench": "bench/bench_reach_guess.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "seed": args.seed, "rows": []}
    for case in cases:
        sc, stated_mm, settings = scan(case, args.seed, say)
        pts = roi_points(sc.grid)
        said = []
        t0 = time.perf_counter()
        res = calibration.calibrate(sc.li, sc.nominal, sc.grid, settings, valid_mask=sc.mask,
                                    progress=lambda m: said.append((time.perf_counter() - t0, m)),
                                    final_volume=False)
        wall = time.perf_counter() - t0
        guess_s = next((t for t, m in said if "was not stated" in m), float("nan"))
        row = {"case": case, "title": CASES[case], "stated_reach_mm": stated_mm,
               "guessed_reach_mm": res.settings.exterior_half_width_mm,
               "modelled": "the object outside the ROI was modelled (exterior model)" in res.notes,
               "nominal_px": reprojection_error(sc.nominal, sc.true, pts)["mean_px"], **outcome(res, sc, pts),
               "model_ncc": float(res.history[-1].projection_ncc) if res.history else None,
               "guess_s": guess_s, "wall_s": wall, "notes": list(res.notes)}
        t0 = time.perf_counter()  # the same scan and settings with the reach its bench states
        res = calibration.calibrate(sc.li, sc.nominal, sc.grid, settings.replace(exterior_half_width_mm=stated_mm),
                                    valid_mask=sc.mask, final_volume=False)
        row["stated"] = {**outcome(res, sc, pts), "wall_s": time.perf_counter() - t0}
        report["rows"].append(row)
        say(f"{case}: reach {row['guessed_reach_mm']:.1f} mm guessed: {row['nominal_px']:.3f} -> {row['error_px']:.3f} px "
            f"(before the guard {row['unguarded_px']:.3f}), {wall:.0f} s; stated {stated_mm:.1f} mm: "
            f"{row['stated']['error_px']:.3f} px, {row['stated']['wall_s']:.0f} s")
    report["wall_s"] = time.perf_counter() - t_all
    lines = ["# The exterior's reach guessed where nobody states it (bench/bench_reach_guess.py)", "",
             "Each strongly truncated scan calibrated by `ncc-lle-exact` with default settings and no "
             "`exterior_half_width_mm`: the loop guesses the reach by held-out prediction "
             "(`exterior_reach_guess`, on by default; robot_ct_ros.ct.calibration.exterior.choose_reach) and "
             "models the object outside the ROI that far. The mice, (b) and (c) run 3 outer iterations at most, "
             "as their benches do; the interior neck the defaults, with the prior at the robots' accuracy; the "
             "`robot-ct simulate` bags the defaults on the grid `robot-ct calibrate` gives them. "
             f"Seed {args.seed}. Error: gauge-aligned reprojection error of ROI points, mean, px. *Stated*: the "
             "same scan and settings with the reach its own bench states (the object's far side from the ROI "
             "centre). *Model NCC*: the estimation model's projection NCC at the end, which the guard's floor "
             "reads (`guard_min_ncc_exterior`). The same scans without a reach before the guess (what "
             "`exterior_reach_guess` off gives) are the rows without a reach in `sweep.md`, `results.md` and "
             "`interior.md`.", "",
             "| scan | nominal (px) | guessed reach (mm) | guessed reach, ncc-lle-exact (px) | before the guard (px) "
             "| guard | model NCC | iterations | the guess (s) | wall time (s) | stated reach (mm) | stated reach, "
             "ncc-lle-exact (px) | wall time (s) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in report["rows"]:
        verdict = "kept nominal" if r["kept_nominal"] else "applied"
        st = r["stated"]
        lines.append(f"| {r['title']} | {r['nominal_px']:.3f} | {r['guessed_reach_mm']:.1f} | {r['error_px']:.3f} "
                     f"| {r['unguarded_px']:.3f} | {verdict} | {ncc3(r['model_ncc'])} | {r['iterations']} "
                     f"| {r['guess_s']:.0f} "
                     f"| {r['wall_s']:.0f} | {r['stated_reach_mm']:.1f} "
                     f"| {st['error_px']:.3f}{' (guard: nominal kept)' if st['kept_nominal'] else ''} "
                     f"| {st['wall_s']:.0f} |")
    lines += ["", "Notes:", ""]
    for r in report["rows"]:
        lines.append(f"- {r['case']}: " + "; ".join(r["notes"]))
    lines += ["", f"Total {report['wall_s'] / 60:.1f} min on this machine ({report['machine']})."]
    with open(os.path.join(args.out, "reach_guess.json"), "w") as f:
        json.dump(report, f, indent=2)
    with open(os.path.join(args.out, "reach_guess.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
