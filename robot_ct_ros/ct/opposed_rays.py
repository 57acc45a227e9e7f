"""Opposed-ray consistency of a circular fan-beam scan: a check of the geometry from the data alone.

Over a full circle every line through the object is measured twice, once from each side, and
both measurements must agree. A wrong detector offset (a centre-of-rotation error) makes the
pairs disagree, whatever the object. The check needs no reconstruction and no projector: only the
scan's own rays and linear interpolation between views and between pixels. It tells how far a
stated geometry is from the one the data hold, independently of every calibration method
(bench/bench_realdata.py and bench/bench_realdata_consistency.py use it on the HTC2022 scans).

Conventions: a one-row detector (the fan plane contains every source and detector centre), the
sources on a circle about the rotation axis (the detector's row direction ``v``), views in the
order of their source angle (either sense). Shifts are along each view's detector ``u``, in mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["OpposedRays", "OpposedViewShifts", "opposed_ray_mismatch", "opposed_ray_offset", "opposed_ray_view_shifts"]


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


def _one_row(line_integrals, geom: ConeGeometry, smooth_px: float) -> np.ndarray:
    """The projections as a (views, cols) float64 array, checked and smoothed along the row."""
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
    return p


def _opposed(p: np.ndarray, g: ConeGeometry, central_fraction: float):
    """Every ray's opposed measurement under the geometry ``g``: (opposed values (views, cols), the
    rays that have one on the detector and lie within ``central_fraction`` of the largest distance
    from the centre (views, cols) bool)."""
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
    return opposed, oka & okb & (dist < central_fraction * dist.max())


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
    p = _one_row(line_integrals, geom, smooth_px)
    g = geom.replace(detector_mm=geom.detector_mm + float(shift_mm) * geom.u)
    opposed, ok = _opposed(p, g, central_fraction)
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
                       smooth_px: float = 1.0, central_fraction: float = 0.8) -> OpposedRays:
    """The detector shift (along ``u``, the same for every view) at which opposed rays agree best,
    searched over ``reach_px`` pixels each way in ``steps`` steps: the stated geometry's
    centre-of-rotation error as the data see it. ``central_fraction`` chooses the rays compared
    (:func:`opposed_ray_mismatch`): on a scan that one geometry explains, the offset is the same
    whichever rays are compared.

    Raises
    ------
    ValueError
        The scan cannot be checked (:func:`opposed_ray_mismatch`), or the best agreement lies at
        the edge of the search: the error is larger than ``reach_px``.
    """
    if not (reach_px > 0 and int(steps) >= 3):
        raise ValueError("the search needs reach_px > 0 and at least 3 steps")
    shifts = np.linspace(-reach_px, reach_px, int(steps)) * geom.col_pitch_mm
    m = np.array([opposed_ray_mismatch(line_integrals, geom, s, smooth_px=smooth_px, central_fraction=central_fraction)
                  for s in shifts])
    k = int(np.argmin(m))
    if k in (0, len(m) - 1):
        raise ValueError(f"the opposed rays agree best at the edge of the search ({shifts[k] / geom.col_pitch_mm:+g} "
                         f"px): the centre of rotation is off by more than {reach_px:g} px; search further")
    a, b, _ = np.polyfit(shifts[k - 1:k + 2], m[k - 1:k + 2], 2)
    best = float(-b / (2 * a)) if a > 0 else float(shifts[k])
    return OpposedRays(tuple(float(x) for x in shifts), tuple(float(x) for x in m), best, best / geom.col_pitch_mm)


@dataclass(frozen=True)
class OpposedViewShifts:
    """Per view, the shift of its detector along ``u`` at which its rays agree best with their
    opposed rays, every other view kept as stated (mm and detector pixels, NaN where the best
    agreement lies at the edge of the search, flagged in ``at_edge``).

    What it measures: if the scan's views were really measured with their detectors shifted by
    e(view) from the stated geometry, a view's shift is about e(view) + e(opposed view), the
    opposed views being those half a turn away (within the fan angle). A component of e that
    repeats every half turn (an even angular harmonic) appears doubled; one that changes sign
    every half turn (an odd harmonic, the first among them a shift of the whole object) cancels
    and cannot be seen.
    """

    shift_mm: np.ndarray
    shift_px: np.ndarray
    at_edge: np.ndarray


def opposed_ray_view_shifts(line_integrals, geom: ConeGeometry, *, reach_px: float = 2.0, steps: int = 41,
                            smooth_px: float = 3.0, central_fraction: float = 0.8) -> OpposedViewShifts:
    """Each view's detector shift (along its ``u``) at which its rays agree best with their opposed
    rays, searched over ``reach_px`` pixels each way in ``steps`` steps (a parabola through the
    least mismatch and its neighbours): how far each view's centre of rotation lies from the
    stated one, as the opposed views see it (:class:`OpposedViewShifts` says what that sum is).
    The same checks as :func:`opposed_ray_mismatch`; every view needs 10 compared rays.

    One view's shift rests on its own rays only, and the opposed rays are interpolated between two
    views, which blurs edges that move far between views: hence the 3 px smoothing by default (on a
    simulated 480-view disc scan it keeps the shifts of error-free data within 0.2 px RMS,
    test/ct/test_opposed_rays.py). The shifts of a scan that its geometry explains are therefore not all zero; compare
    with a scan that it explains exactly and has the same sampling (bench_realdata_consistency.py
    uses a synthetic twin).
    """
    if not (reach_px > 0 and int(steps) >= 3):
        raise ValueError("the search needs reach_px > 0 and at least 3 steps")
    p = _one_row(line_integrals, geom, smooth_px)
    opposed, ok = _opposed(p, geom, central_fraction)
    n, nc = p.shape
    y = np.arange(nc, dtype=np.float64)
    ok &= (y >= reach_px + 1)[None, :] & (y <= nc - 2 - reach_px)[None, :]  # the same rays at every shift
    if np.any(ok.sum(axis=1) < 10):
        raise ValueError(f"{int(np.sum(ok.sum(axis=1) < 10))} views have fewer than 10 rays with an opposed "
                         f"ray on the detector")
    shifts_px = np.linspace(-reach_px, reach_px, int(steps))
    mismatch = np.empty((len(shifts_px), n))
    for k, shift in enumerate(shifts_px):
        # the view's detector moved by +shift: its column c sits where column c + shift was
        src = y - shift
        c0 = np.clip(np.floor(src).astype(np.int64), 0, nc - 2)
        w = src - c0
        moved = (1 - w) * p[:, c0] + w * p[:, c0 + 1]
        mismatch[k] = np.sum(np.where(ok, (moved - opposed) ** 2, 0.0), axis=1) / ok.sum(axis=1)
    best = np.argmin(mismatch, axis=0)
    at_edge = (best == 0) | (best == len(shifts_px) - 1)
    k = np.clip(best, 1, len(shifts_px) - 2)
    views = np.arange(n)
    m0, m1, m2 = mismatch[k - 1, views], mismatch[k, views], mismatch[k + 1, views]
    curv = m0 - 2 * m1 + m2
    step = shifts_px[1] - shifts_px[0]
    frac = np.where(curv > 0, 0.5 * (m0 - m2) / np.where(curv > 0, curv, 1.0), 0.0)
    found_px = np.where(at_edge, np.nan, shifts_px[k] + np.clip(frac, -1, 1) * step)
    return OpposedViewShifts(found_px * geom.col_pitch_mm, found_px, at_edge)
