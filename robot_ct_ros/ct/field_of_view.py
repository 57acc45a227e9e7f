"""The field of view: the voxels a scan's measured rays cross in every direction.

Conventions (world mm, ``volume[k, j, i] = (z, y, x)``, projection matrices) are those of
:mod:`robot_ct_ros.ct.geometry`. FDK reconstructs these voxels from complete data; outside them
(a square grid's corners beyond the circle every view sees) it puts what incomplete data give.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.reconstruction import estimate_scan_axis
from robot_ct_ros.ct.scan_weights import rows_run_across_axis

__all__ = ["field_of_view_mask", "field_of_view_extent", "FieldOfViewExtent", "cone_reach", "ConeReach"]


@njit(parallel=True, cache=True)
def _line_coverage_kernel(pm, depth, src, e1, e2, origin, steps, shape_zyx, across, n_across, n_bins, out):
    """``out[k, j, i]``: 1 where the rays measured through the voxel at block centre (i, j, k)
    cover every one of ``n_bins`` direction bins over 180 degrees, else 0. A ray is measured where
    it meets the detector within its ``n_across`` pixels along the detector index ``across`` (0: the
    column, 1: the row), the one that runs across the scan axis, and it passes through the voxel where
    the voxel lies between the source and the detector plane (``depth``: each view's signed source-to-plane
    distance along the detector normal; ``lambda / depth`` in (0, 1))."""
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
            if depth[v] == 0.0 or not 0.0 < lam / depth[v] < 1.0:
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


def _coverage(geom: ConeGeometry, grid: VolumeGrid, max_evaluations: float) -> np.ndarray:
    """:func:`field_of_view_mask`'s test itself, without its fallbacks: bool ``grid.shape_zyx``."""
    nz, ny, nx = grid.shape_zyx
    n_views = geom.n_views
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
    depth = np.einsum("ij,ij->i", geom.detector_mm - geom.source_mm, geom.w)
    vs = np.asarray(grid.voxel_size_mm)
    D = grid.direction_matrix
    steps = (D * (vs * np.array([bx, by, bz]))).T  # rows: world step per block along the grid's x, y, z
    # the centre of block 0 (clipped into the grid for a block longer than the axis)
    first = 0.5 * (np.array([min(bx, nx), min(by, ny), min(bz, nz)]) - 1)
    origin = grid.index_to_world(first)
    cov = np.zeros(cshape, dtype=np.uint8)
    across = 0 if rows_run_across_axis(geom, axis) else 1
    _line_coverage_kernel(pm, depth, geom.source_mm, e1, e2, origin, np.ascontiguousarray(steps),
                          np.array(cshape, dtype=np.int64), across, int(geom.n_cols if across == 0 else geom.n_rows),
                          n_bins, cov)
    kk, jj, ii = (np.arange(n) // b for n, b in zip((nz, ny, nx), (bz, by, bx)))
    return cov.astype(bool)[kk[:, None, None], jj[None, :, None], ii[None, None, :]]


def field_of_view_mask(geom: ConeGeometry, grid: VolumeGrid, *, max_evaluations: float = 1e8) -> np.ndarray:
    """Voxels FDK reconstructs from complete data: bool ``grid.shape_zyx``.

    A voxel counts when the measured rays through it (those that meet a view's detector within
    its extent across the scan axis: its columns, or its rows on a portrait detector,
    :func:`~robot_ct_ros.ct.scan_weights.rows_run_across_axis`, and that pass through the voxel: it lies
    between the view's source and its detector plane) cover every direction about the scan axis
    (:func:`estimate_scan_axis`), modulo 180 degrees, in bins of at most 45 degrees and at least ~6 views each.
    For a centred detector on a full circle that is the cylinder every view sees; with an offset
    detector the conjugate views fill in; the square grid's corners outside it are left out
    (FDK puts there what incomplete data give, streaks that are no object). The extent along the
    axis is not checked: the cone's top and bottom are the pixel mask's business. To bound the cost
    (voxels x views), the test runs on block centres of a coarser grid (each block takes its
    centre's answer) when the grid holds more than ``max_evaluations / n_views`` voxels.

    Where no voxel of the grid has complete data, the answer depends on the scan: when the scan has
    a field of view elsewhere (:func:`field_of_view_extent` finds one) the grid misses it and no voxel
    counts (all False: callers must not take that for "no support"); when the scan has none at all (a
    limited-angle or degenerate scan, fewer than 3 views), FDK is approximate everywhere and every voxel
    counts (all True).
    """
    if geom.n_views < 3:
        return np.ones(grid.shape_zyx, dtype=bool)
    mask = _coverage(geom, grid, max_evaluations)
    if mask.any():
        return mask
    return np.full(grid.shape_zyx, field_of_view_extent(geom) is None, dtype=bool)


def _xyz(p, digits: int) -> str:
    """``[x, y, z]`` to ``digits`` decimals, no ``-0.0``."""
    return "[" + ", ".join(f"{round(float(x), digits) + 0.0:.{digits}f}" for x in p) + "]"


@dataclass(frozen=True)
class FieldOfViewExtent:
    """Where a scan's field of view lies (:func:`field_of_view_extent`): about the scan axis ``axis`` (unit) through
    ``center_mm`` (world mm: the centre of the views, :func:`~robot_ct_ros.ct.geometry.views_center_mm`), within
    ``radius_mm`` of that axis (the farthest point found with complete data, to about 3 % of it)."""

    center_mm: np.ndarray
    axis: np.ndarray
    radius_mm: float

    def distance_mm(self, point_mm) -> float:
        """How far ``point_mm`` lies from the scan axis."""
        r = np.asarray(point_mm, float) - self.center_mm
        return float(np.linalg.norm(r - np.dot(r, self.axis) * self.axis))

    def misses_note(self, grid: VolumeGrid) -> str:
        """The note for a grid no voxel of which lies in the field of view (:func:`field_of_view_mask` all False)."""
        c = grid.center_mm
        return (f"the grid misses the field of view: none of its voxels is reached by the measured rays from every "
                f"direction about the scan axis (the field of view lies within {self.radius_mm:.1f} mm of the scan "
                f"axis through {_xyz(self.center_mm, 1)} mm, along {_xyz(self.axis, 3)}; the grid's centre "
                f"{_xyz(c, 1)} mm lies {self.distance_mm(c):.1f} mm from that axis): what FDK puts there is "
                f"streaks, not the object; move the grid (roi_center_m) into the field of view")


def field_of_view_extent(geom: ConeGeometry, *, probe_voxels: int = 65) -> FieldOfViewExtent | None:
    """Where the scan's field of view (:func:`field_of_view_mask`) lies across its axis, or None where no point
    has complete data (a limited-angle or degenerate scan, fewer than 3 views). Probed on one slice through the
    centre of the views (:func:`~robot_ct_ros.ct.geometry.views_center_mm`), across the scan axis: first over the
    sources' orbit, then over the disc found, ``probe_voxels`` across each time (the radius to about 1.5 /
    ``probe_voxels`` of it)."""
    from robot_ct_ros.ct.geometry import axis_frame, views_center_mm

    if geom.n_views < 3:
        return None
    center = views_center_mm(geom)
    axis = estimate_scan_axis(geom)
    r = geom.source_mm - center
    orbit = float(np.max(np.linalg.norm(r - np.outer(r @ axis, axis), axis=1)))
    if not orbit > 0:
        return None
    D = axis_frame(axis)
    radius = orbit
    for _ in range(2):
        vox = 2.0 * radius / (probe_voxels - 1)
        probe = VolumeGrid.centered((1, probe_voxels, probe_voxels), vox, center, D)
        cov = _coverage(geom, probe, 1e12)[0]
        if not cov.any():
            return None
        jj, ii = np.nonzero(cov)
        half = 0.5 * (probe_voxels - 1)
        radius = float(np.hypot(ii - half, jj - half).max() + 1.0) * vox
    return FieldOfViewExtent(center, axis, radius - vox)


@njit(parallel=True, cache=True)
def _reach_kernel(pm, depth, ii, jj, kk, origin, steps, n_cols, n_rows, out):
    """``out[a, b, c]``: 1 where the voxel (ii[c], jj[b], kk[a]) lies between some view's source and its detector
    plane (``depth``: the signed source-to-plane distances; ``lambda / depth`` in (0, 1)) and projects onto that
    detector (within its columns and its rows, half a pixel beyond the outer pixel centres), else 0. A voxel behind
    the source or beyond the detector plane is on no measured ray of that view."""
    na, nb, nc = kk.shape[0], jj.shape[0], ii.shape[0]
    for flat in prange(na * nb * nc):
        a = flat // (nb * nc)
        b = (flat // nc) % nb
        c = flat % nc
        i, j, k = ii[c], jj[b], kk[a]
        x = origin[0] + i * steps[0, 0] + j * steps[1, 0] + k * steps[2, 0]
        y = origin[1] + i * steps[0, 1] + j * steps[1, 1] + k * steps[2, 1]
        z = origin[2] + i * steps[0, 2] + j * steps[1, 2] + k * steps[2, 2]
        hit = 0
        for v in range(pm.shape[0]):
            lam = pm[v, 2, 0] * x + pm[v, 2, 1] * y + pm[v, 2, 2] * z + pm[v, 2, 3]
            if depth[v] == 0.0 or not 0.0 < lam / depth[v] < 1.0:
                continue
            col = (pm[v, 0, 0] * x + pm[v, 0, 1] * y + pm[v, 0, 2] * z + pm[v, 0, 3]) / lam
            if col < -0.5 or col > n_cols - 0.5:
                continue
            row = (pm[v, 1, 0] * x + pm[v, 1, 1] * y + pm[v, 1, 2] * z + pm[v, 1, 3]) / lam
            if row < -0.5 or row > n_rows - 0.5:
                continue
            hit = 1
            break
        out[a, b, c] = hit


AXIS_NAMES = ("x", "y", "z")


@dataclass(frozen=True)
class ConeReach:
    """Which part of a grid some view's cone reaches (:func:`cone_reach`).

    ``mask``: bool ``grid.shape_zyx``, True where some view's detector sees the voxel; ``axis``: the grid axis
    (0, 1, 2: x, y, z) closest to the scan axis, along which ``slices`` (bool, one per slice) says which slices
    hold such a voxel; ``shape_xyz``: the grid's shape."""

    mask: np.ndarray
    axis: int
    slices: np.ndarray
    shape_xyz: tuple

    @property
    def outside_fraction(self) -> float:
        """The share of the grid's voxels that no view's detector sees (beyond every cone: FDK puts 0 there)."""
        return 1.0 - float(self.mask.mean())

    @property
    def n_reached(self) -> int:
        return int(self.slices.sum())

    def mostly_outside(self) -> bool:
        """More than half of the grid's slices along the scan axis, or of its voxels, lie beyond every view's cone,
        while some lie within one (where none does, FDK warns that it put nothing into the grid)."""
        n = len(self.slices)
        return 0 < self.n_reached and (self.n_reached < 0.5 * n or self.outside_fraction > 0.5)

    def fitting_shape_xyz(self) -> tuple:
        """The grid's shape with as many slices along the axis as the cones reach."""
        shape = list(self.shape_xyz)
        shape[self.axis] = self.n_reached
        return tuple(shape)

    def note(self, shape_option: str = "--shape {},{},{}") -> str:
        """The note for a grid :meth:`mostly_outside` the cones; ``shape_option`` formats the fitting shape (x, y,
        z) as the user sets it. Empty where the grid is not mostly outside."""
        if not self.mostly_outside():
            return ""
        reached = np.flatnonzero(self.slices)
        first, last = int(reached[0]), int(reached[-1])
        span = f"slice {first}" if first == last else f"slices {first}-{last}"
        where = "" if last - first + 1 == len(reached) else ", not all contiguous"
        return (f"most of the grid lies beyond every view's cone: the rays reach {len(reached)} of its "
                f"{len(self.slices)} slices along {AXIS_NAMES[self.axis]}, the axis nearest the scan axis "
                f"({span}{where}; {100 * self.outside_fraction:.0f} % of the voxels lie where no view's detector "
                f"sees them, and FDK puts 0 there); a grid that fits the cones: "
                f"{shape_option.format(*self.fitting_shape_xyz())}"
                f"{'' if first + last == len(self.slices) - 1 else ' (off-centre in this grid: move its centre too)'}")


def cone_reach(geom: ConeGeometry, grid: VolumeGrid, *, max_evaluations: float = 1e8) -> ConeReach:
    """The voxels of ``grid`` that some view's detector sees (:class:`ConeReach`): those inside one view's cone
    at least. Unlike :func:`field_of_view_mask` it checks the detector's rows too (the cone's top and bottom), and
    any view is enough. Every slice along the grid axis nearest the scan axis is tested; across it, to bound the cost
    (voxels x views within ``max_evaluations``), a regular subset of the voxels, each standing for its neighbours."""
    nz, ny, nx = grid.shape_zyx
    shape_xyz = (nx, ny, nz)
    axis_dir = estimate_scan_axis(geom)
    D = grid.direction_matrix
    axis = int(np.argmax(np.abs(D.T @ axis_dir)))
    budget = max(max_evaluations / max(geom.n_views, 1), 1.0)
    across = [a for a in range(3) if a != axis]
    stride = 1
    while shape_xyz[axis] * math.ceil(shape_xyz[across[0]] / stride) * math.ceil(shape_xyz[across[1]] / stride) \
            > budget and stride < max(shape_xyz):
        stride += 1
    idx = []
    for a in range(3):
        n = shape_xyz[a]
        step = 1 if a == axis else stride
        idx.append(np.minimum(np.arange(n // step + (n % step > 0)) * step + (step - 1) // 2, n - 1).astype(np.int64))
    pm = geom.projection_matrices()
    depth = np.einsum("ij,ij->i", geom.detector_mm - geom.source_mm, geom.w)
    steps = np.ascontiguousarray((D * np.asarray(grid.voxel_size_mm)).T)  # rows: world step per voxel along x, y, z
    origin = grid.index_to_world(np.zeros(3))
    out = np.zeros((len(idx[2]), len(idx[1]), len(idx[0])), dtype=np.uint8)
    _reach_kernel(pm, depth, idx[0], idx[1], idx[2], origin, steps, int(geom.n_cols), int(geom.n_rows), out)
    # each voxel takes the answer of the sampled voxel of its block
    kk, jj, ii = (np.arange(n) // (1 if a == axis else stride) for a, n in ((2, nz), (1, ny), (0, nx)))
    mask = out.astype(bool)[kk[:, None, None], jj[None, :, None], ii[None, None, :]]
    other = tuple(2 - a for a in across)  # the zyx array axes across the scan axis
    return ConeReach(mask, axis, mask.any(axis=other), shape_xyz)
