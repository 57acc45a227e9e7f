"""The reconstruction job: FDK of a scan bag with its nominal or corrected geometry."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from robot_ct_ros.bag.reader import read_scan
from robot_ct_ros.bag.format import ScanBagError
from robot_ct_ros.jobs.calibrate import base_report, cone_note, geometry_error, scan_grid, voxel_size_note
from robot_ct_ros.jobs.output import say as _say
from robot_ct_ros.jobs.output import (check_memory, fdk_warnings, refuse_other_job, refuse_out_in_bag, start_output,
                                      write_json, write_volume)

__all__ = ["reconstruct_bag", "GEOMETRIES"]

GEOMETRIES = ("auto", "nominal", "corrected")
"""Which geometry :func:`reconstruct_bag` uses: ``auto`` is /ct/geometry_corrected when the bag has it."""


def reconstruct_bag(bag, out, *, geometry: str = "auto", voxel_mm=None, shape_xyz=None, say=_say) -> dict:
    """FDK of a scan bag; writes ``volume.npy``, ``volume.tif``, ``volume_grid.json`` and
    ``report.json`` into ``out`` and returns the report. What it warns about (FDK's approximations,
    a grid mostly outside the field of view or beyond every view's cone, voxels in the wrong unit) is
    said and kept in the report's ``notes``.

    ``outside_field_of_view_fraction``: the share of the grid's voxels outside the field of view, that
    is those the measured rays do not reach from every direction about the scan axis
    (:func:`~robot_ct_ros.ct.field_of_view.field_of_view_mask`, which looks across the axis only) or
    that no view's detector sees at all (beyond the cone's top and bottom:
    :func:`~robot_ct_ros.ct.field_of_view.cone_reach`). ``beyond_cone``: the latter alone, and the
    slices along the grid axis nearest the scan axis that the rays reach. A grid wholly outside the field of view
    (none of its voxels with complete data, in a scan that has a field of view) reads 1.0 and gets a note that says
    so and where the field of view lies (:meth:`~robot_ct_ros.ct.field_of_view.FieldOfViewExtent.misses_note`);
    ``beyond_cone`` may still be 0 there: some view's detector sees every voxel, from too few directions.

    Raises
    ------
    ScanBagError
        The bag gives no scan, or ``geometry="corrected"`` and it holds no corrected geometry.
    ValueError
        The grid and the projections would not fit in memory (checked before allocating; the
        message says what would fit).
    """
    from robot_ct_ros.ct.field_of_view import field_of_view_extent, field_of_view_mask
    from robot_ct_ros.ct.reconstruction import fdk

    if geometry not in GEOMETRIES:
        raise ValueError(f"geometry must be one of {', '.join(GEOMETRIES)}")
    t0 = time.perf_counter()
    out = Path(out)
    refuse_out_in_bag(out, bag)
    refuse_other_job(out, "reconstruct")
    scan = read_scan(bag)
    for w in scan.warnings:
        say(f"warning: {w}")
    if geometry == "corrected" and scan.geom_corrected is None:
        raise ScanBagError(f"{bag} has no /ct/geometry_corrected")
    use_corrected = geometry == "corrected" or (geometry == "auto" and scan.geom_corrected is not None)
    geom = scan.geom_corrected if use_corrected else scan.geom
    grid = scan_grid(scan, voxel_mm, shape_xyz)
    notes = []
    unit_note = voxel_size_note(scan, grid, voxel_mm, shape_xyz)
    if unit_note:
        say(f"note: {unit_note}")
        notes.append(unit_note)
    check_memory(grid, scan.n_views, geom.det_shape, "reconstruct", shape_given=shape_xyz is not None)
    li, mask = scan.to_line_integrals()
    say(f"{scan.n_views} views, detector {geom.n_rows}x{geom.n_cols}; FDK on {grid.shape_zyx[::-1]} voxels of "
        f"{grid.voxel_size_mm[0] * 1000:.1f} um ({'corrected' if use_corrected else 'nominal'} geometry)")
    with fdk_warnings(say) as approximate:
        vol = fdk(li, geom, grid, valid_mask=mask)
    out = start_output(out)  # report.json is written last: without it, the folder holds an unfinished run
    complete = field_of_view_mask(geom, grid)  # across the axis only: the cone's top and bottom are not its business
    across = 1.0 - float(np.mean(complete))
    reach, beyond = cone_note(geom, grid)  # ... but they are the report's: a grid taller than the cone
    outside = 1.0 - float(np.mean(complete & reach.mask))
    if not complete.any():  # the grid misses the field of view (a scan with none at all marks every voxel)
        notes.append(field_of_view_extent(geom).misses_note(grid) + (
            "; no view's detector sees any of its voxels either (they lie behind every source or beyond every "
            "detector)" if reach.outside_fraction >= 1.0 else ""))
        say(f"note: {notes[-1]}")
    elif across > 0.3:  # beyond a square grid's corners (21 %): FDK puts streaks there, not the object
        notes.append(f"{100 * across:.0f} % of the grid lies outside the field of view across the scan axis (voxels "
                     "that the measured rays do not reach from every direction); FDK's values there are streaks, "
                     "not the object")
        say(f"note: {notes[-1]}")
    if beyond:  # FDK puts zeros there
        notes.append(beyond)
        say(f"note: {beyond}")
    files = write_volume(vol, grid, out)
    report = base_report(scan, grid)
    report.update({"job": "reconstruct", "geometry": "corrected" if use_corrected else "nominal",
                   "geometry_error": geometry_error(scan, geom, grid), "outside_field_of_view_fraction": outside,
                   "beyond_cone": {"fraction": reach.outside_fraction, "axis": "xyz"[reach.axis],
                                   "slices_reached": reach.n_reached, "slices": len(reach.slices)},
                   "notes": notes + list(approximate), "files": files, "wall_s": time.perf_counter() - t0})
    write_json(out / "report.json", report)
    say(f"wrote {out}/{', '.join(Path(f).name for f in files)}, report.json ({report['wall_s']:.1f} s)")
    return report
