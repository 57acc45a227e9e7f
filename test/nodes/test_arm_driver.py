"""arm_driver in-process: lifecycle, goals, in_position, diagnostics, faults; simulated and over ur-rtde."""

import importlib.util
import sys
from pathlib import Path

import time

import numpy as np
from rclpy.parameter import Parameter
from rclpy.time import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from robot_ct_ros.nodes.arm_driver import ArmDriverNode, pose_msg_to_ur, ur_to_pose_msg


def load_emulator():
    name = "ur_controller_emulator"
    if name not in sys.modules:
        path = Path(__file__).resolve().parents[1] / "hardware" / f"{name}.py"
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


class Probe:
    """Subscribes to everything the driver publishes for one role and can send goals."""

    def __init__(self, ros, role="source"):
        self.node = ros.node(f"probe_{role}")
        ns = f"{role}_arm"
        self.in_position, self.poses, self.true_poses, self.joints, self.diag = [], [], [], [], []
        self.subs = [
            self.node.create_subscription(Bool, f"{ns}/in_position", lambda m: self.in_position.append(m.data), 10),
            self.node.create_subscription(PoseStamped, f"{ns}/tool_pose", self.poses.append, 10),
            self.node.create_subscription(PoseStamped, f"{ns}/true_tool_pose", self.true_poses.append, 10),
            self.node.create_subscription(JointState, f"{ns}/joint_states", self.joints.append, 10),
            self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10),
        ]
        self.goal_pub = self.node.create_publisher(PoseStamped, f"{ns}/goal_pose", 10)

    def send_goal(self, ros, pose, frame="world"):
        assert ros.wait_for_subscribers(self.goal_pub)
        self.in_position.clear()
        msg = ur_to_pose_msg(pose, frame, self.node.get_clock().now().to_msg())
        self.goal_pub.publish(msg)

    def last_level(self, role="source"):
        levels = [s.level for a in self.diag for s in a.status if s.name.endswith(f"{role} arm")]
        return levels[-1] if levels else None


def _driver(ros, **params):
    overrides = [Parameter(k, value=v) for k, v in params.items()]
    return ros.add(ArmDriverNode(context=ros.context, parameter_overrides=overrides))


def _at(msg: PoseStamped, pose, tol=1e-6) -> bool:
    return np.allclose(pose_msg_to_ur(msg), pose, atol=tol)


def test_lifecycle_services_goal_and_in_position(ros):
    node = _driver(ros, role="source", autostart=False)
    probe = Probe(ros)
    change = probe.node.create_client(ChangeState, "/arm_driver/change_state")
    get = probe.node.create_client(GetState, "/arm_driver/get_state")
    assert ros.call(get, GetState.Request()).current_state.label == "unconfigured"
    ok = ros.call(change, ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CONFIGURE)))
    assert ok.success and node.lifecycle_state == "inactive"
    assert ros.spin_until(lambda: node.arm is not None)  # connected off the executor
    assert ros.call(change, ChangeState.Request(transition=Transition(id=Transition.TRANSITION_ACTIVATE))).success
    assert ros.call(get, GetState.Request()).current_state.label == "active"

    assert ros.spin_until(lambda: probe.poses and probe.joints and probe.in_position)
    assert probe.in_position[-1] is False  # nothing commanded yet
    assert probe.poses[-1].header.frame_id == "world"
    assert probe.joints[-1].name[0] == "source_arm_shoulder_pan_joint"
    goal = pose_msg_to_ur(probe.poses[-1]) + np.array([0.02, 0.01, -0.03, 0, 0, 0])
    probe.send_goal(ros, goal)
    assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1] and _at(probe.poses[-1], goal))
    assert probe.in_position[0] is False  # false while moving
    assert ros.spin_until(lambda: probe.true_poses and _at(probe.true_poses[-1], goal))  # no errors configured
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.OK)
    # the two simulated arms are told apart by hardware_id too (both were "simulated_arm")
    assert {s.hardware_id for a in probe.diag for s in a.status if s.name.endswith("source arm")} == {
        "simulated_source_arm"}

    probe.send_goal(ros, goal, frame="some_other_frame")  # wrong frame: ignored, stays in position
    ros.spin_for(0.3)
    assert node.in_position()

    assert ros.call(change, ChangeState.Request(transition=Transition(id=Transition.TRANSITION_DEACTIVATE))).success
    assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1] is False)
    assert ros.call(change, ChangeState.Request(transition=Transition(id=Transition.TRANSITION_CLEANUP))).success
    assert node.arm is None and node.lifecycle_state == "unconfigured"


def test_autostart_with_simulated_errors(ros):
    node = _driver(ros, role="detector", sim_sigma_mm=0.5, sim_sigma_deg=0.05, sim_seed=3)
    probe = Probe(ros, "detector")
    assert ros.spin_until(lambda: node.lifecycle_state == "active" and probe.poses)
    goal = pose_msg_to_ur(probe.poses[-1]) + np.array([-0.02, 0.0, 0.01, 0, 0, 0])
    probe.send_goal(ros, goal)
    assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1] and _at(probe.poses[-1], goal))
    # the measured pose is the commanded one; the true pose carries the coordination error
    def true_error_mm():
        return np.linalg.norm(pose_msg_to_ur(probe.true_poses[-1])[:3] - goal[:3]) * 1e3 if probe.true_poses else -1
    assert ros.spin_until(lambda: 0.01 < true_error_mm() < 5.0)
    np.testing.assert_allclose(node.arm.true_tcp_pose(), pose_msg_to_ur(probe.true_poses[-1]), atol=1e-9)


def test_connection_loss_goes_safe(ros):
    node = _driver(ros, role="source", sim_fail_after_moves=1)
    probe = Probe(ros)
    assert ros.spin_until(lambda: node.lifecycle_state == "active" and probe.poses)
    start = pose_msg_to_ur(probe.poses[-1])
    probe.send_goal(ros, start + np.array([0.01, 0, 0, 0, 0, 0]))
    assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1])
    probe.send_goal(ros, start + np.array([0.02, 0, 0, 0, 0, 0]))
    assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured")
    assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1] is False)
    assert "connection lost" in node.last_error
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.ERROR)
    # configure again reconnects (a fresh simulated arm)
    assert node.trigger_configure().name == "SUCCESS" and node.trigger_activate().name == "SUCCESS"
    assert ros.spin_until(lambda: node.arm is not None and node.runner.active)
    assert node.arm.is_connected and node.last_error == ""


def test_a_failed_connection_returns_to_unconfigured_with_an_error(ros):
    host = load_emulator().free_loopback_host()
    node = _driver(ros, role="source", robot_ip=host, autostart=False, connect_timeout_s=10.0)
    probe = Probe(ros)
    assert node.trigger_configure().name == "SUCCESS"  # the connection is made off the executor
    assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured", timeout_s=20)
    assert node.arm is None and host in node.last_error and "connect failed" in node.last_error
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.ERROR)


def test_end_to_end_over_ur_rtde_with_controller_loss(ros):
    emu = load_emulator().URControllerEmulator(drop_after_moves=1).start()
    try:
        node = _driver(ros, role="detector", robot_ip=emu.host, autostart=False, connect_timeout_s=15.0,
                       move_timeout_s=20.0, publish_rate_hz=20.0)
        probe = Probe(ros, "detector")
        assert node.trigger_configure().name == "SUCCESS", node.last_error
        assert node.trigger_activate().name == "SUCCESS"
        assert ros.spin_until(lambda: node.arm is not None, timeout_s=30), node.last_error
        assert emu.script_running
        assert ros.spin_until(lambda: probe.poses and probe.joints)
        np.testing.assert_allclose(pose_msg_to_ur(probe.poses[-1]), emu.tcp_pose, atol=1e-9)
        goal = pose_msg_to_ur(probe.poses[-1]) + np.array([0.0, 0.02, -0.02, 0, 0, 0])
        probe.send_goal(ros, goal)
        assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1] and _at(probe.poses[-1], goal),
                              timeout_s=30)
        np.testing.assert_allclose(emu.tcp_pose, goal, atol=1e-9)
        assert ros.spin_until(lambda: np.allclose(probe.joints[-1].position, emu.q, atol=1e-9))

        probe.send_goal(ros, goal + np.array([0.01, 0, 0, 0, 0, 0]))  # the controller vanishes here
        assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured", timeout_s=40)
        assert emu.dropped.is_set()
        assert probe.in_position and probe.in_position[-1] is False
        assert emu.host in node.last_error
        assert ros.spin_until(lambda: probe.last_level("detector") == DiagnosticStatus.ERROR)
    finally:
        emu.stop()


def test_bad_parameters_are_refused_with_a_clear_error(ros):
    """A wrong value is a one-line ValueError naming the parameter, before anything starts."""
    import pytest

    for params, words in (({"role": "elbow"}, ("parameter role", "source, detector")),
                          ({"speed": "fast"}, ("parameter speed", "DOUBLE")),
                          ({"sim_sigma_mm": -0.5}, ("parameter sim_sigma_mm",)),
                          ({"sim_fail_after_moves": -3}, ("parameter sim_fail_after_moves", ">= 0"))):
        with pytest.raises(ValueError) as err:
            ArmDriverNode(context=ros.context, parameter_overrides=[Parameter(k, value=v) for k, v in params.items()])
        message = str(err.value)
        assert "\n" not in message and all(w in message for w in words), message


def test_executable_refuses_a_bad_parameter_without_a_traceback(monkeypatch):
    """``ros2 run robot_ct_ros arm_driver --ros-args -p speed:=fast`` says why in one line and exits 2."""
    import os
    import subprocess

    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", ROS_DOMAIN_ID=str(150 + os.getpid() % 50),
               PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    proc = subprocess.run([sys.executable, "-m", "robot_ct_ros.nodes.arm_driver", "--ros-args", "-p", "speed:=fast",
                           "-p", "autostart:=false"], capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr and "parameter speed" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr


def _message(probe, role="source"):
    msgs = [s.message for a in probe.diag for s in a.status if s.name.endswith(f"{role} arm")]
    return msgs[-1] if msgs else ""


def _pose_msg(pose, frame="world"):
    return ur_to_pose_msg(pose, frame, Time().to_msg())


def test_bad_goals_are_refused_at_the_boundary_and_the_arm_keeps_working(ros):
    """A NaN goal used to kill the move thread silently: every later goal was ignored."""
    node = _driver(ros, role="source")
    probe = Probe(ros)
    assert ros.spin_until(lambda: node.lifecycle_state == "active" and probe.poses)
    assert ros.wait_for_subscribers(probe.goal_pub)
    start = pose_msg_to_ur(probe.poses[-1])
    bad = []
    for field, value in (("x", float("nan")), ("y", float("inf"))):
        m = _pose_msg(start)
        setattr(m.pose.position, field, value)
        bad.append(m)
    m = _pose_msg(start)
    o = m.pose.orientation
    o.x, o.y, o.z, o.w = 2 * o.x, 2 * o.y, 2 * o.z, 2 * o.w  # a quaternion scaled by 2
    bad.append(m)
    m = _pose_msg(start)
    m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w = 0.0, 0.0, 0.0, 0.0
    bad.append(m)
    m = _pose_msg(start)
    m.pose.orientation.w = float("nan")
    bad.append(m)
    bad.append(_pose_msg(start + np.array([0.01, 0, 0, 0, 0, 0]), frame="tool0"))
    for m in bad:
        probe.goal_pub.publish(m)
    ros.spin_until(lambda: getattr(node, "goal_rejections", 0) == len(bad), timeout_s=2.0)
    goal = start + np.array([0.0, 0.02, 0.0, 0, 0, 0])
    probe.send_goal(ros, goal)
    assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1] and _at(probe.poses[-1], goal))
    assert node.goal_rejections == len(bad) and node.runner.failure is None and node.lifecycle_state == "active"
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.WARN and "goal refused" in _message(probe),
                          timeout_s=5)


class _BuggyArm:
    """A simulated arm whose move raises what no arm should: a bug in a driver."""

    def __init__(self):
        from robot_ct_ros.hardware.simulated_arm import SimulatedArm

        self._arm = SimulatedArm()

    def __getattr__(self, name):
        return getattr(self._arm, name)

    def move_linear(self, pose, speed=0.25, accel=1.2, timeout_s=None):
        raise ZeroDivisionError("a driver bug")


def test_a_dying_worker_thread_is_an_error_and_an_error_transition(ros):
    node = ros.add(ArmDriverNode(context=ros.context, arm_factory=_BuggyArm))
    probe = Probe(ros)
    assert ros.spin_until(lambda: node.lifecycle_state == "active" and probe.poses)
    probe.send_goal(ros, pose_msg_to_ur(probe.poses[-1]))
    assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured")
    assert "arm_move thread died: ZeroDivisionError" in node.last_error and node.arm is None
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.ERROR and "thread died" in _message(probe))
    assert probe.in_position[-1] is False
    # configure again: a fresh arm and threads
    assert node.trigger_configure().name == "SUCCESS"
    assert ros.spin_until(lambda: node.arm is not None)


def test_connecting_to_a_silent_controller_never_blocks_the_executor(ros):
    """A controller that accepts TCP and never answers: lifecycle services and diagnostics keep answering."""
    emu = load_emulator().URControllerEmulator(silent=True).start()
    try:
        node = _driver(ros, role="source", robot_ip=emu.host, connect_timeout_s=8.0)  # autostart
        probe = Probe(ros)
        get = probe.node.create_client(GetState, "/arm_driver/get_state")
        assert ros.wait_for_service(get)
        t0 = time.monotonic()
        # answered long before the 8 s the connection attempt may take (a blocked executor answers after it)
        assert ros.call(get, GetState.Request(), timeout_s=4.0).current_state.label in ("inactive", "active")
        assert time.monotonic() - t0 < 4.0
        assert ros.spin_until(lambda: "connecting" in _message(probe), timeout_s=5.0)
        assert probe.last_level() == DiagnosticStatus.WARN and node.connecting
        assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured", timeout_s=20)
        assert emu.host in node.last_error and not node.connecting
        assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.ERROR)
    finally:
        emu.stop()


def test_a_frozen_controller_is_noticed_and_its_last_pose_is_not_republished(ros):
    emu = load_emulator().URControllerEmulator().start()
    try:
        node = _driver(ros, role="detector", robot_ip=emu.host, connect_timeout_s=15.0, call_timeout_s=2.0,
                       max_state_age_s=0.2, publish_rate_hz=50.0)
        probe = Probe(ros, "detector")
        assert ros.spin_until(lambda: len(probe.poses) > 5, timeout_s=30)
        goal = pose_msg_to_ur(probe.poses[-1])
        probe.send_goal(ros, goal)
        assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1], timeout_s=20)
        # stamps are the controller's measurement times: they advance, and never run ahead of the clock
        stamps = [Time.from_msg(m.header.stamp).nanoseconds for m in probe.poses[-5:]]
        assert all(b > a for a, b in zip(stamps, stamps[1:]))
        assert stamps[-1] <= node.get_clock().now().nanoseconds
        emu.freeze()
        frozen_at = node.get_clock().now().nanoseconds
        n_before = len(probe.poses)
        # noticed well before the connection is called lost (call_timeout_s 2 s; ur-rtde alone: 2.5 s)
        assert ros.spin_until(lambda: probe.in_position[-1] is False and node.runner.stale(), timeout_s=1.8)
        assert ros.spin_until(lambda: any(w in _message(probe, "detector") for w in ("stale", "stopped updating")),
                              timeout_s=5.0)
        # the last sample is not republished as fresh: whatever arrived after the freeze was measured before it
        assert all(Time.from_msg(m.header.stamp).nanoseconds <= frozen_at + 50_000_000 for m in probe.poses[n_before:])
        if node.lifecycle_state == "active":  # still within call_timeout_s: nothing new is published
            n = len(probe.poses)
            ros.spin_for(0.3)
            assert len(probe.poses) == n or node.lifecycle_state != "active"
        assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured", timeout_s=10)
        assert "stopped updating" in node.last_error
    finally:
        emu.stop()


def test_a_publish_rate_that_would_look_silent_is_refused(ros):
    """0 Hz was accepted and published once every 10 s, so source_control and the orchestrator (1 s) took
    the arm for lost without a word."""
    import pytest
    from rclpy.parameter import Parameter

    from robot_ct_ros.nodes.arm_driver import ArmDriverNode

    for rate in (0.0, 1.0):
        with pytest.raises(ValueError) as err:
            ArmDriverNode(context=ros.context, parameter_overrides=[Parameter("publish_rate_hz", value=rate)])
        assert "publish_rate_hz" in str(err.value) and "\n" not in str(err.value)


def _in_position(ros):
    """An active simulated source arm that reached a goal 1 cm away: (node, probe)."""
    node = _driver(ros, role="source")
    probe = Probe(ros)
    assert ros.spin_until(lambda: node.lifecycle_state == "active" and probe.poses)
    goal = pose_msg_to_ur(probe.poses[-1]) + np.array([0.01, 0, 0, 0, 0, 0])
    probe.send_goal(ros, goal)
    assert ros.spin_until(lambda: probe.in_position and probe.in_position[-1])
    return node, probe


def test_a_protective_stop_clears_in_position_and_is_an_error(ros):
    """The robot's mode (protective stop, power off) once left in_position true and /diagnostics OK."""
    node, probe = _in_position(ros)
    node.arm.fault = "safety_mode PROTECTIVE_STOP (3)"
    assert ros.spin_until(lambda: probe.in_position[-1] is False)
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.ERROR)
    messages = [s.message for a in probe.diag for s in a.status if s.name.endswith("source arm")]
    assert messages[-1] == "robot not ready: safety_mode PROTECTIVE_STOP (3)"
    node.arm.fault = ""
    assert ros.spin_until(lambda: probe.in_position[-1] is True and probe.last_level() == DiagnosticStatus.OK)


def test_a_connection_lost_while_inactive_is_noticed_and_activate_is_refused(ros):
    """Nothing read the arm while the node was configured but inactive: a lost connection went unnoticed and
    activate then succeeded on a dead arm."""
    node = _driver(ros, role="source", autostart=False)
    probe = Probe(ros)
    assert node.trigger_configure().name == "SUCCESS"
    assert ros.spin_until(lambda: node.arm is not None)
    ros.spin_for(1.2)  # the watch reads a healthy arm: nothing happens
    assert node.lifecycle_state == "inactive" and node.last_error == ""
    node.arm.disconnect()  # the connection drops under the inactive node
    assert node.trigger_activate().name == "FAILURE" and node.lifecycle_state == "inactive"
    assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured")
    assert node.last_error.startswith("connection lost") and node.arm is None
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.ERROR)

    # the watch alone (no activate) notices it too; deactivate hands the arm back to the watch
    assert node.trigger_configure().name == "SUCCESS"
    assert ros.spin_until(lambda: node.arm is not None)
    assert node.trigger_activate().name == "SUCCESS" and not node.watch.active
    assert node.trigger_deactivate().name == "SUCCESS" and node.watch.active
    node.arm.disconnect()
    assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured")
    assert "simulated arm not connected" in node.last_error or "disconnected" in node.last_error, node.last_error


def test_a_protective_stop_shorter_than_the_diagnostics_period_is_an_error_at_once(ros):
    """/diagnostics came only from the 1 Hz timer: a protective stop of a few tenths of a second never showed as an
    ERROR (the orchestrator aborts on it) and the scan went on. Now its start and its end are published at once."""
    node, probe = _in_position(ros)
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.OK)
    n = len(probe.in_position)
    node.arm.fault = "safety_mode PROTECTIVE_STOP (3)"
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.ERROR, timeout_s=0.5)
    assert False in probe.in_position[n:]  # in_position false went out with it
    node.arm.fault = ""
    assert ros.spin_until(lambda: probe.last_level() == DiagnosticStatus.OK, timeout_s=0.5)
    assert probe.in_position[-1] is True
