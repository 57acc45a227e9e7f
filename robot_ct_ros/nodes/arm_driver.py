"""arm_driver: one robot arm (UR through ur-rtde, or a simulated arm) as a ROS 2 lifecycle node.

Topics, relative to the node namespace, under ``<role>_arm/`` (role is "source" or "detector"):
  publishes   <role>_arm/joint_states (sensor_msgs/JointState, rad), <role>_arm/tool_pose
              (geometry_msgs/PoseStamped: the measured TCP pose in metres, REP 103, frame_id =
              base_frame), <role>_arm/in_position (std_msgs/Bool: true when the last commanded
              move completed, the state is fresh, the robot runs normally (no protective stop, not
              powered off: else an ERROR on diagnostics) and the measured pose is within tolerance of
              the goal), at publish_rate_hz while active; <role>_arm/true_tool_pose (PoseStamped,
              simulated arm only: the true, perturbed pose, for the simulated detector);
              diagnostics (1 Hz, and at once, after in_position, when the arm's fault state
              changes: a protective stop or power-off begins or ends, the state goes stale or fresh).
  subscribes  <role>_arm/goal_pose (geometry_msgs/PoseStamped in base_frame): a linear move to
              it; moves run on a worker thread, in_position is false while moving. A goal with a
              NaN or infinite value, a non-unit quaternion or another frame is refused at once
              (logged, and a WARN on diagnostics); the arm keeps its last goal.
Stamps and freshness: joint_states and tool_pose carry the time the controller measured them
(the UR controller's clock mapped onto the ROS clock), and each sample is published once; when the
controller's clock stops advancing for max_state_age_s (a hung controller still answering with its
last state) nothing is republished, in_position is false and diagnostics say "state stale"; stale
for call_timeout_s counts as a lost connection.
Lifecycle: configure creates the arm and connects it on a background thread (robot_ip "" =
simulated arm), so the executor, the lifecycle services and diagnostics ("connecting", WARN) keep
running while a controller is slow to answer; activate starts publishing and accepting goals once
the connection is up (at once if it already is); deactivate stops them; cleanup disconnects (off
the executor too). A failed connection, or one lost while configured, is logged, reported as
ERROR on diagnostics, and the node goes back to unconfigured; configure again to reconnect (while
inactive the arm is read at 2 Hz to notice it, and activate is refused on a dead connection). A
worker thread dying on an unexpected exception is an ERROR on diagnostics and takes the node
through the lifecycle error transition (on_error releases the arm; the node ends unconfigured).
With autostart (default) the node configures and activates itself, so a plain ``ros2 run`` works
without a lifecycle manager.
Parameters: config/arm_driver.yaml; the arm itself is robot_ct_ros.hardware.arm (ArmSettings,
ArmRunner, arm_health), connecting it robot_ct_ros.hardware.connection, the simulated arm's sim_*
parameters robot_ct_ros.hardware.simulated_arm.
"""

from __future__ import annotations

from dataclasses import dataclass

from rclpy.duration import Duration
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState
from std_msgs.msg import Bool, Header

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.hardware.arm import ArmError, ArmRunner, ArmSettings, ArmWatch, arm_health
from robot_ct_ros.hardware.arms import make_arm
from robot_ct_ros.hardware.connection import BackgroundConnection
from robot_ct_ros.hardware.simulated_arm import JOINT_NAMES, SimulatedArmSettings
from robot_ct_ros.nodes.common import (LifecycleSettings, WorkerFaults, declare_settings, error_transition,
                                      publish_diagnostic, publish_while_up, refuse_unavailable_transitions,
                                      run_settings_node, to_unconfigured, transition_result)
from robot_ct_ros.nodes.hand_eye_params import pose_msg_to_ur, ur_to_pose_msg  # noqa: F401 - re-exported
from robot_ct_ros.parameters import setting, validate


__all__ = ["ArmDriverNode", "ArmDriverSettings", "pose_msg_to_ur", "ur_to_pose_msg", "main"]


@dataclass(frozen=True)
class ArmDriverSettings:
    """What the node publishes, and where."""

    role: str = setting("source", "which arm: topics go to <role>_arm/", choices=("source", "detector"))
    publish_rate_hz: float = setting(50.0, "joint_states, tool_pose and in_position rate (at least 2 Hz: "
                                     "source_control and the orchestrator take an arm silent for 1 s as lost)",
                                     unit="Hz", minimum=2.0)
    base_frame: str = setting("world", "frame_id of tool_pose and of accepted goals")
    tool_frame: str = setting("", "tool frame reported in diagnostics; empty: <role>_arm_tool0")
    joint_prefix: str = setting("", "joint name prefix; empty: <role>_arm_")

    def __post_init__(self):
        validate(self)


class ArmDriverNode(LifecycleNode):
    def __init__(self, node_name: str = "arm_driver", *, arm_factory=None, **kwargs):
        super().__init__(node_name, **kwargs)
        refuse_unavailable_transitions(self)
        self.settings = s = declare_settings(self, ArmDriverSettings)
        self.arm_settings = declare_settings(self, ArmSettings)
        self.sim_settings = declare_settings(self, SimulatedArmSettings, prefix="sim_")
        autostart = declare_settings(self, LifecycleSettings).autostart
        self.role, self.base_frame, self.robot_ip = s.role, s.base_frame, self.arm_settings.robot_ip
        self.tool_frame = s.tool_frame or f"{s.role}_arm_tool0"
        self.joint_prefix = s.joint_prefix or f"{s.role}_arm_"
        self.joint_names = [self.joint_prefix + n for n in JOINT_NAMES]
        self._arm_factory = arm_factory or (lambda: make_arm(self.arm_settings, self.sim_settings))

        ns = f"{self.role}_arm"
        self.joint_pub = self.create_publisher(JointState, f"{ns}/joint_states", 10)
        self.pose_pub = self.create_publisher(PoseStamped, f"{ns}/tool_pose", 10)
        self.true_pose_pub = self.create_publisher(PoseStamped, f"{ns}/true_tool_pose", 10)
        self.in_position_pub = self.create_publisher(Bool, f"{ns}/in_position", 10)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.TOPIC_DIAGNOSTICS, 10)
        self.create_subscription(PoseStamped, f"{ns}/goal_pose", self._on_goal, 10)
        self.create_timer(1.0, self._publish_diagnostics)

        self.faults = WorkerFaults(self, self._on_fault)
        self.error_transition_pending = False
        self._connected_gc = self.create_guard_condition(self._on_connect_done)
        self.connection = BackgroundConnection(self._connected_gc.trigger, self.get_logger().warn, f"{s.role}_arm")
        self._want_active = False
        self.runner = ArmRunner(self.arm_settings, s.publish_rate_hz, self._move_failed,
                                on_thread_died=self.faults.report)
        # connected but inactive, nothing else reads the arm: a lost connection would go unnoticed
        self.watch = ArmWatch(self.arm_settings, period_s=0.5, on_thread_died=self.faults.report)
        self.create_timer(0.5, self._check_watch)
        self._publish_timer = None
        self.last_error = ""
        self.goal_rejections = 0
        self.last_goal_problem = ""
        self._diag_health = self._health()  # the arm's fault state in the last diagnostics published
        if autostart:
            self._autostart_timer = self.create_timer(0.0, self._autostart)

    # -- lifecycle -------------------------------------------------------------------------
    @property
    def lifecycle_state(self) -> str:
        return self._state_machine.current_state[1]

    @property
    def arm(self):
        """The connected arm (between a successful connect and cleanup), else None."""
        return self.connection.arm

    @property
    def connecting(self) -> bool:
        """A connection attempt is under way (background thread)."""
        return self.connection.connecting

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
        except (ArmError, OSError, ValueError) as exc:
            self.last_error = f"configure failed: {exc}"
            self.get_logger().error(self.last_error)
            return TransitionCallbackReturn.FAILURE
        self.last_error = ""
        self.get_logger().info(f"{self.role} arm: connecting to {self.robot_ip or 'simulated arm'}")
        self.connection.start(arm)
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self.arm is not None and (reason := self._lost_while_inactive()) is not None:
            self.last_error = f"connection lost: {reason}"  # _check_watch takes the node to unconfigured
            self.get_logger().error(f"{self.role} arm activate refused: {self.last_error}")
            return TransitionCallbackReturn.FAILURE
        self._want_active = True
        if self.arm is not None:
            self._start_runner()
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        if self.arm is not None and not self.error_transition_pending:
            self.watch.start(self.arm)
        return transition_result(self)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.on_error(state)  # stop, and disconnect off the executor
        return transition_result(self)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._stop_activity()
        self.watch.stop()
        self.connection.disconnect()  # off the executor
        return TransitionCallbackReturn.SUCCESS

    on_shutdown = on_error

    def _start_runner(self) -> None:
        if self.runner.active:
            return
        self.watch.stop()  # the runner reads the arm from now on
        self.runner.start(self.arm)
        self._publish_timer = self.create_timer(self.runner.period_s, self._publish)

    def _stop_activity(self, publish: bool = True) -> None:
        self._want_active = False
        if self._publish_timer is not None:
            self._publish_timer.cancel()
            self.destroy_timer(self._publish_timer)
            self._publish_timer = None
        if self.runner.stop() and publish:
            publish_while_up(self, self.in_position_pub, Bool(data=False))

    # -- connection, off the executor -------------------------------------------------------
    def _on_connect_done(self) -> None:
        if (result := self.connection.take()) is None:
            return
        _, error = result
        if error is not None:
            return self._unconfigure(f"connect failed: {error}", "retry")
        self.get_logger().info(f"{self.role} arm connected ({self.robot_ip or 'simulated'}) in "
                               f"{self.connection.elapsed_s:.2f} s")
        if self._want_active and self.lifecycle_state == "active":
            self._start_runner()
        else:
            self.watch.start(self.arm)

    def _lost_while_inactive(self) -> str | None:
        """Why the connected, inactive arm is no longer usable (None: it is)."""
        if self.watch.lost_reason is not None:
            return self.watch.lost_reason
        return None if self.arm.is_connected else "the arm reports itself disconnected"

    def _check_watch(self) -> None:
        if self.lifecycle_state != "inactive" or self.arm is None or self.connecting:
            return
        if (reason := self._lost_while_inactive()) is not None:
            publish_while_up(self, self.in_position_pub, Bool(data=False))
            self._unconfigure(f"connection lost: {reason}", "reconnect")

    def _unconfigure(self, error: str, retry: str) -> None:
        self.last_error = error
        self.get_logger().error(f"{self.role} arm {error}; going to unconfigured (configure to {retry})")
        to_unconfigured(self)
        self._publish_diagnostics()

    def destroy_node(self):
        # the context may already be shut down (SIGINT): no publishing here
        self._stop_activity(publish=self.context.ok())
        self.watch.stop()
        self.connection.disconnect()  # off the executor
        self.connection.close(5.0)
        return super().destroy_node()

    # -- faults ------------------------------------------------------------------------------
    def _move_failed(self, message: str) -> None:  # the runner's move thread
        self.last_error = message
        self.get_logger().error(message)

    def _on_fault(self, reason: str) -> None:  # executor, from WorkerFaults
        self.last_error = f"fault: {reason}"
        self.get_logger().error(f"{self.role} arm {self.last_error}; lifecycle error transition (configure to "
                                "restart)")
        publish_while_up(self, self.in_position_pub, Bool(data=False))
        error_transition(self)
        self._publish_diagnostics()

    # -- executor side ---------------------------------------------------------------------
    def _on_goal(self, msg: PoseStamped) -> None:
        if not self.runner.active:
            why = ("the controller is not connected yet (goals are taken once it is)" if self.connecting
                   else f"node is {self.lifecycle_state}, not active")
            self.get_logger().warn(f"goal ignored: {why}", throttle_duration_sec=1.0)
            return
        try:
            self.runner.command(pose_msg_to_ur(msg, self.base_frame))
        except ValueError as exc:
            self.goal_rejections += 1
            self.last_goal_problem = problem = str(exc)
            self.get_logger().error(f"goal refused: {problem}", throttle_duration_sec=1.0)
            return
        self.in_position_pub.publish(Bool(data=False))

    def _stamp(self):
        """The ROS time at which the latest sample was measured (the controller's clock mapped onto ours)."""
        age = self.runner.state_age_s()
        now = self.get_clock().now()
        return (now - Duration(nanoseconds=int(age * 1e9))).to_msg() if age != float("inf") else now.to_msg()

    def _publish(self) -> None:
        if (reason := self.runner.lost_reason) is not None:
            self.in_position_pub.publish(Bool(data=False))
            return self._unconfigure(f"connection lost: {reason}", "reconnect")
        if not self.runner.active or self.runner.latest() is None:
            return
        if (snap := self.runner.new_sample()) is not None:  # fresh, each sample once, with its own time
            stamp = self._stamp()
            self.joint_pub.publish(JointState(header=Header(stamp=stamp), name=self.joint_names,
                                              position=[float(v) for v in snap.joint_positions]))
            self.pose_pub.publish(ur_to_pose_msg(snap.tcp_pose, self.base_frame, stamp))
            if snap.true_tcp_pose is not None:
                self.true_pose_pub.publish(ur_to_pose_msg(snap.true_tcp_pose, self.base_frame, stamp))
        self.in_position_pub.publish(Bool(data=self.in_position()))
        if self._health() != self._diag_health:  # a protective stop shorter than the 1 Hz period is seen too
            self._publish_diagnostics()

    def _health(self) -> tuple[str, bool]:
        """The arm's fault state as diagnostics report it: the fault it reports and whether its state is stale."""
        snap = self.runner.latest() if self.runner.active else None
        return (snap.fault, self.runner.stale()) if snap is not None else ("", False)

    def _publish_diagnostics(self) -> None:
        self._diag_health = self._health()
        level, message, values = arm_health(
            self.runner, self.arm, self.lifecycle_state, self.last_error,
            connecting_s=self.connection.elapsed_s if self.connecting else None,
            where=self.robot_ip or "simulated arm", goal_problem=self.last_goal_problem,
            goals_refused=self.goal_rejections, base_frame=self.base_frame, tool_frame=self.tool_frame)
        publish_diagnostic(self, self.diag_pub, level, f"{self.role} arm", self.robot_ip or f"simulated_{self.role}_arm", message,
                           values)


def main(argv=None) -> int:
    return run_settings_node(ArmDriverNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
