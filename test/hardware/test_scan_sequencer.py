"""The scan state machine without ROS: a scripted graph (fake ports, futures and clock) drives it."""

import json
from types import SimpleNamespace

import numpy as np
import yaml

from robot_ct_ros.ct.hand_eye import HandEye, tool_goals_from_geometry
from robot_ct_ros.hardware.scan_protocol import ScanProtocol
from robot_ct_ros.hardware.scan_sequencer import ScanSequencer, ScanSequencerSettings

PROTOCOL = {"name": "seq", "n_views": 2, "roi_center_m": [0.4, 0.0, 0.3], "fov_diameter_m": 0.004,
            "detector": {"n_rows": 6, "n_cols": 8, "binning": 2, "raw_pixel_m": 0.0005},
            "exposure_s": 0.02, "settle_s": 0.05, "move_timeout_s": 5.0, "exposure_timeout_s": 1.0}


class Future:
    def __init__(self):
        self._result, self._done = None, False

    def set(self, success=True, message=""):
        self._result, self._done = SimpleNamespace(success=success, message=message), True

    def fail(self, exc):
        """The call itself failed (rclpy's future raises from result())."""
        self._result, self._done = exc, True

    def done(self):
        return self._done

    def result(self):
        if isinstance(self._result, Exception):
            raise self._result
        return self._result


class Ports:
    """Records what the sequencer does; every service and subscriber present."""

    def __init__(self):
        self.logs, self.goals, self.armed, self.status, self.info = [], [], [], [], []
        self.beam_calls, self.expose_calls = [], []
        self.ready = True
        self.expose_ready = True
        self.check_detector = False  # a detector node that can be asked for its lifecycle state
        self.check_calls = []

    def log(self, level, message):
        self.logs.append((level, message))

    def publish_goals(self, goals):
        self.goals.append(goals)

    def publish_armed(self, armed):
        self.armed.append(armed)

    def publish_status(self, status):
        self.status.append(status)

    def publish_scan_info(self, info):
        self.info.append(info)

    def call_set_beam(self, on):
        self.beam_calls.append((on, Future()))
        return self.beam_calls[-1][1]

    def call_expose(self):
        self.expose_calls.append(Future())
        return self.expose_calls[-1]

    def beam_service_ready(self):
        return self.ready

    def expose_service_ready(self):
        return self.ready and self.expose_ready

    def call_detector_check(self):
        if not self.check_detector:
            return None
        self.check_calls.append(Future())
        return self.check_calls[-1]

    def detector_node(self):
        return "/pcd_grabber" if self.check_detector else ""

    def armed_subscribers(self):
        return 1 if self.ready else 0

    def goal_subscribers(self, role):
        return 1 if self.ready else 0


class Rig:
    def __init__(self, tmp_path, protocol=None, **settings):
        path = tmp_path / "protocol.yaml"
        path.write_text(yaml.safe_dump({"scan_protocol": dict(PROTOCOL, **(protocol or {}))}))
        self.t = 100.0
        self.ports = Ports()
        self.seq = ScanSequencer(ScanSequencerSettings(protocol_file=str(path), **settings), HandEye(), self.ports,
                                 clock=lambda: self.t)

    def advance(self, dt=0.01, n=1):
        for _ in range(n):
            self.t += dt
            self.seq.tick()

    def report_arms(self, in_position=True):
        """Both arms report, their measured poses at the current goals."""
        goals = self.ports.goals[-1] if self.ports.goals else {}
        for role in ("source", "detector"):
            if role in goals:
                self.seq.on_tool_pose(role, goals[role])
            else:
                self.seq.on_tool_pose(role, np.eye(4))
            self.seq.on_in_position(role, in_position)

    def arrive(self):
        self.report_arms(False)
        self.report_arms(True)

    def run_view(self, stamp):
        """From moving to the next view (or finishing), every answer positive."""
        s, p = self.seq, self.ports
        self.arrive()
        self.advance()
        assert s.state == "settling"
        self.advance(0.03, 2)
        assert s.state == "beam_on" and p.beam_calls[-1][0] is True
        p.beam_calls[-1][1].set(True, "beam on")
        s.on_beam(True)
        self.advance()
        assert s.state == "exposing"
        p.expose_calls[-1].set(True, json.dumps({"stamp_ns": stamp, "exposure_s": 0.02}))
        self.advance()
        assert s.state == "beam_off" and p.beam_calls[-1][0] is False
        s.on_beam(False)
        p.beam_calls[-1][1].set(True, "beam off")
        self.advance()
        assert s.state == "waiting_frame"
        s.on_frame(stamp, (6, 8))
        self.advance()


def test_a_scan_start_to_end(tmp_path):
    rig = Rig(tmp_path)
    s, p = rig.seq, rig.ports
    assert p.armed == [False] and p.status[-1]["state"] == "idle" and p.status[-1]["n_views"] == 2
    rig.report_arms(False)
    ok, msg = s.start()
    assert ok and "2 views (seq)" in msg and s.state == "moving" and p.armed[-1] is True
    assert p.info[-1]["n_views"] == 2 and p.info[-1]["notes"]["scan_id"] == s.scan_id
    # the goals are the protocol's trajectory through the inverse hand-eye transform
    src, det = tool_goals_from_geometry(ScanProtocol.from_dict(PROTOCOL).geometry(), HandEye())
    np.testing.assert_allclose(p.goals[0]["source"], src[0])
    np.testing.assert_allclose(p.goals[0]["detector"], det[0])
    assert s.start() == (False, "a scan is running (moving, view 0)")

    rig.report_arms(True)  # in position without having left it: an old report, not an arrival
    rig.advance()
    assert s.state == "moving"
    rig.run_view(1000)
    assert s.view == 1 and s.frames == 1 and s.state == "moving" and len(p.goals) == 2
    np.testing.assert_allclose(p.goals[1]["detector"], det[1])
    rig.run_view(2000)
    assert s.state == "finishing" and s.frame_stamps == [1000, 2000]
    s.on_geometry(1000)
    s.on_geometry(2000)
    rig.advance()
    assert s.state == "done" and s.message == "scan complete: 2 frames, 2 with geometry"
    assert p.armed[-1] is False and s.health()[0] == "ok"
    states = [st["state"] for st in p.status]
    for state in ("moving", "settling", "beam_on", "exposing", "beam_off", "waiting_frame", "finishing", "done"):
        assert state in states
    assert [on for on, _ in p.beam_calls] == [True, False, True, False]


def _started(tmp_path, **kw):
    rig = Rig(tmp_path, **kw)
    rig.report_arms(False)
    assert rig.seq.start()[0]
    return rig


def _aborted(rig, *words):
    s = rig.seq
    assert s.state == "aborted", s.state
    assert all(w in s.message for w in words), s.message
    assert s.last_abort_reason == s.message and s.health()[0] == "error"
    assert rig.ports.armed[-1] is False and rig.ports.beam_calls[-1][0] is False  # beam off requested


def _to_exposing(rig):
    """From moving to exposing the view in progress: the arms arrive, the beam is switched on and confirmed."""
    rig.arrive()
    rig.advance(0.03, 3)
    rig.ports.beam_calls[-1][1].set(True)
    rig.seq.on_beam(True)
    rig.advance()
    assert rig.seq.state == "exposing", rig.seq.state
    return rig


def _exposing(tmp_path):
    """A three-view scan exposing its second view, its first frame (stamp 11) kept."""
    rig = _started(tmp_path, protocol={"n_views": 3})
    rig.run_view(11)
    return _to_exposing(rig)


def test_start_refused_until_the_graph_is_there(tmp_path):
    rig = Rig(tmp_path)
    rig.ports.ready = False
    ok, msg = rig.seq.start()
    assert not ok
    for what in ("source/set_beam", "pcd/expose", "scan/armed", "source arm not reporting",
                 "detector arm not reporting"):
        assert what in msg
    rig.ports.ready = True
    rig.report_arms(False)
    rig.seq.on_diagnostics([("/pcd_grabber: detector", False, "", "inactive")])
    ok, msg = rig.seq.start()
    assert not ok and "detector is inactive" in msg
    rig.t += 5.0  # that report is too old to count either way (and the arms went silent)
    rig.report_arms(False)
    assert rig.seq.start()[0]


def test_bad_protocol_is_refused_and_flagged(tmp_path):
    rig = Rig(tmp_path, protocol={"n_views": 0})
    assert rig.seq.protocol is None and rig.ports.logs[0][0] == "error"
    assert rig.seq.health()[0] == "warn"
    # scan/status and the diagnostics' message say why, not "ready"
    assert "unreadable" in rig.seq.status()["message"] and "protocol.yaml" in rig.seq.status()["message"]
    ok, msg = rig.seq.start()
    assert not ok and msg.startswith("protocol:") and rig.seq.state == "idle"


def test_arm_leaving_its_position_aborts(tmp_path):
    rig = _started(tmp_path)
    rig.arrive()
    rig.advance()
    assert rig.seq.state == "settling"
    rig.seq.on_in_position("detector", False)
    _aborted(rig, "detector arm left its position", "settling")


def test_arm_falling_silent_or_never_arriving_aborts(tmp_path):
    rig = _started(tmp_path)
    rig.advance(0.6, 2)
    _aborted(rig, "source arm silent")
    rig = _started(tmp_path, protocol={"move_timeout_s": 0.5})
    for _ in range(8):
        rig.report_arms(True)
        rig.advance(0.1)
    _aborted(rig, "not in position within 0.5 s")


def test_beam_refused_lost_or_unexpected_aborts(tmp_path):
    rig = _started(tmp_path)
    rig.arrive()
    rig.advance(0.03, 3)
    rig.ports.beam_calls[-1][1].set(False, "beam refused: e-stop latched")
    rig.advance()
    _aborted(rig, "beam refused", "e-stop")
    assert rig.seq.message == "beam refused: e-stop latched"  # said once (it was "beam refused: beam refused: ...")
    rig = _started(tmp_path)
    rig.arrive()
    rig.advance(0.03, 3)
    rig.ports.beam_calls[-1][1].set(False, "interlock open")  # a source that does not say it
    rig.advance()
    assert rig.seq.message == "beam refused: interlock open"

    rig = _to_exposing(_started(tmp_path))
    rig.seq.on_beam(False)
    _aborted(rig, "beam lost during view 0")

    rig = _started(tmp_path)
    rig.seq.on_beam(True)  # nobody asked for it
    _aborted(rig, "beam on outside an exposure")


def test_detector_failures_abort(tmp_path):
    for answer, words in (((False, "detector timeout"), ("detector: detector timeout",)),
                          ((True, "no json"), ("without a frame stamp",))):
        rig = _to_exposing(_started(tmp_path))
        rig.ports.expose_calls[-1].set(*answer)
        rig.advance()
        _aborted(rig, *words)


def _waiting_frame(tmp_path, stamp):
    rig = _to_exposing(_started(tmp_path))
    rig.ports.expose_calls[-1].set(True, json.dumps({"stamp_ns": stamp}))
    rig.advance()
    rig.seq.on_beam(False)
    rig.ports.beam_calls[-1][1].set(True)
    rig.advance()
    assert rig.seq.state == "waiting_frame"
    return rig


def test_frame_of_the_wrong_size_or_missing_aborts(tmp_path):
    rig = _waiting_frame(tmp_path, 7)
    rig.seq.on_frame(8, (6, 8))  # another frame: not the one exposed
    rig.seq.on_frame(7, (4, 8))
    rig.report_arms(True)
    rig.advance()
    _aborted(rig, "frame is 4 x 8", "6 x 8")
    assert rig.seq.frames == 0
    rig = _waiting_frame(tmp_path, 7)
    for _ in range(5):
        rig.report_arms(True)
        rig.advance(0.5)
    _aborted(rig, "frame of view 0 not received")


def test_arm_driver_error_and_estop_abort(tmp_path):
    rig = _started(tmp_path)
    rig.seq.on_diagnostics([("/source_arm_driver: source arm", True, "connection lost", "unconfigured")])
    _aborted(rig, "arm driver error", "connection lost")
    rig = _started(tmp_path)
    rig.seq.on_estop(True)
    _aborted(rig, "e-stop")


def test_autostart_retries_until_the_graph_is_up(tmp_path):
    rig = Rig(tmp_path, autostart=True)
    rig.ports.ready = False
    rig.advance()
    assert rig.seq.state == "idle" and rig.ports.logs[-1][1].startswith("autostart waiting: cannot start")
    rig.ports.ready = True
    rig.report_arms(False)
    rig.advance(0.5)
    assert rig.seq.state == "idle"  # tries once a second
    rig.report_arms(False)
    rig.advance(0.6)
    assert rig.seq.state == "moving"


def test_no_scan_starts_under_a_latched_estop_and_a_latch_aborts_a_running_one(tmp_path):
    """An outside check started a scan while the source's e-stop was latched: the arms moved, and only the beam
    request failed. Now the start is refused with the reason and no goal goes out; a reset lets it start; a latch
    reported by the source mid-scan aborts it."""
    rig = Rig(tmp_path)
    rig.report_arms(False)
    rig.seq.on_estop_latched(True)
    ok, msg = rig.seq.start()
    assert not ok and "e-stop is latched" in msg and "source/reset_estop" in msg
    assert rig.ports.goals == [] and rig.ports.armed == [False]
    rig.seq.on_estop_latched(False)
    assert rig.seq.start()[0] and rig.ports.goals
    rig.seq.on_estop_latched(True)
    _aborted(rig, "e-stop latched at the source")
    rig = Rig(tmp_path)
    rig.seq.on_estop(True)  # a press on the estop topic counts as latched until the source says otherwise
    rig.report_arms(False)
    assert not rig.seq.start()[0] and rig.ports.goals == []


def test_an_abort_after_the_exposure_counts_the_frame_taken(tmp_path):
    """An abort between the detector's answer and the frame's arrival said "(1 frames kept)" at view 1 while the
    bag held 2 frames: the frame exposed for the view in progress is taken (pcd_grabber publishes it)."""
    rig = _exposing(tmp_path)
    assert rig.seq.frames == 1 and rig.seq.view == 1
    rig.ports.expose_calls[-1].set(True, json.dumps({"stamp_ns": 12}))
    rig.advance()
    assert rig.seq.state == "beam_off"
    rig.seq.abort("aborted on request")
    _aborted(rig, "aborted on request")
    assert rig.seq.frames == 2 and rig.seq.frame_stamps == [11, 12]
    assert ("error", "scan aborted at view 1 (2 frames kept): aborted on request") in rig.ports.logs
    assert rig.ports.status[-1]["frames"] == 2
    # an abort before the exposure counts none for the view in progress; nor one whose frame never came
    rig = _started(tmp_path)
    rig.arrive()
    rig.advance()
    rig.seq.abort("aborted on request")
    assert rig.seq.frames == 0
    rig = _waiting_frame(tmp_path, 7)
    for _ in range(5):
        rig.report_arms(True)
        rig.advance(0.5)
    _aborted(rig, "frame of view 0 not received")
    assert rig.seq.frames == 0


def test_an_abort_while_the_exposure_is_answered_counts_the_frame_the_detector_published(tmp_path):
    """An e-stop during a short exposure said "(1 frames kept)" while the bag held 2: the detector had answered (and
    published the frame) but no tick had taken the answer in, or it answered just after the abort. Now an answer
    waiting at the abort counts, and so does one that comes after it; a refusal (a beam-interrupted frame, which
    went to /ct/projection_rejected) does not."""
    rig = _exposing(tmp_path)
    rig.ports.expose_calls[-1].set(True, json.dumps({"stamp_ns": 12}))  # answered, no tick yet
    rig.seq.abort("e-stop")
    assert rig.seq.frames == 2 and rig.seq.frame_stamps == [11, 12]
    assert ("error", "scan aborted at view 1 (2 frames kept): e-stop") in rig.ports.logs

    rig = _exposing(tmp_path)
    rig.seq.abort("e-stop")  # the detector still exposing
    assert rig.seq.frames == 1
    rig.advance()
    assert rig.seq.frames == 1
    rig.ports.expose_calls[-1].set(True, json.dumps({"stamp_ns": 12}))
    rig.advance()
    assert rig.seq.frames == 2 and rig.seq.frame_stamps == [11, 12] and rig.seq.state == "aborted"
    assert rig.ports.status[-1]["frames"] == 2
    assert any("after the abort: its frame is kept (2 frames kept)" in m for _, m in rig.ports.logs)

    rig = _exposing(tmp_path)
    rig.seq.abort("e-stop")
    rig.ports.expose_calls[-1].set(False, "beam interrupted: on for 40% of the exposure")
    rig.advance()
    assert rig.seq.frames == 1 and rig.seq.frame_stamps == [11]


def test_the_beam_goes_off_when_the_exposure_time_has_passed_not_when_the_detector_answers(tmp_path):
    """Outside tester, F1: the beam stayed on until pcd/expose answered (3 s on a detector timeout, 2.7 s per view
    on a slow read-out, no warning). Now it goes off exposure_s + beam_off_margin_s after the request, the answer
    is awaited with the beam off, and a slow read-out is warned about (once, and counted at the end)."""
    rig = _to_exposing(_started(tmp_path, beam_off_margin_s=0.2, readout_warn_s=0.5))
    s, p = rig.seq, rig.ports
    rig.advance(0.1, 3)  # 0.3 s > exposure 0.02 s + margin 0.2 s, no answer yet
    assert s.state == "beam_off" and p.beam_calls[-1][0] is False and not p.expose_calls[-1].done()
    s.on_beam(False)
    p.beam_calls[-1][1].set(True, "beam off")
    rig.report_arms(True)
    rig.advance()
    assert s.state == "waiting_frame" and "waiting for the detector" in s.message
    for _ in range(20):  # read-out takes 2.2 s more: the beam stays off, nothing aborts
        rig.report_arms(True)
        rig.advance(0.1)
    assert s.state == "waiting_frame" and [on for on, _ in p.beam_calls] == [True, False]
    p.expose_calls[-1].set(True, json.dumps({"stamp_ns": 5, "exposure_s": 0.02}))
    rig.advance()
    warnings = [m for level, m in p.logs if level == "warn"]
    assert len(warnings) == 1 and "slow detector read-out" in warnings[0] and "view 1/2" in warnings[0]
    s.on_frame(5, (6, 8))
    rig.advance()
    assert s.state == "moving" and s.frames == 1 and s.view == 1
    rig.run_view(6)  # a quick answer: beam off at the answer, as before
    s.on_geometry(5)
    s.on_geometry(6)
    rig.advance()
    assert s.state == "done" and "1 slow detector read-outs" in s.message
    assert p.logs[-1][0] == "warn"


def test_a_detector_that_never_answers_times_out_with_the_beam_off(tmp_path):
    rig = _to_exposing(_started(tmp_path, beam_off_margin_s=0.2))
    s, p = rig.seq, rig.ports
    rig.advance(0.25)
    assert s.state == "beam_off"
    s.on_beam(False)
    p.beam_calls[-1][1].set(True)
    for _ in range(26):  # up to exposure_timeout_s 1 + service_timeout_s 2 from the request
        rig.report_arms(True)
        rig.advance(0.1)
    assert s.state == "waiting_frame" and [on for on, _ in p.beam_calls] == [True, False]
    for _ in range(2):
        rig.report_arms(True)
        rig.advance(0.1)
    _aborted(rig, "pcd/expose: no answer within 3 s", "hung or gone")
    assert s.frames == 0


def test_a_gone_detector_gets_no_beam(tmp_path):
    """Outside tester, F1: a killed pcd_grabber: the beam went on 137 ms later and stayed on 5 s, and the abort
    said only "pcd/expose: no answer within 5 s". Now, before the beam: pcd/expose must be offered, and the node
    offering it must answer get_state as active; else the scan aborts naming the detector node, with no beam."""
    def settled(**ports):
        rig = _started(tmp_path)
        for k, v in ports.items():
            setattr(rig.ports, k, v)
        rig.arrive()
        rig.advance(0.03, 3)
        return rig

    rig = settled(expose_ready=False)
    _aborted(rig, "detector node (pcd_grabber) is gone", "pcd/expose is no longer offered", "not switched on")
    assert [on for on, _ in rig.ports.beam_calls] == [False]
    # still in the graph (a SIGKILLed node stays for the DDS lease) but not answering
    rig = settled(check_detector=True)
    assert rig.seq.state == "settling" and len(rig.ports.check_calls) == 1 and not rig.ports.beam_calls
    for _ in range(21):
        rig.report_arms(True)
        rig.advance(0.1)
    _aborted(rig, "detector node (/pcd_grabber) does not answer", "gone or hung", "not switched on")
    assert [on for on, _ in rig.ports.beam_calls] == [False]
    rig = settled(check_detector=True)
    rig.ports.check_calls[-1].set(False, "/pcd_grabber is inactive, not active")
    rig.advance()
    _aborted(rig, "/pcd_grabber is inactive", "not switched on")
    assert [on for on, _ in rig.ports.beam_calls] == [False]
    rig = settled(check_detector=True)
    rig.ports.check_calls[-1].set(True, "/pcd_grabber is active")
    rig.advance()
    assert rig.seq.state == "beam_on" and rig.ports.beam_calls[-1][0] is True
    # the detector going away during the exposure: aborted at once, naming it
    rig.ports.beam_calls[-1][1].set(True)
    rig.seq.on_beam(True)
    rig.advance()
    assert rig.seq.state == "exposing"
    rig.ports.expose_ready = False
    rig.advance()
    _aborted(rig, "detector node (/pcd_grabber) is gone")


def test_an_arm_controller_lost_during_the_exposure_is_named(tmp_path):
    """Outside tester, F3: a UR controller lost during an exposure was reported "source arm left its position
    during view 2 (exposing)"; only /diagnostics said "connection lost". The arm driver drops in_position first (the
    beam goes off at once, as before) and reports the ERROR right after: the abort reason now names it."""
    rig = _exposing(tmp_path)
    s = rig.seq
    s.on_in_position("source", False)
    _aborted(rig, "source arm left its position during view 1 (exposing)")
    s.on_diagnostics([("/detector_arm_driver: detector arm", True, "robot not ready: PROTECTIVE_STOP", "active")])
    assert "PROTECTIVE_STOP" not in s.message  # the other arm: not the cause
    rig.t += 2.0  # a frozen controller: "connection lost" after call_timeout_s
    s.on_diagnostics([("/source_arm_driver: source arm", True,
                       "connection lost: connection to controller at 10.0.0.2 lost (RTDE disconnected)",
                       "unconfigured")])
    _aborted(rig, "source arm left its position during view 1 (exposing)", "arm driver error",
             "connection lost", "RTDE disconnected")
    assert rig.ports.status[-1]["message"] == s.message and s.health()[1][-1] == ("last_abort_reason", s.message)
    assert rig.ports.logs[-1][0] == "error" and "RTDE disconnected" in rig.ports.logs[-1][1]
    # named once; a report long after the abort is not its cause
    s.on_diagnostics([("/source_arm_driver: source arm", True, "fault: something else", "unconfigured")])
    assert "something else" not in s.message
    rig = _exposing(tmp_path)
    rig.seq.on_in_position("source", False)
    rig.t += 10.0
    rig.seq.on_diagnostics([("/source_arm_driver: source arm", True, "connection lost: late", "unconfigured")])
    assert "late" not in rig.seq.message


def test_a_call_that_fails_aborts_with_what_failed_and_no_beam_is_left_on(tmp_path):
    """A service call whose future raises (the server went away mid-call) aborts the scan naming the call."""
    rig = _to_exposing(_started(tmp_path))
    rig.ports.expose_calls[-1].fail(RuntimeError("server gone"))
    rig.advance()
    _aborted(rig, "pcd/expose failed: server gone")

    rig = _started(tmp_path)
    rig.ports.check_detector = True
    rig.arrive()
    rig.advance(0.03, 3)
    assert rig.ports.check_calls and not [on for on, _ in rig.ports.beam_calls if on]
    rig.ports.check_calls[-1].fail(RuntimeError("no state"))
    rig.advance()
    _aborted(rig, "could not be asked for its state (no state)", "the beam was not switched on")
    assert not [on for on, _ in rig.ports.beam_calls if on]
