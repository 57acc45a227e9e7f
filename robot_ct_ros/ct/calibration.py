"""Per-view 9-DOF geometry calibration by locally linear embedding (LLE): building blocks.

Conventions are those of :mod:`robot_ct_ros.ct.geometry`. This module holds

* the embedding weights of one measured projection in K neighbouring reprojections,
  under three metrics (design.md §2): ``"l2"`` (classic LLE), ``"ncc"`` (the published
  closed form w_j ∝ c_j / s_j) and ``"ncc-exact"`` (the exact maximiser of the normalized
  cross-correlation over affine combinations, w = G⁻¹r / 1ᵀG⁻¹r);
* the detector homography: for a fixed source, a moved flat detector sees the same rays
  as an (enlarged) virtual detector, so its image is an exact 2D projective warp of the
  virtual image. Only the 3 source parameters need a new ray-cast.

Weights are computed over a pixel mask (dead pixels, chip gaps, pixels whose rays leave
the reconstructed ROI); all arrays are flattened per view: measured (n, P), neighbours
(n, K, P), mask (n, P) or (P,).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from threadpoolctl import threadpool_limits

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.metrics import ncc, remove_gauge, reprojection_error, roi_points

WEIGHTINGS = ("l2", "ncc", "ncc-exact")

blas_single_threaded = threadpool_limits.wrap(limits=1, user_api="blas")
"""Decorator: BLAS (numpy's matrix products) on one thread while the function runs. The
estimators alternate numba kernels, which use every core, with small BLAS products; BLAS's
idle threads keep spinning after each call and took the cores from the kernels that
followed (calibrate on the scan of bench/bench_calibration_speed.py, 2 cores: 68 s with them,
62 s without)."""


def _masked(measured, neighbours, mask):
    b = np.asarray(measured, dtype=np.float64)
    Y = np.asarray(neighbours)
    if b.ndim == 1:
        b, Y = b[None], Y[None]
    if Y.ndim != 3 or Y.shape[0] != b.shape[0] or Y.shape[2] != b.shape[1]:
        raise ValueError(f"neighbours must be (n, K, P) for measured (n, P); got {Y.shape} and {b.shape}")
    m = np.ones(b.shape, dtype=bool) if mask is None else np.broadcast_to(np.asarray(mask, dtype=bool), b.shape)
    # a sum over the neighbours is finite exactly where all of them are (one pass, no (n, K, P) mask)
    finite = np.isfinite(Y.sum(axis=1, dtype=np.float64))
    m = m & np.isfinite(b) & finite
    if np.any(m.sum(axis=1) < 2):
        raise ValueError("a view has fewer than 2 valid pixels to embed")
    if not finite.all():  # 0 * nan is nan: only then the slower select
        Y = np.where(m[:, None, :], Y, 0.0)
    mf = m.astype(np.float64)
    return np.where(m, b, 0.0), Y * mf[:, None, :], mf


def _gram(A, B) -> np.ndarray:
    """Batched A Bᵀ of (n, K, P) and (n, J, P) stacks: (n, K, J), by BLAS (einsum does not use it)."""
    return np.matmul(A, np.swapaxes(B, 1, 2))


def _regularised(G, reg):
    """G + reg * tr(G)/K * I for a batch of K x K matrices (a zero trace counts as 1)."""
    K = G.shape[-1]
    scale = np.trace(G, axis1=1, axis2=2) / K
    return G + (reg * np.where(scale > 0, scale, 1.0))[:, None, None] * np.eye(K)


REG_FLOOR = 1e-12
"""Smallest ridge :func:`_solve_regularised` applies (relative to tr(G)/K): a measured view that
lies exactly in its neighbours' affine span makes the L2 Gram matrix exactly singular, and LAPACK
then fails or not depending on rounding."""


def _solve_regularised(G, rhs, reg):
    """Solve (G + max(reg, REG_FLOOR) * tr(G)/K * I) x = rhs for a batch of small symmetric matrices."""
    return np.linalg.solve(_regularised(G, max(reg, REG_FLOOR)), rhs[..., None])[..., 0]


def _map_weights(M_data, q_data, prior) -> np.ndarray:
    """argmin_w wᵀ M w - 2 wᵀ q subject to sum(w) = 1, with M = M_data + Pᵀ Λ P (the prior
    on the embedded parameters P w, Λ = diag(inverse variances (D,) or per row (n, D))) and q = q_data."""
    P, inv_var = prior
    P = np.asarray(P, np.float64)
    inv_var = np.broadcast_to(np.asarray(inv_var, np.float64), (P.shape[0], P.shape[2]))
    M = _regularised(M_data + np.einsum("nkd,nd,njd->nkj", P, inv_var, P), 1e-12)
    a = np.linalg.solve(M, q_data[..., None])[..., 0]
    o = np.linalg.solve(M, np.ones(q_data.shape)[..., None])[..., 0]
    lam = (1.0 - a.sum(axis=1)) / o.sum(axis=1)
    return a + lam[:, None] * o


def posterior_cost(dist, params, n_valid, metric: str, inv_var, best_dist=None) -> np.ndarray:
    """Negative log posterior (up to a constant, times 2) of samples of one view or of many.

    ``dist`` (..., S) are :func:`sample_distances` of each view's samples (at least one
    finite per view), ``params`` (..., S, D) their parameters relative to the nominal geometry,
    ``n_valid`` (..., S) their valid pixel counts, ``inv_var`` (D,) the prior's inverse
    variances (the nominal geometry's error, e.g. the robots' coordination error). The data
    term is chi-square with the residual variance of the view's best sample (or of
    ``best_dist`` (...,)) as noise: n d / d_best for ``"l2"``, n (1 - ρ²) / (1 - ρ_best²) for
    ``"ncc"`` (ρ = 1 - d, the residual of a best-gain fit). Noise and model error count alike,
    so a view whose reprojections explain little of its data leans on the prior: a strongly
    truncated scan then stays near its nominal geometry instead of following spurious optima.
    """
    def energy(d):
        return d if metric == "l2" else d * (2.0 - d)

    d = np.asarray(dist, np.float64)
    e = energy(d)
    e_best = (np.min(np.where(np.isfinite(e), e, np.inf), axis=-1, keepdims=True) if best_dist is None
              else energy(np.asarray(best_dist, np.float64))[..., None])
    data = np.asarray(n_valid, np.float64) * e / np.maximum(e_best, 1e-300)
    g = np.asarray(params, np.float64)
    return np.where(np.isfinite(e), data + (g * g * np.asarray(inv_var, np.float64)).sum(axis=-1), np.inf)


def effective_pixel_fraction(measured, predicted, mask, basis=None, highpass_px: float = 16.0) -> np.ndarray:
    """Per view, the fraction of its valid pixels that count as independent in the data term.

    The residual of ``measured`` (n, rows, cols) against the best-gain fit of ``predicted``
    (after projecting out ``basis``, :func:`background_basis`; the mean by default) is noise
    plus model error. Geometry is located by edges, so only the residual at their scale
    matters: a Gaussian of about ``highpass_px`` pixels (masked, normalised;
    :func:`_smooth_images`) takes the smooth part out (what FDK of a truncated scan leaves at
    low frequencies hides no edge). Photon noise stays white; model error at the edges' scale
    (edges of the object outside the ROI that the volume lacks, a blurred or misplaced
    reconstruction) is correlated and would otherwise count its information once per pixel.
    With that residual's lag-one correlation ρ along rows and along columns, the fraction is
    ((1 - ρ_u) / (1 + ρ_u)) ((1 - ρ_v) / (1 + ρ_v)), the effective sample size of a first-order
    autoregressive field: about 1 for white residuals. The 16
    pixels were measured: on the 360-view mouse scan of bench/bench_calibration_speed.py the
    raw residual (0) made the prior hold the views back (0.90 px after 2 iterations, 0.64 px
    without prior), 8 pixels let the carotid scan of bench/bench_calibration.py drift (6.1 px
    against 3.4 px nominal), 16 pixels did neither (0.68 px; 4.0 px).
    """
    mask = np.asarray(mask, bool)
    if basis is None:
        basis = background_basis(mask)
    b = _project_out(np.asarray(measured, np.float64), basis, mask)
    p = _project_out(np.asarray(predicted, np.float64), basis, mask)
    gain = np.einsum("nrc,nrc->n", b, p) / np.maximum(np.einsum("nrc,nrc->n", p, p), 1e-300)
    r = np.where(mask, b - gain[:, None, None] * p, 0.0)
    if highpass_px > 0:
        smooth = _smooth_images(r.astype(np.float32), highpass_px) / np.maximum(
            _smooth_images(mask.astype(np.float32), highpass_px), 1e-6)
        r = np.where(mask, r - smooth, 0.0)
    fraction = np.ones(len(r))
    for axis in (1, 2):
        n = r.shape[axis]
        a, c = np.take(r, range(1, n), axis=axis), np.take(r, range(n - 1), axis=axis)
        both = np.take(mask, range(1, n), axis=axis) & np.take(mask, range(n - 1), axis=axis)
        rho = (np.where(both, a * c, 0.0).sum(axis=(1, 2))
               / np.maximum(np.where(both, a * a, 0.0).sum(axis=(1, 2)), 1e-300))
        rho = np.clip(rho, 0.0, 0.99)
        fraction *= (1.0 - rho) / (1.0 + rho)
    return fraction


def _smooth_images(images: np.ndarray, sigma_px: float) -> np.ndarray:
    """Low-pass of each (rows, cols) image of a stack: three passes of an odd box filter along
    each axis (edges repeated), a Gaussian of about ``sigma_px`` (at 16 px: 16.5) at a cost
    independent of its width, where a truncated Gaussian kernel costs 5 sigma taps a pixel."""
    from scipy.ndimage import uniform_filter1d

    width = 2 * int(np.sqrt(4.0 * sigma_px ** 2 + 1.0) / 2.0) + 1  # 3 (w^2 - 1) / 12 = sigma^2
    out = images
    for axis in (1, 2):
        for _ in range(3):
            out = uniform_filter1d(out, width, axis=axis, mode="nearest")
    return out


def background_basis(mask: np.ndarray, order_u: int = 0, order_v: int = 0) -> np.ndarray:
    """Per-view orthonormal basis (n, B, rows, cols) of smooth backgrounds over each view's mask.

    The monomials col^a row^b (a <= order_u, b <= order_v; coordinates scaled to [-1, 1])
    restricted to the valid pixels of each view and orthonormalised there (zero outside).
    Order (0, 0) is the constant alone: projecting it out is mean-centring, i.e. plain NCC.
    """
    mask = np.asarray(mask, bool)
    n, R, C = mask.shape
    rr, cc = np.meshgrid(np.linspace(-1, 1, R), np.linspace(-1, 1, C), indexing="ij")
    mono = np.stack([(cc ** a * rr ** b).ravel() for a in range(order_u + 1) for b in range(order_v + 1)], axis=1)
    m = mask.reshape(n, -1).astype(np.float64)
    # batched Gram-Cholesky orthonormalisation (one BLAS-free pass for all views; a QR per
    # view was the bottleneck, with OpenBLAS threads fighting numba's)
    G = np.einsum("pb,np,pc->nbc", mono, m, mono)
    G += 1e-12 * np.trace(G, axis1=1, axis2=2)[:, None, None] * np.eye(mono.shape[1])
    L_inv = np.linalg.inv(np.linalg.cholesky(G))
    out = np.einsum("pb,ncb->ncp", mono, L_inv) * m[:, None, :]
    return out.reshape(n, mono.shape[1], R, C)


def lle_weights(measured, neighbours, method: str = "ncc-exact", mask=None, reg: float = 1e-3,
                basis=None, prior=None) -> np.ndarray:
    """Embedding weights (n, K), each row summing to 1, of measured projections in neighbours.

    ``reg`` regularises the K x K Gram matrix by ``reg * trace / K`` on its diagonal (the
    neighbours of a dense sampling grid are nearly collinear). For the NCC weightings,
    ``basis`` (n, B, P), orthonormal over the mask (:func:`background_basis`), is projected
    out of every image instead of the mean: the correlation then ignores any smooth
    background in that span as well as the gain (default: the mean alone, as published).

    ``prior`` = (neighbour parameters (n, K, D), inverse variances (D,) or (n, D)) makes the
    ``l2`` and ``ncc-exact`` weights maximum a posteriori: they minimise the embedding residual
    in units of its own per-pixel variance (that of the best data-only embedding: noise plus
    model error) plus the prior term (sum_k w_k g_k)ᵀ diag(inverse variances) (sum_k w_k g_k), a
    zero-mean Gaussian on the embedded parameters (:func:`posterior_cost`). The published
    ``ncc`` closed form has no such variant and ignores it.
    """
    if method not in WEIGHTINGS:
        raise ValueError(f"unknown weighting {method!r}; choose one of {WEIGHTINGS}")
    b, Y, m = _masked(measured, neighbours, mask)
    n, K, _ = Y.shape
    count = m.sum(axis=1)
    if method == "l2":
        D = b[:, None, :] - Y  # (n, K, P) residuals, zero outside the mask
        C = _gram(D, D)
        w = _solve_regularised(C, np.ones((n, K)), reg)
        w = w / w.sum(axis=1, keepdims=True)
        if prior is None:
            return w
        var = np.einsum("nk,nkj,nj->n", w, C, w) / count  # residual variance per pixel
        return _map_weights(_regularised(C, reg) / np.maximum(var, 1e-300)[:, None, None], np.zeros((n, K)),
                            prior)

    # project the background span out (orthonormal over the mask; the mean alone by default)
    # without forming the centred neighbours: with Q that basis, Ỹ = Y - (Y Q) Qᵀ gives
    # G = ỸỸᵀ = Y Yᵀ - (Y Q)(Y Q)ᵀ and, the centred b being orthogonal to Q, r = Ỹ b̃ = Y b̃
    Q = ((m / np.sqrt(count)[:, None])[:, None, :] if basis is None
         else np.asarray(basis, np.float64).reshape(n, -1, b.shape[1]) * m[:, None, :])
    bc = (b - _gram(_gram(b[:, None, :], Q), np.swapaxes(Q, 1, 2))[:, 0]) * m
    YQ = _gram(Y, Q)
    G = _gram(Y, Y) - _gram(YQ, YQ)
    r = _gram(Y, bc[:, None, :])[:, :, 0]
    if method == "ncc":
        s = np.sqrt(np.diagonal(G, axis1=1, axis2=2) / np.maximum(count - 1, 1)[:, None])
        sb = np.sqrt(np.einsum("np,np->n", bc, bc) / np.maximum(count - 1, 1))
        c = r / np.maximum(count - 1, 1)[:, None] / np.maximum(s * sb[:, None], 1e-300)
        w = c / np.maximum(s, 1e-300)
    else:
        w = _solve_regularised(G, r, reg)
    total = w.sum(axis=1, keepdims=True)
    # A non-positive sum means the affine constraint cannot reach the maximising direction
    # (the best combination would correlate negatively): fall back to the best neighbour.
    bad = ~(total[:, 0] > 1e-12 * np.abs(w).sum(axis=1))
    w = w / np.where(bad[:, None], 1.0, total)
    if np.any(bad):
        best = np.argmax(r[bad], axis=1)
        w[bad] = 0.0
        w[np.flatnonzero(bad), best] = 1.0
    if prior is not None and method == "ncc-exact":
        # b ≈ gain * Ỹ v, v = G⁻¹r unconstrained: its gain 1ᵀv and residual variance fix the
        # data term; with that gain the MAP weights solve a constrained quadratic
        gain = total[:, 0]
        bb = np.einsum("np,np->n", bc, bc)
        var = np.maximum(bb - np.einsum("nk,nk->n", r, w * total), 1e-12 * bb) / count + 1e-300
        ok = ~bad & (gain > 0)
        if np.any(ok):
            P = np.asarray(prior[0], np.float64)
            inv_var = np.broadcast_to(np.asarray(prior[1], np.float64), (n, P.shape[2]))
            scale = gain[ok] / var[ok]
            w[ok] = _map_weights(_regularised(G[ok], reg) * (gain[ok] * scale)[:, None, None], r[ok] * scale[:, None],
                                 (P[ok], inv_var[ok]))
    return w


# ----------------------------------------------------------------------------- homography
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


@njit(inline="always", fastmath=True)
def _warped_value(img, h, r, c):
    """Bilinear value of virtual image ``img`` at the point homography ``h`` maps detector pixel
    (c, r) to, and 1.0 where that point lies on the virtual detector (else 0.0, with the value
    taken at clamped coordinates: branch-free, so the caller's pixel loop vectorises)."""
    vr, vc = img.shape
    x_max = vc - 1.0
    y_max = vr - 1.0
    z = h[2, 0] * c + h[2, 1] * r + h[2, 2]
    on = z != 0.0
    inv = 1.0 / z if on else 0.0
    x = (h[0, 0] * c + h[0, 1] * r + h[0, 2]) * inv
    y = (h[1, 0] * c + h[1, 1] * r + h[1, 2]) * inv
    on = on & (x >= 0.0) & (y >= 0.0) & (x <= x_max) & (y <= y_max)
    xc = min(max(x, 0.0), x_max)
    yc = min(max(y, 0.0), y_max)
    i0 = min(int(xc), vc - 2)
    j0 = min(int(yc), vr - 2)
    fx = np.float32(xc - i0)
    fy = np.float32(yc - j0)
    top = img[j0, i0] + fx * (img[j0, i0 + 1] - img[j0, i0])
    bottom = img[j0 + 1, i0] + fx * (img[j0 + 1, i0 + 1] - img[j0 + 1, i0])
    return np.float64(top + fy * (bottom - top)), 1.0 if on else 0.0


@njit(parallel=True, fastmath=True, cache=True)
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


# ----------------------------------------------------------------------------- sample scoring
N_SUMS = 7  # n, sum p, sum p^2, sum p b, sum b, sum b^2, sum p b_res; then one sum p q_k per basis image


@njit(parallel=True, fastmath=True, cache=True)
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


# ----------------------------------------------------------------------------- LLE estimator
@dataclass(frozen=True)
class LLEConfig:
    """Settings of one LLE estimation pass (all views at once, coarse to fine).

    Each level samples ``n_samples`` geometries per view in a box of ``half_width`` (9
    values: mm x6, rad x3, geometry.py parameter order) around the current estimate; the
    box shrinks by ``shrink`` per level. Source shifts are drawn from a small set of
    positions (``source_positions``: ``"star"`` = centre and ±half width along each axis,
    7 ray-casts per view; ``"grid"`` = 3 x 3 x 3; ``"fixed"`` = the current source only, one
    ray-cast per view: a detector-only refinement); detector shifts and rotations are drawn
    uniformly and rendered by homography from the ray-cast of their source position.
    ``safeguard`` keeps the best sample when the embedding scores worse than it.
    ``background`` = (order along columns, order along rows) of the smooth per-view
    background that the NCC weightings ignore (:func:`background_basis`); (0, 0) is the
    published NCC (offset and gain only). A higher order also absorbs the bowl that the
    truncated object outside the ROI adds to every interior projection.
    ``shift_search_px`` > 0 first searches the detector translation exhaustively over that
    many pixels each way (:func:`_shift_search`). ``prior_sigma`` (9 values, mm x6, rad x3;
    None = off) is the standard deviation of the nominal geometry's error (the robots'
    coordination error): samples are then ranked, and the ``l2`` and ``ncc-exact`` weights
    solved, by posterior instead of data alone (:func:`posterior_cost`), so the parameters
    the data hardly see stay near their nominal values. ``draws`` independent sets of
    ``n_samples`` samples are drawn per level, all scored against the same ray-casts; each set
    is embedded in its own ``n_neighbours`` nearest samples and the sets' estimates are averaged
    (fewer sampling errors for the cost of scoring, :data:`DRAWS`); the safeguard compares the
    average with the best sample of all sets.
    """

    weighting: str = "ncc-exact"
    background: tuple = (0, 0)
    n_samples: int = 192
    n_neighbours: int = 16
    source_positions: str = "star"
    half_width: tuple = (0.6, 0.6, 0.6, 0.6, 0.6, 0.6, 0.0105, 0.0105, 0.0105)
    levels: int = 3
    shrink: float = 0.5
    reg: float = 1e-3
    roi_support_fraction: float = 0.3
    safeguard: bool = True
    virtual_oversample: int = 1
    shift_search_px: float = 0.0
    chunk_views: int = 8
    seed: int = 0
    prior_sigma: tuple | None = None
    draws: int = 1

    def __post_init__(self):
        if self.weighting not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}")
        if len(self.half_width) != 9:
            raise ValueError("half_width needs 9 values (mm x6, rad x3)")
        if self.n_neighbours < 2 or self.n_neighbours > self.n_samples:
            raise ValueError("need 2 <= n_neighbours <= n_samples")
        if not (isinstance(self.draws, (int, np.integer)) and self.draws >= 1):
            raise ValueError("draws must be a whole number >= 1")
        if self.prior_sigma is not None and (len(self.prior_sigma) != 9 or not all(x > 0 for x in self.prior_sigma)):
            raise ValueError("prior_sigma needs 9 positive values (mm x6, rad x3)")

    @property
    def prior_inv_var(self):
        """Inverse prior variances (9,), or None without a prior."""
        return None if self.prior_sigma is None else 1.0 / np.asarray(self.prior_sigma, np.float64) ** 2


def _source_offsets(kind: str, h: np.ndarray) -> np.ndarray:
    if kind == "fixed":
        return np.zeros((1, 3))
    if kind == "star":
        offs = np.zeros((7, 3))
        for k in range(3):
            offs[1 + 2 * k, k] = h[k]
            offs[2 + 2 * k, k] = -h[k]
        return offs
    if kind == "grid":
        g = np.stack(np.meshgrid(*[np.array([0.0, -1.0, 1.0]) * h[k] for k in range(3)], indexing="ij"), -1)
        return g.reshape(-1, 3)
    raise ValueError(f"unknown source_positions {kind!r}")


def _repeat_views(geom: ConeGeometry, times: int) -> ConeGeometry:
    return geom.subset(np.repeat(np.arange(geom.n_views), times))


def _virtual_margin_px(geom: ConeGeometry, h: np.ndarray) -> tuple[int, int]:
    """Pixels to add on each side of the virtual detector so every sample's rays land on it."""
    half_diag_mm = 0.5 * np.hypot(geom.n_rows * geom.row_pitch_mm, geom.n_cols * geom.col_pitch_mm)
    mag = float(np.max(geom.sdd_mm / np.maximum(geom.sdd_mm - np.linalg.norm(h[3:6]), 1e-6)))
    shift_mm = np.linalg.norm(h[3:6]) + np.linalg.norm(h[6:9]) * half_diag_mm * mag
    return (int(np.ceil(shift_mm / geom.row_pitch_mm)) + 2, int(np.ceil(shift_mm / geom.col_pitch_mm)) + 2)


def roi_support_mask(nominal: ConeGeometry, params: np.ndarray, grid: VolumeGrid, fraction: float,
                     axial_tolerance: float = 0.02) -> np.ndarray:
    """(n, rows, cols) pixels whose reprojection of the ROI volume is meaningful.

    A pixel counts when its ray crosses the ROI for at least ``fraction`` of the longest
    chord of that view, and leaves it through the sides, not through the top or bottom
    face: a ray that exits axially also crosses object outside the reconstructed slab
    (the long-object problem), which no offset or gain can absorb. Chords are ray-cast
    through coarse ones-volumes (4x larger voxels: only lengths matter).
    """
    from .projector import forward_project

    geom = nominal.perturbed(params)
    coarse = VolumeGrid.centered(tuple(max(2, s // 4) for s in grid.shape_zyx),
                                 tuple(e / max(2, s // 4) for e, s in zip(grid.extent_mm, grid.shape_xyz)),
                                 grid.center_mm)
    nz, ny, nx = coarse.shape_zyx
    tall = VolumeGrid.centered((3 * nz, ny, nx), coarse.voxel_size_mm, coarse.center_mm)
    chord = forward_project(np.ones(coarse.shape_zyx, np.float32), coarse, geom)
    chord_tall = forward_project(np.ones(tall.shape_zyx, np.float32), tall, geom)
    peak = chord.reshape(chord.shape[0], -1).max(axis=1)
    return (chord > (fraction * peak)[:, None, None]) & (chord >= (1.0 - axial_tolerance) * chord_tall)


def _as_view_mask(valid_mask, shape) -> np.ndarray:
    if valid_mask is None:
        return np.ones(shape, bool)
    return np.broadcast_to(np.asarray(valid_mask, bool), shape)


def _usable_data(line_integrals, valid_mask) -> tuple[np.ndarray, np.ndarray]:
    """float32 line integrals with every pixel that is invalid or not finite set to 0, and the
    (n, rows, cols) mask of the others."""
    li = np.ascontiguousarray(line_integrals, dtype=np.float32)
    mask = _as_view_mask(valid_mask, li.shape) & np.isfinite(li)
    return np.where(mask, li, 0.0).astype(np.float32), mask


def _score_samples(vol, grid, nom_c, src_params, sample_params, image_index, measured_c, mask_c, config,
                   margin_px):
    """Distances (c, S) of each view's samples to its measured image, and the data to embed them.

    ``src_params`` (c * n_src, 9): one ray-cast per row onto a virtual detector enlarged by
    ``margin_px`` (rows, cols) on each side; ``sample_params`` (c, S, 9) are rendered from the
    ray-cast ``image_index`` (c * S,) by exact detector homographies and scored in one kernel.
    Returns the distances, the ray-cast images, the homographies, the samples' valid pixel
    counts (c, S) and the virtual detectors' geometry.
    """
    from .projector import forward_project

    c, S = sample_params.shape[:2]
    n_src = src_params.shape[0] // c
    mr, mc = margin_px
    f = config.virtual_oversample
    virtual = _repeat_views(nom_c, n_src).perturbed(src_params).with_detector(
        (nom_c.n_rows + 2 * mr) * f, (nom_c.n_cols + 2 * mc) * f, nom_c.row_pitch_mm / f, nom_c.col_pitch_mm / f)
    images = forward_project(vol, grid, virtual)
    dist, H, n_valid = _score_warped(images, virtual, nom_c, sample_params, image_index, measured_c, mask_c, config)
    return dist, images, H, n_valid, virtual


def _score_warped(images, virtual, nom_c, sample_params, image_index, measured_c, mask_c, config):
    """Distances (c, S) of samples ``sample_params`` (c, S, 9) rendered by homography from the
    ray-casts ``images`` on the ``virtual`` detectors (``image_index`` (c * S,) picks each
    sample's; it must share that ray-cast's source position), the homographies and the valid
    pixel counts (c, S). ``measured_c`` must be finite outside ``mask_c`` too (the kernel
    weights every pixel by 0 or 1, and 0 * nan is nan)."""
    c, S = sample_params.shape[:2]
    samples = _repeat_views(nom_c, S).perturbed(sample_params.reshape(-1, 9))
    H = np.ascontiguousarray(detector_homographies(virtual.subset(image_index), samples))
    target_index = np.repeat(np.arange(c), S)
    basis = background_basis(mask_c, *config.background)
    residual = _project_out(measured_c, basis, mask_c)
    sums = np.empty((c * S, N_SUMS + basis.shape[1]), np.float64)
    _warp_score_kernel(images, H, image_index, target_index, measured_c, residual.astype(np.float32),
                       basis.astype(np.float32), mask_c.astype(np.float32), sums)
    res2 = np.repeat((residual.reshape(c, -1).astype(np.float64) ** 2).sum(axis=1), S)
    metric = "l2" if config.weighting == "l2" else "ncc"
    return sample_distances(sums, metric, res2).reshape(c, S), H, sums[:, 0].reshape(c, S)


def _ranking(dist, params, n_valid, config, fraction, best_dist=None):
    """What samples (c, S) are ranked by: the data distance, or with a prior the posterior cost,
    counting ``fraction`` (c,) of each view's valid pixels (:func:`effective_pixel_fraction`)."""
    inv_var = config.prior_inv_var
    if inv_var is None:
        return dist
    n_eff = np.asarray(n_valid, np.float64) * np.asarray(fraction)[:, None]
    return posterior_cost(dist, params, n_eff, "l2" if config.weighting == "l2" else "ncc", inv_var, best_dist)


def _best_fit_fraction(images, H, image_index, S, data_dist, measured_c, mask_c, config):
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


def _shift_search(measured, nominal, params, vol, grid, config, mask_all):
    """Exhaustive search of the detector translation (d_u, d_v) within ``config.shift_search_px``.

    Whole-pixel steps, then half-pixel steps around the best; a view moves only where a shift
    scores better (with ``config.prior_sigma``: by posterior) than its current pose. Captures
    large in-plane errors, and the aliased optimum one period away on periodic anatomy (ribs,
    electrode layers), before the local LLE sampling, whose random samples rarely land in the
    right period.
    """
    R = int(np.ceil(config.shift_search_px))
    n = nominal.n_views
    pitch = np.array([nominal.col_pitch_mm, nominal.row_pitch_mm])
    out = params.copy()
    for step, reach in ((1.0, R), (0.5, 1)):
        k = np.arange(-reach, reach + 1) * step
        du, dv = (a.ravel() for a in np.meshgrid(k, k, indexing="ij"))
        offsets = np.stack([du, dv], axis=1) * pitch  # mm, includes (0, 0)
        S = offsets.shape[0]
        margin = (int(np.ceil(reach * step)) + 2, int(np.ceil(reach * step)) + 2)
        for v0 in range(0, n, config.chunk_views):
            idx = np.arange(v0, min(n, v0 + config.chunk_views))
            c = idx.size
            sample_params = np.repeat(out[idx][:, None, :], S, axis=1)
            sample_params[:, :, 3:5] += offsets
            image_index = np.repeat(np.arange(c), S)
            mask_c = np.ascontiguousarray(mask_all[idx])
            dist, images, H, n_valid, _ = _score_samples(vol, grid, nominal.subset(idx), out[idx], sample_params,
                                                         image_index, measured[idx], mask_c, config, margin)
            centre = S // 2  # the zero offset
            fraction = _best_fit_fraction(images, H, image_index, S, dist, measured[idx], mask_c, config)
            dist = _ranking(dist, sample_params, n_valid, config, fraction)
            best = np.argmin(dist, axis=1)
            better = dist[np.arange(c), best] < dist[:, centre]
            out[idx[better]] = sample_params[np.flatnonzero(better), best[better]]
    return out


@blas_single_threaded
def estimate_views(measured: np.ndarray, nominal: ConeGeometry, params0: np.ndarray, volume: np.ndarray,
                   grid: VolumeGrid, config: LLEConfig = LLEConfig(), valid_mask=None,
                   progress=None) -> tuple[np.ndarray, dict]:
    """One LLE pass: new 9-DOF parameters (n, 9) of every view, relative to ``nominal``.

    ``measured`` (n, rows, cols) line integrals on ``nominal``'s detector grid; ``params0``
    the current estimate; ``volume`` on ``grid`` the current reconstruction; ``valid_mask``
    (rows, cols) or (n, rows, cols) marks usable pixels (dead pixels and chip gaps False).
    Returns the parameters and a dict with, per level, the mean distance of the best sample
    (``best_distance``), of the chosen estimate (``chosen_distance``, with the safeguard) and,
    with a prior, the median over views of :func:`effective_pixel_fraction`
    (``independent_fraction``).
    """
    from .projector import forward_project

    n = nominal.n_views
    measured = np.ascontiguousarray(measured, dtype=np.float32)
    if measured.shape != (n,) + nominal.det_shape:
        raise ValueError(f"measured {measured.shape} does not match the geometry ({n}, {nominal.det_shape})")
    params = np.array(params0, dtype=np.float64).reshape(n, 9)
    vol = np.ascontiguousarray(volume, dtype=np.float32)
    metric = "l2" if config.weighting == "l2" else "ncc"
    mask_all = _as_view_mask(valid_mask, measured.shape) & np.isfinite(measured)
    mask_all = mask_all & roi_support_mask(nominal, params, grid, config.roi_support_fraction)
    measured = np.where(mask_all, measured, np.float32(0.0))  # dead pixels may be nan or inf: see _score_warped
    if config.shift_search_px > 0:
        params = _shift_search(measured, nominal, params, vol, grid, config, mask_all)
    rng = np.random.default_rng(config.seed)
    h0 = np.asarray(config.half_width, dtype=np.float64)
    info = {"best_distance": [], "chosen_distance": [], "independent_fraction": []}
    for level in range(config.levels):
        h = h0 * config.shrink ** level
        src_offsets = _source_offsets(config.source_positions, h)
        n_src = src_offsets.shape[0]
        margin = _virtual_margin_px(nominal, h)
        best_d, chosen_d, fractions = [], [], []
        for v0 in range(0, n, config.chunk_views):
            idx = np.arange(v0, min(n, v0 + config.chunk_views))
            c = idx.size
            nom_c, g = nominal.subset(idx), params[idx]
            # one ray-cast per source position; samples: a source position each, detector pose
            # uniform in the box; sample 0 = the current estimate
            src_params = np.repeat(g, n_src, axis=0)
            src_params[:, 0:3] += np.tile(src_offsets, (c, 1))
            # config.draws independent sets of S samples, scored together: set d is samples
            # d * S ... d * S + S - 1, each with the current estimate first
            S, D = config.n_samples, config.draws
            a = rng.integers(0, n_src, size=(c, D, S))
            a[:, :, 0] = 0
            delta = np.zeros((c, D, S, 9))
            delta[..., 0:3] = src_offsets[a]
            delta[..., 3:9] = rng.uniform(-1.0, 1.0, size=(c, D, S, 6)) * h[3:9]
            delta[:, :, 0, 3:9] = 0.0
            sample_params = (g[:, None, None, :] + delta).reshape(c, D * S, 9)
            image_index = (np.arange(c)[:, None] * n_src + a.reshape(c, D * S)).reshape(-1)
            mask_c = np.ascontiguousarray(mask_all[idx])
            data_dist, images, H, n_valid, virtual = _score_samples(
                vol, grid, nom_c, src_params, sample_params, image_index, measured[idx], mask_c, config, margin)
            fraction = _best_fit_fraction(images, H, image_index, D * S, data_dist, measured[idx], mask_c, config)
            dist = _ranking(data_dist, sample_params, n_valid, config, fraction)
            if fraction is not None:
                fractions.append(fraction)
            # one embedding per set, in that set's K nearest samples; the sets' estimates averaged
            K = config.n_neighbours
            near = (np.argpartition(dist.reshape(c, D, S), K - 1, axis=2)[:, :, :K]
                    + (np.arange(D) * S)[None, :, None]).reshape(c, D * K)
            flat_sel = (np.arange(c)[:, None] * (D * S) + near).reshape(-1)
            neigh, on_virtual = warp_projections(images, H[flat_sel], image_index[flat_sel], nominal.n_rows,
                                                 nominal.n_cols)
            m = (mask_all[idx][:, None] & on_virtual.reshape(c, D, K, *nominal.det_shape).all(axis=2)).reshape(
                c * D, *nominal.det_shape)
            g_near = np.take_along_axis(sample_params, near[:, :, None], axis=1).reshape(c * D, K, 9)
            w = lle_weights(np.repeat(measured[idx].reshape(c, -1), D, axis=0), neigh.reshape(c * D, K, -1),
                            config.weighting, mask=m.reshape(c * D, -1), reg=config.reg,
                            basis=None if metric == "l2" else background_basis(m, *config.background).reshape(
                                c * D, -1, m[0].size),
                            prior=None if fraction is None else (
                                g_near, config.prior_inv_var / np.repeat(fraction, D)[:, None]))
            g_new = np.einsum("ck,ckj->cj", w, g_near).reshape(c, D, 9)
            # an embedding may extrapolate; never beyond the sampled box (stability under model error)
            g_new = np.clip(g_new, (g - h)[:, None], (g + h)[:, None]).mean(axis=1)
            rows = np.arange(c)
            best = np.argmin(dist, axis=1)  # by posterior with a prior
            d_best = data_dist[rows, best]
            if config.safeguard:
                if n_src == 1:  # the samples' common source: the ray-cast renders g_new by homography too
                    d_new = _score_warped(images, virtual, nom_c, g_new[:, None, :], np.arange(c), measured[idx],
                                          mask_c, config)[0][:, 0]
                else:
                    p_new = forward_project(vol, grid, nom_c.perturbed(g_new))
                    d_new = _distances(p_new, measured[idx], mask_c, metric, config.background)
                if config.prior_sigma is None:
                    worse = ~(d_new <= d_best)
                else:  # compare posteriors, on the same data reference
                    both = _ranking(np.stack([d_best, d_new], axis=1),
                                    np.stack([sample_params[rows, best], g_new], axis=1),
                                    np.stack([n_valid[rows, best], mask_c.reshape(c, -1).sum(axis=1)], axis=1),
                                    config, fraction, np.min(data_dist, axis=1))
                    worse = ~(both[:, 1] <= both[:, 0])
                g_new[worse] = sample_params[rows, best][worse]
                d_new = np.where(worse, d_best, d_new)
                chosen_d.append(d_new)
            params[idx] = g_new
            best_d.append(d_best)
        info["best_distance"].append(float(np.mean(np.concatenate(best_d))))
        if chosen_d:
            info["chosen_distance"].append(float(np.mean(np.concatenate(chosen_d))))
        if fractions:
            info["independent_fraction"].append(float(np.median(np.concatenate(fractions))))
        if progress is not None:
            progress(level, config.levels, info)
    return params, info


def _project_out(images: np.ndarray, basis: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Residual of (n, rows, cols) images after removing their projection on the basis (masked)."""
    x = np.where(mask, images, 0.0).astype(np.float64)
    coef = np.einsum("nbrc,nrc->nb", basis, x)
    return np.where(mask, x - np.einsum("nbrc,nb->nrc", basis, coef), 0.0)


def _distances(pred: np.ndarray, measured: np.ndarray, mask: np.ndarray, metric: str,
               background=(0, 0)) -> np.ndarray:
    """Per-view distance (as :func:`sample_distances`) between two (n, rows, cols) stacks."""
    basis = background_basis(mask, *background)
    residual = _project_out(measured, basis, mask)
    mk = mask.reshape(mask.shape[0], -1)
    p = np.where(mk, pred.reshape(mk.shape), 0.0).astype(np.float64)
    b = np.where(mk, measured.reshape(mk.shape), 0.0).astype(np.float64)
    q = basis.reshape(basis.shape[0], basis.shape[1], -1)
    sums = np.concatenate([np.stack([mk.sum(1), p.sum(1), (p * p).sum(1), (p * b).sum(1), b.sum(1), (b * b).sum(1),
                                     (p * residual.reshape(mk.shape)).sum(1)], axis=1),
                           np.einsum("nbp,np->nb", q, p)], axis=1)
    return sample_distances(sums, metric, (residual.reshape(mk.shape) ** 2).sum(1))


# ----------------------------------------------------------------------------- alternating loop
LLE_METHODS = {"l2-lle": "l2", "ncc-lle": "ncc", "ncc-lle-exact": "ncc-exact"}
METHODS = tuple(LLE_METHODS) + ("gdc", "gdc-log")
"""Calibration methods :func:`calibrate` runs: the LLE weightings and the GDC baselines
(:mod:`robot_ct_ros.ct.baselines`)."""


@dataclass(frozen=True)
class IterationRecord:
    """What one outer iteration did: projection consistency after it, update size, time, and
    (LLE with a prior) the median fraction of each view's pixels whose residual counted as
    independent at the last level (:func:`effective_pixel_fraction`): near 1 where the volume
    explains the data up to photon noise, near 0 where model error dominates and the estimate
    leans on the prior (ncc-lle-exact on bench/bench_calibration.py: 0.33, 0.73, 0.77 over three
    iterations on the mouse scan, 0.006 on the battery scan, 0.02 to 0.03 on the carotid scan).
    ``update_px``: how far the iteration moved the views, as the mean gauge-aligned displacement
    of the ROI points' projections (full-size detector pixels); the loop stops on it
    (``calibrate(stop_update_px=)``)."""

    iteration: int
    projection_rmse: float
    projection_ncc: float
    update_rms_mm: float
    update_rms_deg: float
    wall_s: float
    independent_fraction: float = float("nan")
    update_px: float = float("nan")


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    method: str
    params: np.ndarray            # (n, 9) relative to the nominal geometry
    geom: ConeGeometry            # nominal.perturbed(params)
    volume: np.ndarray            # reconstruction with the final geometry
    history: tuple                # IterationRecord per outer iteration (an ensemble's: its first member's)
    wall_s: float
    members: int = 1              # estimates averaged (average_estimates, calibrate_ensemble)
    spread_px: float = float("nan")  # an ensemble's mean member-to-mean displacement of ROI points, px


ENSEMBLE_SEED_STEP = 1000
"""Sampling seeds of :func:`calibrate_ensemble`'s members: seed, seed + 1000, seed + 2000, ...
(each run's levels use its seed and seed + 1)."""


def average_estimates(results, line_integrals, nominal: ConeGeometry, grid: VolumeGrid, *, valid_mask=None,
                      points_mm=None, fdk_kwargs: dict | None = None) -> CalibrationResult:
    """One estimate from several :class:`CalibrationResult` of the same scan (e.g. :func:`calibrate`
    with different sampling seeds): the mean of their parameters, reconstructed (FDK).

    Each run's parameters are already in the nominal geometry's gauge (:func:`calibrate` removes
    the global rigid motion and holds the magnification), so they average directly. What the
    runs disagree on is the LLE's sampling noise, which the mean reduces; what they share, the
    bias of the data and of the volume, it keeps. ``spread_px`` of the result is the mean
    gauge-aligned displacement of the ROI points (``points_mm``, default those of ``grid``)
    between each run and the mean: the sampling's share of the error, a measure of the
    estimate's precision that needs no ground truth.
    """
    from .reconstruction import fdk

    results = list(results)
    if not results:
        raise ValueError("no estimates to average")
    if any(r.params.shape != (nominal.n_views, 9) for r in results):
        raise ValueError(f"every estimate needs ({nominal.n_views}, 9) parameters")
    t0 = time.perf_counter()
    params = np.mean([r.params for r in results], axis=0)
    points = roi_points(grid) if points_mm is None else np.asarray(points_mm, float)
    spread = (float(np.mean([_moved_px(nominal, r.params, params, points) for r in results]))
              if len(results) > 1 else float("nan"))
    geom = nominal.perturbed(params)
    li, mask = _usable_data(line_integrals, valid_mask)  # as calibrate's final FDK
    volume = fdk(li, geom, grid, valid_mask=mask, **(fdk_kwargs or {}))
    wall = sum(r.wall_s for r in results) + time.perf_counter() - t0
    return CalibrationResult(results[0].method, params, geom, volume, results[0].history, wall,
                             members=sum(r.members for r in results), spread_px=spread)


def calibrate_ensemble(line_integrals: np.ndarray, nominal: ConeGeometry, grid: VolumeGrid, *, members: int = 3,
                       seed: int = 0, progress=None, **kwargs) -> CalibrationResult:
    """:func:`calibrate` ``members`` times with the sampling seeds ``seed + k *``
    :data:`ENSEMBLE_SEED_STEP`, averaged (:func:`average_estimates`): ``members`` times the
    time for less sampling noise. On scenario (a) of bench/bench_calibration.py (ncc-lle-exact,
    3 iterations) three members took the error from 0.093 / 0.089 / 0.091 px to 0.086 px (with
    one sample set per level, :data:`DRAWS`: from 0.101 / 0.102 / 0.102 px to 0.095 px).
    The baselines draw no samples: their members would all be the same. ``kwargs`` go to
    :func:`calibrate` (``valid_mask`` and ``fdk_kwargs`` also to the final FDK)."""
    if members < 1:
        raise ValueError("members must be >= 1")
    say = progress or (lambda message: None)
    runs = []
    for k in range(members):
        member_seed = seed + k * ENSEMBLE_SEED_STEP
        say(f"ensemble member {k + 1}/{members} (sampling seed {member_seed})")
        runs.append(calibrate(line_integrals, nominal, grid, seed=member_seed, progress=progress, **kwargs))
    if members == 1:
        return runs[0]
    result = average_estimates(runs, line_integrals, nominal, grid, valid_mask=kwargs.get("valid_mask"),
                               points_mm=kwargs.get("gauge_points_mm"), fdk_kwargs=kwargs.get("fdk_kwargs"))
    say(f"ensemble of {members}: the members lie {result.spread_px:.3f} px from their mean")
    return result


def bin_masked(line_integrals: np.ndarray, valid_mask: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Average valid pixels in ``factor`` x ``factor`` bins; a bin with no valid pixel is invalid."""
    from .geometry import bin_projections

    m = _as_view_mask(valid_mask, line_integrals.shape).astype(np.float32)
    total = bin_projections(np.where(m > 0, line_integrals, 0.0).astype(np.float32), factor)
    count = bin_projections(m, factor)
    return (total / np.maximum(count, 1.0)).astype(np.float32), count > 0


def projection_consistency(volume, grid, geom, measured, mask) -> tuple[float, float]:
    """Masked RMSE and mean NCC between the reprojection of ``volume`` and ``measured``."""
    from .projector import forward_project

    pred = forward_project(volume, grid, geom)
    mk = _as_view_mask(mask, measured.shape) & np.isfinite(measured)
    diff = np.where(mk, pred - measured, 0.0)
    rmse = float(np.sqrt((diff.astype(np.float64) ** 2).sum() / max(mk.sum(), 1)))
    return rmse, float(ncc(pred.reshape(len(pred), -1), measured.reshape(len(pred), -1),
                           mk.reshape(len(pred), -1)).mean())


DEFAULT_BACKGROUND = (0, 0)
"""Smooth background ignored by the NCC weightings by default: (0, 0) = offset and gain only,
the metric as published. Against FDK volumes a quadratic one, (2, 2), halved the estimator's
error on truncated scans (it absorbs the bowl the truncated object adds); against the
SIRT-consistent volumes of :func:`reconstruct_for_estimation` the published metric is the more
accurate on the mouse scan (0.14 px against 0.37 px after 3 iterations), the quadratic one on
the battery scan (1.08 px against 1.40 px)."""


def prior_sigma_from(translation_mm: float, rotation_deg: float):
    """The 9 prior standard deviations (mm x6, rad x3) of :func:`calibrate` from one translation
    and one rotation error; None when either is not positive (no prior: the data alone)."""
    if not (translation_mm > 0 and rotation_deg > 0):
        return None
    return (float(translation_mm),) * 6 + (float(np.deg2rad(rotation_deg)),) * 3


DEFAULT_PRIOR_SIGMA = prior_sigma_from(0.3, 0.3)
"""Standard deviation of the nominal geometry's per-view error that :func:`calibrate` assumes by
default (mm x6, rad x3): the seed system's robot coordination error, a fraction of a millimetre
and of a degree per arm (design.md §1). It is the prior of the MAP estimate
(:attr:`LLEConfig.prior_sigma`); set it to the robots' measured accuracy."""


EMBEDDING_SETTINGS = {"l2": {"n_neighbours": 24, "reg": 1e-5}, "ncc-exact": {"n_neighbours": 24, "reg": 1e-5}}
"""Neighbours and Gram regularisation per weighting where they differ from :class:`LLEConfig`'s
(16, 1e-3). The solved weightings embed in more neighbours with a weaker ridge: the ridge pulls
the weights towards the neighbours' centroid, i.e. the weakly seen parameters (scale,
perspective) towards the current estimate, and with the robots' accuracy as prior the ridge
need not hold them any more. Measured with bench/bench_calibration.py's scenario (a) (90
views, 3 iterations): ncc-lle-exact 0.127 -> 0.107 px (0.125 -> 0.109 and 0.136 -> 0.112 with
other sampling seeds), l2-lle 0.124 -> 0.113 px; (b) 1.00 -> 1.00 and 1.00 -> 1.02 px, (c)
4.14 -> 4.05 and 3.69 -> 3.35 px. The published ``ncc`` closed form has no ridge, and 24
neighbours made it worse on the 360-view scan of bench/bench_calibration_speed.py (0.664 ->
0.692 px), so it keeps 16."""


COARSE_SAMPLES = 96
DRAWS = 2
"""Samples per view and level of the coarse pass (:class:`LLEConfig` default 192), and the
independent sample sets per level whose embeddings are averaged (:attr:`LLEConfig.draws`) on
both levels. Each set is one draw of the random sampling; its embedding carries that draw's
noise, which more samples in one set do not average out (they only tighten the K nearest
ones), while a second set is scored against the same ray-casts, so it costs only its
homography scoring and weights. Measured with ncc-lle-exact on scenario (a) of
bench/bench_calibration.py (90 views, 3 iterations, six sampling seeds): 192 samples and one
set per level 0.0995 to 0.102 px (384 samples: 0.101 to 0.103 px), 96 coarse samples 0.094
to 0.096 px, 96 coarse samples and two sets on both levels 0.089 to 0.094 px (mean 0.091) in
24 s instead of 20 s; three sets of 64 coarse samples 0.090 px in 26 s."""


def default_lle_configs(weighting: str, seed: int = 0, background=DEFAULT_BACKGROUND,
                        prior_sigma=DEFAULT_PRIOR_SIGMA) -> tuple[LLEConfig, LLEConfig]:
    """Coarse (binned, wide box) and fine (full size, narrow box) LLE settings."""
    prior = None if prior_sigma is None else tuple(float(x) for x in prior_sigma)
    embedding = EMBEDDING_SETTINGS.get(weighting, {})
    coarse = LLEConfig(weighting=weighting, levels=3, seed=seed, background=tuple(background), shift_search_px=4,
                       prior_sigma=prior, n_samples=COARSE_SAMPLES, draws=DRAWS, **embedding)
    fine = LLEConfig(weighting=weighting, levels=2, seed=seed + 1, background=tuple(background),
                     half_width=tuple(np.asarray(coarse.half_width) * 0.25), prior_sigma=prior, draws=DRAWS,
                     **embedding)
    return coarse, fine


MAX_NARROWING = 2
"""Outer iterations after which the LLE search box stops shrinking. Halving it without end left
the box smaller than the estimator's own scatter: on scenario (a) of bench/bench_calibration.py
the error rose again from 0.101 px (iteration 3) to 0.110 px (iteration 6); held at a quarter
from iteration 3 on, it stayed at 0.100 to 0.101 px."""


def _narrowed(config: LLEConfig, iteration: int) -> LLEConfig:
    """The search box of outer iteration ``iteration`` (0-based): halved each time up to
    :data:`MAX_NARROWING` times, so later iterations refine around the estimate instead of
    re-exploring the whole range."""
    return replace(config, half_width=tuple(np.asarray(config.half_width) * 0.5 ** min(iteration, MAX_NARROWING)),
                   seed=config.seed + 7919 * iteration)


def view_angles(geom: ConeGeometry, center_mm=None) -> np.ndarray:
    """Angle (rad) of each view's source around the scan axis through ``center_mm`` (default:
    the mean source position's projection), measured from view 0, increasing with the scan."""
    from .reconstruction import estimate_scan_axis

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
"""Angular harmonics worth setting by sharpness: the detector shift along u odd under a half
turn (k = 1 is the gauge). The in-plane roll (odd k) and the magnification (even k) are as
invisible to the loop, but the entropy minimum did not recover them on the simulated mouse
scan (it doubled the error), so they are available, not listed here."""


def focus_conjugate_modes(line_integrals, nominal: ConeGeometry, params: np.ndarray, grid: VolumeGrid, mask, *,
                          modes: dict | None = None, step_px: float = 0.5, sweeps: int = 3,
                          focus_slices: int = 64, inner_fraction: float = 1.0,
                          fdk_kwargs=None) -> tuple[np.ndarray, dict]:
    """Set the geometry modes the consistency metric cannot see by image sharpness.

    In a full scan, view angle t and t + pi see the same rays reversed (u -> -u). A change
    of view t's image that its conjugate view can mirror moves each ray and its conjugate
    alike, so the data stay consistent and the alternating loop leaves it in place: a
    detector shift along u or an in-plane roll that is odd under the half turn (odd angular
    harmonics cos(k t), sin(k t)), and a magnification that is even under it. On the
    truncated mouse scan a 0.5 px k = 3 shift mode stayed at 0.5 px through three loop
    iterations while a k = 2 mode fell to 0.04 px. Such modes still blur the image, so each
    coefficient is chosen (coordinate-wise parabola through three reconstructions, ``sweeps``
    rounds, the step halving each round) to minimise :func:`image_entropy` of an FDK of the
    central ``focus_slices`` slices of ``grid``, within ``inner_fraction`` of its half width.

    ``modes`` maps "shift" (detector d_u), "scale" (detector d_w: magnification about the
    principal point) and "roll" (detector r_w) to their harmonics (default
    :data:`CONJUGATE_MODES`). Amplitudes are in pixels: the image displacement at the edge of
    the grid's projection for scale and roll. Returns the parameters and a dict with the
    fitted amplitudes and the entropy before and after.
    """
    from .reconstruction import fdk

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
    slab = VolumeGrid.centered((min(nz, focus_slices), ny, nx), grid.voxel_size_mm, grid.center_mm)
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


class EstimationVolume(NamedTuple):
    volume: np.ndarray    # the volume to register the views against
    fdk_ncc: float        # masked NCC of the FDK's reprojection to the data
    fdk: np.ndarray       # the FDK it started from (zero outside ``fdk_shape_yx``)


def reconstruct_for_estimation(line_integrals, geom, grid, mask, sirt_iterations: int, fdk_kwargs=None,
                               fdk_shape_yx=None, correction=None, measure_fdk: bool = True) -> EstimationVolume:
    """The volume the views are registered against: FDK, then ``sirt_iterations`` of masked SIRT.

    FDK of a truncated scan does not reproject to its own data (the extrapolated rows leave
    low-frequency errors, and what lies outside the grid is missing), and no background
    model absorbs all of that. A few SIRT iterations started from FDK make the volume
    consistent with the measured rays: on the truncated mouse scan the per-view estimates
    against a true-geometry volume became 8x more accurate. Where the object reaches far
    beyond the grid, SIRT piles the missing mass into the border voxels instead; the SIRT
    volume is kept only where it reprojects closer (masked NCC) to the data than the FDK.
    ``fdk_shape_yx`` keeps the FDK to that central part of the grid (zero around it): outside
    the field of view FDK has incomplete data and only SIRT may fill the padding
    (:func:`estimation_grid`). ``correction`` = (volume - fdk of a coarser reconstruction,
    its grid) replaces the SIRT iterations: the difference, resampled onto ``grid``, is added
    to this FDK (the coarse level's SIRT, for the low frequencies and the rim, at a fraction of
    the cost of fine SIRT; on the 360-view scan of :data:`SCHEDULES` it registered the views
    worse than the FDK alone). Returns an :class:`EstimationVolume`; its ``fdk_ncc`` measures how
    consistent the geometry is, which SIRT cannot inflate by fitting an underdetermined
    (few-view) problem. It costs a reprojection: without SIRT and with ``measure_fdk`` False it
    is skipped (NaN).
    """
    from .reconstruction import fdk, resample, sirt

    vol = fdk(line_integrals, geom, grid, valid_mask=mask, **(fdk_kwargs or {}))
    if fdk_shape_yx is not None:
        _, ny, nx = grid.shape_zyx
        y0, x0 = (ny - fdk_shape_yx[0]) // 2, (nx - fdk_shape_yx[1]) // 2
        inner = np.zeros_like(vol)
        inner[:, y0:y0 + fdk_shape_yx[0], x0:x0 + fdk_shape_yx[1]] = vol[:, y0:y0 + fdk_shape_yx[0], x0:x0 + fdk_shape_yx[1]]
        vol = inner
    if correction is not None:
        delta, delta_grid = correction
        return EstimationVolume(vol + resample(delta, delta_grid, grid), float("nan"), vol)
    if sirt_iterations <= 0 and not measure_fdk:
        return EstimationVolume(vol, float("nan"), vol)
    corr_fdk = projection_consistency(vol, grid, geom, line_integrals, mask)[1]
    out = vol
    if sirt_iterations > 0:
        refined = sirt(line_integrals, geom, grid, sirt_iterations, x0=vol, valid_mask=mask)
        if projection_consistency(refined, grid, geom, line_integrals, mask)[1] > corr_fdk:
            out = refined
    return EstimationVolume(out, corr_fdk, vol)


DEFAULT_PADDING = 1.25
"""How many times :func:`calibrate` widens the ROI grid across for the estimation volume
(:func:`estimation_grid`). Wider helped objects several times the field of view and hurt
mildly truncated ones (README, "Between (a) and (c)": scenario (a)'s mouse at 1, 1.25, 1.5, 2
and 3 times its width, padding 1.25 / 1.6 / 2.0)."""


TRUNCATED_ABOVE = 0.01
""":func:`truncation_level` above which :func:`calibrate` treats a scan as truncated."""


def truncation_level(line_integrals: np.ndarray, valid_mask=None, edge_px: int = 2) -> float:
    """How much object the left and right detector edges see: the median over views of the mean
    line integral in the ``edge_px`` outermost columns on each side (valid pixels only),
    relative to the 99.9th percentile of all data. About 0 when the object fits in the field of
    view (noise averages out), a few per cent and more for an interior scan."""
    li = np.asarray(line_integrals, dtype=np.float32)
    mask = _as_view_mask(valid_mask, li.shape) & np.isfinite(li)
    cols = np.r_[0:edge_px, li.shape[-1] - edge_px:li.shape[-1]]
    edge, m = li[..., cols], mask[..., cols]
    per_view = (np.where(m, edge, 0.0).sum(axis=(1, 2)) / np.maximum(m.sum(axis=(1, 2)), 1))
    peak = float(np.percentile(li[mask], 99.9)) if mask.any() else 0.0
    return float(np.median(per_view) / peak) if peak > 0 else 0.0


def estimation_grid(grid: VolumeGrid, padding: float) -> VolumeGrid:
    """``grid`` widened ``padding`` times across (x and y, same voxels and centre): room for
    the part of the object outside the ROI that the truncated rays still cross."""
    nz, ny, nx = grid.shape_zyx
    return VolumeGrid.centered((nz, int(round(ny * padding)), int(round(nx * padding))), grid.voxel_size_mm,
                               grid.center_mm)


def hold_magnification(nominal: ConeGeometry, params: np.ndarray, points_mm, tol: float = 1e-6) -> np.ndarray:
    """``params`` with every detector moved along its normal so the estimate's common
    magnification equals the nominal one (:func:`metrics.fit_object_scale` = 1).

    The loop cannot see a common magnification error (it is the similarity part of the
    gauge) and let it drift to 1.3 % on the simulated mouse scan; the robot's nominal
    magnification is far better than that on average.
    """
    from .metrics import fit_object_scale

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


SCHEDULES = {
    "accurate": {"coarse_binning": 2, "fine_binning": 1, "fine_volume": "sirt", "fine_source": "star",
                 "fine_samples": 192, "fine_draws": DRAWS, "coarse_passes": 3},
    "fast": {"coarse_binning": 4, "fine_binning": 2, "fine_volume": "fdk", "fine_source": "fixed",
             "fine_samples": 96, "fine_draws": 1, "coarse_passes": 1},
}
"""Resolution schedules of :func:`calibrate`. ``accurate``: estimate on 2x2 binned data, then
at full size against a full-size FDK + SIRT volume. ``fast`` (large scans): 4x4 binned
(FDK + SIRT), then 2x2 binned against the FDK alone, the source held at the coarse estimate
on the finer level (one ray-cast per view and level) and 96 samples per view there instead of
192; the final volume is still the full-size FDK (``coarse_passes``: see :func:`calibrate`).
Measured on the truncated mouse scan of bench/bench_calibration_speed.py (360 views of
256 x 256): the FDK alone registered the views better than FDK plus the coarse SIRT correction
(0.64 against 1.05 px after 2 iterations; views started 0.56 px off a true-geometry volume
ended at 0.29 and 0.68 px), and 96 samples
were as accurate as 192 (1.175 against 1.161 px) and 15 % faster. On the 90-view scans of
bench/bench_calibration.py the fine SIRT is what makes the accurate schedule accurate
(0.14 px; 1.69 px with FDK). ``fine_draws``: the finer level's sample sets
(:attr:`LLEConfig.draws`). With one ray-cast per view the finer level of ``fast`` is all
scoring, so a second set costs nearly its whole time again: on that scan two sets took 2
iterations to 0.862 px in 73.6 s, one set to 0.886 px in 66.1 s (the coarse level has two
sets in both)."""


FINE_VOLUMES = ("sirt", "fdk+coarse-sirt", "fdk")
"""The volume the finer level registers against on a truncated scan: its own FDK + SIRT
(:func:`reconstruct_for_estimation`), its FDK plus the coarse level's SIRT correction
resampled, or its FDK alone."""


def _moved_px(geom: ConeGeometry, params: np.ndarray, before: np.ndarray, points_mm) -> float:
    """How far ``params`` moved the views from ``before`` (both relative to ``geom``): the mean
    gauge-aligned displacement of the points' projections, in pixels of ``geom``'s detector."""
    return float(reprojection_error(geom.perturbed(params), geom.perturbed(before), points_mm,
                                    align_gauge=True)["mean_px"])


def _level(li, mask, nominal, grid, factor):
    """Data, mask, nominal geometry and grid binned ``factor`` times (the inputs themselves at 1)."""
    if factor <= 1:
        return li, mask, nominal, grid
    li_b, mask_b = bin_masked(li, mask, factor)
    return li_b, mask_b, nominal.binned(factor), grid.binned(factor)


@blas_single_threaded
def calibrate(line_integrals: np.ndarray, nominal: ConeGeometry, grid: VolumeGrid, *,
              method: str = "ncc-lle-exact", n_iter: int = 2, valid_mask=None, schedule: str = "accurate",
              coarse_binning: int | None = None, fine_binning: int | None = None, fine_volume: str | None = None,
              coarse_passes: int | None = None, coarse_tol_px: float = 0.1, stop_update_px: float = 0.05,
              configs: tuple | None = None, gauge_points_mm=None, sirt_iterations: int = 15,
              truncated: bool | None = True,
              padding: float = DEFAULT_PADDING, undo_inconsistent: bool = False, prior_sigma=DEFAULT_PRIOR_SIGMA,
              drift_order: int | None = None, drift_times=None, focus_modes: dict | None = None,
              fdk_kwargs: dict | None = None, seed: int = 0, progress=None,
              on_iteration=None) -> CalibrationResult:
    """Alternate reconstruction and per-view LLE geometry estimation (design.md §2).

    Each outer iteration reconstructs with the current geometry
    (:func:`reconstruct_for_estimation`: FDK then ``sirt_iterations`` of SIRT, on ``grid``
    widened ``padding`` times across, :func:`estimation_grid`) and
    re-estimates every view, first on ``coarse_binning``-binned projections and a coarser
    volume, then on ``fine_binning``-binned ones (``schedule``, :data:`SCHEDULES`, gives the
    defaults of these two and of ``fine_volume``: the finer level's volume, see
    :data:`FINE_VOLUMES`). In the first outer iteration the coarse level alternates by itself up
    to ``coarse_passes`` times (schedule default: 3 accurate, 1 fast), the coarse volume rebuilt
    with each pass's geometry, until a pass moves the views less than ``coarse_tol_px`` (mean
    gauge-aligned coarse pixels): the volume built with the nominal geometry is too blurred for
    the finer level. On scenario (a) of bench/bench_calibration.py three passes took the first
    iteration from 0.90 to 0.12 px and the third from 0.107 to 0.101 px, for 2.6 s more per
    scan; on the 360-view speed scan a second pass took two iterations from 0.664 to 0.621 px in
    12 s more, where a third iteration reached 0.577 px in 19 s more, so ``fast`` keeps one.
    SIRT runs only on a ``truncated`` scan (True by default, the interior scans this system
    takes; None: decided by :func:`truncation_level` > :data:`TRUNCATED_ABOVE`; False: FDK
    volumes only). When the object fits in the field of view FDK can be the better volume: 360
    views of 256 x 256 started 0.56 px off a true-geometry volume ended at 0.11 px against its
    FDK and 0.27 px against its SIRT volume; but on the demo scan (120 views of 64 x 128, edge
    level 0.0002) SIRT still gave the better result (0.16 against 0.22 px), so detection is not
    the default. The unobservable gauge (a global rigid motion of all views, i.e. of the object)
    is then removed by aligning the estimate to the nominal geometry on ``gauge_points_mm``
    (default: points filling ``grid``), so the correction does not wander between iterations,
    and the common magnification is held at the nominal one (:func:`hold_magnification`).
    Optionally, the modes that conjugate views cannot tell apart (``focus_modes``, e.g.
    :data:`CONJUGATE_MODES`) are then set by image sharpness
    (:func:`focus_conjugate_modes`; off by default: it helped the mouse scan, 0.61 -> 0.28 px,
    and ruined the battery scan, 0.92 -> 1.7 px). With ``undo_inconsistent``, an iteration
    that lowers the data consistency (masked NCC of the FDK, coarse level) is undone and ends
    the loop: that kept the strongly truncated carotid scan at its nominal geometry instead of
    diverging, but also stopped a 24-view scan whose error the iteration had cut from 2.8 to
    1.7 px, so it is off by default. ``prior_sigma`` (9 values, mm x6, rad x3; default
    :data:`DEFAULT_PRIOR_SIGMA`; None = data alone) is the nominal geometry's error: the LLE
    methods then estimate each view by maximum a posteriori (:attr:`LLEConfig.prior_sigma`),
    which kept the strongly truncated carotid scan near its nominal geometry (4.0 px against
    17.9 px without; 3.4 px nominal) and took the battery drift scan from 1.40 to 1.01 px
    (ncc-lle-exact, bench/bench_calibration.py); explicit ``configs``
    carry their own. ``drift_order`` (None = off, the default: the robots' errors are
    independent from view to view) makes the geometry a slow drift: after each outer iteration
    every parameter is replaced by its least-squares polynomial of that degree in time
    (``drift_times`` (n,), e.g. the frames' stamps; default the view index; :func:`fit_drift`).
    Where the errors drift, the polynomial must fit the half of them that the data show
    together with the half that conjugate views cannot tell apart, which per-view estimates
    leave where they start: on scenario (b) of bench/bench_calibration.py ncc-lle-exact went
    from 1.02 px (SSIM 0.825) to 0.69 px (SSIM 0.966) with degree 3 and no prior (0.76 px
    over three sampling seeds; 0.79 px with the default prior, which pulls every view towards
    nominal). Where truncation biases the data term it does not help (a 9 mm cell through a
    7.9 mm field of view: 1.60 px nominal, 1.46 px per view, 1.68 px as a drift; README).
    The returned volume is the full-size FDK with the final geometry. The loop runs
    ``n_iter`` outer iterations, or fewer: it stops after an iteration that moved the views
    less than ``stop_update_px`` (:attr:`IterationRecord.update_px`; 0 = always ``n_iter``).
    The default is the estimator's own scatter (0.04 to 0.05 px on scenario (a) against a true-geometry volume): there an
    iteration that moved the views 0.064 px still cut the error from 0.123 to 0.102 px, the
    next ones, moving them 0.042 and 0.035 px, by 0.001 px.
    ``seed`` starts the LLE methods' random sampling (:func:`default_lle_configs`; explicit
    ``configs`` carry their own, the baselines draw nothing): another seed is another estimate
    of the same scan, which is how bench/bench_calibration.py --repeats measures the scatter.
    ``progress(message)`` receives one line per step, ``on_iteration(record, params)`` the
    :class:`IterationRecord` and the (n, 9) parameters after each outer iteration.
    """
    from .reconstruction import fdk

    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}")
    if schedule not in SCHEDULES:
        raise ValueError(f"schedule must be one of {tuple(SCHEDULES)}")
    plan = SCHEDULES[schedule]
    coarse_binning = plan["coarse_binning"] if coarse_binning is None else int(coarse_binning)
    fine_binning = plan["fine_binning"] if fine_binning is None else int(fine_binning)
    fine_volume = plan["fine_volume"] if fine_volume is None else fine_volume
    coarse_passes = plan["coarse_passes"] if coarse_passes is None else int(coarse_passes)
    if fine_volume not in FINE_VOLUMES:
        raise ValueError(f"fine_volume must be one of {FINE_VOLUMES}")
    if fine_binning < 1 or coarse_binning < 1:
        raise ValueError("binning factors must be >= 1")
    if coarse_passes < 1:
        raise ValueError("coarse_passes must be >= 1")
    if not stop_update_px >= 0:
        raise ValueError("stop_update_px must be >= 0")
    if not padding >= 1:
        raise ValueError("padding must be >= 1 (the estimation grid holds the ROI grid)")
    if drift_order is not None:
        fit_drift(np.zeros((nominal.n_views, 9)), drift_order, drift_times)  # validates order and times
    t_start = time.perf_counter()
    if np.shape(line_integrals) != (nominal.n_views,) + nominal.det_shape:
        raise ValueError(f"{np.shape(line_integrals)[0]} frames but {nominal.n_views} geometries, or detector "
                         f"shape mismatch")
    li, mask = _usable_data(line_integrals, valid_mask)
    say = progress or (lambda message: None)
    if truncated is None:
        level = truncation_level(li, mask)
        truncated = level > TRUNCATED_ABOVE
        say(f"truncation level {level:.4f}: {'truncated, FDK + SIRT' if truncated else 'not truncated, FDK'} volumes")
    if not truncated:
        sirt_iterations = 0  # every volume is then an FDK
    if method in LLE_METHODS:
        estimate, narrowed = estimate_views, _narrowed
        if configs is None:
            coarse_cfg, fine_cfg = default_lle_configs(LLE_METHODS[method], seed=seed, prior_sigma=prior_sigma)
            fine_cfg = replace(fine_cfg, source_positions=plan["fine_source"], n_samples=plan["fine_samples"],
                               draws=plan["fine_draws"])
        else:
            coarse_cfg, fine_cfg = configs
    else:  # the baselines run on the same loop, their own search keeps its range
        from .baselines import default_gdc_configs, estimate_views_gdc

        estimate, narrowed = estimate_views_gdc, (lambda config, iteration: config)
        coarse_cfg, fine_cfg = configs or default_gdc_configs(method)
    fdk_kwargs = dict(fdk_kwargs or {})
    points = roi_points(grid) if gauge_points_mm is None else np.asarray(gauge_points_mm, float)
    grid_e = estimation_grid(grid, padding)
    has_coarse = coarse_binning > fine_binning
    li_f, mask_f, nom_f, grid_f = _level(li, mask, nominal, grid_e, fine_binning)
    inner_f = grid.binned(fine_binning).shape_zyx[1:]
    if has_coarse:
        li_c, mask_c, nom_c, grid_c = _level(li, mask, nominal, grid_e, coarse_binning)
        inner_c = grid.binned(coarse_binning).shape_zyx[1:]
    else:  # one level: it also runs the data consistency check (undo_inconsistent)
        li_c, mask_c, nom_c, grid_c, inner_c = li_f, mask_f, nom_f, grid_f, inner_f
        if fine_volume == "fdk+coarse-sirt":  # no coarse level to take the correction from
            fine_volume = "sirt"
    params = np.zeros((nominal.n_views, 9))
    history = []
    # the coarse level's reconstruction with the geometry entering each iteration: its volume
    # for the coarse estimate, its FDK's NCC for undo_inconsistent, its SIRT correction for a
    # fine level without SIRT
    rec_c = reconstruct_for_estimation(li_c, nom_c, grid_c, mask_c, sirt_iterations, fdk_kwargs, inner_c)
    for it in range(n_iter):
        t0 = time.perf_counter()
        start = params.copy()
        rec_in = rec_c  # the consistency of the geometry entering the iteration (undo_inconsistent)
        n_passes = (coarse_passes if it == 0 else 1) if has_coarse else 0
        for rep in range(n_passes):
            if rep:  # a warm-up pass: the coarse volume again, with the geometry of the last pass
                rec_c = reconstruct_for_estimation(li_c, nom_c.perturbed(params), grid_c, mask_c, sirt_iterations,
                                                   fdk_kwargs, inner_c)
            before = params
            cfg = narrowed(coarse_cfg, it)
            if rep and isinstance(cfg, LLEConfig):  # fresh samples
                cfg = replace(cfg, seed=cfg.seed + 104729 * rep)
            params, _ = estimate(li_c, nom_c, params, rec_c.volume, grid_c, cfg, mask_c)
            moved_px = _moved_px(nom_c, params, before, points)
            say(f"iteration {it + 1}/{n_iter}: coarse estimate {rep + 1} done, views moved {moved_px:.3f} coarse px "
                f"({time.perf_counter() - t0:.1f} s)")
            if moved_px < coarse_tol_px:
                break
        correction = (rec_c.volume - rec_c.fdk, grid_c) if fine_volume == "fdk+coarse-sirt" else None
        vol = reconstruct_for_estimation(li_f, nom_f.perturbed(params), grid_f, mask_f,
                                         sirt_iterations if fine_volume == "sirt" else 0, fdk_kwargs,
                                         inner_f, correction=correction, measure_fdk=False).volume
        params, fine_info = estimate(li_f, nom_f, params, vol, grid_f, narrowed(fine_cfg, it), mask_f)
        params = remove_gauge(nominal.perturbed(params), nominal, points).params_relative_to(nominal)
        params = hold_magnification(nominal, params, points)
        if drift_order is not None:
            params = fit_drift(params, drift_order, drift_times)
        if focus_modes:
            params, focus = focus_conjugate_modes(li, nominal, params, grid, mask, modes=focus_modes,
                                                  fdk_kwargs=fdk_kwargs)
            say(f"iteration {it + 1}/{n_iter}: sharpness focus of {len(focus['modes'])} conjugate modes, entropy "
                f"{focus['entropy_before']:.6f} -> {focus['entropy_after']:.6f}")
        moved_px = _moved_px(nominal, params, start, points)
        last = it + 1 == n_iter or moved_px < stop_update_px
        # the next iteration's coarse volume (and the consistency check): not after the last
        rec_next = (reconstruct_for_estimation(li_c, nom_c.perturbed(params), grid_c, mask_c, sirt_iterations,
                                               fdk_kwargs, inner_c)
                    if undo_inconsistent or not last else None)
        rmse, corr = projection_consistency(vol, grid_f, nom_f.perturbed(params), li_f, mask_f)
        step = params - start
        fractions = fine_info.get("independent_fraction") or [float("nan")]
        rec = IterationRecord(it + 1, rmse, corr, float(np.sqrt((step[:, :6] ** 2).mean())),
                              float(np.rad2deg(np.sqrt((step[:, 6:] ** 2).mean()))), time.perf_counter() - t0,
                              fractions[-1], moved_px)
        if undo_inconsistent and not rec_next.fdk_ncc > rec_in.fdk_ncc:
            say(f"iteration {it + 1}/{n_iter}: data consistency fell ({rec_in.fdk_ncc:.5f} -> {rec_next.fdk_ncc:.5f}); "
                f"undone, stopping")
            params = start
            break
        rec_c = rec_next
        history.append(rec)
        if on_iteration is not None:
            on_iteration(rec, params.copy())
        say(f"iteration {rec.iteration}/{n_iter}: projection RMSE {rec.projection_rmse:.4g}, NCC "
            f"{rec.projection_ncc:.5f}, update {rec.update_rms_mm:.3f} mm / {rec.update_rms_deg:.3f} deg, "
            + ("" if np.isnan(rec.independent_fraction) else f"independent pixels {rec.independent_fraction:.3f}, ")
            + f"views moved {rec.update_px:.3f} px, {rec.wall_s:.1f} s")
        if last and it + 1 < n_iter:
            say(f"converged: the views moved less than {stop_update_px:g} px; stopping after {rec.iteration} of "
                f"{n_iter} iterations")
            break
    geom = nominal.perturbed(params)
    volume = fdk(li, geom, grid, valid_mask=mask, **fdk_kwargs)
    return CalibrationResult(method, params, geom, volume, tuple(history), time.perf_counter() - t_start)
