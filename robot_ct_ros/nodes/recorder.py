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

A bag opens with the first /ct/scan_info (frames and geometries that come just before it, up to
EARLY_FRAMES, follow it into the bag, and the scan_info, flat field and dead-pixel map take the
earliest of their log times, so that by log time too the bag starts with them) and starts with the
latest scan_info, flat field and dead-pixel map received (a flat field or map of another detector
shape than the scan_info's, an earlier scan's, is left out); a different scan_info after frames,
or the bag's first frame stamp again (the same scan replayed), closes it and opens the next.
Every frame and geometry is flushed to disk as it arrives, so a killed recorder leaves a
recoverable bag; shutdown (SIGINT/SIGTERM) and ~/stop close the bag cleanly. A write error (a
full disk, the bag folder removed) gives that bag up with an ERROR in the log and on /diagnostics
(1 Hz; also "recording", "waiting for a scan"), and the node stays up for the next scan.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from pathlib import Path

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from robot_ct_ros.bag import ScanBagWriter
from robot_ct_ros.bag import format as fmt
from robot_ct_ros.nodes.common import (LATCHED, STREAM, declare_settings, publish_diagnostic, run_settings_node,
                                       topic_qos, writable_dir)
from robot_ct_ros.parameters import setting, validate

ANY = QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT)  # any other topic: matches every publisher
STATE = topic_qos(fmt.TOPIC_BEAM_ON, depth=100)  # the state topics, every change kept
"""A state topic's subscription: transient-local like its publisher, but every change kept (a depth of 1 dropped the
first of a beam off and on that arrive in one callback round, as a replay sends them)."""

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
    if topic in fmt.STATE_TOPICS:
        return STATE
    if topic in fmt.LATCHED_TOPICS:
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
        self._early: list = []  # frames and geometries that came before any scan_info
        self._first_stamp = None  # the open bag's first frame stamp: seen again, a new scan starts
        self._gave_up = False  # a write error gave the scan's bag up: drop its frames until the next scan_info
        self.failures, self.last_error = 0, ""
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.node_topic(fmt.TOPIC_DIAGNOSTICS), 10)
        self.create_timer(1.0, self._publish_diagnostics)
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
        self._first_stamp = None
        # the latched messages go first in the file and, by log time, before the frames that came just before the
        # scan_info (readers and `ros2 bag play` go by log time): no later than the earliest of those
        now = min([self.get_clock().now().nanoseconds] + [early[3] for early in self._early])
        shape = _detector_shape(self._latched.get(fmt.TOPIC_SCAN_INFO, (None, None))[1])
        for topic in fmt.LATCHED_TOPICS:  # scan_info first
            if topic in self._latched:
                msgtype, data = self._latched[topic]
                image_shape = None if topic == fmt.TOPIC_SCAN_INFO or shape is None else _image_shape(data)
                if image_shape not in (None, shape):
                    # an earlier scan's flat field or dead-pixel map (another detector): it would make the bag
                    # unusable; this scan's own replaces it when it comes
                    self.get_logger().warning(f"{topic} of {image_shape} pixels is an earlier scan's (this "
                                              f"one's detector is {shape}): not recorded")
                    continue
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
        try:
            self._record(topic, msgtype, bytes(data))
        except OSError as exc:  # a full disk, a bag folder removed: say so, give the bag up, stay up for the next
            self._write_failed(exc)

    def _record(self, topic: str, msgtype: str, data: bytes) -> None:
        if (topic == fmt.TOPIC_SCAN_INFO and self.writer is not None and self.writer.counts.get(fmt.TOPIC_PROJECTION)
                and self._latched.get(topic, (None, None))[1] != data):
            self.close_bag()  # a new scan starts a new bag
        if topic == fmt.TOPIC_PROJECTION and self.writer is not None and self._first_stamp == _stamp_of(data):
            self.get_logger().info("the bag's first frame again: a new scan (the same scan replayed?)")
            self.close_bag()
        if topic in fmt.LATCHED_TOPICS:
            self._latched[topic] = (msgtype, data)
            self._gave_up = self._gave_up and topic != fmt.TOPIC_SCAN_INFO
        if self.writer is None:
            if topic not in OPENS_BAG:
                return
            if fmt.TOPIC_SCAN_INFO not in self._latched:  # a frame before its scan's scan_info: keep it a moment
                if not self._gave_up:  # (the rest of a scan whose bag failed is dropped, not carried over)
                    self._early.append((topic, msgtype, data, self.get_clock().now().nanoseconds))
                    del self._early[:-EARLY_FRAMES]
                return
            self._open_bag()
            for early in self._early:  # the frames that came before the scan_info, after it
                self._write(*early)
            self._early.clear()
            if topic in fmt.LATCHED_TOPICS:
                return  # written by _open_bag
        self._write(topic, msgtype, data, self.get_clock().now().nanoseconds)

    def _write(self, topic: str, msgtype: str, data: bytes, time_ns: int) -> None:
        self.writer.write_raw(topic, msgtype, data, time_ns)
        if topic == fmt.TOPIC_PROJECTION and self._first_stamp is None:
            self._first_stamp = _stamp_of(data)
        if topic in FLUSH_AT_ONCE:
            self.writer.flush()

    def _write_failed(self, exc: OSError) -> None:
        self.failures += 1
        self.last_error = f"writing {self.bag_path}: {exc.strerror or exc}"
        self.get_logger().error(f"{self.last_error}; the bag is given up (what was flushed stays readable: robot-ct "
                                "info recovers it), the next scan_info opens a new one")
        writer, self.writer = self.writer, None
        if writer is not None:
            try:
                writer.close()
            except Exception:  # noqa: BLE001 - the disk that failed the write may fail the close too
                pass
            self.closed_bags.append(self.bag_path)
        self.bag_path = None
        self._latched.pop(fmt.TOPIC_SCAN_INFO, None)  # the rest of this scan is not recorded into a new bag
        self._early.clear()
        self._gave_up = True

    def _publish_diagnostics(self) -> None:
        level = "error" if self.failures else "ok"
        message = (f"{self.failures} bag(s) given up on a write error (last: {self.last_error})" if self.failures
                   else (f"recording {self.bag_path}" if self.writer is not None else "waiting for a scan"))
        counts = dict(self.writer.counts) if self.writer is not None else {}
        publish_diagnostic(self, self.diag_pub, level, "recorder", "recorder", message, (
            ("bag", self.bag_path or ""), ("frames", counts.get(fmt.TOPIC_PROJECTION, 0)),
            ("closed_bags", len(self.closed_bags)), ("write_failures", self.failures)))

    def _flush(self) -> None:
        if self.writer is not None:
            try:
                self.writer.flush()
            except OSError as exc:
                self._write_failed(exc)

    def _on_stop(self, request, response):
        try:
            path = self.close_bag()
        except OSError as exc:
            self._write_failed(exc)
            response.success, response.message = False, self.last_error
            return response
        response.success = path is not None
        response.message = str(path) if path is not None else "no bag open"
        return response

    def destroy_node(self):
        try:
            self.close_bag()
        except OSError as exc:
            self._write_failed(exc)
        return super().destroy_node()


EARLY_FRAMES = 8
"""Frames, geometries kept while their scan's /ct/scan_info has not come yet (it may arrive just after them)."""


def _stamp_of(data: bytes) -> int:
    """The header stamp (ns) of a serialized sensor_msgs/Image."""
    return fmt.stamp_to_ns(fmt.deserialize(data, fmt.IMAGE).header.stamp)


def _image_shape(data: bytes):
    try:
        msg = fmt.deserialize(data, fmt.IMAGE)
        return int(msg.height), int(msg.width)
    except Exception:  # noqa: BLE001 - not an image the reader could use either
        return None


def _detector_shape(scan_info: bytes | None):
    """(rows, cols) of a serialized /ct/scan_info, or None."""
    import json

    try:
        info = json.loads(fmt.deserialize(scan_info, fmt.STRING).data)
        return int(info["n_rows"]), int(info["n_cols"])
    except Exception:  # noqa: BLE001 - no scan_info yet, or one the reader will refuse anyway
        return None


def main(argv=None) -> int:
    return run_settings_node(RecorderNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
