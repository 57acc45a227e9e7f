"""The arm interface without ROS: settings, make_arm, snapshots, and the ArmRunner's threads."""

import threading
import time

import numpy as np
import pytest

from robot_ct_ros.hardware.arm import Arm, ArmConnectionError, ArmMotionError, ArmRunner, ArmSettings, ArmSnapshot
from robot_ct_ros.hardware.arms import make_arm
from robot_ct_ros.hardware.simulated_arm import HOME_Q, SimulatedArm, SimulatedArmSettings, forward_kinematics
from robot_ct_ros.hardware.ur_arm import URArm
from robot_ct_ros.parameters import from_ros_values, ros_defaults
from robot_ct_ros.testing import wait_until


def _wait(predicate):
    return wait_until(predicate, timeout_s=5.0)


def test_settings_defaults_and_refusals():
    assert ros_defaults(ArmSettings) == {
        "robot_ip": "", "connect_timeout_s": 10.0, "call_timeout_s": 2.0, "move_timeout_s": 60.0, "speed": 0.25,
        "acceleration": 1.2, "position_tolerance_m": 1e-4, "orientation_tolerance_rad": 1e-3,
        "max_state_age_s": 0.25}
    assert ros_defaults(SimulatedArmSettings) == {"sigma_mm": 0.0, "sigma_deg": 0.0, "drift_mm_per_move": 0.0,
                                                  "seed": 0, "motion_time_scale": 0.0, "fail_after_moves": -1}
    with pytest.raises(ValueError, match="speed must be >= 0"):
        ArmSettings(speed=-0.1)
    with pytest.raises(ValueError, match="connect_timeout_s must be a number"):
        ArmSettings(connect_timeout_s="soon")
    # -1 on ROS is "never"; a count is kept as given
    assert from_ros_values(SimulatedArmSettings, {"fail_after_moves": -1}).fail_after_moves is None
    assert from_ros_values(SimulatedArmSettings, {"fail_after_moves": 3}).fail_after_moves == 3
    with pytest.raises(ValueError, match="sigma_mm"):
        SimulatedArmSettings(sigma_mm=-1.0)


def test_make_arm_by_address():
    arm = make_arm(ArmSettings(), SimulatedArmSettings(sigma_mm=0.3, seed=4, fail_after_moves=2))
    assert isinstance(arm, SimulatedArm) and isinstance(arm, Arm)
    assert arm.errors.sigma_mm == 0.3 and arm.errors.seed == 4 and arm.fail_after_moves == 2
    ur = make_arm(ArmSettings(robot_ip="192.0.2.1", connect_timeout_s=3.0, move_timeout_s=7.0))
    assert isinstance(ur, URArm) and isinstance(ur, Arm) and not ur.is_connected
    assert (ur.host, ur.connect_timeout_s, ur.move_timeout_s) == ("192.0.2.1", 3.0, 7.0)


def test_simulated_snapshot_carries_the_true_pose():
    arm = SimulatedArm.from_settings(SimulatedArmSettings(sigma_mm=0.5, seed=1))
    arm.connect()
    goal = forward_kinematics(HOME_Q) + np.array([0.01, 0.0, -0.01, 0, 0, 0])
    arm.move_linear(goal)
    snap = arm.snapshot()
    np.testing.assert_allclose(snap.tcp_pose, goal)
    np.testing.assert_allclose(snap.true_tcp_pose, arm.true_tcp_pose())
    assert 0.0 < np.linalg.norm(snap.true_tcp_pose[:3] - goal[:3]) < 5e-3
    assert snap.joint_positions.shape == (6,)
    arm.disconnect()
    with pytest.raises(ArmConnectionError):
        arm.snapshot()


def test_runner_moves_and_reports_in_position():
    arm = SimulatedArm()
    arm.connect()
    runner = ArmRunner(ArmSettings(), rate_hz=200.0)
    runner.start(arm)
    try:
        assert _wait(lambda: runner.latest() is not None)
        assert not runner.in_position()  # nothing commanded
        goal = runner.latest().tcp_pose + np.array([0.02, 0.0, 0.01, 0, 0, 0])
        runner.command(goal)
        assert not runner.in_position()  # moving
        assert _wait(runner.in_position)
        assert runner.moves_completed == 1
        np.testing.assert_allclose(runner.latest().tcp_pose, goal)
    finally:
        assert runner.stop()
    assert not runner.in_position() and not runner.stop()
    np.testing.assert_allclose(runner.target, goal)  # kept for diagnostics


class _FlakyArm:
    """An arm whose state reads fail after ``reads`` successes, and whose moves fail as told."""

    def __init__(self, reads=3, move_error=None):
        self.reads, self.move_error, self.is_connected = reads, move_error, True
        self.pose = forward_kinematics(HOME_Q)

    def snapshot(self):
        if self.reads <= 0:
            raise ArmConnectionError("controller gone")
        self.reads -= 1
        return ArmSnapshot(self.pose.copy(), np.zeros(6))

    def move_linear(self, pose, speed=0.25, accel=1.2, timeout_s=None):
        if self.move_error is not None:
            raise self.move_error
        self.pose = np.asarray(pose, float)


def test_runner_records_a_lost_connection_and_move_failures():
    failures = []
    runner = ArmRunner(ArmSettings(), rate_hz=100.0, on_move_failed=failures.append)
    runner.start(_FlakyArm(reads=3, move_error=ArmMotionError("protective stop")))
    try:
        assert _wait(lambda: runner.latest() is not None)
        runner.command(runner.latest().tcp_pose)
        assert _wait(lambda: failures)
        assert failures == ["move failed: protective stop"] and runner.moves_completed == 0
        assert _wait(lambda: runner.lost_reason == "controller gone")
        assert not runner.in_position()
    finally:
        runner.stop()
    # a failure of an arm the runner has let go of is not recorded
    late = ArmRunner(ArmSettings(), rate_hz=100.0)
    late._connection_lost("too late", object())
    assert late.lost_reason is None


def test_runner_newest_goal_wins():
    gate = threading.Event()

    class SlowArm(_FlakyArm):
        def move_linear(self, pose, speed=0.25, accel=1.2, timeout_s=None):
            gate.wait(2.0)
            super().move_linear(pose)

    arm = SlowArm(reads=10 ** 6)
    runner = ArmRunner(ArmSettings(), rate_hz=200.0)
    runner.start(arm)
    try:
        assert _wait(lambda: runner.latest() is not None)
        first, second = arm.pose + [0.01, 0, 0, 0, 0, 0], arm.pose + [0.02, 0, 0, 0, 0, 0]
        runner.command(first)
        time.sleep(0.05)  # the first move is under way
        runner.command(second)
        gate.set()
        assert _wait(runner.in_position)
        np.testing.assert_allclose(arm.pose, second)
    finally:
        runner.stop()


class _RunnerState:
    """What arm_health reads of an ArmRunner, set by hand."""

    def __init__(self, active=True, snapshot=True, stale=False, age_s=0.01, in_position=False, target=None):
        self.active, self.settings, self.moves_completed = active, ArmSettings(max_state_age_s=0.25), 2
        self._snap = ArmSnapshot(np.zeros(6), np.zeros(6)) if snapshot else None
        self._stale, self._age, self._in_position, self.target = stale, age_s, in_position, target

    def latest(self):
        return self._snap

    def stale(self):
        return self._stale

    def state_age_s(self):
        return self._age

    def in_position(self):
        return self._in_position


def _health(runner, state="active", error="", *, arm=None, connecting_s=None, goal_problem=""):
    from robot_ct_ros.hardware.arm import arm_health

    return arm_health(runner, arm, state, error, connecting_s=connecting_s, where="10.0.0.9", goal_problem=goal_problem,
                      goals_refused=3, base_frame="world", tool_frame="source_arm_tool0")


def test_arm_health_levels_and_messages():
    connected = _FlakyArm()
    level, message, values = _health(_RunnerState(in_position=True, target=np.arange(6) / 3), arm=connected)
    assert (level, message) == ("ok", "active, in position")
    assert dict(values) == {"lifecycle_state": "active", "connection": "connected", "connected": True,
                            "in_position": True, "moves_completed": 2, "state_age_s": "0.010", "goals_refused": 3,
                            "target_pose": [0.0, 0.333333, 0.666667, 1.0, 1.333333, 1.666667],
                            "base_frame": "world", "tool_frame": "source_arm_tool0"}
    assert _health(_RunnerState(), arm=connected)[:2] == ("ok", "active")
    assert _health(_RunnerState(), goal_problem="frame 'map'")[:2] == ("warn", "active; last goal refused: frame 'map'")
    # errors first, whatever else holds; a goal problem does not change a non-OK message
    for error in ("connection lost: gone", "configure failed: x", "connect failed: y", "fault: z"):
        assert _health(_RunnerState(stale=True), error=error, connecting_s=1.0, goal_problem="p")[:2] == ("error", error)
    level, message, values = _health(_RunnerState(snapshot=False), "inactive", connecting_s=2.345, goal_problem="p")
    assert (level, message) == ("warn", "connecting to 10.0.0.9 (2.3 s)")
    assert dict(values)["connection"] == "connecting" and dict(values)["state_age_s"] is None
    assert dict(values)["target_pose"] is None
    assert _health(_RunnerState(stale=True, age_s=0.5))[:2] == (
        "warn", "state stale: no new sample from the controller for 0.50 s (limit 0.25 s)")
    assert _health(_RunnerState(active=False, stale=True), "inactive")[:2] == ("warn", "inactive")
    assert _health(_RunnerState(), "active", "move failed: protective stop")[:2] == (
        "warn", "move failed: protective stop")
    assert dict(_health(_RunnerState())[2])["connection"] == "disconnected"
    connected.is_connected = False
    assert dict(_health(_RunnerState(), arm=connected)[2])["connected"] is False


def test_runner_hands_out_each_fresh_sample_once():
    class ClockedArm(_FlakyArm):
        """A controller clock that follows the host's until frozen (a hung controller answering its last state)."""
        frozen = None

        def snapshot(self):
            t = time.monotonic() if self.frozen is None else self.frozen
            return ArmSnapshot(self.pose.copy(), np.zeros(6), timestamp_s=t)

    arm = ClockedArm(reads=10 ** 9)
    runner = ArmRunner(ArmSettings(max_state_age_s=0.5), rate_hz=200.0)
    assert runner.new_sample() is None
    for _ in range(2):  # a restart hands out samples afresh
        arm.frozen = None
        runner.start(arm)
        try:
            assert _wait(lambda: runner.samples >= 2)
            n = runner.samples
            arm.frozen = time.monotonic()
            assert _wait(lambda: runner.samples > n)  # the frozen sample, seen once
            first = runner.new_sample()
            assert first is not None and first.timestamp_s == arm.frozen
            time.sleep(0.05)
            assert runner.new_sample() is None  # nothing new: not handed out again
            time.sleep(0.6)
            n = runner.samples
            arm.frozen += 0.001  # a new sample, but measured long ago: stale, never handed out
            assert _wait(lambda: runner.samples > n) and runner.stale()
            assert runner.new_sample() is None
            arm.frozen = None
            assert _wait(lambda: not runner.stale())
            assert runner.new_sample() is not None
        finally:
            runner.stop()


def test_an_arm_that_stops_holding_its_pose_is_never_in_position_and_is_an_error():
    """A protective stop or power-off (the snapshot's fault) once left in_position true, and the beam allowed."""
    arm = SimulatedArm()
    arm.connect()
    runner = ArmRunner(ArmSettings(), rate_hz=200.0)
    runner.start(arm)
    try:
        assert _wait(lambda: runner.latest() is not None)
        runner.command(runner.latest().tcp_pose + np.array([0.0, 0.0, 0.01, 0, 0, 0]))
        assert _wait(runner.in_position)
        arm.fault = "safety_mode PROTECTIVE_STOP (3)"
        assert _wait(lambda: not runner.in_position())
        level, message, values = _health(runner, arm=arm)
        assert (level, message) == ("error", "robot not ready: safety_mode PROTECTIVE_STOP (3)")
        assert dict(values)["in_position"] is False
        arm.fault = ""
        assert _wait(runner.in_position)  # the pose held: in position again once the controller runs
        assert _health(runner, arm=arm)[:2] == ("ok", "active, in position")
    finally:
        runner.stop()


def test_the_watch_notices_a_lost_connection_or_a_frozen_controller():
    """Nothing read an arm that was connected but not driven (arm_driver inactive): a lost connection went
    unnoticed until activate, which then succeeded on a dead arm."""
    from robot_ct_ros.hardware.arm import ArmWatch

    flaky = _FlakyArm(reads=3)
    watch = ArmWatch(ArmSettings(), period_s=0.01)
    watch.start(flaky)
    assert _wait(lambda: watch.lost_reason is not None) and watch.lost_reason == "controller gone"
    watch.stop()

    class Frozen(_FlakyArm):  # answers, but its clock stands still
        def snapshot(self):
            return ArmSnapshot(self.pose.copy(), np.zeros(6), timestamp_s=5.0)

    watch = ArmWatch(ArmSettings(call_timeout_s=0.05, max_state_age_s=0.05), period_s=0.01)
    watch.start(Frozen())
    assert _wait(lambda: watch.lost_reason is not None) and "stopped updating" in watch.lost_reason
    watch.stop()

    arm = SimulatedArm()
    arm.connect()
    watch.start(arm)  # no clock: never stale; connected: nothing to report
    time.sleep(0.2)
    assert watch.lost_reason is None and watch.active
    watch.stop()
    assert not watch.active
