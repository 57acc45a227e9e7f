"""The Universal Robots arm driver (ur-rtde behind a process wall).

Units and conventions as in :mod:`robot_ct_ros.hardware.arm` (whose interface :class:`URArm`
implements; the names imported from there below stay importable from here): a TCP pose is
``[x, y, z, rx, ry, rz]`` in metres and a rotation vector (radians), joints in radians.

Why a child process: ur-rtde's constructors block forever on a peer that accepts the TCP
connection and never answers, they hold the GIL while doing so (the Python bindings release it
only in the motion and getter calls), and its background threads call ``std::terminate`` when a
reconnect fails. So the ur-rtde objects live in a child process
(:mod:`robot_ct_ros.hardware.ur_worker`, started with the ``spawn`` context) and every call from
the parent goes over a pipe with a timeout. On a timeout or a dead child the parent kills the
child and raises :class:`ArmConnectionError`; no call ever blocks its caller longer than its
timeout (plus the time to kill the child). On Linux the child dies with the parent, even a parent
killed while the child is stuck in ur-rtde (PR_SET_PDEATHSIG; see :class:`_Spawner`).
"""

from __future__ import annotations

import itertools
import multiprocessing
import os
import queue
import threading
from typing import Sequence

import numpy as np

from robot_ct_ros.hardware.arm import (Arm, ArmConnectionError, ArmError, ArmMotionError, ArmSnapshot, as_pose,
                                       pose_distance)

__all__ = ["URArm", "Arm", "ArmError", "ArmConnectionError", "ArmMotionError", "as_pose", "pose_distance",
           "ROBOT_MODES", "SAFETY_MODES", "mode_fault"]

# The RTDE robot_mode and safety_mode values (UR's RTDE guide).
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
SAFETY_MODES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
                6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
                10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
                13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}
_RUNNING = 7
_HOLDING_SAFETY_MODES = (1, 2)  # NORMAL, REDUCED (slower limits; the arm still holds its pose under control)


def mode_fault(robot_mode, safety_mode) -> str:
    """Why a UR arm in these modes does not hold its pose under control ("" when it does): the robot
    not RUNNING (powered off, idle with brakes on, ...) or a safety stop."""
    problems = []
    if robot_mode is not None and int(robot_mode) != _RUNNING:
        problems.append(f"robot_mode {ROBOT_MODES.get(int(robot_mode), 'unknown')} ({int(robot_mode)})")
    if safety_mode is not None and int(safety_mode) not in _HOLDING_SAFETY_MODES:
        problems.append(f"safety_mode {SAFETY_MODES.get(int(safety_mode), 'unknown')} ({int(safety_mode)})")
    return ", ".join(problems)


class _Spawner:
    """Starts the driver processes from one thread that lives as long as this process.

    A driver process asks to be killed when its parent dies (PR_SET_PDEATHSIG, ur_worker); Linux
    sends that signal when the parent *thread* that started it ends, and URArm.connect runs on
    short-lived threads (arm_driver connects off its executor), which would kill a healthy driver.
    """

    _lock = threading.Lock()
    _requests: queue.SimpleQueue | None = None

    @classmethod
    def start(cls, proc) -> None:
        with cls._lock:
            if cls._requests is None:
                cls._requests = queue.SimpleQueue()
                threading.Thread(target=cls._serve, args=(cls._requests,), name="ur_spawner", daemon=True).start()
        slot = [threading.Event(), None]
        cls._requests.put((proc, slot))
        slot[0].wait()
        if slot[1] is not None:
            raise slot[1]

    @staticmethod
    def _serve(requests: queue.SimpleQueue) -> None:
        while True:
            proc, slot = requests.get()
            try:
                proc.start()
            except BaseException as exc:  # noqa: BLE001 - handed to the caller
                slot[1] = exc
            slot[0].set()


class URArm:
    """A Universal Robots arm through ur-rtde (RTDEReceiveInterface + RTDEControlInterface).

    ``host`` is the controller address. ur-rtde uses the controller's fixed ports (RTDE 30004,
    dashboard 29999, script 30003), so there is nothing to configure but the address.
    ``connect_timeout_s`` bounds connect(), ``call_timeout_s`` bounds state reads,
    ``move_timeout_s`` bounds a move unless move_linear() is given its own timeout.
    """

    def __init__(self, host: str, connect_timeout_s: float = 10.0, call_timeout_s: float = 2.0,
                 move_timeout_s: float = 60.0, frequency_hz: float = -1.0, verbose: bool = False):
        if not host:
            raise ValueError("URArm needs the controller address")
        self.host = host
        self.connect_timeout_s = float(connect_timeout_s)
        self.call_timeout_s = float(call_timeout_s)
        self.move_timeout_s = float(move_timeout_s)
        self.frequency_hz = float(frequency_hz)
        self.verbose = bool(verbose)
        self.controller_info: dict = {}
        self._proc = None
        self._conn = None
        self._send_lock = threading.Lock()
        self._pending: dict[int, list] = {}
        self._pending_lock = threading.Lock()
        self._ids = itertools.count(1)
        self._reader: threading.Thread | None = None
        self._dead_reason: str | None = "not connected"
        self._linked = False  # a connect succeeded on the current child: a failure now is a connection *lost*
        self._progress = None  # how far the current connect got (ur_worker.TCP_ACCEPTED, RTDE_RECEIVING)

    # -- process plumbing -------------------------------------------------------------------
    def _start_child(self) -> None:
        from robot_ct_ros.hardware import ur_worker

        ctx = multiprocessing.get_context("spawn")
        parent_conn, child_conn = ctx.Pipe(duplex=True)
        proc = ctx.Process(target=ur_worker.worker_main, args=(child_conn, self.host, os.getpid()),
                           name=f"ur_worker[{self.host}]", daemon=True)
        _Spawner.start(proc)  # from a thread that outlives this one: the child dies with its parent thread
        child_conn.close()
        self._proc, self._conn = proc, parent_conn
        self._dead_reason, self._linked, self._progress = None, False, None
        self._reader = threading.Thread(target=self._read_loop, name=f"ur_reader[{self.host}]", daemon=True)
        self._reader.start()

    def _read_loop(self) -> None:
        conn, proc = self._conn, self._proc
        while True:
            try:
                if not conn.poll(0.1):
                    if not proc.is_alive():
                        raise EOFError
                    continue
                msg_id, status, payload = conn.recv()
                if status == "progress":  # a connect's progress note, not its reply
                    if self._conn is conn:
                        self._progress = payload
                    continue
            except (EOFError, OSError):
                proc.join(0.5)
                if self._conn is conn:  # not a reader left over from an earlier connection
                    self._fail_all(f"connection to controller at {self.host} lost (driver process exited with code "
                                   f"{proc.exitcode})" if self._linked else
                                   f"driver process for {self.host} exited with code {proc.exitcode} before connecting")
                return
            except Exception as exc:  # noqa: BLE001 - a garbled reply: this reader must not die silently
                if self._conn is conn:
                    self._kill_child(f"driver process for {self.host} sent an unreadable reply "
                                     f"({type(exc).__name__}: {exc})")
                return
            with self._pending_lock:
                slot = self._pending.pop(msg_id, None)
            if slot is not None:
                slot[1], slot[2] = status, payload
                slot[0].set()

    def _fail_all(self, reason: str) -> None:
        if self._dead_reason is None:
            self._dead_reason = reason
        with self._pending_lock:
            pending, self._pending = self._pending, {}
        for slot in pending.values():
            slot[1], slot[2] = "dead", self._dead_reason
            slot[0].set()

    def _kill_child(self, reason: str) -> None:
        proc = self._proc
        self._fail_all(reason)
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(2.0)

    def _request(self, op: str, *args, timeout_s: float):
        if self._proc is None or self._dead_reason is not None:
            raise ArmConnectionError(self._dead_reason or f"arm at {self.host} not connected")
        msg_id = next(self._ids)
        slot = [threading.Event(), None, None]
        with self._pending_lock:
            self._pending[msg_id] = slot
        try:
            with self._send_lock:
                self._conn.send((msg_id, op, args))
        except (OSError, ValueError) as exc:
            self._kill_child(f"connection to controller at {self.host} lost ({exc})")
        if not slot[0].wait(timeout_s):
            self._kill_child(self._timeout_reason(op, timeout_s))
        status, payload = slot[1], slot[2]
        if status == "ok":
            return payload
        if status == "dead":
            raise ArmConnectionError(payload)
        kind, message = payload
        if kind == "connection":  # while connecting nothing was lost: connect() says it could not connect
            self._kill_child(message if op == "connect" else f"connection to controller at {self.host} lost: {message}")
            raise ArmConnectionError(self._dead_reason)
        if kind == "motion":
            raise ArmMotionError(message)
        raise ArmError(message)

    def _timeout_reason(self, op: str, timeout_s: float) -> str:
        """Why a request timed out, as far as it is known: a connect says how far the controller got."""
        from robot_ct_ros.hardware.ur_worker import RTDE_PORT, RTDE_RECEIVING, TCP_ACCEPTED

        progress = self._progress if op == "connect" else None
        if progress == TCP_ACCEPTED:
            return (f"controller at {self.host} accepted the connection (port {RTDE_PORT}) but did not complete the "
                    f"RTDE handshake within {timeout_s:.1f} s (a controller that does not speak RTDE, or refuses "
                    f"the protocol version)")
        if progress == RTDE_RECEIVING:
            return (f"controller at {self.host} completed the RTDE handshake but the RTDE control interface (control "
                    f"script, ports 30003 and 29999) did not come up within {timeout_s:.1f} s")
        return f"controller at {self.host} did not answer within {timeout_s:.1f} s ({op})"

    # -- Arm interface ---------------------------------------------------------------------
    def connect(self) -> None:
        if self.is_connected:
            return
        self._shutdown_child()
        self._start_child()
        try:
            self.controller_info = self._request(
                "connect", {"frequency": self.frequency_hz, "verbose": self.verbose,
                            "timeout_s": self.connect_timeout_s},
                timeout_s=self.connect_timeout_s) or {}
            self._linked = True
        except ArmError as exc:
            self._shutdown_child()
            message = str(exc)
            if not message.startswith(f"controller at {self.host} "):  # else it names the controller already
                message = f"cannot connect to controller at {self.host}: {message}"
            raise ArmConnectionError(message) from exc

    def disconnect(self) -> None:
        if self._proc is None:
            return
        if self._dead_reason is None:
            try:
                self._request("disconnect", timeout_s=max(self.call_timeout_s, 3.0))
            except ArmError:
                pass
        self._shutdown_child()

    def _shutdown_child(self) -> None:
        proc, conn = self._proc, self._conn
        if proc is None:
            return
        proc.join(1.0)
        if proc.is_alive():
            proc.kill()
            proc.join(2.0)
        self._fail_all(f"arm at {self.host} disconnected")
        if self._reader is not None:
            self._reader.join(1.0)
        try:
            conn.close()
        except OSError:
            pass
        self._proc = self._conn = self._reader = None
        self._dead_reason = f"arm at {self.host} not connected"

    @property
    def is_connected(self) -> bool:
        return self._proc is not None and self._dead_reason is None and self._proc.is_alive()

    def move_linear(self, pose: Sequence[float], speed: float = 0.25, accel: float = 1.2,
                    timeout_s: float | None = None) -> None:
        """Linear move of the TCP (moveL), blocking until done, refused, or timed out."""
        pose = as_pose(pose)
        self._request("moveL", pose.tolist(), float(speed), float(accel),
                      timeout_s=self.move_timeout_s if timeout_s is None else float(timeout_s))

    def move_joints(self, q: Sequence[float], speed: float = 1.05, accel: float = 1.4,
                    timeout_s: float | None = None) -> None:
        """Joint-space move (moveJ), blocking."""
        q = as_pose(q)
        self._request("moveJ", q.tolist(), float(speed), float(accel),
                      timeout_s=self.move_timeout_s if timeout_s is None else float(timeout_s))

    def read_state(self) -> dict:
        """tcp_pose, joint_positions, robot_mode, safety_mode, runtime_state, timestamp, connected."""
        state = self._request("state", timeout_s=self.call_timeout_s)
        if not state.get("connected", False):
            self._kill_child(f"connection to controller at {self.host} lost (RTDE disconnected)")
            raise ArmConnectionError(self._dead_reason)
        return state

    def get_tcp_pose(self) -> np.ndarray:
        return np.asarray(self.read_state()["tcp_pose"], dtype=float)

    def get_joint_positions(self) -> np.ndarray:
        return np.asarray(self.read_state()["joint_positions"], dtype=float)

    def snapshot(self) -> ArmSnapshot:
        """Measured TCP pose and joints from one state read, with the controller's clock (a real arm
        does not know its true pose) and :func:`mode_fault` of its modes. Raises ArmConnectionError on non-finite values (a corrupt stream)."""
        state = self.read_state()
        pose, q = np.asarray(state["tcp_pose"], float), np.asarray(state["joint_positions"], float)
        if pose.shape != (6,) or q.shape != (6,) or not (np.all(np.isfinite(pose)) and np.all(np.isfinite(q))):
            self._kill_child(f"controller at {self.host} sent an unusable state (pose {pose.tolist()}, "
                             f"joints {q.tolist()})")
            raise ArmConnectionError(self._dead_reason)
        ts = state.get("timestamp")
        return ArmSnapshot(pose, q, None, float(ts) if ts is not None and np.isfinite(ts) else None,
                           fault=mode_fault(state.get("robot_mode"), state.get("safety_mode")))

    def __enter__(self):
        self.connect()
        return self

    def __exit__(self, *exc):
        self.disconnect()

    def __del__(self):
        try:
            proc = self._proc
            if proc is not None and proc.is_alive():
                proc.kill()
        except Exception:
            pass

