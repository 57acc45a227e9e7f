"""scan_orchestrator in-process with source_control, two simulated arm drivers and a scripted fake detector."""

import json
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Bool, String
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.hand_eye import HandEye, tool_goals_from_geometry
from robot_ct_ros.nodes.arm_driver import ArmDriverNode
from robot_ct_ros.nodes.common import ServiceThread
from robot_ct_ros.nodes.hand_eye_params import ns_to_stamp, pose_to_matrix_mm
from robot_ct_ros.hardware.scan_protocol import ScanProtocol
from robot_ct_ros.nodes.scan_orchestrator import ScanOrchestratorNode
from robot_ct_ros.nodes.source_control import SourceControlNode

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
CONFIG = Path(__file__).resolve().parents[2] / "config"
PROTOCOL = {"name": "test", "n_views": 4, "roi_center_m": [0.4, 0.0, 0.3], "fov_diameter_m": 0.004,
            "detector": {"n_rows": 6, "n_cols": 8, "binning": 2, "raw_pixel_m": 0.0005},
            "exposure_s": 0.02, "settle_s": 0.01, "move_timeout_s": 5.0, "exposure_timeout_s": 1.0}


def _params(**kw):
    return [Parameter(k, value=v) for k, v in kw.items()]


class FakeDetector:
    """pcd/expose answered by the test: 'frame' (publish a frame, answer), 'fail', or 'hold' (answer on release()).

    Served like the real pcd_grabber's, on its own executor thread (ServiceThread), so a held request
    blocks nothing the test spins."""

    def __init__(self, ros, node, source, arms):
        self.ros, self.node, self.source, self.arms = ros, node, source, arms
        self.plan: dict[int, str] = {}
        self.requests = []
        self.held = None
        self._release = threading.Event()
        self.pub = node.create_publisher(Image, fmt.TOPIC_PROJECTION, 100)
        self.srv = ServiceThread(node, Trigger, "pcd/expose", self._on_expose)

    def release(self, success=True, message=""):
        """Answer the held request now."""
        held, self.held = self.held, None
        held.success, held.message = success, message
        self._release.set()

    def _on_expose(self, request, response):
        n = len(self.requests)
        # what the detector would see: beam and arm state at the moment of the request
        self.requests.append((self.source.interlock.beam_on, all(a.in_position() for a in self.arms)))
        mode = self.plan.get(n, "frame")
        if mode == "fail":
            response.success, response.message = False, "detector exploded (scripted)"
            return response
        if mode == "hold":
            self._release.clear()
            self.held = response
            self._release.wait(10.0)
            return response
        stamp = self.node.get_clock().now().nanoseconds
        msg = Image(height=6, width=8, encoding="32FC1", step=32, data=bytes(192))
        msg.header.stamp, msg.header.frame_id = ns_to_stamp(stamp), "pcd_detector"
        self.pub.publish(msg)
        response.success, response.message = True, json.dumps({"stamp_ns": stamp})
        return response


class Graph:
    def __init__(self, ros, tmp_path, protocol=None, **orch_params):
        path = tmp_path / "protocol.yaml"
        path.write_text(yaml.safe_dump({"scan_protocol": dict(PROTOCOL, **(protocol or {}))}))
        self.ros = ros
        self.source = ros.add(SourceControlNode(context=ros.context))
        self.arms = [ros.add(ArmDriverNode(f"{r}_arm_driver", context=ros.context, parameter_overrides=_params(role=r)))
                     for r in ("source", "detector")]
        orch_params.setdefault("pairing_timeout_s", 0.1)  # no geometry_publisher here
        self.orch = ros.add(ScanOrchestratorNode(context=ros.context, parameter_overrides=_params(
            protocol_file=str(path), **orch_params)))
        self.probe = ros.node("probe")
        self.detector = FakeDetector(ros, self.probe, self.source, self.arms)
        self.status, self.armed, self.info, self.goals = [], [], [], {"source": [], "detector": []}
        p = self.probe
        self.subs = [p.create_subscription(String, "scan/status", lambda m: self.status.append(json.loads(m.data)), 10),
                     p.create_subscription(Bool, "scan/armed", lambda m: self.armed.append(m.data), LATCHED),
                     p.create_subscription(String, fmt.TOPIC_SCAN_INFO, lambda m: self.info.append(json.loads(m.data)),
                                           LATCHED)]
        for r in ("source", "detector"):
            self.subs.append(p.create_subscription(PoseStamped, f"{r}_arm/goal_pose",
                                                   lambda m, r=r: self.goals[r].append(pose_to_matrix_mm(m.pose)), 10))
        self.start_client = p.create_client(Trigger, "scan/start")
        self.abort_client = p.create_client(Trigger, "scan/abort")
        # beam transitions as the source sees them
        self.beam_log = []
        src = self.source.interlock.source
        orig = src.set_beam

        def logged(on, now_s):
            if bool(on) != src.beam_on:
                self.beam_log.append(bool(on))
            orig(on, now_s)
        src.set_beam = logged

    def start(self):
        assert self.ros.spin_until(lambda: all(a.lifecycle_state == "active" for a in self.arms))
        assert self.ros.spin_until(lambda: self.orch.set_beam.service_is_ready() and self.orch.expose.service_is_ready()
                                   and all(np.isfinite(t) for t in self.orch.scan.arm_pose_t.values()))
        answer = self.ros.call(self.start_client, Trigger.Request())
        assert answer.success, answer.message
        return answer

    def wait_end(self, timeout_s=30.0):
        assert self.ros.spin_until(lambda: self.orch.state in ("done", "aborted"), timeout_s=timeout_s), self.orch.state

    def safe(self):
        """Beam off and scan disarmed at the source."""
        return (not self.source.interlock.beam_on and not self.source.interlock.inputs.scan_armed)


def test_protocol_files_and_validation():
    for path in sorted(CONFIG.glob("scan_protocol_*.yaml")):
        proto = ScanProtocol.from_yaml(path)
        geom = proto.geometry()
        assert geom.n_views == proto.n_views and geom.det_shape == (proto.n_rows, proto.n_cols)
        info = proto.scan_info(geom, "id")
        assert info["n_views"] == proto.n_views and info["notes"]["protocol"] == proto.name
    proto = ScanProtocol.from_dict({"scan_protocol": PROTOCOL})
    assert proto.n_rows == 6 and proto.raw_pixel_m == 0.0005
    with pytest.raises(ValueError, match="unknown"):
        ScanProtocol.from_dict(dict(PROTOCOL, n_veiws=3))
    with pytest.raises(ValueError, match="exposure"):
        ScanProtocol.from_dict(dict(PROTOCOL, exposure_s=2.0))
    with pytest.raises(ValueError, match="FOV"):
        ScanProtocol.from_dict(dict(PROTOCOL, fov_diameter_m=0.05))


def test_start_refused_until_the_graph_is_there(ros, tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(PROTOCOL))
    orch = ros.add(ScanOrchestratorNode(context=ros.context, parameter_overrides=_params(protocol_file=str(path))))
    ok, msg = orch.start()
    assert not ok
    for what in ("source/set_beam", "pcd/expose", "scan/armed", "source arm", "detector arm"):
        assert what in msg
    path.write_text("scan_protocol: {n_views: 0}")
    ok, msg = orch.start()
    assert not ok and msg.startswith("protocol:")
    assert orch.state == "idle"


def test_runs_the_protocol(ros, tmp_path):
    g = Graph(ros, tmp_path)
    g.start()
    g.wait_end()
    assert g.orch.state == "done", g.orch.message
    assert g.orch.frames == 4 and len(g.detector.requests) == 4
    # every exposure was requested with the beam on and both arms in position
    assert all(beam and in_pos for beam, in_pos in g.detector.requests)
    assert g.beam_log == [True, False] * 4
    assert ros.spin_until(lambda: g.safe() and g.armed and g.armed[-1] is False)
    # the goals are the protocol's trajectory through the inverse hand-eye transform
    proto = ScanProtocol.from_dict(PROTOCOL)
    S, D = tool_goals_from_geometry(proto.geometry(), HandEye())
    assert ros.spin_until(lambda: len(g.goals["detector"]) == 4)
    np.testing.assert_allclose(np.array(g.goals["source"]), S, atol=1e-6)
    np.testing.assert_allclose(np.array(g.goals["detector"]), D, atol=1e-6)
    assert g.info and g.info[-1]["n_views"] == 4 and g.info[-1]["n_rows"] == 6
    assert ros.spin_until(lambda: g.status and g.status[-1]["state"] == "done")
    assert g.status[-1]["frames"] == 4 and g.status[-1]["n_views"] == 4
    states = [s["state"] for s in g.status]
    for s in ("moving", "settling", "beam_on", "exposing", "beam_off", "done"):
        assert s in states
    # a second scan can follow
    g.start()
    g.wait_end()
    assert g.orch.state == "done" and len(g.detector.requests) == 8


def test_autostart_waits_for_the_graph(ros, tmp_path):
    g = Graph(ros, tmp_path, autostart=True)
    g.wait_end()
    assert g.orch.state == "done" and g.orch.frames == 4


def test_detector_failure_aborts_and_keeps_frames(ros, tmp_path):
    g = Graph(ros, tmp_path)
    g.detector.plan = {2: "fail"}
    g.start()
    g.wait_end()
    assert g.orch.state == "aborted" and "detector exploded" in g.orch.message
    assert g.orch.frames == 2
    assert ros.spin_until(g.safe)
    assert ros.spin_until(lambda: g.armed and g.armed[-1] is False)
    assert ros.spin_until(lambda: g.status and g.status[-1]["state"] == "aborted")
    assert g.status[-1]["frames"] == 2 and "detector exploded" in g.status[-1]["message"]


def test_a_latched_estop_refuses_the_start_and_the_arms_stay(ros, tmp_path):
    """The source's e-stop latched before the scan (source/estop, not the estop topic): scan/start once moved the
    arms and failed only at the beam. The orchestrator hears the latch on source/estop_latched and refuses the
    start with the reason, no goal goes out; after source/reset_estop the scan runs."""
    g = Graph(ros, tmp_path)
    estop = g.probe.create_client(Trigger, "source/estop")
    assert ros.call(estop, Trigger.Request()).success
    assert ros.spin_until(lambda: g.orch.scan.estop_latched)
    assert ros.spin_until(lambda: all(a.lifecycle_state == "active" for a in g.arms))
    answer = ros.call(g.start_client, Trigger.Request())
    assert not answer.success and "e-stop is latched" in answer.message, answer.message
    ros.spin_for(0.3)
    assert g.goals == {"source": [], "detector": []} and not g.detector.requests
    assert ros.spin_until(g.safe)
    reset = g.probe.create_client(Trigger, "source/reset_estop")
    assert ros.call(reset, Trigger.Request()).success
    assert ros.spin_until(lambda: not g.orch.scan.estop_latched)
    g.start()
    g.wait_end()
    assert g.orch.state == "done", g.orch.message


def test_beam_refused_aborts(ros, tmp_path):
    g = Graph(ros, tmp_path)
    g.start()
    g.source.interlock.max_report_age_s = 0.0  # every arm report is stale: the interlock refuses the beam
    g.wait_end()
    assert g.orch.state == "aborted" and "beam refused" in g.orch.message and "stale" in g.orch.message
    assert g.orch.frames == 0 and not g.detector.requests
    assert ros.spin_until(g.safe)


def test_beam_lost_during_exposure_aborts(ros, tmp_path):
    g = Graph(ros, tmp_path, beam_off_margin_s=30.0)  # the beam stays on while the detector holds the exposure
    g.detector.plan = {1: "hold"}
    g.start()
    assert ros.spin_until(lambda: g.detector.held is not None)
    assert g.source.interlock.beam_on and g.orch.state == "exposing"
    disarm = g.probe.create_publisher(Bool, "scan/armed", 10)  # someone else disarms: the interlock cuts the beam
    assert ros.wait_for_subscribers(disarm)
    disarm.publish(Bool(data=False))
    g.wait_end()
    assert g.orch.state == "aborted" and "beam lost" in g.orch.message
    assert g.orch.frames == 1
    assert ros.spin_until(g.safe)
    # pcd_grabber refuses a beam-interrupted frame (it goes to /ct/projection_rejected): the late answer counts none
    g.detector.release(False, "beam interrupted: on for 40% of the exposure")
    ros.spin_for(0.1)
    assert g.orch.state == "aborted" and g.orch.frames == 1


def test_abort_service(ros, tmp_path):
    g = Graph(ros, tmp_path)
    g.detector.plan = {0: "hold"}
    g.start()
    assert ros.spin_until(lambda: g.detector.held is not None)
    answer = ros.call(g.abort_client, Trigger.Request())
    assert answer.success
    assert g.orch.state == "aborted" and "on request" in g.orch.message
    assert ros.spin_until(g.safe)
    answer = ros.call(g.abort_client, Trigger.Request())  # nothing running: still answers, still safe
    # the switch-off is asked for, not awaited: the answer says so, and adds what the source last reported
    assert answer.success and "no scan running" in answer.message and "beam off requested" in answer.message
    assert "still reports the beam ON" not in answer.message
    g.detector.release(False, "never answered")


def test_bad_parameters_are_refused_with_a_clear_error(ros):
    for params, words in (({"tick_period_s": 0.0}, ("parameter tick_period_s", "out of range")),
                          ({"frame_timeout_s": "soon"}, ("parameter frame_timeout_s", "DOUBLE")),
                          ({"autostart": 1}, ("parameter autostart", "BOOL"))):
        with pytest.raises(ValueError) as err:
            ScanOrchestratorNode(context=ros.context, parameter_overrides=_params(**params))
        message = str(err.value)
        assert "\n" not in message and all(w in message for w in words), message


def test_the_beam_goes_off_before_a_slow_detector_answers(ros, tmp_path):
    """Outside tester, F1: the beam stayed on until pcd/expose answered (a slow read-out: 2.7 s per view). Now it
    goes off exposure_s + beam_off_margin_s after the request; the frame is awaited with the beam off, the scan
    goes on, and the slow read-out is named in a warning."""
    g = Graph(ros, tmp_path)
    g.detector.plan = {1: "hold"}
    warnings = []
    orig = g.orch.log
    g.orch.log = lambda level, message: (warnings.append(message) if level == "warn" else None, orig(level, message))
    g.start()
    assert ros.spin_until(lambda: g.detector.held is not None)
    # held by the detector (the read-out): the beam goes off without its answer
    assert ros.spin_until(lambda: g.beam_log == [True, False] * 2 and not g.source.interlock.beam_on)
    assert g.detector.held is not None and g.orch.state in ("beam_off", "waiting_frame")
    assert ros.spin_until(lambda: g.orch.state == "waiting_frame")
    ros.spin_for(0.6)  # past exposure_s + readout_warn_s
    assert g.orch.state == "waiting_frame" and not g.source.interlock.beam_on
    stamp = g.probe.get_clock().now().nanoseconds
    msg = Image(height=6, width=8, encoding="32FC1", step=32, data=bytes(192))
    msg.header.stamp, msg.header.frame_id = ns_to_stamp(stamp), "pcd_detector"
    g.detector.pub.publish(msg)
    g.detector.release(True, json.dumps({"stamp_ns": stamp}))
    g.wait_end()
    assert g.orch.state == "done" and g.orch.frames == 4, g.orch.message
    assert g.beam_log == [True, False] * 4
    assert any("slow detector read-out" in w for w in warnings), warnings
    assert "1 slow detector read-outs" in g.orch.message


def test_a_detector_node_that_does_not_answer_or_is_not_active_gets_no_beam(ros, tmp_path):
    """Outside tester, F1: a killed pcd_grabber still seemed to offer pcd/expose (the DDS lease), and the beam went
    on. Before each beam-on the orchestrator asks the node that offers pcd/expose for its lifecycle state: one
    that does not answer (here: never spun, as a killed process) or is not active gets no beam."""
    from rclpy.lifecycle import LifecycleNode

    g = Graph(ros, tmp_path, service_timeout_s=0.5)
    g.detector.srv.close()
    dead = LifecycleNode("pcd_grabber", context=ros.context)  # in the graph, never spun: answers nothing
    dead.create_service(Trigger, "pcd/expose", lambda q, r: r)
    assert ros.spin_until(lambda: g.orch.expose.service_is_ready())
    g.start()
    g.wait_end()
    assert g.orch.state == "aborted" and "/pcd_grabber" in g.orch.message, g.orch.message
    assert "does not answer" in g.orch.message and "not switched on" in g.orch.message
    assert g.beam_log == [] and not g.detector.requests and ros.spin_until(g.safe)



def test_a_detector_node_that_is_not_active_gets_no_beam(ros, tmp_path):
    from rclpy.lifecycle import LifecycleNode

    g = Graph(ros, tmp_path)
    g.detector.srv.close()
    idle = ros.add(LifecycleNode("other_pcd", context=ros.context))  # answers, but unconfigured
    idle.create_service(Trigger, "pcd/expose", lambda q, r: r)
    assert ros.spin_until(lambda: g.orch.expose.service_is_ready() and g.orch.call_detector_check() is not None)
    g.start()
    g.wait_end()
    assert g.orch.state == "aborted" and "/other_pcd is unconfigured, not active" in g.orch.message, g.orch.message
    assert g.beam_log == []
