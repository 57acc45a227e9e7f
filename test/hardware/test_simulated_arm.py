"""Simulated arm: measured = commanded, true pose = commanded + seeded random error + drift."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from robot_ct_ros.hardware.simulated_arm import (HOME_Q, SimulatedArm, SimulatedArmErrors, forward_kinematics,
                                                 inverse_kinematics)
from robot_ct_ros.hardware.ur_arm import Arm, ArmConnectionError, ArmMotionError


def _targets(n, seed=1):
    rng = np.random.default_rng(seed)
    base = forward_kinematics(HOME_Q)
    out = []
    for _ in range(n):
        p = base.copy()
        p[:3] += rng.uniform(-0.05, 0.05, size=3)
        out.append(p)
    return out


def _errors(arm, targets):
    dpos, drot = [], []
    for t in targets:
        arm.move_linear(t)
        true = arm.true_tcp_pose()
        np.testing.assert_allclose(arm.get_tcp_pose(), t)  # measured = commanded
        dpos.append((true[:3] - t[:3]) * 1e3)
        drot.append(np.rad2deg((Rotation.from_rotvec(true[3:]) * Rotation.from_rotvec(t[3:]).inv()).as_rotvec()))
    return np.array(dpos), np.array(drot)


def test_is_an_arm_and_kinematics_round_trip():
    arm = SimulatedArm()
    assert isinstance(arm, Arm)
    target = forward_kinematics(HOME_Q) + np.array([0.03, -0.02, -0.05, 0, 0, 0])
    q, ok = inverse_kinematics(target, HOME_Q)
    assert ok
    np.testing.assert_allclose(forward_kinematics(q), target, atol=1e-9)


def test_random_error_statistics_respect_sigma_and_seed():
    errors = SimulatedArmErrors(sigma_mm=0.2, sigma_deg=0.05, seed=7)
    arm = SimulatedArm(errors=errors)
    arm.connect()
    targets = _targets(300)
    dpos, drot = _errors(arm, targets)
    assert np.all(np.abs(dpos.mean(axis=0)) < 0.05)
    np.testing.assert_allclose(dpos.std(axis=0), 0.2, rtol=0.2)
    np.testing.assert_allclose(drot.std(axis=0), 0.05, rtol=0.2)
    # same seed, same errors; another seed, other errors
    again = SimulatedArm(errors=SimulatedArmErrors(sigma_mm=0.2, sigma_deg=0.05, seed=7))
    again.connect()
    np.testing.assert_allclose(_errors(again, targets)[0], dpos)
    other = SimulatedArm(errors=SimulatedArmErrors(sigma_mm=0.2, sigma_deg=0.05, seed=8))
    other.connect()
    assert not np.allclose(_errors(other, targets)[0], dpos)


def test_drift_grows_linearly_along_one_direction():
    arm = SimulatedArm(errors=SimulatedArmErrors(drift_mm_per_move=0.01, drift_direction=(0, 0, 1)))
    arm.connect()
    dpos, drot = _errors(arm, _targets(50))
    np.testing.assert_allclose(dpos[:, 2], 0.01 * np.arange(1, 51), atol=1e-9)
    np.testing.assert_allclose(dpos[:, :2], 0.0, atol=1e-12)
    np.testing.assert_allclose(drot, 0.0, atol=1e-9)
    # seeded random direction: a unit vector, the same for the same seed
    a = SimulatedArm(errors=SimulatedArmErrors(drift_mm_per_move=1.0, seed=3))
    b = SimulatedArm(errors=SimulatedArmErrors(drift_mm_per_move=1.0, seed=3))
    for arm in (a, b):
        arm.connect()
        arm.move_linear(_targets(1)[0])
    d = (a.true_tcp_pose() - a.get_tcp_pose())[:3] * 1e3
    assert np.linalg.norm(d) == pytest.approx(1.0)
    np.testing.assert_allclose(b.true_tcp_pose(), a.true_tcp_pose())


def test_fault_injection_drops_connection():
    arm = SimulatedArm(fail_after_moves=2)
    arm.connect()
    targets = _targets(3)
    arm.move_linear(targets[0])
    arm.move_linear(targets[1])
    with pytest.raises(ArmConnectionError, match="connection lost"):
        arm.move_linear(targets[2])
    assert not arm.is_connected
    with pytest.raises(ArmConnectionError):
        arm.get_tcp_pose()
    np.testing.assert_allclose(arm.true_tcp_pose(), targets[1])  # it never got to the third pose


def test_motion_time_model_and_bad_commands():
    arm = SimulatedArm(motion_time_scale=1.0)
    with pytest.raises(ArmConnectionError):
        arm.move_linear(_targets(1)[0])  # not connected
    arm.connect()
    far = forward_kinematics(HOME_Q) + np.array([0.2, 0, 0, 0, 0, 0])
    with pytest.raises(ArmMotionError, match="timeout"):
        arm.move_linear(far, speed=0.01, timeout_s=1.0)
    with pytest.raises(ValueError):
        arm.move_linear([0.1, 0.2, 0.3])
    with pytest.raises(ArmMotionError):
        arm.move_linear(far, speed=0.0)
    q_before = arm.get_joint_positions()
    near = forward_kinematics(HOME_Q) + np.array([0.0, 0.0, -0.001, 0, 0, 0])
    arm.move_linear(near, speed=1.0, accel=100.0)
    np.testing.assert_allclose(forward_kinematics(arm.get_joint_positions()), near, atol=1e-9)
    assert not np.allclose(arm.get_joint_positions(), q_before)
