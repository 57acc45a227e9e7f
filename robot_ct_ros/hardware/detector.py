"""Photon-counting detector (PCD) interface and its simulated twin.

Interface (:class:`PhotonCountingDetector`): a detector is configured for a read-out
(binned) pixel grid (:class:`DetectorConfig`), gives its flat field and unusable-pixel map
once connected, and acquires one frame per :meth:`~PhotonCountingDetector.acquire` call:
a blocking call that exposes for ``exposure_s`` and returns a :class:`Frame` (binned photon
counts, float32 (rows, cols), with the exposure start and end times in ns) or raises
:class:`DetectorError`. Callers run it on a worker thread and enforce their own deadline:
a detector may hang (the simulated one can be told to), and a hang must not hang the caller.

The simulated detector (:class:`SimulatedDetector`) ray-casts a voxelised phantom
(:class:`SimulatedScene`, built once) along the *true* geometry of the moment: the true
tool poses of both arms (a callable the owner feeds, e.g. from ``<role>_arm/true_tool_pose``)
through the true hand-eye mounts (:mod:`robot_ct_ros.ct.hand_eye`), one ray per raw pixel
(:func:`robot_ct_ros.ct.projector.forward_project`), then applies the photon-counting model
of :mod:`robot_ct_ros.ct.simulation` (Poisson counts, fixed-pattern gain, chip gaps,
dead/hot pixels, binning over valid raw pixels). The detector does not know the beam
interlock: the photon flux of a frame is scaled by the fraction of the exposure during which
the beam was on (another callable), so a frame taken with the beam off is dark.

Units: mm and radians inside (robot_ct_ros.ct conventions), times in integer nanoseconds of
the owner's clock. No ROS import.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Protocol

import numpy as np

from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.hand_eye import HandEye, geometry_from_tool_poses
from robot_ct_ros.ct.simulation import (DetectorModel, Phantom, battery_phantom, carotid_plaque_phantom,
                                        mouse_phantom, raw_geometry, simulate_counts, simulate_flat, voxelize)


class DetectorError(RuntimeError):
    """The detector could not deliver a frame (the message says why)."""


class DetectorTimeout(DetectorError):
    """No frame within the allowed time."""


@dataclass(frozen=True)
class DetectorConfig:
    """Read-out pixel grid: ``n_rows`` x ``n_cols`` pixels after ``binning`` x ``binning`` binning
    of raw pixels of ``raw_pixel_mm`` (the seed PCD: 55 um raw, read out 2 x 2 binned)."""

    n_rows: int = 272
    n_cols: int = 636
    binning: int = 2
    raw_pixel_mm: float = 0.055

    def __post_init__(self):
        if min(self.n_rows, self.n_cols, self.binning) < 1 or self.raw_pixel_mm <= 0:
            raise ValueError(f"invalid detector configuration {self}")

    @property
    def pitch_mm(self) -> float:
        """Read-out (binned) pixel pitch, mm."""
        return self.raw_pixel_mm * self.binning

    @property
    def shape(self) -> tuple[int, int]:
        return (self.n_rows, self.n_cols)

    @property
    def raw_shape(self) -> tuple[int, int]:
        return (self.n_rows * self.binning, self.n_cols * self.binning)


@dataclass
class Frame:
    """One acquired frame: binned counts float32 (rows, cols); exposure start/end (ns)."""

    counts: np.ndarray
    start_ns: int
    end_ns: int
    info: dict = field(default_factory=dict)

    @property
    def stamp_ns(self) -> int:
        """The frame's time stamp: the middle of the exposure (the bag contract's pairing key)."""
        return (self.start_ns + self.end_ns) // 2


class PhotonCountingDetector(Protocol):
    """What the pcd_grabber node needs from a detector driver (real or simulated)."""

    config: DetectorConfig

    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    @property
    def is_connected(self) -> bool: ...
    def flat_field(self) -> tuple[np.ndarray, np.ndarray]:
        """(flat float32 (rows, cols): mean counts per frame without object, bad bool (rows, cols))."""
    def acquire(self, exposure_s: float) -> Frame:
        """Expose for ``exposure_s`` and read the frame out (blocking); raises DetectorError."""


# ----------------------------------------------------------------------------- scene
PHANTOMS = ("mouse", "battery", "carotid")


def make_phantom(name: str, center_mm=(0.0, 0.0, 0.0), seed: int = 0) -> Phantom:
    """One of the simulation phantoms by name (mouse | battery | carotid), centred at ``center_mm``."""
    if name == "mouse":
        return mouse_phantom(center_mm=center_mm, seed=seed)
    if name == "battery":
        return battery_phantom(center_mm=center_mm, seed=seed)
    if name == "carotid":
        return carotid_plaque_phantom(center_mm=center_mm, seed=seed)
    raise ValueError(f"unknown phantom {name!r} (choose from {', '.join(PHANTOMS)})")


@dataclass(frozen=True, eq=False)
class SimulatedScene:
    """A phantom voxelised once: parts ``[(volume, grid), ...]`` whose projections add up."""

    phantom: Phantom
    parts: tuple

    @property
    def n_voxels(self) -> int:
        return int(sum(v.size for v, _ in self.parts))


def build_scene(phantom: Phantom, voxel_size_mm: float, *, region_center_mm=None, region_size_mm=None,
                roi_center_mm=None, roi_size_mm=None, roi_voxel_size_mm=None, supersample: int = 2,
                max_voxels: int = 300 ** 3) -> SimulatedScene:
    """Voxelise ``phantom`` for the simulated detector.

    The phantom (cut to the box ``region_center_mm +- region_size_mm / 2`` when given; rays
    outside it see nothing) is voxelised at ``voxel_size_mm``. With ``roi_size_mm`` and a
    finer ``roi_voxel_size_mm`` the box around ``roi_center_mm`` (snapped outwards to the
    coarse voxels) is voxelised finely instead, as a second part: a fine ROI for the
    interior scan in a coarse body that only feeds the truncated rays.
    """
    lo, hi = phantom.bounds_mm()
    if region_size_mm is not None and np.any(np.asarray(region_size_mm, float) > 0):
        c = np.asarray(phantom.bounds_mm()[0] + phantom.bounds_mm()[1], float) / 2 \
            if region_center_mm is None else np.asarray(region_center_mm, float)
        half = 0.5 * np.broadcast_to(np.asarray(region_size_mm, float), (3,))
        lo, hi = np.maximum(lo, c - half), np.minimum(hi, c + half)
        if np.any(hi <= lo):
            raise ValueError("the simulation region does not overlap the phantom")
    vs = float(voxel_size_mm)
    if vs <= 0:
        raise ValueError("voxel size must be positive")
    n = np.maximum(1, np.ceil((hi - lo) / vs).astype(int))
    if np.prod(n) > max_voxels:
        raise ValueError(f"coarse grid {tuple(n)} has more than {max_voxels} voxels: raise voxel_size")
    coarse_grid = VolumeGrid(tuple(n[::-1]), (vs,) * 3, tuple(lo + 0.5 * vs))
    coarse = voxelize(phantom, coarse_grid, supersample)
    parts = [(coarse, coarse_grid)]
    if roi_size_mm is not None and roi_voxel_size_mm is not None and np.any(np.asarray(roi_size_mm, float) > 0):
        f = max(1, int(round(vs / float(roi_voxel_size_mm))))
        rc = 0.5 * (lo + hi) if roi_center_mm is None else np.asarray(roi_center_mm, float)
        half = 0.5 * np.broadcast_to(np.asarray(roi_size_mm, float), (3,))
        i0 = np.clip(np.floor((rc - half - lo) / vs).astype(int), 0, n)
        i1 = np.clip(np.ceil((rc + half - lo) / vs).astype(int), 0, n)
        if np.all(i1 > i0) and f > 1:
            nf = (i1 - i0) * f
            if np.prod(nf) > max_voxels:
                raise ValueError(f"fine ROI grid {tuple(nf)} has more than {max_voxels} voxels")
            fvs = vs / f
            fine_grid = VolumeGrid(tuple(nf[::-1]), (fvs,) * 3, tuple(lo + i0 * vs + 0.5 * fvs))
            coarse[i0[2]:i1[2], i0[1]:i1[1], i0[0]:i1[0]] = 0.0
            parts.append((voxelize(phantom, fine_grid, supersample), fine_grid))
    return SimulatedScene(phantom, tuple(parts))


# ----------------------------------------------------------------------------- simulated detector
PoseSource = Callable[[], "tuple[np.ndarray, np.ndarray] | None"]
BeamFraction = Callable[[int, int], float]


def warm_up_projector() -> float:
    """JIT-compile (or load from numba's cache) the projector; returns the seconds spent.

    On a cold cache the first exposure would otherwise compile for many seconds inside the
    acquisition (holding the GIL, so the whole executor stalls): the exposure times out and
    the scan aborts. The simulated detector calls this when it connects.
    """
    from robot_ct_ros.ct.projector import forward_project
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    t0 = time.monotonic()
    geom = robotic_roi_scan(n_views=2, n_rows=4, n_cols=6, fov_diameter_mm=0.3)
    grid = VolumeGrid.centered((4, 4, 4), 0.05)
    forward_project(np.ones(grid.shape_zyx, np.float32), grid, geom)
    return time.monotonic() - t0


class SimulatedDetector:
    """Simulated PCD (module docstring).

    ``true_poses()`` returns the true TCP poses (source, detector), 4 x 4 mm, or None when
    unknown; ``beam_fraction(start_ns, end_ns)`` the fraction of that interval with the beam
    on; ``clock_ns()`` the owner's clock. ``hand_eye`` holds the *true* mounts. ``fail`` =
    ``"timeout"`` makes every acquisition hang (until ``hang_s`` or disconnect) and then raise
    :class:`DetectorTimeout`; ``readout_s`` adds a read-out delay after the exposure. When the true
    poses are not known yet at the end of an exposure (a simulation start-up race), the read-out
    waits up to ``pose_wait_s`` for them before failing.
    """

    def __init__(self, config: DetectorConfig, model: DetectorModel, scene: SimulatedScene, hand_eye: HandEye,
                 true_poses: PoseSource, beam_fraction: BeamFraction, clock_ns: Callable[[], int] = time.time_ns,
                 *, seed: int = 0, fail: str = "none", hang_s: float = 3600.0, readout_s: float = 0.0,
                 pose_wait_s: float = 0.0):
        if model.binning != config.binning or abs(model.raw_pitch_mm - config.raw_pixel_mm) > 1e-12:
            raise ValueError("detector model and configuration disagree on binning or raw pitch")
        if fail not in ("none", "timeout"):
            raise ValueError(f"fail must be 'none' or 'timeout', got {fail!r}")
        self.config = config
        self.model = model
        self.scene = scene
        self.hand_eye = hand_eye
        self._true_poses = true_poses
        self._beam_fraction = beam_fraction
        self._clock_ns = clock_ns
        self._rng = np.random.default_rng(seed)
        self.fail = fail
        self.hang_s = float(hang_s)
        self.readout_s = float(readout_s)
        self.pose_wait_s = float(pose_wait_s)
        self._connected = False
        self._disconnect = threading.Event()
        self._flat = self._bad = None
        self.frames_acquired = 0

    # -- interface ------------------------------------------------------------------------
    def connect(self) -> None:
        warm_up_projector()
        flat, valid = simulate_flat(self.config.raw_shape, self.model, np.random.default_rng(self.model.seed + 1))
        self._flat, self._bad = flat, ~valid
        self._disconnect.clear()
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False
        self._disconnect.set()

    @property
    def is_connected(self) -> bool:
        return self._connected

    def flat_field(self) -> tuple[np.ndarray, np.ndarray]:
        if self._flat is None:
            raise DetectorError("detector not connected")
        return self._flat.copy(), self._bad.copy()

    def acquire(self, exposure_s: float) -> Frame:
        if not self._connected:
            raise DetectorError("detector not connected")
        if not exposure_s > 0:
            raise DetectorError(f"exposure must be positive, got {exposure_s}")
        start = self._clock_ns()
        if self._disconnect.wait(exposure_s):
            raise DetectorError("detector disconnected during the exposure")
        end = self._clock_ns()
        if self.fail == "timeout":
            self._disconnect.wait(self.hang_s)
            raise DetectorTimeout("simulated detector: read-out never completed (fault injected)")
        if self.readout_s > 0 and self._disconnect.wait(self.readout_s):
            raise DetectorError("detector disconnected during read-out")
        poses = self._true_poses()
        give_up = time.monotonic() + self.pose_wait_s
        while poses is None and time.monotonic() < give_up:
            if self._disconnect.wait(0.01):
                raise DetectorError("detector disconnected during read-out")
            poses = self._true_poses()
        if poses is None:
            raise DetectorError("simulated detector: true arm poses unknown, cannot simulate a frame")
        fraction = float(np.clip(self._beam_fraction(start, end), 0.0, 1.0))
        geom = self.true_geometry(*poses)
        counts = self.simulate(geom, fraction)
        self.frames_acquired += 1
        return Frame(counts, start, end, {"beam_fraction": fraction, "geometry": geom})

    # -- simulation -------------------------------------------------------------------------
    def true_geometry(self, source_tcp, detector_tcp) -> ConeGeometry:
        """Read-out geometry (1 view) of the given true TCP poses through the true mounts."""
        c = self.config
        return geometry_from_tool_poses(source_tcp, detector_tcp, self.hand_eye, c.n_rows, c.n_cols, c.pitch_mm)

    def simulate(self, geom: ConeGeometry, beam_fraction: float = 1.0) -> np.ndarray:
        """Binned counts (rows, cols) of one view; the flux scaled by ``beam_fraction``."""
        from robot_ct_ros.ct.projector import forward_project

        raw = raw_geometry(geom, self.config.binning)
        if beam_fraction > 0:
            li = None
            for vol, grid in self.scene.parts:
                p = forward_project(vol, grid, raw)
                li = p if li is None else li + p
        else:
            li = np.zeros((1,) + self.config.raw_shape, np.float32)
        model = replace(self.model, photons_per_pixel=self.model.photons_per_pixel * beam_fraction)
        counts, _, _ = simulate_counts(li, model, self._rng, flat=self._flat)
        return counts[0]
