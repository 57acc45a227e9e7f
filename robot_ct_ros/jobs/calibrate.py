"""The correction job: read a scan bag once, calibrate its geometry, reconstruct, write the results once.

:func:`correct_scan` works in memory on a :class:`~robot_ct_ros.bag.reader.ScanData` and returns
a :class:`Correction`; :func:`write_correction` writes it (the corrected bag, the volume,
report.json); :func:`calibrate_bag` does both for a bag path. ``robot-ct calibrate``, the
recon_service and replay nodes and the demo all run this job.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag.reader import ScanData, read_scan
from robot_ct_ros.ct.calibration import NO_CORRECTION, CalibrationResult, CalibrationSettings, calibrate, get_method
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.jobs.output import say as _say
from robot_ct_ros.jobs.output import (check_memory, fdk_warnings, refuse_other_job, refuse_out_in_bag, start_output,
                                      write_json, write_volume)

__all__ = ["Correction", "correct_scan", "write_correction", "calibrate_bag", "scan_grid", "voxel_size_note",
           "drift_times", "geometry_error", "truth_metrics", "markdown_report", "settings_used"]


@dataclass(frozen=True, eq=False)
class Correction:
    """A corrected scan in memory: the scan as read, the ROI grid, the calibration's result
    (for ``none``: the nominal geometry and its FDK) and the report (what report.json holds)."""

    scan: ScanData
    grid: VolumeGrid
    result: CalibrationResult
    report: dict

    @property
    def geom(self) -> ConeGeometry:
        return self.result.geom

    @property
    def volume(self) -> np.ndarray:
        return self.result.volume


def scan_grid(scan: ScanData, voxel_mm=None, shape_xyz=None) -> VolumeGrid:
    """The ROI grid of a scan: its default (scan_info's ROI, else the field of view), with the
    voxel size (mm) and the shape (nx, ny, nz) overridden where given."""
    return scan.default_grid(voxel_size_mm=voxel_mm, shape_zyx=None if shape_xyz is None else tuple(shape_xyz)[::-1])


def cone_note(geom: ConeGeometry, grid: VolumeGrid, options: str = "command line"):
    """(:class:`~robot_ct_ros.ct.field_of_view.ConeReach` of ``grid``, its note): the note, where most of the grid
    lies beyond every view's cone, says how many slices the rays reach and suggests a shape that fits, as
    ``options`` (a key of jobs.output.GRID_OPTIONS) sets it; empty otherwise."""
    from robot_ct_ros.ct.field_of_view import cone_reach
    from robot_ct_ros.jobs.output import GRID_OPTIONS

    reach = cone_reach(geom, grid)
    return reach, reach.note(GRID_OPTIONS[options][0])


MIN_VOXELS_PER_AXIS = 8
"""A grid sized by the scan with fewer voxels than this along an axis its detector resolves (at least as many
pixels) has voxels in the wrong unit, most likely (:func:`voxel_size_note`)."""
MAX_VOXEL_PER_PIXEL = 20.0
"""Voxels more than this many times the detector pixel at the isocentre: the wrong unit, most likely."""
MICROMETRE_READING_PER_PIXEL = (0.1, 10.0)
"""The voxel figure read as micrometres must lie within these multiples of the detector pixel at the isocentre for
:func:`voxel_size_note` to suspect it: a deliberately coarse voxel reads as an implausibly small one in um."""


def voxel_size_note(scan: ScanData, grid: VolumeGrid, voxel_mm=None, shape_xyz=None,
                    option: str | None = "--voxel-mm") -> str | None:
    """A note when ``grid``'s voxels look like the wrong unit (e.g. ``--voxel-mm 41.2`` meant as um), else None.
    Suspected only where the figure read as um is a plausible voxel (:data:`MICROMETRE_READING_PER_PIXEL` of the
    detector pixel at the isocentre: pitch / magnification at the scan centre), and then when the voxels are more
    than :data:`MAX_VOXEL_PER_PIXEL` times that pixel, or, for a voxel size given (``voxel_mm``) on a grid sized by
    the scan (no ``shape_xyz``), when fewer than :data:`MIN_VOXELS_PER_AXIS` lie along an axis the detector
    resolves (x, y across the scan axis: its columns; z along it: its rows). Whatever the unit, a voxel size given
    on a grid sized by the scan that leaves one voxel along such an axis gets a note too. ``option``: the
    command-line option that set the voxel, named in the advice (None: none to name). A note, not a refusal."""
    g = scan.geom
    pixel_mm = min(g.row_pitch_mm, g.col_pitch_mm) / float(np.median(g.magnification(scan.scan_center_mm())))
    grid_voxel_mm = float(max(grid.voxel_size_mm))
    read_as_um_mm = grid_voxel_mm / 1000.0
    low, high = MICROMETRE_READING_PER_PIXEL
    nx, ny, nz = grid.shape_zyx[::-1]
    resolved = [n for n, pixels in ((nx, g.n_cols), (ny, g.n_cols), (nz, g.n_rows)) if pixels >= MIN_VOXELS_PER_AXIS]
    if not low * pixel_mm <= read_as_um_mm <= high * pixel_mm:
        if voxel_mm is not None and shape_xyz is None and any(n == 1 for n in resolved):
            # whatever the unit: a single voxel across what the detector resolves is no image
            return (f"voxels of {grid_voxel_mm:g} mm make a grid of {nx} x {ny} x {nz}: one voxel across what the "
                    f"detector resolves ({grid_voxel_mm / pixel_mm:.0f} times its pixel at the isocentre, "
                    f"{pixel_mm * 1000:.1f} um)" + (f"; is {option} {voxel_mm:g} meant?" if option else ""))
        return None
    coarse = grid_voxel_mm > MAX_VOXEL_PER_PIXEL * pixel_mm
    few = voxel_mm is not None and shape_xyz is None and any(n < MIN_VOXELS_PER_AXIS for n in resolved)
    if not (coarse or few):
        return None
    advice = (f"{option} is in mm: for {grid_voxel_mm:g} um, give {option} {read_as_um_mm:g}" if option
              else f"um given where mm are meant? {grid_voxel_mm:g} um would be {read_as_um_mm:g} mm")
    return (f"voxels of {grid_voxel_mm:g} mm are {grid_voxel_mm / pixel_mm:.0f} times the detector pixel at the "
            f"isocentre ({pixel_mm * 1000:.1f} um) and make a grid of {nx} x {ny} x {nz}: the voxel size looks like "
            f"the wrong unit ({advice})")


def drift_times(scan: ScanData) -> np.ndarray | None:
    """The frames' stamps in seconds from the first, the drift model's time axis (a pause in the
    scan is then a gap in time, not one view's step); None when they do not span any time."""
    t = (np.asarray(scan.stamps_ns, np.int64) - int(scan.stamps_ns[0])).astype(np.float64) * 1e-9
    return t if np.ptp(t) > 0 else None


def geometry_error(scan: ScanData, geom: ConeGeometry, grid: VolumeGrid | None = None) -> dict | None:
    """How far ``geom`` lies from the bag's true geometry (simulated bags only): with ``grid``, the gauge-aligned
    reprojection error of points filling it (pixels; the best global rigid motion removed, which the data cannot
    tell), the figure to judge a correction by; and the raw RMS of the 9 parameters, which counts that motion too
    (a correct estimate in another gauge reads worse than the nominal geometry there)."""
    if scan.geom_true is None:
        return None
    out = {}
    if grid is not None:
        from robot_ct_ros.ct.metrics import roi_points

        out["reprojection_error_px"] = _reprojection_px(geom, scan.geom_true, roi_points(grid))
    d = geom.params_relative_to(scan.geom_true)
    out.update({"rms_translation_mm": float(np.sqrt((d[:, :6] ** 2).mean())),
                "rms_rotation_deg": float(np.rad2deg(np.sqrt((d[:, 6:] ** 2).mean()))),
                "note": ("reprojection_error_px: pixels, ROI points, best global rigid motion (the gauge) removed; "
                         "rms_*: raw difference to /ct/geometry_true, the gauge not removed")})
    return out


def _reprojection_px(geom: ConeGeometry, true_geom: ConeGeometry, points_mm) -> dict:
    """The gauge-aligned reprojection error of ``geom`` against ``true_geom`` (metrics.reprojection_error), as the
    reports give it: {"mean", "p95", "max"} in pixels, and on a one-row detector "mean_along_row", the part within
    the fan plane, which is all a fan beam corrects (the distance across the row stays as the robots left it)."""
    from robot_ct_ros.ct.metrics import reprojection_error

    e = reprojection_error(geom, true_geom, points_mm)
    out = {"mean": e["mean_px"], "p95": e["p95_px"], "max": e["max_px"]}
    if true_geom.n_rows == 1:
        out["mean_along_row"] = e["mean_u_px"]
    return out


def base_report(scan: ScanData, grid: VolumeGrid) -> dict:
    """What every job's report.json says about the scan it ran on."""
    return {"bag": str(scan.path), "format": scan.info.get("format"), "n_views": scan.n_views,
            "detector": [scan.geom.n_rows, scan.geom.n_cols], "projection_units": scan.units,
            "recovered": scan.recovered, "bag_warnings": list(scan.warnings), "grid": grid.to_dict()}


def truth_metrics(scan: ScanData, line_integrals, mask, geom: ConeGeometry, volume, grid: VolumeGrid, *,
                  nominal_volume=None) -> dict | None:
    """Figures against the true geometry of a simulated scan (None without /ct/geometry_true).

    Gauge-aligned reprojection error (pixels) of the nominal and of the corrected geometry
    against /ct/geometry_true on points filling the ROI, and SSIM of the nominal and the
    corrected reconstruction against the reconstruction with the true geometry (same grid,
    same FDK). ``nominal_volume``: the nominal geometry's FDK where the caller has it (method
    none: its own volume), else it is reconstructed here.
    """
    from robot_ct_ros.ct.metrics import roi_points, ssim
    from robot_ct_ros.ct.reconstruction import fdk

    if scan.geom_true is None:
        return None
    pts = roi_points(grid)
    out = {}
    for name, g in (("nominal", scan.geom), ("corrected", geom)):
        out[f"reprojection_error_{name}_px"] = _reprojection_px(g, scan.geom_true, pts)
    ref = fdk(line_integrals, scan.geom_true, grid, valid_mask=mask)
    nominal = fdk(line_integrals, scan.geom, grid, valid_mask=mask) if nominal_volume is None else nominal_volume
    rng = float(ref.max() - ref.min())
    out["ssim_nominal"] = ssim(nominal, ref, data_range=rng)
    out["ssim_corrected"] = ssim(np.asarray(volume, np.float32), ref, data_range=rng)
    out["note"] = ("reprojection error: pixels, ROI points, best global rigid motion removed; "
                   "SSIM against the FDK with /ct/geometry_true on the same grid")
    return out


def settings_used(result: CalibrationResult) -> dict:
    """What a calibration ran with, as the reports record it: the resolved ``iterations`` (at most) and
    ``schedule``, and the ``prior_sigma`` the estimator used: None for a method without a prior, whose
    settings keep the robots' stated accuracy for the guard all the same."""
    used = result.settings
    return {"iterations": used.iterations, "schedule": used.schedule,
            "prior_sigma": None if used.prior_sigma is None or not get_method(result.method).uses_prior
            else list(used.prior_sigma)}


def correct_scan(scan: ScanData, settings: CalibrationSettings | None = None, grid: VolumeGrid | None = None, *,
                 evaluate_truth: bool = False, say=_say) -> Correction:
    """Calibrate the per-view geometry of a scan in memory and reconstruct it on ``grid``.

    Parameters
    ----------
    scan : ScanData
        The scan as read (:func:`robot_ct_ros.bag.read_scan`).
    settings : CalibrationSettings, optional
        Method (``none``: the nominal geometry), iterations, prior, ... (default settings).
    grid : VolumeGrid, optional
        The ROI grid (default :func:`scan_grid`).
    evaluate_truth : bool
        Simulated scans: add :func:`truth_metrics` to the report under ``truth``.
    say : callable
        Progress, one line per step.

    Returns
    -------
    Correction
    """
    t0 = time.perf_counter()
    settings = CalibrationSettings() if settings is None else settings
    grid = scan_grid(scan) if grid is None else grid
    for w in scan.warnings:
        say(f"warning: {w}")
    li, mask = scan.to_line_integrals()
    say(f"{scan.n_views} views, detector {scan.geom.n_rows}x{scan.geom.n_cols}, grid {grid.shape_zyx[::-1]} of "
        f"{grid.voxel_size_mm[0] * 1000:.1f} um; method {settings.method}"
        + ("" if settings.method == "none" else f", at most {settings.iterations_text()} iteration(s), schedule "
                                                 f"{settings.schedule}"))
    times = drift_times(scan) if settings.drift_order is not None else None
    with fdk_warnings(say) as approximate:  # what FDK only approximates on this geometry goes into the notes
        result = calibrate(li, scan.geom, grid, settings, valid_mask=mask, drift_times=times, progress=say)
    used = result.settings
    report = base_report(scan, grid)
    report.update({"job": "calibrate", "method": settings.method, "method_used": result.method,
                   **settings_used(result), "settings": used.to_dict(),
                   "drift_order": used.drift_order, "seed": used.seed, "padding": used.padding,
                   "ensemble": result.members, "iterations_run": len(result.history),
                   "history": [dict(h.__dict__) for h in result.history],
                   "notes": list(result.notes) + [f"FDK: {w}" for w in approximate]})
    if result.members > 1:  # the members' spread around their mean: the estimate's sampling noise
        report["ensemble_spread_px"] = result.spread_px
    d = result.params
    report.update({"correction_rms_translation_mm": float(np.sqrt((d[:, :6] ** 2).mean())),
                   "correction_rms_rotation_deg": float(np.rad2deg(np.sqrt((d[:, 6:] ** 2).mean()))),
                   "geometry_error_nominal": geometry_error(scan, scan.geom, grid),
                   "geometry_error_corrected": geometry_error(scan, result.geom, grid)})
    nominal_px, corrected_px = (report[k] and report[k].get("reprojection_error_px")
                                for k in ("geometry_error_nominal", "geometry_error_corrected"))
    if nominal_px and corrected_px:  # a simulated bag: the figure to judge the correction by, said, not only kept
        say(f"against the bag's true geometry (gauge removed): nominal {nominal_px['mean']:.3f} px mean "
            f"({nominal_px['p95']:.3f} p95) -> corrected {corrected_px['mean']:.3f} px ({corrected_px['p95']:.3f} p95)"
            + (f"; along the row, the part a fan beam corrects: {nominal_px['mean_along_row']:.3f} -> "
               f"{corrected_px['mean_along_row']:.3f} px" if "mean_along_row" in nominal_px else ""))
    if evaluate_truth and scan.geom_true is not None:
        say("comparing with the true geometry")
        # of the geometry as the corrected bag and /ct/geometry_corrected carry it, to the last bit
        report["truth"] = truth_metrics(scan, li, mask, fmt.as_transmitted(result.geom), result.volume, grid,
                                        nominal_volume=result.volume if result.method == NO_CORRECTION else None)
    report["wall_s"] = time.perf_counter() - t0
    return Correction(scan, grid, result, report)


def write_correction(correction: Correction, out, *, markdown: bool = False, say=_say) -> dict:
    """Write a :class:`Correction` into the folder ``out``, each file once.

    ``<bag name>_corrected``: every message of the scan bag plus /ct/geometry_corrected (copied
    from the messages read with the scan when it was read with ``keep_raw``);
    ``volume.npy``/``.tif``/``_grid.json``; ``report.json`` (the report with ``files`` and
    ``paths``); with ``markdown`` also ``report.md``. The reports are written last and a previous run's are
    removed first, so an interrupted run leaves no report.json. Returns the report as written.
    """
    from robot_ct_ros.bag.writer import write_corrected_bag

    scan, report = correction.scan, dict(correction.report)
    name = _bag_name(scan)
    refuse_another_bags_folder(Path(out), scan)
    out = start_output(out)  # report.json is written last: without it, the folder holds an unfinished run
    corrected_bag = out / f"{name}_corrected"
    if corrected_bag.exists():
        import shutil
        shutil.rmtree(corrected_bag)
    write_corrected_bag(scan.raw if scan.raw is not None else scan.path, corrected_bag, correction.geom,
                        scan.stamps_ns, frame_id=scan.frame_id, namespace=scan.namespace,  # one frame per bag
                        notes=f"calibrated with {report['method_used']}, "
                              f"{report.get('iterations_run', 0)} iteration(s)")
    files = write_volume(correction.volume, correction.grid, out)
    report.update({"corrected_bag": str(corrected_bag), "files": files,
                   "paths": {"input_bag": str(scan.path), "corrected_bag": str(corrected_bag),
                             "volume_npy": files[0], "volume_tif": files[1], "report_json": str(out / "report.json")}})
    if markdown:
        report["paths"]["report_md"] = str(out / "report.md")
        (out / "report.md").write_text(markdown_report(report))
    write_json(out / "report.json", report)
    say(f"wrote {corrected_bag}, {out}/{', '.join(Path(f).name for f in files)}, report.json"
        + (", report.md" if markdown else ""))
    return report


def _bag_name(scan: ScanData) -> str:
    """The scan bag's name, as its corrected copy ``<name>_corrected`` is named."""
    return scan.path.name.removesuffix(".mcap")


def refuse_another_bags_folder(out: Path, scan: ScanData | str, option: str = "--out") -> None:
    """A folder holds one bag's calibration: refuse ``out`` where report.json or a ``*_corrected`` bag is of a bag
    other than ``scan``'s (a ScanData, or the bag's name; two runs would mix there, and export could take the other
    bag's correction). ``option``: what the user sets the folder with, named in the refusal."""
    name = scan if isinstance(scan, str) else _bag_name(scan)
    others = ([p.name.removesuffix("_corrected") for p in out.glob("*_corrected") if p.name != f"{name}_corrected"]
              if out.is_dir() else [])
    previous = out / "report.json"
    if previous.is_file():
        try:
            earlier = Path(json.loads(previous.read_text()).get("paths", {}).get("input_bag", "")).name
        except (ValueError, AttributeError):
            earlier = ""
        if earlier and earlier.removesuffix(".mcap") != name:
            others.append(earlier)
    if others:
        raise ValueError(f"{out} holds the calibration of another bag ({', '.join(sorted(set(others)))}); give each "
                         f"bag its own {option} folder")


def calibrate_bag(bag, out, settings: CalibrationSettings | None = None, *, voxel_mm=None, shape_xyz=None,
                  evaluate_truth: bool = False, markdown: bool = False, say=_say,
                  options: str = "command line") -> Correction:
    """:func:`correct_scan` of the bag at ``bag`` (read once), written by :func:`write_correction`
    into ``out``. Returns the correction, its report as written.

    Refused before the work: a folder holding another bag's calibration, and a grid that would not
    fit in memory (the refusal names the grid settings of ``options``, jobs.output.GRID_OPTIONS)."""
    cli = options == "command line"  # the refusals and notes name the command line's options, else ROS's
    refuse_out_in_bag(out, bag)
    refuse_other_job(out, "calibrate", "--out" if cli else "output_dir")
    scan = read_scan(bag, keep_raw=True)
    refuse_another_bags_folder(Path(out), scan, "--out" if cli else "output_dir")
    grid = scan_grid(scan, voxel_mm, shape_xyz)
    unit_note = voxel_size_note(scan, grid, voxel_mm, shape_xyz, "--voxel-mm" if cli else None)
    if unit_note:
        say(f"note: {unit_note}")
    method = (settings or CalibrationSettings()).method
    check_memory(grid, scan.n_views, scan.geom.det_shape, "reconstruct" if method == "none" else "calibrate",
                 options=options, shape_given=shape_xyz is not None)
    _, beyond = cone_note(scan.geom, grid, options)  # a grid taller than the cone: mostly zeros
    if beyond:
        say(f"note: {beyond}")
    correction = correct_scan(scan, settings, grid, evaluate_truth=evaluate_truth, say=say)
    job_notes = [n for n in (unit_note, beyond) if n]
    if job_notes:  # kept in the report with the calibration's own notes
        correction.report["notes"] = job_notes + correction.report["notes"]
    report = write_correction(correction, out, markdown=markdown, say=say)
    return Correction(correction.scan, correction.grid, correction.result, report)


LEANS_ON_PRIOR_BELOW = 0.5
"""report.md explains a last iteration's independent-pixel fraction below this as the correction leaning on the
prior (the data explaining little of the projections)."""


def markdown_report(report: dict) -> str:
    """report.md: the correction's report as a short Markdown page."""
    settings = report.get("settings") or {}
    lines = [f"# Reconstruction report: {report.get('scan_id') or report.get('bag')}", "",
             f"- views: {report.get('n_views')}, detector {report.get('detector')}",
             f"- method: {report.get('method_used', report.get('method'))}, "
             + (f"{report['iterations_run']} of " if "iterations_run" in report else "")
             + f"{report.get('iterations')} iteration(s), "
             f"{report.get('wall_s', 0.0):.1f} s",
             f"- grid: {report.get('grid', {}).get('shape_zyx')} voxels (z, y, x) of "
             f"{[round(float(v) * 1000, 2) for v in report.get('grid', {}).get('voxel_size_mm', [])]} um",
             f"- correction applied: {report.get('correction_rms_translation_mm', 0.0):.4f} mm RMS translation, "
             f"{report.get('correction_rms_rotation_deg', 0.0):.4f} deg RMS rotation"]
    if report.get("ensemble_spread_px") is not None:
        lines.append(f"- ensemble: the mean of {report['ensemble']} runs with different sampling seeds, which lie "
                     f"{report['ensemble_spread_px']:.3f} px from it (the estimate's sampling noise)")
    last, prior = (report.get("history") or [{}])[-1], report.get("prior_sigma")
    if last.get("independent_fraction") is not None and prior:
        lines.append(f"- last iteration: projection NCC {last['projection_ncc']:.4f}; independent pixels "
                     f"{last['independent_fraction']:.3f}"
                     + (f" (near 0: the data explain little of the projections and the correction leans on the prior "
                        f"of {prior[0]:.3g} mm / {np.rad2deg(prior[6]):.3g} deg)"
                        if last["independent_fraction"] < LEANS_ON_PRIOR_BELOW else ""))
    for note in report.get("notes") or ():
        lines.append(f"- {note}")
    if settings:
        lines.append("- settings: " + ", ".join(f"{k} {v}" for k, v in settings.items()))
    t = report.get("truth")
    if t:
        n, c = t["reprojection_error_nominal_px"], t["reprojection_error_corrected_px"]
        lines += ["", "## Against the true geometry (simulation)", "",
                  "| | nominal | corrected |", "| --- | --- | --- |",
                  f"| reprojection error, mean (px) | {n['mean']:.3f} | {c['mean']:.3f} |",
                  f"| reprojection error, p95 (px) | {n['p95']:.3f} | {c['p95']:.3f} |",
                  f"| SSIM vs true-geometry reconstruction | {t['ssim_nominal']:.4f} | {t['ssim_corrected']:.4f} |",
                  "", t["note"]]
    lines += ["", "## Files", ""] + [f"- {k}: `{v}`" for k, v in report.get("paths", {}).items()]
    return "\n".join(lines) + "\n"
