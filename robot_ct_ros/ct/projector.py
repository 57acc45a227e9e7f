"""Ray-driven Joseph forward projector and its exact adjoint for per-view cone-beam geometry.

Conventions are those of :mod:`robot_ct_ros.ct.geometry` (volumes ``[k, j, i] = (z, y, x)``,
``VolumeGrid.origin_mm`` = centre of voxel 0, projections ``[view, row, col]``, pixel (0, 0)
centre of the first pixel). Projections are line integrals: mm x volume units.

Method (Joseph 1982, as RTK's ``JosephForwardProjectionImageFilter``): the ray from the
source to a pixel centre is clipped to the volume box and to the source-detector segment;
it is stepped one slice at a time along its dominant axis (measured in voxel units, so
anisotropic voxels pick the right axis); at every slice centre the volume is bilinearly
interpolated in the perpendicular plane and weighted by the path length of the ray inside
that slice (full slices: one step, first/last slices: the clipped fraction).

One convention differs from RTK: the box is the outer faces of the voxels
([-0.5, n - 0.5] in index units) and samples outside the volume count as zero. A uniform
volume therefore integrates to the true chord length along a ray that enters and leaves
through the two faces normal to its stepping (dominant) axis, the slices there being
clipped exactly. It does not on a ray that crosses one of the four other (side) faces:
in the outer half voxel beyond the last voxel centres the bilinear interpolation with the
zero outside fades the volume from 1 to 1/2, so the ray comes short by 1/8 of that axis's
voxel size divided by |cos| of the angle between the ray and the face's normal, per side
face crossed: a small fraction of a voxel for a steep crossing, several voxels (a large
share of the chord) for a grazing one, and up to half the path for a ray that runs along
a face inside that outer half voxel. RTK clips the ray to the box of voxel *centres*
([0, n - 1]) and clamps at its borders: along a uniform volume its integrals are short by
half a voxel of the face's axis, over that same |cos|, at each face the ray crosses (one
voxel for a ray straight through; many millimetres for oblique crossings). The two agree
exactly when the volume is zero in its outer two voxel layers.

``back_project`` is the exact transpose of ``forward_project``: the same rays, the same
slices, the same bilinear weights, scattered instead of gathered.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit, prange

from .geometry import ConeGeometry, VolumeGrid

__all__ = ["forward_project", "back_project", "ray_geometry"]

# Margin (in voxels) that keeps the unchecked inner loop away from the array edges. It
# covers the float32 rounding of the perpendicular coordinates, which is below 2e-7 x n
# voxel (|coordinate| <= 2n, |slope| <= 1), i.e. volumes up to ~5000 voxels a side.
_EDGE = 1e-3
# per-view ray table columns: source (3), pixel (0, 0) (3), column step (3), row step (3),
# all in voxel-index units (x, y, z)
_NGEO = 12


def ray_geometry(geom: ConeGeometry, grid: VolumeGrid) -> np.ndarray:
    """Per-view ray table (n_views, 12) float64 in voxel-index units (x, y, z).

    Columns: source, centre of pixel (0, 0), step per column, step per row. Index
    coordinates are ``grid.world_to_index(world_mm)``: the grid's own frame, whatever its
    direction, so the kernels only ever see an axis-aligned grid.
    """
    D = grid.direction_matrix
    vs = np.asarray(grid.voxel_size_mm, dtype=np.float64)
    c0 = 0.5 * (geom.n_cols - 1) * geom.col_pitch_mm
    r0 = 0.5 * (geom.n_rows - 1) * geom.row_pitch_mm
    p00 = geom.detector_mm - c0 * geom.u - r0 * geom.v
    out = np.empty((geom.n_views, _NGEO), dtype=np.float64)
    out[:, 0:3] = grid.world_to_index(geom.source_mm)
    out[:, 3:6] = grid.world_to_index(p00)
    out[:, 6:9] = (geom.u @ D) * geom.col_pitch_mm / vs
    out[:, 9:12] = (geom.v @ D) * geom.row_pitch_mm / vs
    return out


# --------------------------------------------------------------------------- ray setup
@njit(inline="always", fastmath=True)
def _setup_ray(rg, view, row, col, shape_xyz, vs_xyz):
    """Clip one ray; return its stepping parameters in voxel units.

    Returns (ok, a, m0, m1, k0, k1, b0, sb, c0, sc, length_mm_per_step, ab, ac) where a
    is the dominant axis, [m0, m1] the clipped extent along it (m0 <= m1), [k0, k1] the
    slices touched, the perpendicular coordinates along axes ab < ac are
    ``b0 + k * sb`` and ``c0 + k * sc`` at slice k.
    """
    sx = rg[view, 0]
    sy = rg[view, 1]
    sz = rg[view, 2]
    dx = rg[view, 3] + col * rg[view, 6] + row * rg[view, 9] - sx
    dy = rg[view, 4] + col * rg[view, 7] + row * rg[view, 10] - sy
    dz = rg[view, 5] + col * rg[view, 8] + row * rg[view, 11] - sz
    s = (sx, sy, sz)
    d = (dx, dy, dz)
    # slab clipping of s + t d, t in [0, 1] (source to pixel), box [-0.5, n - 0.5]
    tmin = 0.0
    tmax = 1.0
    for i in range(3):
        di = d[i]
        si = s[i]
        lo = -0.5
        hi = shape_xyz[i] - 0.5
        if di == 0.0:
            if si < lo or si > hi:
                tmax = -1.0
        else:
            inv = 1.0 / di
            t1 = (lo - si) * inv
            t2 = (hi - si) * inv
            if t1 > t2:
                t1, t2 = t2, t1
            tmin = max(tmin, t1)
            tmax = min(tmax, t2)
    adx = abs(dx)
    ady = abs(dy)
    adz = abs(dz)
    if adx >= ady and adx >= adz:
        a, ab, ac = 0, 1, 2
    elif ady >= adz:
        a, ab, ac = 1, 0, 2
    else:
        a, ab, ac = 2, 0, 1
    if not tmax > tmin or d[a] == 0.0:  # missed, or a pixel at the source itself
        return False, a, 0.0, 0.0, 0, -1, 0.0, 0.0, 0.0, 0.0, 0.0, ab, ac
    da = d[a]
    m0 = s[a] + tmin * da
    m1 = s[a] + tmax * da
    if m0 > m1:
        m0, m1 = m1, m0
    inv_da = 1.0 / da
    sb = d[ab] * inv_da
    sc = d[ac] * inv_da
    b0 = s[ab] - s[a] * sb
    c0 = s[ac] - s[a] * sc
    length = math.sqrt(vs_xyz[a] ** 2 + (sb * vs_xyz[ab]) ** 2 + (sc * vs_xyz[ac]) ** 2)
    k0 = max(0, int(math.floor(m0 + 0.5)))
    k1 = min(shape_xyz[a] - 1, int(math.floor(m1 + 0.5)))
    return True, a, m0, m1, k0, k1, b0, sb, c0, sc, length, ab, ac


@njit(inline="always", fastmath=True)
def _safe_range(x0, slope, n, k0, k1):
    """Slices k in [k0, k1] where 0 < x0 + k slope < n - 1 with margin (unchecked bilinear)."""
    lo = _EDGE
    hi = n - 1.0 - _EDGE
    if hi < lo:
        return k1 + 1, k1
    if slope > 1e-9:
        inv = 1.0 / slope
        fa = math.ceil((lo - x0) * inv)
        fb = math.floor((hi - x0) * inv)
    elif slope < -1e-9:
        inv = 1.0 / slope
        fa = math.ceil((hi - x0) * inv)
        fb = math.floor((lo - x0) * inv)
    else:
        if x0 >= lo and x0 <= hi:
            return k0, k1
        return k1 + 1, k1
    # clamp in float before converting: the bounds can be huge for nearly parallel rays
    fa = max(float(k0), min(float(k1 + 1), float(fa)))
    fb = min(float(k1), max(float(k0 - 1), float(fb)))
    return int(fa), int(fb)


@njit(inline="always", fastmath=True)
def _interior(m0, m1, b0, sb, nb, c0, sc, nc, k0, k1):
    """Slices [ka, kb] with full weight whose bilinear footprint lies inside the array."""
    ka, kb = _safe_range(b0, sb, nb, k0 + 1, k1 - 1)
    kc, kd = _safe_range(c0, sc, nc, k0 + 1, k1 - 1)
    ka = max(ka, kc)
    kb = min(kb, kd)
    if kb < ka:
        # no unchecked slices: everything through the checked path
        ka = k1 + 1
        kb = k1
    return ka, kb


@njit(inline="always", fastmath=True)
def _slice_weight(k, m0, m1):
    w = min(m1, k + 0.5) - max(m0, k - 0.5)
    return w if w > 0.0 else 0.0


# ------------------------------------------------------------------------ forward kernel
@njit(inline="always", fastmath=True)
def _sample_checked(vol, k, sa, xb, nb, strb, xc, nc, strc):
    fb = math.floor(xb)
    fc = math.floor(xc)
    ib = int(fb)
    ic = int(fc)
    wb1 = xb - fb
    wc1 = xc - fc
    wb0 = 1.0 - wb1
    wc0 = 1.0 - wc1
    base = k * sa
    acc = 0.0
    if ic >= 0 and ic < nc:
        if ib >= 0 and ib < nb:
            acc += wb0 * wc0 * vol[base + ib * strb + ic * strc]
        if ib + 1 >= 0 and ib + 1 < nb:
            acc += wb1 * wc0 * vol[base + (ib + 1) * strb + ic * strc]
    if ic + 1 >= 0 and ic + 1 < nc:
        if ib >= 0 and ib < nb:
            acc += wb0 * wc1 * vol[base + ib * strb + (ic + 1) * strc]
        if ib + 1 >= 0 and ib + 1 < nb:
            acc += wb1 * wc1 * vol[base + (ib + 1) * strb + (ic + 1) * strc]
    return acc


@njit(inline="always", fastmath=True)
def _ray_sum(vol, rg, view, row, col, shape_xyz, strides_xyz, vs_xyz):
    ok, a, m0, m1, k0, k1, b0, sb, c0, sc, length, ab, ac = _setup_ray(
        rg, view, row, col, shape_xyz, vs_xyz)
    if not ok:
        return np.float32(0.0)
    sa = strides_xyz[a]
    strb = strides_xyz[ab]
    strc = strides_xyz[ac]
    nb = shape_xyz[ab]
    nc = shape_xyz[ac]
    ka, kb = _interior(m0, m1, b0, sb, nb, c0, sc, nc, k0, k1)
    total = 0.0
    # checked head: partial first slice and slices whose footprint leaves the array
    for k in range(k0, ka):
        w = _slice_weight(k, m0, m1)
        total += w * _sample_checked(vol, k, sa, b0 + k * sb, nb, strb, c0 + k * sc, nc, strc)
    # unchecked interior, float32: one step per slice, weight 1; a float slice counter
    # saves an int-to-float conversion per step. (Splitting the sum over two accumulators
    # was measured slower: the loop is bound by loads and address arithmetic.)
    b0f = np.float32(b0)
    sbf = np.float32(sb)
    c0f = np.float32(c0)
    scf = np.float32(sc)
    one = np.float32(1.0)
    ustrb = np.uint64(strb)
    ustrc = np.uint64(strc)
    acc = np.float32(0.0)
    kf = np.float32(ka)
    kbase = ka * sa
    for _ in range(ka, kb + 1):
        xb = b0f + kf * sbf
        xc = c0f + kf * scf
        ib = int(xb)  # xb > 0: truncation is floor
        ic = int(xc)
        fb = xb - np.float32(ib)
        fc = xc - np.float32(ic)
        # unsigned indices: numba then skips its negative-index wraparound code
        p = np.uint64(kbase + ib * strb + ic * strc)
        v00 = vol[p]
        v10 = vol[p + ustrb]
        v01 = vol[p + ustrc]
        v11 = vol[p + (ustrb + ustrc)]
        v0 = v00 + fb * (v10 - v00)
        v1 = v01 + fb * (v11 - v01)
        acc += v0 + fc * (v1 - v0)
        kf += one
        kbase += sa
    total += acc
    # checked tail
    for k in range(max(kb + 1, ka), k1 + 1):
        w = _slice_weight(k, m0, m1)
        total += w * _sample_checked(vol, k, sa, b0 + k * sb, nb, strb, c0 + k * sc, nc, strc)
    return np.float32(total * length)


@njit(parallel=True, fastmath=True, cache=True)
def _forward_kernel(vol, rg, shape_xyz, strides_xyz, vs_xyz, out, n_workers, block):
    # Work unit: a block of `block` consecutive detector lines (view, row) of n_cols rays,
    # so consecutive rays, and consecutive lines, share cache lines of the volume. Blocks
    # are dealt round-robin to the workers (b, b + n_workers, ...): every thread gets a
    # share of every view and of every part of the detector, which balances the load even
    # when rays that miss the volume cluster (an enlarged virtual detector, an off-centre
    # ROI), and a batch of a single view still uses all threads.
    n_views, n_rows, n_cols = out.shape
    n_lines = n_views * n_rows
    n_blocks = (n_lines + block - 1) // block
    for worker in prange(n_workers):
        for b in range(worker, n_blocks, n_workers):
            for line in range(b * block, min(n_lines, (b + 1) * block)):
                view = line // n_rows
                row = line - view * n_rows
                for col in range(n_cols):
                    out[view, row, col] = _ray_sum(vol, rg, view, row, col, shape_xyz, strides_xyz, vs_xyz)


# ----------------------------------------------------------------------- adjoint kernel
@njit(inline="always", fastmath=True)
def _scatter_checked(vol, k, sa, xb, nb, strb, xc, nc, strc, val):
    fb = math.floor(xb)
    fc = math.floor(xc)
    ib = int(fb)
    ic = int(fc)
    wb1 = xb - fb
    wc1 = xc - fc
    wb0 = 1.0 - wb1
    wc0 = 1.0 - wc1
    base = k * sa
    if ic >= 0 and ic < nc:
        if ib >= 0 and ib < nb:
            vol[base + ib * strb + ic * strc] += np.float32(wb0 * wc0 * val)
        if ib + 1 >= 0 and ib + 1 < nb:
            vol[base + (ib + 1) * strb + ic * strc] += np.float32(wb1 * wc0 * val)
    if ic + 1 >= 0 and ic + 1 < nc:
        if ib >= 0 and ib < nb:
            vol[base + ib * strb + (ic + 1) * strc] += np.float32(wb0 * wc1 * val)
        if ib + 1 >= 0 and ib + 1 < nb:
            vol[base + (ib + 1) * strb + (ic + 1) * strc] += np.float32(wb1 * wc1 * val)


@njit(inline="always", fastmath=True)
def _ray_scatter(vol, rg, view, row, col, shape_xyz, strides_xyz, vs_xyz, value):
    ok, a, m0, m1, k0, k1, b0, sb, c0, sc, length, ab, ac = _setup_ray(
        rg, view, row, col, shape_xyz, vs_xyz)
    if not ok:
        return
    y = value * length
    sa = strides_xyz[a]
    strb = strides_xyz[ab]
    strc = strides_xyz[ac]
    nb = shape_xyz[ab]
    nc = shape_xyz[ac]
    ka, kb = _interior(m0, m1, b0, sb, nb, c0, sc, nc, k0, k1)
    for k in range(k0, ka):
        w = _slice_weight(k, m0, m1)
        _scatter_checked(vol, k, sa, b0 + k * sb, nb, strb, c0 + k * sc, nc, strc, w * y)
    b0f = np.float32(b0)
    sbf = np.float32(sb)
    c0f = np.float32(c0)
    scf = np.float32(sc)
    yf = np.float32(y)
    ustrb = np.uint64(strb)
    ustrc = np.uint64(strc)
    one = np.float32(1.0)
    kf = np.float32(ka)
    kbase = ka * sa
    for _ in range(ka, kb + 1):
        xb = b0f + kf * sbf
        xc = c0f + kf * scf
        ib = int(xb)
        ic = int(xc)
        fb = xb - np.float32(ib)
        fc = xc - np.float32(ic)
        p = np.uint64(kbase + ib * strb + ic * strc)  # unsigned: no wraparound code
        pb = p + ustrb
        pc = p + ustrc
        pbc = pc + ustrb
        y1 = yf * fc
        y0 = yf - y1
        t0 = y0 * fb
        t1 = y1 * fb
        # all loads before all stores: strc is often a multiple of 4 KiB, and a load that
        # follows a store 4 KiB apart stalls on a false dependency (4K aliasing)
        a00 = vol[p]
        a10 = vol[pb]
        a01 = vol[pc]
        a11 = vol[pbc]
        vol[p] = a00 + (y0 - t0)
        vol[pb] = a10 + t0
        vol[pc] = a01 + (y1 - t1)
        vol[pbc] = a11 + t1
        kf += one
        kbase += sa
    for k in range(max(kb + 1, ka), k1 + 1):
        w = _slice_weight(k, m0, m1)
        _scatter_checked(vol, k, sa, b0 + k * sb, nb, strb, c0 + k * sc, nc, strc, w * y)


@njit(parallel=True, fastmath=True, cache=True)
def _back_kernel(proj, rg, shape_xyz, strides_xyz, vs_xyz, partial, block):
    # Race-free scatter: worker t handles the line blocks t, t + n, t + 2n, ... (n =
    # len(partial), dealt round-robin as in _forward_kernel for load balance) and writes
    # only into its own partial volume partial[t]. prange gives each worker index to exactly
    # one thread, so no voxel is ever written by two threads at once, with no atomics and
    # no locks. The partial volumes are summed afterwards (_reduce_partials) in a fixed
    # order, so the result does not depend on thread timing. Cost: one volume per thread.
    n_views, n_rows, n_cols = proj.shape
    n_lines = n_views * n_rows
    n_workers = partial.shape[0]
    n_blocks = (n_lines + block - 1) // block
    for worker in prange(n_workers):
        vol = partial[worker]
        for b in range(worker, n_blocks, n_workers):
            for line in range(b * block, min(n_lines, (b + 1) * block)):
                view = line // n_rows
                row = line - view * n_rows
                for col in range(n_cols):
                    value = proj[view, row, col]
                    if value != 0.0:  # zero rays add nothing (masks, virtual-detector margins)
                        _ray_scatter(vol, rg, view, row, col, shape_xyz, strides_xyz, vs_xyz, value)


@njit(parallel=True, fastmath=True, cache=True)
def _reduce_partials(partial, out):
    n_chunks, n = partial.shape
    for i in prange(n):
        acc = partial[0, i]
        for t in range(1, n_chunks):
            acc += partial[t, i]
        out[i] = acc


# ------------------------------------------------------------------------- public API
def _grid_arrays(grid: VolumeGrid):
    nz, ny, nx = grid.shape_zyx
    shape_xyz = np.array([nx, ny, nz], dtype=np.int64)
    strides_xyz = np.array([1, nx, nx * ny], dtype=np.int64)
    vs_xyz = np.asarray(grid.voxel_size_mm, dtype=np.float64)
    return shape_xyz, strides_xyz, vs_xyz


def forward_project(volume: np.ndarray, grid: VolumeGrid, geom: ConeGeometry,
                    out: np.ndarray | None = None) -> np.ndarray:
    """Joseph line integrals of ``volume`` on ``grid`` for every view of ``geom``.

    Returns float32 ``(n_views, n_rows, n_cols)`` in mm x volume units (conventions:
    :mod:`robot_ct_ros.ct.geometry`). All rays of all views are computed in one parallel
    kernel call, so a batch of sampled geometries (e.g. LLE samples, ``ConeGeometry.concatenate``)
    or an enlarged virtual detector (``geom.with_detector``) needs nothing special.
    ``out``, if given, must be a C-contiguous float32 array of that shape; it is overwritten.
    ``volume`` must be finite (after conversion to float32); NaN or infinite voxels raise ValueError.
    """
    if tuple(volume.shape) != grid.shape_zyx:
        raise ValueError(f"volume shape {volume.shape} does not match grid {grid.shape_zyx}")
    vol = np.ascontiguousarray(volume, dtype=np.float32).reshape(-1)
    if not np.isfinite(vol).all():
        raise ValueError(f"volume holds {int((~np.isfinite(vol)).sum())} NaN or infinite values (as float32); "
                         "forward_project needs finite ones (each would spoil every ray through it)")
    shape = (geom.n_views, geom.n_rows, geom.n_cols)
    if out is None:
        out = np.empty(shape, dtype=np.float32)
    elif out.shape != shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be C-contiguous float32 of shape {shape}")
    shape_xyz, strides_xyz, vs_xyz = _grid_arrays(grid)
    # one worker per thread (passed in: numba cannot cache a kernel that asks for it)
    n_lines = geom.n_views * geom.n_rows
    n_workers = max(1, min(numba.get_num_threads(), n_lines))
    _forward_kernel(vol, ray_geometry(geom, grid), shape_xyz, strides_xyz, vs_xyz, out, n_workers,
                    _line_block(n_lines, n_workers))
    return out


def _line_block(n_lines: int, n_workers: int) -> int:
    # up to 8 adjacent detector lines per work unit (cache reuse between lines), but at
    # least ~4 units per worker so the round-robin still balances small batches
    return max(1, min(8, n_lines // (4 * n_workers)))


def _n_partials(n_voxels: int, n_lines: int) -> int:
    # one partial volume per thread (no more than there are detector lines to share out),
    # capped so the copies stay under ~1 GB
    budget = max(1, int(2**30 // (4 * max(n_voxels, 1))))
    return max(1, min(numba.get_num_threads(), budget, n_lines))


def back_project(proj: np.ndarray, geom: ConeGeometry, grid: VolumeGrid,
                 out: np.ndarray | None = None) -> np.ndarray:
    """Exact adjoint (transpose) of :func:`forward_project`: float32 ``(nz, ny, nx)``.

    ``<forward_project(x), y> == <x, back_project(y)>`` up to float32 rounding. This is an
    unfiltered, unnormalised back-projection (mm x projection units per voxel), the
    building block of SIRT/CGLS and gradients; FDK uses its own weighted back-projector.
    ``out``, if given, must be C-contiguous float32 of ``grid.shape_zyx``; it is overwritten.
    ``proj`` must be finite: the fast-math kernel would take a NaN for 0 (set unusable pixels to 0).
    """
    shape = (geom.n_views, geom.n_rows, geom.n_cols)
    if tuple(proj.shape) != shape:
        raise ValueError(f"proj shape {proj.shape} does not match geometry {shape}")
    p = np.ascontiguousarray(proj, dtype=np.float32)
    if not np.isfinite(p).all():
        raise ValueError(f"proj holds {int((~np.isfinite(p)).sum())} NaN or infinite values; back_project needs "
                         "finite ones (set unusable pixels to 0)")
    n_vox = int(np.prod(grid.shape_zyx))
    if out is None:
        out = np.empty(grid.shape_zyx, dtype=np.float32)
    elif out.shape != grid.shape_zyx or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be C-contiguous float32 of shape {grid.shape_zyx}")
    shape_xyz, strides_xyz, vs_xyz = _grid_arrays(grid)
    rg = ray_geometry(geom, grid)
    n_lines = geom.n_views * geom.n_rows
    n_part = _n_partials(n_vox, n_lines)
    if n_part == 1:
        flat_out = out.reshape(1, n_vox)
        flat_out[:] = 0.0
        _back_kernel(p, rg, shape_xyz, strides_xyz, vs_xyz, flat_out, _line_block(n_lines, 1))
        return out
    partial = np.zeros((n_part, n_vox), dtype=np.float32)
    _back_kernel(p, rg, shape_xyz, strides_xyz, vs_xyz, partial, _line_block(n_lines, n_part))
    _reduce_partials(partial, out.reshape(n_vox))
    return out
