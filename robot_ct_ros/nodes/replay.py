"""replay: republishes a scan bag and/or calibrates it offline.

Publishes (the bag's own messages, byte for byte, original header stamps)
  /ct/scan_info, /ct/flat_field, /ct/dead_pixels: transient-local, just before the first frame (once
  /ct/projection has wait_for_subscribers subscribers: nothing is published before; every topic's publisher is
  made at start, so a subscriber that comes during the wait is matched by then)
  /source/beam_on: transient-local (depth 1), as live, in its place among the frames
  /ct/projection, /ct/geometry, ... every other topic of the bag: one frame per 1 / rate_hz seconds (the
  messages recorded between two frames go with the later one); the contract's topics with the contract's QoS,
  the others with the QoS the bag recorded for them (replay_qos: a recorded transient-local /tf_static or
  /robot_description stays transient-local), reliable and volatile when it recorded none; the topics named in
  skip_topics (default /rosout, /parameter_events: the recorded graph's logs and parameter events) are not
  republished
  ~/report (std_msgs/String, transient-local): the JSON report when offline calibration is done
Parameters
  bag_path (bag directory or .mcap, damaged bags are recovered), rate_hz (frames per second;
  <= 0: do not republish), wait_for_subscribers (start republishing once /ct/projection has this
  many subscribers), skip_topics (recorded topics not republished), method ("" = no offline job;
  "none" = reconstruct only; else a calibration method, robot_ct_ros.ct.calibration.registry), the other
  calibration settings (robot_ct_ros.ct.calibration.CalibrationSettings: iterations, prior_sigma_translation_m, ...),
  output_dir (corrected bag, volume .npy/.tif and report.json, as ``robot-ct calibrate``; with a method,
  refused at start if it cannot be written),
  exit_when_done (end the node when all is done, exit status 1 if the job failed; default: spin on).
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.bag.reader import read_raw_messages
from robot_ct_ros.ct.calibration import CalibrationSettings
from robot_ct_ros.bag.format import ScanBagError
from robot_ct_ros.jobs.online import JobGridSettings
from robot_ct_ros.nodes.common import LATCHED, STREAM, declare_settings, run_settings_node, writable_dir
from robot_ct_ros.parameters import setting
from robot_ct_ros.nodes.recorder import message_class



def frame_groups(messages) -> tuple[list, list]:
    """(latched messages, groups): each group ends with one /ct/projection; trailing messages join the last."""
    latched = [m for m in messages if m.topic in fmt.LATCHED_TOPICS]
    groups, current = [], []
    for m in messages:
        if m.topic in fmt.LATCHED_TOPICS:
            continue
        current.append(m)
        if m.topic == fmt.TOPIC_PROJECTION:
            groups.append(current)
            current = []
    if current:
        if groups:
            groups[-1].extend(current)
        else:
            groups.append(current)
    return latched, groups


def replay_qos(topic: str, offered=()) -> QoSProfile:
    """The QoS replay republishes ``topic`` with, given the profiles its publishers offered when it was recorded
    (``offered``: rosbags ``Qos``, one per publisher, :attr:`robot_ct_ros.bag.reader.RawBag.qos`).

    The contract's topics (format.TOPIC_TYPES) keep the contract's profile (LATCHED for the latched and state
    topics, STREAM for the others), which the nodes subscribe with, whatever an older bag recorded. Any other
    topic takes the recorded reliability and durability, as ``ros2 bag play`` does: best-effort when every
    publisher offered best-effort, else reliable; transient-local when every publisher offered transient-local,
    else volatile. A transient-local topic keeps the sum of the publishers' depths (what a late subscriber got from
    them live: three static transform broadcasters of depth 1 give depth 3; keep-all if one kept all); a volatile
    one STREAM's depth. Without a recorded profile: STREAM (reliable, volatile)."""
    from rosbags.interfaces import QosDurability, QosHistory, QosReliability

    if topic in fmt.LATCHED_TOPICS or topic in fmt.STATE_TOPICS:
        return LATCHED
    if topic in fmt.TOPIC_TYPES or not offered:
        return STREAM
    best_effort = all(q.reliability == QosReliability.BEST_EFFORT for q in offered)
    reliability = ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE
    if not all(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered):
        return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=STREAM.depth, reliability=reliability,
                          durability=DurabilityPolicy.VOLATILE)
    if any(q.history == QosHistory.KEEP_ALL for q in offered):
        return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=reliability,
                          durability=DurabilityPolicy.TRANSIENT_LOCAL)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=max(1, sum(max(0, int(q.depth)) for q in offered)),
                      reliability=reliability, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _offline_methods():
    from robot_ct_ros.ct.calibration import method_names

    return ("",) + tuple(method_names())


@dataclass(frozen=True)
class ReplaySettings(JobGridSettings):
    """What replay republishes and computes (its own parameters; the calibration's are CalibrationSettings, the
    grid's and the report's JobGridSettings, as the recon_service's)."""

    bag_path: str = setting("", "scan bag directory or .mcap file (required)")
    rate_hz: float = setting(10.0, "frames per second when republishing; <= 0: do not republish", unit="Hz")
    wait_for_subscribers: int = setting(0, "start republishing once /ct/projection has this many subscribers",
                                        minimum=0)
    skip_topics: tuple = setting(("/rosout", "/parameter_events"), "recorded topics not republished (the recorded "
                                 "graph's log lines and parameter events would reach the live graph's tools); []: none",
                                 item_kind=str)
    method: str = setting("", "offline job after republishing: empty = none; none = reconstruct only; else a "
                              "calibration method", choices=_offline_methods)
    output_dir: str = setting("replay_out", "corrected bag, volume .npy/.tif and report.json")
    exit_when_done: bool = setting(False, "end the node once republishing and the offline job are done (exit 0, or 1 "
                                          "if the job failed); off: keep serving ~/report until SIGINT")

    def __post_init__(self):
        super().__post_init__()
        if not self.bag_path:
            raise ValueError("bag_path is required")


class ReplayNode(Node):
    def __init__(self, **kwargs):
        super().__init__("replay", **kwargs)
        self.replay_settings = rs = declare_settings(self, ReplaySettings)
        self.bag_path, self.rate_hz, self.wait_for_subscribers = rs.bag_path, rs.rate_hz, rs.wait_for_subscribers
        self.method = rs.method  # "": no offline job
        self.settings = declare_settings(self, CalibrationSettings, exclude=("method",))
        if self.method:
            self.settings = self.settings.replace(method=self.method)
        # with a job, refused at start if it cannot be written (not after republishing the whole bag)
        self.output_dir = (writable_dir(rs.output_dir, "output_dir") if self.method
                           else Path(rs.output_dir).expanduser().resolve())
        try:
            raw = read_raw_messages(self.bag_path)
        except ScanBagError as exc:
            raise ValueError(f"parameter bag_path: {exc}") from None
        for w in raw.warnings:
            self.get_logger().warning(w)
        skip = {"/" + t.lstrip("/") for t in rs.skip_topics if t.strip("/")}
        skipped = {t: n for t, (_, n) in raw.topics().items() if t in skip}
        messages = [m for m in raw.messages if m.topic not in skip] if skipped else raw.messages
        if skipped and self.rate_hz > 0:
            self.get_logger().info("not republished (skip_topics): "
                                   + ", ".join(f"{t} ({n} messages)" for t, n in sorted(skipped.items())))
        self.skipped_topics = sorted(skipped)
        self.latched, self.groups = frame_groups(messages)
        self._recorded_qos = raw.qos
        self.published_frames = 0
        self.republish_done = self.rate_hz <= 0
        self.report: dict | None = None
        self.error: str | None = None
        self._pubs: dict[str, object] = {}
        self._unavailable: set[str] = set()  # topics whose message type this ROS install lacks
        self._report_pub = self.create_publisher(String, "~/report", LATCHED)
        self._job: threading.Thread | None = None
        self._next = 0
        self._latched_published = False
        self.exit_code = 0
        if rs.exit_when_done:
            self.create_timer(0.2, self._exit_if_done)
        n_frames = sum(1 for g in self.groups for m in g if m.topic == fmt.TOPIC_PROJECTION)
        self.get_logger().info(f"{self.bag_path}: {n_frames} frames, {len(raw.messages)} messages"
                               + (f"; republishing at {self.rate_hz} Hz" if self.rate_hz > 0 else ""))
        if self.rate_hz > 0:
            for m in {(m.topic, m.msgtype): m for m in messages}.values():
                self._publisher_of(m)  # discovery runs during the wait
            self._projection_pub = self._publisher(fmt.TOPIC_PROJECTION, fmt.IMAGE)
            self._timer = self.create_timer(1.0 / self.rate_hz, self._tick)
        elif self.method:
            self._start_job()

    def _publisher(self, topic: str, msgtype: str):
        pub = self._pubs.get(topic)
        if pub is None:
            qos = replay_qos(topic, self._recorded_qos.get(topic, ()))
            pub = self.create_publisher(message_class(msgtype), fmt.node_topic(topic), qos)  # in the namespace
            self._pubs[topic] = pub
        return pub

    def _publisher_of(self, m):
        """The publisher of message ``m``'s topic, None (with one warning per topic) for a type this ROS install
        lacks."""
        if m.topic in self._unavailable:
            return None
        try:
            return self._publisher(m.topic, m.msgtype)
        except (ImportError, AttributeError, ValueError) as exc:
            self._unavailable.add(m.topic)
            self.get_logger().warning(f"cannot republish {m.topic} ({m.msgtype}): {exc}")
            return None

    def _publish(self, m) -> None:
        pub = self._publisher_of(m)
        if pub is not None:
            pub.publish(m.data)

    def _tick(self) -> None:
        if self._next == 0:
            if self._projection_pub.get_subscription_count() < self.wait_for_subscribers:
                return
            if not self._latched_published:  # after the wait: a volatile subscriber that came during it gets them
                self._latched_published = True
                for m in self.latched:
                    self._publish(m)
        if self._next < len(self.groups):
            for m in self.groups[self._next]:
                self._publish(m)
                if m.topic == fmt.TOPIC_PROJECTION:
                    self.published_frames += 1
            self._next += 1
            return
        self._timer.cancel()
        self.republish_done = True
        self.get_logger().info(f"republished {self.published_frames} frames")
        if self.method:
            self._start_job()

    # ----------------------------------------------------------------- offline calibration
    def _start_job(self) -> None:
        self._job = threading.Thread(target=self._run_job, name="replay-calibration", daemon=True)
        self._job.start()

    def _run_job(self) -> None:
        from robot_ct_ros.jobs.calibrate import calibrate_bag
        from robot_ct_ros.jobs.output import clean_json, json_default

        log = self.get_logger()
        try:
            rs = self.replay_settings
            report = calibrate_bag(self.bag_path, self.output_dir, self.settings, voxel_mm=rs.voxel_mm,
                                   shape_xyz=rs.shape_xyz, evaluate_truth=rs.evaluate_truth,
                                   say=lambda s: log.info(s), options="ROS parameters").report
        except Exception as exc:  # noqa: BLE001 - reported, the node keeps running
            error = f"{type(exc).__name__}: {exc}"
            log.error(f"offline calibration failed: {error}")
            self._report_pub.publish(String(data=json.dumps({"error": error})))
            self.error = error  # after the publish: "done" (exit_when_done) must not come before the report
            return
        self._report_pub.publish(String(data=json.dumps(clean_json(report), default=json_default)))
        log.info(f"offline calibration done: {self.output_dir}/report.json")
        self.report = report  # after the publish: "done" (exit_when_done) must not come before the report

    @property
    def done(self) -> bool:
        job_done = not self.method or self.report is not None or self.error is not None
        return self.republish_done and job_done

    def _exit_if_done(self) -> None:
        """With exit_when_done: end the spin (run_node then exits with exit_code) once everything is done."""
        if self.done and self.context.ok():
            import rclpy
            from rclpy.duration import Duration

            from robot_ct_ros.nodes.common import shutdown_once

            self.exit_code = 1 if self.error else 0
            # the report is latched and reliable: let the subscribers that are there take it before the node goes
            # (a script waiting on ~/report missed it when the node ended 35 ms after publishing)
            end = time.monotonic() + REPORT_DISCOVERY_S  # a quick job may end before discovery found the listener
            while not self._report_pub.get_subscription_count() and time.monotonic() < end:
                time.sleep(0.05)
            if self._report_pub.get_subscription_count():
                self._report_pub.wait_for_all_acked(Duration(seconds=REPORT_ACK_S))
            self.get_logger().info("done; exiting (exit_when_done)")
            shutdown_once(rclpy, self.context)


REPORT_ACK_S = 5.0
"""How long an exiting replay waits for ~/report's subscribers to acknowledge it."""
REPORT_DISCOVERY_S = 3.0
"""How long an exiting replay waits for a ~/report subscriber to be discovered (none: it exits after this)."""


def main(argv=None) -> int:
    return run_settings_node(ReplayNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
