"""Benchmark: which angular harmonics of a detector shift the alternating loop sees, and what the focus does.

docs/calibration.md section 10 says that in a full scan the view at angle t and the one at t + pi
see the same rays reversed, so a detector shift along u that is odd under the half turn (angular
harmonics k = 3, 5, ...) leaves the data consistent and the loop cannot see it, and that
``focus_conjugate_modes`` (image entropy) can set such modes instead. This bench measures both.

The scan: bench_calibration's scenario (a) (the mouse's thorax through the seed system's robotic ROI
trajectory, a full circle, photon noise), but with one error only: every view's detector shifted
along u by ``--amplitude-px`` x cos(k t), t the view's angle about the ROI centre
(constraints.view_angles), for each k of ``--harmonics``. k = 1 is nearly the gauge (a
translation of the object). Each scan is calibrated from its nominal geometry with ``ncc-lle-exact``
and the default settings (every setting has its ``robot-ct calibrate`` option), and, for the k of
``--focus``, once more with ``focus_modes`` {"shift": (k,)} (calibrate(focus_modes=); the library
parameter, off by default).

Reported per row: the gauge-aligned reprojection error of ROI points before and after (mean px,
metrics.reprojection_error), and the injected harmonic left in the estimate: each view's shift of
the ROI centre's projection along u, estimate (moved into the true gauge) less truth, fitted with
cos(k t) and sin(k t); its amplitude in px and as a share of the injected one (none for k = 1, whose
harmonic the gauge removes).

    .venv/bin/python bench/bench_conjugate_modes.py --out docs/results     # about 10 min on 2 cores
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_calibration import BENCH_OWNS, bench_settings, changed_sentence, make_scenario  # noqa: E402

from robot_ct_ros.cli import add_settings_arguments  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.calibration.constraints import view_angles  # noqa: E402
from robot_ct_ros.ct.metrics import remove_gauge, reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.jobs.figures import markdown_table  # noqa: E402

COLUMNS = (("k", "harmonic k", "{}"), ("method", "method", "{}"),
           ("nominal_px", "nominal: reproj. error mean (px)", "{:.3f}"),
           ("after_px", "after: reproj. error mean (px)", "{:.3f}"),
           ("mode_left_px", "harmonic left (px)", "{:.3f}"), ("mode_left_share", "share left", "{:.2f}"),
           ("wall_s", "wall time (s)", "{:.1f}"))


def harmonic_amplitude(shift_px: np.ndarray, angles: np.ndarray, k: int) -> float:
    """Amplitude (px) of the least-squares fit a cos(k t) + b sin(k t) (plus a constant) to ``shift_px``."""
    basis = np.stack([np.ones_like(angles), np.cos(k * angles), np.sin(k * angles)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, shift_px, rcond=None)
    return float(np.hypot(coef[1], coef[2]))


def centre_shift_px(est, true, grid, points) -> np.ndarray:
    """Per view, how far ``est`` (moved into ``true``'s gauge on ``points``) puts the grid centre's
    projection from where ``true`` puts it, along u (px)."""
    aligned = remove_gauge(est, true, points)
    c = np.asarray(grid.center_mm)[None]
    return aligned.project_points(c)[:, 0, 0] - true.project_points(c)[:, 0, 0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--harmonics", default="1,2,3,4,5", help="angular harmonics k of the injected shift")
    ap.add_argument("--focus", default="3,5", help="harmonics also run with focus_modes on that k")
    ap.add_argument("--amplitude-px", type=float, default=1.0, help="amplitude of the injected detector shift, px")
    ap.add_argument("--views", type=int, default=90)
    ap.add_argument("--det", default="64x96", help="ROWSxCOLS binned pixels (220 um)")
    ap.add_argument("--vol", type=int, default=64, help="ROI grid voxels across")
    ap.add_argument("--seed", type=int, default=0, help="scan seed: phantom and noise")
    ap.add_argument("--out", default="out/bench_conjugate_modes")
    add_settings_arguments(ap, skip=BENCH_OWNS)
    args = ap.parse_args(argv)
    settings, changed = bench_settings(args)
    settings = settings.replace(method="ncc-lle-exact")
    harmonics = [int(k) for k in args.harmonics.split(",") if k.strip()]
    focus = {int(k) for k in args.focus.split(",") if k.strip()}
    rows_det, cols_det = (int(x) for x in args.det.lower().split("x"))
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(f"[{time.perf_counter() - t_all:7.1f} s] {msg}", flush=True)

    rows = []
    for k in harmonics:
        def harmonic(nominal, k=k):
            p = np.zeros((nominal.n_views, 9))
            t = view_angles(nominal)
            p[:, 3] = args.amplitude_px * nominal.col_pitch_mm * np.cos(k * t)
            return p

        say(f"k = {k}: scan")
        sc = make_scenario("a", args.views, (rows_det, cols_det), args.vol, 4, args.seed, say, errors_of=harmonic)
        pts = roi_points(sc.grid)
        t = view_angles(sc.true, sc.grid.center_mm)
        nominal_px = reprojection_error(sc.nominal, sc.true, pts)["mean_px"]
        injected = harmonic_amplitude(centre_shift_px(sc.nominal, sc.true, sc.grid, pts), t, k)
        runs = [("ncc-lle-exact", None)] + ([(f"ncc-lle-exact + focus (shift, k = {k})", {"shift": (k,)})]
                                            if k in focus else [])
        for name, modes in runs:
            say(f"k = {k}: {name}")
            t0 = time.perf_counter()
            res = calibration.calibrate(sc.li, sc.nominal, sc.grid, settings, valid_mask=sc.mask, focus_modes=modes,
                                        progress=lambda m: say(f"    {m}"))
            wall = time.perf_counter() - t0
            left = harmonic_amplitude(centre_shift_px(res.geom, sc.true, sc.grid, pts), t, k)
            rows.append({"k": k, "method": name, "nominal_px": nominal_px,
                         "after_px": reprojection_error(res.geom, sc.true, pts)["mean_px"],
                         "injected_px": injected, "mode_left_px": left,
                         # k = 1 is nearly the gauge: its injected harmonic is gone once the gauge is removed
                         "mode_left_share": left / injected if injected > 0.05 * args.amplitude_px else None,
                         "wall_s": wall,
                         "notes": list(res.notes)})
            say(markdown_table(rows[-1:], COLUMNS))

    table = markdown_table(rows, COLUMNS)
    lines = ["# Which harmonics of a detector shift the loop sees (bench/bench_conjugate_modes.py)", "",
             f"Scenario (a)'s scan (bench_calibration.make_scenario: the mouse's thorax, the seed system's robotic "
             f"ROI trajectory over a full circle, {args.views} views, {rows_det} x {cols_det} detector of 220 um, "
             f"photon noise) with one error only: each view's detector shifted along u by {args.amplitude_px:g} px "
             f"x cos(k t), t the view's angle about the ROI centre. Calibrated from the nominal geometry by "
             f"ncc-lle-exact with the default settings, at most {settings.iterations_text()} iterations; the focus "
             f"rows add focus_modes {{'shift': (k,)}} (image entropy, constraints.focus_conjugate_modes). "
             "*reproj. error*: gauge-aligned, ROI points, mean px. *harmonic left*: each view's shift of the ROI "
             "centre's projection along u, estimate (in the true gauge) less truth, fitted with cos(k t) and "
             "sin(k t): the amplitude, and its share of the injected one (the nominal geometry's, about "
             f"{args.amplitude_px:g} px; '-' where the gauge removes it, k = 1). Wall time on this machine "
             f"({platform.machine()}, {os.cpu_count()} cores), "
             "shared with other jobs.", ""]
    if changed:
        lines += [changed_sentence(changed, "every run"), ""]
    lines += [table, ""]
    lines += [f"- k = {r['k']}, {r['method']}: {'; '.join(r['notes'])}" for r in rows if r["notes"]]
    wall = time.perf_counter() - t_all
    lines += ["", f"Total {wall / 60:.1f} min."]
    report = {"bench": "bench/bench_conjugate_modes.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "settings": settings.to_dict(),
              "settings_changed": changed, "amplitude_px": args.amplitude_px, "views": args.views,
              "detector": [rows_det, cols_det], "rows": rows, "wall_s": wall}
    with open(os.path.join(args.out, "conjugate_modes.json"), "w") as f:
        json.dump(report, f, indent=2, default=str)
    with open(os.path.join(args.out, "conjugate_modes.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    say(f"wrote {args.out}/conjugate_modes.md, conjugate_modes.json ({wall / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
