"""Virtual detector for FDK: detector rows turned along the source motion.

FDK's ramp filter runs along the detector rows (u). That is FDK only when the rows follow the
direction in which the source moves, projected onto the detector plane; a detector rolled in
its own plane (by a few degrees, or a "portrait" detector whose columns run along the scan
axis, which the bag format allows) filters across the wrong direction and the volume comes out
wrong (at 90 degrees: nothing at all).

:func:`align_rows_to_motion` measures, per view, the angle between u and the source motion
``g`` (:func:`robot_ct_ros.ct.scan_weights.fdk_view_weights`) projected into the detector plane.
Where some view's roll exceeds ``tol_deg``, every view is resampled (bilinear, float32) onto a
virtual detector in the same plane about the same centre, with square pixels of the smaller
pitch, its rows u' along the projected motion (the sign that keeps u' closest to u; views within
the tolerance keep u' = u) and ``v' = w x u'``, so (u', v', w) is right-handed like the original
frame and w is unchanged. It is one size for all views, large enough to hold the whole original
detector in every view; its pixels outside the original detector (or fed by a bad pixel) are
marked invalid, and :func:`robot_ct_ros.ct.reconstruction.fill_invalid_pixels` interpolates them
along the virtual rows before filtering (:func:`robot_ct_ros.ct.reconstruction.fdk_filter_motion_rows`,
which :func:`~robot_ct_ros.ct.reconstruction.fdk` calls). Nothing here assumes an axis or a world frame.

A one-row (fan-beam) or one-column detector is left as it is: its single row defines the fan.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from robot_ct_ros.ct.geometry import ConeGeometry, view_mask
from robot_ct_ros.ct.scan_weights import FDKWarning, fdk_view_weights

__all__ = ["VirtualDetector", "row_roll_deg", "align_rows_to_motion", "outside_footprint"]

DEFAULT_TOL_DEG = 3.0
"""Largest roll (degrees) between the detector rows and the projected source motion that FDK
filters along the rows as they are. The resampling blurs like a bilinear shift of the data by a
fraction of a pixel; on the tests' phantom that costs about as much as filtering along rows rolled
by 5 degrees, and more below (a calibrated detector's roll error is a fraction of a degree)."""


def _motion_in_plane(geom: ConeGeometry, center_mm, axis) -> np.ndarray:
    """Unit source-motion direction per view projected into the detector plane, (n_views, 3);
    zero rows where the motion is (numerically) along the normal or absent."""
    _, g = fdk_view_weights(geom, center_mm, axis, short_scan_weighted=True)  # its warnings come from FDK
    w = geom.w
    gp = g - np.einsum("ij,ij->i", g, w)[:, None] * w
    n = np.linalg.norm(gp, axis=1)
    ok = n > 1e-9 * np.maximum(np.linalg.norm(g, axis=1), 1e-300)
    out = np.zeros_like(gp)
    out[ok] = gp[ok] / n[ok, None]
    return out


def row_roll_deg(geom: ConeGeometry, center_mm=None, axis=None) -> np.ndarray:
    """Per view, the angle (degrees, 0 to 90) between the detector rows (u) and the line of the
    source motion projected into the detector plane (0 where the motion is not defined)."""
    gh = _motion_in_plane(geom, center_mm, axis)
    c = np.abs(np.einsum("ij,ij->i", gh, geom.u))
    roll = np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))
    roll[np.linalg.norm(gh, axis=1) == 0] = 0.0
    return roll


@dataclass(frozen=True)
class VirtualDetector:
    """Projections resampled onto the virtual detector: ``projections`` float32 (n_views, n_rows',
    n_cols'), ``geom`` its geometry, ``valid_mask`` bool (same shape, True = inside the original
    detector and fed by good pixels), ``original`` the geometry it came from."""

    projections: np.ndarray
    geom: ConeGeometry
    valid_mask: np.ndarray
    original: ConeGeometry


@njit(parallel=True, cache=True)
def _resample_kernel(p, valid, A, out, out_valid):
    """out[i, r', c'] = bilinear p[i] at (col, row) = A[i] @ (c', r', 1), pixel indices.

    Positions within half a pixel beyond the outer pixel centres take the edge value; beyond
    that, and where a neighbour with a non-zero weight is invalid, the output is 0 and invalid.
    Positions within 1e-6 pixel of a pixel centre take that pixel (a bad neighbour does not spread
    through a weight of rounding size)."""
    nv, nr, nc = p.shape
    _, nr2, nc2 = out.shape
    for t in prange(nv * nr2):
        i = t // nr2
        r2 = t - i * nr2
        for c2 in range(nc2):
            x = A[i, 0, 0] * c2 + A[i, 0, 1] * r2 + A[i, 0, 2]
            y = A[i, 1, 0] * c2 + A[i, 1, 1] * r2 + A[i, 1, 2]
            if not (-0.5 <= x <= nc - 0.5 and -0.5 <= y <= nr - 0.5):
                out[i, r2, c2] = 0.0
                out_valid[i, r2, c2] = False
                continue
            if abs(x - round(x)) < 1e-6:  # on a pixel centre (up to rounding): that pixel alone
                x = round(x)
            if abs(y - round(y)) < 1e-6:
                y = round(y)
            x = min(max(x, 0.0), nc - 1.0)
            y = min(max(y, 0.0), nr - 1.0)
            x0 = min(int(x), nc - 2)
            y0 = min(int(y), nr - 2)
            fx = x - x0
            fy = y - y0
            acc = 0.0
            ok = True
            for dy in range(2):
                wy = fy if dy == 1 else 1.0 - fy
                if wy <= 0.0:
                    continue
                for dx in range(2):
                    wx = fx if dx == 1 else 1.0 - fx
                    if wx <= 0.0:
                        continue
                    if valid[i, y0 + dy, x0 + dx]:
                        acc += wx * wy * p[i, y0 + dy, x0 + dx]
                    else:
                        ok = False
            out[i, r2, c2] = acc if ok else 0.0
            out_valid[i, r2, c2] = ok


def _pixel_maps(src: ConeGeometry, dst: ConeGeometry) -> np.ndarray:
    """(n_views, 2, 3): (col, row) on ``src`` of pixel (c', r') of ``dst``, an affine map per view
    (both detectors in one plane)."""
    cu, cv = 0.5 * (dst.n_cols - 1), 0.5 * (dst.n_rows - 1)
    off = dst.detector_mm - src.detector_mm
    A = np.empty((src.n_views, 2, 3))
    for k, (axis, pitch, n) in enumerate(((src.u, src.col_pitch_mm, src.n_cols),
                                          (src.v, src.row_pitch_mm, src.n_rows))):
        a = np.einsum("ij,ij->i", dst.u, axis) * dst.col_pitch_mm / pitch
        b = np.einsum("ij,ij->i", dst.v, axis) * dst.row_pitch_mm / pitch
        A[:, k, 0] = a
        A[:, k, 1] = b
        A[:, k, 2] = 0.5 * (n - 1) + np.einsum("ij,ij->i", off, axis) / pitch - a * cu - b * cv
    return A


def _covering(extent_px: float, n_like: int) -> int:
    """Smallest pixel count >= ``extent_px`` (and >= 2) of the parity of ``n_like``."""
    n = max(2, int(math.ceil(extent_px - 1e-6)))
    return n + ((n - n_like) % 2)


def align_rows_to_motion(line_integrals: np.ndarray, geom: ConeGeometry, center_mm=None, axis=None,
                         valid_mask=None, tol_deg: float = DEFAULT_TOL_DEG) -> VirtualDetector | None:
    """The projections on a virtual detector whose rows follow the source motion (module
    docstring), or None when every view's rows are within ``tol_deg`` of it (or the detector has
    one row or one column): then FDK filters the data as they are."""
    if geom.n_views == 0:
        return None
    gh = _motion_in_plane(geom, center_mm, axis)
    cos_r = np.einsum("ij,ij->i", gh, geom.u)
    roll = np.degrees(np.arccos(np.clip(np.abs(cos_r), 0.0, 1.0)))
    turn = (roll > tol_deg) & (np.linalg.norm(gh, axis=1) > 0)
    if not np.any(turn):
        return None
    if geom.n_rows < 2 or geom.n_cols < 2:  # nothing to resample onto: a rolled row's rays leave the fan plane
        warnings.warn(f"a one-{'row' if geom.n_rows < 2 else 'column'} detector up to {roll[turn].max():.1f} degrees "
                      "off the source motion: its rays leave the plane of the slice FDK reconstructs, which it "
                      "filters as they are: FDK is approximate", FDKWarning, stacklevel=3)
        return None
    # u' = +-g: the sign closer to u; at a quarter turn (a tie, up to rounding) the one along -v,
    # so that (u', v') = (-v, u): the portrait detector (u, v) = (v0, -u0) gives back (u0, v0)
    tie = np.abs(cos_r) < 1e-6
    sgn = np.where(tie, np.where(np.einsum("ij,ij->i", gh, geom.v) > 0, -1.0, 1.0), np.where(cos_r < 0, -1.0, 1.0))
    u2 = np.where(turn[:, None], sgn[:, None] * gh, geom.u)
    u2 = u2 - np.einsum("ij,ij->i", u2, geom.w)[:, None] * geom.w  # exactly in the plane
    u2 /= np.linalg.norm(u2, axis=1, keepdims=True)
    cos_t, sin_t = np.abs(np.einsum("ij,ij->i", u2, geom.u)), np.abs(np.einsum("ij,ij->i", u2, geom.v))
    W, H = geom.n_cols * geom.col_pitch_mm, geom.n_rows * geom.row_pitch_mm
    with np.errstate(divide="ignore"):
        chord = np.minimum(W / cos_t, H / sin_t)  # the virtual row through the centre, inside the real detector
    if np.any(turn & (chord < 0.5 * (W * cos_t + H * sin_t))):
        # a detector too short for its roll (a few rows): the virtual rows would end at its top and bottom edges,
        # cut to less than half its reach along them, and their fill would cost more than the roll does
        warnings.warn(f"detector rows up to {roll.max():.1f} degrees off the source motion, on a detector too "
                      "short to filter along the motion (its rows are filtered as they are): FDK is approximate",
                      FDKWarning, stacklevel=3)
        return None
    v2 = np.cross(geom.w, u2)
    pitch = min(geom.row_pitch_mm, geom.col_pitch_mm)
    # extent of the original detector (edge to edge) along u' and v', largest over the views
    eu = np.max(W * np.abs(np.einsum("ij,ij->i", u2, geom.u)) + H * np.abs(np.einsum("ij,ij->i", u2, geom.v)))
    ev = np.max(W * np.abs(np.einsum("ij,ij->i", v2, geom.u)) + H * np.abs(np.einsum("ij,ij->i", v2, geom.v)))
    # sizes of the parity of the original pixels they mostly run along (the virtual pixel centres
    # then fall on the original ones for small and quarter-turn rolls at the same pitch)
    along_u = np.median(np.abs(np.einsum("ij,ij->i", u2, geom.u))) >= math.sqrt(0.5)
    n_cols = _covering(eu / pitch, geom.n_cols if along_u else geom.n_rows)
    n_rows = _covering(ev / pitch, geom.n_rows if along_u else geom.n_cols)
    vgeom = geom.replace(u=u2, v=v2, n_rows=n_rows, n_cols=n_cols, row_pitch_mm=pitch, col_pitch_mm=pitch)

    p = np.ascontiguousarray(line_integrals, dtype=np.float32)
    if p.shape != (geom.n_views,) + geom.det_shape:
        raise ValueError(f"projections must have shape {(geom.n_views,) + geom.det_shape}, got {p.shape}")
    mask = np.ascontiguousarray(view_mask(valid_mask, p.shape))
    out = np.empty((geom.n_views, n_rows, n_cols), np.float32)
    out_valid = np.empty(out.shape, bool)
    _resample_kernel(p, mask, _pixel_maps(geom, vgeom), out, out_valid)
    return VirtualDetector(out, vgeom, out_valid, geom)


def outside_footprint(geom: ConeGeometry, original: ConeGeometry) -> np.ndarray:
    """Bool (n_views, n_rows, n_cols) of ``geom``'s pixels (a detector in the plane of
    ``original``'s, such as the virtual one) whose centres lie beyond the edges of ``original``'s
    pixels: FDK back-projects nothing from there, as from beyond a real detector's edge."""
    A = _pixel_maps(original, geom)
    c = np.arange(geom.n_cols)[None, None, :]
    r = np.arange(geom.n_rows)[None, :, None]
    x = A[:, 0, 0, None, None] * c + A[:, 0, 1, None, None] * r + A[:, 0, 2, None, None]
    y = A[:, 1, 0, None, None] * c + A[:, 1, 1, None, None] * r + A[:, 1, 2, None, None]
    return ~((x >= -0.5) & (x <= original.n_cols - 0.5) & (y >= -0.5) & (y <= original.n_rows - 0.5))
