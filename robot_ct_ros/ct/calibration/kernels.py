"""Numba kernels of the per-view geometry search: detector homographies, warps and sample scores.

For a fixed source, a moved flat detector sees the same rays as an (enlarged) virtual
detector, so its image is an exact 2D projective warp of the virtual image
(:func:`detector_homographies`): only the 3 source parameters need a new ray-cast
(docs/calibration.md §2.2). Conventions are those of :mod:`robot_ct_ros.ct.geometry` (pixel (c, r),
column first, as in the projection matrices).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange
from threadpoolctl import threadpool_limits

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["blas_single_threaded", "detector_homographies", "warp_projections", "N_SUMS", "sample_distances"]

FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
"""numba fast-math flags of the warp kernels: everything but 'nnan' and 'ninf', so that a NaN or
infinite point fails the on-detector test instead of being assumed away."""


blas_single_threaded = threadpool_limits.wrap(limits=1, user_api="blas")
"""Decorator: BLAS (numpy's matrix products) on one thread while the function runs. The
estimators alternate numba kernels, which use every core, with small BLAS products; BLAS's
idle threads keep spinning after each call and took the cores from the kernels that followed
(docs/calibration.md, "Speed")."""


def detector_homographies(virtual: ConeGeometry, target: ConeGeometry) -> np.ndarray:
    """(n, 3, 3) maps from target pixel (col, row, 1) to virtual pixel lambda * (col, row, 1).

    View i of ``target`` and of ``virtual`` must share the source position: then every
    target pixel's ray meets the virtual detector plane in one point, and the line
    integral along it is the same (the ray, not the detector, fixes it).
    """
    if virtual.n_views != target.n_views:
        raise ValueError("virtual and target geometries differ in number of views")
    if not np.allclose(virtual.source_mm, target.source_mm, rtol=0, atol=1e-9):
        raise ValueError("a detector homography needs the same source position in both geometries")
    P = virtual.projection_matrices()  # (n, 3, 4)
    c0 = 0.5 * (target.n_cols - 1)
    r0 = 0.5 * (target.n_rows - 1)
    du = target.u * target.col_pitch_mm
    dv = target.v * target.row_pitch_mm
    M = np.zeros((target.n_views, 4, 3))
    M[:, :3, 0] = du
    M[:, :3, 1] = dv
    M[:, :3, 2] = target.detector_mm - c0 * du - r0 * dv
    M[:, 3, 2] = 1.0
    return np.einsum("nij,njk->nik", P, M)


@njit(inline="always", fastmath=FASTMATH)
def _warped_value(img, h, r, c):
    """Bilinear value of virtual image ``img`` at the point homography ``h`` maps detector pixel
    (c, r) to, and 1.0 where that point lies on the virtual detector (else 0.0, with the value
    taken at clamped coordinates: branch-free, so the caller's pixel loop vectorises)."""
    vr, vc = img.shape
    x_max = vc - 1.0
    y_max = vr - 1.0
    z = h[2, 0] * c + h[2, 1] * r + h[2, 2]
    on = abs(z) > 1e-30  # a denormal or zero depth would make the point infinite or NaN
    inv = 1.0 / z if on else 0.0
    x = (h[0, 0] * c + h[0, 1] * r + h[0, 2]) * inv
    y = (h[1, 0] * c + h[1, 1] * r + h[1, 2]) * inv
    # NaN fails every comparison (FASTMATH keeps NaN and inf semantics): such a point is off the detector
    on = on & (x >= 0.0) & (y >= 0.0) & (x <= x_max) & (y <= y_max)
    xc = x if on else 0.0  # a select, not a clamp of NaN: stays branch-free
    yc = y if on else 0.0
    i0 = min(int(xc), vc - 2)
    j0 = min(int(yc), vr - 2)
    fx = np.float32(xc - i0)
    fy = np.float32(yc - j0)
    top = img[j0, i0] + fx * (img[j0, i0 + 1] - img[j0, i0])
    bottom = img[j0 + 1, i0] + fx * (img[j0 + 1, i0 + 1] - img[j0 + 1, i0])
    return np.float64(top + fy * (bottom - top)), 1.0 if on else 0.0


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _warp_kernel(images, H, image_index, out, valid):
    m, n_rows, n_cols = out.shape
    for t in prange(m * n_rows):
        s = t // n_rows
        r = t - s * n_rows
        img = images[image_index[s]]
        h = H[s]
        for c in range(n_cols):
            p, on = _warped_value(img, h, r, c)
            valid[s, r, c] = on > 0.0
            out[s, r, c] = np.float32(p) if on > 0.0 else np.float32(0.0)


def warp_projections(virtual_images: np.ndarray, homographies: np.ndarray, image_index, n_rows: int,
                     n_cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Resample virtual-detector images onto moved detectors (bilinear), one output per homography.

    ``virtual_images`` (n_virtual, Rv, Cv) float32; ``homographies`` (m, 3, 3) from
    :func:`detector_homographies`; ``image_index`` (m,) picks the virtual image of each
    output. Returns float32 images (m, n_rows, n_cols) and a boolean mask of the pixels whose
    ray falls on the virtual detector (enlarge it until the mask is all true).
    """
    imgs = np.ascontiguousarray(virtual_images, dtype=np.float32)
    H = np.ascontiguousarray(homographies, dtype=np.float64).reshape(-1, 3, 3)
    idx = np.ascontiguousarray(np.broadcast_to(np.asarray(image_index, dtype=np.int64), (H.shape[0],)))
    if idx.size and (idx.min() < 0 or idx.max() >= imgs.shape[0]):
        raise ValueError("image_index out of range")
    if imgs.shape[1] < 2 or imgs.shape[2] < 2:
        raise ValueError(f"virtual images must be at least 2 x 2 pixels, got {imgs.shape[1:]}")
    out = np.empty((H.shape[0], n_rows, n_cols), dtype=np.float32)
    valid = np.empty(out.shape, dtype=np.bool_)
    _warp_kernel(imgs, H, idx, out, valid)
    return out, valid


N_SUMS = 7  # n, sum p, sum p^2, sum p b, sum b, sum b^2, sum p b_res; then one sum p q_k per basis image


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def _warp_score_kernel(images, H, image_index, target_index, measured, residual, basis, weight, out):
    """For each sample s: warp virtual image image_index[s] with H[s] onto the detector and
    accumulate, over pixels valid in ``weight[target_index[s]]`` (1.0 valid, 0.0 not) and on
    the virtual detector, the sums listed at N_SUMS followed by sum p * basis[t, k], without
    storing more than one row of it. Every input must be finite, excluded pixels too (they are
    multiplied by 0, and 0 * nan is nan).

    Branch-free on purpose: every pixel is interpolated (:func:`_warped_value`) and multiplied
    by its 0/1 weight, so LLVM vectorises the pixel loop; skipping invalid pixels with a
    branch, as before, took twice as long on 2 cores. The sums are float64 scalars
    (registers), the first basis image's (the mean: published NCC, L2) among them. Further
    basis images get a second pass that stores each warped row and takes one dot product per
    image: a loop over them, or a store, inside the first pass stops its vectorisation.
    """
    m = H.shape[0]
    _, n_rows, n_cols = measured.shape
    n_basis = basis.shape[1]
    for s in prange(m):
        img = images[image_index[s]]
        t = target_index[s]
        h = H[s]
        wt = weight[t]
        meas = measured[t]
        res = residual[t]
        bas = basis[t]
        n = 0.0
        sp = 0.0
        spp = 0.0
        spb = 0.0
        sb = 0.0
        sbb = 0.0
        spr = 0.0
        sq0 = 0.0
        for r in range(n_rows):
            for c in range(n_cols):
                p, on = _warped_value(img, h, r, c)
                w = np.float64(wt[r, c]) * on
                p *= w
                b = np.float64(meas[r, c])
                bw = b * w
                n += w
                sp += p
                spp += p * p
                spb += p * b
                sb += bw
                sbb += bw * b
                spr += p * res[r, c]
                sq0 += p * bas[0, r, c]
        sq = np.zeros(n_basis)
        sq[0] = sq0
        if n_basis > 1:  # a smooth background beyond the mean: a second pass, row by row
            row = np.empty(n_cols)
            for r in range(n_rows):
                for c in range(n_cols):
                    p, on = _warped_value(img, h, r, c)
                    row[c] = p * np.float64(wt[r, c]) * on
                for k in range(1, n_basis):
                    acc = 0.0
                    for c in range(n_cols):
                        acc += row[c] * bas[k, r, c]
                    sq[k] += acc
        out[s, 0] = n
        out[s, 1] = sp
        out[s, 2] = spp
        out[s, 3] = spb
        out[s, 4] = sb
        out[s, 5] = sbb
        out[s, 6] = spr
        for k in range(n_basis):
            out[s, N_SUMS + k] = sq[k]


def sample_distances(sums: np.ndarray, metric: str, residual_norm2=None) -> np.ndarray:
    """Distance of each sample to the measured view from the sums of ``_warp_score_kernel``.

    ``"l2"``: mean squared difference; ``"ncc"``: 1 - normalized cross-correlation after the
    background basis (see :func:`background_basis`) is projected out of both images; then
    ``residual_norm2`` is the squared norm of the measured view's residual per sample.
    Samples with fewer than 2 valid pixels get +inf.
    """
    n, sp, spp, spb, sb, sbb, spr = (sums[..., k].astype(np.float64) for k in range(N_SUMS))
    with np.errstate(divide="ignore", invalid="ignore"):
        if metric == "l2":
            d = (spp - 2 * spb + sbb) / n
        else:
            var_p = spp - (sums[..., N_SUMS:].astype(np.float64) ** 2).sum(axis=-1)
            d = 1.0 - spr / np.sqrt(np.maximum(var_p * residual_norm2, 1e-300))
    return np.where(n >= 2, d, np.inf)
