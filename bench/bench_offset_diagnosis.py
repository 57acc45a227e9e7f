"""Benchmark: why the seed system's offset-detector scan is corrected less than a centred one.

The scans are bench_fullsize.py's cut-down seed-system scans (make_scan: exact line integrals, photon
counting, the rotation axis +y, independent robot errors per view), of a neck that fits every field of
view here (``--body``, default 15 mm), through fields of view from the centred detector's own (0) to the
offset detector's 50 mm. The estimator is the loop's coarse level: ncc-lle-exact's coarse
configuration on 2 x 2 binned data, the prior at the robots' accuracy, against FDK volumes on the
loop's estimation grid, zero outside the field of view (``projections`` complete with ``fov_support``
on; the object lies inside the field of view). Every figure is the mean gauge-aligned reprojection error of ROI
points (px of the scan's detector) after one pass over all views unless a row says otherwise.

FDK is a sum over views, so a view's own part of a volume (its "own term": its filtered projection
back-projected alone) can be moved or taken out exactly. The views are handled in ``--folds`` folds of
views 360/folds degrees apart, whose own terms hardly overlap in the detail a view registers on; a
fold's own terms are one back-projection. The rows:

* the loop's alternation: the FDK with the geometry the pass starts from, pass after pass;
* the true-geometry FDK: what the estimator reaches when the volume is right;
* the true-geometry FDK with each view's own term placed with the nominal geometry, and the nominal
  FDK with each view's own term placed with the true one: how much of a view's estimate its own term
  decides;
* the true-geometry FDK without the view's own term: a held-out volume (the other views placed
  exactly), registered against the view's data as measured;
* the same, with the view's own term also taken out of its data (its own term reprojected through
  the geometry it was back-projected with): what the other views, placed exactly, tell about a view;
* that leave-one-out from the nominal geometry, pass after pass (the other views' errors in).

Writes ``offset_diagnosis.md`` and ``.json`` into ``--out``.

    .venv/bin/python bench/bench_offset_diagnosis.py --out docs/results     # about 10 min on 2 cores
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from types import SimpleNamespace

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_fullsize import make_scan, scan_layout  # noqa: E402

from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct.calibration.lle.estimator import estimate_views  # noqa: E402
from robot_ct_ros.ct.calibration.masks import bin_masked, roi_support_mask, usable_data  # noqa: E402
from robot_ct_ros.ct.calibration.registry import get_method  # noqa: E402
from robot_ct_ros.ct.calibration.volume import estimation_grid  # noqa: E402
from robot_ct_ros.ct.field_of_view import field_of_view_mask  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.ct.projector import forward_project  # noqa: E402
from robot_ct_ros.ct.reconstruction import fdk_backproject, fdk_filter_projections  # noqa: E402
from robot_ct_ros.ct.trajectory import SeedSystem  # noqa: E402

METHOD = "ncc-lle-exact"
ROWS = (
    ("loop", "the FDK with the geometry the pass starts from (the loop's alternation), from the nominal geometry"),
    ("true", "the true-geometry FDK"),
    ("own_misplaced", "the true-geometry FDK, each view's own term placed with the nominal geometry"),
    ("own_placed", "the nominal FDK, each view's own term placed with the true geometry"),
    ("held_out", "the true-geometry FDK without the view's own term (held out), the data as measured"),
    ("left_out", "the true-geometry FDK without the view's own term, which is taken out of its data too"),
    ("left_out_loop", "each view's own term out of the volume and its data, from the nominal geometry"),
)
"""Row key and what the view is registered against ("loop" and "left_out_loop" run ``--passes`` passes, the others one)."""


class Level:
    """One scan at the loop's coarse level: binned data, FDK volumes and their per-view own terms."""

    def __init__(self, nominal, true, li, mask, grid, settings, folds: int):
        li, mask = usable_data(li, mask)
        self.nominal, self.true = nominal, true
        self.points = roi_points(grid)
        self.grid = estimation_grid(grid, settings.padding).binned(2)
        self.li, self.mask = bin_masked(li, mask, 2)
        self.nom, self.true_c = nominal.binned(2), true.binned(2)
        self.fov = field_of_view_mask(self.nom, self.grid)
        self.config = get_method(METHOD).configs(settings)[0]
        self.n = self.nom.n_views
        self.folds = [np.arange(f, self.n, folds) for f in range(min(folds, self.n))]

    def error_px(self, params) -> float:
        return float(reprojection_error(self.nominal.perturbed(params), self.true, self.points)["mean_px"])

    def filtered(self, geom):
        """FDK's weighted, ramp-filtered projections (and their geometry) for ``geom``."""
        return fdk_filter_projections(self.li, geom, center_mm=self.grid.center_mm, valid_mask=self.mask)

    def backproject(self, filtered, views=None) -> np.ndarray:
        """The FDK sum over ``views`` (default all) of ``filtered`` = (projections, geometry), kept to the field of view."""
        q, geom = filtered
        if views is not None:
            q, geom = q[views], geom.subset(views)
        return np.where(self.fov, fdk_backproject(q, geom, self.grid), np.float32(0.0)).astype(np.float32)

    def estimate(self, params, volume):
        """One pass of the estimator over every view against ``volume``."""
        return estimate_views(self.li, self.nom, params, volume, self.grid, self.config, self.mask)[0]

    def per_fold(self, params, volume_of_fold, take_out_of_data=None):
        """One pass, fold by fold, against ``volume_of_fold(views)``; ``take_out_of_data`` = (filtered, geometry):
        each view's own term, back-projected from ``filtered`` and reprojected through that geometry, is
        subtracted from its data. The ROI support is the whole scan's, as one pass over all views would use."""
        out = params.copy()
        support = roi_support_mask(self.nom, params, self.grid, self.config.roi_support_fraction)
        for views in self.folds:
            measured = self.li[views]
            if take_out_of_data is not None:
                filtered, geom = take_out_of_data
                own = self.backproject(filtered, views)
                measured = (measured - forward_project(own, self.grid, geom.subset(views))).astype(np.float32)
            out[views] = estimate_views(measured, self.nom.subset(views), params[views], volume_of_fold(views),
                                        self.grid, self.config, self.mask[views] if self.mask.ndim == 3 else self.mask,
                                        support_mask=support[views], view_ids=views)[0]
        return out


def run_scan(level: Level, passes: int, say) -> dict:
    """Every row of :data:`ROWS` on one scan: {row: [error after each pass]}."""
    zero = np.zeros((level.n, 9))
    true_p = level.true.params_relative_to(level.nominal)
    q_true, q_nom = level.filtered(level.true_c), level.filtered(level.nom)
    v_true, v_nom = level.backproject(q_true), level.backproject(q_nom)
    rows = {}

    def loop(step):
        params, errors = zero, []
        for _ in range(passes):
            params = step(params)
            errors.append(level.error_px(params))
        return errors

    def alternation(params):
        return level.estimate(params, level.backproject(level.filtered(level.nom.perturbed(params))))

    def leave_out(params):
        geom = level.nom.perturbed(params)
        q = level.filtered(geom)
        v = level.backproject(q)
        return level.per_fold(params, lambda views: v - level.backproject(q, views), (q, geom))

    t0 = time.perf_counter()
    rows["loop"] = loop(alternation)
    rows["true"] = [level.error_px(level.estimate(zero, v_true))]
    rows["own_misplaced"] = [level.error_px(level.per_fold(
        zero, lambda views: v_true - level.backproject(q_true, views) + level.backproject(q_nom, views)))]
    rows["own_placed"] = [level.error_px(level.per_fold(
        zero, lambda views: v_nom - level.backproject(q_nom, views) + level.backproject(q_true, views)))]
    rows["held_out"] = [level.error_px(level.per_fold(zero, lambda views: v_true - level.backproject(q_true, views)))]
    rows["left_out"] = [level.error_px(level.per_fold(
        zero, lambda views: v_true - level.backproject(q_true, views), (q_true, level.true_c)))]
    rows["left_out_loop"] = loop(leave_out)
    say(f"  rows done in {time.perf_counter() - t0:.0f} s; true parameters' rms "
        f"{float(np.sqrt((true_p[:, :6] ** 2).mean())):.3f} mm")
    return rows


def parse_scans(text: str) -> list:
    """``"180:0,180:50"`` -> [(180, 0.0), (180, 50.0)]: views and field of view (mm, 0 the centred detector's own)."""
    scans = []
    for item in text.split(","):
        views, _, fov = item.partition(":")
        try:
            scans.append((int(views), float(fov)))
        except ValueError:
            raise ValueError(f"--scans: {item!r} is not VIEWS:FOV_MM") from None
        if scans[-1][0] < 2:
            raise ValueError(f"--scans: {item!r} needs at least 2 views")
    return scans


def report_markdown(out: dict) -> str:
    scans = out["scans"]
    s = out["args"]
    lines = ["# The offset detector: where its correction stops (CUT-DOWN seed system scans)", "",
             f"`bench/bench_offset_diagnosis.py` on {out['machine']}; {out['wall_s']:.0f} s in all. A {s['body']:g} mm "
             f"neck (interior_neck_phantom), robot errors {s['sigma']:g} mm / {s['sigma']:g} deg per view (seed "
             f"{s['seed']}), {s['views_note']}; {METHOD}'s coarse level (2 x 2 binned data, the prior at the robots' "
             f"accuracy) against FDK volumes kept to the field of view; own terms taken {s['folds']} folds at a time. "
             "Mean gauge-aligned reprojection error of ROI points, px of the scan's detector; one pass unless "
             f"marked (passes 1 .. {s['passes']}).", ""]
    header = ["registered against"] + [f"{sc['views']} views, {sc['geo']['fov_mm']:.1f} mm FOV "
                                       f"(offset {sc['geo']['detector_offset_mm']:.1f} mm)" for sc in scans]
    lines += ["| " + " | ".join(header) + " |", "| " + " | ".join("---" for _ in header) + " |"]
    lines.append("| the nominal geometry (no pass) | " + " | ".join(f"{sc['nominal_px']:.3f}" for sc in scans) + " |")
    for key, label in ROWS:
        cells = []
        for sc in scans:
            errs = sc["rows"][key]
            cells.append(" → ".join(f"{e:.3f}" for e in errs) if len(errs) > 1 else f"{errs[0]:.3f}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += ["", "Per scan: " + "; ".join(f"{sc['views']} views at {sc['geo']['fov_mm']:.1f} mm, {sc['wall_s']:.0f} s"
                                           for sc in scans) + ".", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", default="180:0,180:30,180:40,180:50,360:0,360:50",
                    help="VIEWS:FOV_MM,...: the scans (FOV 0: the centred detector's own; else the offset detector's)")
    ap.add_argument("--scale", type=float, default=0.25, help="as bench_fullsize: 0.25 = 440 um pixels, 180 um voxels")
    ap.add_argument("--body", type=float, default=15.0, help="neck width, mm (inside every field of view)")
    ap.add_argument("--sigma", type=float, default=0.3, help="robot error per view, mm and deg, and the prior")
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--folds", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out/bench_offset_diagnosis")
    args = ap.parse_args(argv)
    try:
        scans = parse_scans(args.scans)
        for views, fov in scans:
            scan_layout(SimpleNamespace(scale=args.scale, fov=fov, views=views), SeedSystem())
    except ValueError as exc:
        ap.error(str(exc))
    if args.passes < 1 or args.folds < 1:
        ap.error("--passes and --folds must be at least 1")
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()
    say = lambda m: print(f"[{time.perf_counter() - t_all:7.1f} s] {m}", flush=True)  # noqa: E731
    settings = calibration.CalibrationSettings(method=METHOD).with_prior(args.sigma, args.sigma)
    results = []
    for views, fov in scans:
        t0 = time.perf_counter()
        scan_args = SimpleNamespace(views=views, scale=args.scale, fov=fov, body=args.body, sigma=args.sigma,
                                    seed=args.seed)
        nominal, true, li, mask, grid, geo = make_scan(scan_args, lambda m: None)
        level = Level(nominal, true, li, mask, grid, settings, args.folds)
        nominal_px = level.error_px(np.zeros((level.n, 9)))
        say(f"{views} views, {geo['fov_mm']:.1f} mm field of view (offset {geo['detector_offset_mm']:.1f} mm): "
            f"nominal {nominal_px:.3f} px")
        rows = run_scan(level, args.passes, say)
        for key, _ in ROWS:
            say(f"  {key}: " + " -> ".join(f"{e:.3f}" for e in rows[key]))
        results.append({"views": views, "fov": fov, "geo": geo, "nominal_px": nominal_px, "rows": rows,
                        "wall_s": time.perf_counter() - t0})
    out = {"bench": "bench/bench_offset_diagnosis.py", "argv": list(sys.argv[1:] if argv is None else argv),
           "machine": f"{platform.machine()}, {os.cpu_count()} cores",
           "args": {"body": args.body, "sigma": args.sigma, "seed": args.seed, "scale": args.scale,
                    "passes": args.passes, "folds": args.folds,
                    "views_note": f"scale {args.scale:g} (bench_fullsize's cut-down: "
                                  f"{results[0]['geo']['pixel_um']:.0f} um pixels, {results[0]['geo']['voxel_um']:.0f} um voxels)"},
           "settings": settings.to_dict(), "rows": dict(ROWS), "scans": results, "wall_s": time.perf_counter() - t_all}
    with open(os.path.join(args.out, "offset_diagnosis.json"), "w") as f:
        json.dump(out, f, indent=2)
    with open(os.path.join(args.out, "offset_diagnosis.md"), "w") as f:
        f.write(report_markdown(out))
    say(f"wrote {args.out}/offset_diagnosis.md, offset_diagnosis.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
