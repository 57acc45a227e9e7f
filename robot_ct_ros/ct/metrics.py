"""Quality measures: gauge-aligned reprojection error, projection and volume similarity, sharpness.

Conventions are those of :mod:`robot_ct_ros.ct.geometry` (world mm, ``volume[k, j, i]``).

The gauge. Moving every source and detector of a scan by one rigid motion (equivalently,
moving the object by its inverse) leaves the data unchanged, so data-driven calibration
recovers geometry only up to that motion. Geometry errors are therefore measured after
removing the best global rigid motion: :func:`fit_gauge` finds the motion that, applied
to the estimated geometry, makes it project a set of ROI points where the reference
geometry projects them.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .geometry import ConeGeometry, VolumeGrid

__all__ = ["rigidly_moved", "fit_gauge", "fit_object_scale", "remove_gauge", "reprojection_error",
           "gauge_aligned_reprojection_error", "roi_points", "ncc", "mean_ncc", "projection_rmse", "psnr", "ssim",
           "edge_sharpness", "sample_volume", "line_profile", "edge_rise_distance_mm", "cap_thickness_mm"]


# ----------------------------------------------------------------------------- gauge
def rigidly_moved(geom: ConeGeometry, rotvec, translation_mm, center_mm=(0.0, 0.0, 0.0)) -> ConeGeometry:
    """``geom`` with every source and detector moved by one rigid motion about ``center_mm``."""
    R = Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()
    c = np.asarray(center_mm, dtype=np.float64)
    t = np.asarray(translation_mm, dtype=np.float64)
    return geom.replace(source_mm=(geom.source_mm - c) @ R.T + c + t,
                        detector_mm=(geom.detector_mm - c) @ R.T + c + t,
                        u=geom.u @ R.T, v=geom.v @ R.T)


def fit_gauge(est: ConeGeometry, ref: ConeGeometry, points_mm) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rigid motion (rotvec rad, translation mm, about the points' centroid) that best aligns
    ``est`` to ``ref``: least squares on the pixel distances of the projected points.

    Returns (rotvec, translation_mm, center_mm).
    """
    pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
    center = pts.mean(axis=0)
    target = ref.project_points(pts)

    def residual(x):
        moved = rigidly_moved(est, x[:3], x[3:], center)
        return (moved.project_points(pts) - target).ravel()

    sol = least_squares(residual, np.zeros(6), method="lm", xtol=1e-12, ftol=1e-12)
    return sol.x[:3], sol.x[3:], center


def fit_object_scale(est: ConeGeometry, ref: ConeGeometry, points_mm) -> float:
    """The object scale s that, with the best rigid motion, makes ``est`` project the points
    scaled by s about their centroid where ``ref`` projects the points themselves.

    A common magnification error of all views reconstructs a sharp object of the wrong size:
    with the small cone angle of an interior scan, data consistency hardly sees it (it is the
    similarity part of the gauge), so calibration holds it at the nominal value.
    """
    pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
    center = pts.mean(axis=0)
    target = ref.project_points(pts)

    def residual(x):
        moved = rigidly_moved(est, x[:3], x[3:6], center)
        return (moved.project_points(center + np.exp(x[6]) * (pts - center)) - target).ravel()

    sol = least_squares(residual, np.zeros(7), method="lm", xtol=1e-12, ftol=1e-12)
    return float(np.exp(sol.x[6]))


def remove_gauge(est: ConeGeometry, ref: ConeGeometry, points_mm) -> ConeGeometry:
    """``est`` moved by the rigid motion of :func:`fit_gauge` (the unobservable part removed)."""
    rotvec, t, c = fit_gauge(est, ref, points_mm)
    return rigidly_moved(est, rotvec, t, c)


def reprojection_error(est: ConeGeometry, true: ConeGeometry, points_mm, align_gauge: bool = True) -> dict:
    """Pixel distances between the projections of ``points_mm`` under ``est`` and ``true``.

    With ``align_gauge`` the best global rigid motion is removed first. Returns mean, p95 and
    max over all views and points (pixels of ``true``'s detector, distances measured with
    its column pitch as the unit along both axes), ``mean_u_px`` (the mean distance along the
    detector's rows alone: on a one-row detector the part a fan beam can see and correct) and the
    fitted motion.
    """
    pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
    gauge = None
    if align_gauge:
        rotvec, t, c = fit_gauge(est, true, pts)
        est = rigidly_moved(est, rotvec, t, c)
        gauge = {"rotvec_rad": rotvec.tolist(), "translation_mm": t.tolist(), "center_mm": c.tolist()}
    d = est.project_points(pts) - true.project_points(pts)
    d[..., 1] *= true.row_pitch_mm / true.col_pitch_mm
    dist = np.linalg.norm(d, axis=-1)
    return {"mean_px": float(dist.mean()), "p95_px": float(np.percentile(dist, 95)),
            "mean_u_px": float(np.abs(d[..., 0]).mean()),
            "max_px": float(dist.max()), "per_view_mean_px": dist.mean(axis=1), "gauge": gauge}


def gauge_aligned_reprojection_error(est_geom: ConeGeometry, true_geom: ConeGeometry, points_mm,
                                     remove: bool = True) -> dict:
    """:func:`reprojection_error` with the gauge removed (``remove=False`` keeps it).

    Returns ``mean_px``, ``p95_px``, ``max_px``, ``per_view_mean_px`` and ``gauge`` (the
    fitted rigid motion applied to ``est_geom``: rotation vector and translation about
    ``center_mm``; ``None`` when not removed).
    """
    return reprojection_error(est_geom, true_geom, points_mm, align_gauge=remove)


def roi_points(grid: VolumeGrid, per_axis: int = 5, inner_fraction: float = 0.8) -> np.ndarray:
    """A ``per_axis``^3 lattice of world points (mm) spanning the inner part of ``grid``, along
    the grid's own axes."""
    centre_idx = 0.5 * (np.array(grid.shape_xyz) - 1)
    half_idx = 0.5 * inner_fraction * np.array(grid.shape_xyz)
    axes = [np.linspace(centre_idx[a] - half_idx[a], centre_idx[a] + half_idx[a], per_axis) for a in range(3)]
    return grid.index_to_world(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3))


# ----------------------------------------------------------------------------- projections
def _masked_rows(a, b, mask):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    n = a.shape[0] if a.ndim > 1 else 1
    a, b = a.reshape(n, -1), b.reshape(n, -1)
    m = np.ones(a.shape, bool) if mask is None else np.broadcast_to(np.asarray(mask, bool).reshape(
        (-1,) + a.shape[1:] if np.asarray(mask).size == a.size else (1, -1)), a.shape)
    return a, b, m & np.isfinite(a) & np.isfinite(b)


def ncc(a, b, mask=None) -> np.ndarray:
    """Normalized cross-correlation per row (view) of two stacks, over the mask (blind to gain/offset)."""
    a, b, m = _masked_rows(a, b, mask)
    cnt = np.maximum(m.sum(axis=1), 1)
    ac = np.where(m, a - (np.where(m, a, 0).sum(axis=1) / cnt)[:, None], 0)
    bc = np.where(m, b - (np.where(m, b, 0).sum(axis=1) / cnt)[:, None], 0)
    den = np.sqrt((ac * ac).sum(axis=1) * (bc * bc).sum(axis=1))
    return (ac * bc).sum(axis=1) / np.maximum(den, 1e-300)


def mean_ncc(a, b, mask=None) -> float:
    """Mean over views of :func:`ncc`."""
    return float(np.mean(ncc(a, b, mask)))


def projection_rmse(a, b, mask=None, per_view: bool = False):
    """Root mean square difference over the mask (all views together, or per view (row))."""
    a, b, m = _masked_rows(a, b, mask)
    sq = np.where(m, (a - b) ** 2, 0)
    if per_view:
        return np.sqrt(sq.sum(axis=1) / np.maximum(m.sum(axis=1), 1))
    return float(np.sqrt(sq.sum() / max(m.sum(), 1)))


# ----------------------------------------------------------------------------- volumes
def _data_range(b: np.ndarray, data_range: float | None) -> float:
    """``data_range``, default the reference ``b``'s range; a constant reference has none to default to."""
    rng = float(b.max() - b.min()) if data_range is None else float(data_range)
    if not rng > 0 or not np.isfinite(rng):
        raise ValueError(f"data_range must be positive and finite, got {rng!r}"
                         + (" (the reference is constant or not finite: give data_range)" if data_range is None else ""))
    return rng


def psnr(a, b, data_range: float | None = None) -> float:
    """Peak signal-to-noise ratio (dB) of ``a`` against the reference ``b`` (same shape); ``data_range``
    defaults to ``b``'s range. Identical images give inf."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    mse = float(np.mean((a - b) ** 2))
    if mse == 0:
        return float("inf")
    rng = _data_range(b, data_range)
    return 10.0 * np.log10(rng * rng / mse)


def ssim(a, b, data_range: float | None = None, sigma_vox: float = 1.5, window: str = "gaussian",
         win_size: int = 7) -> float:
    """Mean structural similarity of two volumes (or images) (Wang et al. 2004, K1 = 0.01, K2 = 0.03).

    ``b`` is the reference; ``data_range`` defaults to its range (a constant reference needs it given;
    identical images give 1 regardless). Window: ``"gaussian"``
    (sigma ``sigma_vox``, truncated at 3.5 sigma) or ``"uniform"`` (``win_size`` voxels a
    side); local statistics by separable scipy.ndimage filters; border voxels included
    (reflected).
    """
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"shapes differ: {a.shape} vs {b.shape}")
    if data_range is None and np.array_equal(a, b) and np.isfinite(a).all():
        return 1.0
    L = _data_range(b, data_range)
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    if window == "gaussian":
        f = lambda x: ndimage.gaussian_filter(x, sigma_vox, truncate=3.5)  # noqa: E731
    elif window == "uniform":
        f = lambda x: ndimage.uniform_filter(x, win_size)  # noqa: E731
    else:
        raise ValueError("window must be 'gaussian' or 'uniform'")
    mu_a, mu_b = f(a), f(b)
    var_a = f(a * a) - mu_a ** 2
    var_b = f(b * b) - mu_b ** 2
    cov = f(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a ** 2 + mu_b ** 2 + c1) * (var_a + var_b + c2))
    return float(s.mean())


def edge_sharpness(volume, mask=None, percentile: float = 99.0) -> float:
    """Sharpness: the ``percentile`` of the gradient magnitude (per voxel) over the image's
    1-99 % intensity range. Geometric blur (double edges, smearing) lowers it; it is
    comparable between reconstructions of the same object on the same grid."""
    v = np.asarray(volume, np.float64)
    g = np.sqrt(sum(ndimage.sobel(v, axis=a) ** 2 for a in range(v.ndim))) / 8.0
    sel = g if mask is None else g[np.asarray(mask, bool)]
    lo, hi = np.percentile(v if mask is None else v[np.asarray(mask, bool)], [1, 99])
    return float(np.percentile(sel, percentile) / max(hi - lo, 1e-12))


def sample_volume(volume, grid: VolumeGrid, points_mm, order: int = 1) -> np.ndarray:
    """Interpolated volume values at world points (..., 3); 0 outside."""
    pts = np.asarray(points_mm, np.float64)
    idx = grid.world_to_index(pts)  # (x, y, z) index
    coords = np.stack([idx[..., 2], idx[..., 1], idx[..., 0]]).reshape(3, -1)
    vals = ndimage.map_coordinates(np.asarray(volume, np.float32), coords, order=order, mode="constant")
    return vals.reshape(pts.shape[:-1])


def line_profile(volume, grid: VolumeGrid, p0_mm, p1_mm, step_mm: float | None = None, order: int = 1):
    """Values of ``volume`` along the segment p0 -> p1 (world mm), trilinear by default.

    Returns (distance_mm from p0, values). Default step: a quarter of the smallest voxel.
    """
    p0, p1 = np.asarray(p0_mm, np.float64), np.asarray(p1_mm, np.float64)
    length = float(np.linalg.norm(p1 - p0))
    step = 0.25 * min(grid.voxel_size_mm) if step_mm is None else float(step_mm)
    s = np.linspace(0.0, length, max(2, int(round(length / step)) + 1))
    pts = p0 + (s / max(length, 1e-300))[:, None] * (p1 - p0)
    return s, sample_volume(volume, grid, pts, order=order)


def edge_rise_distance_mm(volume, grid: VolumeGrid, p0_mm, p1_mm, lo: float = 0.1, hi: float = 0.9,
                          plateau_fraction: float = 0.15) -> float:
    """10-90 % rise distance (mm) of the edge crossed by the segment p0 -> p1.

    The segment must cross one boundary between two plateaus (its first and last
    ``plateau_fraction`` of samples); the profile is normalised between their means (either
    direction) and the distance between the outermost ``lo`` and ``hi`` crossings around the
    steepest point is returned (linear interpolation). Smaller is sharper; it equals the
    system's edge response width, so it is independent of contrast, gain and offset.
    """
    s, v = line_profile(volume, grid, p0_mm, p1_mm)
    n = max(2, int(plateau_fraction * len(s)))
    a, b = v[:n].mean(), v[-n:].mean()
    if abs(b - a) < 1e-12:
        return float("nan")
    y = (v - a) / (b - a)  # rises from 0 to 1
    k = int(np.argmax(np.gradient(y)))

    def crossing(level, direction):
        i = k
        while 0 < i < len(y) - 1 and (y[i] > level if direction < 0 else y[i] < level):
            i += direction
        j = i - direction
        if y[j] == y[i]:
            return s[i]
        return s[j] + (level - y[j]) / (y[i] - y[j]) * (s[i] - s[j])

    return float(abs(crossing(hi, +1) - crossing(lo, -1)))


def cap_thickness_mm(volume, grid: VolumeGrid, cap, step_mm: float = 0.005, n_lines: int | None = None,
                     min_prominence: float = 0.25, min_snr: float = 3.0, n_blocks: int = 8,
                     search_voxels: float = 2.0) -> float:
    """Fibrous-cap thickness measured in a reconstruction: FWHM of the cap ridge.

    ``cap`` is the phantom's :class:`~robot_ct_ros.ct.simulation.CapGeometry`. The profile is
    sampled along ``cap.direction`` from inside the lumen to inside the lipid core, averaged
    over ``n_lines`` lines spread along the vessel axis (within ±0.6 of the core's half
    length; default: one per voxel along the axis; those whose cap point lies outside the
    grid are dropped). The ridge's peak is searched within ``search_voxels`` voxels of the
    true cap: the reconstruction must be in the phantom's frame (e.g. gauge-aligned); a
    blurred cap stays where it was, but further out structured artefacts of a misaligned
    geometry, which like the vessel do not vary along its axis, can read as narrow ridges. A
    maximum on the window's edge is no ridge. The ridge is bounded by the half-maximum
    crossings towards the lumen and towards the core, each against its own plateau (the two
    tissues differ). ``cap`` may also be the phantom. A cap thinner than the system
    resolution reads as about the resolution (FWHM of the PSF).

    NaN when there is no ridge to measure:

    * its rise above the higher plateau must be at least ``min_prominence`` of its rise above
      the lower one (a plain edge between lumen and core, or a cap blurred into it, would
      otherwise read as a thickness: 60 µm for a sharp edge on a 115 µm grid, a few µm in
      blurred reconstructions);
    * that rise must be ``min_snr`` standard errors above zero, the standard error from its
      scatter over ``n_blocks`` groups of neighbouring lines (each measured at the averaged
      profile's peak): in a noisy fine-voxel reconstruction of a blurred cap, the highest
      noise bump would otherwise read as a ridge of about the noise grain. Lines within a
      group share noise (they are closer than the noise's correlation length), so the groups,
      not the lines, are the independent samples. ``min_snr=0`` skips the test.
    """
    cap = getattr(cap, "cap", cap)
    if cap is None:
        raise ValueError("this phantom has no fibrous cap")
    d = np.asarray(cap.direction, np.float64)
    axis = np.asarray(cap.axis, np.float64)
    r = np.arange(-0.6, cap.thickness_mm + 0.5 * cap.core_depth_mm + 1e-9, step_mm)
    start = np.asarray(cap.lumen_point_mm)
    span = 0.6 * cap.half_length_mm
    if n_lines is None:
        n_lines = 1 + 2 * int(span / float(np.abs(axis) @ np.asarray(grid.voxel_size_mm)))
    offs = np.linspace(-span, span, n_lines)
    pts = start[None, None, :] + r[None, :, None] * d + offs[:, None, None] * axis
    at_cap = start + 0.5 * cap.thickness_mm * d + offs[:, None] * axis
    idx = grid.world_to_index(at_cap)
    inside = np.all((idx >= 0) & (idx <= np.asarray(grid.shape_xyz) - 1), axis=1)
    if not inside.any():
        raise ValueError("no measurement line of the cap lies inside the grid")
    lines = sample_volume(volume, grid, pts[inside])  # (lines inside the grid, len(r))
    n_lines = len(lines)
    prof = lines.mean(axis=0)
    in_lumen = r < -0.3
    in_core = r > cap.thickness_mm + 0.25 * cap.core_depth_mm
    inner = prof[in_lumen].mean()  # lumen plateau
    outer = prof[in_core].mean()   # core plateau
    reach = search_voxels * float(np.abs(d) @ np.asarray(grid.voxel_size_mm))  # voxels along d
    search = ~in_lumen & ~in_core & (r >= -reach) & (r <= cap.thickness_mm + reach)
    window = np.flatnonzero(search)
    k = window[np.argmax(prof[window])]
    peak = prof[k]
    if k in (window[0], window[-1]):
        return float("nan")  # the profile still rises out of the window: no ridge at the cap
    if not peak - max(inner, outer) >= min_prominence * (peak - min(inner, outer)) or peak <= max(inner, outer):
        return float("nan")
    if min_snr > 0:
        blocks = [b for b in np.array_split(np.arange(n_lines), min(n_blocks, n_lines)) if b.size]
        if len(blocks) < 2:
            raise ValueError("the noise test needs at least 2 lines (n_lines) and 2 blocks (n_blocks)")
        rise = np.array([lines[b, k].mean() - max(lines[b][:, in_lumen].mean(), lines[b][:, in_core].mean())
                         for b in blocks])
        if not rise.mean() >= min_snr * rise.std(ddof=1) / np.sqrt(len(blocks)):
            return float("nan")
    half_in, half_out = 0.5 * (peak + inner), 0.5 * (peak + outer)
    i = k
    while i > 0 and prof[i] > half_in:
        i -= 1
    j = k
    while j < len(r) - 1 and prof[j] > half_out:
        j += 1
    if i == 0 or j == len(r) - 1:
        return float("nan")
    left = r[i] + (half_in - prof[i]) / (prof[i + 1] - prof[i]) * step_mm
    right = r[j - 1] + (prof[j - 1] - half_out) / (prof[j - 1] - prof[j]) * step_mm
    return float(right - left)
