"""URArm: the real ur-rtde library (in the driver's child process) against the loopback emulator.

The emulator runs in this process; ur-rtde runs in URArm's child process (or a subprocess), which
is also what keeps the library's GIL-holding constructors from starving the emulator's threads.
Every blocking step is bounded: URArm's own timeouts, plus a watchdog thread per risky call.
"""

import importlib.util
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from robot_ct_ros.hardware.ur_arm import Arm, ArmConnectionError, URArm

REPO = Path(__file__).resolve().parents[2]


def load_emulator():
    name = "ur_controller_emulator"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{name}.py"))
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def bounded(fn, timeout_s: float):
    """Run fn() on a thread; fail the test (instead of hanging CI) if it has not returned in time."""
    result = {}

    def run():
        try:
            result["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            result["error"] = exc

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(timeout_s)
    assert not t.is_alive(), f"call still blocked after {timeout_s} s"
    if "error" in result:
        raise result["error"]
    return result.get("value")


@pytest.fixture
def emulator():
    emu = load_emulator().URControllerEmulator().start()
    try:
        yield emu
    finally:
        emu.stop()


def _wait_pose(arm, target, timeout_s=5.0):
    emu = load_emulator()
    emu.wait_until(lambda: np.allclose(arm.get_tcp_pose(), target, atol=1e-9), timeout_s)
    return arm.get_tcp_pose()


def test_connect_read_state_and_move(emulator):
    arm = URArm(emulator.host, connect_timeout_s=15.0, move_timeout_s=15.0)
    assert isinstance(arm, Arm)
    bounded(arm.connect, 30.0)
    try:
        assert arm.is_connected
        assert emulator.script_running  # RTDEControlInterface uploaded its control script
        np.testing.assert_allclose(arm.get_tcp_pose(), emulator.tcp_pose, atol=1e-12)
        np.testing.assert_allclose(arm.get_joint_positions(), emulator.q, atol=1e-12)
        state = arm.read_state()
        assert state["robot_mode"] == 7 and state["runtime_state"] == 2

        target = arm.get_tcp_pose() + np.array([0.02, -0.01, -0.03, 0.0, 0.0, 0.0])
        bounded(lambda: arm.move_linear(target, 0.25, 1.2), 30.0)
        np.testing.assert_allclose(_wait_pose(arm, target), target, atol=1e-9)
        assert emulator.commands[-1] == 3 and emulator.moves_completed == 1  # moveL through the script

        q = arm.get_joint_positions() + np.array([0.05, 0, 0, 0, 0, 0])
        bounded(lambda: arm.move_joints(q, 1.0, 1.4), 30.0)
        emulator.wait_for(lambda: np.allclose(arm.get_joint_positions(), q, atol=1e-9))
        np.testing.assert_allclose(arm.get_joint_positions(), q, atol=1e-9)
    finally:
        bounded(arm.disconnect, 15.0)
    assert not arm.is_connected
    assert emulator.wait_for(lambda: not emulator.script_running)  # stopScript on disconnect


def test_controller_lost_mid_scan_raises_and_does_not_hang():
    emu = load_emulator().URControllerEmulator(drop_after_moves=2).start()
    arm = URArm(emu.host, connect_timeout_s=15.0, move_timeout_s=20.0)
    try:
        bounded(arm.connect, 30.0)
        pose = arm.get_tcp_pose()
        for k in range(2):
            pose = pose + np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.0])
            bounded(lambda: arm.move_linear(pose), 30.0)
        pose = pose + np.array([0.0, 0.01, 0.0, 0.0, 0.0, 0.0])
        with pytest.raises(ArmConnectionError, match=f"controller at {emu.host}"):
            bounded(lambda: arm.move_linear(pose), 30.0)
        assert emu.dropped.is_set()
        assert not arm.is_connected
        with pytest.raises(ArmConnectionError):
            arm.get_tcp_pose()
    finally:
        bounded(arm.disconnect, 15.0)
        emu.stop()


def test_silent_controller_times_out_with_a_clear_error():
    """It accepts the TCP connection and never sends a byte: said as such, not as 'did not answer'."""
    emu = load_emulator().URControllerEmulator(silent=True).start()
    arm = URArm(emu.host, connect_timeout_s=2.0)
    try:
        with pytest.raises(ArmConnectionError, match=rf"controller at {emu.host} accepted the connection \(port "
                           rf"30004\) but did not complete the RTDE handshake within 2\.0 s") as err:
            bounded(arm.connect, 20.0)
        assert "did not answer" not in str(err.value)
        assert not arm.is_connected and arm._proc is None  # the stuck child was killed
    finally:
        emu.stop()


class _NotRtde:
    """A TCP server on the RTDE port that is no UR controller: ``garbage`` answers every connection and request
    with random bytes; ``badver`` speaks RTDE but refuses every protocol version (tester F6)."""

    def __init__(self, mode: str):
        import socket

        self.mode, self.host = mode, load_emulator().free_loopback_host()
        self.listener = socket.create_server((self.host, 30004))
        self.listener.settimeout(0.2)
        self.running, self.conns = True, []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self):
        while self.running:
            try:
                conn, _ = self.listener.accept()
            except OSError:
                continue
            self.conns.append(conn)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn):
        import os
        import struct

        try:
            if self.mode == "garbage":
                conn.sendall(os.urandom(64))
            while self.running:
                data = conn.recv(4096)
                if not data:
                    return
                if self.mode == "garbage":
                    conn.sendall(os.urandom(32))
                elif data[2:3] == bytes([86]):  # RTDE_REQUEST_PROTOCOL_VERSION: not accepted
                    conn.sendall(struct.pack(">HBB", 4, 86, 0))
        except OSError:
            pass

    def stop(self):
        self.running = False
        self.listener.close()
        for c in self.conns:
            c.close()


@pytest.mark.parametrize("mode", ["garbage", "badver"])
def test_a_controller_that_does_not_speak_rtde_is_said_to_have_accepted_the_connection(mode):
    """ur-rtde hangs on a peer that sends garbage or refuses the protocol version; the timeout said "did not
    answer", though the controller had accepted the connection (tester F6)."""
    server = _NotRtde(mode)
    arm = URArm(server.host, connect_timeout_s=3.0)
    try:
        with pytest.raises(ArmConnectionError) as err:
            bounded(arm.connect, 30.0)
        message = str(err.value)
        assert message.startswith(f"controller at {server.host} accepted the connection"), message
        assert ("did not complete the RTDE handshake within 3.0 s (a controller that does not speak RTDE, or "
                "refuses the protocol version)") in message, message
        assert "did not answer" not in message and not arm.is_connected and arm._proc is None
    finally:
        server.stop()


def test_a_controller_that_never_accepts_did_not_answer():
    """Nothing answers (the SYNs go unanswered: a listener whose accept queue is full): still 'did not answer'."""
    import socket

    host = load_emulator().free_loopback_host()
    listener = socket.create_server((host, 30004), backlog=0)
    fill = []
    try:
        for _ in range(3):  # fill the accept queue; later connection attempts hang in the TCP handshake
            c = socket.socket()
            c.setblocking(False)
            c.connect_ex((host, 30004))
            fill.append(c)
        arm = URArm(host, connect_timeout_s=2.0)
        with pytest.raises(ArmConnectionError, match=rf"^controller at {host} did not answer within 2\.0 s"):
            bounded(arm.connect, 20.0)
        assert not arm.is_connected and arm._proc is None
    finally:
        for c in fill:
            c.close()
        listener.close()


def test_nothing_listening_is_a_connection_error():
    host = load_emulator().free_loopback_host()
    arm = URArm(host, connect_timeout_s=10.0)
    with pytest.raises(ArmConnectionError, match=host) as err:
        bounded(arm.connect, 30.0)
    # no connection was made, so none was lost (it said "cannot connect ...: connection to controller at ... lost")
    assert str(err.value).startswith(f"cannot connect to controller at {host}: ") and "lost" not in str(err.value)


CLIENT = r"""
import sys, rtde_receive, dashboard_client
host = sys.argv[1]
d = dashboard_client.DashboardClient(host)
d.connect()
print("mode", d.robotmode())
print("safety", d.safetystatus())
print("remote", d.isInRemoteControl())
print("version", d.polyscopeVersion())
d.loadURP("scan.urp"); d.play()
print("state", d.programState())
d.stop()
print("state", d.programState())
d.disconnect()
try:
    rtde_receive.RTDEReceiveInterface(host, -1.0, ["actual_q", "no_such_variable"])
    print("not_found_reported False")
except RuntimeError as exc:
    print("not_found_reported", "no_such_variable" in str(exc))
"""


def test_dashboard_and_recipe_errors_through_the_real_library(emulator):
    proc = subprocess.run([sys.executable, "-c", CLIENT, emulator.host], capture_output=True, text=True,
                          timeout=60, cwd=REPO)
    out = proc.stdout
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "mode Robotmode: RUNNING" in out and "safety Safetystatus: NORMAL" in out
    assert "remote True" in out and "version 5.11.1.108318" in out
    assert "state PLAYING scan.urp" in out and "state STOPPED scan.urp" in out
    assert "not_found_reported True" in out
    assert "power on" not in emulator.dashboard_log and "load scan.urp" in emulator.dashboard_log


def test_robot_powered_off_refuses_the_control_script():
    emu = load_emulator().URControllerEmulator(powered=False).start()
    arm = URArm(emu.host, connect_timeout_s=20.0)
    try:
        with pytest.raises(ArmConnectionError, match="cannot connect.*control script"):
            bounded(arm.connect, 40.0)
        assert not arm.is_connected and not emu.script_running
    finally:
        emu.stop()


def test_mode_fault_names_the_modes_that_do_not_hold_the_arm():
    from robot_ct_ros.hardware.ur_arm import mode_fault

    assert mode_fault(7, 1) == "" and mode_fault(7, 2) == "" and mode_fault(None, None) == ""
    assert mode_fault(7, 3) == "safety_mode PROTECTIVE_STOP (3)"
    assert mode_fault(3, 1) == "robot_mode POWER_OFF (3)"
    assert mode_fault(5, 7) == "robot_mode IDLE (5), safety_mode ROBOT_EMERGENCY_STOP (7)"
    assert mode_fault(42, 99) == "robot_mode unknown (42), safety_mode unknown (99)"


def test_a_protective_stop_or_power_off_reaches_the_snapshot(emulator):
    """RTDE robot_mode / safety_mode were read on every state read and ignored: a protective stop left the arm
    "in position"."""
    arm = URArm(emulator.host, connect_timeout_s=15.0)
    bounded(arm.connect, 30.0)
    try:
        assert arm.snapshot().fault == ""
        emulator.safety_mode = 3
        assert emulator.wait_for(lambda: arm.snapshot().fault == "safety_mode PROTECTIVE_STOP (3)")
        emulator.safety_mode = 1
        emulator.powered = False
        assert emulator.wait_for(lambda: arm.snapshot().fault == "robot_mode POWER_OFF (3)")
        emulator.powered = True
        assert emulator.wait_for(lambda: arm.snapshot().fault == "")
    finally:
        bounded(arm.disconnect, 15.0)


ORPHAN = r"""
import sys, threading, time
from robot_ct_ros.hardware.ur_arm import URArm
arm = URArm(sys.argv[1], connect_timeout_s=120.0)
threading.Thread(target=arm.connect, daemon=True).start()
while arm._proc is None or arm._proc.pid is None:
    time.sleep(0.01)
print(arm._proc.pid, flush=True)
time.sleep(120)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_the_driver_process_dies_with_its_parent():
    """A parent SIGKILLed while its driver process was stuck connecting (ur-rtde holding the GIL, so the closed
    pipe went unnoticed) left the driver process behind for good, reparented to PID 1."""
    import os
    import signal
    import time

    from robot_ct_ros.testing import wait_until

    emu = load_emulator().URControllerEmulator(silent=True).start()
    parent = subprocess.Popen([sys.executable, "-c", ORPHAN, emu.host], stdout=subprocess.PIPE, text=True, cwd=REPO)
    child = None
    try:
        child = int(parent.stdout.readline())
        time.sleep(1.5)  # stuck in ur-rtde's constructor by now
        assert _alive(child)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        assert wait_until(lambda: not _alive(child), 10.0), "driver process outlived its parent"
    finally:
        parent.kill()
        if child is not None and _alive(child):
            os.kill(child, signal.SIGKILL)
        emu.stop()


def test_a_driver_started_from_a_short_lived_thread_outlives_that_thread(emulator):
    """The parent-death signal follows the thread that started the driver process: URArm starts it from a
    thread of its own, since arm_driver connects on a thread that ends once connected."""
    import time

    arm = URArm(emulator.host, connect_timeout_s=15.0)
    t = threading.Thread(target=arm.connect)
    t.start()
    t.join(30.0)
    try:
        time.sleep(0.5)
        assert arm.is_connected and arm.read_state()["connected"]
    finally:
        bounded(arm.disconnect, 15.0)
