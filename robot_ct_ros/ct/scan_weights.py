"""The weights FDK gives each view and ray for any per-view cone-beam geometry: the scan's axis and each
view's angular quadrature, and the redundancy weights of an offset (displaced) detector and of a short scan.

Conventions (world mm/rad, ``proj[view, row, col]``) are those of :mod:`robot_ct_ros.ct.geometry`. Angles about the
scan's axis count counter-clockwise about it; the scan centre is the point the source circles (FDK takes it from the
geometry, :func:`estimate_scan_centre`, not from the grid, which may sit anywhere). Redundancy weights sum to 2 over a ray and its conjugate, in place of the full circle's 1/2 per
ray pair (:mod:`robot_ct_ros.ct.reconstruction` applies them).
"""

from __future__ import annotations

import warnings

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry

__all__ = ["FDKWarning", "estimate_scan_axis", "estimate_scan_centre", "rows_run_across_axis", "fdk_view_weights", "scan_arc", "source_angles",
           "short_scan_weights", "displaced_detector_weights", "displaced_detector_layout", "displaced_pixel_weights",
           "centre_column"]


class FDKWarning(RuntimeWarning):
    """What FDK can only approximate on this geometry (a short or gapped arc, a rolled or displaced detector, a grid
    the rays miss): the jobs report these in their notes, where numpy's own RuntimeWarnings are not."""


def estimate_scan_axis(geom: ConeGeometry) -> np.ndarray:
    """Unit rotation axis of the scan, from the geometry alone (any frame).

    The normal of the plane fitted to the source positions where they fix it: 4 views or more whose
    scatter off the plane is under 5 % of their bend within it (the normal then known to about 3
    degrees). On a short arc of noisy positions (a live scan's first views, a few degrees of a
    robot's orbit) the bend is hardly above the noise and that normal can be anywhere; there the
    axis is the one across both the sources' motion (their principal direction) and the mean
    viewing direction (the detector normal w), which a short arc fixes well, as long as the views
    look along much the same way (a mean w of length 0.5 or more: a circular arc up to about 215
    degrees). That direction assumes the detector normal across the axis, as in a circular scan: a
    detector tilted out of the orbit plane tilts it as much, on such arcs and with 3 views (whose
    plane always fits, noise or not).
    The sign is chosen so the axis points along the mean detector v (row) direction, i.e. the
    axial direction of a usual scan. With fewer than 3 views, or sources on a line, the mean v
    direction itself is returned.
    """
    s = geom.source_mm
    vmean = geom.v.mean(axis=0)
    vmean = vmean / max(np.linalg.norm(vmean), 1e-12)
    if geom.n_views < 3:
        return vmean
    _, sv, vt = np.linalg.svd(s - s.mean(axis=0), full_matrices=False)
    if sv[1] <= 1e-9 * max(sv[0], 1e-12):  # no bend at all (sources on a line, or one point): no axis to tell
        return vmean
    n = None
    plane_fixed = geom.n_views == 3 or sv[2] <= 0.05 * sv[1]
    wmean = geom.w.mean(axis=0)
    if not (plane_fixed and geom.n_views > 3) and np.linalg.norm(wmean) >= 0.5:
        n = np.cross(vt[0], wmean)
        n = n / np.linalg.norm(n) if np.linalg.norm(n) > 1e-9 else None
    if n is None:  # the plane's normal: fixed, or the best there is (views looking many ways on a noisy arc)
        n = vt[2]
    return n if np.dot(n, vmean) >= 0 else -n


def rows_run_across_axis(geom: ConeGeometry, axis=None) -> bool:
    """Whether the detector's rows (its ``u``, the column index) run across the scan ``axis`` (default
    :func:`estimate_scan_axis`), as on a usual landscape detector, rather than along it (a portrait
    detector, turned a quarter in its plane). Its left and right edges, which an interior scan
    truncates, are then its first and last columns; otherwise its first and last rows. Decided over
    the whole scan: the mean ``|u . axis|`` against the mean ``|v . axis|``, ties to the columns."""
    n = estimate_scan_axis(geom) if axis is None else np.asarray(axis, dtype=np.float64)
    n = n / np.linalg.norm(n)
    return bool(np.mean(np.abs(geom.u @ n)) <= np.mean(np.abs(geom.v @ n)))


def estimate_scan_centre(geom: ConeGeometry, axis=None) -> np.ndarray | None:
    """The scan's rotation centre (3,) in mm, from the geometry alone (any frame), or None where it
    does not tell one.

    The centre of the circle fitted (least squares, Kasa) to the source positions in the plane
    normal to ``axis`` (default :func:`estimate_scan_axis`), placed in the sources' mean plane:
    the axis the orbit turns about, whatever the detector's offset or the grid's position, for a
    full circle or an arc. Where the sources do not bend (fewer than 3 views, or on a line, or
    an arc too flat to fit: a radius over 100 times their spread), the point nearest (least
    squares) to the views' central rays, the lines from each source along its detector normal;
    None where those are parallel too.
    """
    s = geom.source_mm
    if geom.n_views >= 3:
        n = estimate_scan_axis(geom) if axis is None else np.asarray(axis, dtype=np.float64)
        n = n / np.linalg.norm(n)
        e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        m = s.mean(axis=0)
        x, y = (s - m) @ e1, (s - m) @ e2
        spread = float(np.hypot(np.ptp(x), np.ptp(y)))
        if spread > 0:
            a = np.column_stack([2 * x, 2 * y, np.ones_like(x)]) / spread
            sol, _, rank, sv = np.linalg.lstsq(a, (x * x + y * y) / spread, rcond=None)
            radius2 = sol[2] + sol[0] ** 2 + sol[1] ** 2
            if rank == 3 and 0 < radius2 <= (100.0 * spread) ** 2:
                return m + sol[0] * e1 + sol[1] * e2
    w = geom.w
    proj = np.eye(3)[None] - w[:, :, None] * w[:, None, :]  # (I - w w^T): distance from each central ray
    a, b = proj.sum(axis=0), np.einsum("nij,nj->i", proj, s)
    sv = np.linalg.svd(a, compute_uv=False)
    if sv[-1] <= 1e-6 * sv[0]:
        return None
    return np.linalg.solve(a, b)


def _scan_angles(geom: ConeGeometry, center_mm, axis):
    """(phi, n, c, e1, e2): each source's angle phi (n_views,) about the unit ``axis`` n (default
    :func:`estimate_scan_axis`) through ``center_mm`` c (default the world origin), counter-clockwise
    about n from e1 (the in-plane direction of the source furthest from the axis) towards e2 = n x e1."""
    c = np.zeros(3) if center_mm is None else np.asarray(center_mm, dtype=np.float64)
    n = estimate_scan_axis(geom) if axis is None else np.asarray(axis, dtype=np.float64)
    n = n / np.linalg.norm(n)
    r = geom.source_mm - c
    r = r - np.outer(r @ n, n)
    radius = np.linalg.norm(r, axis=1)
    e1 = r[np.argmax(radius)] / radius.max()
    e2 = np.cross(n, e1)
    return np.arctan2(r @ e2, r @ e1), n, c, e1, e2


def scan_arc(geom: ConeGeometry, center_mm=None, axis=None, min_gap_rad: float = np.pi / 9):
    """(arc, first, beta): the angle (rad) the sources cover about ``axis`` through ``center_mm`` (as
    :func:`fdk_view_weights`), 2 pi for a full circle; for a short scan, whose largest gap between
    neighbouring views exceeds ``min_gap_rad`` (20 degrees, as RTK) and five times the median gap, the
    angle from the view after that gap to the view before it, with ``first`` that view's index and
    ``beta`` (n_views,) each view's angle from it, counter-clockwise about the axis (``first``, ``beta``
    None for a full circle). Views in any order."""
    if geom.n_views < 3:
        return 2 * np.pi, None, None
    return _arc(_scan_angles(geom, center_mm, axis)[0], min_gap_rad)


def source_angles(geom: ConeGeometry, center_mm=None, axis=None) -> np.ndarray:
    """Each view's source angle (rad, n_views) about ``axis`` (default :func:`estimate_scan_axis`) through
    ``center_mm`` (default the world origin), counter-clockwise about the axis; differences between views are
    what they mean (the zero direction is the source furthest from the axis)."""
    return _scan_angles(geom, center_mm, axis)[0]


def _arc(phi: np.ndarray, min_gap_rad: float):
    """:func:`scan_arc` of the source angles ``phi`` (at least 3)."""
    nv = phi.size
    order = np.argsort(phi)
    ps = phi[order]
    gaps = np.mod(np.roll(ps, -1) - ps, 2 * np.pi)
    k = int(np.argmax(gaps))
    moved = gaps[gaps > 1e-9]  # views repeated at one angle (several turns) are no gap, as fdk_view_weights counts
    if gaps[k] <= max(min_gap_rad, 5.0 * float(np.median(moved)) if moved.size else 0.0):
        return 2 * np.pi, None, None
    first = int(order[(k + 1) % nv])
    beta = np.mod(phi - phi[first], 2 * np.pi)
    beta[first] = 0.0
    return float(beta.max()), first, beta


def short_scan_weights(geom: ConeGeometry, center_mm=None, axis=None, min_gap_rad: float = np.pi / 9):
    """Parker's redundancy weights (n_views, n_cols) for a short scan, or None for a full one.

    The scan is short as :func:`scan_arc` says; its arc runs from the view after its largest gap
    to the view before it, counter-clockwise about the axis: beta in [0, pi + 2 delta]. Each
    column's fan angle gamma is the angle, in the plane normal to the axis and counted the same
    way, from the ray through the scan centre to the ray through that column's centre (the middle
    row's pixel; a tilted detector's other rows are taken as that column); a ray (beta, gamma) and its
    conjugate (beta + pi + 2 gamma, -gamma) are the same line. Weights (Parker 1982), times 2 so
    that they replace FDK's full-scan 1/2 per ray pair::

        2 sin^2(pi/4 beta / (delta - gamma))               0 <= beta < 2 delta - 2 gamma
        2                                                   up to pi - 2 gamma
        2 sin^2(pi/4 (pi + 2 delta - beta) / (delta + gamma))   up to pi + 2 delta

    They sum to 2 over every ray and its conjugate where delta is at least the fan's half-angle;
    with less (an arc shorter than a half turn plus the fan) the rays at the fan's edge are
    measured once only, and a warning says so. An arc of half a turn or less cannot be weighted
    (None, with a warning). Views in any order; the weights follow each view's own geometry.
    """
    nc = geom.n_cols
    if geom.n_views < 3:
        return None
    phi, n, c, e1, e2 = _scan_angles(geom, center_mm, axis)
    arc, _, beta = _arc(phi, min_gap_rad)
    if beta is None:
        return None
    delta = 0.5 * (arc - np.pi)
    if delta <= 0:
        warnings.warn(f"the scan's arc ({np.degrees(beta.max()):.1f} degrees) is no longer than half a turn: "
                      "no redundancy weights make FDK exact", FDKWarning, stacklevel=3)
        return None
    # fan angle of each column's centre (the middle row), in the plane normal to the axis
    cols = (np.arange(nc) - 0.5 * (nc - 1)) * geom.col_pitch_mm
    ray = geom.detector_mm[:, None, :] + cols[None, :, None] * geom.u[:, None, :] - geom.source_mm[:, None, :]
    central = c[None, :] - geom.source_mm

    def angle(d):
        return np.arctan2(d @ e2, d @ e1)

    gamma = np.mod(angle(ray) - angle(central)[:, None] + np.pi, 2 * np.pi) - np.pi  # (nv, nc)
    if delta < float(np.abs(gamma).max()):
        warnings.warn(f"short scan: the arc exceeds half a turn by {np.degrees(2 * delta):.1f} degrees, less than the "
                      f"fan angle ({np.degrees(2 * np.abs(gamma).max()):.1f} degrees); the rays at the fan's edge are "
                      "measured once only and FDK is approximate there", FDKWarning, stacklevel=3)
    b = beta[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        rise = np.sin(0.25 * np.pi * b / (delta - gamma)) ** 2
        fall = np.sin(0.25 * np.pi * (np.pi + 2 * delta - b) / (delta + gamma)) ** 2
    w = np.where(b < 2 * delta - 2 * gamma, rise, np.where(b <= np.pi - 2 * gamma, 1.0,
                                                           np.where(b <= np.pi + 2 * delta, fall, 0.0)))
    return 2.0 * np.nan_to_num(w, nan=0.0)


def fdk_view_weights(geom: ConeGeometry, center_mm=None, axis=None, *, short_scan_weighted: bool = False,
                     min_gap_rad: float = np.pi / 9):
    """Per-view angular quadrature of the FDK sum.

    Angles of the source positions around ``axis`` (default: :func:`estimate_scan_axis`)
    through ``center_mm`` (default: the world origin; :func:`fdk` passes the scan centre),
    sorted; each view weighs half the angle between its two neighbours (periodic, as RTK),
    whatever the gaps between them: a view next to a gap (dropped or rejected views,
    uneven sampling) stands in for half of it. Only the ends of a short arc (:func:`scan_arc`
    with ``min_gap_rad``: its one largest gap, beyond 20 degrees and five times the median)
    are taken one-sided (the trapezoid rule), as that gap is not measured at all. Other gaps
    beyond five times the median warn: FDK is only approximate across them.

    Returns ``(dbeta, g)``: ``dbeta`` (n_views,) in radians and ``g`` (n_views, 3) in mm,
    the source displacement attributed to each view (``dbeta * R * tangent`` with R the
    distance of the source from the axis). ``short_scan_weighted``: the caller applies
    :func:`short_scan_weights`, so a partial arc is no reason to warn.
    """
    phi, n, c, _, _ = _scan_angles(geom, center_mm, axis)
    r = geom.source_mm - c
    r = r - np.outer(r @ n, n)  # in-plane radius vectors
    radius = np.linalg.norm(r, axis=1)
    nv = geom.n_views
    if nv == 1:
        dbeta = np.array([2.0 * np.pi])
    else:
        order = np.argsort(phi)
        ps = phi[order]
        d_next = np.mod(np.roll(ps, -1) - ps, 2 * np.pi)  # gap to the next view
        first = _arc(phi, min_gap_rad)[1] if nv >= 3 else None
        inner = np.ones(nv, dtype=bool)
        if first is not None:  # a short arc: the gap before its first view is not measured
            if not short_scan_weighted:
                warnings.warn("scan does not cover 360 degrees; FDK full-scan weighting (1/2 per ray pair) "
                              "is then only approximate (no Parker weights)", FDKWarning, stacklevel=3)
            end = (int(np.flatnonzero(order == first)[0]) - 1) % nv
            d_next[end] = 0.0  # trapezoid rule at the ends of the arc
            inner[end] = False
        moved = d_next[inner & (d_next > 1e-9)]  # views repeated at one angle (several turns) are no gap
        med = float(np.median(moved)) if moved.size else 0.0
        wide = inner & (d_next > 5.0 * med) & (med > 0)
        if np.any(wide):
            warnings.warn(f"the views leave {int(wide.sum())} gap(s) of up to {np.degrees(d_next[wide].max()):.1f} "
                          f"degrees (median {np.degrees(med):.2f}); the views beside each stand in for half of it "
                          "and FDK is only approximate there", FDKWarning, stacklevel=3)
        d_prev = np.roll(d_next, 1)
        gaps = 0.5 * (d_next + d_prev)
        dbeta = np.empty(nv)
        dbeta[order] = gaps
    tangent = np.cross(n, r) / np.maximum(radius, 1e-12)[:, None]
    g = (dbeta * radius)[:, None] * tangent
    return dbeta, g


def centre_column(geom: ConeGeometry, center_mm) -> np.ndarray:
    """The detector column (n_views,) the scan centre projects onto, limited to one row length beyond
    either edge: a centre far off the detector (a grid placed away from the scan, or in a source's
    plane, where it projects to infinity) is simply "off the detector", and the widening of the
    filtered rows that follows from it stays bounded (it once asked for 5 GiB)."""
    nc = geom.n_cols
    with np.errstate(all="ignore"):
        cc = geom.project_points(np.asarray(center_mm, dtype=np.float64).reshape(1, 3))[:, 0, 0]
    cc = np.nan_to_num(cc, nan=0.5 * (nc - 1), posinf=2.0 * nc, neginf=-1.0 * nc)
    return np.clip(cc, -1.0 * nc, 2.0 * nc)


def _axis_frame(geom: ConeGeometry, center_mm, axis):
    """Per view, where the scan axis falls on the detector: the centre's projection (col, row) (each bounded as
    :func:`centre_column`), and the unit in-plane direction ``p`` (n_views, 2) in detector mm along (u, v)
    perpendicular to the axis's projected line, turned towards increasing columns; ``(cc, rc, p)``."""
    nr = geom.n_rows
    c = np.asarray(center_mm, dtype=np.float64).reshape(3)
    n = estimate_scan_axis(geom) if axis is None else np.asarray(axis, dtype=np.float64)
    n = n / np.linalg.norm(n)
    step = 0.1 * max(float(np.median(np.linalg.norm(geom.source_mm - c, axis=1))), 1.0)
    with np.errstate(all="ignore"):
        pts = geom.project_points(np.stack([c, c + step * n]))  # (nv, 2, 2): the axis's image is a line
    cc = centre_column(geom, c)
    rc = np.clip(np.nan_to_num(pts[:, 0, 1], nan=0.5 * (nr - 1), posinf=2.0 * nr, neginf=-1.0 * nr), -1.0 * nr,
                 2.0 * nr)
    t = (pts[:, 1] - pts[:, 0]) * np.array([geom.col_pitch_mm, geom.row_pitch_mm])
    norm = np.linalg.norm(t, axis=1)
    ok = np.isfinite(norm) & (norm > 1e-9 * step)
    t = np.where(ok[:, None], t / np.where(ok, norm, 1.0)[:, None], np.array([0.0, 1.0]))  # else along v
    p = np.stack([t[:, 1], -t[:, 0]], axis=1)
    p = np.where((p[:, 0] < 0)[:, None], -p, p)
    return cc, rc, p


def _distance_from_axis(geom: ConeGeometry, cc, rc, p, views=slice(None)):
    """Each pixel's signed distance (mm) from the scan axis's image along ``p``: (n_views', n_rows, n_cols)."""
    dc = (np.arange(geom.n_cols)[None, None, :] - cc[views, None, None]) * geom.col_pitch_mm
    dr = (np.arange(geom.n_rows)[None, :, None] - rc[views, None, None]) * geom.row_pitch_mm
    return dc * p[views, 0, None, None] + dr * p[views, 1, None, None]


def displaced_detector_layout(geom: ConeGeometry, center_mm=(0.0, 0.0, 0.0), min_asymmetry_px: float | None = None,
                              axis=None):
    """What :func:`displaced_detector_weights` weighs by, per view: ``(side, delta_mm, margin_px, frame)``:
    the short side (-1 at low columns, +1 at high ones, 0 where no view is weighted), the overlap's
    half-width (mm, None where no view is weighted), how far (in columns) the long side reaches beyond the
    short one in the row where that is most (FDK widens the filtered rows by it) and the axis's image
    (:func:`_axis_frame`)."""
    nv, nc, nr = geom.n_views, geom.n_cols, geom.n_rows
    cc, rc, p = _axis_frame(geom, center_mm, axis)
    # the reach on each side: from the axis's image to the detector's edge along p, the least over the rows
    corners_c = np.array([-0.5, -0.5, nc - 0.5, nc - 0.5])
    corners_r = np.array([-0.5, nr - 0.5, -0.5, nr - 0.5])
    d = ((corners_c[None] - cc[:, None]) * geom.col_pitch_mm * p[:, :1]
         + (corners_r[None] - rc[:, None]) * geom.row_pitch_mm * p[:, 1:])
    reach_lo = np.min(-d[:, :2], axis=1)
    reach_hi = np.min(d[:, 2:], axis=1)
    asym = (reach_hi - reach_lo) / geom.col_pitch_mm
    # how far the long side reaches beyond the short one in any row (slanted rows: more than asym)
    spread = np.maximum(np.max(d[:, 2:], axis=1) - reach_lo, np.max(-d[:, :2], axis=1) - reach_hi) / geom.col_pitch_mm
    if min_asymmetry_px is None:
        min_asymmetry_px = max(2.0, 0.1 * nc)
    # Wang's weights pair each ray with its conjugate on the other side: the short side must be one side
    # in (nearly) every view. A detector that wobbles about the axis, or an orbit aimed off its own centre,
    # is asymmetric by turns, measures every ray, and such weights would ruin it
    if np.median(np.abs(asym)) < min_asymmetry_px or abs(np.mean(np.sign(asym))) < 0.9:
        return np.zeros(nv, dtype=np.int64), None, spread, (cc, rc, p)
    delta = np.minimum(reach_lo, reach_hi)
    if np.any(delta <= 0):
        warnings.warn("the scan centre projects off the detector in some views; "
                      "displaced-detector weights cannot fill the missing half", FDKWarning, stacklevel=3)
    return np.where(asym >= 0, -1, 1), delta, spread, (cc, rc, p)


def displaced_pixel_weights(geom: ConeGeometry, layout, views=slice(None)) -> np.ndarray | None:
    """The weights (n_views', n_rows, n_cols) of ``views`` for the ``layout`` of
    :func:`displaced_detector_layout` (None where no view is weighted)."""
    side, delta, _, (cc, rc, p) = layout
    if delta is None:
        return None
    x = _distance_from_axis(geom, cc, rc, p, views) * (-side[views, None, None]) \
        / np.maximum(delta[views], 1e-6)[:, None, None]
    return 2.0 * np.sin(0.25 * np.pi * (1.0 + np.clip(x, -1.0, 1.0))) ** 2  # x = -1 at the inner edge


def displaced_detector_weights(geom: ConeGeometry, center_mm=(0.0, 0.0, 0.0),
                               min_asymmetry_px: float | None = None, axis=None):
    """Redundancy weights (n_views, n_rows, n_cols) for an offset (displaced) detector, after Wang 2002.

    The scan axis (``axis``, default :func:`estimate_scan_axis`, through ``center_mm``) falls on each
    view's detector along a line; each pixel's coordinate ``a`` is its signed distance from that line
    along the in-plane direction perpendicular to it (a detector rotated in its own plane has slanted
    rows, and its pixels are weighed by their own distance, not their column's). Where the detector
    reaches further on one side of the line than on the other, rays within ``+-delta`` of it (delta
    = the shorter reach, to the edge of the outer pixel, the least over the rows) are measured twice
    over 360 degrees and the rest once. Weights ``2 sin^2(pi/4 (1 + x))``, ``x = +-a / delta`` (0 at
    the inner edge, 1 on the line, 2 beyond ``delta``) sum to 2 over each ray and its conjugate,
    replacing FDK's 1/2 per ray pair.

    The scan counts as displaced when the median asymmetry of the reaches is at least
    ``min_asymmetry_px`` (default 10 % of the row, at least 2 pixels) and the short side is the
    same side in at least 95 % of the views (the weights pair each ray with its conjugate; a
    detector asymmetric by turns, wobbling about the axis or on an orbit aimed off its own centre,
    measures every ray); then every view is weighted (with its own line and delta), otherwise none
    is: conjugate views must be treated alike, and per-view robot errors of a few pixels must not
    switch a nearly centred detector to redundancy weighting.

    Limit: on a detector rotated in its own plane the weights are right pixel by pixel, but FDK filters
    along the detector rows, which then run slanted to the fan (across the axis's image), and a row and
    the rows holding its conjugate rays are no longer the same lines; weighting before filtering is then
    only approximate, the more so the larger the rotation and the steeper the weights (the smaller
    ``delta``). With the test's 0.15 rad rotation the weighted reconstruction still beats the unweighted
    one, but its error is several times that of the same scan without the rotation. :func:`fdk` resamples
    a detector rolled by more than ``virtual_detector.DEFAULT_TOL_DEG`` onto a virtual detector whose rows
    follow the source motion and weighs that one (:mod:`robot_ct_ros.ct.virtual_detector`), approximate
    too where it reaches beyond the real detector.

    Returns ``(weights, inner_side)``: ``inner_side`` (n_views,) is -1 where the short side is
    at low column indices, +1 at high ones, 0 where no weighting applies. (:func:`fdk` computes
    the weights a few views at a time: :func:`displaced_detector_layout`, :func:`displaced_pixel_weights`.)
    """
    layout = displaced_detector_layout(geom, center_mm, min_asymmetry_px, axis)
    w = displaced_pixel_weights(geom, layout)
    return (np.ones((geom.n_views,) + geom.det_shape) if w is None else w), layout[0]
