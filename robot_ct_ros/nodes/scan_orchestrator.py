"""scan_orchestrator: runs a scan protocol: move both arms, settle, beam on, expose, beam off, next view.

Topics and services (relative names follow the node namespace; /ct/* from robot_ct_ros.bag.format):
  publishes   source_arm/goal_pose, detector_arm/goal_pose (geometry_msgs/PoseStamped, metres, world_frame):
              the TCP goals of each view (robotic_roi_scan through the inverse hand-eye transform),
              scan/armed (std_msgs/Bool, transient-local): true from start to end of a scan, false on
              completion or abort, scan/status (std_msgs/String JSON {"state", "view", "n_views",
              "frames", "message", "scan_id", "protocol"}, transient-local, on change and at 1 Hz),
              /ct/scan_info (std_msgs/String JSON, transient-local: once per scan, at start),
              /diagnostics (1 Hz)
  subscribes  source_arm/in_position, detector_arm/in_position (std_msgs/Bool), source_arm/tool_pose,
              detector_arm/tool_pose (geometry_msgs/PoseStamped), source/beam_on (std_msgs/Bool), estop
              (std_msgs/Bool), source/estop_latched (std_msgs/Bool: while true no scan starts, and a
              running one aborts), /diagnostics (arm driver ERROR aborts; a detector or x-ray source
              lifecycle node reported not active refuses the start), /ct/projection (frame check),
              /ct/geometry (pairing count)
  clients     source/set_beam (std_srvs/SetBool), pcd/expose (std_srvs/Trigger), <detector node>/get_state
              (lifecycle_msgs/GetState) of the node that offers pcd/expose, asked before each beam-on: a
              detector node that does not answer (killed: it stays in the graph for the DDS lease) or is
              not active gets no beam
  services    scan/start (std_srvs/Trigger): load the protocol, check the graph, start; answers at once
              scan/abort (std_srvs/Trigger): abort now (beam off, disarm)
The sequence (states, safety rules, what aborts) is robot_ct_ros.hardware.scan_sequencer.ScanSequencer,
a timer-driven state machine (tick_period_s): no callback ever blocks, service calls are asynchronous
and polled, so it runs on a SingleThreadedExecutor with every other node. Abort = beam off requested,
scan/armed false, state "aborted" with the reason; frames already taken stay published.

Protocol: a YAML file (protocol_file; config/scan_protocol_*.yaml) with a top-level ``scan_protocol``
mapping, SI units; see robot_ct_ros.hardware.scan_protocol.ScanProtocol. Parameters:
config/scan_orchestrator.yaml (ScanSequencerSettings) and the hand_eye.* parameters.
"""

from __future__ import annotations

import json
import time

from types import SimpleNamespace

from rclpy.node import Node
from rclpy.task import Future
from lifecycle_msgs.srv import GetState
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Bool, String
from std_srvs.srv import SetBool, Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.hardware.scan_protocol import ScanProtocol
from robot_ct_ros.hardware.scan_sequencer import ROLES, ScanSequencer, ScanSequencerSettings
from robot_ct_ros.nodes.common import (LATCHED, STREAM, declare_settings, publish_diagnostic, run_settings_node,
                                      service_thread_node_name)
from robot_ct_ros.nodes.hand_eye_params import declare_hand_eye, matrix_mm_to_pose, pose_to_matrix_mm, stamp_to_ns

__all__ = ["ScanOrchestratorNode", "ScanProtocol", "main"]  # ScanProtocol: where it was imported from before

LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN, "error": DiagnosticStatus.ERROR}


def same_namespace(status_name: str, namespace: str) -> bool:
    """Whether a /diagnostics status ``"<node fully qualified name>: <what>"`` comes from a node in
    ``namespace`` (robot_ct_ros.nodes.common.publish_diagnostic names them so)."""
    node = status_name.split(": ", 1)[0]
    if not node.startswith("/"):
        return True  # a status not named by its node: not ours to judge
    return (node.rsplit("/", 1)[0] or "/") == (namespace.rstrip("/") or "/")


class ScanOrchestratorNode(Node):
    def __init__(self, node_name: str = "scan_orchestrator", **kwargs):
        super().__init__(node_name, **kwargs)
        self.settings = s = declare_settings(self, ScanSequencerSettings)
        self.protocol_file, self.world_frame = s.protocol_file, s.world_frame
        self.hand_eye = declare_hand_eye(self)

        self.goal_pubs = {r: self.create_publisher(PoseStamped, f"{r}_arm/goal_pose", 10) for r in ROLES}
        self.armed_pub = self.create_publisher(Bool, "scan/armed", LATCHED)
        self.status_pub = self.create_publisher(String, "scan/status", LATCHED)
        self.info_pub = self.create_publisher(String, fmt.node_topic(fmt.TOPIC_SCAN_INFO), LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.node_topic(fmt.TOPIC_DIAGNOSTICS), 10)
        self.set_beam = self.create_client(SetBool, "source/set_beam")
        self.expose = self.create_client(Trigger, "pcd/expose")
        self._detector: tuple[str, object] | None = None  # (node name, its get_state client)
        self.scan = ScanSequencer(s, self.hand_eye, self, time.monotonic)

        for r in ROLES:
            self.create_subscription(Bool, f"{r}_arm/in_position", lambda m, r=r: self.scan.on_in_position(r, m.data),
                                     10)
            self.create_subscription(PoseStamped, f"{r}_arm/tool_pose", lambda m, r=r: self._on_tool_pose(r, m), 10)
        self.create_subscription(Bool, "source/beam_on", lambda m: self.scan.on_beam(m.data), LATCHED)
        self.create_subscription(Bool, "estop", lambda m: self.scan.on_estop(m.data), 10)
        self.create_subscription(Bool, "source/estop_latched", lambda m: self.scan.on_estop_latched(m.data), LATCHED)
        self.create_subscription(DiagnosticArray, fmt.node_topic(fmt.TOPIC_DIAGNOSTICS), self._on_diagnostics, 50)
        self.create_subscription(Image, fmt.node_topic(fmt.TOPIC_PROJECTION), lambda m: self.scan.on_frame(
            stamp_to_ns(m.header.stamp), (m.height, m.width)), STREAM)
        self.create_subscription(PoseArray, fmt.node_topic(fmt.TOPIC_GEOMETRY), lambda m: self.scan.on_geometry(
            stamp_to_ns(m.header.stamp)), STREAM)
        self.create_service(Trigger, "scan/start", self._on_start)
        self.create_service(Trigger, "scan/abort", self._on_abort)
        self.create_timer(s.tick_period_s, self.scan.tick)
        self.create_timer(1.0, self._periodic)

    # -- the scan, as the sequencer has it ------------------------------------------------------
    state = property(lambda self: self.scan.state)
    message = property(lambda self: self.scan.message)
    view = property(lambda self: self.scan.view)
    frames = property(lambda self: self.scan.frames)
    scan_id = property(lambda self: self.scan.scan_id)
    protocol = property(lambda self: self.scan.protocol)
    running = property(lambda self: self.scan.running)

    def start(self) -> tuple[bool, str]:
        """Load the protocol, check the graph and start a scan: (started, why or what)."""
        return self.scan.start()

    def abort(self, reason: str) -> None:
        self.scan.abort(reason)

    # -- ScanPorts: what the sequencer does to the graph -----------------------------------------
    def log(self, level: str, message: str) -> None:
        logger = self.get_logger()  # one call site per severity (rclpy keys its log filters by call site)
        if level == "error":
            logger.error(message)
        elif level == "warn":
            logger.warn(message)
        else:
            logger.info(message)

    def publish_goals(self, goals: dict) -> None:
        stamp = self.get_clock().now().to_msg()
        for role, T in goals.items():
            msg = PoseStamped()
            msg.header.stamp = stamp
            msg.header.frame_id = self.world_frame
            matrix_mm_to_pose(T, msg.pose)
            self.goal_pubs[role].publish(msg)

    def publish_armed(self, armed: bool) -> None:
        self.armed_pub.publish(Bool(data=armed))

    def publish_status(self, status: dict) -> None:
        self.status_pub.publish(String(data=json.dumps(status)))

    def publish_scan_info(self, info: dict) -> None:
        self.info_pub.publish(String(data=json.dumps(info)))

    def call_set_beam(self, on: bool):
        return self.set_beam.call_async(SetBool.Request(data=on))

    def call_expose(self):
        return self.expose.call_async(Trigger.Request())

    def beam_service_ready(self) -> bool:
        return self.set_beam.service_is_ready()

    def expose_service_ready(self) -> bool:
        return self.expose.service_is_ready()

    def _find_detector(self) -> tuple[str, object] | None:
        """(fully qualified name, get_state client) of the lifecycle node that offers pcd/expose: the node
        itself, or the owner of the helper node a ServiceThread serves it from (``_<owner>_pcd_expose``)."""
        if self._detector is not None and self._detector[1].service_is_ready():
            return self._detector
        if self._detector is not None:  # its node left: a new client for whichever node offers pcd/expose now
            self.destroy_client(self._detector[1])
        self._detector = None
        service = self.resolve_service_name("pcd/expose")

        def services(name, ns):
            try:
                return {n for n, _ in self.get_service_names_and_types_by_node(name, ns)}
            except Exception:  # noqa: BLE001 - the node left the graph meanwhile
                return set()

        nodes = self.get_node_names_and_namespaces()
        for name, ns in nodes:
            if service not in services(name, ns):
                continue
            for candidate in [name] + [n for n, n_ns in nodes
                                       if n_ns == ns and name == service_thread_node_name(n, "pcd/expose")]:
                fqn = (ns.rstrip("/") + "/" + candidate) if ns != "/" else "/" + candidate
                if fqn + "/get_state" in services(candidate, ns):
                    self._detector = (fqn, self.create_client(GetState, fqn + "/get_state"))
                    return self._detector
        return None

    def call_detector_check(self):
        detector = self._find_detector()
        if detector is None:
            return None
        name, client = detector
        answer = Future()

        def done(call):
            try:
                label = call.result().current_state.label
            except Exception as exc:  # noqa: BLE001 - the call failed: the sequencer reports it
                answer.set_exception(exc)
                return
            answer.set_result(SimpleNamespace(success=label == "active",
                                              message=f"{name} is {label}, not active" if label != "active"
                                              else f"{name} is active"))
        client.call_async(GetState.Request()).add_done_callback(done)
        return answer

    def detector_node(self) -> str:
        return self._detector[0] if self._detector is not None else ""

    def armed_subscribers(self) -> int:
        return self.armed_pub.get_subscription_count()

    def goal_subscribers(self, role: str) -> int:
        return self.goal_pubs[role].get_subscription_count()

    # -- callbacks ---------------------------------------------------------------------------------
    def _on_tool_pose(self, role: str, msg: PoseStamped) -> None:
        if msg.header.frame_id not in ("", self.world_frame):
            return
        try:
            self.scan.on_tool_pose(role, pose_to_matrix_mm(msg.pose))
        except ValueError:
            return

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        # /diagnostics is global: only the statuses of nodes in this scanner's namespace count
        # (another scanner's arm error must not abort this scan)
        self.scan.on_diagnostics([(s.name, s.level == DiagnosticStatus.ERROR, s.message,
                                   next((kv.value for kv in s.values if kv.key == "lifecycle_state"), None))
                                  for s in msg.status if same_namespace(s.name, self.get_namespace())])

    def _on_start(self, request, response):
        response.success, response.message = self.scan.start()
        return response

    def _on_abort(self, request, response):
        if self.scan.running:
            self.scan.abort("aborted on request")
            response.success, response.message = True, "scan aborted"
        else:
            self.scan.safe_off()
            # the switch-off is asked for, not awaited: say what the source last reported, not what it should do
            beam = "; the source still reports the beam ON" if self.scan.beam_on else ""
            response.success, response.message = True, (f"no scan running ({self.scan.state}); beam off requested, "
                                                         f"disarmed{beam}")
        return response

    def _periodic(self) -> None:
        self.scan.publish_status()
        level, values = self.scan.health()
        publish_diagnostic(self, self.diag_pub, LEVELS[level], "scan", "scan_orchestrator", self.scan.message, values)

    def destroy_node(self):
        if self.scan.running and self.context.ok():
            self.scan.abort("node shutting down")
        return super().destroy_node()


def main(argv=None) -> int:
    return run_settings_node(ScanOrchestratorNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
