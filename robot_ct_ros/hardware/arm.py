"""Robot arm interface, the arm driver's settings, and the worker threads that drive an arm (no ROS import).

Units and conventions (as UR uses them, and SI at ROS interfaces): a TCP pose is the 6-vector
``[x, y, z, rx, ry, rz]`` -- position in metres and orientation as a rotation vector (axis times
angle, radians) of the tool frame in the robot base frame; joint positions in radians.

An arm (:class:`Arm`) is either a Universal Robots arm through ur-rtde
(:class:`robot_ct_ros.hardware.ur_arm.URArm`) or its simulated twin
(:class:`robot_ct_ros.hardware.simulated_arm.SimulatedArm`); :func:`robot_ct_ros.hardware.arms.make_arm` picks one from the
settings. What differs between them is behind the interface: :meth:`Arm.snapshot` reads the
measured state in one call and carries the true pose where the arm knows it (the simulated arm:
it feeds the simulated detector), and the simulated arm's error injection is its own settings
(:class:`robot_ct_ros.hardware.simulated_arm.SimulatedArmSettings`).

:class:`ArmRunner` drives a connected arm from two threads, as the arm_driver node needs: one
polls the state at a fixed rate, the other runs linear moves one at a time (the newest goal
wins). A lost connection is recorded (:attr:`ArmRunner.lost_reason`) for the owner to act on,
and so is the death of either thread from an unexpected exception (:attr:`ArmRunner.failure`, and
the ``on_thread_died`` callback): a thread never dies silently. :class:`ArmWatch` keeps reading a
connected arm that is not driven (the arm driver configured but inactive) at a low rate, so a
connection lost then is noticed too.

Freshness: a snapshot carries the controller's own clock (``timestamp_s``, the UR controller's time
since power-up; None for an arm without one, whose every read is fresh). The runner keeps the host
time at which each sample was taken (the controller time mapped through the smallest observed
host-minus-controller offset, so transport latency does not age it) and calls the state *stale*
when the controller clock has not advanced for ``max_state_age_s``: a frozen controller keeps
answering with its last sample, which must not be republished as fresh. Stale for longer than
``call_timeout_s`` counts as a lost connection. An arm without a clock is never stale.

:func:`arm_health` is the arm driver's /diagnostics status (level, message, values) from its runner.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence, runtime_checkable

import numpy as np

from robot_ct_ros.parameters import setting, validate

__all__ = ["ArmError", "ArmConnectionError", "ArmMotionError", "ArmSnapshot", "Arm", "as_pose", "pose_distance",
           "ArmSettings", "ArmRunner", "ArmWatch", "ARM_ERRORS", "arm_health"]


class ArmError(RuntimeError):
    """The arm refused or failed a command."""


class ArmConnectionError(ArmError):
    """The controller cannot be reached, stopped answering, or the connection was lost."""


class ArmMotionError(ArmError):
    """A move was refused or did not complete (the connection itself may still be fine)."""


@dataclass(frozen=True)
class ArmSnapshot:
    """The state of an arm at one moment.

    Attributes
    ----------
    tcp_pose : numpy.ndarray
        Measured TCP pose ``[x, y, z, rx, ry, rz]`` (m, rad) in the base frame.
    joint_positions : numpy.ndarray
        Joint positions (rad), shoulder pan first.
    true_tcp_pose : numpy.ndarray or None
        Where the tool really is, when the arm knows it (the simulated arm); None for a real arm.
    timestamp_s : float or None
        The controller's clock when it measured this state (s, any origin; UR: time since the
        controller started); None when the arm has no clock of its own (every read is a new sample).
    fault : str
        Why the arm does not hold its pose under control now, naming the controller's mode (UR: robot
        mode not RUNNING, or a safety stop); empty in normal running. Such an arm is never in position.
    """

    tcp_pose: np.ndarray
    joint_positions: np.ndarray
    true_tcp_pose: np.ndarray | None = None
    timestamp_s: float | None = None
    fault: str = ""


@runtime_checkable
class Arm(Protocol):
    """What the arm_driver node needs from an arm (real or simulated)."""

    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def move_linear(self, pose: Sequence[float], speed: float = 0.25, accel: float = 1.2,
                    timeout_s: float | None = None) -> None: ...
    def get_tcp_pose(self) -> np.ndarray: ...
    def get_joint_positions(self) -> np.ndarray: ...
    def snapshot(self) -> ArmSnapshot:
        """The measured pose and joints read together (and the true pose where known); raises ArmError."""
    @property
    def is_connected(self) -> bool: ...


def as_pose(pose: Sequence[float]) -> np.ndarray:
    """A TCP pose as a float array of shape (6,).

    Raises
    ------
    ValueError
        Not 6 finite numbers.
    """
    p = np.asarray(pose, dtype=float).reshape(-1)
    if p.shape != (6,) or not np.all(np.isfinite(p)):
        raise ValueError(f"a TCP pose is 6 finite numbers [x, y, z, rx, ry, rz], got {pose!r}")
    return p


def pose_distance(a: Sequence[float], b: Sequence[float]) -> tuple[float, float]:
    """Translation distance (m) and rotation angle (rad) between two TCP poses."""
    from scipy.spatial.transform import Rotation

    a, b = as_pose(a), as_pose(b)
    dt = float(np.linalg.norm(a[:3] - b[:3]))
    rel = Rotation.from_rotvec(b[3:]) * Rotation.from_rotvec(a[3:]).inv()
    return dt, float(rel.magnitude())


@dataclass(frozen=True)
class ArmSettings:
    """Connection and motion of one arm (the arm_driver's parameters of the same names, SI units)."""

    robot_ip: str = setting("", "controller address; empty: the simulated arm")
    connect_timeout_s: float = setting(10.0, "the connection fails if the controller does not answer within this",
                                       unit="s", minimum=0.0)
    call_timeout_s: float = setting(2.0, "a state read slower than this counts as a lost connection",
                                    unit="s", minimum=0.0)
    move_timeout_s: float = setting(60.0, "a move not finished within this fails", unit="s", minimum=0.0)
    speed: float = setting(0.25, "moveL tool speed", unit="m/s", minimum=0.0)
    acceleration: float = setting(1.2, "moveL tool acceleration", unit="m/s^2", minimum=0.0)
    position_tolerance_m: float = setting(1e-4, "in position: measured-to-goal distance at most", unit="m",
                                          minimum=0.0)
    orientation_tolerance_rad: float = setting(1e-3, "in position: measured-to-goal angle at most", unit="rad",
                                               minimum=0.0)
    max_state_age_s: float = setting(0.25, "the controller's state is stale (not published, not in position) when "
                                           "its clock has not advanced for this long", unit="s", minimum=0.0)

    def __post_init__(self):
        validate(self)


class ArmRunner:
    """Drives a connected arm from two daemon threads (module docstring).

    Parameters
    ----------
    settings : ArmSettings
        Speed, acceleration, move timeout, in-position tolerances, state freshness.
    rate_hz : float
        State polling rate (at least 0.1 Hz).
    on_move_failed : callable(str), optional
        Called from the move thread with "move failed: <reason>" when a move fails (the
        connection itself still up).
    on_thread_died : callable(str), optional
        Called from the dying thread with "<thread> thread died: <exception>" when either thread
        ends on an unexpected exception (a bug, or a fault nobody foresaw); :attr:`failure` keeps
        the first such reason until the next :meth:`start`.
    clock : callable() -> float, optional
        Host monotonic clock in seconds (tests).

    Notes
    -----
    :meth:`start` and :meth:`stop` are called by the owner's thread; :meth:`command`, the
    read-outs and :meth:`in_position` from any thread. The last target and snapshot outlive
    :meth:`stop` (diagnostics show them); in_position is false until a move completes again.
    """

    def __init__(self, settings: ArmSettings, rate_hz: float, on_move_failed: Callable[[str], None] | None = None,
                 on_thread_died: Callable[[str], None] | None = None, clock: Callable[[], float] = time.monotonic):
        self.settings = settings
        self.period_s = 1.0 / max(float(rate_hz), 0.1)
        self._on_move_failed = on_move_failed or (lambda message: None)
        self._on_thread_died = on_thread_died or (lambda message: None)
        self._clock = clock
        self.arm = None
        self.active = False
        self.snapshot: ArmSnapshot | None = None
        self.target: np.ndarray | None = None
        self.lost_reason: str | None = None
        self.failure: str | None = None
        self.moves_completed = 0
        self.samples = 0                        # new controller samples seen since start
        self._handed_out = -1                   # self.samples when new_sample() last returned one
        self._sample_host_s: float | None = None  # host time at which the latest sample was measured
        self._offset_s: float | None = None       # smallest host - controller clock offset seen
        self._lock = threading.Lock()
        self._moving = False
        self._move_ok = False
        self._next_goal: np.ndarray | None = None
        self._goal_event = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def start(self, arm: Arm) -> None:
        """Start polling and accepting goals for ``arm`` (connected)."""
        self.arm, self.lost_reason, self.failure = arm, None, None
        with self._lock:
            self.snapshot, self._sample_host_s, self._offset_s, self.samples = None, None, None, 0
            self._handed_out = -1
        self._stop.clear()
        self.active = True
        self._threads = [threading.Thread(target=self._guarded, args=(self._poll_loop, "arm_poll", arm),
                                          name="arm_poll", daemon=True),
                         threading.Thread(target=self._guarded, args=(self._move_loop, "arm_move", arm),
                                          name="arm_move", daemon=True)]
        for t in self._threads:
            t.start()

    def stop(self) -> bool:
        """Stop both threads (a move in flight ends on its own timeout; never waited for here).

        Returns
        -------
        bool
            Whether the runner was active.
        """
        was_active, self.active = self.active, False
        self._stop.set()
        self._goal_event.set()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(0.2 if t.name == "arm_move" else 2.0)
        self._threads = []
        with self._lock:
            self._moving, self._move_ok, self._next_goal = False, False, None
        return was_active

    def command(self, goal) -> None:
        """Move to ``goal`` (TCP pose, m and rad) next; a goal not started yet is replaced.

        Raises
        ------
        ValueError
            ``goal`` is not 6 finite numbers (nothing is commanded).
        """
        goal = as_pose(goal)
        with self._lock:
            self.target = goal
            self._next_goal = goal
            self._moving, self._move_ok = True, False
            self._goal_event.set()

    def in_position(self) -> bool:
        """The last commanded move completed, the state is fresh, the arm reports no fault (a protective
        stop or power-off: the beam must not be allowed), and the measured pose is within tolerance of the goal."""
        with self._lock:
            if self._moving or not self._move_ok or self.target is None or self.snapshot is None:
                return False
            if self.snapshot.fault:
                return False
            snap, target = self.snapshot, self.target
        if self.stale():
            return False
        dt, dr = pose_distance(snap.tcp_pose, target)
        s = self.settings
        return dt <= s.position_tolerance_m and dr <= s.orientation_tolerance_rad

    def latest(self) -> ArmSnapshot | None:
        with self._lock:
            return self.snapshot

    def new_sample(self) -> ArmSnapshot | None:
        """The latest snapshot if it is fresh (not :meth:`stale`) and a sample this method has not
        returned since :meth:`start`, else None: each sample is handed out (published) once."""
        snap = self.latest()
        if snap is None or self.stale() or self.samples == self._handed_out:
            return None
        self._handed_out = self.samples
        return snap

    def sample_time_s(self) -> float | None:
        """Host monotonic time (s) at which the latest sample was measured (None before the first)."""
        with self._lock:
            return self._sample_host_s

    def state_age_s(self) -> float:
        """How old the latest sample is (s; infinite before the first)."""
        t = self.sample_time_s()
        return math.inf if t is None else max(0.0, self._clock() - t)

    def stale(self) -> bool:
        """The controller's clock has not advanced for longer than ``max_state_age_s``. An arm without
        a clock of its own (the simulated arm: every read is its current state) is never stale: a
        late poll there is only a busy host, and must not cut the beam."""
        snap = self.latest()
        if snap is None or snap.timestamp_s is None:
            return False
        return self.state_age_s() > self.settings.max_state_age_s

    # -- threads ------------------------------------------------------------------------------
    def _guarded(self, loop, name: str, arm) -> None:
        try:
            loop(arm)
        except BaseException as exc:  # noqa: BLE001 - a thread never dies silently
            reason = f"{name} thread died: {type(exc).__name__}: {exc}"
            with self._lock:
                if arm is not self.arm or not self.active:
                    return  # an arm we already let go of
                if self.failure is None:
                    self.failure = reason
                self._moving, self._move_ok = False, False
            self._on_thread_died(reason)

    def _record(self, snap: ArmSnapshot, received_s: float) -> None:
        with self._lock:
            previous = self.snapshot
            if snap.timestamp_s is None:  # no controller clock: every read is a new sample
                self._sample_host_s = received_s
                self.samples += 1
            elif previous is None or previous.timestamp_s is None or snap.timestamp_s != previous.timestamp_s:
                offset = received_s - float(snap.timestamp_s)
                if self._offset_s is None or offset < self._offset_s or \
                        (previous is not None and previous.timestamp_s is not None
                         and snap.timestamp_s < previous.timestamp_s):  # the controller restarted its clock
                    self._offset_s = offset
                self._sample_host_s = float(snap.timestamp_s) + self._offset_s
                self.samples += 1
            elif self._sample_host_s is not None:
                snap = previous if previous is not None else snap  # the same sample, read again
            self.snapshot = snap

    def _poll_loop(self, arm) -> None:
        while not self._stop.is_set():
            t0 = self._clock()
            try:
                snap = arm.snapshot()
            except ArmError as exc:
                self._connection_lost(str(exc), arm)
                return
            self._record(snap, self._clock())
            age = self.state_age_s()
            if snap.timestamp_s is not None and age > max(self.settings.call_timeout_s, self.settings.max_state_age_s):
                self._connection_lost(f"the controller stopped updating its state (no new sample for {age:.2f} s)",
                                      arm)
                return
            self._stop.wait(max(0.0, self.period_s - (self._clock() - t0)))

    def _move_loop(self, arm) -> None:
        s = self.settings
        while not self._stop.is_set():
            self._goal_event.wait()
            with self._lock:
                goal, self._next_goal = self._next_goal, None
                self._goal_event.clear()
            if goal is None or self._stop.is_set():
                continue
            try:
                arm.move_linear(goal, s.speed, s.acceleration, timeout_s=s.move_timeout_s)
                with self._lock:
                    if self._next_goal is None:
                        self._moving, self._move_ok = False, True
                self.moves_completed += 1
            except ArmConnectionError as exc:
                self._connection_lost(str(exc), arm)
                return
            except ArmError as exc:
                self._on_move_failed(f"move failed: {exc}")
                with self._lock:
                    if self._next_goal is None:
                        self._moving, self._move_ok = False, False

    def _connection_lost(self, reason: str, arm) -> None:
        with self._lock:
            if arm is not self.arm or not self.active:
                return  # a late failure of an arm we already let go of
            if self.lost_reason is None:
                self.lost_reason = reason
            self._moving, self._move_ok = False, False


class ArmWatch:
    """Reads the state of a connected arm nobody drives, every ``period_s`` on a daemon thread, so that
    a connection lost while the arm driver is inactive is noticed (nothing else reads the arm then).

    A failed read, or a controller clock that has not advanced for ``max(call_timeout_s,
    max_state_age_s)`` (a hung controller answering with its last state), is recorded in
    :attr:`lost_reason` for the owner to act on; the thread then ends. :meth:`start` and :meth:`stop`
    are the owner's; a read under way when :meth:`stop` is called is never waited for, and its result
    is dropped. An unexpected exception ends the thread through ``on_thread_died`` (as ArmRunner's).
    """

    def __init__(self, settings: ArmSettings, period_s: float = 0.5,
                 on_thread_died: Callable[[str], None] | None = None, clock: Callable[[], float] = time.monotonic):
        self.settings = settings
        self.period_s = float(period_s)
        self._on_thread_died = on_thread_died or (lambda message: None)
        self._clock = clock
        self.arm = None
        self.lost_reason: str | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def active(self) -> bool:
        return self._thread is not None

    def start(self, arm) -> None:
        self.stop()
        self.arm, self.lost_reason = arm, None
        self._stop = stop = threading.Event()  # a thread left from before keeps its own, set, event
        self._thread = threading.Thread(target=self._guarded, args=(arm, stop), name="arm_watch", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(0.1)
        self._thread, self.arm = None, None

    def _guarded(self, arm, stop: threading.Event) -> None:
        try:
            self._loop(arm, stop)
        except BaseException as exc:  # noqa: BLE001 - a thread never dies silently
            if not stop.is_set():
                self._on_thread_died(f"arm_watch thread died: {type(exc).__name__}: {exc}")

    def _loop(self, arm, stop: threading.Event) -> None:
        limit_s = max(self.settings.call_timeout_s, self.settings.max_state_age_s)
        last_ts, since_s = None, self._clock()
        while not stop.wait(self.period_s):
            try:
                snap = arm.snapshot()
            except ArmError as exc:
                reason = str(exc)
            else:
                if snap.timestamp_s is None or snap.timestamp_s != last_ts:
                    last_ts, since_s = snap.timestamp_s, self._clock()
                    continue
                if self._clock() - since_s <= limit_s:
                    continue
                reason = f"the controller stopped updating its state (no new sample for {self._clock() - since_s:.2f} s)"
            if not stop.is_set():  # not an arm already let go of
                self.lost_reason = reason
            return


ARM_ERRORS = ("connection lost", "configure failed", "connect failed", "fault")
"""How an arm driver's last error starts when it is an ERROR on /diagnostics (any other one is a WARN)."""


def arm_health(runner: ArmRunner, arm, lifecycle_state: str, last_error: str, *, connecting_s: float | None,
               where: str, goal_problem: str, goals_refused: int, base_frame: str, tool_frame: str):
    """The /diagnostics status of an arm driver: ``(level, message, values)``, level "ok", "warn" or "error".

    ``arm`` is the connected arm (None: none); ``connecting_s`` how long a connection attempt to
    ``where`` has been under way (None: none is). In order: a last error starting with one of
    :data:`ARM_ERRORS` is an ERROR; connecting is a WARN; a fault the arm reports (protective stop, power
    off) an ERROR; a stale state, another last error, or a lifecycle
    state other than active a WARN; else OK (with "in position" when it is), made a WARN when
    ``goal_problem`` (the last refused goal) is set. ``values`` are (key, value) pairs."""
    in_position = runner.in_position()
    if last_error.startswith(ARM_ERRORS):
        level, message = "error", last_error
    elif connecting_s is not None:
        level, message = "warn", f"connecting to {where} ({connecting_s:.1f} s)"
    elif runner.active and (snap := runner.latest()) is not None and snap.fault:
        level, message = "error", f"robot not ready: {snap.fault}"
    elif runner.active and runner.latest() is not None and runner.stale():
        level = "warn"
        message = (f"state stale: no new sample from the controller for {runner.state_age_s():.2f} s "
                   f"(limit {runner.settings.max_state_age_s} s)")
    elif lifecycle_state != "active" or last_error:
        level, message = "warn", last_error or lifecycle_state
    else:
        level, message = "ok", f"{lifecycle_state}, in position" if in_position else lifecycle_state
    if goal_problem and level == "ok":
        level, message = "warn", f"{message}; last goal refused: {goal_problem}"
    target = None if runner.target is None else [round(float(v), 6) for v in runner.target]
    age = runner.state_age_s() if runner.latest() is not None else None
    connection = "connecting" if connecting_s is not None else "connected" if (
        arm is not None and arm.is_connected) else "disconnected"
    return level, message, (
        ("lifecycle_state", lifecycle_state), ("connection", connection), ("connected", connection == "connected"),
        ("in_position", in_position), ("moves_completed", runner.moves_completed),
        ("state_age_s", None if age is None else f"{age:.3f}"), ("goals_refused", goals_refused),
        ("target_pose", target), ("base_frame", base_frame), ("tool_frame", tool_frame))
