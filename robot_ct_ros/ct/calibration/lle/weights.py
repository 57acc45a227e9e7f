"""Embedding weights of one measured projection in K neighbouring reprojections (docs/calibration.md §2.1).

Three weightings: ``"l2"`` (classic LLE), ``"ncc"`` (the published closed form w_j ∝ c_j / s_j)
and ``"ncc-exact"`` (the exact maximiser of the normalized cross-correlation over affine
combinations, w = G⁻¹r / 1ᵀG⁻¹r); optionally maximum a posteriori under a Gaussian prior on
the embedded parameters. Arrays are flattened per view: measured (n, P), neighbours (n, K, P),
mask (n, P) or (P,); dead pixels, chip gaps and pixels outside the ROI support are masked.
"""

from __future__ import annotations

import numpy as np

from robot_ct_ros.ct.calibration.kernels import sample_distances

__all__ = ["WEIGHTINGS", "lle_weights", "posterior_cost", "effective_pixel_fraction", "background_basis",
           "project_out", "view_distances"]


WEIGHTINGS = ("l2", "ncc", "ncc-exact")


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
    autoregressive field: about 1 for white residuals. Why 16 pixels: docs/calibration.md,
    "The robots' accuracy as a prior".
    """
    mask = np.asarray(mask, bool)
    if basis is None:
        basis = background_basis(mask)
    b = project_out(np.asarray(measured, np.float64), basis, mask)
    p = project_out(np.asarray(predicted, np.float64), basis, mask)
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


def project_out(images: np.ndarray, basis: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Residual of (n, rows, cols) images after removing their projection on the basis (masked)."""
    x = np.where(mask, images, 0.0).astype(np.float64)
    coef = np.einsum("nbrc,nrc->nb", basis, x)
    return np.where(mask, x - np.einsum("nbrc,nb->nrc", basis, coef), 0.0)


def view_distances(pred: np.ndarray, measured: np.ndarray, mask: np.ndarray, metric: str,
               background=(0, 0)) -> np.ndarray:
    """Per-view distance (as :func:`sample_distances`) between two (n, rows, cols) stacks."""
    basis = background_basis(mask, *background)
    residual = project_out(measured, basis, mask)
    mk = mask.reshape(mask.shape[0], -1)
    p = np.where(mk, pred.reshape(mk.shape), 0.0).astype(np.float64)
    b = np.where(mk, measured.reshape(mk.shape), 0.0).astype(np.float64)
    q = basis.reshape(basis.shape[0], basis.shape[1], -1)
    sums = np.concatenate([np.stack([mk.sum(1), p.sum(1), (p * p).sum(1), (p * b).sum(1), b.sum(1), (b * b).sum(1),
                                     (p * residual.reshape(mk.shape)).sum(1)], axis=1),
                           np.einsum("nbp,np->nb", q, p)], axis=1)
    return sample_distances(sums, metric, (residual.reshape(mk.shape) ** 2).sum(1))
