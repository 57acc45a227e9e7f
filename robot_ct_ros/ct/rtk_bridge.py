"""Bridge between ``robot_ct_ros.ct`` geometry/arrays and RTK (itk-rtk), the independent reference.

Conventions are those of :mod:`robot_ct_ros.ct.geometry`. The mapping to RTK is exact:

* A view is the vector form of RTK's
  ``AddProjection(sourcePosition, detectorPosition, detectorRowVector, detectorColumnVector)``
  with ``source_mm``, ``detector_mm``, ``u`` and ``v``. In RTK, ``detectorPosition`` is the
  world position of the point whose *physical* projection coordinates are (0, 0), the row
  vector is the direction of increasing first image index (our column, ``u``) and the column
  vector that of the second index (our row, ``v``); the normal is ``n = r x c`` (our ``w``).
  RTK stores it as 9 parameters (SID = n.S, SDD = n.(S - R), ZXY Euler angles of (r, c, n),
  offsets S.r, S.c, R.r, R.c), see rtkThreeDCircularProjectionGeometry.cxx. We compute these
  parameters ourselves (the same values) and add them in that form: RTK's own Euler
  decomposition is inexact within ~0.003 deg of 90 deg out of plane (gimbal lock), ours is not.
* The RTK projection stack is an ``itk.Image[F, 3]`` of size (n_cols, n_rows, n_views),
  spacing (col_pitch_mm, row_pitch_mm, 1), identity direction and origin
  (-(n_cols-1)/2*col_pitch_mm, -(n_rows-1)/2*row_pitch_mm, 0): its physical (0, 0) is the
  centre of the pixel grid, i.e. our ``detector_mm``. Its numpy view is our ``proj[view, row, col]``.
* A volume is an ``itk.Image[F, 3]`` of size (nx, ny, nz) with our ``VolumeGrid`` origin
  (centre of voxel 0, ITK's convention) and spacing, identity direction; RTK's volume axes
  are therefore our world axes.
* RTK projection matrices (``GetMatrix(i)``) map world points to *physical* detector
  coordinates; ``K @ M_rtk`` with ``K`` = [[1/col_pitch, 0, (n_cols-1)/2], [0, 1/row_pitch,
  (n_rows-1)/2], [0, 0, 1]] equals our ``ConeGeometry.projection_matrices()`` (same scale:
  both third rows are ``(X - s).w``).

RTK's FDK assumes a circular orbit about RTK's (= our world) y axis; :func:`rtk_fdk` just
wraps it. ``itk`` is imported lazily inside the functions (first import takes ~15 s) so the
core never depends on it at import time.
"""

from __future__ import annotations

import numpy as np

from .geometry import ConeGeometry, VolumeGrid

RTK_PARAM_NAMES = ("sid", "sdd", "gantry_deg", "proj_offset_x", "proj_offset_y",
                   "out_of_plane_deg", "in_plane_deg", "source_offset_x", "source_offset_y")
"""Order of the columns of :func:`to_rtk_parameters` (mm and degrees, RTK's ``AddProjection`` order)."""


def _rtk():
    import itk  # noqa: F401  (lazy: slow import, test/bench dependency only)
    from itk import RTK as rtk
    return itk, rtk


# ------------------------------------------------------------------ geometry
def _rtk_vector_parameters(geom: ConeGeometry) -> np.ndarray:
    """RTK's 9 parameters per view, (n, 9), angles in *radians*, of the vector form (S, R, r, c).

    The same parameters as RTK's own vector ``AddProjection`` (SID = n.S, SDD = n.(S - R),
    offsets S.r, S.c, R.r, R.c, negated ZXY Euler angles of the rows (r, c, n)), but the Euler
    decomposition is well conditioned everywhere. RTK's (ITK's ``Euler3DTransform``) takes the
    out-of-plane angle as asin(n_y) and switches to a fixed gimbal-lock branch under
    cos = 5e-5, which loses up to 2.5e-2 mm within ~0.003 deg of 90 deg. Here the out-of-plane
    angle is atan2(n_y, |(n_x, n_z)|), the gantry angle atan2(-n_x, n_z), and the in-plane angle
    is solved from the full rotation with those two removed: near the lock an error in the
    gantry angle is then a rotation about the normal, which the in-plane angle absorbs, so the
    rebuilt rotation is exact to rounding whatever the tilt.
    """
    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    # the rotation RTK will hold: the nearest one to the rows (u, v, u x v) (ConeGeometry keeps
    # them orthonormal to 1e-6 only); source and detector are then placed exactly in its frame
    m = np.stack([geom.u, geom.v, np.cross(geom.u, geom.v)], axis=1)
    a, _, bt = np.linalg.svd(m)
    rot = a @ bt
    r, c, n = rot[:, 0], rot[:, 1], rot[:, 2]
    oa = np.arctan2(n[:, 1], np.hypot(n[:, 0], n[:, 2]))   # in [-90, 90] deg, as ITK's asin
    ga = np.arctan2(-n[:, 0], n[:, 2])
    # rot = Rz(ia) Rx(oa) Ry(ga) (ITK's ZXY order)  =>  Rz(ia) = rot Ry(ga)^T Rx(oa)^T
    z = rot @ _rot_y(ga).transpose(0, 2, 1) @ _rot_x(oa).transpose(0, 2, 1)
    ia = np.arctan2(z[:, 1, 0] - z[:, 0, 1], z[:, 0, 0] + z[:, 1, 1])
    src, det = geom.source_mm, geom.detector_mm
    sid, sdd = dot(n, src), dot(n, src - det)
    sdd[np.abs(sdd) < 1e-6] = 0.0  # as RTK: a zero SDD means parallel
    # RTK negates the angles it is given (its rotation is Euler(-oop, -gantry, -in-plane))
    return np.stack([sid, sdd, -ga, dot(det, r), dot(det, c), -oa, -ia, dot(src, r), dot(src, c)], axis=1)


def _rot_x(a):
    c, s, o, i = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([i, o, o], -1), np.stack([o, c, -s], -1), np.stack([o, s, c], -1)], -2)


def _rot_y(a):
    c, s, o, i = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, o, s], -1), np.stack([o, i, o], -1), np.stack([-s, o, c], -1)], -2)


def to_rtk_geometry(geom: ConeGeometry):
    """An ``rtk.ThreeDCircularProjectionGeometry`` with the views of ``geom`` (vector form, exact).

    The parameters are those of RTK's vector ``AddProjection`` but decomposed here (see
    :func:`_rtk_vector_parameters`): RTK's own decomposition is inexact near 90 deg out of plane.
    """
    _, rtk = _rtk()
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for row in _rtk_vector_parameters(geom):
        g.AddProjectionInRadians(*[float(x) for x in row])
    return g


def from_rtk_geometry(rtk_geom, n_rows: int, n_cols: int, row_pitch_mm: float,
                      col_pitch_mm: float) -> ConeGeometry:
    """Read source, detector origin and row/column vectors back from an RTK geometry.

    The detector origin (physical (0, 0)) becomes ``detector_mm``, i.e. the projection stack
    is assumed to have the centred origin used by :func:`projections_to_itk`.
    """
    itk, _ = _rtk()
    n = len(rtk_geom.GetGantryAngles())
    src = np.empty((n, 3))
    det = np.empty((n, 3))
    u = np.empty((n, 3))
    v = np.empty((n, 3))
    for i in range(n):
        src[i] = np.asarray(rtk_geom.GetSourcePosition(i))[:3]
        # columns: world directions of projection x, y; last column: world position of (0, 0)
        m = itk.array_from_matrix(rtk_geom.GetProjectionCoordinatesToFixedSystemMatrix(i))
        u[i] = m[:3, 0]
        v[i] = m[:3, 1]
        det[i] = m[:3, 3]
    # remove the last-ulp denormalisation of RTK's Euler round trip
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return ConeGeometry(source_mm=src, detector_mm=det, u=u, v=v, n_rows=n_rows, n_cols=n_cols,
                        row_pitch_mm=row_pitch_mm, col_pitch_mm=col_pitch_mm)


def to_rtk_parameters(geom: ConeGeometry) -> np.ndarray:
    """RTK's 9 parameters per view, (n, 9), columns as :data:`RTK_PARAM_NAMES`.

    ``[sid, sdd, gantry, projOffsetX, projOffsetY, outOfPlane, inPlane, sourceOffsetX,
    sourceOffsetY]``: distances in mm, angles in degrees wrapped to [0, 360) (the units
    ``AddProjection`` takes), as read back from the RTK geometry built by :func:`to_rtk_geometry`.
    """
    return rtk_geometry_parameters(to_rtk_geometry(geom))


def rtk_geometry_parameters(rtk_geom) -> np.ndarray:
    """The (n, 9) parameter table (see :func:`to_rtk_parameters`) of an RTK geometry."""
    cols = [rtk_geom.GetSourceToIsocenterDistances(), rtk_geom.GetSourceToDetectorDistances(),
            np.degrees(rtk_geom.GetGantryAngles()), rtk_geom.GetProjectionOffsetsX(),
            rtk_geom.GetProjectionOffsetsY(), np.degrees(rtk_geom.GetOutOfPlaneAngles()),
            np.degrees(rtk_geom.GetInPlaneAngles()), rtk_geom.GetSourceOffsetsX(),
            rtk_geom.GetSourceOffsetsY()]
    return np.stack([np.asarray(c, dtype=np.float64) for c in cols], axis=1)


def rtk_geometry_from_parameters(params):
    """An RTK geometry built with the 9-parameter ``AddProjection`` from an (n, 9) table (mm, deg)."""
    _, rtk = _rtk()
    p = np.atleast_2d(np.asarray(params, dtype=np.float64))
    if p.ndim != 2 or p.shape[1] != 9:
        raise ValueError(f"params must have shape (n, 9), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("params contain NaN or infinite values")
    g = rtk.ThreeDCircularProjectionGeometry.New()
    for row in p:
        g.AddProjection(*[float(x) for x in row])
    return g


def from_rtk_parameters(params, n_rows: int, n_cols: int, row_pitch_mm: float,
                        col_pitch_mm: float) -> ConeGeometry:
    """ConeGeometry of an (n, 9) RTK parameter table (mm, degrees; see :func:`to_rtk_parameters`)."""
    return from_rtk_geometry(rtk_geometry_from_parameters(params), n_rows, n_cols, row_pitch_mm, col_pitch_mm)


def rtk_projection_matrices(geom: ConeGeometry) -> np.ndarray:
    """RTK's per-view matrices converted to pixel indices: (n, 3, 4), comparable to ``projection_matrices()``."""
    itk, _ = _rtk()
    g = to_rtk_geometry(geom)
    K = np.array([[1.0 / geom.col_pitch_mm, 0.0, 0.5 * (geom.n_cols - 1)],
                  [0.0, 1.0 / geom.row_pitch_mm, 0.5 * (geom.n_rows - 1)],
                  [0.0, 0.0, 1.0]])
    return np.stack([K @ itk.array_from_matrix(g.GetMatrix(i)) for i in range(geom.n_views)])


# -------------------------------------------------------------------- images
def volume_to_itk(volume: np.ndarray, grid: VolumeGrid):
    """``itk.Image[F, 3]`` (size nx, ny, nz) holding a copy of ``volume[k, j, i]`` placed by ``grid``."""
    itk, _ = _rtk()
    vol = np.ascontiguousarray(volume, dtype=np.float32)
    if vol.shape != grid.shape_zyx:
        raise ValueError(f"volume shape {vol.shape} does not match grid {grid.shape_zyx}")
    img = itk.image_from_array(vol.copy())
    img.SetSpacing([float(s) for s in grid.voxel_size_mm])
    img.SetOrigin([float(o) for o in grid.origin_mm])
    if not grid.axis_aligned:  # ITK's direction has the same meaning: columns = the index axes in the world
        img.SetDirection(itk.matrix_from_array(np.ascontiguousarray(grid.direction_matrix)))
    return img


def itk_to_volume(image) -> tuple[np.ndarray, VolumeGrid]:
    """A float32 copy ``volume[k, j, i]`` of an ITK 3D image and its :class:`VolumeGrid`."""
    itk, _ = _rtk()
    vol = np.array(itk.array_from_image(image), dtype=np.float32, copy=True)
    direction = np.array(itk.array_from_matrix(image.GetDirection()), dtype=np.float64)
    grid = VolumeGrid(vol.shape, tuple(float(s) for s in image.GetSpacing()),
                      tuple(float(o) for o in image.GetOrigin()), tuple(direction.reshape(-1)))
    return vol, grid


def rtk_stack_origin_spacing(geom: ConeGeometry) -> tuple[list, list]:
    """(origin, spacing) in mm of the RTK projection stack of ``geom``: the centred origin that
    puts physical (0, 0) at the pixel-grid centre (our ``detector_mm``), in ITK's (x, y, z) order."""
    origin = [-0.5 * (geom.n_cols - 1) * geom.col_pitch_mm, -0.5 * (geom.n_rows - 1) * geom.row_pitch_mm, 0.0]
    return origin, [geom.col_pitch_mm, geom.row_pitch_mm, 1.0]


def projections_to_itk(proj: np.ndarray | None, geom: ConeGeometry):
    """RTK projection stack (size n_cols x n_rows x n_views) of ``proj[view, row, col]``.

    ``proj=None`` gives a zero stack (the template RTK forward projectors write into).
    Origin and spacing put physical (0, 0) at the pixel-grid centre, matching :func:`to_rtk_geometry`.
    """
    itk, _ = _rtk()
    shape = (geom.n_views, geom.n_rows, geom.n_cols)
    if proj is None:
        arr = np.zeros(shape, dtype=np.float32)
    else:
        arr = np.array(proj, dtype=np.float32, copy=True, order="C")
        if arr.shape != shape:
            raise ValueError(f"projections shape {arr.shape} does not match geometry {shape}")
    img = itk.image_from_array(arr)
    origin, spacing = rtk_stack_origin_spacing(geom)
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    return img


def itk_to_projections(image) -> np.ndarray:
    """A float32 copy ``proj[view, row, col]`` of an RTK projection stack."""
    itk, _ = _rtk()
    return np.array(itk.array_from_image(image), dtype=np.float32, copy=True)


# ------------------------------------------------------------------ filters
def rtk_forward_project(volume: np.ndarray, grid: VolumeGrid, geom: ConeGeometry) -> np.ndarray:
    """Line integrals (mm x volume units) by RTK's Joseph forward projector, (n_views, n_rows, n_cols) f32."""
    itk, rtk = _rtk()
    img_type = itk.Image[itk.F, 3]
    fp = rtk.JosephForwardProjectionImageFilter[img_type, img_type].New()
    fp.SetInput(0, projections_to_itk(None, geom))
    fp.SetInput(1, volume_to_itk(volume, grid))
    fp.SetGeometry(to_rtk_geometry(geom))
    fp.Update()
    return itk_to_projections(fp.GetOutput())


def rtk_fdk(proj: np.ndarray, geom: ConeGeometry, grid: VolumeGrid, hann_cutoff: float = 0.0) -> np.ndarray:
    """RTK's FDK (``FDKConeBeamReconstructionFilter``) of ``proj`` on ``grid``, float32 ``volume[k, j, i]``.

    Plain RTK FDK: cosine weighting, ramp filter (Hann window cut at ``hann_cutoff`` x
    Nyquist; 0 = no window), voxel-based back projection. No displaced-detector or Parker
    weighting, and RTK assumes a circular orbit about the world y axis (our axes are RTK's).
    """
    itk, rtk = _rtk()
    img_type = itk.Image[itk.F, 3]
    fdk = rtk.FDKConeBeamReconstructionFilter[img_type].New()
    fdk.SetInput(0, volume_to_itk(np.zeros(grid.shape_zyx, dtype=np.float32), grid))
    fdk.SetInput(1, projections_to_itk(proj, geom))
    fdk.SetGeometry(to_rtk_geometry(geom))
    fdk.GetRampFilter().SetHannCutFrequency(float(hann_cutoff))
    fdk.Update()
    return itk_to_volume(fdk.GetOutput())[0]


def rtk_ellipsoid_projections(ellipsoids, geom: ConeGeometry, *, chunk_views: int = 30) -> np.ndarray:
    """Exact line integrals of a sum of ellipsoids by RTK's analytic ray-quadric intersection
    (``RayConvexIntersectionImageFilter`` with ``QuadricShape`` ellipsoids): (n_views, n_rows,
    n_cols) float32, a projector independent of ours.

    ``ellipsoids`` are :class:`robot_ct_ros.ct.simulation.Primitive` of kind ``"ellipsoid"``
    and mode ``"add"`` (their densities add up): centre (mm), rotation (local axes to the world),
    semi-axes (mm), attenuation (1/mm). Any orientation: each quadric is built at the origin,
    rotated, then translated.
    """
    itk, rtk = _rtk()
    shapes = []
    for p in ellipsoids:
        if p.kind != "ellipsoid" or p.mode != "add":
            raise ValueError(f"{p.name or p.kind}: only additive ellipsoids have an RTK quadric here")
        q = rtk.QuadricShape.New()
        q.SetEllipsoid([0.0, 0.0, 0.0], [float(a) for a in p.params[:3]], 0.0)
        q.Rotate(itk.matrix_from_array(np.ascontiguousarray(p.rotation, dtype=np.float64)))
        q.Translate([float(c) for c in p.center_mm])
        q.SetDensity(float(p.value))
        shapes.append(q)
    img_type = itk.Image[itk.F, 3]
    out = np.empty((geom.n_views, geom.n_rows, geom.n_cols), np.float32)
    for v0 in range(0, geom.n_views, chunk_views):
        g = geom.subset(np.arange(v0, min(geom.n_views, v0 + chunk_views)))
        img, rg = projections_to_itk(None, g), to_rtk_geometry(g)
        for q in shapes:
            f = rtk.RayConvexIntersectionImageFilter[img_type, img_type].New()
            f.SetInput(img)
            f.SetGeometry(rg)
            f.SetConvexShape(q)
            f.Update()
            img = f.GetOutput()
            img.DisconnectPipeline()
        out[v0:v0 + g.n_views] = itk_to_projections(img)
    return out
