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
Parameters: config/arm_driver.yaml; the arm itself is robot_ct_ros.hardware.arm (ArmSettings,
ArmRunner), the simulated arm's sim_* parameters robot_ct_ros.hardware.simulated_arm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from scipy.spatial.transform import Rotation
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool

from robot_ct_ros.hardware.arm import ArmError, ArmRunner, ArmSettings
from robot_ct_ros.hardware.arms import make_arm
from robot_ct_ros.hardware.simulated_arm import JOINT_NAMES, SimulatedArmSettings
from robot_ct_ros.nodes.common import LifecycleSettings, declare_settings, publish_diagnostic, run_settings_node
from robot_ct_ros.parameters import setting, validate

__all__ = ["ArmDriverNode", "ArmDriverSettings", "pose_msg_to_ur", "ur_to_pose_msg", "main"]


@dataclass(frozen=True)
class ArmDriverSettings:
    """What the node publishes, and where."""

    role: str = setting("source", "which arm: topics go to <role>_arm/", choices=("source", "detector"))
    publish_rate_hz: float = setting(50.0, "joint_states, tool_pose and in_position rate", unit="Hz", minimum=0.0)
    base_frame: str = setting("world", "frame_id of tool_pose and of accepted goals")
    tool_frame: str = setting("", "tool frame reported in diagnostics; empty: <role>_arm_tool0")
    joint_prefix: str = setting("", "joint name prefix; empty: <role>_arm_")

    def __post_init__(self):
        validate(self)


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
        self.settings = s = declare_settings(self, ArmDriverSettings)
        self.arm_settings = declare_settings(self, ArmSettings)
        self.sim_settings = declare_settings(self, SimulatedArmSettings, prefix="sim_")
        autostart = declare_settings(self, LifecycleSettings).autostart
        self.role, self.base_frame, self.robot_ip = s.role, s.base_frame, self.arm_settings.robot_ip
        self.tool_frame = s.tool_frame or f"{s.role}_arm_tool0"
        self.joint_prefix = s.joint_prefix or f"{s.role}_arm_"
        self._arm_factory = arm_factory or (lambda: make_arm(self.arm_settings, self.sim_settings))

        ns = f"{self.role}_arm"
        self.joint_pub = self.create_publisher(JointState, f"{ns}/joint_states", 10)
        self.pose_pub = self.create_publisher(PoseStamped, f"{ns}/tool_pose", 10)
        self.true_pose_pub = self.create_publisher(PoseStamped, f"{ns}/true_tool_pose", 10)
        self.in_position_pub = self.create_publisher(Bool, f"{ns}/in_position", 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(PoseStamped, f"{ns}/goal_pose", self._on_goal, 10)
        self.create_timer(1.0, self._publish_diagnostics)

        self.arm = None
        self.runner = ArmRunner(self.arm_settings, s.publish_rate_hz, self._move_failed)
        self._publish_timer = None
        self.last_error = ""
        if autostart:
            self._autostart_timer = self.create_timer(0.0, self._autostart)

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def lifecycle_state(self) -> str:
        return self._state_machine.current_state[1]

    @property
    def moves_completed(self) -> int:
        return self.runner.moves_completed

    def in_position(self) -> bool:
        return self.runner.in_position()

    def _autostart(self) -> None:
        self._autostart_timer.cancel()
        self.destroy_timer(self._autostart_timer)
        if self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self.trigger_activate()

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            arm = self._arm_factory()
            arm.connect()
        except (ArmError, OSError, ValueError) as exc:
            self.last_error = f"configure failed: {exc}"
            self.get_logger().error(self.last_error)
            return TransitionCallbackReturn.FAILURE
        self.arm = arm
        self.last_error = ""
        self.get_logger().info(f"{self.role} arm connected ({self.robot_ip or 'simulated'})")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.runner.start(self.arm)
        self._publish_timer = self.create_timer(self.runner.period_s, self._publish)
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        self._disconnect()
        return TransitionCallbackReturn.SUCCESS

    on_shutdown = on_error = on_cleanup

    def _stop_activity(self, publish: bool = True) -> None:
        if self._publish_timer is not None:
            self._publish_timer.cancel()
            self.destroy_timer(self._publish_timer)
            self._publish_timer = None
        if self.runner.stop() and publish:
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

    def _move_failed(self, message: str) -> None:  # the runner's move thread
        self.last_error = message
        self.get_logger().error(message)

    # -- executor side ---------------------------------------------------------------------
    def _on_goal(self, msg: PoseStamped) -> None:
        if not self.runner.active:
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
        self.runner.command(goal)
        self.in_position_pub.publish(Bool(data=False))

    def _publish(self) -> None:
        if self.runner.lost_reason is not None:
            self._handle_connection_loss()
            return
        snap = self.runner.latest()
        if not self.runner.active or snap is None:
            return
        stamp = self.get_clock().now().to_msg()
        js = JointState()
        js.header.stamp = stamp
        js.name = [self.joint_prefix + n for n in JOINT_NAMES]
        js.position = [float(v) for v in snap.joint_positions]
        self.joint_pub.publish(js)
        self.pose_pub.publish(ur_to_pose_msg(snap.tcp_pose, self.base_frame, stamp))
        if snap.true_tcp_pose is not None:
            self.true_pose_pub.publish(ur_to_pose_msg(snap.true_tcp_pose, self.base_frame, stamp))
        self.in_position_pub.publish(Bool(data=self.in_position()))

    def _handle_connection_loss(self) -> None:
        reason = self.runner.lost_reason
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
        target = self.runner.target
        target = None if target is None else [round(float(v), 6) for v in target]
        publish_diagnostic(self, self.diag_pub, level, f"{self.role} arm", self.robot_ip or "simulated_arm", message, (
            ("lifecycle_state", state), ("connected", self.arm is not None and self.arm.is_connected),
            ("in_position", self.in_position()), ("moves_completed", self.moves_completed),
            ("target_pose", target), ("base_frame", self.base_frame), ("tool_frame", self.tool_frame)))

def main(argv=None) -> int:
    return run_settings_node(ArmDriverNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
