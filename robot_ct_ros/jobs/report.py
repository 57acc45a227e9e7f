"""The comparison job: several calibration methods on one scan bag, figures and a table."""

from __future__ import annotations

import time
from pathlib import Path

from robot_ct_ros.bag.reader import read_scan
from robot_ct_ros.ct.calibration import CalibrationSettings, calibrate, get_method
from robot_ct_ros.jobs.calibrate import cone_note, drift_times, scan_grid, settings_used, voxel_size_note
from robot_ct_ros.jobs.output import check_memory, fdk_warnings, refuse_other_job, refuse_out_in_bag
from robot_ct_ros.jobs.output import say as _say

__all__ = ["report_bag", "REPORT_METHODS"]

REPORT_METHODS = ("none", "ncc-lle-exact", "gdc-log")
"""Default columns of ``robot-ct report``: the nominal geometry, this system's method, and the
strongest published baseline."""


def report_bag(bag, out, methods=REPORT_METHODS, settings: CalibrationSettings | None = None, *, voxel_mm=None,
               shape_xyz=None, say=_say) -> dict:
    """Compare calibration methods on one scan bag: figures like the NCC-LLE paper's and a table.

    Each of ``methods`` (registry names, ``none`` for the nominal geometry) runs on the same data
    with ``settings`` (its ``method`` replaced). Added by themselves: ``"bag corrected"`` when the
    bag holds /ct/geometry_corrected, and ``"true geometry"`` when it holds /ct/geometry_true
    (simulated scans): then the table also has the gauge-aligned reprojection error and the SSIM
    against the true-geometry reconstruction, and a figure the per-view parameter error. Writes
    into ``out`` (:func:`robot_ct_ros.jobs.figures.write_report`, name ``report``). Returns the
    table rows and the paths.

    report.json's ``notes`` record the settings as given (``settings``) and, per method, what it ran
    with as a calibration's report does (:func:`~robot_ct_ros.jobs.calibrate.settings_used`:
    ``iterations``, ``schedule``, ``prior_sigma``, and ``ensemble``, the runs averaged); their
    ``notes`` keep a voxel size that looks like the wrong unit and what FDK only approximates on
    this geometry, which are also said.

    Raises
    ------
    ValueError
        An unknown method, or none given; a grid that would not fit in memory with the projections
        (checked before the work; the message says what would fit).
    """
    from robot_ct_ros.ct.calibration.volume import projection_consistency
    from robot_ct_ros.ct.reconstruction import fdk
    from robot_ct_ros.ct.metrics import roi_points
    from robot_ct_ros.jobs.figures import markdown_table, method_notes, write_report

    methods = tuple(methods)
    if not methods:
        raise ValueError("no method given")
    for m in methods:
        get_method(m)
    settings = CalibrationSettings() if settings is None else settings
    t0 = time.perf_counter()
    refuse_out_in_bag(out, bag)
    refuse_other_job(out, "report")
    scan = read_scan(bag)
    for w in scan.warnings:
        say(f"warning: {w}")
    grid = scan_grid(scan, voxel_mm, shape_xyz)
    job_notes = []
    unit_note = voxel_size_note(scan, grid, voxel_mm, shape_xyz)
    if unit_note:
        say(f"note: {unit_note}")
        job_notes.append(unit_note)
    check_memory(grid, scan.n_views, scan.geom.det_shape, "report", methods=len(methods),
                 shape_given=shape_xyz is not None)
    _, beyond = cone_note(scan.geom, grid)  # a grid taller than the cone: mostly zeros in every volume
    if beyond:
        say(f"note: {beyond}")
        job_notes.append(beyond)
    li, mask = scan.to_line_integrals()
    times = drift_times(scan) if settings.drift_order is not None else None
    say(f"{scan.n_views} views, detector {scan.geom.n_rows}x{scan.geom.n_cols}, grid {grid.shape_zyx[::-1]} of "
        f"{grid.voxel_size_mm[0] * 1000:.1f} um; methods {', '.join(methods)}; at most {settings.iterations_text()} "
        f"iteration(s), schedule {settings.schedule}")

    def reconstruct(geom):
        return fdk(li, geom, grid, valid_mask=mask)

    def timed_fdk(geom):
        t = time.perf_counter()
        return geom, reconstruct(geom), (), time.perf_counter() - t

    results = {}
    with fdk_warnings(say) as approximate:  # what FDK only approximates on this geometry goes into the notes
        for method in methods:
            if method != "none":
                say(f"{method}:")
            results[method] = calibrate(li, scan.geom, grid, settings.replace(method=method), valid_mask=mask,
                                        drift_times=times, progress=lambda m: say(f"  {m}"))
        if scan.geom_corrected is not None:
            results["bag corrected"] = timed_fdk(scan.geom_corrected)
        truth = None
        if scan.geom_true is not None:
            results["true geometry"] = timed_fdk(scan.geom_true)
            truth = (scan.geom_true, results["true geometry"][1], None)
    job_notes += [f"FDK: {w}" for w in approximate]
    used = {m: settings_used(results[m]) | {"ensemble": results[m].members} for m in methods}
    initial = projection_consistency(results["none"].volume, grid, scan.geom, li, mask)[0] if "none" in results else None
    name = Path(bag).name.removesuffix(".mcap")
    pts = roi_points(grid)
    per_method = method_notes({m: results[m] for m in methods}, scan.geom, scan.geom_true, pts)
    shared = {k: v for k, v in settings.to_dict().items() if k != "method"}  # the method is each column's
    paths = write_report(out, results, grid, truth, scan.geom, name="report", title=f"{name}: {scan.n_views} views",
                         initial_rmse=initial, reconstruct=reconstruct if truth is not None else None,
                         points_mm=pts, notes_per_method=per_method,
                         notes={"bag": str(bag), "methods": list(methods), "settings": shared,
                                # what each method ran with (method -> value), as a calibration's report.json says
                                **{k: {m: used[m][k] for m in methods}
                                   for k in ("iterations", "schedule", "prior_sigma", "ensemble")},
                                "drift_order": settings.drift_order, "seed": settings.seed,
                                "padding": settings.padding, "grid": grid.to_dict(),
                                "bag_warnings": list(scan.warnings), "notes": job_notes})
    say("\n" + markdown_table(paths["rows"]) + "".join(f"\n{m}: {'; '.join(n)}" for m, n in per_method.items()))
    say(f"wrote {', '.join(str(paths[k]) for k in ('slices', 'rmse', 'param_error', 'markdown', 'json') if k in paths)}"
        f" ({time.perf_counter() - t0:.1f} s)")
    return paths
