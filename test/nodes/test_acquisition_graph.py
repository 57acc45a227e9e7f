"""The acquisition graph in-process: source_control, two simulated arm drivers (with coordination
errors), pcd_grabber (tiny simulated detector), geometry_publisher and scan_orchestrator on one
SingleThreadedExecutor. A small scan end to end, and the faults that must abort it safely."""

import json
from pathlib import Path

import numpy as np
import yaml
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from geometry_msgs.msg import PoseArray
from sensor_msgs.msg import Image
from std_msgs.msg import Bool, String
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag import read_raw_messages, read_scan
from robot_ct_ros.ct.hand_eye import HandEye, geometry_from_tool_poses, pose_matrix
from robot_ct_ros.nodes.arm_driver import ArmDriverNode
from robot_ct_ros.nodes.geometry_publisher import GeometryPublisherNode
from robot_ct_ros.nodes.hand_eye_params import stamp_to_ns
from robot_ct_ros.nodes.pcd_grabber import PcdGrabberNode
from robot_ct_ros.nodes.recon_service import ReconServiceNode
from robot_ct_ros.nodes.recorder import RecorderNode
from robot_ct_ros.hardware.scan_protocol import ScanProtocol
from robot_ct_ros.nodes.scan_orchestrator import ScanOrchestratorNode
from robot_ct_ros.nodes.source_control import SourceControlNode

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
STREAM = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
CONFIG = Path(__file__).resolve().parents[2] / "config"
DETECTOR = {"n_rows": 24, "n_cols": 32, "binning": 2, "raw_pixel_m": 0.0005}
PROTOCOL = {"name": "graph_test", "n_views": 12, "roi_center_m": [0.4, 0.0, 0.3], "fov_diameter_m": 0.01,
            "detector": DETECTOR, "exposure_s": 0.03, "settle_s": 0.01, "move_timeout_s": 5.0,
            "exposure_timeout_s": 2.0}
ARM_ERRORS = {"sim_sigma_mm": 0.3, "sim_sigma_deg": 0.05}


def _params(d):
    return [Parameter(k, value=v) for k, v in d.items()]


def _ur_to_mm(pose):
    return pose_matrix(np.asarray(pose[:3]) * 1e3, pose[3:6])


class AcquisitionGraph:
    """All acquisition nodes plus a probe recording what matters for the checks."""

    def __init__(self, ros, tmp_path, grabber=None, arms=None):
        self.ros = ros
        path = tmp_path / "protocol.yaml"
        # the protocol's exposure is the detector's (the orchestrator switches the beam off after the protocol's)
        protocol = dict(PROTOCOL, exposure_s=(grabber or {}).get("exposure_s", PROTOCOL["exposure_s"]))
        path.write_text(yaml.safe_dump({"scan_protocol": protocol}))
        self.protocol = ScanProtocol.from_yaml(path)
        # the shipped hand-eye file, as a launch would pass it
        he_args = ["--ros-args", "--params-file", str(CONFIG / "hand_eye.yaml")]
        self.source = ros.add(SourceControlNode(context=ros.context))
        arm_params = arms or {}
        self.arms = {r: ros.add(ArmDriverNode(f"{r}_arm_driver", context=ros.context, parameter_overrides=_params(
            dict(role=r, sim_seed=seed, **ARM_ERRORS, **arm_params.get(r, {})))))
            for r, seed in (("source", 1), ("detector", 2))}
        grabber_params = dict(DETECTOR, sim_phantom="mouse", sim_phantom_center_m=PROTOCOL["roi_center_m"],
                              sim_voxel_size_m=0.001, sim_photons_per_pixel=20000.0, sim_chip_size_px=20,
                              sim_chip_gap_px=1, exposure_s=PROTOCOL["exposure_s"], exposure_timeout_s=1.0)
        grabber_params.update(grabber or {})
        self.grabber = ros.add(PcdGrabberNode(context=ros.context, cli_args=he_args,
                                              parameter_overrides=_params(grabber_params)))
        self.geometry = ros.add(GeometryPublisherNode(context=ros.context, cli_args=he_args))
        self.orch = ros.add(ScanOrchestratorNode(context=ros.context, cli_args=he_args,
                                                 parameter_overrides=_params({"protocol_file": str(path)})))
        self.hand_eye = HandEye()
        assert self.orch.hand_eye == self.hand_eye == self.grabber.hand_eye

        # instrumentation: beam transitions at the source, with the arms' state at that moment,
        # and every acquisition of the detector, with the arms' true and measured poses
        self.beam_log = []
        src = self.source.interlock.source
        set_beam = src.set_beam

        def logged_set_beam(on, now_s):
            if bool(on) != src.beam_on:
                self.beam_log.append({"on": bool(on), "t_ns": int(now_s * 1e9), "arms": self._arm_state()})
            set_beam(on, now_s)
        src.set_beam = logged_set_beam
        self.acquisitions = []
        det = self.grabber.detector  # None until the grabber is configured (autostart false)
        if det is not None:
            acquire = det.acquire

            def logged_acquire(exposure_s):
                frame = acquire(exposure_s)
                self.acquisitions.append({"start": frame.start_ns, "end": frame.end_ns, "stamp": frame.stamp_ns,
                                          "arms": self._arm_state(), "fraction": frame.info["beam_fraction"]})
                return frame
            det.acquire = logged_acquire

        probe = self.probe = ros.node("probe")
        self.frames, self.geoms, self.true_geoms, self.status = {}, {}, {}, []
        self.subs = [
            probe.create_subscription(Image, fmt.TOPIC_PROJECTION,
                                      lambda m: self.frames.__setitem__(stamp_to_ns(m.header.stamp), m), STREAM),
            probe.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY,
                                      lambda m: self.geoms.__setitem__(stamp_to_ns(m.header.stamp), m), STREAM),
            probe.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY_TRUE,
                                      lambda m: self.true_geoms.__setitem__(stamp_to_ns(m.header.stamp), m), STREAM),
            probe.create_subscription(String, "scan/status", lambda m: self.status.append(json.loads(m.data)), 10)]
        self.start_client = probe.create_client(Trigger, "scan/start")

    def _arm_state(self):
        out = {}
        for r, node in self.arms.items():
            arm = node.arm
            out[r] = {"in_position": node.in_position(), "moves": None if arm is None else arm.moves_done,
                      "true": None if arm is None else arm.true_tcp_pose(),
                      "measured": None if arm is None else arm._commanded.copy()}
        return out

    def start(self):
        ros = self.ros
        assert ros.spin_until(lambda: all(a.lifecycle_state == "active" for a in self.arms.values()))
        assert ros.spin_until(lambda: self.orch.start()[0] if self._ready() else False, timeout_s=15.0), \
            self.orch.start()[1]

    def _ready(self):
        o = self.orch
        return (o.set_beam.service_is_ready() and o.expose.service_is_ready()
                and all(np.isfinite(t) for t in o.scan.arm_pose_t.values())
                and all(np.isfinite(t) for t in o.scan.arm_in_position_t.values()))

    def wait_end(self, timeout_s=60.0):
        assert self.ros.spin_until(lambda: self.orch.state in ("done", "aborted"), timeout_s=timeout_s), self.orch.state

    def safe(self):
        return not self.source.interlock.beam_on and not self.source.interlock.inputs.scan_armed

    def beam_intervals(self):
        """[(on_ns, off_ns, arms at on, arms at off)] from the source's beam transitions."""
        out, on = [], None
        for e in self.beam_log:
            if e["on"]:
                on = e
            elif on is not None:
                out.append((on["t_ns"], e["t_ns"], on["arms"], e["arms"]))
                on = None
        assert on is None, "beam left on"
        return out


def test_small_scan_end_to_end(ros, tmp_path):
    g = AcquisitionGraph(ros, tmp_path)
    g.start()
    g.wait_end()
    n = PROTOCOL["n_views"]
    assert g.orch.state == "done", g.orch.message
    assert g.orch.frames == n and g.grabber.frames_published == n
    assert ros.spin_until(lambda: len(g.frames) == n and len(g.geoms) == n and len(g.true_geoms) == n)
    assert ros.spin_until(g.safe)

    # every frame has exactly one geometry, with the same stamp
    assert set(g.frames) == set(g.geoms) == set(g.true_geoms)
    assert "with geometry" in g.orch.message and f"{n} with geometry" in g.orch.message

    # the beam was on once per exposure, only with both arms in position and not moving,
    # and every exposure lay inside a beam-on interval
    intervals = g.beam_intervals()
    assert len(intervals) == n and len(g.acquisitions) == n
    for on_ns, off_ns, arms_on, arms_off in intervals:
        for r in ("source", "detector"):
            assert arms_on[r]["in_position"] and arms_off[r]["in_position"]
            assert arms_on[r]["moves"] == arms_off[r]["moves"]  # no move while the beam was on
    for acq in g.acquisitions:
        assert any(on <= acq["start"] and acq["end"] <= off for on, off, _, _ in intervals)
        assert acq["fraction"] == 1.0

    # nominal geometry = the protocol's plan (measured = commanded poses); true geometry = the arms'
    # true poses through the hand-eye; they differ by the arms' coordination errors
    plan = g.protocol.geometry()
    stamps = sorted(g.frames)
    for view, (stamp, acq) in enumerate(zip(stamps, sorted(g.acquisitions, key=lambda a: a["stamp"]))):
        assert acq["stamp"] == stamp
        s, d, u, v = fmt.view_from_pose_array(g.geoms[stamp])
        np.testing.assert_allclose(s, plan.source_mm[view], atol=1e-5)
        np.testing.assert_allclose(d, plan.detector_mm[view], atol=1e-5)
        np.testing.assert_allclose(u, plan.u[view], atol=1e-8)
        arms = acq["arms"]
        true = geometry_from_tool_poses(_ur_to_mm(arms["source"]["true"]), _ur_to_mm(arms["detector"]["true"]),
                                        g.hand_eye, 24, 32, 1.0)
        st, dt, ut, vt = fmt.view_from_pose_array(g.true_geoms[stamp])
        np.testing.assert_allclose(st, true.source_mm[0], atol=1e-5)
        np.testing.assert_allclose(dt, true.detector_mm[0], atol=1e-5)
        np.testing.assert_allclose(vt, true.v[0], atol=1e-8)
        err_s, err_d = np.linalg.norm(st - s), np.linalg.norm(dt - d)
        assert 1e-3 < err_s < 5.0 and 1e-3 < err_d < 5.0  # 0.3 mm/axis + 0.05 deg at 80-120 mm: about 0.5 mm

    # frames are the detector's: 24 x 32 counts with the flat field's order of magnitude
    counts = fmt.array_from_image(g.frames[stamps[0]])
    assert counts.shape == (24, 32) and counts.max() > 1000
    assert ros.spin_until(lambda: g.status and g.status[-1]["state"] == "done")


def test_detector_timeout_aborts_with_beam_off(ros, tmp_path):
    g = AcquisitionGraph(ros, tmp_path, grabber={"sim_fail": "timeout", "exposure_timeout_s": 0.3})
    g.start()
    g.wait_end()
    assert g.orch.state == "aborted" and "detector timeout" in g.orch.message
    assert ros.spin_until(g.safe)
    assert g.orch.frames == 0 and not g.frames
    assert len(g.beam_intervals()) == 1  # the one exposure that never came back


def test_estop_mid_scan_cuts_the_beam_and_aborts(ros, tmp_path):
    g = AcquisitionGraph(ros, tmp_path, grabber={"exposure_s": 0.2, "sim_readout_s": 0.0})
    estop = g.probe.create_publisher(Bool, "estop", 10)
    assert ros.wait_for_subscribers(estop, count=2)  # source_control and the orchestrator
    g.start()
    assert ros.spin_until(lambda: g.orch.frames >= 2 and g.orch.state == "exposing" and g.source.interlock.beam_on,
                          timeout_s=30)
    estop.publish(Bool(data=True))
    assert ros.spin_until(lambda: not g.source.interlock.beam_on, timeout_s=2.0)  # at once
    g.wait_end()
    assert g.orch.state == "aborted"
    assert "e-stop" in g.orch.message or "beam lost" in g.orch.message
    assert ros.spin_until(g.safe)
    assert g.source.interlock.inputs.estop_latched
    assert g.orch.frames == 2


def test_arm_failure_mid_scan_aborts_and_keeps_frames(ros, tmp_path):
    g = AcquisitionGraph(ros, tmp_path, arms={"detector": {"sim_fail_after_moves": 5}})
    g.start()
    g.wait_end()
    assert g.orch.state == "aborted", g.orch.message
    assert "detector arm" in g.orch.message
    assert ros.spin_until(g.safe)
    # five moves succeeded: five frames, each with its geometry, stay published
    assert g.orch.frames == 5
    assert ros.spin_until(lambda: len(g.frames) == 5 and len(g.geoms) == 5)
    assert set(g.frames) == set(g.geoms)
    assert ros.spin_until(lambda: g.status and g.status[-1]["state"] == "aborted")
    assert g.status[-1]["frames"] == 5


def test_beam_drop_mid_exposure_rejects_that_frame(ros, tmp_path, monkeypatch):
    """The e-stop cuts the beam during the third exposure: the scan aborts, that frame goes to
    /ct/projection_rejected only, and neither the recorded bag nor recon_service's collection uses it;
    the two earlier frames are kept, paired and readable."""
    g = AcquisitionGraph(ros, tmp_path, grabber={"exposure_s": 0.4})
    rec = ros.add(RecorderNode(context=ros.context, parameter_overrides=_params(
        {"output_dir": str(tmp_path / "bags"), "record_arm_topics": False})))
    recon = ros.add(ReconServiceNode(context=ros.context, parameter_overrides=_params(
        {"output_dir": str(tmp_path / "recon"), "auto_run": False, "evaluate_truth": False})))
    rejected = []
    g.subs.append(g.probe.create_subscription(Image, fmt.TOPIC_PROJECTION_REJECTED,
                                              lambda m: rejected.append(stamp_to_ns(m.header.stamp)), STREAM))
    estop = g.probe.create_publisher(Bool, "estop", 10)
    assert ros.wait_for_subscribers(estop, count=2)
    g.start()
    assert ros.spin_until(lambda: g.orch.frames == 2 and g.grabber.exposures.pending is not None, timeout_s=30)
    assert g.source.interlock.beam_on
    estop.publish(Bool(data=True))
    g.wait_end()
    assert g.orch.state == "aborted" and g.orch.frames == 2
    assert ros.spin_until(lambda: rejected and g.grabber.frames_rejected == 1)  # the exposure ends meanwhile
    assert ros.spin_until(g.safe)
    (bad,) = rejected
    assert g.acquisitions[-1]["stamp"] == bad and 0.0 <= g.acquisitions[-1]["fraction"] < 1.0
    assert "beam interrupted" in g.grabber.last_error

    # on the topics: two frames with their geometry; the rejected one has neither
    assert ros.spin_until(lambda: len(g.frames) == 2 and len(g.geoms) == 2)
    kept = sorted(g.frames)
    assert bad not in g.frames and bad not in g.geoms and bad not in g.true_geoms and set(g.geoms) == set(kept)

    # recon_service collected the two frames only
    assert ros.spin_until(lambda: recon.n_paired == 2)
    assert bad not in recon.scan.per_frame[fmt.TOPIC_PROJECTION]
    snapshot, n = recon.scan.write_bag(tmp_path / "snapshot")
    monkeypatch.setattr("robot_ct_ros.bag.reader.MIN_VIEWS", 1)  # two views: pairing, not a reconstruction
    assert n == 2 and read_scan(snapshot).stamps_ns.tolist() == kept

    # the recorded bag keeps the rejected frame on its own topic; the reader never uses it
    assert ros.spin_until(lambda: rec.writer is not None
                          and rec.writer.counts.get(fmt.TOPIC_PROJECTION_REJECTED, 0) == 1
                          and rec.writer.counts.get(fmt.TOPIC_GEOMETRY, 0) == 2)
    bag = rec.close_bag()
    assert read_raw_messages(bag).topics()[fmt.TOPIC_PROJECTION][1] == 2
    scan = read_scan(bag)
    assert scan.n_views == 2 and scan.stamps_ns.tolist() == kept
    assert any(fmt.TOPIC_PROJECTION_REJECTED in w and "not used" in w for w in scan.warnings)


def test_start_refuses_an_inactive_detector(ros, tmp_path):
    """A configured but inactive pcd_grabber (lifecycle) is refused at scan start, from its
    /diagnostics report, instead of failing at the first exposure; once active the scan starts."""
    g = AcquisitionGraph(ros, tmp_path, grabber={"autostart": False})
    assert g.grabber.lifecycle_state == "unconfigured"
    g.grabber.trigger_configure()
    assert g.grabber.lifecycle_state == "inactive"
    assert ros.spin_until(lambda: g._ready() and g.orch.scan.device_state.get("detector", (0, ""))[1] == "inactive",
                          timeout_s=10.0)
    ok, message = g.orch.start()
    assert not ok and "detector is inactive" in message, message
    assert g.orch.state == "idle" and g.safe()
    g.grabber.trigger_activate()
    assert ros.spin_until(lambda: g.orch.scan.device_state["detector"][1] == "active", timeout_s=10.0)
    g.start()
    assert g.orch.running
    g.orch.abort("test over")
    assert ros.spin_until(g.safe)
