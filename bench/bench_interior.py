"""Benchmark: calibration of a strongly truncated interior scan, simulated by a projector that is not ours.

The object: robot_ct_ros.ct.simulation.interior_neck_phantom, a 41 mm neck of additive
ellipsoids (vertebrae, trachea, muscles, bones and blobs outside the field of view; a vessel
with a plaque, a calcification and micro-calcifications inside), more than 6 times the field
of view wide. The scan: the seed system's robotic ROI trajectory (robotic_roi_scan), 180 views,
a 96 x 160 detector of 110 um binned pixels, the world rotated so that the rotation axis is
+y (RTK's convention; ``--axis``). The data: RTK's exact ray-ellipsoid line integrals
(rtk_bridge.rtk_ellipsoid_projections) on the raw 55 um detector, then photon counting with
4,000 counts behind the body, chip gaps and dead pixels (DetectorModel), binned 2 x 2.
Independent per-view robot errors of sigma 0.1 mm / 0.1 deg and 0.3 mm / 0.3 deg.

Every method of the registry runs through calibration.calibrate with default settings twice: as
is, and with the object's reach stated (``exterior_half_width_mm`` 30 mm; ``exterior`` auto then
models the object outside the ROI: the "+ exterior" rows); per method: gauge-aligned reprojection error of ROI points (mean, p95, px), SSIM against the FDK
with the true geometry, wall time. Every other calibration setting has its option as on ``robot-ct
calibrate`` (``--exterior-voxel-mm 0.25``, ...), applied to every method and named in ``interior.md``;
the prior is each scan's robot error. Writes ``interior.md``, ``interior.json`` and figures into
``--out``.

    .venv/bin/python bench/bench_interior.py --out docs/results --oracle # about 90 min on 2 cores
    .venv/bin/python bench/bench_interior.py --sigmas 0.1 --methods none,ncc-lle-exact --views 90
    .venv/bin/python bench/bench_interior.py --sigmas 0.1 --methods "none,ncc-lle-exact + exterior" \
        --exterior-voxel-mm 0.25 --out docs/results/interior_exterior_voxel_0.25
    .venv/bin/python bench/bench_interior.py --methods none --oracle --oracle-voxels 0.25,0.125 \
        --out docs/results/interior_oracle_fine   # the perfect volume on finer exterior voxels, about 15 min
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
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from bench_calibration import BENCH_OWNS, bench_settings, centred_fov_mm, changed_sentence  # noqa: E402

from robot_ct_ros.cli import add_settings_arguments  # noqa: E402
from robot_ct_ros.ct import calibration  # noqa: E402
from robot_ct_ros.ct import simulation as sim  # noqa: E402
from robot_ct_ros.ct.geometry import VolumeGrid  # noqa: E402
from robot_ct_ros.ct.metrics import reprojection_error, roi_points  # noqa: E402
from robot_ct_ros.ct.reconstruction import fdk  # noqa: E402
from robot_ct_ros.ct.rtk_bridge import rtk_ellipsoid_projections  # noqa: E402
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan  # noqa: E402
from robot_ct_ros.jobs.figures import markdown_table, method_notes, write_report  # noqa: E402

AXES = {"y": Rotation.from_rotvec([-np.pi / 2, 0.0, 0.0]),        # the scan's z axis becomes +y (RTK)
        "z": Rotation.identity(),
        "oblique": Rotation.from_rotvec([0.5, -0.9, 0.3])}
"""World rotations applied to the whole scene (trajectory, phantom, ROI)."""
REACH_MM = 30.0
"""How far the neck reaches from the ROI centre across the axis (its far side lies 29.5 mm away), as its user states it."""
CORRECTING = calibration.method_names(include_none=False)
VARIANTS = {f"{m} + exterior": {"method": m, "exterior_half_width_mm": REACH_MM} for m in CORRECTING}
"""Every method with the object's reach stated and otherwise default settings: ``exterior`` auto then models the
object outside the ROI (the truncation level is far above EXTERIOR_ABOVE). The plain rows state no reach."""
METHODS = ("none", *CORRECTING, *VARIANTS, "true geometry")
PHOTONS_BEHIND_BODY = 4000.0


def make_scan(sigma: float, *, views: int, det: tuple, axis: str, seed: int, nxy: int, say, errors=None):
    """The interior scan with robot errors of ``sigma`` mm and deg: data, geometries, ROI grid.
    ``errors`` (views, 9), if given, replaces the independent per-view errors drawn from ``sigma``."""
    system = SeedSystem()
    rows, cols = det
    binning = 2
    pitch = system.raw_pixel_mm * binning
    fov = centred_fov_mm(system, cols, pitch)
    R = AXES[axis].as_matrix()
    nominal_z = robotic_roi_scan(system, roi_center_mm=(0.0, 0.0, 0.0), fov_diameter_mm=fov, n_views=views,
                                 binning=binning, n_rows=rows, n_cols=cols)
    errors = sim.robot_coordination(sigma, sigma, seed=seed).sample(views) if errors is None else np.asarray(errors)
    nominal = nominal_z.moved(R)
    true = nominal.perturbed(errors)  # the errors live in the detector frames: the same in any world
    phantom = sim.interior_neck_phantom(seed).moved(R)
    axial = rows * pitch / system.magnification
    vs = 0.95 * fov / nxy
    nz = max(8, min(nxy, int(0.9 * axial / (pitch / system.magnification))))
    grid = VolumeGrid.centered((nz, nxy, nxy), vs).moved(R)
    t0 = time.perf_counter()
    raw = sim.raw_geometry(true, binning)
    li_raw = rtk_ellipsoid_projections(phantom.primitives, raw)
    body = phantom.info["body_width_mm"]
    detector = sim.DetectorModel.from_transmitted(PHOTONS_BEHIND_BODY, body, binning=binning,
                                                  raw_pitch_mm=raw.col_pitch_mm, seed=seed)
    counts, flat, valid = sim.simulate_counts(li_raw, detector, np.random.default_rng(seed + 12345))
    li, mask = sim.counts_to_line_integrals(counts, flat, valid)
    say(f"  sigma {sigma}: {views} views {rows}x{cols} at {pitch * 1000:.0f} um, FOV {fov:.2f} mm, body {body:.0f} mm "
        f"({body / fov:.1f}x the FOV), axis {axis}, grid {grid.shape_zyx[::-1]} of {vs * 1000:.1f} um; "
        f"RTK line integrals and counts in {time.perf_counter() - t0:.1f} s")
    sc = SimpleNamespace(sigma=sigma, nominal=nominal, true=true, grid=grid, li=li, mask=np.broadcast_to(mask, li.shape),
                         fov_mm=fov, body_mm=body, phantom=phantom, axis=R[:, 2].copy(), seed=seed)
    sc.reconstruct = lambda geom: fdk(sc.li, geom, sc.grid, valid_mask=sc.mask)
    return sc


def oracle(sc, phantom, say, exterior_voxels=(None, 1.0, 0.5, 0.25)) -> list:
    """What the data term can do when the volume is right: each view estimated (coarse, then fine LLE
    pass, ncc-lle-exact) against the true object voxelised, with the ROI alone (None) or with the
    object outside it on voxels of the given sizes; from the nominal and from the true geometry
    (the bias at the optimum). No reconstruction error, no alternation."""
    from dataclasses import replace

    from robot_ct_ros.ct.calibration.lle.estimator import default_lle_configs, estimate_views
    from robot_ct_ros.ct.calibration.masks import bin_masked
    from robot_ct_ros.ct.calibration.model import VolumeParts
    from robot_ct_ros.ct.calibration.volume import estimation_grid
    pts = roi_points(sc.grid)
    grid_e = estimation_grid(sc.grid, calibration.DEFAULT_PADDING)
    coarse, fine = default_lle_configs("ncc-exact", prior_sigma=calibration.prior_sigma_from(sc.sigma, sc.sigma))
    li_c, m_c = bin_masked(sc.li, sc.mask, 2)
    n = sc.nominal.n_views
    rows = []
    for outer in exterior_voxels:
        t0 = time.perf_counter()
        if outer is None:
            vol, c_cfg, f_cfg = sim.voxelize(phantom, grid_e, 2), coarse, fine
        else:
            parts = sim.scan_volumes(phantom, sc.true, grid_e.voxel_size_mm[0], grid_e, outer, roi_margin_mm=0.0,
                                     supersample=2, max_voxels=400 ** 3)
            vol = VolumeParts(tuple(parts))
            c_cfg, f_cfg = replace(coarse, roi_support_fraction=None), replace(fine, roi_support_fraction=None)
        p, _ = estimate_views(li_c, sc.nominal.binned(2), np.zeros((n, 9)), vol, grid_e, c_cfg, m_c)
        p, _ = estimate_views(sc.li, sc.nominal, p, vol, grid_e, f_cfg, sc.mask)
        q, _ = estimate_views(sc.li, sc.nominal, sc.true.params_relative_to(sc.nominal), vol, grid_e, f_cfg, sc.mask)
        row = {"model": "ROI only" if outer is None else f"ROI + exterior on {outer:g} mm voxels",
               "from_nominal_px": reprojection_error(sc.nominal.perturbed(p), sc.true, pts)["mean_px"],
               "from_true_px": reprojection_error(sc.nominal.perturbed(q), sc.true, pts)["mean_px"],
               "wall_s": time.perf_counter() - t0}
        say(f"  oracle, {row['model']}: {row['from_nominal_px']:.3f} px from nominal, {row['from_true_px']:.3f} px "
            f"from the truth ({row['wall_s']:.0f} s)")
        rows.append(row)
    return rows


def run(method: str, sc, settings, say, per_iteration: list | None = None):
    """``method`` on the scan; ``per_iteration``, if given, receives the loop's gauge-aligned error (mean px)
    after each outer iteration (before the guard)."""
    t0 = time.perf_counter()
    if method == "true geometry":
        return (sc.true, sc.reconstruct(sc.true), (), time.perf_counter() - t0)
    changes = VARIANTS.get(method, {"method": method})
    pts = roi_points(sc.grid)

    def record(rec, params):
        if per_iteration is not None:
            per_iteration.append(reprojection_error(sc.nominal.perturbed(params), sc.true, pts)["mean_px"])

    return calibration.calibrate(sc.li, sc.nominal, sc.grid, settings.replace(**changes), valid_mask=sc.mask,
                                 progress=lambda m: say(f"    {m}"), on_iteration=record)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sigmas", default="0.1,0.3", help="robot errors, mm and deg each (comma-separated)")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--views", type=int, default=180)
    ap.add_argument("--det", default="96x160", help="ROWSxCOLS binned pixels (110 um)")
    ap.add_argument("--nxy", type=int, default=96, help="ROI grid voxels across")
    ap.add_argument("--axis", choices=tuple(AXES), default="y")
    ap.add_argument("--iterations", type=int, default=None,
                    help="outer iterations at most (default: the calibration's, its schedule's: 2, and 8 under the "
                         "exterior schedule that the '+ exterior' rows run)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--oracle", action="store_true",
                    help="also estimate the views against the true object (ROI alone, and with the outside on 1, "
                         "0.5, 0.25 mm voxels): what the data term can do with a perfect volume")
    ap.add_argument("--oracle-voxels", default="roi,1,0.5,0.25",
                    help="--oracle's volumes: 'roi' (the ROI alone) and exterior voxel sizes in mm, comma-separated")
    ap.add_argument("--out", default="out/bench_interior")
    add_settings_arguments(ap, skip=BENCH_OWNS)
    args = ap.parse_args(argv)
    if args.prior_sigma is not None:
        ap.error("--prior-sigma: the prior is each scan's robot error (--sigmas), as a user states it")
    settings, changed = bench_settings(args)
    if args.iterations is not None:
        settings = settings.replace(iterations=args.iterations)
    rows, cols = (int(x) for x in args.det.lower().split("x"))
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    try:
        oracle_voxels = tuple(None if v.strip() == "roi" else float(v) for v in args.oracle_voxels.split(","))
    except ValueError:
        ap.error(f"--oracle-voxels: 'roi' or voxel sizes in mm, comma-separated, not {args.oracle_voxels!r}")
    os.makedirs(args.out, exist_ok=True)
    t_all = time.perf_counter()

    def say(msg):
        print(msg, flush=True)

    report = {"bench": "bench/bench_interior.py", "argv": sys.argv[1:] if argv is None else list(argv),
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "settings": settings.to_dict(),
              "settings_changed": changed, "scans": []}
    lines = ["# Interior-scan benchmark (bench/bench_interior.py)", "",
             f"A {sim.interior_neck_phantom(args.seed).info['body_width_mm']:.0f} mm neck of ellipsoids through the "
             f"seed system's robotic ROI trajectory, {args.views} views, {rows} x {cols} detector of 110 um; "
             f"exact line integrals by RTK (rtk_bridge.rtk_ellipsoid_projections), photon counting "
             f"({PHOTONS_BEHIND_BODY:.0f} counts behind the body), rotation axis along {args.axis}. Every method "
             f"through calibration.calibrate, at most {settings.iterations_text()} iterations, the prior (and the "
             f"guard's reference) "
             f"set to the robots' accuracy, default settings otherwise (exterior auto); the '+ exterior' rows state the "
             f"object's reach, exterior_half_width_mm {REACH_MM:g} mm, so that the object outside the ROI is modelled. "
             "Reprojection error: ROI points, gauge removed, px of the 110 um detector; SSIM against the FDK "
             "with the true geometry; wall time on this machine. Each method's notes (the guard's verdict) below "
             "its table.", ""]
    if changed:
        lines += [changed_sentence(changed, "every method"), ""]
    for sigma in (float(x) for x in args.sigmas.split(",")):
        sc = make_scan(sigma, views=args.views, det=(rows, cols), axis=args.axis, seed=args.seed, nxy=args.nxy,
                       say=say)
        results, per_iteration = {}, {}
        for method in methods:
            say(f"  {method}:")
            # the prior (and the guard's reference) is the robots' accuracy, as a user sets it
            per_iteration[method] = []
            results[method] = run(method, sc, settings.with_prior(sigma, sigma), say, per_iteration[method])
        per_iteration = {m: [round(e, 4) for e in v] for m, v in per_iteration.items() if v}
        truth_vol = results["true geometry"][1] if "true geometry" in results else sc.reconstruct(sc.true)
        name = f"interior_{sigma:g}"
        title = f"interior neck, robot errors {sigma:g} mm / {sigma:g} deg, axis {args.axis}"
        paths = write_report(args.out, results, sc.grid, (sc.true, truth_vol, None), sc.nominal, name=name,
                             title=title, reconstruct=sc.reconstruct, notes={"sigma": sigma, "fov_mm": sc.fov_mm})
        rows_ = paths["rows"]
        notes = method_notes(results, sc.nominal, sc.true, roi_points(sc.grid))
        report["scans"].append({"sigma": sigma, "fov_mm": sc.fov_mm, "body_mm": sc.body_mm, "rows": rows_,
                                "notes": notes, "error_per_iteration_px": per_iteration})
        table = markdown_table(rows_)
        say("\n" + table)
        lines += [f"## {title}", "", table, ""]
        lines += [f"- {m}: {'; '.join(n)}" for m, n in notes.items()]
        if per_iteration:
            lines += ["", "The loop's error after each outer iteration (mean px, before the guard):", ""]
            lines += [f"- {m}: {', '.join(f'{e:.3f}' for e in v)}" for m, v in per_iteration.items()]
        if args.oracle:
            rows_o = oracle(sc, sim.interior_neck_phantom(args.seed).moved(AXES[args.axis].as_matrix()), say,
                            oracle_voxels)
            report["scans"][-1]["oracle"] = rows_o
            lines += ["", "What the data term can do with a perfect volume (the true object voxelised; ncc-lle-exact, "
                      "one coarse and one fine pass, no alternation):", "",
                      "| volume | from the nominal geometry (px) | from the true geometry (px) |", "| --- | --- | --- |"]
            lines += [f"| {r['model']} | {r['from_nominal_px']:.3f} | {r['from_true_px']:.3f} |" for r in rows_o]
            lines += [""]
        lines += [f"![slices]({name}_slices.png) ![parameter error]({name}_param_error.png)", ""]
    report["wall_s"] = time.perf_counter() - t_all
    with open(os.path.join(args.out, "interior.json"), "w") as f:
        json.dump(report, f, indent=2, default=lambda o: o.tolist() if isinstance(o, np.ndarray) else str(o))
    with open(os.path.join(args.out, "interior.md"), "w") as f:
        f.write("\n".join(lines) + f"\nTotal {report['wall_s'] / 60:.1f} min.\n")
    say(f"wrote {args.out}/interior.md, interior.json ({report['wall_s'] / 60:.1f} min)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
