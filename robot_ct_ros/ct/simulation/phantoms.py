"""Analytic phantoms (mouse, battery, carotid plaque) and their voxelisation; materials in :data:`MU`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange
from scipy.spatial.transform import Rotation

from robot_ct_ros.ct.geometry import VolumeGrid

__all__ = ["MU", "Primitive", "ellipsoid", "elliptic_cylinder", "box", "spiral", "CapGeometry", "Phantom",
           "voxelize", "mouse_phantom", "battery_phantom", "carotid_plaque_phantom", "interior_neck_phantom"]


# ----------------------------------------------------------------------------- materials
MU = {
    # linear attenuation (1/mm) at ~70 keV: NIST XCOM mass attenuation x typical density
    "air": 0.0,
    "lung": 0.005,          # inflated lung, ~0.26 g/cm3
    "lipid": 0.018,         # adipose tissue / lipid core, ~0.95 g/cm3
    "water": 0.0193,
    "soft": 0.0205,         # soft tissue, ~1.06 g/cm3
    "blood": 0.0207,
    "muscle": 0.0212,
    "vessel_wall": 0.0215,
    "fibrous": 0.026,       # fibrous cap / plaque collagen; exaggerated (~0.022 real) so the cap is measurable
    "trabecular": 0.030,
    "bone": 0.048,          # cortical bone, ~1.9 g/cm3
    "calcification": 0.075, # hydroxyapatite deposit
    "electrolyte": 0.020,   # separator soaked in electrolyte
    "anode": 0.024,         # porous graphite coating
    "cathode": 0.12,        # porous NMC coating
    "aluminium": 0.064,
    "steel": 0.67,
    "copper": 0.99,
}
"""Default attenuation coefficients (1/mm) at ~70 keV used by the phantom factories."""

ELLIPSOID, CYLINDER, BOX, SPIRAL = 0, 1, 2, 3
_KINDS = {"ellipsoid": ELLIPSOID, "cylinder": CYLINDER, "box": BOX, "spiral": SPIRAL}
_MODES = {"set": 0, "add": 1}


# ----------------------------------------------------------------------------- primitives
@dataclass(frozen=True)
class Primitive:
    """One analytic object in world mm.

    ``kind`` is ``"ellipsoid"``, ``"cylinder"``, ``"box"`` or ``"spiral"``; ``center_mm``
    its centre; ``rotvec`` the rotation (radians, rotation vector) taking its local axes to
    the world; ``params`` (up to 6 floats, meaning per kind, see the constructors
    :func:`ellipsoid`, :func:`elliptic_cylinder`, :func:`box`, :func:`spiral`); ``value``
    the attenuation (1/mm); ``mode`` ``"set"`` (paint) or ``"add"``.
    """

    kind: str
    center_mm: tuple
    rotvec: tuple
    params: tuple
    value: float
    mode: str = "set"
    name: str = ""

    def __post_init__(self):
        if self.kind not in _KINDS:
            raise ValueError(f"unknown primitive kind {self.kind!r}")
        if self.mode not in _MODES:
            raise ValueError(f"unknown mode {self.mode!r}")
        object.__setattr__(self, "center_mm", tuple(float(c) for c in self.center_mm))
        object.__setattr__(self, "rotvec", tuple(float(c) for c in self.rotvec))
        p = tuple(float(c) for c in self.params) + (0.0,) * (6 - len(self.params))
        object.__setattr__(self, "params", p[:6])
        object.__setattr__(self, "value", float(self.value))

    @property
    def rotation(self) -> np.ndarray:
        """3 x 3 matrix taking local coordinates to world directions."""
        return Rotation.from_rotvec(self.rotvec).as_matrix()

    def local_half_extent(self) -> np.ndarray:
        p = self.params
        if self.kind == "spiral":
            r = p[0] + p[1] * p[2] / (2 * np.pi) + 0.5 * p[3]
            return np.array([r, r, p[4]])
        return np.array(p[:3])

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned world bounding box (lower, upper corner)."""
        R = self.rotation
        h = self.local_half_extent()
        if self.kind == "ellipsoid":
            ext = np.sqrt(((R * h[None, :]) ** 2).sum(axis=1))
        else:
            ext = np.abs(R) @ h
        ext = ext + 1e-9
        c = np.asarray(self.center_mm)
        return c - ext, c + ext

    def moved(self, rotation, translation_mm=(0.0, 0.0, 0.0)) -> "Primitive":
        """The primitive after the rigid motion x -> rotation @ x + translation_mm."""
        R = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        c = R @ np.asarray(self.center_mm) + np.asarray(translation_mm, dtype=np.float64)
        rotvec = Rotation.from_matrix(R @ self.rotation).as_rotvec()
        return Primitive(self.kind, tuple(c), tuple(rotvec), self.params, self.value, self.mode, self.name)

    def analytic_volume_mm3(self) -> float:
        """Exact volume (mm^3) of the primitive (spiral: arc length x thickness x height)."""
        p = self.params
        if self.kind == "ellipsoid":
            return 4.0 / 3.0 * np.pi * p[0] * p[1] * p[2]
        if self.kind == "box":
            return 8.0 * p[0] * p[1] * p[2]
        if self.kind == "cylinder":
            # polar half angle phi -> parametric angle t of each ellipse; sector area = a b t
            phi = min(p[5], np.pi)
            t_out = np.arctan2(p[0] * np.sin(phi), p[1] * np.cos(phi))
            area = p[0] * p[1] * t_out
            if p[3] > 0:
                area -= p[3] * p[4] * np.arctan2(p[3] * np.sin(phi), p[4] * np.cos(phi))
            return area * 2.0 * p[2]
        a = p[1] / (2 * np.pi)
        theta = np.linspace(0.0, p[2], 200001)
        ds = np.sqrt((p[0] + a * theta) ** 2 + a * a)
        arc = float(np.sum(0.5 * (ds[1:] + ds[:-1]) * np.diff(theta)))
        return arc * p[3] * 2.0 * p[4]


def ellipsoid(center_mm, semi_axes_mm, value, rotvec=(0, 0, 0), mode="set", name="") -> Primitive:
    """Ellipsoid with local semi-axes (a, b, c) mm."""
    return Primitive("ellipsoid", center_mm, rotvec, tuple(semi_axes_mm), value, mode, name)


def elliptic_cylinder(center_mm, semi_axes_mm, half_length_mm, value, inner_semi_axes_mm=None,
                      half_angle_rad=np.pi, rotvec=(0, 0, 0), mode="set", name="") -> Primitive:
    """Finite elliptic cylinder along local z; an annulus when ``inner_semi_axes_mm`` is given;
    an annular sector ``|atan2(y, x)| <= half_angle_rad`` (about local +x) when < pi."""
    a, b = semi_axes_mm
    ai, bi = (0.0, 0.0) if inner_semi_axes_mm is None else inner_semi_axes_mm
    if ai > 0 and (ai > a or bi > b or bi <= 0):
        raise ValueError("inner semi-axes must be positive and inside the outer ones")
    return Primitive("cylinder", center_mm, rotvec, (a, b, half_length_mm, ai, bi, half_angle_rad),
                     value, mode, name)


def box(center_mm, half_sizes_mm, value, rotvec=(0, 0, 0), mode="set", name="") -> Primitive:
    """Box with local half sizes (hx, hy, hz) mm."""
    return Primitive("box", center_mm, rotvec, tuple(half_sizes_mm), value, mode, name)


def spiral(center_mm, r0_mm, pitch_mm, n_turns, thickness_mm, half_length_mm, value,
           phase_rad=0.0, rotvec=(0, 0, 0), mode="set", name="") -> Primitive:
    """Archimedean spiral sheet ``r = r0 + pitch * theta / (2 pi)``, theta in [0, 2 pi n_turns],
    starting at local angle ``phase_rad``, of normal thickness ``thickness_mm``, extruded along
    local z over ``+-half_length_mm``. Voxelised by distance to the curve in each z-slice."""
    rv = (Rotation.from_rotvec(rotvec) * Rotation.from_rotvec([0, 0, phase_rad])).as_rotvec()
    return Primitive("spiral", center_mm, tuple(rv),
                     (r0_mm, pitch_mm, 2 * np.pi * n_turns, thickness_mm, half_length_mm), value, mode, name)


@dataclass(frozen=True)
class CapGeometry:
    """Where the fibrous cap of a plaque phantom lies (world mm).

    The cap is the plaque tissue between the lumen and the lipid core along ``direction``
    (unit, perpendicular to the vessel ``axis``) from ``axis_point_mm``; it is uniform over
    ``+-half_length_mm`` along the axis. ``lumen_point_mm`` and ``core_point_mm`` are its
    inner and outer boundary points on that line, ``thickness_mm`` their distance.
    """

    axis_point_mm: tuple
    axis: tuple
    direction: tuple
    lumen_radius_mm: float
    thickness_mm: float
    core_depth_mm: float
    half_length_mm: float

    @property
    def lumen_point_mm(self) -> np.ndarray:
        return np.asarray(self.axis_point_mm) + self.lumen_radius_mm * np.asarray(self.direction)

    @property
    def core_point_mm(self) -> np.ndarray:
        return self.lumen_point_mm + self.thickness_mm * np.asarray(self.direction)


@dataclass(frozen=True, eq=False)
class Phantom:
    """An ordered set of painted primitives (see the module docstring)."""

    name: str
    primitives: tuple
    background: float = 0.0
    cap: CapGeometry | None = None
    info: dict = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "primitives", tuple(self.primitives))
        if not self.primitives:
            raise ValueError("a phantom needs at least one primitive")

    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        """World bounding box of all primitives (lower, upper corner)."""
        b = [p.bounds_mm() for p in self.primitives]
        return np.min([x[0] for x in b], axis=0), np.max([x[1] for x in b], axis=0)

    def moved(self, rotation, translation_mm=(0.0, 0.0, 0.0)) -> "Phantom":
        """The phantom after the rigid motion x -> rotation @ x + translation_mm (its cap, if any,
        is dropped: a cap's measurement lines are given in the original frame)."""
        return Phantom(self.name, tuple(p.moved(rotation, translation_mm) for p in self.primitives), self.background,
                       None, dict(self.info))

    def grid(self, voxel_size_mm, margin_mm: float = 0.0) -> VolumeGrid:
        """A grid covering the whole phantom with the given voxel size."""
        lo, hi = self.bounds_mm()
        lo, hi = lo - margin_mm, hi + margin_mm
        vs = np.broadcast_to(np.asarray(voxel_size_mm, float), (3,))
        n = np.maximum(1, np.ceil((hi - lo) / vs).astype(int))
        return VolumeGrid.centered(tuple(n[::-1]), vs, 0.5 * (lo + hi))

    def _arrays(self):
        n = len(self.primitives)
        kind = np.empty(n, np.int64)
        mode = np.empty(n, np.int64)
        center = np.empty((n, 3))
        rot = np.empty((n, 3, 3))
        par = np.empty((n, 6))
        value = np.empty(n)
        bbox = np.empty((n, 6))
        for q, p in enumerate(self.primitives):
            kind[q] = _KINDS[p.kind]
            mode[q] = _MODES[p.mode]
            center[q] = p.center_mm
            rot[q] = p.rotation.T  # world -> local
            par[q] = p.params
            value[q] = p.value
            lo, hi = p.bounds_mm()
            bbox[q, :3], bbox[q, 3:] = lo, hi
        return kind, mode, center, rot, par, value, bbox

    def evaluate(self, points_mm) -> np.ndarray:
        """Exact (un-anti-aliased) attenuation at world points (n, 3) -> (n,) float64."""
        pts = np.ascontiguousarray(np.atleast_2d(points_mm), dtype=np.float64)
        kind, mode, center, rot, par, value, bbox = self._arrays()
        return _evaluate_points(pts, kind, mode, center, rot, par, value, bbox, float(self.background))


# ----------------------------------------------------------------------------- numba kernels
@njit(inline="always", fastmath=True, cache=True)
def _coverage(kind, lx, ly, lz, p0, p1, p2, p3, p4, p5, h):
    """Fraction (0..1) of a sample at local (lx, ly, lz) inside the primitive.
    Binary except for spirals, which are box-filtered along the normal over width h (h <= 0: binary)."""
    if kind == ELLIPSOID:
        q = (lx / p0) ** 2 + (ly / p1) ** 2 + (lz / p2) ** 2
        return 1.0 if q <= 1.0 else 0.0
    if kind == BOX:
        return 1.0 if (abs(lx) <= p0 and abs(ly) <= p1 and abs(lz) <= p2) else 0.0
    if kind == CYLINDER:
        if abs(lz) > p2:
            return 0.0
        if (lx / p0) ** 2 + (ly / p1) ** 2 > 1.0:
            return 0.0
        if p3 > 0.0 and (lx / p3) ** 2 + (ly / p4) ** 2 <= 1.0:
            return 0.0
        if p5 < math.pi and abs(math.atan2(ly, lx)) > p5:
            return 0.0
        return 1.0
    # spiral: p0 r0, p1 pitch, p2 theta_max, p3 thickness, p4 half length
    if abs(lz) > p4:
        return 0.0
    r = math.sqrt(lx * lx + ly * ly)
    phi = math.atan2(ly, lx)
    if phi < 0.0:
        phi += 2.0 * math.pi
    a = p1 / (2.0 * math.pi)
    n = int(math.floor((r - p0 - a * phi) / p1 + 0.5))
    best = 1e30
    for m in range(n - 1, n + 2):
        theta = phi + 2.0 * math.pi * m
        if theta < 0.0 or theta > p2:
            continue
        d = abs(r - (p0 + a * theta))
        if d < best:
            best = d
    if best >= 1e29:
        return 0.0
    d = best * r / math.sqrt(r * r + a * a)  # radial -> normal distance
    t2 = 0.5 * p3
    if h <= 0.0:
        return 1.0 if d <= t2 else 0.0
    ov = min(d + 0.5 * h, t2) - max(d - 0.5 * h, -t2)
    if ov <= 0.0:
        return 0.0
    return min(ov / h, 1.0)


@njit(parallel=True, fastmath=True, cache=True)
def _evaluate_points(pts, kind, mode, center, rot, par, value, bbox, background):
    n = pts.shape[0]
    out = np.empty(n)
    for q in prange(n):
        x, y, z = pts[q, 0], pts[q, 1], pts[q, 2]
        val = background
        for p in range(kind.shape[0]):
            if (x < bbox[p, 0] or x > bbox[p, 3] or y < bbox[p, 1] or y > bbox[p, 4]
                    or z < bbox[p, 2] or z > bbox[p, 5]):
                continue
            dx, dy, dz = x - center[p, 0], y - center[p, 1], z - center[p, 2]
            lx = rot[p, 0, 0] * dx + rot[p, 0, 1] * dy + rot[p, 0, 2] * dz
            ly = rot[p, 1, 0] * dx + rot[p, 1, 1] * dy + rot[p, 1, 2] * dz
            lz = rot[p, 2, 0] * dx + rot[p, 2, 1] * dy + rot[p, 2, 2] * dz
            c = _coverage(kind[p], lx, ly, lz, par[p, 0], par[p, 1], par[p, 2], par[p, 3], par[p, 4],
                          par[p, 5], 0.0)
            if c > 0.0:
                if mode[p] == 0:
                    val = val + c * (value[p] - val)
                else:
                    val = val + c * value[p]
        out[q] = val
    return out


@njit(parallel=True, fastmath=True, cache=True)
def _voxelize_kernel(nz, ny, nx, origin, vs, ss, kind, mode, center, rot, par, value, bbox, background):
    out = np.empty((nz, ny, nx), np.float32)
    hx, hy, hz = vs[0] / ss, vs[1] / ss, vs[2] / ss
    # world coordinate of sub-sample 0 along each axis
    x0 = origin[0] - 0.5 * vs[0] + 0.5 * hx
    y0 = origin[1] - 0.5 * vs[1] + 0.5 * hy
    nsx, nsy = nx * ss, ny * ss
    h_aa = 0.5 * (hx + hy)
    npr = kind.shape[0]
    inv = 1.0 / (ss * ss * ss)
    for k in prange(nz):
        acc = np.zeros((ny, nx))
        buf = np.empty((nsy, nsx))
        for sz in range(ss):
            z = origin[2] - 0.5 * vs[2] + (sz + 0.5) * hz + k * vs[2]
            buf[:, :] = background
            for p in range(npr):
                if z < bbox[p, 2] or z > bbox[p, 5]:
                    continue
                fi0 = max(0.0, math.floor((bbox[p, 0] - x0) / hx))
                fi1 = min(nsx - 1.0, math.ceil((bbox[p, 3] - x0) / hx))
                fj0 = max(0.0, math.floor((bbox[p, 1] - y0) / hy))
                fj1 = min(nsy - 1.0, math.ceil((bbox[p, 4] - y0) / hy))
                if fi0 > fi1 or fj0 > fj1:
                    continue
                i0, i1, j0, j1 = int(fi0), int(fi1), int(fj0), int(fj1)
                kd, md, val = kind[p], mode[p], value[p]
                p0, p1, p2, p3, p4, p5 = par[p, 0], par[p, 1], par[p, 2], par[p, 3], par[p, 4], par[p, 5]
                cx, cy, cz = center[p, 0], center[p, 1], center[p, 2]
                r00, r01, r02 = rot[p, 0, 0], rot[p, 0, 1], rot[p, 0, 2]
                r10, r11, r12 = rot[p, 1, 0], rot[p, 1, 1], rot[p, 1, 2]
                r20, r21, r22 = rot[p, 2, 0], rot[p, 2, 1], rot[p, 2, 2]
                dz = z - cz
                for j in range(j0, j1 + 1):
                    dy = y0 + j * hy - cy
                    for i in range(i0, i1 + 1):
                        dx = x0 + i * hx - cx
                        lx = r00 * dx + r01 * dy + r02 * dz
                        ly = r10 * dx + r11 * dy + r12 * dz
                        lz = r20 * dx + r21 * dy + r22 * dz
                        c = _coverage(kd, lx, ly, lz, p0, p1, p2, p3, p4, p5, h_aa)
                        if c > 0.0:
                            if md == 0:
                                buf[j, i] += c * (val - buf[j, i])
                            else:
                                buf[j, i] += c * val
            for j in range(nsy):
                jj = j // ss
                for i in range(nsx):
                    acc[jj, i // ss] += buf[j, i]
        for j in range(ny):
            for i in range(nx):
                out[k, j, i] = acc[j, i] * inv
    return out


def voxelize(phantom, grid: VolumeGrid, supersample: int = 2) -> np.ndarray:
    """Voxelise a :class:`Phantom` (or a sequence of primitives) on ``grid``.

    Each voxel is the mean over ``supersample**3`` regularly spaced sample points (float32,
    (nz, ny, nx)). Parallel over z-slices; cost scales with the voxels each primitive's
    bounding box covers.
    """
    if not isinstance(phantom, Phantom):
        phantom = Phantom("primitives", tuple(phantom))
    if supersample < 1:
        raise ValueError("supersample must be >= 1")
    if not grid.axis_aligned:  # voxelise in the grid's own frame
        grid, R = grid.in_own_frame()
        phantom = phantom.moved(R)
    kind, mode, center, rot, par, value, bbox = phantom._arrays()
    nz, ny, nx = grid.shape_zyx
    return _voxelize_kernel(nz, ny, nx, np.asarray(grid.origin_mm, float), np.asarray(grid.voxel_size_mm, float),
                            int(supersample), kind, mode, center, rot, par, value, bbox,
                            float(phantom.background))


# ----------------------------------------------------------------------------- phantom factories
def _rng(seed_or_rng) -> np.random.Generator:
    if isinstance(seed_or_rng, np.random.Generator):
        return seed_or_rng
    return np.random.default_rng(seed_or_rng)


def mouse_phantom(body_width_mm: float = 25.0, length_mm: float = 80.0, center_mm=(0.0, 0.0, 0.0),
                  n_details: int = 16, seed: int = 0) -> Phantom:
    """A mouse-like phantom, long axis along z, dorsal side towards -y.

    ``center_mm`` is the centre of the thorax (the natural interior ROI). Body of soft tissue
    under a thin fat layer, spine (vertebral bodies with cortical shell, neural arches),
    ribs (annular sectors open ventrally), sternum, two lungs, heart, trachea, liver,
    kidneys, gas pockets and ``n_details`` random small details (calcifications, fat
    droplets, air bubbles, dense soft tissue) placed with ``seed``. All sizes scale with
    ``body_width_mm / 25``.
    """
    s = body_width_mm / 25.0
    c = np.asarray(center_mm, float)
    L = float(length_mm)
    rng = _rng(seed)
    P = []

    def at(x, y, z):
        return tuple(c + np.array([x, y, z]))

    zb = -0.2 * L  # body centre: the thorax lies towards +z, the abdomen towards -z
    P.append(ellipsoid(at(0, 0, zb), (12.5 * s, 10.0 * s, L / 2), MU["lipid"], name="fat"))
    P.append(ellipsoid(at(0, 0, zb), (11.8 * s, 9.3 * s, L / 2 - 0.7 * s), MU["soft"], name="body"))
    # thorax organs
    for sx in (-1, 1):
        P.append(ellipsoid(at(sx * 4.6 * s, 0.8 * s, 0), (3.6 * s, 4.6 * s, 7.0 * s), MU["lung"],
                           rotvec=(0, 0, sx * 0.15), name="lung"))
    P.append(ellipsoid(at(0.8 * s, 2.6 * s, -1.0 * s), (3.2 * s, 3.0 * s, 3.8 * s), MU["blood"],
                       rotvec=(0.3, 0.0, 0.4), name="heart"))
    P.append(elliptic_cylinder(at(0, 4.6 * s, 0.3 * L), (0.7 * s, 0.6 * s), 0.3 * L - 3.0 * s, MU["air"],
                               inner_semi_axes_mm=None, name="trachea"))
    # abdomen
    P.append(ellipsoid(at(-2.0 * s, 1.5 * s, -11.0 * s), (7.5 * s, 6.0 * s, 4.5 * s), MU["muscle"], name="liver"))
    for sx in (-1, 1):
        P.append(ellipsoid(at(sx * 4.5 * s, -4.0 * s, -18.0 * s), (1.8 * s, 1.4 * s, 3.0 * s), MU["muscle"],
                           name="kidney"))
    for _ in range(4):
        pos = at(rng.uniform(-5, 5) * s, rng.uniform(-1, 5) * s, rng.uniform(-32, -20) * s)
        P.append(ellipsoid(pos, tuple(rng.uniform(0.6, 1.6, 3) * s), MU["air"],
                           rotvec=tuple(rng.normal(0, 0.5, 3)), name="gas"))
    # spine: vertebrae every 2 mm (scaled) along the whole body, discs in between
    z_lo, z_hi = zb - L / 2 + 4 * s, zb + L / 2 - 4 * s
    for z in np.arange(z_lo, z_hi, 2.0 * s):
        P.append(elliptic_cylinder(at(0, -6.6 * s, z), (1.5 * s, 1.2 * s), 0.8 * s, MU["trabecular"],
                                   name="vertebral body"))
        P.append(elliptic_cylinder(at(0, -6.6 * s, z), (1.5 * s, 1.2 * s), 0.8 * s, MU["bone"],
                                   inner_semi_axes_mm=(1.2 * s, 0.9 * s), name="cortex"))
        P.append(elliptic_cylinder(at(0, -8.7 * s, z), (1.1 * s, 0.95 * s), 0.6 * s, MU["bone"],
                                   inner_semi_axes_mm=(0.6 * s, 0.5 * s), name="neural arch"))
    # ribs: annular sectors open ventrally (+y); local +x points dorsally (-y)
    for z in np.arange(-8.0 * s, 8.01 * s, 1.6 * s):
        P.append(elliptic_cylinder(at(0, 0.4 * s, z), (10.0 * s, 8.2 * s), 0.22 * s, MU["bone"],
                                   inner_semi_axes_mm=(9.6 * s, 7.8 * s), half_angle_rad=np.deg2rad(145),
                                   rotvec=(0, 0, -np.pi / 2), name="rib"))
        P.append(box(at(0, 8.3 * s, z), (0.5 * s, 0.3 * s, 0.5 * s), MU["bone"], name="sternum"))
    # small details
    kinds = (("calcification", 0.05, 0.25), ("lipid", 0.1, 0.4), ("air", 0.05, 0.3), ("muscle", 0.1, 0.4),
             ("trabecular", 0.08, 0.3))
    for q in range(n_details):
        mat, rmin, rmax = kinds[q % len(kinds)]
        # uniformly inside an ellipse within the body, avoiding the spine column
        for _ in range(100):
            x, y = rng.uniform(-8, 8) * s, rng.uniform(-5, 7) * s
            if (x / 8.5) ** 2 + (y / 7.0) ** 2 < s * s and abs(x) > 2.0 * s:
                break
        z = rng.uniform(-0.35 * L, 0.15 * L)
        r = rng.uniform(rmin, rmax) * s
        P.append(ellipsoid(at(x, y, z), (r, r * rng.uniform(0.6, 1.0), r * rng.uniform(0.6, 1.4)), MU[mat],
                           rotvec=tuple(rng.normal(0, 1, 3)), name=f"detail:{mat}"))
    return Phantom("mouse", tuple(P), info={"body_width_mm": body_width_mm, "length_mm": L, "seed": seed})


def battery_phantom(radius_mm: float = 9.0, height_mm: float = 20.0, pitch_mm: float = 0.4,
                    mandrel_radius_mm: float = 1.0, can_thickness_mm: float = 0.25,
                    cu_thickness_mm: float = 0.015, al_thickness_mm: float = 0.02,
                    electrode_fraction: float = 0.35, center_mm=(0.0, 0.0, 0.0), n_defects: int = 6,
                    seed: int = 0) -> Phantom:
    """A cylindrical Li-ion cell (axis along z): a "jelly roll" of electrode spirals in a steel can.

    Per turn of ``pitch_mm``: an anode (graphite coating on a copper foil) and, half a pitch
    further out, a cathode (NMC coating on an aluminium foil); each electrode is
    ``electrode_fraction * pitch_mm`` thick, the rest is electrolyte-soaked separator. The
    foils are thin high-attenuation Archimedean spirals. A central mandrel hole, a nickel-like
    tab and ``n_defects`` seeded defects (gas voids and metal particles) on the roll.
    """
    c = np.asarray(center_mm, float)
    rng = _rng(seed)
    R, H, t_can = float(radius_mm), float(height_mm), float(can_thickness_mm)
    P = [
        elliptic_cylinder(c, (R, R), H / 2 + t_can, MU["steel"], name="can"),
        elliptic_cylinder(c, (R - t_can, R - t_can), H / 2, MU["electrolyte"], name="fill"),
    ]
    r0 = mandrel_radius_mm + 0.2
    r_max = R - t_can - 0.15
    n_turns = max(1, int((r_max - r0 - pitch_mm) / pitch_mm))
    hl = H / 2 - 0.3
    t_el = electrode_fraction * pitch_mm
    P.append(spiral(c, r0, pitch_mm, n_turns, t_el, hl, MU["anode"], phase_rad=0.0, name="anode coating"))
    P.append(spiral(c, r0, pitch_mm, n_turns, t_el, hl - 0.1, MU["cathode"], phase_rad=np.pi,
                    name="cathode coating"))
    P.append(spiral(c, r0, pitch_mm, n_turns, cu_thickness_mm, hl + 0.1, MU["copper"], phase_rad=0.0,
                    name="copper foil"))
    P.append(spiral(c, r0, pitch_mm, n_turns, al_thickness_mm, hl, MU["aluminium"], phase_rad=np.pi,
                    name="aluminium foil"))
    P.append(elliptic_cylinder(c, (mandrel_radius_mm, mandrel_radius_mm), H / 2, MU["air"], name="mandrel"))
    P.append(box(tuple(c + [r_max - 0.6, 0.0, 0.0]), (0.05, 1.5, 0.45 * H), 0.6, name="tab"))
    for q in range(n_defects):
        rr = rng.uniform(r0 + 1.0, r_max - 0.5)
        ang = rng.uniform(0, 2 * np.pi)
        z = rng.uniform(-0.4 * H, 0.4 * H)
        pos = tuple(c + [rr * np.cos(ang), rr * np.sin(ang), z])
        if q % 2 == 0:
            P.append(ellipsoid(pos, tuple(rng.uniform(0.08, 0.25, 3)), MU["air"], name="defect:void"))
        else:
            P.append(ellipsoid(pos, tuple(rng.uniform(0.02, 0.06, 3)), MU["copper"], name="defect:particle"))
    return Phantom("battery", tuple(P), info={"radius_mm": R, "height_mm": H, "pitch_mm": pitch_mm,
                                              "n_turns": n_turns, "r0_mm": r0, "seed": seed})


def carotid_plaque_phantom(cap_thickness_mm: float = 0.065, lumen_radius_mm: float = 2.5,
                           wall_thickness_mm: float = 0.8, plaque_thickness_mm: float = 2.2,
                           core_radial_mm: float = 0.6, core_tangential_mm: float = 1.2,
                           core_half_length_mm: float = 3.0, plaque_half_length_mm: float = 5.0,
                           cap_direction_rad: float = -np.pi / 2, neck_semi_axes_mm=(55.0, 45.0),
                           length_mm: float = 60.0, center_mm=(0.0, 0.0, 0.0), calcification: bool = True,
                           cap_mu: float | None = None, lumen_mu: float | None = None, seed: int = 0) -> Phantom:
    """A neck with a carotid artery (axis along z through ``center_mm``) carrying a plaque.

    The neck (soft tissue under a fat layer, vertebra, trachea, muscle, jugular vein) is much
    larger than any ROI, so the scan is truncated. The plaque is an eccentric thickening of the
    wall towards ``cap_direction_rad`` (angle in the x-y plane) made of fibrous tissue
    (``cap_mu``, default ``MU["fibrous"]``, brighter than blood and lipid so the cap is a
    ridge). Its lipid core, an elliptic cylinder (radial/tangential semi-axes, half length),
    sits ``cap_thickness_mm`` from the lumen along the cap direction: the fibrous cap. A
    calcification lies in the plaque away from the cap. The returned phantom's ``cap`` holds
    the cap geometry.
    """
    if cap_thickness_mm <= 0:
        raise ValueError("cap_thickness_mm must be positive")
    if lumen_radius_mm + cap_thickness_mm + 2 * core_radial_mm >= lumen_radius_mm + plaque_thickness_mm - 0.1:
        raise ValueError("lipid core does not fit in the plaque: raise plaque_thickness_mm")
    rng = _rng(seed)
    c = np.asarray(center_mm, float)
    d = np.array([np.cos(cap_direction_rad), np.sin(cap_direction_rad), 0.0])
    t = np.array([-d[1], d[0], 0.0])
    cap_mu = MU["fibrous"] if cap_mu is None else float(cap_mu)
    lumen_mu = MU["blood"] if lumen_mu is None else float(lumen_mu)
    hl = length_mm / 2
    # neck centred medially and posteriorly of the carotid (which lies at +x, anterior side +y)
    nc = c + np.array([-28.0, -6.0, 0.0])
    na, nb = neck_semi_axes_mm
    P = [
        elliptic_cylinder(nc, (na, nb), hl, MU["lipid"], name="neck fat"),
        elliptic_cylinder(nc, (na - 3, nb - 3), hl, MU["soft"], name="neck"),
        elliptic_cylinder(nc + [10, 14, 0], (12, 4.5), hl, MU["muscle"], rotvec=(0, 0, -0.6), name="muscle"),
        elliptic_cylinder(nc + [-10, 14, 0], (12, 4.5), hl, MU["muscle"], rotvec=(0, 0, 0.6), name="muscle"),
        elliptic_cylinder(nc + [0, -14, 0], (9.0, 7.0), hl, MU["trabecular"], name="vertebral body"),
        elliptic_cylinder(nc + [0, -14, 0], (9.0, 7.0), hl, MU["bone"], inner_semi_axes_mm=(8.0, 6.0),
                          name="cortex"),
        elliptic_cylinder(nc + [0, -24, 0], (6.0, 4.5), hl, MU["bone"], inner_semi_axes_mm=(4.5, 3.2),
                          name="neural arch"),
        elliptic_cylinder(nc + [0, 24, 0], (8.0, 6.0), hl, MU["soft"], inner_semi_axes_mm=(7.0, 5.0),
                          name="trachea wall"),
        elliptic_cylinder(nc + [0, 24, 0], (7.0, 5.0), hl, MU["air"], name="trachea"),
        elliptic_cylinder(c + 7.8 * np.array([np.cos(cap_direction_rad + np.pi * 0.75),
                                              np.sin(cap_direction_rad + np.pi * 0.75), 0.0]),
                          (3.0, 2.2), hl, MU["blood"], name="jugular vein"),
    ]
    r_l, T_p, T_w = float(lumen_radius_mm), float(plaque_thickness_mm), float(wall_thickness_mm)
    P.append(elliptic_cylinder(c, (r_l + T_w, r_l + T_w), hl, MU["vessel_wall"], name="vessel wall"))
    # plaque: eccentric cylinder, wall thickness T_p towards d and T_w opposite
    r_p, e = r_l + 0.5 * (T_p + T_w), 0.5 * (T_p - T_w)
    P.append(elliptic_cylinder(c + e * d, (r_p, r_p), plaque_half_length_mm, cap_mu, name="plaque"))
    P.append(elliptic_cylinder(c, (r_l, r_l), hl, lumen_mu, name="lumen"))
    rot_d = (0.0, 0.0, float(cap_direction_rad))  # local +x along d
    core_c = c + (r_l + cap_thickness_mm + core_radial_mm) * d
    P.append(elliptic_cylinder(core_c, (core_radial_mm, core_tangential_mm), core_half_length_mm, MU["lipid"],
                               rotvec=rot_d, name="lipid core"))
    if calcification:
        ang = cap_direction_rad + np.deg2rad(55) * (1 if rng.uniform() < 0.5 else -1)
        pc = c + (r_l + 0.45 * T_p) * np.array([np.cos(ang), np.sin(ang), 0.0])
        pc[2] += rng.uniform(-1.0, 1.0)
        P.append(ellipsoid(pc, (0.3, 0.25, 0.8), MU["calcification"], rotvec=(0, 0, ang), name="calcification"))
    cap = CapGeometry(axis_point_mm=tuple(c), axis=(0.0, 0.0, 1.0), direction=tuple(d), lumen_radius_mm=r_l,
                      thickness_mm=float(cap_thickness_mm), core_depth_mm=2 * core_radial_mm,
                      half_length_mm=float(core_half_length_mm))
    return Phantom("carotid_plaque", tuple(P), cap=cap,
                   info={"cap_thickness_mm": cap_thickness_mm, "cap_mu": cap_mu, "lumen_mu": lumen_mu,
                         "seed": seed, "tangent": tuple(t)})


def interior_neck_phantom(seed: int = 0, body_width_mm: float = 41.0) -> Phantom:
    """A neck of additive ellipsoids for interior scans, with a carotid plaque at the origin.

    The body is ``body_width_mm`` wide (an interior scan's field of view of ~6.6 mm sees a sixth
    of it); outside the ROI: vertebrae (cortex, trabecular bone, neural arch, a transverse
    process), trachea, muscles, a vein, a mandible-like bone and random blobs at all heights;
    inside: the vessel wall and lumen, a plaque, a calcification, a rod and micro-calcifications.
    The neck runs along z. Every primitive is an additive ellipsoid, so RTK's analytic projector
    gives exact line integrals of the same object
    (:func:`robot_ct_ros.ct.rtk_bridge.rtk_ellipsoid_projections`).
    """
    s = body_width_mm / 41.0
    c = np.array([-9.0, -3.0, 0.0]) * s

    def e(center, axes, density, name, about_y_deg=0.0, about_z_deg=0.0):
        rot = Rotation.from_euler("zy", [about_z_deg, about_y_deg], degrees=True).as_rotvec()
        return ellipsoid(tuple(center), tuple(axes), density, rotvec=tuple(rot), mode="add", name=name)

    prims = [
        e(c, (20.5 * s, 15.5 * s, 90.0), 0.018, "body (fat)"),
        e(c, (18.5 * s, 13.5 * s, 90.0), 0.0025, "body (soft)"),
        e(c + [0, -13 * s, 3.0], (7.5 * s, 5.5 * s, 7.0), 0.027, "vertebral cortex"),
        e(c + [0, -13 * s, 3.0], (6.8 * s, 4.8 * s, 6.3), -0.017, "vertebral trabecular bone"),
        e(c + [0, -13 * s, -13.0], (7.5 * s, 5.5 * s, 7.0), 0.027, "vertebral cortex 2"),
        e(c + [0, -13 * s, -13.0], (6.8 * s, 4.8 * s, 6.3), -0.017, "vertebral trabecular bone 2"),
        e(c + [0, -21.5 * s, 3.0], (4.5 * s, 2.8 * s, 5.0), 0.026, "neural arch"),
        e(c + [5.5 * s, -12.5 * s, 0.0], (1.8 * s, 3.5 * s, 30.0), 0.02, "transverse process", about_y_deg=25.0),
        e(c + [0, 10.0 * s, 0], (7.5 * s, 6.0 * s, 90.0), 0.002, "trachea wall"),
        e(c + [0, 10.0 * s, 0], (6.5 * s, 5.0 * s, 90.0), -0.0225, "trachea air"),
        e([2.0 * s, 7.5 * s, 0.0], (9.0 * s, 3.0 * s, 90.0), 0.0012, "muscle"),
        e(c + [-11.0 * s, 6.0 * s, 0], (6.0 * s, 4.0 * s, 90.0), 0.0012, "muscle 2"),
        e([5.5 * s, 3.2 * s, 0.0], (2.6 * s, 2.0 * s, 90.0), 0.0003, "jugular vein"),
        e([7.0 * s, -6.5 * s, 0.0], (2.0 * s, 3.0 * s, 60.0), 0.010, "mandible-like bone", about_y_deg=15.0),
    ]
    rng = np.random.default_rng(seed)
    while sum(p.name.startswith("blob") for p in prims) < 8:  # outside the field of view, all heights
        p = c + rng.uniform([-17 * s, -12 * s, -8], [17 * s, 12 * s, 8])
        if np.hypot(p[0], p[1]) < 5.0 or np.hypot((p[0] - c[0]) / (17 * s), (p[1] - c[1]) / (12 * s)) > 1.0:
            continue
        prims.append(e(p, rng.uniform(0.8, 3.0, 3), float(rng.choice([-1, 1]) * rng.uniform(0.003, 0.012)),
                       f"blob {len(prims)}", about_y_deg=float(rng.uniform(-60, 60))))
    prims += [
        e([0.0, 0.0, 0.0], (2.7, 2.7, 90.0), 0.0015, "vessel wall"),
        e([0.0, 0.0, 0.0], (2.0, 2.0, 90.0), -0.0013, "lumen"),
        e([0.0, -2.3, 0.3], (1.8, 0.8, 2.5), 0.006, "plaque"),
        e([1.2, -1.9, -0.5], (0.35, 0.25, 0.8), 0.05, "calcification", about_y_deg=30.0),
        e([-0.3, 0.2, 0.6], (0.15, 0.15, 1.0), 0.02, "rod", about_y_deg=40.0),
    ]
    n = 0
    while n < 7:
        p = rng.uniform([-2.6, -2.6, -1.5], [2.6, 2.6, 1.5])
        if np.hypot(p[0], p[1]) > 2.8:
            continue
        prims.append(e(p, rng.uniform(0.08, 0.2, 3), float(rng.uniform(0.02, 0.05)), f"micro-calcification {n}",
                       about_y_deg=float(rng.uniform(-90, 90))))
        n += 1
    return Phantom("interior neck", tuple(prims), info={"body_width_mm": body_width_mm})
