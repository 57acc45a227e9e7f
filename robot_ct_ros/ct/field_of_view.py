"""The field of view: the voxels a scan's measured rays cross in every direction.

Conventions (world mm, ``volume[k, j, i] = (z, y, x)``, projection matrices) are those of
:mod:`robot_ct_ros.ct.geometry`. FDK reconstructs these voxels from complete data; outside them
(a square grid's corners beyond the circle every view sees) it puts what incomplete data give.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.reconstruction import estimate_scan_axis
from robot_ct_ros.ct.scan_weights import rows_run_across_axis

__all__ = ["field_of_view_mask"]


@njit(parallel=True, cache=True)
def _line_coverage_kernel(pm, depth_sign, src, e1, e2, origin, steps, shape_zyx, across, n_across, n_bins, out):
    """``out[k, j, i]``: 1 where the rays measured through the voxel at block centre (i, j, k)
    cover every one of ``n_bins`` direction bins over 180 degrees, else 0. A ray is measured where
    it meets the detector within its ``n_across`` pixels along the detector index ``across`` (0: the
    column, 1: the row), the one that runs across the scan axis."""
    nz, ny, nx = shape_zyx[0], shape_zyx[1], shape_zyx[2]
    full = np.uint64((1 << n_bins) - 1)
    for flat in prange(nz * ny * nx):
        k = flat // (ny * nx)
        j = (flat // nx) % ny
        i = flat % nx
        x = origin[0] + i * steps[0, 0] + j * steps[1, 0] + k * steps[2, 0]
        y = origin[1] + i * steps[0, 1] + j * steps[1, 1] + k * steps[2, 1]
        z = origin[2] + i * steps[0, 2] + j * steps[1, 2] + k * steps[2, 2]
        hit = np.uint64(0)
        for v in range(pm.shape[0]):
            lam = pm[v, 2, 0] * x + pm[v, 2, 1] * y + pm[v, 2, 2] * z + pm[v, 2, 3]
            if lam * depth_sign[v] <= 0.0:
                continue
            c = (pm[v, across, 0] * x + pm[v, across, 1] * y + pm[v, across, 2] * z + pm[v, across, 3]) / lam
            if c < -0.5 or c > n_across - 0.5:
                continue
            dx, dy, dz = x - src[v, 0], y - src[v, 1], z - src[v, 2]
            a = math.atan2(dx * e2[0] + dy * e2[1] + dz * e2[2], dx * e1[0] + dy * e1[1] + dz * e1[2])
            if a < 0.0:
                a += math.pi
            b = int(a * n_bins / math.pi)
            if b >= n_bins:
                b = n_bins - 1
            hit |= np.uint64(1) << np.uint64(b)
        out[k, j, i] = 1 if hit == full else 0


def field_of_view_mask(geom: ConeGeometry, grid: VolumeGrid, *, max_evaluations: float = 1e8) -> np.ndarray:
    """Voxels FDK reconstructs from complete data: bool ``grid.shape_zyx``.

    A voxel counts when the measured rays through it (those that meet a view's detector within
    its extent across the scan axis: its columns, or its rows on a portrait detector,
    :func:`~robot_ct_ros.ct.scan_weights.rows_run_across_axis`) cover every direction about the scan axis (:func:`estimate_scan_axis`),
    modulo 180 degrees, in bins of at most 45 degrees and at least ~6 views each. For a
    centred detector on a full circle that is the cylinder every view sees; with an offset
    detector the conjugate views fill in; the square grid's corners outside it are left out
    (FDK puts there what incomplete data give, streaks that are no object). The extent along the
    axis is not checked: the cone's top and bottom are the pixel mask's business. To bound the cost
    (voxels x views), the test runs on block centres of a coarser grid (each block takes its
    centre's answer) when the grid holds more than ``max_evaluations / n_views`` voxels. When
    no voxel has complete data (a limited-angle or degenerate scan), every voxel counts.
    """
    nz, ny, nx = grid.shape_zyx
    n_views = geom.n_views
    if n_views < 3:
        return np.ones(grid.shape_zyx, dtype=bool)
    n_bins = int(min(32, max(4, n_views // 6)))
    budget = max(max_evaluations / n_views, 1.0)
    block = max(1, int(math.ceil((nz * ny * nx / budget) ** (1.0 / 3.0))))
    while True:  # blocks per axis (a thin axis keeps its voxels when it is shorter than the block)
        bz, by, bx = (min(block, n) for n in (nz, ny, nx))
        cshape = (-(-nz // bz), -(-ny // by), -(-nx // bx))
        if cshape[0] * cshape[1] * cshape[2] <= budget or block > max(nz, ny, nx):
            break
        block += 1
    axis = estimate_scan_axis(geom)
    # direction bins start at the first source seen from the grid centre: they turn with the scan, not the world
    r0 = geom.source_mm[0] - grid.center_mm
    e1 = r0 - np.dot(r0, axis) * axis
    if np.linalg.norm(e1) < 1e-9 * max(np.linalg.norm(r0), 1e-12):
        e1 = geom.u[0] - np.dot(geom.u[0], axis) * axis
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    pm = geom.projection_matrices()
    depth_sign = np.sign(np.einsum("ij,ij->i", geom.detector_mm - geom.source_mm, geom.w))
    vs = np.asarray(grid.voxel_size_mm)
    D = grid.direction_matrix
    steps = (D * (vs * np.array([bx, by, bz]))).T  # rows: world step per block along the grid's x, y, z
    # the centre of block 0 (clipped into the grid for a block longer than the axis)
    first = 0.5 * (np.array([min(bx, nx), min(by, ny), min(bz, nz)]) - 1)
    origin = grid.index_to_world(first)
    cov = np.zeros(cshape, dtype=np.uint8)
    across = 0 if rows_run_across_axis(geom, axis) else 1
    _line_coverage_kernel(pm, depth_sign, geom.source_mm, e1, e2, origin, np.ascontiguousarray(steps),
                          np.array(cshape, dtype=np.int64), across, int(geom.n_cols if across == 0 else geom.n_rows),
                          n_bins, cov)
    if not cov.any():
        return np.ones(grid.shape_zyx, dtype=bool)
    kk, jj, ii = (np.arange(n) // b for n, b in zip((nz, ny, nx), (bz, by, bx)))
    return cov.astype(bool)[kk[:, None, None], jj[None, :, None], ii[None, None, :]]
