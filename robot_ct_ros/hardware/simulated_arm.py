"""Simulated UR arm with configurable coordination errors, and UR5e kinematics.

The simulated arm reaches a *true* pose that differs from the commanded one by
  - a per-move random error: each translation axis ~ N(0, sigma_mm) mm, and a rotation
    error whose rotation-vector components are each ~ N(0, sigma_deg) degrees, applied in the
    base frame (true R = R_err @ R_cmd);
  - a slow drift: after k moves the position is offset by k * drift_mm_per_move mm along
    ``drift_direction`` (a unit vector; a seeded random direction when not given).
Like a real robot whose encoders do not see the coordination error, its *measured* TCP pose
(get_tcp_pose) is the commanded pose; the true pose (true_tcp_pose) is for the simulated
detector only. Poses: [x, y, z, rx, ry, rz] in metres and a rotation vector (radians).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from robot_ct_ros.hardware.arm import ArmConnectionError, ArmMotionError, ArmSnapshot, as_pose, pose_distance
from robot_ct_ros.parameters import setting, validate

__all__ = ["UR5E_DH", "HOME_Q", "JOINT_NAMES", "pose_to_matrix", "matrix_to_pose", "forward_kinematics",
           "inverse_kinematics", "SimulatedArmErrors", "SimulatedArmSettings", "SimulatedArm"]

# UR5e standard Denavit-Hartenberg parameters (metres, radians), from Universal Robots.
UR5E_DH = {
    "d": (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996),
    "a": (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
    "alpha": (np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0),
}
HOME_Q = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
JOINT_NAMES = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint",
               "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")


def pose_to_matrix(pose: Sequence[float]) -> np.ndarray:
    p = as_pose(pose)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(p[3:]).as_matrix()
    T[:3, 3] = p[:3]
    return T


def matrix_to_pose(T: np.ndarray) -> np.ndarray:
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec()])


def forward_kinematics(q: Sequence[float], dh: dict = UR5E_DH) -> np.ndarray:
    """TCP pose (flange, no tool offset) of joint positions ``q``."""
    T = np.eye(4)
    for theta, d, a, alpha in zip(q, dh["d"], dh["a"], dh["alpha"]):
        ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
        T = T @ np.array([[ct, -st * ca, st * sa, a * ct],
                          [st, ct * ca, -ct * sa, a * st],
                          [0.0, sa, ca, d],
                          [0.0, 0.0, 0.0, 1.0]])
    return matrix_to_pose(T)


def _pose_error(target_T: np.ndarray, q: np.ndarray, dh: dict) -> np.ndarray:
    T = pose_to_matrix(forward_kinematics(q, dh))
    dp = target_T[:3, 3] - T[:3, 3]
    dr = Rotation.from_matrix(target_T[:3, :3] @ T[:3, :3].T).as_rotvec()
    return np.concatenate([dp, dr])


def inverse_kinematics(pose: Sequence[float], q_seed: Sequence[float], dh: dict = UR5E_DH,
                       iterations: int = 40, tol: float = 1e-20) -> tuple[np.ndarray, bool]:
    """Joint positions near ``q_seed`` reaching ``pose`` (damped least squares).

    Returns ``(q, converged)``; when the pose is out of reach, q is the closest configuration found.
    """
    target_T = pose_to_matrix(pose)
    q = np.asarray(q_seed, dtype=float).copy()
    eps = 1e-6
    err = _pose_error(target_T, q, dh)
    for _ in range(iterations):
        if float(err @ err) < tol:
            break
        J = np.empty((6, 6))
        for j in range(6):
            dq = np.zeros(6)
            dq[j] = eps
            J[:, j] = (err - _pose_error(target_T, q + dq, dh)) / eps
        lam = 1e-4
        step = np.linalg.solve(J.T @ J + lam * np.eye(6), J.T @ err)
        q = q + np.clip(step, -0.5, 0.5)
        err = _pose_error(target_T, q, dh)
    q = (q + np.pi) % (2 * np.pi) - np.pi
    return q, float(err @ err) < 1e-12


@dataclass
class SimulatedArmErrors:
    """Error model of the simulated arm (see the module docstring)."""

    sigma_mm: float = 0.0
    sigma_deg: float = 0.0
    drift_mm_per_move: float = 0.0
    drift_direction: Sequence[float] | None = None
    seed: int | None = 0


@dataclass(frozen=True)
class SimulatedArmSettings:
    """Error model and fault injection of the simulated arm: the arm_driver's ``sim_*`` parameters.

    Units: mm and degrees as the parameter names say (the module docstring defines the errors);
    ``motion_time_scale`` as in :class:`SimulatedArm`; ``fail_after_moves`` None (-1 on ROS) = never.
    """

    sigma_mm: float = setting(0.0, "per-move random translation error, per axis", unit="mm", minimum=0.0)
    sigma_deg: float = setting(0.0, "per-move random rotation error, per axis", unit="deg", minimum=0.0)
    drift_mm_per_move: float = setting(0.0, "slow drift along a seeded random direction", unit="mm/move")
    seed: int = setting(0, "seed of the errors and of the drift direction", minimum=0)
    motion_time_scale: float = setting(0.0, "0: moves complete instantly; else the scale of the motion-time model",
                                       minimum=0.0)
    fail_after_moves: int | None = setting(None, "drop the connection at move N + 1 (fault tests)", kind=int,
                                           minimum=0, ros_none=-1)

    def __post_init__(self):
        validate(self)

    def errors(self) -> SimulatedArmErrors:
        """The error model of these settings."""
        return SimulatedArmErrors(sigma_mm=self.sigma_mm, sigma_deg=self.sigma_deg,
                                  drift_mm_per_move=self.drift_mm_per_move, seed=self.seed)


@dataclass
class SimulatedArm:
    """A UR-like arm that follows commands instantly or with a simple motion-time model.

    ``motion_time_scale``: 0 moves instantly; otherwise a move takes
    ``scale * (distance / speed + angle / (4 * speed) + speed / accel)`` seconds.
    ``fail_after_moves``: the connection drops at the start of move number N + 1 (fault tests).
    ``fault``: set it to the reason (e.g. "protective stop") for a controller that stops holding
    the arm; snapshots carry it (never in position) until it is cleared.
    """

    errors: SimulatedArmErrors = field(default_factory=SimulatedArmErrors)
    initial_q: Sequence[float] = HOME_Q
    motion_time_scale: float = 0.0
    fail_after_moves: int | None = None
    fault: str = ""

    @classmethod
    def from_settings(cls, settings: SimulatedArmSettings) -> "SimulatedArm":
        """A simulated arm with the errors and faults of ``settings``."""
        return cls(errors=settings.errors(), motion_time_scale=settings.motion_time_scale,
                   fail_after_moves=settings.fail_after_moves)

    def __post_init__(self):
        self._lock = threading.Lock()
        self._rng = np.random.default_rng(self.errors.seed)
        if self.errors.drift_direction is None:
            d = self._rng.normal(size=3)
        else:
            d = np.asarray(self.errors.drift_direction, dtype=float)
        n = np.linalg.norm(d)
        self._drift_dir = d / n if n > 0 else np.zeros(3)
        self._q = np.asarray(self.initial_q, dtype=float).copy()
        self._commanded = forward_kinematics(self._q)
        self._true = self._commanded.copy()
        self._connected = False
        self.moves_done = 0

    # -- Arm interface ---------------------------------------------------------------------
    def connect(self) -> None:
        if self.fail_after_moves is not None and self.moves_done > self.fail_after_moves:
            raise ArmConnectionError("simulated arm: controller gone (fault injected)")
        self._connected = True

    def disconnect(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    def _check(self) -> None:
        if not self._connected:
            raise ArmConnectionError("simulated arm not connected")

    def move_linear(self, pose: Sequence[float], speed: float = 0.25, accel: float = 1.2,
                    timeout_s: float | None = None) -> None:
        pose = as_pose(pose)
        self._check()
        if speed <= 0 or accel <= 0:
            raise ArmMotionError(f"speed and acceleration must be positive (got {speed}, {accel})")
        if self.fail_after_moves is not None and self.moves_done >= self.fail_after_moves:
            self._connected = False
            self.moves_done += 1
            raise ArmConnectionError(
                f"simulated arm: connection lost during move {self.moves_done} (fault injected)")
        if self.motion_time_scale > 0:
            dist, ang = pose_distance(self._commanded, pose)
            duration = self.motion_time_scale * (dist / speed + ang / (4 * speed) + speed / accel)
            if timeout_s is not None and duration > timeout_s:
                raise ArmMotionError(f"move would take {duration:.2f} s, more than the {timeout_s:.2f} s timeout")
            time.sleep(duration)
            self._check()
        q, _ = inverse_kinematics(pose, self._q)
        true = self._perturb(pose, self.moves_done + 1)
        with self._lock:
            self._q = q
            self._commanded = pose.copy()
            self._true = true
            self.moves_done += 1

    def _perturb(self, pose: np.ndarray, k: int) -> np.ndarray:
        e = self.errors
        dp = self._rng.normal(0.0, e.sigma_mm, size=3) * 1e-3 if e.sigma_mm > 0 else np.zeros(3)
        dp = dp + self._drift_dir * (k * e.drift_mm_per_move * 1e-3)
        true = pose.copy()
        true[:3] += dp
        if e.sigma_deg > 0:
            r_err = Rotation.from_rotvec(np.deg2rad(self._rng.normal(0.0, e.sigma_deg, size=3)))
            true[3:] = (r_err * Rotation.from_rotvec(pose[3:])).as_rotvec()
        return true

    def get_tcp_pose(self) -> np.ndarray:
        """The measured (= commanded) TCP pose."""
        self._check()
        with self._lock:
            return self._commanded.copy()

    def true_tcp_pose(self) -> np.ndarray:
        """Where the tool really is (simulation only: feeds the simulated detector)."""
        with self._lock:
            return self._true.copy()

    def get_joint_positions(self) -> np.ndarray:
        self._check()
        with self._lock:
            return self._q.copy()

    def snapshot(self) -> ArmSnapshot:
        """Measured (= commanded) TCP pose, joints, and the true pose (for the simulated detector)."""
        return ArmSnapshot(self.get_tcp_pose(), self.get_joint_positions(), self.true_tcp_pose(), fault=self.fault)
