"""geometry_publisher in-process: one geometry per frame with the frame's stamp; stale or missing poses skip."""

import numpy as np
from rclpy.parameter import Parameter
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.hand_eye import HandEye, Mount, geometry_from_tool_poses, tool_goals_from_geometry
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan
from robot_ct_ros.nodes.geometry_publisher import STREAM, GeometryPublisherNode
from robot_ct_ros.nodes.hand_eye_params import matrix_mm_to_pose, ns_to_stamp, stamp_to_ns

GEOM = robotic_roi_scan(SeedSystem(), roi_center_mm=(400.0, 0.0, 300.0), fov_diameter_mm=0.5, n_views=6,
                        n_rows=8, n_cols=10)


class Probe:
    def __init__(self, ros):
        self.node = ros.node("probe")
        n = self.node
        self.geoms, self.diag = [], []
        self.subs = [n.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY, self.geoms.append, STREAM),
                     n.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10)]
        self.pose_pubs = {r: n.create_publisher(PoseStamped, f"{r}_arm/tool_pose", 10) for r in ("source", "detector")}
        self.frame_pub = n.create_publisher(Image, fmt.TOPIC_PROJECTION, STREAM)

    def now_ns(self):
        return self.node.get_clock().now().nanoseconds

    def pose(self, ros, role, T, stamp_ns, frame="world"):
        assert ros.wait_for_subscribers(self.pose_pubs[role])
        msg = PoseStamped()
        msg.header.frame_id, msg.header.stamp = frame, ns_to_stamp(stamp_ns)
        matrix_mm_to_pose(T, msg.pose)
        self.pose_pubs[role].publish(msg)

    def frame(self, ros, stamp_ns):
        assert ros.wait_for_subscribers(self.frame_pub)
        msg = Image(height=8, width=10, encoding="32FC1", step=40, data=bytes(320))
        msg.header.stamp, msg.header.frame_id = ns_to_stamp(stamp_ns), "pcd_detector"
        self.frame_pub.publish(msg)

    def level(self):
        levels = [s.level for a in self.diag for s in a.status if s.name.endswith(": geometry")]
        return levels[-1] if levels else None


def _node(ros, **params):
    return ros.add(GeometryPublisherNode(context=ros.context,
                                         parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))


def test_geometry_per_frame_with_the_frame_stamp(ros):
    node = _node(ros)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())
    t = probe.now_ns()
    # the pose nearest in time to the frame stamp is used: view 1 just before, view 2 just after
    probe.pose(ros, "source", S[1], t - 50_000_000)
    probe.pose(ros, "detector", D[1], t - 50_000_000)
    probe.pose(ros, "source", S[2], t + 10_000_000)
    probe.pose(ros, "detector", D[2], t + 10_000_000)
    assert ros.spin_until(lambda: all(len(h) == 2 for h in node._history.values()))
    probe.frame(ros, t)
    assert ros.spin_until(lambda: probe.geoms)
    msg = probe.geoms[-1]
    assert stamp_to_ns(msg.header.stamp) == t and msg.header.frame_id == "world"
    s, d, u, v = fmt.view_from_pose_array(msg)
    np.testing.assert_allclose(s, GEOM.source_mm[2], atol=1e-6)
    np.testing.assert_allclose(d, GEOM.detector_mm[2], atol=1e-6)
    np.testing.assert_allclose(np.stack([u, v]), np.stack([GEOM.u[2], GEOM.v[2]]), atol=1e-9)
    assert node.published == 1 and node.skipped == 0
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.OK)


def test_stale_missing_or_foreign_poses_give_no_geometry(ros):
    node = _node(ros, max_pose_age_s=0.2, wait_for_poses_s=0.2)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())
    t = probe.now_ns()
    probe.pose(ros, "source", S[0], t)
    assert ros.spin_until(lambda: node._history["source"])
    probe.frame(ros, t)  # no detector pose at all
    assert ros.spin_until(lambda: node.skipped == 1)
    assert "no detector arm tool pose" in node.last_problem
    probe.pose(ros, "detector", D[0], t - 1_000_000_000)  # one second old
    assert ros.spin_until(lambda: node._history["detector"])
    probe.frame(ros, t)
    assert ros.spin_until(lambda: node.skipped == 2)
    assert "stale" in node.last_problem
    probe.pose(ros, "detector", D[0], t, frame="detector_arm_base")  # refused as it arrives
    assert ros.spin_until(lambda: node.poses_refused == 1)
    assert "not 'world'" in node.last_refused and len(node._history["detector"]) == 1
    probe.frame(ros, t)
    assert ros.spin_until(lambda: node.skipped == 3)
    assert "stale" in node.last_problem
    ros.spin_for(0.1)
    assert not probe.geoms and node.published == 0
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.WARN)


def test_hand_eye_parameters_are_used(ros):
    params = {"hand_eye.source.translation_m": [0.001, 0.0, 0.15], "hand_eye.source.rotvec_rad": [3.0, 0.1, 0.0],
              "hand_eye.detector.translation_m": [0.0, 0.002, 0.07], "hand_eye.detector.rpy_rad": [0.0, 0.05, 0.1]}
    node = _node(ros, **params)
    he = HandEye(Mount((1.0, 0.0, 150.0), (3.0, 0.1, 0.0)), Mount.from_rpy((0.0, 2.0, 70.0), (0.0, 0.05, 0.1)))
    assert np.allclose(node.hand_eye.source.matrix, he.source.matrix)
    assert np.allclose(node.hand_eye.detector.matrix, he.detector.matrix)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())  # goals for the default mounts, seen through others
    t = probe.now_ns()
    probe.pose(ros, "source", S[3], t)
    probe.pose(ros, "detector", D[3], t)
    assert ros.spin_until(lambda: all(node._history.values()))
    probe.frame(ros, t)
    assert ros.spin_until(lambda: probe.geoms)
    expect = geometry_from_tool_poses(S[3], D[3], he, 8, 10, 0.11)
    s, d, u, v = fmt.view_from_pose_array(probe.geoms[-1])
    np.testing.assert_allclose(s, expect.source_mm[0], atol=1e-6)
    np.testing.assert_allclose(d, expect.detector_mm[0], atol=1e-6)
    np.testing.assert_allclose(v, expect.v[0], atol=1e-9)


def test_whole_numbers_set_double_parameters(ros):
    """``-p hand_eye.source.rotvec_rad:=[0,0,0]`` is an integer array to ROS; rclpy alone refuses it."""
    node = _node(ros, **{"hand_eye.source.rotvec_rad": [0, 0, 0], "hand_eye.detector.translation_m": [0, 0, 0],
                         "max_pose_age_s": 1})
    assert np.allclose(node.hand_eye.source.matrix[:3, :3], np.eye(3))
    assert np.allclose(node.hand_eye.detector.matrix[:3, 3], 0.0)
    assert node.get_parameter("max_pose_age_s").value == 1.0


def test_bad_parameter_values_are_refused_with_a_clear_error(ros):
    import pytest

    with pytest.raises(ValueError, match="parameter max_pose_age_s.*out of range"):
        GeometryPublisherNode(context=ros.context, parameter_overrides=[Parameter("max_pose_age_s", value=-0.1)])


def test_broken_tool_poses_are_refused_and_never_shadow_good_ones(ros):
    node = _node(ros)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())
    t = probe.now_ns()
    probe.pose(ros, "source", S[1], t - 50_000_000)
    probe.pose(ros, "detector", D[1], t - 50_000_000)
    for i, breakage in enumerate(("nan", "scaled", "frame")):  # each nearer to the frame than the good ones
        T = S[1].copy()
        if breakage == "nan":
            T[0, 3] = np.nan
        msg = PoseStamped()
        msg.header.frame_id = "tool0" if breakage == "frame" else "world"
        msg.header.stamp = ns_to_stamp(t - i * 1_000_000)
        matrix_mm_to_pose(np.nan_to_num(T), msg.pose)
        if breakage == "nan":
            msg.pose.position.x = float("nan")
        if breakage == "scaled":
            o = msg.pose.orientation
            o.x, o.y, o.z, o.w = 2 * o.x, 2 * o.y, 2 * o.z, 2 * o.w
        probe.pose_pubs["source"].publish(msg)
    ros.spin_until(lambda: getattr(node, "poses_refused", 0) == 3, timeout_s=2.0)
    probe.frame(ros, t)
    assert ros.spin_until(lambda: probe.geoms)
    assert node.poses_refused == 3
    s, d, u, v = fmt.view_from_pose_array(probe.geoms[-1])
    np.testing.assert_allclose(s, GEOM.source_mm[1], atol=1e-6)
    assert node.published == 1 and node.skipped == 0
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.WARN)


def test_a_pose_stamped_far_ahead_does_not_age_out_the_good_ones_and_a_skip_is_reported(ros):
    """One source pose stamped 100 s ahead emptied that arm's history, so the frame got no geometry although a
    pose at its very stamp had arrived; a skipped frame followed within the diagnostics period by a good one left
    every status OK."""
    node = _node(ros)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())
    t = probe.now_ns()
    probe.pose(ros, "source", S[1], t)
    probe.pose(ros, "detector", D[1], t)
    probe.pose(ros, "source", S[1], t + 100_000_000_000)
    ros.spin_for(0.2)
    probe.frame(ros, t)
    assert ros.spin_until(lambda: probe.geoms)
    np.testing.assert_allclose(fmt.view_from_pose_array(probe.geoms[-1])[0], GEOM.source_mm[1], atol=1e-6)
    # a frame with no pose near it, then a good one: the report between them still says WARN
    probe.diag.clear()
    node._publish_diagnostics()  # the period's report: a clean start
    probe.frame(ros, t - 3_000_000_000)
    assert ros.spin_until(lambda: node.skipped == 1)
    probe.frame(ros, t)
    assert ros.spin_until(lambda: node.published == 2)
    node._publish_diagnostics()
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.WARN)
    status = [s for a in probe.diag for s in a.status if s.name.endswith(": geometry")][-1]
    assert "1 frame(s) without geometry since the last report" in status.message, status.message


def test_a_frame_before_the_poses_that_bracket_it_waits_for_them(ros):
    """Under CPU load the frame was judged before the poses stamped after it had been received: 'source arm tool
    pose stale (0.511 s from the frame)' while the bag held poses within 8 ms of it (tester F2)."""
    node = _node(ros, max_pose_age_s=0.2)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())
    t = probe.now_ns()
    probe.pose(ros, "source", S[1], t - 500_000_000)  # the last poses before the frame: too old for it
    probe.pose(ros, "detector", D[1], t - 500_000_000)
    assert ros.spin_until(lambda: all(node._history.values()))
    probe.frame(ros, t)
    assert ros.spin_until(lambda: node.skipped + node.published + len(getattr(node, "_pending", ())) == 1)
    assert node.skipped == 0 and not probe.geoms  # held, not judged
    probe.pose(ros, "source", S[2], t + 5_000_000)  # the poses after the frame arrive late
    ros.spin_for(0.1)
    assert not probe.geoms  # the detector arm's history does not reach the frame yet
    probe.pose(ros, "detector", D[2], t + 8_000_000)
    assert ros.spin_until(lambda: probe.geoms)
    msg = probe.geoms[-1]
    assert stamp_to_ns(msg.header.stamp) == t
    s, d, u, v = fmt.view_from_pose_array(msg)
    np.testing.assert_allclose(s, GEOM.source_mm[2], atol=1e-6)
    np.testing.assert_allclose(d, GEOM.detector_mm[2], atol=1e-6)
    assert node.published == 1 and node.skipped == 0 and not node._pending


def test_held_frames_are_published_in_arrival_order(ros):
    node = _node(ros, max_pose_age_s=0.2)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())
    t = probe.now_ns()
    probe.pose(ros, "source", S[0], t - 10_000_000)
    probe.pose(ros, "detector", D[0], t - 10_000_000)
    assert ros.spin_until(lambda: all(node._history.values()))
    for k in range(3):
        probe.frame(ros, t + k * 20_000_000)
    assert ros.spin_until(lambda: len(node._pending) == 3)
    probe.pose(ros, "source", S[1], t + 60_000_000)
    probe.pose(ros, "detector", D[1], t + 60_000_000)
    assert ros.spin_until(lambda: len(probe.geoms) == 3)
    assert [stamp_to_ns(m.header.stamp) for m in probe.geoms] == [t, t + 20_000_000, t + 40_000_000]
    assert node.skipped == 0


def test_a_frame_whose_poses_never_come_gets_no_geometry_after_the_wait(ros):
    node = _node(ros, max_pose_age_s=0.2, wait_for_poses_s=0.5)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(GEOM, HandEye())
    t = probe.now_ns()
    probe.pose(ros, "source", S[1], t - 1_000_000_000)
    probe.pose(ros, "detector", D[1], t + 1_000_000)  # this arm is fine
    assert ros.spin_until(lambda: all(node._history.values()))
    import time

    probe.frame(ros, t)
    assert ros.spin_until(lambda: node.skipped + node.published + len(getattr(node, "_pending", ())) == 1)
    held = time.monotonic()
    assert ros.spin_until(lambda: node.skipped == 1)
    assert time.monotonic() - held >= 0.4  # it waited (a lower bound only: the machine may be slow)
    assert "source arm tool pose stale (1.000 s from the frame" in node.last_problem, node.last_problem
    assert "waited" in node.last_problem and "wait_for_poses_s 0.5 s" in node.last_problem, node.last_problem
    assert "source 1.000 s before the frame" in node.last_problem, node.last_problem
    assert "detector" not in node.last_problem
    assert not probe.geoms and node.published == 0
    # a pose within max_pose_age_s before the frame still gives the geometry when nothing newer comes
    probe.pose(ros, "source", S[1], t + 1_000_000_000 - 100_000_000)
    probe.pose(ros, "detector", D[1], t + 1_000_000_000 - 100_000_000)
    assert ros.spin_until(lambda: all(len(h) == 2 for h in node._history.values()))
    probe.frame(ros, t + 1_000_000_000)
    assert ros.spin_until(lambda: node.published == 1)
    assert node.skipped == 1
