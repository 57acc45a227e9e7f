"""pcd_grabber in-process: frames on request, latched flat/dead maps, true geometry, dark frames,
beam-interrupted frames, timeouts, lifecycle."""

import json

import numpy as np
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Bool
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.hand_eye import HandEye, tool_goals_from_geometry
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan
from robot_ct_ros.nodes.hand_eye_params import matrix_mm_to_pose, stamp_to_ns
from robot_ct_ros.nodes.pcd_grabber import PcdGrabberNode

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
CENTER_M = (0.4, 0.0, 0.3)
TINY = dict(n_rows=12, n_cols=16, binning=2, raw_pixel_m=0.5e-3, sim_phantom="mouse",
            sim_phantom_center_m=list(CENTER_M), sim_voxel_size_m=1e-3, sim_photons_per_pixel=20000.0,
            sim_chip_size_px=10, sim_chip_gap_px=1, exposure_s=0.05, exposure_timeout_s=2.0)


def tiny_geometry(n_views=4):
    system = SeedSystem(raw_pixel_mm=0.5, binning=2)
    return robotic_roi_scan(system, roi_center_mm=np.array(CENTER_M) * 1e3, fov_diameter_mm=8.0, n_views=n_views,
                            n_rows=12, n_cols=16)


def _grabber(ros, name="pcd_grabber", **params):
    values = dict(TINY, **params)
    return ros.add(PcdGrabberNode(name, context=ros.context,
                                  parameter_overrides=[Parameter(k, value=v) for k, v in values.items()]))


class Probe:
    def __init__(self, ros):
        self.node = ros.node("probe")
        self.frames, self.true_geoms, self.flat, self.dead, self.diag, self.rejected = [], [], [], [], [], []
        n = self.node
        self.subs = [n.create_subscription(Image, fmt.TOPIC_PROJECTION, self.frames.append, 10),
                     n.create_subscription(Image, fmt.TOPIC_PROJECTION_REJECTED, self.rejected.append, 10),
                     n.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY_TRUE, self.true_geoms.append, 10),
                     n.create_subscription(Image, fmt.TOPIC_FLAT_FIELD, self.flat.append, LATCHED),
                     n.create_subscription(Image, fmt.TOPIC_DEAD_PIXELS, self.dead.append, LATCHED),
                     n.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10)]
        self.beam = n.create_publisher(Bool, "source/beam_on", LATCHED)
        self.pose = {r: n.create_publisher(PoseStamped, f"{r}_arm/true_tool_pose", 10) for r in ("source", "detector")}
        self.expose = n.create_client(Trigger, "pcd/expose")

    def publish_poses(self, ros, S, D, frame="world"):
        for role, T in (("source", S), ("detector", D)):
            assert ros.wait_for_subscribers(self.pose[role])
            msg = PoseStamped()
            msg.header.frame_id = frame
            msg.header.stamp = self.node.get_clock().now().to_msg()
            matrix_mm_to_pose(T, msg.pose)
            self.pose[role].publish(msg)

    def set_beam(self, ros, node, on):
        assert ros.wait_for_subscribers(self.beam)
        self.beam.publish(Bool(data=on))
        assert ros.spin_until(lambda: node.beam_log.entries and node.beam_log.entries[-1][1] == on)

    def level(self):
        levels = [s.level for a in self.diag for s in a.status if s.name.endswith(": detector")]
        return levels[-1] if levels else None


def test_frame_on_request_with_true_geometry_and_latched_maps(ros):
    node = _grabber(ros)
    probe = Probe(ros)
    assert ros.spin_until(lambda: probe.flat and probe.dead)  # latched, subscribed after the node started
    flat = fmt.array_from_image(probe.flat[-1])
    dead = fmt.array_from_image(probe.dead[-1])
    assert flat.shape == dead.shape == (12, 16) and probe.dead[-1].encoding == "mono8"
    assert dead.any() and np.all(flat[dead == 0] > 0)

    geom = tiny_geometry()
    S, D = tool_goals_from_geometry(geom, HandEye())
    probe.publish_poses(ros, S[1], D[1])
    assert ros.spin_until(lambda: len(node.true_poses) == 2)
    probe.set_beam(ros, node, True)
    answer = ros.call(probe.expose, Trigger.Request())
    assert answer.success, answer.message
    info = json.loads(answer.message)
    assert ros.spin_until(lambda: probe.frames and probe.true_geoms)
    frame = probe.frames[-1]
    assert stamp_to_ns(frame.header.stamp) == info["stamp_ns"] == stamp_to_ns(probe.true_geoms[-1].header.stamp)
    assert frame.header.frame_id == "pcd_detector" and frame.encoding == "32FC1"
    counts = fmt.array_from_image(frame)
    assert counts.shape == (12, 16) and 0 < counts[dead == 0].mean() < flat[dead == 0].mean()
    s, d, u, v = fmt.view_from_pose_array(probe.true_geoms[-1])
    np.testing.assert_allclose(s, geom.source_mm[1], atol=1e-6)
    np.testing.assert_allclose(d, geom.detector_mm[1], atol=1e-6)
    np.testing.assert_allclose(u, geom.u[1], atol=1e-9)
    assert node.last_beam_fraction == 1.0
    assert info["valid_pixel_fraction"] > 0.5 and node.frames_low_valid == 0 and not node.valid_warning
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.OK)

    # the beam is off: the detector still delivers, a dark frame
    probe.publish_poses(ros, S[1], D[1])  # fresh poses (older than sim_pose_max_age_s count as unknown)
    probe.set_beam(ros, node, False)
    answer = ros.call(probe.expose, Trigger.Request())
    assert answer.success
    assert ros.spin_until(lambda: len(probe.frames) == 2)
    assert np.all(fmt.array_from_image(probe.frames[-1]) == 0.0) and node.last_beam_fraction == 0.0


def test_the_true_geometry_is_in_the_world_frame_of_the_graph(ros):
    """Outside test 27 A #1: /ct/geometry_true always named "world", while the arms (base_frame) and the geometry
    publisher (world_frame) worked in "lab"; world_frame says the frame, and true poses in another are ignored."""
    node = _grabber(ros, world_frame="lab")
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(tiny_geometry(), HandEye())
    probe.publish_poses(ros, S[1], D[1], frame="world")
    ros.spin_for(0.3)
    assert len(node.true_poses) == 0  # not the graph's frame: unknown poses, no frame (as geometry_publisher)
    probe.publish_poses(ros, S[1], D[1], frame="lab")
    assert ros.spin_until(lambda: len(node.true_poses) == 2)
    probe.set_beam(ros, node, True)
    answer = ros.call(probe.expose, Trigger.Request())
    assert answer.success, answer.message
    assert ros.spin_until(lambda: probe.true_geoms)
    assert probe.true_geoms[-1].header.frame_id == "lab"


def test_requests_never_block_the_executor(ros):
    """While one exposure runs, a second request is answered at once (busy) and other callbacks run."""
    node = _grabber(ros, exposure_s=0.4)
    probe = Probe(ros)
    geom = tiny_geometry()
    S, D = tool_goals_from_geometry(geom, HandEye())
    probe.publish_poses(ros, S[0], D[0])
    probe.set_beam(ros, node, True)
    assert ros.wait_for_service(probe.expose)
    first = probe.expose.call_async(Trigger.Request())
    assert ros.spin_until(lambda: node.exposures.pending is not None)
    second = probe.expose.call_async(Trigger.Request())
    assert ros.spin_until(second.done)
    assert not first.done()
    assert not second.result().success and "busy" in second.result().message
    probe.set_beam(ros, node, False)  # a subscription callback runs during the exposure
    assert ros.spin_until(first.done)
    # switched off part-way through the exposure: the frame is rejected, not a projection
    assert not first.result().success and "beam interrupted" in first.result().message
    assert 0.0 < node.last_beam_fraction < 1.0
    assert ros.spin_until(lambda: probe.rejected)
    assert not probe.frames and not probe.true_geoms and node.frames_published == 0 and node.failures == 0
    assert str(stamp_to_ns(probe.rejected[-1].header.stamp)) in first.result().message


def test_detector_timeout_answers_failure_in_time(ros):
    node = _grabber(ros, name="pcd_timeout", sim_fail="timeout", exposure_timeout_s=0.5)
    probe = Probe(ros)
    geom = tiny_geometry()
    S, D = tool_goals_from_geometry(geom, HandEye())
    probe.publish_poses(ros, S[0], D[0])
    answer = ros.call(probe.expose, Trigger.Request(), timeout_s=5.0)
    assert not answer.success and "timeout" in answer.message
    answer = ros.call(probe.expose, Trigger.Request(), timeout_s=5.0)  # the detector still hangs
    assert not answer.success and "not responding" in answer.message
    assert not probe.frames and node.failures == 2
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.ERROR)


def test_no_true_poses_is_an_error_not_a_frame(ros):
    node = _grabber(ros, name="pcd_noposes")
    probe = Probe(ros)
    answer = ros.call(probe.expose, Trigger.Request())
    assert not answer.success and "poses unknown" in answer.message
    ros.spin_for(0.2)
    assert not probe.frames and node.frames_published == 0


def _transition(ros, client, transition_id):
    return ros.call(client, ChangeState.Request(transition=Transition(id=transition_id))).success


def test_lifecycle_configure_activate_deactivate_cleanup(ros):
    """configure connects and offers pcd/expose, activate serves it, deactivate drops the exposure in flight."""
    node = _grabber(ros, name="pcd_lc", autostart=False, exposure_s=0.5)
    probe = Probe(ros)
    change = probe.node.create_client(ChangeState, "/pcd_lc/change_state")
    assert ros.wait_for_service(change)
    ros.spin_for(0.2)
    assert node.lifecycle_state == "unconfigured" and node.detector is None
    assert not probe.expose.service_is_ready() and not probe.flat  # no detector, no service

    assert _transition(ros, change, Transition.TRANSITION_CONFIGURE)
    assert node.detector.is_connected and node.lifecycle_state == "inactive"
    answer = ros.call(probe.expose, Trigger.Request())
    assert not answer.success and "not active" in answer.message and "inactive" in answer.message
    assert node.failures == 0  # a refusal, not a detector fault

    assert _transition(ros, change, Transition.TRANSITION_ACTIVATE)
    assert ros.spin_until(lambda: probe.flat and probe.dead)  # published on activation
    geom = tiny_geometry()
    S, D = tool_goals_from_geometry(geom, HandEye())
    probe.publish_poses(ros, S[0], D[0])
    assert ros.spin_until(lambda: len(node.true_poses) == 2)
    probe.set_beam(ros, node, True)
    call = probe.expose.call_async(Trigger.Request())
    assert ros.spin_until(lambda: node.exposures.pending is not None)
    assert _transition(ros, change, Transition.TRANSITION_DEACTIVATE)  # mid-exposure
    assert ros.spin_until(call.done)
    assert not call.result().success and "deactivated" in call.result().message
    ros.spin_for(0.6)  # the acquisition ends meanwhile: its frame is dropped
    assert not probe.frames and node.frames_published == 0
    answer = ros.call(probe.expose, Trigger.Request())
    assert not answer.success and "not active" in answer.message

    detector = node.detector
    assert _transition(ros, change, Transition.TRANSITION_CLEANUP)
    assert node.detector is None and not detector.is_connected
    assert ros.spin_until(lambda: not probe.expose.service_is_ready())


def test_configure_fails_without_a_driver(ros):
    node = _grabber(ros, name="pcd_nodriver", driver="real")
    assert node.lifecycle_state == "unconfigured" and node.detector is None
    assert "configure failed" in node.last_error and "not available" in node.last_error


def test_beam_coming_on_mid_exposure_rejects_the_frame(ros):
    """Neither a projection nor a dark frame: off at the request, on for part of the exposure."""
    node = _grabber(ros, name="pcd_beam_late", exposure_s=0.4)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(tiny_geometry(), HandEye())
    probe.publish_poses(ros, S[0], D[0])
    probe.set_beam(ros, node, False)
    assert ros.wait_for_service(probe.expose)
    call = probe.expose.call_async(Trigger.Request())
    assert ros.spin_until(lambda: node.exposures.pending is not None)
    probe.set_beam(ros, node, True)
    assert ros.spin_until(call.done)
    assert not call.result().success and "beam interrupted" in call.result().message
    assert 0.0 < node.last_beam_fraction < 1.0
    assert ros.spin_until(lambda: probe.rejected) and not probe.frames


def test_bad_parameters_are_refused_with_a_clear_error(ros):
    """A negative exposure, a string for a float, an inconsistent pair, a short list: one line naming the
    parameter, raised before anything is built."""
    import pytest

    cases = (({"exposure_s": -0.1}, ("parameter exposure_s", "out of range")),
             ({"exposure_s": "fast"}, ("parameter exposure_s", "STRING", "DOUBLE")),
             ({"exposure_s": 3.0}, ("exposure_s < exposure_timeout_s",)),
             ({"sim_phantom": "teapot"}, ("parameter sim_phantom", "mouse, battery, carotid")),
             ({"sim_region_center_m": [0.4, 0.0]}, ("parameter sim_region_center_m", "needs 3")),
             ({"sim_roi_size_m": [0.01, -0.01, 0.01]}, ("parameter sim_roi_size_m", ">= 0")))
    for params, words in cases:
        with pytest.raises(ValueError) as err:
            PcdGrabberNode("pcd_bad", context=ros.context, parameter_overrides=[
                Parameter(k, value=v) for k, v in dict(TINY, **params).items()])
        message = str(err.value)
        assert "\n" not in message and all(w in message for w in words), message


def test_simulation_settings_reach_the_detector(ros):
    """The sim_* parameters are one settings object, and the detector is built from it."""
    node = _grabber(ros, name="pcd_settings", autostart=False, sim_seed=5, sim_readout_s=0.01,
                    sim_region_center_m=[0.4, 0.0, 0.29])
    assert node.sim.seed == 5 and node.sim.region_center_m == (0.4, 0.0, 0.29) and node.sim.phantom == "mouse"
    assert list(node.get_parameter("sim_region_center_m").value) == [0.4, 0.0, 0.29]
    assert node.trigger_configure().name == "SUCCESS"
    det = node.detector
    assert det.readout_s == 0.01 and det.model.seed == 5 and det.model.chip_size_px == 10
    assert det.config.shape == (12, 16) and det.config.raw_pixel_mm == 0.5


class _BuggyDetector:
    """A working simulated detector whose acquisition raises what no driver should: a bug."""

    def __init__(self, detector):
        self._detector = detector

    def __getattr__(self, name):
        return getattr(self._detector, name)

    def acquire(self, exposure_s):
        raise ZeroDivisionError("a driver bug")


def test_a_driver_bug_is_an_error_and_an_error_transition(ros):
    node = _grabber(ros, name="pcd_buggy", autostart=False)
    node._detector_factory = lambda: _BuggyDetector(node._make_detector())
    probe = Probe(ros)
    assert node.trigger_configure().name == "SUCCESS" and node.trigger_activate().name == "SUCCESS"
    answer = ros.call(probe.expose, Trigger.Request(), timeout_s=5.0)
    assert not answer.success and "ZeroDivisionError" in answer.message
    assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured")
    assert node.detector is None and "fault" in node.last_error
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.ERROR)


def test_a_failing_service_callback_is_answered_and_reported(ros):
    node = _grabber(ros, name="pcd_cb_bug")

    def broken(request, response):
        raise KeyError("a bug in the callback")
    node._on_expose = broken  # the ServiceThread was built with the bound method: rebuild it
    node.trigger_deactivate(), node.trigger_cleanup()
    assert node.trigger_configure().name == "SUCCESS" and node.trigger_activate().name == "SUCCESS"
    probe = Probe(ros)
    answer = ros.call(probe.expose, Trigger.Request(), timeout_s=5.0)
    assert not answer.success and "KeyError" in answer.message
    assert ros.spin_until(lambda: node.lifecycle_state == "unconfigured")
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.ERROR)


def test_a_mostly_dead_detector_is_warned_about(ros):
    """A detector 98.7 % dead (sim_dead_pixel_fraction 0.9) gave no warning anywhere: the scan ended 'scan complete:
    6 frames, 6 with geometry'; only robot-ct info showed 'pixels 1.27 % valid' (tester F5)."""
    node = _grabber(ros, sim_dead_pixel_fraction=0.9)
    probe = Probe(ros)
    assert ros.spin_until(lambda: probe.dead)
    dead = fmt.array_from_image(probe.dead[-1])
    assert (dead == 0).mean() < 0.5

    def status():
        found = [s for a in probe.diag for s in a.status if s.name.endswith(": detector")]
        return found[-1] if found else None

    # on activation: the maps alone leave too few pixels
    assert ros.spin_until(lambda: status() is not None and "% of the pixels valid" in status().message)
    assert status().level == DiagnosticStatus.WARN and "dead-pixel map" in status().message
    S, D = tool_goals_from_geometry(tiny_geometry(), HandEye())
    probe.publish_poses(ros, S[1], D[1])
    assert ros.spin_until(lambda: len(node.true_poses) == 2)
    probe.set_beam(ros, node, True)
    answer = ros.call(probe.expose, Trigger.Request())
    assert answer.success, answer.message  # still a frame: the warning does not stop a scan
    fraction = json.loads(answer.message)["valid_pixel_fraction"]
    assert fraction == (dead == 0).mean()
    assert node.frames_low_valid == 1
    probe.diag.clear()
    assert ros.spin_until(lambda: status() is not None)
    st = status()
    assert st.level == DiagnosticStatus.WARN
    assert f"frame 1 (stamp {json.loads(answer.message)['stamp_ns']}): only {100 * fraction:.2f} % of the pixels " \
           "valid (min_valid_pixel_fraction 50 %" in st.message, st.message
    values = {kv.key: kv.value for kv in st.values}
    assert float(values["valid_pixel_fraction"]) == fraction and values["frames_low_valid_pixels"] == "1"


def test_the_valid_pixel_threshold_is_a_parameter(ros):
    node = _grabber(ros, sim_dead_pixel_fraction=0.9, min_valid_pixel_fraction=0.0)
    probe = Probe(ros)
    S, D = tool_goals_from_geometry(tiny_geometry(), HandEye())
    probe.publish_poses(ros, S[1], D[1])
    assert ros.spin_until(lambda: len(node.true_poses) == 2)
    probe.set_beam(ros, node, True)
    answer = ros.call(probe.expose, Trigger.Request())
    assert answer.success, answer.message
    assert node.frames_low_valid == 0 and not node.valid_warning
    assert ros.spin_until(lambda: probe.level() == DiagnosticStatus.OK)
