"""Reconstruction for arbitrary per-view cone-beam geometry: FDK (the iterative methods are in
:mod:`robot_ct_ros.ct.iterative`).

All conventions (world mm/rad, ``volume[k, j, i] = (z, y, x)``, ``proj[view, row, col]``,
projection matrices mapping (x, y, z, 1) to ``lambda * (col, row, 1)``) are those of
:mod:`robot_ct_ros.ct.geometry`. Projections are line integrals (mm x attenuation per mm);
volumes come back in attenuation per mm, float32, shaped ``grid.shape_zyx``.

FDK here makes no assumption that the views rotate about one fixed axis with an ideal
detector (RTK's circular geometry does). Each view is weighted and filtered in its own
detector frame:

* principal point: foot of the perpendicular from the source onto the detector plane;
  ``a``, ``b`` are the in-plane offsets (mm) of a pixel from it along u and v, ``D`` the
  source-to-plane distance;
* weight ``D * |g . theta(a)| / sqrt(D^2 + a^2 + b^2)`` with ``g`` the source displacement
  per view (angular increment times the local source velocity around the scan centre,
  measured in the plane orthogonal to the estimated scan axis) and ``theta(a)`` the unit
  normal of the ray in the fan plane. For an ideal circular scan this is the classic
  FDK cosine weight ``D / sqrt(D^2 + a^2 + b^2)`` times ``R * dbeta``; for tilted or
  shifted detectors it is the exact 2D fan-beam Jacobian (as in Rit & Clackdoyle 2014);
* ramp filter along detector rows (u) in detector millimetres, which is the standard
  FDK filter on the virtual detector through the ROI centre rescaled by the
  magnification (the ramp kernel is homogeneous of degree -2); rows rolled off the
  source motion are first resampled onto a detector whose rows follow it
  (:mod:`robot_ct_ros.ct.virtual_detector`);
* voxel-driven back-projection through ``geom.projection_matrices()``: bilinear
  interpolation and weight ``1 / depth^2`` (depth along the detector normal); with the
  ``D`` above this is FDK's ``(D / depth)^2`` distance weight for the filter in detector
  millimetres; full-scan factor 1/2 per ray pair. Scaled so a uniform object
  reconstructs to its attenuation; on an ideal circle it equals RTK's FDK to float
  rounding (see the tests).

A one-row detector is a fan beam: the same weights and filter are then the exact fan-beam
FBP of the plane through the source and the row, and the back-projection fills the voxels
within half a pixel of that plane (a grid of one or a few slices).

Offset (displaced) detectors, as the robotic ROI scan uses to widen its field of view,
get Wang's redundancy weights instead of the 1/2 (:func:`displaced_detector_weights`), pixel by
pixel; on a detector rotated in its own plane they are only approximate (see there).

Interior (truncated) scans: before filtering each detector row is extended beyond both
edges (point-symmetric continuation or capped symmetric mirror, cosine-tapered to zero)
so the ramp filter does not see a jump at the detector edge, which would otherwise
produce a bright rim ("truncation ring") in the ROI.

Short scans (an arc of half a turn plus the fan angle, as robots that cannot circle the whole
object take) get Parker's redundancy weights instead of the 1/2 (:func:`short_scan_weights`):
each ray and its conjugate, measured from both ends of the arc, weigh 2 together. An arc of
half a turn or less cannot be weighted so; FDK then warns, weighs each ray 1 (it is measured once
at most: the density keeps its scale) and is only approximate (what the arc misses stays missing).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.fft
from scipy import ndimage
from numba import njit, prange

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid, view_mask
from robot_ct_ros.ct.virtual_detector import DEFAULT_TOL_DEG, align_rows_to_motion, outside_footprint
from robot_ct_ros.ct.scan_weights import (  # noqa: F401  (re-exported: FDK's weights live there)
    FDKWarning,
    centre_column,
    displaced_detector_layout,
    displaced_detector_weights,
    displaced_pixel_weights,
    estimate_scan_axis,
    estimate_scan_centre,
    fdk_view_weights,
    scan_arc,
    short_scan_weights,
)

__all__ = [
    "FDKWarning",
    "fdk",
    "fdk_filter_projections",
    "fdk_backproject",
    "warn_if_empty",
    "fdk_view_weights",
    "displaced_detector_weights",
    "short_scan_weights",
    "scan_arc",
    "estimate_scan_axis",
    "estimate_scan_centre",
    "scan_centre",
    "ramp_kernel_spectrum",
    "fill_invalid_pixels",
    "resample",
    "WINDOWS",
]

WINDOWS = ("ram-lak", "hann", "hamming", "cosine", "shepp-logan")


# ---------------------------------------------------------------------------- geometry
def _principal_point(geom: ConeGeometry):
    """Principal point (col, row) in pixel indices and signed unit normal towards the detector."""
    s, d, u, v, w = geom.source_mm, geom.detector_mm, geom.u, geom.v, geom.w
    sdd_signed = np.einsum("ij,ij->i", d - s, w)
    foot = s + sdd_signed[:, None] * w
    c0 = 0.5 * (geom.n_cols - 1) + np.einsum("ij,ij->i", foot - d, u) / geom.col_pitch_mm
    r0 = 0.5 * (geom.n_rows - 1) + np.einsum("ij,ij->i", foot - d, v) / geom.row_pitch_mm
    w_s = np.sign(sdd_signed)[:, None] * w  # unit normal pointing from source to detector
    return c0, r0, np.abs(sdd_signed), w_s


def scan_centre(geom: ConeGeometry, axis=None, fallback_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
    """The centre FDK weights about: :func:`estimate_scan_centre`, or ``fallback_mm`` where the geometry
    tells none (a single view; :func:`fdk` falls back to the grid's centre)."""
    c = estimate_scan_centre(geom, axis)
    return np.asarray(fallback_mm, dtype=np.float64) if c is None else c


# ------------------------------------------------------------------------- filtering
def ramp_kernel_spectrum(n_fft: int, window: str = "hann", cutoff: float = 1.0) -> np.ndarray:
    """Real spectrum (n_fft // 2 + 1,) of the windowed discrete ramp filter in pixel units.

    The spatial kernel is Kak & Slaney's band-limited ramp (h[0] = 1/4, h[n odd] =
    -1/(pi n)^2) sampled on the circular grid of length ``n_fft``; its FFT avoids the DC
    error of a sampled ``|f|``. ``cutoff`` is the window's cut-off as a fraction of the
    Nyquist frequency (as RTK counts it: of the ``n_fft // 2 + 1`` rfft bins, rounded half up to
    a whole bin); the filter is zero from there on.
    """
    if window not in WINDOWS:
        raise ValueError(f"window must be one of {WINDOWS}, got {window!r}")
    if not 0 < cutoff <= 1:
        raise ValueError("cutoff must be in (0, 1]")
    h = np.zeros(n_fft)
    h[0] = 0.25
    k = np.arange(1, n_fft // 2, 2)
    h[k] = -1.0 / (np.pi * k) ** 2
    h[n_fft - k] = h[k]
    H = np.fft.rfft(h).real
    # RTK's convention (rtkFFTRampImageFilter): the window reaches zero at bin
    # (n_fft // 2 + 1) * cutoff rounded half up (itk::Math::Round; Python's round() would
    # round halves to even), so equal settings give equal filters
    n_cut = max(1, int(math.floor(H.size * cutoff + 0.5)))
    f = np.arange(H.size) / n_cut
    inside = f < 1.0
    if window == "ram-lak":
        win = np.ones_like(f)
    elif window == "hann":
        win = 0.5 * (1 + np.cos(np.pi * f))
    elif window == "hamming":
        win = 0.54 + 0.46 * np.cos(np.pi * f)
    elif window == "cosine":
        win = np.cos(0.5 * np.pi * f)
    else:  # shepp-logan
        win = np.sinc(0.5 * f)
    return np.where(inside, H * win, 0.0)


@njit(parallel=True, fastmath=True, cache=True)
def _fill_invalid_rows(rows, valid):
    """In place: replace invalid samples of each row by linear interpolation along the row
    (nearest valid value beyond the ends). rows (n, m) float32, valid (n, m) bool."""
    n, m = rows.shape
    for t in prange(n):
        last = -1
        for i in range(m):
            if valid[t, i]:
                if last < i - 1:
                    if last < 0:
                        for q in range(0, i):
                            rows[t, q] = rows[t, i]
                    else:
                        a = rows[t, last]
                        b = rows[t, i]
                        inv = 1.0 / (i - last)
                        for q in range(last + 1, i):
                            rows[t, q] = a + (b - a) * (q - last) * inv
                last = i
        if last < 0:
            for q in range(m):
                rows[t, q] = 0.0
        elif last < m - 1:
            for q in range(last + 1, m):
                rows[t, q] = rows[t, last]


def fill_invalid_pixels(proj: np.ndarray, valid_mask: np.ndarray) -> np.ndarray:
    """Copy of ``proj`` (n_views, n_rows, n_cols) with invalid pixels interpolated along rows.

    ``valid_mask`` is boolean, True = good pixel, shaped (n_rows, n_cols) (one map for all
    views) or (n_views, n_rows, n_cols).
    """
    out = np.array(proj, dtype=np.float32, copy=True)
    mask = view_mask(valid_mask, out.shape)
    nv, nr, nc = out.shape
    rows = out.reshape(nv * nr, nc)
    _fill_invalid_rows(rows, np.ascontiguousarray(mask).reshape(nv * nr, nc))
    return out


def _cylinder_extension(p_edge, slope, mu_px, n_ext):
    """Water-cylinder continuation (after Hsieh et al. 2004) of rows beyond an edge.

    Per row, the chord profile ``2 mu sqrt(R^2 - (x - x_c)^2)`` of a cylinder of attenuation
    ``mu_px`` (per detector pixel) matching the edge value ``p_edge`` and outward slope
    ``slope`` (per pixel); evaluated at x = 1 .. n_ext pixels beyond the edge. Also returns
    the distance (pixels) at which each cylinder ends.
    """
    mu = np.maximum(mu_px, 1e-12)[:, None]
    pe = np.maximum(p_edge, 0.0)[:, None]
    xc = slope[:, None] * pe / (4.0 * mu * mu)
    r2 = (pe / (2.0 * mu)) ** 2 + xc * xc
    x = np.arange(1, n_ext + 1)[None, :]
    vals = 2.0 * mu * np.sqrt(np.maximum(r2 - (x - xc) ** 2, 0.0))
    end = (xc + np.sqrt(r2))[:, 0]
    return vals, np.where(pe[:, 0] > 0, end, 0.0)


def _edge_fit(rows, k):
    """Value and outward slope (per pixel) of a line fitted to the last k pixels at each edge.

    Returns ((value_left, slope_left), (value_right, slope_right)), arrays (B,)."""
    x = np.arange(k) - 0.5 * (k - 1)
    den = float(np.sum(x * x))
    right = rows[:, -k:]
    sr = (right @ x) / den
    vr = right.mean(axis=1) + sr * x[-1]
    left = rows[:, :k][:, ::-1]  # outward = towards lower columns
    sl = (left @ x) / den
    vl = left.mean(axis=1) + sl * x[-1]
    return (vl, sl), (vr, sr)


def _extend_rows(rows: np.ndarray, n_fft: int, ext: int, mode: str | None,
                 keep_left=None, keep_right=None, given=None) -> np.ndarray:
    """Rows (B, n) into a circular buffer (B, n_fft): data at [0, n), right extension at
    [n, n+ext), left extension wrapped at [n_fft-ext, n_fft), zeros elsewhere.
    ``keep_left`` / ``keep_right`` (B,) float: per-row factors of the extensions (0 = none).
    ``given``: precomputed (left, right) extensions (B, ext), for ``mode="cylinder"``."""
    b, n = rows.shape
    buf = np.zeros((b, n_fft), dtype=np.float32)
    buf[:, :n] = rows
    if mode is None or ext <= 0:
        return buf
    if mode == "cylinder":
        left, right = (np.asarray(a, dtype=np.float32) for a in given)
        # cosine roll-off over the last quarter, for cylinders cut at the buffer end
        k = np.arange(1, ext + 1)
        tail = np.clip((k - 0.75 * ext) / max(0.25 * ext, 1.0), 0.0, 1.0)
        taper = (0.5 * (1.0 + np.cos(np.pi * tail))).astype(np.float32)
        right = right * taper
        left = left * taper
        return _place_extensions(buf, n, n_fft, ext, left, right, keep_left, keep_right)
    k = np.arange(1, ext + 1)
    taper = (0.5 * (1.0 + np.cos(np.pi * k / (ext + 1)))).astype(np.float32)  # 1 -> 0, C1 at the edge
    # reflect indices about the edge pixels (valid for ext larger than the row, too)
    period = 2 * (n - 1) if n > 1 else 1
    idx_r = np.abs(np.mod((n - 1 - k), period))
    idx_r = np.where(idx_r > n - 1, period - idx_r, idx_r)
    idx_l = np.abs(np.mod(k, period))
    idx_l = np.where(idx_l > n - 1, period - idx_l, idx_l)
    right_edge = rows[:, n - 1:n]
    left_edge = rows[:, 0:1]
    if mode == "mirror":  # symmetric mirror (after Ohnesorge et al. 2000)
        # capped at the edge value so a row that is not truncated (edge ~ 0) stays unextended
        right = np.minimum(rows[:, idx_r], right_edge)
        left = np.minimum(rows[:, idx_l], left_edge)
    elif mode == "extrapolate":  # point-symmetric: continues value and slope at the edge
        right = 2.0 * right_edge - rows[:, idx_r]
        left = 2.0 * left_edge - rows[:, idx_l]
        np.maximum(right, 0.0, out=right)  # line integrals are non-negative
        np.maximum(left, 0.0, out=left)
        # bound the continuation so a steep edge cannot run away
        np.minimum(right, 2.0 * np.abs(right_edge), out=right)
        np.minimum(left, 2.0 * np.abs(left_edge), out=left)
    else:
        raise ValueError(f"truncation must be 'extrapolate', 'mirror', 'cylinder' or None, got {mode!r}")
    return _place_extensions(buf, n, n_fft, ext, left * taper, right * taper, keep_left, keep_right)


def _place_extensions(buf, n, n_fft, ext, left, right, keep_left, keep_right):
    """Write the (per-row weighted) extensions into the circular buffer of ``_extend_rows``."""
    if keep_right is not None:
        right = right * keep_right[:, None]
    if keep_left is not None:
        left = left * keep_left[:, None]
    buf[:, n:n + ext] = right
    buf[:, n_fft - ext:] = left[:, ::-1]
    return buf


def _edge_above_noise(rows: np.ndarray, z: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Per row (B, n): is the row's (left, right) edge truncated, i.e. does the mean of its outermost pixels
    stand above the row's noise (more than ``z`` standard errors; the noise from the median absolute first
    difference over the row's outer parts, which the object's edges hardly move)? An edge in air, however noisy, is not extended: the
    point-symmetric continuation of noise is a positive plateau beyond the row that the ramp filter turns into
    a negative offset of the whole volume, largest for a faint object at a low dose."""
    b, n = rows.shape
    k = max(1, min(8, n // 8))
    if n < 3:
        return np.ones(b, bool), np.ones(b, bool)
    w = max(2, min(32, n // 4))  # the outer parts only: cheap, and the noise that matters is the edges'
    outer = np.concatenate([np.diff(rows[:, :w], axis=1), np.diff(rows[:, -w:], axis=1)], axis=1)
    sigma = np.median(np.abs(outer), axis=1) / (0.6745 * math.sqrt(2.0))
    bound = z * sigma / math.sqrt(k)
    return np.abs(rows[:, :k].mean(axis=1)) > bound, np.abs(rows[:, -k:].mean(axis=1)) > bound


def _refuse_non_finite(p: np.ndarray, valid_mask) -> None:
    """ValueError when a pixel that ``valid_mask`` (None: all) counts as valid is NaN or infinite: the
    ramp filter would spread it along the whole row and the back-projection into every voxel it reaches."""
    bad = ~np.isfinite(p)
    if not bad.any():
        return
    if valid_mask is not None:
        bad &= view_mask(valid_mask, p.shape)
    n_bad = int(np.count_nonzero(bad))
    if n_bad:
        raise ValueError(f"{n_bad} projection pixel(s) are NaN or infinite and not excluded by valid_mask; FDK needs "
                         "finite data: mark them False in valid_mask (e.g. valid_mask=np.isfinite(line_integrals)) "
                         "and they are interpolated along their row")


def _edges_are_empty(p: np.ndarray, rel_tol: float = 1e-3) -> bool:
    """True when the first and last detector columns hold (almost) nothing in every row."""
    peak = float(np.max(np.abs(p))) if p.size else 0.0
    edge = max(float(np.max(np.abs(p[..., 0]))), float(np.max(np.abs(p[..., -1]))))
    return edge <= rel_tol * peak


def fdk_filter_projections(line_integrals: np.ndarray, geom: ConeGeometry, *, center_mm=None,
                           axis=None, window: str = "hann", cutoff: float = 1.0,
                           truncation: str | None = "extrapolate", extension: int | None = None,
                           pad_factor: float = 2.0, valid_mask=None, displaced_detector: bool = True,
                           short_scan: bool = True, mu_water_per_mm: float = 0.02,
                           view_chunk: int = 32) -> tuple[np.ndarray, ConeGeometry]:
    """Weighted and ramp-filtered projections ready for :func:`fdk_backproject`.

    Folds in everything that does not depend on the voxel: the generalised cosine weight,
    the angular quadrature, the full-scan 1/2 (or the displaced-detector weights, or on a
    short scan with ``short_scan`` Parker's, :func:`short_scan_weights`), the
    ``D`` of the distance weight and the pixel pitch of the discrete convolution.
    ``extension`` is the number of pixels each row is extended by on each side (default:
    the row length) when ``truncation`` is set and the data are truncated (some edge pixel
    above 1e-3 of the peak), on the edges of the rows that are (their outermost pixels stand
    above the row's noise, :func:`_edge_above_noise`); the FFT length is the next power of two
    >= ``pad_factor * (n_cols + max(extension, margin))``.

    ``center_mm`` (default :func:`scan_centre`, the centre the sources circle) and ``axis`` are the
    scan's, for the angular and redundancy weights.

    Displaced detector: on the inner (short) side the weighted row falls to zero, so it is
    padded with zeros there; the ramp-filtered row is not zero beyond that edge, and voxels
    that project there (seen by the conjugate views) need it, so the filtered rows are
    returned on a detector widened by the largest asymmetry on that side.

    Returns ``(filtered, filtered_geom)``: float32 (n_views, n_rows, n_cols') and the
    geometry of that (possibly widened) detector; same views and pixel pitch.
    """
    if truncation not in (None, "extrapolate", "mirror", "cylinder"):
        raise ValueError(f"truncation must be 'extrapolate', 'mirror', 'cylinder' or None, got {truncation!r}")
    p = np.asarray(line_integrals)
    if p.shape != (geom.n_views,) + geom.det_shape:
        raise ValueError(f"projections must have shape {(geom.n_views,) + geom.det_shape}, got {p.shape}")
    if geom.n_views == 0:
        raise ValueError("FDK needs at least one view, got none")
    valid_mask = None if valid_mask is None else view_mask(valid_mask, p.shape)  # a clear error if it does not fit
    _refuse_non_finite(p, valid_mask)
    if valid_mask is not None:
        p = fill_invalid_pixels(p, valid_mask)
    nv, nr, nc = p.shape
    cm = scan_centre(geom, axis) if center_mm is None else np.asarray(center_mm, dtype=np.float64)

    c0, r0, sdd, w_s = _principal_point(geom)
    parker = short_scan_weights(geom, cm, axis) if short_scan else None
    # an arc of half a turn or less (no Parker weights) measures each ray once at most: weight 1 keeps the
    # density's scale (the full scan's 1/2 per ray pair halved it); what the arc misses stays missing
    once = short_scan and parker is None and geom.n_views >= 3 and scan_arc(geom, cm, axis)[0] <= np.pi
    _, g = fdk_view_weights(geom, cm, axis, short_scan_weighted=parker is not None or once)
    g_u = np.einsum("ij,ij->i", g, geom.u)
    g_w = np.einsum("ij,ij->i", g, w_s)
    if np.any(np.abs(g_u) < 0.5 * np.linalg.norm(g, axis=1)):
        warnings.warn("detector rows (u) are not along the source motion for some views; this filters along u "
                      "(fdk() filters on a virtual detector: fdk_filter_motion_rows)",
                      FDKWarning, stacklevel=2)
    sgn = np.sign(g_u)
    sgn[sgn == 0] = 1.0
    a_mm = (np.arange(nc)[None, :] - c0[:, None]) * geom.col_pitch_mm  # (nv, nc)
    b_mm = (np.arange(nr)[None, :] - r0[:, None]) * geom.row_pitch_mm  # (nv, nr)
    # per ray: (1/2 full scan) * D / depth^2 * |g . theta(a)| (2D fan-beam Jacobian), with the
    # cone-beam form g . theta = (D g_u - a g_w) / sqrt(D^2 + a^2 + b^2); here everything but
    # the 1/depth^2, which the back-projection applies, and 1/col_pitch for the discrete
    # convolution in mm. Ideal circle: R dbeta * D/sqrt(..) * D/depth^2 = FDK's weights.
    lin = sgn[:, None] * (sdd[:, None] * g_u[:, None] - a_mm * g_w[:, None])  # (nv, nc)
    const = sdd * (1.0 if once else 0.5) / geom.col_pitch_mm

    keep_lo = keep_hi = None
    m_lo = m_hi = 0  # output margins (pixels) beyond the low / high column edge
    layout = None
    if displaced_detector:
        layout = displaced_detector_layout(geom, cm, axis=axis)
        side = layout[0]
        if np.any(side != 0):
            keep_lo = np.repeat((side != -1).astype(np.float32), nr)
            keep_hi = np.repeat((side != 1).astype(np.float32), nr)
            asym = np.minimum(np.abs(layout[2]), 3.0 * nc)  # bounded: the centre's image is within a row
            m_lo = int(math.ceil(asym[side == -1].max())) if np.any(side == -1) else 0
            m_hi = int(math.ceil(asym[side == 1].max())) if np.any(side == 1) else 0
            if parker is not None:  # each covers half of the rays' redundancy; both at once is not derived here
                warnings.warn("a short scan with a displaced detector: only the displaced-detector weights are "
                              "applied, and FDK is approximate", FDKWarning, stacklevel=2)
                parker = None
    if parker is not None:
        lin = lin * parker

    ext = 0 if truncation is None else (nc if extension is None else int(extension))
    if ext and _edges_are_empty(p):
        ext = 0  # nothing is truncated: plain zero padding (RTK's filter length)
    if ext and truncation == "cylinder":
        # attenuation per detector pixel of water seen at the scan centre's magnification
        sod = np.abs(np.einsum("ij,ij->i", cm - geom.source_mm, geom.w))
        mu_px = np.repeat(mu_water_per_mm * geom.col_pitch_mm * sod / sdd, nr)
        k_fit = max(2, min(8, nc // 4))
        (vl, sl_), (vr, sr) = _edge_fit(p.reshape(-1, nc).astype(np.float64), k_fit)
        cyl_l = (vl, sl_)
        cyl_r = (vr, sr)
        _, end_l = _cylinder_extension(vl, sl_, mu_px, 1)
        _, end_r = _cylinder_extension(vr, sr, mu_px, 1)
        longest = float(max(end_l.max(), end_r.max()))
        if extension is None:  # as long as the fitted cylinders, within 4 rows
            ext = int(min(4 * nc, max(8, math.ceil(1.34 * longest))))
    span = max(ext, m_lo, m_hi)
    n_fft = 1 << int(math.ceil(math.log2(max(2, pad_factor * (nc + span)))))
    H = ramp_kernel_spectrum(n_fft, window, cutoff).astype(np.float32)
    n_out = nc + m_lo + m_hi
    cols = np.r_[np.arange(n_fft - m_lo, n_fft), np.arange(nc + m_hi)]  # buffer columns kept

    out = np.empty((nv, nr, n_out), dtype=np.float32)
    for v0 in range(0, nv, view_chunk):
        v1 = min(nv, v0 + view_chunk)
        sl = slice(v0, v1)
        inv = 1.0 / np.sqrt(sdd[sl, None, None] ** 2 + a_mm[sl, None, :] ** 2 + b_mm[sl, :, None] ** 2)
        wgt = const[sl, None, None] * lin[sl, None, :] * inv
        red = None if layout is None else displaced_pixel_weights(geom, layout, sl)
        wgt = (wgt if red is None else wgt * red).astype(np.float32)
        rows = (p[sl].astype(np.float32, copy=False) * wgt).reshape(-1, nc)
        rsl = slice(v0 * nr, v1 * nr)
        given = None
        if ext and truncation == "cylinder":
            # raw-data cylinders, scaled by the (slowly varying) weight at each edge
            w2 = wgt.reshape(-1, nc)
            left, _ = _cylinder_extension(cyl_l[0][rsl], cyl_l[1][rsl], mu_px[rsl], ext)
            right, _ = _cylinder_extension(cyl_r[0][rsl], cyl_r[1][rsl], mu_px[rsl], ext)
            given = (left * w2[:, :1], right * w2[:, -1:])
        keep_l = None if keep_lo is None else keep_lo[rsl]
        keep_r = None if keep_hi is None else keep_hi[rsl]
        if ext:
            left_cut, right_cut = _edge_above_noise(rows)
            keep_l = left_cut.astype(np.float32) if keep_l is None else keep_l * left_cut
            keep_r = right_cut.astype(np.float32) if keep_r is None else keep_r * right_cut
        buf = _extend_rows(rows, n_fft, ext, truncation, keep_l, keep_r, given)
        spec = scipy.fft.rfft(buf, axis=1, workers=-1)
        spec *= H
        filt = scipy.fft.irfft(spec, n=n_fft, axis=1, workers=-1)
        filt = filt[:, :nc] if n_out == nc else filt[:, cols]
        out[sl] = filt.reshape(v1 - v0, nr, n_out)
    if n_out == nc:
        return out, geom
    # widened detector: same pixels, grid centre moved by (m_hi - m_lo) / 2 columns
    det = geom.detector_mm + (0.5 * (m_hi - m_lo) * geom.col_pitch_mm) * geom.u
    return out, geom.replace(detector_mm=det, n_cols=n_out)


# --------------------------------------------------------------------- back-projection
@njit(inline="always")
def _in_front_range(aw, bw, n):
    """Real interval [t0, t1] of i in [0, n-1] with aw + i bw > 0: the voxels of a row in front of the
    source (a positive depth). Those at or behind it lie on no ray from the source to the detector, though
    the projection matrix maps them onto it (and a depth of 0 divides by zero)."""
    t0 = 0.0
    t1 = n - 1.0
    if bw > 0:
        t0 = max(t0, -aw / bw + 1e-6)
    elif bw < 0:
        t1 = min(t1, -aw / bw - 1e-6)
    elif aw <= 0:
        t1 = -1.0
    return t0, t1


@njit(inline="always")
def _clip_linear(m, k, t0, t1):
    """[t0, t1] narrowed to the i with m + i k >= 0 (empty: t1 = -1)."""
    if k > 0:
        t0 = max(t0, -m / k)
    elif k < 0:
        t1 = min(t1, -m / k)
    elif m < 0:
        t1 = -1.0
    return t0, t1


@njit(inline="always")
def _affine_ratio_range(a, b, aw, bw, lo, hi, n):
    """Real interval [t0, t1] of i in [0, n-1] with lo <= (a + i b) / (aw + i bw) <= hi, for the
    i where the denominator (a voxel's depth) is positive (:func:`_in_front_range` bounds them):
    each bound is then a linear inequality in i.
    """
    t0, t1 = _clip_linear(a - lo * aw, b - lo * bw, 0.0, n - 1.0)  # (a - lo aw) + i (b - lo bw) >= 0
    return _clip_linear(hi * aw - a, hi * bw - b, t0, t1)  # (hi aw - a) + i (hi bw - b) >= 0


@njit(parallel=True, fastmath=True, cache=True)
def _fdk_backproject_kernel(q, pm, vol, ox, oy, oz, dx, dy, dz, view_chunk):
    """vol[k, j, i] += sum_views bilinear(q[view], P @ x) / depth^2.

    Parallel over (k, j) voxel rows, so each thread owns its output row (no write races);
    views are processed in chunks so the chunk's projections stay in cache across rows.
    P @ x is affine in i: each row evaluates numerator/denominator as a + i * b, and the
    range of i that projects onto the detector is solved for up front, so the inner loop
    is branch-free with unsigned flat indices and vectorises (AVX gathers).
    A one-row (fan-beam) or one-column detector has no neighbour to interpolate with: its
    step to the next row (column) is 0, so the "bilinear" value is the pixel's own, and a
    voxel gets it where it projects within half a pixel of that row (the slab the row sees).
    """
    nz, ny, nx = vol.shape
    nv, nr, nc = q.shape
    qf = q.reshape(nv * nr * nc)
    volf = vol.reshape(nz * ny * nx)
    cmax = np.float32(nc - 1)
    rmax = np.float32(nr - 1)
    zero = np.float32(0.0)
    ncm2 = np.uint32(max(nc - 2, 0))
    nrm2 = np.uint32(max(nr - 2, 0))
    unc = np.uint64(nc) if nr > 1 else np.uint64(0)  # step to the next row (none on one row)
    one = np.uint64(1) if nc > 1 else np.uint64(0)  # step to the next column
    n_rows_vox = nz * ny
    for v0 in range(0, nv, view_chunk):
        v1 = min(nv, v0 + view_chunk)
        for t in prange(n_rows_vox):
            k = t // ny
            j = t - k * ny
            z = oz + k * dz
            y = oy + j * dy
            rowbase = np.uint64(t * nx)
            for v in range(v0, v1):
                au = pm[v, 0, 0] * ox + pm[v, 0, 1] * y + pm[v, 0, 2] * z + pm[v, 0, 3]
                av = pm[v, 1, 0] * ox + pm[v, 1, 1] * y + pm[v, 1, 2] * z + pm[v, 1, 3]
                aw = pm[v, 2, 0] * ox + pm[v, 2, 1] * y + pm[v, 2, 2] * z + pm[v, 2, 3]
                bu = pm[v, 0, 0] * dx
                bv = pm[v, 1, 0] * dx
                bw = pm[v, 2, 0] * dx
                # voxels whose projection lies on the detector (pixel centres +- 1/2)
                l0, h0 = _in_front_range(aw, bw, nx)
                l1, h1 = _affine_ratio_range(au, bu, aw, bw, -0.5, nc - 0.5, nx)
                l2, h2 = _affine_ratio_range(av, bv, aw, bw, -0.5, nr - 0.5, nx)
                # clamp in floating point before converting: a view nearly parallel to a grid axis gives
                # bounds near +-1e19, whose int() would overflow and wrap the loop's trip count
                i0 = int(math.ceil(min(max(max(l0, l1, l2), 0.0), nx * 1.0)))
                i1 = int(math.floor(max(min(min(h0, h1, h2), nx - 1.0), -1.0))) + 1
                fau = np.float32(au)
                fbu = np.float32(bu)
                fav = np.float32(av)
                fbv = np.float32(bv)
                faw = np.float32(aw)
                fbw = np.float32(bw)
                vbase = np.uint64(v * nr * nc)
                for i in range(i0, i1):
                    fi = np.float32(i)
                    inv = np.float32(1.0) / (faw + fi * fbw)
                    c = min(max((fau + fi * fbu) * inv, zero), cmax)
                    r = min(max((fav + fi * fbv) * inv, zero), rmax)
                    ic = min(np.uint32(c), ncm2)
                    ir = min(np.uint32(r), nrm2)
                    fc = c - np.float32(ic)
                    fr = r - np.float32(ir)
                    b0 = vbase + np.uint64(ir) * unc + np.uint64(ic)
                    q00 = qf[b0]
                    q01 = qf[b0 + one]
                    q10 = qf[b0 + unc]
                    q11 = qf[b0 + unc + one]
                    top = q00 + fc * (q01 - q00)
                    bot = q10 + fc * (q11 - q10)
                    volf[rowbase + np.uint64(i)] += (top + fr * (bot - top)) * inv * inv


def fdk_backproject(filtered: np.ndarray, geom: ConeGeometry, grid: VolumeGrid,
                    view_chunk: int = 16) -> np.ndarray:
    """Voxel-driven FDK back-projection: sum over views of bilinear(filtered) / depth^2.

    ``depth`` is the distance of the voxel from the source along the detector normal
    (third row of ``geom.projection_matrices()``). Pixels are sampled with bilinear
    interpolation; voxels projecting outside the detector, and voxels at or behind the source
    (a grid reaching past the source), receive nothing from that view.
    A one-row detector (fan beam) back-projects onto the voxels within half a pixel of its
    row's plane: the slice(s) it sees; the grid may be one voxel thick.
    """
    q = np.ascontiguousarray(filtered, dtype=np.float32)
    if q.shape != (geom.n_views,) + geom.det_shape:
        raise ValueError(f"filtered projections must have shape {(geom.n_views,) + geom.det_shape}")
    # express P in the grid's own frame, relative to its centre: axis-aligned voxels, and small
    # numbers for float32
    centre = grid.center_mm
    T = np.eye(4)
    T[:3, :3] = grid.direction_matrix
    T[:3, 3] = centre
    pm = geom.projection_matrices() @ T
    # P's scale sign follows w's; flipped so that lambda > 0 in front of the source in every view (the kernel's test)
    pm *= np.sign(np.einsum("ij,ij->i", geom.detector_mm - geom.source_mm, geom.w))[:, None, None]
    pm = np.ascontiguousarray(pm)
    origin = -0.5 * (np.array(grid.shape_xyz) - 1) * np.asarray(grid.voxel_size_mm)
    dx, dy, dz = grid.voxel_size_mm
    vol = np.zeros(grid.shape_zyx, dtype=np.float32)
    _fdk_backproject_kernel(q, pm, vol, float(origin[0]), float(origin[1]), float(origin[2]),
                            float(dx), float(dy), float(dz), int(view_chunk))
    return vol


def fdk_filter_motion_rows(line_integrals: np.ndarray, geom: ConeGeometry, *, center_mm=None, axis=None,
                           valid_mask=None, tol_deg: float = DEFAULT_TOL_DEG, **filter_kwargs):
    """:func:`fdk_filter_projections` with the rows along the source
    motion: the data as they are where every view's rows are within ``tol_deg`` of it (the very same
    call), else on the virtual detector of :func:`~robot_ct_ros.ct.virtual_detector.align_rows_to_motion`, its filtered pixels beyond the
    real detector's edges set to 0 (FDK back-projects nothing from beyond a detector's edge; columns
    the filter adds for a displaced detector are kept). Returns ``(filtered, filtered_geom)`` as
    ``fdk_filter_projections`` does; ``filtered_geom`` is then the virtual detector's."""
    virt = align_rows_to_motion(line_integrals, geom, center_mm, axis, valid_mask, tol_deg)
    if virt is None:
        return fdk_filter_projections(line_integrals, geom, center_mm=center_mm, axis=axis,
                                      valid_mask=valid_mask, **filter_kwargs)
    if filter_kwargs.get("displaced_detector", True):
        cm = scan_centre(virt.geom, axis) if center_mm is None else np.asarray(center_mm, dtype=np.float64)
        if np.any(displaced_detector_layout(virt.geom, cm, axis=axis)[0] != 0) \
                and outside_footprint(virt.geom, virt.original).any():
            warnings.warn("a displaced detector turned in its plane: its redundancy weights are taken on the "
                          "virtual detector, which reaches beyond the real one, and FDK is approximate",
                          FDKWarning, stacklevel=3)
    q, q_geom = fdk_filter_projections(virt.projections, virt.geom, center_mm=center_mm, axis=axis,
                                       valid_mask=virt.valid_mask, **filter_kwargs)
    q[outside_footprint(q_geom, virt.original) & ~outside_footprint(q_geom, virt.geom)] = 0.0
    return q, q_geom


def fdk(line_integrals: np.ndarray, geom: ConeGeometry, grid: VolumeGrid, *, window: str = "hann",
        cutoff: float = 1.0, truncation: str | None = "extrapolate", extension: int | None = None,
        pad_factor: float = 2.0, valid_mask=None, displaced_detector: bool = True, short_scan: bool = True,
        mu_water_per_mm: float = 0.02, center_mm=None, axis=None) -> np.ndarray:
    """FDK reconstruction (float32, ``grid.shape_zyx``) from line integrals for any per-view geometry.

    Where the detector rows of some view are more than 3 degrees off the source motion projected
    onto the detector (a detector rolled in its own plane, or a portrait one), the projections are
    first resampled (bilinear) onto a virtual detector in the same plane whose rows follow the motion
    (:mod:`robot_ct_ros.ct.virtual_detector`); other scans are filtered as they are.

    Parameters
    ----------
    line_integrals : (n_views, n_rows, n_cols) projections, see geometry.py conventions.
    geom, grid : per-view geometry and the (ROI) volume grid to reconstruct.
    window, cutoff : apodisation of the ramp (one of ``WINDOWS``) and its cut-off as a
        fraction of Nyquist.
    truncation : ``"extrapolate"`` (point-symmetric continuation, cosine taper),
        ``"mirror"`` (symmetric mirror capped at the edge value, cosine taper) or None (zero
        padding, as plain FDK and RTK), or ``"cylinder"``: per row, the chord profile of a
        water cylinder (``mu_water_per_mm``) matching the value and slope at the edge
        (Hsieh et al. 2004), for objects much larger than the field of view. Skipped when
        no detector edge pixel exceeds 1e-3 of the peak (object inside the field of view).
    extension : pixels added on each side of a row when handling truncation (default n_cols;
        for ``"cylinder"`` the length of the longest fitted cylinder, at most 4 n_cols).
    pad_factor : FFT length = next power of two >= pad_factor * (n_cols + extension).
    valid_mask : boolean (n_rows, n_cols) or (n_views, n_rows, n_cols), True = good pixel;
        bad pixels are interpolated along the row before filtering. A NaN or infinite pixel
        that the mask does not exclude raises ValueError.
    displaced_detector : apply redundancy weights (:func:`displaced_detector_weights`) in the
        views where the detector reaches further on one side of the scan centre than on the
        other (offset-detector ROI scans); centred views are unaffected.
    short_scan : on an arc short of a full turn, apply Parker's weights
        (:func:`short_scan_weights`) in place of the full scan's 1/2 per ray pair.
    center_mm, axis : scan centre and axis for the angular and redundancy weights (default:
        the centre of the circle the sources describe, :func:`estimate_scan_centre` (the grid
        centre where the geometry tells none), and the normal of the plane fitted to the source
        positions). Not the grid centre: a grid off the axis would make a centred detector look
        displaced, and its redundancy weights would ruin a full scan.
    """
    c = scan_centre(geom, axis, grid.center_mm) if center_mm is None else center_mm
    # rows not along the source motion (a detector rolled in its plane): filtered on a virtual detector
    q, q_geom = fdk_filter_motion_rows(line_integrals, geom, center_mm=c, axis=axis, window=window,
                                       cutoff=cutoff, truncation=truncation, extension=extension,
                                       pad_factor=pad_factor, valid_mask=valid_mask,
                                       displaced_detector=displaced_detector, short_scan=short_scan,
                                       mu_water_per_mm=mu_water_per_mm)
    vol = fdk_backproject(q, q_geom, grid)
    warn_if_empty(vol, q, geom)
    return vol


def warn_if_empty(vol: np.ndarray, filtered: np.ndarray, geom: ConeGeometry) -> None:
    """:class:`FDKWarning` where the back-projection of ``filtered`` (not all zero) put nothing into ``vol``: any
    executor's :func:`fdk` says it alike."""
    if not vol.any() and np.any(filtered):
        # not an error (a slab beyond the cone's ends is legitimately empty), but nothing of the data is in it
        hint = (": a one-row detector back-projects onto the voxels within half a pixel of its plane, and no voxel "
                "centre lies there (a grid one slice thick, or an odd number of slices centred on the row, has one)"
                if geom.n_rows == 1 else ": the grid lies outside every view's cone")
        warnings.warn(f"FDK put nothing into the grid{hint}", FDKWarning, stacklevel=3)


def resample(volume: np.ndarray, src: VolumeGrid, dst: VolumeGrid) -> np.ndarray:
    """Trilinear resampling of ``volume`` (on ``src``) at the voxel centres of ``dst``.

    The grids may have any directions; a ``dst`` voxel outside ``src`` takes the nearest border
    value (a coarse grid covering the same box as a fine one has its outer voxel centres half a
    coarse voxel inside the box).
    """
    # src index = A @ dst index + b, in (x, y, z) order; affine_transform works in (z, y, x)
    A = (src.direction_matrix.T @ dst.direction_matrix) * np.asarray(dst.voxel_size_mm)[None, :] \
        / np.asarray(src.voxel_size_mm)[:, None]
    b = src.world_to_index(dst.origin_mm)
    out = ndimage.affine_transform(np.asarray(volume, dtype=np.float32), A[::-1, ::-1], offset=b[::-1],
                                   output_shape=dst.shape_zyx, order=1, mode="nearest")
    return out.astype(np.float32, copy=False)
