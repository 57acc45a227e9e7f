"""Exact line integrals of additive ellipsoids (numba): a full-size scan's simulation without voxels.

The same object as RTK's ray-quadric intersection (:func:`robot_ct_ros.ct.rtk_bridge.rtk_ellipsoid_projections`)
computes, in-process and parallel over detector rows: each ray, source to pixel centre, is mapped
into each ellipsoid's unit-sphere frame, where the chord is the root difference of a quadratic.
A seed-system scan (360 views of 1272 x 544 raw pixels, some 40 ellipsoids) takes a minute or two
on 2 cores instead of the hours a voxelised phantom at its resolution would.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["ellipsoid_line_integrals"]


@njit(parallel=True, cache=True)
def _ellipsoid_kernel(src, p00, du, dv, M, c, dens, out):
    nv, nr, nc = out.shape
    ne = M.shape[0]
    for job in prange(nv * nr):
        v, r = job // nr, job % nr
        sx, sy, sz = src[v, 0], src[v, 1], src[v, 2]
        for col in range(nc):
            px = p00[v, 0] + col * du[v, 0] + r * dv[v, 0]
            py = p00[v, 1] + col * du[v, 1] + r * dv[v, 1]
            pz = p00[v, 2] + col * du[v, 2] + r * dv[v, 2]
            dx, dy, dz = px - sx, py - sy, pz - sz
            length = np.sqrt(dx * dx + dy * dy + dz * dz)
            acc = 0.0
            for e in range(ne):
                ox, oy, oz = sx - c[e, 0], sy - c[e, 1], sz - c[e, 2]
                a0 = M[e, 0, 0] * ox + M[e, 0, 1] * oy + M[e, 0, 2] * oz
                a1 = M[e, 1, 0] * ox + M[e, 1, 1] * oy + M[e, 1, 2] * oz
                a2 = M[e, 2, 0] * ox + M[e, 2, 1] * oy + M[e, 2, 2] * oz
                b0 = M[e, 0, 0] * dx + M[e, 0, 1] * dy + M[e, 0, 2] * dz
                b1 = M[e, 1, 0] * dx + M[e, 1, 1] * dy + M[e, 1, 2] * dz
                b2 = M[e, 2, 0] * dx + M[e, 2, 1] * dy + M[e, 2, 2] * dz
                qa = b0 * b0 + b1 * b1 + b2 * b2
                qb = a0 * b0 + a1 * b1 + a2 * b2
                qc = a0 * a0 + a1 * a1 + a2 * a2 - 1.0
                disc = qb * qb - qa * qc
                if disc <= 0.0:
                    continue
                root = np.sqrt(disc)
                t0 = max((-qb - root) / qa, 0.0)  # the segment source (t = 0) to pixel (t = 1)
                t1 = min((-qb + root) / qa, 1.0)
                if t1 > t0:
                    acc += dens[e] * (t1 - t0) * length
            out[v, r, col] = acc


def ellipsoid_line_integrals(ellipsoids, geom: ConeGeometry) -> np.ndarray:
    """Line integrals (float32 (n_views, n_rows, n_cols)) of a sum of ellipsoids along ``geom``'s rays.

    ``ellipsoids`` are :class:`~robot_ct_ros.ct.simulation.Primitive` of kind ``"ellipsoid"`` and
    mode ``"add"`` (densities add up, e.g. :func:`~robot_ct_ros.ct.simulation.interior_neck_phantom`),
    any orientation. A ray runs from the source to the pixel centre (geometry.py conventions:
    ``detector_mm`` the centre of the pixel grid, columns along ``u``, rows along ``v``); the chord
    is clipped to that segment. Computed in float64, returned as float32.

    Raises
    ------
    ValueError
        A primitive that is not an additive ellipsoid.
    """
    prims = list(ellipsoids)
    for p in prims:
        if p.kind != "ellipsoid" or p.mode != "add":
            raise ValueError(f"{p.name or p.kind}: only additive ellipsoids have an analytic line integral here")
    ne = len(prims)
    M = np.empty((ne, 3, 3))
    c = np.empty((ne, 3))
    dens = np.empty(ne)
    for e, p in enumerate(prims):
        M[e] = np.asarray(p.rotation, float).T / np.asarray(p.params[:3], float)[:, None]  # world -> unit sphere
        c[e] = p.center_mm
        dens[e] = p.value
    du = geom.u * geom.col_pitch_mm
    dv = geom.v * geom.row_pitch_mm
    p00 = geom.detector_mm - 0.5 * (geom.n_cols - 1) * du - 0.5 * (geom.n_rows - 1) * dv
    out = np.empty((geom.n_views, geom.n_rows, geom.n_cols), np.float64)
    if ne:
        _ellipsoid_kernel(np.ascontiguousarray(geom.source_mm, float), np.ascontiguousarray(p00), np.ascontiguousarray(du),
                          np.ascontiguousarray(dv), M, c, dens, out)
    else:
        out[:] = 0.0
    return out.astype(np.float32)
