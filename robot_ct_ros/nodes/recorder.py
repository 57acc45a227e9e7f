"""recorder: records the scan topics into a scan bag (rosbag2 MCAP, docs/bag-format.md).

Subscribes (serialized, written unchanged)
  /ct/scan_info (std_msgs/String), /ct/flat_field, /ct/dead_pixels (sensor_msgs/Image): transient-local
  /ct/projection, /ct/projection_rejected (sensor_msgs/Image), /ct/geometry, /ct/geometry_corrected,
              /ct/geometry_true (geometry_msgs/PoseArray): reliable
  /source_arm/tool_pose, /detector_arm/tool_pose (geometry_msgs/PoseStamped), /diagnostics
  (diagnostic_msgs/DiagnosticArray): best effort (matches any publisher); /source/beam_on (std_msgs/Bool)
Services
  ~/stop (std_srvs/Trigger): close the current bag (the answer names it)
Parameters
  output_dir (bags go to <output_dir>/<bag_prefix>_<UTC time>), bag_prefix, record_arm_topics,
  flush_period_s (s: how often arm and diagnostics messages are pushed to disk).

A bag opens on the first /ct/scan_info, /ct/projection or /ct/geometry message and starts
with the latest scan_info, flat field and dead-pixel map received; a different scan_info after
frames closes it and opens the next. Every frame and geometry is
flushed to disk as it arrives, so a killed recorder leaves a recoverable bag; shutdown
(SIGINT/SIGTERM) and ~/stop close the bag cleanly.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from robot_ct_ros.bag import ScanBagWriter
from robot_ct_ros.bag import format as fmt
from robot_ct_ros.nodes.common import declare_settings, run_settings_node, writable_dir
from robot_ct_ros.parameters import setting, validate

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
STREAM = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
ANY = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)

SCAN_TOPICS = (fmt.TOPIC_SCAN_INFO, fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY, fmt.TOPIC_FLAT_FIELD,
               fmt.TOPIC_DEAD_PIXELS, fmt.TOPIC_GEOMETRY_CORRECTED, fmt.TOPIC_GEOMETRY_TRUE,
               fmt.TOPIC_PROJECTION_REJECTED)
ARM_TOPICS = (fmt.TOPIC_SOURCE_POSE, fmt.TOPIC_DETECTOR_POSE, fmt.TOPIC_DIAGNOSTICS, fmt.TOPIC_BEAM_ON)
OPENS_BAG = (fmt.TOPIC_SCAN_INFO, fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY)
FLUSH_AT_ONCE = (fmt.TOPIC_PROJECTION, fmt.TOPIC_GEOMETRY, fmt.TOPIC_GEOMETRY_CORRECTED,
                 fmt.TOPIC_PROJECTION_REJECTED) + fmt.LATCHED_TOPICS


def message_class(msgtype: str):
    """The rclpy message class of ``pkg/msg/Name``."""
    pkg, _, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def qos_for(topic: str) -> QoSProfile:
    if topic in fmt.LATCHED_TOPICS or topic == fmt.TOPIC_BEAM_ON:
        return LATCHED
    if topic in SCAN_TOPICS:
        return STREAM
    return ANY


@dataclass(frozen=True)
class RecorderSettings:
    """Where and how scans are recorded (the recorder's parameters)."""

    output_dir: str = setting("bags", "each scan bag goes to <output_dir>/<bag_prefix>_<UTC time>")
    bag_prefix: str = setting("scan", "name prefix of each bag")
    record_arm_topics: bool = setting(True, "also record the tool poses, /diagnostics and source/beam_on")
    flush_period_s: float = setting(1.0, "other topics are flushed to disk at this period (frames and geometries at "
                                         "once); 0: only at close", unit="s", minimum=0.0)

    def __post_init__(self):
        validate(self)
        if not self.bag_prefix or "/" in self.bag_prefix:
            raise ValueError(f"bag_prefix must be a plain name, got {self.bag_prefix!r}")


class RecorderNode(Node):
    def __init__(self, **kwargs):
        super().__init__("recorder", **kwargs)
        self.settings = st = declare_settings(self, RecorderSettings)
        self.output_dir = writable_dir(st.output_dir, "output_dir").resolve()  # refused at start, not at the scan
        self.bag_prefix = st.bag_prefix
        record_arm, flush_period = st.record_arm_topics, st.flush_period_s
        self.writer: ScanBagWriter | None = None
        self.bag_path: Path | None = None
        self.closed_bags: list[Path] = []
        self._latched: dict[str, tuple[str, bytes]] = {}
        topics = SCAN_TOPICS + (ARM_TOPICS if record_arm else ())
        for topic in topics:
            msgtype = fmt.TOPIC_TYPES[topic]
            self.create_subscription(message_class(msgtype), fmt.node_topic(topic),  # bag: contract name
                                     lambda data, t=topic, m=msgtype: self._on_message(t, m, data),
                                     qos_for(topic), raw=True)
        self.create_service(Trigger, "~/stop", self._on_stop)
        if flush_period > 0:
            self.create_timer(flush_period, self._flush)
        self.get_logger().info(f"recording {len(topics)} topics into {self.output_dir}/")

    # ----------------------------------------------------------------- bag handling
    def _new_bag_path(self) -> Path:
        stamp = time.strftime("%Y%m%d_%H%M%S", time.gmtime())
        path = self.output_dir / f"{self.bag_prefix}_{stamp}"
        k = 1
        while path.exists():
            path = self.output_dir / f"{self.bag_prefix}_{stamp}_{k}"
            k += 1
        return path

    def _open_bag(self) -> None:
        self.output_dir.mkdir(parents=True, exist_ok=True)  # checked at start; made again if removed since
        self.bag_path = self._new_bag_path()
        self.writer = ScanBagWriter(self.bag_path, None, flush_every_frame=False).open()
        now = self.get_clock().now().nanoseconds
        for topic in fmt.LATCHED_TOPICS:  # scan_info first
            if topic in self._latched:
                msgtype, data = self._latched[topic]
                self.writer.write_raw(topic, msgtype, data, now)
        self.writer.flush()
        self.get_logger().info(f"recording scan bag {self.bag_path}")

    def close_bag(self) -> Path | None:
        """Close the current bag (summary + metadata.yaml); returns its path."""
        if self.writer is None:
            return None
        path, counts = self.bag_path, dict(self.writer.counts)
        self.writer.close()
        self.writer = None
        self.bag_path = None
        self.closed_bags.append(path)
        self.get_logger().info(f"closed {path}: {counts.get(fmt.TOPIC_PROJECTION, 0)} frames, "
                               f"{counts.get(fmt.TOPIC_GEOMETRY, 0)} geometries")
        return path

    def _on_message(self, topic: str, msgtype: str, data: bytes) -> None:
        if (topic == fmt.TOPIC_SCAN_INFO and self.writer is not None and self.writer.counts.get(fmt.TOPIC_PROJECTION)
                and self._latched.get(topic, (None, None))[1] != bytes(data)):
            self.close_bag()  # a new scan starts a new bag
        if topic in fmt.LATCHED_TOPICS:
            self._latched[topic] = (msgtype, bytes(data))
        if self.writer is None:
            if topic not in OPENS_BAG:
                return
            self._open_bag()
            if topic in fmt.LATCHED_TOPICS:
                return  # written by _open_bag
        self.writer.write_raw(topic, msgtype, bytes(data), self.get_clock().now().nanoseconds)
        if topic in FLUSH_AT_ONCE:
            self.writer.flush()

    def _flush(self) -> None:
        if self.writer is not None:
            self.writer.flush()

    def _on_stop(self, request, response):
        path = self.close_bag()
        response.success = path is not None
        response.message = str(path) if path is not None else "no bag open"
        return response

    def destroy_node(self):
        self.close_bag()
        return super().destroy_node()


def main(argv=None) -> int:
    return run_settings_node(RecorderNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
