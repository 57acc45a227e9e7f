"""Simulation of a robotic interior CT scan: phantoms, photon-counting detector, geometric errors.

Units and conventions are those of :mod:`robot_ct_ros.ct.geometry` (world mm, radians,
``volume[k, j, i]`` = (z, y, x), ``proj[view, row, col]``). Attenuation coefficients are
linear attenuation in 1/mm at an effective energy of about 70 keV (see :data:`MU`).

Phantoms
    A :class:`Phantom` is an ordered list of analytic :class:`Primitive` objects in world
    mm (ellipsoids, finite elliptic cylinders / annuli / annular sectors, boxes and
    Archimedean spirals). Primitives are *painted* in order: mode ``"set"`` replaces the
    value inside the primitive, mode ``"add"`` adds to it. :func:`voxelize` evaluates the
    painting on ``supersample**3`` points per voxel (numba, parallel over z-slices) and
    averages them. Spirals (thin foils) are anti-aliased along their normal: each sample
    takes the fraction of a sample-sized window that the foil covers, so a 15 um copper
    foil keeps its mass on a 40 um grid.

Detector
    :class:`DetectorModel` is a Timepix-like photon-counting detector read out ``binning``
    x ``binning`` binned. Raw pixels lie on chips of ``chip_size_px`` with ``chip_gap_px``
    insensitive pixels between chips (gaps start after the first chip at raw index 0).
    Dead pixels and chip gaps count 0; hot pixels saturate. The bad-pixel map (gaps, dead,
    hot) is known, as it is for a calibrated detector, and binning sums only the valid raw
    pixels of a bin, for the projections and for the flat field alike. The flat-field ratio
    of a partly bad bin is therefore unbiased (equivalent to scaling by the number of valid
    raw pixels) while its counts stay honest Poisson counts; a binned pixel with fewer than
    ``min_valid_fraction`` valid raw pixels is masked.

Geometric errors
    :class:`GeometryErrorModel` samples per-view 9-DOF parameters (geometry.py convention,
    apply with ``geom.perturbed(params)``): independent per-view errors (robot
    coordination), slow drift (detector creep) and static offsets.

Scan simulation
    :func:`simulate_scan` voxelises the phantom finer than the reconstruction (avoids the
    inverse crime), optionally as two parts (a fine ROI grid and a coarse grid for the
    rest of the irradiated object, which only feeds truncation), forward projects with
    :func:`robot_ct_ros.ct.projector.forward_project` onto the *raw* detector (one ray per
    raw pixel, so a binned pixel integrates binning**2 rays), applies the detector model
    and bins. The geometry passed in is the readout (binned) geometry that reconstruction
    uses; the raw geometry is ``raw_geometry(geom, binning)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from .geometry import ConeGeometry, VolumeGrid, bin_projections

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


# ----------------------------------------------------------------------------- detector model
@dataclass(frozen=True)
class DetectorModel:
    """Timepix-like photon-counting detector, read out ``binning`` x ``binning`` binned.

    ``photons_per_pixel``: expected unattenuated counts per *binned* pixel per view (the
    flat field). The design's "4,000 photons per 110 um pixel through 13 cm of water" is
    ``DetectorModel.from_transmitted(4000, 130.0)`` (I0 ~ 49,000). ``flat_field_sigma``:
    relative raw-pixel gain variation (fixed pattern, in flat and projections alike).
    ``flat_frames``: frames averaged into the flat field. ``saturation_counts``: raw counter
    maximum (hot pixels sit there). ``poisson=False`` gives the noiseless expectation. The
    fixed pattern (gain, dead, hot) is drawn from ``seed``; Poisson noise from the ``rng``
    passed to :func:`simulate_counts`.
    """

    photons_per_pixel: float = 4000.0
    binning: int = 2
    chip_size_px: int = 256
    chip_gap_px: int = 2
    dead_pixel_fraction: float = 1e-3
    hot_pixel_fraction: float = 2e-4
    flat_field_sigma: float = 0.03
    flat_frames: int = 20
    saturation_counts: float = 65535.0
    min_valid_fraction: float = 0.5
    poisson: bool = True
    raw_pitch_mm: float = 0.055
    seed: int = 0

    @classmethod
    def from_transmitted(cls, photons_behind: float = 4000.0, water_path_mm: float = 130.0,
                         mu_water: float = MU["water"], **kw) -> "DetectorModel":
        """A model whose flat field gives ``photons_behind`` counts behind ``water_path_mm`` of water."""
        return cls(photons_per_pixel=photons_behind * float(np.exp(mu_water * water_path_mm)), **kw)

    def raw_shape(self, binned_shape) -> tuple[int, int]:
        return (int(binned_shape[0]) * self.binning, int(binned_shape[1]) * self.binning)

    def gap_mask(self, raw_shape) -> np.ndarray:
        """True on raw pixels that fall in a gap between chips, (rows, cols)."""
        period = self.chip_size_px + self.chip_gap_px
        rows = (np.arange(raw_shape[0]) % period) >= self.chip_size_px
        cols = (np.arange(raw_shape[1]) % period) >= self.chip_size_px
        return rows[:, None] | cols[None, :]

    def pixel_maps(self, raw_shape):
        """Fixed pattern of the raw detector from ``seed``: (gain f64, dead bool, hot bool, gap bool)."""
        rng = np.random.default_rng(self.seed)
        gain = np.clip(1.0 + self.flat_field_sigma * rng.standard_normal(raw_shape), 0.05, None)
        u = rng.uniform(size=raw_shape)
        dead = u < self.dead_pixel_fraction
        hot = (u >= self.dead_pixel_fraction) & (u < self.dead_pixel_fraction + self.hot_pixel_fraction)
        return gain, dead, hot, self.gap_mask(raw_shape)

    def valid_raw(self, raw_shape) -> np.ndarray:
        _, dead, hot, gap = self.pixel_maps(raw_shape)
        return ~(dead | hot | gap)

    def valid_mask(self, raw_shape) -> np.ndarray:
        """Binned validity: at least ``min_valid_fraction`` of the bin's raw pixels are good."""
        n_ok = bin_projections(self.valid_raw(raw_shape).astype(np.int32), self.binning)
        return n_ok >= max(1.0, self.min_valid_fraction * self.binning ** 2)


def _poisson(rng, lam, noisy: bool) -> np.ndarray:
    return rng.poisson(lam).astype(np.float64) if noisy else lam


def simulate_flat(raw_shape, model: DetectorModel, rng=None):
    """Binned flat field (mean counts per frame, float32 (rows, cols)) and binned valid mask."""
    rng = _rng(model.seed + 1 if rng is None else rng)
    gain, dead, hot, gap = model.pixel_maps(raw_shape)
    ok = ~(dead | hot | gap)
    i0_raw = model.photons_per_pixel / model.binning ** 2
    F = max(1, int(model.flat_frames))
    flat_raw = _poisson(rng, F * i0_raw * gain, model.poisson) / F
    flat = bin_projections(np.where(ok, flat_raw, 0.0), model.binning).astype(np.float32)
    return flat, model.valid_mask(raw_shape) & (flat > 0)


def simulate_counts(line_integrals_raw: np.ndarray, model: DetectorModel, rng=None, flat=None,
                    return_raw: bool = False):
    """Photon counts of the raw-detector line integrals ``(n_views, rows, cols)``, binned.

    Raw counts are Poisson(I0_raw * gain * exp(-p)) (I0_raw = photons_per_pixel / binning^2),
    clipped at saturation; gap and dead pixels read 0, hot pixels read ``saturation_counts``.
    Binning sums the *valid* raw pixels only (module docstring), flat field likewise.

    Returns ``(counts, flat, valid)``: counts float32 (n_views, rows/b, cols/b) (integer
    valued when ``model.poisson``), flat float32 (rows/b, cols/b) mean counts per frame,
    valid bool (rows/b, cols/b). With ``return_raw`` also the raw counts (with the defects).
    ``flat`` may be passed (from :func:`simulate_flat`) to share one flat over several calls.
    """
    li = np.asarray(line_integrals_raw)
    if li.ndim == 2:
        li = li[None]
    rng = _rng(model.seed + 2 if rng is None else rng)
    raw_shape = li.shape[1:]
    if raw_shape[0] % model.binning or raw_shape[1] % model.binning:
        raise ValueError(f"raw detector shape {raw_shape} is not a multiple of binning {model.binning}")
    gain, dead, hot, gap = model.pixel_maps(raw_shape)
    ok = ~(dead | hot | gap)
    if flat is None:
        flat, valid = simulate_flat(raw_shape, model, rng)
    else:
        flat = np.asarray(flat, np.float32)
        valid = model.valid_mask(raw_shape) & (flat > 0)
    i0_raw = model.photons_per_pixel / model.binning ** 2
    nb = (li.shape[0], raw_shape[0] // model.binning, raw_shape[1] // model.binning)
    counts = np.empty(nb, np.float32)
    raw_out = np.empty(li.shape, np.float32) if return_raw else None
    for v in range(li.shape[0]):  # one view at a time keeps float64 temporaries small
        lam = i0_raw * gain * np.exp(-li[v].astype(np.float64))
        raw = np.minimum(_poisson(rng, lam, model.poisson), model.saturation_counts)
        if raw_out is not None:
            raw_out[v] = np.where(dead | gap, 0.0, np.where(hot, model.saturation_counts, raw))
        counts[v] = bin_projections(np.where(ok, raw, 0.0), model.binning)
    if return_raw:
        return counts, flat, valid, raw_out
    return counts, flat, valid


def counts_to_line_integrals(counts, flat, valid_mask, min_counts: float = 0.5):
    """Line integrals ``log(flat / counts)`` (float32), NaN/inf free.

    Counts are clipped below at ``min_counts`` (photon starvation); pixels outside
    ``valid_mask`` (or with a non-positive flat) are set to 0. Returns ``(line_integrals,
    mask)`` with mask the bool validity actually used, broadcast to the projection frame.
    """
    counts = np.asarray(counts, np.float32)
    flat = np.asarray(flat, np.float32)
    mask = np.asarray(valid_mask, bool) & (flat > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        li = np.log(np.where(flat > 0, flat, 1.0)) - np.log(np.maximum(counts, np.float32(min_counts)))
    li = np.where(mask, li, 0.0).astype(np.float32)
    li[~np.isfinite(li)] = 0.0
    return li, mask


# ----------------------------------------------------------------------------- geometric errors
@dataclass(frozen=True)
class GeometryErrorModel:
    """Per-view 9-DOF geometric errors (geometry.py order and units: mm x6, rad x3).

    ``sample(n)`` = ``static_offset`` + drift + white noise, where the white noise is
    independent per view with ``per_view_sigma`` (robot coordination), and the drift is
    ``drift_per_view * view_index`` (``drift_kind="linear"``, creep starting at 0) or a
    random walk with step sigma ``drift_per_view`` smoothed by a Gaussian of
    ``drift_smooth_views`` views (``"random_walk"``). Reproducible from ``seed``.
    """

    per_view_sigma: tuple = (0.0,) * 9
    drift_per_view: tuple = (0.0,) * 9
    static_offset: tuple = (0.0,) * 9
    drift_kind: str = "linear"
    drift_smooth_views: float = 10.0
    seed: int = 0

    def __post_init__(self):
        for name in ("per_view_sigma", "drift_per_view", "static_offset"):
            v = tuple(float(x) for x in np.broadcast_to(np.asarray(getattr(self, name), float), (9,)))
            object.__setattr__(self, name, v)
        if self.drift_kind not in ("linear", "random_walk"):
            raise ValueError("drift_kind must be 'linear' or 'random_walk'")
        if min(self.per_view_sigma) < 0:
            raise ValueError("per_view_sigma must be non-negative")

    def sample(self, n_views: int, rng=None) -> np.ndarray:
        """(n_views, 9) float64 parameters for ``ConeGeometry.perturbed``."""
        rng = _rng(self.seed if rng is None else rng)
        sigma = np.asarray(self.per_view_sigma)
        drift = np.asarray(self.drift_per_view)
        out = np.broadcast_to(np.asarray(self.static_offset), (n_views, 9)).copy()
        out += rng.standard_normal((n_views, 9)) * sigma
        if np.any(drift != 0):
            if self.drift_kind == "linear":
                out += np.arange(n_views)[:, None] * drift
            else:
                walk = np.cumsum(rng.standard_normal((n_views, 9)) * drift, axis=0)
                if self.drift_smooth_views > 0 and n_views > 1:
                    walk = gaussian_filter1d(walk, self.drift_smooth_views, axis=0, mode="nearest")
                out += walk - walk[:1]
        return out

    def __add__(self, other: "GeometryErrorModel") -> "SumOfErrorModels":
        return SumOfErrorModels((self, other))


@dataclass(frozen=True)
class SumOfErrorModels:
    """Several error models added (e.g. robot coordination + detector drift + static offset)."""

    models: tuple

    def sample(self, n_views: int, rng=None) -> np.ndarray:
        rng = None if rng is None else _rng(rng)
        return sum(m.sample(n_views, rng) for m in self.models)

    def __add__(self, other) -> "SumOfErrorModels":
        return SumOfErrorModels(self.models + (other.models if isinstance(other, SumOfErrorModels) else (other,)))


def robot_coordination(sigma_mm: float = 0.3, sigma_deg: float = 0.3, seed: int = 0) -> GeometryErrorModel:
    """Independent per-view errors of both arms: source and detector shifts (sigma_mm each
    axis) and detector rotations (sigma_deg each axis)."""
    return GeometryErrorModel(per_view_sigma=(sigma_mm,) * 6 + (np.deg2rad(sigma_deg),) * 3, seed=seed)


def detector_drift(mm_per_view: float = 0.002, deg_per_view: float = 0.0005, kind: str = "linear",
                   smooth_views: float = 10.0, seed: int = 0) -> GeometryErrorModel:
    """Slow detector creep: all detector shifts and rotations drift by the given amount per view
    (linear), or as a smoothed random walk with that step sigma."""
    drift = (0.0,) * 3 + (mm_per_view,) * 3 + (np.deg2rad(deg_per_view),) * 3
    return GeometryErrorModel(drift_per_view=drift, drift_kind=kind, drift_smooth_views=smooth_views, seed=seed)


def static_misalignment(offset) -> GeometryErrorModel:
    """A constant 9-DOF offset on every view."""
    return GeometryErrorModel(static_offset=tuple(offset))


# ----------------------------------------------------------------------------- scan simulation
def raw_geometry(geom: ConeGeometry, binning: int) -> ConeGeometry:
    """The unbinned detector whose ``binning`` x ``binning`` binning is ``geom`` (same centre)."""
    if binning == 1:
        return geom
    return geom.with_detector(geom.n_rows * binning, geom.n_cols * binning,
                              geom.row_pitch_mm / binning, geom.col_pitch_mm / binning)


def irradiated_bounds_mm(geom: ConeGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box holding every ray of the scan (hull of sources and detector corners)."""
    hu = 0.5 * geom.n_cols * geom.col_pitch_mm
    hv = 0.5 * geom.n_rows * geom.row_pitch_mm
    pts = [geom.source_mm]
    for a in (-1, 1):
        for b in (-1, 1):
            pts.append(geom.detector_mm + a * hu * geom.u + b * hv * geom.v)
    pts = np.concatenate(pts)
    return pts.min(axis=0), pts.max(axis=0)


def _box_ramp(grid: VolumeGrid, lo, hi, blend_mm) -> np.ndarray:
    """Separable weight at the voxel centres of ``grid``: 1 deeper than ``blend_mm`` inside the
    box [lo, hi], falling linearly to 0 at its faces, 0 outside. float32 (nz, ny, nx)."""
    ramps = []
    for a, ax in enumerate(grid.axes_mm()):
        dist = np.minimum(ax - lo[a], hi[a] - ax)
        ramps.append(np.clip(dist / blend_mm[a], 0.0, 1.0).astype(np.float32))
    return ramps[2][:, None, None] * ramps[1][None, :, None] * ramps[0][None, None, :]


def scan_volumes(phantom: Phantom, geom: ConeGeometry, voxel_size_mm, roi_grid: VolumeGrid | None = None,
                 outer_voxel_size_mm=None, roi_margin_mm: float = 0.5, supersample: int = 2,
                 max_voxels: int = 400 ** 3, blend_voxels: int = 2):
    """The voxelised parts ``[(volume, grid), ...]`` whose projections sum to the scan.

    Without ``roi_grid``/``outer_voxel_size_mm``: one grid of ``voxel_size_mm`` over the
    irradiated part of the phantom. With both: a coarse grid (``outer_voxel_size_mm``, rounded
    to a multiple of ``voxel_size_mm``) over the irradiated phantom and a fine grid
    (``voxel_size_mm``) over the box around ``roi_grid`` (+ ``roi_margin_mm``, snapped to
    coarse voxels, + ``blend_voxels`` coarse voxels), combined by a partition of unity: the
    fine part is weighted by ``w`` (1 inside the ROI + margin, falling linearly to 0 over the
    blend band), the coarse part by ``1 - w``. A hard cut would leave line artefacts where
    rays graze the box faces (the two grids' interpolation kernels do not add up to one
    there); the blend, with its kinks on voxel centres of both grids, removes them.
    The coarse part only feeds the truncated rays; the ROI is fine.
    """
    vs = np.broadcast_to(np.asarray(voxel_size_mm, float), (3,)).copy()
    plo, phi = phantom.bounds_mm()
    ilo, ihi = irradiated_bounds_mm(geom)
    lo, hi = np.maximum(plo, ilo), np.minimum(phi, ihi)
    if np.any(hi <= lo):
        raise ValueError("the phantom is not irradiated by this geometry")
    if roi_grid is None or outer_voxel_size_mm is None:
        n = np.maximum(1, np.ceil((hi - lo) / vs).astype(int))
        if np.prod(n) > max_voxels:
            raise ValueError(f"fine grid {tuple(n)} exceeds max_voxels; pass roi_grid and outer_voxel_size_mm")
        g = VolumeGrid.centered(tuple(n[::-1]), vs, 0.5 * (lo + hi))
        return [(voxelize(phantom, g, supersample), g)]
    # both lattices share the node c0 and the coarse pitch is a multiple of the fine one, so
    # every coarse voxel centre is a fine voxel centre and the ramp kinks sit on both lattices:
    # linear interpolation (the projector's) of the two weighted parts then sums exactly.
    fac = np.maximum(1, np.round(np.broadcast_to(np.asarray(outer_voxel_size_mm, float), (3,)) / vs)).astype(int)
    ovs = fac * vs
    c0 = roi_grid.center_mm
    rlo, rhi = roi_grid.bounds_mm()
    in_lo = c0 + np.floor((rlo - roi_margin_mm - c0) / ovs) * ovs
    in_hi = c0 + np.ceil((rhi + roi_margin_mm - c0) / ovs) * ovs
    nb = max(1, int(blend_voxels))
    out_lo, out_hi = in_lo - nb * ovs, in_hi + nb * ovs
    k_lo = np.floor((lo - c0) / ovs - 0.5).astype(int)
    k_hi = np.ceil((hi - c0) / ovs + 0.5).astype(int)
    nc = k_hi - k_lo + 1
    if np.prod(nc) > max_voxels:
        raise ValueError(f"coarse grid {tuple(nc)} exceeds max_voxels; raise outer_voxel_size_mm")
    cg = VolumeGrid(tuple(nc[::-1]), tuple(ovs), tuple(c0 + k_lo * ovs))
    nf = np.round((out_hi - out_lo) / vs).astype(int) + 1
    if np.prod(nf) > max_voxels:
        raise ValueError(f"fine ROI grid {tuple(nf)} exceeds max_voxels")
    fg = VolumeGrid(tuple(nf[::-1]), tuple(vs), tuple(out_lo))
    blend = nb * ovs
    coarse = voxelize(phantom, cg, supersample)
    coarse *= 1.0 - _box_ramp(cg, out_lo, out_hi, blend)
    fine = voxelize(phantom, fg, supersample) * _box_ramp(fg, out_lo, out_hi, blend)
    return [(coarse, cg), (fine, fg)]


@dataclass(frozen=True, eq=False)
class SimulatedScan:
    """Result of :func:`simulate_scan` (arrays per the geometry.py conventions).

    ``line_integrals`` float32 (n_views, rows, cols) on the readout detector ``geom``, 0 where
    ``valid_mask`` (bool (rows, cols)) is False; ``ideal_line_integrals`` the noiseless,
    defect-free line integrals (mean over the raw pixels of each bin); ``counts`` and
    ``flat`` the binned detector output (None without a detector model).
    """

    line_integrals: np.ndarray
    valid_mask: np.ndarray
    geom: ConeGeometry
    ideal_line_integrals: np.ndarray
    counts: np.ndarray | None = None
    flat: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def project_parts(parts, geom: ConeGeometry) -> np.ndarray:
    """Line integrals of the voxelised parts ``[(volume, grid), ...]`` (:func:`scan_volumes`), summed."""
    from .projector import forward_project

    li = None
    for vol, grid in parts:
        p = forward_project(vol, grid, geom)
        li = p if li is None else li + p
    return li


def simulate_scan(phantom: Phantom, geom_true: ConeGeometry, detector: DetectorModel | None = None, *,
                  voxel_size_mm=0.02, roi_grid: VolumeGrid | None = None, outer_voxel_size_mm=None,
                  roi_margin_mm: float = 0.5, supersample: int = 2, pixel_supersample: int = 1, rng=None,
                  chunk_views: int = 16, parts=None) -> SimulatedScan:
    """Simulate the measured projections of ``phantom`` along the true geometry.

    ``geom_true`` is the readout (binned) geometry. The phantom is voxelised at
    ``voxel_size_mm`` (choose finer than the reconstruction), see :func:`scan_volumes` for
    ``roi_grid``/``outer_voxel_size_mm`` (fine ROI + coarse rest; use it for large objects),
    or pass pre-voxelised ``parts``. With a ``detector`` the projection runs on the raw
    detector (``raw_geometry(geom_true, binning)``), then :func:`simulate_counts` and
    :func:`counts_to_line_integrals`; without one, on ``pixel_supersample``-times finer
    pixels averaged back, noise free. Processed in chunks of ``chunk_views`` views.
    """
    sub = detector.binning if detector is not None else int(pixel_supersample)
    gproj = raw_geometry(geom_true, sub)
    if parts is None:
        parts = scan_volumes(phantom, gproj, voxel_size_mm, roi_grid, outer_voxel_size_mm, roi_margin_mm,
                             supersample)
    rng = _rng(rng)
    nv, nr, nc = geom_true.n_views, geom_true.n_rows, geom_true.n_cols
    ideal = np.empty((nv, nr, nc), np.float32)
    counts = np.empty((nv, nr, nc), np.float32) if detector is not None else None
    flat = valid = None
    if detector is not None:
        flat, valid = simulate_flat((nr * sub, nc * sub), detector, rng)
    for v0 in range(0, nv, chunk_views):
        sel = np.arange(v0, min(nv, v0 + chunk_views))
        li = project_parts(parts, gproj.subset(sel))
        ideal[sel] = bin_projections(li, sub, mean=True)
        if detector is not None:
            counts[sel] = simulate_counts(li, detector, rng, flat=flat)[0]
    if detector is None:
        return SimulatedScan(ideal, np.ones((nr, nc), bool), geom_true, ideal,
                             info={"parts": [g.to_dict() for _, g in parts]})
    li, mask = counts_to_line_integrals(counts, flat, valid)
    return SimulatedScan(li, mask, geom_true, ideal, counts, flat,
                         info={"parts": [g.to_dict() for _, g in parts], "detector": detector})
