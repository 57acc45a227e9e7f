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

Settings: :class:`DetectorSettings` (driver, read-out grid, exposure) and
:class:`SimulatedDetectorSettings` (the simulation: phantom, voxelisation, photon counts, defects,
faults) are the pcd_grabber's parameters, SI units as there; :func:`make_detector` builds the
detector they describe, fed by a :class:`TruePoses` store of the arms' true poses.

Units: mm and radians inside (robot_ct_ros.ct conventions), times in integer nanoseconds of
the owner's clock. No ROS import.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Protocol

import numpy as np

from robot_ct_ros.bag.format import FRAME_DETECTOR, FRAME_WORLD
from robot_ct_ros.ct.geometry import ConeGeometry, VolumeGrid
from robot_ct_ros.ct.hand_eye import HandEye, geometry_from_tool_poses
from robot_ct_ros.ct.simulation import (DetectorModel, Phantom, battery_phantom, carotid_plaque_phantom,
                                        mouse_phantom, raw_geometry, simulate_counts, simulate_flat, voxelize)
from robot_ct_ros.parameters import setting, validate

__all__ = ["DetectorError", "DetectorTimeout", "DetectorConfig", "Frame", "PhotonCountingDetector", "PHANTOMS",
           "make_phantom", "SimulatedScene", "build_scene", "warm_up_projector", "SimulatedDetector",
           "DetectorSettings", "SimulatedDetectorSettings", "TruePoses", "make_detector", "valid_pixel_fraction"]


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


def valid_pixel_fraction(flat: np.ndarray, bad: np.ndarray, counts: np.ndarray | None = None) -> float:
    """The fraction of pixels a reconstruction can use, as ``robot-ct info`` counts it (bag/reader.py): not in the
    unusable-pixel map ``bad``, a finite flat field > 0 and, given a frame's ``counts``, a finite, non-negative
    count. Without ``counts``: what the maps alone leave usable."""
    flat = np.asarray(flat)
    valid = ~np.asarray(bad, bool) & np.isfinite(flat) & (np.nan_to_num(flat) > 0)
    if counts is not None:
        counts = np.asarray(counts)
        valid &= np.isfinite(counts) & (np.nan_to_num(counts, nan=-1.0) >= 0)
    return float(valid.mean()) if valid.size else 0.0


# ----------------------------------------------------------------------------- settings and construction
@dataclass(frozen=True)
class DetectorSettings:
    """The detector of the pcd_grabber: driver, read-out grid, exposure, and the frames' frame_id and
    true geometry output (SI units; its parameters of the same names).

    Raises
    ------
    ValueError
        A field out of its range, an impossible grid, or not 0 < exposure_s < exposure_timeout_s.
    """

    driver: str = setting("simulated", "detector driver (only 'simulated' so far)")
    n_rows: int = setting(272, "read-out (binned) rows, along v", unit="px", minimum=1)
    n_cols: int = setting(636, "read-out (binned) columns, along u", unit="px", minimum=1)
    binning: int = setting(2, "raw pixels per read-out pixel, per axis", minimum=1)
    raw_pixel_m: float = setting(55e-6, "raw pixel pitch", unit="m", minimum=0.0)
    exposure_s: float = setting(0.1, "exposure per frame", unit="s", minimum=0.0)
    exposure_timeout_s: float = setting(5.0, "pcd/expose answers failure if no frame within this (> exposure_s)",
                                        unit="s", minimum=0.0)
    frame_id: str = setting(FRAME_DETECTOR, "frame_id of the published frames")
    world_frame: str = setting(FRAME_WORLD, "frame of the true tool poses and of /ct/geometry_true (the arms' "
                               "base_frame, geometry_publisher's world_frame)")
    publish_true_geometry: bool = setting(True, "simulated detector: the true geometry of each frame is published")
    min_valid_pixel_fraction: float = setting(0.5, "a frame (or the dead-pixel map) with fewer valid pixels than "
                                              "this fraction is warned about (log and /diagnostics WARN)",
                                              minimum=0.0, maximum=1.0)

    def __post_init__(self):
        validate(self)
        self.config  # raises on an impossible grid
        if not 0 < self.exposure_s < self.exposure_timeout_s:
            raise ValueError(f"need 0 < exposure_s < exposure_timeout_s, got {self.exposure_s}, "
                             f"{self.exposure_timeout_s}")

    @property
    def config(self) -> DetectorConfig:
        """The read-out grid in the core's units (mm)."""
        return DetectorConfig(n_rows=self.n_rows, n_cols=self.n_cols, binning=self.binning,
                              raw_pixel_mm=self.raw_pixel_m * 1e3)


@dataclass(frozen=True)
class SimulatedDetectorSettings:
    """The simulated detector: phantom, voxelisation, photon-counting model, faults (the ``sim_*``
    parameters of the pcd_grabber, SI units as there; mount errors in the device frames)."""

    phantom: str = setting("carotid", "simulated phantom", choices=PHANTOMS)
    phantom_center_m: tuple = setting((0.4, 0.0, 0.3), "where the phantom is centred (world frame)", unit="m")
    region_center_m: tuple | None = setting(None, "centre of region_size_m and roi_size_m (unset: the phantom "
                                            "centre)", unit="m", kind=tuple, length=3)
    phantom_seed: int = setting(0, "seed of the phantom's random structures", minimum=0)
    voxel_size_m: float = setting(5e-4, "voxels of the whole phantom (or of the region)", unit="m", minimum=0.0)
    region_size_m: tuple = setting((0.0, 0.0, 0.0), "> 0: only this box around the centre is voxelised",
                                   unit="m", minimum=0.0)
    roi_size_m: tuple = setting((0.0, 0.0, 0.0), "> 0: this box around the centre is voxelised finer",
                                unit="m", minimum=0.0)
    roi_voxel_size_m: float = setting(5e-5, "voxel size of the finer ROI", unit="m", minimum=0.0)
    supersample: int = setting(1, "sub-samples per voxel axis when voxelising", minimum=1)
    photons_per_pixel: float = setting(49000.0, "flat-field counts per read-out pixel per frame", minimum=0.0)
    chip_size_px: int = setting(256, "raw pixels per chip side; chips are separated by gaps", unit="px", minimum=1)
    chip_gap_px: int = setting(2, "raw pixels between chips", unit="px", minimum=0)
    dead_pixel_fraction: float = setting(1e-3, "fraction of dead raw pixels", minimum=0.0, maximum=1.0)
    hot_pixel_fraction: float = setting(2e-4, "fraction of hot raw pixels", minimum=0.0, maximum=1.0)
    flat_field_sigma: float = setting(0.03, "relative raw-pixel gain variation", minimum=0.0)
    flat_frames: int = setting(20, "frames averaged into the flat field", minimum=1)
    poisson: bool = setting(True, "Poisson counting noise")
    seed: int = setting(0, "seed of the fixed pattern and the noise", minimum=0)
    fail: str = setting("none", "fault injection: timeout = no frame is ever read out", choices=("none", "timeout"))
    readout_s: float = setting(0.0, "extra read-out delay after the exposure", unit="s", minimum=0.0)
    pose_max_age_s: float = setting(1.0, "true arm poses older than this count as unknown (the frame fails)",
                                    unit="s", minimum=0.0)
    source_mount_error_m: tuple = setting((0.0, 0.0, 0.0), "static hand-eye error of the source mount", unit="m",
                                          ros_name="mount_error.source_translation_m")
    detector_mount_error_m: tuple = setting((0.0, 0.0, 0.0), "static hand-eye error of the detector mount",
                                            unit="m", ros_name="mount_error.detector_translation_m")
    detector_mount_error_rotvec_rad: tuple = setting((0.0, 0.0, 0.0), "static rotation error of the detector "
                                                     "mount", unit="rad", ros_name="mount_error.detector_rotvec_rad")

    def __post_init__(self):
        validate(self)
        if not (self.voxel_size_m > 0 and self.roi_voxel_size_m > 0):
            raise ValueError(f"voxel sizes must be positive, got {self.voxel_size_m}, {self.roi_voxel_size_m} m")


class TruePoses:
    """The latest true TCP pose of each arm (the simulated detector's pose source), thread-safe.

    Parameters
    ----------
    clock_ns : callable() -> int
        The owner's clock (ns).
    max_age_s : float
        A pose older than this (by its stamp) counts as unknown.
    """

    ROLES = ("source", "detector")

    def __init__(self, clock_ns: Callable[[], int], max_age_s: float):
        self._clock_ns = clock_ns
        self.max_age_ns = max_age_s * 1e9
        self._lock = threading.Lock()
        self._poses: dict[str, tuple[int, np.ndarray]] = {}

    def update(self, role: str, stamp_ns: int, T: np.ndarray) -> None:
        """Record the true TCP pose ``T`` (4 x 4, mm) of ``role`` stamped ``stamp_ns``."""
        with self._lock:
            self._poses[role] = (int(stamp_ns), T)

    def __len__(self) -> int:
        with self._lock:
            return len(self._poses)

    def __call__(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(source, detector) TCP poses, 4 x 4 mm; None while either is unknown or stale."""
        now = self._clock_ns()
        with self._lock:
            poses = [self._poses.get(r) for r in self.ROLES]
        if any(p is None or now - p[0] > self.max_age_ns for p in poses):
            return None
        return poses[0][1], poses[1][1]


def make_detector(detector: DetectorSettings, sim: SimulatedDetectorSettings, hand_eye: HandEye,
                  true_poses: PoseSource, beam_fraction: BeamFraction, clock_ns: Callable[[], int]):
    """The detector the settings describe (not connected yet).

    Parameters
    ----------
    detector, sim : DetectorSettings, SimulatedDetectorSettings
        The pcd_grabber's parameters.
    hand_eye : HandEye
        The nominal mounts; the simulated detector projects through them plus ``sim``'s mount errors.
    true_poses, beam_fraction, clock_ns : callable
        As :class:`SimulatedDetector` takes them.

    Returns
    -------
    SimulatedDetector

    Raises
    ------
    ValueError
        An unknown driver, or a scene that cannot be built (region outside the phantom, too many voxels).
    """
    if detector.driver != "simulated":
        raise ValueError(f"detector driver {detector.driver!r} is not available (only 'simulated')")
    config, s = detector.config, sim
    center_mm = np.asarray(s.phantom_center_m, float) * 1e3
    region_mm = np.asarray(s.region_center_m, float) * 1e3 if s.region_center_m is not None else center_mm
    phantom = make_phantom(s.phantom, center_mm, seed=s.phantom_seed)
    scene = build_scene(phantom, s.voxel_size_m * 1e3, region_center_mm=region_mm,
                        region_size_mm=np.asarray(s.region_size_m, float) * 1e3, roi_center_mm=region_mm,
                        roi_size_mm=np.asarray(s.roi_size_m, float) * 1e3,
                        roi_voxel_size_mm=s.roi_voxel_size_m * 1e3, supersample=s.supersample)
    model = DetectorModel(photons_per_pixel=s.photons_per_pixel, binning=config.binning,
                          chip_size_px=s.chip_size_px, chip_gap_px=s.chip_gap_px,
                          dead_pixel_fraction=s.dead_pixel_fraction, hot_pixel_fraction=s.hot_pixel_fraction,
                          flat_field_sigma=s.flat_field_sigma, flat_frames=s.flat_frames,
                          poisson=s.poisson, raw_pitch_mm=config.raw_pixel_mm, seed=s.seed)
    true_mounts = hand_eye.with_errors(
        source_translation_mm=np.asarray(s.source_mount_error_m, float) * 1e3,
        detector_translation_mm=np.asarray(s.detector_mount_error_m, float) * 1e3,
        detector_rotvec=list(s.detector_mount_error_rotvec_rad))
    return SimulatedDetector(config, model, scene, true_mounts, true_poses, beam_fraction, clock_ns,
                             seed=s.seed + 7, fail=s.fail, readout_s=s.readout_s,
                             pose_wait_s=min(1.0, 0.5 * (detector.exposure_timeout_s - detector.exposure_s)))
