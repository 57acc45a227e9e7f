"""Loopback emulator of a Universal Robots controller, good enough for the real ur-rtde library.

Test code. It serves, on one loopback address:
  - the dashboard server (29999): line commands answered as PolyScope 5 does
    ("PolyscopeVersion", "robotmode", "safetystatus", "is in remote control", "power on",
    "brake release", "play", "stop", "load <p>", "get serial number", ...);
  - the primary/secondary/realtime script ports (30001/30002/30003): URScript programs sent
    there are recorded; a program named ``rtde_control`` (the control script that ur-rtde's
    RTDEControlInterface uploads) is *emulated*: the emulator runs the same register handshake
    as that script (see below). No robot-state stream is sent on these ports (ur-rtde does not
    read them);
  - RTDE (30004), protocol versions 1 and 2: version negotiation, controller version, output and
    input recipe setup (types from the RTDE guide's table; unknown names answer ``NOT_FOUND``
    and recipe id 0), start/pause, data packages streamed at min(requested, ``max_rate_hz``),
    and input data packages written into the input registers.

The control-script handshake (ur-rtde's rtde_control script, register offset 0 or 24):
``input_int_register_0`` carries a command id, ``input_double_register_0..7`` its arguments
(pose or q, speed, acceleration) and ``input_int_register_1`` the async flag; the script answers
in ``output_int_register_0``: 1 = ready for a command (command register is 0), 2 = done with the
command; ``runtime_state`` is PLAYING (2) while the script runs. Emulated commands: 1 movej,
2 movej_ik, 3 movel, 4 movel_fk (executed over a short time, TCP and joints interpolated,
UR5e kinematics), 33/34 stopl/stopj, 15/16 speed/servo stop, 47 is_steady, 40 get_tcp_offset,
255 stop script; any other command is acknowledged as done without effect.

ur-rtde connects to fixed ports (30004, 29999, 30003), so two emulators cannot share an address:
each instance binds its own address in 127.0.0.0/8 (all of it is loopback on Linux), picked at
random unless given. Fault options: ``drop_after_moves=N`` closes every socket and listener when
move N + 1 arrives (a controller lost mid-scan); ``silent=True`` accepts connections and never
sends a byte; ``freeze()`` stops the RTDE data stream while every connection stays open (a hung
controller: the last state is all a client has); setting ``safety_mode`` (3 = PROTECTIVE_STOP) or
``powered = False`` (robot_mode 3 = POWER_OFF) changes what the RTDE stream reports.
"""

from __future__ import annotations

import random
import re
import select
import socket
import struct
import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from robot_ct_ros.hardware.simulated_arm import HOME_Q, forward_kinematics, inverse_kinematics
from robot_ct_ros.testing import wait_until  # noqa: F401  (also this module's: test_ur_arm calls emu.wait_until)

DEFAULT_PORTS = {"dashboard": 29999, "primary": 30001, "secondary": 30002, "realtime": 30003, "rtde": 30004}

# RTDE package types (RTDE guide)
RTDE_REQUEST_PROTOCOL_VERSION = 86   # 'V'
RTDE_GET_URCONTROL_VERSION = 118     # 'v'
RTDE_TEXT_MESSAGE = 77               # 'M'
RTDE_DATA_PACKAGE = 85               # 'U'
RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # 'O'
RTDE_CONTROL_PACKAGE_SETUP_INPUTS = 73   # 'I'
RTDE_CONTROL_PACKAGE_START = 83      # 'S'
RTDE_CONTROL_PACKAGE_PAUSE = 80      # 'P'

TYPE_FORMAT = {"BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
               "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I"}

_OUTPUT_FIXED = {
    "timestamp": "DOUBLE", "target_q": "VECTOR6D", "target_qd": "VECTOR6D", "target_qdd": "VECTOR6D",
    "target_current": "VECTOR6D", "target_moment": "VECTOR6D", "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D", "actual_current": "VECTOR6D", "actual_current_window": "VECTOR6D",
    "joint_control_output": "VECTOR6D", "actual_TCP_pose": "VECTOR6D", "actual_TCP_speed": "VECTOR6D",
    "actual_TCP_force": "VECTOR6D", "target_TCP_pose": "VECTOR6D", "target_TCP_speed": "VECTOR6D",
    "actual_digital_input_bits": "UINT64", "joint_temperatures": "VECTOR6D",
    "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE", "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": "VECTOR6D", "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32", "analog_io_types": "UINT32", "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE", "io_current": "DOUBLE", "euromap67_input_bits": "UINT32",
    "euromap67_output_bits": "UINT32", "euromap67_24V_voltage": "DOUBLE",
    "euromap67_24V_current": "DOUBLE", "tool_mode": "UINT32", "tool_analog_input_types": "UINT32",
    "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE", "tool_output_voltage": "INT32",
    "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE", "tcp_force_scalar": "DOUBLE",
    "output_bit_registers0_to_31": "UINT32", "output_bit_registers32_to_63": "UINT32",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "payload": "DOUBLE", "payload_cog": "VECTOR3D", "payload_inertia": "VECTOR6D",
    "script_control_line": "UINT32", "ft_raw_wrench": "VECTOR6D", "tcp_offset": "VECTOR6D",
    "actual_current_as_torque": "VECTOR6D",
}
_INPUT_FIXED = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}
_REGISTER = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")
N_REGISTERS = 48


def _register_type(name: str, direction: str | None) -> str | None:
    m = _REGISTER.match(name)
    if not m:
        return None
    io, kind, n = m.group(1), m.group(2), int(m.group(3))
    if direction == "input" and io != "input":
        return None
    if kind == "bit":
        return "BOOL" if 64 <= n <= 127 else None
    if n >= N_REGISTERS:
        return None
    return "INT32" if kind == "int" else "DOUBLE"


def output_type(name: str) -> str:
    return _OUTPUT_FIXED.get(name) or _register_type(name, None) or "NOT_FOUND"


def input_type(name: str) -> str:
    return _INPUT_FIXED.get(name) or _register_type(name, "input") or "NOT_FOUND"


def free_loopback_host() -> str:
    """A random address in 127.0.0.0/8 (not 127.0.0.1) where all the UR ports are free."""
    for _ in range(200):
        host = f"127.{random.randint(1, 254)}.{random.randint(0, 255)}.{random.randint(2, 254)}"
        socks = []
        try:
            for port in DEFAULT_PORTS.values():
                s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                socks.append(s)
                s.bind((host, port))
            return host
        except OSError:
            continue
        finally:
            for s in socks:
                s.close()
    raise RuntimeError("no free loopback address for the UR emulator")


class _Motion:
    def __init__(self, kind, q0, q1, p0, p1, t0, duration):
        self.kind, self.q0, self.q1, self.p0, self.p1 = kind, q0, q1, p0, p1
        self.t0, self.duration = t0, max(duration, 1e-3)
        self.slerp = Slerp([0.0, 1.0], Rotation.from_rotvec([p0[3:], p1[3:]]))


class URControllerEmulator:
    """See the module docstring. Use as a context manager or call start()/stop()."""

    def __init__(self, host: str | None = None, ports: dict | None = None,
                 controller_version: tuple[int, int, int, int] = (5, 11, 1, 108318),
                 max_rate_hz: float = 125.0, motion_time_scale: float = 0.2, max_motion_time_s: float = 0.5,
                 drop_after_moves: int | None = None, silent: bool = False,
                 initial_q=HOME_Q, powered: bool = True, serial_number: str = "20205500001"):
        self.requested_host = host
        self.ports = dict(DEFAULT_PORTS, **(ports or {}))
        self.controller_version = tuple(int(v) for v in controller_version)
        self.max_rate_hz = float(max_rate_hz)
        self.motion_time_scale = float(motion_time_scale)
        self.max_motion_time_s = float(max_motion_time_s)
        self.drop_after_moves = drop_after_moves
        self.silent = bool(silent)
        self.serial_number = serial_number
        self.host = host
        self._lock = threading.RLock()
        self._running = False
        self._threads: list[threading.Thread] = []
        self._listeners: list[socket.socket] = []
        self._clients: list[socket.socket] = []
        self.dropped = threading.Event()
        self._t_start = time.monotonic()
        # robot state
        self.q = np.asarray(initial_q, dtype=float).copy()
        self.tcp_pose = forward_kinematics(self.q)
        self.powered = bool(powered)
        self.brakes_released = bool(powered)
        self.safety_mode = 1  # NORMAL; 3 PROTECTIVE_STOP, 7 ROBOT_EMERGENCY_STOP (RTDE safety_mode, safety_status)
        self.in_int = [0] * N_REGISTERS
        self.in_double = [0.0] * N_REGISTERS
        self.out_int = [0] * N_REGISTERS
        self.out_double = [0.0] * N_REGISTERS
        self.script_running = False
        self.reg_offset = 0
        self._executing = False
        self._sync_pending = False
        self._motion: _Motion | None = None
        self._settled_at = 0.0
        self._async_motion = False
        self.moves_started = 0
        self.moves_completed = 0
        self.commands: list[int] = []
        self.programs: list[str] = []
        self.dashboard_log: list[str] = []
        self.loaded_program: str | None = None
        self.program_playing = False  # a loaded .urp "playing" (dashboard only, not executed)
        self.rtde_connections = 0
        self._drop_requested = False
        self.frozen = threading.Event()

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> "URControllerEmulator":
        self.host = self.requested_host or free_loopback_host()
        self._running = True
        handlers = {"dashboard": self._serve_dashboard, "primary": self._serve_script,
                    "secondary": self._serve_script, "realtime": self._serve_script, "rtde": self._serve_rtde}
        for name, port in self.ports.items():
            ls = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            ls.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            ls.bind((self.host, port))
            ls.listen(8)
            ls.settimeout(0.1)
            self._listeners.append(ls)
            handler = self._serve_silent if self.silent else handlers[name]
            self._spawn(self._accept_loop, ls, handler, name=f"emu-accept-{name}")
        if not self.silent:
            self._spawn(self._control_loop, name="emu-controller")
        return self

    def _spawn(self, target, *args, name: str) -> None:
        t = threading.Thread(target=target, args=args, name=name, daemon=True)
        t.start()
        self._threads.append(t)

    def freeze(self) -> None:
        """Behave like a hung controller: no more RTDE data packages, every connection left open."""
        self.frozen.set()

    def drop(self) -> None:
        """Behave like a controller that vanished: close every connection and stop listening."""
        self.dropped.set()
        self._running = False
        with self._lock:
            socks = self._listeners + self._clients
            self._listeners, self._clients = [], []
        for s in socks:
            try:
                s.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            try:
                s.close()
            except OSError:
                pass

    def stop(self) -> None:
        was_dropped = self.dropped.is_set()
        self.drop()
        if not was_dropped:
            self.dropped.clear()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(2.0)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()

    def wait_for(self, predicate, timeout_s: float = 10.0) -> bool:
        return wait_until(predicate, timeout_s)

    # -- sockets -----------------------------------------------------------------------------
    def _accept_loop(self, ls: socket.socket, handler) -> None:
        while self._running:
            try:
                conn, _ = ls.accept()
            except socket.timeout:
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(None)
            with self._lock:
                if not self._running:
                    conn.close()
                    return
                self._clients.append(conn)
            self._spawn(self._guarded, handler, conn, name=f"emu-{handler.__name__}")

    def _guarded(self, handler, conn: socket.socket) -> None:
        try:
            handler(conn)
        except OSError:
            pass
        finally:
            with self._lock:
                if conn in self._clients:
                    self._clients.remove(conn)
            try:
                conn.close()
            except OSError:
                pass

    def _serve_silent(self, conn: socket.socket) -> None:
        while self._running:
            r, _, _ = select.select([conn], [], [], 0.2)
            if r and not conn.recv(65536):
                return

    # -- dashboard ---------------------------------------------------------------------------
    def _dashboard_answer(self, line: str) -> str | None:
        cmd = line.strip()
        low = cmd.lower()
        self.dashboard_log.append(cmd)
        v = self.controller_version
        with self._lock:
            if low == "polyscopeversion":
                return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Jan 01 2022)"
            if low == "robotmode":
                return "Robotmode: " + self._robot_mode_name()
            if low == "safetymode":
                return "Safetymode: NORMAL"
            if low == "safetystatus":
                return "Safetystatus: NORMAL"
            if low == "is in remote control":
                return "true"
            if low == "get serial number":
                return self.serial_number
            if low == "get robot model":
                return "UR5"
            if low == "power on":
                self.powered = True
                return "Powering on"
            if low == "power off":
                self.powered = self.brakes_released = False
                self.script_running = False
                return "Powering off"
            if low == "brake release":
                if self.powered:
                    self.brakes_released = True
                return "Brake releasing"
            if low.startswith("load "):
                self.loaded_program = cmd[5:].strip()
                return f"Loading program: {self.loaded_program}"
            if low == "get loaded program":
                return f"Loaded program: {self.loaded_program}" if self.loaded_program else "No program loaded"
            if low == "play":
                if not self.loaded_program:
                    return "Failed to execute: play"
                self.program_playing = True
                return "Starting program"
            if low == "stop":
                self.program_playing = False
                self.script_running = False
                self._motion = None
                return "Stopped"
            if low == "pause":
                self.program_playing = False
                return "Pausing program"
            if low == "running":
                running = self.script_running or self.program_playing
                return f"Program running: {'true' if running else 'false'}"
            if low == "programstate":
                running = self.script_running or self.program_playing
                return ("PLAYING " if running else "STOPPED ") + (self.loaded_program or "<unnamed>")
            if low == "isprogramsaved":
                return f"true {self.loaded_program or '<unnamed>'}"
            if low.startswith("popup "):
                return "showing popup"
            if low == "close popup":
                return "closing popup"
            if low == "close safety popup":
                return "closing safety popup"
            if low == "unlock protective stop":
                return "Protective stop releasing"
            if low == "restart safety":
                return "Restarting safety"
            if low.startswith("addtolog "):
                return "Added log message"
            if low.startswith("setuserrole "):
                return "Setting user role: " + cmd[12:].strip()
            if low == "shutdown":
                return "Shutting down"
            if low == "quit":
                return None
        return f"could not understand: '{cmd}'"

    def _robot_mode_name(self) -> str:
        if not self.powered:
            return "POWER_OFF"
        return "RUNNING" if self.brakes_released else "IDLE"

    def _robot_mode(self) -> int:
        if not self.powered:
            return 3
        return 7 if self.brakes_released else 5

    def _serve_dashboard(self, conn: socket.socket) -> None:
        conn.sendall(b"Connected: Universal Robots Dashboard Server\n")
        buf = b""
        while self._running:
            data = conn.recv(4096)
            if not data:
                return
            buf += data
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                answer = self._dashboard_answer(line.decode(errors="replace"))
                if answer is None:
                    conn.sendall(b"Disconnected\n")
                    return
                conn.sendall(answer.encode() + b"\n")

    # -- script ports ------------------------------------------------------------------------
    def _serve_script(self, conn: socket.socket) -> None:
        buf = ""
        while self._running:
            r, _, _ = select.select([conn], [], [], 0.2)
            if r:
                data = conn.recv(65536)
                if not data:
                    return
                buf += data.decode(errors="replace")
            elif buf:  # a quiet line: whatever arrived is one program or command
                self._on_script(buf)
                buf = ""
                continue
            stripped = buf.rstrip()
            if stripped.startswith("def ") and (stripped.endswith("\nend") or stripped == "end"):
                self._on_script(buf)
                buf = ""

    def _on_script(self, text: str) -> None:
        self.programs.append(text)
        m = re.match(r"\s*def\s+(\w+)\s*\(", text)
        if not m:
            return
        with self._lock:
            if m.group(1) == "rtde_control":
                if not (self.powered and self.brakes_released):
                    return  # a program cannot start on a robot that is off or braked
                off = re.search(r"# int register offset\n\s*(\d+)", text)
                self.reg_offset = int(off.group(1)) if off else 0
                self._executing = False
                self._sync_pending = False
                self.script_running = True
                self.out_int[self.reg_offset] = 1  # signal_ready()
            else:
                # another program replaces the control script and ends at once
                self.script_running = False

    # -- the control script ------------------------------------------------------------------
    def _control_loop(self) -> None:
        while self._running:
            time.sleep(0.004)
            with self._lock:
                self._step(time.monotonic())
                drop = self._drop_requested
            if drop:
                self.drop()
                return

    def _advance_motion(self, now: float) -> None:
        m = self._motion
        if m is None:
            return
        s = min(1.0, (now - m.t0) / m.duration)
        s_smooth = s * s * (3.0 - 2.0 * s)
        q = m.q0 + (m.q1 - m.q0) * s_smooth
        if m.kind == "joint":
            pose = forward_kinematics(q)
        else:
            pose = np.concatenate([m.p0[:3] + (m.p1[:3] - m.p0[:3]) * s_smooth, m.slerp(s_smooth).as_rotvec()])
        if s >= 1.0:
            q, pose = m.q1.copy(), m.p1.copy()
            self._motion = None
            self._settled_at = now + 2.5 / self.max_rate_hz
            self.moves_completed += 1
            self.out_int[self.reg_offset + 2] = 0
        self.q, self.tcp_pose = q, pose

    def _step(self, now: float) -> None:
        self._advance_motion(now)
        if not self.script_running:
            return
        off = self.reg_offset
        if self._sync_pending:
            # done once the move ended and the final state has been streamed (settled)
            if self._motion is None and now >= self._settled_at:
                self._sync_pending = False
                self.out_int[off] = 2  # signal_done_with_cmd()
            return
        cmd = self.in_int[off]
        if cmd == 0:
            self._executing = False
            self.out_int[off] = 1
        elif not self._executing:
            self._executing = True
            self.commands.append(cmd)
            self._process(cmd, now)

    def _process(self, cmd: int, now: float) -> None:
        off = self.reg_offset
        args = np.asarray(self.in_double[off:off + 8], dtype=float)
        if cmd in (1, 2, 3, 4):
            self.moves_started += 1
            if self.drop_after_moves is not None and self.moves_started > self.drop_after_moves:
                self._drop_requested = True
                return
            target, v, a = args[:6], max(args[6], 1e-3), max(args[7], 1e-3)
            if cmd in (1, 4):
                q1 = target.copy()
                p1 = forward_kinematics(q1)
            else:
                p1 = target.copy()
                q1, _ = inverse_kinematics(p1, self.q)
            if cmd in (1, 2):
                dist = float(np.max(np.abs(q1 - self.q)))
                ang = 0.0
            else:
                dist = float(np.linalg.norm(p1[:3] - self.tcp_pose[:3]))
                ang = float((Rotation.from_rotvec(p1[3:]) * Rotation.from_rotvec(self.tcp_pose[3:]).inv()).magnitude())
            duration = min(self.max_motion_time_s,
                           self.motion_time_scale * (dist / v + ang / (4.0 * v) + v / a))
            kind = "joint" if cmd in (1, 2) else "linear"
            self._motion = _Motion(kind, self.q.copy(), q1, self.tcp_pose.copy(), p1, now, duration)
            if self.in_int[off + 1] == 1:  # async: done at once, the move goes on
                self.out_int[off + 2] = 32768
                self.out_int[off] = 2
            else:
                self._sync_pending = True
            return
        if cmd == 255:  # stop script
            self.script_running = False
            self._executing = False
            self.out_int[off] = 0
            return
        if cmd in (15, 16, 33, 34, 42):  # speed/servo stop, stopl, stopj, stop jog
            self._motion = None
        elif cmd == 47:  # is_steady
            self.out_int[off + 1] = 1 if self._motion is None else 0
        elif cmd == 40:  # get_tcp_offset
            for i in range(6):
                self.out_double[off + i] = 0.0
        self.out_int[off] = 2

    # -- RTDE --------------------------------------------------------------------------------
    def _runtime_state(self) -> int:
        return 2 if self.script_running else 1  # PLAYING / STOPPED

    def _value(self, name: str, now: float):
        if name in ("actual_q", "target_q"):
            return tuple(self.q)
        if name in ("actual_TCP_pose", "target_TCP_pose"):
            return tuple(self.tcp_pose)
        if name == "timestamp":
            return now - self._t_start
        if name == "robot_mode":
            return self._robot_mode()
        if name == "safety_mode" or name == "safety_status":
            return self.safety_mode
        if name == "safety_status_bits":
            return 1
        if name == "runtime_state":
            return self._runtime_state()
        if name == "robot_status_bits":
            return (1 if self.powered else 0) | (2 if self.script_running else 0)
        if name == "joint_mode":
            return (253,) * 6
        if name in ("speed_scaling", "target_speed_fraction"):
            return 1.0
        m = _REGISTER.match(name)
        if m and m.group(2) != "bit":
            n = int(m.group(3))
            bank = {("output", "int"): self.out_int, ("output", "double"): self.out_double,
                    ("input", "int"): self.in_int, ("input", "double"): self.in_double}[(m.group(1), m.group(2))]
            return bank[n]
        fmt = TYPE_FORMAT[output_type(name)]
        count = int(fmt[:-1]) if len(fmt) > 1 else 1
        zero = False if fmt[-1] == "?" else 0
        return (zero,) * count if count > 1 else zero

    def _pack_outputs(self, recipe_id: int, names: list[str]) -> bytes:
        now = time.monotonic()
        parts = [struct.pack(">B", recipe_id)]
        with self._lock:
            for name in names:
                fmt = TYPE_FORMAT[output_type(name)]
                value = self._value(name, now)
                parts.append(struct.pack(">" + fmt, *(value if isinstance(value, tuple) else (value,))))
        return b"".join(parts)

    def _apply_inputs(self, names: list[str], payload: bytes) -> None:
        offset = 0
        with self._lock:
            for name in names:
                fmt = ">" + TYPE_FORMAT[input_type(name)]
                values = struct.unpack_from(fmt, payload, offset)
                offset += struct.calcsize(fmt)
                m = _REGISTER.match(name)
                if m and m.group(2) == "int":
                    self.in_int[int(m.group(3))] = values[0]
                elif m and m.group(2) == "double":
                    self.in_double[int(m.group(3))] = values[0]

    @staticmethod
    def _send(conn: socket.socket, kind: int, payload: bytes = b"") -> None:
        conn.sendall(struct.pack(">HB", len(payload) + 3, kind) + payload)

    def _serve_rtde(self, conn: socket.socket) -> None:
        with self._lock:
            self.rtde_connections += 1
        protocol = 1
        outputs: dict[int, list[str]] = {}
        inputs: dict[int, list[str]] = {}
        next_out, next_in = 1, 1
        started = False
        period = 1.0 / self.max_rate_hz
        next_send = time.monotonic()
        buf = b""
        while self._running:
            timeout = max(0.0, next_send - time.monotonic()) if started and outputs else 0.2
            r, _, _ = select.select([conn], [], [], timeout)
            if r:
                data = conn.recv(65536)
                if not data:
                    return
                buf += data
                while len(buf) >= 3:
                    size, kind = struct.unpack_from(">HB", buf)
                    if size < 3 or len(buf) < size:
                        break
                    payload, buf = buf[3:size], buf[size:]
                    if kind == RTDE_REQUEST_PROTOCOL_VERSION:
                        version = struct.unpack(">H", payload[:2])[0]
                        ok = version in (1, 2)
                        protocol = version if ok else protocol
                        self._send(conn, kind, struct.pack(">B", 1 if ok else 0))
                    elif kind == RTDE_GET_URCONTROL_VERSION:
                        self._send(conn, kind, struct.pack(">IIII", *self.controller_version))
                    elif kind == RTDE_CONTROL_PACKAGE_SETUP_OUTPUTS:
                        freq = 125.0
                        if protocol >= 2:
                            freq = struct.unpack(">d", payload[:8])[0]
                            payload = payload[8:]
                        names = [n for n in payload.decode().split(",") if n]
                        types = [output_type(n) for n in names]
                        rid = 0
                        if "NOT_FOUND" not in types and names:
                            rid, next_out = next_out, next_out + 1
                            outputs[rid] = names
                            period = 1.0 / max(1.0, min(freq if freq > 0 else 125.0, self.max_rate_hz))
                        self._send(conn, kind, struct.pack(">B", rid) + ",".join(types).encode())
                    elif kind == RTDE_CONTROL_PACKAGE_SETUP_INPUTS:
                        names = [n for n in payload.decode().split(",") if n]
                        types = [input_type(n) for n in names]
                        rid = 0
                        if "NOT_FOUND" not in types and names:
                            rid, next_in = next_in, next_in + 1
                            inputs[rid] = names
                        self._send(conn, kind, struct.pack(">B", rid) + ",".join(types).encode())
                    elif kind == RTDE_CONTROL_PACKAGE_START:
                        self._send(conn, kind, struct.pack(">B", 1))
                        started = True
                        next_send = time.monotonic()
                    elif kind == RTDE_CONTROL_PACKAGE_PAUSE:
                        self._send(conn, kind, struct.pack(">B", 1))
                        started = False
                    elif kind == RTDE_DATA_PACKAGE and payload:
                        names = inputs.get(payload[0])
                        if names:
                            self._apply_inputs(names, payload[1:])
                    # text messages from the client and unknown packages are ignored
            now = time.monotonic()
            if started and outputs and now >= next_send:
                for rid, names in outputs.items():
                    if not self.frozen.is_set():
                        self._send(conn, RTDE_DATA_PACKAGE, self._pack_outputs(rid, names))
                next_send += period
                if next_send < now:
                    next_send = now + period


def main(argv=None) -> int:
    """Run an emulator from the command line (e.g. to point ur-rtde examples at it)."""
    import argparse

    parser = argparse.ArgumentParser(description="Loopback UR controller emulator for ur-rtde")
    parser.add_argument("--host", default=None, help="address in 127.0.0.0/8 (default: a free random one)")
    parser.add_argument("--drop-after-moves", type=int, default=None)
    parser.add_argument("--silent", action="store_true", help="accept connections, never answer")
    parser.add_argument("--seconds", type=float, default=3600.0, help="run this long, then exit")
    args = parser.parse_args(argv)
    emulator = URControllerEmulator(host=args.host, drop_after_moves=args.drop_after_moves, silent=args.silent)
    with emulator:
        print(emulator.host, flush=True)
        end = time.monotonic() + args.seconds
        while time.monotonic() < end and not emulator.dropped.is_set():
            time.sleep(0.1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
