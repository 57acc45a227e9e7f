"""Iterative reconstruction for arbitrary per-view cone-beam geometry: SIRT and CGLS.

Conventions (units, array layouts, projection matrices) are those of
:mod:`robot_ct_ros.ct.geometry`; the forward projector and its exact adjoint are
:mod:`robot_ct_ros.ct.projector`'s. Volumes come back float32, shaped ``grid.shape_zyx``.
"""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid, view_mask
from robot_ct_ros.ct.projector import back_project as bp, forward_project as fp

__all__ = ["sirt", "cgls"]


def _projections(line_integrals, geom: ConeGeometry) -> np.ndarray:
    """float32 projections, checked against the geometry (numpy's broadcast error would name no cause)."""
    b = np.asarray(line_integrals, dtype=np.float32)
    if b.shape != (geom.n_views,) + geom.det_shape:
        raise ValueError(f"projections must have shape {(geom.n_views,) + geom.det_shape}, got {b.shape}")
    return b


def sirt(line_integrals: np.ndarray, geom: ConeGeometry, grid: VolumeGrid, n_iter: int, x0=None,
         nonneg: bool = True, relaxation: float = 1.0, callback=None, valid_mask=None) -> np.ndarray:
    """SIRT: ``x <- x + relaxation * C A^T R M (b - A x)``, R = 1/row sums, C = 1/column sums.

    Row sums ``A 1`` and column sums ``A^T M 1`` come from projecting ones with
    :mod:`robot_ct_ros.ct.projector`. ``valid_mask`` (rows, cols) or (n, rows, cols), True =
    usable, drops dead pixels, chip gaps and non-finite values from the fit (M); a voxel no
    valid ray crosses keeps its ``x0`` value. ``callback(it, x, residual_norm)`` is called after
    each iteration with the norm of the masked residual of the iterate *before* the update.
    """
    b = _projections(line_integrals, geom)
    mask = view_mask(valid_mask, b.shape) & np.isfinite(b)
    b = np.where(mask, b, 0.0).astype(np.float32)
    row_sum = fp(np.ones(grid.shape_zyx, dtype=np.float32), grid, geom)
    eps = np.float32(1e-6)
    R = np.where(mask & (row_sum > eps * row_sum.max()), 1.0 / np.maximum(row_sum, eps), 0.0).astype(np.float32)
    col_sum = bp(mask.astype(np.float32), geom, grid)
    C = np.where(col_sum > eps * col_sum.max(), 1.0 / np.maximum(col_sum, eps), 0.0).astype(np.float32)
    x = np.zeros(grid.shape_zyx, dtype=np.float32) if x0 is None else np.array(x0, dtype=np.float32)
    for it in range(n_iter):
        res = (b - fp(x, grid, geom)) * mask
        x += np.float32(relaxation) * C * bp(res * R, geom, grid)
        if nonneg:
            np.maximum(x, 0.0, out=x)
        if callback is not None:
            callback(it, x, float(np.linalg.norm(res)))
    return x


def cgls(line_integrals: np.ndarray, geom: ConeGeometry, grid: VolumeGrid, n_iter: int, x0=None,
         callback=None) -> np.ndarray:
    """CGLS on ``min ||A x - b||^2`` with A the projector of :mod:`robot_ct_ros.ct.projector`.

    ``callback(it, x, residual_norm)`` gets the residual norm ``||b - A x||`` of the new
    iterate (monotonically non-increasing in exact arithmetic).
    """
    b = _projections(line_integrals, geom)
    x = np.zeros(grid.shape_zyx, dtype=np.float32) if x0 is None else np.array(x0, dtype=np.float32)
    r = b - fp(x, grid, geom) if x0 is not None else b.copy()
    s = bp(r, geom, grid)
    p = s.copy()
    gamma = float(np.vdot(s.ravel().astype(np.float64), s.ravel()))
    for it in range(n_iter):
        if gamma == 0.0:
            break
        q = fp(p, grid, geom)
        qq = float(np.vdot(q.ravel().astype(np.float64), q.ravel()))
        if qq == 0.0:
            break
        alpha = gamma / qq
        x += np.float32(alpha) * p
        r -= np.float32(alpha) * q
        s = bp(r, geom, grid)
        gamma_new = float(np.vdot(s.ravel().astype(np.float64), s.ravel()))
        p = s + np.float32(gamma_new / gamma) * p
        gamma = gamma_new
        if callback is not None:
            callback(it, x, float(np.linalg.norm(r)))
    return x
