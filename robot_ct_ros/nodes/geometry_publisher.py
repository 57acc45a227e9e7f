"""geometry_publisher: the nominal geometry of every detector frame, from the arms' measured tool poses.

Topics (contract names from robot_ct_ros.bag.format; relative names follow the node namespace):
  subscribes  source_arm/tool_pose, detector_arm/tool_pose (geometry_msgs/PoseStamped, metres, frame
              world_frame): the *measured* TCP poses (a history of history_s seconds is kept),
              /ct/projection (sensor_msgs/Image): only the header is used
  publishes   /ct/geometry (geometry_msgs/PoseArray, reliable, depth 100): for each frame, with
              exactly the frame's header.stamp: poses[0] the source focal spot, poses[1] the detector
              centre with orientation columns (u, v, w), metres, frame world_frame; /diagnostics (1 Hz)
Every incoming tool pose is checked first: one with a NaN or infinite value, a non-unit quaternion
or another frame is refused (logged, counted on /diagnostics, WARN) and never used.
For each frame, each arm's pose nearest in time to the frame stamp is taken through the hand-eye
mounts (robot_ct_ros.ct.hand_eye.geometry_from_tool_poses). This is the nominal geometry: the arms'
coordination errors are invisible here (the calibration estimates them from the data). When a pose
is missing, further than max_pose_age_s from the frame stamp, or not in world_frame, no geometry is
published for that frame; the skip is logged and counted on /diagnostics (WARN).
Late poses: under CPU load a frame can be taken before the tool poses stamped after it, already on
their way, have been received. A frame is therefore judged only once both arms' histories reach its
stamp (a pose stamped at or after it has arrived; the nearest pose can then no longer change); until
then it is held, and retried as poses arrive, for at most wait_for_poses_s. After that wait it is
judged on what arrived: a pose within max_pose_age_s still gives its geometry, otherwise the frame gets
"no geometry" as above, naming how stale the poses were and that it waited. wait_for_poses_s = 0 judges
every frame as it arrives. Order: geometries are published in the order their frames arrived (a held
frame holds back the frames after it, never longer than its own wait), each with its frame's stamp.
Parameters: max_pose_age_s (s), history_s (s), wait_for_poses_s (s), world_frame
(GeometryPublisherSettings), and the hand_eye.* parameters (nodes/hand_eye_params.py).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass

from rclpy.node import Node
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.hand_eye import geometry_from_tool_poses
from robot_ct_ros.nodes.common import STREAM, declare_settings, publish_diagnostic, run_settings_node
from robot_ct_ros.nodes.hand_eye_params import check_pose, declare_hand_eye, pose_to_matrix_mm, stamp_to_ns
from robot_ct_ros.parameters import setting, validate

__all__ = ["GeometryPublisherNode", "GeometryPublisherSettings", "STREAM", "ROLES", "main"]

ROLES = ("source", "detector")


@dataclass(frozen=True)
class GeometryPublisherSettings:
    """How tool poses are matched to frames (SI units)."""

    max_pose_age_s: float = setting(0.2, "a tool pose further than this from the frame stamp is stale: no geometry",
                                    unit="s", minimum=0.0)
    history_s: float = setting(5.0, "tool-pose history kept to find the pose nearest to a frame stamp", unit="s",
                               minimum=0.0)
    wait_for_poses_s: float = setting(2.0, "a frame is held this long for the tool poses stamped after it that "
                                           "have not arrived yet (late under CPU load); then judged on what arrived",
                                      unit="s", minimum=0.0)
    world_frame: str = setting(fmt.FRAME_WORLD, "frame of the tool poses and of /ct/geometry")

    def __post_init__(self):
        validate(self)


class GeometryPublisherNode(Node):
    def __init__(self, node_name: str = "geometry_publisher", **kwargs):
        super().__init__(node_name, **kwargs)
        self.settings = s = declare_settings(self, GeometryPublisherSettings)
        self.max_pose_age_s, history_s, self.world_frame = s.max_pose_age_s, s.history_s, s.world_frame
        self.wait_for_poses_s = s.wait_for_poses_s
        self.hand_eye = declare_hand_eye(self)
        self._history = {r: deque() for r in ROLES}
        self._newest = {r: None for r in ROLES}  # the latest stamp received per arm (ns), kept when aged out
        # frames held until both arms' poses reach past their stamps: (stamp_ns, height, width, held since, until)
        self._pending = deque()
        self._history_ns = int(history_s * 1e9)
        for role in ROLES:
            self.create_subscription(PoseStamped, f"{role}_arm/tool_pose", lambda m, r=role: self._on_pose(r, m), 50)
        self.create_subscription(Image, fmt.node_topic(fmt.TOPIC_PROJECTION), self._on_frame, STREAM)
        self.geometry_pub = self.create_publisher(PoseArray, fmt.node_topic(fmt.TOPIC_GEOMETRY), STREAM)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.node_topic(fmt.TOPIC_DIAGNOSTICS), 10)
        self.create_timer(1.0, self._publish_diagnostics)
        self.create_timer(0.05, self._judge_pending)  # a frame whose poses never come is judged at its deadline
        self.published = 0
        self.skipped = 0
        self.poses_refused = 0
        self.last_refused = ""
        self.last_problem = ""
        self._last_frame_ok = True
        self._skipped_since_report = 0

    def _on_pose(self, role: str, msg: PoseStamped) -> None:
        try:  # checked at the boundary: a broken pose must never shadow the good ones around it
            check_pose(msg.pose)
            if msg.header.frame_id not in ("", self.world_frame):
                raise ValueError(f"frame {msg.header.frame_id!r} is not {self.world_frame!r}")
        except ValueError as exc:
            self.poses_refused += 1
            self.last_refused = f"{role} arm tool pose refused: {exc}"
            self.get_logger().warn(self.last_refused, throttle_duration_sec=1.0)
            return
        t = stamp_to_ns(msg.header.stamp)
        hist = self._history[role]
        # a stamp far ahead of the arm's others does not age them out (one broken pose must not shadow the good
        # ones); the next pose as far ahead, a real jump, does
        newest = hist[-1][0] if hist else t
        reference = t if t <= newest + self._history_ns else newest
        hist.append((t, msg.header.frame_id, msg.pose))
        while hist and hist[0][0] < reference - self._history_ns:
            hist.popleft()
        if self._newest[role] is None or t > self._newest[role]:
            self._newest[role] = t
        if self._pending:
            self._judge_pending()

    def _reaches(self, stamp_ns: int) -> bool:
        """Both arms have sent a pose stamped at or after ``stamp_ns``: no later pose can be nearer."""
        return all(self._newest[r] is not None and self._newest[r] >= stamp_ns for r in ROLES)

    def _nearest(self, role: str, stamp_ns: int):
        hist = self._history[role]
        if not hist:
            return None, f"no {role} arm tool pose received"
        t, frame_id, pose = min(hist, key=lambda e: abs(e[0] - stamp_ns))
        age = abs(t - stamp_ns) * 1e-9
        if age > self.max_pose_age_s:
            return None, f"{role} arm tool pose stale ({age:.3f} s from the frame, limit {self.max_pose_age_s} s)"
        if frame_id not in ("", self.world_frame):
            return None, f"{role} arm tool pose in frame {frame_id!r}, not {self.world_frame!r}"
        return pose, ""

    def _on_frame(self, msg: Image) -> None:
        now = time.monotonic()
        self._pending.append((stamp_to_ns(msg.header.stamp), msg.height, msg.width, now, now + self.wait_for_poses_s))
        self._judge_pending()

    def _judge_pending(self) -> None:
        """Judge the held frames in arrival order: each once the poses reach past it, or at its deadline."""
        while self._pending:
            stamp, height, width, since, until = self._pending[0]
            now = time.monotonic()
            reached = self._reaches(stamp)
            if not reached and now < until:
                return
            self._pending.popleft()
            self._judge(stamp, height, width, waited_s=None if reached else now - since)

    def _judge(self, stamp: int, height: int, width: int, waited_s: float | None = None) -> None:
        poses, problems = {}, []
        for role in ROLES:
            poses[role], problem = self._nearest(role, stamp)
            if problem:
                problems.append(problem)
        if not problems:
            try:
                g = geometry_from_tool_poses(pose_to_matrix_mm(poses["source"]), pose_to_matrix_mm(poses["detector"]),
                                             self.hand_eye, max(1, height), max(1, width), 1.0)
            except ValueError as exc:
                problems.append(f"unusable tool pose: {exc}")
        if problems:
            self.skipped += 1
            self.last_problem = "; ".join(problems)
            if waited_s is not None and self.wait_for_poses_s > 0:
                newest = ", ".join(f"{r} {(stamp - self._newest[r]) * 1e-9:.3f} s before the frame"
                                   for r in ROLES if self._newest[r] is not None and self._newest[r] < stamp)
                self.last_problem += (f" (waited {waited_s:.1f} s, wait_for_poses_s {self.wait_for_poses_s} s, for "
                                      f"tool poses stamped after the frame; newest received: {newest or 'none'})")
            self._last_frame_ok = False
            self._skipped_since_report += 1
            self.get_logger().warn(f"no geometry for the frame stamped {stamp * 1e-9:.6f}: {self.last_problem}")
            return
        out = fmt.view_pose_array(g.source_mm[0], g.detector_mm[0], g.u[0], g.v[0], stamp, self.world_frame)
        self.geometry_pub.publish(fmt.serialize(out, fmt.POSE_ARRAY))
        self.published += 1
        self._last_frame_ok = True

    def _publish_diagnostics(self) -> None:
        # a skip since the last report is a WARN even when a good frame followed it within the period
        skipped, self._skipped_since_report = self._skipped_since_report, 0
        ok = self._last_frame_ok and not skipped and not self.poses_refused
        level = DiagnosticStatus.OK if ok else DiagnosticStatus.WARN
        message = ("ok" if self._last_frame_ok and not skipped else
                   f"last frame without geometry: {self.last_problem}" if not self._last_frame_ok else
                   f"{skipped} frame(s) without geometry since the last report (last: {self.last_problem})")
        if self.poses_refused:
            message += f"; {self.poses_refused} tool poses refused (last: {self.last_refused})"
        ages = {r: (f"{(self.get_clock().now().nanoseconds - self._history[r][-1][0]) * 1e-9:.3f}"
                    if self._history[r] else "none") for r in ROLES}
        publish_diagnostic(self, self.diag_pub, level, "geometry", "hand_eye", message, (
            ("published", self.published), ("skipped", self.skipped), ("last_problem", self.last_problem),
            ("poses_refused", self.poses_refused), ("frames_waiting_for_poses", len(self._pending)),
            ("source_pose_age_s", ages["source"]), ("detector_pose_age_s", ages["detector"]),
            ("max_pose_age_s", self.max_pose_age_s)))


def main(argv=None) -> int:
    return run_settings_node(GeometryPublisherNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
