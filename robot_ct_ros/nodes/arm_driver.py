"""arm_driver: one robot arm (UR through ur-rtde, or a simulated arm) as a ROS 2 lifecycle node.

Topics, relative to the node namespace, under ``<role>_arm/`` (role is "source" or "detector"):
  publishes   <role>_arm/joint_states (sensor_msgs/JointState, rad), <role>_arm/tool_pose
              (geometry_msgs/PoseStamped: the measured TCP pose in metres, REP 103, frame_id =
              base_frame), <role>_arm/in_position (std_msgs/Bool: true when the last commanded
              move completed and the measured pose is within tolerance of it), all at
              publish_rate_hz while active; <role>_arm/true_tool_pose (PoseStamped, simulated arm
              only: the true, perturbed pose, for the simulated detector); /diagnostics (1 Hz).
  subscribes  <role>_arm/goal_pose (geometry_msgs/PoseStamped in base_frame): a linear move to
              it; moves run on a worker thread, in_position is false while moving.
Lifecycle: configure connects (robot_ip "" = simulated arm), activate starts publishing and
accepting goals, deactivate stops them, cleanup disconnects. A failed connection fails the
configure transition with a logged reason. When the connection is lost while active the node
publishes in_position false, logs an error, reports ERROR on /diagnostics and goes back to
unconfigured (deactivate + cleanup); configure again to reconnect. With autostart (default) the
node configures and activates itself, so a plain ``ros2 run`` works without a lifecycle manager.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from scipy.spatial.transform import Rotation
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from robot_ct_ros.hardware.simulated_arm import JOINT_NAMES, SimulatedArm, SimulatedArmErrors
from robot_ct_ros.hardware.ur_arm import ArmConnectionError, ArmError, URArm, pose_distance
from robot_ct_ros.nodes.common import run_node


def pose_msg_to_ur(msg: PoseStamped) -> np.ndarray:
    p, o = msg.pose.position, msg.pose.orientation
    rotvec = Rotation.from_quat([o.x, o.y, o.z, o.w]).as_rotvec()
    return np.array([p.x, p.y, p.z, *rotvec])


def ur_to_pose_msg(pose, frame_id: str, stamp) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = stamp
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in pose[:3])
    x, y, z, w = Rotation.from_rotvec(pose[3:6]).as_quat()
    msg.pose.orientation.x, msg.pose.orientation.y = float(x), float(y)
    msg.pose.orientation.z, msg.pose.orientation.w = float(z), float(w)
    return msg


class ArmDriverNode(LifecycleNode):
    def __init__(self, node_name: str = "arm_driver", *, arm_factory=None, **kwargs):
        super().__init__(node_name, **kwargs)
        p = self.declare_parameter
        self.role = p("role", "source").value
        if self.role not in ("source", "detector"):
            raise ValueError(f"role must be 'source' or 'detector', got {self.role!r}")
        self.robot_ip = p("robot_ip", "").value
        self.connect_timeout_s = p("connect_timeout_s", 10.0).value
        self.call_timeout_s = p("call_timeout_s", 2.0).value
        self.move_timeout_s = p("move_timeout_s", 60.0).value
        self.speed = p("speed", 0.25).value
        self.acceleration = p("acceleration", 1.2).value
        self.position_tolerance_m = p("position_tolerance_m", 1e-4).value
        self.orientation_tolerance_rad = p("orientation_tolerance_rad", 1e-3).value
        self.publish_rate_hz = p("publish_rate_hz", 50.0).value
        self.base_frame = p("base_frame", "world").value
        self.tool_frame = p("tool_frame", "").value or f"{self.role}_arm_tool0"
        self.joint_prefix = p("joint_prefix", "").value or f"{self.role}_arm_"
        self.sim_errors = SimulatedArmErrors(
            sigma_mm=p("sim_sigma_mm", 0.0).value, sigma_deg=p("sim_sigma_deg", 0.0).value,
            drift_mm_per_move=p("sim_drift_mm_per_move", 0.0).value, seed=p("sim_seed", 0).value)
        self.sim_motion_time_scale = p("sim_motion_time_scale", 0.0).value
        self.sim_fail_after_moves = p("sim_fail_after_moves", -1).value
        autostart = p("autostart", True).value
        self._arm_factory = arm_factory or self._make_arm

        ns = f"{self.role}_arm"
        self.joint_pub = self.create_publisher(JointState, f"{ns}/joint_states", 10)
        self.pose_pub = self.create_publisher(PoseStamped, f"{ns}/tool_pose", 10)
        self.true_pose_pub = self.create_publisher(PoseStamped, f"{ns}/true_tool_pose", 10)
        self.in_position_pub = self.create_publisher(Bool, f"{ns}/in_position", 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(PoseStamped, f"{ns}/goal_pose", self._on_goal, 10)
        self.create_timer(1.0, self._publish_diagnostics)

        self.arm = None
        self._lock = threading.Lock()
        self._active = False
        self._snapshot: dict | None = None
        self._target: np.ndarray | None = None
        self._moving = False
        self._move_ok = False
        self._next_goal: np.ndarray | None = None
        self._goal_event = threading.Event()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._publish_timer = None
        self._lost_reason: str | None = None
        self.last_error = ""
        self.moves_completed = 0
        if autostart:
            self._autostart_timer = self.create_timer(0.0, self._autostart)

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def lifecycle_state(self) -> str:
        return self._state_machine.current_state[1]

    def _autostart(self) -> None:
        self._autostart_timer.cancel()
        self.destroy_timer(self._autostart_timer)
        if self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self.trigger_activate()

    def _make_arm(self):
        if self.robot_ip:
            return URArm(self.robot_ip, connect_timeout_s=self.connect_timeout_s,
                         call_timeout_s=self.call_timeout_s, move_timeout_s=self.move_timeout_s)
        fail = self.sim_fail_after_moves if self.sim_fail_after_moves >= 0 else None
        return SimulatedArm(errors=self.sim_errors, motion_time_scale=self.sim_motion_time_scale,
                            fail_after_moves=fail)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            arm = self._arm_factory()
            arm.connect()
        except (ArmError, OSError, ValueError) as exc:
            self.last_error = f"configure failed: {exc}"
            self.get_logger().error(self.last_error)
            return TransitionCallbackReturn.FAILURE
        self.arm = arm
        self._lost_reason = None
        self.last_error = ""
        self.get_logger().info(f"{self.role} arm connected ({self.robot_ip or 'simulated'})")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop.clear()
        self._active = True
        self._threads = [threading.Thread(target=self._poll_loop, name="arm_poll", daemon=True),
                         threading.Thread(target=self._move_loop, name="arm_move", daemon=True)]
        for t in self._threads:
            t.start()
        self._publish_timer = self.create_timer(1.0 / max(self.publish_rate_hz, 0.1), self._publish)
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        self._disconnect()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        self._disconnect()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        self._disconnect()
        return TransitionCallbackReturn.SUCCESS

    def _stop_activity(self, publish: bool = True) -> None:
        was_active = self._active
        self._active = False
        self._stop.set()
        self._goal_event.set()
        if self._publish_timer is not None:
            self._publish_timer.cancel()
            self.destroy_timer(self._publish_timer)
            self._publish_timer = None
        for t in self._threads:
            # a move in flight ends on its own timeout; never wait on it here
            t.join(0.2 if t.name == "arm_move" else 2.0)
        self._threads = []
        with self._lock:
            self._moving, self._move_ok, self._next_goal = False, False, None
        if was_active and publish:
            self.in_position_pub.publish(Bool(data=False))

    def _disconnect(self) -> None:
        arm, self.arm = self.arm, None
        if arm is not None:
            try:
                arm.disconnect()
            except ArmError as exc:
                self.get_logger().warn(f"disconnect: {exc}")

    def destroy_node(self):
        # the context may already be shut down (SIGINT): no publishing here
        self._stop_activity(publish=self.context.ok())
        self._disconnect()
        return super().destroy_node()

    # -- worker threads --------------------------------------------------------------------
    def _poll_loop(self) -> None:
        period = 1.0 / max(self.publish_rate_hz, 0.1)
        arm = self.arm
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                if isinstance(arm, URArm):
                    state = arm.read_state()
                    snap = {"pose": np.asarray(state["tcp_pose"]), "q": np.asarray(state["joint_positions"])}
                else:
                    snap = {"pose": arm.get_tcp_pose(), "q": arm.get_joint_positions()}
                    if isinstance(arm, SimulatedArm):
                        snap["true_pose"] = arm.true_tcp_pose()
            except ArmError as exc:
                self._connection_lost(str(exc), arm)
                return
            with self._lock:
                self._snapshot = snap
            self._stop.wait(max(0.0, period - (time.monotonic() - t0)))

    def _move_loop(self) -> None:
        arm = self.arm
        while not self._stop.is_set():
            self._goal_event.wait()
            with self._lock:
                goal, self._next_goal = self._next_goal, None
                self._goal_event.clear()
            if goal is None or self._stop.is_set():
                continue
            try:
                arm.move_linear(goal, self.speed, self.acceleration, timeout_s=self.move_timeout_s)
                with self._lock:
                    if self._next_goal is None:
                        self._moving, self._move_ok = False, True
                self.moves_completed += 1
            except ArmConnectionError as exc:
                self._connection_lost(str(exc), arm)
                return
            except ArmError as exc:
                self.last_error = f"move failed: {exc}"
                self.get_logger().error(self.last_error)
                with self._lock:
                    if self._next_goal is None:
                        self._moving, self._move_ok = False, False

    def _connection_lost(self, reason: str, arm) -> None:
        with self._lock:
            if arm is not self.arm or not self._active:
                return  # a late failure of an arm we already let go of
            if self._lost_reason is None:
                self._lost_reason = reason
            self._moving, self._move_ok = False, False

    # -- executor side ---------------------------------------------------------------------
    def _on_goal(self, msg: PoseStamped) -> None:
        if not self._active:
            self.get_logger().warn(f"goal ignored: node is {self.lifecycle_state}, not active")
            return
        if msg.header.frame_id not in ("", self.base_frame):
            self.get_logger().error(f"goal ignored: frame {msg.header.frame_id!r} is not {self.base_frame!r}")
            return
        try:
            goal = pose_msg_to_ur(msg)
        except ValueError as exc:
            self.get_logger().error(f"goal ignored: {exc}")
            return
        with self._lock:
            self._target = goal
            self._next_goal = goal
            self._moving, self._move_ok = True, False
            self._goal_event.set()
        self.in_position_pub.publish(Bool(data=False))

    def in_position(self) -> bool:
        with self._lock:
            if self._moving or not self._move_ok or self._target is None or self._snapshot is None:
                return False
            dt, dr = pose_distance(self._snapshot["pose"], self._target)
        return dt <= self.position_tolerance_m and dr <= self.orientation_tolerance_rad

    def _publish(self) -> None:
        if self._lost_reason is not None:
            self._handle_connection_loss()
            return
        with self._lock:
            snap = self._snapshot
        if not self._active or snap is None:
            return
        stamp = self.get_clock().now().to_msg()
        js = JointState()
        js.header.stamp = stamp
        js.name = [self.joint_prefix + n for n in JOINT_NAMES]
        js.position = [float(v) for v in snap["q"]]
        self.joint_pub.publish(js)
        self.pose_pub.publish(ur_to_pose_msg(snap["pose"], self.base_frame, stamp))
        if "true_pose" in snap:
            self.true_pose_pub.publish(ur_to_pose_msg(snap["true_pose"], self.base_frame, stamp))
        self.in_position_pub.publish(Bool(data=self.in_position()))

    def _handle_connection_loss(self) -> None:
        reason = self._lost_reason
        self.in_position_pub.publish(Bool(data=False))
        self.last_error = f"connection lost: {reason}"
        self.get_logger().error(f"{self.role} arm {self.last_error}; going to unconfigured (configure to reconnect)")
        self.trigger_deactivate()
        self.trigger_cleanup()
        self._publish_diagnostics()

    def _publish_diagnostics(self) -> None:
        state = self.lifecycle_state
        if self.last_error.startswith(("connection lost", "configure failed")):
            level = DiagnosticStatus.ERROR
        elif state != "active" or self.last_error:
            level = DiagnosticStatus.WARN
        else:
            level = DiagnosticStatus.OK
        message = self.last_error or (f"{state}, in position" if self.in_position() else state)
        with self._lock:
            target = None if self._target is None else [round(float(v), 6) for v in self._target]
        status = DiagnosticStatus(
            level=level, name=f"{self.get_fully_qualified_name()}: {self.role} arm",
            hardware_id=self.robot_ip or "simulated_arm", message=message,
            values=[KeyValue(key=k, value=str(v)) for k, v in (
                ("lifecycle_state", state), ("connected", self.arm is not None and self.arm.is_connected),
                ("in_position", self.in_position()), ("moves_completed", self.moves_completed),
                ("target_pose", target), ("base_frame", self.base_frame), ("tool_frame", self.tool_frame))])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)


def main(argv=None) -> int:
    return run_node(ArmDriverNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
