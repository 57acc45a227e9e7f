"""nodes.common: the nodes' topic QoS profiles come from one place, the topic contract (bag.format.offered_qos)."""

from __future__ import annotations

import importlib

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
