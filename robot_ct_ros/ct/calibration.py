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

import numpy as np
from numba import njit, prange

from robot_ct_ros.ct.geometry import ConeGeometry

WEIGHTINGS = ("l2", "ncc", "ncc-exact")


def _masked(measured, neighbours, mask):
    b = np.asarray(measured, dtype=np.float64)
    Y = np.asarray(neighbours, dtype=np.float64)
    if b.ndim == 1:
        b, Y = b[None], Y[None]
    if Y.ndim != 3 or Y.shape[0] != b.shape[0] or Y.shape[2] != b.shape[1]:
        raise ValueError(f"neighbours must be (n, K, P) for measured (n, P); got {Y.shape} and {b.shape}")
    m = np.ones(b.shape, dtype=bool) if mask is None else np.broadcast_to(np.asarray(mask, dtype=bool), b.shape)
    m = m & np.isfinite(b) & np.all(np.isfinite(Y), axis=1)
    if np.any(m.sum(axis=1) < 2):
        raise ValueError("a view has fewer than 2 valid pixels to embed")
    return np.where(m, b, 0.0), np.where(m[:, None, :], Y, 0.0), m.astype(np.float64)


def _solve_regularised(G, rhs, reg):
    """Solve (G + reg * tr(G)/K * I) x = rhs for a batch of small symmetric matrices."""
    K = G.shape[-1]
    scale = np.trace(G, axis1=1, axis2=2) / K
    scale = np.where(scale > 0, scale, 1.0)
    Greg = G + (reg * scale)[:, None, None] * np.eye(K)
    return np.linalg.solve(Greg, rhs[..., None])[..., 0]


def lle_weights(measured, neighbours, method: str = "ncc-exact", mask=None, reg: float = 1e-3) -> np.ndarray:
    """Embedding weights (n, K), each row summing to 1, of measured projections in neighbours.

    ``reg`` regularises the K x K Gram matrix by ``reg * trace / K`` on its diagonal (the
    neighbours of a dense sampling grid are nearly collinear).
    """
    if method not in WEIGHTINGS:
        raise ValueError(f"unknown weighting {method!r}; choose one of {WEIGHTINGS}")
    b, Y, m = _masked(measured, neighbours, mask)
    n, K, _ = Y.shape
    count = m.sum(axis=1)
    if method == "l2":
        D = b[:, None, :] - Y  # (n, K, P) residuals, zero outside the mask
        C = np.einsum("nkp,njp->nkj", D, D)
        w = _solve_regularised(C, np.ones((n, K)), reg)
        return w / w.sum(axis=1, keepdims=True)

    # mean-centre over the valid pixels of each view
    bc = (b - (b.sum(axis=1) / count)[:, None]) * m
    Yc = (Y - (Y.sum(axis=2) / count[:, None])[:, :, None]) * m[:, None, :]
    r = np.einsum("nkp,np->nk", Yc, bc)
    if method == "ncc":
        s = np.sqrt(np.einsum("nkp,nkp->nk", Yc, Yc) / np.maximum(count - 1, 1)[:, None])
        sb = np.sqrt(np.einsum("np,np->n", bc, bc) / np.maximum(count - 1, 1))
        c = r / np.maximum(count - 1, 1)[:, None] / np.maximum(s * sb[:, None], 1e-300)
        w = c / np.maximum(s, 1e-300)
    else:
        G = np.einsum("nkp,njp->nkj", Yc, Yc)
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
    return w


def ncc(a, b, mask=None) -> np.ndarray:
    """Normalized cross-correlation of (n, P) arrays, per row, over the mask."""
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    b = np.atleast_2d(np.asarray(b, dtype=np.float64))
    m = np.ones(a.shape, bool) if mask is None else np.broadcast_to(np.asarray(mask, bool), a.shape)
    m = m & np.isfinite(a) & np.isfinite(b)
    cnt = np.maximum(m.sum(axis=1), 1)
    ac = np.where(m, a - (np.where(m, a, 0).sum(axis=1) / cnt)[:, None], 0)
    bc = np.where(m, b - (np.where(m, b, 0).sum(axis=1) / cnt)[:, None], 0)
    den = np.sqrt((ac * ac).sum(axis=1) * (bc * bc).sum(axis=1))
    return (ac * bc).sum(axis=1) / np.maximum(den, 1e-300)


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


@njit(parallel=True, fastmath=True, cache=True)
def _warp_kernel(images, H, image_index, out, valid):
    m, n_rows, n_cols = out.shape
    _, vr, vc = images.shape
    for t in prange(m * n_rows):
        s = t // n_rows
        r = t - s * n_rows
        img = image_index[s]
        h = H[s]
        for c in range(n_cols):
            x = h[0, 0] * c + h[0, 1] * r + h[0, 2]
            y = h[1, 0] * c + h[1, 1] * r + h[1, 2]
            z = h[2, 0] * c + h[2, 1] * r + h[2, 2]
            if z == 0.0:
                out[s, r, c] = 0.0
                valid[s, r, c] = False
                continue
            x /= z
            y /= z
            if x < 0.0 or y < 0.0 or x > vc - 1 or y > vr - 1:
                out[s, r, c] = 0.0
                valid[s, r, c] = False
                continue
            i0 = min(int(x), vc - 2) if vc > 1 else 0
            j0 = min(int(y), vr - 2) if vr > 1 else 0
            fx = x - i0
            fy = y - j0
            a = images[img, j0, i0] * (1 - fx) + images[img, j0, min(i0 + 1, vc - 1)] * fx
            b = images[img, min(j0 + 1, vr - 1), i0] * (1 - fx) + images[img, min(j0 + 1, vr - 1), min(i0 + 1, vc - 1)] * fx
            out[s, r, c] = a * (1 - fy) + b * fy
            valid[s, r, c] = True


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
    out = np.empty((H.shape[0], n_rows, n_cols), dtype=np.float32)
    valid = np.empty(out.shape, dtype=np.bool_)
    _warp_kernel(imgs, H, idx, out, valid)
    return out, valid
