"""Cone-beam geometry of a robotic CT scan: per-view vector geometry and volume grids.

Conventions (stated once, used everywhere in ``robot_ct_ros.ct``):

* World frame: right-handed, millimetres, radians. Geometry is float64, images float32.
* Volumes are numpy arrays indexed ``volume[k, j, i]`` (z, y, x; x fastest in memory).
  A :class:`VolumeGrid` maps index (i, j, k) to the world point
  ``origin_mm + D @ (i * dx, j * dy, k * dz)``: ``origin_mm`` is the centre of voxel
  [0, 0, 0] and the columns of the rotation ``D`` (``direction``) are the world directions
  of the grid's x, y and z axes (ITK's convention; identity by default). ``voxel_size_mm``
  and ``origin_mm`` are (x, y, z). No world axis is special: a scan about any axis is
  reconstructed on a grid whose z axis follows it (:meth:`VolumeGrid.centered`'s
  ``direction``), and the kernels work in the grid's own frame.
* Projections are arrays ``proj[view, row, col]``. Column index c runs along the unit
  vector ``u`` (a detector row), row index r along the unit vector ``v`` (a detector
  column). The centre of pixel (r, c) lies at
  ``detector_mm + (c - (n_cols - 1) / 2) * col_pitch_mm * u + (r - (n_rows - 1) / 2) * row_pitch_mm * v``,
  so ``detector_mm`` is the centre of the pixel grid and pixel (0, 0) is the centre of
  the first pixel in memory. ``w = u x v`` is the detector normal.
* A projection matrix ``P`` (3 x 4) maps homogeneous world points (x, y, z, 1) in mm to
  ``lambda * (c, r, 1)`` in pixel indices (column first, as RTK and OpenCV do).
* The 9 geometry parameters of a view, ``params[view] = [s_u, s_v, s_w, d_u, d_v, d_w,
  r_u, r_v, r_w]``, perturb a *nominal* geometry and are expressed in that view's nominal
  detector frame (u, v, w): source shift (mm), detector-centre shift (mm), and detector
  rotation as a rotation vector (radians) about the detector centre. Expressing them in
  the local frame makes them comparable across views of any trajectory: s_u, s_v and d_u,
  d_v move the image in-plane, s_w and d_w change magnification, r_w is the in-plane skew,
  r_u and r_v tilt the detector.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

PARAM_NAMES = ("s_u", "s_v", "s_w", "d_u", "d_v", "d_w", "r_u", "r_v", "r_w")
"""Names of the 9 per-view geometry parameters, in array order (mm, mm, mm, ..., rad)."""

FAN_BEAM_PARAMS = ("s_u", "s_w", "d_u", "d_w", "r_v")
"""The parameters a one-row (fan-beam) detector sees: those that move its rays within the fan
plane (spanned by u and w): the source's in-plane position (s_u, s_w), the detector's in-plane
shift (d_u) and distance (d_w: with s_w, the magnification), and its rotation within the fan
plane (r_v, about the detector's v axis). Three others (s_v, d_v: out of the plane; r_w: the
row's roll out of the plane) move the rays off the one slice the row sees, which a one-row scan
cannot tell from the object changing along the axis; r_u turns the detector about its own row
and moves none of a one-row detector's pixels. All four stay nominal."""


def observable_params(geom: "ConeGeometry") -> np.ndarray:
    """(9,) bool: the parameters the calibration estimates for ``geom``'s detector. All nine for a
    detector of two or more rows; :data:`FAN_BEAM_PARAMS` for one row (fan beam): the others stay
    at their current (nominal, or prior) values."""
    if geom.n_rows >= 2:
        return np.ones(9, bool)
    return np.array([name in FAN_BEAM_PARAMS for name in PARAM_NAMES])


def _as_vectors(a, n: int | None = None) -> np.ndarray:
    arr = np.array(a, dtype=np.float64, copy=True)
    arr = np.atleast_2d(arr)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"expected an (n, 3) array of vectors, got shape {arr.shape}")
    if n is not None and arr.shape[0] == 1 and n > 1:
        arr = np.repeat(arr, n, axis=0)
    arr.setflags(write=False)
    return arr


def _normalized(a: np.ndarray) -> np.ndarray:
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


_IDENTITY = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True)
class VolumeGrid:
    """A regular voxel grid in the world frame.

    ``shape_zyx`` is the numpy array shape (nz, ny, nx); ``voxel_size_mm`` and
    ``origin_mm`` are (x, y, z); ``origin_mm`` is the centre of voxel [0, 0, 0];
    ``direction`` the 3 x 3 rotation (row-major, 9 values) whose columns are the world
    directions of the grid's x, y and z axes (identity: axis-aligned).
    """

    shape_zyx: tuple[int, int, int]
    voxel_size_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: tuple = _IDENTITY

    def __post_init__(self):
        if any(float(x) != int(float(x)) for x in self.shape_zyx if np.isfinite(float(x))):
            raise ValueError(f"shape_zyx must be 3 positive whole numbers, got {self.shape_zyx}")
        object.__setattr__(self, "shape_zyx", tuple(int(s) for s in self.shape_zyx))
        object.__setattr__(self, "voxel_size_mm", tuple(float(s) for s in self.voxel_size_mm))
        object.__setattr__(self, "origin_mm", tuple(float(s) for s in self.origin_mm))
        if len(self.shape_zyx) != 3 or min(self.shape_zyx) < 1:
            raise ValueError(f"shape_zyx must be 3 positive ints, got {self.shape_zyx}")
        if len(self.voxel_size_mm) != 3 or not all(0 < x < np.inf for x in self.voxel_size_mm):
            raise ValueError(f"voxel_size_mm must be 3 positive finite numbers, got {self.voxel_size_mm}")
        if len(self.origin_mm) != 3 or not np.all(np.isfinite(self.origin_mm)):
            raise ValueError(f"origin_mm must be 3 finite numbers, got {self.origin_mm}")
        D = np.asarray(self.direction, dtype=np.float64).reshape(-1)
        if D.size != 9 or not np.all(np.isfinite(D)):
            raise ValueError("direction must be a 3 x 3 rotation matrix")
        D = D.reshape(3, 3)
        if np.abs(D.T @ D - np.eye(3)).max() > 1e-6 or np.linalg.det(D) < 0:
            raise ValueError("direction must be a proper rotation (orthonormal columns, determinant +1)")
        object.__setattr__(self, "direction", tuple(float(x) for x in D.reshape(-1)))

    @classmethod
    def centered(cls, shape_zyx: Sequence[int], voxel_size_mm, center_mm=(0.0, 0.0, 0.0),
                 direction=None) -> "VolumeGrid":
        """A grid of ``shape_zyx`` voxels whose centre lies at ``center_mm`` (x, y, z), its axes
        along the columns of ``direction`` (default: the world axes)."""
        vs = np.broadcast_to(np.asarray(voxel_size_mm, dtype=np.float64), (3,))
        D = np.eye(3) if direction is None else np.asarray(direction, dtype=np.float64).reshape(3, 3)
        nxyz = np.array(shape_zyx[::-1], dtype=np.float64)
        origin = np.asarray(center_mm, dtype=np.float64) - D @ (0.5 * (nxyz - 1) * vs)
        return cls(tuple(shape_zyx), tuple(vs), tuple(origin), tuple(D.reshape(-1)))

    @property
    def direction_matrix(self) -> np.ndarray:
        """(3, 3) rotation: columns are the world directions of the grid's x, y, z axes."""
        return np.asarray(self.direction, dtype=np.float64).reshape(3, 3)

    @property
    def axis_aligned(self) -> bool:
        return self.direction == _IDENTITY

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        return self.shape_zyx[::-1]

    @property
    def center_mm(self) -> np.ndarray:
        return self.index_to_world(0.5 * (np.array(self.shape_xyz) - 1))

    @property
    def extent_mm(self) -> np.ndarray:
        """Edge-to-edge size along the grid's own x, y, z axes, in mm."""
        return np.array(self.shape_xyz) * np.asarray(self.voxel_size_mm)

    def index_to_world(self, index_xyz) -> np.ndarray:
        """World points (..., 3) of (fractional) voxel indices (..., 3) in (i, j, k) = (x, y, z) order."""
        idx = np.asarray(index_xyz, dtype=np.float64)
        return np.asarray(self.origin_mm) + (idx * np.asarray(self.voxel_size_mm)) @ self.direction_matrix.T

    def world_to_index(self, points_mm) -> np.ndarray:
        """Fractional voxel indices (..., 3) in (x, y, z) order of world points (..., 3)."""
        p = np.asarray(points_mm, dtype=np.float64) - np.asarray(self.origin_mm)
        return (p @ self.direction_matrix) / np.asarray(self.voxel_size_mm)

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y, z) lower and upper corners of the box that holds every voxel (the voxel
        box itself for an axis-aligned grid)."""
        half = 0.5 * self.extent_mm
        reach = np.abs(self.direction_matrix) @ half
        return self.center_mm - reach, self.center_mm + reach

    def axes_mm(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Coordinates of the voxel centres along the grid's x, y and z axes: world coordinates
        for an axis-aligned grid, else relative to the grid's own frame (``origin_mm`` rotated)."""
        o = self.direction_matrix.T @ np.asarray(self.origin_mm)
        return tuple(o[a] + self.voxel_size_mm[a] * np.arange(self.shape_xyz[a]) for a in range(3))

    def resized(self, shape_zyx: Sequence[int], voxel_size_mm=None) -> "VolumeGrid":
        """Another grid with the same centre and direction: ``shape_zyx`` voxels of
        ``voxel_size_mm`` (default: this grid's)."""
        return VolumeGrid.centered(tuple(shape_zyx), self.voxel_size_mm if voxel_size_mm is None else voxel_size_mm,
                                   self.center_mm, self.direction_matrix)

    def binned(self, factor: int) -> "VolumeGrid":
        """The grid with ``factor``-times larger voxels about the same centre, covering the same box where
        each axis's voxels divide by ``factor`` (otherwise the box shrinks by the remainder); an axis with
        fewer than ``factor`` voxels (a thin fan-beam slab) keeps its voxels (:func:`bin_factors`)."""
        f = bin_factors(self.shape_zyx, factor)
        return self.resized(tuple(s // k for s, k in zip(self.shape_zyx, f)),
                            tuple(v * k for v, k in zip(self.voxel_size_mm, f[::-1])))

    def slab(self, z0: int, z1: int) -> "VolumeGrid":
        """Voxel planes ``z0`` to ``z1 - 1`` along the first axis of ``shape_zyx`` (the grid's own z):
        the same voxels, so a volume on it is ``volume[z0:z1]`` of one on this grid."""
        nz = self.shape_zyx[0]
        if not 0 <= z0 < z1 <= nz:
            raise ValueError(f"a slab needs 0 <= z0 < z1 <= {nz}, got {z0}, {z1}")
        return VolumeGrid((z1 - z0,) + self.shape_zyx[1:], self.voxel_size_mm,
                          tuple(self.index_to_world((0.0, 0.0, float(z0)))), self.direction)

    def in_own_frame(self) -> tuple["VolumeGrid", np.ndarray]:
        """This grid axis-aligned in its own frame, and the rotation R (= direction transposed)
        that takes world coordinates into that frame: a kernel that assumes an axis-aligned grid
        runs on (grid, geometry rotated by R) unchanged."""
        R = self.direction_matrix.T
        return VolumeGrid(self.shape_zyx, self.voxel_size_mm, tuple(R @ np.asarray(self.origin_mm))), R

    def moved(self, rotation, translation_mm=(0.0, 0.0, 0.0)) -> "VolumeGrid":
        """The grid after the rigid motion x -> rotation @ x + translation_mm (3 x 3, 3)."""
        Rm = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        return VolumeGrid(self.shape_zyx, self.voxel_size_mm,
                          tuple(Rm @ np.asarray(self.origin_mm) + np.asarray(translation_mm, dtype=np.float64)),
                          tuple((Rm @ self.direction_matrix).reshape(-1)))

    def to_dict(self) -> dict:
        d = {"shape_zyx": list(self.shape_zyx), "voxel_size_mm": list(self.voxel_size_mm),
             "origin_mm": list(self.origin_mm)}
        if not self.axis_aligned:
            d["direction"] = list(self.direction)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "VolumeGrid":
        return cls(tuple(d["shape_zyx"]), tuple(d["voxel_size_mm"]), tuple(d["origin_mm"]),
                   tuple(d.get("direction", _IDENTITY)))


@dataclass(frozen=True, eq=False)
class ConeGeometry:
    """Per-view flat-panel cone-beam geometry (ASTRA ``cone_vec`` / RTK vector form).

    Arrays have one row per view: ``source_mm`` and ``detector_mm`` (n, 3) are the source
    focal spot and the detector centre; ``u`` and ``v`` (n, 3) are the unit vectors of
    increasing column and row index. See the module docstring for all conventions.
    """

    source_mm: np.ndarray
    detector_mm: np.ndarray
    u: np.ndarray
    v: np.ndarray
    n_rows: int
    n_cols: int
    row_pitch_mm: float
    col_pitch_mm: float
    _w: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        src = _as_vectors(self.source_mm)
        n = src.shape[0]
        det = _as_vectors(self.detector_mm, n)
        u = _as_vectors(self.u, n)
        v = _as_vectors(self.v, n)
        if not (src.shape == det.shape == u.shape == v.shape):
            raise ValueError("source_mm, detector_mm, u and v must have the same number of views")
        if not np.all(np.isfinite(np.concatenate([src, det, u, v]))):
            raise ValueError("geometry contains NaN or infinite values")
        nu, nv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
        if np.any(np.abs(nu - 1) > 1e-6) or np.any(np.abs(nv - 1) > 1e-6):
            raise ValueError("u and v must be unit vectors")
        if np.any(np.abs(np.einsum("ij,ij->i", u, v)) > 1e-6):
            raise ValueError("u and v must be orthogonal")
        if any(float(n) != int(float(n)) for n in (self.n_rows, self.n_cols)):
            raise ValueError(f"n_rows and n_cols must be whole numbers, got {self.n_rows}, {self.n_cols}")
        if (self.n_rows < 1 or self.n_cols < 1
                or not (0 < self.row_pitch_mm < np.inf) or not (0 < self.col_pitch_mm < np.inf)):
            raise ValueError(f"detector shape and pitch must be positive and finite, got {self.n_rows} x "
                             f"{self.n_cols} pixels of {self.row_pitch_mm} x {self.col_pitch_mm} mm")
        w = np.cross(u, v)
        w.setflags(write=False)
        for name, val in (("source_mm", src), ("detector_mm", det), ("u", u), ("v", v), ("_w", w)):
            object.__setattr__(self, name, val)
        object.__setattr__(self, "n_rows", int(self.n_rows))
        object.__setattr__(self, "n_cols", int(self.n_cols))
        object.__setattr__(self, "row_pitch_mm", float(self.row_pitch_mm))
        object.__setattr__(self, "col_pitch_mm", float(self.col_pitch_mm))

    # ------------------------------------------------------------------ basics
    @property
    def n_views(self) -> int:
        return self.source_mm.shape[0]

    def __len__(self) -> int:
        return self.n_views

    @property
    def w(self) -> np.ndarray:
        """Unit detector normal ``u x v`` per view, (n, 3)."""
        return self._w

    @property
    def det_shape(self) -> tuple[int, int]:
        return (self.n_rows, self.n_cols)

    @property
    def sdd_mm(self) -> np.ndarray:
        """Perpendicular source-to-detector-plane distance per view (mm)."""
        return np.abs(np.einsum("ij,ij->i", self.detector_mm - self.source_mm, self.w))

    def sod_mm(self, point_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Distance from the source to ``point_mm`` along the detector normal, per view."""
        p = np.asarray(point_mm, dtype=np.float64)
        return np.abs(np.einsum("ij,ij->i", p - self.source_mm, self.w))

    def magnification(self, point_mm=(0.0, 0.0, 0.0)) -> np.ndarray:
        return self.sdd_mm / self.sod_mm(point_mm)

    def local_frames(self) -> np.ndarray:
        """(n, 3, 3) matrices whose columns are u, v, w: local detector frame to world."""
        return np.stack([self.u, self.v, self.w], axis=2)

    def __eq__(self, other) -> bool:
        return isinstance(other, ConeGeometry) and self.allclose(other, atol=0.0)

    def allclose(self, other: "ConeGeometry", atol: float = 1e-9) -> bool:
        return (
            self.det_shape == other.det_shape
            and self.n_views == other.n_views
            and abs(self.row_pitch_mm - other.row_pitch_mm) <= atol
            and abs(self.col_pitch_mm - other.col_pitch_mm) <= atol
            and all(np.allclose(getattr(self, k), getattr(other, k), rtol=0, atol=atol)
                    for k in ("source_mm", "detector_mm", "u", "v"))
        )

    def replace(self, **changes) -> "ConeGeometry":
        kw = dict(source_mm=self.source_mm, detector_mm=self.detector_mm, u=self.u, v=self.v,
                  n_rows=self.n_rows, n_cols=self.n_cols, row_pitch_mm=self.row_pitch_mm,
                  col_pitch_mm=self.col_pitch_mm)
        kw.update(changes)
        return ConeGeometry(**kw)

    def subset(self, views) -> "ConeGeometry":
        """The geometry of the selected views (index array, slice or boolean mask)."""
        return self.replace(source_mm=np.atleast_2d(self.source_mm[views]),
                            detector_mm=np.atleast_2d(self.detector_mm[views]),
                            u=np.atleast_2d(self.u[views]), v=np.atleast_2d(self.v[views]))

    @staticmethod
    def concatenate(parts: Sequence["ConeGeometry"]) -> "ConeGeometry":
        first = parts[0]
        if any(p.det_shape != first.det_shape or p.row_pitch_mm != first.row_pitch_mm
               or p.col_pitch_mm != first.col_pitch_mm for p in parts):
            raise ValueError("cannot concatenate geometries with different detectors")
        return first.replace(**{k: np.concatenate([getattr(p, k) for p in parts])
                                for k in ("source_mm", "detector_mm", "u", "v")})

    # ------------------------------------------------------------ detector grid
    def with_detector(self, n_rows: int, n_cols: int, row_pitch_mm: float | None = None,
                      col_pitch_mm: float | None = None) -> "ConeGeometry":
        """Same views and detector centre, another pixel grid (e.g. an enlarged virtual detector)."""
        return self.replace(n_rows=n_rows, n_cols=n_cols,
                            row_pitch_mm=self.row_pitch_mm if row_pitch_mm is None else row_pitch_mm,
                            col_pitch_mm=self.col_pitch_mm if col_pitch_mm is None else col_pitch_mm)

    def binned(self, factor: int) -> "ConeGeometry":
        """Geometry of ``factor`` x ``factor`` binned projections (see ``bin_projections``).

        Binning drops trailing rows/columns that do not fill a bin, which moves the grid
        centre; the detector centre is shifted accordingly so each binned pixel lies
        exactly over the raw pixels it sums. Rows (or columns) fewer than ``factor`` are not
        binned (:func:`bin_factors`): a one-row fan-beam detector stays one row at every level.
        """
        fr, fc = bin_factors(self.det_shape, factor)
        if fr == fc == 1:
            return self
        nr, nc = self.n_rows // fr, self.n_cols // fc
        # centre of the kept raw pixels relative to the raw grid centre, in raw pixels
        dr = 0.5 * (nr * fr - self.n_rows)
        dc = 0.5 * (nc * fc - self.n_cols)
        det = (self.detector_mm + dc * self.col_pitch_mm * self.u + dr * self.row_pitch_mm * self.v)
        return self.replace(detector_mm=det, n_rows=nr, n_cols=nc,
                            row_pitch_mm=self.row_pitch_mm * fr, col_pitch_mm=self.col_pitch_mm * fc)

    def pixel_centers_mm(self, view: int) -> np.ndarray:
        """World positions (n_rows, n_cols, 3) of the pixel centres of one view."""
        r = (np.arange(self.n_rows) - 0.5 * (self.n_rows - 1)) * self.row_pitch_mm
        c = (np.arange(self.n_cols) - 0.5 * (self.n_cols - 1)) * self.col_pitch_mm
        return (self.detector_mm[view] + c[None, :, None] * self.u[view] + r[:, None, None] * self.v[view])

    # ---------------------------------------------------------- projection maps
    def projection_matrices(self) -> np.ndarray:
        """(n, 3, 4) matrices P with ``P @ (x, y, z, 1) = lambda * (col, row, 1)``.

        lambda = (X - s) . w, the depth of the point along the detector normal; it has
        the sign of (d - s) . w for points between source and detector.
        """
        s, d, u, v, w = self.source_mm, self.detector_mm, self.u, self.v, self.w
        depth = np.einsum("ij,ij->i", d - s, w)  # signed source-to-plane distance
        c0 = 0.5 * (self.n_cols - 1)
        r0 = 0.5 * (self.n_rows - 1)
        su = np.einsum("ij,ij->i", s - d, u)
        sv = np.einsum("ij,ij->i", s - d, v)
        sw = np.einsum("ij,ij->i", s, w)
        # lambda * (D - d).u = su * lambda + depth * (u.X - u.s)
        P = np.empty((self.n_views, 3, 4))
        row_w = np.concatenate([w, -sw[:, None]], axis=1)
        row_u = (su[:, None] * row_w + depth[:, None] * np.concatenate(
            [u, -np.einsum("ij,ij->i", u, s)[:, None]], axis=1))
        row_v = (sv[:, None] * row_w + depth[:, None] * np.concatenate(
            [v, -np.einsum("ij,ij->i", v, s)[:, None]], axis=1))
        P[:, 0] = row_u / self.col_pitch_mm + c0 * row_w
        P[:, 1] = row_v / self.row_pitch_mm + r0 * row_w
        P[:, 2] = row_w
        return P

    def project_points(self, points_mm) -> np.ndarray:
        """Pixel coordinates (n_views, n_points, 2) as (col, row) of world points (n_points, 3)."""
        pts = np.atleast_2d(np.asarray(points_mm, dtype=np.float64))
        hom = np.concatenate([pts, np.ones((pts.shape[0], 1))], axis=1)
        q = np.einsum("vab,pb->vpa", self.projection_matrices(), hom)
        return q[..., :2] / q[..., 2:3]

    # ------------------------------------------------------- 9-DOF parameters
    def perturbed(self, params) -> "ConeGeometry":
        """Apply per-view 9-DOF parameters (n, 9) or (9,), in this geometry's local frames."""
        p = np.asarray(params, dtype=np.float64)
        p = np.broadcast_to(p, (self.n_views, 9)) if p.ndim == 1 else p
        if p.shape != (self.n_views, 9):
            raise ValueError(f"params must have shape ({self.n_views}, 9), got {p.shape}")
        B = self.local_frames()
        src = self.source_mm + np.einsum("vij,vj->vi", B, p[:, 0:3])
        det = self.detector_mm + np.einsum("vij,vj->vi", B, p[:, 3:6])
        rot = Rotation.from_rotvec(np.einsum("vij,vj->vi", B, p[:, 6:9]))
        return self.replace(source_mm=src, detector_mm=det, u=rot.apply(np.array(self.u)), v=rot.apply(np.array(self.v)))

    def moved(self, rotation, translation_mm=(0.0, 0.0, 0.0)) -> "ConeGeometry":
        """Every view after the rigid motion x -> rotation @ x + translation_mm (3 x 3, 3). The
        9-DOF parameters relative to a geometry are invariant under it (local frames)."""
        Rm = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        t = np.asarray(translation_mm, dtype=np.float64)
        return self.replace(source_mm=self.source_mm @ Rm.T + t, detector_mm=self.detector_mm @ Rm.T + t,
                            u=self.u @ Rm.T, v=self.v @ Rm.T)

    def params_relative_to(self, nominal: "ConeGeometry") -> np.ndarray:
        """The 9-DOF parameters (n, 9) that take ``nominal`` to this geometry."""
        if nominal.n_views != self.n_views:
            raise ValueError("geometries differ in number of views")
        B0 = nominal.local_frames()
        B1 = self.local_frames()
        out = np.empty((self.n_views, 9))
        out[:, 0:3] = np.einsum("vji,vj->vi", B0, self.source_mm - nominal.source_mm)
        out[:, 3:6] = np.einsum("vji,vj->vi", B0, self.detector_mm - nominal.detector_mm)
        R = np.einsum("vij,vkj->vik", B1, B0)  # world rotation taking frame 0 to frame 1
        rotvec = Rotation.from_matrix(R).as_rotvec()
        out[:, 6:9] = np.einsum("vji,vj->vi", B0, rotvec)
        return out

    # --------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        return {
            "format": "robot_ct_ros.ConeGeometry/1",
            "units": "mm",
            "n_rows": self.n_rows, "n_cols": self.n_cols,
            "row_pitch_mm": self.row_pitch_mm, "col_pitch_mm": self.col_pitch_mm,
            "source_mm": self.source_mm.tolist(), "detector_mm": self.detector_mm.tolist(),
            "u": self.u.tolist(), "v": self.v.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "ConeGeometry":
        fmt = d.get("format", "robot_ct_ros.ConeGeometry/1")
        if fmt != "robot_ct_ros.ConeGeometry/1":
            raise ValueError(f"unknown geometry format {fmt!r}")
        return cls(source_mm=d["source_mm"], detector_mm=d["detector_mm"], u=d["u"], v=d["v"],
                   n_rows=d["n_rows"], n_cols=d["n_cols"], row_pitch_mm=d["row_pitch_mm"],
                   col_pitch_mm=d["col_pitch_mm"])

    def to_json(self) -> str:
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> "ConeGeometry":
        return cls.from_dict(json.loads(text))

    # ------------------------------------------------------------ ASTRA form
    def to_astra_vec(self) -> np.ndarray:
        """ASTRA ``cone_vec`` rows (n, 12): src, detector centre, u*col_pitch, v*row_pitch (mm)."""
        return np.concatenate([self.source_mm, self.detector_mm, self.u * self.col_pitch_mm,
                               self.v * self.row_pitch_mm], axis=1)

    @classmethod
    def from_astra_vec(cls, vectors, n_rows: int, n_cols: int) -> "ConeGeometry":
        vec = np.asarray(vectors, dtype=np.float64).reshape(-1, 12)
        cu = np.linalg.norm(vec[:, 6:9], axis=1)
        rv = np.linalg.norm(vec[:, 9:12], axis=1)
        if np.ptp(cu) > 1e-9 * cu.max() or np.ptp(rv) > 1e-9 * rv.max():
            raise ValueError("pixel pitch varies between views; ConeGeometry needs one pitch")
        return cls(source_mm=vec[:, 0:3], detector_mm=vec[:, 3:6], u=vec[:, 6:9] / cu[:, None],
                   v=vec[:, 9:12] / rv[:, None], n_rows=n_rows, n_cols=n_cols,
                   row_pitch_mm=float(rv[0]), col_pitch_mm=float(cu[0]))


def axis_frame(axis) -> np.ndarray:
    """A grid direction (3 x 3 rotation, columns x, y, z) whose z axis is the scan ``axis``: the
    smallest rotation taking the world z axis there, the axis' sign chosen so that its largest
    component is positive (a scan about +-z gets the identity, one about y a quarter turn about x)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    if a[np.argmax(np.abs(a))] < 0:
        a = -a
    v = np.cross([0.0, 0.0, 1.0], a)
    c = float(a[2])
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def bin_factors(shape, factor: int) -> tuple[int, ...]:
    """The factor each axis of ``shape`` is binned by in a ``factor``-times binning: ``factor``
    where the axis has at least that many pixels (voxels), else 1. Binning thus never reduces a
    dimension to zero: a one-row (fan-beam) detector, or a grid one voxel thick, keeps it."""
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"binning factor must be >= 1, got {factor}")
    return tuple(factor if int(n) >= factor else 1 for n in shape)


def bin_projections(proj: np.ndarray, factor: int, mean: bool = False) -> np.ndarray:
    """Sum (counts) or average (line integrals, ``mean=True``) ``factor`` x ``factor`` blocks.

    Works on (..., rows, cols) arrays. Trailing rows/columns that do not fill a bin are
    dropped, as in ``ConeGeometry.binned``; rows (columns) fewer than ``factor`` are not
    binned (:func:`bin_factors`).
    """
    fr, fc = bin_factors(proj.shape[-2:], factor)
    if fr == fc == 1:
        return proj
    nr, nc = proj.shape[-2] // fr, proj.shape[-1] // fc
    p = proj[..., : nr * fr, : nc * fc]
    p = p.reshape(p.shape[:-2] + (nr, fr, nc, fc))
    return p.mean(axis=(-3, -1)) if mean else p.sum(axis=(-3, -1))


def view_mask(valid_mask, shape) -> np.ndarray:
    """``valid_mask`` (None: all valid) as a read-only bool array of the projections' ``shape``
    (n_views, n_rows, n_cols): one (n_rows, n_cols) map for all views, or one per view.
    ValueError naming both shapes where it does not fit (numpy's broadcast error names neither)."""
    shape = tuple(shape)
    if valid_mask is None:
        return np.ones(shape, bool)
    m = np.asarray(valid_mask, dtype=bool)
    try:
        return np.broadcast_to(m, shape)
    except ValueError:
        raise ValueError(f"valid_mask must have shape {shape[-2:]} (one map for all views) or {shape}, "
                         f"got {m.shape}") from None


def central_points_mm(geom: ConeGeometry) -> np.ndarray:
    """(n_views, 3) the point of each view's detector plane that its central ray (from the source) passes through
    (mm, world): the principal point (the foot of the source's perpendicular, the ray along the detector normal w)
    where the detector holds it, else the detector centre, each way separately: the principal point's offset
    from the detector centre along u is kept when it lies within the detector's columns, and along v within its
    rows, and set to 0 otherwise. A detector shifted in its plane (half-fan) keeps its principal ray; one tilted
    out of its plane so far that the detector does not see the principal ray (25 degrees about v: the principal
    ray misses the axis by SOD sin 25 = 85 mm) gets the ray through its centre."""
    depth = np.einsum("ij,ij->i", geom.detector_mm - geom.source_mm, geom.w)
    off = geom.source_mm + depth[:, None] * geom.w - geom.detector_mm  # principal point - detector centre
    ou, ov = np.einsum("ij,ij->i", off, geom.u), np.einsum("ij,ij->i", off, geom.v)
    ou = np.where(np.abs(ou) <= 0.5 * geom.n_cols * geom.col_pitch_mm, ou, 0.0)
    ov = np.where(np.abs(ov) <= 0.5 * geom.n_rows * geom.row_pitch_mm, ov, 0.0)
    return geom.detector_mm + ou[:, None] * geom.u + ov[:, None] * geom.v


def views_center_mm(geom: ConeGeometry, *, determined_only: bool = False) -> np.ndarray | None:
    """The centre of the views (mm, world): the point nearest, in least squares, to every view's central ray
    (from the source through :func:`central_points_mm`: the principal ray where the detector sees it). Where the
    rays fix no point (one view, or rays all parallel) it is the mean source position, or None with
    ``determined_only``. The default ROI centre of a bag (``ScanData.scan_center_mm``, which ``robot-ct info``
    prints) and the centre the field of view is located about (``field_of_view.field_of_view_extent``)."""
    d = central_points_mm(geom) - geom.source_mm
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-300)
    projectors = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # onto each ray's normal plane
    A = projectors.sum(axis=0)
    if np.linalg.eigvalsh(A)[0] < 1e-9 * geom.n_views:
        return None if determined_only else geom.source_mm.mean(axis=0)
    return np.linalg.solve(A, np.einsum("nij,nj->i", projectors, geom.source_mm))
