"""source_control: the X-ray source behind the beam interlock.

Topics (relative names; namespace the node to place them):
  subscribes  scan/armed (std_msgs/Bool), source_arm/in_position (std_msgs/Bool),
              detector_arm/in_position (std_msgs/Bool), estop (std_msgs/Bool: true latches the e-stop)
  publishes   source/beam_on (std_msgs/Bool, transient-local, on every change and at 10 Hz),
              /diagnostics (diagnostic_msgs/DiagnosticArray, 1 Hz)
  services    source/set_beam (std_srvs/SetBool), source/estop (std_srvs/Trigger),
              source/reset_estop (std_srvs/Trigger)
Parameters: kvp (kVp, 60-120), power_w (W, <= 150), max_report_age_s (s): an arm report
older than this counts as "not in position" and cuts the beam.
"""

from __future__ import annotations

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger

from robot_ct_ros.hardware.xray_source import InterlockedSource, SimulatedXraySource
from robot_ct_ros.nodes.common import run_node

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


class SourceControlNode(Node):
    def __init__(self, **kwargs):
        super().__init__("source_control", **kwargs)
        kvp = self.declare_parameter("kvp", 90.0).value
        power_w = self.declare_parameter("power_w", 150.0).value
        max_age_s = self.declare_parameter("max_report_age_s", 1.0).value
        source = SimulatedXraySource()
        source.configure(kvp, power_w)
        self.interlock = InterlockedSource(source, max_report_age_s=max_age_s)

        self.beam_pub = self.create_publisher(Bool, "source/beam_on", LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.create_subscription(Bool, "scan/armed", lambda m: self._update(scan_armed=m.data), 10)
        self.create_subscription(Bool, "source_arm/in_position", lambda m: self._arm("source", m.data), 10)
        self.create_subscription(Bool, "detector_arm/in_position", lambda m: self._arm("detector", m.data), 10)
        self.create_subscription(Bool, "estop", self._on_estop_topic, 10)
        self.create_service(SetBool, "source/set_beam", self._on_set_beam)
        self.create_service(Trigger, "source/estop", self._on_estop_srv)
        self.create_service(Trigger, "source/reset_estop", self._on_reset_estop)
        self.create_timer(0.1, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self._last_published: bool | None = None
        self._publish_beam()

    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _publish_beam(self, force: bool = False) -> None:
        on = self.interlock.beam_on
        if force or on != self._last_published:
            self.beam_pub.publish(Bool(data=on))
            if self._last_published is not None and on != self._last_published:
                self.get_logger().info(f"beam {'ON' if on else 'OFF'} ({self.interlock.last_reason})")
            self._last_published = on

    def _update(self, **changes) -> None:
        self.interlock.update(self._now_s(), **changes)
        self._publish_beam()

    def _arm(self, which: str, in_position: bool) -> None:
        self.interlock.report_arm(which, in_position, self._now_s())
        self._publish_beam()

    def _on_estop_topic(self, msg: Bool) -> None:
        if msg.data:
            self.interlock.estop(self._now_s())
            self.get_logger().error("e-stop latched")
            self._publish_beam()

    def _on_set_beam(self, request, response):
        response.success, response.message = self.interlock.request_beam(request.data, self._now_s())
        self._publish_beam()
        return response

    def _on_estop_srv(self, request, response):
        self.interlock.estop(self._now_s())
        self._publish_beam()
        response.success, response.message = True, "e-stop latched, beam off"
        return response

    def _on_reset_estop(self, request, response):
        self.interlock.reset_estop(self._now_s())
        response.success, response.message = True, "e-stop reset (scan must be re-armed)"
        return response

    def _tick(self) -> None:
        self.interlock.tick(self._now_s())
        self._publish_beam(force=True)

    def _publish_diagnostics(self) -> None:
        src = self.interlock.source
        inputs = self.interlock.inputs
        level = DiagnosticStatus.ERROR if inputs.estop_latched else DiagnosticStatus.OK
        status = DiagnosticStatus(
            level=level, name=f"{self.get_fully_qualified_name()}: x-ray source",
            hardware_id="simulated_xray_source", message=self.interlock.last_reason,
            values=[KeyValue(key=k, value=str(v)) for k, v in (
                ("beam_on", src.beam_on), ("kvp", src.kvp), ("power_w", src.power_w),
                ("scan_armed", inputs.scan_armed), ("estop_latched", inputs.estop_latched),
                ("beam_on_seconds", f"{src.beam_on_seconds:.3f}"))])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)


def main(argv=None) -> int:
    return run_node(SourceControlNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
