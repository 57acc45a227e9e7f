"""Opposed-ray consistency of a circular fan-beam scan: a check of the geometry from the data alone.

Over a full circle every line through the object is measured twice, once from each side, and
both measurements must agree. A wrong detector offset (a centre-of-rotation error) makes the
pairs disagree, whatever the object. The check needs no reconstruction and no projector: only the
scan's own rays and linear interpolation between views and between pixels. It tells how far a
stated geometry is from the one the data hold, independently of every calibration method
(bench/bench_realdata.py uses it on the HTC2022 scans).

Conventions: a one-row detector (the fan plane contains every source and detector centre), the
sources on a circle about the rotation axis (the detector's row direction ``v``), views in the
order of their source angle (either sense). Shifts are along each view's detector ``u``, in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["OpposedRays", "opposed_ray_mismatch", "opposed_ray_offset"]


def _plane_frame(geom: ConeGeometry):
    """Rotation centre (3,) and in-plane unit axes e1, e2 of the sources' circle."""
    axis = np.asarray(geom.v, np.float64).mean(axis=0)
    axis /= np.linalg.norm(axis)
    e1 = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    s = geom.source_mm
    x, y = s @ e1, s @ e2
    # algebraic circle fit (Kasa): x^2 + y^2 = 2 a x + 2 b y + c
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)
    (a, b, _), *_ = np.linalg.lstsq(A, x ** 2 + y ** 2, rcond=None)
    centre = a * e1 + b * e2 + float(np.mean(s @ axis)) * axis
    return centre, e1, e2


def opposed_ray_mismatch(line_integrals, geom: ConeGeometry, shift_mm: float = 0.0, *, smooth_px: float = 1.0,
                         central_fraction: float = 0.8) -> float:
    """RMS difference between every ray and its opposed ray, with every detector shifted by
    ``shift_mm`` along its ``u``.

    Parameters
    ----------
    line_integrals : (n, 1, cols) or (n, cols) array
        One-row projections over a full circle.
    smooth_px : float
        Gaussian smoothing along the detector row before comparing (sigma, pixels), so that the
        interpolation of the opposed rays does not favour fractional offsets by averaging noise.
    central_fraction : float
        Only rays within this fraction of the largest distance from the centre are compared
        (the outermost rays have no opposed partner inside the row).
    """
    p = np.asarray(line_integrals, np.float64)
    p = p.reshape(p.shape[0], -1) if p.ndim == 3 and p.shape[1] == 1 else p
    if p.ndim != 2 or geom.n_rows != 1 or p.shape != (geom.n_views, geom.n_cols):
        raise ValueError(f"opposed rays need one-row projections (views, cols) matching the geometry "
                         f"({geom.n_views}, {geom.n_cols}); got {np.shape(line_integrals)} and a "
                         f"{geom.n_rows}-row detector")
    if not np.all(np.isfinite(p)):
        raise ValueError("opposed rays need finite projections")
    if smooth_px > 0:
        p = ndimage.gaussian_filter1d(p, smooth_px, axis=1, mode="nearest")
    g = geom.replace(detector_mm=geom.detector_mm + float(shift_mm) * geom.u)
    n, nc = p.shape
    centre, e1, e2 = _plane_frame(g)
    phi = np.unwrap(np.arctan2((g.source_mm - centre) @ e2, (g.source_mm - centre) @ e1))
    if phi[-1] < phi[0]:
        phi, order = -phi, -1
    else:
        order = 1
    if not np.all(np.diff(phi) > 0):
        raise ValueError("opposed rays need the views in the order of their source angle")
    if phi[-1] - phi[0] < 2 * np.pi * (1 - 1.5 / n):
        raise ValueError("opposed rays need a full circle of views")
    cols = (np.arange(nc) - (nc - 1) / 2) * g.col_pitch_mm
    pix = g.detector_mm[:, None, :] + cols[None, :, None] * g.u[:, None, :]  # (n, nc, 3)
    src = g.source_mm[:, None, :]
    d = pix - src
    s0 = src - centre
    t = -2.0 * np.einsum("vci,vci->vc", np.broadcast_to(s0, d.shape), d) / np.einsum("vci,vci->vc", d, d)
    other = src + t[..., None] * d - centre  # the line's second point on the sources' circle
    phi_o = order * np.arctan2(other @ e2, other @ e1)
    period = 2 * np.pi
    phi_o = phi[0] + np.mod(phi_o - phi[0], period)
    # fractional view index of the opposed source; views wrap around the circle
    ext_phi = np.concatenate([phi, [phi[0] + period]])
    j = np.interp(phi_o, ext_phi, np.arange(n + 1, dtype=np.float64))
    j0 = np.floor(j).astype(np.int64)
    f = j - j0
    j0 %= n
    j1 = (j0 + 1) % n
    # the original source lies on the line: its column in the two opposed views
    P = g.projection_matrices()  # (n, 3, 4)
    hom = np.concatenate([g.source_mm, np.ones((n, 1))], axis=1)  # (n, 4)

    def column(jv):
        q = np.einsum("vcab,vb->vca", P[jv], hom)
        return q[..., 0] / q[..., 2]

    def sample(jv, c):
        c0 = np.floor(c).astype(np.int64)
        w = c - c0
        ok = (c0 >= 0) & (c0 + 1 < nc)
        c0c = np.clip(c0, 0, nc - 2)
        return (1 - w) * p[jv, c0c] + w * p[jv, c0c + 1], ok

    c_a, c_b = column(j0), column(j1)
    va, oka = sample(j0, c_a)
    vb, okb = sample(j1, c_b)
    opposed = (1 - f) * va + f * vb
    dist = _line_distance(src - centre, d)  # of each line from the rotation centre
    ok = oka & okb & (dist < central_fraction * dist.max())
    if ok.sum() < 10:
        raise ValueError("fewer than 10 rays have an opposed ray on the detector")
    return float(np.sqrt(np.mean((opposed[ok] - p[ok]) ** 2)))


def _line_distance(point, direction):
    """Distance of the lines point + t * direction from the origin (broadcast over leading axes)."""
    u = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    q = np.broadcast_to(point, u.shape)
    return np.linalg.norm(q - np.einsum("...i,...i->...", q, u)[..., None] * u, axis=-1)


@dataclass(frozen=True)
class OpposedRays:
    """The mismatch at each tried shift and the shift of least mismatch (a parabola through the
    smallest value and its neighbours), in mm and in detector pixels."""

    shifts_mm: tuple
    mismatch: tuple
    best_shift_mm: float
    best_shift_px: float


def opposed_ray_offset(line_integrals, geom: ConeGeometry, *, reach_px: float = 1.0, steps: int = 21,
                       smooth_px: float = 1.0) -> OpposedRays:
    """The detector shift (along ``u``, the same for every view) at which opposed rays agree best,
    searched over ``reach_px`` pixels each way in ``steps`` steps: the stated geometry's
    centre-of-rotation error as the data see it.

    Raises
    ------
    ValueError
        The scan cannot be checked (:func:`opposed_ray_mismatch`), or the best agreement lies at
        the edge of the search: the error is larger than ``reach_px``.
    """
    if not (reach_px > 0 and int(steps) >= 3):
        raise ValueError("the search needs reach_px > 0 and at least 3 steps")
    shifts = np.linspace(-reach_px, reach_px, int(steps)) * geom.col_pitch_mm
    m = np.array([opposed_ray_mismatch(line_integrals, geom, s, smooth_px=smooth_px) for s in shifts])
    k = int(np.argmin(m))
    if k in (0, len(m) - 1):
        raise ValueError(f"the opposed rays agree best at the edge of the search ({shifts[k] / geom.col_pitch_mm:+g} "
                         f"px): the centre of rotation is off by more than {reach_px:g} px; search further")
    a, b, _ = np.polyfit(shifts[k - 1:k + 2], m[k - 1:k + 2], 2)
    best = float(-b / (2 * a)) if a > 0 else float(shifts[k])
    return OpposedRays(tuple(float(x) for x in shifts), tuple(float(x) for x in m), best, best / geom.col_pitch_mm)
