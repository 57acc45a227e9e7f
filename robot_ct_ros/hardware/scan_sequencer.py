"""The scan sequence: move both arms, settle, beam on, expose, beam off, next view (no ROS import).

:class:`ScanSequencer` is the scan orchestrator's state machine. It sees the graph through
observations its owner feeds it (arm reports, beam state, device lifecycle states, frames and
geometries seen, each timestamped by its clock) and acts through :class:`ScanPorts` (publish goals,
status, arming and scan info; call the source's beam and the detector's exposure services). It
never blocks: service calls return futures (anything with ``done()`` and ``result()``; a result has
``success`` and ``message``) that :meth:`ScanSequencer.tick`, called periodically, polls.

States: idle, moving, settling, beam_on, exposing, beam_off, waiting_frame, finishing, done,
aborted; ``view`` is the 0-based index of the view in progress, ``frames`` the frames taken so far.

Safety: the beam is requested only after both arms reported in position (an in_position false and
then true after the goal was sent, with the measured pose at the goal) and stayed so through the
settle time, and only after the detector was seen alive (pcd/expose offered, and the node that offers
it answering a lifecycle get_state as "active", where the owner can ask: a SIGKILLed node stays in
the graph for the DDS lease, about 20 s); only for the exposure: it is switched off as soon as the
detector answers, and at the latest ``exposure_s + beam_off_margin_s`` after the pcd/expose request,
answered or not. The detector's answer is then awaited with the beam off, up to the protocol's
``exposure_timeout_s`` plus ``service_timeout_s`` from the request; an answer later than
``exposure_s + readout_warn_s`` is warned about as a slow read-out. Any fault
aborts: an arm leaving position or falling silent, an arm driver reporting ERROR, a move not done
within move_timeout_s, the interlock refusing the beam, the beam dropping during an exposure or
showing up outside one, the detector failing, timing out or gone, a frame not arriving or of the wrong
size, an e-stop (seen on the estop topic or latched at the source). No scan starts while the source's
e-stop is latched: the arms do not move. Abort = beam off requested, disarmed, state "aborted" with the reason. Frames
already taken stay published; a beam-interrupted frame is never one of them (the pcd_grabber
publishes it on /ct/projection_rejected only), so it is neither counted nor paired.

Units: poses are 4 x 4 matrices in mm (world frame), times in seconds of the owner's clock.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from robot_ct_ros.bag import format as fmt
from robot_ct_ros.ct.geometry import ConeGeometry
from robot_ct_ros.ct.hand_eye import HandEye, tool_goals_from_geometry
from robot_ct_ros.hardware.scan_protocol import PROTOCOL_ERRORS, ScanProtocol
from robot_ct_ros.parameters import setting, validate

__all__ = ["ROLES", "RUNNING", "DEVICE_DIAGNOSTICS", "ScanSequencerSettings", "ScanPorts", "ScanSequencer"]

ROLES = ("source", "detector")
RUNNING = ("moving", "settling", "beam_on", "exposing", "beam_off", "waiting_frame", "finishing")
IN_POSITION_REQUIRED = ("settling", "beam_on", "exposing", "beam_off")
DEVICE_DIAGNOSTICS = ("detector", "x-ray source")
"""/diagnostics status names (suffixes) of pcd_grabber and source_control, whose
``lifecycle_state`` value must be "active" for a scan to start."""
DEVICE_REPORT_MAX_AGE_S = 3.0  # they report at 1 Hz; an older report is not evidence either way
ARM_CAUSE_WINDOW_S = 5.0
"""An arm driver ERROR this long after an abort for that arm leaving its position names the cause
(a lost controller drops in_position first; "connection lost" follows, up to call_timeout_s later)."""


def _answered_stamp(future) -> int | None:
    """The frame stamp in a finished pcd/expose call's successful answer, else None (never raises)."""
    try:
        answer = future.result()
        return int(json.loads(answer.message)["stamp_ns"]) if answer.success else None
    except Exception:  # noqa: BLE001 - a failed call or an answer without a stamp: no frame to count
        return None


@dataclass(frozen=True)
class ScanSequencerSettings:
    """The scan orchestrator's parameters (SI units)."""

    protocol_file: str = setting("", "a config/scan_protocol_*.yaml; empty: the built-in seed protocol")
    autostart: bool = setting(False, "start the scan as soon as the graph is ready")
    tick_period_s: float = setting(0.02, "state machine period", unit="s", minimum=1e-3)
    arm_report_timeout_s: float = setting(1.0, "an arm silent for longer aborts the scan", unit="s", minimum=0.0)
    goal_tolerance_m: float = setting(1e-3, "measured TCP within this of the goal counts as arrived", unit="m",
                                      minimum=0.0)
    goal_tolerance_rad: float = setting(0.01, "the same for the orientation", unit="rad", minimum=0.0)
    service_timeout_s: float = setting(2.0, "source/set_beam must answer within this", unit="s", minimum=0.0)
    beam_off_margin_s: float = setting(1.0, "the beam goes off this long after the exposure time has passed "
                                       "since the pcd/expose request, whether the detector answered or not (it "
                                       "covers the request's way to the detector on a loaded machine: a margin "
                                       "too short cuts the exposure)", unit="s", minimum=0.0)
    readout_warn_s: float = setting(1.0, "a detector answer later than exposure_s + this after the request "
                                    "is warned about as a slow read-out", unit="s", minimum=0.0)
    frame_timeout_s: float = setting(2.0, "the frame must appear within this after pcd/expose answered", unit="s",
                                     minimum=0.0)
    pairing_timeout_s: float = setting(3.0, "at the end, wait this long for the last geometries (longer than "
                                       "geometry_publisher's wait_for_poses_s, 2 s, which may hold the last frame)",
                                       unit="s", minimum=0.0)
    world_frame: str = setting(fmt.FRAME_WORLD, "frame of the goals and of the accepted tool poses")

    def __post_init__(self):
        validate(self)


class ScanPorts(Protocol):
    """What the sequencer does to the graph (the scan orchestrator node implements it)."""

    def log(self, level: str, message: str) -> None:
        """Log at level "info", "warn" or "error"."""
    def publish_goals(self, goals: dict) -> None:
        """Send each arm (role -> 4 x 4 TCP pose, mm, world frame) its goal, one stamp for all."""
    def publish_armed(self, armed: bool) -> None: ...
    def publish_status(self, status: dict) -> None: ...
    def publish_scan_info(self, info: dict) -> None: ...
    def call_set_beam(self, on: bool):
        """Ask the source for the beam on or off; returns a future."""
    def call_expose(self):
        """Ask the detector for one exposure; returns a future."""
    def beam_service_ready(self) -> bool: ...
    def expose_service_ready(self) -> bool: ...
    def call_detector_check(self):
        """Ask the node that offers pcd/expose whether it is alive and active; a future whose result has
        ``success`` (active) and ``message`` (what it is), or None where that cannot be asked."""
    def detector_node(self) -> str:
        """The name of the node that offers pcd/expose, "" when not known."""
    def armed_subscribers(self) -> int: ...
    def goal_subscribers(self, role: str) -> int: ...


class ScanSequencer:
    """The scan state machine (module docstring).

    Parameters
    ----------
    settings : ScanSequencerSettings
        Timeouts, tolerances, protocol file, autostart.
    hand_eye : HandEye
        The nominal mounts: TCP goals are the protocol's geometry through their inverse.
    ports : ScanPorts
        The graph.
    clock : callable() -> float
        Seconds, monotonic (default :func:`time.monotonic`).

    Attributes
    ----------
    state, message, view, frames, scan_id, protocol, last_abort_reason
        The scan as scan/status reports it.
    arm_in_position, arm_in_position_t, arm_pose, arm_pose_t : dict
        Per role: the last in_position report and when it came, the last measured TCP pose (mm)
        and when it came (-inf before the first).
    device_state : dict
        Device ("detector", "x-ray source") -> (time, lifecycle state) from its last report.
    """

    def __init__(self, settings: ScanSequencerSettings, hand_eye: HandEye, ports: ScanPorts,
                 clock: Callable[[], float] = time.monotonic):
        self.settings, self.hand_eye, self.ports, self._now = settings, hand_eye, ports, clock
        self.arm_in_position: dict[str, bool | None] = {r: None for r in ROLES}
        self.arm_in_position_t: dict[str, float] = {r: -math.inf for r in ROLES}
        self.arm_pose: dict[str, np.ndarray | None] = {r: None for r in ROLES}
        self.arm_pose_t: dict[str, float] = {r: -math.inf for r in ROLES}
        self.device_state: dict[str, tuple[float, str]] = {}
        self.beam_on: bool | None = None
        self.estop_latched = False  # as source_control last said (source/estop_latched), or an e-stop seen since
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
        self._late_expose = None  # the pcd/expose call in flight when a scan aborted
        self._expose = None  # the pcd/expose call of the view in progress, until it is answered
        self._t_expose = 0.0  # when it was sent
        self._check = None  # the detector check before the beam, while in flight
        self._t_check = 0.0
        self.slow_readouts = 0  # this scan's detector answers later than exposure_s + readout_warn_s
        self._slowest_readout = 0.0
        self._arm_abort: tuple[str, float] | None = None  # (role, when): the last abort for an arm leaving position
        self.last_abort_reason = ""
        if settings.protocol_file:
            try:
                self.protocol = ScanProtocol.from_yaml(settings.protocol_file)
            except PROTOCOL_ERRORS as exc:
                ports.log("error", f"protocol {settings.protocol_file}: {exc}")
                # scan/status and /diagnostics say so (not "ready"); scan/start reads the file again
                self.message = f"protocol {settings.protocol_file} unreadable, fix it before scan/start: {exc}"
        self._autostart = settings.autostart
        self._autostart_next = 0.0
        self._autostart_reason = ""
        ports.publish_armed(False)
        self.publish_status()

    # -- state ---------------------------------------------------------------------------------
    @property
    def running(self) -> bool:
        return self.state in RUNNING

    def _set_state(self, state: str, message: str | None = None) -> None:
        self.state = state
        if message is not None:
            self.message = message
        self._t_state = self._now()
        self.publish_status()

    def status(self) -> dict:
        """The scan/status content."""
        p = self.protocol
        return {"state": self.state, "view": self.view, "n_views": p.n_views if p is not None else 0,
                "frames": self.frames, "message": self.message, "scan_id": self.scan_id,
                "protocol": p.name if p else ""}

    def publish_status(self) -> None:
        self.ports.publish_status(self.status())

    def health(self) -> tuple[str, list[tuple[str, object]]]:
        """Diagnostic level ("ok", "warn": protocol file unreadable, "error": aborted) and key values."""
        if self.state == "aborted":
            level = "error"
        elif self.protocol is None and self.settings.protocol_file:
            level = "warn"
        else:
            level = "ok"
        return level, [("state", self.state), ("view", self.view),
                       ("n_views", self.protocol.n_views if self.protocol else 0), ("frames", self.frames),
                       ("scan_id", self.scan_id), ("protocol_file", self.settings.protocol_file),
                       ("last_abort_reason", self.last_abort_reason)]

    # -- observations ----------------------------------------------------------------------------
    def on_in_position(self, role: str, in_position: bool) -> None:
        self.arm_in_position[role] = bool(in_position)
        self.arm_in_position_t[role] = self._now()
        if not in_position:
            if self.state == "moving":
                self._saw_false[role] = True
            elif self.state in IN_POSITION_REQUIRED:
                self.abort(f"{role} arm left its position during view {self.view} ({self.state})")
                self._arm_abort = (role, self._now())

    def on_tool_pose(self, role: str, T: np.ndarray) -> None:
        """The measured TCP pose of ``role`` (4 x 4, mm, world frame)."""
        self.arm_pose[role] = T
        self.arm_pose_t[role] = self._now()

    def on_beam(self, on: bool) -> None:
        on = bool(on)
        self.beam_on = on
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

    def on_estop(self, pressed: bool) -> None:
        if pressed:
            self.estop_latched = True  # until source_control says it was reset
            if self.running:
                self.abort("e-stop")

    def on_estop_latched(self, latched: bool) -> None:
        """source_control's e-stop latch (source/estop_latched): a scan neither starts nor goes on under it."""
        self.estop_latched = bool(latched)
        if latched and self.running:
            self.abort("e-stop latched at the source")

    def on_diagnostics(self, reports) -> None:
        """/diagnostics statuses as (name, is_error, message, lifecycle_state or None): device
        lifecycle states are kept; an arm driver's ERROR aborts a running scan."""
        for name, _, _, state in reports:
            device = next((d for d in DEVICE_DIAGNOSTICS if name.endswith(": " + d)), None)
            if device is not None and state is not None:
                self.device_state[device] = (self._now(), state)
        if not self.running:
            self._name_arm_cause(reports)
            return
        for name, is_error, message, _ in reports:
            if is_error and name.endswith((": source arm", ": detector arm")):
                self.abort(f"arm driver error: {name}: {message}")
                return

    def _name_arm_cause(self, reports) -> None:
        """After an abort for an arm leaving its position: that arm's driver ERROR (connection lost, a
        protective stop) that follows within ARM_CAUSE_WINDOW_S is the cause; the abort reason names it."""
        if self._arm_abort is None or self.state != "aborted":
            return
        role, t = self._arm_abort
        if self._now() - t > ARM_CAUSE_WINDOW_S:
            self._arm_abort = None
            return
        for name, is_error, message, _ in reports:
            if is_error and name.endswith(f": {role} arm"):
                self._arm_abort = None
                reason = f"{self.last_abort_reason}: arm driver error: {name}: {message}"
                self.last_abort_reason = reason
                self.ports.log("error", f"scan aborted at view {self.view}: {reason}")
                self._set_state("aborted", reason)
                return

    def on_frame(self, stamp_ns: int, shape: tuple[int, int]) -> None:
        if self.running:
            self._seen_frames[stamp_ns] = shape

    def on_geometry(self, stamp_ns: int) -> None:
        if self.running:
            self._seen_geometries.add(stamp_ns)

    # -- commands ----------------------------------------------------------------------------------
    def start(self) -> tuple[bool, str]:
        """Load the protocol, check the graph, start; (started, why or what)."""
        if self.running:
            return False, f"a scan is running ({self.state}, view {self.view})"
        try:
            if self.settings.protocol_file:
                self.protocol = ScanProtocol.from_yaml(self.settings.protocol_file)
            elif self.protocol is None:
                self.protocol = ScanProtocol()
            geom = self.protocol.geometry()
            src, det = tool_goals_from_geometry(geom, self.hand_eye)
        except PROTOCOL_ERRORS as exc:
            return False, f"protocol: {exc}"
        now, ports, timeout = self._now(), self.ports, self.settings.arm_report_timeout_s
        problems = []
        if self.estop_latched:  # the arms must not move either
            problems.append("the e-stop is latched (reset it: source/reset_estop)")
        if not ports.beam_service_ready():
            problems.append("source/set_beam not available (source_control)")
        if not ports.expose_service_ready():
            problems.append("pcd/expose not available (pcd_grabber)")
        for device, (t, state) in self.device_state.items():
            if now - t <= DEVICE_REPORT_MAX_AGE_S and state != "active":
                problems.append(f"{device} is {state}, not active (lifecycle: configure and activate it)")
        if ports.armed_subscribers() < 1:
            problems.append("nobody subscribes to scan/armed (source_control)")
        for r in ROLES:
            if now - self.arm_pose_t[r] > timeout or now - self.arm_in_position_t[r] > timeout:
                problems.append(f"{r} arm not reporting")
            elif ports.goal_subscribers(r) < 1:
                problems.append(f"{r} arm driver not subscribed to its goals")
        if problems:
            return False, "cannot start: " + "; ".join(problems)
        self.geom = geom
        self._goal_list = {"source": src, "detector": det}
        self.scan_id = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + f"-{int(now * 1e3) % 1000:03d}"
        self.view, self.frames, self._expected_stamp, self._late_expose = 0, 0, None, None
        self.frame_stamps, self._seen_frames, self._seen_geometries = [], {}, set()
        self.last_abort_reason = ""
        self._expose, self._check, self._arm_abort = None, None, None
        self.slow_readouts, self._slowest_readout = 0, 0.0
        ports.publish_scan_info(self.protocol.scan_info(geom, self.scan_id))
        ports.publish_armed(True)
        self._beam_expect, self._beam_confirmed = False, True
        self._send_goals()
        msg = f"scan {self.scan_id} started: {self.protocol.n_views} views ({self.protocol.name})"
        ports.log("info", msg)
        return True, msg

    def safe_off(self) -> None:
        """Beam off (not waited for: disarming cuts it too) and disarmed."""
        if self.ports.beam_service_ready():
            self.ports.call_set_beam(False)
        self.ports.publish_armed(False)

    def abort(self, reason: str) -> None:
        """Abort a running scan: beam off, disarmed, state "aborted" with ``reason``."""
        if not self.running:
            return
        self.safe_off()
        stamp = self._expected_stamp if self.state in ("beam_off", "waiting_frame") else None
        if self._expose is not None:  # exposing, or the beam already off and the answer still awaited
            if self._expose.done():
                stamp = _answered_stamp(self._expose)  # answered, not yet taken in by a tick
            else:
                self._late_expose = self._expose  # an answer after the abort still names a frame the bag keeps
        self._expose, self._check = None, None
        if stamp is not None and stamp not in self.frame_stamps:
            # the detector took this view's frame and published it (the bag keeps it): count it
            self.frames += 1
            self.frame_stamps.append(stamp)
        self._future = None
        self._beam_expect = None
        self.last_abort_reason = reason
        self.ports.log("error", f"scan aborted at view {self.view} ({self.frames} frames kept): {reason}")
        self._set_state("aborted", reason)

    def _count_late_frame(self) -> None:
        """The detector answered the exposure in flight after the abort: a frame it took was published (the bag
        keeps it), so it counts among the frames kept."""
        stamp, self._late_expose = _answered_stamp(self._late_expose), None
        if stamp is not None and stamp not in self.frame_stamps and self.state == "aborted":
            self.frames += 1
            self.frame_stamps.append(stamp)
            self.ports.log("info", f"the detector answered view {self.view}'s exposure after the abort: its frame is "
                                   f"kept ({self.frames} frames kept)")
            self.publish_status()

    # -- sequence ----------------------------------------------------------------------------------
    def _send_goals(self) -> None:
        self._goals = {r: self._goal_list[r][self.view] for r in ROLES}
        self._saw_false = {r: False for r in ROLES}
        self.ports.publish_goals(dict(self._goals))
        self._set_state("moving", f"view {self.view + 1}/{self.protocol.n_views}: moving")

    def _at_goal(self, role: str) -> bool:
        T, G = self.arm_pose[role], self._goals.get(role)
        if T is None or G is None:
            return False
        dt = np.linalg.norm(T[:3, 3] - G[:3, 3]) * 1e-3
        c = (np.trace(G[:3, :3].T @ T[:3, :3]) - 1.0) / 2.0
        s = self.settings
        return dt <= s.goal_tolerance_m and math.acos(min(1.0, max(-1.0, c))) <= s.goal_tolerance_rad

    def _arrived(self, role: str) -> bool:
        return bool(self._saw_false.get(role)) and self.arm_in_position[role] is True and self._at_goal(role)

    def _request_beam(self, on: bool):
        self._beam_expect = on
        self._beam_confirmed = False
        return self.ports.call_set_beam(on)

    def _answer(self, future, failed):
        """The answer of the done call ``future``; None after aborting with ``failed(exc)`` where the call failed."""
        try:
            return future.result()
        except Exception as exc:  # noqa: BLE001 - report any failure of the call
            self.abort(failed(exc))
            return None

    def _check_future(self, timeout_s: float, what: str):
        """The answer of the pending call, None while waiting; aborts on timeout (returns False)."""
        if self._future is not None and self._future.done():
            future, self._future = self._future, None
            answer = self._answer(future, lambda exc: f"{what} failed: {exc}")
            return False if answer is None else answer
        if self._now() - self._t_state > timeout_s:
            self.abort(f"{what}: no answer within {timeout_s:.3g} s")
            return False
        return None

    def tick(self) -> None:
        """One step of the state machine (call every tick_period_s)."""
        if self._autostart and self.state == "idle" and self._now() >= self._autostart_next:
            self._autostart_next = self._now() + 1.0  # try once a second until the graph is up
            ok, msg = self.start()
            if ok:
                self._autostart = False
            elif msg != self._autostart_reason:
                self._autostart_reason = msg
                self.ports.log("info", f"autostart waiting: {msg}")
        if self._late_expose is not None and self._late_expose.done():
            self._count_late_frame()
        if not self.running:
            return
        now, s = self._now(), self.settings
        for r in ROLES:
            if now - self.arm_in_position_t[r] > s.arm_report_timeout_s:
                self.abort(f"{r} arm silent for more than {s.arm_report_timeout_s:.3g} s")
                return
        p = self.protocol
        elapsed = now - self._t_state
        step = f"view {self.view + 1}/{p.n_views}"
        if self.state == "moving":
            if all(self._arrived(r) for r in ROLES):
                self._set_state("settling", f"{step}: settling")
            elif elapsed > p.move_timeout_s:
                self.abort(f"view {self.view}: arms not in position within {p.move_timeout_s:.3g} s")
        elif self.state == "settling":
            if elapsed >= p.settle_s and self._detector_alive(s):
                self._future = self._request_beam(True)
                self._set_state("beam_on", f"{step}: beam on")
        elif self.state == "beam_on":
            if self._future is not None:
                answer = self._check_future(s.service_timeout_s, "source/set_beam")
                if answer is None or answer is False:
                    return
                if not answer.success:  # source_control's refusals already say "beam refused: "
                    refusal = answer.message if answer.message.startswith("beam refused") \
                        else f"beam refused: {answer.message}"
                    self.abort(refusal)
                    return
            if self._beam_confirmed:
                self._expected_stamp = None
                self._expose, self._t_expose = self.ports.call_expose(), now
                self._set_state("exposing", f"{step}: exposing")
            elif elapsed > s.service_timeout_s:
                self.abort("beam switched on but source/beam_on never said so")
        elif self.state == "exposing":
            self._tick_exposing(p, s, step)
        elif self.state == "beam_off":
            answer = self._check_future(s.service_timeout_s, "source/set_beam (off)")
            if answer is None or answer is False:
                return
            if not answer.success:
                self.abort(f"beam off refused?! {answer.message}")
                return
            self._set_state("waiting_frame")
        elif self.state == "waiting_frame":
            if self._expose is not None:  # the beam went off before the detector answered
                if self._take_expose_answer(p, s, step):
                    self._set_state("waiting_frame", f"{step}: beam off, waiting for the frame")
                return
            self._tick_waiting_frame(p, s, elapsed)
        elif self.state == "finishing":
            paired = sum(st in self._seen_geometries for st in self.frame_stamps)
            if paired == len(self.frame_stamps) or elapsed > s.pairing_timeout_s:
                self.ports.publish_armed(False)
                self._beam_expect = None
                msg = f"scan complete: {self.frames} frames, {paired} with geometry"
                if self.slow_readouts:
                    msg += (f"; {self.slow_readouts} slow detector read-outs (pcd/expose answered up to "
                            f"{self._slowest_readout:.2f} s after the request, for {p.exposure_s:.3g} s exposures)")
                self.ports.log("warn" if self.slow_readouts else "info", msg)
                self._set_state("done", msg)

    def _detector_name(self) -> str:
        return f"the detector node ({self.ports.detector_node() or 'pcd_grabber'})"

    def _detector_alive(self, s: ScanSequencerSettings) -> bool:
        """Before the beam: pcd/expose is offered and the node offering it answers as active (where it
        can be asked). False while the check is in flight; aborts (no beam) when the detector is gone."""
        if not self.ports.expose_service_ready():
            self.abort(f"{self._detector_name()} is gone: pcd/expose is no longer offered; the beam was not "
                       "switched on")
            return False
        if self._check is None:
            self._check, self._t_check = self.ports.call_detector_check(), self._now()
            if self._check is None:
                return True  # nothing more to ask
        if not self._check.done():
            if self._now() - self._t_check > s.service_timeout_s:
                self.abort(f"{self._detector_name()} does not answer within {s.service_timeout_s:.3g} s: gone or "
                           "hung; the beam was not switched on")
            return False
        check, self._check = self._check, None
        answer = self._answer(check, lambda exc: f"{self._detector_name()} could not be asked for its state ({exc}); "
                                                 "the beam was not switched on")
        if answer is None:
            return False
        if not answer.success:
            self.abort(f"{self._detector_name()}: {answer.message}; the beam was not switched on")
            return False
        return True

    def _tick_exposing(self, p: ScanProtocol, s: ScanSequencerSettings, step: str) -> None:
        if not self._expose.done() and self._now() - self._t_expose >= p.exposure_s + s.beam_off_margin_s:
            # the exposure time has passed: the beam goes off whether or not the detector answered
            self._future = self._request_beam(False)
            self._set_state("beam_off", f"{step}: beam off (exposure over), waiting for the detector's answer")
        elif self._take_expose_answer(p, s, step):
            self._future = self._request_beam(False)
            self._set_state("beam_off", f"{step}: beam off")

    def _take_expose_answer(self, p: ScanProtocol, s: ScanSequencerSettings, step: str) -> bool:
        """The pcd/expose answer of this view, if there is one: True once taken (``_expected_stamp`` set);
        False while waiting, or after an abort (failure, no stamp, timeout, detector gone)."""
        waited = self._now() - self._t_expose
        limit = p.exposure_timeout_s + s.service_timeout_s
        if not self._expose.done():
            if waited > limit:
                gone = "" if self.ports.expose_service_ready() else "; pcd/expose is no longer offered"
                self.abort(f"pcd/expose: no answer within {limit:.3g} s of the request: {self._detector_name()} is "
                           f"hung or gone{gone}")
            elif not self.ports.expose_service_ready():
                self.abort(f"{self._detector_name()} is gone: pcd/expose is no longer offered, view {self.view}'s "
                           "exposure is not answered")
            return False
        future, self._expose = self._expose, None
        answer = self._answer(future, lambda exc: f"pcd/expose failed: {exc}")
        if answer is None:
            return False
        if not answer.success:
            self.abort(f"detector: {answer.message}")
            return False
        try:
            info = json.loads(answer.message)
            self._expected_stamp = int(info["stamp_ns"])
        except (ValueError, KeyError, TypeError):
            self.abort(f"detector answer without a frame stamp: {answer.message!r}")
            return False
        exposure = info.get("exposure_s")
        if isinstance(exposure, (int, float)) and abs(exposure - p.exposure_s) > 1e-9 and self.frames == 0:
            self.ports.log("warn", f"the detector exposes {exposure} s, the protocol says {p.exposure_s} s")
        if waited > p.exposure_s + s.readout_warn_s:
            self.slow_readouts += 1
            self._slowest_readout = max(self._slowest_readout, waited)
            if self.slow_readouts == 1:
                self.ports.log("warn", f"{step}: slow detector read-out: pcd/expose answered {waited:.2f} s after "
                                       f"the request, for a {p.exposure_s:.3g} s exposure (more than readout_warn_s "
                                       f"{s.readout_warn_s:.3g} s over it); the beam went off "
                                       f"{s.beam_off_margin_s:.3g} s after the exposure time, the frame is awaited "
                                       "with the beam off (the scan's total is given at its end)")
        return True

    def _tick_waiting_frame(self, p: ScanProtocol, s: ScanSequencerSettings, elapsed: float) -> None:
        shape = self._seen_frames.get(self._expected_stamp)
        if shape is not None:
            if shape != (self.geom.n_rows, self.geom.n_cols):
                self._expected_stamp = None  # not a frame of this scan's detector: not kept
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
        elif elapsed > s.frame_timeout_s:
            self._expected_stamp = None  # never arrived: not kept
            self.abort(f"frame of view {self.view} not received on {fmt.TOPIC_PROJECTION}")
