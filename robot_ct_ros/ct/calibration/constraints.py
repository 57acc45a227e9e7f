"""Constraints the alternating loop applies to the per-view estimates: the gauge's similarity part
(magnification), a drift model, and the conjugate modes set by sharpness."""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.metrics import reprojection_error

__all__ = ["hold_magnification", "fit_drift", "view_angles", "image_entropy", "focus_conjugate_modes",
           "CONJUGATE_MODES", "moved_px"]


def view_angles(geom: ConeGeometry, center_mm=None) -> np.ndarray:
    """Angle (rad) of each view's source around the scan axis through ``center_mm`` (default:
    the mean source position's projection), measured from view 0, increasing with the scan."""
    from robot_ct_ros.ct.reconstruction import estimate_scan_axis

    axis = estimate_scan_axis(geom)
    c = geom.source_mm.mean(axis=0) if center_mm is None else np.asarray(center_mm, float)
    r = geom.source_mm - c
    r -= np.outer(r @ axis, axis)
    e1 = r[0] / max(np.linalg.norm(r[0]), 1e-12)
    e2 = np.cross(axis, e1)
    ang = np.unwrap(np.arctan2(r @ e2, r @ e1))
    return ang if ang[-1] >= ang[0] else -ang


def image_entropy(volume: np.ndarray) -> float:
    """Entropy of |volume| normalised to unit sum: low for a sharp image, higher when blurred
    (the passive auto-focus metric of Kingston et al. 2011)."""
    a = np.abs(volume.astype(np.float64)).ravel()
    q = a / max(a.sum(), 1e-300)
    return float(-(q * np.log(np.where(q > 0, q, 1.0))).sum())


CONJUGATE_MODES = {"shift": (3, 5, 7)}
"""Angular harmonics the focus sets by default: the detector shift along u odd under a half
turn (k = 1 is the gauge). The in-plane roll (odd k) and the magnification (even k) are the
parallel-beam analogues, but the entropy minimum did not recover them on the simulated mouse
scan (it doubled the error), so they are available, not listed here. On a cone beam the loop
itself removes most of an odd shift harmonic, and more than the focus does
(docs/results/conjugate_modes.md): the focus is off by default."""


def focus_conjugate_modes(line_integrals, nominal: ConeGeometry, params: np.ndarray, grid: VolumeGrid, mask, *,
                          modes: dict | None = None, step_px: float = 0.5, sweeps: int = 3,
                          focus_slices: int = 64, inner_fraction: float = 1.0,
                          fdk_kwargs=None) -> tuple[np.ndarray, dict]:
    """Set the geometry modes the consistency metric cannot see by image sharpness.

    In a parallel-beam full scan, view angle t and t + pi see the same rays reversed (u -> -u). A
    change of view t's image that its conjugate view can mirror moves each ray and its conjugate
    alike, so the data stay consistent and no consistency metric sees it: a detector shift along
    u or an in-plane roll that is odd under the half turn (odd angular harmonics cos(k t),
    sin(k t)), and a magnification that is even under it. A cone beam pairs rays only on the
    central ray, and the loop sees such modes weakly (docs/calibration.md, "What the data cannot
    tell"). Such modes still blur the image, so each
    coefficient is chosen (coordinate-wise parabola through three reconstructions, ``sweeps``
    rounds, the step halving each round) to minimise :func:`image_entropy` of an FDK of the
    central ``focus_slices`` slices of ``grid``, within ``inner_fraction`` of its half width.

    ``modes`` maps "shift" (detector d_u), "scale" (detector d_w: magnification about the
    principal point) and "roll" (detector r_w) to their harmonics (default
    :data:`CONJUGATE_MODES`). Amplitudes are in pixels: the image displacement at the edge of
    the grid's projection for scale and roll. Returns the parameters and a dict with the
    fitted amplitudes and the entropy before and after.
    """
    from robot_ct_ros.ct.reconstruction import fdk

    n = nominal.n_views
    params = np.array(params, dtype=np.float64).reshape(n, 9)
    modes = CONJUGATE_MODES if modes is None else modes
    t = view_angles(nominal, grid.center_mm)
    pitch = nominal.col_pitch_mm
    magnification = nominal.sdd_mm / np.linalg.norm(nominal.source_mm - np.asarray(grid.center_mm), axis=1)
    edge_px = 0.5 * max(grid.extent_mm[:2]) * magnification / pitch  # (n,) grid half width on the detector
    per_px = {"shift": (3, np.full(n, pitch)), "scale": (5, nominal.sdd_mm / edge_px), "roll": (8, 1.0 / edge_px)}
    basis = []  # (name, k, trig, param index, per-view parameter change for +1 px)
    for name, harmonics in modes.items():
        if name not in per_px:
            raise ValueError(f"unknown mode {name!r}; choose from {tuple(per_px)}")
        index, unit = per_px[name]
        for k in harmonics:
            for trig, f in (("cos", np.cos), ("sin", np.sin)):
                basis.append((name, int(k), trig, index, unit * f(k * t)))
    nz, ny, nx = grid.shape_zyx
    slab = grid.resized((min(nz, focus_slices), ny, nx))
    fdk_kwargs = dict(fdk_kwargs or {})

    # only the inner part counts: the truncation ring and what lies near the edge of the field
    # of view change with the geometry too, and on the battery scan they steered the focus wrong
    yy, xx = np.meshgrid(np.linspace(-1, 1, ny), np.linspace(-1, 1, nx), indexing="ij")
    inner = (yy ** 2 + xx ** 2) <= inner_fraction ** 2

    def entropy(p):
        return image_entropy(fdk(line_integrals, nominal.perturbed(p), slab, valid_mask=mask, **fdk_kwargs)[:, inner])

    def moved(p, j, a_px):
        q = p.copy()
        q[:, basis[j][3]] += a_px * basis[j][4]
        return q

    e0 = e_cur = entropy(params)
    amplitude = np.zeros(len(basis))
    step = float(step_px)
    for _ in range(sweeps):
        for j in range(len(basis)):
            e_minus, e_plus = entropy(moved(params, j, -step)), entropy(moved(params, j, step))
            curvature = e_plus + e_minus - 2 * e_cur
            if curvature > 0:
                a = float(np.clip(0.5 * step * (e_minus - e_plus) / curvature, -2 * step, 2 * step))
            else:  # no minimum in reach: take the better side
                a = -step if e_minus < e_plus else step
            candidates = [(e_cur, 0.0), (e_minus, -step), (e_plus, step)]
            if a not in (0.0, -step, step):
                candidates.append((entropy(moved(params, j, a)), a))
            e_best, a_best = min(candidates)
            if a_best != 0.0:
                params = moved(params, j, a_best)
                amplitude[j] += a_best
                e_cur = e_best
        step *= 0.5
    fitted = [{"mode": b[0], "k": b[1], "trig": b[2], "amplitude_px": float(x)} for b, x in zip(basis, amplitude)]
    return params, {"modes": fitted, "entropy_before": e0, "entropy_after": e_cur}


def hold_magnification(nominal: ConeGeometry, params: np.ndarray, points_mm, tol: float = 1e-6) -> np.ndarray:
    """``params`` with every detector moved along its normal so the estimate's common
    magnification equals the nominal one (:func:`metrics.fit_object_scale` = 1).

    The loop cannot see a common magnification error (it is the similarity part of the
    gauge) and lets it drift; the robots' nominal magnification is far better than that on
    average (docs/calibration.md, "Gauge fixing and magnification hold").
    """
    from robot_ct_ros.ct.metrics import fit_object_scale

    params = np.array(params, dtype=np.float64)
    probe_mm = 1.0
    for _ in range(3):
        s0 = fit_object_scale(nominal.perturbed(params), nominal, points_mm)
        if abs(s0 - 1.0) < tol:
            break
        moved = params.copy()
        moved[:, 5] += probe_mm
        slope = (fit_object_scale(nominal.perturbed(moved), nominal, points_mm) - s0) / probe_mm
        if not np.isfinite(slope) or slope == 0.0:
            break
        params[:, 5] -= (s0 - 1.0) / slope
    return params


def fit_drift(params: np.ndarray, order: int, times=None) -> np.ndarray:
    """``params`` (n, 9) projected, parameter by parameter, onto polynomials of degree ``order``
    in time: the geometry of a slowly drifting system (a detector warming up, a stage creeping)
    instead of independent per-view errors. ``times`` (n,), any unit (e.g. the frames' stamps),
    default the view index (views taken in order at a steady rate); Legendre basis over their
    range. Least squares, so views the data place badly are outvoted by the rest of the scan.
    """
    p = np.asarray(params, np.float64)
    n = p.shape[0]
    order = int(order)
    if order < 0:
        raise ValueError("drift order must be >= 0")
    if order >= n:
        raise ValueError(f"drift order {order} needs more than {order} views, got {n}")
    if times is None:
        t = np.linspace(-1.0, 1.0, n)
    else:
        t = np.asarray(times, np.float64).ravel()
        if t.shape != (n,) or not np.isfinite(t).all() or np.ptp(t) <= 0:
            raise ValueError(f"drift times must be {n} finite values, not all equal")
        t = 2.0 * (t - t.min()) / np.ptp(t) - 1.0
    V = np.polynomial.legendre.legvander(t, order)
    coef, *_ = np.linalg.lstsq(V, p.reshape(n, -1), rcond=None)
    return (V @ coef).reshape(p.shape)


def moved_px(geom: ConeGeometry, params: np.ndarray, before: np.ndarray, points_mm) -> float:
    """How far ``params`` moved the views from ``before`` (both relative to ``geom``): the mean
    gauge-aligned displacement of the points' projections, in pixels of ``geom``'s detector."""
    return float(reprojection_error(geom.perturbed(params), geom.perturbed(before), points_mm,
                                    align_gauge=True)["mean_px"])
