"""Which detector pixels the calibration may use: valid pixels, finite data, ROI support, binning."""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid, view_mask

__all__ = ["roi_support_mask", "ray_chords_mm", "as_view_mask", "usable_data", "bin_masked", "usable_views", "view_chunks",
           "estimator_inputs", "summarise_views", "MIN_VIEW_PIXELS", "FACE_MARGIN_SHARE", "AXIS_ALIGNED_DEG"]

MIN_VIEW_PIXELS = 16
"""A view with fewer usable pixels than this (its rays barely cross the grid, or its detector is
mostly dead) is not estimated: it keeps its current geometry, i.e. the nominal one or the prior's."""


def ray_chords_mm(geom: ConeGeometry, grid: VolumeGrid, z_stretch: float = 1.0,
                  chunk_pixels: int = 1 << 21, axis=None) -> np.ndarray:
    """Exact length (mm) of every pixel's ray, source to pixel centre, inside the box of ``grid``
    (its voxels' outer faces), float32 (n, rows, cols). ``z_stretch`` > 1 sweeps the box along
    ``axis`` (a world unit vector; default the grid's own z axis) about its centre, to ``z_stretch``
    times its length along that axis (the comparison body of the axial test of
    :func:`roi_support_mask`): along the grid's z that is the box stretched, along any other
    direction the box swept by a segment, a zonotope (its faces: the normals of each pair of the
    box's three edges and the segment). Pure geometry, slab clipping in the grid's own frame
    (mm about its centre), batched over views (no interpolation: a thin grid's chords are as
    exact as a thick one's)."""
    from robot_ct_ros.ct.projector import ray_geometry

    rg = ray_geometry(geom, grid)  # source, pixel (0, 0), column and row steps in index units
    n = np.asarray(grid.shape_xyz, np.float64)
    vs = np.asarray(grid.voxel_size_mm, np.float64)
    half = 0.5 * n * vs  # the box's half edges along the grid's x, y, z (mm)
    gens = [np.eye(3)[k] * half[k] for k in range(3)]
    a = np.array([0.0, 0.0, 1.0]) if axis is None else grid.direction_matrix.T @ np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    if z_stretch != 1.0:  # the sweep: a segment along a, half as long as (z_stretch - 1) times the box's length there
        gens.append(a * (z_stretch - 1.0) * float(np.abs(a * half).sum()))  # that length is 2 sum|a_k half_k|
    slabs = []  # (unit normal, half width): the zonotope's faces, one per non-parallel pair of generators
    for i in range(len(gens)):
        for j in range(i + 1, len(gens)):
            nrm = np.cross(gens[i], gens[j])
            if np.linalg.norm(nrm) > 1e-9 * np.linalg.norm(gens[i]) * np.linalg.norm(gens[j]):
                nrm = nrm / np.linalg.norm(nrm)
                slabs.append((nrm, sum(abs(float(nrm @ g)) for g in gens)))
    normals = np.array([x[0] for x in slabs])  # (m, 3) in the grid's frame
    widths = np.array([x[1] for x in slabs])
    centre_idx = 0.5 * (n - 1.0)
    rows = np.arange(geom.n_rows, dtype=np.float64)
    cols = np.arange(geom.n_cols, dtype=np.float64)
    out = np.empty((geom.n_views, geom.n_rows, geom.n_cols), np.float32)
    step = max(1, int(chunk_pixels) // max(1, geom.n_rows * geom.n_cols))
    for v0 in range(0, geom.n_views, step):
        g = rg[v0:v0 + step]
        src = (g[:, None, None, 0:3] - centre_idx) * vs  # mm about the grid's centre, along its axes
        pix = ((g[:, None, None, 3:6] + cols[None, None, :, None] * g[:, None, None, 6:9]
                + rows[None, :, None, None] * g[:, None, None, 9:12]) - centre_idx) * vs
        d = pix - src
        s_n, d_n = src @ normals.T, d @ normals.T  # (..., m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-widths - s_n) / d_n
            t2 = (widths - s_n) / d_n
        inside = np.abs(s_n) <= widths  # a ray parallel to a face: all or nothing
        t_in = np.where(d_n == 0, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        t_out = np.where(d_n == 0, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        t0 = np.maximum(t_in.max(axis=-1), 0.0)
        t1 = np.minimum(t_out.min(axis=-1), 1.0)
        out[v0:v0 + step] = np.maximum(t1 - t0, 0.0) * np.linalg.norm(d, axis=-1)
    return out


FACE_MARGIN_SHARE = 0.6
""":func:`roi_support_mask` keeps its margin along the grid's top and bottom faces while the margin
keeps at least this share of the rays that stay inside the slab (normal detectors and grids: a few
rows at the top and bottom; measured 0.7 to 0.9 on the test scans), and drops it where it would cost
more (thin, few-row detectors on the slab their cone sees, whose every ray runs close to its faces:
the margin keeps about half of them)."""


AXIS_ALIGNED_DEG = 1.0
""":func:`roi_support_mask` takes a grid's z within this angle of the scan axis as along it (the
robots' errors tilt an estimated axis by a fraction of a degree)."""


def roi_support_mask(nominal: ConeGeometry, params: np.ndarray, grid: VolumeGrid, fraction: float,
                     axial_tolerance: float = 0.02) -> np.ndarray:
    """(n, rows, cols) pixels whose reprojection of the ROI volume is meaningful.

    A pixel counts when its ray crosses the ROI for at least ``fraction`` of the longest
    chord of that view, and leaves it through the sides, not through the top or bottom
    face: a ray that exits axially also crosses object outside the reconstructed slab
    (the long-object problem), which no offset or gain can absorb. "Exits axially" means its
    chord in the grid is shorter, by more than ``axial_tolerance``, than in the grid swept to three
    times its length along the scan axis (:func:`~robot_ct_ros.ct.scan_weights.estimate_scan_axis`),
    whichever way the grid is turned: the object goes on along the axis, not along the grid's z.

    Two measures of the chords: ray-cast through coarse ones-volumes (4x larger voxels), whose
    interpolation falls off over the outer half voxel of the top and bottom faces, so rays
    running that close to a face count as leaving it (a margin: the rows nearest the top and
    bottom of a normal detector); and exact (:func:`ray_chords_mm`), no margin. The margin is
    kept unless it drops 40 % or more of the rays the exact test keeps (:data:`FACE_MARGIN_SHARE`,
    over the whole scan): a thin (few-row) detector whose grid is the slab its cone sees runs
    every ray near the faces, and keeps them all. The margin needs the grid's z along the scan axis
    (within :data:`AXIS_ALIGNED_DEG`); a grid turned otherwise gets the exact test alone.
    """
    from robot_ct_ros.ct.projector import forward_project

    from robot_ct_ros.ct.scan_weights import estimate_scan_axis

    geom = nominal.perturbed(params)
    axis = estimate_scan_axis(geom)
    aligned = abs(float(axis @ grid.direction_matrix[:, 2])) >= np.cos(np.deg2rad(AXIS_ALIGNED_DEG))
    chord = ray_chords_mm(geom, grid)
    chord_tall = ray_chords_mm(geom, grid, z_stretch=3.0, axis=None if aligned else axis)
    peak = chord.reshape(chord.shape[0], -1).max(axis=1)
    exact = (chord > (fraction * peak)[:, None, None]) & (chord >= (1.0 - axial_tolerance) * chord_tall)
    if not aligned:
        return exact
    coarse = grid.resized(tuple(max(2, s // 4) for s in grid.shape_zyx),
                          tuple(e / max(2, s // 4) for e, s in zip(grid.extent_mm, grid.shape_xyz)))
    nz, ny, nx = coarse.shape_zyx
    tall = coarse.resized((3 * nz, ny, nx))
    chord = forward_project(np.ones(coarse.shape_zyx, np.float32), coarse, geom)
    chord_tall = forward_project(np.ones(tall.shape_zyx, np.float32), tall, geom)
    peak = chord.reshape(chord.shape[0], -1).max(axis=1)
    margin = (chord > (fraction * peak)[:, None, None]) & (chord >= (1.0 - axial_tolerance) * chord_tall)
    return margin if margin.sum() >= FACE_MARGIN_SHARE * exact.sum() else exact


def as_view_mask(valid_mask, shape) -> np.ndarray:
    return view_mask(valid_mask, shape)


def usable_data(line_integrals, valid_mask) -> tuple[np.ndarray, np.ndarray]:
    """float32 line integrals with every pixel that is invalid or not finite set to 0, and the
    (n, rows, cols) mask of the others.

    Data that are float32, C-contiguous and already 0 wherever the mask is False (a scan as
    :func:`~robot_ct_ros.ct.simulation.simulate_scan` and the importers deliver it) are returned
    as they are, not copied: the caller's array, which the calibration only reads (a full-size
    stack is 250 MB)."""
    li = np.ascontiguousarray(line_integrals, dtype=np.float32)
    mask = as_view_mask(valid_mask, li.shape) & np.isfinite(li)
    if mask.all() or not np.any(li[~mask]):  # nothing to zero (a NaN in li[~mask] counts as non-zero)
        return li, mask
    return np.where(mask, li, np.float32(0.0)), mask


BIN_CHUNK_VIEWS = 32
"""Views :func:`bin_masked` bins at a time (its float32 temporaries are a chunk, not the stack)."""


def bin_masked(line_integrals: np.ndarray, valid_mask: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Average valid pixels in ``factor`` x ``factor`` bins; a bin with no valid pixel is invalid.

    Binned :data:`BIN_CHUNK_VIEWS` views at a time, so no full-size temporary is made."""
    from robot_ct_ros.ct.geometry import bin_factors, bin_projections

    shape = np.shape(line_integrals)
    fr, fc = bin_factors(shape[-2:], factor)
    n = shape[0]
    out = np.empty((n, shape[-2] // fr, shape[-1] // fc), np.float32)
    valid = np.empty(out.shape, bool)
    full_mask = as_view_mask(valid_mask, shape)
    for v0 in range(0, n, BIN_CHUNK_VIEWS):
        sl = slice(v0, min(n, v0 + BIN_CHUNK_VIEWS))
        m = full_mask[sl].astype(np.float32)
        total = bin_projections(np.where(m > 0, line_integrals[sl], 0.0).astype(np.float32), factor)
        count = bin_projections(m, factor)
        out[sl] = total / np.maximum(count, 1.0)
        valid[sl] = count > 0
    return out, valid


def usable_views(mask: np.ndarray, minimum: int = MIN_VIEW_PIXELS) -> np.ndarray:
    """Indices of the views of an (n, rows, cols) pixel mask with at least ``minimum`` usable pixels."""
    m = np.asarray(mask, bool)
    return np.flatnonzero(m.reshape(m.shape[0], -1).sum(axis=1) >= minimum)


def view_chunks(views: np.ndarray, size: int):
    """The view indices ``views`` in chunks of at most ``size``: those in the same window of ``size``
    consecutive indices (``v // size``) together, so a block of views starting at a multiple of
    ``size`` chunks its views as the whole scan does (:mod:`robot_ct_ros.ct.calibration.distributed`)."""
    views = np.asarray(views, np.int64)
    if views.size == 0:
        return
    window = views // max(1, int(size))
    yield from np.split(views, np.flatnonzero(np.diff(window)) + 1)


def estimator_inputs(measured, nominal: ConeGeometry, params0, valid_mask, grid: VolumeGrid,
                     support_fraction: float | None, support_mask=None):
    """What every per-view estimator starts from: the measured views as float32 (n, rows, cols)
    checked against ``nominal``, the starting parameters (n, 9) as a copy, the valid pixels
    (valid and finite) and the pixels to register (also on the ROI support, unless
    ``support_fraction`` is None: every ray modelled).

    ``support_mask`` (n, rows, cols), when given, is that ROI support, computed beforehand: for a
    block of views of a larger scan it must be the whole scan's (:func:`roi_support_mask` decides
    between its margin and exact forms over all views).

    Raises
    ------
    ValueError
        The views do not match the geometry's count or detector.
    """
    n = nominal.n_views
    meas = np.ascontiguousarray(measured, dtype=np.float32)
    if meas.shape != (n,) + nominal.det_shape:
        raise ValueError(f"measured {meas.shape} does not match the geometry ({n}, {nominal.det_shape})")
    params = np.array(params0, dtype=np.float64).reshape(n, 9)
    valid = as_view_mask(valid_mask, meas.shape) & np.isfinite(meas)
    if support_fraction is None:
        mask = valid
    elif support_mask is not None:
        mask = valid & np.asarray(support_mask, bool).reshape(meas.shape)
    else:
        mask = valid & roi_support_mask(nominal, params, grid, support_fraction)
    return meas, params, valid, mask


_REDUCERS = {"mean": np.mean, "median": np.median, "nanmean": np.nanmean}


def summarise_views(per_view: dict) -> dict:
    """An estimator's summaries from its per-view values: ``per_view`` maps a name to (reducer,
    empty, [values per step]), reducer ``"mean"``, ``"median"`` or ``"nanmean"`` over one step's
    views (a 1-D array each), ``empty`` the summary of a step without values (None: the step is
    left out). Returns name -> [summary per step]. Blocks of views estimated apart are summarised
    alike after joining their values step by step (:mod:`robot_ct_ros.ct.calibration.distributed`)."""
    out = {}
    for key, (reducer, empty, steps) in per_view.items():
        summary = []
        for values in steps:
            values = np.asarray(values, np.float64)
            if values.size == 0 or (reducer == "nanmean" and not np.isfinite(values).any()):
                if empty is not None:
                    summary.append(float(empty))
                continue
            summary.append(float(_REDUCERS[reducer](values)))
        out[key] = summary
    return out

