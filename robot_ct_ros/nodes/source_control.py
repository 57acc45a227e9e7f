"""source_control: the X-ray source behind the beam interlock, as a ROS 2 lifecycle node.

Topics (relative names; namespace the node to place them):
  subscribes  scan/armed (std_msgs/Bool), source_arm/in_position (std_msgs/Bool),
              detector_arm/in_position (std_msgs/Bool), estop (std_msgs/Bool: true latches the e-stop)
  publishes   source/beam_on (std_msgs/Bool, transient-local: on every change, at 10 Hz while active,
              and on every transition out of active: false, unless the source refused to switch off), source/estop_latched (std_msgs/Bool,
              transient-local, on every change: the orchestrator refuses to start a scan while it is true),
              /diagnostics (diagnostic_msgs/DiagnosticArray, 1 Hz)
  services    source/set_beam (std_srvs/SetBool), source/estop (std_srvs/Trigger),
              source/reset_estop (std_srvs/Trigger); <node>/change_state, <node>/get_state (lifecycle_msgs)
Parameters: kvp (kVp, 60-120), power_w (W, <= 150), max_report_age_s (s): an arm report
older than this counts as "not in position" and cuts the beam; max_beam_on_s (s): a beam on for longer
is cut (no exposure takes that long, so a controller that dies with the beam on cannot leave it on; a
WARN on /diagnostics until the beam is switched on again or a scan is armed anew)
(hardware.xray_source.SourceSettings); autostart (default true). An e-stop disarms the scan: after
source/reset_estop the beam needs scan/armed true anew.

Lifecycle: configure builds the (simulated) source at kvp/power_w behind the interlock, activate
serves source/set_beam and publishes the beam state, deactivate switches the beam off at once and
refuses beam requests, cleanup/shutdown/error switch it off and release the source (one that refuses
to switch off is reported on, an ERROR, and retried every tick; configure is refused meanwhile). The
beam is off in every state but active. A driver fault (SourceError, or any exception the driver
raises on the beam path) is a refused answer or, for a switch-off, retried every tick until it
succeeds (even while the interlock permits the beam); either is an ERROR on /diagnostics until the
refused command succeeds. The interlock inputs (armed, arm reports, e-stop) are followed in every
state, so they are current on activation; an e-stop is latched in any state (one received while
unconfigured latches the source built by the next configure). With autostart the node configures and
activates itself in its constructor, so a plain ``ros2 run`` works without a lifecycle manager.
"""

from __future__ import annotations

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from std_msgs.msg import Bool
from std_srvs.srv import SetBool, Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.hardware.xray_source import InterlockedSource, SimulatedXraySource, SourceError, SourceSettings
from robot_ct_ros.nodes.common import (LATCHED, LifecycleSettings, declare_settings, publish_diagnostic,
                                      publish_while_up, refuse_unavailable_transitions, run_settings_node)

__all__ = ["SourceControlNode", "LATCHED", "main"]



class SourceControlNode(LifecycleNode):
    def __init__(self, node_name: str = "source_control", *, source_factory=None, **kwargs):
        super().__init__(node_name, **kwargs)
        refuse_unavailable_transitions(self)
        self.settings = declare_settings(self, SourceSettings)
        s = self.settings
        self.kvp, self.power_w, self.max_age_s = s.kvp, s.power_w, s.max_report_age_s
        autostart = declare_settings(self, LifecycleSettings).autostart
        self._source_factory = source_factory or SimulatedXraySource
        self.interlock: InterlockedSource | None = None  # exists between configure and cleanup
        self._released_on: InterlockedSource | None = None  # released (shutdown, error) with the beam still on
        self._active = False
        self._estop_unconfigured = False
        self.last_error = ""
        self._refused_settings = ""  # why the source refused kvp/power_w at the last configure
        self._starting = False

        self.beam_pub = self.create_publisher(Bool, "source/beam_on", LATCHED)
        self.estop_pub = self.create_publisher(Bool, "source/estop_latched", LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.TOPIC_DIAGNOSTICS, 10)
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
        self._logged_fault = ""
        self._publish_beam()
        self._publish_estop()
        if autostart:
            self._starting = True  # a refusal of the parameters is then the executable's one line, not a log too
            configured = self.trigger_configure() == TransitionCallbackReturn.SUCCESS
            self._starting = False
            if configured:
                self.trigger_activate()
            elif self._refused_settings:  # read-only parameters: no later configure can succeed
                raise ValueError(f"parameters kvp/power_w: {self._refused_settings}")

    # -- lifecycle ---------------------------------------------------------------------------
    @property
    def lifecycle_state(self) -> str:
        return self._state_machine.current_state[1]

    def _holder(self) -> InterlockedSource | None:
        """The configured source, or one released while it refused to switch off (the driver's state counts)."""
        return self.interlock if self.interlock is not None else self._released_on

    @property
    def beam_on(self) -> bool:
        holder = self._holder()
        return holder is not None and holder.beam_on

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        if self._released_on is not None and self._released_on.beam_on:  # not a second source beside a beam on
            self.last_error = ("configure refused: the source released with the beam on still refuses to switch "
                               f"off ({self._released_on.fault})")
            self.get_logger().error(self.last_error)
            return TransitionCallbackReturn.FAILURE
        self._released_on = None
        try:
            interlock = self.settings.interlocked(self._source_factory())
        except (SourceError, ValueError, OSError) as exc:
            self.last_error = f"configure failed: {exc}"
            self._refused_settings = str(exc) if isinstance(exc, SourceError) else ""  # the source said no to them
            if not (self._starting and self._refused_settings):
                self.get_logger().error(self.last_error)
            return TransitionCallbackReturn.FAILURE
        if self._estop_unconfigured:
            interlock.estop(self._now_s())
        self.interlock, self.last_error = interlock, ""
        self._publish_estop()
        self.get_logger().info(f"source configured: {self.kvp} kVp, {self.power_w} W")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = True
        self._publish_beam(force=True)
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._beam_off("deactivated")
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._beam_off("cleaned up")
        if self.beam_on:  # keep the source (and the tick retrying the switch-off) rather than lose it with the beam on
            self.get_logger().error("cleanup refused: the beam is still on")
            return TransitionCallbackReturn.FAILURE
        self._release("cleaned up")
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("shut down")
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release("error")
        return TransitionCallbackReturn.SUCCESS

    def _beam_off(self, why: str) -> None:
        """Refuse beam requests from now on and switch the beam off at once."""
        self._active = False
        if self.interlock is not None:
            done, answer = self.interlock.request_beam(False, self._now_s())
            if not done:  # logged, not raised: every way out of active must finish (destroy_node included)
                self.get_logger().error(f"source_control {why} with the beam on: {answer}")
            self.interlock.last_reason = f"source_control {why}"
        self._publish_beam(force=True)  # not after SIGINT: publish_while_up then publishes nothing

    def _release(self, why: str) -> None:
        """Switch the beam off and drop the source. A source that refuses to switch off is not reported off:
        it is kept aside (the beam state published and on /diagnostics is the driver's, an ERROR) and the
        switch-off is retried on every tick while the node runs."""
        self._beam_off(why)
        il = self.interlock
        if il is not None and il.inputs.estop_latched:
            self._estop_unconfigured = True  # the latch outlives the source object
        if il is not None and il.beam_on:
            self._released_on = il
            self.get_logger().error(f"the source refused to switch off: the beam may still be on ({il.fault}); "
                                    f"source_control {why}, the switch-off is retried while the node runs")
        self.interlock = None
        self._publish_beam(force=True)

    def destroy_node(self):
        self._release("destroyed")
        return super().destroy_node()

    # -- interlock inputs (followed in every state) --------------------------------------------
    def _now_s(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _publish_beam(self, force: bool = False) -> None:
        on = self.beam_on
        if force or on != self._last_published:
            if not publish_while_up(self, self.beam_pub, Bool(data=on)):
                return
            if self._last_published is not None and on != self._last_published:
                reason = self.interlock.last_reason if self.interlock is not None else self.lifecycle_state
                self.get_logger().info(f"beam {'ON' if on else 'OFF'} ({reason})")
            self._last_published = on

    def _update(self, **changes) -> None:
        if self.interlock is not None:
            self.interlock.update(self._now_s(), **changes)
            self._publish_beam()

    def _arm(self, which: str, in_position: bool) -> None:
        if self.interlock is not None:
            self.interlock.report_arm(which, in_position, self._now_s())
            self._publish_beam()

    @property
    def estop_latched(self) -> bool:
        return self._estop_unconfigured or (self.interlock is not None and self.interlock.inputs.estop_latched)

    def _publish_estop(self) -> None:
        publish_while_up(self, self.estop_pub, Bool(data=self.estop_latched))

    def _estop(self) -> None:
        if self.interlock is None:
            self._estop_unconfigured = True
        else:
            self.interlock.estop(self._now_s())
        self.get_logger().error("e-stop latched")
        self._publish_beam()
        self._publish_estop()

    def _on_estop_topic(self, msg: Bool) -> None:
        if msg.data:
            self._estop()

    # -- services ------------------------------------------------------------------------------
    def _on_set_beam(self, request, response):
        if not request.data:
            response.success, response.message = True, "beam off"
            if self._holder() is not None:
                response.success, response.message = self._holder().request_beam(False, self._now_s())
            self._publish_beam()
        elif not self._active:
            response.success = False
            response.message = f"beam refused: source_control is {self.lifecycle_state}, not active"
        else:
            response.success, response.message = self.interlock.request_beam(True, self._now_s())
            self._publish_beam()
        return response

    def _on_estop_srv(self, request, response):
        self._estop()
        if self.beam_on:  # the driver's state, not the request's: a refused switch-off is not reported off
            fault = self._holder().fault if self._holder() is not None else ""
            response.success = False
            response.message = (f"e-stop latched, but the beam is still ON: "
                                f"{fault or 'the source did not switch off'}; the switch-off is retried on every tick")
        else:
            response.success, response.message = True, "e-stop latched, beam off"
        return response

    def _on_reset_estop(self, request, response):
        self._estop_unconfigured = False
        if self.interlock is not None:
            self.interlock.reset_estop(self._now_s())
        self._publish_estop()
        response.success, response.message = True, "e-stop reset (scan must be re-armed)"
        return response

    # -- periodic -------------------------------------------------------------------------------
    def _tick(self) -> None:
        if self.interlock is not None:
            self.interlock.tick(self._now_s())  # retries a switch-off the source refused
            if self.interlock.fault != self._logged_fault:
                if self.interlock.fault:
                    self.get_logger().error(self.interlock.fault)
                self._logged_fault = self.interlock.fault
        if self._active:
            self._publish_beam(force=True)
        elif self.beam_on:  # every way out of active cuts the beam, unless the source refused: retry
            holder = self._holder()
            if holder is not self.interlock or not holder.off_pending:  # else its tick above retried it
                holder.request_beam(False, self._now_s())
            if self._released_on is not None and not self._released_on.beam_on:
                self.get_logger().info("the released source switched off at last")
                self._released_on = None
            self._publish_beam(force=True)

    def _beam_on_seconds(self, il: InterlockedSource) -> float:
        total = getattr(il.source, "total_beam_on_s", None)  # the current stretch too, where the driver can tell
        return total(self._now_s()) if total is not None else getattr(il.source, "beam_on_seconds", 0.0)

    def _publish_diagnostics(self) -> None:
        state = self.lifecycle_state
        il = self.interlock
        latched = self.estop_latched
        fault = il.fault if il is not None else ""
        if il is None and self._released_on is not None:  # released with the beam on: say so, not the state
            fault = ("the source refused to switch off: the beam may still be on"
                     f" ({self._released_on.fault or 'no fault reported'})")
        if latched or self.last_error or fault:
            level = DiagnosticStatus.ERROR
        elif not self._active or (il is not None and il.watchdog_cut):  # the cut says the controller died
            level = DiagnosticStatus.WARN
        else:
            level = DiagnosticStatus.OK
        values = [("lifecycle_state", state), ("beam_on", self.beam_on), ("kvp", self.kvp),
                  ("power_w", self.power_w), ("estop_latched", latched), ("source_fault", fault or "-")]
        if il is not None:
            values += [("scan_armed", il.inputs.scan_armed), ("last_beam_cut", il.last_cut_reason or "-"),
                       ("beam_on_seconds", f"{self._beam_on_seconds(il):.3f}")]
        watchdog = il.watchdog_cut if il is not None and self._active else ""
        message = self.last_error or fault or watchdog or (il.last_reason if il is not None and self._active else state)
        publish_diagnostic(self, self.diag_pub, level, "x-ray source", "simulated_xray_source", message, values)


def main(argv=None) -> int:
    return run_settings_node(SourceControlNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
