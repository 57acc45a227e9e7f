"""Hand-eye transforms: robot tool poses <-> the per-view cone-beam geometry.

Each arm carries its device on the tool flange (the TCP). The *mount* of a device is the
rigid transform from the TCP frame to the device frame, fixed by the hand-eye calibration:

* source frame: origin at the X-ray focal spot; its axes are parallel to the detector's
  (u, v, w) in the nominal geometry, so its -z axis is the central beam direction (towards
  the detector) and its x axis runs along the detector columns (u). Only the focal-spot
  position enters the geometry; the orientation fixes how the source arm is posed.
* detector frame: origin at the centre of the read-out pixel grid (``ConeGeometry.detector_mm``),
  x = u (increasing column), y = v (increasing row), z = w = u x v (towards the source).

With ``T_tool`` the TCP pose in the world (4 x 4, mm) and ``M`` the mount, the device frame
in the world is ``T_tool @ M``. :func:`geometry_from_tool_poses` applies this to both arms,
:func:`tool_goals_from_geometry` inverts it (``T_tool = F @ inv(M)``) to turn a planned
geometry into TCP goals. Units are those of :mod:`robot_ct_ros.ct.geometry` (mm, radians);
poses are 4 x 4 homogeneous matrices (or stacks (n, 4, 4)). ROS nodes convert metres at
their message boundary.

Why here (``ct/``) and not in ``hardware/``: the transforms are pure geometry, shared by the
simulated detector, the geometry publisher, the scan orchestrator and offline tools (e.g.
recomputing the nominal geometry from recorded arm poses, or estimating the mounts from the
corrected geometry); none of it talks to a device.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from .geometry import ConeGeometry

__all__ = ["pose_matrix", "matrix_to_position_rotvec", "invert", "Mount", "HandEye", "mount_from_si",
           "device_position_sigma_mm",
           "geometry_from_tool_poses", "device_frames", "tool_goals_from_geometry"]


def pose_matrix(position_mm, rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4 x 4 homogeneous matrix from a position (mm) and a rotation vector (rad); stacks (n, 3) too."""
    p = np.asarray(position_mm, dtype=np.float64)
    r = np.asarray(rotvec, dtype=np.float64)
    single = p.ndim == 1 and r.ndim == 1
    p, r = np.atleast_2d(p), np.atleast_2d(r)
    n = max(len(p), len(r))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = Rotation.from_rotvec(np.array(np.broadcast_to(r, (n, 3)))).as_matrix()
    T[:, :3, 3] = np.broadcast_to(p, (n, 3))
    return T[0] if single else T


def matrix_to_position_rotvec(T) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pose_matrix`: (position mm, rotation vector rad), (3,) or (n, 3) each."""
    T = np.asarray(T, dtype=np.float64)
    return T[..., :3, 3].copy(), Rotation.from_matrix(T[..., :3, :3]).as_rotvec()


def invert(T) -> np.ndarray:
    """Inverse of rigid transforms (4, 4) or (n, 4, 4)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _orthonormalised(T: np.ndarray) -> np.ndarray:
    """Project the rotation part onto SO(3) (poses from float32 or quaternions drift slightly)."""
    T = np.array(T, dtype=np.float64, copy=True)
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    R = U @ Vt
    det = np.linalg.det(R)
    if np.any(det < 0):
        raise ValueError("pose rotation is a reflection")
    T[..., :3, :3] = R
    return T


@dataclass(frozen=True)
class Mount:
    """Rigid transform from a TCP (tool flange) frame to a device frame (mm, rotation vector rad)."""

    translation_mm: tuple = (0.0, 0.0, 0.0)
    rotvec: tuple = (0.0, 0.0, 0.0)

    def __post_init__(self):
        t = tuple(float(x) for x in np.asarray(self.translation_mm, float).reshape(3))
        r = tuple(float(x) for x in np.asarray(self.rotvec, float).reshape(3))
        if not np.all(np.isfinite(t + r)):
            raise ValueError("mount translation and rotation must be finite")
        object.__setattr__(self, "translation_mm", t)
        object.__setattr__(self, "rotvec", r)

    @classmethod
    def from_rpy(cls, translation_mm, rpy_rad) -> "Mount":
        """Mount from roll, pitch, yaw (rad) about the fixed x, y, z axes (URDF/REP 103: R = Rz Ry Rx)."""
        return cls(translation_mm, Rotation.from_euler("xyz", rpy_rad).as_rotvec())

    @property
    def matrix(self) -> np.ndarray:
        return pose_matrix(self.translation_mm, self.rotvec)

    def compose(self, error: "Mount") -> "Mount":
        """This mount followed by a small error expressed in the device frame (``M @ E``)."""
        p, r = matrix_to_position_rotvec(self.matrix @ error.matrix)
        return Mount(p, r)


def _default_source() -> Mount:
    # focal spot 120 mm out along the flange axis; the beam leaves along tool +z (source -z)
    return Mount((0.0, 0.0, 120.0), (np.pi, 0.0, 0.0))


def _default_detector() -> Mount:
    # detector centre 80 mm out along the flange axis, sensitive face (w) along tool +z
    return Mount((0.0, 0.0, 80.0), (0.0, 0.0, 0.0))


@dataclass(frozen=True)
class HandEye:
    """The two mounts: source arm TCP -> focal spot, detector arm TCP -> detector frame."""

    source: Mount = field(default_factory=_default_source)
    detector: Mount = field(default_factory=_default_detector)

    def to_dict(self) -> dict:
        """SI form, as in the ROS parameters (``hand_eye.<device>.translation_m`` / ``rotvec_rad``)."""
        return {k: {"translation_m": [x * 1e-3 for x in m.translation_mm], "rotvec_rad": list(m.rotvec)}
                for k, m in (("source", self.source), ("detector", self.detector))}

    @classmethod
    def from_dict(cls, d: dict) -> "HandEye":
        """From the SI form: per device ``translation_m`` and either ``rotvec_rad`` or ``rpy_rad``; what a device
        leaves out keeps the default mount's (as the nodes' ``hand_eye.*`` parameters do)."""
        mounts = {}
        for key in ("source", "detector"):
            m, default = d.get(key), getattr(cls(), key)
            if m is None:
                mounts[key] = default
                continue
            rotvec, rpy = m.get("rotvec_rad"), m.get("rpy_rad")
            if rotvec is None and rpy is None:
                rotvec = list(default.rotvec)
            translation = m.get("translation_m", [x * 1e-3 for x in default.translation_mm])
            mounts[key] = mount_from_si(translation, rotvec, rpy, what=key)
        return cls(**mounts)

    def with_errors(self, source_translation_mm=(0, 0, 0), detector_translation_mm=(0, 0, 0),
                    detector_rotvec=(0, 0, 0)) -> "HandEye":
        """Mounts off by a static error (device frame): the true mounts of a miscalibrated system."""
        return HandEye(self.source.compose(Mount(source_translation_mm)),
                       self.detector.compose(Mount(detector_translation_mm, detector_rotvec)))


def device_position_sigma_mm(mount: Mount, tcp_sigma_mm: float, tcp_sigma_rad: float) -> np.ndarray:
    """Standard deviations (3,) of a device origin's position along the device's own x, y, z axes
    (mm) when its arm's TCP errs independently by ``tcp_sigma_mm`` along each axis and by
    ``tcp_sigma_rad`` in each rotation-vector component (small isotropic errors, as
    :class:`robot_ct_ros.hardware.simulated_arm.SimulatedArm` draws them).

    A rotation error turns the device about the flange, so its origin also moves by the rotation
    error crossed with the lever arm ``l`` (the mount's translation): across the lever the variance
    gains ``(tcp_sigma_rad * |l|)**2``, along it nothing. The device axes are the geometry's
    (u, v, w) (module docstring), the frame of the 9 calibration parameters, so this, not the TCP's
    own accuracy, is what the calibration's prior on the source and detector positions should
    state: with the default mounts (focal spot 120 mm, detector centre 80 mm out along w) 0.1 mm
    and 0.05 deg at the TCP are 0.145 / 0.122 mm across the beam.
    """
    if tcp_sigma_mm < 0 or tcp_sigma_rad < 0:
        raise ValueError("the TCP's accuracy must be non-negative")
    lever_device = Rotation.from_rotvec(mount.rotvec).inv().apply(np.asarray(mount.translation_mm, float))
    across = float(lever_device @ lever_device) - lever_device ** 2
    return np.sqrt(tcp_sigma_mm ** 2 + tcp_sigma_rad ** 2 * across)


MAX_MOUNT_M = 2.0
"""The farthest a device may sit from its flange (m): beyond it a hand-eye translation is taken for millimetres."""


def mount_from_si(translation_m, rotvec_rad=None, rpy_rad=None, what: str = "mount") -> Mount:
    """A :class:`Mount` from SI parameters; the rotation as a rotation vector or roll-pitch-yaw, not both.

    Empty sequences count as not given (ROS parameters cannot be None).
    """
    t = np.asarray(translation_m, dtype=float).reshape(-1)
    if t.shape != (3,):
        raise ValueError(f"{what}: translation_m needs 3 numbers, got {t.tolist()}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{what}: translation_m must be finite, got {t.tolist()}")
    if np.linalg.norm(t) > MAX_MOUNT_M:
        raise ValueError(f"{what}: translation_m {t.tolist()} puts the device {np.linalg.norm(t):g} m from the flange "
                         f"(more than {MAX_MOUNT_M:g} m: millimetres given for metres?)")
    rv = None if rotvec_rad is None or len(rotvec_rad) == 0 else np.asarray(rotvec_rad, float).reshape(-1)
    rpy = None if rpy_rad is None or len(rpy_rad) == 0 else np.asarray(rpy_rad, float).reshape(-1)
    if rv is not None and rpy is not None:
        raise ValueError(f"{what}: give the rotation as rotvec_rad or rpy_rad, not both")
    for name, val in (("rotvec_rad", rv), ("rpy_rad", rpy)):
        if val is not None and val.shape != (3,):
            raise ValueError(f"{what}: {name} needs 3 numbers, got {val.tolist()}")
        if val is not None and not np.all(np.isfinite(val)):
            raise ValueError(f"{what}: {name} must be finite, got {val.tolist()}")
        if val is not None and np.abs(val).max() > 2 * np.pi:  # a rotation needs no angle beyond a turn
            raise ValueError(f"{what}: {name} {val.tolist()} exceeds a full turn (2 pi): degrees given for radians?")
    if rpy is not None:
        return Mount.from_rpy(t * 1e3, rpy)
    return Mount(t * 1e3, (0.0, 0.0, 0.0) if rv is None else rv)


def geometry_from_tool_poses(source_tcp, detector_tcp, hand_eye: HandEye, n_rows: int, n_cols: int,
                             row_pitch_mm: float, col_pitch_mm: float | None = None) -> ConeGeometry:
    """The cone-beam geometry seen by the devices when the TCPs are at the given poses.

    ``source_tcp``, ``detector_tcp``: world poses of the two tool flanges, (4, 4) or (n, 4, 4)
    in mm. ``n_rows``, ``n_cols`` and the pitches describe the read-out (binned) detector,
    whose pixel-grid centre is the detector frame origin.
    """
    S = np.asarray(source_tcp, dtype=np.float64)
    D = np.asarray(detector_tcp, dtype=np.float64)
    if S.shape[-2:] != (4, 4) or D.shape[-2:] != (4, 4):
        raise ValueError(f"tool poses must be 4 x 4 matrices, got {S.shape} and {D.shape}")
    S = _orthonormalised(S.reshape(-1, 4, 4)) @ hand_eye.source.matrix
    D = _orthonormalised(D.reshape(-1, 4, 4)) @ hand_eye.detector.matrix
    if len(S) != len(D):
        raise ValueError(f"{len(S)} source poses for {len(D)} detector poses")
    return ConeGeometry(source_mm=S[:, :3, 3], detector_mm=D[:, :3, 3], u=D[:, :3, 0], v=D[:, :3, 1],
                        n_rows=n_rows, n_cols=n_cols, row_pitch_mm=row_pitch_mm,
                        col_pitch_mm=row_pitch_mm if col_pitch_mm is None else col_pitch_mm)


def device_frames(geom: ConeGeometry) -> tuple[np.ndarray, np.ndarray]:
    """World frames (n, 4, 4) of the source (focal spot, axes u, v, w) and of the detector."""
    B = geom.local_frames()
    S = np.tile(np.eye(4), (geom.n_views, 1, 1))
    D = S.copy()
    S[:, :3, :3] = B
    D[:, :3, :3] = B
    S[:, :3, 3] = geom.source_mm
    D[:, :3, 3] = geom.detector_mm
    return S, D


def tool_goals_from_geometry(geom: ConeGeometry, hand_eye: HandEye) -> tuple[np.ndarray, np.ndarray]:
    """TCP goal poses (n, 4, 4) mm of the source arm and of the detector arm, per view of ``geom``.

    The inverse of :func:`geometry_from_tool_poses`: the detector frame is (u, v, w) at the
    detector centre; the source frame is the focal spot with the same axes (the source faces
    the detector along -w).
    """
    S, D = device_frames(geom)
    return S @ invert(hand_eye.source.matrix), D @ invert(hand_eye.detector.matrix)
