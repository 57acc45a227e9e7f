"""nodes.common: the nodes' topic QoS profiles come from one place, the topic contract (bag.format.offered_qos)."""

from __future__ import annotations

import importlib

import numpy as np

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from robot_ct_ros.bag import format as fmt

NODES = ("arm_driver", "geometry_publisher", "pcd_grabber", "recon_service", "recorder", "replay", "scan_orchestrator",
         "source_control")


def test_the_nodes_qos_profiles_are_the_contracts_and_unchanged():
    """Review I8: each node restated the contract's profiles; they are now common's, derived from offered_qos, and
    equal to what the nodes used before (no behaviour changes)."""
    from robot_ct_ros.nodes import common

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    stream = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
    assert common.LATCHED == latched and common.STREAM == stream
    for topic in fmt.LATCHED_TOPICS + fmt.STATE_TOPICS:
        assert common.topic_qos(topic) == latched, topic
    for topic in (fmt.TOPIC_PROJECTION, fmt.TOPIC_PROJECTION_REJECTED, fmt.TOPIC_GEOMETRY, fmt.TOPIC_GEOMETRY_TRUE,
                  fmt.TOPIC_GEOMETRY_CORRECTED):
        assert common.topic_qos(topic) == stream, topic
    for name in NODES:
        module = importlib.import_module(f"robot_ct_ros.nodes.{name}")
        for profile in ("LATCHED", "STREAM"):
            assert getattr(module, profile, getattr(common, profile)) is getattr(common, profile), (name, profile)
        assert not hasattr(module, "TOPIC_DIAGNOSTICS"), name  # the contract's fmt.TOPIC_DIAGNOSTICS
    recorder, recon = importlib.import_module("robot_ct_ros.nodes.recorder"), importlib.import_module(
        "robot_ct_ros.nodes.recon_service")
    assert recorder.STATE == QoSProfile(depth=100, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                        reliability=ReliabilityPolicy.RELIABLE)
    assert recon.STATUS == QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                                      reliability=ReliabilityPolicy.RELIABLE)


def test_every_parameter_of_every_node_comes_back_in_one_get_parameters_call(ros, tmp_path):
    """Outside test 27 A #2: rclpy answers a GetParameters request that names an unset parameter (declared by
    type only) with no values at all, so ``ros2 param dump`` (one request for every name) came back empty for
    pcd_grabber, geometry_publisher and scan_orchestrator. Optional parameters now hold an empty array (unset)."""
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import GetParameters, ListParameters
    from rclpy.parameter import Parameter

    from robot_ct_ros.bag import write_scan
    from robot_ct_ros.ct.trajectory import robotic_roi_scan

    geom = robotic_roi_scan(n_views=4, n_rows=4, n_cols=6, fov_diameter_mm=0.3)
    bag = write_scan(tmp_path / "scan", np.ones((4, 4, 6), np.float32), geom, projection_units="line_integral")
    overrides = {"pcd_grabber": {"autostart": False}, "recon_service": {"output_dir": str(tmp_path / "recon")},
                 "recorder": {"output_dir": str(tmp_path / "bags")},
                 "replay": {"bag_path": str(bag), "rate_hz": 0.0, "output_dir": str(tmp_path / "replay")}}
    probe = ros.node("probe")
    for name in NODES:
        module = importlib.import_module(f"robot_ct_ros.nodes.{name}")
        cls = next(c for c in vars(module).values() if isinstance(c, type) and c.__module__ == module.__name__
                   and c.__name__.endswith("Node"))
        ros.add(cls(context=ros.context, parameter_overrides=[Parameter(k, value=v)
                                                              for k, v in overrides.get(name, {}).items()]))
        names = ros.call(probe.create_client(ListParameters, f"/{name}/list_parameters"),
                         ListParameters.Request()).result.names
        got = ros.call(probe.create_client(GetParameters, f"/{name}/get_parameters"),
                       GetParameters.Request(names=names))
        assert len(got.values) == len(names), (name, len(got.values), len(names))
        unset = [n for n, v in zip(names, got.values) if v.type == ParameterType.PARAMETER_NOT_SET]
        assert not unset, (name, unset)


def test_on_and_off_set_a_string_choice_though_yaml_reads_them_as_booleans(ros):
    """An outside check: `-p exterior:=off` and `-p fov_support:=on` were refused as booleans (YAML reads off and on
    so); they set the choice they name now. A boolean where no such choice exists is still refused."""
    import pytest
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    from robot_ct_ros.ct.calibration import CalibrationSettings
    from robot_ct_ros.nodes.common import declare_settings

    node = ros.add(Node("choices", context=ros.context, parameter_overrides=[
        Parameter("exterior", value=False), Parameter("fov_support", value=True)]))
    settings = declare_settings(node, CalibrationSettings)
    assert (settings.exterior, settings.fov_support) == ("off", "on")
    other = ros.add(Node("choices_bad", context=ros.context, parameter_overrides=[Parameter("method", value=True)]))
    with pytest.raises(ValueError, match="method"):
        declare_settings(other, CalibrationSettings)
