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
              (std_msgs/Bool), /diagnostics (arm driver ERROR aborts; a detector or x-ray source
              lifecycle node reported not active refuses the start), /ct/projection (frame check),
              /ct/geometry (pairing count)
  clients     source/set_beam (std_srvs/SetBool), pcd/expose (std_srvs/Trigger)
  services    scan/start (std_srvs/Trigger): load the protocol, check the graph, start; answers at once
              scan/abort (std_srvs/Trigger): abort now (beam off, disarm)
States (scan/status "state"): idle, moving, settling, beam_on, exposing, beam_off, waiting_frame,
finishing, done, aborted; "view" is the 0-based index of the view in progress, "frames" the frames
taken so far. The sequence is a timer-driven state machine (tick_period_s): no callback
ever blocks, service calls are asynchronous and polled, so it runs on a SingleThreadedExecutor with
every other node.

Safety: the beam is requested only after both arms reported in position (an in_position false and
then true after the goal was sent, with the measured pose at the goal) and stayed so through the
settle time, only for the exposure, and switched off as soon as the detector answers. Any fault
aborts: an arm leaving position or falling silent, an arm driver reporting ERROR, a move not done
within move_timeout_s, the interlock refusing the beam, the beam dropping during an exposure or
showing up outside one, the detector failing or timing out, a frame not arriving or of the wrong
size, an e-stop. Abort = beam off requested, scan/armed false, state "aborted" with the reason.
Frames already taken stay published (the recorder keeps them). The frame whose exposure a beam drop
interrupted is not one of them: pcd_grabber publishes it on /ct/projection_rejected only (README
"Bag format"), so it is neither counted here nor paired with a geometry.

Protocol: a YAML file (protocol_file; config/scan_protocol_*.yaml) with a top-level ``scan_protocol``
mapping, SI units; see :class:`ScanProtocol`.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field

import numpy as np
import yaml
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseArray, PoseStamped
from sensor_msgs.msg import Image
from std_msgs.msg import Bool, String
from std_srvs.srv import SetBool, Trigger

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.geometry import ConeGeometry
from robot_ct_ros.ct.hand_eye import HandEye, tool_goals_from_geometry
from robot_ct_ros.ct.trajectory import SeedSystem, robotic_roi_scan
from robot_ct_ros.nodes.common import run_node
from robot_ct_ros.nodes.hand_eye_params import declare_hand_eye, matrix_mm_to_pose, pose_to_matrix_mm, stamp_to_ns

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
STREAM = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
ROLES = ("source", "detector")
RUNNING = ("moving", "settling", "beam_on", "exposing", "beam_off", "waiting_frame", "finishing")
IN_POSITION_REQUIRED = ("settling", "beam_on", "exposing", "beam_off")
DEVICE_DIAGNOSTICS = ("detector", "x-ray source")
"""/diagnostics status names (suffixes) of pcd_grabber and source_control, whose
``lifecycle_state`` value must be "active" for a scan to start."""
DEVICE_REPORT_MAX_AGE_S = 3.0  # they report at 1 Hz; an older report is not evidence either way


# ------------------------------------------------------------------------------ protocol
@dataclass(frozen=True)
class ScanProtocol:
    """A scan protocol (SI units, as in the YAML file).

    Trajectory (robotic_roi_scan of the seed system): ``n_views`` views over ``arc_deg`` from
    ``start_deg`` about ``axis`` through ``roi_center_m``; source at ``sdd_m / magnification``
    from the ROI centre; offset detector for ``fov_diameter_m``. Detector read-out: ``n_rows`` x
    ``n_cols`` pixels (0 = the full seed detector) of ``raw_pixel_m * binning``. Timing:
    ``settle_s`` after both arms are in position, ``exposure_s`` (must match the pcd_grabber's),
    ``move_timeout_s`` per move, ``exposure_timeout_s`` for the detector's answer. ``kvp``,
    ``power_w``: recorded in the scan info (the source is configured on source_control).
    ``voxel_size_m``, ``roi_size_m``: the reconstruction grid for the scan info (0 = derived
    by the reader).
    """

    name: str = "protocol"
    n_views: int = 360
    roi_center_m: tuple = (0.4, 0.0, 0.3)
    axis: tuple = (0.0, 0.0, 1.0)
    fov_diameter_m: float = 0.05
    start_deg: float = 0.0
    arc_deg: float = 360.0
    sdd_m: float = 0.3424
    magnification: float = 2.67
    n_rows: int = 0
    n_cols: int = 0
    binning: int = 2
    raw_pixel_m: float = 55e-6
    exposure_s: float = 0.1
    settle_s: float = 0.05
    move_timeout_s: float = 30.0
    exposure_timeout_s: float = 5.0
    kvp: float = 90.0
    power_w: float = 150.0
    voxel_size_m: float = 0.0
    roi_size_m: tuple = (0.0, 0.0, 0.0)
    notes: dict = field(default_factory=dict)

    @classmethod
    def from_dict(cls, d: dict) -> "ScanProtocol":
        if not isinstance(d, dict):
            raise ValueError("a scan protocol must be a mapping")
        d = dict(d.get("scan_protocol", d))
        det = dict(d.pop("detector", None) or {})
        for k in ("n_rows", "n_cols", "binning", "raw_pixel_m"):
            if k in det:
                d[k] = det.pop(k)
        unknown = (set(d) - set(cls.__dataclass_fields__)) | set(det)
        if unknown:
            raise ValueError(f"unknown scan protocol keys: {', '.join(sorted(unknown))}")
        for k in ("roi_center_m", "axis", "roi_size_m"):
            if k in d:
                d[k] = tuple(float(x) for x in np.broadcast_to(np.asarray(d[k], float), (3,)))
        proto = cls(**d)
        proto.validate()
        return proto

    @classmethod
    def from_yaml(cls, path) -> "ScanProtocol":
        with open(path) as f:
            return cls.from_dict(yaml.safe_load(f))

    def validate(self) -> None:
        if self.n_views < 1:
            raise ValueError("n_views must be positive")
        if not (0 < self.exposure_s < self.exposure_timeout_s):
            raise ValueError("need 0 < exposure_s < exposure_timeout_s")
        if self.settle_s < 0 or self.move_timeout_s <= 0:
            raise ValueError("settle_s must be >= 0 and move_timeout_s > 0")
        if self.magnification <= 1 or self.sdd_m <= 0:
            raise ValueError("need sdd_m > 0 and magnification > 1")
        self.geometry()  # raises on an impossible field of view

    def geometry(self) -> ConeGeometry:
        """The nominal geometry (mm) of the scan."""
        system = SeedSystem(sdd_mm=self.sdd_m * 1e3, magnification=self.magnification,
                            raw_pixel_mm=self.raw_pixel_m * 1e3, binning=self.binning, n_views=self.n_views)
        return robotic_roi_scan(system, roi_center_mm=np.asarray(self.roi_center_m) * 1e3,
                                fov_diameter_mm=self.fov_diameter_m * 1e3, n_views=self.n_views,
                                binning=self.binning, axis=self.axis, n_rows=self.n_rows or None,
                                n_cols=self.n_cols or None, arc_rad=math.radians(self.arc_deg),
                                start_rad=math.radians(self.start_deg))

    def scan_info(self, geom: ConeGeometry, scan_id: str) -> dict:
        kw = {}
        if self.voxel_size_m > 0:
            kw["voxel_size_mm"] = self.voxel_size_m * 1e3
        if min(self.roi_size_m) > 0:
            kw["roi_size_mm"] = np.asarray(self.roi_size_m) * 1e3
        notes = {"scan_id": scan_id, "protocol": self.name, "kvp": self.kvp, "power_w": self.power_w,
                 "exposure_s": self.exposure_s, "settle_s": self.settle_s, **self.notes}
        return fmt.scan_info_for(geom, binning=self.binning, projection_units="counts",
                                 roi_center_mm=np.asarray(self.roi_center_m) * 1e3, notes=notes, **kw)


# ------------------------------------------------------------------------------ node
class ScanOrchestratorNode(Node):
    def __init__(self, node_name: str = "scan_orchestrator", **kwargs):
        super().__init__(node_name, **kwargs)
        p = self.declare_parameter
        self.protocol_file = p("protocol_file", "").value
        self.tick_period_s = float(p("tick_period_s", 0.02).value)
        self.arm_report_timeout_s = float(p("arm_report_timeout_s", 1.0).value)
        self.goal_tolerance_m = float(p("goal_tolerance_m", 1e-3).value)
        self.goal_tolerance_rad = float(p("goal_tolerance_rad", 0.01).value)
        self.service_timeout_s = float(p("service_timeout_s", 2.0).value)
        self.frame_timeout_s = float(p("frame_timeout_s", 2.0).value)
        self.pairing_timeout_s = float(p("pairing_timeout_s", 1.0).value)
        self.world_frame = p("world_frame", fmt.FRAME_WORLD).value
        autostart = p("autostart", False).value
        self.hand_eye: HandEye = declare_hand_eye(self)

        self.goal_pubs = {r: self.create_publisher(PoseStamped, f"{r}_arm/goal_pose", 10) for r in ROLES}
        self.armed_pub = self.create_publisher(Bool, "scan/armed", LATCHED)
        self.status_pub = self.create_publisher(String, "scan/status", LATCHED)
        self.info_pub = self.create_publisher(String, fmt.TOPIC_SCAN_INFO, LATCHED)
        self.diag_pub = self.create_publisher(DiagnosticArray, fmt.TOPIC_DIAGNOSTICS, 10)
        for r in ROLES:
            self.create_subscription(Bool, f"{r}_arm/in_position", lambda m, r=r: self._on_in_position(r, m), 10)
            self.create_subscription(PoseStamped, f"{r}_arm/tool_pose", lambda m, r=r: self._on_tool_pose(r, m), 10)
        self.create_subscription(Bool, "source/beam_on", self._on_beam, LATCHED)
        self.create_subscription(Bool, "estop", self._on_estop, 10)
        self.create_subscription(DiagnosticArray, fmt.TOPIC_DIAGNOSTICS, self._on_diagnostics, 50)
        self.create_subscription(Image, fmt.TOPIC_PROJECTION, self._on_frame, STREAM)
        self.create_subscription(PoseArray, fmt.TOPIC_GEOMETRY, self._on_geometry, STREAM)
        self.set_beam = self.create_client(SetBool, "source/set_beam")
        self.expose = self.create_client(Trigger, "pcd/expose")
        self.create_service(Trigger, "scan/start", self._on_start)
        self.create_service(Trigger, "scan/abort", self._on_abort)

        # arm and beam observations
        self._in_pos: dict[str, bool | None] = {r: None for r in ROLES}
        self._in_pos_t: dict[str, float] = {r: -math.inf for r in ROLES}
        self._pose: dict[str, np.ndarray | None] = {r: None for r in ROLES}
        self._pose_t: dict[str, float] = {r: -math.inf for r in ROLES}
        # latest /diagnostics lifecycle state of the detector and the source: (time, state)
        self._device_state: dict[str, tuple[float, str]] = {}
        self._beam_on: bool | None = None
        # scan state
        self.state = "idle"
        self.message = "ready"
        self.protocol: ScanProtocol | None = None
        self.geom: ConeGeometry | None = None
        self._goals: dict[str, np.ndarray] = {}
        self._goal_list: dict[str, np.ndarray] = {}
        self.view = 0
        self.frames = 0
        self.scan_id = ""
        self.frame_stamps: list[int] = []
        self._seen_frames: dict[int, tuple[int, int]] = {}
        self._seen_geometries: set[int] = set()
        self._t_state = 0.0
        self._future = None
        self._saw_false: dict[str, bool] = {}
        self._beam_expect: bool | None = None
        self._beam_confirmed = False
        self._expected_stamp: int | None = None
        self.last_abort_reason = ""

        self.create_timer(self.tick_period_s, self._tick)
        self.create_timer(1.0, self._periodic)
        if self.protocol_file:
            try:
                self.protocol = ScanProtocol.from_yaml(self.protocol_file)
            except (OSError, ValueError, TypeError, yaml.YAMLError) as exc:
                self.get_logger().error(f"protocol {self.protocol_file}: {exc}")
        self._autostart = autostart
        self._autostart_next = 0.0
        self._autostart_reason = ""
        self._publish_armed(False)
        self._publish_status()

    # -- helpers -------------------------------------------------------------------------------
    def _now(self) -> float:
        return time.monotonic()

    def _set_state(self, state: str, message: str | None = None) -> None:
        self.state = state
        if message is not None:
            self.message = message
        self._t_state = self._now()
        self._publish_status()

    def _publish_status(self) -> None:
        n = self.protocol.n_views if self.protocol is not None else 0
        self.status_pub.publish(String(data=json.dumps({
            "state": self.state, "view": self.view, "n_views": n, "frames": self.frames, "message": self.message,
            "scan_id": self.scan_id, "protocol": self.protocol.name if self.protocol else ""})))

    def _publish_armed(self, armed: bool) -> None:
        self.armed_pub.publish(Bool(data=armed))

    def _request_beam(self, on: bool):
        self._beam_expect = on
        self._beam_confirmed = False
        return self.set_beam.call_async(SetBool.Request(data=on))

    @property
    def running(self) -> bool:
        return self.state in RUNNING

    # -- observations ----------------------------------------------------------------------------
    def _on_in_position(self, role: str, msg: Bool) -> None:
        self._in_pos[role] = bool(msg.data)
        self._in_pos_t[role] = self._now()
        if not msg.data:
            if self.state == "moving":
                self._saw_false[role] = True
            elif self.state in IN_POSITION_REQUIRED:
                self.abort(f"{role} arm left its position during view {self.view} ({self.state})")

    def _on_tool_pose(self, role: str, msg: PoseStamped) -> None:
        if msg.header.frame_id not in ("", self.world_frame):
            return
        try:
            self._pose[role] = pose_to_matrix_mm(msg.pose)
        except ValueError:
            return
        self._pose_t[role] = self._now()

    def _on_beam(self, msg: Bool) -> None:
        on = bool(msg.data)
        self._beam_on = on
        if not self.running or self._beam_expect is None:
            return
        if on == self._beam_expect:
            self._beam_confirmed = True
            return
        if not self._beam_confirmed:
            return  # published before our request was served: stale
        if self._beam_expect:
            self.abort(f"beam lost during view {self.view} ({self.state}): interlock or source cut it")
        else:
            self.abort(f"beam on outside an exposure (view {self.view}, {self.state})")

    def _on_estop(self, msg: Bool) -> None:
        if msg.data and self.running:
            self.abort("e-stop")

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        for s in msg.status:
            device = next((d for d in DEVICE_DIAGNOSTICS if s.name.endswith(": " + d)), None)
            state = next((kv.value for kv in s.values if kv.key == "lifecycle_state"), None)
            if device is not None and state is not None:
                self._device_state[device] = (self._now(), state)
        if not self.running:
            return
        for s in msg.status:
            if s.level == DiagnosticStatus.ERROR and s.name.endswith((": source arm", ": detector arm")):
                self.abort(f"arm driver error: {s.name}: {s.message}")
                return

    def _on_frame(self, msg: Image) -> None:
        if self.running:
            self._seen_frames[stamp_to_ns(msg.header.stamp)] = (msg.height, msg.width)

    def _on_geometry(self, msg: PoseArray) -> None:
        if self.running:
            self._seen_geometries.add(stamp_to_ns(msg.header.stamp))

    # -- services --------------------------------------------------------------------------------
    def _on_start(self, request, response):
        response.success, response.message = self.start()
        return response

    def _on_abort(self, request, response):
        if self.running:
            self.abort("aborted on request")
            response.success, response.message = True, "scan aborted"
        else:
            self._safe_off()
            response.success, response.message = True, f"no scan running ({self.state}); beam off, disarmed"
        return response

    def start(self) -> tuple[bool, str]:
        if self.running:
            return False, f"a scan is running ({self.state}, view {self.view})"
        try:
            if self.protocol_file:
                self.protocol = ScanProtocol.from_yaml(self.protocol_file)
            elif self.protocol is None:
                self.protocol = ScanProtocol()
            geom = self.protocol.geometry()
            src, det = tool_goals_from_geometry(geom, self.hand_eye)
        except (OSError, ValueError, TypeError, yaml.YAMLError) as exc:
            return False, f"protocol: {exc}"
        now = self._now()
        problems = []
        if not self.set_beam.service_is_ready():
            problems.append("source/set_beam not available (source_control)")
        if not self.expose.service_is_ready():
            problems.append("pcd/expose not available (pcd_grabber)")
        for device, (t, state) in self._device_state.items():
            if now - t <= DEVICE_REPORT_MAX_AGE_S and state != "active":
                problems.append(f"{device} is {state}, not active (lifecycle: configure and activate it)")
        if self.armed_pub.get_subscription_count() < 1:
            problems.append("nobody subscribes to scan/armed (source_control)")
        for r in ROLES:
            if now - self._pose_t[r] > self.arm_report_timeout_s or now - self._in_pos_t[r] > self.arm_report_timeout_s:
                problems.append(f"{r} arm not reporting")
            elif self.goal_pubs[r].get_subscription_count() < 1:
                problems.append(f"{r} arm driver not subscribed to its goals")
        if problems:
            return False, "cannot start: " + "; ".join(problems)
        self.geom = geom
        self._goal_list = {"source": src, "detector": det}
        self.scan_id = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + f"-{int(now * 1e3) % 1000:03d}"
        self.view, self.frames = 0, 0
        self.frame_stamps, self._seen_frames, self._seen_geometries = [], {}, set()
        self.last_abort_reason = ""
        self.info_pub.publish(String(data=json.dumps(self.protocol.scan_info(geom, self.scan_id))))
        self._publish_armed(True)
        self._beam_expect, self._beam_confirmed = False, True
        self._send_goals()
        msg = f"scan {self.scan_id} started: {self.protocol.n_views} views ({self.protocol.name})"
        self.get_logger().info(msg)
        return True, msg

    # -- sequence ----------------------------------------------------------------------------------
    def _send_goals(self) -> None:
        stamp = self.get_clock().now().to_msg()
        self._goals = {}
        self._saw_false = {r: False for r in ROLES}
        for r in ROLES:
            T = self._goal_list[r][self.view]
            self._goals[r] = T
            msg = PoseStamped()
            msg.header.stamp = stamp
            msg.header.frame_id = self.world_frame
            matrix_mm_to_pose(T, msg.pose)
            self.goal_pubs[r].publish(msg)
        self._set_state("moving", f"view {self.view + 1}/{self.protocol.n_views}: moving")

    def _at_goal(self, role: str) -> bool:
        T, G = self._pose[role], self._goals.get(role)
        if T is None or G is None:
            return False
        dt = np.linalg.norm(T[:3, 3] - G[:3, 3]) * 1e-3
        c = (np.trace(G[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0
        return dt <= self.goal_tolerance_m and math.acos(min(1.0, max(-1.0, c))) <= self.goal_tolerance_rad

    def _arrived(self, role: str) -> bool:
        return bool(self._saw_false.get(role)) and self._in_pos[role] is True and self._at_goal(role)

    def _check_future(self, timeout_s: float, what: str):
        """The answer of the pending call, None while waiting; aborts on timeout (returns False)."""
        if self._future is not None and self._future.done():
            future, self._future = self._future, None
            try:
                return future.result()
            except Exception as exc:  # noqa: BLE001 - report any failure of the call
                self.abort(f"{what} failed: {exc}")
                return False
        if self._now() - self._t_state > timeout_s:
            self.abort(f"{what}: no answer within {timeout_s:.3g} s")
            return False
        return None

    def _tick(self) -> None:
        if self._autostart and self.state == "idle" and self._now() >= self._autostart_next:
            self._autostart_next = self._now() + 1.0  # try once a second until the graph is up
            ok, msg = self.start()
            if ok:
                self._autostart = False
            elif msg != self._autostart_reason:
                self._autostart_reason = msg
                self.get_logger().info(f"autostart waiting: {msg}")
        if not self.running:
            return
        now = self._now()
        for r in ROLES:
            if now - self._in_pos_t[r] > self.arm_report_timeout_s:
                self.abort(f"{r} arm silent for more than {self.arm_report_timeout_s:.3g} s")
                return
        p = self.protocol
        elapsed = now - self._t_state
        if self.state == "moving":
            if all(self._arrived(r) for r in ROLES):
                self._set_state("settling", f"view {self.view + 1}/{p.n_views}: settling")
            elif elapsed > p.move_timeout_s:
                self.abort(f"view {self.view}: arms not in position within {p.move_timeout_s:.3g} s")
        elif self.state == "settling":
            if elapsed >= p.settle_s:
                self._future = self._request_beam(True)
                self._set_state("beam_on", f"view {self.view + 1}/{p.n_views}: beam on")
        elif self.state == "beam_on":
            if self._future is not None:
                answer = self._check_future(self.service_timeout_s, "source/set_beam")
                if answer is None or answer is False:
                    return
                if not answer.success:
                    self.abort(f"beam refused: {answer.message}")
                    return
            if self._beam_confirmed:
                self._future = self.expose.call_async(Trigger.Request())
                self._set_state("exposing", f"view {self.view + 1}/{p.n_views}: exposing")
            elif elapsed > self.service_timeout_s:
                self.abort("beam switched on but source/beam_on never said so")
        elif self.state == "exposing":
            answer = self._check_future(p.exposure_timeout_s + self.service_timeout_s, "pcd/expose")
            if answer is None or answer is False:
                return
            if not answer.success:
                self.abort(f"detector: {answer.message}")
                return
            try:
                info = json.loads(answer.message)
                self._expected_stamp = int(info["stamp_ns"])
            except (ValueError, KeyError, TypeError):
                self.abort(f"detector answer without a frame stamp: {answer.message!r}")
                return
            exposure = info.get("exposure_s")
            if isinstance(exposure, (int, float)) and abs(exposure - p.exposure_s) > 1e-9 and self.frames == 0:
                self.get_logger().warn(f"the detector exposes {exposure} s, the protocol says {p.exposure_s} s")
            self._future = self._request_beam(False)
            self._set_state("beam_off", f"view {self.view + 1}/{p.n_views}: beam off")
        elif self.state == "beam_off":
            answer = self._check_future(self.service_timeout_s, "source/set_beam (off)")
            if answer is None or answer is False:
                return
            if not answer.success:
                self.abort(f"beam off refused?! {answer.message}")
                return
            self._set_state("waiting_frame")
        elif self.state == "waiting_frame":
            shape = self._seen_frames.get(self._expected_stamp)
            if shape is not None:
                if shape != (self.geom.n_rows, self.geom.n_cols):
                    self.abort(f"frame is {shape[0]} x {shape[1]}, the protocol's detector "
                               f"{self.geom.n_rows} x {self.geom.n_cols}")
                    return
                self.frames += 1
                self.frame_stamps.append(self._expected_stamp)
                self.view += 1
                if self.view >= p.n_views:
                    self._set_state("finishing", "waiting for the last geometries")
                else:
                    self._send_goals()
            elif elapsed > self.frame_timeout_s:
                self.abort(f"frame of view {self.view} not received on {fmt.TOPIC_PROJECTION}")
        elif self.state == "finishing":
            paired = sum(s in self._seen_geometries for s in self.frame_stamps)
            if paired == len(self.frame_stamps) or elapsed > self.pairing_timeout_s:
                self._publish_armed(False)
                self._beam_expect = None
                msg = f"scan complete: {self.frames} frames, {paired} with geometry"
                self.get_logger().info(msg)
                self._set_state("done", msg)

    # -- abort ------------------------------------------------------------------------------------
    def _safe_off(self) -> None:
        if self.set_beam.service_is_ready():
            self.set_beam.call_async(SetBool.Request(data=False))  # answer not awaited: disarming cuts it too
        self._publish_armed(False)

    def abort(self, reason: str) -> None:
        if not self.running:
            return
        self._safe_off()
        self._future = None
        self._beam_expect = None
        self.last_abort_reason = reason
        self.get_logger().error(f"scan aborted at view {self.view} ({self.frames} frames kept): {reason}")
        self._set_state("aborted", reason)

    # -- periodic -----------------------------------------------------------------------------------
    def _periodic(self) -> None:
        self._publish_status()
        if self.state == "aborted":
            level = DiagnosticStatus.ERROR
        elif self.protocol is None and self.protocol_file:
            level = DiagnosticStatus.WARN
        else:
            level = DiagnosticStatus.OK
        status = DiagnosticStatus(
            level=level, name=f"{self.get_fully_qualified_name()}: scan", hardware_id="scan_orchestrator",
            message=self.message, values=[KeyValue(key=k, value=str(v)) for k, v in (
                ("state", self.state), ("view", self.view),
                ("n_views", self.protocol.n_views if self.protocol else 0), ("frames", self.frames),
                ("scan_id", self.scan_id), ("protocol_file", self.protocol_file),
                ("last_abort_reason", self.last_abort_reason))])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)

    def destroy_node(self):
        if self.running and self.context.ok():
            self.abort("node shutting down")
        return super().destroy_node()


def main(argv=None) -> int:
    return run_node(ScanOrchestratorNode, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
