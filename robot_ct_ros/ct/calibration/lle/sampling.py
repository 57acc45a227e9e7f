"""Sampling and scoring of candidate geometries of each view (the LLE's neighbours).

Candidates are drawn around the current estimate: a few source positions, each ray-cast once
onto an enlarged virtual detector, and detector poses rendered from that ray-cast by
homography (:mod:`robot_ct_ros.ct.calibration.kernels`).
"""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct.calibration.kernels import (N_SUMS, _warp_score_kernel, detector_homographies,
                                                 sample_distances, warp_projections)
from robot_ct_ros.ct.calibration.model import project
from robot_ct_ros.ct.calibration.lle.weights import (background_basis, effective_pixel_fraction, posterior_cost,
                                                     project_out)
from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["source_offsets", "repeat_views", "virtual_margin_px", "score_samples", "score_warped", "ranking",
           "best_fit_fraction"]


def source_offsets(kind: str, h: np.ndarray) -> np.ndarray:
    """Source offsets (m, 3) of the ray-casts of one view, the first one zero (the current source);
    an axis of zero half width ``h`` (a parameter held, e.g. out of a fan beam's plane) gets none."""
    if kind == "fixed":
        return np.zeros((1, 3))
    if kind == "star":
        offs = [np.zeros(3)]
        for k in range(3):
            if h[k] > 0:
                offs += [np.eye(3)[k] * h[k], -np.eye(3)[k] * h[k]]
        return np.array(offs)
    if kind == "grid":
        g = np.stack(np.meshgrid(*[np.array([0.0, -1.0, 1.0] if h[k] > 0 else [0.0]) * h[k] for k in range(3)],
                                 indexing="ij"), -1)
        return g.reshape(-1, 3)
    raise ValueError(f"unknown source_positions {kind!r}")


def repeat_views(geom: ConeGeometry, times: int) -> ConeGeometry:
    return geom.subset(np.repeat(np.arange(geom.n_views), times))


def virtual_margin_px(geom: ConeGeometry, h: np.ndarray) -> tuple[int, int]:
    """Pixels to add on each side of the virtual detector so every sample's rays land on it."""
    half_diag_mm = 0.5 * np.hypot(geom.n_rows * geom.row_pitch_mm, geom.n_cols * geom.col_pitch_mm)
    mag = float(np.max(geom.sdd_mm / np.maximum(geom.sdd_mm - np.linalg.norm(h[3:6]), 1e-6)))
    shift_mm = np.linalg.norm(h[3:6]) + np.linalg.norm(h[6:9]) * half_diag_mm * mag
    return (int(np.ceil(shift_mm / geom.row_pitch_mm)) + 2, int(np.ceil(shift_mm / geom.col_pitch_mm)) + 2)


def score_samples(vol, grid, nom_c, src_params, sample_params, image_index, measured_c, mask_c, config,
                   margin_px):
    """Distances (c, S) of each view's samples to its measured image, and the data to embed them.

    ``src_params`` (c * n_src, 9): one ray-cast per row onto a virtual detector enlarged by
    ``margin_px`` (rows, cols) on each side; ``sample_params`` (c, S, 9) are rendered from the
    ray-cast ``image_index`` (c * S,) by exact detector homographies and scored in one kernel.
    Returns the distances, the ray-cast images, the homographies, the samples' valid pixel
    counts (c, S) and the virtual detectors' geometry.
    """
    c, S = sample_params.shape[:2]
    n_src = src_params.shape[0] // c
    mr, mc = margin_px
    f = config.virtual_oversample
    virtual = repeat_views(nom_c, n_src).perturbed(src_params).with_detector(
        (nom_c.n_rows + 2 * mr) * f, (nom_c.n_cols + 2 * mc) * f, nom_c.row_pitch_mm / f, nom_c.col_pitch_mm / f)
    images = project(vol, grid, virtual)
    dist, H, n_valid = score_warped(images, virtual, nom_c, sample_params, image_index, measured_c, mask_c, config)
    return dist, images, H, n_valid, virtual


def score_warped(images, virtual, nom_c, sample_params, image_index, measured_c, mask_c, config):
    """Distances (c, S) of samples ``sample_params`` (c, S, 9) rendered by homography from the
    ray-casts ``images`` on the ``virtual`` detectors (``image_index`` (c * S,) picks each
    sample's; it must share that ray-cast's source position), the homographies and the valid
    pixel counts (c, S). ``measured_c`` must be finite outside ``mask_c`` too (the kernel
    weights every pixel by 0 or 1, and 0 * nan is nan)."""
    c, S = sample_params.shape[:2]
    samples = repeat_views(nom_c, S).perturbed(sample_params.reshape(-1, 9))
    H = np.ascontiguousarray(detector_homographies(virtual.subset(image_index), samples))
    target_index = np.repeat(np.arange(c), S)
    basis = background_basis(mask_c, *config.background)
    residual = project_out(measured_c, basis, mask_c)
    sums = np.empty((c * S, N_SUMS + basis.shape[1]), np.float64)
    _warp_score_kernel(images, H, image_index, target_index, measured_c, residual.astype(np.float32),
                       basis.astype(np.float32), mask_c.astype(np.float32), sums)
    res2 = np.repeat((residual.reshape(c, -1).astype(np.float64) ** 2).sum(axis=1), S)
    metric = "l2" if config.weighting == "l2" else "ncc"
    return sample_distances(sums, metric, res2).reshape(c, S), H, sums[:, 0].reshape(c, S)


def ranking(dist, params, n_valid, config, fraction, best_dist=None):
    """What samples (c, S) are ranked by: the data distance, or with a prior the posterior cost,
    counting ``fraction`` (c,) of each view's valid pixels (:func:`effective_pixel_fraction`)."""
    inv_var = config.prior_inv_var
    if inv_var is None:
        return dist
    n_eff = np.asarray(n_valid, np.float64) * np.asarray(fraction)[:, None]
    return posterior_cost(dist, params, n_eff, "l2" if config.weighting == "l2" else "ncc", inv_var, best_dist)


def best_fit_fraction(images, H, image_index, S, data_dist, measured_c, mask_c, config):
    """:func:`effective_pixel_fraction` of each view at its best sample by data distance
    (``data_dist`` (c, S)): the residual there is what the data cannot explain; at the
    current estimate it would hold the misalignment itself. None without a prior (only the
    posterior needs it)."""
    if config.prior_sigma is None:
        return None
    c = measured_c.shape[0]
    first = np.arange(c) * S + np.argmin(data_dist, axis=1)
    pred, on = warp_projections(images, H[first], image_index[first], *measured_c.shape[1:])
    m = mask_c & on
    basis = None if config.weighting == "l2" else background_basis(m, *config.background)
    return effective_pixel_fraction(measured_c, pred, m, basis)
