"""One namespace moves a whole scanner: every name a node uses is relative (but /diagnostics), and the
bag's recorded topic names stay the contract's (/ct/projection ...) whatever the namespace."""

from pathlib import Path

import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag import read_raw_messages, scan_info_for
from robot_ct_ros.ct.trajectory import robotic_roi_scan

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
GLOBAL = ("/diagnostics", "/rosout", "/parameter_events")


def _nodes(ros, tmp_path, ns):
    from robot_ct_ros.nodes.arm_driver import ArmDriverNode
    from robot_ct_ros.nodes.geometry_publisher import GeometryPublisherNode
    from robot_ct_ros.nodes.pcd_grabber import PcdGrabberNode
    from robot_ct_ros.nodes.recon_service import ReconServiceNode
    from robot_ct_ros.nodes.recorder import RecorderNode
    from robot_ct_ros.nodes.scan_orchestrator import ScanOrchestratorNode
    from robot_ct_ros.nodes.source_control import SourceControlNode

    def params(**kw):
        return [Parameter(k, value=v) for k, v in kw.items()]
    kw = dict(context=ros.context, namespace=ns)
    return [ArmDriverNode(**kw), SourceControlNode(**kw), GeometryPublisherNode(**kw), ScanOrchestratorNode(**kw),
            PcdGrabberNode(**kw, parameter_overrides=params(autostart=False)),
            ReconServiceNode(**kw, parameter_overrides=params(output_dir=str(tmp_path / "recon"))),
            RecorderNode(**kw, parameter_overrides=params(output_dir=str(tmp_path / "bags")))]


def test_every_name_of_every_node_follows_its_namespace(ros, tmp_path):
    for node in _nodes(ros, tmp_path, "/scanner_a"):
        names = [p.topic_name for p in node.publishers] + [s.topic_name for s in node.subscriptions] + \
                [node.resolve_service_name(s.srv_name) for s in [*node.services, *node.clients]]
        outside = [n for n in names if not n.startswith("/scanner_a/") and n not in GLOBAL]
        assert not outside, (node.get_name(), outside)
        assert any(n.startswith("/scanner_a/ct/") or "/scanner_a/" in n for n in names)
        node.destroy_node()


def test_a_namespaced_recorder_records_its_scanner_under_the_contract_names(ros, tmp_path):
    from robot_ct_ros.nodes.recorder import STREAM, RecorderNode

    rec = ros.add(RecorderNode(context=ros.context, namespace="/scanner_a",
                               parameter_overrides=[Parameter("output_dir", value=str(tmp_path))]))
    probe = ros.node("probe")
    geom = robotic_roi_scan(n_views=2, n_rows=4, n_cols=6, fov_diameter_mm=0.3)
    pubs = {}
    for ns in ("scanner_a", "scanner_b"):
        pubs[ns] = (probe.create_publisher(String, f"/{ns}/ct/scan_info", LATCHED),
                    probe.create_publisher(Image, f"/{ns}/ct/projection", STREAM))
    assert ros.wait_for_subscribers(pubs["scanner_a"][0]) and ros.wait_for_subscribers(pubs["scanner_a"][1])
    for ns, value in (("scanner_b", 7.0), ("scanner_a", 3.0)):  # another scanner in the same domain
        info, proj = pubs[ns]
        info.publish(String(data=fmt.scan_info_to_msg(scan_info_for(geom)).data))
        msg = Image(height=4, width=6, encoding="32FC1", step=24,
                    data=np.full((4, 6), value, np.float32).tobytes())
        proj.publish(msg)
    assert ros.spin_until(lambda: rec.writer is not None and rec.writer.counts.get(fmt.TOPIC_PROJECTION, 0) == 1)
    ros.spin_for(0.3)
    stop = probe.create_client(Trigger, "/scanner_a/recorder/stop")
    bag = Path(ros.call(stop, Trigger.Request()).message)
    raw = read_raw_messages(bag)
    assert {m.topic for m in raw.messages} == {fmt.TOPIC_SCAN_INFO, fmt.TOPIC_PROJECTION}
    frames = [fmt.array_from_image(fmt.deserialize(m.data, fmt.IMAGE)) for m in raw.messages
              if m.topic == fmt.TOPIC_PROJECTION]
    assert len(frames) == 1 and np.all(frames[0] == 3.0)


@pytest.mark.parametrize("name, ns, ours", [
    ("/scanner_a/source_arm_driver: source arm", "/scanner_a", True),
    ("/scanner_b/source_arm_driver: source arm", "/scanner_a", False),
    ("/source_arm_driver: source arm", "/", True),
    ("/scanner_a/source_arm_driver: source arm", "/", False),
    ("some other tool", "/scanner_a", True)])
def test_the_orchestrator_listens_to_its_own_scanners_diagnostics_only(name, ns, ours):
    from robot_ct_ros.nodes.scan_orchestrator import same_namespace

    assert same_namespace(name, ns) is ours
