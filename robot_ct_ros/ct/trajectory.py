"""Nominal scan trajectories: circular scans and the seed system's patient-centred robotic ROI scan.

Conventions are those of :mod:`robot_ct_ros.ct.geometry`. Every trajectory here is built by
the same orbit rule, stated once:

* The orbit turns about the unit ``axis`` through ``center_mm``. ``e1`` is the direction of
  the source at angle 0: world +x projected off the axis (world +y if the axis is along x);
  ``e2 = axis x e1``, so angles increase counter-clockwise seen from the tip of ``axis``.
* A full circle (``arc_rad`` of 2 pi or more) puts view k at ``theta_k = start_rad + k * arc_rad /
  n_views``: the last view does not repeat the first. A partial arc (a short scan) spans the whole
  arc asked for: ``theta_k = start_rad + k * arc_rad / (n_views - 1)``, the first view at
  ``start_rad``, the last at ``start_rad + arc_rad``.
  The source sits at ``center + sod * w``, ``w = cos(theta) e1 + sin(theta) e2``, on the
  central ray pointing from the detector to the source; the detector is perpendicular to
  the central ray at ``center - (sdd - sod) * w``, shifted by ``det_offset_u_mm`` along u.
* ``v = axis`` (detector rows are stacked along the axis) and ``u = v x w``, so that
  ``u x v = w`` points from the detector towards the source, as RTK's detector normal does
  for positive SID/SDD. Seen from the source, u points right and v up.

For the default ``axis=(0, 0, 1)`` the source starts on +x, u = +y, v = +z; for
``axis=(0, 1, 0)`` the source starts on +x as well and v = +y (RTK's rotation axis, needed
by RTK's FDK).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .geometry import ConeGeometry

__all__ = ["circular_scan", "SeedSystem", "fov_radius_mm", "detector_edge_for_fov_mm", "roi_scan_offset_mm",
           "robotic_roi_scan"]


def _orbit_frame(axis) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(axis, dtype=np.float64).reshape(3)
    norm = np.linalg.norm(a)
    if not np.isfinite(norm) or norm == 0:
        raise ValueError(f"axis must be a non-zero finite vector, got {axis!r}")
    a = a / norm
    ref = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ a) * a
    e1 /= np.linalg.norm(e1)
    return a, e1, np.cross(a, e1)


def circular_scan(n_views: int, sod_mm: float, sdd_mm: float, n_rows: int, n_cols: int,
                  row_pitch_mm: float, col_pitch_mm: float, arc_rad: float = 2 * math.pi,
                  start_rad: float = 0.0, det_offset_u_mm: float = 0.0, center_mm=(0.0, 0.0, 0.0),
                  axis=(0.0, 0.0, 1.0)) -> ConeGeometry:
    """A circular cone-beam scan about ``axis`` through ``center_mm`` (see the module docstring).

    ``sod_mm`` is the source to rotation-centre distance, ``sdd_mm`` the source to detector
    distance (magnification ``sdd/sod`` at the centre). ``det_offset_u_mm`` shifts the
    detector along u (offset detector): the centre then projects onto column
    ``(n_cols - 1)/2 - det_offset_u_mm / col_pitch_mm`` in every view.
    """
    if n_views < 1:
        raise ValueError("n_views must be positive")
    if not (0 < sod_mm < sdd_mm):
        raise ValueError(f"need 0 < sod_mm < sdd_mm, got sod={sod_mm}, sdd={sdd_mm}")
    a, e1, e2 = _orbit_frame(axis)
    c = np.asarray(center_mm, dtype=np.float64).reshape(3)
    full = abs(arc_rad) >= 2 * math.pi - 1e-12  # either sense of rotation
    theta = start_rad + arc_rad * np.arange(n_views) / (n_views if full else max(n_views - 1, 1))
    w = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    v = np.broadcast_to(a, w.shape)
    u = np.cross(v, w)
    src = c + sod_mm * w
    det = c - (sdd_mm - sod_mm) * w + det_offset_u_mm * u
    return ConeGeometry(source_mm=src, detector_mm=det, u=u, v=v, n_rows=n_rows, n_cols=n_cols,
                        row_pitch_mm=row_pitch_mm, col_pitch_mm=col_pitch_mm)


# ---------------------------------------------------------------- seed system
@dataclass(frozen=True)
class SeedSystem:
    """Figures of the seed robotic micro-CT (Li et al., arXiv 2406.18063).

    Detector: photon counting, 70 x 30 mm^2 active area (u along the 70 mm side), 55 um raw
    pixels read out 2 x 2 binned (110 um). Source to detector 342.4 mm at magnification
    2.67 at the ROI centre; 360 views per scan; offset detector for a field of view up to 50 mm.
    """

    sdd_mm: float = 342.4
    magnification: float = 2.67
    detector_width_mm: float = 70.0   # along u (transaxial)
    detector_height_mm: float = 30.0  # along v (axial)
    raw_pixel_mm: float = 0.055
    binning: int = 2
    n_views: int = 360
    max_fov_diameter_mm: float = 50.0

    @property
    def sod_mm(self) -> float:
        """Source to ROI-centre distance, ``sdd / magnification`` (about 128.2 mm)."""
        return self.sdd_mm / self.magnification

    @property
    def n_cols_raw(self) -> int:
        return int(math.floor(self.detector_width_mm / self.raw_pixel_mm + 1e-9))

    @property
    def n_rows_raw(self) -> int:
        return int(math.floor(self.detector_height_mm / self.raw_pixel_mm + 1e-9))


def fov_radius_mm(edge_u_mm: float, sod_mm: float, sdd_mm: float) -> float:
    """Radius of the circle about the rotation centre whose tangent rays hit the detector at ``edge_u_mm``.

    Exact for a flat detector perpendicular to the central ray: ``r = sod * t / sqrt(sdd^2 + t^2)``
    with ``t = edge_u_mm``; the paraxial approximation is ``t / M``, M = sdd / sod.
    """
    return sod_mm * edge_u_mm / math.hypot(sdd_mm, edge_u_mm)


def detector_edge_for_fov_mm(fov_radius: float, sod_mm: float, sdd_mm: float) -> float:
    """Inverse of :func:`fov_radius_mm`: detector coordinate ``t = sdd * r / sqrt(sod^2 - r^2)``."""
    if not 0 <= fov_radius < sod_mm:
        raise ValueError(f"the FOV radius {fov_radius:g} mm must lie in [0, sod = {sod_mm:g} mm)")
    return sdd_mm * fov_radius / math.sqrt(sod_mm ** 2 - fov_radius ** 2)


def roi_scan_offset_mm(fov_diameter_mm: float, half_width_mm: float, sod_mm: float, sdd_mm: float) -> float:
    """Smallest lateral detector offset along u giving a full-scan FOV of ``fov_diameter_mm``.

    Zero when the centred detector already covers it; raises ``ValueError`` when the
    required offset exceeds the half width (the central ray would leave the detector).
    """
    t = detector_edge_for_fov_mm(0.5 * fov_diameter_mm, sod_mm, sdd_mm)
    offset = max(0.0, t - half_width_mm)
    if offset > half_width_mm + 1e-12:
        raise ValueError(f"a {fov_diameter_mm} mm FOV needs a detector offset of {offset:.2f} mm, more than "
                         f"the half width {half_width_mm:.2f} mm (max FOV "
                         f"{2 * fov_radius_mm(2 * half_width_mm, sod_mm, sdd_mm):.2f} mm)")
    return offset


def robotic_roi_scan(system: SeedSystem = SeedSystem(), roi_center_mm=(0.0, 0.0, 0.0),
                     fov_diameter_mm: float = 50.0, n_views: int | None = None, binning: int | None = None,
                     axis=(0.0, 0.0, 1.0), n_rows: int | None = None, n_cols: int | None = None,
                     arc_rad: float = 2 * math.pi, start_rad: float = 0.0) -> ConeGeometry:
    """The seed system's patient-centred ROI scan (nominal geometry).

    The source always faces the ROI centre at ``system.sod_mm`` and the detector follows on
    the far side, perpendicular to the central ray at ``system.sdd_mm``, so the magnification
    at the ROI centre is constant (``system.magnification``); the orbit is the circle of
    :func:`circular_scan` about ``axis`` through ``roi_center_mm``.

    Offset detector: the detector (half width ``h = n_cols * pitch / 2``) is shifted by
    ``o >= 0`` along +u. With full 360 degree coverage every line through a point at
    distance r from the ROI centre is measured, in one view or its conjugate, iff the tangent
    ray of the circle of radius r hits the detector within ``t = h + o`` of the central ray,
    as long as the central ray stays on the detector (``o <= h``). Hence the transaxial FOV
    radius is ``r = sod * t / sqrt(sdd^2 + t^2)`` (paraxially ``(h + o) / M``), and the offset
    chosen is the smallest one reaching ``fov_diameter_mm``: ``o = max(0, sdd r / sqrt(sod^2 - r^2) - h)``
    (see :func:`roi_scan_offset_mm`). The full seed detector (h = 34.98 mm) needs o = 33.1 mm
    for 50 mm. The ROI centre projects onto column ``(n_cols - 1)/2 - o / pitch``.

    ``binning`` (default ``system.binning``) sets pitch ``raw_pixel_mm * binning`` and the
    full detector's ``n_raw // binning`` pixels; ``n_rows`` / ``n_cols`` override the pixel
    counts (a reduced detector for fast tests and demos; the FOV shrinks with it).
    """
    n_views = system.n_views if n_views is None else n_views
    binning = system.binning if binning is None else binning
    if binning < 1:
        raise ValueError("binning must be >= 1")
    pitch = system.raw_pixel_mm * binning
    n_cols = system.n_cols_raw // binning if n_cols is None else n_cols
    n_rows = system.n_rows_raw // binning if n_rows is None else n_rows
    offset = roi_scan_offset_mm(fov_diameter_mm, 0.5 * n_cols * pitch, system.sod_mm, system.sdd_mm)
    return circular_scan(n_views, system.sod_mm, system.sdd_mm, n_rows, n_cols, pitch, pitch,
                         arc_rad=arc_rad, start_rad=start_rad, det_offset_u_mm=offset,
                         center_mm=roi_center_mm, axis=axis)
