"""Hand-eye transforms: tool poses <-> cone-beam geometry, both ways."""

import math

import numpy as np
import pytest

from robot_ct_ros.ct.geometry import ConeGeometry
from robot_ct_ros.ct.hand_eye import (HandEye, Mount, device_frames, device_position_sigma_mm,
                                      geometry_from_tool_poses, invert, matrix_to_position_rotvec, mount_from_si, pose_matrix,
                                      tool_goals_from_geometry)
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan


def _scan(n=12):
    return robotic_roi_scan(SeedSystem(), roi_center_mm=(400.0, 20.0, 300.0), fov_diameter_mm=30.0, n_views=n,
                            axis=(0.2, 0.1, 1.0))


def _hand_eye():
    return HandEye(Mount((3.0, -2.0, 118.0), (math.pi, 0.02, -0.01)), Mount.from_rpy((1.0, 4.0, 81.0), (0.01, -0.02, 0.3)))


def test_pose_matrix_roundtrip_and_invert():
    rng = np.random.default_rng(0)
    p, r = rng.normal(size=(5, 3)) * 100, rng.normal(size=(5, 3))
    T = pose_matrix(p, r)
    p2, r2 = matrix_to_position_rotvec(T)
    np.testing.assert_allclose(pose_matrix(p2, r2), T, atol=1e-12)
    np.testing.assert_allclose(T @ invert(T), np.tile(np.eye(4), (5, 1, 1)), atol=1e-12)
    assert pose_matrix(p[0], r[0]).shape == (4, 4)


def test_geometry_tool_goal_roundtrip():
    geom, he = _scan(), _hand_eye()
    src_tcp, det_tcp = tool_goals_from_geometry(geom, he)
    assert src_tcp.shape == det_tcp.shape == (geom.n_views, 4, 4)
    back = geometry_from_tool_poses(src_tcp, det_tcp, he, geom.n_rows, geom.n_cols, geom.row_pitch_mm)
    assert back.allclose(geom, atol=1e-9)
    # the other way round: random tool poses -> geometry -> goals reproduce the detector TCP exactly
    # and the source TCP up to a rotation about the focal spot (its orientation is not geometry)
    rng = np.random.default_rng(1)
    S = pose_matrix(rng.normal(size=(4, 3)) * 200, rng.normal(size=(4, 3)))
    D = pose_matrix(rng.normal(size=(4, 3)) * 200, rng.normal(size=(4, 3)))
    g = geometry_from_tool_poses(S, D, he, 10, 20, 0.11)
    S2, D2 = tool_goals_from_geometry(g, he)
    np.testing.assert_allclose(D2, D, atol=1e-9)
    np.testing.assert_allclose((S2 @ he.source.matrix)[:, :3, 3], (S @ he.source.matrix)[:, :3, 3], atol=1e-9)


def test_default_mounts_face_each_other():
    """With the default mounts the source TCP sits behind the focal spot, the detector TCP behind the panel."""
    geom, he = _scan(4), HandEye()
    S, D = tool_goals_from_geometry(geom, he)
    for i in range(geom.n_views):
        beam = geom.detector_mm[i] - geom.source_mm[i]
        beam /= np.linalg.norm(beam)
        # source TCP 120 mm behind the focal spot, its z axis along the beam
        np.testing.assert_allclose(S[i, :3, 3], geom.source_mm[i] - 120.0 * S[i, :3, 2], atol=1e-9)
        assert S[i, :3, 2] @ beam > 0.99
        # detector TCP 80 mm behind the detector centre, its z axis towards the source (w)
        np.testing.assert_allclose(D[i, :3, 3], geom.detector_mm[i] - 80.0 * geom.w[i], atol=1e-9)


def test_mount_errors_shift_the_geometry_by_the_error():
    geom, he = _scan(3), HandEye()
    S, D = tool_goals_from_geometry(geom, he)
    bad = he.with_errors(source_translation_mm=(0.5, 0, 0), detector_translation_mm=(0, 0.3, 0),
                         detector_rotvec=(0, 0, 0.01))
    g = geometry_from_tool_poses(S, D, bad, geom.n_rows, geom.n_cols, geom.row_pitch_mm)
    p = g.params_relative_to(geom)
    np.testing.assert_allclose(p[:, 0], 0.5, atol=1e-9)   # source along u
    np.testing.assert_allclose(p[:, 4], 0.3, atol=1e-9)   # detector along v
    np.testing.assert_allclose(p[:, 8], 0.01, atol=1e-9)  # in-plane rotation
    np.testing.assert_allclose(p[:, [1, 2, 3, 5, 6, 7]], 0.0, atol=1e-9)


def test_config_forms():
    he = HandEye.from_dict({"source": {"translation_m": [0, 0, 0.12], "rotvec_rad": [math.pi, 0, 0]},
                            "detector": {"translation_m": [0, 0, 0.08], "rpy_rad": [0, 0, 0]}})
    assert he == HandEye()
    assert HandEye.from_dict(he.to_dict()) == he
    assert HandEye.from_dict({}) == HandEye()
    # what a device leaves out keeps the default mount's, as the nodes' parameters do (a translation alone gave
    # rotvec 0: the source's beam turned round)
    assert HandEye.from_dict({"source": {"translation_m": [0, 0, 0.12]}, "detector": {"rpy_rad": [0, 0, 0]}}) == he
    m = mount_from_si([0, 0, 0], rpy_rad=[0.1, 0.2, 0.3])
    np.testing.assert_allclose(m.matrix[:3, :3], Mount.from_rpy((0, 0, 0), (0.1, 0.2, 0.3)).matrix[:3, :3])
    with pytest.raises(ValueError, match="not both"):
        mount_from_si([0, 0, 0], [0, 0, 1], [0, 0, 1])
    with pytest.raises(ValueError, match="3 numbers"):
        mount_from_si([0, 0])


def test_device_frames_are_the_geometry_frames():
    geom = _scan(5)
    S, D = device_frames(geom)
    np.testing.assert_allclose(D[:, :3, 0], geom.u)
    np.testing.assert_allclose(D[:, :3, 2], geom.w)
    np.testing.assert_allclose(S[:, :3, 3], geom.source_mm)
    single = geometry_from_tool_poses(S[0] @ invert(HandEye().source.matrix), D[0] @ invert(HandEye().detector.matrix),
                                      HandEye(), geom.n_rows, geom.n_cols, geom.row_pitch_mm)
    assert isinstance(single, ConeGeometry) and single.n_views == 1
    assert single.allclose(geom.subset([0]), atol=1e-9)


@pytest.mark.parametrize("mount", [HandEye().source, HandEye().detector, _hand_eye().detector],
                         ids=["source", "detector", "tilted-detector"])
def test_device_position_sigma_matches_the_simulated_arms_errors_at_the_device(mount):
    """The simulated arm's per-move errors carried through a mount to the device origin: their
    standard deviation along each device axis is what device_position_sigma_mm predicts, the lever
    arm included (across it the default source's error is 45 % larger than the TCP's)."""
    from robot_ct_ros.hardware.simulated_arm import HOME_Q, SimulatedArm, SimulatedArmErrors, forward_kinematics

    sigma_mm, sigma_deg = 0.1, 0.05
    arm = SimulatedArm(errors=SimulatedArmErrors(sigma_mm=sigma_mm, sigma_deg=sigma_deg, seed=3))
    arm.connect()
    goal = forward_kinematics(np.asarray(HOME_Q, float))
    errors = []
    for _ in range(3000):
        arm.move_linear(goal)
        true, cmd = (pose_matrix(p[:3] * 1e3, p[3:]) @ mount.matrix for p in (arm.true_tcp_pose(), goal))
        errors.append(cmd[:3, :3].T @ (true[:3, 3] - cmd[:3, 3]))  # along the device's axes
    measured = np.sqrt(np.mean(np.square(errors), axis=0))
    predicted = device_position_sigma_mm(mount, sigma_mm, math.radians(sigma_deg))
    np.testing.assert_allclose(measured, predicted, rtol=0.05)
    assert predicted.max() > 1.2 * sigma_mm  # the lever arm matters at these mounts
    with pytest.raises(ValueError, match="non-negative"):
        device_position_sigma_mm(mount, -0.1, 0.0)


def test_a_mount_in_millimetres_or_degrees_is_refused():
    """translation_m [0, 0, 120] (a focal spot 120 m from the flange) and rotvec_rad [180, 0, 0] started the nodes
    without a word; lists were shown as numpy reprs."""
    import pytest

    from robot_ct_ros.ct.hand_eye import mount_from_si

    with pytest.raises(ValueError, match="millimetres given for metres"):
        mount_from_si([0.0, 0.0, 120.0], what="hand_eye.source")
    with pytest.raises(ValueError, match="degrees given for radians"):
        mount_from_si([0.0, 0.0, 0.12], [180.0, 0.0, 0.0], what="hand_eye.source")
    with pytest.raises(ValueError, match=r"rotvec_rad needs 3 numbers, got \[3.14, 0.0\]"):
        mount_from_si([0.0, 0.0, 0.12], [3.14, 0.0], what="hand_eye.source")
    with pytest.raises(ValueError, match="translation_m must be finite"):
        mount_from_si([0.0, float("nan"), 0.12], what="hand_eye.source")
    assert mount_from_si([0.0, 0.0, 0.12], [0.0, 0.0, 3.0]) is not None
